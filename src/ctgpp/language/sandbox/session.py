"""One generated loss, guarded call by call, inside the worker process (DESIGN.md, Language interface).

Every call of generated code — in its trial (:mod:`ctgpp.language.sandbox.trial`) and for its whole life
during sampling (:class:`ctgpp.language.llm.remote.RemoteLoss`) — goes through :meth:`LossSession.call`,
which refuses (:class:`~ctgpp.language.sandbox.checks.LossCheckError`, with the reason):

- a result outside the contract: not a floating tensor of shape (B, N) or (N,), or not finite;
- a gradient with respect to x that is not finite (or, when one is asked for, a cost that does
  not depend differentiably on x);
- a write into ``data_batch``: every tensor of the batch has a version counter that each in-place
  write bumps, through views too; a call after which one moved is refused, naming the field. The
  helpers' memory (``data_batch.memo``: lane choices the helpers keep per batch) is read-only to
  the program too: the helpers may add entries, but an entry the call found there must come out
  unchanged (the same object, a tensor's version, a list's length and items). The
  worker holds its own copy of the batch, so not even a refused write reaches the main process;
- state that grows between calls: :func:`state_size` counts what the loss object, its classes and
  its module's namespace hold (tensor elements, autograd nodes, container lengths; a number counts
  one, so a call counter is no growth); a call that leaves more than the previous call with the same
  shape of x did is refused, naming what grew (the attribute or global, its kind, before and after);
- recursion deeper than ``RECURSION_FRAMES`` frames (mutual recursion included).

Time and memory are bounded by the worker (``SIGPROF`` per call, ``RLIMIT_AS``); the time of the
whole life by :class:`ctgpp.language.llm.remote.RemoteLoss`. ``rows`` (the vehicles the sentence
names, the paper's ``agt_mask``) restricts a per-vehicle cost (B, N) to those rows.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import fields
from types import BuiltinFunctionType, FrameType, FunctionType, ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.language.sandbox.checks import LossCheckError

__all__ = ["RECURSION_FRAMES", "LossSession", "state_size"]

RECURSION_FRAMES = 250  # frames a call may stack above its caller (the helpers need a few dozen)
MAX_STATE_ITEMS = 200_000  # objects state_size visits before it refuses the state as too large
GENERATED_MODULE = "ctgpp_generated"  # __name__ of the namespace load_loss_class executes in


def _graph_nodes(tensor: Tensor, limit: int) -> int:
    """The number of autograd nodes behind ``tensor`` (at most ``limit``): a stored tensor that keeps
    its history grows with every call that extends it."""
    seen: set[int] = set()
    stack = [tensor.grad_fn]
    while stack and len(seen) < limit:
        node = stack.pop()
        if node is None or id(node) in seen:
            continue
        seen.add(id(node))
        stack.extend(nxt for nxt, _ in node.next_functions)
    return len(seen)


def state_size(roots: Iterable[object]) -> int:
    """What ``roots`` hold, in items: tensor and array elements, autograd nodes of stored tensors,
    container lengths, one per number; generated classes and functions are walked through (class
    attributes, default arguments, closure cells), library modules, classes and functions are not.
    Raises LossCheckError beyond ``MAX_STATE_ITEMS`` objects."""
    seen: dict[int, object] = {}  # id -> the object, held so that no id is reused during the walk
    stack = list(roots)
    total = 0
    while stack:
        obj = stack.pop()
        if id(obj) in seen:
            continue
        seen[id(obj)] = obj
        if len(seen) > MAX_STATE_ITEMS:
            raise LossCheckError(f"the loss keeps more than {MAX_STATE_ITEMS} objects in its state")
        if isinstance(obj, Tensor):
            total += obj.numel() + (_graph_nodes(obj, MAX_STATE_ITEMS) if obj.grad_fn is not None else 0)
        elif isinstance(obj, np.ndarray):
            total += int(obj.size)
        elif isinstance(obj, str | bytes):
            total += len(obj)
        elif isinstance(obj, dict):
            total += len(obj)
            stack.extend(v for k, v in obj.items() if k != "__builtins__")
            stack.extend(obj)
        elif isinstance(obj, list | tuple | set | frozenset):
            total += len(obj)
            stack.extend(obj)
        elif isinstance(obj, ModuleType | BuiltinFunctionType):
            continue
        elif isinstance(obj, FunctionType):
            if obj.__module__ == GENERATED_MODULE:
                stack.extend([obj.__defaults__ or (), obj.__kwdefaults__ or {}])
                stack.extend(cell.cell_contents for cell in obj.__closure__ or () if _filled(cell))
        elif isinstance(obj, type):
            if obj.__module__ == GENERATED_MODULE:
                stack.extend(vars(obj).values())
        elif hasattr(obj, "__dict__"):  # modules of torch.nn, dataclasses, other objects
            total += 1
            stack.append(vars(obj))
        else:
            total += 1
    return total


_MODULE_FIELDS = frozenset({"_parameters", "_buffers", "_modules", "_non_persistent_buffers_set",
                            "_backward_pre_hooks", "_backward_hooks", "_forward_hooks", "_forward_pre_hooks",
                            "_forward_hooks_with_kwargs", "_forward_pre_hooks_with_kwargs",
                            "_forward_hooks_always_called", "_state_dict_hooks", "_state_dict_pre_hooks",
                            "_load_state_dict_pre_hooks", "_load_state_dict_post_hooks",
                            "_is_full_backward_hook", "training"})


def _kind(value: object) -> str:
    """A few words on what ``value`` is, for a message."""
    if isinstance(value, Tensor):
        return "a tensor that keeps its autograd history" if value.grad_fn is not None else "a tensor"
    return f"a {type(value).__name__}"


def _memo_marks(batch: Any) -> dict[Any, Any]:
    """What each entry of ``batch.memo`` is now: the object's id, and for a tensor its version and
    shape, for a list or tuple its length and the marks of its items."""
    memo = getattr(batch, "memo", None)
    return {key: _mark(value) for key, value in memo.items()} if isinstance(memo, dict) else {}


def _mark(value: Any) -> Any:
    if isinstance(value, Tensor):
        return ("tensor", id(value), value._version, tuple(value.shape))
    if isinstance(value, list | tuple):
        return (type(value).__name__, id(value), len(value), tuple(_mark(v) for v in value))
    if isinstance(value, dict):
        return ("dict", id(value), tuple((k, _mark(v)) for k, v in value.items()))
    return ("value", id(value))


def _filled(cell: Any) -> bool:
    try:
        cell.cell_contents  # noqa: B018
    except ValueError:
        return False
    return True


@contextmanager
def recursion_cap(frames: int = RECURSION_FRAMES) -> Iterator[None]:
    """Allow at most ``frames`` Python frames above the current one while the block runs."""
    depth = 0
    frame: FrameType | None = sys._getframe()
    while frame is not None:
        depth, frame = depth + 1, frame.f_back
    before = sys.getrecursionlimit()
    sys.setrecursionlimit(depth + frames)
    try:
        yield
    finally:
        sys.setrecursionlimit(before)


def _batch_tensors(batch: Any) -> dict[str, Tensor]:
    """The tensor fields of a dataclass batch by name (nothing for other objects)."""
    try:
        values = {f.name: getattr(batch, f.name) for f in fields(batch)}
        return {name: value for name, value in values.items() if isinstance(value, Tensor)}
    except TypeError:
        return {}


class LossSession:
    """A loss instance and the batch its calls see, each call checked (module docstring).

    loss: the instance; roots: what its state lives in besides itself (its module's namespace).
    """

    def __init__(self, loss: nn.Module, batch: Any, roots: Iterable[object] = (),
                 rows: Sequence[int] | None = None) -> None:
        self.loss = loss
        self.roots = [loss, *roots]
        self.calls = 0
        self.rows = None if rows is None else tuple(int(r) for r in rows)
        self.sizes: dict[tuple[int, ...], int] = {}
        self.parts: dict[tuple[int, ...], dict[str, int]] = {}
        self.set_batch(batch)

    @classmethod
    def build(cls, loss_cls: type[GuidanceLoss], batch: Any,
              rows: Sequence[int] | None = None) -> LossSession:
        """``loss_cls()`` with the namespace of its module (where generated code keeps globals); a
        per-vehicle cost restricted to ``rows`` when given."""
        try:
            with recursion_cap():
                loss = loss_cls()
        except TypeError as err:
            raise LossCheckError(f"could not build {loss_cls.__name__}() without arguments ({err}): give "
                                 "every parameter of __init__ a default value") from None
        forward = getattr(loss_cls, "forward", None)
        namespace = getattr(forward, "__globals__", None)
        generated = isinstance(namespace, dict) and namespace.get("__name__") == GENERATED_MODULE
        return cls(loss, batch, [namespace] if generated else [], rows)

    def set_batch(self, batch: Any) -> None:
        """Hand the calls a new ``data_batch`` (the next re-plan's); its tensors' versions are noted."""
        self.batch = batch
        self.versions = {name: t._version for name, t in _batch_tensors(batch).items()}

    def _check_batch(self, memo: dict[Any, Any]) -> None:
        for name, t in _batch_tensors(self.batch).items():
            if t._version != self.versions.get(name):
                raise LossCheckError(f"the loss wrote into data_batch.{name}: the batch is read-only "
                                     "(compute new tensors instead of changing the batch)")
        now = _memo_marks(self.batch)
        for key, mark in memo.items():
            if now.get(key) != mark:
                raise LossCheckError(
                    f"the loss changed data_batch.memo[{key!r}], the helpers' memory of lane choices: it is "
                    "read-only (a helper's result is shared with later calls; copy it, e.g. with "
                    "torch.cat or * 1.0, before changing it)")

    def _parts(self) -> dict[str, object]:
        """What the state lives in, by the name a message gives it: ``self.NAME`` for the loss's
        attributes, ``NAME`` for the program's globals."""
        parts: dict[str, object] = {}
        for root in self.roots:
            if isinstance(root, dict):
                parts.update({k: v for k, v in root.items() if k != "__builtins__" and not isinstance(
                    v, ModuleType | BuiltinFunctionType)})
            else:
                parts.update({f"self.{k}": v for k, v in vars(root).items() if k not in _MODULE_FIELDS})
                for field in ("_modules", "_parameters", "_buffers"):  # what nn.Module keeps aside
                    parts.update({f"self.{k}": v for k, v in getattr(root, field, {}).items()})
        return parts

    def _check_state(self, shape: tuple[int, ...]) -> None:
        parts = {name: state_size([value]) for name, value in self._parts().items()}
        size = sum(parts.values())
        before = self.sizes.get(shape)
        if before is not None and size > before:
            grew = [(n, parts[n] - self.parts.get(shape, {}).get(n, 0)) for n in parts]
            name, _ = max(grew, key=lambda g: g[1])
            was = self.parts.get(shape, {}).get(name, 0)
            raise LossCheckError(
                f"the loss keeps state that grows between calls: {name} ({_kind(self._parts()[name])}) held "
                f"{was} items before call {self.calls} and {parts[name]} after, for x of shape {shape} (a "
                "loss must not remember its inputs or their history; a plain number such as a call "
                "counter is fine)")
        if before is None or size >= before:
            self.parts[shape] = parts
        self.sizes[shape] = size if before is None else max(before, size)

    def call(self, x: Tensor, *, want_grad: bool, agt_mask: Tensor | None = None,
             weights: Tensor | None = None, name: str = "x") -> tuple[Tensor, Tensor | None]:
        """One checked call on x (B, N, T, 6): the cost (B, N) or (N,), detached, and — with
        ``want_grad`` — the gradient of Σ weights·cost (weights 1 when None) w.r.t. x, (B, N, T, 6).
        ``name`` names x in messages. Raises LossCheckError."""
        self.calls += 1
        xg = x.detach().clone().requires_grad_(want_grad)
        memo = _memo_marks(self.batch)
        with torch.enable_grad(), recursion_cap():
            out = self.loss(xg, self.batch) if agt_mask is None else self.loss(xg, self.batch, agt_mask)
        self._check_batch(memo)
        n_b, n_n = int(x.shape[0]), int(x.shape[1])
        if not isinstance(out, Tensor):
            raise LossCheckError(f"forward must return a torch tensor, not {type(out).__name__}")
        shape = tuple(out.shape)
        if shape not in ((n_b, n_n), (n_n,)):
            raise LossCheckError(f"forward returned shape {shape}; expected ({n_b}, {n_n}) = (B, N) per "
                                 f"vehicle or ({n_n},) = (N,) per sample, for x of shape {tuple(x.shape)}")
        if not out.dtype.is_floating_point:
            raise LossCheckError(f"forward returned a {out.dtype} tensor; expected floating point")
        if not bool(torch.isfinite(out).all()):
            raise LossCheckError(f"forward returned non-finite values (nan or inf) for {name} "
                                 f"(call {self.calls}, x of shape {tuple(x.shape)})")
        if self.rows is not None and out.dim() == 2:  # the paper's agt_mask: the named vehicles' rows
            keep = torch.zeros(n_b, dtype=out.dtype)
            keep[[r for r in self.rows if r < n_b]] = 1.0
            out = out * keep[:, None]  # (B, N)
        grad = None
        if want_grad:
            if not out.requires_grad:
                raise LossCheckError("the cost does not depend differentiably on x (no gradient): guidance "
                                     "moves the plans only along the gradient, so this loss would steer "
                                     "nothing (no .detach(), comparisons, argmax or rounding alone)")
            w = torch.ones_like(out) if weights is None else weights.to(out.dtype).reshape(out.shape)
            with recursion_cap():
                (grad,) = torch.autograd.grad(out, xg, w, allow_unused=True)
            grad = torch.zeros_like(xg) if grad is None else grad
            if not bool(torch.isfinite(grad).all()):
                raise LossCheckError(f"the gradient with respect to x has nan or inf values for {name} "
                                     f"(call {self.calls}, x of shape {tuple(x.shape)})")
        self._check_state(tuple(x.shape))
        return out.detach(), grad
