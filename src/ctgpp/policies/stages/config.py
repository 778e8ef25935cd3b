"""The plan stages' switches and constants, in one frozen value (:class:`StageConfig`).

Every constant that changes a plan after the denoiser lives here with the reason it has its value; the
measurements behind them are summarised in ``docs/decisions/plan-stages.md``. ``--stages`` chooses which
of the switchable stages run (:data:`SWITCHABLE`), independently of ``--guards``: the stages read what
the loss asks of the plan (:class:`~ctgpp.guidance.constraints.PlanConstraints`), not the guards.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ctgpp.geometry import CONTACT_GAP_M

# the stages a user may switch off, in pipeline order: each is a test-time controller beyond the paper
SWITCHABLE = ("steer", "cap", "brake")


@dataclass(frozen=True)
class SteeringConfig:
    """Pure pursuit along a committed turn (:mod:`ctgpp.policies.stages.steering`).

    These values were set by hand while looking at scene-0103's left turn and the paper's failure case
    (scene-0553) — not swept, and chosen on the scenes they were reported on; the decision record
    (``docs/decisions/plan-stages.md``) says what each was meant to do and what was measured.

    look_ahead_s, look_ahead_min_m: the pursued point lies 0.8 s of driving ahead along the path, at
    least 4 m (about a car's length, so that a slow car does not pursue a point under its bonnet).
    merge_m_per_m: and 8 m ahead per metre the vehicle lies beside the path, so that a path starting
    in the lane beside (about 3.5 m over) is joined over about 28 m, a lane change's length at urban
    speed, not in one swerve.
    curve_lat_acc_mps2: a bend is taken no faster than 3 m/s² of lateral acceleration allows (ordinary
    urban driving; sporty driving reaches 4–5 m/s²). curve_brake_mps2: a bend ahead is braked for at
    4 m/s², a firm but ordinary deceleration. curve_samples: points across the braking distance at
    which the bends ahead are read.
    keep_mps, keep_acc_mps2, keep_from_mps: a vehicle that moves (1 m/s or more) on a clear way is kept
    going at least 5 m/s (or its bend's speed, if less) by accelerating at most 2 m/s² (a gentle
    pull-away): steered but not kept going, vehicle 20 of the paper's failure case crawled through
    its turn at 1–3 m/s and vehicle 21 behind it never finished its own; one slower than 1 m/s is
    left to stop, as its plan says. A query's speed cap lowers the speed kept (the cap stage's limit
    is never lifted).
    clear_m: a way is clear where no replayed agent comes within 2 m of the path ahead (beyond both
    halves' widths); without the clear-way condition the left turn pushed into the crowd on the
    crossing.
    """

    look_ahead_s: float = 0.8
    look_ahead_min_m: float = 4.0
    merge_m_per_m: float = 8.0
    curve_lat_acc_mps2: float = 3.0
    curve_brake_mps2: float = 4.0
    curve_samples: int = 8
    keep_mps: float = 5.0
    keep_acc_mps2: float = 2.0
    keep_from_mps: float = 1.0
    clear_m: float = 2.0


@dataclass(frozen=True)
class BrakeConfig:
    """Braking the executed plans for what lies ahead (:mod:`ctgpp.policies.stages.brakes`).

    Set by hand from NGSIM Peachtree's "vehicle 11 should drive at 10 m/s", where the chosen plan
    overlapped the car in front 4 s on; not swept. horizon_s: contacts within the next 2 s count (the
    usual following gap, and four re-plans at 2 Hz, so a contact further out is met again before it is
    near). buffer_m: boxes nearer than 0.1 m touch. The executed plan is what the metrics measure
    exactly, so this buffer only has to absorb round-off; the collision guard keeps a larger one
    (``GuardConfig.collision_buffer_m``, 0.2 m) on the sampled plans, which guidance bends only
    approximately. rounds: the vehicles behind one that brakes are checked again against its new
    plan 3 times (a queue of four reacts within one re-plan). bisections: the braking share is found
    to 2⁻¹⁰ of the way to the braking bound.
    """

    horizon_s: float = 2.0
    buffer_m: float = CONTACT_GAP_M
    rounds: int = 3
    bisections: int = 10


@dataclass(frozen=True)
class StageConfig:
    """Which switchable stages run (``stages``, in :data:`SWITCHABLE` order) and their constants.

    The default runs all of them (``ctgpp simulate``); :meth:`off` runs none — the paper's protocol,
    the samples ranked by the loss alone (``ctgpp evaluate``).
    """

    stages: tuple[str, ...] = SWITCHABLE
    steering: SteeringConfig = field(default_factory=SteeringConfig)
    brakes: BrakeConfig = field(default_factory=BrakeConfig)

    def __post_init__(self) -> None:
        unknown = [s for s in self.stages if s not in SWITCHABLE]
        if unknown:
            raise ValueError(f"unknown stage {unknown[0]!r}; the stages are: {', '.join(SWITCHABLE)}")
        object.__setattr__(self, "stages", tuple(s for s in SWITCHABLE if s in self.stages))

    @classmethod
    def off(cls) -> StageConfig:
        """No switchable stage: sampling and ranking only."""
        return cls(stages=())

    @classmethod
    def parse(cls, text: str) -> StageConfig:
        """``on`` (or ``all``): every stage; ``off`` (or ``none``): none; else a comma-separated subset
        such as ``steer,cap``."""
        word = text.strip().lower()
        if word in ("on", "all"):
            return cls()
        if word in ("off", "none", ""):
            return cls.off()
        return cls(stages=tuple(s.strip() for s in word.split(",") if s.strip()))

    def runs(self, name: str) -> bool:
        return name in self.stages


__all__ = ["SWITCHABLE", "BrakeConfig", "StageConfig", "SteeringConfig"]
