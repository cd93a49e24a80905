"""Aggregate a seed sweep: per-seed test scores, IQM and stratified-bootstrap 95 % CIs.

``python -m rlplat.eval.aggregate SWEEP_DIR`` reads every training run under ``SWEEP_DIR``
(e.g. ``runs/multirun/<time>`` of ``train.py -m seed=0,1,2``), groups the runs by the Hydra
overrides that set them apart other than ``seed`` (one group per configuration), and writes
``SWEEP_DIR/aggregate/seeds.{csv,md,png}`` and ``summary.json``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from rlplat.cli import exit_on_error
from rlplat.errors import ConfigError
from rlplat.eval.metrics import iqm, stratified_bootstrap_ci
from rlplat.eval.plots import plot_seeds
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)

#: What is aggregated: the best checkpoint's scores on the test split (training's summary.json).
METRICS = {"test_capture_rate": "test capture rate", "test_mean_return": "test mean return"}


def find_runs(sweep_dir: Path) -> list[Path]:
    """Training run directories under ``sweep_dir`` (a ``summary.json`` beside a
    ``config.yaml``), the sweep directory itself included."""
    found = {
        p.parent for p in sweep_dir.rglob("summary.json") if (p.parent / "config.yaml").is_file()
    }
    return sorted(found)


def overrides(run_dir: Path) -> list[str]:
    """The run's Hydra overrides other than ``seed`` (``.hydra/overrides.yaml``)."""
    path = run_dir / ".hydra" / "overrides.yaml"
    found = list(OmegaConf.load(path)) if path.is_file() else []
    return [o for o in found if not o.split("=", 1)[0].lstrip("+~").startswith("seed")]


def collect(sweep_dir: str | Path) -> tuple[dict[str, list[dict[str, Any]]], list[str]]:
    """Per variant, one record per run (``seed``, ``run_dir`` and the :data:`METRICS`), and the
    overrides every run shares. A variant is named by the overrides that set its runs apart
    (other than ``seed``); ``default`` when there are none."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise ConfigError(f"sweep_dir: no directory at {sweep_dir}")
    runs = find_runs(sweep_dir)
    if not runs:
        raise ConfigError(
            f"sweep_dir: no finished training run under {sweep_dir} "
            "(a summary.json beside a config.yaml)"
        )
    unfinished = sorted(
        str(p.parent.parent.relative_to(sweep_dir))
        for p in sweep_dir.rglob(".hydra/overrides.yaml")
        if not (p.parent.parent / "summary.json").is_file()
    )
    if unfinished:
        log.warning(
            "aggregate: %d job(s) of %s did not finish (no summary.json) and are left out: %s",
            len(unfinished), sweep_dir, ", ".join(unfinished),
        )  # fmt: skip
    found = {run: overrides(run) for run in runs}
    common = [o for o in found[runs[0]] if all(o in v for v in found.values())]
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for run in runs:
        path = run / "summary.json"
        try:
            summary = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            reason = " ".join(str(e).split())
            raise ConfigError(f"{path}: cannot be read as JSON ({reason})") from None
        missing = [k for k in ("seed", *METRICS) if k not in summary]
        if missing:
            raise ConfigError(f"{path}: missing {', '.join(missing)}")
        for key in METRICS:
            value = summary[key]
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"{path}: {key} is {value!r}, not a finite number")
        record = {"seed": summary["seed"], "run_dir": str(run.relative_to(sweep_dir))}
        name = " ".join(o for o in found[run] if o not in common) or "default"
        groups[name].append(record | {k: float(summary[k]) for k in METRICS})
    for name, records in groups.items():
        seeds = [r["seed"] for r in records]
        twice = sorted({s for s in seeds if seeds.count(s) > 1})
        if twice:  # copies of one run would count as seeds of their own
            log.warning("aggregate: variant %s has seed(s) %s more than once (%s); each run "
                        "counts as a seed", name, twice,
                        ", ".join(r["run_dir"] for r in records if r["seed"] in twice))  # fmt: skip
    return {k: sorted(v, key=lambda r: r["seed"]) for k, v in sorted(groups.items())}, common


def aggregate_scores(
    records: list[dict[str, Any]], reps: int = 2000, seed: int = 0
) -> dict[str, dict[str, Any]]:
    """Per metric: IQM and mean over seeds, each with its stratified-bootstrap 95 % CI.

    The scores form a (seeds, 1) array: one task, the test split, so the stratified bootstrap
    resamples seeds with replacement (fixed ``seed`` for the resampling).
    """
    out = {}
    for key in METRICS:
        scores = np.array([[r[key]] for r in records])
        point, low, high = stratified_bootstrap_ci(scores, iqm, reps=reps, seed=seed)
        mean, mean_low, mean_high = stratified_bootstrap_ci(scores, np.mean, reps=reps, seed=seed)
        out[key] = {
            "iqm": point,
            "iqm_ci95": [low, high],
            "mean": mean,
            "mean_ci95": [mean_low, mean_high],
            "std": float(scores.std(ddof=1)) if len(scores) > 1 else None,  # of one: undefined
        }
    return out


def markdown(groups: dict[str, list[dict]], stats: dict[str, dict], reps: int) -> str:
    """The per-seed table and the aggregates, one section per variant."""
    lines = [
        f"IQM (mean of the middle 50 % of seeds) and mean, with stratified-bootstrap 95 % "
        f"confidence intervals ({reps} resamples of the seeds).",
    ]
    for name, records in groups.items():
        lines += ["", f"## {name} ({len(records)} seeds)", ""]
        lines += ["| seed | run | test capture rate | test mean return |", "|---|---|---|---|"]
        lines += [
            f"| {r['seed']} | {r['run_dir']} | {r['test_capture_rate']:.3f} "
            f"| {r['test_mean_return']:.2f} |"
            for r in records
        ]
        s = stats[name]
        for label, key in (("IQM", "iqm"), ("mean", "mean")):
            cells = [
                _with_ci(s[m][key], s[m][key + "_ci95"], d)
                for m, d in (("test_capture_rate", 3), ("test_mean_return", 2))
            ]
            lines.append(f"| **{label}** [95 % CI] | | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


def _with_ci(value: float, ci: list[float], digits: int) -> str:
    return f"{value:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def aggregate(sweep_dir: str | Path, reps: int = 2000, seed: int = 0) -> str:
    """Aggregate the seeds of a sweep into ``<sweep_dir>/aggregate/``; returns the Markdown."""
    if not isinstance(reps, int) or reps < 1:
        raise ConfigError(f"reps: must be a positive integer, got {reps}")
    if not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed: must be an integer >= 0, got {seed}")
    sweep_dir = Path(sweep_dir)
    groups, common = collect(sweep_dir)
    stats = {name: aggregate_scores(records, reps, seed) for name, records in groups.items()}
    out = sweep_dir / "aggregate"
    buffer = io.StringIO()
    writer = csv.DictWriter(
        buffer, fieldnames=["variant", "seed", "run_dir", *METRICS], lineterminator="\n"
    )
    writer.writeheader()
    for name, records in groups.items():
        writer.writerows({"variant": name, **r} for r in records)
    atomic_write_text(out / "seeds.csv", buffer.getvalue())
    table = markdown(groups, stats, reps)
    title = f"# Seeds of `{sweep_dir}`\n\n"
    if common:
        title += "Every run: " + " ".join(f"`{o}`" for o in common) + "\n\n"
    atomic_write_text(out / "seeds.md", title + table + "\n\n![seeds](seeds.png)\n")
    summary = {
        "reps": reps,
        "bootstrap_seed": seed,
        "common_overrides": common,
        "variants": stats,
        "runs": groups,
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    plot_seeds(groups, stats, METRICS, out / "seeds.png")
    log.info("aggregated %d runs in %s", sum(map(len, groups.values())), out)
    return table


@exit_on_error
def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m rlplat.eval.aggregate", description=__doc__.splitlines()[0]
    )
    parser.add_argument("sweep_dir", help="a sweep directory, e.g. runs/multirun/<time>")
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap resamples (2000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the resampling (0)")
    args = parser.parse_args(argv)
    print(aggregate(args.sweep_dir, args.reps, args.seed))


if __name__ == "__main__":
    main()
