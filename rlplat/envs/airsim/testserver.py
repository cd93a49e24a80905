"""A loopback server that speaks the AirSim RPC protocol subset a lock-step client needs.

It stands in for AirSim / Cosys-AirSim (Unreal) in tests and benchmarks: real clients connect to
it as to the simulator. It proves protocol conformance, not physical fidelity (its world is the
small model of :mod:`rlplat.envs.airsim.simworld`).

Protocol (rpclib's msgpack-rpc, as AirSim's ``RpcLibServerBase``): a msgpack stream over TCP;
a request ``[0, id, method, params]`` is answered ``[1, id, error, result]`` (``error`` nil or
a string; ``result`` nil for void calls and on error); a notification ``[2, method, params]`` is
run and never answered. Each request runs on its own, so many requests pipelined on one
connection are answered as they complete, out of order: a pending move does not block later
calls. Structs are maps keyed by field name (``x_val``, ``w_val``, ``position``, ...); fields a
client leaves out of a struct keep their defaults and unknown ones are ignored (msgpack-c).

Errors carry rpclib's texts: an unknown method ``rpclib: server could not find function 'X' with
argument count N.``; a wrong argument count ``rpclib: Function 'X' was called with an invalid
number of arguments. Expected: G, got: A`` (rpclib passes its two numbers swapped: G is the count
given, A the count the function takes); an argument of the wrong type (e.g. a float for a bool)
or a failing call ``rpclib: function 'X' (called with N arg(s)) threw an exception. The exception
contained this information: WHAT.``, WHAT being ``std::bad_cast`` for a type and AirSim's message
otherwise (e.g. an unknown vehicle: ``Vehicle API for 'V' is not available. This could either
because this is simulation-only API or this vehicle does not exist``). An empty vehicle name is
the first vehicle.

Deliberately stricter than AirSim: a motion call (``moveByVelocity``, ``takeoff``, ``hover``) on
a vehicle without API control fails with simple_flight's message ``requestApiControl() must be
called before using API control`` (AirSim only logs it and ignores the command), and on a
disarmed vehicle with ``Vehicle 'V' is not armed: call armDisarm(True) first`` (AirSim's motors
just stay off). ``armDisarm(True)`` without API control returns False, as in AirSim.

Sim time: the clock (ns, from the wall clock at start) runs in ``physics_dt`` steps. Unpaused,
it follows the wall clock times the speed k that AirSim runs ``clock_speed`` at (above 1 its
whole part: :func:`~rlplat.envs.airsim.settings.effective_clock_speed`); ``simPause(True)``
freezes it. ``simContinueForTime(s)`` advances it by exactly ``round(s * k * 1e9)`` ns (whole
physics steps and one shorter last step; ``whole_ticks=True``: whole steps only, up to the first
at or past that time, as AirSim's clock does), then answers and leaves the simulation paused: like
AirSim's, its argument counts wall seconds, so with ClockSpeed k a client wanting ``dt`` of sim
time asks for ``dt / k``. It runs as fast as the machine allows (``realtime=True``: it takes
``s`` wall seconds, as a simulator running in real time would; ``continue_runs`` < 1: it runs
that fraction of ``s``, as AirSim does when its physics ticks run long).
``simContinueForFrames(n)`` advances ``n`` physics steps. A move (``moveByVelocity``) answers
True once its ``duration`` of sim time has passed, False when a later motion call on the same
vehicle (or ``reset``, ``cancelLastTask``, disarming, releasing API control) cancels it; while
paused it never completes. ``reset()`` puts every vehicle back at its spawn point and clears
API control and arming. ``getMultirotorState().collision`` is never filled;
``simGetCollisionInfo`` returns the latched contact and clears it, as Cosys-AirSim does
(``collision_stays=True``: keeps it until the next contact or a reset, as AirSim's
``getCollisionInfo``).

Faults for tests: ``stall()`` keeps every socket open but answers nothing (and freezes the
clock) until ``unstall()``; ``drop_connections()`` closes every client connection; ``stop()``
closes the server, after which a new server can listen on the same port.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import msgpack

from rlplat.cli import ArgumentParser, exit_on_error, path_arg
from rlplat.envs.airsim.settings import effective_clock_speed
from rlplat.envs.airsim.simworld import Physics, SimWorld, Vehicle
from rlplat.errors import ConfigError
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)

SERVER_VERSION = 4  # what Cosys-AirSim's client expects; AirSim's own accepts >= 1
MIN_CLIENT_VERSION = 1
DEFAULT_PORT = 41451
_WAIT_S = 10.0  # bound on every wait for the server thread
_TICK_S = 0.005  # wall period of the free-running clock
_MAX_CATCH_UP_S = 0.25  # sim seconds the free-running clock may catch up in one tick


class _Fail(Exception):
    """A call failed; ``str()`` is the ``what()`` rpclib puts in its error text."""


def error_no_function(name: str, count: int) -> str:
    return f"rpclib: server could not find function '{name}' with argument count {count}."


def error_arity(name: str, given: int, arity: int) -> str:
    # rpclib's dispatcher calls enforce_arg_count(name, arity, given) against the parameter
    # order (func, found, expected): the numbers come out swapped, and so they are here.
    return (
        f"rpclib: Function '{name}' was called with an invalid number of arguments. "
        f"Expected: {given}, got: {arity}"
    )


def error_threw(name: str, count: int, what: str) -> str:
    return (
        f"rpclib: function '{name}' (called with {count} arg(s)) threw an exception. "
        f"The exception contained this information: {what}."
    )


# Argument conversion, as msgpack-c converts into the C++ parameter types ----------------------


def _float(x: Any) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise _Fail("std::bad_cast")
    return float(x)


def _bool(x: Any) -> bool:
    if not isinstance(x, bool):
        raise _Fail("std::bad_cast")
    return x


def _int(x: Any) -> int:
    if isinstance(x, bool) or not isinstance(x, int):
        raise _Fail("std::bad_cast")
    return x


def _uint(x: Any) -> int:
    if _int(x) < 0:
        raise _Fail("std::bad_cast")
    return x


def _str(x: Any) -> str:
    if isinstance(x, bytes):
        return x.decode("utf-8", "replace")
    if not isinstance(x, str):
        raise _Fail("std::bad_cast")
    return x


def _struct(x: Any, fields: Mapping[str, tuple[Callable[[Any], Any], Any]]) -> dict[str, Any]:
    """A MSGPACK_DEFINE_MAP struct: a map; missing fields keep defaults, unknown are ignored."""
    if not isinstance(x, dict):
        raise _Fail("std::bad_cast")
    return {k: (conv(x[k]) if k in x else default) for k, (conv, default) in fields.items()}


def _vector3r(x: Any) -> dict[str, Any]:
    return _struct(x, {k: (_float, 0.0) for k in ("x_val", "y_val", "z_val")})


def _quaternionr(x: Any) -> dict[str, Any]:
    return _struct(
        x, {"w_val": (_float, 1.0), **{k: (_float, 0.0) for k in ("x_val", "y_val", "z_val")}}
    )


def _pose(x: Any) -> dict[str, Any]:
    zero = {"x_val": 0.0, "y_val": 0.0, "z_val": 0.0}
    unit = {"w_val": 1.0, "x_val": 0.0, "y_val": 0.0, "z_val": 0.0}
    return _struct(x, {"position": (_vector3r, zero), "orientation": (_quaternionr, unit)})


def _yaw_mode(x: Any) -> dict[str, Any]:
    return _struct(x, {"is_rate": (_bool, True), "yaw_or_rate": (_float, 0.0)})


class TestServer:
    """A loopback AirSim-protocol simulator on ``host:port`` (see the module docstring).

    Args:
        settings: the settings.json dict it simulates (vehicles, spawn points, ``ClockSpeed``);
            ``getSettingsString`` returns it as JSON.
        host: address to listen on.
        port: TCP port; 0 picks a free one (read ``.port`` after ``start()``).
        tau_xy, tau_z, a_xy_max, a_up_max, a_down_max: the velocity response (s, m/s^2), as
            ``dynamics=velocity``.
        physics_dt: s, physics step.
        clock_speed: the ``ClockSpeed`` setting; None takes the settings' (1). The clock runs
            at it, above 1 at its whole part, as AirSim's does.
        hover_after_s: s of sim time after a move ends before the vehicle holds position.
        drag_xy, drag_z, mass: quadratic drag (N/(m/s)^2, none by default) and mass (kg).
        collision_radius: m, two vehicles closer than this are in contact.
        realtime: ``simContinueForTime(s)`` takes ``s`` wall seconds instead of running at once.
        continue_answers_at_once: ``simContinueForTime`` answers as soon as it starts the
            simulation, which runs on and pauses when its time is up (``simIsPaused`` tells):
            AirSim versions whose ``continueForTime`` does not wait.
        continue_runs: the fraction of a ``simContinueForTime``'s time the simulation runs
            (in (0, 1]): AirSim's call counts its wall clock, and on a machine too loaded for
            its physics ticks it runs less sim time than asked (a long tick is not made up).
        collision_stays: ``simGetCollisionInfo`` keeps reporting the latest contact (its flag
            set, its ``time_stamp``) until the next contact or a reset, as AirSim's
            ``getCollisionInfo`` does, instead of clearing it once read (Cosys-AirSim).
        whole_ticks: ``simContinueForTime`` runs whole physics steps, up to the first that
            ends at or past its time (AirSim: 34 steps of 3 ms, 0.102 s, for 0.1 s), instead
            of ending on its time with a shorter last step.
    """

    __test__ = False  # not a pytest test class

    def __init__(
        self,
        settings: Mapping[str, Any],
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        tau_xy: float = 0.9,
        tau_z: float = 0.08,
        a_xy_max: float = 6.3,
        a_up_max: float = 6.9,
        a_down_max: float = 4.8,
        physics_dt: float = 0.003,
        clock_speed: float | None = None,
        hover_after_s: float = 0.06,
        drag_xy: float = 0.0,
        drag_z: float = 0.0,
        mass: float = 1.0,
        collision_radius: float = 0.5,
        realtime: bool = False,
        continue_answers_at_once: bool = False,
        continue_runs: float = 1.0,
        whole_ticks: bool = False,
        collision_stays: bool = False,
    ) -> None:
        if not isinstance(settings, Mapping):
            raise ConfigError(f"settings must be a dict (settings.json), got {type(settings)}")
        self.settings = dict(settings)
        if clock_speed is None:
            clock_speed = self.settings.get("ClockSpeed", 1.0)
        if isinstance(clock_speed, bool) or not isinstance(clock_speed, (int, float)):
            raise ConfigError(f"clock_speed must be a number > 0, got {clock_speed!r}")
        if not (math.isfinite(clock_speed) and clock_speed > 0):
            raise ConfigError(f"clock_speed must be a number > 0, got {clock_speed!r}")
        if (
            isinstance(continue_runs, bool)
            or not isinstance(continue_runs, (int, float))
            or (not 0 < continue_runs <= 1)
        ):
            raise ConfigError(f"continue_runs must be a number in (0, 1], got {continue_runs!r}")
        if not isinstance(port, int) or not 0 <= port < 65536:
            raise ConfigError(f"port must be an integer in [0, 65535], got {port!r}")
        self.physics = Physics(
            tau_xy=tau_xy,
            tau_z=tau_z,
            a_xy_max=a_xy_max,
            a_up_max=a_up_max,
            a_down_max=a_down_max,
            drag_xy=drag_xy,
            drag_z=drag_z,
            mass=mass,
            physics_dt=physics_dt,
            hover_after_s=hover_after_s,
            collision_radius=collision_radius,
        )
        self.world = SimWorld(self.settings, self.physics, start_ns=time.time_ns())
        self.host, self.port = host, port
        self.clock_speed = float(clock_speed)
        self.sim_speed = effective_clock_speed(self.clock_speed)  # AirSim's rule
        self.realtime = bool(realtime)
        self.continue_answers_at_once = bool(continue_answers_at_once)
        self.continue_runs = float(continue_runs)
        self.whole_ticks = bool(whole_ticks)
        self.collision_stays = bool(collision_stays)
        self.recording: list[dict[str, Any]] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task] = set()
        self._connections: set[asyncio.Task] = set()
        self._paused = False
        self._continuing = False
        self._anchor = (0.0, 0)  # (wall monotonic s, sim ns) the free-running clock follows
        self._methods = self._method_table()

    # Lifecycle --------------------------------------------------------------------------------

    @property
    def address(self) -> str:
        """``"host:port"``."""
        return f"{self.host}:{self.port}"

    def start(self) -> TestServer:
        """Listen and serve in a background thread; returns once the port is open."""
        if self._thread is not None:
            raise RuntimeError("TestServer already started")
        ready: dict[str, Any] = {}
        started = threading.Event()
        # The thread shares the interpreter lock with its process: a waiter that spins in
        # Python (TorchRL's ParallelEnv polls its workers' flags so) would hold it for whole
        # switch intervals (5 ms) between the server's callbacks, and a real-time continue of
        # hundreds of ticks would miss its client's deadline. Hand the lock over every tick/10.
        sys.setswitchinterval(min(sys.getswitchinterval(), _TICK_S / 10))
        self._thread = threading.Thread(
            target=self._run, args=(ready, started), name=f"airsim-testserver-{self.port}"
        )
        self._thread.daemon = True
        self._thread.start()
        if not started.wait(_WAIT_S) or "error" in ready:
            self._thread.join(_WAIT_S)
            self._thread = None
            err = ready.get("error", "timed out")
            raise OSError(f"test server could not listen on {self.host}:{self.port}: {err}")
        log.info("AirSim test server listening on %s (vehicles: %s)", self.address, self.names)
        return self

    def stop(self) -> None:
        """Close every connection and the listening socket; join the server thread."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        if loop.is_running():
            asyncio.run_coroutine_threadsafe(self._shutdown(), loop).result(_WAIT_S)
        thread.join(_WAIT_S)
        if thread.is_alive():
            raise RuntimeError(f"test server thread on {self.address} did not stop")
        self._thread = self._loop = None
        log.info("AirSim test server on %s stopped", self.address)

    def __enter__(self) -> TestServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def names(self) -> list[str]:
        """The vehicles, in settings order."""
        return list(self.world.vehicles)

    # Fault injection and inspection (thread-safe) -------------------------------------------

    def stall(self) -> None:
        """Answer nothing and freeze the clock until ``unstall()``; sockets stay open."""
        self._call(self._set_stalled, True)

    def unstall(self) -> None:
        """Answer again (requests held while stalled are answered now)."""
        self._call(self._set_stalled, False)

    def drop_connections(self) -> None:
        """Close every open client connection (the server keeps listening)."""
        self._call(self._drop)

    def snapshot(self) -> dict[str, Any]:
        """Sim time and every vehicle's world state: ``{"t_ns", "paused", "vehicles": {name:
        {"position", "velocity"} (NED world, m, m/s), "api_control", "armed"}}``."""
        return self._call(self._snapshot)

    def start_recording(self) -> None:
        """Record from now on every call received and the state after every continue."""
        self._call(lambda: setattr(self, "recording", []))

    def take_recording(self) -> list[dict[str, Any]]:
        """The records since ``start_recording()``, in order, and stop recording.

        Returns:
            ``{"t_ns", "call", "params"}`` for each call received (sim time when it arrived) and
            ``{"t_ns", "paused", "vehicles"}`` (as :meth:`snapshot`) after each continue: the
            commands and world states of a lock-step run, for replay or calibration.
        """

        def take():
            out, self.recording = self.recording or [], None
            return out

        return self._call(take)

    def _call(self, fn: Callable, *args: Any) -> Any:
        loop = self._loop
        if loop is None or not loop.is_running():
            raise RuntimeError("TestServer is not running")

        async def run():
            return fn(*args)

        return asyncio.run_coroutine_threadsafe(run(), loop).result(_WAIT_S)

    # The event loop ---------------------------------------------------------------------------

    def _run(self, ready: dict[str, Any], started: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._open(ready))
        except OSError as err:
            ready["error"] = err.strerror or str(err)
            started.set()
            loop.close()
            return
        started.set()
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _open(self, ready: dict[str, Any]) -> None:
        self._unstalled = asyncio.Event()
        self._unstalled.set()
        self._running = asyncio.Event()  # set while the free-running clock should run
        self._step_lock = asyncio.Lock()
        self._server = await asyncio.start_server(self._connection, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._set_paused(False)
        self._spawn(self._free_run())

    async def _shutdown(self) -> None:
        self._server.close()
        self._drop()
        if self._connections:  # each ends once its socket is closed
            await asyncio.wait(set(self._connections), timeout=_WAIT_S / 2)
        for veh in self.world.vehicles.values():
            self.world.cancel(veh)
        tasks = [t for t in self._tasks if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await self._server.wait_closed()
        asyncio.get_running_loop().call_soon(asyncio.get_running_loop().stop)

    def _spawn(self, coro) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _set_stalled(self, stalled: bool) -> None:
        if stalled:
            self._unstalled.clear()
        else:
            self._unstalled.set()
            self._reanchor()

    def _drop(self) -> None:
        for writer in list(self._writers):
            writer.close()
        self._writers.clear()

    def _snapshot(self) -> dict[str, Any]:
        return {
            "t_ns": self.world.t_ns,
            "paused": self._paused,
            "vehicles": {
                n: {
                    "position": list(v.p),
                    "velocity": list(v.v),
                    "api_control": v.api_control,
                    "armed": v.armed,
                }
                for n, v in self.world.vehicles.items()
            },
        }

    # Clock ------------------------------------------------------------------------------------

    def _reanchor(self) -> None:
        self._anchor = (time.monotonic(), self.world.t_ns)

    def _set_paused(self, paused: bool) -> None:
        self._paused = paused
        if paused:
            self._running.clear()
        else:
            self._reanchor()
            self._running.set()

    async def _free_run(self) -> None:
        """While unpaused (and not stalled or continuing), follow the wall clock."""
        dt_ns = self.world.dt_ns
        while True:
            await self._running.wait()
            await asyncio.sleep(_TICK_S)
            if self._paused or self._continuing or not self._unstalled.is_set():
                continue
            wall0, sim0 = self._anchor
            target = sim0 + round((time.monotonic() - wall0) * self.sim_speed * 1e9)
            steps = (target - self.world.t_ns) // dt_ns
            if steps * dt_ns > _MAX_CATCH_UP_S * 1e9:  # fell behind: run slower than asked
                steps = int(_MAX_CATCH_UP_S * 1e9) // dt_ns
                self._anchor = (time.monotonic(), self.world.t_ns + steps * dt_ns)
            for _ in range(max(0, steps)):
                self.world.step(dt_ns)

    async def _continue(self, sim_ns: int) -> None:
        """Advance exactly ``sim_ns``, then stay paused."""
        async with self._step_lock:
            self._continuing = True
            self._paused = False
            try:
                target = self.world.t_ns + sim_ns
                if self.realtime:
                    wall0, sim0 = time.monotonic(), self.world.t_ns
                    while self.world.t_ns < target:
                        await asyncio.sleep(_TICK_S)
                        now = sim0 + round((time.monotonic() - wall0) * self.sim_speed * 1e9)
                        self.world.advance(min(now, target) - self.world.t_ns)
                else:
                    chunk = 2000 * self.world.dt_ns  # let other connections in between
                    while self.world.t_ns < target:
                        self.world.advance(min(chunk, target - self.world.t_ns))
                        if self.world.t_ns < target:
                            await asyncio.sleep(0)
            finally:
                self._continuing = False
                self._set_paused(True)
            if self.recording is not None:
                self.recording.append(self._snapshot())

    # Connections ------------------------------------------------------------------------------

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self._connections.add(asyncio.current_task())
        self._writers.add(writer)
        peer = writer.get_extra_info("peername")
        log.debug("client %s connected", peer)
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=False)
        pending: set[asyncio.Task] = set()
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                unpacker.feed(data)
                for message in unpacker:
                    task = self._spawn(self._message(message, writer))
                    pending.add(task)
                    task.add_done_callback(pending.discard)
        except (ConnectionError, msgpack.UnpackException, ValueError) as err:
            log.warning("client %s: %s; closing the connection", peer, err)
        finally:
            self._writers.discard(writer)
            writer.close()
            for task in pending:
                task.cancel()
            self._connections.discard(asyncio.current_task())
            log.debug("client %s disconnected", peer)

    async def _message(self, message: Any, writer: asyncio.StreamWriter) -> None:
        if not isinstance(message, (list, tuple)) or len(message) not in (3, 4):
            log.warning("ignoring a message that is not msgpack-rpc: %r", message)
            return
        await self._unstalled.wait()
        if len(message) == 3:  # notification: run, never answered (as rpclib)
            await self._dispatch(message[1], message[2])
            return
        msgid = message[1]
        error, result = await self._dispatch(message[2], message[3])
        await self._unstalled.wait()
        if writer.is_closing():
            return
        writer.write(msgpack.packb([1, msgid, error, result], use_bin_type=True))

    async def _dispatch(self, name: Any, params: Any) -> tuple[str | None, Any]:
        params = list(params) if isinstance(params, (list, tuple)) else []
        count = len(params)
        if self.recording is not None:
            self.recording.append({"t_ns": self.world.t_ns, "call": name, "params": params})
        entry = self._methods.get(name) if isinstance(name, str) else None
        if entry is None:
            return error_no_function(str(name), count), None
        converters, handler = entry
        if count != len(converters):
            return error_arity(name, count, len(converters)), None
        try:
            args = [conv(arg) for conv, arg in zip(converters, params, strict=True)]
            result = handler(*args)
            if asyncio.iscoroutine(result):
                result = await result
            return None, result
        except _Fail as err:
            return error_threw(name, count, str(err)), None
        except (ValueError, KeyError) as err:
            return error_threw(name, count, str(err).strip("'\"")), None
        except asyncio.CancelledError:
            raise
        except Exception as err:  # a bug here: say so to the client, keep serving
            log.exception("test server: %s failed", name)
            return error_threw(name, count, f"{type(err).__name__}: {err}"), None

    # The calls --------------------------------------------------------------------------------

    def _method_table(self) -> dict[str, tuple[Sequence[Callable], Callable]]:
        f, b, s = _float, _bool, _str
        return {
            "ping": ((), lambda: True),
            "getServerVersion": ((), lambda: SERVER_VERSION),
            "getMinRequiredClientVersion": ((), lambda: MIN_CLIENT_VERSION),
            "listVehicles": ((), lambda: self.names),
            "getSettingsString": ((), lambda: json.dumps(self.settings)),
            "reset": ((), self.world.reset),
            "simPause": ((b,), self._set_paused),
            "simIsPaused": ((), lambda: self._paused),
            "simContinueForTime": ((f,), self._continue_for_time),
            "simContinueForFrames": ((_uint,), self._continue_for_frames),
            "enableApiControl": ((b, s), self._enable_api_control),
            "isApiControlEnabled": ((s,), lambda n: self._vehicle(n).api_control),
            "armDisarm": ((b, s), self._arm_disarm),
            "takeoff": ((f, s), self._takeoff),
            "moveByVelocity": ((f, f, f, f, _int, _yaw_mode, s), self._move_by_velocity),
            "hover": ((s,), self._hover),
            "cancelLastTask": ((s,), lambda n: self.world.cancel(self._vehicle(n))),
            "getMultirotorState": ((s,), lambda n: self.world.multirotor_state(self._vehicle(n))),
            "simGetVehiclePose": ((s,), lambda n: self.world.pose(self._vehicle(n, sim=True))),
            "simSetVehiclePose": ((_pose, b, s), self._set_pose),
            "simGetCollisionInfo": (
                (s,),
                lambda n: self.world.read_collision(
                    self._vehicle(n, sim=True), clear=not self.collision_stays
                ),
            ),
            "simGetGroundTruthKinematics": (
                (s,),
                lambda n: self.world.kinematics(self._vehicle(n, sim=True)),
            ),
        }

    def _vehicle(self, name: str, sim: bool = False) -> Vehicle:
        vehicles = self.world.vehicles
        veh = vehicles.get(name) if name else next(iter(vehicles.values()))
        if veh is None:
            if sim:
                raise _Fail(
                    f"Vehicle Sim-API for '{name}' is not available. This could either because "
                    "this is not a simulation or this vehicle does not exist"
                )
            raise _Fail(
                f"Vehicle API for '{name}' is not available. This could either because this is "
                "simulation-only API or this vehicle does not exist"
            )
        return veh

    def _controllable(self, name: str) -> Vehicle:
        veh = self._vehicle(name)
        if not veh.api_control:
            raise _Fail("requestApiControl() must be called before using API control")
        if not veh.armed:
            raise _Fail(f"Vehicle '{veh.name}' is not armed: call armDisarm(True) first")
        return veh

    def _pending(self, start: Callable[[Callable[[bool], None]], None]) -> asyncio.Future:
        future = asyncio.get_running_loop().create_future()

        def done(ok: bool) -> None:
            if not future.done():
                future.set_result(ok)

        start(done)
        return future

    async def _continue_for_time(self, seconds: float) -> None:
        if not math.isfinite(seconds) or seconds < 0:
            raise _Fail(f"seconds must be a finite number >= 0, got {seconds}")
        sim_ns = round(seconds * self.continue_runs * self.sim_speed * 1e9)
        if self.whole_ticks:  # the first whole physics step at or past the time
            sim_ns = -(-sim_ns // self.world.dt_ns) * self.world.dt_ns
        if self.continue_answers_at_once:
            self._paused = False  # running until the continue ends
            self._spawn(self._continue(sim_ns))
            return
        await self._continue(sim_ns)

    async def _continue_for_frames(self, frames: int) -> None:
        await self._continue(frames * self.world.dt_ns)

    def _enable_api_control(self, enabled: bool, name: str) -> None:
        veh = self._vehicle(name)
        if not enabled and veh.api_control:
            self.world.hover(veh)
        veh.api_control = enabled

    def _arm_disarm(self, arm: bool, name: str) -> bool:
        veh = self._vehicle(name)
        if not veh.api_control:
            return False
        if not arm and veh.armed:
            self.world.hover(veh)
        veh.armed = arm
        return True

    async def _takeoff(self, timeout: float, name: str) -> bool:
        veh = self._controllable(name)
        return await self._pending(lambda done: self.world.takeoff(veh, timeout, done))

    async def _move_by_velocity(self, vx, vy, vz, duration, drivetrain, yaw_mode, name) -> bool:
        veh = self._controllable(name)
        if not all(map(math.isfinite, (vx, vy, vz, duration))):
            raise _Fail(f"moveByVelocity needs finite numbers, got {(vx, vy, vz, duration)}")
        return await self._pending(
            lambda done: self.world.move_by_velocity(veh, (vx, vy, vz), duration, done)
        )

    def _hover(self, name: str) -> bool:
        self.world.hover(self._controllable(name))
        return True

    def _set_pose(self, pose: dict[str, Any], ignore_collision: bool, name: str) -> None:
        veh = self._vehicle(name, sim=True)
        position = [pose["position"][k] for k in ("x_val", "y_val", "z_val")]
        orientation = [pose["orientation"][k] for k in ("w_val", "x_val", "y_val", "z_val")]
        self.world.set_pose(veh, position, orientation)
        if not ignore_collision:
            self.world.touching(veh)


# Command line -------------------------------------------------------------------------------


@exit_on_error
def main(argv: Sequence[str] | None = None, settings: Mapping[str, Any] | None = None) -> int:
    """Serve until interrupted (Ctrl-C or SIGTERM), logging the address; what
    ``python -m rlplat.airsim serve`` runs.

    Args:
        argv: ``--settings FILE`` (required unless ``settings`` is given), ``--host``,
            ``--port`` (default: the settings' ``ApiServerPort``, else 41451; 0 picks a free
            one), ``--clock-speed``, ``--realtime``, ``--continue-runs``, ``--whole-ticks``,
            ``--collision-stays`` and the physics constants (``--tau-xy`` ...).
        settings: the settings dict to serve when ``--settings`` is not given.
    """
    parser = ArgumentParser(
        prog="python -m rlplat.airsim serve",
        description="Loopback AirSim-protocol simulator (protocol conformance, not physics).",
    )
    parser.add_argument(
        "--settings", type=path_arg, required=settings is None, help="settings.json to serve"
    )
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=None, help="default: ApiServerPort, 41451")
    parser.add_argument("--clock-speed", type=float, default=None, help="default: ClockSpeed")
    parser.add_argument("--realtime", action="store_true", help="continues take wall time")
    parser.add_argument(
        "--continue-runs", type=float, default=1.0,
        help="fraction of a continue's time the simulation runs (AirSim, loaded)",
    )  # fmt: skip
    parser.add_argument(
        "--whole-ticks", action="store_true",
        help="continues run whole physics steps, to the first at or past their time (AirSim)",
    )  # fmt: skip
    parser.add_argument(
        "--collision-stays", action="store_true",
        help="a contact's collision info is kept once read, until the next one (AirSim)",
    )  # fmt: skip
    for name, default in (
        ("tau_xy", 0.9),
        ("tau_z", 0.08),
        ("a_xy_max", 6.3),
        ("a_up_max", 6.9),
        ("a_down_max", 4.8),
        ("physics_dt", 0.003),
        ("hover_after_s", 0.06),
        ("drag_xy", 0.0),
        ("drag_z", 0.0),
        ("collision_radius", 0.5),
    ):
        parser.add_argument(f"--{name.replace('_', '-')}", type=float, default=default)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if args.settings is not None:
        path = Path(args.settings)
        try:
            settings = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise ConfigError(f"--settings {path}: cannot read a settings.json: {err}") from None
    port = args.port
    if port is None:  # the settings' own port where they give one
        given = settings.get("ApiServerPort") if isinstance(settings, Mapping) else None
        port = given if isinstance(given, int) else DEFAULT_PORT
    server = TestServer(
        settings,
        args.host,
        port,
        tau_xy=args.tau_xy,
        tau_z=args.tau_z,
        a_xy_max=args.a_xy_max,
        a_up_max=args.a_up_max,
        a_down_max=args.a_down_max,
        physics_dt=args.physics_dt,
        clock_speed=args.clock_speed,
        hover_after_s=args.hover_after_s,
        drag_xy=args.drag_xy,
        drag_z=args.drag_z,
        collision_radius=args.collision_radius,
        realtime=args.realtime,
        continue_runs=args.continue_runs,
        whole_ticks=args.whole_ticks,
        collision_stays=args.collision_stays,
    )
    return serve_forever(server)


def write_recording(path: str | Path, records: Sequence[Mapping[str, Any]]) -> Path:
    """Write ``records`` (from :meth:`TestServer.take_recording`) as JSON lines, atomically."""
    path = Path(path)
    atomic_write_text(path, "".join(json.dumps(r, allow_nan=False) + "\n" for r in records))
    return path


def serve_forever(server: TestServer) -> int:
    """Run ``server`` until SIGINT or SIGTERM; stop it cleanly; return 0."""
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with server:
            while not stop.wait(0.5):
                pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
