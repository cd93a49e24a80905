"""What a reviewer reads: PNG plots and ``report.md`` of one evaluation."""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from rlplat.eval.episodes import EpisodeResults
from rlplat.eval.plots import plot_groups, plot_learning_curve, plot_trajectories
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)


def read_scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """A run's logged scalars, ``metrics/scalars/<ns>/<name>.csv`` (``step,value`` lines)."""
    root = run_dir / "metrics" / "scalars"
    history = {}
    for path in sorted(root.rglob("*.csv")):
        name = path.relative_to(root).with_suffix("").as_posix()
        points = [line.split(",") for line in path.read_text().splitlines() if line]
        history[name] = [(int(float(s)), float(v)) for s, v in points]
    return history


def pick_episodes(rows: Sequence[Mapping[str, Any]], k: int) -> list[tuple[int, str]]:
    """Up to ``k`` episodes worth drawing, as (row, label): half the fastest captures, the rest
    the worst outcomes (misses with the largest closest distance, then the slowest captures)."""
    caught = sorted((r["time_to_capture_s"], i) for i, r in enumerate(rows) if r["captured"])
    missed = sorted((-r["min_distance_m"], i) for i, r in enumerate(rows) if not r["captured"])
    best = [i for _, i in caught[: (k + 1) // 2]]
    worst = [i for _, i in missed] + [i for _, i in reversed(caught)]
    worst = [i for i in worst if i not in best][: k - len(best)]
    picked = [(i, "best") for i in best] + [(i, "worst") for i in worst]
    return picked


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def outcome_table(groups: Mapping[str, Mapping[str, Any]], first: str) -> list[str]:
    """Markdown table of :func:`rlplat.eval.metrics.outcome_stats` rows, one per group."""
    lines = [
        f"| {first} | n | captured | capture rate | 95 % CI | mean / median time to capture [s] "
        "| mean return | visible fraction | mean closest distance [m] | route fraction "
        "| evasion score |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in groups.items():
        lo, hi = s["capture_rate_ci95"]
        times = f"{_fmt(s['mean_time_to_capture_s'], 1)} / {_fmt(s['median_time_to_capture_s'], 1)}"
        lines.append(
            f"| {name} | {s['n']} | {s['captured']} | {_fmt(s['capture_rate'])} "
            f"| [{_fmt(lo)}, {_fmt(hi)}] | {times} | {_fmt(s['mean_return'], 2)} "
            f"| {_fmt(s['mean_visible_fraction'])} | {_fmt(s['mean_min_distance_m'], 2)} "
            f"| {_fmt(s.get('mean_route_fraction'))} | {_fmt(s.get('evasion_score'))} |"
        )
    return lines


def _separation_lines(s: Mapping[str, Any]) -> list[str]:
    """A team's line on how near its attackers came to each other (nothing stops them)."""
    sep = s.get("attacker_separation")
    if not sep or not sep["episodes"]:
        return []
    return [
        "",
        f"Attackers' least separation from each other (nothing in the simulator keeps them "
        f"apart): {_fmt(sep['least_m'], 2)} m at least, median over episodes "
        f"{_fmt(sep['median_m'], 2)} m; {sep['near_misses']} of {sep['episodes']} episodes "
        f"within {sep['near_miss_m']:g} m.",
    ]


def _artifact_lines(s: Mapping[str, Any]) -> list[str]:
    """What an evaluation of an exported artifact adds: its files, and the episodes whose
    outcome differs from the torch policy's on the same scenarios."""
    if "artifact" not in s:
        return []
    files = ", ".join(f"`{k}` sha256 `{v[:12]}`" for k, v in s["artifact"]["files"].items())
    lines = [
        f"- artifact: {files} from `{s['artifact']['dir']}`",
        f"- outcomes differing from the torch policy on the same scenarios: "
        f"**{s['outcomes_differing_from_torch']}**, {s['captures_differing_from_torch']} of "
        f"them in capture (torch capture rate {_fmt(s['torch_capture_rate'])})",
    ]
    if s["differences_from_torch"]:
        lines += [
            "",
            "| scenario | torch: captured, crashed, steps | this policy |",
            "|---|---|---|",
        ]
        for d in s["differences_from_torch"]:
            ref, own = d["torch"], d[s["policy"]]
            lines.append(f"| {d['scenario_id']} | {_outcome(ref)} | {_outcome(own)} |")
    return lines


def _outcome(o: Mapping[str, Any]) -> str:
    yes = {True: "yes", False: "no"}
    text = f"{yes[bool(o['captured'])]}, {yes[bool(o['grounded'])]}, {o['steps']}"
    return text + (f", {o['defenders_caught']} caught" if "defenders_caught" in o else "")


def write_report(
    out_dir: Path,
    summary: Mapping[str, Any],
    rows: Sequence[Mapping[str, Any]],
    results: EpisodeResults,
    routes: torch.Tensor,
    run_dir: Path,
    trajectories: int,
    plots: bool,
) -> None:
    """Plots (if ``plots``) and ``report.md`` of one evaluation into ``out_dir``."""
    s = summary
    learned = f"{s['drone']} ({s['name']} checkpoint)"
    who = learned if s["policy"] == "checkpoint" else f"{s['policy']} (scripted baseline)"
    if "artifact" in s:
        kind = {"onnx": "ONNX, in ONNX Runtime", "c": "C, one call per drone and step"}
        who = f"{s['drone']} ({s['name']}: the export as {kind[s['policy']]})"
    md = [
        f"# Evaluation: {who} on the {s['split']} split",
        "",
        f"- run: `{s['run_dir']}` (drone `{s['drone']}`, seed {s['seed']}, "
        f"dynamics `{s.get('dynamics', '?')}`)",
        f"- policy: `{s['policy']}`"
        + (f", checkpoint `{s['checkpoint']}`" if s["checkpoint"] else ""),
        f"- scenarios: {s['scenarios']} from `{s['scenario_dir']}`, "
        f"digest `{s['scenario_digest'][:12]}`"
        + ("" if s["scenario_digest_matches"] else " (**not the set the run trained with**)"),
        "- every episode flown once, deterministically: `episodes.csv` has one row per scenario "
        "(its parameters and its outcome)",
        *_artifact_lines(s),
        "",
        "## Outcome",
        "",
        *outcome_table({"all scenarios": s}, "episodes"),
        "",
        f"Episodes ended on the ground: {_fmt(s['ground_rate'])}. Mean steps: "
        f"{_fmt(s['mean_steps'], 1)}. Mean episode sum of each reward term: "
        + ", ".join(f"{k} {v:.2f}" for k, v in s["reward_terms"].items())
        + ".",
        *_separation_lines(s),
        "",
    ]
    for key, title, first in (
        ("by_strategy", "By defender strategy", "strategy"),
        ("by_route", "By route", "route"),
        ("by_speed_ratio", "By speed ratio (attacker / defender maximum speed)", "ratio"),
    ):
        md += [f"## {title}", "", *outcome_table(s[key], first), ""]
    picked = pick_episodes(rows, trajectories)
    if plots:
        md += ["## Plots", ""]
        history = read_scalars(run_dir)
        if history:
            plot_learning_curve(history, out_dir / "learning_curve.png")
            md += ["Learning curves of the run (validation every few frames):", ""]
            md += ["![learning curves](learning_curve.png)", ""]
        plot_groups(s["by_speed_ratio"], "speed ratio", "Capture rate against speed ratio",
                    out_dir / "capture_vs_speed_ratio.png")  # fmt: skip
        plot_groups(s["by_route"], "route", "Capture rate per route",
                    out_dir / "capture_by_route.png")  # fmt: skip
        md += ["![capture rate against speed ratio](capture_vs_speed_ratio.png)", ""]
        md += ["![capture rate per route](capture_by_route.png)", ""]
        if picked and results.positions is not None:
            plot_trajectories(rows, results.positions, routes, picked,
                              out_dir / "trajectories.png", s.get("attackers", 1))  # fmt: skip
            md += ["Chosen episodes in 3D (best captures and worst outcomes):", ""]
            md += ["![trajectories](trajectories.png)", ""]
    if picked:
        md += [
            "## Chosen episodes",
            "",
            "| | scenario | route | speed ratio | captured | time to capture [s] "
            "| closest distance [m] | return |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for e, label in picked:
            r = rows[e]
            md.append(
                f"| {label} | {_md_cell(r['scenario_id'])} | {r['route']} ({r['route_direction']}) "
                f"| {r['speed_ratio']:.2f} | {'yes' if r['captured'] else 'no'} "
                f"| {_fmt(r['time_to_capture_s'], 1)} | {r['min_distance_m']:.2f} "
                f"| {r['return']:.2f} |"
            )
        md.append("")
    atomic_write_text(out_dir / "report.md", "\n".join(md))


def _md_cell(text: str) -> str:
    """``text`` as one Markdown table cell: control characters (a line break in a hand-made
    scenario id) written as escapes, ``|`` escaped."""
    text = re.sub(r"[\x00-\x1f\x7f]", lambda m: repr(m.group())[1:-1], str(text))
    return text.replace("|", "\\|")
