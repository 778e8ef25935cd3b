"""The syntax-tree walk of the sandbox: which statements, names, attributes and calls a generated
program may contain (see :mod:`ctgpp.language.sandbox.program` for the policy in words)."""

from __future__ import annotations

import ast
import difflib
from collections.abc import Collection

from ctgpp.language.llm.extract import loss_classes, main_class
from ctgpp.language.sandbox.vocabulary import (
    BATCH_ATTRIBUTES,
    FORBIDDEN_CALLS,
    HELPER_MODULES,
    MAX_INT_CONSTANT,
    MODULE_ATTRIBUTES,
    PLAIN_IMPORTS,
    SAFE_BUILTIN_NAMES,
    TENSOR_ATTRIBUTES,
    prebound_names,
)

PREBOUND = frozenset(prebound_names())
MODULE_NAMES = frozenset({"torch", "math", "F"})
LOOP_CALLS = frozenset({"range", "enumerate", "zip", "reversed"})
MAX_CLASSES = 8  # loss classes in one program: the main one and the helper losses it builds
EXPRESSIONS = (
    ast.BoolOp, ast.BinOp, ast.UnaryOp, ast.Lambda, ast.IfExp, ast.Dict, ast.Set, ast.ListComp,
    ast.SetComp, ast.DictComp, ast.GeneratorExp, ast.Compare, ast.Call, ast.Constant, ast.Attribute,
    ast.Subscript, ast.Starred, ast.Name, ast.List, ast.Tuple, ast.Slice, ast.NamedExpr, ast.JoinedStr,
    ast.FormattedValue, ast.comprehension, ast.keyword, ast.arguments, ast.arg, ast.operator,
    ast.boolop, ast.unaryop, ast.cmpop, ast.expr_context,
)
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


class SandboxError(ValueError):
    """Generated code refused by the sandbox; ``reason`` and ``lineno`` say why and where."""

    def __init__(self, reason: str, lineno: int) -> None:
        super().__init__(f"line {lineno}: {reason}")
        self.reason = reason
        self.lineno = lineno


def _refuse(node: ast.AST, reason: str) -> SandboxError:
    return SandboxError(reason, getattr(node, "lineno", 1))


def _is_literal(node: ast.expr) -> bool:
    """Constants, negated constants and lists/tuples of literals (safe to evaluate at definition time)."""
    if isinstance(node, ast.Constant):
        return True
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        return _is_literal(node.operand)
    return isinstance(node, ast.List | ast.Tuple) and all(_is_literal(e) for e in node.elts)


def _fold_int(node: ast.AST) -> int | None:
    """The value of an integer-literal expression (``10 ** 12``, ``4 * 10**9``), refusing huge ones."""
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return node.value
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow | ast.Mult | ast.LShift):
        left, right = _fold_int(node.left), _fold_int(node.right)
        if left is None or right is None:
            return None
        shifts = isinstance(node.op, ast.Pow | ast.LShift)
        if abs(left) > 2**64 or abs(right) > 2**64 or (shifts and right > 64):
            raise _refuse(node, "integer constant too large (allocation or computation bomb)")
        if isinstance(node.op, ast.Pow):
            return left**right
        return left * right if isinstance(node.op, ast.Mult) else left << right
    return None


def _bound_names(tree: ast.Module) -> set[str]:
    """Every name the program binds anywhere (assignments, arguments, loop targets, definitions)."""
    bound: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            bound.add(node.id)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
        elif isinstance(node, ast.FunctionDef | ast.ClassDef):
            bound.add(node.name)
    return bound


class ProgramChecker:
    """Walks one module; ``check_module`` raises :class:`SandboxError` at the first violation."""

    def __init__(self) -> None:
        self.bound: set[str] = set()
        self.self_attributes: set[str] = set()
        self.functions: list[str] = []  # enclosing function names, innermost last
        self.method: str | None = None  # the enclosing method of a loss class
        self.class_name: str | None = None  # the enclosing loss class

    # ---- statements -------------------------------------------------------------------------------
    def check_module(self, tree: ast.Module) -> None:
        self.bound = _bound_names(tree)
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
                raise _refuse(stmt, f"module-level {type(stmt).__name__} statement is not allowed: only "
                                    "imports, constants, functions and loss classes")
        self._check_classes(tree)

    def _check_classes(self, tree: ast.Module) -> None:
        """Between 1 and ``MAX_CLASSES`` loss classes with distinct names; the main one
        (:func:`ctgpp.language.llm.extract.main_class`) can be built without arguments."""
        classes = loss_classes(tree)
        if not classes:
            raise SandboxError("the program defines no class deriving from GuidanceLoss", 1)
        if len(classes) > MAX_CLASSES:
            raise _refuse(classes[MAX_CLASSES], f"at most {MAX_CLASSES} classes are allowed in one program")
        names = [c.name for c in classes]
        for cls in classes:
            if names.count(cls.name) > 1:
                raise _refuse(cls, f"two classes are named {cls.name}")
        main = main_class(tree)
        assert main is not None
        init = next((s for s in main.body if isinstance(s, ast.FunctionDef) and s.name == "__init__"), None)
        if init is not None:
            required = _required_parameters(init.args)
            if required:
                listing = ", ".join(required)
                example = ", ".join(f"{n}=..." for n in required)
                raise _refuse(init, f"{main.name} is the loss and is built without arguments, as "
                                    f"{main.name}(), but its __init__ needs {listing}: give every parameter "
                                    f"of __init__ a default value (def __init__(self, {example}) with the "
                                    "values the query asks for)")

    def _check_binding(self, name: str, tree: ast.Module) -> None:
        node = next(n for n in ast.walk(tree) if name in (getattr(n, "id", None), getattr(n, "arg", None),
                                                           getattr(n, "name", None)))
        is_init = name == "__init__" and isinstance(node, ast.FunctionDef)
        if name.startswith("_") and name != "_" and not is_init:
            raise _refuse(node, f"names starting with '_' are not allowed ({name})")
        if name in PREBOUND or name in SAFE_BUILTIN_NAMES or name in FORBIDDEN_CALLS:
            raise _refuse(node, f"rebinding the name {name} is not allowed")

    def _is_constant_definition(self, stmt: ast.Assign | ast.AnnAssign) -> bool:
        if isinstance(stmt, ast.AnnAssign):
            self._check_annotation(stmt.annotation)
        targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]
        return (stmt.value is not None and _is_literal(stmt.value) and len(targets) == 1
                and isinstance(targets[0], ast.Name))

    def _check_import(self, stmt: ast.Import | ast.ImportFrom) -> None:
        if isinstance(stmt, ast.Import):
            for alias in stmt.names:
                if alias.name not in PLAIN_IMPORTS or alias.asname != PLAIN_IMPORTS[alias.name]:
                    shown = alias.name + (f" as {alias.asname}" if alias.asname else "")
                    raise _refuse(stmt, f"import {shown} is not allowed (only `import torch`, `import math`,"
                                        " `import torch.nn.functional as F`)")
            return
        allowed = HELPER_MODULES.get(stmt.module or "")
        if allowed is None or stmt.level:
            modules = ", ".join(sorted(m for m in HELPER_MODULES if m.startswith("ctgpp")))
            raise _refuse(stmt, f"import from {stmt.module} is not allowed (the helper modules: {modules})")
        for alias in stmt.names:
            if alias.asname is not None:
                raise _refuse(stmt, f"from {stmt.module} import {alias.name} as {alias.asname} is not "
                                    "allowed (import helpers under their own names)")
            if alias.name not in allowed:
                raise _refuse(stmt, _unknown_helper(stmt.module or "", alias.name, allowed))

    def _check_class(self, cls: ast.ClassDef) -> None:
        if cls.decorator_list:
            raise _refuse(cls, "decorators are not allowed")
        if cls.keywords:
            raise _refuse(cls, "class keywords (metaclass=...) are not allowed")
        base = cls.bases[0] if len(cls.bases) == 1 else None
        if not (isinstance(base, ast.Name) and base.id == "GuidanceLoss"):
            raise _refuse(cls, f"class {cls.name} must derive from GuidanceLoss only")
        self.class_name = cls.name
        methods = [s for s in cls.body if isinstance(s, ast.FunctionDef)]
        if "forward" not in {m.name for m in methods}:
            raise _refuse(cls, f"class {cls.name} has no forward(self, x, data_batch, agt_mask=None) method")
        self.self_attributes = {m.name for m in methods}
        for stmt in cls.body:  # class constants, wherever they stand
            if isinstance(stmt, ast.Assign | ast.AnnAssign) and self._is_constant_definition(stmt):
                target = stmt.targets[0] if isinstance(stmt, ast.Assign) else stmt.target
                self.self_attributes.add(target.id)  # type: ignore[attr-defined]
        for node in ast.walk(cls):
            if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and _is_self(node.value):
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
                raise _refuse(stmt, f"{type(stmt).__name__} statement in the class body is not allowed: "
                                    "only a docstring, constants and methods")
        self.class_name = None

    def _check_function(self, fn: ast.FunctionDef) -> None:
        if fn.decorator_list:
            raise _refuse(fn, "decorators are not allowed")
        self._check_arguments(fn.args)
        self._check_annotation(fn.returns)
        self.functions.append(fn.name)
        for stmt in fn.body:
            self._check_statement(stmt)
        self.functions.pop()

    def _check_annotation(self, node: ast.AST | None) -> None:
        """Annotations are removed before execution; still, only plain type expressions are allowed."""
        if node is None:
            return
        for part in ast.walk(node):
            if not isinstance(part, ast.Name | ast.Attribute | ast.Subscript | ast.Constant | ast.Tuple
                              | ast.List | ast.BinOp | ast.BitOr | ast.expr_context):
                raise _refuse(part, f"{type(part).__name__} is not allowed in an annotation")
            name = getattr(part, "id", None) or getattr(part, "attr", None) or ""
            if name.startswith("_") or (isinstance(part, ast.Constant) and "__" in str(part.value)):
                raise _refuse(part, "names starting with '_' are not allowed in annotations")

    def _check_arguments(self, args: ast.arguments) -> None:
        for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg]:
            if arg is not None:
                self._check_annotation(arg.annotation)
        for default in [*args.defaults, *(d for d in args.kw_defaults if d is not None)]:
            if not _is_literal(default):
                raise _refuse(default, "default values must be literal constants")
            self._check_expr(default)

    def _check_statement(self, stmt: ast.stmt) -> None:
        kind = type(stmt).__name__
        if kind in REFUSED_STATEMENTS:
            raise _refuse(stmt, REFUSED_STATEMENTS[kind])
        if not isinstance(stmt, FUNCTION_STATEMENTS):
            raise _refuse(stmt, f"{kind} statements are not allowed")
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
            or (isinstance(node, ast.Attribute) and _is_self(node.value))
            or (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in LOOP_CALLS)
        )
        if not ok:
            raise _refuse(node, "for loops may only run over range(), enumerate(), zip(), reversed(), "
                                "a list or tuple, or a variable")

    # ---- expressions ------------------------------------------------------------------------------
    def _check_expr(self, node: ast.AST) -> None:
        if not isinstance(node, EXPRESSIONS):
            raise _refuse(node, f"{type(node).__name__} expressions are not allowed")
        if isinstance(node, ast.Name):
            self._check_name(node)
            return
        if isinstance(node, ast.Attribute):
            self._check_attribute(node)
            return
        if isinstance(node, ast.Constant):
            self._check_constant(node)
        elif isinstance(node, ast.BinOp):
            value = _fold_int(node)
            if value is not None and abs(value) > MAX_INT_CONSTANT:
                raise _refuse(node, f"integer constant too large ({value}; at most {MAX_INT_CONSTANT})")
        elif isinstance(node, ast.Call) and self._check_call(node):
            return
        elif isinstance(node, ast.keyword) and node.arg is not None and node.arg.startswith("_"):
            raise _refuse(node, f"names starting with '_' are not allowed ({node.arg})")
        elif isinstance(node, ast.arguments):
            self._check_arguments(node)
        for child in ast.iter_child_nodes(node):
            self._check_expr(child)

    def _check_constant(self, node: ast.Constant) -> None:
        value = node.value
        if isinstance(value, str | bytes) and ("__" in str(value)):
            raise _refuse(node, "string constants may not contain '__'")
        if type(value) is int and abs(value) > MAX_INT_CONSTANT:
            raise _refuse(node, f"integer constant too large ({value}; at most {MAX_INT_CONSTANT})")

    def _check_name(self, node: ast.Name) -> None:
        name = node.id
        if name.startswith("_") and name != "_":
            raise _refuse(node, f"names starting with '_' are not allowed ({name})")
        if name in FORBIDDEN_CALLS:
            raise _refuse(node, f"{name} is not allowed")
        if name in MODULE_NAMES:
            raise _refuse(node, f"the module {name} may only be used as {name}.<function>, not as a value")
        if name not in self.bound and name not in PREBOUND and name not in SAFE_BUILTIN_NAMES:
            raise _refuse(node, f"unknown name {name} (not a builtin, helper or variable of the program)")

    def _check_attribute(self, node: ast.Attribute) -> None:
        attr = node.attr
        if attr.startswith("_"):
            raise _refuse(node, f"attributes starting with '_' are not allowed (.{attr})")
        module = _module_path(node.value)
        if module is not None:
            allowed = MODULE_ATTRIBUTES[module]
            if attr not in allowed:
                raise _refuse(node, f"{module}.{attr} is not on the allow list")
            if module == "torch" and attr == "linalg":
                raise _refuse(node, "torch.linalg may only be used as torch.linalg.<function>")
            if not isinstance(node.ctx, ast.Load):
                raise _refuse(node, f"assigning to {module}.{attr} is not allowed")
            return
        if _is_self(node.value):
            if attr not in self.self_attributes:
                raise _refuse(node, f"self.{attr} is never assigned in the class")
            return
        if not isinstance(node.ctx, ast.Load):
            raise _refuse(node, f"assigning to the attribute .{attr} is only allowed on self")
        self._check_expr(node.value)  # the innermost problem is the most telling one
        if attr not in TENSOR_ATTRIBUTES and attr not in BATCH_ATTRIBUTES:
            raise _refuse(node, f"the attribute .{attr} is not on the allow list")

    def _check_call(self, node: ast.Call) -> bool:
        """Call-specific rules; True when the call is fully checked (``super().__init__()``)."""
        func = node.func
        if isinstance(func, ast.Name) and self.functions and func.id == self.functions[-1]:
            raise _refuse(node, f"recursion is not allowed ({func.id} calls itself)")
        if isinstance(func, ast.Attribute) and _is_self(func.value) and func.attr == self.method:
            raise _refuse(node, f"recursion is not allowed ({func.attr} calls itself)")
        if isinstance(func, ast.Attribute) and func.attr == "__init__" and _is_super_call(func.value,
                                                                                         self.class_name):
            if self.method != "__init__" or node.args or node.keywords:
                raise _refuse(node, "super().__init__() is only allowed, without arguments, inside __init__")
            return True  # nothing else in `super().__init__()` to check
        return False


def _is_self(node: ast.AST) -> bool:
    return isinstance(node, ast.Name) and node.id == "self"


def _is_super_call(node: ast.AST, class_name: str | None) -> bool:
    """``super()``, or ``super(C, self)`` inside class C."""
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "super"
            and not node.keywords):
        return False
    if not node.args:
        return True
    return (len(node.args) == 2 and isinstance(node.args[0], ast.Name) and node.args[0].id == class_name
            and _is_self(node.args[1]))


def _required_parameters(args: ast.arguments) -> list[str]:
    """Names of the parameters (after ``self``) that a call without arguments would leave unset."""
    positional = [*args.posonlyargs, *args.args]  # defaults belong to the last ones
    required = [a.arg for a in positional[1 : len(positional) - len(args.defaults)]]
    return required + [a.arg for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True) if d is None]


def _module_path(node: ast.AST) -> str | None:
    """"torch", "math", "F" or "torch.linalg" when ``node`` names that module, else None."""
    if isinstance(node, ast.Name) and node.id in MODULE_NAMES:
        return node.id
    if isinstance(node, ast.Attribute) and node.attr == "linalg" and _module_path(node.value) == "torch":
        return "torch.linalg"
    return None


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
