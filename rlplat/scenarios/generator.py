"""Draw a non-repeating, constraint-satisfying, split-stratified set of pursuit scenarios."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from rlplat.errors import ConfigError
from rlplat.scenarios.spec import PARAM_NAMES, STRATEGIES, ScenarioSpec

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
_MAX_ROUNDS = 60


@dataclass(frozen=True)
class SplitColumns:
    """One split as columns.

    Attributes:
        ids: scenario ids, e.g. ``"train-000042"``.
        values: (n, 6) float64, the continuous parameters in ``PARAM_NAMES`` order.
        route: (n,) int64 route index.
        strategy: (n,) int64 index into ``STRATEGIES``.
    """

    ids: list[str]
    values: np.ndarray
    route: np.ndarray
    strategy: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def grid_keys(spec: ScenarioSpec, values: np.ndarray, route, strategy) -> np.ndarray:
    """Identity of scenarios at the configured resolution: (n, 8) int64 grid indices."""
    low = np.array([spec.params[n].low for n in PARAM_NAMES])
    res = np.array([spec.params[n].resolution for n in PARAM_NAMES])
    k = np.rint((values - low) / res).astype(np.int64)
    return np.concatenate([k, np.asarray(route)[:, None], np.asarray(strategy)[:, None]], axis=1)


def _values(spec: ScenarioSpec, keys: np.ndarray) -> np.ndarray:
    low = np.array([spec.params[n].low for n in PARAM_NAMES])
    res = np.array([spec.params[n].resolution for n in PARAM_NAMES])
    return np.round(low + keys[:, : len(PARAM_NAMES)] * res, 6)


def _draw(spec: ScenarioSpec, rng: np.random.Generator, m: int) -> np.ndarray:
    """Draw ``m`` candidate grid keys (m, 8) from the configured distributions."""
    cols = []
    for name in PARAM_NAMES:
        p = spec.params[name]
        if p.dist == "uniform":  # uniform over the grid values
            k = rng.integers(0, p.levels, m)
        else:  # gaussian, clipped to the range, snapped to the grid
            x = np.clip(rng.normal(p.mean, p.std, m), p.low, p.high)
            k = np.clip(np.rint((x - p.low) / p.resolution), 0, p.levels - 1).astype(np.int64)
        cols.append(k)
    cols.append(rng.integers(0, len(spec.routes), m))
    levels = spec.strategy_levels
    w = np.array([spec.strategy_mix[STRATEGIES[i]] for i in levels], dtype=np.float64)
    cols.append(np.asarray(levels)[rng.choice(len(levels), size=m, p=w / w.sum())])
    return np.stack(cols, axis=1).astype(np.int64)


def feasible(spec: ScenarioSpec, values: np.ndarray) -> np.ndarray:
    """Which rows of (n, 6) parameter values meet every start constraint: (n,) bool.

    The defender lies inside the attacker's vision ellipsoid, at least ``min_distance`` away, and
    the attacker starts at or above ``min_altitude``.
    """
    z, dx, dy, dz = values[:, 0], values[:, 1], values[:, 2], values[:, 3]
    a, b, c = spec.vision_semi_axes
    inside = (dx / a) ** 2 + (dy / b) ** 2 + (dz / c) ** 2 <= 1.0
    far = np.sqrt(dx**2 + dy**2 + dz**2) >= spec.min_distance
    return inside & far & (z + dz >= spec.min_altitude)


def _distinct_feasible(spec: ScenarioSpec, rng: np.random.Generator) -> np.ndarray:
    """Draw until ``n_total`` distinct feasible keys are found, in draw order."""
    n = spec.n_total
    keys = np.empty((0, len(PARAM_NAMES) + 2), dtype=np.int64)
    drawn = 0
    for _ in range(_MAX_ROUNDS):
        m = max(1024, int(2.5 * (n - len(keys))))
        cand = _draw(spec, rng, m)
        drawn += m
        cand = cand[feasible(spec, _values(spec, cand))]
        keys = np.concatenate([keys, cand])
        _, first = np.unique(keys, axis=0, return_index=True)
        keys = keys[np.sort(first)]
        if len(keys) >= n:
            log.debug("drew %d candidates for %d scenarios", drawn, n)
            return keys[:n]
    raise ConfigError(
        f"scenario: only {len(keys)} distinct scenarios meet the constraints after {drawn} draws, "
        f"{n} requested (n_train + n_val + n_test); lower the counts, refine the resolution or "
        "relax the constraints"
    )


def _stratified_labels(spec: ScenarioSpec, strata: np.ndarray, rng: np.random.Generator):
    """Assign a split to each row so every stratum is shared among splits in proportion."""
    n = len(strata)
    perm = rng.permutation(n)
    order = perm[np.argsort(strata[perm], kind="stable")]  # grouped by stratum, random inside
    # Interleave split labels evenly: split s takes the positions (j + 0.5) / n_s.
    pos = np.concatenate([(np.arange(c) + 0.5) / c for c in spec.counts.values() if c])
    lab = np.concatenate([np.full(c, i) for i, c in enumerate(spec.counts.values()) if c])
    labels = np.empty(n, dtype=np.int64)
    labels[order] = lab[np.argsort(pos, kind="stable")]
    return labels


def generate(spec: ScenarioSpec) -> dict[str, SplitColumns]:
    """Generate the train/val/test splits of ``spec`` (deterministic in ``spec.seed``)."""
    rng = np.random.default_rng(spec.seed)
    keys = _distinct_feasible(spec, rng)
    strata = keys[:, -2] * len(STRATEGIES) + keys[:, -1]
    labels = _stratified_labels(spec, strata, rng)
    out = {}
    for i, split in enumerate(SPLITS):
        rows = np.flatnonzero(labels == i)
        rows = rows[rng.permutation(len(rows))]
        k = keys[rows]
        out[split] = SplitColumns(
            ids=[f"{split}-{j:06d}" for j in range(len(rows))],
            values=_values(spec, k),
            route=k[:, -2].copy(),
            strategy=k[:, -1].copy(),
        )
    return out
