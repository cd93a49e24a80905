"""Compare the policies evaluated on one split of a run: one table, one plot.

``python -m rlplat.eval.compare RUN_DIR [--split test]`` reads every
``RUN_DIR/eval/<split>-*/summary.json`` (written by ``evaluate.py``) and writes
``RUN_DIR/eval/compare-<split>.md``, ``.csv`` and ``.png``; ``--eval-dir DIR`` reads and
writes ``DIR`` in place of ``RUN_DIR/eval`` (``evaluate.py compare=true out_dir=DIR``).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
from pathlib import Path
from typing import Any

from rlplat.agents.policies import POLICIES
from rlplat.cli import ArgumentParser, exit_on_error, path_arg
from rlplat.errors import ConfigError
from rlplat.eval.plots import plot_comparison
from rlplat.eval.pool import paired_markdown, paired_rows
from rlplat.eval.summaries import is_learned, num, policy_label
from rlplat.io import atomic_write_text
from rlplat.scenarios import SPLITS

log = logging.getLogger(__name__)

COLUMNS = (
    "policy",
    "kind",
    "scenarios",
    "captured",
    "capture_rate",
    "ci95_low",
    "ci95_high",
    "mean_time_to_capture_s",
    "median_time_to_capture_s",
    "mean_return",
    "mean_visible_fraction",
    "mean_min_distance_m",
    "mean_route_fraction",
    "evasion_score",
)


def _order(summary: dict[str, Any]) -> tuple[int, int, str]:
    if is_learned(summary):
        return (0, 0 if summary["name"] == "best" else 1, summary["name"])
    return (1, list(POLICIES).index(summary["policy"]), summary["name"])


def evaluations_dir(run_dir: str | Path, eval_dir: str | Path | None = None) -> Path:
    """The folder a run's evaluations are in: ``eval_dir``, by default ``<run_dir>/eval``."""
    return Path(eval_dir or Path(run_dir) / "eval")


def load_summaries(
    run_dir: str | Path, split: str = "test", eval_dir: str | Path | None = None
) -> list[dict[str, Any]]:
    """The evaluation summaries of ``split`` in a run's ``eval_dir`` (default
    ``<run_dir>/eval``): learned policies first, then baselines.

    Refuses summaries flown on different scenario sets: their numbers do not compare.
    """
    run_dir = Path(run_dir)
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    if not run_dir.is_dir():
        raise ConfigError(f"run_dir: no run directory at {run_dir}")
    where = evaluations_dir(run_dir, eval_dir)
    paths = sorted(where.glob(f"{split}-*/summary.json"))
    if not paths:
        raise ConfigError(
            f"compare: no evaluation of the {split} split in {where}; "
            f"run evaluate.py run_dir={run_dir} split={split} first"
        )
    summaries = sorted((json.loads(p.read_text()) for p in paths), key=_order)
    digests = {s["scenario_digest"] for s in summaries}
    if len(digests) > 1:
        flown = ", ".join(f"{s['name']}: {s['scenario_digest'][:12]}" for s in summaries)
        raise ConfigError(f"compare: the evaluations used different scenario sets ({flown})")
    edges = {tuple(s.get("speed_ratio_bins", ())) for s in summaries}
    if len(edges) > 1:  # the tables per bin line them up
        binned = ", ".join(f"{s['name']}: {s.get('speed_ratio_bins')}" for s in summaries)
        raise ConfigError(
            f"compare: the evaluations bin speed ratios differently ({binned}); evaluate them "
            "with the same speed_ratio_bins"
        )
    return summaries


def flown_as(summary: dict[str, Any]) -> tuple[Any, Any]:
    """The game an evaluation flew besides its scenarios: its dynamics and team size."""
    return summary.get("dynamics"), summary.get("attackers")


def row_label(summary: dict[str, Any], mixed: bool) -> str:
    """A policy's label, with its dynamics and team size where the evaluations mix them."""
    if not mixed:
        return policy_label(summary)
    dynamics, attackers = flown_as(summary)
    return f"{policy_label(summary)} ({dynamics}, {attackers} attacker{'s' * (attackers != 1)})"


def table_rows(summaries: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row of :data:`COLUMNS` per evaluated policy (labelled with its dynamics and team
    size where the summaries fly several)."""
    mixed = len({flown_as(s) for s in summaries}) > 1
    rows = []
    for s in summaries:
        rows.append(
            {
                "policy": row_label(s, mixed),
                "kind": "learned" if is_learned(s) else "scripted",
                "scenarios": s["scenarios"],
                "captured": s["captured"],
                "capture_rate": s["capture_rate"],
                "ci95_low": s["capture_rate_ci95"][0],
                "ci95_high": s["capture_rate_ci95"][1],
                **{k: s.get(k) for k in COLUMNS[7:]},
            }
        )
    return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The comparison as a Markdown table."""
    lines = [
        "| policy | scenarios | capture rate [95 % CI] | mean / median time to capture [s] "
        "| mean return | visible fraction | mean closest distance [m] | route fraction "
        "| evasion score |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['scenarios']} | {num(r['capture_rate'])} "
            f"[{num(r['ci95_low'])}, {num(r['ci95_high'])}] "
            f"| {num(r['mean_time_to_capture_s'], 1)} / {num(r['median_time_to_capture_s'], 1)} "
            f"| {num(r['mean_return'], 2)} | {num(r['mean_visible_fraction'])} "
            f"| {num(r['mean_min_distance_m'], 2)} | {num(r['mean_route_fraction'])} "
            f"| {num(r['evasion_score'])} |"
        )
    return "\n".join(lines)


def ceiling_table(summaries: list[dict[str, Any]]) -> str | None:
    """Capture rates against the capture ceiling (:mod:`rlplat.eval.ceiling`) on the scenarios
    it covers (route-flying defenders), per speed-ratio bin; None if no summary has it."""
    if not summaries or not summaries[0].get("ceiling", {}).get("scenarios"):
        return None  # not recorded, or no scenario it covers (network defenders, several ones)
    bins = [b for b, v in summaries[0]["by_speed_ratio"].items() if v["ceiling"]["scenarios"]]
    return _bound_table(
        summaries, "ceiling", "by_speed_ratio", bins,
        "attacker / defender max speed", "**ceiling** (an intercept exists)",
    )  # fmt: skip


def route_ceiling_table(summaries: list[dict[str, Any]]) -> str | None:
    """Capture rates against the route ceiling (:mod:`rlplat.eval.ceiling`) per defender
    strategy; None unless the summaries record it for a defender that reacts (the route flyers'
    route ceiling is their capture ceiling)."""
    if not summaries or "route_ceiling" not in summaries[0]:
        return None
    groups = summaries[0]["by_strategy"]
    if all(g["route_ceiling"]["scenarios"] == g["ceiling"]["scenarios"] for g in groups.values()):
        return None
    return _bound_table(
        summaries, "route_ceiling", "by_strategy", list(groups),
        "defender", "**route ceiling** (an intercept exists on its route)",
    )  # fmt: skip


def _bound_table(
    summaries: list[dict[str, Any]], block: str, by: str, groups: list[str], head: str, label: str
) -> str:
    """One column for all scenarios and one per group of the summaries' ``by`` breakdown: the
    scenarios the ``block`` bound covers, the bound, then each policy's capture rate there."""

    def cell(stats: dict[str, Any], key: str) -> str:
        value = stats.get(block, {}).get(key)
        return "–" if value is None else f"{value:.3f}"

    def row(*cells: Any) -> str:
        return "| " + " | ".join(str(c) for c in cells) + " |"

    first = summaries[0]
    lines = [
        row(head, "all", *groups),
        "|---|" + "---|" * (len(groups) + 1),
        row("scenarios", first[block]["scenarios"],
            *(first[by][g][block]["scenarios"] for g in groups)),
        row(label, cell(first, "interceptable_rate"),
            *(cell(first[by][g], "interceptable_rate") for g in groups)),
    ]  # fmt: skip
    for s in summaries:
        rates = (cell(s[by][g], "capture_rate") for g in groups)
        lines.append(row(policy_label(s), cell(s, "capture_rate"), *rates))
    return "\n".join(lines)


def compare(
    run_dir: str | Path,
    split: str = "test",
    eval_dir: str | Path | None = None,
    plots: bool = True,
) -> str:
    """Write ``compare-<split>.{md,csv,png}`` beside a run's evaluations, in ``eval_dir``
    (default ``<run_dir>/eval``; the PNG only with ``plots``); returns the Markdown table."""
    run_dir = Path(run_dir)
    out = evaluations_dir(run_dir, eval_dir)
    summaries = load_summaries(run_dir, split, out)
    rows = table_rows(summaries)
    table = markdown_table(rows)
    paired = _paired_section(out, summaries, split)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(out / f"compare-{split}.csv", buffer.getvalue())
    if plots:
        plot_comparison(summaries, out / f"compare-{split}.png")
    s = summaries[0]
    header = (
        f"# Policies on the {split} split of `{run_dir}`"
        + (f" (evaluations in `{out}`)" if eval_dir is not None else "")
        + "\n\n"
        f"{s['scenarios']} scenarios, digest `{s['scenario_digest'][:12]}`; every policy flies "
        "each scenario once, deterministically.\n\n"
    )
    figure = f"\n\n![capture rate against speed ratio](compare-{split}.png)\n" if plots else "\n"
    games = list(dict.fromkeys(flown_as(s) for s in summaries))
    if len(games) > 1:  # e.g. evaluate.py compare=true dynamics=quadrotor beside velocity's
        log.warning("compare: the evaluations fly %d games (dynamics, attackers: %s); the rows "
                    "say which, and the bound tables hold the first's", len(games),
                    ", ".join(f"{d}, {a}" for d, a in games))  # fmt: skip
        summaries = [s for s in summaries if flown_as(s) == games[0]]
    ceiling = ceiling_table(summaries)
    if ceiling is not None:
        figure += (
            "\n## Against the capture ceiling\n\n"
            f"On the {summaries[0]['ceiling']['scenarios']} scenarios whose defender flies its "
            "route (its path is known in advance): the fraction where an attacker at its maximum "
            "speed per axis, with the dynamics' acceleration limits, can reach the defender at "
            "all, and each policy's capture rate there.\n\n" + ceiling + "\n"
        )
    route = route_ceiling_table(summaries)
    if route is not None:
        figure += (
            "\n## Against the route ceiling\n\n"
            "The same bound with every defender flying its route, as if a network defender "
            "ignored the attackers: not a bound for a defender that reacts (its evasion can slow "
            "it down or turn it towards an attacker), but a scenario outside it is one that the "
            "defender can win by running along its route.\n\n" + route + "\n"
        )
    figure += paired
    atomic_write_text(out / f"compare-{split}.md", header + table + figure)
    log.info("comparison of %d policies in %s", len(rows), out / f"compare-{split}.md")
    return table


def _paired_section(out: Path, summaries: list[dict[str, Any]], split: str) -> str:
    """Every other policy against proportional navigation scenario by scenario
    (:func:`rlplat.eval.pool.paired_rows`), where ``out`` holds its evaluation; else ""."""
    law = "proportional_navigation"
    if len(summaries) < 2 or not any(s.get("policy") == law for s in summaries):
        return ""
    try:
        flown = sorted(p.parent for p in out.glob(f"{split}-*/summary.json"))
        rows = paired_rows(flown, law, split)
    except ConfigError as err:  # e.g. the run also holds evaluations on other dynamics
        log.info("compare: no scenario-by-scenario section (%s)", err)
        return ""
    return (
        "\n## Against proportional navigation, scenario by scenario\n\n"
        "Per scenario each policy's outcome against the law's on the same scenario: the gain "
        "is the mean difference of the captures, with its 95 % interval over scenarios (what "
        "another draw of as many scenarios would show); the scenarios gained and lost; the "
        "difference of the times to capture where both captured.\n\n" + paired_markdown(rows) + "\n"
    )


@exit_on_error
def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="python -m rlplat.eval.compare", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "run_dir", type=path_arg, help="a training run directory with eval/<split>-*/ results"
    )
    parser.add_argument("--split", default="test", help="test | val | train (default: test)")
    parser.add_argument(
        "--eval-dir", default=None, type=path_arg,
        help="the evaluations' folder (evaluate.py compare=true out_dir=...; default RUN_DIR/eval)",
    )  # fmt: skip
    parser.add_argument("--plots", action=argparse.BooleanOptionalAction, default=True,
                        help="write compare-<split>.png (default: yes)")  # fmt: skip
    args = parser.parse_args(argv)
    print(compare(args.run_dir, args.split, args.eval_dir, plots=args.plots))


if __name__ == "__main__":
    main()
