"""The training run: SAC over the batched pursuit env, validation, checkpoints, summary.

``train(cfg)`` is what ``train.py`` calls; tests and notebooks call it the same way.
"""

from __future__ import annotations

import json
import logging
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import RewardSum, TransformedEnv
from torchrl.envs.utils import ExplorationType
from tqdm import tqdm

from rlplat.agents.checkpoint import (
    check_compatible,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from rlplat.agents.metrics import Metrics, make_logger, plot_learning_curve
from rlplat.agents.sac import SACAgent, net_spec
from rlplat.agents.transitions import agent_rows, n_step_transitions, shape_rewards
from rlplat.config import checked_threads
from rlplat.envs.factory import build_env, resolve_scenarios
from rlplat.errors import ConfigError
from rlplat.eval.baselines import BASELINES, NoisyPolicy, make_baseline
from rlplat.eval.episodes import SCORE_NAME, EpisodeResults, evaluate
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)

#: What the replay buffer keeps of each transition.
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


#: Who flies the first ``algo.init_random_frames`` frames, which fill the replay buffer:
#: uniform random actions, or a classical controller of the learner's role (plus noise).
INIT_POLICIES = ("random", *BASELINES)

#: The scripted controller each learner is measured against on the validation split.
REFERENCE = {"attacker": "pure_pursuit", "defender": "setpoint_follower"}


@dataclass(frozen=True)
class Budget:
    """When a run stops: whichever of frames or wall-clock minutes comes first."""

    frames: int
    minutes: float | None

    @classmethod
    def from_cfg(cls, node) -> Budget:
        frames, minutes = node.total_frames, node.max_minutes
        if not isinstance(frames, int) or frames <= 0:
            raise ConfigError(f"train.total_frames: must be a positive integer, got {frames}")
        if minutes is not None and not minutes > 0:
            raise ConfigError(f"train.max_minutes: must be > 0 or null, got {minutes}")
        return cls(frames, None if minutes is None else float(minutes))


def _positive(node, where: str, *keys: str) -> None:
    for key in keys:
        value = node[key]
        if not value > 0:
            raise ConfigError(f"{where}.{key}: must be > 0, got {value}")


def _run_dir(run_dir: str | Path | None) -> Path:
    if run_dir is not None:
        return Path(run_dir)
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        raise ConfigError("run_dir: not under @hydra.main; pass train(cfg, run_dir=...)")
    return Path(HydraConfig.get().runtime.output_dir)


def _interface(cfg: DictConfig, env) -> dict[str, Any]:
    """The drone interface a checkpoint is bound to: the learner, its observation and action,
    and how many drones of each role flew (what the observation's blocks are)."""
    return {
        "drone.learner": cfg.drone.learner,
        "observation.name": cfg.observation.name,
        "action.name": cfg.action.name,
        "attackers": env.num_attackers,
        "defenders": env.num_defenders,
    }


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> dict[str, Any]:
    """Train the configured learner with SAC; returns the run's summary (also summary.json).

    The run directory receives ``config.yaml`` (resolved), ``checkpoints/{best,last}.pt``,
    ``metrics/`` (CSV), ``learning_curve.png`` and ``summary.json``.
    """
    # Everything is checked before any work starts.
    run_dir = _run_dir(run_dir)
    budget = Budget.from_cfg(cfg.train)
    algo = cfg.algo
    _positive(algo, "algo", "num_envs", "frames_per_batch", "batch_size", "buffer_size")
    _positive(cfg.train, "train", "eval_every_frames")
    if algo.frames_per_batch % algo.num_envs:
        raise ConfigError(
            f"algo.frames_per_batch: {algo.frames_per_batch} is not a multiple of "
            f"algo.num_envs={algo.num_envs}"
        )
    if not algo.utd_ratio > 0:
        raise ConfigError(f"algo.utd_ratio: must be > 0, got {algo.utd_ratio}")
    if not isinstance(algo.n_steps, int) or algo.n_steps < 1:
        raise ConfigError(f"algo.n_steps: must be an integer >= 1, got {algo.n_steps}")
    valid_init = [
        k for k in INIT_POLICIES if k == "random" or BASELINES[k].role == cfg.drone.learner
    ]
    if algo.init_policy not in valid_init:
        why = "unknown" if algo.init_policy not in INIT_POLICIES else "not for this learner"
        raise ConfigError(
            f"algo.init_policy: {why} '{algo.init_policy}'; valid: {', '.join(valid_init)}"
        )
    if not algo.init_noise >= 0:
        raise ConfigError(f"algo.init_noise: must be >= 0, got {algo.init_noise}")
    if algo.potential_weight and algo.potential_key not in ("distance",):
        raise ConfigError(f"algo.potential_key: unknown '{algo.potential_key}'; valid: distance")
    role = cfg.drone.learner
    score_name = SCORE_NAME.get(role, "capture_rate")
    keep = (*TRANSITION_KEYS, "steps_to_next_obs") if algo.n_steps > 1 else TRANSITION_KEYS
    threads = checked_threads(cfg.train.threads, "train.threads")
    device = torch.device(cfg.train.device)
    ckpt_dir = run_dir / "checkpoints"
    resume_state = None
    if cfg.resume:
        resume_state = load_checkpoint(ckpt_dir / "last.pt")

    if threads is not None:
        # On a few cores, runs side by side (hydra/launcher=joblib) want one thread each:
        # torch's threads wait for each other on every small kernel when a core is taken.
        torch.set_num_threads(threads)
    scenarios = resolve_scenarios(cfg, cfg.scenarios_dir)
    env = build_env(cfg, scenarios=scenarios, split="train", num_envs=algo.num_envs, device=device)
    terms = list(env.reward_fn.weights)
    train_env = TransformedEnv(
        env,
        RewardSum(
            in_keys=["reward", *[("reward_terms", k) for k in terms]],
            out_keys=["episode_reward", *[("episode_terms", k) for k in terms]],
        ),
    )
    n_val = len(scenarios.split("val"))
    val_env = build_env(
        cfg, scenarios=scenarios, split="val", num_envs=n_val, device=device,
        scenario_order="sequential",
    )  # fmt: skip
    net = net_spec(env.obs_fn.scale, env.drone_action_spec.shape[-1], algo)
    if resume_state is not None:
        check_compatible(resume_state, net, _interface(cfg, env), ckpt_dir / "last.pt")

    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    env.set_seed(cfg.seed)
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
        compile=algo.compile,
        group=env.group,
        device=device,
    )
    counters = {"frames": 0, "updates": 0, "evals": 0, "wall_time_s": 0.0}
    best = {"score": -1.0, "capture_rate": -1.0, "mean_return": -float("inf"), "frames": 0}
    if resume_state is not None:
        agent.load_state_dict(resume_state["agent"])
        counters.update(resume_state["counters"])
        best.update(resume_state["best"])
        if "score" not in resume_state["best"]:  # written before scores were role-aware
            best["score"] = best["capture_rate"]
        set_rng_state(resume_state["rng"])
        env.sampler.generator.set_state(resume_state["scenario_rng"])
        log.info("resuming %s at %d frames", run_dir, counters["frames"])

    run_dir.mkdir(parents=True, exist_ok=True)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(resolved))
    metrics = Metrics(run_dir, make_logger(cfg.logger, run_dir, cfg.drone.name, resolved))

    # The scripted reference on the same validation split: the rate a policy has to beat.
    reference = evaluate(val_env, make_baseline(REFERENCE[role], val_env))
    metrics.log({f"reference/{k}": v for k, v in reference.summary().items()}, counters["frames"])
    log.info("%s on the validation split: %s", REFERENCE[role], _outcome(reference, role))

    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(algo.buffer_size, device=device),
        batch_size=algo.batch_size,
    )
    # The buffer is not checkpointed: a resumed run refills it (see the scripted start below).
    learning_starts = algo.init_random_frames
    # A scripted init_policy fills the buffer before the collector starts, also on a resume;
    # otherwise the collector starts with random actions, or with the policy on a resume.
    scripted_start = algo.init_policy != "random" and learning_starts > 0
    collector = Collector(
        train_env,
        agent.policy,
        frames_per_batch=algo.frames_per_batch,
        total_frames=-1,
        init_random_frames=0 if resume_state is not None or scripted_start else learning_starts,
        exploration_type=ExplorationType.RANDOM,
        device=device,
        auto_register_policy_transforms=False,  # a memoryless MLP policy: no transforms needed
    )

    def payload() -> dict[str, Any]:
        return {
            "net": net.as_dict(),
            "interface": _interface(cfg, env),
            "actor": agent.actor.state_dict(),
            "agent": agent.state_dict(),
            "counters": dict(counters),
            "best": dict(best),
            "rng": rng_state(),
            "scenario_rng": env.sampler.generator.get_state(),
            "scenario_digest": scenarios.digest,
            "config": resolved,
        }

    def validate() -> EpisodeResults:
        t0 = time.perf_counter()
        results = evaluate(val_env, agent.policy)
        counters["evals"] += 1
        values = {f"eval/{k}": v for k, v in results.summary().items()}
        values["time/eval_s"] = time.perf_counter() - t0
        values["time/elapsed_s"] = time.perf_counter() - start
        metrics.log(values, counters["frames"])
        better = (results.score(role), results.mean_return) > (best["score"], best["mean_return"])
        if better:
            best.update(
                score=results.score(role),
                capture_rate=results.capture_rate,
                mean_return=results.mean_return,
                frames=counters["frames"],
            )
            save_checkpoint(ckpt_dir / "best.pt", payload())
        log.info(
            "frames %d: validation %s, mean return %.2f%s",
            counters["frames"],
            _outcome(results, role),
            results.mean_return,
            " (best)" if better else "",
        )
        return results

    start = time.perf_counter() - counters["wall_time_s"]
    deadline = None if budget.minutes is None else start + 60.0 * budget.minutes
    if scripted_start:
        prefilled = _prefill(buffer, train_env, env, algo, keep)
        if resume_state is None:  # a resumed run has counted those frames already
            counters["frames"] += prefilled
        log.info(
            "replay buffer filled with %d frames of noisy %s (%d transitions)",
            prefilled,
            algo.init_policy,
            len(buffer),
        )
    next_eval = (
        counters["frames"] // cfg.train.eval_every_frames + 1
    ) * cfg.train.eval_every_frames
    update_credit = 0.0
    bar = tqdm(
        total=budget.frames,
        initial=counters["frames"],
        unit="frame",
        unit_scale=True,
        disable=not cfg.train.progress,
        dynamic_ncols=True,
    )
    last_val = best["score"] if best["score"] >= 0 else float("nan")
    frames_at_start, session_start = counters["frames"], time.perf_counter()
    try:
        for batch in collector:
            t_collected = time.perf_counter()
            n = batch.numel()
            counters["frames"] += n
            _store(buffer, batch, algo, keep, env.group)
            values = _episode_metrics(batch, terms)

            # The buffer holds one transition per learning drone and frame.
            if len(buffer) >= max(learning_starts * env.team_size, algo.batch_size):
                update_credit += n * algo.utd_ratio
                losses = []
                while update_credit >= 1.0:
                    losses.append(agent.update(buffer.sample()))
                    update_credit -= 1.0
                    counters["updates"] += 1
                if losses:
                    values.update(
                        {
                            f"train/{k}": torch.stack([x[k] for x in losses]).mean().item()
                            for k in losses[0]
                        }
                    )
            now = time.perf_counter()
            counters["wall_time_s"] = now - start
            values["time/update_s"] = now - t_collected
            values["time/frames_per_s"] = (counters["frames"] - frames_at_start) / (
                now - session_start
            )
            values["train/updates"] = counters["updates"]
            metrics.log(values, counters["frames"])

            out_of_budget = counters["frames"] >= budget.frames or (
                deadline is not None and now >= deadline
            )
            if counters["frames"] >= next_eval or out_of_budget:
                last_val = validate().score(role)
                next_eval += cfg.train.eval_every_frames
                counters["wall_time_s"] = time.perf_counter() - start
                save_checkpoint(ckpt_dir / "last.pt", payload())
            bar.update(n)
            bar.set_postfix({f"val_{score_name}": f"{last_val:.2f}"}, refresh=False)
            if out_of_budget:
                break
    finally:
        bar.close()
        collector.shutdown()

    # Test the best policy on the test split.
    best_state = load_checkpoint(ckpt_dir / "best.pt")
    agent.actor.load_state_dict(best_state["actor"])
    n_test = len(scenarios.split("test"))
    test_env = build_env(
        cfg, scenarios=scenarios, split="test", num_envs=n_test, device=device,
        scenario_order="sequential",
    )  # fmt: skip
    test = evaluate(test_env, agent.policy)
    metrics.log({f"test/{k}": v for k, v in test.summary().items()}, counters["frames"])
    summary = {
        "frames": counters["frames"],
        "updates": counters["updates"],
        "wall_time_s": round(counters["wall_time_s"], 3),
        "val_score": score_name,
        "best_val_score": best["score"],
        "best_val_capture_rate": best["capture_rate"],
        "best_val_mean_return": best["mean_return"],
        "best_frames": best["frames"],
        "reference_policy": REFERENCE[role],
        "reference_val_score": reference.score(role),
        "reference_val_capture_rate": reference.capture_rate,
        "test_score": test.score(role),
        "test_capture_rate": test.capture_rate,
        "test_mean_return": test.mean_return,
        "test_route_fraction": test.route_fraction.mean().item(),
        "test_mean_time_to_capture_s": test.summary().get("mean_time_to_capture_s"),
        "test_scenarios": n_test,
        "scenario_digest": scenarios.digest,
        "scenario_dir": str(scenarios.path),
        "drone": cfg.drone.name,
        "attackers": scenarios.attackers,
        "defenders": scenarios.defenders,
        "seed": cfg.seed,
        "run_dir": str(run_dir),
    }
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    plot_learning_curve(metrics.history, run_dir / "learning_curve.png")
    metrics.close()
    log.info(
        "test %s (%d scenarios), mean return %.2f; run directory %s",
        _outcome(test, role),
        n_test,
        test.mean_return,
        run_dir,
    )
    return summary


def _outcome(results: EpisodeResults, role: str) -> str:
    """The capture rate, and a defender's evasion score before it, for a log line."""
    text = f"capture rate {results.capture_rate:.3f}"
    if SCORE_NAME[role] != "capture_rate":
        text = f"{SCORE_NAME[role].replace('_', ' ')} {results.score(role):.3f}, {text}"
    return text


def _prefill(buffer, train_env, env, algo, keep) -> int:
    """Fill the replay buffer with ``algo.init_random_frames`` frames of the scripted
    ``algo.init_policy`` plus Gaussian noise (``algo.init_noise``); returns the frames."""
    policy = NoisyPolicy(make_baseline(algo.init_policy, env), algo.init_noise, env.action_key)
    steps = algo.frames_per_batch // algo.num_envs
    frames, td = 0, train_env.reset()
    while frames < algo.init_random_frames:
        trajectory = []
        for _ in range(steps):  # what a collector does, with a scripted policy
            out, td = train_env.step_and_maybe_reset(policy(td))
            trajectory.append(out)
        batch = torch.stack(trajectory, dim=1)  # (envs, time), as a collector's batch
        _store(buffer, batch, algo, keep, env.group)
        frames += batch.numel()
    return frames


def _store(buffer, batch, algo, keep, group: str | None) -> None:
    """Add a collected ``(envs, time)`` batch to the buffer as what the learner trains on:
    a row per drone of a team, shaped rewards, n-step transitions, only the ``keep`` keys."""
    if group is not None:
        batch = agent_rows(batch, group)
    transitions = shape_rewards(batch, algo.potential_key, algo.potential_weight, algo.gamma)
    transitions = n_step_transitions(transitions, algo.n_steps, algo.gamma)
    if group is None:
        buffer.extend(transitions.select(*keep).reshape(-1))
        return
    flat = transitions.select(*keep, "alive").reshape(-1)
    buffer.extend(flat[flat["alive"].squeeze(-1)].exclude("alive"))  # a caught drone is out


def _episode_metrics(batch, terms: list[str]) -> dict[str, float]:
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
