"""The sandbox's rules on the expressions of a generated program: which names, attributes, calls and
constants it may use, and what its annotations, argument lists and default values may hold — given
the scope the statement walk (:mod:`ctgpp.language.sandbox.statements`) keeps: the names the program
binds, the attributes its class assigns on ``self`` and the enclosing function, method and class.
"""

from __future__ import annotations

import ast

from ctgpp.language.sandbox.nodes import (
    MODULE_NAMES,
    fold_int,
    is_literal,
    is_self,
    is_super_call,
    module_path,
    refuse,
)
from ctgpp.language.sandbox.vocabulary import (
    BATCH_ATTRIBUTES,
    FORBIDDEN_CALLS,
    MAX_INT_CONSTANT,
    MODULE_ATTRIBUTES,
    SAFE_BUILTIN_NAMES,
    TENSOR_ATTRIBUTES,
    prebound_names,
)

PREBOUND = frozenset(prebound_names())
EXPRESSIONS = (
    ast.BoolOp, ast.BinOp, ast.UnaryOp, ast.Lambda, ast.IfExp, ast.Dict, ast.Set, ast.ListComp,
    ast.SetComp, ast.DictComp, ast.GeneratorExp, ast.Compare, ast.Call, ast.Constant, ast.Attribute,
    ast.Subscript, ast.Starred, ast.Name, ast.List, ast.Tuple, ast.Slice, ast.NamedExpr, ast.JoinedStr,
    ast.FormattedValue, ast.comprehension, ast.keyword, ast.arguments, ast.arg, ast.operator,
    ast.boolop, ast.unaryop, ast.cmpop, ast.expr_context,
)


class ExpressionChecker:
    """Checks expressions, annotations and arguments; raises :class:`SandboxError` at the first
    violation. The walk over statements (:class:`ctgpp.language.sandbox.statements.ProgramChecker`)
    extends it and keeps its scope up to date."""

    def __init__(self) -> None:
        self.bound: set[str] = set()
        self.self_attributes: set[str] = set()
        self.functions: list[str] = []  # enclosing function names, innermost last
        self.method: str | None = None  # the enclosing method of a loss class
        self.class_name: str | None = None  # the enclosing loss class

    def _check_annotation(self, node: ast.AST | None) -> None:
        """Annotations are removed before execution; still, only plain type expressions are allowed."""
        if node is None:
            return
        for part in ast.walk(node):
            if not isinstance(part, ast.Name | ast.Attribute | ast.Subscript | ast.Constant | ast.Tuple
                              | ast.List | ast.BinOp | ast.BitOr | ast.expr_context):
                raise refuse(part, f"{type(part).__name__} is not allowed in an annotation")
            name = getattr(part, "id", None) or getattr(part, "attr", None) or ""
            if name.startswith("_") or (isinstance(part, ast.Constant) and "__" in str(part.value)):
                raise refuse(part, "names starting with '_' are not allowed in annotations")

    def _check_arguments(self, args: ast.arguments) -> None:
        for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg]:
            if arg is not None:
                self._check_annotation(arg.annotation)
        for default in [*args.defaults, *(d for d in args.kw_defaults if d is not None)]:
            if not is_literal(default):
                raise refuse(default, "default values must be literal constants")
            self._check_expr(default)

    def _check_expr(self, node: ast.AST) -> None:
        if not isinstance(node, EXPRESSIONS):
            raise refuse(node, f"{type(node).__name__} expressions are not allowed")
        if isinstance(node, ast.Name):
            self._check_name(node)
            return
        if isinstance(node, ast.Attribute):
            self._check_attribute(node)
            return
        if isinstance(node, ast.Constant):
            self._check_constant(node)
        elif isinstance(node, ast.BinOp):
            value = fold_int(node)
            if value is not None and abs(value) > MAX_INT_CONSTANT:
                raise refuse(node, f"integer constant too large ({value}; at most {MAX_INT_CONSTANT})")
        elif isinstance(node, ast.Call) and self._check_call(node):
            return
        elif isinstance(node, ast.keyword) and node.arg is not None and node.arg.startswith("_"):
            raise refuse(node, f"names starting with '_' are not allowed ({node.arg})")
        elif isinstance(node, ast.arguments):
            self._check_arguments(node)
        for child in ast.iter_child_nodes(node):
            self._check_expr(child)

    def _check_constant(self, node: ast.Constant) -> None:
        value = node.value
        if isinstance(value, str | bytes) and ("__" in str(value)):
            raise refuse(node, "string constants may not contain '__'")
        if type(value) is int and abs(value) > MAX_INT_CONSTANT:
            raise refuse(node, f"integer constant too large ({value}; at most {MAX_INT_CONSTANT})")

    def _check_name(self, node: ast.Name) -> None:
        name = node.id
        if name.startswith("_") and name != "_":
            raise refuse(node, f"names starting with '_' are not allowed ({name})")
        if name in FORBIDDEN_CALLS:
            raise refuse(node, f"{name} is not allowed")
        if name in MODULE_NAMES:
            raise refuse(node, f"the module {name} may only be used as {name}.<function>, not as a value")
        if name not in self.bound and name not in PREBOUND and name not in SAFE_BUILTIN_NAMES:
            raise refuse(node, f"unknown name {name} (not a builtin, helper or variable of the program)")

    def _check_attribute(self, node: ast.Attribute) -> None:
        attr = node.attr
        if attr.startswith("_"):
            raise refuse(node, f"attributes starting with '_' are not allowed (.{attr})")
        module = module_path(node.value)
        if module is not None:
            allowed = MODULE_ATTRIBUTES[module]
            if attr not in allowed:
                raise refuse(node, f"{module}.{attr} is not on the allow list")
            if module == "torch" and attr == "linalg":
                raise refuse(node, "torch.linalg may only be used as torch.linalg.<function>")
            if not isinstance(node.ctx, ast.Load):
                raise refuse(node, f"assigning to {module}.{attr} is not allowed")
            return
        if is_self(node.value):
            if attr not in self.self_attributes:
                raise refuse(node, f"self.{attr} is never assigned in the class")
            return
        if not isinstance(node.ctx, ast.Load):
            raise refuse(node, f"assigning to the attribute .{attr} is only allowed on self")
        self._check_expr(node.value)  # the innermost problem is the most telling one
        if attr not in TENSOR_ATTRIBUTES and attr not in BATCH_ATTRIBUTES:
            raise refuse(node, f"the attribute .{attr} is not on the allow list")

    def _check_call(self, node: ast.Call) -> bool:
        """Call-specific rules; True when the call is fully checked (``super().__init__()``)."""
        func = node.func
        if isinstance(func, ast.Name) and self.functions and func.id == self.functions[-1]:
            raise refuse(node, f"recursion is not allowed ({func.id} calls itself)")
        if isinstance(func, ast.Attribute) and is_self(func.value) and func.attr == self.method:
            raise refuse(node, f"recursion is not allowed ({func.attr} calls itself)")
        if isinstance(func, ast.Attribute) and func.attr == "__init__" and is_super_call(func.value,
                                                                                        self.class_name):
            if self.method != "__init__" or node.args or node.keywords:
                raise refuse(node, "super().__init__() is only allowed, without arguments, inside __init__")
            return True  # nothing else in `super().__init__()` to check
        return False
