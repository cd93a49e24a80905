"""AirSim backend: fly rlplat's drones in an AirSim-protocol simulator (AirSim, Cosys-AirSim).

- ``frames``: ENU (rlplat) <-> NED (AirSim) and each vehicle's spawn-relative frame, converted
  in this one place.
- ``settings``: vehicle names and the ``settings.json`` a simulator is started with.
- ``testserver``: ``TestServer``, a loopback AirSim-protocol simulator for tests and benchmarks
  (its simple world: ``simworld``); it proves protocol conformance, not physical fidelity.

Nothing here imports an AirSim client library: the package imports without the ``airsim`` extra.
"""

from rlplat.envs.airsim.frames import (
    enu_to_ned,
    local_to_world,
    ned_to_enu,
    spawn_offsets,
    world_to_local,
)
from rlplat.envs.airsim.settings import make_settings, vehicle_names, write_settings
from rlplat.envs.airsim.testserver import TestServer

__all__ = [
    "TestServer",
    "enu_to_ned",
    "local_to_world",
    "make_settings",
    "ned_to_enu",
    "spawn_offsets",
    "vehicle_names",
    "world_to_local",
    "write_settings",
]
