"""Scripted reference policies: what a learned controller must beat on the same scenarios.

Each is a TorchRL-style policy with the in/out keys of a learned actor: it reads an env output
(``positions``, ``waypoint``, ``caught``) and writes the env's action (``action``, or a team's
``("attacker", "action")``) in the action's [-1, 1] units (command / the learner's maximum speed
per axis). ``BASELINES`` names them for the evaluator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from rlplat.envs.controllers import follow_route, gather_drones, nearest, targets
from rlplat.envs.pursuit import ATTACKER, DEFENDER, ROLES, PursuitEnv
from rlplat.errors import ConfigError


def _nearest_opponent(env: PursuitEnv, td: TensorDictBase):
    """The learners' positions (N, K, 3), their maximum speeds (N, K, 1), and the index (N, K)
    of each one's nearest opponent in play (a defender not yet caught)."""
    p = td["positions"]
    own, others = p[:, env.team], p[:, env.opponents]
    allowed = targets(td["caught"]) if env.learner == ATTACKER else None
    speed = env.max_speed[:, env.team].unsqueeze(-1)
    return own, speed, nearest(own, others, allowed)


def _act(env: PursuitEnv, td: TensorDictBase, action: torch.Tensor) -> TensorDictBase:
    """Write the learners' actions (N, K, 3) where the env reads them."""
    return td.set(env.action_key, action if env.group is not None else action[:, 0])


class PurePursuitPolicy:
    """Fly each learner straight at its nearest opponent's current position (pure pursuit).

    A TorchRL-style policy for :func:`rlplat.eval.episodes.evaluate`: reads the env's
    ``positions`` (and ``caught``), writes the env's action, the command ``gain * (p_other -
    p_own)`` saturated at the learner's maximum speed per axis, expressed in the action's
    [-1, 1] units. An attacker team's drones each chase the defender in play nearest to them.

    Args:
        env: the env the policy flies in (its learners and per-drone maximum speeds).
        gain: 1/s, command per metre of separation; None takes the env's ``pursuit_gain``.
    """

    def __init__(self, env: PursuitEnv, gain: float | None = None) -> None:
        self.env = env
        self.gain = env.pursuit_gain if gain is None else float(gain)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        own, speed, near = _nearest_opponent(self.env, td)
        rel = gather_drones(td["positions"][:, self.env.opponents], near) - own
        return _act(self.env, td, (self.gain * rel / speed).clamp(-1.0, 1.0))


class ProportionalNavigationPolicy:
    """Proportional navigation with lead, in the velocity-command form a multirotor flies.

    PN turns the pursuer until the line of sight to the target stops rotating: a collision
    course, on which the pursuer flies at the point where the target will be. A drone that is
    commanded in velocity can fly that course directly: aim at the predicted intercept point
    ``p_other + lead * v_other * t_go`` and command ``gain * (aim - p_own)`` saturated at the
    maximum speed per axis, as pure pursuit does with the current position. ``t_go`` is the
    time the learner needs to close the largest per-axis gap at full speed while the target
    keeps its velocity (speed limits are per axis, so each axis closes on its own), capped at
    ``max_lead_time``; on an axis where the target is as fast as the learner the cap applies.
    The target (each learner's nearest opponent in play) and its velocity are read from the
    env's dynamics (a scripted controller sees the full state); with ``lead = 0`` this is pure
    pursuit.

    Args:
        env: the env the policy flies in.
        gain: 1/s, command per metre to the aim point; None takes the env's ``pursuit_gain``.
        lead: fraction of the predicted target motion to lead by (0 = pure pursuit).
        max_lead_time: s, longest prediction.
    """

    def __init__(
        self,
        env: PursuitEnv,
        *,
        gain: float | None = None,
        lead: float = 0.5,
        max_lead_time: float = 4.0,
    ) -> None:
        if not max_lead_time >= 0:
            raise ConfigError(f"max_lead_time: must be >= 0, got {max_lead_time}")
        self.env = env
        self.gain = env.pursuit_gain if gain is None else float(gain)
        self.lead, self.max_lead_time = float(lead), float(max_lead_time)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        own, speed, near = _nearest_opponent(self.env, td)
        others = self.env.opponents
        rel = gather_drones(td["positions"][:, others], near) - own
        v_other = gather_drones(self.env.dynamics.velocity[:, others], near)
        closing = speed - torch.sign(rel) * v_other  # per-axis closing speed at full throttle
        t_axis = torch.where(
            closing > 1e-6, rel.abs() / closing.clamp_min(1e-6), self.max_lead_time
        )
        t_go = t_axis.amax(-1, keepdim=True).clamp(max=self.max_lead_time)
        aim = rel + self.lead * v_other * t_go
        return _act(self.env, td, (self.gain * aim / speed).clamp(-1.0, 1.0))


class SetpointFollowerPolicy:
    """The defender's ``setpoints`` strategy as a policy: fly to the route's next setpoint.

    For a run whose learner is the defender: the command is the env's own route follower
    (``setpoint_gain`` per metre, saturated at the defender's maximum speed, hold once the route
    is flown), so this baseline is exactly what a scripted defender does.
    """

    def __init__(self, env: PursuitEnv) -> None:
        self.env = env

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        routes = self.env.routes
        last = routes.shape[1] - 1
        waypoint = td["waypoint"]  # (N, m)
        target = routes[self.env.route, waypoint.clamp(max=last)]
        speed = self.env.max_speed[:, self.env.team]
        position = td["positions"][:, self.env.team]
        cmd = follow_route(position, target, waypoint > last, speed, self.env.setpoint_gain)
        return _act(self.env, td, (cmd / speed.unsqueeze(-1)).clamp(-1.0, 1.0))


@dataclass(frozen=True)
class Baseline:
    """A scripted controller the evaluator can fly: how to build it, and which drone it flies."""

    make: Callable[[PursuitEnv], Callable[[TensorDictBase], TensorDictBase]]
    role: str


#: Classical controllers by name (``evaluate.py policy=<name>``).
BASELINES: dict[str, Baseline] = {
    "pure_pursuit": Baseline(PurePursuitPolicy, ROLES[ATTACKER]),
    "proportional_navigation": Baseline(ProportionalNavigationPolicy, ROLES[ATTACKER]),
    "setpoint_follower": Baseline(SetpointFollowerPolicy, ROLES[DEFENDER]),
}


def make_baseline(name: str, env: PursuitEnv):
    """The baseline ``name`` flying ``env``'s learner; a clear error for an unknown name or a
    baseline made for the other drone."""
    if name not in BASELINES:
        raise ConfigError(f"policy: unknown baseline '{name}'; valid: {', '.join(BASELINES)}")
    baseline, learner = BASELINES[name], ROLES[env.learner]
    if baseline.role != learner:
        valid = [k for k, b in BASELINES.items() if b.role == learner]
        raise ConfigError(
            f"policy: {name} flies the {baseline.role}, this run's learner is the {learner}; "
            f"valid: {', '.join(valid)}"
        )
    return baseline.make(env)


class NoisyPolicy:
    """A scripted policy with Gaussian exploration: ``clamp(action + noise_std * N(0, 1))``.

    Fills a replay buffer with a classical controller's experience, widened by noise so that
    the critic sees actions around the controller's too. Draws from torch's global generator
    (seeded by the run).
    """

    def __init__(self, policy, noise_std: float, key: str | tuple[str, ...] = "action") -> None:
        self.policy = policy
        self.noise_std = float(noise_std)
        self.key = key  # the env's action key

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td)
        action = td[self.key]
        noise = torch.randn(action.shape, device=action.device, dtype=action.dtype)
        return td.set(self.key, (action + self.noise_std * noise).clamp(-1.0, 1.0))
