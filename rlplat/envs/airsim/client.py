"""The connection to one AirSim-protocol simulator (AirSim, Cosys-AirSim) at ``host:port``.

:class:`AirSimClient` speaks through the ``cosysairsim`` client library (the ``airsim`` extra:
``pip install -e .[airsim]``), imported when a client is first made, never at import time. What
it adds to the library is what a lock-step loop needs to fail cleanly:

- only Python floats, ints, bools and strings go on the wire (numpy scalars make the simulator
  raise, drop the value or hang);
- every call that waits has a deadline (``timeout_s``; ``connect_timeout_s`` while connecting),
  so a simulator that stops answering is an :class:`AirSimError` naming the call it was
  waiting for, never a hang (the library's own timeout defaults to an hour);
- a connection the simulator closes fails every pending call at once and is not silently
  reopened (the library would reconnect on the next call and lose the paused sim's state);
- no simulator at the address, a vehicle name it does not have, a refused call: one line each.

Moves are sent without waiting for their end (a move answers only when it is done or cancelled,
and the simulation is paused between steps: waiting on one would block until the timeout). State
reads of several vehicles are sent together and awaited together: one round trip per step. What is
sent without waiting goes out in one write with the next call that waits (a step's moves with its
``simContinueForTime``), and answers awaited together are awaited in one run of the event loop
under one deadline: a lock step is two writes and two waits, whatever the number of vehicles.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

from rlplat.errors import ConfigError, RlplatError

log = logging.getLogger(__name__)

#: How a user starts a simulator that rlplat can fly (said when none answers).
START_HINT = (
    "start AirSim/Unreal with the settings.json of `python -m rlplat.airsim settings out=PATH` "
    "(SimMode Multirotor, ApiServerPort = this port), or the loopback test server with "
    "`python -m rlplat.airsim serve --port PORT`"
)


#: rpclib's words for a method the server does not have.
NO_FUNCTION = "could not find function"


class AirSimError(RlplatError):
    """The simulator is unreachable, stopped answering, lost the connection or refused a call;
    the message names the address and what was being waited for."""


class AirSimRefused(AirSimError):
    """The simulator answered a call with an error (rather than not answering): for a call
    that only checks (``ping``, ``listVehicles``, ``getSettingsString``, ``simIsPaused``) or
    only reports (``simGetCollisionInfo``), a simulator without it, whatever its words.
    ``reason``: its words, on one line."""

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)  # one argument: it pickles (a worker's fault) as it is
        self.reason = message if reason is None else reason


@dataclass(frozen=True)
class VehicleState:
    """What one ``getMultirotorState`` read gives a lock-step loop (NED, the vehicle's own
    spawn-relative frame, SI units)."""

    position: tuple[float, float, float]  # m, relative to the vehicle's spawn point
    velocity: tuple[float, float, float]  # m/s
    timestamp_ns: int  # the simulator's clock


def parse_endpoint(text: Any, field: str = "dynamics.endpoints") -> tuple[str, int]:
    """``"host:port"`` -> (host, port); a clear one-line :class:`ConfigError` naming ``field``
    and the value for anything else (no port, a port outside 1..65535, an empty host)."""
    if isinstance(text, str) and ":" in text:
        host, _, port = text.strip().rpartition(":")
        host = host.strip("[]")
        if host and port.isdigit() and 1 <= int(port) <= 65535:
            return host, int(port)
    raise ConfigError(
        f"{field}: {text!r} is not host:port (e.g. 127.0.0.1:41451, port in 1..65535)"
    )


#: Types that go on the wire as they are.
_WIRE_TYPES = frozenset({bool, int, float, str, type(None)})


def plain(value: Any) -> Any:
    """``value`` as what may go on the wire: a Python bool, int, float or str (numpy and torch
    scalars, 0-d arrays and tensors converted), or a list/dict of them."""
    if type(value) in _WIRE_TYPES:  # already plain (most arguments)
        return value
    if isinstance(value, (bool, str)) or value is None:
        return value
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if hasattr(value, "to_msgpack"):  # a library struct (Pose, YawMode): its fields made plain
        for key, field in vars(value).items():
            setattr(value, key, plain(field))
        return value
    if hasattr(value, "item"):  # numpy / torch scalars and single-element arrays
        value = value.item()
    if isinstance(value, bool):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    raise TypeError(f"cannot send {type(value).__name__} to the simulator: {value!r}")


def _field(raw: Any, path: str) -> Any:
    """``raw[k1][k2]...`` for the dotted ``path``; KeyError naming the first key missing."""
    value = raw
    for key in path.split("."):
        if isinstance(value, dict) and key not in value and key.encode() in value:
            key = key.encode()  # a server that packs its map keys as bin
        if not isinstance(value, dict) or key not in value:
            raise KeyError(key)
        value = value[key]
    return value


def _fields(raw: Any) -> VehicleState:
    """What a lock step reads of a ``getMultirotorState`` answer, taken from its map (the
    values the library's ``MultirotorState`` would hold).

    Raises:
        ValueError: a field is missing or not a number, naming its path.
    """
    values = {}
    for path in (
        *(f"kinematics_estimated.{v}.{a}_val" for v in ("position", "linear_velocity")
          for a in "xyz"),
        "timestamp",
    ):  # fmt: skip
        try:
            value = _field(raw, path)
        except KeyError:
            raise ValueError(f"has no {path}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{path} is {value!r:.40}, not a number")
        values[path] = value
    k = "kinematics_estimated."
    position = tuple(float(values[f"{k}position.{a}_val"]) for a in "xyz")
    velocity = tuple(float(values[f"{k}linear_velocity.{a}_val"]) for a in "xyz")
    return VehicleState(position, velocity, int(values["timestamp"]))


class _Lost(Exception):
    """The simulator closed the connection."""


class _Expired(Exception):
    """No answer before the deadline."""


class _Unreadable(Exception):
    """The simulator sent something that is not a msgpack-rpc message."""


def one_line(reason: Any, limit: int = 300) -> str:
    """``reason`` as one line of at most ``limit`` characters (a server's error text may hold
    newlines or bytes)."""
    if isinstance(reason, bytes):
        reason = reason.decode("utf-8", "backslashreplace")
    text = " ".join(str(reason).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


#: How the msgpack-rpc library words a failed or closed connection (the text of its
#: ``TransportError``s, which is what a call's error then holds).
_LIBRARY_LOSSES = (
    "Retry connection over the limit",
    "Client is closed, connection could not be set",
)


def _no_connection(reason: Any) -> bool:
    """The connection failed or was lost (not a timeout, not an error the simulator answered,
    whatever its words)."""
    from msgpackrpc.error import TransportError

    if isinstance(reason, (_Lost, TransportError, OSError)):
        return True
    return isinstance(reason, str) and reason in _LIBRARY_LOSSES


def _words(refusal: AirSimRefused) -> str:
    """Nothing for rpclib's words for a missing method; otherwise the simulator's, in
    parentheses (a call that checks and that it refused in other words)."""
    return "" if NO_FUNCTION in refusal.reason else f" (it answered: {refusal.reason})"


def _retrieved(task) -> None:
    """Mark a send task's exception as seen (the call it belongs to reports the loss)."""
    if not task.cancelled():
        task.exception()


def _ignore(data: bytes) -> None:
    """A sink that drops what it is given."""


def _settled(futures: Sequence[Any]) -> bool:
    """Every future answered, or one failed after all those before it were answered."""
    for future in futures:
        if not future._set_flag:
            return False
        if future._error is not None:
            return True
    return True


def _session_types():
    """The msgpack-rpc session and transport the library rides on, with rlplat's policy: no
    silent reconnect after a loss, read errors kept quiet (the loss is reported), answers
    handed to the session as they are read."""
    import msgpack
    import msgpackrpc
    from msgpackrpc.future import Future
    from msgpackrpc.message import NOTIFY, REQUEST, RESPONSE
    from msgpackrpc.transport import tcp
    from tornado.iostream import IOStream, StreamClosedError

    class Stream(IOStream):
        """A stream whose bytes go to ``sink`` as they are read, in the loop's I/O callback
        (no read future and no coroutine step per arrival). End of stream and read errors
        close it as any stream (its close callback reports the loss)."""

        sink = None

        def read_from_fd(self, buf):
            count = super().read_from_fd(buf)
            if not count or self.sink is None:
                return count
            self.sink(bytes(memoryview(buf)[:count]))
            return None  # consumed: nothing for the stream's own buffer

    class Socket(tcp.ClientSocket):
        def __init__(self, stream, transport):
            super().__init__(stream, transport)
            # Maps with integer keys, and text that is not UTF-8, are read (not a reason to
            # stop reading): what an answer holds is checked where it is used.
            self._unpacker = msgpack.Unpacker(
                raw=False, strict_map_key=False, unicode_errors="backslashreplace"
            )

        async def on_connect(self):
            self._stream.set_nodelay(True)  # small requests go out at once (no Nagle delay)
            self._stream.sink = self.on_data
            await self._transport.on_connect(self)

        def on_data(self, data: bytes) -> None:
            """Answers to the session as they arrive; notifications, and requests from the
            server (rlplat serves none), are skipped. Anything else is not msgpack-rpc: every
            call in flight fails at once with what was read, and the connection is closed."""
            self._unpacker.feed(data)
            try:
                for message in self._unpacker:
                    kind = message[0] if isinstance(message, list) and message else None
                    if kind == NOTIFY and len(message) == 3:
                        continue
                    if kind == REQUEST and len(message) == 4:
                        log.debug("simulator sent request %r: not served", message[2])
                        continue
                    if kind != RESPONSE or len(message) != 4:
                        raise ValueError(f"not a msgpack-rpc message: {message!r:.120}")
                    self.on_response(message[1], message[2], message[3])
            except Exception as e:
                self._stream.sink = _ignore
                self._transport._session.on_connect_failed(_Unreadable(one_line(e)))

    class Transport(tcp.ClientTransport):
        async def connect(self):
            await Socket(Stream(self._address.socket()), self).connect()

        async def on_close(self, sock):
            if self._closed:
                return
            self._closed = True
            self._sockets = []
            self._session.on_connect_failed(_Lost("the simulator closed the connection"))

    class Session(msgpackrpc.Client):
        """The library's session, driven in batches: a request is packed into an outbox when it
        is sent, the outbox goes out in one write when something is awaited, and the loop runs
        once for all the answers awaited together (no task, timer or loop restart per call)."""

        def __init__(self, host: str, port: int) -> None:
            # timeout=0: no library timer; every wait has its own deadline (settle()).
            super().__init__(
                msgpackrpc.Address(host, port),
                timeout=0,
                builder=SimpleNamespace(ClientTransport=Transport),
                reconnect_limit=0,
                pack_encoding="utf-8",
                unpack_encoding="utf-8",
            )
            self._outbox: list[bytes] = []
            self._awaited: Sequence[Any] | None = None

        def send_request(self, method, args):
            sockets = self._transport._sockets
            if not sockets:  # still connecting: the library queues it until connected
                future = super().send_request(method, args)
                future.task.add_done_callback(_retrieved)  # a send on a lost connection: reported
                return future
            msgid = next(self._generator)
            self._outbox.append(sockets[0]._packer.pack([REQUEST, msgid, method, args]))
            future = Future(self._loop, self._timeout)
            self._request_table[msgid] = future
            return future

        def flush(self) -> None:
            """Write the requests sent since the last flush, in one write: straight to the
            socket when the stream has nothing queued, what the socket does not take (or an
            error) through the stream. A stream already closed is left to its close callback
            (it fails every pending call)."""
            if not self._outbox:
                return
            data, self._outbox = b"".join(self._outbox), []
            sockets = self._transport._sockets if self._transport is not None else ()
            if not sockets or sockets[0]._stream.closed():
                return
            stream = sockets[0]._stream
            if not stream.writing():
                # would block, or an error the stream meets again and reports
                with contextlib.suppress(OSError):
                    data = data[stream.socket.send(data) :]
            if data:
                with contextlib.suppress(StreamClosedError):
                    stream.write(data)

        def close(self) -> None:
            self._outbox = []
            super().close()

        def call(self, method, *args):
            future = self.call_async(method, *args)
            self.settle((future,), self.deadline_s)
            return future.get()

        def settle(self, futures: Sequence[Any], seconds: float) -> None:
            """Run the loop until ``futures`` are answered, or one of them failed after all
            those before it were answered, for at most ``seconds``; those still unanswered
            then fail with ``_Expired``."""
            self.flush()
            if _settled(futures):
                return
            ioloop = self._loop._ioloop

            def expire():
                for future in futures:
                    if not future._set_flag:
                        future.set_error(_Expired())
                self._loop.stop()

            handle = ioloop.call_later(seconds, expire)
            self._awaited = futures
            try:
                while not _settled(futures):
                    self._loop.start()
            finally:
                self._awaited = None
                ioloop.remove_timeout(handle)

        def on_response(self, msgid, error, result):
            future = self._request_table.pop(msgid, None)
            if future is None:
                return
            if error is not None:
                future.set_error(error)
            else:
                future.set_result(result)
            if self._awaited is None or _settled(self._awaited):
                self._loop.stop()

    return Session


#: The asyncio loop each thread's clients run on, made by the first of them.
_THREAD_LOOP = threading.local()


def _ensure_event_loop() -> None:
    """The library runs tornado on this thread's current asyncio loop: set this thread's own
    (made once, again if closed), unless a loop runs here already. Asking asyncio whether one
    is set would warn where none is (Python 3.12 and 3.13) and fail in 3.14."""
    with contextlib.suppress(RuntimeError):
        asyncio.get_running_loop()
        return
    loop = getattr(_THREAD_LOOP, "loop", None)
    if loop is None or loop.is_closed():
        _THREAD_LOOP.loop = loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)


class AirSimClient:
    """A connection to the simulator at ``address`` (``host:port``), paused on connect.

    Args:
        address: ``host:port`` of the simulator's RPC server (``ApiServerPort``, 41451 by
            default).
        connect_timeout_s: s, the longest wait for the connection and the first answer.
        timeout_s: s, the longest wait for any later answer (a ``simContinueForTime`` of a
            control period included).

    Raises:
        ConfigError: ``address`` is not ``host:port``.
        AirSimError: nothing answers at ``address`` within ``connect_timeout_s``.
    """

    def __init__(
        self, address: str, *, connect_timeout_s: float = 10.0, timeout_s: float = 10.0
    ) -> None:
        self.host, self.port = parse_endpoint(address)
        host = f"[{self.host}]" if ":" in self.host else self.host  # IPv6 in brackets
        self.address = f"{host}:{self.port}"
        self.connect_timeout_s, self.timeout_s = float(connect_timeout_s), float(timeout_s)
        self._api, self._field = None, "dynamics.timeout_s"
        self._moves: dict[str, Any] = {}  # the last move sent to each vehicle
        self._no_is_paused = False  # the simulator lacks simIsPaused
        self._no_collisions = False  # the simulator lacks simGetCollisionInfo
        self._contacts: dict[str, Any] = {}  # each vehicle's last reported contact's time_stamp
        self._kept_flag = False  # a contact's flag was read set again (logged once)
        try:
            import cosysairsim
        except ImportError:
            raise AirSimError(
                "dynamics=airsim needs the cosysairsim client library: pip install -e .[airsim]"
            ) from None
        self._lib = cosysairsim
        try:  # the library's connect would swallow this and wait out the timeout
            socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)
        except (socket.gaierror, UnicodeError) as e:
            raise AirSimError(
                f"no simulator at {self.address}: the host name does not resolve "
                f"({getattr(e, 'strerror', None) or e}); {START_HINT}"
            ) from None
        _ensure_event_loop()
        api = cosysairsim.MultirotorClient.__new__(cosysairsim.MultirotorClient)
        api.client = _session_types()(self.host, self.port)
        api.client.deadline_s, self._field = self.connect_timeout_s, "dynamics.connect_timeout_s"
        self._api = api
        try:
            self.call("ping", "connecting", api.ping)
        except AirSimRefused as e:  # an msgpack-rpc answer: a server is there, without ping
            log.warning("simulator at %s has no ping%s: connected without it",
                        self.address, _words(e))  # fmt: skip
        except BaseException:
            self.close()
            raise
        api.client.deadline_s, self._field = self.timeout_s, "dynamics.timeout_s"
        log.info("connected to the simulator at %s", self.address)

    # Calls -----------------------------------------------------------------------------

    def call(self, method: str, what: str, fn, *args: Any) -> Any:
        """``fn(*args)`` (a library method that sends ``method``), every argument made plain;
        its faults as :class:`AirSimError` saying ``what`` was awaited."""
        return self._guard(method, what, lambda: fn(*plain(list(args))))

    def _guard(self, method: str, what: str, thunk) -> Any:
        if self._api is None or self._api.client._transport is None:
            raise AirSimError(f"simulator at {self.address}: the connection is closed ({what})")
        return self._answer(method, what, thunk)

    def _answer(self, method: str, what: str, thunk) -> Any:
        """``thunk()``, its faults as :class:`AirSimError` naming ``method`` and ``what``."""
        from msgpackrpc.error import RPCError

        try:
            return thunk()
        except RPCError as e:
            reason = e.args[0] if e.args else e
            lost = _no_connection(reason)
            connecting = self._field == "dynamics.connect_timeout_s"
            if isinstance(reason, _Unreadable):
                raise AirSimError(
                    f"simulator at {self.address} sent an answer that is not msgpack-rpc while "
                    f"waiting for {method} ({what}): {reason}; is it an AirSim RPC server?"
                ) from None
            if connecting and isinstance(reason, _Lost):  # something listens, then hangs up
                raise AirSimError(
                    f"{self.address} closed the connection before answering {method} "
                    f"({what}): is it an AirSim RPC server? {START_HINT}"
                ) from None
            if connecting and lost:  # the first call: nothing listens there
                raise AirSimError(
                    f"no simulator at {self.address} (connection refused or unreachable); "
                    f"{START_HINT}"
                ) from None
            if isinstance(reason, _Expired):
                wait = self._api.client.deadline_s
                hint = f"; {START_HINT}" if connecting else self._pending_hint()
                raise AirSimError(
                    f"simulator at {self.address} stopped answering: no answer to {method} "
                    f"({what}) within {wait:g} s ({self._field}){hint}"
                ) from None
            if lost:
                raise AirSimError(
                    f"lost the connection to the simulator at {self.address} while waiting for "
                    f"{method} ({what}); restart it and resume the run"
                ) from None
            words = one_line(reason)
            raise AirSimRefused(
                f"simulator at {self.address} refused {method} ({what}): {words}", words
            ) from None

    def _pending_hint(self) -> str:
        """Why a wait may have expired with moves in flight (sent, never waited on): each holds
        a server thread until the next one cancels it (AirSim serves vehicles + 4 at once)."""
        pending = sum(not f._set_flag for f in self._moves.values())
        if not pending:
            return ""
        return (
            f"; {pending} moveByVelocity calls were still open, and a server that serves "
            f"fewer than {pending + 1} calls at once cannot answer beside them"
        )

    def send(self, method: str, *args: Any):
        """Send ``method`` without waiting for its answer (a future for :meth:`gather`; it goes
        out with the next wait)."""
        if self._api is None or self._api.client._transport is None:
            raise AirSimError(f"simulator at {self.address}: the connection is closed ({method})")
        return self._api.client.call_async(method, *plain(list(args)))

    def gather(self, futures: Sequence[Any], method: str | Sequence[str], what: str) -> list[Any]:
        """The answers to futures sent together, within one ``timeout_s`` deadline: the loop
        runs once for all of them; the first that failed, in order, is the error.

        Args:
            futures: from :meth:`send`.
            method: the method each future called (one name for all, or one per future), for
                the errors.
            what: what was being waited for, for the errors.
        """
        if not futures:
            return []
        methods = [method] * len(futures) if isinstance(method, str) else list(method)
        session = self._api.client

        def first() -> Any:
            session.settle(futures, self.timeout_s)
            return futures[0].get()

        answers = [self._guard(methods[0], what, first)]
        pairs = zip(futures[1:], methods[1:], strict=True)
        return answers + [self._answer(m, what, f.get) for f, m in pairs]

    # What a lock-step loop uses ----------------------------------------------------------

    def vehicles(self) -> list[str]:
        """The simulator's vehicle names (``listVehicles``)."""
        names = self.call("listVehicles", "its vehicles", self._api.listVehicles)
        if not isinstance(names, list):
            raise AirSimError(
                f"simulator at {self.address}: listVehicles answered {names!r:.80}, not a list"
            )
        return [v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v) for v in names]

    def require_vehicles(self, names: Sequence[str]) -> None:
        """Raise :class:`AirSimError` listing the simulator's vehicles if one of ``names`` is
        not among them."""
        try:
            have = self.vehicles()
        except AirSimRefused as e:
            log.warning("simulator at %s has no listVehicles%s: vehicles %s not checked",
                        self.address, _words(e), ", ".join(names))  # fmt: skip
            return
        missing = [n for n in names if n not in have]
        if missing:
            raise AirSimError(
                f"simulator at {self.address} has no vehicle {', '.join(map(repr, missing))}; "
                f"its vehicles: {', '.join(have) or 'none'} (dynamics.attacker_name, "
                "dynamics.defender_name or dynamics.vehicles; settings.json Vehicles)"
            )

    def settings(self) -> dict[str, Any]:
        """The simulator's settings.json (``getSettingsString``), {} if it gives none."""
        try:
            text = self.call("getSettingsString", "its settings", self._api.getSettingsString)
        except AirSimRefused as e:
            log.warning("simulator at %s has no getSettingsString%s: its settings are not "
                        "checked (dynamics.spawn places the vehicles)",
                        self.address, _words(e))  # fmt: skip
            return {}
        try:
            parsed = json.loads(text) if text else {}
        except (TypeError, ValueError):
            log.warning("simulator at %s: settings string is not JSON; ignored", self.address)
            return {}
        return parsed if isinstance(parsed, dict) else {}

    def pause(self, paused: bool = True) -> None:
        """Pause (or release) the simulation and check that it took."""
        self.call("simPause", "pausing", self._api.simPause, bool(paused))
        now = self.is_paused("pause state")
        if now is not None and bool(now) != bool(paused):
            raise AirSimError(f"simulator at {self.address}: simPause({paused}) did not take")

    def reset(self) -> None:
        """Every vehicle back to its spawn point at rest (``reset``); API control and arming
        are cleared by it: :meth:`take_control` again."""
        self.call("reset", "resetting the simulation", self._api.reset)
        self._moves.clear()  # the reset ended them
        self._contacts.clear()  # a contact after it is new, whatever its time_stamp

    def take_control(self, name: str) -> None:
        """API control on and armed (again after any simulator ``reset``)."""
        self.call("enableApiControl", f"control of {name}", self._api.enableApiControl, True, name)
        armed = self.call("armDisarm", f"arming {name}", self._api.armDisarm, True, name)
        if armed is False:  # AirSim answers false when the vehicle would not arm
            raise AirSimError(f"simulator at {self.address}: {name} did not arm (armDisarm)")

    def set_position(self, name: str, position_ned: Sequence[float]) -> None:
        """Place ``name`` at ``position_ned`` (its spawn-relative NED frame), level, with
        collisions ignored for the placement."""
        lib = self._lib
        x, y, z = (float(v) for v in plain(list(position_ned)))  # Vector3r's fields are floats
        pose = lib.Pose(lib.Vector3r(x, y, z), lib.Quaternionr())
        self.call("simSetVehiclePose", f"placing {name}", self._api.simSetVehiclePose,
                  pose, True, name)  # fmt: skip

    def move_velocity(self, name: str, velocity_ned: Sequence[float], duration_s: float):
        """Command ``name``'s velocity (NED m/s) for ``duration_s`` sim seconds; not awaited
        (a move answers when it ends or the next one cancels it): :meth:`check_moves` reports
        one the simulator refused."""
        vx, vy, vz = (float(v) for v in plain(list(velocity_ned)))  # floats on the wire
        self._moves[name] = self.send(
            "moveByVelocity", vx, vy, vz, float(duration_s),
            self._lib.DrivetrainType.MaxDegreeOfFreedom, self._lib.YawMode(), name,
        )  # fmt: skip
        return self._moves[name]

    def check_moves(self) -> None:
        """Raise :class:`AirSimError` if the simulator answered a move with an error (an
        unknown vehicle, one not under API control, wrong arguments): the drone would not fly
        its commands. A move cancelled by the next one is not an error."""
        for name, future in self._moves.items():
            error = future.error if future._set_flag else None
            if error is not None and "cancel" not in str(error).lower():
                raise AirSimError(
                    f"simulator at {self.address} refused moveByVelocity for {name}: "
                    f"{one_line(error)}"
                )

    def continue_for(self, seconds: float, what: str) -> None:
        """Run the paused simulation for ``seconds`` (of the simulator's wall clock) and wait
        until it is paused again."""
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"seconds must be > 0, got {seconds!r}")
        self.call("simContinueForTime", what, self._api.simContinueForTime, float(seconds))

    def is_paused(self, what: str) -> bool | None:
        """Whether the simulation is paused (``simIsPaused``); None from a simulator without
        that call (logged once)."""
        if self._no_is_paused:
            return None
        try:
            return bool(self.call("simIsPaused", what, self._api.simIsPause))
        except AirSimRefused as e:
            self._no_is_paused = True
            log.warning("simulator at %s has no simIsPaused%s: pauses are not checked",
                        self.address, _words(e))  # fmt: skip
            return None

    @property
    def tells_pause(self) -> bool:
        """Whether the simulator answers ``simIsPaused`` (as far as asked so far)."""
        return not self._no_is_paused

    def wait_paused(self, what: str) -> bool:
        """Wait until the simulation is paused again (``simIsPaused``), within ``timeout_s``:
        for a simulator whose ``simContinueForTime`` answers before its time has run. True if
        it was still running."""
        deadline = time.monotonic() + self.timeout_s
        running = False
        while self.is_paused(what) is False:
            running = True
            if time.monotonic() > deadline:
                raise AirSimError(
                    f"simulator at {self.address} still runs {self.timeout_s:g} s after "
                    f"simContinueForTime ({what}; dynamics.timeout_s)"
                )
            time.sleep(0.001)
        return running

    def read(self, names: Sequence[str], what: str) -> tuple[list[VehicleState], list[bool]]:
        """Every vehicle's state and collision flag, sent together. The fields are read from
        the answers' maps: an answer that lacks one is an :class:`AirSimError` naming it (never
        a default).

        A collision is reported once: Cosys-AirSim clears the flag it reports, but AirSim's
        ``getCollisionInfo`` keeps it set with the contact's ``time_stamp`` until the next
        contact or a reset, so a set flag whose nonzero ``time_stamp`` is the one last
        reported for that vehicle is the same contact read again, not a new one."""
        states = [self.send("getMultirotorState", n) for n in names]
        asks = not self._no_collisions
        hits = [self.send("simGetCollisionInfo", n) for n in names] if asks else []
        methods = ["getMultirotorState"] * len(names) + ["simGetCollisionInfo"] * len(hits)
        try:
            answers = self.gather(states + hits, methods, what)
        except AirSimRefused as e:
            if not (asks and "simGetCollisionInfo" in str(e)):
                raise
            self._no_collisions = True  # the states' answers came first: they were fine
            log.warning("simulator at %s has no simGetCollisionInfo%s: no collisions are reported",
                        self.address, _words(e))  # fmt: skip
            return self.read(names, what)
        self.check_moves()  # a refused move has been answered by now: it came first
        raw_states = answers[: len(names)]
        raw_hits = answers[len(names) :] if asks else [{"has_collided": False}] * len(names)
        out, hits = [], []
        for name, raw in zip(names, raw_states, strict=True):
            try:
                out.append(_fields(raw))
            except ValueError as e:
                raise AirSimError(
                    f"simulator at {self.address}: its getMultirotorState for {name} ({what}) {e}"
                ) from None
        for name, raw in zip(names, raw_hits, strict=True):
            try:
                flag = _field(raw, "has_collided")
            except KeyError:
                flag = None
            if not isinstance(flag, (bool, int)):
                raise AirSimError(
                    f"simulator at {self.address}: its simGetCollisionInfo for {name} ({what}) "
                    f"has no has_collided flag: {raw!r:.80}"
                )
            hits.append(self._new_contact(name, bool(flag), raw))
        return out, hits

    def _new_contact(self, name: str, flag: bool, raw: Any) -> bool:
        """Whether a collision answer ``raw`` (flag ``flag``) reports a contact not reported
        before: see :meth:`read`."""
        try:
            stamp = _field(raw, "time_stamp")
        except KeyError:
            stamp = None
        if not flag or isinstance(stamp, bool) or not isinstance(stamp, int) or stamp == 0:
            return flag
        if self._contacts.get(name) == stamp:
            if not self._kept_flag:
                self._kept_flag = True
                log.info("simulator at %s keeps a collision's flag set after it is read (as "
                         "AirSim's getCollisionInfo); a contact counts once, by its time_stamp",
                         self.address)  # fmt: skip
            return False
        self._contacts[name] = stamp
        return True

    def close(self) -> None:
        """Close the connection (the simulation stays as it is)."""
        if self._api is not None and self._api.client._transport is not None:
            self._api.client.close()
        self._api = None


def check_simulators(dynamics: Mapping[str, Any]) -> None:
    """Each of a ``dynamics=airsim`` node's ``endpoints`` answers (an AirSim RPC server
    there), before any work that needs them: one line naming the field and the first that
    does not."""
    for endpoint in dynamics["endpoints"]:
        try:
            client = AirSimClient(
                endpoint,
                connect_timeout_s=dynamics["connect_timeout_s"],
                timeout_s=dynamics["timeout_s"],
            )
        except AirSimError as e:
            raise AirSimError(f"dynamics.endpoints: {e}") from None
        client.close()
