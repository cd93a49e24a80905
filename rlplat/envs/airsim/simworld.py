"""The simulated world behind the loopback AirSim-protocol server (``testserver``).

A small, deterministic stand-in for AirSim's multirotors: it proves that a client speaks the
protocol and respects its timing (pause, continue, moves that complete in sim time, per-vehicle
frames, the collision latch); it makes no claim of physical fidelity.

Frames: NED, metres. The world frame is the one of ``settings.json``; each vehicle reports
positions relative to its own spawn point (``Vehicles.<name>.X/Y/Z``), as AirSim does. The ground
is the plane z = 0 of the world frame.

Physics, per vehicle and axis, is the embedded ``velocity`` model of :mod:`rlplat.envs.dynamics`
(the same sub-step, in NED): the velocity tracks a goal with a first-order lag integrated exactly
(``dv = (v_goal - v)(1 - exp(-dt / tau))``), each component of ``dv`` clipped to the acceleration
limits times ``dt`` (vertical: ``a_up_max`` up, ``a_down_max`` down), then quadratic drag
``-c v |v| / mass`` (zero by default); the position advances with the mean of the velocities at
both ends of the sub-step; a vehicle below the ground is put back on it and its downward velocity
zeroed. With the same constants, drag and sub-step, ``dynamics=velocity`` flies the same
trajectory under the same commands (no ``max_speed`` clamp here: commands are the client's).

The velocity goal of a vehicle at a sub-step is, in order:

1. its running task: a move's commanded velocity, or takeoff's climb (3 m at 0.5 m/s, slowing
   to ``hold_gain * distance`` for the last metres, done within 0.1 m);
2. the last move's velocity for ``hover_after_s`` of sim time after that move ended;
3. otherwise it holds position as simple_flight does: ``v_goal = hold_gain * (hold - p)``
   clipped per axis to ``hold_max_speed``, ``hold`` being where it stood when it began to hold.

Contact: two vehicles closer than ``collision_radius`` (centre to centre), or a vehicle reaching
the ground with downward velocity, latch a collision record on the vehicle (the latest contact
wins) until it is read.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rlplat.envs.airsim.frames import spawn_offsets
from rlplat.errors import ConfigError

# AirSim's default OriginGeopoint (settings.json), for gps_location.
HOME_GEOPOINT = (47.641468, -122.140165, 122.0)
EARTH_RADIUS = 6378137.0
# simple_flight constants (MultirotorApiBase, OffboardApi).
TAKEOFF_HEIGHT = 3.0  # m, climbed by takeoff
TAKEOFF_SPEED = 0.5  # m/s
TAKEOFF_TOLERANCE = 0.1  # m, takeoff is complete within this distance of its target
APPROX_ZERO_VEL = 0.05  # m/s, takeoff refuses a vehicle moving faster than this
LANDED_SPEED = 0.08  # m/s, a vehicle on the ground slower than this is landed

Vec = list[float]
Done = Callable[[bool], None]


@dataclass(frozen=True)
class Physics:
    """Constants of the simulated world (SI units; see the module docstring)."""

    tau_xy: float = 0.9
    tau_z: float = 0.08
    a_xy_max: float = 6.3
    a_up_max: float = 6.9
    a_down_max: float = 4.8
    drag_xy: float = 0.0
    drag_z: float = 0.0
    mass: float = 1.0
    physics_dt: float = 0.003
    hover_after_s: float = 0.06
    hold_gain: float = 1.5
    hold_max_speed: float = 6.0
    collision_radius: float = 0.5

    def __post_init__(self) -> None:
        positive = ("tau_xy", "tau_z", "a_xy_max", "a_up_max", "a_down_max", "mass", "physics_dt")
        positive += ("hold_gain", "hold_max_speed", "collision_radius")
        for name in (*positive, "drag_xy", "drag_z", "hover_after_s"):
            value, strict = getattr(self, name), name in positive
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not (number and math.isfinite(value) and (value > 0 if strict else value >= 0)):
                bound = "> 0" if strict else ">= 0"
                raise ConfigError(f"{name} must be a finite number {bound}, got {value!r}")
        if round(self.physics_dt * 1e9) < 1000:
            raise ConfigError(f"physics_dt must be >= 1e-6 s, got {self.physics_dt!r}")


@dataclass
class Task:
    """A running command of one vehicle: a move (velocity until ``deadline_ns``) or takeoff."""

    kind: str  # "move" | "takeoff"
    done: Done
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    deadline_ns: int = 0
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)


class Vehicle:
    """State of one simulated multirotor (world NED)."""

    def __init__(self, name: str, spawn: Sequence[float]) -> None:
        self.name = name
        self.spawn = tuple(float(v) for v in spawn)
        self.reset()

    def reset(self) -> None:
        self.p: Vec = list(self.spawn)
        self.v: Vec = [0.0, 0.0, 0.0]
        self.accel: Vec = [0.0, 0.0, 0.0]
        self.orientation = (1.0, 0.0, 0.0, 0.0)  # w, x, y, z
        self.api_control = False
        self.armed = False
        self.task: Task | None = None
        self.command: tuple[float, float, float] | None = None
        self.command_until_ns = 0
        self.hold: Vec | None = None
        self.collision: dict[str, Any] | None = None

    def local(self) -> Vec:
        return [self.p[i] - self.spawn[i] + 0.0 for i in range(3)]


class SimWorld:
    """Vehicles, a sim clock in integer nanoseconds and the stepping rule.

    Not thread-safe: the server drives it from its event loop only.

    Args:
        settings: a settings.json dict; its ``Vehicles`` (spawn ``X``/``Y``/``Z``, NED) are the
            vehicles, in order (none: one vehicle ``SimpleFlight`` at the origin, as AirSim).
        physics: the constants.
        start_ns: sim clock at start, ns.
    """

    def __init__(self, settings: Mapping[str, Any], physics: Physics, start_ns: int) -> None:
        mode = settings.get("SimMode", "Multirotor")
        if mode not in ("", "Multirotor"):
            raise ConfigError(f"SimMode must be Multirotor for this server, got {mode!r}")
        names = list(settings.get("Vehicles") or {}) or ["SimpleFlight"]
        spawns = spawn_offsets(settings, names, {"SimpleFlight": (0.0, 0.0, 0.0)})
        self.vehicles = {n: Vehicle(n, spawns[n]) for n in names}
        self.physics = physics
        self.t_ns = int(start_ns)
        self.dt_ns = round(physics.physics_dt * 1e9)
        self._cache: dict[float, tuple[tuple[float, ...], ...]] = {}

    # Commands ---------------------------------------------------------------------------------

    def reset(self) -> None:
        """Every vehicle back to its spawn point at rest; control, arming and tasks cleared."""
        for veh in self.vehicles.values():
            self.cancel(veh)
            veh.reset()

    def cancel(self, veh: Vehicle) -> None:
        """End the running task of ``veh`` as interrupted (its call returns False)."""
        task, veh.task = veh.task, None
        if task is not None:
            task.done(False)

    def move_by_velocity(
        self, veh: Vehicle, velocity: Sequence[float], duration: float, done: Done
    ):
        """Fly ``velocity`` (NED m/s) for ``duration`` s of sim time; ``done(True)`` at the end,
        ``done(False)`` if cancelled first. A duration <= 0 completes at once without a command
        (as AirSim)."""
        self.cancel(veh)
        if not duration > 0:
            done(True)
            return
        deadline = self.t_ns + round(duration * 1e9)
        vel = (float(velocity[0]), float(velocity[1]), float(velocity[2]))
        veh.task = Task("move", done, velocity=vel, deadline_ns=deadline)
        veh.command, veh.command_until_ns, veh.hold = vel, deadline, None

    def takeoff(self, veh: Vehicle, timeout: float, done: Done) -> None:
        """Climb TAKEOFF_HEIGHT from where it is; ``done(False)`` after ``timeout`` s."""
        speed = math.sqrt(sum(c * c for c in veh.v))
        if speed > APPROX_ZERO_VEL:
            raise ValueError(
                "Cannot perform takeoff because vehicle is already moving with velocity "
                f"{speed:f} m/s"
            )
        self.cancel(veh)
        target = (veh.p[0], veh.p[1], veh.p[2] - TAKEOFF_HEIGHT)
        deadline = self.t_ns + max(0, round(timeout * 1e9))
        veh.task = Task("takeoff", done, deadline_ns=deadline, target=target)
        veh.command, veh.hold = None, None

    def hover(self, veh: Vehicle) -> None:
        """Cancel the running task and hold the current position."""
        self.cancel(veh)
        veh.command, veh.hold = None, list(veh.p)

    def set_pose(self, veh: Vehicle, local: Sequence[float], orientation: Sequence[float]) -> None:
        """Teleport to ``local`` (NED, spawn-relative; NaN keeps a coordinate) with ``orientation``
        (w, x, y, z; any NaN keeps the orientation). The velocity is kept; a vehicle holding
        position holds at the new one; below the ground it is put on the ground."""
        for i in range(3):
            if not math.isnan(local[i]):
                veh.p[i] = float(local[i]) + veh.spawn[i]
        veh.p[2] = min(veh.p[2], 0.0)
        if not any(math.isnan(q) for q in orientation):
            veh.orientation = tuple(float(q) for q in orientation)
        if veh.hold is not None:
            veh.hold = list(veh.p)

    def touching(self, veh: Vehicle) -> None:
        """Latch a collision if ``veh`` is in contact with another vehicle now."""
        for other in self.vehicles.values():
            if other is not veh:
                self._contact_pair(veh, other)

    # Stepping ---------------------------------------------------------------------------------

    def advance(self, ns: int) -> None:
        """Advance the clock by exactly ``ns``: full physics steps, then one shorter step."""
        full, rest = divmod(int(ns), self.dt_ns)
        for _ in range(full):
            self.step(self.dt_ns)
        if rest:
            self.step(rest)

    def step(self, dt_ns: int) -> None:
        """One physics sub-step of ``dt_ns`` for every vehicle, then contacts and task ends."""
        t0, dt = self.t_ns, dt_ns * 1e-9
        for veh in self.vehicles.values():
            self._integrate(veh, self._goal(veh, t0), dt)
        self.t_ns = t1 = t0 + dt_ns
        vehicles = list(self.vehicles.values())
        for i, a in enumerate(vehicles):
            for b in vehicles[i + 1 :]:
                self._contact_pair(a, b)
        for veh in vehicles:
            task = veh.task
            if task is None:
                continue
            if task.kind == "move" and t1 >= task.deadline_ns:
                veh.task = None
                task.done(True)
            elif task.kind == "takeoff":
                if abs(task.target[2] - veh.p[2]) <= TAKEOFF_TOLERANCE:
                    veh.task, veh.hold = None, list(task.target)
                    task.done(True)
                elif t1 >= task.deadline_ns:
                    veh.task, veh.hold = None, list(veh.p)
                    task.done(False)

    def _goal(self, veh: Vehicle, t: int) -> Sequence[float]:
        ph, task = self.physics, veh.task
        if task is not None and task.kind == "move":
            return task.velocity
        if task is not None:  # takeoff: hold x, y; climb at TAKEOFF_SPEED, slowing at the end
            goal = self._hold_goal(veh, task.target)
            dz = task.target[2] - veh.p[2]
            goal[2] = math.copysign(min(TAKEOFF_SPEED, ph.hold_gain * abs(dz)), dz)
            return goal
        if veh.command is not None and t < veh.command_until_ns + round(ph.hover_after_s * 1e9):
            return veh.command
        veh.command = None
        if veh.hold is None:
            veh.hold = list(veh.p)
        return self._hold_goal(veh, veh.hold)

    def _hold_goal(self, veh: Vehicle, hold: Sequence[float]) -> Vec:
        ph = self.physics
        cap = ph.hold_max_speed
        return [max(-cap, min(cap, ph.hold_gain * (hold[i] - veh.p[i]))) for i in range(3)]

    def _constants(self, dt: float) -> tuple[tuple[float, ...], ...]:
        """Per-axis (gain, dv low, dv high, drag factor) of a sub-step of ``dt`` s (cached)."""
        cached = self._cache.get(dt)
        if cached is None:
            ph = self.physics
            taus = (ph.tau_xy, ph.tau_xy, ph.tau_z)
            lows = (-ph.a_xy_max, -ph.a_xy_max, -ph.a_up_max)  # NED: up is -z
            highs = (ph.a_xy_max, ph.a_xy_max, ph.a_down_max)
            drags = (ph.drag_xy, ph.drag_xy, ph.drag_z)
            cached = tuple(
                (-math.expm1(-dt / taus[i]), lows[i] * dt, highs[i] * dt, drags[i] / ph.mass * dt)
                for i in range(3)
            )
            if len(self._cache) < 8:  # the full step and a few remainders
                self._cache[dt] = cached
        return cached

    def _integrate(self, veh: Vehicle, goal: Sequence[float], dt: float) -> None:
        p, v = veh.p, veh.v
        half = 0.5 * dt
        old = list(v)
        for i, (gain, low, high, drag) in enumerate(self._constants(dt)):
            p[i] += v[i] * half
            dv = min(max((goal[i] - v[i]) * gain, low), high)
            v[i] += dv - drag * v[i] * abs(v[i])
            p[i] += v[i] * half
        if p[2] >= 0.0:  # on or below the ground: back on it, no downward velocity
            if p[2] > 0.0 and v[2] > 0.0:
                self._latch(veh, "Ground", (0.0, 0.0, -1.0), (p[0], p[1], 0.0), p[2])
            p[2] = 0.0
            if v[2] > 0.0:
                v[2] = 0.0
        veh.accel = [(v[i] - old[i]) / dt for i in range(3)]

    def _contact_pair(self, a: Vehicle, b: Vehicle) -> None:
        d = [a.p[i] - b.p[i] for i in range(3)]
        dist = math.sqrt(sum(c * c for c in d))
        radius = self.physics.collision_radius
        if dist >= radius:
            return
        normal = [c / dist for c in d] if dist > 0 else [0.0, 0.0, -1.0]
        mid = [(a.p[i] + b.p[i]) / 2 for i in range(3)]
        self._latch(a, b.name, normal, mid, radius - dist)
        self._latch(b, a.name, [-c for c in normal], mid, radius - dist)

    def _latch(self, veh: Vehicle, other: str, normal, point, depth: float) -> None:
        veh.collision = {
            "has_collided": True,
            "penetration_depth": float(depth),
            "time_stamp": self.t_ns,
            "normal": vector3r(normal),
            "impact_point": vector3r(point),
            "position": vector3r(veh.p),
            "object_name": other,
            "object_id": -1,
        }

    # State, as AirSim's map-structs ----------------------------------------------------------

    def kinematics(self, veh: Vehicle) -> dict[str, Any]:
        """KinematicsState: spawn-relative position, orientation, velocities, accelerations."""
        zero = vector3r((0.0, 0.0, 0.0))
        return {
            "position": vector3r(veh.local()),
            "orientation": quaternionr(veh.orientation),
            "linear_velocity": vector3r(veh.v),
            "angular_velocity": zero,
            "linear_acceleration": vector3r(veh.accel),
            "angular_acceleration": dict(zero),
        }

    def multirotor_state(self, veh: Vehicle) -> dict[str, Any]:
        """MultirotorState; ``collision`` is never filled (as AirSim)."""
        on_ground = veh.p[2] >= -0.01
        slow = math.sqrt(sum(c * c for c in veh.v)) < LANDED_SPEED
        return {
            "collision": collision_info(None),
            "kinematics_estimated": self.kinematics(veh),
            "gps_location": geopoint(veh.p),
            "timestamp": self.t_ns,
            "landed_state": 0 if on_ground and slow else 1,
            "rc_data": {
                "timestamp": 0,
                "pitch": 0.0,
                "roll": 0.0,
                "throttle": 0.0,
                "yaw": 0.0,
                "left_z": 0.0,
                "right_z": 0.0,
                "switches": 0,
                "vendor_id": "",
                "is_initialized": False,
                "is_valid": False,
            },
        }

    def pose(self, veh: Vehicle) -> dict[str, Any]:
        """Pose: spawn-relative position and orientation."""
        return {"position": vector3r(veh.local()), "orientation": quaternionr(veh.orientation)}

    def read_collision(self, veh: Vehicle, clear: bool = True) -> dict[str, Any]:
        """CollisionInfo of the latest contact since the last read (then cleared; ``clear=False``:
        of the latest contact since the reset, kept)."""
        info = veh.collision
        if clear:
            veh.collision = None
        return collision_info(info)


def vector3r(v: Sequence[float]) -> dict[str, float]:
    return {"x_val": float(v[0]) + 0.0, "y_val": float(v[1]) + 0.0, "z_val": float(v[2]) + 0.0}


def quaternionr(q: Sequence[float]) -> dict[str, float]:
    return {"w_val": q[0], "x_val": q[1], "y_val": q[2], "z_val": q[3]}


def collision_info(info: dict[str, Any] | None) -> dict[str, Any]:
    if info is not None:
        return info
    zero = (0.0, 0.0, 0.0)
    return {
        "has_collided": False,
        "penetration_depth": 0.0,
        "time_stamp": 0,
        "normal": vector3r(zero),
        "impact_point": vector3r(zero),
        "position": vector3r(zero),
        "object_name": "",
        "object_id": -1,
    }


def geopoint(p_world: Sequence[float]) -> dict[str, float]:
    lat0, lon0, alt0 = HOME_GEOPOINT
    lat = lat0 + math.degrees(p_world[0] / EARTH_RADIUS)
    lon = lon0 + math.degrees(p_world[1] / (EARTH_RADIUS * math.cos(math.radians(lat0))))
    return {"latitude": lat, "longitude": lon, "altitude": alt0 - p_world[2]}
