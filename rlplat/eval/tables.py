"""An evaluation as a table: one row per scenario (its parameters, then its outcome), the
summary computed from the rows alone, and the CSV file of the rows."""

from __future__ import annotations

import csv
import io
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlplat.eval.episodes import EpisodeResults
from rlplat.eval.metrics import (
    CSV_FLOAT,
    breakdown,
    outcome_stats,
    speed_ratio,
    speed_ratio_bin,
    speed_ratio_labels,
)
from rlplat.io import atomic_write_text
from rlplat.scenarios import STRATEGIES, ScenarioSet


def route_labels(routes: torch.Tensor) -> list[str]:
    """A direction per route, its first setpoint to its last (the origin, where a defender
    starts, to a route of one setpoint): ``+X``, ``-X``, ``+Y`` or ``-Y``. A route that ends
    where it starts (a loop) takes the direction to its setpoint farthest from the start, and
    one that never leaves its start's vertical is ``Z``."""
    out = []
    for route in routes:
        start = route[0, :2] if len(route) > 1 else route.new_zeros(2)
        away = route[:, :2] - start
        end = away[-1]
        if end.norm() < 1e-6:  # a loop: the farthest setpoint says where it goes
            end = away[int(away.norm(dim=1).argmax())]
        if end.norm() < 1e-6:
            out.append("Z")
            continue
        axis = int(end.abs().argmax())
        out.append(("+" if end[axis] >= 0 else "-") + "XY"[axis])
    return out


def episode_rows(
    results: EpisodeResults,
    scenarios: ScenarioSet,
    split: str,
    routes: torch.Tensor,
    attackers: int | None = None,
    interceptable: torch.Tensor | None = None,
    route_interceptable: torch.Tensor | None = None,
) -> list[dict[str, Any]]:
    """One row per scenario (in split order): its id and parameters, then its outcome.

    The parameter columns describe the first attacker and defender (index 0 of the drone
    dimension); a set with k > 1 attackers or m > 1 defenders adds ``attacker{i}_start_x/y/z``
    and ``attacker{i}_max_speed`` per extra attacker i, ``defender{j}_route``,
    ``defender{j}_route_direction``, ``defender{j}_strategy``, ``defender{j}_start_x/y/z`` and
    ``defender{j}_max_speed`` per extra defender j and ``defenders_caught``, after
    ``speed_ratio``; when more than one attacker flies, ``team_speed_ratio`` follows
    ``speed_ratio``: the fastest of them over the first defender. ``attackers``: how many of
    each scenario's attackers flew (``env.attackers``; None: all). ``interceptable`` (E,) (see
    :mod:`rlplat.eval.ceiling`) adds the column ``interceptable``: True, False, or None where
    the bound is not defined; ``route_interceptable`` (E,), the route ceiling, adds the column
    ``route_interceptable`` the same way.
    """
    sc = {k: v.tolist() for k, v in scenarios.split(split).items()}
    ids = scenarios.ids[split]
    directions = route_labels(routes)
    keys = ("scenario_index", "captured", "grounded", "time_to_capture", "length")
    keys += ("min_distance", "visible_fraction", "route_fraction", "evasion", "returns")
    out = {k: getattr(results, k).tolist() for k in keys}
    separation = results.attacker_separation
    separation = None if separation is None else separation.tolist()
    terms = {k: v.tolist() for k, v in results.term_sums.items()}
    caught_count = results.defender_caught.sum(-1).tolist()
    bound = _flags(interceptable)
    route_bound = _flags(route_interceptable)
    rows = []
    for e, i in enumerate(out["scenario_index"]):
        v_a, v_d = sc["attacker_max_speed"][i], sc["defender_max_speed"][i]
        starts_a, starts_d = sc["attacker_start"][i], sc["defender_start"][i]
        routes_d, strategies_d = sc["route"][i], sc["defender_strategy"][i]
        captured = out["captured"][e]
        flown = len(v_a) if attackers is None else attackers
        extra: dict[str, Any] = {}
        if flown > 1:
            extra["team_speed_ratio"] = speed_ratio(max(v_a[:flown]), v_d[0])
        for a in range(1, flown):
            extra.update(_xyz(f"attacker{a}_start", starts_a[a]))
            extra[f"attacker{a}_max_speed"] = v_a[a]
        for d in range(1, len(v_d)):
            extra[f"defender{d}_route"] = routes_d[d]
            extra[f"defender{d}_route_direction"] = directions[routes_d[d]]
            extra[f"defender{d}_strategy"] = STRATEGIES[strategies_d[d]]
            extra.update(_xyz(f"defender{d}_start", starts_d[d]))
            extra[f"defender{d}_max_speed"] = v_d[d]
        if len(v_d) > 1:
            extra["defenders_caught"] = caught_count[e]
        route = routes_d[0]
        row = {
            "scenario_id": ids[i],
            "route": route,
            "route_direction": directions[route],
            "defender_strategy": STRATEGIES[strategies_d[0]],
            **_xyz("defender_start", starts_d[0]),
            **_xyz("attacker_start", starts_a[0]),
            "defender_max_speed": v_d[0],
            "attacker_max_speed": v_a[0],
            "speed_ratio": speed_ratio(v_a[0], v_d[0]),
            **extra,
            **({} if bound is None else {"interceptable": bound[e]}),
            **({} if route_bound is None else {"route_interceptable": route_bound[e]}),
            "captured": captured,
            "grounded": out["grounded"][e],
            "time_to_capture_s": out["time_to_capture"][e] if captured else None,
            "steps": out["length"][e],
            "min_distance_m": out["min_distance"][e],
            **(
                {"attacker_separation_m": _or_none(separation[e])}
                if flown > 1 and separation is not None
                else {}
            ),
            "visible_fraction": out["visible_fraction"][e],
            "route_fraction": out["route_fraction"][e],
            "evasion": out["evasion"][e],
            "return": out["returns"][e],
            **{f"reward_{k}": v[e] for k, v in terms.items()},
        }
        rows.append(row)
    return rows


def _or_none(x: float) -> float | None:
    """``x``, None (an empty cell) where it is NaN."""
    return None if math.isnan(x) else x


def _flags(bound: torch.Tensor | None) -> list[bool | None] | None:
    """A ceiling's values as column cells: True, False, or None where it is not defined."""
    if bound is None:
        return None
    return [None if math.isnan(x) else bool(x) for x in bound.tolist()]


def summarize(rows: list[dict[str, Any]], terms: list[str], edges: list[float]) -> dict:
    """Overall and per-group outcome statistics of a per-episode table (see
    :func:`episode_rows`): what ``summary.json`` holds, computed from the rows alone."""

    def col(key: str) -> np.ndarray:
        return np.array([np.nan if r[key] is None else r[key] for r in rows], dtype=float)

    columns = {
        "captured": col("captured").astype(bool),
        "time_to_capture": col("time_to_capture_s"),
        "returns": col("return"),
        "visible_fraction": col("visible_fraction"),
        "min_distance": col("min_distance_m"),
        "route_fraction": col("route_fraction"),
        "evasion": col("evasion"),
    }
    for key in ("interceptable", "route_interceptable"):
        if rows and key in rows[0]:
            columns[key] = col(key)
    routes = sorted({(r["route"], r["route_direction"]) for r in rows})
    strategies = {i: s for i, s in enumerate(STRATEGIES)}
    labels = speed_ratio_labels(edges)
    team = {}
    if rows and "attacker_separation_m" in rows[0]:
        team["attacker_separation"] = separation_stats(col("attacker_separation_m"))
    return {
        **outcome_stats(**columns),
        **team,
        "ground_rate": float(np.mean(col("grounded"))),
        "mean_steps": float(np.mean(col("steps"))),
        "reward_terms": {k: float(np.mean(col(f"reward_{k}"))) for k in terms},
        "speed_ratio_bins": edges,
        "by_strategy": breakdown(
            np.array([STRATEGIES.index(r["defender_strategy"]) for r in rows]),
            strategies,
            columns,
        ),
        "by_route": breakdown(
            col("route").astype(int), {i: f"{i} ({d})" for i, d in routes}, columns
        ),
        "by_speed_ratio": breakdown(
            speed_ratio_bin(col("speed_ratio"), edges), dict(enumerate(labels)), columns
        ),
    }


#: Team-mates nearer than this (m) count as a near miss of each other: two small quadrotors'
#: rotors and their downwash meet well before their centres do.
NEAR_MISS_M = 1.0


def separation_stats(separation: np.ndarray) -> dict[str, Any]:
    """How near a team's attackers came to each other, from each episode's least separation
    (NaN where fewer than two were in play): the least and the median over the episodes, and
    how many came within :data:`NEAR_MISS_M`."""
    x = separation[~np.isnan(separation)]
    return {
        "episodes": int(x.size),
        "least_m": float(x.min()) if x.size else None,
        "median_m": float(np.median(x)) if x.size else None,
        "near_miss_m": NEAR_MISS_M,
        "near_misses": int((x < NEAR_MISS_M).sum()),
    }


#: The columns that make an episode's outcome: two policies agree on a scenario when these do.
OUTCOME_COLUMNS = ("captured", "grounded", "steps", "defenders_caught")


def differing_outcomes(
    rows: list[dict[str, Any]], reference: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """The episodes whose outcome (:data:`OUTCOME_COLUMNS`: capture, crash, episode length,
    defenders caught) differs between two tables of the same scenarios (:func:`episode_rows`):
    ``{"scenario_id", "outcome", "reference"}`` each, the two outcomes as column -> value."""
    if [r["scenario_id"] for r in rows] != [r["scenario_id"] for r in reference]:
        raise ValueError("differing_outcomes: the tables hold different scenarios")
    keys = [k for k in OUTCOME_COLUMNS if rows and k in rows[0]]
    out = []
    for a, b in zip(rows, reference, strict=True):
        if any(a[k] != b[k] for k in keys):
            outcome, ref = ({k: r[k] for k in keys} for r in (a, b))
            out.append({"scenario_id": a["scenario_id"], "outcome": outcome, "reference": ref})
    return out


def _xyz(name: str, value: list[float]) -> dict[str, float]:
    return {f"{name}_{a}": v for a, v in zip("xyz", value, strict=True)}


#: The columns that say what a scenario is (starts, maximum speeds, speed ratios): written to at
#: most 6 decimals, the scenario files' (:func:`_scenario_float`), not to the 6 significant
#: digits of what was measured, so that read back they bin as the summary did (1.249999 stays
#: below 1.25).
SCENARIO_COLUMN = re.compile(r".*(_start_[xyz]|max_speed|speed_ratio)")


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    exact = {k for k in rows[0] if SCENARIO_COLUMN.fullmatch(k)}
    for row in rows:
        writer.writerow({k: _cell(v, k in exact) for k, v in row.items()})
    atomic_write_text(path, buffer.getvalue())


def _cell(value: Any, scenario: bool = False) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float):
        return _scenario_float(value) if scenario else f"{value:{CSV_FLOAT}}"
    return str(value)


def _scenario_float(value: float) -> str:
    """A scenario's value to at most 6 decimals: a start or a maximum speed flies as float32
    (1.1 is 1.10000002), so the shortest decimal of its float32 value (a value of more than
    about 7 significant digits comes back as float32 keeps it); a speed ratio is rounded to 6
    decimals already and written as it is."""
    if not math.isfinite(value):
        return f"{value:{CSV_FLOAT}}"
    if value != round(value, 6):
        value = float(str(np.float32(value)))
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text == "-0" else text
