"""Reading the syntax-tree nodes of a generated program for the sandbox: the refusal
(:class:`SandboxError`), literals and folded integer constants, the names a program binds, and what a
node refers to (``self``, ``super()``, the modules ``torch``, ``math``, ``F``, ``torch.linalg``).
"""

from __future__ import annotations

import ast

MODULE_NAMES = frozenset({"torch", "math", "F"})


class SandboxError(ValueError):
    """Generated code refused by the sandbox; ``reason`` and ``lineno`` say why and where."""

    def __init__(self, reason: str, lineno: int) -> None:
        super().__init__(f"line {lineno}: {reason}")
        self.reason = reason
        self.lineno = lineno


def refuse(node: ast.AST, reason: str) -> SandboxError:
    """The refusal of ``node`` for ``reason``, at its line."""
    return SandboxError(reason, getattr(node, "lineno", 1))


def is_literal(node: ast.expr) -> bool:
    """Constants, negated constants and lists/tuples of literals (safe to evaluate at definition time)."""
    if isinstance(node, ast.Constant):
        return True
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        return is_literal(node.operand)
    return isinstance(node, ast.List | ast.Tuple) and all(is_literal(e) for e in node.elts)


def fold_int(node: ast.AST) -> int | None:
    """The value of an integer-literal expression (``10 ** 12``, ``4 * 10**9``), refusing huge ones."""
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return node.value
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow | ast.Mult | ast.LShift):
        left, right = fold_int(node.left), fold_int(node.right)
        if left is None or right is None:
            return None
        shifts = isinstance(node.op, ast.Pow | ast.LShift)
        if abs(left) > 2**64 or abs(right) > 2**64 or (shifts and right > 64):
            raise refuse(node, "integer constant too large (allocation or computation bomb)")
        if isinstance(node.op, ast.Pow):
            return left**right
        return left * right if isinstance(node.op, ast.Mult) else left << right
    return None


def bound_names(tree: ast.Module) -> set[str]:
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


def is_self(node: ast.AST) -> bool:
    """Whether ``node`` is the name ``self``."""
    return isinstance(node, ast.Name) and node.id == "self"


def is_super_call(node: ast.AST, class_name: str | None) -> bool:
    """``super()``, or ``super(C, self)`` inside class C."""
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "super"
            and not node.keywords):
        return False
    if not node.args:
        return True
    return (len(node.args) == 2 and isinstance(node.args[0], ast.Name) and node.args[0].id == class_name
            and is_self(node.args[1]))


def required_parameters(args: ast.arguments) -> list[str]:
    """Names of the parameters (after ``self``) that a call without arguments would leave unset."""
    positional = [*args.posonlyargs, *args.args]  # defaults belong to the last ones
    required = [a.arg for a in positional[1 : len(positional) - len(args.defaults)]]
    return required + [a.arg for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True) if d is None]


def module_path(node: ast.AST) -> str | None:
    """"torch", "math", "F" or "torch.linalg" when ``node`` names that module, else None."""
    if isinstance(node, ast.Name) and node.id in MODULE_NAMES:
        return node.id
    if isinstance(node, ast.Attribute) and node.attr == "linalg" and module_path(node.value) == "torch":
        return "torch.linalg"
    return None
