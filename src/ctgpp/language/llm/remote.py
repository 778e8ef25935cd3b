"""A generated loss that steers sampling from its worker process, for its whole life (DESIGN.md,
Language interface: generated code is untrusted).

:class:`RemoteLoss` is the guidance loss the sampler sees. Every call sends x (B, N, T, 6) to the worker
that loaded the program (:mod:`ctgpp.language.sandbox.worker`); the worker runs the loss within a per-call
time limit and its memory limit, checks the call (:class:`ctgpp.language.sandbox.session.LossSession`:
contract shape, finite cost and gradient, the batch read-only, no state that grows, bounded recursion) and
sends back the cost and its gradient with respect to x, which a ``torch.autograd.Function`` hands to
autograd. The worker holds its own copy of ``data_batch`` (the scene once, the rest once per re-plan), so
nothing the program does reaches the main process or the other losses.

Over the whole episode, the worker's CPU time in the program is bounded too
(:class:`ctgpp.language.llm.budget.LifetimeBudget`, when one is given): each call's time limit is the
per-call limit or what is left of the budget, whichever is less. ``rows`` restricts a per-vehicle
cost (B, N) to the vehicles the sentence names (the paper's ``agt_mask``).

The first breach stops the loss: the worker is killed, and this call and every later one raise
:class:`GeneratedLossError` with the reason in one line. The caller decides what follows (``ctgpp
simulate`` falls back to the offline compiler's loss, or stops with exit code 2 before writing).
"""

from __future__ import annotations

import weakref
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.llm.budget import LifetimeBudget
from ctgpp.language.sandbox.checks import GRACE_S, LossChecker, LossCheckError

__all__ = ["CALL_TIME_LIMIT_S", "GeneratedLossError", "RemoteLoss"]

CALL_TIME_LIMIT_S = 2.0  # a call of a loss takes milliseconds; a call that runs this long is stopped
TRANSFER_TIME_LIMIT_S = 60.0  # sending the scene or a batch to the worker, and loading the program
DTYPES = {torch.float32: 4, torch.float64: 8, torch.float16: 2, torch.bfloat16: 2}


class GeneratedLossError(RuntimeError):
    """A generated loss was stopped during sampling (time, memory, contract, batch write, growing
    state, recursion, an exception); the message is one line with the reason."""


class _RemoteCall(torch.autograd.Function):
    """cost = loss(x) computed in the worker; backward uses the gradient the worker computed."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, owner: RemoteLoss, batch: Any, agt_mask: Tensor | None,
                want_grad: bool) -> Tensor:
        out, grad = owner.evaluate(x, batch, agt_mask, want_grad=want_grad)
        ctx.owner, ctx.batch, ctx.agt_mask = owner, batch, agt_mask
        ctx.save_for_backward(x, grad if grad is not None else torch.zeros(0))
        return out

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, None, None, None, None]:
        x, grad = ctx.saved_tensors
        flat = grad_out.reshape(-1)
        if grad.numel() == x.numel() and bool((flat == flat[0]).all()):  # Σ c·cost: c times Σ cost's
            return grad * flat[0], None, None, None, None
        _, exact = ctx.owner.evaluate(x, ctx.batch, ctx.agt_mask, want_grad=True, weights=grad_out)
        return exact, None, None, None, None


class RemoteLoss(GuidanceLoss):
    """The generated program ``code`` as a guidance loss whose every call runs in ``worker``.

    worker: a :class:`LossChecker` (None starts one); with ``own_worker`` this loss takes it over and
    stops it when the loss is stopped or closed, else it leaves it running for a next loss (the
    worker drops a failed loss's instance itself, and was killed when it did not answer in time).
    call_time_limit_s: the time limit of each call. rows: the vehicles a per-vehicle cost is
    restricted to (None: all). budget: the episode's :class:`LifetimeBudget` (None: none). The
    program is loaded and its instance built here (within ``TRANSFER_TIME_LIMIT_S``); a program that
    fails to load raises GeneratedLossError.
    """

    def __init__(self, code: str, worker: LossChecker | None = None,
                 call_time_limit_s: float = CALL_TIME_LIMIT_S, own_worker: bool = True,
                 rows: tuple[int, ...] | None = None, budget: LifetimeBudget | None = None) -> None:
        super().__init__()
        self.code = code
        self.call_time_limit_s = float(call_time_limit_s)
        self.budget = budget
        self.cpu_s = 0.0  # the worker's CPU time in this loss's calls
        self.worker = LossChecker() if worker is None else worker
        self.own_worker = own_worker or worker is None
        self.failure: str | None = None
        self.calls = 0
        self._scene: tuple[weakref.ref[Any], weakref.ref[Any]] | None = None
        self._batch: weakref.ref[Any] | None = None
        rows = None if rows is None else tuple(int(r) for r in rows)
        header = self._request(("load", code, rows, TRANSFER_TIME_LIMIT_S), TRANSFER_TIME_LIMIT_S)
        self.name = str(header.get("name", "generated loss"))
        self._couples = bool(header.get("couples_agents", False))

    @property
    def couples_agents(self) -> bool:  # type: ignore[override]
        return self._couples

    def close(self) -> None:
        """Stop the loss and, when it owns it, its worker (calls after this raise GeneratedLossError)."""
        self.failure = self.failure or "the loss was closed"
        if self.own_worker:
            self.worker.close()

    def _stop(self, reason: str) -> GeneratedLossError:
        """Mark the loss stopped, kill the worker it owns; the error to raise."""
        reason = " ".join(reason.split())
        name = getattr(self, "name", "generated loss")
        self.failure = f"the language model's loss {name} was stopped at call {self.calls}: {reason}"
        if self.own_worker:
            self.worker.kill()
        return GeneratedLossError(self.failure)

    def _request(self, message: tuple[Any, ...], timeout_s: float) -> dict[str, Any]:
        """The worker's answer header to ``message`` (a request that expects no payload)."""
        return self._exchange(message, timeout_s, 0)[0]

    def _exchange(
        self, message: tuple[Any, ...], timeout_s: float, max_payload: int
    ) -> tuple[dict[str, Any], bytes | None]:
        """The worker's answer to ``message``: its header and a payload of at most ``max_payload``
        bytes; a failed or refused request stops the loss."""
        try:
            header, payload = self.worker.request(message, timeout_s, max_payload)
        except (LossCheckError, RuntimeError) as err:
            raise self._stop(str(err)) from None
        if not header.get("ok"):
            raise self._stop(str(header.get("error", "unknown error")))
        return header, payload

    def _send_batch(self, batch: Any) -> None:
        """Hand ``batch`` to the worker unless it already has it: a :class:`GuidanceBatch`'s scene and
        SDF once per scene, the rest once per batch; any other object whole, every call."""
        if not isinstance(batch, GuidanceBatch):
            self._batch = None
            self._request(("batch", batch), TRANSFER_TIME_LIMIT_S)
            return
        if self._batch is not None and self._batch() is batch:
            return
        if self._scene is None or self._scene[0]() is not batch.scene or self._scene[1]() is not batch.sdf:
            self._request(("scene", batch.scene, batch.sdf), TRANSFER_TIME_LIMIT_S)
            self._scene = (weakref.ref(batch.scene), weakref.ref(batch.sdf))
        # the worker already holds the scene and the SDF: the batch travels without them
        stub = replace(batch, scene=None, sdf=batch.sdf[:0], memo={})  # type: ignore[arg-type]
        self._request(("batch", stub), TRANSFER_TIME_LIMIT_S)
        self._batch = weakref.ref(batch)

    def evaluate(self, x: Tensor, batch: Any, agt_mask: Tensor | None = None, *, want_grad: bool,
                 weights: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """One call in the worker: cost (B, N) or (N,) and, with ``want_grad``, the gradient of
        Σ weights·cost w.r.t. x (B, N, T, 6), both on x's device and dtype. Raises GeneratedLossError."""
        if self.failure is not None:
            raise GeneratedLossError(self.failure)
        if x.dtype not in DTYPES:
            raise self._stop(f"x has dtype {x.dtype}; expected floating point")
        self._send_batch(batch)
        self.calls += 1
        xc = x.detach().cpu()
        mask = None if agt_mask is None else agt_mask.detach().cpu()
        w = None if weights is None else weights.detach().cpu()
        size = DTYPES[x.dtype]
        limit = (x.shape[0] * x.shape[1] + (x.numel() if want_grad else 0)) * size
        time_limit = self.call_time_limit_s
        if self.budget is not None:
            self.budget.admit(x, batch, want_grad)
            time_limit = self.budget.call_limit_s(self.call_time_limit_s)
        try:
            header, payload = self._exchange(("call", xc, mask, w, bool(want_grad), time_limit),
                                             time_limit + GRACE_S, max(limit, 1))
        except GeneratedLossError as err:
            if (self.budget is not None and time_limit < self.call_time_limit_s
                    and "did not finish within" in str(err)):
                self.budget.charge(time_limit)  # stopped at what was left of the budget
                self.failure = None
                raise self._stop(self.budget.overrun()) from None
            raise
        self.cpu_s += float(header.get("cpu_s", 0.0))
        if self.budget is not None and (overrun := self.budget.charge(float(header.get("cpu_s", 0.0)))):
            raise self._stop(overrun)
        shape = tuple(int(d) for d in header.get("shape", ()))
        n_out = int(torch.Size(shape).numel())
        expected = (n_out + (x.numel() if want_grad else 0)) * size
        contract = ((x.shape[0], x.shape[1]), (x.shape[1],))
        if payload is None or len(payload) != expected or shape not in contract:
            raise self._stop("the worker's answer does not match the call")
        values = torch.frombuffer(bytearray(payload), dtype=x.dtype)
        out = values[:n_out].reshape(shape).to(x.device)
        grad = values[n_out:].reshape(x.shape).to(x.device) if want_grad else None
        return out, grad

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        """The generated loss of x (B, N, T, 6): (B, N) or (N,), differentiable w.r.t. x."""
        want_grad = torch.is_grad_enabled() and x.requires_grad
        return _RemoteCall.apply(x, self, data_batch, agt_mask, want_grad)
