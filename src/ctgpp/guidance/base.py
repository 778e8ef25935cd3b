"""The guidance-loss contract of the paper's LLM API (DESIGN.md, Guided sampling), and its registry.

A guidance loss is a ``torch.nn.Module`` whose ``forward(x, data_batch, agt_mask=None)`` takes
x of shape (B, N, T, 6): B vehicles (the controlled vehicles in displayed order: row i is
"vehicle i"), N samples, T future steps of 0.1 s, channels (x, y, vel, yaw, acc, yawvel) in each
vehicle's own current frame; and returns a differentiable cost of shape (B, N) (per vehicle) or (N)
(per sample, for rules that couple vehicles). Lower is better. ``data_batch`` is whatever the
sampler passes (a :class:`ctgpp.guidance.context.GuidanceBatch`); loss code only hands it on to the
helpers. ``agt_mask`` (B,) bool, when given, selects the vehicles the loss applies to. ``scope()``
says which vehicles a loss addresses (:class:`ctgpp.guidance.scope.LossScope`), so that the realism
guards leave alone what the loss asks for; ``constraints()`` what it asks of the executed plan beyond
its gradient (:class:`ctgpp.guidance.constraints.PlanConstraints`: a speed limit held exactly, a turn's
lane path, the pairs it may ask to collide), which the plan stages read; ``guided_parts()`` and
``ranking()`` what the guidance step and filtration minimize (the cost itself, unless the loss carries
the realism guards apart). A loss is pure: the same x and batch give the same cost, whatever it saw
before (the episode's start is on the batch).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, ClassVar

from torch import Tensor, nn

from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.scope import LossScope

# what a guidance step minimizes (GuidanceLoss.guided_parts): the cost; (Adam's part, the need step's:
# the guards or a limit); or (the rule's other parts, the guards, the limits)
GuidedParts = Tensor | tuple[Tensor, Tensor] | tuple[Tensor, Tensor, Tensor]


class GuidanceLoss(nn.Module):
    """Base class of every guidance loss: rules of the library, compiled queries, generated code.

    ``couples_agents`` is True when the cost depends on several vehicles jointly (collision,
    keep distance): filtration then keeps one sample index for the whole scene. ``sets_pace`` is True
    for a loss that sets the speed of the vehicles it moves (a target speed, a stop, a limit, a
    following distance): a sequence does not also hold such a vehicle to its pace while a later part
    waits (:class:`~ctgpp.guidance.sequence.KeepPace`). ``separable`` is True for a loss whose cost
    of each vehicle reads that vehicle's trajectory alone (a speed, a lane, the road): restricted to
    some vehicles, it reads only theirs (:meth:`reads`). ``need_step`` is True for a limit that a
    plan meets unless it strays (an acceleration limit): the guidance step moves it only as far as its
    cost needs, as the realism guards (:meth:`guided_parts`), not by Adam's step, which moves every
    action with any gradient by the whole learning rate.
    """

    couples_agents: ClassVar[bool] = False
    sets_pace: ClassVar[bool] = False
    separable: ClassVar[bool] = False
    need_step: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A subclass that writes its own ``forward`` does not inherit ``separable`` or ``need_step``:
        they describe the cost the declaring class computes (a user's subclass of a speed rule that
        reads a pair would otherwise be composed as if it read one vehicle)."""
        super().__init_subclass__(**kwargs)
        if "forward" in cls.__dict__:
            for name in ("separable", "need_step"):
                if name not in cls.__dict__ and getattr(cls, name) is True:
                    setattr(cls, name, False)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        raise NotImplementedError

    def scope(self) -> LossScope:
        """Which vehicles the loss addresses, which it moves out of their lanes and which pairs it
        asks to collide (for the realism guards). A loss that does not say is opaque."""
        return LossScope.unknown()

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """What the loss asks of the executed plan beyond its gradient, at the re-plan of
        ``data_batch``: by default no cap and no route (its limits are left to guidance), and the pairs
        its scope may ask to collide."""
        return PlanConstraints.of_scope(self.scope(), int(data_batch.num_vehicles))

    def reached(self, data_batch: Any) -> bool | None:
        """Whether what the loss asks is achieved at the re-plan of ``data_batch``, judged from the
        vehicles' state at its step (never a later one): a sequence's next stage waits for it
        (:class:`~ctgpp.guidance.sequence.InOrder`). None: the loss cannot tell (the default), and a
        sequence does not wait for it."""
        return None

    def involved(self, x: Tensor, data_batch: Any) -> Tensor | None:
        """(B,) bool for one scene x (B, 1, T, 6): the vehicles that a term of :meth:`ranking` costing
        anything there reads, for a loss that is a sum of non-negative terms each reading one vehicle or
        a pair. Another vehicle's trajectory can then only add to the cost: composing a plan
        (:func:`~ctgpp.diffusion.filtration.compose`) need not try it elsewhere. None: the loss cannot
        tell (the default), and every vehicle is tried."""
        return None

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        """The vehicles (displayed numbers, of ``num_vehicles``) whose trajectories the cost reads: a
        switch of any other vehicle's trajectory leaves it unchanged (composing a plan need not try
        it for this loss: :meth:`involved` of a guarded loss). Every vehicle for a separable loss;
        None: the loss cannot tell (the default)."""
        return frozenset(range(num_vehicles)) if self.separable else None

    def reached_for(self, data_batch: Any, vehicles: Sequence[int]) -> bool | None:
        """:meth:`reached` for some ``vehicles`` (displayed numbers) only, as a loss restricted to them
        (:class:`~ctgpp.guidance.rules.relative.ForVehicles`) asks; by default :meth:`reached`."""
        return self.reached(data_batch)

    def guided_parts(self, x: Tensor, data_batch: Any) -> GuidedParts:
        """What a guidance step minimizes (:func:`ctgpp.diffusion.guided.guide_mean`): the cost; or the
        pair (what Adam's step minimizes, what the need step does) for a loss that carries the realism
        guards or a limit apart (``need_step``: (0, the cost)); or, for a guarded loss with limits,
        (the rule's other parts, the guards, the limits)."""
        cost = self(x, data_batch)
        return (cost.new_zeros(()), cost) if self.need_step else cost

    def ranking(self, x: Tensor, data_batch: Any) -> Tensor:
        """What filtration minimizes among the samples: the cost (a loss with the realism guards ranks
        them first)."""
        return self(x, data_batch)


LossFactory = Callable[..., GuidanceLoss]
_REGISTRY: dict[str, LossFactory] = {}


def register_loss(name: str) -> Callable[[LossFactory], LossFactory]:
    """Register a loss class (or factory) under ``name``; a name may be registered once."""

    def decorator(factory: LossFactory) -> LossFactory:
        if name in _REGISTRY:
            raise ValueError(f"guidance loss {name!r} is already registered")
        _REGISTRY[name] = factory
        return factory

    return decorator


def registered_losses() -> dict[str, LossFactory]:
    """Name -> factory of every registered loss (a copy)."""
    return dict(_REGISTRY)
