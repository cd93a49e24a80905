"""One check of a composed config's values before any work starts, and of a resume's config.

``validate_train_config`` checks ``conf/train.yaml`` as composed (whichever group options were
chosen) and ``validate_evaluate_config`` checks ``conf/evaluate.yaml``. Both raise
:class:`~rlplat.errors.ConfigError` with one line that names the first offending field and its
value, or the valid choices, e.g. ``algo.actor_lr: must be a finite number > 0, got nan``.

The rules are tables of dotted key -> rule (:mod:`rlplat.experiment.rules`). A node that holds
table keys (``train``, ``env``, ``algo``, ``logger``, ...) refuses a key the table does not
name, and a key the table names must be set unless its rule is ``Opt``. The component nodes
(``dynamics``, ``observation``, ``action``) take the knobs of the registered class their
``name`` picks (optional: the class's default applies); ``scenario`` is checked by
:meth:`ScenarioSpec.from_dict`. Rules between fields follow the tables. NaN and infinity are
refused wherever a number is expected.

``config_diff`` and ``check_resume`` compare a run's saved config with the one it resumes with.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rlplat.agents.export import ARTIFACTS, check_prefix
from rlplat.agents.policies import POLICIES as SCRIPTED
from rlplat.agents.sac import ACTIVATIONS
from rlplat.envs.airsim.client import parse_endpoint
from rlplat.envs.airsim.dynamics import TIME_MISMATCH
from rlplat.envs.airsim.settings import effective_clock_speed
from rlplat.envs.components import ACTIONS, OBSERVATIONS, REWARD_TERMS
from rlplat.envs.dynamics import DYNAMICS
from rlplat.envs.kinematics import UNREACHABLE
from rlplat.envs.pursuit import ORDERS, ROLES, reward_role_problem
from rlplat.errors import ConfigError
from rlplat.experiment.logger import BACKENDS
from rlplat.experiment.rules import (
    COUNT,
    FINITE,
    MISSING,
    NON_NEGATIVE,
    POSITIVE,
    THREADS,
    Choice,
    Num,
    Opt,
    Rule,
    Seq,
    Text,
    TextList,
    check_table,
    device,
    flag,
    keyword_parameters,
    lookup,
    show,
)
from rlplat.scenarios import SPLITS, ScenarioSpec

# Rules of this config -----------------------------------------------------------------------


def scenario(value: Any) -> str | None:
    """A scenario family (``conf/scenario/``): :meth:`ScenarioSpec.from_dict` names the field."""
    if not isinstance(value, Mapping):
        return f"must be a mapping, got {show(value)}"
    try:
        ScenarioSpec.from_dict(value)
    except ConfigError:
        raise
    except (TypeError, ValueError, KeyError) as e:
        return f"invalid ({show(str(e))})"
    return None


def endpoints(value: Any) -> str | None:
    """A non-empty list of distinct ``host:port`` simulator addresses."""
    if not isinstance(value, list) or not value:
        return f"must be a non-empty list of host:port, got {show(value)}"
    for item in value:
        try:
            parse_endpoint(item)
        except ConfigError:
            return f"{show(item)} is not host:port (e.g. 127.0.0.1:41451, port in 1..65535)"
    if len(set(value)) < len(value):
        return f"names a simulator twice, got {show(value)}"
    return None


def time_mismatch(value: Any) -> str | None:
    """What a step off the control period does: one of ``TIME_MISMATCH``."""
    if isinstance(value, str) and value in TIME_MISMATCH:
        return None
    return f"must be one of {', '.join(TIME_MISMATCH)}, got {show(value)}"


def spawn_points(value: Any) -> str | None:
    """null, or a mapping of vehicle names to (x, y, z) NED metres."""
    if value is None:
        return None
    if isinstance(value, Mapping) and all(
        isinstance(v, list) and len(v) == 3 and all(FINITE.fits(x) for x in v)
        for v in value.values()
    ):
        return None
    return f"must be null or {{vehicle: [x, y, z]}} (NED m), got {show(value)}"


def vehicle_list(value: Any) -> str | None:
    """null, or the vehicles' names (non-empty, distinct strings; their number is checked
    against the team where the env is built, which knows the scenario set's)."""
    if value is None:
        return None
    if (
        isinstance(value, list)
        and value
        and all(isinstance(v, str) and v.strip() for v in value)
        and len(set(value)) == len(value)
    ):
        return None
    return f"must be null or a list of distinct vehicle names, got {show(value)}"


def reward_terms(value: Any) -> str | None:
    """A non-empty mapping of reward terms to weights (each weight is checked on its own)."""
    if isinstance(value, Mapping) and value:
        return None
    return f"must weigh at least one of {', '.join(REWARD_TERMS)}, got {show(value)}"


#: Who may fly ``algo.init_random_frames``: uniform actions, or a baseline of the learner's role.
INIT_POLICIES = ("random", *SCRIPTED)
#: ``evaluate.py policy=`` choices: the run's checkpoint, its export, or a baseline.
POLICIES = ("checkpoint", *ARTIFACTS, *SCRIPTED)
#: Env outputs a learner's potential-based shaping may read (``algo.potential_key``).
POTENTIAL_KEYS = ("distance",)
#: What self-imitation does with an episode cut short (``algo.self_imitation_truncated``).
TRUNCATED_EPISODES = ("drop", "bootstrap")
#: torchrl's critic regression losses.
LOSS_FUNCTIONS = ("l2", "l1", "smooth_l1")
#: wandb modes that ``logger.mode`` may set (others are read from ``WANDB_MODE``).
WANDB_MODES = ("offline", "online")


# Tables -----------------------------------------------------------------------------------

#: conf/train.yaml, but for the component groups (see ``_component_rules``).
TRAIN_RULES: dict[str, Rule] = {
    "seed": Num(integer=True, ge=0, le=2**32 - 1),  # numpy's seed range
    "resume": flag,
    "init_from": Text(null=True),
    "scenarios_dir": Text(null=True),
    "scenario": scenario,
    "train.total_frames": COUNT,
    "train.max_minutes": Num(gt=0, null=True),
    "train.eval_every_frames": COUNT,
    "train.keep_checkpoints": flag,
    "train.device": device,
    "train.progress": flag,
    "train.threads": THREADS,
    "env.control_period": POSITIVE,
    "env.time_limit": POSITIVE,
    "env.capture_radius": POSITIVE,
    "env.ground_altitude": NON_NEGATIVE,  # the dynamics hold every drone at z >= 0
    "env.vision_semi_axes": Seq(POSITIVE, n=3),
    "env.terminate_out_of_view": flag,
    "env.scenario_order": Choice(ORDERS),
    "env.setpoint_acceptance": POSITIVE,
    "env.setpoint_gain": POSITIVE,
    "env.pursuit_gain": POSITIVE,
    "env.compile_step": flag,
    "env.defender_network": Text(null=True),
    "env.attackers": Num(integer=True, ge=1, null=True),
    "reward.distance_scale": Opt(POSITIVE),
    "reward.terms": reward_terms,
    **{f"reward.terms.{term}": Opt(FINITE) for term in REWARD_TERMS},
    "algo.name": Text(),
    "algo.num_envs": COUNT,
    "algo.frames_per_batch": COUNT,
    "algo.init_random_frames": Num(integer=True, ge=0),
    "algo.init_policy": Text(),  # one of INIT_POLICIES for drone.learner, checked below
    "algo.init_noise": NON_NEGATIVE,
    "algo.noise_correlation": Num(ge=0, lt=1),
    "algo.utd_ratio": POSITIVE,
    "algo.batch_size": COUNT,
    "algo.buffer_size": COUNT,
    "algo.gamma": Num(ge=0, lt=1),
    "algo.n_steps": COUNT,
    "algo.potential_key": Choice(POTENTIAL_KEYS),
    "algo.potential_weight": FINITE,
    "algo.tau": Num(gt=0, le=1),
    "algo.actor_lr": POSITIVE,
    "algo.critic_lr": POSITIVE,
    "algo.alpha_lr": POSITIVE,
    "algo.alpha_init": POSITIVE,
    "algo.target_entropy": Num(words=("auto",)),
    "algo.loss_function": Choice(LOSS_FUNCTIONS),
    "algo.actor_cells": Seq(COUNT),
    "algo.critic_cells": Seq(COUNT),
    "algo.activation": Choice(ACTIVATIONS),
    "algo.action_margin": Num(ge=0, le=1),
    "algo.actor_zero_mean": flag,
    "algo.actor_init_std": Num(gt=0, null=True),
    "algo.actor_warmup_updates": Num(integer=True, ge=0),
    "algo.anchor_weight": Num(ge=0),
    "algo.actor_average": Num(ge=0, le=1),
    "algo.failure_weight": Num(gt=0),
    "algo.failure_evaders_only": flag,
    "algo.evader_weight": Num(gt=0),
    "algo.priority_alpha": Num(ge=0, le=1),
    "algo.priority_beta": Num(ge=0, le=1),
    "algo.demonstrations": TextList(),
    "algo.demonstration_repeat": COUNT,
    "algo.self_imitation": Num(ge=0),
    "algo.self_imitation_every": COUNT,
    "algo.self_imitation_truncated": Choice(TRUNCATED_EPISODES),
    "algo.compile": flag,
    "drone.name": Text(),
    "drone.learner": Choice(ROLES),
    "logger.backend": Choice(BACKENDS),
}

#: Keys of the ``logger`` node besides ``backend``, per backend.
LOGGER_RULES: dict[str, dict[str, Rule]] = {
    "wandb": {"logger.project": Opt(Text()), "logger.mode": Opt(Choice(WANDB_MODES))},
}

#: Knobs of the dynamics models (conf/dynamics/, SI units): what physics needs positive is
#: positive; drag, gravity and the vertical integral term may be 0.
DYNAMICS_KNOBS: dict[str, Rule] = {
    "physics_dt": POSITIVE,
    "mass": POSITIVE,
    "tau_xy": POSITIVE,
    "tau_z": POSITIVE,
    "a_xy_max": POSITIVE,
    "a_up_max": POSITIVE,
    "a_down_max": POSITIVE,
    "drag_xy": NON_NEGATIVE,
    "drag_z": NON_NEGATIVE,
    "gravity": NON_NEGATIVE,
    "arm_length": POSITIVE,
    "inertia_xx": POSITIVE,
    "inertia_yy": POSITIVE,
    "inertia_zz": POSITIVE,
    "max_rotor_thrust": POSITIVE,
    "motor_time_constant": POSITIVE,
    "yaw_torque_coefficient": POSITIVE,
    "tilt_gain": POSITIVE,
    "max_tilt": Num(gt=0, lt=math.pi / 2),
    "vz_p_gain": POSITIVE,
    "vz_i_gain": NON_NEGATIVE,
    "vz_i_limit": NON_NEGATIVE,
    "angle_gain": POSITIVE,
    "max_angle_rate": POSITIVE,
    "rate_gain": POSITIVE,
    # airsim: the simulators and how long to wait for them
    "endpoints": endpoints,
    "attacker_name": Text(),
    "defender_name": Text(),
    "vehicles": vehicle_list,
    "connect_timeout_s": POSITIVE,
    "timeout_s": POSITIVE,
    "step_tolerance_s": NON_NEGATIVE,
    "on_time_mismatch": time_mismatch,
    "clock_speed": POSITIVE,
    "spawn": spawn_points,
    "move_margin_s": POSITIVE,
}
#: Knobs of the observations (conf/observation/).
OBSERVATION_KNOBS: dict[str, Rule] = {
    "position_scale": POSITIVE,
    "velocity_scale": POSITIVE,
    "time_scale": POSITIVE,
    "accel_scale": POSITIVE,
    "world_scale": POSITIVE,
    "conformity_time": POSITIVE,
    "route_lag": Seq(POSITIVE, n=3),
    "team_sight": flag,
}
#: Knobs of the actions (conf/action/).
ACTION_KNOBS: dict[str, Rule] = {
    "gain": POSITIVE,
    "lead": NON_NEGATIVE,
    "max_lead_time": NON_NEGATIVE,
    "scale": POSITIVE,
    "gain_factor": Num(gt=1),
    "lead_reach": NON_NEGATIVE,
    "horizon_factor": Num(gt=1),
    "accel_lead": NON_NEGATIVE,
    "accel_reach": NON_NEGATIVE,
    "correction_reach": NON_NEGATIVE,
    "homing_time": NON_NEGATIVE,
    "start_lag": NON_NEGATIVE,
    "horizon": Num(gt=0, null=True),
    "unreachable": Choice(UNREACHABLE),
    "gate_low": NON_NEGATIVE,
    "gate_high": NON_NEGATIVE,
    "gate_unreachable": flag,
}
#: Component groups: registry, knob rules, and the arguments the env factory passes itself.
COMPONENTS: dict[str, tuple[Mapping[str, Any], Mapping[str, Rule], tuple[str, ...]]] = {
    "dynamics": (DYNAMICS, DYNAMICS_KNOBS, ("num_envs", "num_drones", "num_attackers", "device")),
    "observation": (OBSERVATIONS, OBSERVATION_KNOBS, ("opponents", "mates", "in_play")),
    "action": (ACTIONS, ACTION_KNOBS, ()),
}

#: conf/evaluate.yaml.
EVALUATE_RULES: dict[str, Rule] = {
    "run_dir": Text(),
    "policy": Choice(POLICIES),
    "ckpt": Text(),  # best | last | a checkpoint path
    "export_dir": Text(null=True),
    "split": Choice(SPLITS),
    "compare": flag,
    "strict_scenarios": flag,
    "scenarios_dir": Text(null=True),
    "attackers": Num(integer=True, ge=1, null=True),
    "lone_in_team": flag,
    "out_dir": Text(null=True),
    "device": device,
    "threads": THREADS,
    "trajectories": Num(integer=True, ge=0),
    "plots": flag,
    "speed_ratio_bins": Seq(POSITIVE, increasing=True),
    "compiler": Text(),
    "ensemble": TextList(),
}

#: conf/export.yaml.
EXPORT_RULES: dict[str, Rule] = {
    "run_dir": Text(null=True),
    "ckpt": Text(),  # best | last | a checkpoint path
    "controller": Text(null=True),
    "out_dir": Text(null=True),
    "scenarios_dir": Text(null=True),
    "split": Choice(SPLITS),
    "prefix": Text(),
    "min_observations": COUNT,
    "tolerance": POSITIVE,
    "timing_calls": Num(integer=True, ge=100),
    "compiler": Text(),
    "retime": flag,
    "threads": THREADS,
}


def knobs(cls: Callable[..., Any], factory_args: Iterable[str]) -> dict[str, Any]:
    """A component class's config knobs and their defaults (its keyword arguments but those
    the env factory passes)."""
    params = keyword_parameters(cls).values()
    return {p.name: p.default for p in params if p.name not in factory_args}


def _component_rules(c: Mapping[str, Any], groups: Iterable[str] = COMPONENTS) -> dict[str, Rule]:
    rules: dict[str, Rule] = {}
    for group in groups:
        registry, rule_of, factory_args = COMPONENTS[group]
        rules[f"{group}.name"] = Choice(registry)
        name = lookup(c, f"{group}.name")
        if isinstance(name, str) and name in registry:
            for knob in knobs(registry[name], factory_args):
                rules[f"{group}.{knob}"] = Opt(rule_of.get(knob, FINITE))
    return rules


# Rules between fields ---------------------------------------------------------------------


def _component(c: Mapping[str, Any], group: str) -> dict[str, Any]:
    """The knobs a component is built with: the node's over the class's defaults."""
    registry, _, factory_args = COMPONENTS[group]
    node = dict(c[group])
    return {**knobs(registry[node.pop("name")], factory_args), **node}


def _learning_drones(c: Mapping[str, Any]) -> int:
    """Drones that share the policy, as far as the config tells (1 with ``scenarios_dir``)."""
    if c["scenarios_dir"] is not None:
        return 1
    if c["drone"]["learner"] == "defender":
        return c["scenario"].get("defenders", 1)
    return c["env"]["attackers"] or c["scenario"].get("attackers", 1)


def _check_training(c: Mapping[str, Any]) -> None:
    """What a training run needs of its config besides its env's."""
    algo, learner = c["algo"], c["drone"]["learner"]
    problem = reward_role_problem(c["reward"]["terms"], learner)
    if problem is not None:  # training on it would learn the other side's game
        raise ConfigError(problem)
    if learner != "attacker":  # the env refuses these too; said first, before what follows
        if getattr(ACTIONS.get(c["action"].get("name")), "guided", False):
            raise ConfigError("action: a guided action flies attackers; this run's learner is "
                              f"the {learner} (valid: velocity)")  # fmt: skip
        seen = OBSERVATIONS.get(c["observation"].get("name"))
        if getattr(seen, "reads_conformity", False) or getattr(seen, "reads_intercept", False):
            raise ConfigError(
                f"observation: {c['observation']['name']} reads the defender's route as an "
                f"attacker sees it; this run's learner is the {learner}"
            )
    if c["scenarios_dir"] is None:  # the configured set: training flies all three splits
        for split in ("train", "val", "test"):
            n = c["scenario"].get(f"n_{split}")
            if isinstance(n, int) and not isinstance(n, bool) and n == 0:
                raise ConfigError(
                    f"scenario.n_{split}: training needs {split} scenarios, got 0 (a set "
                    "without them is for evaluate.py scenarios_dir=...)"
                )
    if algo["frames_per_batch"] % algo["num_envs"]:
        raise ConfigError(
            f"algo.frames_per_batch: {algo['frames_per_batch']} is not a multiple of "
            f"algo.num_envs={algo['num_envs']}"
        )
    valid = [k for k in INIT_POLICIES if k == "random" or SCRIPTED[k].role == learner]
    policy = algo["init_policy"]
    if policy not in INIT_POLICIES:
        raise ConfigError(f"algo.init_policy: unknown {show(policy)}; valid: {', '.join(valid)}")
    if policy not in valid:
        raise ConfigError(
            f"algo.init_policy: {show(policy)} flies the {SCRIPTED[policy].role}, "
            f"drone.learner is the {learner}; valid: {', '.join(valid)}"
        )
    if algo["evader_weight"] != 1 and learner != "attacker":
        raise ConfigError(
            f"algo.evader_weight: {show(algo['evader_weight'])} weights the network "
            f"defenders' scenarios for an attacker; drone.learner is the {learner}; valid: 1"
        )
    action = ACTIONS.get(c["action"].get("name"))
    own_law = policy == "route_intercept" and c["action"].get("name") == "route_law"
    if (
        policy != "random"
        and not own_law
        and action is not None
        and not action.flies_any_command(c["action"])
    ):
        why, valid_here = (
            ("a gated correction flies only its law where the defender keeps its route",
             "random, route_intercept")
            if c["action"].get("name") == "route_law"
            else ("its actions set the guidance law's parameters; action.correction_reach >= 2 "
                  "flies it", "random")
        )  # fmt: skip
        raise ConfigError(
            f"algo.init_policy: {show(policy)} cannot be flown through action="
            f"{c['action']['name']} ({why}); valid: {valid_here}"
        )
    first_update = max(algo["batch_size"], algo["init_random_frames"] * _learning_drones(c))
    if algo["buffer_size"] < first_update:
        raise ConfigError(
            f"algo.buffer_size: {algo['buffer_size']} transitions never reach the "
            f"{first_update} the first update waits for (algo.batch_size, "
            "algo.init_random_frames x learning drones)"
        )


def _check_env_fields(c: Mapping[str, Any], env_batch: int | None = None) -> None:
    """What the env needs of its config: a training run's (``algo.num_envs`` envs) or an env
    of ``env_batch`` envs (``make_env``'s ``num_envs``)."""
    env = c["env"]
    if env["time_limit"] < env["control_period"]:
        raise ConfigError(
            f"env.time_limit: {env['time_limit']} s is shorter than one control period "
            f"(env.control_period={env['control_period']} s)"
        )
    dynamics = _component(c, "dynamics")
    if c["dynamics"]["name"] == "airsim":
        if env_batch is None:
            _check_airsim(dynamics, env, c["algo"]["num_envs"], "algo.num_envs")
        else:
            _check_airsim(dynamics, env, env_batch, "num_envs")
    elif dynamics["physics_dt"] > env["control_period"]:
        raise ConfigError(
            f"dynamics.physics_dt: {dynamics['physics_dt']} s is longer than one control "
            f"period (env.control_period={env['control_period']} s)"
        )
    if "rate_gain" in dynamics and dynamics["physics_dt"] * dynamics["rate_gain"] > 1.0:
        # the sub-step integrates the rate loop explicitly: too coarse a step overshoots and
        # grows (at 0.1 s with the default gain of 25/s the drones fly twice their top speed)
        raise ConfigError(
            f"dynamics.physics_dt: {dynamics['physics_dt']} s is too coarse for the rate loop "
            f"(dynamics.rate_gain={dynamics['rate_gain']}/s): at most 1 / rate_gain = "
            f"{1.0 / dynamics['rate_gain']:.3g} s keeps the sub-step stable"
        )
    if "max_rotor_thrust" in dynamics:
        thrust, weight = dynamics["max_rotor_thrust"], dynamics["mass"] * dynamics["gravity"]
        if 4 * thrust <= weight:
            raise ConfigError(
                f"dynamics.max_rotor_thrust: 4 rotors of {thrust} N cannot hold a weight of "
                f"{weight:g} N (dynamics.mass x dynamics.gravity)"
            )


def _check_airsim(dynamics: Mapping[str, Any], env: Mapping[str, Any], n: int, field: str):
    """The simulators of ``dynamics=airsim`` against the env: one env per simulator, a
    timeout longer than a step, no compiled step (a step is calls to the simulator)."""
    if n != len(dynamics["endpoints"]):
        raise ConfigError(
            f"{field}: {n}, dynamics.endpoints names {len(dynamics['endpoints'])} simulator(s) "
            f"(one env per simulator): {show(dynamics['endpoints'])}"
        )
    wall = env["control_period"] / effective_clock_speed(dynamics["clock_speed"])
    if dynamics["timeout_s"] <= wall:
        raise ConfigError(
            f"dynamics.timeout_s: {dynamics['timeout_s']} s is not longer than one step of the "
            f"simulator's clock (env.control_period / dynamics.clock_speed, above 1 its whole "
            f"part, = {wall:g} s)"
        )
    if env["compile_step"]:
        raise ConfigError("env.compile_step: true, must be false with dynamics=airsim")


def _check_evaluate_fields(c: Mapping[str, Any]) -> None:
    if c["policy"] in SCRIPTED and c["ckpt"] != "best":
        raise ConfigError(
            f"ckpt: {show(c['ckpt'])} is for policy=checkpoint, onnx or c, got policy={c['policy']}"
        )
    if c["export_dir"] is not None and c["policy"] not in ("onnx", "c"):
        raise ConfigError(
            f"export_dir: {show(c['export_dir'])} is for policy=onnx or c, got policy={c['policy']}"
        )
    if c["ensemble"] and c["policy"] != "checkpoint":
        raise ConfigError(
            f"ensemble: flies checkpoints (policy=checkpoint), got policy={c['policy']}"
        )


def _check_export_fields(c: Mapping[str, Any]) -> None:
    if (c["run_dir"] is None) == (c["controller"] is None):
        raise ConfigError(
            f"run_dir: set run_dir=DIR (a training run) or controller=FILE (a controller file), "
            f"got run_dir={show(c['run_dir'])}, controller={show(c['controller'])}"
        )
    if c["controller"] is not None and c["out_dir"] is None:
        raise ConfigError("out_dir: a controller export needs out_dir=DIR, got None")
    if c["controller"] is not None and c["ckpt"] != "best":
        raise ConfigError(f"ckpt: {show(c['ckpt'])} is for run_dir only, not with controller")
    check_prefix(c["prefix"])


# Checking ---------------------------------------------------------------------------------


def validate_train_config(cfg: DictConfig, env_batch: int | None = None) -> None:
    """Check a composed ``conf/train.yaml`` before any work starts.

    ``env_batch``: the config of an env of that many envs, built to fly policies
    (:func:`rlplat.make_env`), not of a training run: its values and the env's rules are
    checked, not the training loop's (``algo``'s batches, its scripted start), and a reward of
    the other side's game, which training refuses, is left to the env's warning.

    Raises:
        ConfigError: one line naming the first offending field and its value.
    """
    c = _resolved(cfg)
    backend = lookup(c, "logger.backend")
    logger = LOGGER_RULES.get(backend, {}) if isinstance(backend, str) else {}
    rules = {**TRAIN_RULES, **_component_rules(c), **logger}
    check_table(c, rules)
    k, scenario_k = c["env"]["attackers"], c["scenario"].get("attackers", 1)
    if k is not None and c["scenarios_dir"] is None and k > scenario_k:  # sizes the buffer check
        raise ConfigError(f"env.attackers: {k}, the scenarios have {scenario_k} (at most)")
    if env_batch is None:
        _check_training(c)
    _check_env_fields(c, env_batch)


def validate_evaluate_config(cfg: DictConfig) -> None:
    """Check a composed ``conf/evaluate.yaml`` before any work starts (the run directory
    itself is read, and checked, by the evaluator).

    Raises:
        ConfigError: one line naming the first offending field and its value.
    """
    c = _resolved(cfg)
    swap = _component_rules(c, ["dynamics"]) if c.get("dynamics") is not None else {}
    check_table(c, {**EVALUATE_RULES, **swap})
    _check_evaluate_fields(c)


def validate_dynamics_swap(dynamics: Mapping[str, Any], run_config: Mapping[str, Any]) -> None:
    """Check a dynamics node (``evaluate.py dynamics=...``) that replaces a run's own, against
    the run's env: its knobs, and with ``airsim`` its timing and step rules.

    Raises:
        ConfigError: one line naming the first offending field and its value.
    """
    c = {"dynamics": dict(dynamics)}
    check_table(c, _component_rules(c, ["dynamics"]))
    env = {**run_config["env"], "compile_step": False}  # an evaluation never compiles here
    if c["dynamics"]["name"] == "airsim":
        node = _component(c, "dynamics")
        _check_airsim(node, env, len(node["endpoints"]), "dynamics.endpoints")


def validate_export_config(cfg: DictConfig) -> None:
    """Check a composed ``conf/export.yaml`` before any work starts (the run directory or
    controller file itself is read, and checked, by the export).

    Raises:
        ConfigError: one line naming the first offending field and its value.
    """
    c = _resolved(cfg)
    check_table(c, EXPORT_RULES)
    _check_export_fields(c)


def _resolved(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    """The config as plain containers, interpolations resolved (``???`` stays as it is)."""
    if not isinstance(cfg, DictConfig):
        return dict(cfg)
    if "hydra" in cfg:  # only where composed with return_hydra_config
        cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or "config"
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ConfigError(_broken_reference(cfg, key, message) or f"{key}: {message}") from None


def _broken_reference(cfg: DictConfig, key: str, message: str) -> str | None:
    """For an interpolation that reads through a node the command line removed or replaced
    (``~env``, ``env=foo``), that node's error rather than the reader's; None otherwise."""
    found = re.search(r"access ([\w.]+)|key '([\w.]+)'", message)
    ref = (found.group(1) or found.group(2)) if found is not None else ""
    if not ref or ref.startswith("."):  # a relative one names no node from the top
        return None
    parts, node = ref.split("."), cfg
    for i, part in enumerate(parts[:-1]):
        here = ".".join(parts[: i + 1])
        child = node._get_node(part) if isinstance(node, DictConfig) and part in node else None
        if child is None:
            return f"{here}: missing ({key} reads {ref})"
        if not isinstance(child, DictConfig):
            return f"{here}: must be a mapping, got {show(child._value())} ({key} reads {ref})"
        node = child
    return None


# Resume -----------------------------------------------------------------------------------

#: What a resumed run may change (a trailing ``.*``: the whole node): its budget, its progress
#: bar, knobs of speed that leave what is learned alone, and where its metrics go (the CSV
#: files are always written). Everything else, ``train.device`` included, must stay.
RESUME_FREE: tuple[str, ...] = (
    "resume",
    "train.total_frames",
    "train.max_minutes",
    "train.progress",
    "train.threads",
    "train.keep_checkpoints",
    "env.compile_step",
    "algo.compile",
    "logger.*",
)


#: Keys added to the config after runs were saved, with the value that flies as those runs
#: flew: a saved config without such a key, resumed with that value, is the same config.
ADDED_KEYS: dict[str, Any] = {
    "algo.failure_weight": 1.0,
    "algo.failure_evaders_only": False,
    "algo.evader_weight": 1.0,
    "algo.priority_alpha": 0.0,
    "algo.priority_beta": 0.4,
    "action.accel_lead": 0.0,
    "action.accel_reach": 0.0,
    "action.correction_reach": 0.0,
    "action.start_lag": 0.0,
    "action.gate_low": 0.0,
    "action.gate_high": 0.0,
    "action.gate_unreachable": False,
    "action.horizon": None,
    "action.unreachable": "chase",
    "algo.actor_average": 0.0,
    "algo.noise_correlation": 0.0,
    "algo.demonstrations": [],
    "algo.demonstration_repeat": 4,
    "algo.self_imitation": 0.0,
    "algo.self_imitation_every": 2,
    "algo.self_imitation_truncated": "drop",
    "init_from": None,
    "train.keep_checkpoints": False,
    "dynamics.vehicles": None,
}


def _flat(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, (DictConfig, ListConfig)):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, Mapping) or (prefix and not node):
        return {prefix: node}
    out: dict[str, Any] = {}
    for key, value in node.items():
        out.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _ignored(key: str, ignore: Iterable[str]) -> bool:
    for pattern in ignore:
        base = pattern.removesuffix(".*")
        if key == base or key.startswith(base + "."):
            return True
    return False


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b and isinstance(a, bool) == isinstance(b, bool)


def config_diff(
    saved: Mapping[str, Any], current: Mapping[str, Any], ignore: Iterable[str] = RESUME_FREE
) -> list[str]:
    """Dotted keys whose values differ between two resolved configs (added, removed or
    changed; a list is one value), but for those ``ignore`` matches (``RESUME_FREE``), sorted.
    A key of ``ADDED_KEYS`` that one config lacks and the other has counts with its value
    there (a config saved before the key existed)."""
    ignore = tuple(ignore)
    a, b = _flat(saved), _flat(current)
    a.update({k: v for k, v in ADDED_KEYS.items() if k not in a and k in b})
    b.update({k: v for k, v in ADDED_KEYS.items() if k not in b and k in a})
    keys = (k for k in a.keys() | b.keys() if not _ignored(k, ignore))
    return sorted(k for k in keys if not _same(a.get(k, MISSING), b.get(k, MISSING)))


def check_resume(saved: Mapping[str, Any], current: Mapping[str, Any]) -> None:
    """Refuse to resume a run whose saved config (its checkpoint's, as in its ``config.yaml``)
    differs from the current one in more than ``RESUME_FREE``.

    Raises:
        ConfigError: one line listing each differing key with its saved -> current value.
    """
    keys = config_diff(saved, current)
    if not keys:
        return
    a, b = _flat(saved), _flat(current)

    def value(flat: dict[str, Any], key: str) -> str:
        return "absent" if key not in flat else show(flat[key], limit=40)

    # The choices (``drone.name``, ``action.name``, ...) first: they say the most.
    keys = sorted(keys, key=lambda k: (not k.endswith(".name"), k))
    shown = [f"{k} ({value(a, k)} -> {value(b, k)})" for k in keys[:10]]
    more = f" and {len(keys) - 10} more" if len(keys) > 10 else ""
    raise ConfigError(
        f"resume: the config differs from the run's own in {', '.join(shown)}{more}; "
        f"only {', '.join(RESUME_FREE)} may change on a resume"
    )
