"""Scripted velocity controllers for the drones that do not learn."""

from __future__ import annotations

import torch
from torch import Tensor


def follow_route(
    position: Tensor, target: Tensor, route_done: Tensor, max_speed: Tensor, gain: float
) -> Tensor:
    """Deterministic setpoint follower without avoidance.

    Args:
        position: (N, 3) m, the drone's position.
        target: (N, 3) m, the setpoint being flown to.
        route_done: (N,) bool, the whole route has been flown.
        max_speed: (N,) m/s per axis.
        gain: 1/s, commanded velocity per metre of error before saturation.

    Returns:
        (N, 3) velocity command in m/s; zero (hold) once the route is done.
    """
    cmd = _saturate(gain * (target - position), max_speed)
    return cmd.masked_fill(route_done.unsqueeze(-1), 0.0)


def pure_pursuit(position: Tensor, target: Tensor, max_speed: Tensor, gain: float) -> Tensor:
    """Fly straight at the target's current position: (N, 3) command in m/s."""
    return _saturate(gain * (target - position), max_speed)


def _saturate(command: Tensor, max_speed: Tensor) -> Tensor:
    bound = max_speed.unsqueeze(-1)
    return torch.maximum(torch.minimum(command, bound), -bound)
