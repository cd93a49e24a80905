"""Pool the evaluations of several runs: every episode of every seed in one table per policy.

``python -m rlplat.eval.pool DIR [DIR ...] [--split test]`` reads ``DIR/eval/<split>-*/``
(``summary.json`` and ``episodes.csv``, written by ``evaluate.py``) of each run, or a DIR that
is itself one evaluation (an ``evaluate.py`` ``out_dir``: a run flown on another scenario set or
in a team), and prints one Markdown row per policy: the episodes of all runs pooled (capture
rate with its 95 % Wilson interval, mean and median time to capture) and, where the evaluations
report the capture ceiling, the capture rate on the scenarios it covers against it. Seeds of
one configuration fly the same scenarios, so a scripted baseline's rows repeat the same
episodes once per run; one evaluation of it, passed once, counts once.

With ``--headroom`` a second table splits the scenarios by defender strategy and speed-ratio
bin (of the first attacker and defender, as ``episodes.csv`` records them; with ``--ratio
team``, of a team's fastest attacker and the first defender, its ``team_speed_ratio``): per
group the capture ceiling (where it is defined), the route ceiling (where the evaluations
record it: whether an intercept would exist had every defender kept to its route), the
fraction of scenarios that at least one episode of any policy and run captured ("captured by
any": a capture shown possible, not a bound), and each policy's pooled capture rate. The gap
between a policy and the ceiling or "captured by any" is where there is something left to win.

With ``--against POLICY`` (e.g. ``proportional_navigation``) a third table sets every other
policy against that one scenario by scenario: per scenario each policy's capture fraction over
its runs, the gain as the mean difference over the scenarios with its 95 % interval (normal,
over scenarios: what another draw of as many scenarios would show), the scenarios gained and
lost, and the difference of the mean time to capture on the scenarios both captured. Each run
of a learned policy is also set against the reference alone: the gain per run, and over the
runs their mean with a 95 % Student t interval: where another seed's run would land on these
same scenarios, which the interval over scenarios does not say (a margin over the reference
that three runs meet pooled may still be one that a new seed misses).
"""

from __future__ import annotations

import csv
import json
import logging
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from rlplat.agents.policies import POLICIES
from rlplat.cli import ArgumentParser, exit_on_error, name_arg, path_arg
from rlplat.errors import ConfigError
from rlplat.eval.metrics import speed_ratio_bin, speed_ratio_labels, wilson_interval
from rlplat.eval.summaries import is_learned, launch_overrides, num, policy_label
from rlplat.scenarios import SPLITS

#: What :func:`_read` returns: episodes and run count per policy, and every summary read.
#: Each episode row carries ``RUN``: the folder of the evaluation it comes from.
Evaluations = tuple[dict[str, list[dict[str, str]]], dict[str, int], list[dict[str, Any]]]
RUN = "_run"  # not a column of episodes.csv

log = logging.getLogger(__name__)


def pooled_rows(run_dirs: list[Path], split: str = "test") -> list[dict[str, Any]]:
    """Per policy (learned ones first, in the order met), the pooled outcome of its episodes.
    Evaluations of several scenario sets pool with a warning (``--headroom`` and ``--against``
    refuse them)."""
    return _pooled(_read(run_dirs, split))


def _pooled(read: Evaluations) -> list[dict[str, Any]]:
    """The plain table's rows; evaluations of several scenario sets, dynamics or team sizes
    pool with a warning (``--headroom`` and ``--against`` refuse them)."""
    episodes, runs, summaries = read
    for key, what in GAMES:
        seen = sorted({str(s.get(key))[:12] for s in summaries})
        if len(seen) > 1:
            log.warning(
                "pool: the evaluations flew %d %s (%s); the rows of policies flown on "
                "different ones do not compare", len(seen), what, ", ".join(seen),
            )  # fmt: skip
    return [_pool(label, runs[label], rows) for label, rows in episodes.items()]


def _read(run_dirs: list[Path], split: str) -> Evaluations:
    """Every evaluation of ``split`` under the runs: episodes and run count per policy (learned
    ones first, in the order met), and the evaluations' summaries. Runs of one drone launched
    with different overrides (other than ``seed``) are different policies: their label names
    the overrides that set them apart (as ``aggregate`` names its variants)."""
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    flown: list[tuple[str, dict[str, Any], list[dict[str, str]]]] = []
    seen: set[Path] = set()
    for run_dir in run_dirs:
        for path in _evaluations(Path(run_dir), split):
            if path.resolve() in seen:  # named twice (a run and one of its evaluations, ...)
                log.warning("pool: %s is named more than once; its episodes count once",
                            path.parent)  # fmt: skip
                continue
            seen.add(path.resolve())
            summary = json.loads(path.read_text())
            of = summary.get("split", split)  # a run's eval/<split>-* are of it by name
            if of != split:
                raise ConfigError(
                    f"pool: {path.parent} evaluates the {of} split, not {split}; pass --split {of}"
                )
            with open(path.parent / "episodes.csv", newline="") as f:
                rows = [{**r, RUN: str(path.parent)} for r in csv.DictReader(f)]
            flown.append((policy_label(summary), summary, rows))
    labels = _variant_labels(flown)
    episodes: dict[str, list[dict[str, str]]] = defaultdict(list)
    runs: dict[str, int] = defaultdict(int)
    learned: dict[str, bool] = {}
    for label, (_, summary, rows) in zip(labels, flown, strict=True):
        summary[LABEL] = label
        learned[label] = is_learned(summary)
        episodes[label].extend(rows)
        runs[label] += 1
    order = sorted(episodes, key=lambda k: (not learned[k], list(episodes).index(k)))
    return {label: episodes[label] for label in order}, runs, [s for _, s, _ in flown]


LABEL = "_label"  # the label pool gives an evaluation's policy, set on its summary


def _variant_labels(flown: list[tuple[str, dict[str, Any], list[dict[str, str]]]]) -> list[str]:
    """Each evaluation's label: its policy's, and for a learned policy whose runs were launched
    with different overrides, the overrides that set its run apart from the others (``default``
    for none). The overrides are the evaluation's ``run_overrides``, or those in its run's
    ``.hydra/`` where an older evaluation has none."""
    launches = [
        None if not is_learned(s) or (o := launch_overrides(s)) is None else tuple(o)
        for _, s, _ in flown
    ]
    labels = [label for label, _, _ in flown]
    for label in dict.fromkeys(labels):
        mine = [i for i, (other, s, _) in enumerate(flown) if other == label and is_learned(s)]
        known = {launches[i] for i in mine} - {None}
        if len(known) < 2:  # one launch (or none recorded): one policy
            continue
        if any(launches[i] is None for i in mine):
            log.warning("pool: some runs of %s have no record of their overrides; the others "
                        "are labelled by them", label)  # fmt: skip
        common = set.intersection(*map(set, known))
        for i in mine:
            if launches[i] is not None:
                apart = [o for o in launches[i] if o not in common]
                labels[i] = f"{label} {' '.join(apart) or 'default'}"
    return labels


def _evaluations(path: Path, split: str) -> list[Path]:
    """The ``summary.json`` of each evaluation ``path`` names: a training run's
    ``eval/<split>-*``, a folder of evaluations (``evaluate.py compare=true out_dir=``: its
    ``<split>-*``), or one evaluation directory (``evaluate.py``'s ``out_dir``: its
    ``summary.json`` beside its ``episodes.csv``)."""
    if not path.is_dir():
        raise ConfigError(f"pool: {path} is not a directory (a run, or an evaluation's folder)")
    own = path / "summary.json"
    if own.is_file() and (path / "episodes.csv").is_file():
        return [own]
    paths = sorted(path.glob(f"eval/{split}-*/summary.json")) or sorted(
        path.glob(f"{split}-*/summary.json")
    )
    if not paths:
        raise ConfigError(
            f"pool: no evaluation of the {split} split in {path} (a run's eval/{split}-*, a "
            f"folder of {split}-* evaluations, or one evaluation)"
        )
    return paths


#: What makes two evaluations' scenario ids one game: summary key, and what it is called.
GAMES = (
    ("scenario_digest", "scenario sets"),
    ("attackers", "team sizes"),
    ("dynamics", "dynamics"),
)


def _one_set(summaries: list[dict[str, Any]], option: str) -> None:
    """Refuse evaluations of different scenario sets, team sizes or dynamics: their scenario
    ids name different games."""
    for key, what in GAMES:
        values = {s.get(key) for s in summaries}
        if len(values) > 1:
            raise ConfigError(
                f"pool {option}: the evaluations fly {len(values)} {what} "
                f"({key}: {', '.join(sorted(map(str, values)))}); pool evaluations of one"
            )


def _attackers_only(summaries: list[dict[str, Any]], option: str, why: str) -> None:
    """Refuse the evaluation of a defender (a defender learner's, or its baselines)."""
    for s in summaries:
        scripted = POLICIES.get(s.get("policy"))
        role = scripted.role if scripted else s.get("learner", "attacker")
        if role != "attacker":
            raise ConfigError(
                f"pool {option}: {s.get('run_dir')} evaluates {s.get('name')}, a {role}; {why}"
            )


def _flag(value: str | None) -> bool:
    """A boolean cell of ``episodes.csv``."""
    return value in ("1", "True", "true")


def _captured(row: dict[str, str]) -> bool:
    return _flag(row["captured"])


def headroom_rows(
    run_dirs: list[Path], split: str = "test", ratio: str = "first"
) -> list[dict[str, Any]]:
    """Per group of scenarios (all; each defender strategy; each strategy and speed-ratio bin of
    the evaluations, by the first attacker and defender, or with ``ratio="team"`` by a team's
    fastest attacker, its episodes' ``team_speed_ratio``; for one attacker the two are the
    same), ``scenarios``, ``ceiling`` (None unless every scenario of the group has one),
    ``route_ceiling`` (the same for the route ceiling, where the evaluations record it),
    ``any`` (the fraction that some episode captured) and ``rates`` (policy -> pooled capture
    rate).

    Every evaluation must fly attackers (a learned or scripted one, not a defender learner's),
    on the same scenario set (its digest), team size, dynamics and bins.
    """
    _check_ratio(ratio)  # before any work
    return _headroom(_read(run_dirs, split), ratio)


#: ``--ratio``: which speed ratio bins the headroom: the first attacker's or the team's fastest.
RATIOS = ("first", "team")


def _check_ratio(ratio: str) -> None:
    if ratio not in RATIOS:
        raise ConfigError(f"pool --ratio: unknown '{ratio}'; valid: {', '.join(RATIOS)}")


def _headroom(read: Evaluations, ratio: str = "first") -> list[dict[str, Any]]:
    episodes, _, summaries = read
    _attackers_only(summaries, "--headroom", "the headroom is an attacker's")
    _one_set(summaries, "--headroom")
    edges = {tuple(s.get("speed_ratio_bins", ())) for s in summaries}
    if len(edges) > 1:
        raise ConfigError(f"pool --headroom: the evaluations bin differently: {sorted(edges)}")
    (bins,) = edges
    labels = speed_ratio_labels(bins) if bins else []
    column = "team_speed_ratio" if ratio == "team" and summaries[0].get("attackers", 1) > 1 else ""
    scenarios: dict[str, list[tuple[str, str]]] = {}
    bound: dict[str, bool] = {}  # from the first evaluation that bounds the scenario
    route_bound: dict[str, bool] = {}  # the same for the route ceiling
    captured: dict[str, bool] = defaultdict(bool)
    for label, rows in episodes.items():
        if column and rows and column not in rows[0]:
            raise ConfigError(
                f"pool --ratio team: the episodes of {label} have no {column} column (evaluated "
                "before it was recorded); evaluate again"
            )
        for r in rows:
            sid = r["scenario_id"]
            captured[sid] |= _captured(r)
            for key, known in (("interceptable", bound), ("route_interceptable", route_bound)):
                if sid not in known and r.get(key, "") not in ("", None):
                    known[sid] = _flag(r[key])
            if sid in scenarios:
                continue
            strategy = r.get("defender_strategy", "") or "all"
            groups = [("all", "all"), (strategy, "all")] if strategy != "all" else [("all", "all")]
            if labels:
                v = float(r[column or "speed_ratio"])
                groups.append((strategy, labels[int(speed_ratio_bin(np.array([v]), bins)[0])]))
            scenarios[sid] = groups
    members: dict[tuple[str, str], list[str]] = defaultdict(list)
    for sid, groups in scenarios.items():
        for g in groups:
            members[g].append(sid)

    def share(known: dict[str, bool], sids: list[str]) -> float | None:
        values = [known[s] for s in sids if s in known]
        return float(np.mean(values)) if len(values) == len(sids) else None

    out = []
    for group, sids in members.items():
        inside = set(sids)
        rates = {}
        for label, rows in episodes.items():
            flown = [_captured(r) for r in rows if r["scenario_id"] in inside]
            rates[label] = float(np.mean(flown)) if flown else None
        out.append({
            "defender": group[0],
            "speed_ratio": group[1],
            "scenarios": len(sids),
            "ceiling": share(bound, sids),
            **({"route_ceiling": share(route_bound, sids)} if route_bound else {}),
            "any": float(np.mean([captured[s] for s in sids])),
            "rates": rates,
        })  # fmt: skip
    order = ["all", *labels]
    out.sort(key=lambda r: (r["defender"] != "all", r["defender"], order.index(r["speed_ratio"])))
    return out


def paired_rows(run_dirs: list[Path], against: str, split: str = "test") -> list[dict[str, Any]]:
    """Every other policy against ``against``, scenario by scenario: ``gain`` (the mean over
    scenarios of the policy's capture fraction over its runs minus the reference's) with
    ``ci95`` and ``sd`` (of the per-scenario difference), ``gained`` and ``lost`` (scenarios
    where the policy's fraction is above or below the reference's), and ``time_delta_s`` (the
    mean over the scenarios both captured at least once of the difference of their mean times
    to capture; None if there are none) with ``both_captured``; ``run_gains``, each run's own
    gain over the reference on the same scenarios (a learned policy's; a scripted one's runs fly
    the same episodes: empty), and with two runs or more ``runs_sd`` and
    ``runs_ci95``, their standard deviation and the Student t interval of their mean (the
    expected gain of another seed's run; ``gain`` is that mean when every run flew every
    scenario once).

    The evaluations must fly attackers (not a defender learner's) on one scenario set, team
    size and dynamics, every policy all of the reference's scenarios."""
    return _paired(_read(run_dirs, split), against)


def _paired(read: Evaluations, against: str) -> list[dict[str, Any]]:
    episodes, runs, summaries = read
    if against not in episodes:
        raise ConfigError(
            f"pool --against: no evaluation of '{against}' under the runs; "
            f"valid: {', '.join(episodes)}"
        )
    _attackers_only(summaries, "--against", "the gain is an attacker's capture rate")
    _one_set(summaries, "--against")
    per = {label: _per_scenario(rows) for label, rows in episodes.items()}
    learned = {s[LABEL] for s in summaries if is_learned(s)}
    reference = per[against]
    sids = sorted(reference)
    out = []
    for label, outcome in per.items():
        if label == against:
            continue
        if set(outcome) != set(reference):
            raise ConfigError(
                f"pool --against: {label} flew {len(outcome)} scenarios, {against} "
                f"{len(reference)}, not the same ones; evaluate both on one split"
            )
        d = np.array([outcome[s][0] - reference[s][0] for s in sids])
        sd = float(d.std(ddof=1)) if d.size > 1 else float("nan")
        half = 1.96 * sd / np.sqrt(d.size)
        both = [s for s in sids if outcome[s][1] is not None and reference[s][1] is not None]
        run_gains = (
            _run_gains(episodes[label], reference, label, against) if label in learned else []
        )
        out.append({
            "policy": label,
            "runs": runs[label],
            "against": against,
            "scenarios": d.size,
            "gain": float(d.mean()),
            "ci95": _gain_interval(float(d.mean()), half),
            "sd": sd,
            "gained": int((d > 0).sum()),
            "lost": int((d < 0).sum()),
            "both_captured": len(both),
            "time_delta_s": (
                float(np.mean([outcome[s][1] - reference[s][1] for s in both])) if both else None
            ),
            "run_gains": run_gains,
            **_over_runs(run_gains),
        })  # fmt: skip
    return out


def _run_gains(
    rows: list[dict[str, Any]],
    reference: dict[str, tuple[float, float | None]],
    label: str,
    against: str,
) -> list[float]:
    """Each run's gain over the reference: the mean over the reference's scenarios of the run's
    capture fraction minus the reference's."""
    by_run: dict[str, list[dict[str, Any]]] = defaultdict(list)  # in the order read
    for r in rows:
        by_run[r[RUN]].append(r)
    gains = []
    for folder, run_rows in by_run.items():
        outcome = _per_scenario(run_rows)
        if set(outcome) != set(reference):
            raise ConfigError(
                f"pool --against: {label} in {folder} flew {len(outcome)} scenarios, "
                f"{against} {len(reference)}, not the same ones; evaluate each run on one split"
            )
        gains.append(float(np.mean([outcome[s][0] - reference[s][0] for s in reference])))
    return gains


def _over_runs(gains: list[float]) -> dict[str, Any]:
    """The spread of the runs' gains and the 95 % Student t interval of their mean (two runs or
    more)."""
    if len(gains) < 2:
        return {}
    from scipy import stats  # on first use: scipy takes a second to import

    g = np.asarray(gains)
    sd = float(g.std(ddof=1))
    half = float(stats.t.ppf(0.975, g.size - 1)) * sd / np.sqrt(g.size)
    return {"runs_sd": sd, "runs_ci95": _gain_interval(float(g.mean()), half)}


def _gain_interval(gain: float, half: float) -> tuple[float, float]:
    """``gain`` +- ``half``, within [-1, 1]: a gain is a difference of capture fractions (NaN,
    for one scenario, stays NaN)."""
    return float(np.clip(gain - half, -1.0, 1.0)), float(np.clip(gain + half, -1.0, 1.0))


def _per_scenario(rows: list[dict[str, str]]) -> dict[str, tuple[float, float | None]]:
    """Scenario id -> (capture fraction over its episodes, mean time to capture of the captured
    ones or None)."""
    flown: dict[str, list[bool]] = defaultdict(list)
    times: dict[str, list[float]] = defaultdict(list)
    for r in rows:
        caught = _captured(r)
        flown[r["scenario_id"]].append(caught)
        if caught:
            times[r["scenario_id"]].append(float(r["time_to_capture_s"]))
    return {
        sid: (float(np.mean(f)), float(np.mean(times[sid])) if times[sid] else None)
        for sid, f in flown.items()
    }


def paired_markdown(rows: list[dict[str, Any]]) -> str:
    """The paired comparison as Markdown; with a learned policy of two runs or more, a column of
    the gain per run and their mean with its interval over runs."""
    against = rows[0]["against"] if rows else "the reference"
    spread = any(len(r["run_gains"]) > 1 for r in rows)
    lines = [
        f"| policy | runs | scenarios | gain over {against} [95 % CI] | scenarios gained / lost "
        "| time to capture, where both capture [s] |"
        + (" gain per run; their mean [95 % CI over runs] |" if spread else ""),
        "|---|---|---|---|---|---|" + ("---|" if spread else ""),
    ]
    for r in rows:
        low, high = r["ci95"]
        interval = f" [{low:+.3f}, {high:+.3f}]" if np.isfinite(low) else ""  # one scenario: none
        delta = r["time_delta_s"]
        time = f"{delta:+.1f} ({r['both_captured']} scenarios)" if delta is not None else "–"
        per_run = ", ".join(f"{g:+.3f}" for g in r["run_gains"]) or "–"
        if "runs_ci95" in r:
            low, high = r["runs_ci95"]
            mean = float(np.mean(r["run_gains"]))
            per_run += f"; {mean:+.3f} [{low:+.3f}, {high:+.3f}]"
        lines.append(
            f"| {r['policy']} | {r['runs']} | {r['scenarios']} | {r['gain']:+.3f}{interval} "
            f"| {r['gained']} / {r['lost']} | {time} |" + (f" {per_run} |" if spread else "")
        )
    return "\n".join(lines)


def headroom_markdown(rows: list[dict[str, Any]], ratio: str = "first") -> str:
    """The headroom table as Markdown: one column per policy after the ceiling, the route
    ceiling (where recorded) and "captured by any"; ``ratio`` names the speed ratio that binned
    it."""
    policies = list(rows[0]["rates"]) if rows else []
    route = bool(rows) and "route_ceiling" in rows[0]
    lines = [
        f"| defender | {'team speed ratio' if ratio == 'team' else 'speed ratio'} | scenarios "
        f"| ceiling | {'route ceiling | ' if route else ''}captured by any | "
        + " | ".join(policies)
        + " |",
        "|---|---|---|---|---|" + "---|" * (len(policies) + route),
    ]
    for r in rows:
        bounds = [r["ceiling"], *([r["route_ceiling"]] if route else []), r["any"]]
        cells = [num(v) for v in bounds] + [num(r["rates"][p]) for p in policies]
        lines.append(
            f"| {r['defender']} | {r['speed_ratio']} | {r['scenarios']} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def _pool(label: str, runs: int, rows: list[dict[str, str]]) -> dict[str, Any]:
    captured = np.array([_captured(r) for r in rows])
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
        out["ceiling"] = float(np.mean([_flag(bound[i]) for i in np.flatnonzero(covered)]))
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
    parser = ArgumentParser(prog="python -m rlplat.eval.pool", description=__doc__.splitlines()[0])
    parser.add_argument(
        "run_dirs",
        nargs="+",
        type=path_arg,
        help="training run directories (their eval/<split>-*), or evaluation directories "
        "(an evaluate.py out_dir, e.g. of another scenario set)",
    )
    parser.add_argument("--split", default="test", help="test | val | train (default: test)")
    parser.add_argument(
        "--headroom",
        action="store_true",
        help="also split the scenarios by defender strategy and speed ratio: the ceiling, the "
        "fraction some policy and run captured, and each policy",
    )
    parser.add_argument(
        "--ratio",
        default="first",
        help="which speed ratio bins --headroom: first (the first attacker's, default) | team "
        "(the fastest attacker's of a team)",
    )
    parser.add_argument(
        "--against",
        metavar="POLICY",
        type=name_arg,
        help="also set every other policy against this one (e.g. proportional_navigation), "
        "scenario by scenario: the gain with its interval, scenarios gained and lost",
    )
    args = parser.parse_args(argv)
    _check_ratio(args.ratio)  # before any work
    read = _read(args.run_dirs, args.split)  # once, for every table
    tables = [markdown(_pooled(read))]  # all checked before any output
    if args.headroom:
        tables.append(headroom_markdown(_headroom(read, args.ratio), args.ratio))
    if args.against:
        tables.append(paired_markdown(_paired(read, args.against)))
    print("\n\n".join(tables))


if __name__ == "__main__":
    main()
