"""Frame conversions between rlplat and AirSim: the one place they happen.

rlplat's world frame is ENU (x east, y north, z up). AirSim's is NED (x north, y east, z down),
and every vehicle's positions are relative to its own spawn point (the ``X``/``Y``/``Z`` of its
entry in ``settings.json``, NED metres). A point goes ENU world -> NED world -> NED local on the
way out, and back on the way in:

    p_local_ned = world_to_local(enu_to_ned(p_enu), spawn_ned)
    p_enu = ned_to_enu(local_to_world(p_local_ned, spawn_ned))

Velocities convert with ``enu_to_ned``/``ned_to_enu`` alone (spawn offsets are constant).

Every function works on the last axis (size 3) and keeps the kind of its input: a torch Tensor
gives a Tensor (same dtype and device), a numpy array an array, and a flat sequence of three
numbers a tuple of three Python floats (what goes on the wire). Nested sequences give a float64
array.

``enu_rows_to_ned`` and ``ned_rows_to_enu`` convert a few rows of Python floats (one per vehicle)
with the arithmetic of the float64 tensor path, -0.0 included, without building tensors: what a
lock-step loop does every step.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from rlplat.errors import ConfigError

log = logging.getLogger(__name__)

if TYPE_CHECKING:  # torch is not imported here: a tensor exists only if torch was imported
    from torch import Tensor

    Vector = Tensor | np.ndarray | Sequence[Any]

__all__ = [
    "enu_rows_to_ned",
    "enu_to_ned",
    "local_to_world",
    "ned_rows_to_enu",
    "ned_to_enu",
    "spawn_offsets",
    "world_to_local",
]


def _is_tensor(x: Any) -> bool:
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _swap(x: Any) -> Any:
    """(a, b, c) -> (b, a, -c) on the last axis: ENU <-> NED (the map is its own inverse)."""
    if _is_tensor(x):
        import torch

        if x.shape[-1:] != (3,):
            raise ValueError(f"expected a last axis of size 3, got shape {tuple(x.shape)}")
        return torch.stack((x[..., 1], x[..., 0], -x[..., 2]), dim=-1)
    if not isinstance(x, np.ndarray) and _is_flat_triple(x):
        a, b, c = (float(v) for v in x)
        return (b, a, -c + 0.0)  # + 0.0: no -0.0
    arr = np.asarray(x, dtype=None if isinstance(x, np.ndarray) else np.float64)
    if arr.shape[-1:] != (3,):
        raise ValueError(f"expected a last axis of size 3, got shape {arr.shape}")
    return np.stack((arr[..., 1], arr[..., 0], -arr[..., 2]), axis=-1)


def _is_flat_triple(x: Any) -> bool:
    return (
        isinstance(x, Sequence)
        and not isinstance(x, str)
        and len(x) == 3
        and all(isinstance(v, (int, float, np.number)) and not isinstance(v, bool) for v in x)
    )


def enu_to_ned(x: Vector) -> Vector:
    """ENU (x east, y north, z up) -> NED (x north, y east, z down): (x, y, z) -> (y, x, -z)."""
    return _swap(x)


def ned_to_enu(x: Vector) -> Vector:
    """NED (x north, y east, z down) -> ENU (x east, y north, z up): (x, y, z) -> (y, x, -z)."""
    return _swap(x)


def enu_rows_to_ned(rows: Sequence[Sequence[float]]) -> list[tuple[float, float, float]]:
    """ENU rows (x, y, z) of Python floats -> NED rows (y, x, -z), as ``enu_to_ned`` of their
    float64 tensor gives them (a zero z becomes -0.0)."""
    return [(y, x, -z) for x, y, z in rows]


def ned_rows_to_enu(
    rows: Sequence[Sequence[float]], spawn_ned: Sequence[Sequence[float]] | None = None
) -> list[tuple[float, float, float]]:
    """NED rows (x, y, z) of Python floats -> ENU rows, as the float64 tensor path gives them.

    Args:
        rows: (x, y, z) per vehicle, NED; with ``spawn_ned``, positions relative to each
            vehicle's spawn point (``ned_to_enu(local_to_world(rows, spawn_ned))``), without,
            velocities (``ned_to_enu(rows)``).
        spawn_ned: (x, y, z) NED metres of each row's spawn point, or None.
    """
    if spawn_ned is None:
        return [(y, x, -z) for x, y, z in rows]
    return [
        (y + sy, x + sx, -(z + sz)) for (x, y, z), (sx, sy, sz) in zip(rows, spawn_ned, strict=True)
    ]


def _combine(p: Any, spawn: Any, sign: float) -> Any:
    if _is_tensor(p):
        import torch

        s = torch.as_tensor(spawn, dtype=p.dtype, device=p.device)
        if s.shape[-1:] != (3,) or p.shape[-1:] != (3,):
            shapes = f"{tuple(p.shape)}, {tuple(s.shape)}"
            raise ValueError(f"expected last axes of size 3, got {shapes}")
        return p + sign * s
    if not isinstance(p, np.ndarray) and _is_flat_triple(p) and _is_flat_triple(spawn):
        return tuple(float(a) + sign * float(b) + 0.0 for a, b in zip(p, spawn, strict=True))
    arr = np.asarray(p, dtype=None if isinstance(p, np.ndarray) else np.float64)
    s = np.asarray(spawn, dtype=arr.dtype)
    if s.shape[-1:] != (3,) or arr.shape[-1:] != (3,):
        raise ValueError(f"expected last axes of size 3, got {arr.shape}, {s.shape}")
    return arr + sign * s


def world_to_local(p_ned_world: Vector, spawn_ned: Any) -> Vector:
    """NED world position -> NED position relative to the vehicle's spawn point (p - spawn).

    Args:
        p_ned_world: (..., 3) metres NED, world frame.
        spawn_ned: (..., 3) metres NED, the vehicle's spawn point (broadcast against p).
    """
    return _combine(p_ned_world, spawn_ned, -1.0)


def local_to_world(p_ned_local: Vector, spawn_ned: Any) -> Vector:
    """NED position relative to the vehicle's spawn point -> NED world position (p + spawn).

    Args:
        p_ned_local: (..., 3) metres NED, relative to the vehicle's spawn point.
        spawn_ned: (..., 3) metres NED, the vehicle's spawn point (broadcast against p).
    """
    return _combine(p_ned_local, spawn_ned, 1.0)


def spawn_offsets(
    settings: Mapping[str, Any],
    names: Sequence[str],
    fallback: Mapping[str, Sequence[float]] | None = None,
) -> dict[str, tuple[float, float, float]]:
    """Spawn point of each named vehicle, NED metres, from a ``settings.json`` dict.

    A vehicle's spawn point is ``Vehicles.<name>.X``, ``Y``, ``Z`` of the settings when they
    give all three: AirSim places a vehicle at its settings' position only when no coordinate
    of it is missing (a missing one reads as NaN), and otherwise at its PlayerStart, the
    origin. A vehicle whose settings give none or only some of them therefore spawns at
    ``fallback[name]`` when the fallback has it, else at (0, 0, 0), with a logged warning: one
    that names the coordinates a partial position lacks, or, for a name the settings do not
    have, one that lists the settings' vehicles (check the vehicles themselves against
    ``listVehicles``).

    Args:
        settings: the parsed settings.json (e.g. ``json.loads`` of ``getSettingsString()``).
        names: the vehicles wanted.
        fallback: name -> (x, y, z) NED metres, for vehicles the settings do not place.

    Returns:
        name -> (x, y, z) Python floats, NED metres, in the order of ``names``.

    Raises:
        ConfigError: a coordinate is not a number, or a fallback is not (x, y, z).
    """
    vehicles = settings.get("Vehicles") or {}
    if not isinstance(vehicles, Mapping):
        raise ConfigError(f"settings Vehicles must be an object, got {vehicles!r}")
    fallback = fallback or {}
    out = {}
    for name in names:
        entry, backup = vehicles.get(name), fallback.get(name)
        if entry is None and backup is None:
            log.warning(
                "vehicle %r is in neither the simulator's settings (its vehicles: %s) nor "
                "dynamics.spawn: its spawn point is taken as the origin",
                name, ", ".join(vehicles) or "none",
            )  # fmt: skip
        if backup is not None and len(backup) != 3:
            raise ConfigError(f"fallback spawn of {name!r} must be (x, y, z), got {backup!r}")
        given = {key: (entry or {}).get(key) for key in "XYZ"}
        for key, value in given.items():
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, (int, float, np.number))
            ):
                raise ConfigError(f"Vehicles.{name}.{key} must be a number, got {value!r}")
        missing = [key for key, value in given.items() if value is None]
        if entry is not None and missing and len(missing) < 3:
            log.warning(
                "vehicle %r: its settings give no %s, so AirSim ignores its X/Y/Z and spawns it "
                "at its PlayerStart; its spawn point is taken as %s",
                name, "/".join(missing),
                "the fallback (dynamics.spawn)" if backup is not None else "the origin",
            )  # fmt: skip
        if not missing:
            coords = [given[key] for key in "XYZ"]
        else:
            coords = list(backup) if backup is not None else [0.0, 0.0, 0.0]
        out[name] = tuple(float(value) + 0.0 for value in coords)
    return out
