"""The scenario generator's schema: typed, validated, built from a plain mapping."""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from rlplat.errors import ConfigError

#: Continuous parameters of the first attacker and defender, in file and column order (the
#: columns of extra drones follow, see ``ScenarioSpec.param_names``).
PARAM_NAMES = (
    "defender_z",
    "attacker_dx",
    "attacker_dy",
    "attacker_dz",
    "defender_max_speed",
    "attacker_max_speed",
)
#: Defender strategies; a scenario stores the index into this tuple.
STRATEGIES = ("setpoints", "nn")
DISTRIBUTIONS = ("uniform", "gaussian")
#: The finest grid step: values are written to 6 decimals.
MIN_RESOLUTION = 1e-6
#: The largest magnitude of a position (m) or a speed (m/s) in a set: the simulator computes in
#: float32, which keeps 1e5 m to a centimetre; far larger values overflow its squares.
MAX_MAGNITUDE = 1e5
#: The most grid values a parameter may have (the quality report bins them all).
MAX_LEVELS = 10_000_000


@dataclass(frozen=True)
class ParamSpec:
    """Range, grid and distribution of one continuous parameter.

    Attributes:
        low: least value.
        high: largest value (> low).
        resolution: grid step; drawn values are snapped to ``low + k * resolution``.
        dist: ``uniform`` on [low, high] or ``gaussian`` clipped to [low, high].
        mean: gaussian mean (None: centre of the range).
        std: gaussian standard deviation (None: a sixth of the range).
    """

    low: float
    high: float
    resolution: float
    dist: Literal["uniform", "gaussian"] = "uniform"
    mean: float | None = None
    std: float | None = None

    def cdf(self, x: float) -> float:
        """The gaussian's probability of a draw below ``x`` before it is clipped to
        [low, high] (a gaussian parameter's; its mean and std are resolved)."""
        return 0.5 * (1.0 + math.erf((x - self.mean) / (self.std * math.sqrt(2.0))))

    @property
    def levels(self) -> int:
        """Number of grid values in [low, high], counted in millionths (the files keep 6
        decimals) so that a rounded ``high - low`` loses no value."""
        step = micro(self.resolution)
        if step < 1:  # finer than the files keep: from_dict refuses it, the float count stays
            return math.floor((self.high - self.low) / self.resolution + 1e-9) + 1
        return (micro(self.high) - micro(self.low)) // step + 1


def micro(value: float) -> int:
    """``value`` in millionths, the resolution of the files (exact for 6 decimals and
    magnitudes up to ``MAX_MAGNITUDE``)."""
    return round(value * 1_000_000)


#: The most ``quality_bins``: bins per column of the completeness check (each bin's count is
#: reported; a billion of them took gigabytes before a set was written).
MAX_QUALITY_BINS = 10_000
#: The most scenarios a set holds (n_train + n_val + n_test): a generation draws two and a half
#: times as many candidates in one batch (a hundred million took all of 24 GB).
MAX_SCENARIOS = 1_000_000
#: The most drones of a side (attackers, defenders): the pairwise separation check of a draw
#: grows with their square (64 defenders took four minutes to find no place for them).
MAX_TEAM = 32
#: Default ``defender_spread``: x and y offset of an extra defender from the first one, m.
DEFAULT_DEFENDER_SPREAD = ParamSpec(low=-15.0, high=15.0, resolution=0.5)
#: Fields ``from_dict`` accepts but does not require, and ``to_dict`` omits for 1 vs 1.
TEAM_FIELDS = ("attackers", "defenders", "min_separation", "defender_spread")


@dataclass(frozen=True)
class ScenarioSpec:
    """Everything that defines a scenario set (see ``conf/scenario/pursuit.yaml``).

    A scenario has ``attackers`` (k) attackers and ``defenders`` (m) defenders. Its continuous
    columns (``param_names``) are the six of ``PARAM_NAMES`` for the first attacker and defender,
    then per extra attacker i = 1..k-1 ``attacker{i}_dx``, ``attacker{i}_dy``, ``attacker{i}_dz``
    (offset from the first defender's start, drawn from the ``attacker_d*`` specs) and
    ``attacker{i}_max_speed``, then per extra defender j = 1..m-1 ``defender{j}_dx`` and
    ``defender{j}_dy`` (offset from the first defender's start, ``defender_spread``),
    ``defender{j}_z`` (absolute altitude, ``defender_z``) and ``defender{j}_max_speed``. Its
    categorical columns (``categorical_names``) are the route and strategy of every defender.
    """

    seed: int
    n_train: int
    n_val: int
    n_test: int
    vision_semi_axes: tuple[float, float, float]
    min_distance: float
    min_altitude: float
    quality_bins: int
    params: dict[str, ParamSpec]
    strategy_mix: dict[str, float]
    routes: tuple[tuple[tuple[float, float, float], ...], ...]
    attackers: int = 1
    defenders: int = 1
    min_separation: float = 3.0
    defender_spread: ParamSpec = DEFAULT_DEFENDER_SPREAD

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of the continuous columns, in column order (``PARAM_NAMES`` first)."""
        names = list(PARAM_NAMES)
        for i in range(1, self.attackers):
            names += [f"attacker{i}_{a}" for a in ("dx", "dy", "dz", "max_speed")]
        for j in range(1, self.defenders):
            names += [f"defender{j}_{a}" for a in ("dx", "dy", "z", "max_speed")]
        return tuple(names)

    @property
    def param_specs(self) -> tuple[ParamSpec, ...]:
        """The ParamSpec each continuous column is drawn from, in ``param_names`` order."""
        return tuple(
            self.params[n] if n in self.params else self._extra_spec(n) for n in self.param_names
        )

    def _extra_spec(self, name: str) -> ParamSpec:
        team, attr = name.split("_", 1)
        if team.startswith("attacker"):
            return self.params[f"attacker_{attr}"]
        if attr in ("dx", "dy"):
            return self.defender_spread
        return self.params[f"defender_{attr}"]

    @property
    def categorical_names(self) -> tuple[str, ...]:
        """Names of the categorical columns: route and strategy of every defender, in order."""
        names = ["route", "defender_strategy"]
        for j in range(1, self.defenders):
            names += [f"defender{j}_route", f"defender{j}_strategy"]
        return tuple(names)

    @property
    def counts(self) -> dict[str, int]:
        """Scenarios per split, in split order."""
        return {"train": self.n_train, "val": self.n_val, "test": self.n_test}

    @property
    def n_total(self) -> int:
        return self.n_train + self.n_val + self.n_test

    @property
    def strategy_levels(self) -> list[int]:
        """Indices (into STRATEGIES) of the strategies with positive weight."""
        return [i for i, s in enumerate(STRATEGIES) if self.strategy_mix.get(s, 0.0) > 0]

    def max_combinations(self) -> int:
        """Distinct parameter combinations on the grid (an upper bound of the feasible ones)."""
        n = (len(self.routes) * len(self.strategy_levels)) ** self.defenders
        for p in self.param_specs:
            n *= p.levels
        return n

    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON-ready form (the ``config`` of a manifest).

        For 1 vs 1 the team fields (``TEAM_FIELDS``) are left out, so a 1-vs-1 manifest is the
        one written before they existed.
        """
        d = dataclasses.asdict(self)
        d["vision_semi_axes"] = list(self.vision_semi_axes)
        d["routes"] = [[list(p) for p in r] for r in self.routes]
        if self.attackers == 1 and self.defenders == 1:
            for k in TEAM_FIELDS:
                del d[k]
        return d

    @classmethod
    def from_dict(
        cls, raw: Mapping[str, Any], where: str = "scenario", written: bool = False
    ) -> ScenarioSpec:
        """Validate ``raw`` (e.g. the resolved ``scenario`` config) and build the spec.
        ``written``: the config of a set already written (its manifest), whose report exists:
        ``quality_bins`` is not held to :data:`MAX_QUALITY_BINS`, the counts to
        :data:`MAX_SCENARIOS` nor the team sizes to :data:`MAX_TEAM`, which guard generation.

        Raises:
            ConfigError: one line naming the first offending field and its value.
        """
        raw = dict(raw)
        fields = {f.name for f in dataclasses.fields(cls)}
        _no_unknown(raw, fields, where)
        missing = sorted(fields - set(TEAM_FIELDS) - raw.keys())
        if missing:
            raise ConfigError(f"{where}: missing field(s) {', '.join(missing)}")

        counts = {k: _int(raw[k], f"{where}.{k}") for k in ("n_train", "n_val", "n_test")}
        for k, v in counts.items():
            if v < 0:
                raise ConfigError(f"{where}.{k}: count must be >= 0, got {v}")
        if sum(counts.values()) == 0:
            raise ConfigError(f"{where}: n_train + n_val + n_test must be > 0, got 0")
        if sum(counts.values()) > MAX_SCENARIOS and not written:
            raise ConfigError(
                f"{where}: n_train + n_val + n_test must be at most {MAX_SCENARIOS:,}, "
                f"got {sum(counts.values()):,}"
            )

        axes = _floats(raw["vision_semi_axes"], f"{where}.vision_semi_axes", 3)
        if min(axes) <= 0:
            raise ConfigError(f"{where}.vision_semi_axes: must be > 0, got {list(axes)}")
        if max(axes) > MAX_MAGNITUDE:
            raise ConfigError(
                f"{where}.vision_semi_axes: must be at most {MAX_MAGNITUDE:g} m, got {list(axes)}"
            )
        min_distance = _finite(raw["min_distance"], f"{where}.min_distance")
        if min_distance < 0:
            raise ConfigError(f"{where}.min_distance: must be >= 0 m, got {min_distance}")
        if min_distance >= max(axes):
            raise ConfigError(
                f"{where}.min_distance: {min_distance} m cannot be met inside the vision "
                f"ellipsoid (largest semi-axis {max(axes)} m)"
            )
        bins = _int(raw["quality_bins"], f"{where}.quality_bins")
        if bins < 1 or (bins > MAX_QUALITY_BINS and not written):
            raise ConfigError(
                f"{where}.quality_bins: must be in [1, {MAX_QUALITY_BINS}], got {bins}"
            )

        params_raw = dict(raw["params"] or {})
        if set(params_raw) != set(PARAM_NAMES):
            unknown = sorted(set(params_raw) - set(PARAM_NAMES))
            missing = sorted(set(PARAM_NAMES) - set(params_raw))
            raise ConfigError(
                f"{where}.params: unknown {unknown} / missing {missing}; "
                f"expected {', '.join(PARAM_NAMES)}"
            )
        params = {n: _param(params_raw[n], f"{where}.params.{n}", written) for n in PARAM_NAMES}
        if not params["defender_z"].low > 0:  # a start on or under the ground ends at once
            raise ConfigError(
                f"{where}.params.defender_z.low: starts are above the ground (0 m), got "
                f"{params['defender_z'].low}"
            )
        for n in ("attacker_max_speed", "defender_max_speed"):
            if not params[n].low > 0:
                raise ConfigError(
                    f"{where}.params.{n}.low: a maximum speed must be > 0 m/s, got {params[n].low}"
                )

        if not isinstance(raw["strategy_mix"], Mapping):
            raise ConfigError(
                f"{where}.strategy_mix: expected a mapping of strategy to weight, got "
                f"{raw['strategy_mix']!r}"
            )
        mix = {
            str(k): _finite(v, f"{where}.strategy_mix.{k}") for k, v in raw["strategy_mix"].items()
        }
        for k, v in mix.items():
            if k not in STRATEGIES:
                raise ConfigError(
                    f"{where}.strategy_mix: unknown strategy '{k}'; valid: {', '.join(STRATEGIES)}"
                )
            if v < 0 or not math.isfinite(v):
                raise ConfigError(f"{where}.strategy_mix.{k}: weight must be >= 0, got {v}")
        if sum(mix.values()) <= 0:
            raise ConfigError(f"{where}.strategy_mix: weights must sum to > 0, got {mix}")

        if not isinstance(raw["routes"], Sequence) or isinstance(raw["routes"], str):
            raise ConfigError(
                f"{where}.routes: expected a list of routes (each a list of [x, y, z]), got "
                f"{raw['routes']!r:.60}"
            )
        routes = tuple(_route(r, f"{where}.routes[{i}]") for i, r in enumerate(raw["routes"]))
        if not routes:
            raise ConfigError(f"{where}.routes: at least one route is needed")
        if len({len(r) for r in routes}) != 1:
            raise ConfigError(
                f"{where}.routes: all routes need the same number of setpoints, "
                f"got {[len(r) for r in routes]}"
            )

        team = {k: _int(raw.get(k, 1), f"{where}.{k}") for k in ("attackers", "defenders")}
        for k, v in team.items():
            if v < 1 or (v > MAX_TEAM and not written):
                raise ConfigError(f"{where}.{k}: must be in [1, {MAX_TEAM}], got {v}")
        separation = _finite(raw.get("min_separation", 3.0), f"{where}.min_separation")
        if not separation >= 0:
            raise ConfigError(
                f"{where}.min_separation: must be a finite distance >= 0 m, got {separation}"
            )
        spread = raw.get("defender_spread")
        if spread is None:
            spread = DEFAULT_DEFENDER_SPREAD
        else:
            spread = _param(spread, f"{where}.defender_spread", written)

        spec = cls(
            seed=_int(raw["seed"], f"{where}.seed", low=0),
            vision_semi_axes=axes,
            min_distance=min_distance,
            min_altitude=_above_ground(raw["min_altitude"], f"{where}.min_altitude"),
            quality_bins=bins,
            params=params,
            strategy_mix=mix,
            routes=routes,
            min_separation=separation,
            defender_spread=spread,
            **counts,
            **team,
        )
        available = spec.max_combinations()
        if spec.n_total > available:
            raise ConfigError(
                f"{where}: {spec.n_total} scenarios requested (n_train + n_val + n_test) but only "
                f"{available} distinct combinations exist at the configured resolution"
            )
        return spec


def _no_unknown(raw: Mapping[str, Any], known: set[str], where: str) -> None:
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown field; valid: {', '.join(sorted(known))}")


def _int(v: Any, where: str, low: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(f"{where}: expected an integer, got {v!r}")
    if low is not None and v < low:
        raise ConfigError(f"{where}: must be an integer >= {low}, got {v!r}")
    return v


def _above_ground(v: Any, where: str) -> float:
    """``v`` as an altitude above the ground (> 0 m); one line naming ``where`` otherwise."""
    out = _finite(v, where)
    if not out > 0:
        raise ConfigError(f"{where}: starts are above the ground (0 m), got {out}")
    return out


def _finite(v: Any, where: str) -> float:
    """``v`` as a finite float; a one-line :class:`ConfigError` naming ``where`` otherwise."""
    if not _real(v) or not math.isfinite(v):
        raise ConfigError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _real(x: Any) -> bool:
    """Whether ``x`` is a number, not what float() would also take: true is no 1.0 and "7.5"
    is no 7.5."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _floats(v: Any, where: str, n: int) -> tuple[float, ...]:
    if isinstance(v, (str, bytes)):  # its characters are no list of numbers ('985': 9, 8, 5)
        raise ConfigError(f"{where}: expected {n} numbers, got {v!r}")
    try:
        items = list(v)
    except TypeError:
        raise ConfigError(f"{where}: expected {n} finite numbers, got {v!r}") from None
    if len(items) != n or not all(_real(x) and math.isfinite(x) for x in items):
        raise ConfigError(f"{where}: expected {n} finite numbers, got {v!r}")
    return tuple(float(x) for x in items)


def _param(raw: Any, where: str, written: bool = False) -> ParamSpec:
    """One parameter's range, grid and distribution. ``written`` (a set's manifest): the rules
    that only guard generation are not applied (sets written before them load): the grid's
    size, a gaussian mean outside the range, and a mean or std on a uniform parameter, which
    draws nothing from them (dropped)."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{where}: expected a mapping of low, high, resolution, ..., got {raw!r}")
    raw = dict(raw)
    _no_unknown(raw, {f.name for f in dataclasses.fields(ParamSpec)}, where)
    low, high = _floats([raw.get("low"), raw.get("high")], f"{where}.low/high", 2)
    if not low < high:
        raise ConfigError(f"{where}: empty or inverted range [low={low}, high={high}]")
    res = _finite(raw.get("resolution"), f"{where}.resolution")
    for key, value in (("low", low), ("high", high)):
        if abs(value) > MAX_MAGNITUDE:
            raise ConfigError(
                f"{where}.{key}: must lie in [-{MAX_MAGNITUDE:g}, {MAX_MAGNITUDE:g}], got {value:g}"
            )
    # the finest step of 6 decimals (what the files keep) that makes at most MAX_LEVELS values
    least = max(micro(MIN_RESOLUTION), math.ceil((micro(high) - micro(low)) / (MAX_LEVELS - 1)))
    if 0 < res < MIN_RESOLUTION:
        raise ConfigError(
            f"{where}.resolution: {res:g} is finer than the files keep (6 decimals); at least "
            f"{least / 1e6:g}"
        )
    for key, value in (("low", low), ("high", high), ("resolution", res)):
        if round(value, 6) != value:  # the files keep 6 decimals: grid values would move
            raise ConfigError(
                f"{where}.{key}: at most 6 decimals (what the files keep), got {value!r}"
            )
    # Counted in millionths, exactly: high - low in floats is rounded (5.0 - 4.9 < 0.1).
    if not 0 < micro(res) <= micro(high) - micro(low):
        raise ConfigError(f"{where}.resolution: must be in (0, high - low], got {res}")
    if ParamSpec(low=low, high=high, resolution=res).levels > MAX_LEVELS and not written:
        raise ConfigError(
            f"{where}.resolution: {res:g} makes more than {MAX_LEVELS:,} values in "
            f"[low={low:g}, high={high:g}]; at least {least / 1e6:g}"
        )
    dist = raw.get("dist", "uniform")
    if dist not in DISTRIBUTIONS:
        raise ConfigError(
            f"{where}.dist: unknown distribution '{dist}'; valid: {', '.join(DISTRIBUTIONS)}"
        )
    mean = raw.get("mean")
    std = raw.get("std")
    if dist != "gaussian" and written:
        mean = std = None
    if dist != "gaussian":  # would change the set's digest and draw nothing
        for key, value in (("mean", mean), ("std", std)):
            if value is not None:
                raise ConfigError(
                    f"{where}.{key}: only dist=gaussian has a {key}; dist={dist}, got {value!r}"
                )
    if dist == "gaussian":
        mean = (low + high) / 2 if mean is None else _finite(mean, f"{where}.mean")
        std = (high - low) / 6 if std is None else _finite(std, f"{where}.std")
        if not low <= mean <= high and not written:
            raise ConfigError(f"{where}.mean: must lie in [low={low}, high={high}], got {mean}")
        if not std > 0:
            raise ConfigError(f"{where}.std: must be > 0 for a gaussian, got {std}")
    return ParamSpec(low=low, high=high, resolution=res, dist=dist, mean=mean, std=std)


def _route(raw: Any, where: str) -> tuple[tuple[float, float, float], ...]:
    if not isinstance(raw, Sequence) or isinstance(raw, str):
        raise ConfigError(f"{where}: expected a list of [x, y, z] setpoints, got {raw!r:.60}")
    pts = tuple(_floats(p, f"{where}[{i}]", 3) for i, p in enumerate(raw))
    if not pts:
        raise ConfigError(f"{where}: a route needs at least one setpoint")
    for i, p in enumerate(pts):
        if max(abs(x) for x in p) > MAX_MAGNITUDE:
            raise ConfigError(
                f"{where}[{i}]: setpoint must lie within [-{MAX_MAGNITUDE:g}, {MAX_MAGNITUDE:g}] "
                f"m per axis, got {list(p)}"
            )
        if p[2] <= 0:
            raise ConfigError(f"{where}[{i}]: setpoint altitude must be > 0 m, got {p[2]}")
    return pts
