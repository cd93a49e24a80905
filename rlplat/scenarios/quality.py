"""Quality of a scenario set: completeness, representativeness and independence of the splits."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from itertools import combinations
from typing import Any

import numpy as np

from rlplat.scenarios.generator import SplitColumns, drawable, grid_keys
from rlplat.scenarios.spec import STRATEGIES, ParamSpec, ScenarioSpec


def quality_report(spec: ScenarioSpec, splits: dict[str, SplitColumns]) -> dict[str, Any]:
    """Measure the three quality criteria of a generated set.

    Returns a JSON-ready dict with ``completeness`` (levels and bins absent from a split),
    ``representativeness`` (two-sample KS per continuous column, ``spec.param_names``, and
    chi-square per categorical column, ``spec.categorical_names``, for each pair of non-empty
    splits) and ``independence`` (duplicate counts over all columns).
    """
    full = {s: c for s, c in splits.items() if len(c)}
    pairs = list(combinations(full, 2))
    return {
        "completeness": _completeness(spec, full),
        "representativeness": {
            "ks": {
                name: {
                    f"{a}-{b}": _ks(full[a].values[:, i], full[b].values[:, i]) for a, b in pairs
                }
                for i, name in enumerate(spec.param_names)
            },
            "chi2": {
                name: {f"{a}-{b}": _chi2(get(full[a]), get(full[b])) for a, b in pairs}
                for name, get, _ in _categoricals(spec)
            },
        },
        "independence": _independence(spec, splits),
    }


_Getter = Callable[[SplitColumns], np.ndarray]


def _categoricals(spec: ScenarioSpec) -> list[tuple[str, _Getter, dict[int, str]]]:
    """Every categorical column in ``categorical_names`` order: its name, a getter of its (n,)
    values and its configured levels (value -> label)."""
    routes = {r: str(r) for r in range(len(spec.routes))}
    strategies = {i: STRATEGIES[i] for i in spec.strategy_levels}
    names = iter(spec.categorical_names)
    out = []
    for j in range(spec.defenders):
        out.append((next(names), lambda c, j=j: c.route[:, j], routes))
        out.append((next(names), lambda c, j=j: c.strategy[:, j], strategies))
    return out


def _completeness(spec: ScenarioSpec, splits: dict[str, SplitColumns]) -> dict[str, Any]:
    missing = []
    for split, cols in splits.items():
        for name, get, levels in _categoricals(spec):
            for v in sorted(set(levels) - set(get(cols).tolist())):
                missing.append(f"{split}: {name} {levels[v]}")
        for i, (name, p) in enumerate(zip(spec.param_names, spec.param_specs, strict=True)):
            edges = np.linspace(p.low, p.high, spec.quality_bins + 1)
            counts, _ = np.histogram(cols.values[:, i], bins=edges)
            # A bin that holds no grid value (narrower than the resolution) cannot be filled.
            # The grid as the files hold it (6 decimals): 0.1 + 2 * 0.1 is 0.30000000000000004,
            # whose edge a written 0.3 falls below.
            values = np.round(p.low + np.arange(p.levels) * p.resolution, 6)
            values = values[drawable(spec, name, values)]  # e.g. not beyond the ellipsoid
            grid, _ = np.histogram(values, bins=edges)
            likely = _expected_draws(p, edges, len(cols)) >= 1.0
            for b in np.flatnonzero((counts == 0) & (grid > 0) & likely):
                step = min(p.resolution, edges[1] - edges[0])
                low, high = (_edge(x, step) for x in edges[b : b + 2])
                missing.append(f"{split}: {name} bin [{low}, {high}]")
    return {"complete": not missing, "bins": spec.quality_bins, "missing": missing}


def _expected_draws(p: ParamSpec, edges: np.ndarray, n: int) -> np.ndarray:
    """How many of ``n`` draws of parameter ``p`` each bin (``edges``) expects: a uniform
    parameter's every bin is asked for (infinity); a gaussian's, clipped to [low, high], puts
    its tails' mass in the end bins. A bin a split of this size would fill less than once in
    expectation (a narrow gaussian's far tail) is not asked for."""
    if p.dist != "gaussian":
        return np.full(len(edges) - 1, np.inf)
    cdf = np.array([p.cdf(x) for x in edges])
    cdf[0], cdf[-1] = 0.0, 1.0  # clipped: the tails are drawn at low and high
    return n * np.diff(cdf)


def _edge(x: float, step: float) -> str:
    """A bin edge with one decimal more than ``step`` (the finer of the grid's and the bins'),
    so that a fine grid's edges read apart ([79.6674736, 79.6674762], not [79.67, 79.67])."""
    decimals = min(9, max(0, -math.floor(math.log10(step))) + 1)
    text = f"{x:.{decimals}f}".rstrip("0").rstrip(".")  # decimals >= 1: "100.0" keeps "100"
    return "0" if text == "-0" else text


def _ks(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    from scipy import stats  # on first use: scipy takes a second to import

    with warnings.catch_warnings():  # scipy's exact p-value may fall back to the asymptotic
        warnings.filterwarnings("ignore", "ks_2samp: Exact calculation unsuccessful")
        r = stats.ks_2samp(a, b)
    return {"statistic": round(float(r.statistic), 6), "pvalue": round(float(r.pvalue), 6)}


def _chi2(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    levels = np.union1d(a, b)
    table = np.array([[np.sum(x == v) for v in levels] for x in (a, b)])
    if len(levels) < 2:  # a single level: the splits agree trivially
        return {"statistic": 0.0, "pvalue": 1.0}
    from scipy import stats

    r = stats.chi2_contingency(table, correction=False)
    return {"statistic": round(float(r.statistic), 6), "pvalue": round(float(r.pvalue), 6)}


def _independence(spec: ScenarioSpec, splits: dict[str, SplitColumns]) -> dict[str, Any]:
    keys = {
        s: {tuple(k) for k in grid_keys(spec, c.values, c.route, c.strategy).tolist()}
        for s, c in splits.items()
    }
    within = {s: len(c) - len(keys[s]) for s, c in splits.items()}
    across = {f"{a}-{b}": len(keys[a] & keys[b]) for a, b in combinations(splits, 2)}
    return {
        "independent": not any(within.values()) and not any(across.values()),
        "duplicates_within": within,
        "duplicates_across": across,
    }


def format_quality(quality: dict[str, Any]) -> str:
    """The report as a plain-text table."""
    lines = []
    comp = quality["completeness"]
    lines.append(
        f"completeness      {'complete' if comp['complete'] else 'INCOMPLETE'} "
        f"({comp['bins']} bins per continuous parameter)"
    )
    lines += [f"  missing: {m}" for m in comp["missing"][:20]]
    if len(comp["missing"]) > 20:
        lines.append(f"  ... and {len(comp['missing']) - 20} more")
    rep = quality["representativeness"]
    tables = (("KS", rep["ks"]), ("chi2", rep["chi2"]))
    pairs = sorted({p for _, table in tables for v in table.values() for p in v})
    if not pairs:  # a single non-empty split: nothing to set it against
        lines.append(f"{'representativeness':<22}one non-empty split: no pair to compare")
    else:
        width = max([18, *(len(n) for _, table in tables for n in table)])  # column names
        lines.append(f"{'representativeness':<22}" + "".join(f"{p:>22}" for p in pairs))
        lines.append(f"{'  (stat / p-value)':<22}" + "".join(f"{'':>22}" for _ in pairs))
        for test, table in tables:
            for name, by_pair in table.items():
                cells = "".join(
                    f"{by_pair[p]['statistic']:>11.4f} / {by_pair[p]['pvalue']:<8.4f}"
                    for p in pairs
                )
                lines.append(f"  {test:<4} {name:<{width}}{cells}")
    ind = quality["independence"]
    lines.append(
        f"independence      {'independent' if ind['independent'] else 'DUPLICATES'}  "
        f"within {ind['duplicates_within']}  across {ind['duplicates_across']}"
    )
    return "\n".join(lines)
