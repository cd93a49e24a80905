"""The ``settings.json`` an AirSim simulator is started with, for an rlplat team.

``vehicle_names`` names the team's vehicles, ``make_settings`` builds the settings dict
(SimpleFlight multirotors on a steppable clock, spawn points converted from rlplat's ENU world
frame to NED through ``frames``) and ``write_settings`` writes it atomically with a stable
layout, so that the simulator and rlplat cannot disagree on names or spawn points.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rlplat.envs.airsim.frames import enu_to_ned
from rlplat.errors import ConfigError
from rlplat.io import atomic_write_text

__all__ = ["effective_clock_speed", "make_settings", "vehicle_names", "write_settings"]


def vehicle_names(
    attackers: int,
    defenders: int,
    attacker: str = "Attacker",
    defender: str = "Defender",
    names: Sequence[str] | None = None,
) -> list[str]:
    """Names of a team's vehicles: attackers first, then defenders.

    ``names`` (``dynamics.vehicles``) names them all, in that order; without it the first of
    each side gets the bare name and the i-th (i >= 2) gets ``f"{name}{i}"``:
    ``vehicle_names(2, 1)`` is ``["Attacker", "Attacker2", "Defender"]``.

    Raises:
        ConfigError: a negative count, an empty name, ``names`` of another length than the
            team, or two vehicles with the same name.
    """
    for field, count in (("attackers", attackers), ("defenders", defenders)):
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ConfigError(f"{field} must be an integer >= 0, got {count!r}")
    if names is not None:
        names = list(names) if not isinstance(names, str) else [names]
        if len(names) != attackers + defenders or not all(
            isinstance(n, str) and n.strip() for n in names
        ):
            raise ConfigError(
                f"dynamics.vehicles: must name the {attackers} attacker(s), then the "
                f"{defenders} defender(s): {attackers + defenders} non-empty names, got {names!r}"
            )
        _require_unique(names)
        return names
    for field, name in (("attacker", attacker), ("defender", defender)):
        if not isinstance(name, str) or not name.strip():
            raise ConfigError(f"{field} vehicle name must be a non-empty string, got {name!r}")
    names = [attacker if i == 1 else f"{attacker}{i}" for i in range(1, attackers + 1)]
    names += [defender if i == 1 else f"{defender}{i}" for i in range(1, defenders + 1)]
    _require_unique(names)
    return names


def _require_unique(names: Sequence[str]) -> None:
    seen = set()
    for name in names:
        if name in seen:
            raise ConfigError(f"vehicle names must be unique, {name!r} is repeated in {names}")
        seen.add(name)


def effective_clock_speed(clock_speed: float) -> float:
    """The sim seconds per wall second of AirSim's ``SteppableClock`` at ``ClockSpeed``
    ``clock_speed``: above 1 it keeps its 3-ms physics step and divides its loop's period by
    the speed's whole part (``SimModeWorldMultiRotor::setupClockSpeed``), so 2.5 runs at 2;
    below 1 it scales the step itself."""
    return float(math.floor(clock_speed)) if clock_speed >= 1 else float(clock_speed)


def make_settings(
    names: Sequence[str],
    spawn_enu: Mapping[str, Sequence[float]],
    clock_speed: float = 1.0,
) -> dict[str, Any]:
    """A settings.json dict for SimpleFlight multirotors named ``names``.

    Args:
        names: the vehicles, in the order they are listed.
        spawn_enu: name -> (x, y, z) spawn point, metres in rlplat's ENU world frame; written as
            the vehicle's ``X``/``Y``/``Z`` in NED.
        clock_speed: AirSim's ``ClockSpeed`` (sim seconds per wall second), > 0: a whole
            number, or one below 1 (see :func:`effective_clock_speed`).

    Returns:
        ``{"SettingsVersion": 1.2, "SimMode": "Multirotor", "ClockType": "SteppableClock",
        "ClockSpeed": ..., "Vehicles": {name: {"VehicleType": "SimpleFlight", "AutoCreate": true,
        "X": .., "Y": .., "Z": ..}}}``.

    Raises:
        ConfigError: no names, repeated names, a name without a spawn point (or a spawn point for
            no name), a spawn point that is not three finite numbers, or a bad clock_speed (not
            a number > 0, or one above 1 that AirSim would run at its whole part).
    """
    names = list(names)
    if not names:
        raise ConfigError("names must list at least one vehicle, got []")
    _require_unique(names)
    if isinstance(clock_speed, bool) or not _finite(clock_speed) or not clock_speed > 0:
        raise ConfigError(f"clock_speed must be a finite number > 0, got {clock_speed!r}")
    if effective_clock_speed(clock_speed) != clock_speed:
        raise ConfigError(
            f"clock_speed: AirSim speeds its clock up by whole factors only (ClockSpeed "
            f"{clock_speed:g} runs at {effective_clock_speed(clock_speed):g}); give a whole number "
            f"or one below 1, got {clock_speed!r}"
        )
    missing = [n for n in names if n not in spawn_enu]
    extra = [n for n in spawn_enu if n not in names]
    if missing or extra:
        raise ConfigError(
            f"spawn_enu must give a spawn point for exactly the vehicles {names}, "
            f"missing {missing}, unknown {extra}"
        )
    vehicles = {}
    for name in names:
        point = spawn_enu[name]
        if isinstance(point, (str, bytes)) or len(point) != 3 or not all(map(_finite, point)):
            raise ConfigError(f"spawn_enu[{name!r}] must be three finite numbers, got {point!r}")
        x, y, z = enu_to_ned(tuple(float(v) for v in point))
        vehicles[name] = {"VehicleType": "SimpleFlight", "AutoCreate": True, "X": x, "Y": y, "Z": z}
    return {
        "SettingsVersion": 1.2,
        "SimMode": "Multirotor",
        "ClockType": "SteppableClock",
        "ClockSpeed": float(clock_speed),
        "Vehicles": vehicles,
    }


def _finite(value: Any) -> bool:
    try:
        return not isinstance(value, bool) and math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def write_settings(path: str | os.PathLike, settings: Mapping[str, Any]) -> Path:
    """Write ``settings`` as JSON to ``path`` (temporary name + rename).

    The layout is stable: keys in the order of the dict (``make_settings`` builds them in a fixed
    order), two-space indent, a final newline; the same settings give the same bytes.

    Returns:
        the path written.

    Raises:
        ConfigError: the settings hold a value JSON cannot carry (NaN, infinity, an object).
    """
    try:
        text = json.dumps(settings, indent=2, allow_nan=False) + "\n"
    except (TypeError, ValueError) as err:
        raise ConfigError(f"settings cannot be written as JSON: {err}") from None
    path = Path(path)
    atomic_write_text(path, text)
    return path
