"""Time the evaluator on a large test split: replay alone, and the whole evaluate_run.

    .venv/bin/python benchmarks/evaluation.py [--n 1000] [--run-dir DIR] [--threads 2 1]

Generates the default scenario family with ``--n`` test scenarios into a temporary directory.
The checkpoint policy is the best network of ``--run-dir``, evaluated on that set (its
scenario digest differs: the evaluator warns), or else of a training run of a few seconds on
that set (default networks, 2x64; what it learned does not matter for speed). Every episode
lasts up to 60 s (600 steps); all scenarios fly in one batch until the last one ends. Each
policy is timed with each torch thread count of ``--threads`` (evaluate.py's ``threads=``).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from rlplat.experiment import evaluate_run, train
from rlplat.experiment.config import compose_config
from rlplat.scenarios import ScenarioSpec, write_scenario_set

SHORT_RUN = (
    "algo.num_envs=16",
    "algo.frames_per_batch=256",
    "algo.init_random_frames=256",
    "algo.compile=false",
    "train.total_frames=512",
    "train.max_minutes=null",
    "train.eval_every_frames=512",
    "train.progress=false",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1000, help="test scenarios (1000)")
    parser.add_argument("--run-dir", type=Path, default=None, help="a trained run to time")
    parser.add_argument("--threads", type=int, nargs="+", default=[torch.get_num_threads(), 1])
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cfg = compose_config(
            "scenarios",
            ["out_dir=unused", "scenario.n_train=400", "scenario.n_val=100",
             f"scenario.n_test={args.n}"],
        )  # fmt: skip
        spec = ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))
        write_scenario_set(spec, tmp / "scenarios")
        run_dir, scenarios_dir = args.run_dir, tmp / "scenarios"
        if run_dir is None:
            run_dir = tmp / "run"
            t, threads = time.perf_counter(), torch.get_num_threads()
            torch.set_num_threads(1)  # setup, not timed: a few seconds of training
            train(compose_config("train", [*SHORT_RUN, f"scenarios_dir={scenarios_dir}"]), run_dir)
            torch.set_num_threads(threads)
            print(f"(a training run of {time.perf_counter() - t:.0f} s made the checkpoint)")
        rows = []
        for threads in args.threads:
            torch.set_num_threads(threads)
            for policy in ("checkpoint", "pure_pursuit", "proportional_navigation"):
                t = time.perf_counter()
                ev = evaluate_run(
                    run_dir, policy=policy, scenarios_dir=scenarios_dir, out_dir=tmp / policy
                )
                rows.append((threads, time.perf_counter() - t, ev.summary))
    print(f"{'policy':<26}{'threads':>8}{'scenarios':>10}{'replay s':>10}{'scen./s':>9}"
          f"{'total s':>9}{'capture':>9}")  # fmt: skip
    for threads, total, s in rows:
        n, replay = s["scenarios"], s["eval_wall_time_s"]
        print(f"{s['name']:<26}{threads:>8}{n:>10}{replay:>10.2f}{n / replay:>9.0f}"
              f"{total:>9.2f}{s['capture_rate']:>9.3f}")  # fmt: skip
    print("total: rebuild env and policy, replay, episodes.csv, summary, plots, report.md")


if __name__ == "__main__":
    main()
