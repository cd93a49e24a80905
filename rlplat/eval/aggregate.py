"""Aggregate a seed sweep: per-seed test scores, IQM and stratified-bootstrap 95 % CIs.

``python -m rlplat.eval.aggregate SWEEP_DIR`` reads every training run under ``SWEEP_DIR``
(e.g. ``runs/multirun/<time>`` of ``train.py -m seed=0,1,2``), groups the runs by the Hydra
overrides that set them apart other than ``seed`` (one group per configuration), and writes
``SWEEP_DIR/aggregate/seeds.{csv,md,png}`` and ``summary.json``. Each run is scored by what
its learner maximises (the summary's ``val_score``): an attacker's capture rate, a
defender's evasion score (beside the capture rate it allows).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from rlplat.cli import ArgumentParser, exit_on_error, path_arg
from rlplat.errors import ConfigError
from rlplat.eval.metrics import iqm, stratified_bootstrap_ci
from rlplat.eval.plots import plot_seeds
from rlplat.eval.summaries import run_overrides
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)

#: What is aggregated: the best checkpoint's scores on the test split (training's summary.json).
METRICS = {"test_capture_rate": "test capture rate", "test_mean_return": "test mean return"}
#: The learner's own score where it is not the capture rate (``val_score`` of the summary):
#: its key in the records and the table's label, the decimals it is shown with.
SCORES = {"evasion_score": ("test_evasion_score", "test evasion score")}
DIGITS = {"test_capture_rate": 3, "test_mean_return": 2, "test_evasion_score": 3}


def metrics_of(records: list[dict[str, Any]]) -> dict[str, str]:
    """The metrics (key -> label) the records hold: the learner's score first, where it is not
    the capture rate."""
    own = {key: label for key, label in SCORES.values() if records and key in records[0]}
    return own | METRICS


def find_runs(sweep_dir: Path) -> list[Path]:
    """Training run directories under ``sweep_dir`` (a ``summary.json`` beside a
    ``config.yaml``), the sweep directory itself included."""
    found = {
        p.parent for p in sweep_dir.rglob("summary.json") if (p.parent / "config.yaml").is_file()
    }
    return sorted(found)


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
    found = {run: run_overrides(run) or [] for run in runs}
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
        score = summary.get("val_score", "capture_rate")  # what the learner maximised
        if score != "capture_rate" and score not in SCORES:
            raise ConfigError(
                f"{path}: val_score {score!r} is none of capture_rate, {', '.join(SCORES)}"
            )
        values = {k: summary[k] for k in METRICS}
        if score in SCORES:
            if "test_score" not in summary:
                raise ConfigError(f"{path}: missing test_score (its val_score is {score})")
            values[SCORES[score][0]] = summary["test_score"]
        for key, value in values.items():
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                shown = "test_score" if key not in summary else key
                raise ConfigError(f"{path}: {shown} is {value!r}, not a finite number")
        record = {"seed": summary["seed"], "run_dir": str(run.relative_to(sweep_dir))}
        name = " ".join(o for o in found[run] if o not in common) or "default"
        groups[name].append(record | {k: float(v) for k, v in values.items()})
    for name, records in groups.items():
        kinds = {tuple(k for k, _ in SCORES.values() if k in r) for r in records}
        if len(kinds) > 1:  # one configuration, one learner: a mix is a sweep over roles
            raise ConfigError(
                f"sweep_dir: variant {name} mixes runs scored differently (an attacker's and a "
                f"defender's: {', '.join(r['run_dir'] for r in records)}); aggregate them apart"
            )
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
    """Per metric (:func:`metrics_of`): IQM and mean over seeds, each with its
    stratified-bootstrap 95 % CI.

    The scores form a (seeds, 1) array: one task, the test split, so the stratified bootstrap
    resamples seeds with replacement (fixed ``seed`` for the resampling).
    """
    out = {}
    for key in metrics_of(records):
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
        metrics = metrics_of(records)
        lines += ["", f"## {name} ({len(records)} seed{'s' if len(records) != 1 else ''})", ""]
        lines += ["| seed | run | " + " | ".join(metrics.values()) + " |"]
        lines += ["|---|---|" + "---|" * len(metrics)]
        lines += [
            f"| {r['seed']} | {r['run_dir']} | "
            + " | ".join(f"{r[m]:.{DIGITS[m]}f}" for m in metrics)
            + " |"
            for r in records
        ]
        s = stats[name]
        for label, key in (("IQM", "iqm"), ("mean", "mean")):
            cells = [_with_ci(s[m][key], s[m][key + "_ci95"], DIGITS[m]) for m in metrics]
            lines.append(f"| **{label}** [95 % CI] | | " + " | ".join(cells) + " |")
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
    every = {}  # every metric of every variant, in order: a variant without one leaves it empty
    for records in groups.values():
        every |= metrics_of(records)
    writer = csv.DictWriter(
        buffer, fieldnames=["variant", "seed", "run_dir", *every], lineterminator="\n"
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
    plot_seeds(groups, stats, every, out / "seeds.png")
    log.info("aggregated %d runs in %s", sum(map(len, groups.values())), out)
    return table


@exit_on_error
def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="python -m rlplat.eval.aggregate", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "sweep_dir", type=path_arg, help="a sweep directory, e.g. runs/multirun/<time>"
    )
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap resamples (2000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the resampling (0)")
    args = parser.parse_args(argv)
    print(aggregate(args.sweep_dir, args.reps, args.seed))


if __name__ == "__main__":
    main()
