"""rlplat SAC against the paper's stack: Stable-Baselines3 SAC through the Gymnasium adapter.

One run, three tables, figures as ratios against SB3 measured in the same run:

(a) gradient updates per second at equal network (2x64 ReLU actor and critics) and batch (128),
    replay sampling included: SB3 ``SAC.train`` against rlplat's ``SACAgent.update_from`` (what
    the training loop calls), eager and with ``algo.compile=true`` (its compile time printed
    apart), timed in alternating rounds (the ratio is the median of the rounds', with range);
(b) frames per second of the whole training loop: SB3 ``learn`` with the paper's settings (one
    env, one update per step) against ``rlplat.agents.train`` with the default ``algo=sac``;
(c) wall-clock time until the validation capture rate reaches the threshold. Both policies are
    scored by the same evaluator (``rlplat.eval.evaluate``, deterministic, the whole
    validation split). SB3's clock stops while it is evaluated; rlplat's runs on, its own
    validations included. SB3 stops at its cap; a capped run reads "> cap".

    .venv/bin/python benchmarks/sac_vs_sb3.py [--threshold T] [--minutes 10] [--sb3-minutes 30]

The default threshold is the pure-pursuit capture rate on the validation split, capped at 0.9
(the training target). Parts can be run alone: ``--parts a`` takes about a minute.
"""

from __future__ import annotations

import argparse
import csv
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from rlplat.agents.policies import make_scripted_policy
from rlplat.agents.sac import SACAgent, net_spec
from rlplat.agents.transitions import TRANSITION_KEYS
from rlplat.eval.episodes import evaluate
from rlplat.experiment import train
from rlplat.experiment.config import compose_config
from rlplat.experiment.factory import build_env, resolve_scenarios

PAPER = "algo=sac_paper"


def fill_buffer(env, size: int) -> TensorDictReplayBuffer:
    """A replay buffer of ``size`` random-action transitions of ``env``."""
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(size), batch_size=128)
    td = env.reset()
    while len(buffer) < size:
        td = td.set("action", env.action_spec.rand())
        td, nxt = env.step_and_maybe_reset(td)
        buffer.extend(td.select(*TRANSITION_KEYS).clone())
        td = nxt
    return buffer


def sb3_model(gym_env, seed: int = 0):
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import Logger

    # The paper's settings; the rest are SB3's defaults.
    model = SAC(
        "MlpPolicy",
        gym_env,
        learning_rate=1e-3,
        batch_size=128,
        gamma=0.99,
        policy_kwargs={"net_arch": [64, 64]},
        seed=seed,
        device="cpu",
        verbose=0,
    )
    model.set_logger(Logger(folder=None, output_formats=[]))  # SB3's own makes a /tmp folder
    return model


def part_a(cfg, scenarios, updates: int, rounds: int) -> list[tuple[str, float, str]]:
    """Updates/s of SB3 and of rlplat (eager, compiled), timed in alternating rounds of
    ``updates / rounds`` updates each, so that a change of the machine's load falls on all
    three alike; each ratio is the median of the rounds' ratios, with their range."""
    from rlplat import make_gym_env

    gym_env = make_gym_env(PAPER, scenarios=scenarios)
    model = sb3_model(gym_env)
    obs, _ = gym_env.reset(seed=0)
    for _ in range(5000):
        action = gym_env.action_space.sample()
        nxt, reward, term, trunc, _ = gym_env.step(action)
        model.replay_buffer.add(
            obs[None], nxt[None], action[None], np.array([reward]), np.array([term]), [{}]
        )
        obs = gym_env.reset()[0] if term or trunc else nxt
    model.train(gradient_steps=20, batch_size=128)  # warm-up
    runs = {"SB3 SAC.train (reference)": lambda n: model.train(gradient_steps=n, batch_size=128)}

    env = build_env(cfg, scenarios=scenarios, split="train", num_envs=32)
    buffer = fill_buffer(env, 5000)
    for compile_ in (False, True):
        agent = SACAgent(
            net_spec(env.obs_fn.scale, env.action_spec.shape[-1], cfg.algo),
            env.action_spec[0],
            gamma=0.99,
            tau=0.005,
            actor_lr=1e-3,
            critic_lr=1e-3,
            alpha_lr=1e-3,
            compile=compile_,
        )
        t0 = time.perf_counter()
        for _ in range(20):  # warm-up (and compilation)
            agent.update_from(buffer)
        warm = time.perf_counter() - t0
        label = "rlplat SACAgent.update_from" + (f", compiled ({warm:.0f} s to compile)" * compile_)

        def run(n, agent=agent):
            for _ in range(n):  # what the training loop calls
                agent.update_from(buffer)

        runs[label] = run

    per_round = max(1, updates // rounds)
    seconds: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(rounds):
        for name, run in runs.items():
            t0 = time.perf_counter()
            run(per_round)
            seconds[name].append(time.perf_counter() - t0)
    sb3 = seconds[next(iter(runs))]
    rows = []
    for name, times in seconds.items():
        ratios = sorted(s / t for s, t in zip(sb3, times, strict=True))
        ratio = f"{np.median(ratios):.2f}x ({ratios[0]:.2f}-{ratios[-1]:.2f})"
        rows.append((name, per_round * rounds / sum(times), ratio))
    return rows


def sb3_until(cfg, scenarios, threshold: float, cap_s: float, eval_every: int) -> dict:
    """Train SB3 with the paper's settings until the threshold or the cap (training time)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from rlplat import make_gym_env

    val_env = build_env(
        cfg, scenarios=scenarios, split="val", num_envs=len(scenarios.split("val")),
        scenario_order="sequential",
    )  # fmt: skip
    model = sb3_model(make_gym_env(PAPER, scenarios=scenarios))

    def policy(td):
        with torch.no_grad():
            return td.set("action", model.policy.actor(td["observation"], deterministic=True))

    class Clock(BaseCallback):
        def __init__(self):
            super().__init__()
            self.train_s, self.mark, self.best, self.reached = 0.0, time.perf_counter(), 0.0, None
            self.history: list[tuple[float, float]] = []

        def _on_step(self) -> bool:
            if self.num_timesteps % eval_every:
                return True
            self.train_s += time.perf_counter() - self.mark
            rate = evaluate(val_env, policy).capture_rate
            self.best = max(self.best, rate)
            self.history.append((self.train_s, rate))
            logging.info("SB3 %d frames, %.0f s: capture rate %.3f", self.num_timesteps,
                         self.train_s, rate)  # fmt: skip
            if rate >= threshold:
                self.reached = self.train_s
            self.mark = time.perf_counter()
            return self.reached is None and self.train_s < cap_s  # stop at the target or cap

    clock = Clock()
    model.learn(total_timesteps=10**9, callback=clock)
    return {
        "frames": clock.num_timesteps,
        "train_s": clock.train_s,
        "fps": clock.num_timesteps / clock.train_s,
        "history": clock.history,
        "best": clock.best,
    }


def rlplat_until(overrides: list[str], minutes: float) -> dict:
    """The default training run; time to threshold from its validation log."""
    cfg = compose_config("train", ["train.progress=false", f"train.max_minutes={minutes}",
                                   "train.total_frames=1000000000", *overrides])  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        summary = train(cfg, run_dir=tmp)
        scalars = Path(tmp) / "metrics" / "scalars"

        def read(name):
            with open(scalars / f"{name}.csv") as fh:
                return [float(row[1]) for row in csv.reader(fh)]

        rates, elapsed = read("eval/capture_rate"), read("time/elapsed_s")
        fps = read("time/frames_per_s")[-1]
    return {
        "frames": summary["frames"],
        "train_s": summary["wall_time_s"],
        "fps": fps,
        "history": list(zip(elapsed, rates, strict=True)),
        "best": summary["best_val_capture_rate"],
        "summary": summary,
    }


def reached(history: list[tuple[float, float]], threshold: float) -> float | None:
    """Seconds until the first validation at or above ``threshold``; None if never."""
    return next((t for t, rate in history if rate >= threshold), None)


def table(title: str, header: tuple[str, ...], rows) -> None:
    print(f"\n{title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(str(x) for x in row) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="a,b,c", help="which tables: a, b, c")
    parser.add_argument("--updates", type=int, default=2000, help="updates timed in (a)")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds in (a)")
    parser.add_argument("--threshold", type=float, default=None, help="the target level")
    parser.add_argument("--levels", type=float, nargs="*", default=[0.3, 0.5],
                        help="further capture-rate levels timed in (c)")  # fmt: skip
    parser.add_argument("--minutes", type=float, default=10.0, help="rlplat's budget")
    parser.add_argument("--sb3-minutes", type=float, default=30.0, help="SB3's cap")
    parser.add_argument("--sb3-eval-every", type=int, default=10000, help="SB3 frames")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for both stacks")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    parts = set(args.parts.split(","))

    cfg = compose_config("train", [*args.overrides, PAPER])
    scenarios = resolve_scenarios(cfg, None)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    if "a" in parts:
        rows = part_a(cfg, scenarios, args.updates, args.rounds)
        table(
            "(a) gradient updates/s, actor and critics 2x64 ReLU, batch 128",
            ("implementation", "updates/s", "vs SB3 (median of rounds, range)"),
            [(name, f"{ups:,.0f}", ratio) for name, ups, ratio in rows],
        )
    if parts & {"b", "c"}:
        threshold = args.threshold
        if threshold is None:
            val_env = build_env(
                cfg, scenarios=scenarios, split="val", num_envs=len(scenarios.split("val")),
                scenario_order="sequential",
            )  # fmt: skip
            threshold = min(
                0.9, evaluate(val_env, make_scripted_policy("pure_pursuit", val_env)).capture_rate
            )
        ours = rlplat_until(args.overrides, args.minutes)
        sb3 = sb3_until(cfg, scenarios, threshold, 60 * args.sb3_minutes, args.sb3_eval_every)

        cap_sb3, cap_ours = 60 * args.sb3_minutes, 60 * args.minutes
        table(
            "(b) frames/s of the whole training loop",
            ("stack", "frames", "frames/s", "vs SB3"),
            [
                ("SB3 SAC, paper settings (reference)", sb3["frames"], f"{sb3['fps']:.0f}",
                 "1.00x"),
                ("rlplat, default algo=sac", ours["frames"], f"{ours['fps']:.0f}",
                 f"{ours['fps'] / sb3['fps']:.1f}x"),
            ],
        )  # fmt: skip
        rows = []
        for level in sorted({*args.levels, threshold}):
            t_sb3, t_ours = reached(sb3["history"], level), reached(ours["history"], level)
            if t_ours is None:
                ratio = "n/a (rlplat did not reach it)"
            elif t_sb3 is None:
                ratio = f"> {cap_sb3 / t_ours:.1f}x"
            else:
                ratio = f"{t_sb3 / t_ours:.1f}x"
            rows.append((
                f"{level:.2f}" + (" (target)" if level == threshold else ""),
                f"{t_sb3:.0f}" if t_sb3 is not None else f"> {cap_sb3:.0f}",
                f"{t_ours:.0f}" if t_ours is not None else f"> {cap_ours:.0f}",
                ratio,
            ))  # fmt: skip
        table(
            "(c) wall-clock seconds until the validation capture rate reaches each level "
            f"(best: SB3 {sb3['best']:.3f}, rlplat {ours['best']:.3f})",
            ("capture rate", "SB3 (reference)", "rlplat", "rlplat faster by"),
            rows,
        )
        run = ours["summary"]
        print(
            f"\nrlplat run: {run['frames']:,} frames, {run['updates']:,} updates in "
            f"{run['wall_time_s']:.0f} s; best validation capture rate "
            f"{run['best_val_capture_rate']:.3f} at {run['best_frames']:,} frames; "
            f"test capture rate {run['test_capture_rate']:.3f}; "
            f"pure pursuit on validation {run['reference_val_capture_rate']:.3f}"
        )


if __name__ == "__main__":
    main()
