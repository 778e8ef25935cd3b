"""The syntax-tree walk of the sandbox over a generated program's statements: which statements a module,
a loss class and a function may contain, which imports are allowed, and the program's loss classes
(see :mod:`ctgpp.language.sandbox.program` for the policy in words; the rules on expressions are in
:mod:`ctgpp.language.sandbox.expressions`)."""

from __future__ import annotations

import ast
import difflib
from collections.abc import Collection

from ctgpp.language.llm.extract import loss_classes, main_class
from ctgpp.language.sandbox.expressions import PREBOUND, ExpressionChecker
from ctgpp.language.sandbox.nodes import (
    SandboxError,
    bound_names,
    is_literal,
    is_self,
    refuse,
    required_parameters,
)
from ctgpp.language.sandbox.vocabulary import (
    FORBIDDEN_CALLS,
    HELPER_MODULES,
    PLAIN_IMPORTS,
    SAFE_BUILTIN_NAMES,
)

LOOP_CALLS = frozenset({"range", "enumerate", "zip", "reversed"})
MAX_CLASSES = 8  # loss classes in one program: the main one and the helper losses it builds
FUNCTION_STATEMENTS = (
    ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Return, ast.If, ast.For, ast.Expr, ast.Pass, ast.Break,
    ast.Continue, ast.Assert, ast.Raise, ast.FunctionDef,
)
REFUSED_STATEMENTS = {
    "While": "while loops are not allowed (they may never end): use `for i in range(n)`",
    "Try": "try/except is not allowed (it could hide errors and time limits)",
    "TryStar": "try/except is not allowed (it could hide errors and time limits)",
    "With": "with statements are not allowed",
    "AsyncWith": "async code is not allowed",
    "AsyncFor": "async code is not allowed",
    "AsyncFunctionDef": "async code is not allowed",
    "Global": "global statements are not allowed",
    "Nonlocal": "nonlocal statements are not allowed",
    "Delete": "del statements are not allowed",
    "Import": "imports are only allowed at the top of the program",
    "ImportFrom": "imports are only allowed at the top of the program",
    "ClassDef": "classes are only allowed at the top level of the program",
    "Match": "match statements are not allowed",
}


class ProgramChecker(ExpressionChecker):
    """Walks one module; ``check_module`` raises :class:`SandboxError` at the first violation."""

    def check_module(self, tree: ast.Module) -> None:
        self.bound = bound_names(tree)
        for name in sorted(self.bound):
            self._check_binding(name, tree)
        for stmt in tree.body:
            if isinstance(stmt, ast.Import | ast.ImportFrom):
                self._check_import(stmt)
            elif isinstance(stmt, ast.ClassDef):
                self._check_class(stmt)
            elif isinstance(stmt, ast.FunctionDef):
                self._check_function(stmt)
            elif isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant):
                self._check_expr(stmt.value)
            elif isinstance(stmt, ast.Assign | ast.AnnAssign) and self._is_constant_definition(stmt):
                self._check_expr(stmt.value)  # type: ignore[arg-type]
            else:
                raise refuse(stmt, f"module-level {type(stmt).__name__} statement is not allowed: only "
                                   "imports, constants, functions and loss classes")
        self._check_classes(tree)

    def _check_classes(self, tree: ast.Module) -> None:
        """Between 1 and ``MAX_CLASSES`` loss classes with distinct names; the main one
        (:func:`ctgpp.language.llm.extract.main_class`) can be built without arguments."""
        classes = loss_classes(tree)
        if not classes:
            raise SandboxError("the program defines no class deriving from GuidanceLoss", 1)
        if len(classes) > MAX_CLASSES:
            raise refuse(classes[MAX_CLASSES], f"at most {MAX_CLASSES} classes are allowed in one program")
        names = [c.name for c in classes]
        for cls in classes:
            if names.count(cls.name) > 1:
                raise refuse(cls, f"two classes are named {cls.name}")
        main = main_class(tree)
        assert main is not None
        init = next((s for s in main.body if isinstance(s, ast.FunctionDef) and s.name == "__init__"), None)
        if init is not None:
            required = required_parameters(init.args)
            if required:
                listing = ", ".join(required)
                example = ", ".join(f"{n}=..." for n in required)
                raise refuse(init, f"{main.name} is the loss and is built without arguments, as "
                                   f"{main.name}(), but its __init__ needs {listing}: give every parameter "
                                   f"of __init__ a default value (def __init__(self, {example}) with the "
                                   "values the query asks for)")

    def _check_binding(self, name: str, tree: ast.Module) -> None:
        node = next(n for n in ast.walk(tree) if name in (getattr(n, "id", None), getattr(n, "arg", None),
                                                           getattr(n, "name", None)))
        is_init = name == "__init__" and isinstance(node, ast.FunctionDef)
        if name.startswith("_") and name != "_" and not is_init:
            raise refuse(node, f"names starting with '_' are not allowed ({name})")
        if name in PREBOUND or name in SAFE_BUILTIN_NAMES or name in FORBIDDEN_CALLS:
            raise refuse(node, f"rebinding the name {name} is not allowed")

    def _is_constant_definition(self, stmt: ast.Assign | ast.AnnAssign) -> bool:
        if isinstance(stmt, ast.AnnAssign):
            self._check_annotation(stmt.annotation)
        targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]
        return (stmt.value is not None and is_literal(stmt.value) and len(targets) == 1
                and isinstance(targets[0], ast.Name))

    def _check_import(self, stmt: ast.Import | ast.ImportFrom) -> None:
        if isinstance(stmt, ast.Import):
            for alias in stmt.names:
                if alias.name not in PLAIN_IMPORTS or alias.asname != PLAIN_IMPORTS[alias.name]:
                    shown = alias.name + (f" as {alias.asname}" if alias.asname else "")
                    raise refuse(stmt, f"import {shown} is not allowed (only `import torch`, `import math`,"
                                       " `import torch.nn.functional as F`)")
            return
        allowed = HELPER_MODULES.get(stmt.module or "")
        if allowed is None or stmt.level:
            modules = ", ".join(sorted(m for m in HELPER_MODULES if m.startswith("ctgpp")))
            raise refuse(stmt, f"import from {stmt.module} is not allowed (the helper modules: {modules})")
        for alias in stmt.names:
            if alias.asname is not None:
                raise refuse(stmt, f"from {stmt.module} import {alias.name} as {alias.asname} is not "
                                   "allowed (import helpers under their own names)")
            if alias.name not in allowed:
                raise refuse(stmt, _unknown_helper(stmt.module or "", alias.name, allowed))

    def _check_class(self, cls: ast.ClassDef) -> None:
        if cls.decorator_list:
            raise refuse(cls, "decorators are not allowed")
        if cls.keywords:
            raise refuse(cls, "class keywords (metaclass=...) are not allowed")
        base = cls.bases[0] if len(cls.bases) == 1 else None
        if not (isinstance(base, ast.Name) and base.id == "GuidanceLoss"):
            raise refuse(cls, f"class {cls.name} must derive from GuidanceLoss only")
        self.class_name = cls.name
        methods = [s for s in cls.body if isinstance(s, ast.FunctionDef)]
        if "forward" not in {m.name for m in methods}:
            raise refuse(cls, f"class {cls.name} has no forward(self, x, data_batch, agt_mask=None) method")
        self.self_attributes = {m.name for m in methods}
        for stmt in cls.body:  # class constants, wherever they stand
            if isinstance(stmt, ast.Assign | ast.AnnAssign) and self._is_constant_definition(stmt):
                target = stmt.targets[0] if isinstance(stmt, ast.Assign) else stmt.target
                self.self_attributes.add(target.id)  # type: ignore[attr-defined]
        for node in ast.walk(cls):
            if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and is_self(node.value):
                self.self_attributes.add(node.attr)
        for stmt in cls.body:
            if isinstance(stmt, ast.FunctionDef):
                self.method = stmt.name
                self._check_function(stmt)
                self.method = None
            elif isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant):
                self._check_expr(stmt.value)
            elif isinstance(stmt, ast.Assign | ast.AnnAssign) and self._is_constant_definition(stmt):
                self._check_expr(stmt.value)  # type: ignore[arg-type]
            else:
                raise refuse(stmt, f"{type(stmt).__name__} statement in the class body is not allowed: "
                                   "only a docstring, constants and methods")
        self.class_name = None

    def _check_function(self, fn: ast.FunctionDef) -> None:
        if fn.decorator_list:
            raise refuse(fn, "decorators are not allowed")
        self._check_arguments(fn.args)
        self._check_annotation(fn.returns)
        self.functions.append(fn.name)
        for stmt in fn.body:
            self._check_statement(stmt)
        self.functions.pop()

    def _check_statement(self, stmt: ast.stmt) -> None:
        kind = type(stmt).__name__
        if kind in REFUSED_STATEMENTS:
            raise refuse(stmt, REFUSED_STATEMENTS[kind])
        if not isinstance(stmt, FUNCTION_STATEMENTS):
            raise refuse(stmt, f"{kind} statements are not allowed")
        if isinstance(stmt, ast.FunctionDef):
            outer, self.method = self.method, None
            self._check_function(stmt)
            self.method = outer
            return
        if isinstance(stmt, ast.For):
            self._check_loop_iterable(stmt.iter)
        for field, value in ast.iter_fields(stmt):
            if field == "annotation":
                self._check_annotation(value)
                continue
            for child in value if isinstance(value, list) else [value]:
                if isinstance(child, ast.stmt):
                    self._check_statement(child)
                elif isinstance(child, ast.AST):
                    self._check_expr(child)

    def _check_loop_iterable(self, node: ast.expr) -> None:
        ok = (
            isinstance(node, ast.List | ast.Tuple | ast.Name)
            or (isinstance(node, ast.Attribute) and is_self(node.value))
            or (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in LOOP_CALLS)
        )
        if not ok:
            raise refuse(node, "for loops may only run over range(), enumerate(), zip(), reversed(), "
                               "a list or tuple, or a variable")


def _unknown_helper(module: str, name: str, allowed: Collection[str]) -> str:
    """The refusal of ``from module import name`` where ``module`` has no helper ``name``: the module
    that has it, where one does (the local 1.5B model imported ``get_turn_lane_projection`` from
    ``ctgpp.guidance.helpers`` in all six rounds of the left turn, told only what that module has);
    else what ``module`` has, the closest first (a small model otherwise sends the same import again)."""
    elsewhere = sorted(m for m, names in HELPER_MODULES.items() if name in names and m != module)
    if elsewhere:
        return (f"from {module} import {name} is not allowed: {module} has no helper {name}; it is in "
                f"{elsewhere[0]}: write `from {elsewhere[0]} import {name}`.")
    close = difflib.get_close_matches(name, sorted(allowed), n=3, cutoff=0.0)
    rest = sorted(set(allowed) - set(close))
    return (f"from {module} import {name} is not allowed: {module} has no helper {name}. Its helpers, the "
            f"closest first: {', '.join([*close, *rest])}. Use one of them, or compute it from x with torch.")
