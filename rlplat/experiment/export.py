"""Export a run's policy as ONNX and dependency-free C, verified and timed, with its card.

``export_run(run_dir, ckpt=...)`` is what ``export.py`` calls; tests call it the same way. It
writes ``<run_dir>/export/<ckpt>/`` (or ``out_dir``):

- ``policy.onnx``: the deterministic actor (observation scaling, MLP, squashed and clamped
  mean), dynamic batch dimension, checked with the ONNX checker; its metadata names the drone,
  the source checkpoint's sha256, the scenario digest and the card's interface
  (:func:`onnx_metadata`), so the file alone says what it reads and where it came from;
- ``policy.h``, ``policy.c``: the same network in C99 (``rlplat_policy(obs, action)``);
- ``card.json``: interface (observation and action layout, units, scales), network, source
  checkpoint sha256, scenario digest, the equivalence of torch, ONNX Runtime and C on the
  observations of rollouts of the run's test split, and their timing on this machine.

A second export of the same checkpoint is byte-identical: the artifacts are generated
deterministically, and the card keeps the timing of the card it replaces when that card timed
the same artifacts with the same number of calls on the same machine (CPU, compiler, system,
library versions; ``retime=True`` measures again, ``load_average`` records the load of the
timing). Everything is checked before any work, everything is verified before anything is
written, and every file is written atomically. A controller file (e.g. the shipped defender
network) exports the same way (``controller=``), rolled out on the configured scenario set of
its drone bundle.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import textwrap
import time
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf, open_dict
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlplat.agents.checkpoint import actor_from_state, load_checkpoint, route_path_interface
from rlplat.agents.export import (
    C_PREFIX,
    VELOCITY_ACTION,
    DeterministicActor,
    c_api,
    c_sources,
    check_prefix,
    observation_key,
    onnx_bytes,
)
from rlplat.agents.native import (
    OnnxPolicy,
    build_library,
    compiler_version,
    cpu_model,
    find_compiler,
    time_c,
    time_onnx,
)
from rlplat.envs.kinematics import ROUTE_RESOLUTION
from rlplat.envs.pursuit import ROLES
from rlplat.errors import ConfigError, ExportError
from rlplat.eval.episodes import rollout_observations
from rlplat.experiment.config import compose_config
from rlplat.experiment.evaluation import (
    check_policy_fits,
    check_scenarios,
    checkpoint_path,
    default_export_dir,
    load_run_config,
)
from rlplat.experiment.factory import build_eval_env, require_scenarios, resolve_scenarios
from rlplat.experiment.schema import validate_export_config
from rlplat.io import (
    atomic_write_bytes,
    atomic_write_text,
    check_writable_dir,
    refuse_run_dir,
    sha256_bytes,
)
from rlplat.scenarios import SPLITS

log = logging.getLogger(__name__)

#: The files of an export, in the order they are written (the card last).
FILES = ("policy.onnx", "policy.h", "policy.c", "card.json")
#: Observations per ONNX Runtime batch in the timing.
ONNX_BATCH = 1024
#: Rollout observations the card lists with the torch actor's actions: reference pairs that
#: check a build of ``policy.c`` (another compiler, flags, target) without Python.
CARD_SAMPLES = 16
#: The world frame of every vector the artifacts read and the velocity command they make.
FRAME = (
    "world frame ENU (x east, y north, z up; m, m/s, m/s^2), the command's too; "
    "from NED: (x, y, z) = (y_ned, x_ned, -z_ned)"
)


@dataclass(frozen=True)
class Source:
    """What an export reads: the checkpoint, the config of the env its rollouts fly in, where
    its files go, and how the card names it."""

    state: dict[str, Any]
    path: Path
    sha256: str
    cfg: DictConfig
    out_dir: Path
    scenarios_dir: str | None
    scenario_digest: str | None
    described: dict[str, Any]


def _load(path: Path, field: str) -> tuple[dict[str, Any], str]:
    state = load_checkpoint(path, field)
    if "actor" not in state or "net" not in state:
        raise ConfigError(f"{field}: {path} holds no actor network")
    return state, sha256_bytes(path.read_bytes())


def run_source(run_dir: Path, ckpt: str, out_dir, scenarios_dir) -> Source:
    """A run's checkpoint ``ckpt`` (``best``, ``last`` or a path)."""
    cfg = load_run_config(run_dir)
    path = checkpoint_path(run_dir, ckpt)
    state, sha = _load(path, "ckpt")
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    digest = summary.get("scenario_digest") or state.get("scenario_digest")
    described = {"run_dir": str(run_dir), "checkpoint": ckpt, "frames": _frames(state)}
    out = Path(out_dir) if out_dir is not None else default_export_dir(run_dir, ckpt, path)
    chosen = scenarios_dir or cfg.get("scenarios_dir")
    return Source(state, path, sha, cfg, out, chosen, digest, described)


def controller_source(controller: Path, out_dir, scenarios_dir) -> Source:
    """A controller file (:mod:`rlplat.experiment.controller`, e.g. the shipped defender):
    rolled out in the env of its drone bundle with the observation it was trained on."""
    state, sha = _load(controller, "controller")  # "controller: no file at ..." where none is
    config = state.get("config", {})
    drone = config.get("drone", {}).get("name")
    try:
        cfg = compose_config("train", [f"drone={drone}"])
    except HydraException:
        raise ConfigError(
            f"controller: {controller} names drone '{drone}', which conf/drone does not hold"
        ) from None
    with open_dict(cfg):
        for node in ("observation", "action"):
            if node in config:
                cfg[node] = OmegaConf.create(dict(config[node]))
    source = state.get("source", {})
    described = {"controller": controller.name, **source}
    digest = source.get("scenario_digest")
    return Source(state, controller, sha, cfg, Path(out_dir), scenarios_dir, digest, described)


def _frames(state: dict[str, Any]) -> int | None:
    return state.get("counters", {}).get("frames")


def _check_tools() -> None:
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as e:
        raise ConfigError(
            f"export: needs onnx, onnxruntime and onnxscript ({e.name} is missing); "
            "pip install 'rlplat[export]'"
        ) from None


# Measuring ----------------------------------------------------------------------------------


def collect_observations(env, actor, key, minimum: int) -> tuple[torch.Tensor, dict[str, Any]]:
    """At least ``minimum`` observations from rollouts of ``env``'s split: the deterministic
    pass (what the evaluator flies), then passes with sampled actions (seeded 1, 2, ...)."""
    rows = [rollout_observations(env, actor, key)]
    first, passes = len(rows[0]), 0
    while sum(map(len, rows)) < minimum:
        passes += 1
        with torch.random.fork_rng():
            torch.manual_seed(passes)
            rows.append(rollout_observations(env, actor, key, deterministic=False))
    obs = torch.cat(rows)
    about = {
        "count": len(obs),
        "deterministic_pass": first,
        "sampled_passes": passes,
        "sampled_seeds": list(range(1, passes + 1)),
    }
    return obs, about


def torch_actions(state: dict[str, Any], obs: torch.Tensor) -> np.ndarray:
    """The actions of the checkpoint's TorchRL actor as the evaluator flies it
    (``ExplorationType.DETERMINISTIC``), one batch."""
    from torchrl.data import Bounded

    dim = state["net"]["action_dim"]
    actor = actor_from_state(state, Bounded(-1.0, 1.0, shape=(dim,)))
    td = TensorDict(observation=obs, batch_size=[len(obs)])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return actor(td)["action"].numpy()


def samples(obs: np.ndarray, actions: np.ndarray, count: int = CARD_SAMPLES) -> list[dict]:
    """``count`` observations spread evenly over ``obs`` (first and last included) with their
    ``actions``, as the exact float32 values."""
    rows = np.unique(np.linspace(0, len(obs) - 1, count).round().astype(int))
    return [{"observation": obs[i].tolist(), "action": actions[i].tolist()} for i in rows]


def max_differences(actions: dict[str, np.ndarray]) -> dict[str, float]:
    """Largest |Δ action| of each pair of implementations, ``a_vs_b``."""
    names = list(actions)
    return {
        f"{a}_vs_{b}": float(np.abs(actions[a] - actions[b]).max())
        for i, a in enumerate(names)
        for b in names[i + 1 :]
    }


# The card -----------------------------------------------------------------------------------


def describe_lines(src: Source, env, features: list[dict[str, Any]]) -> list[str]:
    """The header comment of ``policy.h``: where the network came from and what it reads."""
    who = f"{src.cfg.drone.name} ({src.cfg.drone.learner})"
    lines = [f"Network: {who}; source checkpoint sha256:", f"  {src.sha256}"]
    if env.group is not None:
        lines.append(f"A team of {env.team_size} drones shares it: one call per drone and step.")
    lines += [
        "",
        f"Frame: {FRAME}.",
        "obs[i]: feature, unit (the network multiplies it by float32(1 / scale)):",
    ]
    lines += [
        f"  [{i}] {f['name']}, {f['unit']} (scale {f['scale']:g})" for i, f in enumerate(features)
    ]
    if getattr(env.action_fn, "guided", False):
        lines += ["", *env.action_fn.describe()]
    for name, model in host_models(env).items():  # the numbers too, not only card.json's
        numbers = ", ".join(f"{k} {_number(v)}" for k, v in model.items()
                            if k != "model" and not isinstance(v, str))  # fmt: skip
        words = "".join(f" {k.capitalize()}: {v}." for k, v in model.items()
                        if k != "model" and isinstance(v, str))  # fmt: skip
        lines += ["", *textwrap.wrap(f"{name}, computed by the host: {model['model']}; "
                                     f"{numbers}.{words}", 76)]  # fmt: skip
    return lines


def _number(value: Any) -> str:
    """A setting in the header: ``0.9``, ``0.9 0.9 0.35``, ``null``."""
    if isinstance(value, (list, tuple)):
        return " ".join(_number(v) for v in value)
    return "null" if value is None else f"{value:g}"


def action_line(env) -> str:
    """What ``rlplat_policy``'s action is, next to its declaration in ``policy.h``."""
    if getattr(env.action_fn, "guided", False):
        return (
            "in [-1, 1]; not the velocity command itself: the guidance law above makes the "
            "velocity command of it."
        )
    return VELOCITY_ACTION


def network_card(actor: DeterministicActor, state: dict[str, Any]) -> dict[str, Any]:
    net = state["net"]
    params = sum(p.numel() for p in actor.mlp.parameters())
    return {
        "layers": actor.layers(),
        "hidden": list(net["actor_cells"]),
        "activation": net["activation"],
        "parameters": params,
        "action_margin": actor.action_margin,
        "output": (
            f"action = clamp({1 + actor.action_margin:g} * tanh(loc), -1, 1), loc = the first "
            f"{actor.action_dim} outputs of the last layer (the others set the spread of the "
            "trained stochastic policy and are not used)"
        ),
    }


#: :func:`rlplat.envs.kinematics.route_path` as a formula, with the card's ``lag``, ``gain``,
#: ``acceptance`` (tests/test_export.py computes it from this text's steps).
ROUTE_PATH_FORMULA = (
    "p_0 = the defender's position, p_1..p_S its route's setpoints from its current one on "
    "(the last repeated to S), V its maximum speed per axis; leg i runs from p_(i-1) to p_i. "
    "d_i = max over axes of |p_i - p_(i-1)|; lag_i = lag if d_i > 0 else 0, and lag_1 is "
    "multiplied by clamp(1 - u / V, 0, 1), u the defender's velocity on leg 1's longest axis "
    "(the first such axis), signed towards p_1; approach_i = 0 if gain is infinite, else "
    "max(0, max(d_i - n, 0) / V + ln(max(min(d_i, n), acceptance) / acceptance) / gain - "
    "d_i / V) with n = max(V / gain, acceptance); arrive_i = sum over j <= i of (lag_j + "
    "d_j / V + approach_j), arrive_0 = 0; start_i = arrive_(i-1) + lag_i. At time t the leg "
    "flown is the first i with arrive_i > t (leg S past every arrival) and the position is, "
    "per axis, p_(i-1) + sign(p_i - p_(i-1)) * min(|p_i - p_(i-1)|, max(t - start_i, 0) * V)"
)


#: How the meeting point's search decides that a point of the path is reachable
#: (rlplat.envs.kinematics.route_intercept), as the card words it.
REACHABLE_RULE = (
    "a point at time t counts when the attacker's largest per-axis gap to it is at most "
    "max_speed * max(t - start_lag, 0) + reach_m; t runs over resolution_s, 2 * resolution_s, "
    "... up to the horizon, and the first that counts is the meeting point"
)


#: Which setpoint of its route a defender flies to (the observation's ``setpoint`` and
#: ``next_setpoint``), as the card words it.
SETPOINT_RULE = (
    "setpoint = the route setpoint the defender flies to: its route's first at the episode's "
    "start; it moves on to the next when, after a step, the defender (not caught before that "
    "step) is within acceptance m of it (Euclidean distance); past the route's end it stays "
    "the route's last. next_setpoint = the one after it (the route's last past the end)"
)


def host_models(env) -> dict[str, dict[str, Any]]:
    """What the caller computes itself for the observation and the law, with its numbers: the
    route setpoint the observation reads, the meeting point's route path and the route
    conformity features (none for other drones)."""
    models: dict[str, dict[str, Any]] = {}
    path = route_path_interface(env)
    uses, whose = [], []  # what reads the setpoint, and whose it is there
    if any("setpoint" in name for name in env.obs_fn.own_names):
        uses.append("the observation's setpoint features")
        whose.append("the observation's setpoint features: the scenario's first defender, for "
                     "every attacker, caught or not")  # fmt: skip
    if path is not None:
        uses.append("the route path")
        whose.append("route_path: each defender's own")
    if uses:
        models["route_setpoint"] = {
            "model": f"rlplat.envs.pursuit (the defender's waypoint), for {' and '.join(uses)}",
            "rule": SETPOINT_RULE,
            "defender": "the drone itself"
            if ROLES[env.learner] == "defender"
            else "; ".join(whose),
            "acceptance": env.setpoint_acceptance,
        }
    if path is not None:  # the meeting point the caller computes, from this path
        models["route_path"] = {
            "model": "rlplat.envs.kinematics.route_path (velocity lag, setpoint gain, acceptance), "
            "from the defender's position, velocity, maximum speed and route ahead; the meeting "
            "point is its earliest point the attacker reaches at full speed per axis after "
            "start_lag s, within horizon s from now (rlplat.envs.kinematics.route_intercept)",
            **path,
            "path": ROUTE_PATH_FORMULA,
            "horizon": env.meeting_horizon,  # the seconds searched (a null setting: the limit)
            "resolution_s": ROUTE_RESOLUTION,  # the instants tried: every resolution_s s
            "reach_m": env.capture_radius,  # a point within this of the attacker's reach counts
            "reachable": REACHABLE_RULE,
            "unreachable": "where no instant counts, the point is the path's at the horizon "
            "(the route's end if it gets there sooner), its time the horizon, reachable 0",
            "defender": "each attacker's nearest defender not yet caught (by distance); its "
            "position, velocity, maximum speed and the setpoints of its route from its current "
            "one on",
        }
    if getattr(env.obs_fn, "reads_conformity", False):  # features the caller computes, with state
        models["route_conformity"] = {
            "model": "route_residual = a - (c - v) * (1 - exp(-dt / route_lag)) / dt per axis, "
            "a the defender's mean acceleration over the last control period dt, v its velocity "
            "and c its setpoint follower's command (rlplat.envs.kinematics.follow_route) at the "
            "period's start (0 from the step after its capture); route_deviation += "
            "(||route_residual|| - route_deviation) * (1 - exp(-dt / conformity_time)), "
            "||.|| the Euclidean norm over the three axes; both 0 at the episode's start",
            "command": "c = clamp(setpoint_gain * (s - p), -V, V) per axis, p the defender's "
            "position, V its maximum speed per axis and s its current setpoint; c = 0 once its "
            "route is done. It moves on to the next setpoint when, after a step, it is within "
            "acceptance m of s (Euclidean distance); past the route's end the setpoint and the "
            "next one are its last setpoint",
            "acceptance": env.setpoint_acceptance,
            "route_lag": list(env.obs_fn.route_lag),
            "conformity_time": env.obs_fn.conformity_time,
            "control_period": env.control_period,
            "setpoint_gain": env.setpoint_gain,
        }
    return models


def onnx_metadata(src: Source, interface: dict[str, Any]) -> dict[str, str]:
    """The ONNX model's metadata (``rlplat.*`` keys, string values): the drone and its role,
    the source checkpoint's sha256, the scenario digest it was trained on (empty if not
    recorded) and the card's ``interface`` as JSON (sorted keys): nothing that depends on
    where or when the export ran."""
    return {
        "rlplat.format_version": "1",
        "rlplat.drone": str(src.cfg.drone.name),
        "rlplat.learner": str(src.cfg.drone.learner),
        "rlplat.source_sha256": src.sha256,
        "rlplat.scenario_digest": src.scenario_digest or "",
        "rlplat.interface": json.dumps(interface, sort_keys=True),
    }


def interface_card(src: Source, env, actor: DeterministicActor, features) -> dict[str, Any]:
    """What the artifacts read and write, feature by feature, and who calls them."""
    action = {
        "name": src.cfg.action.name,
        "dim": actor.action_dim,
        "range": [-1.0, 1.0],
        "features": ["v_cmd.x", "v_cmd.y", "v_cmd.z"][: actor.action_dim],
        "unit": "1: times the drone's maximum speed per axis (m/s) = the velocity command",
    }
    if getattr(env.action_fn, "guided", False):
        card = env.action_fn.card()
        action.update(card, features=card["features"][: actor.action_dim])
    interface = {
        "frame": FRAME,
        "observation": {"name": src.cfg.observation.name, "dim": actor.obs_dim,
                        "features": features},
        "action": action,
        "team": {"attackers": env.num_attackers, "defenders": env.num_defenders,
                 "drones_sharing_the_policy": env.team_size},
    }  # fmt: skip
    interface.update(host_models(env))
    return interface


def measure_timing(header, source, onnx_policy, obs: np.ndarray, calls: int, compiler: str):
    """The C function per call (``calls``, after a tenth as many), ONNX Runtime per call (a
    tenth) and per batch of :data:`ONNX_BATCH` (a hundredth), on rows of ``obs``."""
    return {
        "c": time_c(header, source, obs[: ONNX_BATCH * 10], calls=calls,
                    warmup=max(calls // 10, 1), compiler=compiler),
        "onnxruntime_per_call": time_onnx(onnx_policy, obs, batch=1, calls=max(calls // 10, 1)),
        f"onnxruntime_per_batch_{ONNX_BATCH}": time_onnx(
            onnx_policy, obs, batch=ONNX_BATCH, calls=max(calls // 100, 1)
        ),
    }  # fmt: skip


def load_average() -> list[float] | None:
    """The system's 1-, 5- and 15-minute load averages (None where the system has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_card(compiler: str) -> dict[str, Any]:
    """Where the figures were measured (``load_average``: now; the export samples it again
    right after timing)."""
    return {
        "cpu": cpu_model(),
        "compiler": compiler_version(compiler),
        "system": f"{platform.system()} {platform.release()} {platform.machine()}",
        "python": platform.python_version(),
        "torch": torch.__version__,
        "onnxruntime": version("onnxruntime"),
        "onnx": version("onnx"),
        "load_average": load_average(),
    }


def earlier_timing(
    out_dir: Path, files: dict[str, Any], machine: dict[str, Any], calls: int
) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """The timing and machine of ``out_dir/card.json`` when that card timed the same artifacts
    (``files``: their hashes and sizes) with ``calls`` C calls on this machine (``machine``
    but its load); else None."""
    try:
        card = json.loads((out_dir / "card.json").read_text())
        timing, earlier = card["timing"], card["machine"]
        same = (
            card["files"] == files
            and timing["c"]["calls"] == calls
            and {k: v for k, v in earlier.items() if k != "load_average"}
            == {k: v for k, v in machine.items() if k != "load_average"}
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (timing, earlier) if same else None


# Export -------------------------------------------------------------------------------------


def export_run(
    run_dir: str | Path | None = None,
    *,
    ckpt: str = "best",
    controller: str | Path | None = None,
    out_dir: str | Path | None = None,
    scenarios_dir: str | Path | None = None,
    split: str = "test",
    min_observations: int = 10_000,
    tolerance: float = 1e-5,
    timing_calls: int = 100_000,
    compiler: str = "cc",
    retime: bool = False,
    prefix: str = C_PREFIX,
) -> dict[str, Any]:
    """Export the policy of ``run_dir``'s checkpoint ``ckpt`` (or of a ``controller`` file) and
    return its card; see the module docstring for what is written. ``prefix`` starts the C
    names (``<prefix>_policy``, ``<PREFIX>_OBS_DIM``, ...).

    Raises:
        ConfigError: bad input (no such run, checkpoint or tool, another interface, a layer the
            C generator does not know), before any work.
        ExportError: the implementations differ by more than ``tolerance``; nothing written.
    """
    # Everything is checked before any work starts.
    if (run_dir is None) == (controller is None):
        raise ConfigError(
            f"run_dir: set either run_dir=DIR (a training run) or controller=FILE, got "
            f"run_dir={run_dir}, controller={controller}"
        )
    if controller is not None and out_dir is None:
        raise ConfigError(f"out_dir: a controller export needs out_dir, got {out_dir}")
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    check_prefix(prefix)
    _check_tools()
    compiler = find_compiler(compiler)
    if controller is not None:
        src = controller_source(Path(controller), out_dir, scenarios_dir)
    else:
        src = run_source(Path(run_dir), ckpt, out_dir, scenarios_dir)
    refuse_run_dir(src.out_dir, "out_dir", "the export's files would mix with the run's "
                   "(choose a folder of its own, e.g. <run>/export/NAME)")  # fmt: skip
    check_writable_dir(src.out_dir, "out_dir")
    scenarios = resolve_scenarios(src.cfg, src.scenarios_dir)
    same_set = check_scenarios(
        scenarios, src.scenario_digest, False, f"recorded with {src.path}", "exporting"
    )
    require_scenarios(scenarios, [split], "the export (its rollouts)")
    n = len(scenarios.split(split))
    env = build_eval_env(src.cfg, scenarios=scenarios, split=split, num_envs=n)
    check_policy_fits(src.state, src.cfg, env, src.path, settings="scenarios_dir", job="export",
                      field="ckpt" if controller is None else "controller")  # fmt: skip
    actor = DeterministicActor.from_state(src.state)
    actor.layers()  # a layer the C generator does not know fails here

    # Observations from rollouts of the split, flown by the checkpoint's actor.
    t0 = time.perf_counter()
    flying = actor_from_state(src.state, env.drone_action_spec, "cpu", env.group)
    obs, about = collect_observations(env, flying, observation_key(env.group), min_observations)
    log.info("%d observations from rollouts of %d %s scenarios in %.1f s",
             len(obs), n, split, time.perf_counter() - t0)  # fmt: skip

    # The artifacts, in memory.
    features = env.obs_fn.features()
    interface = interface_card(src, env, actor, features)
    model = onnx_bytes(actor, onnx_metadata(src, interface))
    header, source = c_sources(actor, describe_lines(src, env, features), action_line(env), prefix)

    # Equivalence: torch, ONNX Runtime and C on every observation.
    onnx_policy = OnnxPolicy(model, actor.obs_dim, actor.action_dim)
    c_policy, diagnostics = build_library(header, source, actor.obs_dim, actor.action_dim, compiler)
    if diagnostics:
        log.warning("the compiler warned about policy.c: %s", diagnostics.splitlines()[0])
    x = obs.numpy()
    actions = {"torch": torch_actions(src.state, obs), "onnx": onnx_policy(x), "c": c_policy(x)}
    diffs = max_differences(actions)
    if np.ptp(actions["torch"], axis=0).max() == 0:  # one action for every observation
        one = actions["torch"][0].tolist()
        log.warning("export: the actor gives one action, %s, on all %d rollout observations: "
                    "the equivalence check tests no network (a run that stopped before "
                    "algo.actor_warmup_updates?)", one, len(x))  # fmt: skip
    worst = max(diffs, key=diffs.get)
    if diffs[worst] > tolerance:
        raise ExportError(
            f"export: {worst.replace('_vs_', ' and ')} differ by {diffs[worst]:.3g} on rollout "
            f"observations, more than tolerance={tolerance:g}; nothing written"
        )

    # Timing on this machine (or the replaced card's, of the same artifacts here), then the
    # card; the artifacts are written first, the card (which names their hashes) last.
    files = {"policy.onnx": model, "policy.h": header.encode(), "policy.c": source.encode()}
    files_card = {k: {"sha256": sha256_bytes(v), "bytes": len(v)} for k, v in files.items()}
    machine = machine_card(compiler)
    kept = None if retime else earlier_timing(src.out_dir, files_card, machine, timing_calls)
    if kept is None:
        timing = measure_timing(header, source, onnx_policy, x, timing_calls, compiler)
        machine["load_average"] = load_average()  # what ran beside the timing, not before it
    else:
        timing, machine = kept
        log.info("timing kept from %s (the same artifacts timed on this machine); "
                 "retime=true measures again", src.out_dir / "card.json")  # fmt: skip
    card = {
        "format_version": 1,
        "source": {
            **src.described,
            "path": str(src.path),
            "sha256": src.sha256,
            "drone": src.cfg.drone.name,
            "learner": src.cfg.drone.learner,
            "scenario_digest": src.scenario_digest,
        },
        "interface": {**interface, "c_api": c_api(prefix)},
        "network": network_card(actor, src.state),
        "files": files_card,
        "equivalence": {
            "observations": {**about, "split": split, "scenarios": n,
                             "scenario_digest": scenarios.digest,
                             "scenario_digest_matches": same_set},
            "max_abs_action_difference": diffs,
            "tolerance": tolerance,
            "samples": samples(x, actions["torch"]),
        },
        "timing": timing,
        "machine": machine,
    }  # fmt: skip
    for name, data in files.items():
        atomic_write_bytes(src.out_dir / name, data)
    atomic_write_text(src.out_dir / "card.json", json.dumps(card, indent=2) + "\n")
    log.info("wrote %s", src.out_dir)
    return {**card, "out_dir": str(src.out_dir)}


def export_from_config(cfg: DictConfig) -> list[str]:
    """What ``export.py`` does with its config (conf/export.yaml); returns the lines to print."""
    validate_export_config(cfg)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    card = export_run(
        cfg.run_dir,
        ckpt=str(cfg.ckpt),
        controller=cfg.controller,
        out_dir=cfg.out_dir,
        scenarios_dir=cfg.scenarios_dir,
        split=cfg.split,
        min_observations=cfg.min_observations,
        tolerance=cfg.tolerance,
        timing_calls=cfg.timing_calls,
        compiler=cfg.compiler,
        retime=cfg.retime,
        prefix=cfg.prefix,
    )
    eq, t = card["equivalence"], card["timing"]
    d = eq["max_abs_action_difference"]
    batch = t[f"onnxruntime_per_batch_{ONNX_BATCH}"]
    return [
        f"max |action difference| on {eq['observations']['count']} rollout observations: "
        f"torch-ONNX {d['torch_vs_onnx']:.2g}, torch-C {d['torch_vs_c']:.2g}, "
        f"ONNX-C {d['onnx_vs_c']:.2g} (tolerance {eq['tolerance']:g})",
        f"C call: median {t['c']['median_us']:.3f} us, p99 {t['c']['p99_us']:.3f} us, "
        f"max {t['c']['max_us']:.1f} us over {t['c']['calls']} calls; ONNX Runtime: "
        f"{t['onnxruntime_per_call']['median_us']:.1f} us per call, "
        f"{batch['median_us']:.0f} us per batch of {ONNX_BATCH}",
        f"wrote {', '.join(FILES)} to {card['out_dir']}",
    ]
