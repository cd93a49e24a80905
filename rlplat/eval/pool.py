"""Pool the evaluations of several runs: every episode of every seed in one table per policy.

``python -m rlplat.eval.pool DIR [DIR ...] [--split test]`` reads ``DIR/eval/<split>-*/``
(``summary.json`` and ``episodes.csv``, written by ``evaluate.py``) of each run and prints one
Markdown row per policy: the episodes of all runs pooled (capture rate with its 95 % Wilson
interval, mean and median time to capture) and, where the evaluations report the capture
ceiling, the capture rate on the scenarios it covers against it. Seeds of one configuration
fly the same scenarios, so a scripted baseline's rows repeat the same episodes once per run.
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from rlplat.cli import exit_on_error
from rlplat.errors import ConfigError
from rlplat.eval.compare import _learned, num
from rlplat.eval.metrics import wilson_interval
from rlplat.scenarios import SPLITS


def _label(summary: dict[str, Any]) -> str:
    return f"{summary['drone']} ({summary['name']})" if _learned(summary) else summary["policy"]


def pooled_rows(run_dirs: list[Path], split: str = "test") -> list[dict[str, Any]]:
    """Per policy (learned ones first, in the order met), the pooled outcome of its episodes."""
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    episodes: dict[str, list[dict[str, str]]] = defaultdict(list)
    runs: dict[str, int] = defaultdict(int)
    learned: dict[str, bool] = {}
    for run_dir in run_dirs:
        paths = sorted(Path(run_dir).glob(f"eval/{split}-*/summary.json"))
        if not paths:
            raise ConfigError(f"pool: no evaluation of the {split} split under {run_dir}/eval")
        for path in paths:
            summary = json.loads(path.read_text())
            label = _label(summary)
            learned[label] = _learned(summary)
            runs[label] += 1
            with open(path.parent / "episodes.csv", newline="") as f:
                episodes[label].extend(csv.DictReader(f))
    order = sorted(episodes, key=lambda k: (not learned[k], list(episodes).index(k)))
    return [_pool(label, runs[label], episodes[label]) for label in order]


def _pool(label: str, runs: int, rows: list[dict[str, str]]) -> dict[str, Any]:
    captured = np.array([r["captured"] in ("1", "True", "true") for r in rows])
    times = np.array([float(r["time_to_capture_s"]) for r in rows if r["time_to_capture_s"]])
    n, k = len(rows), int(captured.sum())
    low, high = wilson_interval(k, n)
    out = {
        "policy": label,
        "runs": runs,
        "episodes": n,
        "capture_rate": k / n,
        "ci95": (low, high),
        "mean_time_to_capture_s": float(times.mean()) if times.size else None,
        "median_time_to_capture_s": float(np.median(times)) if times.size else None,
    }
    bound = [r.get("interceptable", "") for r in rows]
    covered = np.array([b not in ("", None) for b in bound])
    if covered.any():
        out["ceiling"] = float(np.mean([bound[i] in ("1", "True", "true") for i in
                                        np.flatnonzero(covered)]))  # fmt: skip
        out["capture_rate_covered"] = float(captured[covered].mean())
    return out


def markdown(rows: list[dict[str, Any]]) -> str:
    """The pooled comparison as a Markdown table."""
    lines = [
        "| policy | runs | episodes | capture rate [95 % CI] | mean / median time to capture "
        "[s] | route-flying defenders: capture rate / ceiling |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        low, high = r["ci95"]
        ceiling = (
            f"{num(r['capture_rate_covered'])} / {num(r['ceiling'])}" if "ceiling" in r else "–"
        )
        lines.append(
            f"| {r['policy']} | {r['runs']} | {r['episodes']} | {num(r['capture_rate'])} "
            f"[{num(low)}, {num(high)}] | {num(r['mean_time_to_capture_s'], 1)} / "
            f"{num(r['median_time_to_capture_s'], 1)} | {ceiling} |"
        )
    return "\n".join(lines)


@exit_on_error
def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m rlplat.eval.pool", description=__doc__.splitlines()[0]
    )
    parser.add_argument("run_dirs", nargs="+", type=Path, help="training run directories")
    parser.add_argument("--split", default="test", help="test | val | train (default: test)")
    args = parser.parse_args(argv)
    print(markdown(pooled_rows(args.run_dirs, args.split)))


if __name__ == "__main__":
    main()
