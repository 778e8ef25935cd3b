"""The sandbox for generated guidance-loss code (DESIGN.md, Language interface: generated code is
untrusted).

:func:`check_source` parses the program and walks its syntax tree against an allow list
(:mod:`ctgpp.language.sandbox.vocabulary`); anything not listed is refused with a :class:`SandboxError` naming
the reason and the line. The program must be: a docstring, imports from a fixed list (``import
torch``, ``import math``, ``import torch.nn.functional as F``, ``from ctgpp.guidance.helpers import
...`` and the like; they bind names that are pre-bound anyway), literal constants, plain functions,
and one or more (at most 8) classes deriving from ``GuidanceLoss``, each with ``forward`` and
optionally ``__init__`` (calling only ``super().__init__()`` or ``super(C, self).__init__()`` among
dunders) and helper methods. The loss that runs is the *main class*
(:func:`ctgpp.language.llm.extract.main_class`: the last class no other part of the program names; the
others are helper losses it builds); it is built as ``cls()``, so its ``__init__`` must give every
parameter a default value — a program whose main class does not is refused with a message asking
for defaults. Helper classes may take arguments (the main class passes them).

Refused: any other import; every name or attribute starting with ``_`` (``__class__``,
``__globals__``, ``__subclasses__``, ``__builtins__``, ``__import__``); ``getattr``/``eval``/
``exec``/``open``/``globals``/``type``/...; ``torch``/``math``/``F`` attributes outside their allow
lists (so ``torch.load``, ``torch.save``, ``torch.hub``, ``torch.jit``, ``torch.ops``, ``torch._C``,
``torch.utils``, ``torch.from_file`` ... are refused *because they are not listed*); modules used as
values (``t = torch``); attributes on other values outside the tensor/batch allow lists (``.format``,
``.numpy``, ``.gi_frame``); attribute assignment except on ``self``; ``while``, ``try``, ``with``,
``global``, ``nonlocal``, ``del``, ``yield``, ``async``, decorators, class keywords; ``for`` loops
over anything but ``range``/``enumerate``/``zip``/``reversed``, literals and variables; direct
recursion; integer constants above 10**8 (allocation bombs); string constants containing ``__``.
Annotations are never evaluated (they are removed before execution); they may only hold plain type
expressions (names, attributes, subscripts, ``|``), without calls or ``_`` names.

:func:`load_loss_class` executes the checked tree in a fresh namespace whose ``__builtins__`` is a
small table (``range``, ``len``, ``min``, ``max``, ``zip``, ``super`` ...) with ``torch``, ``math``,
``F``, the helpers and ``GuidanceLoss`` pre-bound. Run time and memory are bounded by
:mod:`ctgpp.language.sandbox.checks`, which runs the loss in a separate, memory-limited process.
"""

from __future__ import annotations

import ast
import copy

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.language.llm.extract import main_class
from ctgpp.language.sandbox.nodes import SandboxError
from ctgpp.language.sandbox.statements import ProgramChecker
from ctgpp.language.sandbox.vocabulary import prebound_names, safe_builtins

__all__ = ["GENERATED_FILENAME", "MAX_SOURCE_CHARS", "SandboxError", "check_source", "load_loss_class"]

GENERATED_FILENAME = "<generated-loss>"
MAX_SOURCE_CHARS = 20_000


def check_source(code: str) -> ast.Module:
    """Parse ``code`` and check it against the allow list; returns the parsed module.

    Raises :class:`SandboxError` (a ``ValueError``) whose message names the line and the reason.
    """
    if len(code) > MAX_SOURCE_CHARS:
        raise SandboxError(f"the program is too long ({len(code)} characters, at most {MAX_SOURCE_CHARS})", 1)
    try:
        tree = ast.parse(code, filename=GENERATED_FILENAME)
    except SyntaxError as err:
        raise SandboxError(f"syntax error: {err.msg}", err.lineno or 1) from None
    ProgramChecker().check_module(tree)
    return tree


class _StripUnevaluated(ast.NodeTransformer):
    """Remove imports (their names are pre-bound) and annotations (never evaluated) from a checked tree."""

    def visit_Import(self, node: ast.Import) -> ast.AST:
        return ast.copy_location(ast.Pass(), node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> ast.AST:
        return ast.copy_location(ast.Pass(), node)

    def visit_arg(self, node: ast.arg) -> ast.AST:
        node.annotation = None
        return node

    def visit_FunctionDef(self, node: ast.FunctionDef) -> ast.AST:
        node.returns = None
        self.generic_visit(node)
        return node

    def visit_AnnAssign(self, node: ast.AnnAssign) -> ast.AST:
        if node.value is None:
            return ast.copy_location(ast.Pass(), node)
        self.generic_visit(node)
        return ast.copy_location(ast.Assign(targets=[node.target], value=node.value), node)


def _class_name(tree: ast.Module) -> str:
    """The name of the main loss class of a checked module (:func:`main_class`)."""
    cls = main_class(tree)
    if cls is None:
        raise SandboxError("the program defines no class deriving from GuidanceLoss", 1)
    return cls.name


def load_loss_class(code: str) -> type[GuidanceLoss]:
    """Check ``code`` (:func:`check_source`) and execute it in a restricted namespace; returns the loss
    class (a subclass of :class:`GuidanceLoss`, not yet instantiated). The class carries its source
    as ``_ctgpp_source`` so that :mod:`ctgpp.language.sandbox.checks` can rebuild it in a worker process."""
    tree = check_source(code)
    name = _class_name(tree)
    runnable = ast.fix_missing_locations(_StripUnevaluated().visit(copy.deepcopy(tree)))
    namespace = {"__builtins__": safe_builtins(), "__name__": "ctgpp_generated", **prebound_names()}
    # The only execution of generated code: a tree that passed check_source, restricted builtins.
    exec(compile(runnable, GENERATED_FILENAME, "exec"), namespace)  # noqa: S102
    cls = namespace.get(name)
    if not (isinstance(cls, type) and issubclass(cls, GuidanceLoss)):
        raise SandboxError(f"{name} is not a subclass of GuidanceLoss after execution", 1)
    cls._ctgpp_source = code  # type: ignore[attr-defined]  # the program, kept for the checks
    return cls
