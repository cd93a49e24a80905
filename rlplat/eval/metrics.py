"""Statistics of an evaluation: Wilson intervals, IQM, stratified bootstrap, breakdowns.

Plain numpy/scipy, no torch: every function takes arrays and returns floats or dicts, so the
numbers in a report can be checked by hand.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

#: Two-sided 95 % normal quantile: scipy's ``stats.norm.ppf(0.975)`` (a test checks it), written
#: out so that importing the metrics does not import scipy.
Z95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default).

    Unlike the normal approximation it stays inside [0, 1] and is sensible at 0/n and n/n,
    e.g. 8/10 gives (0.4902, 0.9433) and 0/10 gives (0.0, 0.2775). ``n = 0`` gives (nan, nan).
    """
    if n <= 0:
        return (math.nan, math.nan)
    if not 0 <= successes <= n:
        raise ValueError(f"wilson_interval: successes must be in [0, {n}], got {successes}")
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    low = 0.0 if successes == 0 else max(0.0, centre - half)  # exact at the ends
    high = 1.0 if successes == n else min(1.0, centre + half)
    return (low, high)


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50 % of all scores (25 % cut at each end)."""
    from scipy import stats  # on first use: scipy takes a second to import

    return float(stats.trim_mean(np.asarray(scores, dtype=float).reshape(-1), 0.25))


def stratified_bootstrap_ci(
    scores: np.ndarray,
    statistic: Callable[[np.ndarray], float] = iqm,
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Point estimate and percentile confidence interval of ``statistic`` over runs.

    Args:
        scores: (runs, tasks) array, or (runs,) for one task. Each bootstrap replicate draws
            ``runs`` rows with replacement independently within every task (column), the
            stratified bootstrap of Agarwal et al. (2021, the ``rliable`` library), and applies
            ``statistic`` to the resampled (runs, tasks) array.
        statistic: maps an array of scores to a float (IQM by default).
        reps: bootstrap replicates.
        confidence: coverage of the interval.
        seed: seed of the resampling generator (same seed, same interval).

    Returns:
        (point, low, high).
    """
    x = np.asarray(scores, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] < 1:
        raise ValueError(f"stratified_bootstrap_ci: scores must be (runs, tasks), got {x.shape}")
    runs, tasks = x.shape
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, runs, size=(reps, runs, tasks))
    replicates = np.array([statistic(np.take_along_axis(x, r, axis=0)) for r in rows])
    alpha = (1.0 - confidence) / 2
    low, high = np.percentile(replicates, [100 * alpha, 100 * (1 - alpha)])
    return float(statistic(x)), float(low), float(high)


def speed_ratio_labels(edges: Sequence[float]) -> list[str]:
    """Bin labels for inner ``edges`` (sorted): ``<a``, ``a-b``, …, ``>=z``."""
    e = [f"{v:g}" for v in edges]
    return [f"<{e[0]}", *[f"{a}-{b}" for a, b in zip(e[:-1], e[1:], strict=True)], f">={e[-1]}"]


def speed_ratio(attacker: float, defender: float) -> float:
    """``attacker / defender`` maximum speed, rounded to 6 decimals: the speeds fly as float32,
    whose quotient misses the ratio of the speeds as written by a few 1e-8 (1.5 / 1.2 gives
    1.24999995), which would put a ratio on a bin's edge into the bin below."""
    return round(attacker / defender, 6)


def speed_ratio_bin(ratio: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """Bin index (E,) of each speed ratio for the sorted inner ``edges``; a ratio on an edge
    goes to the bin above it."""
    return np.searchsorted(np.asarray(edges, dtype=float), np.asarray(ratio), side="right")


#: How episodes.csv writes a float (6 significant digits).
CSV_FLOAT = ".6g"


def outcome_stats(
    captured: np.ndarray,
    time_to_capture: np.ndarray,
    returns: np.ndarray,
    visible_fraction: np.ndarray,
    min_distance: np.ndarray,
    route_fraction: np.ndarray | None = None,
    evasion: np.ndarray | None = None,
    interceptable: np.ndarray | None = None,
    route_interceptable: np.ndarray | None = None,
) -> dict[str, Any]:
    """Capture rate with its 95 % Wilson interval and the means of a group of episodes.

    Times to capture are averaged over the captured episodes only (None if there are none).
    ``route_fraction`` (share of its route the defender flew) and ``evasion`` (the same, 0 for
    a captured or crashed defender) are averaged into ``mean_route_fraction`` and
    ``evasion_score`` when given. ``interceptable`` (1, 0 or NaN where the bound is not
    defined, see :mod:`rlplat.eval.ceiling`) adds ``ceiling``: over the scenarios the bound
    covers, how many there are, the fraction where an intercept exists, the capture rate, and
    that capture rate as a fraction of the ceiling. ``route_interceptable`` (the route
    ceiling, defined for reacting defenders too) adds ``route_ceiling`` the same way.
    """
    captured = np.asarray(captured, dtype=bool)
    n, k = int(captured.size), int(captured.sum())
    low, high = wilson_interval(k, n)
    # The times as episodes.csv holds them, so that a summary's means and pool's, read back
    # from the CSV, are the same numbers (float32 12.3 is 12.3000002).
    times = np.array(
        [float(f"{t:{CSV_FLOAT}}") for t in np.asarray(time_to_capture, dtype=float)[captured]]
    )
    return {
        "n": n,
        "captured": k,
        "capture_rate": k / n if n else math.nan,
        "capture_rate_ci95": [low, high],
        "mean_time_to_capture_s": float(times.mean()) if k else None,
        "median_time_to_capture_s": float(np.median(times)) if k else None,
        "mean_return": float(np.mean(returns)) if n else math.nan,
        "mean_visible_fraction": float(np.mean(visible_fraction)) if n else math.nan,
        "mean_min_distance_m": float(np.mean(min_distance)) if n else math.nan,
        **{
            key: float(np.mean(v)) if n else math.nan
            for key, v in (("mean_route_fraction", route_fraction), ("evasion_score", evasion))
            if v is not None
        },
        **{
            key: _ceiling(captured, bound)
            for key, bound in (("ceiling", interceptable), ("route_ceiling", route_interceptable))
            if bound is not None
        },
    }


def _ceiling(captured: np.ndarray, interceptable: np.ndarray) -> dict[str, Any]:
    interceptable = np.asarray(interceptable, dtype=float)
    covered = ~np.isnan(interceptable)
    n = int(covered.sum())
    if not n:
        return {"scenarios": 0}
    rate, bound = float(captured[covered].mean()), float(interceptable[covered].mean())
    return {
        "scenarios": n,
        "interceptable_rate": bound,
        "capture_rate": rate,
        "fraction_of_ceiling": rate / bound if bound else None,
    }


def breakdown(
    groups: np.ndarray, labels: Mapping[int, str], columns: Mapping[str, np.ndarray]
) -> dict[str, dict[str, Any]]:
    """:func:`outcome_stats` per group: ``groups`` (E,) int codes, ``labels`` code -> name (in
    the order to report; empty groups are left out), ``columns`` the keyword arguments of
    :func:`outcome_stats` as (E,) arrays."""
    out = {}
    for code, name in labels.items():
        mask = np.asarray(groups) == code
        if mask.any():
            out[name] = outcome_stats(**{k: np.asarray(v)[mask] for k, v in columns.items()})
    return out
