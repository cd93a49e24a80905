"""The AirSim tools of ``python -m rlplat.airsim``: the configured team's settings.json, and a
loopback test server for it.

The team comes from the train config: ``scenario.attackers`` (or ``env.attackers`` when set)
and ``scenario.defenders``; its vehicle names from ``dynamics.attacker_name`` and
``dynamics.defender_name`` when the dynamics has them (``dynamics=airsim``), else ``Attacker``
and ``Defender``; spawn points
from ``dynamics.spawn`` (``{vehicle: [x, y, z]}``, NED metres as settings.json X/Y/Z) where it
gives them, else on a line along east, ``SPAWN_SPACING`` metres apart at ground level; the
``ClockSpeed`` from ``dynamics.clock_speed`` (else 1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf

from rlplat.envs.airsim import make_settings, ned_to_enu, vehicle_names, write_settings
from rlplat.errors import ConfigError
from rlplat.experiment.config import compose_config

SPAWN_SPACING = 5.0  # m between default spawn points (ten times the contact radius of a quad)


def compose_train(overrides: Sequence[str]) -> DictConfig:
    """The train config with command-line ``overrides``; a bad override is a one-line error."""
    try:
        return compose_config("train", overrides)
    except HydraException as err:
        message = " ".join(str(err).split())
        raise ConfigError(f"overrides {list(overrides)}: {message}") from None


def team_settings(cfg: DictConfig) -> dict[str, Any]:
    """The settings.json dict for the team of ``cfg`` (see the module docstring)."""
    scenario, dynamics = cfg.scenario, cfg.dynamics
    for field in ("attackers", "defenders"):
        count = scenario.get(field)
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ConfigError(f"scenario.{field} must be an integer >= 1, got {count!r}")
    attackers = cfg.env.get("attackers") or scenario.attackers
    if not isinstance(attackers, int) or not 1 <= attackers <= scenario.attackers:
        raise ConfigError(f"env.attackers must be in [1, {scenario.attackers}], got {attackers}")
    names = vehicle_names(
        attackers,
        scenario.defenders,
        attacker=dynamics.get("attacker_name", "Attacker"),
        defender=dynamics.get("defender_name", "Defender"),
    )
    spawn_ned = dynamics.get("spawn") or {}
    spawn_ned = OmegaConf.to_container(spawn_ned) if not isinstance(spawn_ned, dict) else spawn_ned
    if not isinstance(spawn_ned, dict):
        raise ConfigError(f"dynamics.spawn must map vehicles to [x, y, z], got {spawn_ned!r}")
    unknown = sorted(set(spawn_ned) - set(names))
    if unknown:
        raise ConfigError(f"dynamics.spawn names {unknown}, not vehicles of the team {names}")
    spawn_enu = {}
    for i, name in enumerate(names):
        point = spawn_ned.get(name)
        if point is None:
            spawn_enu[name] = (SPAWN_SPACING * i, 0.0, 0.0)
            continue
        if not _triple(point):
            raise ConfigError(f"dynamics.spawn.{name} must be [x, y, z] in metres, got {point!r}")
        spawn_enu[name] = ned_to_enu(tuple(float(v) for v in point))
    return make_settings(names, spawn_enu, clock_speed=dynamics.get("clock_speed", 1.0))


def _triple(point: Any) -> bool:
    if isinstance(point, (str, bytes)) or not hasattr(point, "__len__") or len(point) != 3:
        return False
    return all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in point
    )


def settings_command(args: Sequence[str]) -> str:
    """``settings out=PATH [overrides]``: write the team's settings.json; returns a summary."""
    outs = [a for a in args if a.startswith("out=")]
    overrides = [a for a in args if not a.startswith("out=")]
    if len(outs) != 1 or not outs[0][4:]:
        raise ConfigError(f"settings needs exactly one out=PATH, got {outs or 'none'}")
    settings = team_settings(compose_train(overrides))
    path = write_settings(Path(outs[0][4:]), settings)
    vehicles = ", ".join(settings["Vehicles"])
    return f"settings.json for {vehicles} (ClockSpeed {settings['ClockSpeed']:g}) -> {path}"


def serve_command(args: Sequence[str]) -> int:
    """``serve [--settings FILE] [--port P] [server flags] [overrides]``: serve a test server
    until interrupted, for ``FILE`` or else for the team of the train config."""
    from rlplat.envs.airsim.testserver import main

    flags = [a for a in args if a.startswith("-") or "=" not in a]
    overrides = [a for a in args if a not in flags]
    if any(f == "--settings" or f.startswith("--settings=") for f in flags):
        if overrides:
            raise ConfigError(f"serve: overrides {overrides} do not apply with --settings")
        return main(flags)
    return main(flags, settings=team_settings(compose_train(overrides)))
