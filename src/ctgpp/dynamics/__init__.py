"""Vehicle dynamics: the unicycle model of DESIGN.md."""

from ctgpp.dynamics.unicycle import (
    ACC_MAX_MPS2,
    ACC_MIN_MPS2,
    KAPPA_MAX_PER_M,
    SPEED_MAX_MPS,
    YAW_RATE_MAX_RPS,
    bound_yaw_rate,
    clip_actions,
    inverse,
    rollout,
    step,
)

__all__ = [
    "ACC_MAX_MPS2",
    "ACC_MIN_MPS2",
    "KAPPA_MAX_PER_M",
    "SPEED_MAX_MPS",
    "YAW_RATE_MAX_RPS",
    "bound_yaw_rate",
    "clip_actions",
    "inverse",
    "rollout",
    "step",
]
