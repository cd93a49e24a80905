"""Draw a non-repeating, constraint-satisfying, split-stratified set of pursuit scenarios."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from rlplat.errors import ConfigError
from rlplat.scenarios.spec import MAX_MAGNITUDE, PARAM_NAMES, STRATEGIES, ParamSpec, ScenarioSpec

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
_MAX_ROUNDS = 60
_MAX_BATCH = 1 << 18  # most candidates per round grown for the rejection rate


@dataclass(frozen=True)
class SplitColumns:
    """One split as columns (k attackers, m defenders).

    Attributes:
        ids: scenario ids, e.g. ``"train-000042"``.
        values: (n, n_params) float64, the continuous columns in ``spec.param_names`` order.
        route: (n, m) int64 route index of every defender.
        strategy: (n, m) int64 index into ``STRATEGIES`` of every defender.
    """

    ids: list[str]
    values: np.ndarray
    route: np.ndarray
    strategy: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def grid_keys(spec: ScenarioSpec, values: np.ndarray, route, strategy) -> np.ndarray:
    """Identity of scenarios at the configured resolution: (n, n_params + 2 m) int64.

    The continuous columns' grid indices, then route and strategy of each defender in turn;
    ``route`` and ``strategy`` are (n, m) or, for one defender, (n,).
    """
    low, res = _grid(spec)
    k = np.rint((values - low) / res).astype(np.int64)
    shape = (len(k), spec.defenders)
    cat = np.stack([np.asarray(route).reshape(shape), np.asarray(strategy).reshape(shape)], 2)
    return np.concatenate([k, cat.reshape(len(k), 2 * spec.defenders)], axis=1)


def _grid(spec: ScenarioSpec) -> tuple[np.ndarray, np.ndarray]:
    """Low end and resolution of every continuous column: two (n_params,) float64."""
    specs = spec.param_specs
    return np.array([p.low for p in specs]), np.array([p.resolution for p in specs])


def _values(spec: ScenarioSpec, keys: np.ndarray) -> np.ndarray:
    low, res = _grid(spec)
    return np.round(low + keys[:, : len(low)] * res, 6)


def _draw_param(p: ParamSpec, rng: np.random.Generator, m: int) -> np.ndarray:
    if p.dist == "uniform":  # uniform over the grid values
        return rng.integers(0, p.levels, m)
    # gaussian, clipped to the range, snapped to the grid
    x = np.clip(rng.normal(p.mean, p.std, m), p.low, p.high)
    return np.clip(np.rint((x - p.low) / p.resolution), 0, p.levels - 1).astype(np.int64)


def _draw(spec: ScenarioSpec, rng: np.random.Generator, m: int) -> np.ndarray:
    """Draw ``m`` candidate grid keys (m, n_params + 2 defenders) from the distributions.

    The draws of the first attacker and defender come first (six columns, route, strategy),
    then those of the extra drones, so a 1-vs-1 set draws exactly what it always did.
    """
    levels = spec.strategy_levels
    w = np.array([spec.strategy_mix[STRATEGIES[i]] for i in levels], dtype=np.float64)

    def categorical() -> list[np.ndarray]:
        route = rng.integers(0, len(spec.routes), m)
        return [route, np.asarray(levels)[rng.choice(len(levels), size=m, p=w / w.sum())]]

    specs = spec.param_specs
    base = [_draw_param(p, rng, m) for p in specs[: len(PARAM_NAMES)]]
    cat = categorical()
    extra = [_draw_param(p, rng, m) for p in specs[len(PARAM_NAMES) :]]
    for _ in range(1, spec.defenders):
        cat += categorical()
    return np.stack(base + extra + cat, axis=1).astype(np.int64)


def _drone_columns(
    spec: ScenarioSpec, values: np.ndarray, team: str, attrs: tuple[str, ...], first: int = 0
) -> np.ndarray:
    """Columns ``{team}{i}_{attr}`` (no index for the first drone) of drones ``first..``:
    (n, drones - first, len(attrs))."""
    names = spec.param_names
    count = spec.attackers if team == "attacker" else spec.defenders
    idx = [[names.index(f"{team}{i or ''}_{a}") for a in attrs] for i in range(first, count)]
    return values[:, np.asarray(idx, dtype=np.int64).reshape(count - first, len(attrs))]


def start_positions(spec: ScenarioSpec, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start positions from (n, n_params) column values: attackers (n, k, 3), defenders
    (n, m, 3), m ENU.

    The first defender starts at x = y = 0; attackers' x, y and z and extra defenders' x and y
    are offsets from its start (the files round attackers' altitudes to 1e-6 m).
    """
    z = values[:, 0]
    attackers = _drone_columns(spec, values, "attacker", ("dx", "dy", "dz")).copy()
    attackers[..., 2] += z[:, None]
    defenders = np.zeros((len(values), spec.defenders, 3))
    defenders[:, 0, 2] = z
    defenders[:, 1:] = _drone_columns(spec, values, "defender", ("dx", "dy", "z"), first=1)
    return attackers, defenders


def max_speeds(spec: ScenarioSpec, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Max speeds from (n, n_params) column values: attackers (n, k), defenders (n, m), m/s."""
    return (
        _drone_columns(spec, values, "attacker", ("max_speed",))[..., 0],
        _drone_columns(spec, values, "defender", ("max_speed",))[..., 0],
    )


def feasible(spec: ScenarioSpec, values: np.ndarray) -> np.ndarray:
    """Which rows of (n, n_params) column values meet every start constraint: (n,) bool.

    For every attacker-defender pair the defender lies inside the attacker's vision ellipsoid
    (world-axis aligned) and at least ``min_distance`` away; every attacker starts at or above
    ``min_altitude``; every two drones of the same team start at least ``min_separation`` apart;
    every start lies within ±``MAX_MAGNITUDE`` m (what the files hold).
    """
    offsets = _drone_columns(spec, values, "attacker", ("dx", "dy", "dz"))  # (n, k, 3)
    attackers, defenders = start_positions(spec, values)
    # Defender minus attacker for every pair, (n, k, m, 3); for the first defender exactly
    # minus the drawn offset.
    rel = defenders[:, None, :, :] - attackers[:, :, None, :]
    rel[:, :, 0, :] = -offsets
    a, b, c = spec.vision_semi_axes
    x, y, h = rel[..., 0], rel[..., 1], rel[..., 2]
    inside = (x / a) ** 2 + (y / b) ** 2 + (h / c) ** 2 <= 1.0
    far = np.sqrt(x**2 + y**2 + h**2) >= spec.min_distance
    ok = (inside & far).all(axis=(1, 2))
    ok &= (attackers[..., 2] >= spec.min_altitude).all(axis=1)
    for pos in (attackers, defenders):  # what the files hold (an altitude plus an offset)
        ok &= (np.abs(pos) <= MAX_MAGNITUDE).all(axis=(1, 2))
    for pos in (offsets, defenders):  # same-team pairs (z offsets compare like altitudes)
        for i, j in combinations(range(pos.shape[1]), 2):
            d = pos[:, i] - pos[:, j]
            ok &= np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2) >= spec.min_separation
    return ok


def _distinct_feasible(spec: ScenarioSpec, rng: np.random.Generator) -> np.ndarray:
    """Draw until ``n_total`` distinct feasible keys are found, in draw order."""
    n = spec.n_total
    keys = np.empty((0, len(spec.param_names) + 2 * spec.defenders), dtype=np.int64)
    drawn = accepted = 0
    teams = spec.attackers > 1 or spec.defenders > 1
    # With more drones, whose pairwise constraints reject far more candidates, the batch
    # grows with the rejection so far. 1 vs 1 keeps its batch sizes for _MAX_ROUNDS rounds
    # (same draws, same files as ever), then grows as well, for as many rounds again (a small
    # vision ellipsoid under the default offset ranges: most draws are rejected).
    for round_ in range(_MAX_ROUNDS if teams else 2 * _MAX_ROUNDS):
        need = 2.5 * (n - len(keys))
        m = max(1024, int(need))
        if (teams or round_ >= _MAX_ROUNDS) and drawn:
            m = max(m, min(int(need / max(accepted / drawn, 1e-3)), _MAX_BATCH))
        cand = _draw(spec, rng, m)
        drawn += m
        cand = cand[feasible(spec, _values(spec, cand))]
        accepted += len(cand)
        keys = np.concatenate([keys, cand])
        _, first = np.unique(keys, axis=0, return_index=True)
        keys = keys[np.sort(first)]
        if len(keys) >= n:
            log.debug("drew %d candidates for %d scenarios", drawn, n)
            return keys[:n]
    wide = offsets_out_of_view(spec)
    hint = f"narrow the offsets out of view ({'; '.join(wide)}), " if wide else ""
    raise ConfigError(
        f"scenario: {len(keys)} distinct scenarios of the {n} requested (n_train + n_val + "
        f"n_test) meet the constraints after {drawn:,} draws ({accepted:,} draws met them); "
        f"{hint}lower the counts, refine the resolution or relax the constraints (the attacker "
        "offset ranges against the vision ellipsoid, min_distance, min_altitude, min_separation, "
        f"starts within ±{MAX_MAGNITUDE:g} m)"
    )


def offsets_out_of_view(spec: ScenarioSpec) -> list[str]:
    """The attacker offset ranges that reach beyond the vision ellipsoid's semi-axis on their
    axis (draws there are never in view; with several attackers, all of them must be), as
    ``"attacker_dx [-48, 48] beyond 8 m"``."""
    out = []
    for name in ("attacker_dx", "attacker_dy", "attacker_dz"):
        p, semi = spec.params[name], offset_reach(spec, name)
        if max(-p.low, p.high) > semi:
            out.append(f"{name} [{p.low:g}, {p.high:g}] beyond {semi:g} m")
    return out


def offset_reach(spec: ScenarioSpec, name: str) -> float | None:
    """The vision ellipsoid's semi-axis (m) that bounds the attacker offset column ``name``
    (``attacker_dx``, ``attacker1_dz``, ...: the first defender starts in every attacker's
    view), or None for another column."""
    match = re.fullmatch(r"attacker\d*_d([xyz])", name)
    return None if match is None else spec.vision_semi_axes["xyz".index(match.group(1))]


def drawable(spec: ScenarioSpec, name: str, values: np.ndarray) -> np.ndarray:
    """Which ``values`` (grid values of column ``name``) some scenario can hold, by the start
    constraints one column meets alone, (len(values),) bool: an attacker offset within the
    vision ellipsoid's semi-axis on its axis; an attacker altitude (``defender_z`` plus an
    ``attacker*_dz``) of at least ``min_altitude`` and at most ``MAX_MAGNITUDE``."""
    ok = np.ones(len(values), dtype=bool)
    reach = offset_reach(spec, name)
    if reach is not None:  # an offset beyond the vision ellipsoid is never drawn
        ok &= np.abs(values) <= reach
    z, dz = spec.params["defender_z"], spec.params["attacker_dz"]
    if re.fullmatch(r"attacker\d*_dz", name):
        ok &= (values + z.high >= spec.min_altitude) & (values + z.low <= MAX_MAGNITUDE)
    elif name == "defender_z":  # the first defender: every attacker's offset is from it
        ok &= (values + dz.high >= spec.min_altitude) & (values + dz.low <= MAX_MAGNITUDE)
    return ok


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


def _warn_clipped(spec: ScenarioSpec, share: float = 0.05) -> None:
    """Log each gaussian parameter that draws more than ``share`` of its values outside
    [low, high]: those are drawn at the ends, which the quality report does not show. Once per
    config field (an extra drone's columns are drawn from their first drone's field)."""
    fields = [(f"params.{name}", p) for name, p in spec.params.items()]
    if spec.defenders > 1:  # the extra defenders' x and y offsets
        fields.append(("defender_spread", spec.defender_spread))
    for field, p in fields:
        if p.dist != "gaussian":
            continue
        below, above = p.cdf(p.low), 1.0 - p.cdf(p.high)
        if below + above > share:
            log.warning(
                "scenario.%s: the gaussian (mean %g, std %g) puts %.0f %% of its draws "
                "below low %g and %.0f %% above high %g; they are drawn at low and high",
                field, p.mean, p.std, 100 * below, p.low, 100 * above, p.high,
            )  # fmt: skip


def generate(spec: ScenarioSpec) -> dict[str, SplitColumns]:
    """Generate the train/val/test splits of ``spec`` (deterministic in ``spec.seed``)."""
    _warn_clipped(spec)
    rng = np.random.default_rng(spec.seed)
    keys = _distinct_feasible(spec, rng)
    n_cont = len(spec.param_names)
    # Strata: the combination of every defender's route and strategy (for one defender the
    # order of route * len(STRATEGIES) + strategy).
    _, strata = np.unique(keys[:, n_cont:], axis=0, return_inverse=True)
    labels = _stratified_labels(spec, strata.reshape(-1), rng)
    out = {}
    for i, split in enumerate(SPLITS):
        rows = np.flatnonzero(labels == i)
        rows = rows[rng.permutation(len(rows))]
        k = keys[rows]
        out[split] = SplitColumns(
            ids=[f"{split}-{j:06d}" for j in range(len(rows))],
            values=_values(spec, k),
            route=k[:, n_cont::2].copy(),
            strategy=k[:, n_cont + 1 :: 2].copy(),
        )
    return out
