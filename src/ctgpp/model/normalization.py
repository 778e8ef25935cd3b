"""Per-channel normalization of actions and agent-frame states with the config's fixed constants."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ctgpp.model.config import ModelConfig


class Normalizer(nn.Module):
    """Maps actions (..., 2) and states (..., 4) to zero mean and unit variance and back.

    The constants are non-persistent buffers: they move with the model between devices but live in
    the checkpoint's config, not in its weights.
    """

    action_mean: Tensor
    action_std: Tensor
    state_mean: Tensor
    state_std: Tensor

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        for name in ("action_mean", "action_std", "state_mean", "state_std"):
            value = torch.tensor(getattr(config, name), dtype=torch.float32)
            self.register_buffer(name, value, persistent=False)

    def normalize_actions(self, actions: Tensor) -> Tensor:
        """(…, 2) acceleration m/s², yaw rate rad/s -> normalized (…, 2)."""
        return (actions - self.action_mean) / self.action_std

    def denormalize_actions(self, actions: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_actions`."""
        return actions * self.action_std + self.action_mean

    def normalize_states(self, states: Tensor) -> Tensor:
        """(…, 4) x m, y m, speed m/s, yaw rad in an agent frame -> normalized (…, 4)."""
        return (states - self.state_mean) / self.state_std

    def denormalize_states(self, states: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_states`."""
        return states * self.state_std + self.state_mean

    def state_error(self, pred: Tensor, target: Tensor) -> Tensor:
        """Normalized difference of states (…, 4), the yaw difference wrapped to [−π, π)."""
        diff = pred - target
        yaw = torch.remainder(diff[..., 3] + torch.pi, 2 * torch.pi) - torch.pi
        diff = torch.cat([diff[..., :3], yaw[..., None]], dim=-1)
        return diff / self.state_std
