"""The pursuit environment: an attacker and a defender drone, batched, in lock-step."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal, Protocol

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rlplat.envs.components import DroneView, Reward, RewardContext, inside_ellipsoid
from rlplat.envs.controllers import follow_route, pure_pursuit
from rlplat.errors import ConfigError
from rlplat.scenarios import STRATEGIES, ScenarioSet

ATTACKER, DEFENDER = 0, 1
NN = STRATEGIES.index("nn")
ROLES = ("attacker", "defender")
ORDERS = ("sequential", "shuffled", "random")


class Dynamics(Protocol):
    """What the env needs of a dynamics model (see :mod:`rlplat.envs.dynamics`)."""

    position: Tensor  # (N, D, 3)
    velocity: Tensor  # (N, D, 3)

    def reset(self, mask: Tensor, position: Tensor, velocity: Tensor, max_speed: Tensor): ...

    def advance(self, command: Tensor, period: float) -> None: ...


class ScenarioSampler:
    """Hands out scenario indices of a split to the envs that reset, in the configured order."""

    def __init__(self, n: int, order: str, device: torch.device) -> None:
        if order not in ORDERS:
            raise ConfigError(f"env.scenario_order: unknown order '{order}'; valid: {ORDERS}")
        self.n, self.order, self.device = n, order, device
        self.seed(0)

    def seed(self, seed: int) -> None:
        self.generator = torch.Generator().manual_seed(seed)
        self.queue = torch.empty(0, dtype=torch.int64)

    def next(self, k: int) -> Tensor:
        """Indices (k,) int64 of the next k scenarios."""
        if self.order == "random":
            idx = torch.randint(self.n, (k,), generator=self.generator)
        else:
            while len(self.queue) < k:  # sequential walks the split; shuffled, one perm per pass
                epoch = (
                    torch.arange(self.n)
                    if self.order == "sequential"
                    else torch.randperm(self.n, generator=self.generator)
                )
                self.queue = torch.cat([self.queue, epoch])
            idx, self.queue = self.queue[:k], self.queue[k:]
        return idx.to(self.device)


class PursuitEnv(EnvBase):
    """An attacker drone pursues a defender drone that flies a route.

    Every step commands the drone that does not learn (the defender flies its route with the
    scenario's strategy: ``setpoints``, straight from setpoint to setpoint, or ``nn``, the
    defender network; an attacker that does not learn flies pure pursuit), applies the
    learner's action to its own drone, advances the dynamics one control period and reports
    what happened.

    Observation:
        ``observation`` (N, obs.dim) from the observation component, seen from the learner.
        Also ``distance`` (N, 1) m, ``visible`` and ``captured`` (N, 1) bool, ``positions``
        (N, 2, 3) m (attacker, defender), ``waypoint`` (N, 1) the defender's next setpoint,
        ``scenario_index`` (N, 1) row of the split.
    Action:
        ``action`` (N, action.dim) in [-1, 1], mapped by the action component.
    Reward:
        ``reward`` (N, 1): the reward component's weighted sum of terms, and each weighted term
        ``("reward_terms", name)`` (N, 1), both entries of the reward spec.
    Episode end:
        terminated on capture (closest approach during the step <= capture_radius) or when a
        drone touches the ground (z <= ground_altitude), and, if ``terminate_out_of_view``, when
        the defender leaves the attacker's vision ellipsoid; truncated at ``time_limit`` or when
        the defender has flown its whole route. The observation of a done step is the true one.
    Config:
        ``env`` of ``conf/train.yaml``; the components come from the ``dynamics``,
        ``observation``, ``action`` and ``reward`` groups. ``compile_step`` runs the step's
        numerical work (:meth:`_advance_eager`: commands, physics, reward, flags, observation)
        as one ``torch.compile`` program for this batch size: with the ``velocity`` model about
        3x the steps/s of the eager env at N=1 and 2x at N=4096 on a 2-core CPU, after a few
        seconds of compiling (~1 min for ``quadrotor``, which it does not speed up). Input
        checks, resets and the tensordict plumbing stay eager. ``defender_network`` flies the
        defenders of ``nn`` scenarios when the attacker learns (the env factory loads
        ``env.defender_network``, by default the shipped ``defender_v1``).
    """

    def __init__(
        self,
        *,
        scenarios: ScenarioSet,
        dynamics: Dynamics,
        observation,
        action,
        reward: Reward,
        split: str = "train",
        learner: Literal["attacker", "defender"] = "attacker",
        control_period: float = 0.1,
        time_limit: float = 60.0,
        capture_radius: float = 1.2,
        ground_altitude: float = 0.0,
        vision_semi_axes: tuple[float, float, float] = (48.0, 42.0, 13.0),
        terminate_out_of_view: bool = False,
        scenario_order: Literal["sequential", "shuffled", "random"] = "sequential",
        setpoint_acceptance: float = 1.0,
        setpoint_gain: float = 1.0,
        pursuit_gain: float = 5.0,
        compile_step: bool = False,
        defender_network: Callable[[DroneView], Tensor] | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        num_envs = dynamics.position.shape[0]
        super().__init__(device=device, batch_size=[num_envs])
        if learner not in ROLES:
            raise ConfigError(f"drone.learner: unknown role '{learner}'; valid: {ROLES}")
        for name, v in (("control_period", control_period), ("time_limit", time_limit)):
            if not v > 0:
                raise ConfigError(f"env.{name}: must be > 0, got {v}")
        self.scenario_set, self.split_name = scenarios, split
        self.scenarios = scenarios.split(split).to(self.device)
        n_nn = int((self.scenarios["defender_strategy"] == NN).sum())
        if n_nn and learner == "attacker" and defender_network is None:
            raise ConfigError(
                f"scenario split '{split}': {n_nn} scenarios ask for defender_strategy 'nn' but "
                "no defender network is given (env.defender_network)"
            )
        # Maps the defender's view to its action in [-1, 1] (see rlplat.agents.controller);
        # only a scripted defender of an `nn` scenario flies it.
        self.defender_network = defender_network if n_nn and learner == "attacker" else None
        self.routes = scenarios.routes.to(self.device)
        self.dynamics = dynamics
        self.obs_fn, self.action_fn, self.reward_fn = observation, action, reward
        self.learner = ROLES.index(learner)
        self.control_period = float(control_period)
        self.max_steps = math.ceil(time_limit / control_period - 1e-9)
        self.capture_radius = float(capture_radius)
        self.ground_altitude = float(ground_altitude)
        self.semi_axes = torch.tensor(vision_semi_axes, dtype=torch.float32, device=self.device)
        self.terminate_out_of_view = bool(terminate_out_of_view)
        self.setpoint_acceptance = float(setpoint_acceptance)
        self.setpoint_gain, self.pursuit_gain = float(setpoint_gain), float(pursuit_gain)
        self.sampler = ScenarioSampler(len(self.scenarios), scenario_order, self.device)
        # One fused program per step instead of ~100 small kernels (static shapes: N is fixed).
        self._advance = self._advance_eager
        if compile_step:
            self._advance = torch.compile(self._advance_eager, dynamic=False)

        # Per-env episode state.
        z = dict(device=self.device, dtype=torch.int64)
        self.scenario_index = torch.zeros(num_envs, **z)
        self.route = torch.zeros(num_envs, **z)
        self.waypoint = torch.zeros(num_envs, **z)
        self.step_count = torch.zeros(num_envs, **z)
        self.nn_defender = torch.zeros(num_envs, dtype=torch.bool, device=self.device)
        self.max_speed = torch.ones(num_envs, 2, device=self.device)
        self._make_specs(num_envs)

    # Specs -------------------------------------------------------------------------------

    def _make_specs(self, n: int) -> None:
        def flag():
            return Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device)

        def real(*shape):
            return Unbounded(shape=(n, *shape), dtype=torch.float32, device=self.device)

        def index():
            return Unbounded(shape=(n, 1), dtype=torch.int64, device=self.device)

        self.observation_spec = Composite(
            observation=real(self.obs_fn.dim),
            distance=real(1),
            visible=flag(),
            captured=flag(),
            positions=real(2, 3),
            waypoint=index(),
            scenario_index=index(),
            shape=(n,),
            device=self.device,
        )
        self.action_spec = Bounded(
            -1.0, 1.0, shape=(n, self.action_fn.dim), dtype=torch.float32, device=self.device
        )
        # Each weighted reward term is a reward entry of its own, so that TorchRL transforms
        # (e.g. RewardSum) can sum it over an episode; ``reward`` is what the learner optimises.
        self.reward_spec = Composite(
            reward=real(1),
            reward_terms=Composite(
                {k: real(1) for k in self.reward_fn.weights}, shape=(n,), device=self.device
            ),
            shape=(n,),
            device=self.device,
        )
        self.done_spec = Composite(
            done=flag(), terminated=flag(), truncated=flag(), shape=(n,), device=self.device
        )

    # TorchRL hooks -----------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        self.sampler.seed(0 if seed is None else int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n = self.batch_size[0]
        mask = torch.ones(n, dtype=torch.bool, device=self.device)
        if tensordict is not None and "_reset" in tensordict:
            mask = tensordict["_reset"].reshape(n)
        k = int(mask.sum())
        if k:
            idx = self.sampler.next(k)
            sc = self.scenarios[idx]
            # New tensors, not in-place writes: earlier outputs keep their values.
            self.scenario_index = self.scenario_index.masked_scatter(mask, idx)
            self.route = self.route.masked_scatter(mask, sc["route"])
            self.waypoint = self.waypoint.masked_fill(mask, 0)
            self.step_count = self.step_count.masked_fill(mask, 0)
            self.nn_defender = self.nn_defender.masked_scatter(mask, sc["defender_strategy"] == NN)
            self.max_speed = self.max_speed.masked_scatter(
                mask.unsqueeze(-1),
                torch.stack([sc["attacker_max_speed"], sc["defender_max_speed"]], -1),
            )
            position = self.dynamics.position.clone()
            position[mask] = torch.stack([sc["attacker_start"], sc["defender_start"]], 1)
            self.dynamics.reset(mask, position, torch.zeros_like(position), self.max_speed.clone())
        p = self.dynamics.position
        rel = p[:, DEFENDER] - p[:, ATTACKER]
        visible = inside_ellipsoid(rel, self.semi_axes)
        flag = torch.zeros(n, 1, dtype=torch.bool, device=self.device)
        out = self._outputs(
            rel.norm(dim=-1),
            visible,
            torch.zeros_like(visible),
            done=flag,
            terminated=flag.clone(),
            truncated=flag.clone(),
        )
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict["action"]
        if action.shape != self.action_spec.shape:
            raise ValueError(
                f"action: shape {tuple(action.shape)}, expected {tuple(self.action_spec.shape)}"
            )
        if not torch.isfinite(action).all():
            raise ValueError("action: contains NaN or inf")
        return TensorDict(self._advance(action), batch_size=self.batch_size, device=self.device)

    def _advance_eager(self, action: Tensor) -> dict[str, Tensor | dict[str, Tensor]]:
        """One control period for every env: the step's whole numerical work on tensors.

        Reads and replaces the episode state and the dynamics' state; returns the entries of the
        step's output tensordict. ``env.compile_step`` wraps this method in ``torch.compile``.
        """
        # Command every drone: the opponent by its script, the learner by the policy.
        p = self.dynamics.position
        target, route_done = self._target()
        opponent = self._scripted_command(p, self.dynamics.velocity, target, route_done)
        own = self.action_fn(action, self.max_speed[:, self.learner])
        pair = (own, opponent) if self.learner == ATTACKER else (opponent, own)
        rel_before = p[:, DEFENDER] - p[:, ATTACKER]
        to_target = (target - p[:, DEFENDER]).norm(dim=-1)
        self.dynamics.advance(torch.stack(pair, 1), self.control_period)
        p = self.dynamics.position
        self.step_count = self.step_count + 1
        # The defender moves on once it is within the acceptance radius of its setpoint.
        to_target_after = (target - p[:, DEFENDER]).norm(dim=-1)
        reached = (to_target_after <= self.setpoint_acceptance) & ~route_done
        self.waypoint = self.waypoint + reached
        progress = (to_target - to_target_after).masked_fill(route_done, 0.0)

        rel = p[:, DEFENDER] - p[:, ATTACKER]
        distance, visible = rel.norm(dim=-1), inside_ellipsoid(rel, self.semi_axes)
        captured = _closest_approach(rel_before, rel) <= self.capture_radius
        grounded = (p[..., 2] <= self.ground_altitude).any(-1)
        total, terms = self.reward_fn(
            RewardContext(
                distance,
                visible,
                captured,
                grounded,
                self.reward_fn.distance_scale,
                route_progress=progress,
                setpoint_reached=reached,
            )
        )
        terminated = captured | grounded
        if self.terminate_out_of_view:
            terminated = terminated | ~visible
        truncated = (self.step_count >= self.max_steps) | (self.waypoint >= self.routes.shape[1])
        truncated = truncated & ~terminated
        return self._outputs(
            distance,
            visible,
            captured,
            reward=total.unsqueeze(-1),
            reward_terms={k: t.unsqueeze(-1) for k, t in terms.items()},
            terminated=terminated.unsqueeze(-1),
            truncated=truncated.unsqueeze(-1),
            done=(terminated | truncated).unsqueeze(-1),
        )

    # Helpers -----------------------------------------------------------------------------

    def _target(self) -> tuple[Tensor, Tensor]:
        """The defender's current setpoint (N, 3) and whether its route is done (N,)."""
        last = self.routes.shape[1] - 1
        return self.routes[self.route, self.waypoint.clamp(max=last)], self.waypoint > last

    def _scripted_command(self, p: Tensor, v: Tensor, target: Tensor, route_done: Tensor) -> Tensor:
        opponent = 1 - self.learner
        speed = self.max_speed[:, opponent]
        if opponent == ATTACKER:
            return pure_pursuit(p[:, ATTACKER], p[:, DEFENDER], speed, self.pursuit_gain)
        command = follow_route(p[:, DEFENDER], target, route_done, speed, self.setpoint_gain)
        if self.defender_network is None:
            return command
        view = DroneView(p[:, DEFENDER], v[:, DEFENDER], p[:, ATTACKER], v[:, ATTACKER], target)
        learned = self.action_fn(self.defender_network(view), speed)
        use = (self.nn_defender & ~route_done).unsqueeze(-1)
        return torch.where(use, learned, command)

    def _outputs(
        self,
        distance: Tensor,
        visible: Tensor,
        captured: Tensor,
        **extra: Tensor | dict[str, Tensor],
    ) -> dict[str, Tensor | dict[str, Tensor]]:
        """The output entries; every tensor in them is fresh (no alias of the env's state)."""
        p, v = self.dynamics.position, self.dynamics.velocity  # replaced on every advance/reset
        me, other = self.learner, 1 - self.learner
        view = DroneView(p[:, me], v[:, me], p[:, other], v[:, other], self._target()[0])
        return {
            "observation": self.obs_fn(view),
            "distance": distance.unsqueeze(-1),
            "visible": visible.unsqueeze(-1),
            "captured": captured.unsqueeze(-1),
            "positions": p,
            "waypoint": self.waypoint.unsqueeze(-1),
            "scenario_index": self.scenario_index.unsqueeze(-1),
            **extra,
        }


def _closest_approach(before: Tensor, after: Tensor) -> Tensor:
    """Least norm (N,) of the relative position moving linearly from ``before`` to ``after``."""
    delta = after - before
    t = (-(before * delta).sum(-1) / (delta * delta).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (before + t.unsqueeze(-1) * delta).norm(dim=-1)
