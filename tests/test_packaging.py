"""Dependencies declared honestly (issue 18 item 6): every module that src and the tests import is
the standard library, ctgpp itself, or a distribution that pyproject.toml names (src: the
dependencies or an extra; tests: the dev extra too); the package says it is typed."""

from __future__ import annotations

import ast
import re
import sys
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # the standard library's from Python 3.11
ROOT = Path(__file__).resolve().parents[1]


def _requirement_names(requirements: list[str]) -> set[str]:
    return {re.split(r"[\s<>=!~\[;]", r, maxsplit=1)[0].lower().replace("_", "-") for r in requirements}


def _imported_modules(folder: Path) -> dict[str, str]:
    """Top-level module name -> a file importing it, for every absolute import under ``folder``."""
    found: dict[str, str] = {}
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], str(path.relative_to(ROOT)))
    return found


def _undeclared(folder: Path, declared: set[str]) -> list[str]:
    distributions = packages_distributions()
    missing = []
    for module, where in _imported_modules(folder).items():
        if module in sys.stdlib_module_names or module in ("ctgpp", "tests", "__future__"):
            continue
        names = {d.lower().replace("_", "-") for d in distributions.get(module, [module])}
        if not names & declared:
            missing.append(f"{module} (imported by {where}; distributions {sorted(names)})")
    return missing


def test_every_import_is_declared() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    extras = project["optional-dependencies"]
    runtime = _requirement_names(project["dependencies"])
    optional = set().union(*(_requirement_names(v) for k, v in extras.items() if k != "dev"))
    assert _undeclared(ROOT / "src", runtime | optional) == []
    assert _undeclared(ROOT / "tests", runtime | optional | _requirement_names(extras["dev"])) == []


def test_the_package_is_typed() -> None:
    assert (ROOT / "src" / "ctgpp" / "py.typed").is_file()
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    assert "py.typed" in package_data["package-data"]["ctgpp"]


def test_the_packages_import_downwards_only() -> None:
    """No import cycle between ctgpp's packages and no import running back up the declared layers
    (``scripts/import_graph.py --check``: docs/layout.md)."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, str(root / "scripts" / "import_graph.py"), "--check", "--quiet"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "cycles: 0" in done.stdout and "arrows back up: 0 edges" in done.stdout
