"""Each checkpoint a run kept (``train.keep_checkpoints=true``: ``checkpoints/val-<frames>.pt``)
flown on other scenario sets: what a selection on another set than the run's validation
split would keep, and what that checkpoint captures elsewhere.

    .venv/bin/python benchmarks/checkpoints.py RUN_DIR \\
        --on v2=data/scenarios/pursuit2v1:val t2=data/scenarios/pursuit2v1:test \\
        [--from-frames 280000]

Each ``--on`` is ``NAME=DIR:SPLIT``. A set whose team of the run's learning role is larger
than the one the run trained with flies the checkpoint in each seat (``evaluate.py
lone_in_team=true``). Prints one row per checkpoint, in the order of its frames: its
captures on each set, in the order given, a column's largest count in bold.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from rlplat.agents.checkpoint import actor_from_state, load_checkpoint, saved_interface
from rlplat.envs.pursuit import ROLES
from rlplat.eval.episodes import evaluate
from rlplat.experiment.evaluation import check_policy_fits, load_run_config
from rlplat.experiment.factory import build_eval_env, eval_num_envs, resolve_scenarios
from rlplat.experiment.training import validation_checkpoint


def scenario_split(text: str) -> tuple[str, str, str]:
    """``NAME=DIR:SPLIT`` as (name, dir, split)."""
    name, _, rest = text.partition("=")
    where, _, split = rest.rpartition(":")
    if not name or not where or split not in ("train", "val", "test"):
        raise argparse.ArgumentTypeError(
            f"NAME=DIR:SPLIT with SPLIT train, val or test, got {text!r}"
        )
    return name, where, split


def kept_checkpoints(run_dir: Path, from_frames: int) -> list[tuple[int, Path]]:
    """The run's kept checkpoints from ``from_frames`` on, as (frames, path), by frames."""
    kept = []
    for path in (run_dir / "checkpoints").glob("val-*.pt"):
        frames = path.stem.removeprefix("val-")
        if frames.isdigit() and path.name == validation_checkpoint(int(frames)):
            kept.append((int(frames), path))
    return sorted(k for k in kept if k[0] >= from_frames)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run trained with train.keep_checkpoints=true")
    parser.add_argument("--on", nargs="+", type=scenario_split, required=True)
    parser.add_argument("--from-frames", type=int, default=0, help="skip earlier checkpoints")
    args = parser.parse_args()
    names = [name for name, _, _ in args.on]
    if len(set(names)) < len(names):
        parser.error(f"argument --on: each NAME once, got {', '.join(names)}")
    logging.basicConfig(level=logging.WARNING)

    cfg = load_run_config(args.run_dir)
    kept = kept_checkpoints(args.run_dir, args.from_frames)
    if not kept:
        raise SystemExit(
            f"checkpoints: no checkpoints/val-<frames>.pt in {args.run_dir} from "
            f"{args.from_frames} frames on (train with train.keep_checkpoints=true)"
        )
    counts: dict[str, list[int]] = {}
    sizes: dict[str, int] = {}
    for name, where, split in args.on:
        scenarios = resolve_scenarios(cfg, where)
        n = len(scenarios.split(split))
        env = build_eval_env(cfg, scenarios=scenarios, split=split, num_envs=eval_num_envs(cfg, n))
        counts[name], sizes[name] = [], n
        team = env.num_attackers if ROLES[env.learner] == "attacker" else env.num_defenders
        learners = f"{ROLES[env.learner]}s"
        for _, path in kept:
            state = load_checkpoint(path)
            lone = saved_interface(state)[learners] == 1 and team > 1
            features = check_policy_fits(state, cfg, env, path, lone_in_team=lone)
            actor = actor_from_state(state, env.drone_action_spec, "cpu", env.group, features)
            counts[name].append(int(evaluate(env, actor).captured.sum()))
        env.close()

    print(f"{cfg.drone.name} ({args.run_dir}), kept checkpoints: {len(kept)}\n")
    print("| frames | " + " | ".join(f"{k} ({sizes[k]:,})" for k in counts) + " |")
    print("|---" * (len(counts) + 1) + "|")
    for row, (frames, _) in enumerate(kept):
        cells = [f"**{c[row]:,}**" if c[row] == max(c) else f"{c[row]:,}" for c in counts.values()]
        print(f"| {frames:,} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
