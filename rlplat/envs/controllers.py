"""Scripted velocity controllers for the drones that do not learn."""

from __future__ import annotations

import torch
from torch import Tensor


def follow_route(
    position: Tensor, setpoints: Tensor, waypoint: Tensor, max_speed: Tensor, gain: float
) -> Tensor:
    """Deterministic setpoint follower without avoidance.

    Args:
        position: (N, 3) m, the drone's position.
        setpoints: (N, S, 3) m, each env's route.
        waypoint: (N,) int64, index of the setpoint being flown to; S means the route is done.
        max_speed: (N,) m/s per axis.
        gain: 1/s, commanded velocity per metre of error before saturation.

    Returns:
        (N, 3) velocity command in m/s; zero (hold) once the route is done.
    """
    done = waypoint >= setpoints.shape[1]
    idx = waypoint.clamp(max=setpoints.shape[1] - 1)
    target = setpoints[torch.arange(len(idx), device=idx.device), idx]
    cmd = _saturate(gain * (target - position), max_speed)
    return torch.where(done.unsqueeze(-1), torch.zeros_like(cmd), cmd)


def pure_pursuit(position: Tensor, target: Tensor, max_speed: Tensor, gain: float) -> Tensor:
    """Fly straight at the target's current position: (N, 3) command in m/s."""
    return _saturate(gain * (target - position), max_speed)


def _saturate(command: Tensor, max_speed: Tensor) -> Tensor:
    bound = max_speed.unsqueeze(-1)
    return torch.maximum(torch.minimum(command, bound), -bound)
