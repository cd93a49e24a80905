"""The training run: SAC over the batched pursuit env, validation, checkpoints, summary.

``train(cfg)`` is what ``train.py`` calls; tests and notebooks call it the same way. It reads
like TorchRL's ``sota-implementations/sac/sac.py``: ``make_*`` helpers build the parts, one
linear loop collects, stores and updates, and validation and the end-of-run test are functions
of a :class:`Run` (what a run is made of) and its :class:`RunState` (what it has done so far).
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import math
import os
import random
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor
from torchrl.collectors import Collector
from torchrl.envs import RewardSum, TransformedEnv
from torchrl.envs.utils import ExplorationType
from tqdm import tqdm

from rlplat.agents.checkpoint import (
    check_compatible,
    check_route_path,
    check_same_interface,
    check_same_net,
    embedded_networks,
    load_checkpoint,
    rng_state,
    route_path_interface,
    save_checkpoint,
    saved_interface,
    set_rng_state,
)
from rlplat.agents.plays import AimPlay, Plays, load_plays
from rlplat.agents.policies import REFERENCE, NoisyPolicy, make_scripted_policy
from rlplat.agents.sac import NetSpec, SACAgent, actor_body, make_replay_buffer, net_spec
from rlplat.agents.self_imitation import SelfImitation
from rlplat.agents.transitions import replay_rows
from rlplat.envs.pursuit import ROLES, PursuitEnv, flown_attackers
from rlplat.errors import ConfigError, DivergenceError
from rlplat.eval.episodes import SCORE_NAME, EpisodeResults, evaluate
from rlplat.eval.metrics import wilson_interval
from rlplat.eval.plots import plot_learning_curve
from rlplat.experiment.evaluation import plain_action
from rlplat.experiment.factory import (
    build_env,
    build_eval_env,
    require_scenarios,
    resolve_scenarios,
    with_set_scenario,
)
from rlplat.experiment.logger import Metrics, check_logger, make_logger
from rlplat.experiment.schema import check_resume, validate_train_config
from rlplat.io import atomic_write_text
from rlplat.scenarios import SPLITS, STRATEGIES, ScenarioSet

log = logging.getLogger(__name__)

#: The embedded model a run that trains on AirSim validates and tests on (see make_eval_env).
VALIDATION_DYNAMICS = "velocity"


@dataclass
class RunState:
    """What a run has done so far: its counters and its best validation (checkpointed)."""

    frames: int = 0
    updates: int = 0
    evals: int = 0
    wall_time_s: float = 0.0
    best_score: float = -1.0
    best_capture_rate: float = -1.0
    best_mean_return: float = -float("inf")
    best_frames: int = 0

    COUNTERS = ("frames", "updates", "evals", "wall_time_s")

    def as_checkpoint(self) -> dict[str, dict[str, Any]]:
        """The ``counters`` and ``best`` entries of a checkpoint."""
        best = {
            k.removeprefix("best_"): v for k, v in asdict(self).items() if k.startswith("best_")
        }
        return {"counters": {k: getattr(self, k) for k in self.COUNTERS}, "best": best}

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any]) -> RunState:
        best = dict(state["best"])
        best.setdefault("score", best["capture_rate"])  # written before role-aware scores
        return cls(**state["counters"], **{f"best_{k}": v for k, v in best.items()})


@dataclass
class Run:
    """What one training run is made of (everything :func:`validate` and checkpoints need)."""

    run_dir: Path
    role: str
    env: PursuitEnv  # the training env (its scenario walk is checkpointed)
    val_env: PursuitEnv
    scenarios: ScenarioSet
    agent: SACAgent
    net: NetSpec
    interface: dict[str, Any]
    config: dict[str, Any]  # resolved
    metrics: Metrics | None = None
    keep_checkpoints: bool = False  # each validation's checkpoint as val-<frames>.pt too

    @property
    def ckpt_dir(self) -> Path:
        return self.run_dir / "checkpoints"


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> dict[str, Any]:
    """Train the configured learner with SAC; returns the run's summary (also summary.json).

    The run directory receives ``config.yaml`` (resolved), ``checkpoints/{best,last}.pt``,
    ``metrics/`` (CSV), ``learning_curve.png`` and ``summary.json``.
    """
    # Check everything before any work starts.
    field = "hydra.run.dir" if run_dir is None else "run_dir"
    run_dir = make_run_dir(run_dir)
    begin = checked_start(cfg, run_dir, field)
    cfg, scenarios, config, algo = begin.cfg, begin.scenarios, begin.config, begin.cfg.algo
    resume_state, init = begin.resume_state, begin.init
    if cfg.train.threads is not None:
        # On a few cores, runs side by side (hydra/launcher=joblib) want one thread each:
        # torch's threads wait for each other on every small kernel when a core is taken.
        torch.set_num_threads(cfg.train.threads)
    device = torch.device(cfg.train.device)

    # Create the environments
    evaders = network_defenders(scenarios, algo.evader_weight)
    env = build_env(cfg, scenarios=scenarios, split="train", num_envs=algo.num_envs, device=device)
    train_env = make_train_env(env)
    val_env = make_eval_env(cfg, scenarios, "val", device, compiled=True)
    if cfg.dynamics.name == "airsim":
        log.info("training on AirSim (%s); validation and the final test fly on the embedded "
                 "%s model", ", ".join(cfg.dynamics.endpoints), VALIDATION_DYNAMICS)  # fmt: skip
    net = net_spec(env.obs_fn.scale, env.drone_action_spec.shape[-1], algo)
    interface = make_interface(cfg, env)
    if resume_state is not None:
        check_compatible(resume_state, net, interface, run_dir / "checkpoints" / "last.pt")

    # Create the agent
    seed_everything(cfg.seed, env)
    agent = make_agent(net, env, algo, device)
    if init is not None:
        warm_start(agent, *init, net, interface, env)
    run = Run(run_dir, cfg.drone.learner, env, val_env, scenarios, agent, net, interface, config,
              keep_checkpoints=cfg.train.keep_checkpoints)  # fmt: skip
    state = RunState()
    if resume_state is not None:
        state = RunState.from_checkpoint(resume_state)
        agent.load_state_dict(resume_state["agent"])
        set_rng_state(resume_state["rng"])
        env.sampler.set_state(resume_state["scenario_rng"])
        log.info("resuming %s at %d frames", run_dir, state.frames)
    done_before = resume_state is not None and state.frames >= cfg.train.total_frames
    if done_before:
        log.warning("train.total_frames=%d: the run has %d frames already; nothing is "
                    "trained, the best checkpoint is tested again (a larger "
                    "train.total_frames trains on)", cfg.train.total_frames,
                    state.frames)  # fmt: skip

    # Create the logger; measure the scripted reference on the validation split
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(config))
    run.metrics = Metrics(
        run_dir, make_logger(cfg.logger, run_dir, cfg.drone.name, config), resume=cfg.resume
    )
    reference = fly_reference(cfg, run, "val", device)
    run.metrics.log({f"reference/{k}": v for k, v in reference.summary().items()}, state.frames)
    log.info("%s on the validation split: %s", REFERENCE[run.role], outcome(reference, run.role))
    if algo.failure_weight != 1.0 or algo.evader_weight != 1.0:
        weight_scenarios(cfg, run, algo, evaders, device)

    # Create the replay buffer and the collector
    # Not checkpointed: a resumed run refills it (see the scripted start below).
    buffer = make_replay_buffer(algo, device)
    # A scripted init_policy fills the buffer before the collector starts, also on a resume;
    # otherwise the collector starts with random actions, or with the policy on a resume.
    # A warm start (init_from) flies its own policy from the first frame.
    scripted_start = init is None and algo.init_policy != "random" and algo.init_random_frames > 0
    own_policy = resume_state is not None or init is not None
    random_frames = 0 if own_policy or scripted_start else algo.init_random_frames
    collector = make_collector(train_env, agent.collect_policy, algo, random_frames, device)
    imitation = None
    if algo.self_imitation > 0:
        bootstrap = algo.self_imitation_truncated == "bootstrap"
        imitation = SelfImitation(
            agent, num_envs=algo.num_envs, gamma=algo.gamma, lr=algo.self_imitation,
            bootstrap=bootstrap, device=device,
        )  # fmt: skip

    # Scripted start
    start = time.perf_counter() - state.wall_time_s
    deadline = None if cfg.train.max_minutes is None else start + 60.0 * cfg.train.max_minutes
    if scripted_start and not done_before:
        # The scripted start's frames count toward the budget: a fresh run's stops with it.
        fill = algo.init_random_frames
        if resume_state is None and cfg.train.total_frames < fill:
            fill = cfg.train.total_frames
            log.warning("train.total_frames=%d is under algo.init_random_frames=%d: the run is "
                        "the scripted start alone, without a gradient update",
                        cfg.train.total_frames, algo.init_random_frames)  # fmt: skip
        prefilled = prefill(buffer, train_env, env, algo, fill, deadline)
        if resume_state is None:  # a resumed run has counted those frames already
            state.frames += prefilled
        log.info("replay buffer filled with %d frames of noisy %s (%d transitions)",
                 prefilled, algo.init_policy, len(buffer))  # fmt: skip
    for plays in [] if done_before else begin.plays:
        if not plays.scenario_ids:
            log.warning("algo.demonstrations: %s holds no play that captured", plays.path)
            continue
        demos, captured = demonstrations(cfg, scenarios, plays, device)
        for _ in range(algo.demonstration_repeat):
            buffer.extend(demos)
        log.info("replay buffer: %d transitions of the %d of %d plays (%s) that capture "
                 "through the action, stored %d times", demos.shape[0], captured,
                 len(plays.scenario_ids), plays.path, algo.demonstration_repeat)  # fmt: skip

    # Validate the policy as initialised: best.pt is never worse than where learning started,
    # and last.pt is where a run stopped before its first validation in the loop resumes from
    if resume_state is None:
        validate(run, state, start)

    # Training loop (none when the scripted start spent the budget)
    spent = state.frames >= cfg.train.total_frames or (
        deadline is not None and time.perf_counter() >= deadline
    )
    if resume_state is None or spent:
        state.wall_time_s = time.perf_counter() - start  # what a resume counts on from
        save_checkpoint(run.ckpt_dir / "last.pt", checkpoint(run, state))
    every = cfg.train.eval_every_frames
    next_eval = (state.frames // every + 1) * every
    update_credit, last_val = 0.0, state.best_score if state.best_score >= 0 else float("nan")
    progress = Progress(cfg.train, state, start)
    frames_at_start, session_start = state.frames, time.perf_counter()
    try:
        for batch in () if spent else collector:
            t_collected = time.perf_counter()
            state.frames += batch.numel()
            buffer.extend(replay(batch, env.group, algo))
            if imitation is not None:
                imitation.observe(batch)
            values = episode_metrics(batch, list(env.reward_fn.weights))

            # Optimization: the buffer holds one transition per learning drone and frame.
            if len(buffer) >= max(algo.init_random_frames * env.team_size, algo.batch_size):
                update_credit += batch.numel() * algo.utd_ratio
                losses = []
                while update_credit >= 1.0:
                    held = state.updates < algo.actor_warmup_updates
                    with held_actor(agent, held):
                        losses.append(agent.update_from(buffer))
                    if imitation and not held and state.updates % algo.self_imitation_every == 0:
                        values.update(imitation.step())
                    agent.average_actor()
                    update_credit -= 1.0
                    state.updates += 1
                if losses:
                    stacked = {k: torch.stack([x[k] for x in losses]) for k in losses[0]}
                    values.update({f"train/{k}": v.mean().item() for k, v in stacked.items()})

            # Logging
            now = time.perf_counter()
            state.wall_time_s = now - start
            values["time/update_s"] = now - t_collected
            values["time/frames_per_s"] = (state.frames - frames_at_start) / (now - session_start)
            values["train/updates"] = state.updates
            run.metrics.log(values, state.frames)
            check_finite(values, state)  # after the log, which then shows where it diverged

            # Validation and the last checkpoint
            out_of_budget = state.frames >= cfg.train.total_frames or (
                deadline is not None and now >= deadline
            )
            if state.frames >= next_eval or out_of_budget:
                last_val = validate(run, state, start).score(run.role)
                next_eval += every
                state.wall_time_s = time.perf_counter() - start
                save_checkpoint(run.ckpt_dir / "last.pt", checkpoint(run, state))
            progress.update(state, last_val)
            if out_of_budget:
                break
    except BaseException:
        run.metrics.close()  # what was logged reaches every logger (wandb, TensorBoard)
        raise
    finally:
        progress.close()
        collector.shutdown()
    if state.frames < cfg.train.total_frames:
        log.warning(
            "train.max_minutes=%s reached at %d of train.total_frames=%d frames: "
            "the run stopped on the clock, so a re-run of this seed may stop elsewhere",
            cfg.train.max_minutes, state.frames, cfg.train.total_frames,
        )  # fmt: skip

    # Test the best policy on the test split
    summary = test_best(cfg, run, state, reference, device)
    plot_learning_curve(run.metrics.history, run_dir / "learning_curve.png", REFERENCE[run.role])
    run.metrics.close()
    return summary


# Set-up ----------------------------------------------------------------------------------


@dataclass
class Start:
    """What a run starts from, checked (:func:`checked_start`)."""

    cfg: DictConfig  # with scenarios_dir, its scenario node is the set's own config
    scenarios: ScenarioSet
    config: dict[str, Any]  # cfg resolved: what config.yaml records
    resume_state: dict[str, Any] | None  # with resume: the run's last.pt
    init: tuple[Path, dict[str, Any]] | None  # init_from's path and checkpoint
    plays: list[Plays]  # of algo.demonstrations


def checked_start(cfg: DictConfig, run_dir: Path | None, field: str = "hydra.run.dir") -> Start:
    """The config a run flies, checked, and what it starts from: its scenario set (with
    ``scenarios_dir``, the set's own scenario config replaces the composed one: what it
    flies, recorded), the run directory (``run_dir`` named by ``field``; None: not known
    yet) and, with ``resume``, its checkpoint against this config, ``init_from`` and
    ``algo.demonstrations``."""
    validate_train_config(cfg)
    check_logger(cfg.logger)
    cfg = with_absolute_paths(cfg)  # hydra.job.chdir=true moves the job, not its paths
    scenarios = resolve_scenarios(cfg, cfg.scenarios_dir)
    require_scenarios(scenarios, SPLITS, "training")  # it validates, and tests at its end
    attackers = flown_attackers(cfg.env.attackers, scenarios)
    network_defenders(scenarios, cfg.algo.evader_weight)  # both kinds where they are weighted
    learners = attackers if cfg.drone.learner == "attacker" else scenarios.defenders
    imitation = cfg.algo.self_imitation
    if imitation > 0 and learners > 1:
        raise ConfigError(f"algo.self_imitation: {imitation} is a lone learner's option; "
                          f"this run trains a team of {learners} {cfg.drone.learner}s (set it "
                          "to 0)")  # fmt: skip
    if imitation > 0 and cfg.algo.potential_weight != 0:
        raise ConfigError(f"algo.self_imitation: {imitation} compares the env's returns with "
                          "critics that learn a shaped reward (algo.potential_weight="
                          f"{cfg.algo.potential_weight}); set algo.potential_weight=0")  # fmt: skip
    if cfg.scenarios_dir is not None:
        cfg = with_set_scenario(cfg, scenarios)
    config = OmegaConf.to_container(cfg, resolve=True)  # its paths absolute already
    resume_state = None
    if run_dir is not None:
        check_run_dir(run_dir, cfg.resume, field)
        if cfg.resume:
            resume_state = load_resume_state(run_dir, config)
    plays = [checked_plays(cfg, scenarios, path) for path in cfg.algo.demonstrations]
    return Start(cfg, scenarios, config, resume_state, warm_start_state(cfg), plays)


def check_run_dir(run_dir: Path, resume: bool, field: str = "hydra.run.dir") -> None:
    """Refuse a run directory that holds a run (its ``config.yaml``, written before its
    first frame, or its ``checkpoints/last.pt``) without ``resume=true``, which would mix two
    runs' checkpoints and metrics, and ``resume=true`` where there is no run to continue (a
    run stopped in its scripted start, before it validated, has none)."""
    last = run_dir / "checkpoints" / "last.pt"
    stopped = (run_dir / "config.yaml").is_file() and not last.is_file()
    if stopped:  # e.g. in its scripted start, before the validation that writes last.pt
        raise ConfigError(
            f"{'resume: true, and ' if resume else ''}{field}: {run_dir} holds a run that "
            f"stopped before it saved a checkpoint to continue from (no {last.name}); another "
            "directory starts a new one"
        )
    if resume and not last.is_file():
        raise ConfigError(
            f"resume: true, and {field}={run_dir} holds no run to continue (no {last.name})"
        )
    if not resume and (last.is_file() or (run_dir / "summary.json").is_file()):
        raise ConfigError(
            f"{field}: {run_dir} holds a run already; resume=true continues it, another "
            "directory starts a new one"
        )


def preflight(cfg: DictConfig, run_dir: Path | None, field: str = "hydra.run.dir") -> None:
    """What :func:`train` checks before its first frame, done before a command line's run
    directory is made (``train.py``): the config, the scenario set, the run directory (with
    ``resume``: the saved config and networks), ``init_from``, ``algo.demonstrations`` and,
    on the embedded dynamics, the env the config builds (its components together, the
    defender network). ``run_dir`` None: where it is not known before Hydra starts (a job
    of a sweep past the jobs checked one by one). Warnings of the set or the env show here
    and again in the job; an uncached scenario set is generated here, in the launching
    process."""
    start = checked_start(cfg, run_dir, field)
    cfg = start.cfg
    if cfg.dynamics.name == "airsim":
        from rlplat.envs.airsim.settings import vehicle_names

        flown = flown_attackers(cfg.env.attackers, start.scenarios)
        vehicle_names(flown, start.scenarios.defenders, names=cfg.dynamics.get("vehicles"))
        # Building its env connects to the simulators, which train() does; here, for a run
        # launched here, only whether each answers, so that a simulator not started leaves no
        # run directory behind (a sweep's jobs may run where their simulators are: a cluster).
        if field == "hydra.run.dir":
            from rlplat.envs.airsim.client import check_simulators

            check_simulators(cfg.dynamics)
        return
    env = build_env(cfg, scenarios=start.scenarios, split="train", num_envs=1)
    net = net_spec(env.obs_fn.scale, env.drone_action_spec.shape[-1], cfg.algo)
    interface = make_interface(cfg, env)
    if start.resume_state is not None:
        check_compatible(start.resume_state, net, interface, run_dir / "checkpoints" / "last.pt")
    if start.init is not None:
        warm_start_features(*start.init, net, interface, env)
    env.close()


def make_run_dir(run_dir: str | Path | None) -> Path:
    """The given run directory, or Hydra's output directory under ``@hydra.main``."""
    if run_dir is not None:
        return Path(run_dir)
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        raise ConfigError("run_dir: not under @hydra.main; pass train(cfg, run_dir=...)")
    return Path(HydraConfig.get().runtime.output_dir)


def load_resume_state(run_dir: Path, config: dict[str, Any]) -> dict[str, Any]:
    """The run's ``last.pt``, after checking that this config is the one it was trained with
    (only the budget and speed settings may change on a resume, see ``check_resume``)."""
    state = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    check_resume(absolute_paths(state["config"]), config)  # one saved as typed, as it flew
    return state


#: The settings that name files: a run records them absolute, so that its config.yaml reads
#: the same from any working directory (evaluate.py, export.py, a resume elsewhere).
PATH_SETTINGS = (("scenarios_dir",), ("init_from",), ("env", "defender_network"),
                 ("algo", "demonstrations"))  # fmt: skip


def launch_dir() -> str:
    """Where the command was started: Hydra's ``runtime.cwd`` inside a job (whose working
    directory ``hydra.job.chdir=true`` moves into the run), else the working directory."""
    from hydra.core.hydra_config import HydraConfig

    return HydraConfig.get().runtime.cwd if HydraConfig.initialized() else os.getcwd()


def _absolute(value: Any) -> str | list[str]:
    """A path (or a list of paths) made absolute against :func:`launch_dir`."""
    if isinstance(value, (list, tuple)) or OmegaConf.is_list(value):
        return [_absolute(v) for v in value]
    return os.path.abspath(os.path.join(launch_dir(), str(value)))


def absolute_paths(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` (a resolved config as a dict) with every :data:`PATH_SETTINGS` path made
    absolute against :func:`launch_dir`; a copy."""
    out = copy.deepcopy(config)
    for keys in PATH_SETTINGS:
        node = out
        for key in keys[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
        if not isinstance(node, dict) or node.get(keys[-1]) is None:
            continue
        node[keys[-1]] = _absolute(node[keys[-1]])
    return out


def with_absolute_paths(cfg: DictConfig) -> DictConfig:
    """``cfg`` with every :data:`PATH_SETTINGS` path absolute against :func:`launch_dir`
    (a path on the command line is where the user typed it); a copy."""
    cfg = copy.deepcopy(cfg)
    for keys in PATH_SETTINGS:
        key = ".".join(keys)
        value = OmegaConf.select(cfg, key)
        if value is not None:
            OmegaConf.update(cfg, key, _absolute(value), merge=False)
    return cfg


def warm_start_state(cfg: DictConfig) -> tuple[Path, dict[str, Any]] | None:
    """``init_from``'s checkpoint (a run directory: its ``checkpoints/best.pt``), loaded;
    None without one or on a resume (which continues from its own ``last.pt``)."""
    if cfg.init_from is None or cfg.resume:
        return None
    path = Path(cfg.init_from)
    if path.is_dir():
        path = path / "checkpoints" / "best.pt"
    if not path.is_file():
        raise ConfigError(f"init_from: no checkpoint at {path} (a run directory or a .pt file)")
    try:
        return path, load_checkpoint(path)
    except ConfigError as e:
        raise ConfigError(f"init_from: {e}") from None


def warm_start(agent: SACAgent, path: Path, state: dict[str, Any], net: NetSpec,
               interface: dict[str, Any], env: PursuitEnv) -> None:  # fmt: skip
    """Start the agent's actor, critics and entropy coefficient at a checkpoint's, and fly
    the actor it flew (its moving average where it kept one); the optimisers and the replay
    buffer start afresh. The checkpoint must share the drone's interface and network sizes;
    one trained alone may start a team of its role against as many opponents (each drone then
    reads it on its ``lone_features``, its team-mates with zero weights), as ``evaluate.py
    lone_in_team=true`` flies it."""
    features = warm_start_features(path, state, net, interface, env)
    agent.load_networks(*embedded_networks(state, net, features))
    alone = len(features) < net.obs_dim
    log.info("networks start at %s%s", path, ", in each seat of the team" if alone else "")


def warm_start_features(
    path: Path, state: dict[str, Any], net: NetSpec, interface: dict[str, Any], env: PursuitEnv
) -> list[int] | range:
    """Check that ``state`` can start this run (:func:`warm_start`) and return the features
    of this run's observation its networks read: all, or a lone drone's in a team."""
    if "agent" not in state:  # an actor alone: nothing to start the critics from
        raise ConfigError(
            f"init_from: {path} holds a policy alone (a controller file, no critics or "
            "entropy coefficient), not a training checkpoint; give a run directory or its "
            "checkpoints/*.pt"
        )
    saved, here = saved_interface(state), dict(interface)
    here.pop("route_path", None)  # checked below
    learners = "attackers" if ROLES[env.learner] == "attacker" else "defenders"
    alone = saved[learners] == 1 < here[learners]
    if alone:
        saved[learners] = here[learners]  # a lone drone's network starts each of the team's
    check_same_interface(saved, here, path, "init_from")
    # In-play flags come with more than one defender, as for evaluate.py's lone_in_team.
    features = env.obs_fn.lone_features(saved["defenders"] > 1) if alone else range(net.obs_dim)
    sizes = {k: v for k, v in net.as_dict().items() if k not in ("obs_dim", "obs_scale")}
    check_same_net(state, {**sizes, "obs_dim": len(features)}, path, "init_from")
    check_route_path(state, env, path, "init_from")  # last: it may only warn, about a fitting one
    return features


def make_interface(cfg: DictConfig, env: PursuitEnv) -> dict[str, Any]:
    """The drone interface a checkpoint is bound to: the learner, its observation and action,
    how many drones of each role flew (what the observation's blocks are) and, where the env
    computes the meeting point, the defender's path it assumes."""
    interface = {
        "drone.learner": cfg.drone.learner,
        "observation.name": cfg.observation.name,
        "action.name": cfg.action.name,
        "attackers": env.num_attackers,
        "defenders": env.num_defenders,
    }
    path = route_path_interface(env)
    if path is not None:
        interface["route_path"] = path
    return interface


def make_train_env(env: PursuitEnv) -> TransformedEnv:
    """The training env: episode sums of the reward and of each weighted term."""
    terms = list(env.reward_fn.weights)
    return TransformedEnv(
        env,
        RewardSum(
            in_keys=["reward", *[("reward_terms", k) for k in terms]],
            out_keys=["episode_reward", *[("episode_terms", k) for k in terms]],
        ),
    )


def make_eval_env(
    cfg: DictConfig, scenarios: ScenarioSet, split: str, device, *, compiled: bool = False
) -> PursuitEnv:
    """One env per scenario of ``split``, walked in order (:func:`build_eval_env`): eager, or
    with ``compiled`` as ``env.compile_step`` says (the validations and the reference flown
    beside them; the test split is flown eagerly, as ``evaluate.py`` flies it).

    A run that trains on AirSim validates (and tests) on the embedded ``velocity`` model, with
    its defaults (simple_flight's fit): the simulators are the collector's, whose episodes in
    flight a validation there would cut; ``evaluate.py run_dir=... dynamics=airsim`` flies the
    trained policy on AirSim afterwards."""
    if cfg.dynamics.name == "airsim":
        cfg = cfg.copy()
        cfg.dynamics = OmegaConf.create({"name": VALIDATION_DYNAMICS})
    n = len(scenarios.split(split))
    compile_step = compiled and bool(cfg.env.compile_step)
    return build_eval_env(
        cfg, scenarios=scenarios, split=split, num_envs=n, device=device, compile_step=compile_step
    )


def fly_reference(cfg: DictConfig, run: Run, split: str, device) -> EpisodeResults:
    """The scripted reference on ``split``: through the run's action where a scripted command
    can be flown through it, else on the plain velocity action."""
    if split == "val":
        env = run.val_env
    else:
        env = make_eval_env(cfg, run.scenarios, split, device, compiled=True)
    if not getattr(env.action_fn, "invertible", True):
        env = make_eval_env(plain_action(cfg), run.scenarios, split, device, compiled=True)
    return evaluate(env, make_scripted_policy(REFERENCE[run.role], env))


def network_defenders(scenarios: ScenarioSet, evader_weight: float) -> torch.Tensor:
    """(n,) bool: the train scenarios with a defender that flies the network. Weighting them
    (``algo.evader_weight``) needs both kinds in the split.

    Raises:
        ConfigError: a weight other than 1 and a split of one kind only.
    """
    train = scenarios.split("train")
    evades = (train["defender_strategy"] == STRATEGIES.index("nn")).any(-1).cpu()
    k, n = int(evades.sum()), len(train)
    if evader_weight != 1.0 and not 0 < k < n:
        raise ConfigError(
            f"algo.evader_weight: {evader_weight:g} weights the network defenders' scenarios "
            f"against the others; the train split has {k} of {n}"
        )
    return evades


def weight_scenarios(
    cfg: DictConfig, run: Run, algo: DictConfig, evades: torch.Tensor, device
) -> None:
    """Replace the training env's walk over the train split by weighted draws.

    ``algo.failure_weight``: the scenarios the scripted reference fails (an attacker: no
    capture; a defender: caught; the reference flown once on the train split) are drawn that
    many times as often; where the reference already succeeds there is little to learn. With
    ``algo.failure_evaders_only``, only those with a network defender.
    ``algo.evader_weight``: the scenarios with a defender that flies the trained network
    (strategy ``nn``, the one that leaves its route to evade) are drawn that many times as
    often; where a law meets a route flyer on its route, an attacker's learned correction is
    for those. A scenario's weight is the product of the two."""
    n = len(evades)
    failed = torch.zeros(n, dtype=torch.bool)
    if algo.failure_weight != 1.0:
        flown = fly_reference(cfg, run, "train", device)
        lost = ~flown.captured if run.role == "attacker" else flown.captured
        failed[flown.scenario_index.cpu()] = lost.cpu()
        if algo.get("failure_evaders_only", False):
            failed &= evades
    weight = torch.where(failed, algo.failure_weight, 1.0)
    weight = torch.where(evades, algo.evader_weight * weight, weight)
    run.env.sampler.set_weights(weight)

    def share(drawn: torch.Tensor) -> float:  # percent of the episodes
        return 100 * float(weight[drawn].sum() / weight.sum())

    if algo.failure_weight != 1.0:
        log.info("%s fails %d of %d train scenarios; drawn %g times as often: %.0f %% of "
                 "episodes", REFERENCE[run.role], int(failed.sum()), n, algo.failure_weight,
                 share(failed))  # fmt: skip
    if algo.evader_weight != 1.0:
        log.info("%d of %d train scenarios have a network defender; drawn %g times as often: "
                 "%.0f %% of episodes", int(evades.sum()), n, algo.evader_weight,
                 share(evades))  # fmt: skip


def seed_everything(seed: int, env: PursuitEnv) -> None:
    """The run's one root seed: torch, numpy, Python and the env's scenario walk."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    env.set_seed(seed)


def make_agent(net: NetSpec, env: PursuitEnv, algo: DictConfig, device) -> SACAgent:
    agent = SACAgent(
        net,
        env.drone_action_spec,
        gamma=algo.gamma,
        tau=algo.tau,
        actor_lr=algo.actor_lr,
        critic_lr=algo.critic_lr,
        alpha_lr=algo.alpha_lr,
        alpha_init=algo.alpha_init,
        target_entropy=algo.target_entropy,
        loss_function=algo.loss_function,
        anchor_weight=algo.anchor_weight,
        actor_average=algo.actor_average,
        compile=algo.compile,
        noise_correlation=algo.noise_correlation,
        group=env.group,
        device=device,
    )
    if algo.actor_zero_mean or algo.actor_init_std is not None:
        init_actor_output(agent.actor, net.action_dim, algo.actor_zero_mean, algo.actor_init_std)
        agent.restart_average()
    return agent


def init_actor_output(actor, action_dim: int, zero_mean: bool, std: float | None) -> None:
    """Start ``actor`` at a zero mean action (``zero_mean``: tanh of a zero mean) and/or at the
    pre-tanh spread ``std`` in every state: the output rows of its last layer that give the
    mean, the spread, or both, get zero weights and the bias that yields that output."""
    last = [m for m in actor_body(actor).modules() if isinstance(m, torch.nn.Linear)][-1]
    spread = [m for m in actor_body(actor).modules() if isinstance(m, NormalParamExtractor)][0]
    mapping = spread.scale_mapping  # biased softplus: std = softplus(x + bias) + min_val
    with torch.no_grad():
        if zero_mean:
            last.weight[:action_dim].zero_()
            last.bias[:action_dim].zero_()
        if std is not None:
            x = torch.tensor(float(std) - mapping.min_val)
            raw = x + torch.log(-torch.expm1(-x)) - mapping.bias  # inverse softplus, unbiased
            last.weight[action_dim:].zero_()
            last.bias[action_dim:].fill_(raw.item())


@contextlib.contextmanager
def held_actor(agent: SACAgent, hold: bool):
    """With ``hold``, the update leaves the actor's parameters as they were (they are put back
    in place afterwards) while the critics and the entropy coefficient learn. The first updates
    of a run train a critic that has not seen a return yet; an actor that follows its gradient
    then leaves the policy it started from (``algo.actor_warmup_updates``). The actor's Adam
    moments and step count run on, so that a compiled update sees every tensor as before."""
    if not hold:
        yield
        return
    params = [p for group in agent.optimizers["actor"].param_groups for p in group["params"]]
    saved = [p.detach().clone() for p in params]
    try:
        yield
    finally:
        with torch.no_grad():
            for p, before in zip(params, saved, strict=True):
                p.copy_(before)


def make_collector(env, policy, algo: DictConfig, init_random_frames: int, device) -> Collector:
    return Collector(
        env,
        policy,
        frames_per_batch=algo.frames_per_batch,
        total_frames=-1,
        init_random_frames=init_random_frames,
        exploration_type=ExplorationType.RANDOM,
        device=device,
        auto_register_policy_transforms=False,  # a memoryless MLP policy: no transforms needed
    )


# Replay ----------------------------------------------------------------------------------


def replay(batch, group: str | None, algo: DictConfig):
    """A collected batch as the transitions the replay buffer stores."""
    return replay_rows(
        batch,
        group=group,
        potential_key=algo.potential_key,
        potential_weight=algo.potential_weight,
        gamma=algo.gamma,
        n_steps=algo.n_steps,
    )


def prefill(
    buffer, train_env, env: PursuitEnv, algo: DictConfig, frames_wanted: int,
    deadline: float | None = None,
) -> int:  # fmt: skip
    """Fill the replay buffer with ``frames_wanted`` frames (whole batches of
    ``algo.frames_per_batch``; fewer if the clock passes ``deadline``) of the scripted
    ``algo.init_policy`` plus Gaussian noise (``algo.init_noise``, correlated in time by
    ``algo.noise_correlation``); returns the frames."""
    policy = NoisyPolicy(make_scripted_policy(algo.init_policy, env), algo.init_noise,
                         env.action_key, algo.noise_correlation)  # fmt: skip
    steps = algo.frames_per_batch // algo.num_envs
    frames, td = 0, train_env.reset()
    while frames < frames_wanted and (deadline is None or time.perf_counter() < deadline):
        trajectory = []
        for _ in range(steps):  # what a collector does, with a scripted policy
            out, td = train_env.step_and_maybe_reset(policy(td))
            trajectory.append(out)
        batch = torch.stack(trajectory, dim=1)  # (envs, time), as a collector's batch
        buffer.extend(replay(batch, env.group, algo))
        frames += batch.numel()
    return frames


def checked_plays(cfg: DictConfig, scenarios: ScenarioSet, path: str) -> Plays:
    """The plays of a file of ``algo.demonstrations`` that captured in their search, checked
    against the train split and the learner before any work: one line naming the field."""
    plays = load_plays(path).capturing()
    ids = set(scenarios.ids["train"])
    foreign = [i for i in plays.scenario_ids if i not in ids]
    if plays.split != "train":
        raise ConfigError(f"algo.demonstrations: {path} holds plays of the {plays.split} split; "
                          "valid: plays searched on the train split (--split train)")  # fmt: skip
    if foreign:
        raise ConfigError(f"algo.demonstrations: {path} holds plays of another scenario set "
                          f"({foreign[0]} is not in this train split)")  # fmt: skip
    if cfg.dynamics.name == "airsim":
        raise ConfigError("algo.demonstrations: plays are flown on the embedded dynamics, "
                          "got dynamics=airsim")  # fmt: skip
    attackers = flown_attackers(cfg.env.attackers, scenarios)
    if cfg.drone.learner != "attacker":
        raise ConfigError("algo.demonstrations: plays fly an attacker, drone.learner is the "
                          f"{cfg.drone.learner}")  # fmt: skip
    if attackers != 1:
        raise ConfigError(f"algo.demonstrations: plays are a lone attacker's, the run flies "
                          f"{attackers} attackers (scenario.attackers, env.attackers)")  # fmt: skip
    if plays.scenario_ids and plays.offset.shape[2] != 1:
        raise ConfigError(
            f"algo.demonstrations: {path} plays {plays.offset.shape[2]} attackers, the run "
            "flies 1; valid: plays searched with --attackers 1"
        )
    return plays


def demonstrations(
    cfg: DictConfig, scenarios: ScenarioSet, plays: Plays, device
) -> tuple[TensorDictBase, int]:
    """The transitions of ``plays`` (each on its own train scenario) flown through the
    learner's own action, as :func:`replay` stores them: every step of each play's first
    episode, for the plays that capture so (behind a shut gate the law flies, and an episode
    may leave its play); and how many of the plays those are."""
    algo, split = cfg.algo, "train"
    rows = torch.tensor([scenarios.ids[split].index(i) for i in plays.scenario_ids])
    flown = scenarios.picked(split, rows)
    env = build_eval_env(cfg, scenarios=flown, split=split, num_envs=len(rows), device=device)
    k = env.num_attackers
    per_part = -(-env.max_steps // plays.offset.shape[1])
    speed = env.scenarios["attacker_max_speed"][:, :k]  # env i flies scenario i (from seed 0)
    policy = AimPlay(plays.offset.to(device), plays.fraction.to(device), speed, per_part, k,
                     env.action_key, env=env)  # fmt: skip
    env.set_seed(0)  # env i flies play i from the start of its scenario
    batch = env.rollout(env.max_steps, policy, break_when_any_done=False)  # (N, T)
    env.close()
    done = batch["next", "done"].squeeze(-1)
    t = torch.arange(done.shape[1], device=done.device)
    first = torch.where(done.any(1), done.int().argmax(1), done.shape[1] - 1)
    episode = t <= first.unsqueeze(1)  # each env's first episode
    captured = (batch["next", "captured"].squeeze(-1) & episode).any(1)
    keep = (episode & captured.unsqueeze(1)).flatten()
    transitions = replay(batch, None, algo)  # (N * T,), each env's steps in order
    return transitions[keep], int(captured.sum())


# Validation, checkpoints, test -----------------------------------------------------------


def validation_checkpoint(frames: int) -> str:
    """The file name ``train.keep_checkpoints`` gives the checkpoint validated at ``frames``
    (zero-padded, so that the names sort as the frames do)."""
    return f"val-{frames:07d}.pt"


def checkpoint(run: Run, state: RunState) -> dict[str, Any]:
    """What ``best.pt`` and ``last.pt`` hold: the policy, the learner, the run's state."""
    return {
        "net": run.net.as_dict(),
        "interface": run.interface,
        "actor": run.agent.flown_actor.state_dict(),  # the weight average where there is one
        "agent": run.agent.state_dict(),
        **state.as_checkpoint(),
        "rng": rng_state(),
        "scenario_rng": run.env.sampler.get_state(),
        "scenario_digest": run.scenarios.digest,
        "config": run.config,
    }


def validate(run: Run, state: RunState, start: float) -> EpisodeResults:
    """Fly the validation split; keep the policy as ``best.pt`` if it beats the best so far
    (on the role's score, then the mean return), and as ``val-<frames>.pt`` with
    ``train.keep_checkpoints``."""
    t0 = time.perf_counter()
    results = evaluate(run.val_env, run.agent.flown_policy)
    state.evals += 1
    values = {f"eval/{k}": v for k, v in results.summary().items()}
    captured = int(results.captured.sum())
    low, high = wilson_interval(captured, results.captured.numel())
    values["eval/capture_rate_ci95_low"], values["eval/capture_rate_ci95_high"] = low, high
    values["time/eval_s"] = time.perf_counter() - t0
    values["time/elapsed_s"] = time.perf_counter() - start
    run.metrics.log(values, state.frames)
    score = results.score(run.role)
    if run.keep_checkpoints:
        save_checkpoint(run.ckpt_dir / validation_checkpoint(state.frames), checkpoint(run, state))
    better = (score, results.mean_return) > (state.best_score, state.best_mean_return)
    if better:
        state.best_score, state.best_capture_rate = score, results.capture_rate
        state.best_mean_return, state.best_frames = results.mean_return, state.frames
        save_checkpoint(run.ckpt_dir / "best.pt", checkpoint(run, state))
    mark = " (best)" if better else ""
    log.info("frames %d: validation %s, mean return %.2f%s", state.frames,
             outcome(results, run.role), results.mean_return, mark)  # fmt: skip
    return results


def test_best(
    cfg: DictConfig, run: Run, state: RunState, reference: EpisodeResults, device
) -> dict[str, Any]:
    """Fly the best policy on the test split; write and return the run's summary."""
    run.agent.flown_actor.load_state_dict(load_checkpoint(run.ckpt_dir / "best.pt")["actor"])
    test_env = make_eval_env(cfg, run.scenarios, "test", device)  # eager, as evaluate.py
    test = evaluate(test_env, run.agent.flown_policy)
    run.metrics.log({f"test/{k}": v for k, v in test.summary().items()}, state.frames)
    role, n_test = run.role, len(test_env.scenarios)
    summary = {
        "frames": state.frames,
        "updates": state.updates,
        "wall_time_s": round(state.wall_time_s, 3),
        "val_score": SCORE_NAME[role],
        "best_val_score": state.best_score,
        "best_val_capture_rate": state.best_capture_rate,
        "best_val_mean_return": state.best_mean_return,
        "best_frames": state.best_frames,
        "reference_policy": REFERENCE[role],
        "reference_val_score": reference.score(role),
        "reference_val_capture_rate": reference.capture_rate,
        "test_score": test.score(role),
        "test_capture_rate": test.capture_rate,
        "test_mean_return": test.mean_return,
        "test_route_fraction": test.route_fraction.mean().item(),
        "test_mean_time_to_capture_s": test.summary().get("mean_time_to_capture_s"),
        "test_scenarios": n_test,
        "scenario_digest": run.scenarios.digest,
        "scenario_dir": str(run.scenarios.path),
        "drone": cfg.drone.name,
        "attackers": run.scenarios.attackers,
        "defenders": run.scenarios.defenders,
        "seed": cfg.seed,
        "run_dir": str(run.run_dir),
    }
    atomic_write_text(run.run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    log.info("test %s (%d scenarios), mean return %.2f; run directory %s",
             outcome(test, role), n_test, test.mean_return, run.run_dir)  # fmt: skip
    return summary


# Reporting -------------------------------------------------------------------------------


def outcome(results: EpisodeResults, role: str) -> str:
    """The capture rate, and a defender's evasion score before it, for a log line."""
    text = f"capture rate {results.capture_rate:.3f}"
    if SCORE_NAME[role] != "capture_rate":
        text = f"{SCORE_NAME[role].replace('_', ' ')} {results.score(role):.3f}, {text}"
    return text


def check_finite(values: dict[str, float], state: RunState) -> None:
    """Stop a run whose ``train/*`` scalars (the losses, means over a batch's updates, and the
    returns of the episodes that ended in it) are no longer finite: every later update,
    validation and checkpoint would carry the NaN on. The checkpoints on disk are all from
    before: they are written at validations, after this check."""
    for key, value in values.items():
        if key.startswith("train/") and not math.isfinite(value):
            name = key.removeprefix("train/")
            raise DivergenceError(
                f"train: {name} is {value} in the updates up to {state.updates} "
                f"({state.frames} frames): the run diverged and stopped; its checkpoints are from "
                "before (lower algo.critic_lr / algo.actor_lr, or check the reward's scale)"
            )


def episode_metrics(batch, terms: list[str]) -> dict[str, float]:
    """Means over the training episodes that ended in this batch."""
    done = batch["next", "done"].squeeze(-1)
    if not done.any():
        return {}
    nxt = batch["next"]
    values = {
        "train/episode_return": nxt["episode_reward"][done].mean().item(),
        "train/capture_rate": nxt["captured"][done].float().mean().item(),
        "train/episodes": int(done.sum()),
    }
    values.update({f"reward/{k}": nxt["episode_terms", k][done].mean().item() for k in terms})
    return values


class Progress:
    """The progress bar, in percent of the budget: of ``train.total_frames``, or of
    ``train.max_minutes`` while the clock is further along (a run ends at the first budget
    reached)."""

    def __init__(self, node: DictConfig, state: RunState, start: float) -> None:
        self.start, self.frames = start, node.total_frames
        self.seconds = None if node.max_minutes is None else 60.0 * node.max_minutes
        self.bar = tqdm(
            total=100,
            initial=self._percent(state.frames, time.perf_counter() - start),
            unit="%",
            bar_format="{l_bar}{bar}| {elapsed}<{remaining}{postfix}",
            disable=not node.progress,
            dynamic_ncols=True,
        )

    def _percent(self, frames: int, seconds: float) -> int:
        done = frames / self.frames
        if self.seconds is not None:
            done = max(done, seconds / self.seconds)
        return min(100, int(100 * done))

    def update(self, state: RunState, last_val: float) -> None:
        done = self._percent(state.frames, time.perf_counter() - self.start)
        self.bar.update(max(0, done - self.bar.n))
        self.bar.set_postfix(
            {"frames": f"{state.frames:,}", "val": f"{last_val:.2f}"}, refresh=False
        )

    def close(self) -> None:
        self.bar.close()
