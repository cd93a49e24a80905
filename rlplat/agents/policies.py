"""Every policy that is not being trained, in one place.

- The scripted references a learned controller must beat: pure pursuit, proportional
  navigation, the route-intercept law and the setpoint follower. Each is a
  ``TensorDictModule`` that reads only entries of the env's output (``positions``,
  ``velocities``, ``max_speed``, ``caught``, ``setpoints``, ``route_done``, ``waypoint``,
  ``scenario_index``; the route-intercept law also knows the split's routes) and writes the
  env's action key (``action``, or a team's ``("attacker", "action")``) in the action's
  [-1, 1] units: the command divided by the drone's maximum speed per axis. :data:`POLICIES`
  names them (``evaluate.py policy=<name>``).
- :class:`NetworkController`: a trained actor's deterministic action as a plain torch module of
  a :class:`~rlplat.envs.components.DroneView`, what the env flies for a scripted drone (the
  defender's ``nn`` strategy); :func:`load_controller` reads one from a checkpoint or the
  shipped weights.
- :class:`NoisyPolicy`: a scripted policy with Gaussian exploration, for the scripted start.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import Tensor, nn
from torchrl.data import Bounded

from rlplat.agents.checkpoint import actor_from_state, load_checkpoint, saved_interface
from rlplat.agents.sac import CorrelatedNoise
from rlplat.envs.components import OBSERVATIONS, DroneView
from rlplat.envs.kinematics import (
    SetpointFlight,
    aim_velocity,
    follow_route,
    gather_drones,
    intercept_action,
    law_horizon,
    law_times,
    law_unreachable,
    nearest,
    route_law,
    route_meeting,
    route_times,
    targets,
)
from rlplat.envs.pursuit import ROLES, PursuitEnv
from rlplat.errors import ConfigError

# Scripted policies -----------------------------------------------------------------------


class _Scripted(nn.Module):
    """What every scripted policy knows of its env: which drones it flies, which it faces.

    Drones are the env's k attackers, then its m defenders (the order of ``positions``). The
    output is (N, K, 3) for a team (``team=True``: the group layout) and (N, 3) for a lone
    drone.
    """

    def __init__(
        self,
        *,
        learner: Literal["attacker", "defender"],
        attackers: int,
        defenders: int,
        team: bool,
    ) -> None:
        super().__init__()
        k, m = attackers, defenders
        self.learner, self.team = learner, team
        self.own, self.others = (
            (slice(0, k), slice(k, k + m))
            if learner == "attacker"
            else (slice(k, k + m), slice(0, k))
        )

    def _nearest(self, positions: Tensor, max_speed: Tensor, caught: Tensor):
        """The flown drones' positions (N, K, 3), their maximum speeds (N, K, 1) and the index
        (N, K) of each one's nearest opponent in play (an attacker chases no caught defender)."""
        own, others = positions[:, self.own], positions[:, self.others]
        allowed = targets(caught) if self.learner == "attacker" else None
        return own, max_speed[:, self.own].unsqueeze(-1), nearest(own, others, allowed)

    def _action(self, action: Tensor) -> Tensor:
        return action if self.team else action[:, 0]


class PurePursuit(_Scripted):
    """Fly each attacker straight at its nearest defender in play (pure pursuit).

    The command ``gain * (p_other - p_own)`` saturated at the drone's maximum speed per axis.

    Args:
        gain: 1/s, command per metre of separation (``env.pursuit_gain``).
    """

    in_keys = ("positions", "max_speed", "caught")

    def __init__(self, *, gain: float, **drones: Any) -> None:
        super().__init__(**drones)
        self.gain = float(gain)

    def forward(self, positions: Tensor, max_speed: Tensor, caught: Tensor) -> Tensor:
        own, speed, near = self._nearest(positions, max_speed, caught)
        rel = gather_drones(positions[:, self.others], near) - own
        return self._action((self.gain * rel / speed).clamp(-1.0, 1.0))


class ProportionalNavigation(_Scripted):
    """Proportional navigation with lead, in the velocity-command form a multirotor flies.

    PN turns the pursuer until the line of sight to the target stops rotating: a collision
    course, on which the pursuer flies at the point where the target will be. A drone that is
    commanded in velocity can fly that course directly: aim at the predicted intercept point
    ``p_other + lead * v_other * t_go`` and command ``gain * (aim - p_own)`` saturated at the
    maximum speed per axis, as pure pursuit does with the current position. ``t_go`` is the
    time the attacker needs to close the largest per-axis gap at full speed while the target
    keeps its velocity (speed limits are per axis, so each axis closes on its own), capped at
    ``max_lead_time``; on an axis where the target is as fast as the attacker the cap applies.
    The target is each attacker's nearest defender in play; with ``lead = 0`` this is pure
    pursuit.

    Args:
        gain: 1/s, command per metre to the aim point (``env.pursuit_gain``).
        lead: fraction of the predicted target motion to lead by (0 = pure pursuit).
        max_lead_time: s, longest prediction.
        accel_lead: s, aim with the target's velocity ``v + accel_lead * a`` (its acceleration
            over the last control period; augmented proportional navigation); 0, the default,
            is the textbook law.
    """

    in_keys: tuple[str, ...] = ("positions", "velocities", "max_speed", "caught")

    def __init__(
        self,
        *,
        gain: float,
        lead: float = 0.5,
        max_lead_time: float = 4.0,
        accel_lead: float = 0.0,
        **drones: Any,
    ) -> None:
        super().__init__(**drones)
        for name, v in (("max_lead_time", max_lead_time), ("accel_lead", accel_lead)):
            if not v >= 0:
                raise ConfigError(f"{name}: must be >= 0, got {v}")
        self.gain, self.lead, self.max_lead_time = float(gain), float(lead), float(max_lead_time)
        self.accel_lead = float(accel_lead)
        if self.accel_lead:  # the augmented law reads the accelerations too
            self.in_keys = (*self.in_keys, "accelerations")

    def forward(
        self,
        positions: Tensor,
        velocities: Tensor,
        max_speed: Tensor,
        caught: Tensor,
        accelerations: Tensor | None = None,
    ) -> Tensor:
        own, speed, near = self._nearest(positions, max_speed, caught)
        rel = gather_drones(positions[:, self.others], near) - own
        v_other = gather_drones(velocities[:, self.others], near)
        if self.accel_lead:
            if accelerations is None:
                raise ValueError("proportional_navigation: accel_lead > 0 needs accelerations")
            a_other = gather_drones(accelerations[:, self.others], near)
            v_other = aim_velocity(v_other, a_other, self.accel_lead)
        action = intercept_action(rel, v_other, speed, self.gain, self.lead, self.max_lead_time)
        return self._action(action)


class RouteIntercept(ProportionalNavigation):
    """Fly to where the defender's known route lets the attacker meet it, then proportional
    navigation: the classical law with the information of ``observation=pursuit_route`` and
    more (the whole route ahead, not two setpoints).

    Each step, for the nearest defender in play: its path as a ``setpoints`` defender would fly
    the rest of its route (:func:`rlplat.envs.kinematics.route_path`), and the earliest point of
    that path the attacker can reach in time (:func:`~rlplat.envs.kinematics.route_intercept`,
    at full speed per axis after a start-up lag ``start_lag``). The attacker flies to that point
    (``gain`` per metre, saturated at its maximum speed) and waits there, until the defender is
    due within ``homing_time``; from then on it flies proportional navigation (``lead``,
    ``max_lead_time``), and where no point is reachable it does as ``unreachable`` says. A
    defender that leaves its route (the ``nn`` strategy evades) is met where its route would
    have taken it, so the law can do worse than proportional navigation there.

    Args:
        routes: (R, S, 3) m, the scenario set's routes. scenario_routes: (E, m) int64, each
            defender's route in every scenario of the split (``scenario_index`` rows).
        capture_radius: m, how close counts as a meeting. time_limit: s, the episode's.
        flight: how the defenders fly their routes (the env's setpoint gain and acceptance
            radius, :func:`~rlplat.envs.kinematics.setpoint_flight`; the default, without lags).
        homing_time: s, switch to proportional navigation when the meeting is this close.
        start_lag: s, the attacker's start-up lag the meeting point allows for.
        horizon: s, how far ahead it looks for a meeting point (None: ``time_limit``).
        unreachable: where no point is reachable, ``chase`` (proportional navigation) or
            ``head_off`` (to the path's point at the horizon's end, and hold there).
        gain, lead, max_lead_time: as :class:`ProportionalNavigation`.

    Made by name (``make_scripted_policy``), it flies the law of the env's action where that
    action is the route law (``action=route_law``: its ``homing_time``, ``start_lag``,
    ``horizon`` and ``unreachable``), so
    the baseline is the law a run's correction corrects; otherwise these defaults.
    """

    in_keys = ("positions", "velocities", "max_speed", "caught", "waypoint", "scenario_index")

    def __init__(
        self,
        *,
        routes: Tensor,
        scenario_routes: Tensor,
        capture_radius: float,
        time_limit: float,
        flight: SetpointFlight | None = None,
        homing_time: float = 2.0,
        start_lag: float = 0.0,
        horizon: float | None = None,
        unreachable: str = "chase",
        **pn: Any,
    ) -> None:
        super().__init__(**pn)
        times = law_times("route_intercept", homing_time=homing_time, start_lag=start_lag)
        horizon = law_horizon("route_intercept", horizon)
        self.unreachable = law_unreachable("route_intercept", unreachable)
        self.register_buffer("routes", routes.float())
        self.register_buffer("scenario_routes", scenario_routes.long())
        self.register_buffer("times", route_times(time_limit if horizon is None else horizon))
        self.capture_radius = float(capture_radius)
        self.homing_time, self.start_lag = times["homing_time"], times["start_lag"]
        self.flight = SetpointFlight() if flight is None else flight

    def forward(
        self,
        positions: Tensor,
        velocities: Tensor,
        max_speed: Tensor,
        caught: Tensor,
        waypoint: Tensor,
        scenario_index: Tensor,
    ) -> Tensor:
        own, speed, near = self._nearest(positions, max_speed, caught)
        other = gather_drones(positions[:, self.others], near)  # (N, K, 3)
        rel = other - own
        v_other = gather_drones(velocities[:, self.others], near)
        homing = intercept_action(rel, v_other, speed, self.gain, self.lead, self.max_lead_time)
        routes = self.routes[self.scenario_routes[scenario_index.reshape(-1).long()]]
        aim, due, reachable = route_meeting(
            own, speed.squeeze(-1), positions[:, self.others], velocities[:, self.others],
            max_speed[:, self.others], routes, waypoint, near, times=self.times,
            reach=self.capture_radius, flight=self.flight, lag=self.start_lag,
        )  # fmt: skip
        action = route_law(homing, aim - own, due, reachable, speed, self.gain, self.homing_time,
                           self.unreachable)  # fmt: skip
        return self._action(action)


class SetpointFollower(_Scripted):
    """The defender's ``setpoints`` strategy as a policy: fly to the route's next setpoint.

    The command is the env's own route follower (``gain`` per metre, saturated at the
    defender's maximum speed, hold once the route is flown), so this policy is exactly what a
    scripted defender does.

    Args:
        gain: 1/s, command per metre to the setpoint (``env.setpoint_gain``).
    """

    in_keys = ("positions", "max_speed", "setpoints", "route_done")

    def __init__(self, *, gain: float, **drones: Any) -> None:
        super().__init__(**drones)
        self.gain = float(gain)

    def forward(
        self, positions: Tensor, max_speed: Tensor, setpoints: Tensor, route_done: Tensor
    ) -> Tensor:
        speed = max_speed[:, self.own]
        cmd = follow_route(positions[:, self.own], setpoints, route_done, speed, self.gain)
        return self._action((cmd / speed.unsqueeze(-1)).clamp(-1.0, 1.0))


@dataclass(frozen=True)
class Scripted:
    """A scripted policy the evaluator can fly: its module, the drone it flies, and which env
    gain it takes."""

    module: Callable[..., _Scripted]
    role: Literal["attacker", "defender"]
    gain: Literal["pursuit_gain", "setpoint_gain"]
    env_args: Callable[[PursuitEnv], dict[str, Any]] | None = None  # what else it takes


def _known_routes(env: PursuitEnv) -> dict[str, Any]:
    """What :class:`RouteIntercept` knows in advance: the routes of the env's split, and the
    law of the env's action where it corrects the route-intercept law."""
    law = env.action_fn
    return {
        "routes": env.routes,
        "scenario_routes": env.scenarios["route"],
        "capture_radius": env.capture_radius,
        "time_limit": env.max_steps * env.control_period,
        "flight": env.route_flight,
        **{k: getattr(law, k) for k in getattr(law, "law_args", ())},
    }


#: Scripted policies by name (``evaluate.py policy=<name>``, ``algo.init_policy``).
POLICIES: dict[str, Scripted] = {
    "pure_pursuit": Scripted(PurePursuit, "attacker", "pursuit_gain"),
    "proportional_navigation": Scripted(ProportionalNavigation, "attacker", "pursuit_gain"),
    "route_intercept": Scripted(RouteIntercept, "attacker", "pursuit_gain", _known_routes),
    "setpoint_follower": Scripted(SetpointFollower, "defender", "setpoint_gain"),
}


#: The scripted policy each learner is measured against on the validation split.
REFERENCE = {"attacker": "proportional_navigation", "defender": "setpoint_follower"}


def policies_for(role: str) -> list[str]:
    """The scripted policies that fly a drone of ``role``."""
    return [name for name, p in POLICIES.items() if p.role == role]


def make_scripted_policy(name: str, env: PursuitEnv, **kwargs: Any) -> TensorDictModule:
    """The scripted policy ``name`` flying ``env``'s learners, as a ``TensorDictModule``.

    The env gives the drone counts, the action key and the gain (``kwargs`` may override the
    module's other arguments); the module reads only the env's output. A clear error for an
    unknown name or a policy made for the other drone.
    """
    if name not in POLICIES:
        raise ConfigError(f"policy: unknown baseline '{name}'; valid: {', '.join(POLICIES)}")
    scripted, learner = POLICIES[name], ROLES[env.learner]
    if scripted.role != learner:
        raise ConfigError(
            f"policy: {name} flies the {scripted.role}, this run's learner is the {learner}; "
            f"valid: {', '.join(policies_for(learner))}"
        )
    env_args = scripted.env_args(env) if scripted.env_args else {}
    module = scripted.module(
        learner=learner,
        attackers=env.num_attackers,
        defenders=env.num_defenders,
        team=env.group is not None,
        **{"gain": getattr(env, scripted.gain), **env_args, **kwargs},
    )
    if getattr(env.action_fn, "guided", False):
        # A gated correction flies only its own law where the gate is shut: through it, the
        # route-intercept law (a zero correction) and nothing else.
        gated = getattr(env.action_fn, "gated", False)
        own_law = gated and name == "route_intercept" and not kwargs
        if gated and not own_law:
            raise ConfigError(
                f"policy: {name} cannot be flown through action={env.action_fn.name} with a gate "
                "(action.gate_high > 0: where the defender keeps its route the correction is shut "
                "and only the law flies); valid: route_intercept, or fly it on action=velocity"
            )
        if not gated and not getattr(env.action_fn, "invertible", True):
            raise ConfigError(
                f"policy: {name} cannot be flown through action={env.action_fn.name} (its "
                "actions set the guidance law's parameters; fly it on action=velocity, or give "
                "the action a correction: action.correction_reach >= 2)"
            )
        module = Unguided(module, env)
    return TensorDictModule(module, in_keys=list(module.in_keys), out_keys=[env.action_key])


class Unguided(nn.Module):
    """A scripted policy flown through a guided action (a correction to proportional
    navigation, :class:`rlplat.envs.components.GuidedVelocityAction`, or to the route-intercept
    law, ``RouteLawAction``, or the law's parameters at zero and a correction,
    ``GuidanceLawAction``): the correction that makes the env fly exactly the policy's own
    command (for ``scale >= 2``, resp. ``correction_reach >= 2``)."""

    def __init__(self, policy: _Scripted, env: PursuitEnv) -> None:
        super().__init__()
        self.policy, self.action = policy, env.action_fn
        law = {
            "gain": self.action.gain,
            "lead": self.action.lead,
            "max_lead_time": self.action.max_lead_time,
            "learner": policy.learner,
            "attackers": env.num_attackers,
            "defenders": env.num_defenders,
            "team": policy.team,
        }
        if getattr(self.action, "reads_route", False):  # the route-intercept law
            self.guidance = RouteIntercept(**law, **_known_routes(env))
        else:
            self.guidance = ProportionalNavigation(**law, accel_lead=self.action.accel_lead)
        self.in_keys = tuple(dict.fromkeys((*policy.in_keys, *self.guidance.in_keys)))

    def forward(self, *inputs: Tensor) -> Tensor:
        named = dict(zip(self.in_keys, inputs, strict=True))
        flown = self.policy(*(named[k] for k in self.policy.in_keys))
        guidance = self.guidance(*(named[k] for k in self.guidance.in_keys))
        return self.action.inverse(flown, guidance)


class MeanAction(TensorDictModuleBase):
    """An ensemble of policies that fly the same drone interface: the mean of their actions.

    Each member acts on its own copy of the input entries it reads; the mean of their
    ``action_key`` entries is written into the input. Flown by the evaluator, the members act
    deterministically, so the ensemble is deterministic too. Averaging keeps an action inside
    the box [-1, 1] that every member's lies in.
    """

    def __init__(self, members: list[TensorDictModuleBase], action_key) -> None:
        super().__init__()
        if not members:
            raise ValueError("MeanAction: needs at least one member")
        self.members = nn.ModuleList(members)
        self.action_key = action_key
        self.in_keys = list(dict.fromkeys(k for m in members for k in m.in_keys))
        self.out_keys = [action_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = tensordict.select(*self.in_keys)
        actions = [m(inputs.copy())[self.action_key] for m in self.members]
        return tensordict.set(self.action_key, torch.stack(actions).mean(0))


class NoisyPolicy:
    """A policy with Gaussian exploration: ``clamp(action + noise_std * N(0, 1))``.

    Fills a replay buffer with a classical controller's experience, widened by noise so that
    the critic sees actions around the controller's too. Draws from torch's global generator
    (seeded by the run); with ``correlation`` > 0 each step's draw keeps that correlation with
    the last (:class:`~rlplat.agents.sac.CorrelatedNoise`), so that the noise moves the drone
    instead of averaging out.
    """

    def __init__(
        self,
        policy,
        noise_std: float,
        key: str | tuple[str, ...] = "action",
        correlation: float = 0.0,
    ) -> None:
        self.policy = policy
        self.noise_std = float(noise_std)
        self.key = key  # the env's action key
        self.noise = CorrelatedNoise(correlation)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td)
        action = td[self.key]
        return td.set(self.key, (action + self.noise_std * self.noise(action)).clamp(-1.0, 1.0))


# Trained networks flown as controllers ----------------------------------------------------

#: The defender network the package ships: ``nn`` defenders fly it unless the config names
#: another checkpoint (``env.defender_network``). Its evaluation is in ``defender_v1.json``.
SHIPPED_DEFENDER = "defender_v1.pt"


def shipped_path(name: str) -> Path:
    """Path of a controller file shipped in ``rlplat/agents/weights/``."""
    return Path(str(resources.files("rlplat.agents") / "weights" / name))


class NetworkController(nn.Module):
    """A trained actor's deterministic action as a function of what its drone sees.

    ``forward(view)`` builds the observation the network was trained on (the checkpoint's
    ``observation`` config) from a :class:`DroneView` and returns the action (N, action_dim) in
    [-1, 1]: the squashed mean of the actor's ``TanhNormal``, as ``ExplorationType.DETERMINISTIC``
    gives it, without tensordicts, so that it runs inside a compiled env step.

    Args:
        state: a loaded checkpoint (:func:`rlplat.agents.checkpoint.load_checkpoint`) of a run
            or an exported controller.
        role: the drone it must have been trained to fly.
        where: the config field named in errors.
    """

    def __init__(self, state: dict[str, Any], role: str, where: str) -> None:
        super().__init__()
        interface = saved_interface(state)
        learner = interface.get("drone.learner")
        if learner != role:
            raise ConfigError(f"{where}: the checkpoint flies the {learner}, not the {role}")
        team = interface["attackers"], interface["defenders"]
        if team != (1, 1):
            raise ConfigError(
                f"{where}: the network was trained with {team[0]} attackers and {team[1]} "
                "defenders; a scripted drone flies a 1-vs-1 network (it sees its nearest opponent)"
            )
        node = dict(state["config"]["observation"])
        name = node.pop("name")
        if name not in OBSERVATIONS:
            raise ConfigError(f"{where}: unknown observation '{name}' in the checkpoint")
        self.observation = OBSERVATIONS[name](**node)
        if self.observation.dim != state["net"]["obs_dim"]:
            raise ConfigError(
                f"{where}: observation '{name}' has {self.observation.dim} features, the "
                f"network takes {state['net']['obs_dim']}"
            )
        dim = state["net"]["action_dim"]
        actor = actor_from_state(state, Bounded(-1.0, 1.0, shape=(dim,)))
        self.body = actor.module[0].module[0]  # Scaled(MLP): observation -> (loc, raw scale)
        self.dim, self.margin = dim, float(state["net"].get("action_margin", 0.0))
        self.requires_grad_(False)

    def forward(self, view: DroneView) -> Tensor:
        loc = self.body(self.observation(view))[..., : self.dim]
        return ((1.0 + self.margin) * torch.tanh(loc)).clamp(-1.0, 1.0)


def load_controller(path: str | Path | None, role: str, where: str) -> NetworkController:
    """The controller in checkpoint ``path`` (None = the shipped one of ``role``)."""
    if path is None:
        if role != "defender":
            raise ConfigError(f"{where}: no controller is shipped for the {role}")
        path = shipped_path(SHIPPED_DEFENDER)
        if not path.is_file():
            raise ConfigError(f"{where}: the shipped defender network {path} is missing")
    try:
        state = load_checkpoint(path)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    return NetworkController(state, role, where)
