"""Time windows of a sentence ("within 5 s", "after 3 s", "for the first 4 s") and the part of a rollout
a behaviour is judged on inside one.

Times count from the episode start (t = 0). A behaviour judged in a window is judged by its own check on
the rollout cut to the window (:func:`windowed`): its first judged step is the window's start, its start
state the step before (the lane it is on then, its speed then), its end the window's end. Times in the
verdict's words stay episode times. A *deadline* of a behaviour that holds over time ("stop within 5 s",
"slow down to under 2 m/s within 3 s", "stay within 20 m of vehicle 1 within 4 s") is the window from
the deadline to the end with ``hold``: the behaviour must hold from the window's first step, with no
allowance for getting there. A deadline of an event ("change to the left lane within 5 s", "collide
within 4 s") is the window from t = 0 to the deadline. A sequence's earlier stage ("slows down to 5
m/s and then stops") is judged with ``once``: a behaviour that reaches a state and stays there holds
it for its hold time at some step of the window, the later stage taking over after that.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ctgpp.interfaces import Rollout
from ctgpp.scene.types import AgentTracks


@dataclass(frozen=True)
class TimeWindow:
    """[start_s, end_s] of the episode (end_s None: to the end); ``hold``: the behaviour must hold
    from the window's first step (a deadline), not only from when it first does; ``once``: a state
    reached and held for the hold time at some step suffices, not to the window's end (a sequence's
    earlier stage)."""

    start_s: float = 0.0
    end_s: float | None = None
    hold: bool = False
    once: bool = False

    def __post_init__(self) -> None:
        if self.start_s < 0 or (self.end_s is not None and self.end_s < self.start_s):
            raise ValueError(f"a time window needs 0 <= start_s <= end_s, got {self.start_s}, {self.end_s}")

    def words(self) -> str:
        """The window in words."""
        end = "the end" if self.end_s is None else f"t = {self.end_s:g} s"
        held = ", holding from its start" if self.hold else ""
        once = ", held once (a later stage takes over)" if self.once else ""
        return f"t = {self.start_s:g} s to {end}{held}{once}"

    def as_dict(self) -> dict[str, float | bool | None]:
        return {"start_s": self.start_s, "end_s": self.end_s, "hold": self.hold, "once": self.once}


@dataclass(frozen=True, eq=False)
class WindowedRollout(Rollout):
    """A rollout cut to a time window: ``shift_steps`` future steps of the episode lie before its
    t = 0; ``hold`` and ``once`` as in :class:`TimeWindow`."""

    shift_steps: int = 0
    hold: bool = False
    once: bool = False


def _cut(tracks: AgentTracks, stop: int) -> AgentTracks:
    return replace(tracks, xy=tracks.xy[:, :stop], yaw=tracks.yaw[:, :stop], speed=tracks.speed[:, :stop],
                   valid=tracks.valid[:, :stop])


def windowed(rollout: Rollout, window: TimeWindow | None) -> Rollout:
    """``rollout`` cut to ``window`` (itself when None): t = 0 moves to the window's start, the
    simulated future ends at its end (a window past the end leaves no future step)."""
    if window is None:
        return rollout
    dt, last = rollout.dt_s, rollout.sim.num_steps - 1
    shift = min(max(round(window.start_s / dt) - 1, 0), last - rollout.current)  # first judged: start_s
    current = rollout.current + shift
    stop = rollout.sim.num_steps if window.end_s is None else min(
        rollout.current + round(window.end_s / dt) + 1, rollout.sim.num_steps)
    sim = _cut(rollout.sim, max(stop, current + 1))
    return WindowedRollout(rollout.scene, rollout.first_step, current, sim, rollout.controlled,
                           rollout.number, rollout.policy, shift_steps=shift, hold=window.hold,
                           once=window.once)
