"""The drone interface as components: observation, action and reward, each chosen by config.

Every component is small and batched: shapes below use ``*B`` for the batch (N envs, or N envs
by the drones of a team), M for the opponents a drone sees and K for its team-mates.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from rlplat.envs.kinematics import (
    aim_velocity,
    intercept_action,
    law_horizon,
    law_times,
    law_unreachable,
    route_law,
    targets,
)
from rlplat.errors import ConfigError


@dataclass(frozen=True)
class DroneView:
    """The world seen from one drone: its own state, its opponents', its team-mates' and the
    defender's route.

    Attributes:
        own_position, own_velocity: (*B, 3) float32, m and m/s, world frame ENU.
        other_position, other_velocity: (*B, M, 3) float32, the opponents (attackers of a
            defender, defenders of an attacker), in drone order.
        setpoint: (*B, 3) float32 m, the route setpoint the (first) defender flies to (its last
            one once the route is flown).
        next_setpoint: (*B, 3) float32 m, the (first) defender's setpoint after that one (its
            last one at the end of its route); None where no observation reads it.
        mate_position, mate_velocity: (*B, K, 3) float32, the drone's team-mates in drone
            order; None (or K = 0) for a drone that flies alone.
        other_in_play, mate_in_play: (*B, M) and (*B, K) bool, which opponents and team-mates
            are still in play (False: a caught defender); None where no observation reads them.
        own_max_speed: (*B,) float32 m/s, the drone's maximum speed per axis.
        time_left: (*B,) float32 s, the time until the episode's time limit.
        other_acceleration, mate_acceleration: (*B, M, 3) and (*B, K, 3) float32 m/s^2, each
            opponent's and team-mate's mean acceleration over the last control period; None
            where no observation reads them.
        intercept, intercept_time: (*B, 3) float32 m and (*B,) float32 s, an attacker's meeting
            point on its nearest defender's route and when the defender is there
            (:func:`rlplat.envs.kinematics.route_intercept`; where none is reachable, the
            defender's position after the episode's time limit from now, and that time); None
            where no observation reads them.
        route_residual, route_deviation: (*B, 3) m/s^2 and (*B,) m/s^2, how an attacker's
            nearest defender in play departs from its route: its acceleration over the last
            control period less the acceleration a ``setpoints`` defender in its state would
            have had, and that residual's magnitude averaged over the last seconds
            (:class:`PursuitConformObservation`); None where no observation reads them.
    """

    own_position: Tensor
    own_velocity: Tensor
    other_position: Tensor
    other_velocity: Tensor
    setpoint: Tensor | None = None
    next_setpoint: Tensor | None = None
    mate_position: Tensor | None = None
    mate_velocity: Tensor | None = None
    other_in_play: Tensor | None = None
    mate_in_play: Tensor | None = None
    own_max_speed: Tensor | None = None
    time_left: Tensor | None = None
    other_acceleration: Tensor | None = None
    mate_acceleration: Tensor | None = None
    intercept: Tensor | None = None
    intercept_time: Tensor | None = None
    route_residual: Tensor | None = None
    route_deviation: Tensor | None = None


def inside_ellipsoid(rel: Tensor, semi_axes: Tensor) -> Tensor:
    """Whether offsets rel (*B, 3) lie in the axis-aligned ellipsoid (3,) semi-axes: (*B,) bool.

    The boundary counts as inside.
    """
    return ((rel / semi_axes) ** 2).sum(-1) <= 1.0


# Observations ----------------------------------------------------------------------------

#: Own features an observation has only in a team (they compare the drone with its team-mates).
TEAM_ONLY = frozenset({"sight_margin"})


class _Observation:
    """Base of the observations: ``dim`` features, each with a typical magnitude in ``scale``.

    An observation is the drone's own features followed by a block per other drone it sees:
    first each opponent, then each team-mate, in drone order (``other_layout`` per block, then,
    with ``in_play``, 1 if that drone is still in play and 0 if it was caught or is down). With
    one opponent and no team-mate this is the 1-vs-1 observation.

    The env emits raw values (m, m/s); the agent's networks divide by ``scale`` first.

    Args:
        position_scale: m, typical magnitude of a position feature.
        velocity_scale: m/s, typical magnitude of a velocity feature.
        time_scale: s, typical magnitude of a time feature.
        accel_scale: m/s^2, typical magnitude of an acceleration feature.
        world_scale: m, typical magnitude of a position in the world frame (a "w" feature).
        opponents: M, opponents the drone sees (set by the env factory from the scenarios).
        mates: K, team-mates the drone sees (set by the env factory from the scenarios).
        in_play: add each other drone's in-play flag (set by the env factory where defenders
            can leave play before the episode ends: more than one of them; a downed attacker's
            flag is 0 too).
    """

    # "p"/"v"/"w"/"a" per 3-vector; "s" speed, "t" time, "e" accel, "d" distance (scalars)
    own_layout: tuple[str, ...] = ()
    other_layout: tuple[str, ...] = ()  # "p", "v" or "a" per 3-vector of each other drone's block
    own_names: tuple[str, ...] = ()  # what each own entry is (same order as own_layout)
    other_names: tuple[str, ...] = ()  # each other drone's, "{d}" standing for that drone
    route_ahead: bool = False  # reads the view's next_setpoint
    reads_intercept: bool = False  # reads the view's intercept and intercept_time
    reads_conformity: bool = False  # reads the view's route_residual and route_deviation

    def __init__(
        self,
        *,
        position_scale: float = 50.0,
        velocity_scale: float = 5.0,
        time_scale: float = 60.0,
        accel_scale: float = 5.0,
        world_scale: float = 50.0,
        opponents: int = 1,
        mates: int = 0,
        in_play: bool = False,
    ) -> None:
        scales = {"position_scale": position_scale, "velocity_scale": velocity_scale,
                  "time_scale": time_scale, "accel_scale": accel_scale,
                  "world_scale": world_scale}  # fmt: skip
        for name, v in scales.items():
            if not v > 0:
                raise ConfigError(f"observation.{name}: must be > 0, got {v}")
        if opponents < 1 or mates < 0:
            raise ConfigError(
                f"observation: opponents must be >= 1 and mates >= 0, got {opponents}, {mates}"
            )
        for names, layout in (("own_names", "own_layout"), ("other_names", "other_layout")):
            if len(getattr(self, names)) != len(getattr(self, layout)):
                raise TypeError(  # a class's definition, not a config value
                    f"{type(self).__name__}.{names}: {len(getattr(self, names))} names for the "
                    f"{len(getattr(self, layout))} entries of {layout}; name every one "
                    "(export's feature table and a team seat's lone features read them)"
                )
        self.opponents, self.mates, self.in_play = int(opponents), int(mates), bool(in_play)
        block = self.other_layout + (("f",) if self.in_play else ())
        layout = self.own_layout + block * (self.opponents + self.mates)
        per = {
            "p": [float(position_scale)] * 3,
            "v": [float(velocity_scale)] * 3,
            "a": [float(accel_scale)] * 3,
            "w": [float(world_scale)] * 3,
            "s": [float(velocity_scale)],
            "t": [float(time_scale)],
            "e": [float(accel_scale)],
            "d": [float(position_scale)],
            "f": [1.0],
        }
        self.scale = [x for kind in layout for x in per[kind]]
        self.dim = len(self.scale)

    def features(self) -> list[dict[str, str | float]]:
        """What each of the ``dim`` features is: ``name`` (e.g. ``(p_opponent0 - p_own).x``),
        ``unit`` (``m``, ``m/s``, ``m/s^2``, ``s`` or ``1`` for an in-play flag) and ``scale``,
        in order."""
        kinds = {"p": ("m", 3), "w": ("m", 3), "v": ("m/s", 3), "a": ("m/s^2", 3),
                 "s": ("m/s", 1), "t": ("s", 1), "e": ("m/s^2", 1), "d": ("m", 1),
                 "f": ("1", 1)}  # fmt: skip
        named = list(zip(self.own_names, self.own_layout, strict=True))
        others = [f"opponent{i}" for i in range(self.opponents)]
        others += [f"mate{j}" for j in range(self.mates)]
        for d in others:
            block = zip(self.other_names, self.other_layout, strict=True)
            named += [(name.format(d=d), kind) for name, kind in block]
            if self.in_play:
                named.append((f"in_play_{d}", "f"))
        out = []
        for name, kind in named:
            unit, size = kinds[kind]
            if size == 1:
                out.append({"name": name, "unit": unit})
            else:
                vector = f"({name})" if " " in name else name
                out += [{"name": vector + axis, "unit": unit} for axis in (".x", ".y", ".z")]
        return [{**f, "scale": s} for f, s in zip(out, self.scale, strict=True)]

    def lone_features(self, in_play: bool | None = None) -> list[int]:
        """Indices of the features the same observation has for a drone without team-mates, in
        its order: the own features but those seen only in a team (``TEAM_ONLY``), then every
        opponent's block, with its in-play flag where the lone observation has one
        (``in_play``; None: where this one has). A policy trained alone flies a seat of a
        team on these."""
        in_play = self.in_play if in_play is None else in_play
        if in_play and not self.in_play:
            raise ValueError("lone_features: this observation has no in-play flags to give")
        sizes = {"p": 3, "v": 3, "a": 3, "w": 3, "s": 1, "t": 1, "e": 1, "d": 1, "f": 1}
        kept, at = [], 0
        for name, kind in zip(self.own_names, self.own_layout, strict=True):
            if name not in TEAM_ONLY:
                kept += range(at, at + sizes[kind])
            at += sizes[kind]
        state = sum(sizes[kind] for kind in self.other_layout)
        block = state + (1 if self.in_play else 0)
        for _ in range(self.opponents):
            kept += range(at, at + (block if in_play else state))
            at += block
        return kept

    def __call__(self, view: DroneView) -> Tensor:
        """The observation (*B, dim) float32."""
        blocks = self._block(view, view.other_position, view.other_velocity,
                             view.other_acceleration, view.other_in_play)  # fmt: skip
        if self.mates:
            mates = self._block(view, view.mate_position, view.mate_velocity,
                                view.mate_acceleration, view.mate_in_play)  # fmt: skip
            blocks = torch.cat([blocks, mates], -2)
        return torch.cat([*self._own(view), blocks.flatten(-2)], -1)  # (*B, dim)

    def _block(self, view: DroneView, position: Tensor, velocity: Tensor,
               acceleration: Tensor | None, in_play: Tensor | None) -> Tensor:  # fmt: skip
        block = self._other(view, position, velocity, acceleration)
        if not self.in_play:
            return block
        return torch.cat([block, in_play.unsqueeze(-1).to(block.dtype)], -1)

    def _own(self, view: DroneView) -> list[Tensor]:
        """The drone's own features, each (*B, 3) (a speed or a time (*B, 1))."""
        return []

    def _other(
        self, view: DroneView, position: Tensor, velocity: Tensor, acceleration: Tensor | None
    ) -> Tensor:
        """The block of each other drone at ``position``/``velocity``/``acceleration`` (*B, X, 3;
        the acceleration None where the view has none): (*B, X, f)."""
        raise NotImplementedError


class AbsoluteObservation(_Observation):
    """Absolute positions and velocities: [p_own, v_own, (p_other, v_other) per other drone],
    (*B, 12) with one opponent."""

    own_layout, other_layout = ("p", "v"), ("p", "v")
    own_names, other_names = ("p_own", "v_own"), ("p_{d}", "v_{d}")

    def _own(self, view: DroneView) -> list[Tensor]:
        return [view.own_position, view.own_velocity]

    def _other(
        self, view: DroneView, position: Tensor, velocity: Tensor, acceleration: Tensor | None
    ) -> Tensor:
        return torch.cat([position, velocity], -1)


class RelativePositionObservation(_Observation):
    """Relative position only: [p_other - p_own per other drone], (*B, 3) with one opponent."""

    other_layout = ("p",)
    other_names = ("p_{d} - p_own",)

    def _other(
        self, view: DroneView, position: Tensor, velocity: Tensor, acceleration: Tensor | None
    ) -> Tensor:
        return position - view.own_position.unsqueeze(-2)


class RelativeStateObservation(_Observation):
    """Own velocity and each other drone's relative state (paper eq. 1 for the attacker).

    s = [v_own, (p_other - p_own, v_other - v_own) per other drone], (*B, 9) with one opponent.
    """

    own_layout, other_layout = ("v",), ("p", "v")
    own_names, other_names = ("v_own",), ("p_{d} - p_own", "v_{d} - v_own")

    def _own(self, view: DroneView) -> list[Tensor]:
        return [view.own_velocity]

    def _other(
        self, view: DroneView, position: Tensor, velocity: Tensor, acceleration: Tensor | None
    ) -> Tensor:
        own_p, own_v = view.own_position.unsqueeze(-2), view.own_velocity.unsqueeze(-2)
        return torch.cat([position - own_p, velocity - own_v], -1)


class PursuitStateObservation(RelativeStateObservation):
    """Eq. 1 and what the drone can do: its own velocity, its own maximum speed per axis and each
    other drone's relative state.

    s = [v_own, max_speed_own, (p_other - p_own, v_other - v_own) per other drone], (*B, 10)
    with one opponent. Actions are fractions of the maximum speed, so a policy that knows it
    knows what its action commands (and how soon it can be anywhere).
    """

    own_layout = ("v", "s")
    own_names = ("v_own", "max_speed_own")

    def _own(self, view: DroneView) -> list[Tensor]:
        if view.own_max_speed is None:
            raise ValueError("observation pursuit_state: the view has no own_max_speed")
        return [view.own_velocity, view.own_max_speed.unsqueeze(-1)]


class PursuitClockObservation(PursuitStateObservation):
    """``pursuit_state`` and the time left until the episode's time limit.

    s = [v_own, max_speed_own, time_left, (p_other - p_own, v_other - v_own) per other drone],
    (*B, 11) with one opponent. An episode cut at its time limit ends a chase whatever the
    drones do; without the clock that cut is noise to the critic, and the policy cannot tell a
    chase with a minute left from one with seconds left.
    """

    own_layout = ("v", "s", "t")
    own_names = ("v_own", "max_speed_own", "time_left")

    def _own(self, view: DroneView) -> list[Tensor]:
        if view.time_left is None:
            raise ValueError("observation pursuit_clock: the view has no time_left")
        return [*super()._own(view), view.time_left.unsqueeze(-1)]


class PursuitAccelObservation(PursuitStateObservation):
    """``pursuit_state`` and each other drone's acceleration.

    s = [v_own, max_speed_own, (p_other - p_own, v_other - v_own, a_other) per other drone],
    (*B, 13) with one opponent; a_other is the drone's mean acceleration over the last control
    period (zero at the first step). It holds nothing the velocities of two steps do not, but a
    policy sees one step: a drone's velocity follows its command with a lag, and its
    acceleration says where that velocity is going, e.g. into an evading defender's turn.
    """

    other_layout = ("p", "v", "a")
    other_names = ("p_{d} - p_own", "v_{d} - v_own", "a_{d}")

    def _other(
        self, view: DroneView, position: Tensor, velocity: Tensor, acceleration: Tensor | None
    ) -> Tensor:
        if acceleration is None:
            raise ValueError("observation pursuit_accel: the view has no acceleration")
        return torch.cat([super()._other(view, position, velocity, acceleration), acceleration], -1)


class PursuitWorldObservation(PursuitStateObservation):
    """``pursuit_state`` and where the drone is in the world.

    s = [v_own, max_speed_own, p_own, (p_other - p_own, v_other - v_own) per other drone],
    (*B, 13) with one opponent; p_own is the drone's position in the world frame (ENU, m), so
    p_own + (p_other - p_own) is where the other drone is. Defenders fly the scenario family's
    routes, which are the same in every episode: a policy that knows where a defender is on
    the map can learn where its route takes it next, which a law of relative states cannot.
    """

    own_layout = ("v", "s", "w")
    own_names = ("v_own", "max_speed_own", "p_own")

    def _own(self, view: DroneView) -> list[Tensor]:
        return [*super()._own(view), view.own_position]


class PursuitRouteObservation(PursuitStateObservation):
    """``pursuit_state`` and the (first) defender's route ahead: its next two setpoints.

    s = [v_own, max_speed_own, setpoint - p_own, next_setpoint - p_own, (p_other - p_own,
    v_other - v_own) per other drone], (*B, 16) with one opponent. A defender on a known route
    (a patrol) will be near its setpoints: a faster defender is met by flying to where its
    route goes, which no law of its present position and velocity can do. This is more than
    the law sees: the route is known in advance, as the capture ceiling assumes.
    """

    own_layout = ("v", "s", "p", "p")
    own_names = ("v_own", "max_speed_own", "setpoint - p_own", "next_setpoint - p_own")
    route_ahead = True  # the env fills the view's next_setpoint

    def _own(self, view: DroneView) -> list[Tensor]:
        if view.setpoint is None or view.next_setpoint is None:
            raise ValueError("observation pursuit_route: the view has no setpoints")
        ahead = [view.setpoint - view.own_position, view.next_setpoint - view.own_position]
        return [*super()._own(view), *ahead]


class PursuitInterceptObservation(PursuitRouteObservation):
    """``pursuit_route`` and where the route lets the attacker meet the defender: the meeting
    point of the route-intercept law and the time until the defender is there.

    s = [v_own, max_speed_own, setpoint - p_own, next_setpoint - p_own, intercept - p_own,
    t_intercept, p_other - p_own, v_other - v_own], (*B, 20) with one opponent. The meeting
    point is the earliest point of the defender's path, as a ``setpoints`` defender flies the
    rest of its route, that the attacker can reach at full speed per axis
    (:func:`rlplat.envs.kinematics.route_intercept`): what ``action=route_law`` flies to, so
    the policy sees what its law does. Attackers only.
    """

    own_layout = ("v", "s", "p", "p", "p", "t")
    own_names = ("v_own", "max_speed_own", "setpoint - p_own", "next_setpoint - p_own",
                 "intercept - p_own", "t_intercept")  # fmt: skip
    reads_intercept = True  # the env fills the view's intercept and intercept_time

    def _own(self, view: DroneView) -> list[Tensor]:
        if view.intercept is None or view.intercept_time is None:
            raise ValueError("observation pursuit_intercept: the view has no meeting point")
        meet = [view.intercept - view.own_position, view.intercept_time.unsqueeze(-1)]
        return [*super()._own(view), *meet]


class PursuitConformObservation(PursuitInterceptObservation):
    """``pursuit_intercept`` and whether the defender flies its route: how its acceleration
    departs from a ``setpoints`` defender's.

    s = [v_own, max_speed_own, setpoint - p_own, next_setpoint - p_own, intercept - p_own,
    t_intercept, route_residual, route_deviation, p_other - p_own, v_other - v_own], (*B, 24)
    with one opponent. The residual is the nearest defender's measured acceleration less the
    one its route's setpoint follower would have given it (a first-order velocity lag of
    ``route_lag`` seconds per axis x, y, z), near zero while it flies its route; the deviation
    is the residual's size averaged over the last ``conformity_time`` seconds. A defender that
    leaves its route to evade shows at once: the meeting point on its route is then no longer
    where it will be, and a policy that sees it can tell the route flyers, which the law
    meets, from the evaders. Attackers only.

    With ``team_sight``, an attacker with team-mates also sees ``sight_margin``
    (:func:`sight_margin`, one more feature after the deviation): whether it or a team-mate is
    nearer the defender, i.e. which of them a network defender sees and evades. Without
    team-mates it adds nothing.
    """

    own_layout = ("v", "s", "p", "p", "p", "t", "a", "e")
    own_names = ("v_own", "max_speed_own", "setpoint - p_own", "next_setpoint - p_own",
                 "intercept - p_own", "t_intercept", "route_residual",
                 "route_deviation")  # fmt: skip
    reads_conformity = True  # the env fills the view's route_residual and route_deviation

    def __init__(
        self,
        *,
        conformity_time: float = 1.0,
        route_lag: Sequence[float] = (0.9, 0.9, 0.35),
        team_sight: bool = False,
        **scales: Any,
    ) -> None:
        if not isinstance(team_sight, bool):
            raise ConfigError(f"observation.team_sight: must be true or false, got {team_sight!r}")
        self.team_sight = team_sight and scales.get("mates", 0) > 0
        if self.team_sight:  # one more own feature, in a team only
            self.own_layout = (*type(self).own_layout, "d")
            self.own_names = (*type(self).own_names, "sight_margin")
        super().__init__(**scales)  # the scales, opponents, mates and in_play of the base
        if not conformity_time > 0:
            raise ConfigError(f"observation.conformity_time: must be > 0, got {conformity_time}")
        self.conformity_time = float(conformity_time)
        try:
            lag = tuple(float(x) for x in route_lag)
        except (TypeError, ValueError):
            lag = ()
        if len(lag) != 3 or not all(x > 0 for x in lag):  # NaN fails too
            raise ConfigError(f"observation.route_lag: must be 3 numbers > 0, got {route_lag}")
        self.route_lag = lag

    def _own(self, view: DroneView) -> list[Tensor]:
        if view.route_residual is None or view.route_deviation is None:
            raise ValueError("observation pursuit_conform: the view has no route residual")
        conform = [view.route_residual, view.route_deviation.unsqueeze(-1)]
        if self.team_sight:
            conform.append(sight_margin(view))
        return [*super()._own(view), *conform]


def sight_margin(view: DroneView) -> Tensor:
    """How much nearer the drone is to its nearest opponent in play than its nearest team-mate
    is to that opponent, (*B, 1) m: positive where the drone is the opponent's nearest, the one
    a network defender sees and evades (it sees only its nearest attacker)."""
    distance = (view.other_position - view.own_position.unsqueeze(-2)).norm(dim=-1)  # (*B, M)
    chosen = distance
    if view.other_in_play is not None:  # the env's rule: once none is in play, all of them
        chosen = distance.masked_fill(~targets(~view.other_in_play), float("inf"))
    near = chosen.argmin(-1, keepdim=True)  # (*B, 1)
    target = view.other_position.gather(-2, near.unsqueeze(-1).expand(*near.shape, 3))
    mates = (view.mate_position - target).norm(dim=-1)  # (*B, K)
    if view.mate_in_play is not None:  # a team-mate out of play counts as far away
        mates = mates.masked_fill(~view.mate_in_play, float("inf"))
    return (mates.amin(-1, keepdim=True) - distance.gather(-1, near)).clamp(max=100.0)


class RouteStateObservation(RelativeStateObservation):
    """What a route-flying defender needs: its own velocity, the way to its next setpoint and
    each other drone's relative state.

    s = [v_own, setpoint - p_own, (p_other - p_own, v_other - v_own) per other drone], (*B, 12)
    with one opponent.
    """

    own_layout = ("v", "p")
    own_names = ("v_own", "setpoint - p_own")

    def _own(self, view: DroneView) -> list[Tensor]:
        return [view.own_velocity, view.setpoint - view.own_position]


OBSERVATIONS = {
    "absolute": AbsoluteObservation,
    "relative_position": RelativePositionObservation,
    "relative_state": RelativeStateObservation,
    "pursuit_state": PursuitStateObservation,
    "pursuit_clock": PursuitClockObservation,
    "pursuit_accel": PursuitAccelObservation,
    "pursuit_world": PursuitWorldObservation,
    "pursuit_route": PursuitRouteObservation,
    "pursuit_intercept": PursuitInterceptObservation,
    "pursuit_conform": PursuitConformObservation,
    "route_state": RouteStateObservation,
}


# Actions ---------------------------------------------------------------------------------


class VelocityAction:
    """Paper eq. 2: a velocity command, the policy output in [-1, 1]^3 times the max speed."""

    dim = 3
    guided = False  # the env passes no guidance action

    @classmethod
    def flies_any_command(cls, cfg: Mapping[str, Any]) -> bool:
        """Whether the action configured by ``cfg`` (a ``conf/action/`` node) flies every
        command, so a scripted policy can be flown through it."""
        return True

    def __call__(self, action: Tensor, max_speed: Tensor, guidance: Tensor | None = None) -> Tensor:
        """Map action (*B, 3) in [-1, 1] and max_speed (*B,) m/s to a command (*B, 3) m/s."""
        return action.clamp(-1.0, 1.0) * max_speed.unsqueeze(-1)


class GuidedVelocityAction(VelocityAction):
    """A learned correction to proportional navigation (a residual policy on guidance).

    The command is ``clamp(g + scale * action, -1, 1) * max_speed`` per axis, with ``g`` the
    action of proportional navigation towards the attacker's nearest defender in play
    (:func:`rlplat.envs.kinematics.intercept_action`, computed by the env from the state the
    policy observed). A zero action flies proportional navigation exactly, so learning starts
    where the textbook law is; with ``scale >= 2`` every command in the box is reachable from any
    guidance, and :meth:`inverse` recovers the action that flies a given command. Attackers only.

    Args:
        gain: 1/s, the guidance's command per metre to its aim point (``env.pursuit_gain``).
        lead: fraction of the target's predicted motion the guidance leads by.
        max_lead_time: s, the guidance's longest prediction.
        scale: the correction's reach, in units of the maximum speed per axis.
        accel_lead: s, the guidance predicts the target's velocity this far ahead at its
            acceleration over the last control period, ``v_other + accel_lead * a_other``
            (augmented proportional navigation: a target whose velocity lags its command by a
            first-order time constant tau is flying towards ``v + tau * a``); 0 is the textbook
            law.
    """

    guided = True
    invertible = True  # inverse() gives the action that flies any command

    def __init__(
        self,
        *,
        gain: float = 5.0,
        lead: float = 0.5,
        max_lead_time: float = 4.0,
        scale: float = 2.0,
        accel_lead: float = 0.0,
    ) -> None:
        for name, v in (("gain", gain), ("scale", scale)):
            if not v > 0:
                raise ConfigError(f"action.{name}: must be > 0, got {v}")
        for name, v in (
            ("lead", lead),
            ("max_lead_time", max_lead_time),
            ("accel_lead", accel_lead),
        ):
            if not v >= 0:
                raise ConfigError(f"action.{name}: must be >= 0, got {v}")
        self.gain, self.lead = float(gain), float(lead)
        self.max_lead_time, self.scale = float(max_lead_time), float(scale)
        self.accel_lead = float(accel_lead)

    def guidance(
        self, rel: Tensor, v_other: Tensor, max_speed: Tensor, a_other: Tensor | None = None
    ) -> Tensor:
        """Guidance action (*B, 3) in [-1, 1] for targets at ``rel`` (*B, 3) m moving at
        ``v_other`` (*B, 3) m/s and accelerating at ``a_other`` (*B, 3) m/s^2 (None: not
        known, the textbook law), pursuers of ``max_speed`` (*B,) m/s."""
        speed, v = max_speed.unsqueeze(-1), aim_velocity(v_other, a_other, self.accel_lead)
        return intercept_action(rel, v, speed, self.gain, self.lead, self.max_lead_time)

    def __call__(self, action: Tensor, max_speed: Tensor, guidance: Tensor | None = None) -> Tensor:
        if guidance is None:
            raise ValueError("action: a guided action needs the guidance action")
        total = (guidance + self.scale * action.clamp(-1.0, 1.0)).clamp(-1.0, 1.0)
        return total * max_speed.unsqueeze(-1)

    def inverse(self, flown: Tensor, guidance: Tensor) -> Tensor:
        """The action (*B, 3) that flies the action ``flown`` (*B, 3) of a plain velocity
        action (command / max speed) under ``guidance``: exact for ``scale >= 2``."""
        return ((flown - guidance) / self.scale).clamp(-1.0, 1.0)

    corrects = ("proportional navigation", "pn")  # the law corrected, and its term in the card

    def card(self) -> dict[str, Any]:
        """What an exported controller's action means (the ``action`` entry of its card)."""
        law, term = self.corrects
        return {
            "features": ["dv_cmd.x", "dv_cmd.y", "dv_cmd.z"],
            "unit": f"1: a correction to {law}; the velocity command is "
            f"clamp({term} + {self.scale:g} * action, -1, 1) times the drone's maximum speed per "
            "axis",
            "guidance": {**self._law_card(), "scale": self.scale},
        }

    def _law_card(self) -> dict[str, Any]:
        """The guidance law under the action, for the card."""
        return {
            "law": "proportional_navigation (rlplat.envs.kinematics.intercept_action)",
            "formula": self.pn_formula(),
            "gain": self.gain,
            "lead": self.lead,
            "max_lead_time": self.max_lead_time,
            "accel_lead": self.accel_lead,
        }

    def pn_formula(self, accel: bool = True) -> str:
        """Proportional navigation as the card and header state it, for a host to compute;
        ``accel``: with this action's acceleration lead (the route law homes without one)."""
        lead = accel and self._accel_term() is not None
        u = (
            "u = v + accel_lead * a, v the defender's velocity and a its mean "
            "acceleration over the last control period (m/s, m/s^2; world frame, not relative "
            "to the attacker)"
            if lead
            else "u the defender's velocity (m/s, world frame, not relative to the attacker)"
        )
        return (
            "pn = clamp(gain * (r + lead * u * t_go) / V, -1, 1) per axis: r the nearest "
            "defender's position minus the attacker's (m), "
            f"{u}, V the attacker's maximum speed per axis; t_go = min(max over the axes of "
            "t_i, max_lead_time), t_i = |r_i| / (V - sign(r_i) * u_i) where that closing speed "
            "exceeds 1e-6 m/s, else max_lead_time"
        )

    def describe(self) -> list[str]:
        """The same for a C header's comment."""
        return [
            "action is a CORRECTION to proportional navigation (action guided_velocity): the",
            f"velocity command is clamp(pn + {self.scale:g} * action, -1, 1) x max speed per axis,",
            f"pn the law's action (gain {self.gain:g}/s, lead {self.lead:g}, max lead time "
            f"{self.max_lead_time:g} s; rlplat.envs.kinematics.intercept_action).",
            *self._describe_accel(),
            *textwrap.wrap(self.pn_formula() + ".", 78),
        ]

    def _accel_term(self) -> str | None:
        """The acceleration lead as the card and header state it (None: the textbook law)."""
        return f"{self.accel_lead:g} s" if self.accel_lead else None

    def _describe_accel(self) -> list[str]:
        """The acceleration lead's lines of :meth:`describe` (none for the textbook law)."""
        term = self._accel_term()
        if term is None:
            return []
        return [
            f"The law aims with the target's velocity v + {term} * a, a its mean",
            "acceleration over the last control period (augmented proportional navigation).",
        ]


class RouteLawAction(GuidedVelocityAction):
    """A learned correction to the route-intercept law (a residual policy on a law that knows
    the defender's route).

    As :class:`GuidedVelocityAction`, ``clamp(g + scale * action, -1, 1) * max_speed`` per
    axis, with ``g`` the action of :func:`rlplat.envs.kinematics.route_law`: fly to the
    earliest point of the nearest defender's route-flying path the attacker can reach and hold
    there until the defender is due within ``homing_time``, proportional navigation from then
    on (the ``route_intercept`` baseline); where no such point exists, as ``unreachable``
    says. The env computes the meeting point from the defender's route (known in advance, as
    the capture ceiling assumes), with the attacker at full speed per axis from ``start_lag``
    s on. A zero action flies the law; with ``scale >= 2`` :meth:`inverse` flies any command.
    Attackers only.

    Args:
        gain, lead, max_lead_time, scale: as :class:`GuidedVelocityAction` (``gain`` is also
            the command per metre to the meeting point).
        homing_time: s, when the law turns to proportional navigation.
        start_lag: s, the attacker's start-up lag the meeting point allows for: a point the
            attacker could reach only by flying at full speed from this instant is one its
            velocity dynamics cannot keep.
        gate_low, gate_high: m/s^2, the correction's gate on how far the nearest defender
            departs from its route (``route_deviation`` of ``observation=pursuit_conform``, as
            the policy saw it): the correction is scaled by ``clamp((deviation - gate_low) /
            (gate_high - gate_low), 0, 1)``, so a defender that keeps its route is met by the
            law alone and one that leaves it gets the whole correction. 0 and 0: no gate.
        gate_unreachable: with a gate, it also opens wholly where no meeting point is
            reachable: the law meets no route-flying defender there, so the correction can
            cost the route flyers nothing, and a defender faster than the attacker is left to
            the correction whatever its route deviation (``reachable`` of the state the policy
            saw).
        horizon: s, how far ahead the law looks for a meeting point (None: the episode's time
            limit). A longer look finds a point further along the route for an attacker too
            slow to meet the defender sooner.
        unreachable: where no meeting point within the horizon is reachable, ``chase`` flies
            proportional navigation at the defender; ``head_off`` flies to where its
            route-flying path puts it at the horizon's end (its route's end, if it gets there
            sooner) and holds there: a defender faster than the attacker that leaves its route
            to evade is met where the route takes it back.
    """

    name = "route_law"
    reads_route = True  # the env passes the meeting point with the guidance
    #: The law's own settings: what the ``route_intercept`` baseline flies with to be this law.
    law_args = ("homing_time", "start_lag", "horizon", "unreachable")
    corrects = ("the route-intercept law", "law")

    def __init__(
        self,
        *,
        gain: float = 5.0,
        lead: float = 0.5,
        max_lead_time: float = 4.0,
        scale: float = 2.0,
        homing_time: float = 2.0,
        start_lag: float = 0.0,
        gate_low: float = 0.0,
        gate_high: float = 0.0,
        gate_unreachable: bool = False,
        horizon: float | None = None,
        unreachable: str = "chase",
    ) -> None:
        super().__init__(gain=gain, lead=lead, max_lead_time=max_lead_time, scale=scale)
        times = law_times("action", homing_time=homing_time, start_lag=start_lag)
        self.homing_time, self.start_lag = times["homing_time"], times["start_lag"]
        self.horizon = law_horizon("action", horizon)
        self.unreachable = law_unreachable("action", unreachable)
        for name, v in (("gate_low", gate_low), ("gate_high", gate_high)):
            if not v >= 0:
                raise ConfigError(f"action.{name}: must be >= 0, got {v}")
        if gate_high > 0 and not gate_high > gate_low:
            raise ConfigError(
                f"action.gate_high: must be > action.gate_low={gate_low:g} (or both 0: no gate), "
                f"got {gate_high:g}"
            )
        if gate_high == 0 and gate_low > 0:
            raise ConfigError(
                f"action.gate_high: 0 turns the gate off, but action.gate_low is {gate_low:g}; "
                "set gate_high > gate_low, or both to 0"
            )
        self.gate_low, self.gate_high = float(gate_low), float(gate_high)
        if gate_unreachable and not gate_high > 0:
            raise ConfigError(
                "action.gate_unreachable: opens the gate where no meeting point is reachable, "
                "and this action has no gate (gate_high 0)"
            )
        self.gate_unreachable = bool(gate_unreachable)

    @property
    def gated(self) -> bool:
        """Whether the correction is gated on the defender's route deviation (the env then
        passes the deviation the policy saw, ``deviation``)."""
        return self.gate_high > 0

    @classmethod
    def flies_any_command(cls, cfg: Mapping[str, Any]) -> bool:
        """A gated correction flies only the law where the defender keeps its route."""
        return not float(cfg.get("gate_high", 0.0) or 0.0) > 0

    @property
    def invertible(self) -> bool:
        """Whether :meth:`inverse` flies any command: not through a gate."""
        return not self.gated

    def reach(self, deviation: Tensor, reachable: Tensor | None = None) -> Tensor:
        """The gate (*B, 1) in [0, 1] for route deviations ``deviation`` (*B,) m/s^2; with
        ``gate_unreachable``, 1 where ``reachable`` (*B,) bool is False."""
        span = self.gate_high - self.gate_low
        gate = ((deviation - self.gate_low) / span).clamp(0.0, 1.0)
        if self.gate_unreachable:
            if reachable is None:
                raise ValueError("action route_law: gate_unreachable needs the meeting point")
            gate = gate.masked_fill(~reachable.bool(), 1.0)
        return gate.unsqueeze(-1)

    def __call__(
        self,
        action: Tensor,
        max_speed: Tensor,
        guidance: Tensor | None = None,
        deviation: Tensor | None = None,
        reachable: Tensor | None = None,
    ) -> Tensor:
        """As :class:`GuidedVelocityAction`; a gated action also needs ``deviation`` (*B,)
        m/s^2, the nearest defender's route deviation in the state the policy observed (and,
        with ``gate_unreachable``, ``reachable`` (*B,) bool: whether that state's meeting
        point is)."""
        if self.gated:
            if deviation is None:
                raise ValueError("action route_law: a gated correction needs the route deviation")
            action = action.clamp(-1.0, 1.0) * self.reach(deviation, reachable)
        return super().__call__(action, max_speed, guidance)

    def guidance(
        self,
        rel: Tensor,
        v_other: Tensor,
        max_speed: Tensor,
        a_other: Tensor | None = None,
        meeting: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> Tensor:
        """The law's action (*B, 3); ``meeting`` is the meeting point relative to the pursuer
        (*B, 3) m, when the defender is there (*B,) s and whether it is reachable (*B,)
        (:func:`rlplat.envs.kinematics.route_intercept`)."""
        if meeting is None:
            raise ValueError("action route_law: the guidance needs the meeting point")
        homing = super().guidance(rel, v_other, max_speed)
        aim, due, reachable = meeting
        speed = max_speed.unsqueeze(-1)
        return route_law(homing, aim, due, reachable, speed, self.gain, self.homing_time,
                         self.unreachable)  # fmt: skip

    def card(self) -> dict[str, Any]:
        card = super().card()
        if self.gated:
            card["unit"] = (
                f"1: a correction to {self.corrects[0]}, gated on the defender's route "
                f"deviation d (the observation's route_deviation): the velocity command is "
                f"clamp(law + {self.scale:g} * gate(d) * action, -1, 1) times the drone's maximum "
                f"speed per axis, gate(d) = clamp((d - {self.gate_low:g}) / "
                f"{self.gate_high - self.gate_low:g}, 0, 1)"
                + (", and 1 where no meeting point is reachable" if self.gate_unreachable else "")
            )
            card["guidance"]["gate"] = {"low": self.gate_low, "high": self.gate_high,
                                        "unreachable_opens": self.gate_unreachable}  # fmt: skip
        return card

    def route_formula(self) -> str:
        """The route-intercept law as the card and header state it, for a host to compute."""
        if self.unreachable == "chase":
            until, rest = " and the point is reachable", "; pn from then on and wherever none is"
        else:
            until = ""
            rest = (
                "; pn from then on. Where none is reachable it flies to route_path's unreachable "
                "point all the same and holds there"
            )
        return (
            "law = clamp(gain * m / V, -1, 1) per axis, m the meeting point relative to the "
            "attacker (route_path; the observation's intercept - p_own where it has one), V its "
            "maximum speed per axis, "
            f"while the defender is due there later than homing_time s (t_intercept > "
            f"homing_time){until}{rest}. A null horizon is the episode's time limit "
            f"(route_path's horizon, s). {self.pn_formula(accel=False)}"
        )

    def _law_card(self) -> dict[str, Any]:
        return {
            "law": "route_intercept (rlplat.envs.kinematics.route_law), proportional navigation "
            "when homing (rlplat.envs.kinematics.intercept_action)",
            "formula": self.route_formula(),
            "gain": self.gain,
            "lead": self.lead,
            "max_lead_time": self.max_lead_time,
            "homing_time": self.homing_time,
            "start_lag": self.start_lag,
            "horizon": self.horizon,
            "unreachable": self.unreachable,
        }

    def describe(self) -> list[str]:
        return [
            "action is a CORRECTION to the route-intercept law (action route_law): the velocity",
            f"command is clamp(law + {self.scale:g} * action, -1, 1) x max speed per axis; the",
            "law flies to the earliest point of the defender's route-flying path it can reach",
            f"after a {self.start_lag:g}-s start-up lag (gain {self.gain:g}/s) and holds there",
            f"until the defender is due within {self.homing_time:g} s (meeting points up to",
            f"{'the time limit' if self.horizon is None else f'{self.horizon:g} s'} ahead),",
            f"then proportional navigation (lead {self.lead:g}, max lead time "
            f"{self.max_lead_time:g} s;",
            "rlplat.envs.kinematics.route_law). Where no point is reachable, it",
            "chases with proportional navigation."
            if self.unreachable == "chase"
            else "flies to where the route puts the defender at the horizon's end and holds.",
            *textwrap.wrap(self.route_formula() + ".", 78),
            *(
                [
                    "GATED: the correction is multiplied by clamp((d - "
                    f"{self.gate_low:g}) / {self.gate_high - self.gate_low:g}, 0, 1),",
                    "d the route_deviation input feature (m/s^2): 0 while the defender keeps its",
                    "route (the law alone), 1 once it departs from it.",
                    *(
                        ["It is 1 where the meeting point's search finds none reachable."]
                        if self.gate_unreachable
                        else []
                    ),
                ]
                if self.gated
                else []
            ),
        ]


class GuidanceLawAction(GuidedVelocityAction):
    """The policy flies proportional navigation and sets the law's parameters, every step.

    The action's three components in [-1, 1] set, around the law of ``gain``, ``lead`` and
    ``max_lead_time`` (a zero action flies that law exactly):
    ``gain * gain_factor ** a0``, ``lead + lead_reach * a1`` (at least 0) and
    ``max_lead_time * horizon_factor ** a2``. Every action flies some guidance law, so
    exploring never leaves the family; a scripted policy cannot be flown through it (no
    inverse) unless a correction of reach 2 or more is added. Attackers only.

    Args:
        gain, lead, max_lead_time: the law of the zero action.
        accel_lead: s, as for :class:`GuidedVelocityAction`: every law of the family aims
            with the target's velocity ``accel_lead`` seconds ahead at its acceleration.
        gain_factor: > 1, the gain's range is [gain / factor, gain * factor].
        lead_reach: >= 0, the lead's range is lead ± reach (clipped at 0).
        horizon_factor: > 1, the longest prediction's range, as for the gain.
        accel_reach: >= 0; above 0 the action has a fourth component that sets the
            acceleration lead too, ``accel_lead + accel_reach * a3`` (at least 0), so the
            policy chooses where to trust the target's acceleration.
        correction_reach: >= 0; above 0 the action has three more (last) components ``c``, a
            correction added to the law's command as :class:`GuidedVelocityAction` adds it:
            ``clamp(law + correction_reach * c, -1, 1) * max_speed``. From 2 on every command
            is reachable and :meth:`inverse` flies a scripted policy (parameters at zero).
    """

    name = "guidance_law"

    def __init__(
        self,
        *,
        gain: float = 5.0,
        lead: float = 0.5,
        max_lead_time: float = 4.0,
        gain_factor: float = 5.0,
        lead_reach: float = 0.5,
        horizon_factor: float = 4.0,
        accel_lead: float = 0.0,
        accel_reach: float = 0.0,
        correction_reach: float = 0.0,
    ) -> None:
        super().__init__(gain=gain, lead=lead, max_lead_time=max_lead_time, accel_lead=accel_lead)
        for name, v in (("gain_factor", gain_factor), ("horizon_factor", horizon_factor)):
            if not v > 1:
                raise ConfigError(f"action.{name}: must be > 1, got {v}")
        reaches = (("lead_reach", lead_reach), ("accel_reach", accel_reach),
                   ("correction_reach", correction_reach))  # fmt: skip
        for name, v in reaches:
            if not v >= 0:
                raise ConfigError(f"action.{name}: must be >= 0, got {v}")
        self.gain_factor, self.lead_reach = float(gain_factor), float(lead_reach)
        self.horizon_factor, self.accel_reach = float(horizon_factor), float(accel_reach)
        self.correction_reach = float(correction_reach)
        self.law_dim = 4 if self.accel_reach > 0 else 3  # the components that set the law
        self.dim = self.law_dim + (3 if self.correction_reach > 0 else 0)

    @classmethod
    def flies_any_command(cls, cfg: Mapping[str, Any]) -> bool:
        """With a correction of reach 2 or more. Where no action flies a command, a scripted
        policy is flown on a plain velocity action instead (the training's reference), or not
        at all (``algo.init_policy``)."""
        return float(cfg.get("correction_reach", 0.0)) >= 2.0

    @property
    def invertible(self) -> bool:
        """Whether :meth:`inverse` flies any command (see :meth:`flies_any_command`)."""
        return self.flies_any_command({"correction_reach": self.correction_reach})

    def guidance(
        self, rel: Tensor, v_other: Tensor, max_speed: Tensor, a_other: Tensor | None = None
    ) -> Tensor:
        """The geometry the law needs, (*B, 10): target offset, its velocity, its acceleration
        (zero where not known) and the max speed."""
        a = torch.zeros_like(v_other) if a_other is None else a_other
        return torch.cat([rel, v_other, a, max_speed.unsqueeze(-1)], -1)

    def __call__(self, action: Tensor, max_speed: Tensor, guidance: Tensor | None = None) -> Tensor:
        """The law's command (*B, 3) m/s for the parameters ``action`` sets; the speed limit is
        the one ``guidance`` carries (the same ``max_speed``)."""
        if guidance is None:
            raise ValueError("action: a guided action needs the guidance action")
        gain, lead, horizon = self.law(action)
        rel, v_other, a_other = guidance[..., :3], guidance[..., 3:6], guidance[..., 6:9]
        v, speed = aim_velocity(v_other, a_other, self.accel(action)), guidance[..., 9:10]
        command = intercept_action(rel, v, speed, gain, lead, horizon)
        if self.correction_reach > 0:
            correction = action[..., self.law_dim :].clamp(-1.0, 1.0)
            command = (command + self.correction_reach * correction).clamp(-1.0, 1.0)
        return command * speed

    def inverse(self, flown: Tensor, guidance: Tensor) -> Tensor:
        """The action (*B, dim) that flies the action ``flown`` (*B, 3) of a plain velocity
        action under ``guidance``, the zero action's law as an action (*B, 3): the law's
        ``law_dim`` parameters at zero, then the correction that makes up the difference (exact
        for ``correction_reach >= 2``)."""
        if not self.invertible:
            raise ConfigError(
                "action=guidance_law: a scripted policy cannot be flown through it (no action "
                "gives an arbitrary command; action.correction_reach >= 2 gives one)"
            )
        correction = ((flown - guidance) / self.correction_reach).clamp(-1.0, 1.0)
        return torch.cat([flown.new_zeros(*flown.shape[:-1], self.law_dim), correction], -1)

    def law(self, action: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The gain, lead and longest prediction (each (*B, 1)) that ``action`` (*B, 3) sets."""
        a = action.clamp(-1.0, 1.0)
        gain = self.gain * self.gain_factor ** a[..., 0:1]
        lead = (self.lead + self.lead_reach * a[..., 1:2]).clamp_min(0.0)
        return gain, lead, self.max_lead_time * self.horizon_factor ** a[..., 2:3]

    def _accel_term(self) -> str | None:
        if self.law_dim == 3:
            return super()._accel_term()
        return f"max({self.accel_lead:g} + {self.accel_reach:g} * a3, 0) s"

    def accel(self, action: Tensor) -> Tensor | float:
        """The acceleration lead in s that ``action`` sets: (*B, 1) from its fourth component,
        or the configured one for a three-component action."""
        if self.law_dim == 3:
            return self.accel_lead
        a3 = action[..., 3:4].clamp(-1.0, 1.0)
        return (self.accel_lead + self.accel_reach * a3).clamp_min(0.0)

    def card(self) -> dict[str, Any]:
        learned = self.law_dim == 4
        features = ["log_gain", "lead", "log_max_lead_time"] + ["accel_lead"] * learned
        if self.correction_reach > 0:
            features += ["correction.x", "correction.y", "correction.z"]
        return {
            "features": features,
            "unit": "1: the parameters of proportional navigation, flown by the env: gain = "
            f"{self.gain:g} * {self.gain_factor:g}^a0 1/s, lead = max({self.lead:g} + "
            f"{self.lead_reach:g} * a1, 0), max lead time = {self.max_lead_time:g} * "
            f"{self.horizon_factor:g}^a2 s"
            + (f", acceleration lead = {self._accel_term()}" if learned else "")
            + f"; {self._command_term()}",
            "guidance": {
                **self._law_card(),
                "gain_factor": self.gain_factor,
                "lead_reach": self.lead_reach,
                "horizon_factor": self.horizon_factor,
                "accel_reach": self.accel_reach,
                "correction_reach": self.correction_reach,
            },
        }

    def _command_term(
        self, pn: str = "pn as guidance.formula, with the gain, lead and max lead time above"
    ) -> str:
        """The velocity command the law (``pn``, with the parameters the action sets) and the
        correction make."""
        if self.correction_reach <= 0:
            return f"velocity command = pn x max speed per axis ({pn})"
        c = f"a{self.law_dim}..a{self.law_dim + 2}"
        return (
            f"velocity command = clamp(pn + {self.correction_reach:g} * ({c}), -1, 1) x "
            f"max speed per axis ({pn})"
        )

    def describe(self) -> list[str]:
        return [
            "action SETS proportional navigation's parameters (action guidance_law); the env",
            f"flies the law: gain {self.gain:g} * {self.gain_factor:g}^a0 1/s, lead max("
            f"{self.lead:g} + {self.lead_reach:g} * a1, 0), max lead time {self.max_lead_time:g}"
            f" * {self.horizon_factor:g}^a2 s (rlplat.envs.kinematics.intercept_action).",
            *self._describe_accel(),
            *textwrap.wrap(f"The {self._command_term('pn as follows with those parameters')}:", 78),
            *textwrap.wrap(self.pn_formula() + ".", 78),
        ]


ACTIONS = {
    "velocity": VelocityAction,
    "guided_velocity": GuidedVelocityAction,
    "guidance_law": GuidanceLawAction,
    "route_law": RouteLawAction,
}


# Rewards ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RewardContext:
    """What reward terms may read after a step, per learning drone: (*B,) is (N,) for a lone
    learner and (N, K) for a team of K.

    Attributes:
        distance: (*B,) m from the drone to the nearest opponent still in play (a defender not
            yet caught) at the end of the step.
        visible: (*B,) bool: for an attacker, a defender in play inside its vision ellipsoid;
            for a defender, itself inside some attacker's ellipsoid.
        captured: (*B,) bool, a capture happened during the step (closest approach <= capture
            radius): of any defender, for an attacker (the team shares it); of itself, for a
            defender.
        grounded: (*B,) bool, a drone is at or below the ground altitude after the step.
        distance_scale: m, the normalising distance of the ``distance_sq`` and ``proximity``
            terms.
        route_progress: (*B,) m the defender gained on its current setpoint during the step
            (negative when it moved away; 0 once its route is flown).
        setpoint_reached: (*B,) bool, the defender reached its current setpoint in the step.
        action: (*B, A) the learner's action of the step, in [-1, 1] per component.
    """

    distance: Tensor
    visible: Tensor
    captured: Tensor
    grounded: Tensor
    distance_scale: float
    route_progress: Tensor | None = None
    setpoint_reached: Tensor | None = None
    action: Tensor | None = None


def _capture(c: RewardContext) -> Tensor:
    return c.captured.float()


def _ground_contact(c: RewardContext) -> Tensor:
    return (c.grounded & ~c.captured).float()


def _out_of_view(c: RewardContext) -> Tensor:
    return (~c.visible & ~c.captured).float()


def _distance_sq(c: RewardContext) -> Tensor:
    in_view = c.visible & ~c.captured
    return torch.where(in_view, (c.distance / c.distance_scale) ** 2, 0.0)


def _in_view_step(c: RewardContext) -> Tensor:
    return (c.visible & ~c.captured).float()


def _proximity(c: RewardContext) -> Tensor:
    """0 beyond ``distance_scale``, rising quadratically to 1 at contact (the defender's
    threat term: it grows as the attacker closes in)."""
    return (1.0 - c.distance / c.distance_scale).clamp_min(0.0) ** 2


def _route_progress(c: RewardContext) -> Tensor:
    return c.route_progress


def _setpoint_reached(c: RewardContext) -> Tensor:
    return c.setpoint_reached.float()


def _action_sq(c: RewardContext) -> Tensor:
    """The action's mean square per component: 1 at full scale, 0 for a zero action (with a
    correction action such as ``route_law``, flying the law unchanged)."""
    return c.action.square().mean(-1)


#: Reward terms: each returns an unweighted (*B,) float32 value; a YAML gives the weights.
REWARD_TERMS: dict[str, Callable[[RewardContext], Tensor]] = {
    "capture": _capture,
    "out_of_view": _out_of_view,
    "distance_sq": _distance_sq,
    "in_view_step": _in_view_step,
    "ground_contact": _ground_contact,
    "proximity": _proximity,
    "route_progress": _route_progress,
    "setpoint_reached": _setpoint_reached,
    "action_sq": _action_sq,
}


class Reward:
    """A weighted sum of named terms; each weighted term is reported on its own.

    With ``capture: 10, out_of_view: -1, distance_sq: -2, in_view_step: -0.1`` and
    ``distance_scale: 60`` this is paper eq. 3 exactly: +10 on capture; -1 if the defender is
    out of view; otherwise -2 d^2 / 60^2 - 0.1. ``ground_contact`` prices a crash: an
    attacker's own landing, and for every learner a crash that ends the episode (eq. 3 has no
    crash; see ``conf/reward/shaped.yaml``). The defender's reward (``conf/reward/evasion.yaml``)
    pays ``route_progress`` and ``setpoint_reached`` and charges
    ``proximity``, ``capture`` and ``ground_contact``.
    """

    def __init__(self, *, terms: Mapping[str, float], distance_scale: float = 60.0) -> None:
        for name in terms:
            if name not in REWARD_TERMS:
                raise ConfigError(
                    f"reward.terms.{name}: unknown reward term; valid: {', '.join(REWARD_TERMS)}"
                )
        if not distance_scale > 0:
            raise ConfigError(f"reward.distance_scale: must be > 0, got {distance_scale}")
        self.weights = {k: float(v) for k, v in terms.items()}
        self.distance_scale = float(distance_scale)

    def __call__(self, ctx: RewardContext) -> tuple[Tensor, dict[str, Tensor]]:
        """Return the total reward (*B,) and each weighted term (*B,) by name."""
        parts = {name: w * REWARD_TERMS[name](ctx) for name, w in self.weights.items()}
        return torch.stack(list(parts.values())).sum(0), parts
