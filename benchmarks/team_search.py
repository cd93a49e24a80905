"""Whether any team play captures what a policy missed: a search over the attackers' plays,
flown against the split's own defenders (route flyers and the defender network alike).

The capture ceiling (``rlplat.eval.ceiling``) bounds what any attacker can capture of a
defender that flies its route; it says nothing of a defender that reacts. The defender
network is deterministic, so the episode is a function of the attackers' commands alone:
a play that captures it in a search captures it, and the captures a search finds are a
lower bound on that defender's ceiling. This script searches, for each scenario a policy
missed (the ``captured`` column of its ``episodes.csv``), over plays of the whole team:

- each attacker flies, in each of ``--segments`` equal parts of the time limit, towards an
  aim point at a world-frame offset from the (first) defender's current position, at a
  fraction of its maximum speed (per axis, the plain velocity command of
  ``action=velocity``); offsets and fractions per attacker and part are the play's
  parameters. A zero offset at full speed is pure pursuit; other offsets lead, flank or
  wait for the defender, a low fraction holds back;
- the cross-entropy method draws ``--samples`` plays per scenario, flies them all in one
  batch on the embedded dynamics (the run's ``dynamics``, ``env`` and defender network),
  and refits the draw to the best tenth, for ``--iterations`` rounds. A play's score is its
  capture (the sooner the better) or else its least distance to the defender;
- each scenario's best play is flown again, one env per scenario (another batch, so other
  rounding): only a capture it repeats there counts.

Prints, per scenario, the defender's strategy, the speed ratio (the team's), the route
ceiling (the whole team's, also with ``--attackers 1``), whether the best play captured,
when, and its least distance; then the count per strategy and, per strategy and speed-ratio
bin (``--bins``), the ceiling between the captures shown possible (the policy's, the plays'
and those of the ``--others`` evaluations, e.g. the baselines') and the scenarios not
provably out of reach (route flyers outside the capture ceiling), with each policy's capture
rate as a fraction of its lower end. Same seed, same plays.

    .venv/bin/python benchmarks/team_search.py RUN_DIR --scenarios data/scenarios/pursuit2v1 \\
        --episodes RUN_DIR/eval/val-best/episodes.csv [--split val] [--samples 256] \\
        [--iterations 10] [--segments 6] [--seed 0] [--attackers 1] [--out plays.json] \\
        [--others OTHER/episodes.csv ...] [--bins 0.6 0.8] [--strategy nn] [--through-action]

``--through-action`` flies each play through the run's own action instead (the correction
that makes its law's action the play's command, :class:`rlplat.agents.plays.AimPlay`): behind
a gate that is shut the law flies, so these are the plays the run's learner can fly, and the
``--out`` file is what ``algo.demonstrations`` stores in the replay buffer. It is slower (the
run's observation and law are computed for every play).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from rlplat.agents.plays import GAIN, AimPlay
from rlplat.errors import ConfigError, ScenarioFileError
from rlplat.eval.episodes import evaluate
from rlplat.eval.metrics import speed_ratio_bin, speed_ratio_labels
from rlplat.eval.pool import _captured
from rlplat.experiment.evaluation import load_run_config, plain_action
from rlplat.experiment.factory import build_eval_env, resolve_scenarios
from rlplat.io import atomic_write_text
from rlplat.scenarios import STRATEGIES

#: Offsets are drawn in a box around the defender, m (x, y, z); the first draw's spread.
OFFSET_BOUND = torch.tensor([40.0, 40.0, 15.0])
OFFSET_SPREAD = torch.tensor([15.0, 15.0, 6.0])
ELITE = 0.1  # the fraction of each round's plays the next draw is fitted to


def search_env(cfg, scenarios, split: str, rows: torch.Tensor, attackers: int, through: bool):
    """The env that flies split rows ``rows`` (one env each, in order): with plain velocity
    commands, the attacker observing only the paper's relative state (the play reads the
    drones' positions, and no observation changes what the drones or defenders do); with
    ``through``, the run's own observation and action (the play flown as a correction)."""
    flown_cfg = cfg
    if not through:
        flown_cfg = OmegaConf.merge(plain_action(cfg), {"observation": None})
        flown_cfg.observation = {"name": "relative_state"}
    return build_eval_env(flown_cfg, scenarios=scenarios.picked(split, rows), split=split,
                          num_envs=len(rows), attackers=attackers)  # fmt: skip


def play(env, offset, fraction, speed, per_part: int, k: int, through: bool) -> AimPlay:
    """The plays flown by ``env``: plain commands, or ``through`` its guided action."""
    return AimPlay(offset, fraction, speed, per_part, k, env.action_key,
                   env=env if through else None)  # fmt: skip


def misses(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    if not path.is_file():
        raise SystemExit(f"team_search: {path} is not a file")
    with path.open() as f:
        rows = list(csv.DictReader(f))
    if not rows or "captured" not in rows[0]:
        raise SystemExit(f"team_search: {path} has no captured column")
    return [r["scenario_id"] for r in rows if not _captured(r)], rows


def search(env, args, s: int, k: int, per_part: int):
    """The cross-entropy search: ``args.samples`` plays per scenario, in the env's batch of
    ``s`` scenarios x samples. Returns per scenario the best play's offsets (s, S, k, 3) and
    fractions (s, S, k) and the earliest capture time found (NaN if none: a capture scores
    1000 - its time, a miss minus its least distance)."""
    n = args.samples
    speed = env.scenarios["attacker_max_speed"][:, :k]
    generator = torch.Generator().manual_seed(args.seed)
    dims = (s, args.segments, k)
    mean_o, std_o = torch.zeros(*dims, 3), OFFSET_SPREAD.expand(*dims, 3).clone()
    mean_f, std_f = torch.ones(*dims), torch.full(dims, 0.5)
    best = torch.full((s,), -float("inf"))
    best_o, best_f = torch.zeros(*dims, 3), torch.zeros(dims)
    elite = int(n * ELITE)  # >= 2 (main checks --samples)
    rows = torch.arange(s)
    started = time.perf_counter()
    for round_ in range(args.iterations):
        noise = torch.randn(s, n, *dims[1:], 3, generator=generator)
        offset = (mean_o.unsqueeze(1) + std_o.unsqueeze(1) * noise).clamp(
            -OFFSET_BOUND, OFFSET_BOUND
        )
        noise = torch.randn(s, n, *dims[1:], generator=generator)
        fraction = (mean_f.unsqueeze(1) + std_f.unsqueeze(1) * noise).clamp(0.0, 1.0)
        if round_ == 0:  # the first play of each scenario is pure pursuit at full speed
            offset[:, 0], fraction[:, 0] = 0.0, 1.0
        plays = play(env, offset.flatten(0, 1), fraction.flatten(0, 1), speed, per_part, k,
                     args.through_action)  # fmt: skip
        result = evaluate(env, plays)
        captured = result.captured.view(s, n)
        when = result.time_to_capture.view(s, n)
        score = torch.where(captured, 1000.0 - when, -result.min_distance.view(s, n))
        top_score, top_play = score.max(1)
        better = top_score > best
        best_o[better] = offset[rows, top_play][better]
        best_f[better] = fraction[rows, top_play][better]
        best = best.maximum(top_score)
        top = score.topk(elite, dim=1).indices  # (s, elite)
        pick_o = offset.gather(1, top.view(s, elite, 1, 1, 1).expand(-1, -1, *dims[1:], 3))
        pick_f = fraction.gather(1, top.view(s, elite, 1, 1).expand(-1, -1, *dims[1:]))
        mean_o, std_o = pick_o.mean(1), pick_o.std(1).clamp_min(0.5)
        mean_f, std_f = pick_f.mean(1), pick_f.std(1).clamp_min(0.05)
        print(f"round {round_ + 1}: {int((best > 0).sum())} of {s} captured, "
              f"{time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)  # fmt: skip
    return best_o, best_f, torch.where(best > 0, 1000.0 - best, float("nan"))


def ceiling_table(
    rows: list[dict[str, str]],
    played: set[str],
    others: dict[str, set[str]],
    ratio: str,
    edges: list[float],
) -> None:
    """Per defender strategy and speed-ratio bin: the scenarios, those provably out of reach
    (route flyers outside the capture ceiling), the ceiling between the captures shown
    possible (the policy's, the plays' and ``others``': policy name -> the scenarios it
    captured) and the scenarios not provably out of reach, and each policy's capture rate
    with, in brackets, its fraction of the ceiling's lower end."""
    bins = speed_ratio_bin(np.array([float(r[ratio]) for r in rows]), edges)
    names = ["policy", *others]
    print(f"\n| defender | {ratio.replace('_', ' ')} | scenarios | provably not | ceiling | "
          + " | ".join(f"{n} (of the ceiling)" for n in names) + " |")  # fmt: skip
    print("|---|---|---|---|---|" + "---|" * len(names))
    for strategy in STRATEGIES:
        for b, label in enumerate(speed_ratio_labels(edges)):
            group = [r for r, g in zip(rows, bins, strict=True)
                     if r["defender_strategy"] == strategy and g == b]  # fmt: skip
            if not group:
                continue
            n = len(group)
            out = sum(r.get("interceptable") == "0" for r in group)
            caught = {"policy": {r["scenario_id"] for r in group if _captured(r)}}
            ids = {r["scenario_id"] for r in group}
            caught.update({name: ids & got for name, got in others.items()})
            possible = len(set().union(*caught.values()) | (ids & played))
            low, high = possible / n, (n - out) / n
            bound = f"{low:.3f}" if low == high else f"{low:.3f}–{high:.3f}"
            rates = [f"{len(c) / n:.3f} ({len(c) / max(possible, 1):.3f})" for c in caught.values()]
            print(f"| {strategy} | {label} | {n} | {out} | {bound} | " + " | ".join(rates) + " |")


def write_plays(args, plays: dict) -> None:
    """Each scenario's best play to ``--out`` (if given), with what it needs to be flown again."""
    if args.out is not None:
        doc = {
            "segments": args.segments,
            "gain": GAIN,
            "seed": args.seed,
            "split": args.split,
            "through_action": args.through_action,
            "plays": plays,
        }
        atomic_write_text(args.out, json.dumps(doc, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a training run (its config flies the env)")
    parser.add_argument("--scenarios", required=True, help="the scenario set")
    parser.add_argument("--episodes", required=True, type=Path,
                        help="a policy's episodes.csv of the split (its misses)")  # fmt: skip
    parser.add_argument("--split", default="val", choices=("train", "val", "test"))
    parser.add_argument("--samples", type=int, default=256)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--segments", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None,
                        help="write each scenario's best play here (JSON)")  # fmt: skip
    parser.add_argument("--others", type=Path, nargs="*", default=[],
                        help="other policies' episodes.csv (the ceiling table)")  # fmt: skip
    parser.add_argument("--bins", type=float, nargs="+", default=[0.6, 0.8],
                        help="inner speed-ratio bin edges of the ceiling table")  # fmt: skip
    parser.add_argument("--strategy", choices=STRATEGIES, default=None,
                        help="search only the misses of defenders of this strategy")  # fmt: skip
    parser.add_argument("--through-action", action="store_true",
                        help="fly the plays through the run's own action (a correction "
                             "to its law, behind its gate): what its learner can fly")  # fmt: skip
    parser.add_argument("--attackers", type=int, default=None,
                        help="fly only the first this many attackers of each team")  # fmt: skip
    args = parser.parse_args()
    for name in ("samples", "iterations", "segments"):
        if getattr(args, name) < 1:
            raise SystemExit(f"team_search: --{name} must be >= 1, got {getattr(args, name)}")
    if args.samples * ELITE < 2:
        raise SystemExit(f"team_search: --samples must be >= {int(2 / ELITE)}, got {args.samples}")
    if sorted(args.bins) != args.bins or any(b <= 0 for b in args.bins):
        raise SystemExit(f"team_search: --bins must be increasing and > 0, got {args.bins}")
    if args.out is not None and not args.out.parent.is_dir():
        raise SystemExit(f"team_search: --out {args.out}: no directory {args.out.parent}")
    logging.basicConfig(level=logging.WARNING)

    try:
        cfg = load_run_config(args.run_dir)
        scenarios = resolve_scenarios(cfg, args.scenarios)
    except (ConfigError, ScenarioFileError) as error:
        raise SystemExit(f"team_search: {error}") from None
    if cfg.dynamics.name == "airsim":
        raise SystemExit("team_search: flies the embedded dynamics only, got dynamics=airsim")
    missed, rows = misses(args.episodes)
    ids = scenarios.ids[args.split]
    unknown = [i for i in missed if i not in ids]
    if unknown or len(rows) != len(ids):
        raise SystemExit(f"team_search: {args.episodes} is not an evaluation of the {args.split} "
                         f"split of {args.scenarios} ({len(rows)} rows, the split has "
                         f"{len(ids)}: --split?)")  # fmt: skip
    info = {r["scenario_id"]: r for r in rows}
    if args.strategy is not None:  # only the misses of that defender strategy are searched
        missed = [i for i in missed if info[i]["defender_strategy"] == args.strategy]
    others = {}
    for path in args.others:  # each named by its evaluation's directory (test-pure_pursuit)
        other_missed, other_rows = misses(path)
        if sorted(r["scenario_id"] for r in other_rows) != sorted(info):
            raise SystemExit(f"team_search: --others {path} flew other scenarios than --episodes")
        name = path.parent.name if path.parent.name not in ("policy", *others) else str(path)
        others[name] = {r["scenario_id"] for r in other_rows} - set(other_missed)
    index = torch.tensor([ids.index(i) for i in missed])
    s, n, k = len(missed), args.samples, scenarios.attackers
    if args.attackers is not None:
        if not 1 <= args.attackers <= k:
            raise SystemExit(f"team_search: --attackers must be in 1..{k}, got {args.attackers}")
        k = args.attackers
    print(f"{s} scenarios {args.episodes} missed of {len(ids)} ({args.split}, {args.scenarios}); "
          f"{k} attacker{'s' if k > 1 else ''}, {n} plays x {args.iterations} rounds, "
          f"{args.segments} parts, seed {args.seed}\n")  # fmt: skip
    if not s:
        write_plays(args, {})
        return

    # One env per play, all in one wave (evaluate flies as many envs as the split has), so
    # a play's step counter is the episode's.
    env = search_env(cfg, scenarios, args.split, index.repeat_interleave(n), k,
                     args.through_action)  # fmt: skip
    per_part = -(-env.max_steps // args.segments)
    best_o, best_f, found = search(env, args, s, k, per_part)
    strategies = env.scenarios["defender_strategy"][::n, 0]
    env.close()

    # Each best play flown again, one env per scenario: a capture that needs the search's
    # batch (its rounding) is not counted.
    env = search_env(cfg, scenarios, args.split, index, k, args.through_action)
    speed = env.scenarios["attacker_max_speed"][:, :k]
    again = evaluate(env, play(env, best_o, best_f, speed, per_part, k, args.through_action))
    env.close()
    hit = again.captured & ~found.isnan()

    ratio = "team_speed_ratio" if k > 1 else "speed_ratio"
    print(f"| scenario | defender | {ratio.replace('_', ' ')} | route ceiling | a play captures "
          "| at (s) | least distance (m) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for i, name in enumerate(missed):
        r = info[name]
        at = f"{again.time_to_capture[i]:.1f}" if hit[i] else ""
        route = {"1": "yes", "0": "no"}.get(r.get("route_interceptable", ""), "")
        print(f"| {name} | {r['defender_strategy']} | {float(r[ratio]):.2f} | {route} | "
              f"{'yes' if hit[i] else 'no'} | {at} | {again.min_distance[i]:.2f} |")  # fmt: skip
    lost = int((~found.isnan()).sum() - hit.sum())
    print(f"\n(plays that captured in the search but not when flown again: {lost})")
    route = torch.tensor([info[i].get("route_interceptable") == "1" for i in missed])
    whose = "whole team's " if k < scenarios.attackers else ""
    for code, label in enumerate(STRATEGIES):
        mine = strategies == code
        if mine.any():
            print(f"{label}: a play captures {int(hit[mine].sum())} of {int(mine.sum())} missed "
                  f"({int(hit[mine & route].sum())} of the {int((mine & route).sum())} the {whose}"
                  f"route ceiling calls interceptable, {int(hit[mine & ~route].sum())} of the "
                  f"other {int((mine & ~route).sum())})")  # fmt: skip
    if k == scenarios.attackers:  # a lone attacker's plays say nothing of the team's ceiling
        played = {name for i, name in enumerate(missed) if hit[i]}
        ceiling_table(rows, played, others, ratio, args.bins)
    else:
        print("\n(no ceiling table: the plays flew fewer attackers than the scenarios hold)")
    write_plays(args, {
        name: {"captured_at_s": round(float(again.time_to_capture[i]), 2) if hit[i] else None,
               "least_distance_m": round(float(again.min_distance[i]), 3),
               "offset_m": best_o[i].tolist(), "fraction": best_f[i].tolist()}
        for i, name in enumerate(missed)
    })  # fmt: skip


if __name__ == "__main__":
    main()
