"""The pursuit environment: attacker and defender drones, batched, in lock-step."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any, Literal, NamedTuple, Protocol

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rlplat.envs.components import (
    OBSERVATIONS,
    DroneView,
    Reward,
    RewardContext,
    inside_ellipsoid,
)
from rlplat.envs.kinematics import (
    blocked_search,
    follow_route,
    gather_drones,
    nearest,
    pure_pursuit,
    route_meeting,
    route_times,
    setpoint_flight,
    targets,
)
from rlplat.errors import ConfigError
from rlplat.scenarios import STRATEGIES, ScenarioSet

log = logging.getLogger(__name__)

ATTACKER, DEFENDER = 0, 1  # role indices into ROLES (and the drones of a 1-vs-1 env)
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
    """Hands out scenario indices of a split to the envs that reset, in the configured order.

    ``share=(i, c)``: this sampler is the i-th of c that split one walk, each taking every c-th
    index of it from the i-th on (c single-env workers flying one split, as one batch of c
    envs would: with ``sequential``, worker i flies scenarios i, i + c, ...; with ``shuffled``,
    ``random`` or weights, every worker draws the whole walk from the same random state and
    keeps its share, so the c samplers must be seeded alike: ``set_seed(seed,
    static_seed=True)`` on a SerialEnv or ParallelEnv of them).

    :meth:`set_weights` replaces the order by draws in proportion to per-scenario weights.
    """

    def __init__(
        self, n: int, order: str, device: torch.device, share: tuple[int, int] = (0, 1)
    ) -> None:
        if order not in ORDERS:
            raise ConfigError(f"env.scenario_order: unknown order '{order}'; valid: {ORDERS}")
        index, count = share
        if not 0 <= index < count:
            raise ValueError(f"scenario_share: (index, count) with 0 <= index < count, got {share}")
        self.n, self.order, self.device = n, order, device
        self.index, self.count = int(index), int(count)
        self.weights: Tensor | None = None  # (n,) float64: scenario i drawn with weight i
        self.seed(0)

    def seed(self, seed: int) -> None:
        """Restart the walk from ``seed``, any integer (as a 64-bit word: torch's generators take
        no more, and Gymnasium hands any non-negative one)."""
        self.generator = torch.Generator().manual_seed(int(seed) % 2**64)
        self.queue = torch.empty(0, dtype=torch.int64)

    def set_weights(self, weights: Tensor | None) -> None:
        """Draw each scenario in proportion to ``weights`` (n,) >= 0 (None: the order again)."""
        if weights is not None:
            weights = torch.as_tensor(weights, dtype=torch.float64).cpu()
            if weights.shape != (self.n,) or not (weights >= 0).all() or weights.sum() <= 0:
                raise ValueError(f"scenario weights: ({self.n},) >= 0, not all 0; got {weights}")
        self.weights = weights

    def get_state(self) -> Tensor:
        """The walk's random state (what a checkpoint keeps)."""
        return self.generator.get_state()

    def set_state(self, state: Tensor) -> None:
        """Restore :meth:`get_state`; a (c, L) stack of the c shares' states sets row i."""
        self.generator.set_state(state[self.index] if state.dim() == 2 else state)

    def next(self, k: int) -> Tensor:
        """Indices (k,) int64 of the next k scenarios."""
        need = k * self.count  # the walk's next indices for all c shares: this one keeps its own
        if self.weights is not None:
            idx = torch.multinomial(self.weights, need, replacement=True, generator=self.generator)
            idx = idx[self.index :: self.count]
        elif self.order == "random":
            idx = torch.randint(self.n, (need,), generator=self.generator)[self.index :: self.count]
        else:
            while len(self.queue) < need:  # sequential walks the split; shuffled, one perm per pass
                epoch = (
                    torch.arange(self.n)
                    if self.order == "sequential"
                    else torch.randperm(self.n, generator=self.generator)
                )
                self.queue = torch.cat([self.queue, epoch])
            idx, self.queue = self.queue[:need][self.index :: self.count], self.queue[need:]
        return idx.to(self.device)


class _Sight(NamedTuple):
    """What the drones see of each other after a step or a reset."""

    team_distance: Tensor  # (N, K) m, each learner to its nearest opponent (for an attacker,
    #                        the nearest defender in play)
    team_visible: Tensor  # (N, K) bool, the learner sees (attacker) or is seen (defender)
    distance: Tensor  # (N,) m, the least distance of a pair in play
    visible: Tensor  # (N,) bool, some pair in play in view


#: Reward terms that only a defender earns (its route), by name.
DEFENDER_TERMS = ("route_progress", "setpoint_reached")


def reward_role_problem(weights: Mapping[str, float], learner: str) -> str | None:
    """What makes a reward one of the other side, in one line naming the term, or None: it
    pays a defender for being caught (``capture`` > 0), charges an attacker for catching
    (< 0), or pays an attacker for the defender's route. Training refuses it
    (``validate_train_config``); an env built to fly policies only warns."""
    capture = float(weights.get("capture", 0.0))
    if learner == "defender" and capture > 0:
        return (f"reward.terms.capture: {capture:g} pays the defender for being caught; a "
                "defender's reward charges it (< 0, e.g. reward=evasion)")  # fmt: skip
    if learner == "attacker" and capture < 0:
        return (f"reward.terms.capture: {capture:g} charges the attacker for catching; an "
                "attacker's reward pays it (> 0, e.g. reward=shaped)")  # fmt: skip
    if learner == "attacker":
        for term in DEFENDER_TERMS:
            if weights.get(term, 0.0):
                return (f"reward.terms.{term}: is the defender's route, this run's learner is "
                        "the attacker (e.g. reward=shaped)")  # fmt: skip
    return None


class PursuitEnv(EnvBase):
    """Attacker drones pursue defender drones that fly routes (1 vs 1 unless the scenarios say
    otherwise).

    Every step commands the drones that do not learn (a defender flies its route with its
    scenario's strategy: ``setpoints``, straight from setpoint to setpoint, or ``nn``, the
    defender network; an attacker that does not learn flies pure pursuit of the nearest defender
    in play), applies the learners' actions to their drones, advances the dynamics one control
    period and reports what happened.

    Drones: the scenarios' k attackers, then their m defenders (``positions`` in that order).
    The drones of the learner's role share one policy. A lone learner reads and writes root
    keys; a team of K > 1 follows TorchRL's multi-agent layout: its entries sit under the group
    key of its role (``"attacker"`` or ``"defender"``) with an agent dimension, and the done
    flags stay at the root (the whole env ends at once).

    Observation:
        ``observation`` (N, obs.dim), or ``(group, "observation")`` (N, K, obs.dim) for a
        team, from the observation component: the drone's own features, then each opponent's
        and each team-mate's. A team also gets ``(group, "distance")`` (N, K, 1), each drone's
        distance to its nearest opponent (an attacker's: the nearest defender in play), and a
        defender team ``("defender", "caught")`` (N, K, 1), an attacker team
        ``("attacker", "down")`` (N, K, 1), each drone out of play. Also ``distance`` (N, 1) m,
        the least attacker-defender distance among the defenders in play (and the attackers
        flying), ``visible`` (N, 1) bool (a defender in play inside some flying attacker's
        vision ellipsoid), ``captured`` (N, 1) bool (every defender caught), ``caught`` (N, m)
        bool per defender, ``positions`` and ``velocities`` (N, k + m, 3) m and m/s,
        ``max_speed`` (N, k + m) m/s per axis,
        ``waypoint`` (N, m) the index of each defender's next setpoint, ``setpoints`` (N, m, 3)
        m its position (the last one once the route is flown), ``route_done`` (N, m) bool the
        whole route flown, ``scenario_index`` (N, 1) row of the split; with dynamics that
        report contacts (AirSim's), ``collided`` (N, k + m) bool, during the last step. The
        drone-indexed entries are all the scripted policies read
        (:mod:`rlplat.agents.policies`).
    Action:
        ``action`` (N, action.dim), or ``(group, "action")`` (N, K, action.dim), in [-1, 1],
        mapped by the action component.
    Reward:
        per learning drone, the reward component's weighted sum of terms: ``reward`` (N, 1) and
        each weighted term ``("reward_terms", name)`` (N, 1) for a lone learner. A team gets
        ``(group, "reward")`` (N, K, 1), and the root ``reward`` and ``reward_terms`` are the
        team's means (what returns and episode metrics report). A defender earns nothing after
        the step it is caught in, an attacker nothing after the step it lands in.
    Episode end:
        a defender is caught when some attacker's closest approach to it during a step is <=
        capture_radius; a caught defender stops, hovers where it was caught and is out of play
        (no attacker targets, measures or catches it again). An attacker that touches the ground
        (z <= ground_altitude) is down: it is commanded to hold, catches nothing, earns nothing
        after that step and is out of play (no defender flees from it, it sees nothing), while
        its team-mates fly on. Terminated when every defender is caught, when a defender
        touches the ground or every attacker is down and, if ``terminate_out_of_view``, when no
        defender in play is inside any flying attacker's vision ellipsoid; truncated at
        ``time_limit`` or when every defender in play has flown its whole route. With m = 1
        the first capture ends the episode. The observation of a done step is the true one.
    Config:
        ``env`` of ``conf/train.yaml``; the drone counts come from the scenarios
        (``scenario.attackers``, ``scenario.defenders``); the components from the ``dynamics``,
        ``observation``, ``action`` and ``reward`` groups. ``compile_step`` runs the step's
        numerical work (:meth:`_advance_eager`: commands, physics, reward, flags, observation)
        as one ``torch.compile`` program for this batch size: with the ``velocity`` model about
        3x the steps/s of the eager env at N=1 and 2x at N=4096 on a 2-core CPU, after a few
        seconds of compiling (~1 min for ``quadrotor``, which it does not speed up). Input
        checks, resets and the tensordict plumbing stay eager. ``defender_network`` flies the
        defenders of ``nn`` scenarios when the attacker learns (the env factory loads
        ``env.defender_network``, by default the shipped ``defender_v1``); a network defender
        sees its nearest attacker, as in the 1-vs-1 setting it was trained in. ``attackers``
        flies only the first this many attackers of each scenario (None: all of them), e.g. to
        measure a 1-vs-1 policy on the defenders of a 2-vs-1 set. ``scenario_share=(i, c)``
        makes this env the i-th of c single-env workers that split the split's walk (see
        :class:`ScenarioSampler`; set by the factory of a parallel env, not a config key).
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
        attackers: int | None = None,
        scenario_share: tuple[int, int] = (0, 1),
        device: torch.device | str = "cpu",
    ) -> None:
        num_envs = dynamics.position.shape[0]
        super().__init__(device=device, batch_size=[num_envs])
        if learner not in ROLES:
            raise ConfigError(f"drone.learner: unknown role '{learner}'; valid: {ROLES}")
        for name, v in (("control_period", control_period), ("time_limit", time_limit)):
            if not v > 0:
                raise ConfigError(f"env.{name}: must be > 0, got {v}")
        k, m = flown_attackers(attackers, scenarios), scenarios.defenders
        if dynamics.position.shape[1] != k + m:
            raise ValueError(
                f"dynamics: {dynamics.position.shape[1]} drones, the scenarios have {k + m}"
            )
        self.scenario_set, self.split_name = scenarios, split
        self.scenarios = scenarios.split(split).to(self.device)
        if k < scenarios.attackers:  # fly the first k attackers of each scenario
            cut = {
                key: self.scenarios[key][:, :k] for key in ("attacker_start", "attacker_max_speed")
            }
            self.scenarios = self.scenarios.clone(False).update(cut)
        n_nn = int((self.scenarios["defender_strategy"] == NN).any(-1).sum())
        if n_nn and learner == "attacker" and defender_network is None:
            raise ConfigError(
                f"scenario split '{split}': {n_nn} scenarios ask for defender_strategy 'nn' but "
                "no defender network is given (env.defender_network)"
            )
        # Maps a defender's view to its action in [-1, 1] (an injected callable, e.g.
        # rlplat.agents.policies.NetworkController); only a scripted `nn` defender flies it.
        self.defender_network = defender_network if n_nn and learner == "attacker" else None
        self.routes = scenarios.routes.to(self.device)
        self._guided = bool(getattr(action, "guided", False))
        if self._guided and learner != "attacker":
            raise ConfigError("action: a guided action flies attackers; this run's learner is "
                              f"the {learner} (valid: velocity)")  # fmt: skip
        self._conforms = bool(getattr(observation, "reads_conformity", False))
        if (self._conforms or getattr(observation, "reads_intercept", False)) and (
            learner != "attacker"
        ):  # the route's meeting point or conformity; an action that reads it is guided
            shown = next((k for k, c in OBSERVATIONS.items() if type(observation) is c),
                         type(observation).__name__)  # fmt: skip
            raise ConfigError(f"observation: {shown} reads the defender's route as an attacker "
                              f"sees it; this run's learner is the {learner}")  # fmt: skip
        # A correction gated on the route deviation reads the one its policy saw.
        self._gated = bool(getattr(action, "gated", False))
        if self._gated and not getattr(observation, "reads_conformity", False):
            shown = next((k for k, c in OBSERVATIONS.items() if type(observation) is c),
                         type(observation).__name__)  # fmt: skip
            raise ConfigError("action.gate_high: the gate reads the route deviation that "
                              "observation=pursuit_conform reports; this run's observation is "
                              f"{shown}")  # fmt: skip
        self._meets = bool(getattr(action, "reads_route", False))  # the guidance's meeting point
        meets = self._meets or getattr(observation, "reads_intercept", False)
        if self._conforms:  # a setpoints defender's mean acceleration per m/s of velocity
            # error over one control period: its velocity follows its command with these lags
            lag = torch.tensor(observation.route_lag, device=self.device)
            self._route_rate = -torch.expm1(-control_period / lag) / control_period
            # the deviation's step towards each new residual size (time constant conformity_time)
            self._conform_blend = -math.expm1(-control_period / observation.conformity_time)
        problem = reward_role_problem(getattr(reward, "weights", {}), learner)
        if problem is not None:
            log.warning("%s", problem)
        self.dynamics = dynamics
        # A simulator that reports contacts (AirSim): its flags go out with every state.
        self._reports_collisions = isinstance(getattr(dynamics, "collided", None), Tensor)
        self.obs_fn, self.action_fn, self.reward_fn = observation, action, reward
        # Drones: attackers first, then defenders; the learner's role is its team.
        self.learner = ROLES.index(learner)
        self.num_attackers, self.num_defenders = k, m
        self.attackers, self.defenders = slice(0, k), slice(k, k + m)
        self.team, self.opponents = (
            (self.attackers, self.defenders)
            if self.learner == ATTACKER
            else (self.defenders, self.attackers)
        )
        self.team_size = k if self.learner == ATTACKER else m
        self.group = learner if self.team_size > 1 else None
        t = self.team_size
        mates = [[j for j in range(t) if j != i] for i in range(t)]
        self._mate_index = torch.tensor(mates, dtype=torch.int64, device=self.device).view(t, -1)
        self.control_period = float(control_period)
        self.max_steps = math.ceil(time_limit / control_period - 1e-9)
        self.capture_radius = float(capture_radius)
        self._meeting: tuple[Tensor, Tensor, Tensor] | None = None  # set by every output
        self._deviation_seen: Tensor | None = None  # each attacker's, set by every output
        self.ground_altitude = float(ground_altitude)
        self.semi_axes = torch.tensor(vision_semi_axes, dtype=torch.float32, device=self.device)
        self.terminate_out_of_view = bool(terminate_out_of_view)
        self.setpoint_acceptance = float(setpoint_acceptance)
        self.setpoint_gain, self.pursuit_gain = float(setpoint_gain), float(pursuit_gain)
        #: How :meth:`meeting` expects a route-flying defender to fly, the attacker's start-up
        #: lag it allows for (s, the route law's ``start_lag``), how far ahead it looks (s,
        #: ``meeting_horizon``: the law's ``horizon``, ``law_horizon``, or the time limit), and
        #: whether every step computes the meeting point (the action or the observation reads it).
        self.route_flight = setpoint_flight(self.setpoint_gain, self.setpoint_acceptance)
        self.meeting_lag = float(getattr(action, "start_lag", 0.0))
        self.law_horizon = getattr(action, "horizon", None)  # its setting; None: the limit
        limit = self.max_steps * self.control_period
        self.meeting_horizon = limit if self.law_horizon is None else self.law_horizon
        self._route_times = route_times(self.meeting_horizon, self.device)
        self.computes_meeting = meets
        self.sampler = ScenarioSampler(
            len(self.scenarios), scenario_order, self.device, scenario_share
        )
        self.compile_step = compile_step
        self._advance = self._stepper()

        # Per-env episode state.
        z = dict(device=self.device, dtype=torch.int64)
        self.scenario_index = torch.zeros(num_envs, **z)
        self.step_count = torch.zeros(num_envs, **z)
        self.route = torch.zeros(num_envs, m, **z)
        self.waypoint = torch.zeros(num_envs, m, **z)
        self.nn_defender = torch.zeros(num_envs, m, dtype=torch.bool, device=self.device)
        self.caught = torch.zeros(num_envs, m, dtype=torch.bool, device=self.device)
        self.down = torch.zeros(num_envs, k, dtype=torch.bool, device=self.device)  # attackers
        self.max_speed = torch.ones(num_envs, k + m, device=self.device)
        # Each drone's mean acceleration over the last control period (m/s^2).
        self.acceleration = torch.zeros(num_envs, k + m, 3, device=self.device)
        # How each defender departs from its route (pursuit_conform): the residual of its last
        # acceleration (m/s^2) and that residual's size averaged over conformity_time.
        self.route_residual = torch.zeros(num_envs, m, 3, device=self.device)
        self.route_deviation = torch.zeros(num_envs, m, device=self.device)
        # Whether each env's episode has ended (done) since its reset: an env stepped on past
        # its end (as an evaluation's waves do) skips the meeting point's search, where the
        # search is blocked (eager, on the CPU: kinematics.blocked_search).
        self.ended = torch.zeros(num_envs, dtype=torch.bool, device=self.device)
        self._make_specs(num_envs)

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the env and its dynamics' connection, if it has one (``dynamics=airsim``)."""
        close = getattr(self.dynamics, "close", None)
        if close is not None:
            close()
        super().close(raise_if_closed=raise_if_closed)

    @property
    def drone_action_spec(self) -> Bounded:
        """One drone's action spec, (action.dim,): the bounds of a policy network's output."""
        spec = self.full_action_spec[self.action_key]
        return spec[(0,) * (spec.ndim - 1)]

    # Specs -------------------------------------------------------------------------------

    def _make_specs(self, n: int) -> None:
        t, m = self.team_size, self.num_defenders

        def flag(*shape):
            return Categorical(2, shape=(n, *shape), dtype=torch.bool, device=self.device)

        def real(*shape):
            return Unbounded(shape=(n, *shape), dtype=torch.float32, device=self.device)

        def index(*shape):
            return Unbounded(shape=(n, *shape), dtype=torch.int64, device=self.device)

        def team(**specs):  # a lone learner's entries at the root, a team's under its group
            if self.group is None:
                return {k: s[:, 0] for k, s in specs.items()}
            return {self.group: Composite(specs, shape=(n, t), device=self.device)}

        team_obs = {"observation": real(t, self.obs_fn.dim)}
        if self.group is not None:
            team_obs["distance"] = real(t, 1)
        if self.group is not None:  # which of the team's drones are out: caught, or down
            team_obs["caught" if self.learner == DEFENDER else "down"] = flag(t, 1)
        self.observation_spec = Composite(
            **team(**team_obs),
            distance=real(1),
            visible=flag(1),
            captured=flag(1),
            caught=flag(m),
            positions=real(self.num_attackers + m, 3),
            velocities=real(self.num_attackers + m, 3),
            accelerations=real(self.num_attackers + m, 3),
            max_speed=real(self.num_attackers + m),
            waypoint=index(m),
            setpoints=real(m, 3),
            route_done=flag(m),
            scenario_index=index(1),
            shape=(n,),
            device=self.device,
        )
        if self._reports_collisions:  # per drone, in the order of positions
            self.observation_spec["collided"] = flag(self.num_attackers + m)
        action = Bounded(
            -1.0, 1.0, shape=(n, t, self.action_fn.dim), dtype=torch.float32, device=self.device
        )
        self.full_action_spec = Composite(team(action=action), shape=(n,), device=self.device)
        # Each weighted reward term is a reward entry of its own, so that TorchRL transforms
        # (e.g. RewardSum) can sum it over an episode; ``reward`` is what the learner optimises
        # (a team optimises its per-drone rewards; the root holds their mean).
        terms = Composite(
            {k: real(1) for k in self.reward_fn.weights}, shape=(n,), device=self.device
        )
        per_drone = team(reward=real(t, 1)) if self.group is not None else {}
        self.full_reward_spec = Composite(
            reward=real(1), reward_terms=terms, **per_drone, shape=(n,), device=self.device
        )
        self.done_spec = Composite(
            done=flag(1), terminated=flag(1), truncated=flag(1), shape=(n,), device=self.device
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
            rows = mask.unsqueeze(-1)  # per-drone state: the masked rows, in drone order
            self.scenario_index = self.scenario_index.masked_scatter(mask, idx)
            self.step_count = self.step_count.masked_fill(mask, 0)
            self.route = self.route.masked_scatter(rows, sc["route"])
            self.waypoint = self.waypoint.masked_fill(rows, 0)
            self.caught = self.caught.masked_fill(rows, False)
            self.down = self.down.masked_fill(rows, False)
            self.nn_defender = self.nn_defender.masked_scatter(rows, sc["defender_strategy"] == NN)
            self.max_speed = self.max_speed.masked_scatter(
                rows, torch.cat([sc["attacker_max_speed"], sc["defender_max_speed"]], -1)
            )
            position = self.dynamics.position.clone()
            position[mask] = torch.cat([sc["attacker_start"], sc["defender_start"]], 1)
            self.dynamics.reset(mask, position, torch.zeros_like(position), self.max_speed.clone())
            self.acceleration = self.acceleration.masked_fill(mask.view(n, 1, 1), 0.0)
            self.route_residual = self.route_residual.masked_fill(mask.view(n, 1, 1), 0.0)
            self.route_deviation = self.route_deviation.masked_fill(rows, 0.0)
            self.ended = self.ended.masked_fill(mask, False)
        sight = self._sight(self._relative(self.dynamics.position))
        flag = torch.zeros(n, 1, dtype=torch.bool, device=self.device)
        out = self._outputs(  # an env left ended keeps its meeting point
            sight, flag, running=~self.ended, done=flag.clone(), terminated=flag.clone(),
            truncated=flag.clone(),
        )  # fmt: skip
        return self._tensordict(out)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict[self.action_key]
        expected = self.full_action_spec[self.action_key].shape
        if action.shape != expected:
            raise ValueError(f"action: shape {tuple(action.shape)}, expected {tuple(expected)}")
        if not torch.isfinite(action).all():
            raise ValueError("action: contains NaN or inf")
        return self._tensordict(self._advance(action))

    def _tensordict(self, out: dict) -> TensorDictBase:
        """The output entries as a tensordict; a team's group has the agent dimension.

        Built without per-entry checks when the dynamics' state is on the env's device (the
        entries are then this env's own tensors, of its batch size, on its device), as
        TorchRL's own env wrappers build their outputs.
        """
        if self.dynamics.position.device == self.device:
            td = TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)
        else:
            td = TensorDict(out, batch_size=self.batch_size, device=self.device)
        if self.group is not None:
            td.get(self.group).batch_size = (*self.batch_size, self.team_size)
        return td

    def _stepper(self) -> Callable[[Tensor], dict[str, Tensor | dict[str, Tensor]]]:
        """The step's numerical work: :meth:`_advance_eager`, or with ``compile_step`` one
        fused program per step instead of ~100 small kernels (static shapes: N is fixed)."""
        if self.compile_step:
            return torch.compile(self._advance_eager, dynamic=False)
        return self._advance_eager

    def __getstate__(self) -> dict[str, Any]:
        # A compiled step is bound to the env it was made for: a copy (deepcopy, pickle,
        # a worker process) makes its own, or it would step the original's state.
        state = super().__getstate__()
        state.pop("_advance", None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        super().__setstate__(state)
        self._advance = self._stepper()

    def _advance_eager(self, action: Tensor) -> dict[str, Tensor | dict[str, Tensor]]:
        """One control period for every env: the step's whole numerical work on tensors.

        Reads and replaces the episode state and the dynamics' state; returns the entries of the
        step's output tensordict. ``env.compile_step`` wraps this method in ``torch.compile``.
        """
        n, t = self.batch_size[0], self.team_size
        running = ~self.ended  # the envs whose episode goes on
        down = self.down  # the attackers on the ground before this step: out of play
        # Command every drone: the other role by its script, the learners by the policy.
        p, v = self.dynamics.position, self.dynamics.velocity
        target, route_done = self._target()
        guidance = self.guidance(p, v, self.acceleration, self._meeting) if self._guided else None
        gate = {"deviation": self._deviation_seen} if self._gated else {}
        if self._gated and self.action_fn.gate_unreachable:  # the observed state's point
            gate["reachable"] = self._meeting[2]
        own = self.action_fn(action.reshape(n, t, -1), self.max_speed[:, self.team], guidance,
                             **gate)  # fmt: skip
        if self.learner == ATTACKER:
            attack, defend = own, self._defender_command(p, v, target, route_done)
        else:
            attack, defend = self._attacker_command(p), own
        caught, in_play = self.caught, ~self.caught
        defend = defend.masked_fill(caught.unsqueeze(-1), 0.0)  # a caught defender holds
        attack = attack.masked_fill(down.unsqueeze(-1), 0.0)  # and so does a downed attacker
        rel_before = self._relative(p)
        to_target = (target - p[:, self.defenders]).norm(dim=-1)
        if self._conforms:  # what a defender flying its route would do in this state
            speed = self.max_speed[:, self.defenders]
            follow = follow_route(p[:, self.defenders], target, route_done, speed,
                                  self.setpoint_gain)  # fmt: skip
            expected = (follow - v[:, self.defenders]) * self._route_rate
        self.dynamics.advance(torch.cat([attack, defend], 1), self.control_period)
        p = self.dynamics.position
        self.acceleration = (self.dynamics.velocity - v) / self.control_period
        if self._conforms:
            self._conform(expected, caught)
        self.step_count = self.step_count + 1
        # A defender moves on once it is within the acceptance radius of its setpoint.
        to_target_after = (target - p[:, self.defenders]).norm(dim=-1)
        reached = (to_target_after <= self.setpoint_acceptance) & ~route_done & in_play
        self.waypoint = self.waypoint + reached
        progress = (to_target - to_target_after).masked_fill(route_done | caught, 0.0)

        # Captures: any attacker's closest approach to a defender in play, during the step.
        rel = self._relative(p)
        hit = _closest_approach(rel_before, rel) <= self.capture_radius  # (N, k, m)
        hit = hit & ~down.unsqueeze(-1)  # a downed attacker catches nothing
        newly = (hit & in_play.unsqueeze(1)).any(1)  # (N, m)
        self.caught = self.caught | newly
        # Crashes: an attacker on the ground is down for the rest of the episode; the episode
        # ends on a defender's crash or once every attacker is down.
        low = p[..., 2] <= self.ground_altitude
        fell = low[:, self.attackers] & ~down
        self.down = down | low[:, self.attackers]
        crashed = low[:, self.defenders].any(-1) | self.down.all(-1)
        sight = self._sight(rel)
        # The crash term: an attacker's own fall, and for every learner a crash that ends it.
        grounded = crashed.unsqueeze(-1).expand(n, t)
        if self.learner == ATTACKER:
            grounded = grounded | fell
        captured = newly
        if self.learner == ATTACKER:  # a capture is the team's; route terms read the defenders'
            if self.num_defenders > 1:
                captured = newly.any(-1, keepdim=True)
                progress, reached = progress.sum(-1, keepdim=True), reached.any(-1, keepdim=True)
            captured, progress, reached = (x.expand(n, t) for x in (captured, progress, reached))
        total, terms = self.reward_fn(
            RewardContext(
                sight.team_distance,
                sight.team_visible,
                captured,
                grounded,
                self.reward_fn.distance_scale,
                route_progress=progress,
                setpoint_reached=reached,
                action=action.reshape(n, t, -1),
            )
        )
        # A defender caught, or an attacker down, before this step is out: no reward.
        out = caught if self.learner != ATTACKER else down
        total = total.masked_fill(out, 0.0)
        terms = {k: x.masked_fill(out, 0.0) for k, x in terms.items()}
        all_caught = self.caught.all(-1)
        terminated = all_caught | crashed
        if self.terminate_out_of_view:
            terminated = terminated | ~sight.visible
        flown = (self.waypoint >= self.routes.shape[1]) | self.caught
        truncated = (self.step_count >= self.max_steps) | flown.all(-1)
        truncated = truncated & ~terminated

        def team_mean(x: Tensor) -> Tensor:  # (N, K) -> (N, 1)
            return x if t == 1 else x.mean(-1, keepdim=True)

        rewards = {"reward": team_mean(total)}
        rewards["reward_terms"] = {k: team_mean(x) for k, x in terms.items()}
        self.ended = self.ended | terminated | truncated
        return self._outputs(
            sight,
            all_caught.unsqueeze(-1),
            running=running,
            team_reward=total.unsqueeze(-1),
            terminated=terminated.unsqueeze(-1),
            truncated=truncated.unsqueeze(-1),
            done=(terminated | truncated).unsqueeze(-1),
            **rewards,
        )

    # Helpers -----------------------------------------------------------------------------

    def _conform(self, expected: Tensor, caught: Tensor) -> None:
        """Update each defender's route conformity from the acceleration ``expected`` (N, m, 3)
        m/s^2 of a ``setpoints`` defender in the state before this step; a caught defender's
        is zero."""
        residual = self.acceleration[:, self.defenders] - expected
        residual = residual.masked_fill(caught.unsqueeze(-1), 0.0)
        self.route_residual = residual
        self.route_deviation = torch.lerp(
            self.route_deviation, residual.norm(dim=-1), self._conform_blend
        )

    def _target(self) -> tuple[Tensor, Tensor]:
        """Each defender's current setpoint (N, m, 3) and whether its route is done (N, m)."""
        return self._setpoint(0), self.waypoint >= self.routes.shape[1]

    def _setpoint(self, ahead: int) -> Tensor:
        """Each defender's setpoint ``ahead`` after its current one (N, m, 3); the route's last
        one beyond its end."""
        last = self.routes.shape[1] - 1
        return self.routes[self.route, (self.waypoint + ahead).clamp(max=last)]

    def law_action(self) -> Tensor:
        """The guided action's law in the current state, (N, k, 3): what the next step adds
        the learner's correction to (a script flown through the action inverts it)."""
        if not self._guided:
            raise ValueError(f"action {self.action_fn.name}: corrects no law")
        p, v = self.dynamics.position, self.dynamics.velocity
        return self.guidance(p, v, self.acceleration, self._meeting)

    def guidance(
        self,
        p: Tensor,
        v: Tensor,
        a: Tensor | None = None,
        meeting: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> Tensor:
        """A guided action's guidance for each attacker (N, k, 3): proportional navigation
        towards its nearest defender in play, from positions p, velocities v and accelerations
        a (N, k + m, 3; None: not known, the law leads on velocity only). An action that reads
        the route gets :meth:`meeting` of p (``meeting``: already computed for this state)."""
        own, defenders = p[:, self.attackers], p[:, self.defenders]
        a_other = None
        if self.num_defenders == 1:  # every attacker's nearest: the one defender
            rel, v_other = defenders - own, v[:, self.defenders].expand_as(own)
            if a is not None:
                a_other = a[:, self.defenders].expand_as(own)
        else:
            near = nearest(own, defenders, targets(self.caught))
            rel = gather_drones(defenders, near) - own
            v_other = gather_drones(v[:, self.defenders], near)
            if a is not None:
                a_other = gather_drones(a[:, self.defenders], near)
        speed = self.max_speed[:, self.attackers]
        if not self._meets:
            return self.action_fn.guidance(rel, v_other, speed, a_other)
        aim, due, reachable = self.meeting(p, v) if meeting is None else meeting
        meeting = (aim - own, due, reachable)
        return self.action_fn.guidance(rel, v_other, speed, a_other, meeting=meeting)

    def meeting(
        self, p: Tensor, v: Tensor, running: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Where each attacker can meet its nearest defender in play on that defender's route,
        from positions p and velocities v (N, k + m, 3): the point (N, k, 3) m, when the
        defender is there (N, k) s and whether the attacker can be there by then (N, k) bool
        (:func:`rlplat.envs.kinematics.route_intercept`, the route flown as a ``setpoints``
        defender flies it, with this env's setpoint gain and acceptance radius, and the
        attacker's start-up lag ``meeting_lag``).

        With ``running`` (N,) bool, only those envs' are searched; the others keep the last
        computed (an eager CPU step's saving for envs stepped on past their episode's end,
        :func:`~rlplat.envs.kinematics.blocked_search`).
        """
        last = self._meeting
        if running is None or last is None or not blocked_search(p.device) or running.all():
            return self._meet(p, v, slice(None))
        if not running.any():
            return last
        rows = running.nonzero().squeeze(-1)
        found = self._meet(p, v, rows)
        return tuple(x.index_put((rows,), y) for x, y in zip(last, found, strict=True))  # type: ignore[return-value]

    def _meet(self, p: Tensor, v: Tensor, rows: Tensor | slice) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`meeting` of the envs ``rows``."""
        own, defenders = p[rows, self.attackers], p[rows, self.defenders]
        speed, caught = self.max_speed[rows], self.caught[rows]
        near = nearest(own, defenders, targets(caught))
        return route_meeting(
            own, speed[:, self.attackers], defenders, v[rows, self.defenders],
            speed[:, self.defenders], self.routes[self.route[rows]], self.waypoint[rows], near,
            times=self._route_times, reach=self.capture_radius,
            flight=self.route_flight, lag=self.meeting_lag,
        )  # fmt: skip

    def _relative(self, p: Tensor) -> Tensor:
        """Defender minus attacker position for every pair: (N, k, m, 3)."""
        return p[:, self.defenders].unsqueeze(1) - p[:, self.attackers].unsqueeze(2)

    def _sight(self, rel: Tensor) -> _Sight:
        """Distances and visibility of the pairs ``rel`` (N, k, m, 3), among the defenders in
        play (all of them once every one is caught) and the attackers flying (all of them once
        every one is down); each attacker's own entries are its own, down or not."""
        distance, visible = rel.norm(dim=-1), inside_ellipsoid(rel, self.semi_axes)
        far, seen = distance, visible
        if self.num_defenders > 1:  # a lone defender is in play until the episode ends
            chased = targets(self.caught).unsqueeze(1)
            far, seen = far.masked_fill(~chased, float("inf")), seen & chased
        own = far.amin(-1), seen.any(-1)  # each attacker: the nearest defender in play
        if self.num_attackers > 1:  # a lone attacker flies until the episode ends
            flying = targets(self.down).unsqueeze(-1)  # the attackers not down
            far, seen = far.masked_fill(~flying, float("inf")), seen & flying
            distance, visible = distance.masked_fill(~flying, float("inf")), visible & flying
        overall = far.flatten(1).amin(-1), seen.flatten(1).any(-1)
        if self.learner == ATTACKER:
            return _Sight(*own, *overall)
        return _Sight(distance.amin(1), visible.any(1), *overall)  # each defender: its attackers

    def _defender_command(self, p: Tensor, v: Tensor, target: Tensor, route_done: Tensor):
        """Scripted defenders: (N, m, 3) m/s."""
        speed = self.max_speed[:, self.defenders]
        own_p, own_v = p[:, self.defenders], v[:, self.defenders]
        command = follow_route(own_p, target, route_done, speed, self.setpoint_gain)
        flies = self.nn_defender & ~route_done if self.defender_network is not None else None
        # Eager, the network runs only while some defender flies it (its output is unused
        # otherwise); a compiled step always runs it (no data-dependent branch).
        if flies is not None and (torch.compiler.is_compiling() or bool(flies.any())):
            near = nearest(own_p, p[:, self.attackers], targets(self.down))  # not down
            view = DroneView(
                own_p,
                own_v,
                gather_drones(p[:, self.attackers], near).unsqueeze(-2),
                gather_drones(v[:, self.attackers], near).unsqueeze(-2),
                target,
                next_setpoint=self._setpoint(1),
                own_max_speed=speed,
                time_left=self._time_left(p.dtype).unsqueeze(1).expand_as(speed),
                other_acceleration=gather_drones(
                    self.acceleration[:, self.attackers], near
                ).unsqueeze(-2),
            )
            # A network defender flies eq. 2 (velocity) actions, whatever the learner's action.
            learned = self.defender_network(view).clamp(-1.0, 1.0) * speed.unsqueeze(-1)
            command = torch.where(flies.unsqueeze(-1), learned, command)
        return command

    def _time_left(self, dtype: torch.dtype) -> Tensor:
        """The time until each env's time limit, (N,) s."""
        return ((self.max_steps - self.step_count) * self.control_period).to(dtype)

    def _attacker_command(self, p: Tensor) -> Tensor:
        """Scripted attackers: pure pursuit of the nearest defender in play, (N, k, 3) m/s."""
        own, defenders = p[:, self.attackers], p[:, self.defenders]
        goal = gather_drones(defenders, nearest(own, defenders, targets(self.caught)))
        return pure_pursuit(own, goal, self.max_speed[:, self.attackers], self.pursuit_gain)

    def _outputs(
        self,
        sight: _Sight,
        captured: Tensor,
        team_reward: Tensor | None = None,
        running: Tensor | None = None,
        **extra,
    ) -> dict[str, Tensor | dict[str, Tensor]]:
        """The output entries; every tensor in them is fresh (no alias of the env's state).
        ``running`` (N,) bool: the envs whose episode went on into this state (None: all)."""
        p, v = self.dynamics.position, self.dynamics.velocity  # replaced on every advance/reset
        n, t = self.batch_size[0], self.team_size
        own_p, own_v = p[:, self.team], v[:, self.team]
        other_p = p[:, self.opponents].unsqueeze(1).expand(n, t, -1, 3)
        other_v = v[:, self.opponents].unsqueeze(1).expand(n, t, -1, 3)
        target, route_done = self._target()

        def route_view(x: Tensor) -> Tensor:  # each defender's own, or every attacker the first's
            return x if self.learner != ATTACKER else x[:, :1].expand(n, t, 3)

        view = DroneView(own_p, own_v, other_p, other_v, route_view(target),
                         own_max_speed=self.max_speed[:, self.team],
                         time_left=self._time_left(p.dtype).unsqueeze(1).expand(n, t))  # fmt: skip
        if t > 1:
            view = replace(view, mate_position=own_p[:, self._mate_index],
                           mate_velocity=own_v[:, self._mate_index])  # fmt: skip
        if self.obs_fn.route_ahead:  # an observation that reads the route ahead
            view = replace(view, next_setpoint=route_view(self._setpoint(1)))
        # The meeting point of this state: the observation's, and the next step's guidance.
        self._meeting = self.meeting(p, v, running) if self.computes_meeting else None
        if self.obs_fn.reads_intercept:  # an observation that reads the meeting point
            aim, due, _ = self._meeting
            view = replace(view, intercept=aim, intercept_time=due)
        if self._conforms:  # an observation that reads how the nearest defender keeps its route
            near = nearest(p[:, self.attackers], p[:, self.defenders], targets(self.caught))
            residual = gather_drones(self.route_residual, near)
            deviation = self.route_deviation.gather(1, near)
            self._deviation_seen = deviation  # a gated correction's, in the next step
            view = replace(view, route_residual=residual, route_deviation=deviation)
        if "a" in self.obs_fn.other_layout:  # an observation that reads accelerations
            a = self.acceleration
            other_a = a[:, self.opponents].unsqueeze(1).expand(n, t, -1, 3)
            view = replace(view, other_acceleration=other_a)
            if t > 1:
                view = replace(view, mate_acceleration=a[:, self.team][:, self._mate_index])
        if self.obs_fn.in_play:  # which drones are still in play (not caught, not down)
            playing = torch.cat([~self.down, ~self.caught], 1)  # (N, k + m)
            others = playing[:, self.opponents].unsqueeze(1).expand(n, t, -1)
            mates = playing[:, self.team][:, self._mate_index]
            view = replace(view, other_in_play=others, mate_in_play=mates)
        team = {"observation": self.obs_fn(view)}
        out = {
            "distance": sight.distance.unsqueeze(-1),
            "visible": sight.visible.unsqueeze(-1),
            "captured": captured,
            "caught": self.caught.clone(),
            "positions": p,
            "velocities": v,
            "accelerations": self.acceleration,
            "max_speed": self.max_speed.clone(),
            "waypoint": self.waypoint.clone(),
            "setpoints": target,
            "route_done": route_done,
            "scenario_index": self.scenario_index.unsqueeze(-1),
            **extra,
        }
        if self._reports_collisions:  # what the simulator reported during the last step
            out["collided"] = self.dynamics.collided.clone()
        if self.group is None:
            out.update({k: x[:, 0] for k, x in team.items()})
        else:
            team["distance"] = sight.team_distance.unsqueeze(-1)
            if self.learner == DEFENDER:
                team["caught"] = self.caught.unsqueeze(-1)
            else:
                team["down"] = self.down.unsqueeze(-1)
            if team_reward is not None:
                team["reward"] = team_reward
            out[self.group] = team
        return out


def flown_attackers(
    attackers: int | None, scenarios: ScenarioSet, field: str = "env.attackers"
) -> int:
    """How many attackers an env flies: ``attackers`` (the first that many of each scenario),
    or all of the scenarios' when None; a clear error naming ``field`` for anything else."""
    if attackers is None:
        return scenarios.attackers
    if isinstance(attackers, bool) or not isinstance(attackers, int) or attackers < 1:
        raise ConfigError(f"{field}: a positive integer or null, got {attackers!r}")
    if attackers > scenarios.attackers:
        raise ConfigError(
            f"{field}: {attackers}, the scenarios have {scenarios.attackers} (at most)"
        )
    return attackers


def _closest_approach(before: Tensor, after: Tensor) -> Tensor:
    """Least norm (*B,) of relative positions (*B, 3) moving linearly from ``before`` to
    ``after``."""
    delta = after - before
    t = (-(before * delta).sum(-1) / (delta * delta).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (before + t.unsqueeze(-1) * delta).norm(dim=-1)
