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
    """Fly straight at the target's current position: (*B, 3) command in m/s."""
    return _saturate(gain * (target - position), max_speed)


def aim_velocity(v_other: Tensor, a_other: Tensor | None, accel_lead: float | Tensor) -> Tensor:
    """The target velocity augmented proportional navigation aims with, ``v + accel_lead * a``:
    a target whose velocity follows its command with time constant tau is turning to
    ``v + tau * a``. ``a_other`` None (not known) or ``accel_lead`` 0 is the textbook law's
    ``v_other``. ``accel_lead`` may be a tensor (*B, 1), one per row."""
    if a_other is None or (isinstance(accel_lead, float) and accel_lead == 0.0):
        return v_other
    return v_other + accel_lead * a_other


def intercept_action(
    rel: Tensor,
    v_other: Tensor,
    max_speed: Tensor,
    gain: float | Tensor,
    lead: float | Tensor = 0.5,
    max_lead_time: float | Tensor = 4.0,
) -> Tensor:
    """Proportional navigation with lead, as an action in [-1, 1] per axis (command / max speed).

    Aims at the predicted intercept point ``rel + lead * v_other * t_go`` and commands
    ``gain * aim`` saturated at the maximum speed per axis. ``t_go`` is the time the pursuer needs
    to close the largest per-axis gap at full speed while the target keeps its velocity (speed
    limits are per axis, so each axis closes on its own), capped at ``max_lead_time``; on an axis
    where the target is as fast as the pursuer the cap applies. ``lead = 0`` is pure pursuit.

    Args:
        rel: (*B, 3) m, target minus pursuer position.
        v_other: (*B, 3) m/s, the target's velocity.
        max_speed: (*B, 1) m/s per axis, the pursuer's.
        gain: 1/s, command per metre to the aim point.
        lead: fraction of the predicted target motion to lead by.
        max_lead_time: s, longest prediction.

    The three parameters may also be tensors (*B, 1), one law per row.
    """
    closing = max_speed - torch.sign(rel) * v_other  # per-axis closing speed at full throttle
    t_axis = torch.where(closing > 1e-6, rel.abs() / closing.clamp_min(1e-6), max_lead_time)
    t_go = t_axis.amax(-1, keepdim=True).clamp(max=max_lead_time)
    aim = rel + lead * v_other * t_go
    return (gain * aim / max_speed).clamp(-1.0, 1.0)


def targets(caught: Tensor) -> Tensor:
    """The defenders an attacker may still chase and measure, (N, m) bool: those not caught, or
    all of them once every one is (the episode ends then)."""
    return ~caught | caught.all(-1, keepdim=True)


def nearest(own: Tensor, others: Tensor, allowed: Tensor | None = None) -> Tensor:
    """Index of the nearest other drone for each own drone.

    Args:
        own: (N, K, 3) m, the positions of K drones.
        others: (N, M, 3) m, the positions of M other drones.
        allowed: (N, M) bool, the other drones that may be picked (None: all); every row needs
            one.

    Returns:
        (N, K) int64 indices into the M other drones.
    """
    if others.shape[1] == 1:  # nothing to choose from
        return torch.zeros(own.shape[:2], dtype=torch.int64, device=own.device)
    distance = (others.unsqueeze(1) - own.unsqueeze(2)).norm(dim=-1)  # (N, K, M)
    if allowed is not None:
        distance = distance.masked_fill(~allowed.unsqueeze(1), float("inf"))
    return distance.argmin(-1)


def gather_drones(x: Tensor, index: Tensor) -> Tensor:
    """``x[n, index[n, k]]`` for per-drone values x (N, M, ...) and index (N, K): (N, K, ...)."""
    if x.shape[1] == 1:  # every index is 0
        return x.expand(*index.shape, *x.shape[2:])
    flat = index.reshape(*index.shape, *([1] * (x.ndim - 2))).expand(*index.shape, *x.shape[2:])
    return x.gather(1, flat)


def _saturate(command: Tensor, max_speed: Tensor) -> Tensor:
    bound = max_speed.unsqueeze(-1)
    return torch.maximum(torch.minimum(command, bound), -bound)
