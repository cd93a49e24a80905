"""Where the network defender stops: stalls of the defenders on a split, flown against a run's
checkpoint (in every seat of a team, as ``evaluate.py lone_in_team=true``) or a baseline.

A stall is a stretch of at least ``--seconds`` s, from ``--after`` s into the episode (every
drone starts at rest) until its end, in which the defender flies slower than ``--speed`` m/s
(its speed over each control period, from the recorded positions). Per defender strategy (the
route flyers are the control: they slow down only at the route's end), prints: the episodes,
those with a stall, the stalls' median length and the nearest attacker's median distance at a
stall's start and end, and the capture rates of the episodes with and without one.

    .venv/bin/python benchmarks/defender_stalls.py RUN_DIR --scenarios data/scenarios/pursuit2v1 \\
        [--split test] [--policy checkpoint|proportional_navigation|pure_pursuit|route_intercept]
        [--speed 0.5] [--seconds 5] [--after 2]
"""

from __future__ import annotations

import argparse
import logging
import statistics

import torch

from rlplat.envs.pursuit import ROLES
from rlplat.errors import RlplatError
from rlplat.eval.episodes import evaluate
from rlplat.experiment.evaluation import flight_arguments, flown_split
from rlplat.scenarios import STRATEGIES


def stalls(slow: torch.Tensor, first: int, last: int, shortest: int) -> list[tuple[int, int]]:
    """The runs of True in ``slow`` (T,) within steps [first, last) at least ``shortest`` long,
    as (start, end) steps."""
    runs, start = [], None
    for t in range(first, last):
        if slow[t] and start is None:
            start = t
        if start is not None and (not slow[t] or t == last - 1):
            end = t + 1 if slow[t] else t
            if end - start >= shortest:
                runs.append((start, end))
            start = None
    return runs


def rate(captured: torch.Tensor, rows: torch.Tensor) -> str:
    """The capture rate of ``rows`` (bool) of ``captured`` and their count, or "-"."""
    return f"{captured[rows].float().mean():.3f} ({int(rows.sum())})" if rows.any() else "-"


def median(values: list[float]) -> str:
    return f"{statistics.median(values):.1f}" if values else "-"


def positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


def non_negative(text: str) -> float:
    value = float(text)
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}")
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    flight_arguments(parser, split="test")
    parser.add_argument("--speed", type=positive, default=0.5, help="m/s, slower is a stall")
    parser.add_argument("--seconds", type=positive, default=5.0, help="s, a stall's least length")
    parser.add_argument("--after", type=non_negative, default=2.0, help="s, from the start")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    try:  # a bad run, set or policy: one line
        cfg, env, policy = flown_split(args.run_dir, args.scenarios, args.split, args.policy,
                                       args.ckpt)  # fmt: skip
    except RlplatError as e:
        raise SystemExit(f"defender_stalls: {e}") from None
    split = env.scenario_set.split(args.split)
    n = len(split)
    if ROLES[env.learner] != "attacker":
        raise SystemExit(f"defender_stalls: {args.run_dir} trains a {ROLES[env.learner]}")
    if env.num_defenders != 1:
        raise SystemExit(f"defender_stalls: one defender per scenario, got {env.num_defenders}")
    results = evaluate(env, policy, record=True)
    env.close()

    period = float(cfg.env.control_period)
    k = env.num_attackers
    positions = results.positions  # (E, T + 1, drones, 3): attackers, then defenders
    defender, attackers = positions[:, :, k], positions[:, :, :k]
    speed = (defender[:, 1:] - defender[:, :-1]).norm(dim=-1) / period  # (E, T)
    nearest = (attackers - defender.unsqueeze(2)).norm(dim=-1).amin(-1)  # (E, T + 1)
    first, shortest = round(args.after / period), round(args.seconds / period)
    strategy = split["defender_strategy"][:, 0]

    flown = f"{args.run_dir}, {args.ckpt}" if args.policy == "checkpoint" else args.run_dir
    print(f"{args.policy} ({flown}) on {n} {args.split} scenarios of "
          f"{args.scenarios}, {k} attacker(s): stalls under {args.speed:g} m/s for "
          f"{args.seconds:g} s or more, from {args.after:g} s on\n")  # fmt: skip
    print("| defenders | episodes | with a stall | median stall (s) | nearest attacker at its "
          "start / end (m, medians) | captured: with a stall / without |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for index, name in enumerate(STRATEGIES):
        rows = (strategy == index).nonzero().flatten().tolist()
        if not rows:
            continue
        lengths, starts, ends, stalled = [], [], [], []
        for e in rows:
            found = stalls(speed[e] < args.speed, first, int(results.length[e]), shortest)
            stalled.append(bool(found))
            for a, b in found:
                lengths.append((b - a) * period)
                starts.append(float(nearest[e, a]))
                ends.append(float(nearest[e, b]))
        captured = results.captured[rows]
        with_stall = torch.tensor(stalled, dtype=torch.bool)
        rates = f"{rate(captured, with_stall)} / {rate(captured, ~with_stall)}"
        print(f"| {name} | {len(rows)} | {int(with_stall.sum())} | {median(lengths)} | "
              f"{median(starts)} / {median(ends)} | {rates} |")  # fmt: skip


if __name__ == "__main__":
    main()
