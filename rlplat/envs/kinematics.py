"""Scripted velocity controllers for the drones that do not learn."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rlplat.errors import ConfigError


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


@dataclass(frozen=True)
class SetpointFlight:
    """How a ``setpoints`` drone flies from one setpoint to the next, as :func:`route_path`
    models it. The defaults are no lags at all: full speed until the setpoint is reached.

    Attributes:
        lag: s, the velocity time constant: each leg starts this late (the first one less the
            part of its speed the drone already flies along it).
        gain: 1/s, the command per metre to the setpoint: within ``max_speed / gain`` of it
            the drone slows down in proportion (an exponential approach).
        acceptance: m, the drone moves on within this distance of its setpoint.
    """

    lag: float = 0.0
    gain: float = math.inf
    acceptance: float = 0.0

    def __post_init__(self) -> None:
        if not self.lag >= 0:
            raise ValueError(f"SetpointFlight.lag: must be >= 0, got {self.lag}")
        if not self.gain > 0:
            raise ValueError(f"SetpointFlight.gain: must be > 0, got {self.gain}")
        if math.isfinite(self.gain) and not self.acceptance > 0:
            raise ValueError(
                f"SetpointFlight.acceptance: must be > 0 with a finite gain, got {self.acceptance}"
            )

    def approach(self, distance: Tensor, speed: Tensor) -> Tensor:
        """The time (s) the proportional approach adds to a leg of ``distance`` (m, largest
        per axis) over flying it at full ``speed`` (m/s): from ``speed / gain`` on, the distance
        to go falls as exp(-gain t) until it is ``acceptance``."""
        if not math.isfinite(self.gain):
            return torch.zeros_like(distance)
        near = (speed / self.gain).clamp_min(self.acceptance)  # where the command stops saturating
        slow = torch.log(torch.minimum(distance, near).clamp_min(self.acceptance) / self.acceptance)
        fast = (distance - near).clamp_min(0) / speed
        return (fast + slow / self.gain - distance / speed).clamp_min(0)


def route_path(
    position: Tensor,
    route: Tensor,
    max_speed: Tensor,
    times: Tensor,
    *,
    velocity: Tensor | None = None,
    flight: SetpointFlight = SetpointFlight(),
) -> Tensor:
    """Where a drone that flies ``route`` from ``position`` at full speed per axis will be.

    The model of the ``setpoints`` strategy: from each setpoint to the next, every axis moves at
    the maximum speed until it is there (speed limits are per axis, so a short axis arrives
    first), and the drone moves on when the last axis arrives. ``flight`` adds its lags: each
    leg starts ``flight.lag`` late and ends with the proportional approach's extra time, held
    at the setpoint (with the defaults, none).

    Args:
        position: (*B, 3) m, the drone now.
        route: (*B, S, 3) m, the setpoints it will fly to, in order (a route flown to its end
            repeats its last setpoint: the drone holds there).
        max_speed: (*B,) m/s per axis.
        times: (T,) s from now, increasing; or (*B, T), each drone's own.
        velocity: (*B, 3) m/s, the drone's now (None: at rest); what it already flies along
            its first leg shortens that leg's lag.
        flight: how it flies a leg.

    Returns:
        (*B, T, 3) m, the drone's position at each time.
    """
    points = torch.cat([position.unsqueeze(-2), route], -2)  # (*B, S + 1, 3)
    step = points.diff(dim=-2)  # (*B, S, 3)
    speed = max_speed.clamp_min(1e-6).unsqueeze(-1)  # (*B, 1)
    distance = step.abs().amax(-1)  # (*B, S) m, the longest axis of each leg
    lag = torch.where(distance > 0, flight.lag, 0.0)  # a repeated setpoint is no leg
    if velocity is not None and flight.lag > 0:
        first = step[..., 0, :]
        axis = first.abs().argmax(-1, keepdim=True)
        along = (velocity.gather(-1, axis) * first.gather(-1, axis).sign()).squeeze(-1)
        lag = torch.cat([lag[..., :1] * (1 - along / speed.squeeze(-1)).clamp(0, 1).unsqueeze(-1),
                         lag[..., 1:]], -1)  # fmt: skip
    arrive = (lag + distance / speed + flight.approach(distance, speed)).cumsum(-1)  # (*B, S) s
    t = times.to(position).expand(*arrive.shape[:-1], times.shape[-1]).contiguous()
    leg = torch.searchsorted(arrive.contiguous(), t, right=True)  # (*B, T): the leg flown
    leg = leg.clamp(max=step.shape[-2] - 1)
    start = torch.cat([torch.zeros_like(arrive[..., :1]), arrive[..., :-1]], -1) + lag
    index = leg.unsqueeze(-1).expand(*leg.shape, 3)
    origin, move = points.gather(-2, index), step.gather(-2, index)  # (*B, T, 3)
    flown = (t - start.gather(-1, leg)).clamp_min(0).unsqueeze(-1) * speed.unsqueeze(-1)
    return origin + move.sign() * torch.minimum(move.abs(), flown)


def route_ahead(routes: Tensor, waypoint: Tensor, index: Tensor) -> Tensor:
    """The setpoints the chosen defenders have yet to fly, their last one repeated at the end.

    Args:
        routes: (N, m, S, 3) m, each defender's route. waypoint: (N, m) the index of each one's
            next setpoint. index: (N, K) which defender each of K drones chooses.

    Returns:
        (N, K, S, 3) m: row j is setpoint ``waypoint + j`` of the chosen defender's route.
    """
    route, next_one = gather_drones(routes, index), gather_drones(waypoint, index)  # (N, K, ...)
    last = route.shape[-2] - 1
    ahead = (next_one.unsqueeze(-1) + torch.arange(last + 1, device=route.device)).clamp(max=last)
    return route.gather(-2, ahead.unsqueeze(-1).expand(*ahead.shape, 3))


def route_intercept(
    own: Tensor,
    own_speed: Tensor,
    other: Tensor,
    route: Tensor,
    other_speed: Tensor,
    *,
    times: Tensor,
    lag: float,
    reach: float,
    time_left: Tensor | None = None,
    other_velocity: Tensor | None = None,
    flight: SetpointFlight = SetpointFlight(),
) -> tuple[Tensor, Tensor, Tensor]:
    """The earliest point of a route-flying drone's path that a pursuer can reach in time.

    The target's path is :func:`route_path`; the pursuer reaches a point at time ``t`` if its
    largest per-axis gap to it is at most ``own_speed * (t - lag) + reach`` (full speed per axis
    after a start-up lag). Where no point before ``time_left`` (or the last time) is reachable,
    the answer is the target's position at that last time: the route's end, or as far along as
    the horizon goes.

    Args:
        own: (*B, 3) m, the pursuer. own_speed: (*B,) m/s per axis, its maximum.
        other, route, other_speed: the target, its setpoints ahead and its maximum speed (as
            :func:`route_path`).
        times: (T,) s from now, increasing: the instants tried.
        lag: s, the pursuer's start-up lag. reach: m, how close counts (the capture radius).
        time_left: (*B,) s, the time until the episode ends (None: no limit before the last
            time).
        other_velocity, flight: the target's velocity and how it flies (as
            :func:`route_path`).

    Returns:
        The point (*B, 3) m, the time the target is there (*B,) s and whether the pursuer can
        be there by then (*B,) bool.
    """
    t, n_t = times.to(own), times.shape[0]
    args = (own, own_speed, other, route, other_speed, other_velocity, time_left)
    event = (1, 0, 1, 2, 0, 1, 0)  # each argument's dimensions beyond the batch's
    given = [(x, k) for x, k in zip(args, event, strict=True) if x is not None]
    batch = torch.broadcast_shapes(*(x.shape[: x.dim() - k] for x, k in given))

    def on_batch(x: Tensor | None, k: int) -> Tensor | None:
        """``x`` on the common batch, flattened to one dimension."""
        if x is None:
            return None
        tail = x.shape[x.dim() - k :]
        return x.expand(*batch, *tail).reshape(-1, *tail)

    flat = [on_batch(x, k) for x, k in zip(args, event, strict=True)]
    own, own_speed, other, route, other_speed, other_velocity, time_left = flat

    def search(rows: Tensor | None, lo: int, hi: int) -> tuple[Tensor, Tensor]:
        """For the pursuers ``rows`` (None: all), the first instant of ``t[lo:hi]`` at which
        the target's path is reachable (an index into ``t``) and whether there is one."""
        o, o_speed, x, r, x_speed, x_velocity, left = (
            a if a is None or rows is None else a[rows] for a in flat
        )
        path = route_path(x, r, x_speed, t[lo:hi], velocity=x_velocity, flight=flight)
        gap = (path - o.unsqueeze(-2)).abs().amax(-1)  # (M, hi - lo)
        reachable = gap <= o_speed.unsqueeze(-1) * (t[lo:hi] - lag).clamp_min(0) + reach
        if left is not None:
            reachable &= t[lo:hi] <= left.unsqueeze(-1)
        return lo + reachable.to(torch.uint8).argmax(-1), reachable.any(-1)

    if not blocked_search(own.device):  # every instant for every pursuer
        first, found = search(None, 0, n_t)
    else:  # in blocks: a block is searched only by the pursuers without a point yet
        first = torch.full(own.shape[:1], -1, dtype=torch.int64, device=own.device)
        rows, lo = torch.arange(first.shape[0], device=own.device), 0
        for hi in (*sorted({b for b in SEARCH_BLOCKS if 0 < b < n_t}), n_t):
            index, hit = search(rows if lo else None, lo, hi)
            first[rows[hit]] = index[hit]
            rows, lo = rows[~hit], hi
            if rows.numel() == 0:
                break
        found = first >= 0
    last = torch.full_like(first, n_t - 1)
    if time_left is not None:
        last = ((t <= time_left.unsqueeze(-1)).sum(-1) - 1).clamp_min(0)
    first = torch.where(found, first, last)
    due = t[first]  # the path at that instant alone: as the full search's, value for value
    point = route_path(other, route, other_speed, due.unsqueeze(-1), velocity=other_velocity,
                       flight=flight)  # fmt: skip
    return point.reshape(*batch, 3), due.reshape(batch), found.reshape(batch)


#: The blocks of instants :func:`route_intercept` searches in turn (the index where each
#: next block starts): many meeting points lie a few seconds ahead, so the later instants
#: are tried only by the pursuers that have none yet; the answer is the full search's.
SEARCH_BLOCKS = (8, 32)


def blocked_search(device: torch.device) -> bool:
    """Whether :func:`route_intercept` searches in blocks (and an env's step searches only its
    running envs) on ``device``: eagerly on the CPU. A compiled step keeps static shapes; on
    an accelerator each block waits for the device to say which rows still search, which
    costs more than the instants it saves (benchmarks.md, "Meeting point")."""
    return device.type == "cpu" and not torch.compiler.is_compiling()


#: s, the route-intercept law's prediction: the instants tried (every ROUTE_RESOLUTION s up to
#: the episode's time limit).
ROUTE_RESOLUTION = 0.25
#: s, the defender's velocity time constant the law assumes (the embedded velocity dynamics'
#: horizontal one, ``dynamics=velocity`` ``tau_xy``), for every leg whatever the dynamics: a
#: vertical leg lags less (``tau_z`` 0.08 s).
ROUTE_TAU = 0.9


def setpoint_flight(gain: float, acceptance: float) -> SetpointFlight:
    """How the law expects a ``setpoints`` defender to fly: the env's setpoint ``gain`` (1/s)
    and ``acceptance`` radius (m), and the velocity lag ``ROUTE_TAU``."""
    return SetpointFlight(ROUTE_TAU, gain, acceptance)


def route_meeting(
    own: Tensor,
    own_speed: Tensor,
    defenders: Tensor,
    defender_velocity: Tensor,
    defender_speed: Tensor,
    routes: Tensor,
    waypoint: Tensor,
    index: Tensor,
    *,
    times: Tensor,
    reach: float,
    flight: SetpointFlight,
    lag: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`route_intercept` of K pursuers (own (N, K, 3), own_speed (N, K)) with the chosen
    defenders (``index`` (N, K) into defenders (N, m, 3), defender_velocity (N, m, 3),
    defender_speed (N, m), routes (N, m, S, 3), waypoint (N, m)) flying as ``flight``, with
    the pursuers' start-up ``lag`` (s)."""
    ahead = route_ahead(routes, waypoint, index)
    other, other_speed = gather_drones(defenders, index), gather_drones(defender_speed, index)
    return route_intercept(
        own, own_speed, other, ahead, other_speed, times=times, lag=lag, reach=reach,
        other_velocity=gather_drones(defender_velocity, index), flight=flight,
    )  # fmt: skip


def route_times(time_limit: float, device=None) -> Tensor:
    """The instants (T,) s the route-intercept law tries, up to ``time_limit``."""
    steps = max(1, round(time_limit / ROUTE_RESOLUTION))
    return torch.arange(1, steps + 1, device=device) * ROUTE_RESOLUTION


def law_horizon(where: str, horizon: float | None) -> float | None:
    """The route-intercept law's look-ahead (s) as a float, or None (the episode's time limit);
    a one-line error naming ``where.horizon`` for one that is not a finite number > 0."""
    if horizon is None:
        return None
    number = isinstance(horizon, (int, float)) and not isinstance(horizon, bool)
    if not (number and 0 < horizon < math.inf):
        raise ConfigError(f"{where}.horizon: must be a number > 0 (s) or null, got {horizon!r}")
    return float(horizon)


#: What the route-intercept law flies where no meeting point within its look-ahead is
#: reachable: ``chase``, proportional navigation at the defender; ``head_off``, to the point of
#: the defender's route-flying path at the end of the look-ahead (its route's end, if it gets
#: there sooner), held there as a meeting point is.
UNREACHABLE = ("chase", "head_off")


def law_unreachable(where: str, unreachable: str) -> str:
    """The route-intercept law's ``unreachable`` setting, checked: one of :data:`UNREACHABLE`,
    or a one-line error naming ``where.unreachable``."""
    if unreachable not in UNREACHABLE:
        raise ConfigError(
            f"{where}.unreachable: unknown {unreachable!r}; valid: {', '.join(UNREACHABLE)}"
        )
    return unreachable


def law_times(where: str, **times: float) -> dict[str, float]:
    """The route-intercept law's times (s) as floats; a one-line error naming ``where.key`` for
    one that is negative or not finite."""
    for key, value in times.items():
        if not 0 <= value < math.inf:
            raise ConfigError(f"{where}.{key}: must be finite and >= 0, got {value}")
    return {key: float(value) for key, value in times.items()}


def route_law(
    homing: Tensor,
    aim: Tensor,
    due: Tensor,
    reachable: Tensor,
    max_speed: Tensor,
    gain: float,
    homing_time: float,
    unreachable: str = "chase",
) -> Tensor:
    """The route-intercept law's action in [-1, 1] per axis: fly to the meeting point ``aim``
    (*B, 3) m relative to the pursuer (``gain`` per metre, saturated at ``max_speed`` (*B, 1)),
    and hold there, until the target is ``due`` (*B,) s within ``homing_time``; from then on
    the ``homing`` action (*B, 3), e.g. proportional navigation's. Where no meeting point is
    ``reachable`` (*B,), ``unreachable="chase"`` flies ``homing`` at once; ``"head_off"`` flies
    to ``aim`` all the same (:func:`route_intercept`'s answer then: the target's path at the
    last instant searched)."""
    fly_to = (gain * aim / max_speed).clamp(-1.0, 1.0)
    chase = due <= homing_time
    if unreachable == "chase":
        chase = chase | ~reachable
    return torch.where(chase.unsqueeze(-1), homing, fly_to)


def targets(caught: Tensor) -> Tensor:
    """The defenders an attacker may still chase and measure, (N, m) bool: those not caught, or
    all of them once every one is (the episode ends then). Of attackers, ``targets(down)``: those
    still flying."""
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
