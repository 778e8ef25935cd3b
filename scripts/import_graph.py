"""The import graph between ctgpp's top-level packages, its cycles, and the arrows that run back up.

Every module under ``src/ctgpp`` is parsed with :mod:`ast` (nothing is imported). Each ``import
ctgpp.X...`` / ``from ctgpp.X... import ...`` (and relative imports) is mapped to the top-level node
``X``: a package (``scene/``, ``sim/``) or a top-level module (``geometry.py``, ``interfaces.py``),
so ``ctgpp.geometry`` is one node whether it is a module or a package. ``ctgpp/__init__.py`` is the
node ``ctgpp`` (the lazy façade over ``api``), except that ``from ctgpp import __version__`` counts as
the node ``__version__`` at the bottom: the root module runs before any submodule anyway and imports
nothing when it does (its ``api`` imports are typing-only and lazy). An import is

- *eager*: at module level, run when the module is imported;
- *typing*: under ``if TYPE_CHECKING:`` (never run, but still a dependency of the code's meaning);
- *lazy*: inside a function or method body, run on first call.

Cycles are the strongly connected components with more than one node of the graph of eager and
typing edges (a lazy import is how a cycle is hidden, not removed, so lazy edges are reported
apart and checked for cycles on their own as well).

Layers, bottom to top (a node may import only from its own layer or below; an edge from a lower
layer to a higher one is an "arrow that runs back up"). Nodes on one line share a layer::

    geometry, rule_params,          frames, boxes and contact distances; the rules' parameter table;
      __version__                     the version string: no ctgpp imports
    scene                           scene and map types, lane maths, which vehicles move
    interfaces                      Observation, Plan, Policy, Rollout (built on scene types)
    io, ray_cluster                 atomic writes, strict JSON, map edges, exporters of a Rollout; Ray,
                                      optional, for --engine ray (no ctgpp imports)
    dynamics                        the unicycle model (pure functions of state, action, dt)
    data                            datasets, batches, training windows (actions by inverse dynamics)
    diffusion                       schedules and samplers (a denoiser is a callable they are given)
    model                           the denoiser network and its training loss (adds noise by a schedule)
    metrics                         pure functions of a rollout
    guidance                        guidance losses and guards
    behaviours                      the vocabulary: each behaviour's measure, check and guidance loss
    language                        sentence -> behaviours and losses
    policies, baselines             policies (diffusion, replay) and the CTG/BITS baselines
    train                           the training loop (the denoiser's and the baselines')
    sim                             the closed-loop simulator
    viz                             plots and animations of a rollout
    api, ctgpp                      the Python API and the package façade over it
    eval, generate                  evaluation runs and tables, scenario libraries (every episode
                                      through api.simulate)
    bench                           benchmarks
    serve                           the web app
    cli                             the command line

This differs from issue 33's rough order where the code says otherwise: dynamics below data (windows
derive actions by inverse dynamics), diffusion below model (the training loss adds noise with the
schedule; the samplers never import the network), guidance below behaviours (a behaviour builds its
guidance loss; no guidance module imports a behaviour), train above the baselines it trains, and
eval above api (evaluation runs each episode through the public ``simulate``).

Usage::

    python scripts/import_graph.py            # the graph, the cycles, the arrows back up; exits 0
    python scripts/import_graph.py --check    # same, exits 1 on any cycle or arrow back up
    python scripts/import_graph.py --quiet    # the summary only
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "src" / "ctgpp"
PACKAGE = "ctgpp"

LAYERS: tuple[tuple[str, ...], ...] = (
    ("geometry", "rule_params", "__version__"),
    ("scene",),
    ("interfaces",),
    ("io", "ray_cluster"),
    ("dynamics",),
    ("data",),
    ("diffusion",),
    ("model",),
    ("metrics",),
    ("guidance",),
    ("behaviours",),
    ("language",),
    ("policies", "baselines"),
    ("train",),
    ("sim",),
    ("viz",),
    ("api", "ctgpp"),
    ("eval", "generate"),
    ("bench",),
    ("serve",),
    ("cli",),
)
LAYER_OF = {node: rank for rank, nodes in enumerate(LAYERS) for node in nodes}

KINDS = ("eager", "typing", "lazy")


@dataclass(frozen=True)
class Import:
    """One import of ctgpp code: the importing module's file, its line, the two nodes, the kind."""

    path: Path
    line: int
    source: str
    target: str
    module: str  # the imported module, dotted ("ctgpp.scene.types")
    kind: str  # one of KINDS


def node_of(path: Path, root: Path = ROOT) -> str:
    """The top-level node of a source file: ``scene/types.py`` -> ``scene``, ``interfaces.py`` ->
    ``interfaces``."""
    parts = path.relative_to(root).with_suffix("").parts
    if parts == ("__init__",):
        return PACKAGE
    return parts[0]


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join([PACKAGE, *parts])


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _walk(node: ast.AST, kind: str) -> Iterator[tuple[ast.Import | ast.ImportFrom, str]]:
    """Every import statement below ``node`` with its kind, given the kind of ``node``'s context."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child, kind
        elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            yield from _walk(child, "lazy")
        elif isinstance(child, ast.If) and _is_type_checking(child.test) and kind == "eager":
            for stmt in child.body:
                yield from _walk(ast.Module(body=[stmt], type_ignores=[]), "typing")
            for stmt in child.orelse:
                yield from _walk(ast.Module(body=[stmt], type_ignores=[]), kind)
        else:
            yield from _walk(child, kind)


def _targets(stmt: ast.Import | ast.ImportFrom, importer: str, is_package: bool) -> list[str]:
    """The dotted ctgpp modules (or module-or-name paths) that one import statement reaches."""
    if isinstance(stmt, ast.Import):
        return [alias.name for alias in stmt.names]
    base = stmt.module or ""
    if stmt.level:
        anchor = importer.split(".")
        if not is_package:
            anchor = anchor[:-1]
        anchor = anchor[: len(anchor) - (stmt.level - 1)]
        base = ".".join([*anchor, base]) if base else ".".join(anchor)
    if base == PACKAGE:  # from ctgpp import geometry, api
        return [f"{PACKAGE}.{alias.name}" for alias in stmt.names]
    return [base]


def collect(root: Path = ROOT) -> list[Import]:
    """Every import of ctgpp code by a module under ``root``."""
    found: list[Import] = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        importer = module_name(path, root)
        source = node_of(path, root)
        for stmt, kind in _walk(tree, "eager"):
            for module in _targets(stmt, importer, path.name == "__init__.py"):
                parts = module.split(".")
                if parts[0] != PACKAGE:
                    continue
                target = parts[1] if len(parts) > 1 else PACKAGE
                if target != source:
                    found.append(Import(path, stmt.lineno, source, target, module, kind))
    return found


def strongly_connected(edges: set[tuple[str, str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one node, each sorted, largest first."""
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
        graph.setdefault(b, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(components, key=lambda c: (-len(c), c))


def upward(imports: list[Import]) -> list[Import]:
    """Imports from a lower layer into a higher one (unknown nodes count as the top layer)."""
    top = len(LAYERS)
    return [i for i in imports if LAYER_OF.get(i.target, top) > LAYER_OF.get(i.source, top)]


def _rel(path: Path, root: Path) -> str:
    return str(path.relative_to(root.parent))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 on any package cycle or import running back up")
    parser.add_argument("--quiet", action="store_true", help="print the summary only")
    parser.add_argument("--root", type=Path, default=ROOT, help="the ctgpp package (default: src/ctgpp)")
    args = parser.parse_args(argv)

    root = args.root.resolve()
    imports = collect(root)
    nodes = sorted({node_of(p, root) for p in root.rglob("*.py")})
    unplaced = [n for n in nodes if n not in LAYER_OF]
    static = [i for i in imports if i.kind != "lazy"]
    lazy = [i for i in imports if i.kind == "lazy"]
    cycles = strongly_connected({(i.source, i.target) for i in static})
    lazy_cycles = [
        c for c in strongly_connected({(i.source, i.target) for i in imports}) if c not in cycles
    ]
    up = upward(static)
    up_lazy = upward(lazy)
    up_edges = Counter((i.source, i.target) for i in up)
    up_lazy_edges = Counter((i.source, i.target) for i in up_lazy)

    if not args.quiet:
        for title, chosen in (("Package graph (eager + typing imports)", static), ("Lazy imports", lazy)):
            print(f"{title}: source -> target  count")
            counts = Counter((i.source, i.target) for i in chosen)
            for (a, b), n in sorted(counts.items()):
                print(f"  {a:>12} -> {b:<12} {n}")
            print()
        print("Arrows that run back up (eager + typing), by module:")
        for i in sorted(up, key=lambda i: (i.source, i.target, str(i.path), i.line)):
            print(f"  {i.source} -> {i.target}: {_rel(i.path, root)}:{i.line} {i.module} [{i.kind}]")
        print("Arrows that run back up (lazy), by module:")
        for i in sorted(up_lazy, key=lambda i: (i.source, i.target, str(i.path), i.line)):
            print(f"  {i.source} -> {i.target}: {_rel(i.path, root)}:{i.line} {i.module}")
        print()

    print("Summary")
    print(f"  nodes: {len(nodes)}; edges: {len({(i.source, i.target) for i in static})} "
          f"(eager + typing), {len({(i.source, i.target) for i in lazy})} lazy")
    if unplaced:
        print(f"  nodes without a layer (counted as the top): {', '.join(unplaced)}")
    print(f"  cycles: {len(cycles)}" + "".join(f"\n    {{{', '.join(c)}}}" for c in cycles))
    if lazy_cycles:
        print(f"  cycles closed only by lazy imports: {len(lazy_cycles)}"
              + "".join(f"\n    {{{', '.join(c)}}}" for c in lazy_cycles))
    print(f"  arrows back up: {len(up_edges)} edges ({sum(up_edges.values())} imports)"
          + "".join(f"\n    {a} -> {b} ({n})" for (a, b), n in sorted(up_edges.items())))
    print(f"  lazy arrows back up: {len(up_lazy_edges)} edges ({sum(up_lazy_edges.values())} imports)"
          + "".join(f"\n    {a} -> {b} ({n})" for (a, b), n in sorted(up_lazy_edges.items())))
    return 1 if args.check and (cycles or up_edges) else 0


if __name__ == "__main__":
    sys.exit(main())
