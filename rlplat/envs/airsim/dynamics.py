"""``AirSimDynamics``: the drones of one env flown in an AirSim-protocol simulator, in lock step.

The contract of :mod:`rlplat.envs.dynamics` (``position``/``velocity`` (N, D, 3) ENU world,
``max_speed`` (N, D), ``reset``, ``advance``) with the physics done by the simulator at one
endpoint (N = 1: an env batch of several simulators is a TorchRL ``ParallelEnv`` of these, see
``rlplat.experiment.factory``). The simulation stays paused between calls:

- ``advance(command, period)``: each drone's command, clipped per axis to its ``max_speed``,
  goes out ENU -> NED as ``moveByVelocity`` lasting ``period + move_margin_s`` (so it never
  lapses into simple_flight's hover failsafe during the step); then ``simContinueForTime`` of
  ``period / clock_speed`` (the call counts the simulator's wall clock; a clock speed above 1
  at its whole part, :func:`~rlplat.envs.airsim.settings.effective_clock_speed`); then every
  drone's state and collision flag are read. The sim time that passed is measured from the state
  timestamps; off by more than ``step_tolerance_s`` it is an error or a logged warning
  (``on_time_mismatch``), never silent. AirSim ends a continue at the first physics tick at or
  past its time (3-ms ticks: 0.102 s for 0.1 s), so each step asks for the time to the env's
  clock (the period, less what the sim clock ran over, or more where it fell behind): the sim
  clock keeps to ``steps x period`` within a tick instead of drifting by the overshoot every
  step.
- ``reset``: the simulation is reset (every vehicle at rest at its spawn point), paused again,
  each drone given API control and armed again (a reset clears both) and placed at its start
  (ENU world -> NED world -> the vehicle's own spawn-relative frame, spawn points from the
  simulator's settings.json, ``spawn`` for those it lacks) with ``simSetVehiclePose``; its
  collision flag is read (so a contact from before counts no more). The state the simulator
  then reports is the drone's position and velocity.

Frames are converted only through :mod:`rlplat.envs.airsim.frames`. ``collided`` (N, D) bool
holds which drones the simulator reported a collision for during the last step (logged, and
the env's ``collided`` entry; a capture stays the env's distance test). The client library is
imported when the first simulator is connected, not when this module is.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from typing import Literal

import torch
from torch import Tensor

from rlplat.envs.airsim.client import AirSimClient, AirSimError, parse_endpoint
from rlplat.envs.airsim.frames import (
    enu_rows_to_ned,
    enu_to_ned,
    ned_rows_to_enu,
    spawn_offsets,
    world_to_local,
)
from rlplat.envs.airsim.settings import effective_clock_speed, vehicle_names
from rlplat.envs.dynamics import DroneDynamics
from rlplat.errors import ConfigError

log = logging.getLogger(__name__)

#: What a step whose sim time differs from the control period does.
TIME_MISMATCH = ("error", "warn")


#: s of wall time the sim clock must stand still for a simulator that cannot say it is paused
#: (no ``simIsPaused``) to count as paused short of a whole step (within the tolerance).
STILL_S = 0.05
#: The most times a short step is run on for its missing time (:meth:`AirSimDynamics.advance`).
TOP_UPS = 3
#: m, how far a drone may read from where it was placed (a simulator that applies a pose late
#: reads the old one: read again for up to ``PLACEMENT_WAIT_S``, then logged once).
PLACEMENT_TOLERANCE_M = 0.1
#: s of wall time a placement is read again for (a simulator that applies poses on its next
#: frame while paused), at most ``timeout_s``.
PLACEMENT_WAIT_S = 1.0


class AirSimDynamics(DroneDynamics):
    """The drones of one env in the simulator at ``endpoints[0]`` (one endpoint, N = 1).

    Args:
        num_envs: N, must be 1 (one simulator per env).
        num_drones: D, the env's drones: ``num_attackers`` attackers, then the defenders.
        num_attackers: how many of the drones are attackers (names their vehicles).
        device: torch device of the state tensors.
        endpoints: ``["host:port"]``, the simulator's RPC server.
        attacker_name: vehicle name of the first attacker (the i-th: ``f"{name}{i}"``).
        defender_name: vehicle name of the first defender (the i-th: ``f"{name}{i}"``).
        vehicles: every vehicle's name, the attackers first, then the defenders (in place of
            ``attacker_name`` and ``defender_name``).
        connect_timeout_s: s, the longest wait for the simulator to accept and answer.
        timeout_s: s, the longest wait for any later answer (must exceed one control period
            of simulator wall time, ``period / clock_speed``, above 1 its whole part).
        step_tolerance_s: s, the largest accepted difference between the sim time a step
            advanced (from the state timestamps) and the control period.
        on_time_mismatch: ``error`` or ``warn`` (log a warning and go on) beyond the tolerance.
        clock_speed: the simulator's ``ClockSpeed`` (settings.json); a step of ``period``
            sim seconds asks for ``period / clock_speed`` seconds of its wall clock (above 1,
            ``clock_speed``'s whole part: AirSim runs 2.5 at 2).
        spawn: vehicle name -> (x, y, z) NED metres of its spawn point, as settings.json's
            ``X``/``Y``/``Z``, for vehicles or coordinates the simulator's settings lack.
        move_margin_s: s, how much longer than a control period each velocity command lasts.
    """

    def __init__(
        self,
        *,
        num_envs: int,
        num_drones: int,
        num_attackers: int = 1,
        device: torch.device | str = "cpu",
        endpoints: Sequence[str] = ("127.0.0.1:41451",),
        attacker_name: str = "Attacker",
        defender_name: str = "Defender",
        vehicles: Sequence[str] | None = None,
        connect_timeout_s: float = 10.0,
        timeout_s: float = 10.0,
        step_tolerance_s: float = 0.02,
        on_time_mismatch: Literal["error", "warn"] = "error",
        clock_speed: float = 1.0,
        spawn: Mapping[str, Sequence[float]] | None = None,
        move_margin_s: float = 0.1,
    ) -> None:
        super().__init__(num_envs=num_envs, num_drones=num_drones, device=device, physics_dt=0.003)
        if num_envs != 1 or isinstance(endpoints, str) or len(endpoints) != 1:
            raise ConfigError(
                f"dynamics.endpoints: one simulator per env, got {len(endpoints)} endpoint(s) "
                f"for {num_envs} env(s) (several simulators fly as a parallel env)"
            )
        parse_endpoint(endpoints[0])
        for name, value in (
            ("connect_timeout_s", connect_timeout_s),
            ("timeout_s", timeout_s),
            ("clock_speed", clock_speed),
            ("move_margin_s", move_margin_s),
        ):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"dynamics.{name}: must be a finite number > 0, got {value!r}")
        if not step_tolerance_s >= 0:
            raise ConfigError(f"dynamics.step_tolerance_s: must be >= 0, got {step_tolerance_s!r}")
        if on_time_mismatch not in TIME_MISMATCH:
            raise ConfigError(
                f"dynamics.on_time_mismatch: unknown {on_time_mismatch!r}; valid: error, warn"
            )
        if not 0 <= num_attackers <= num_drones:
            raise ValueError(f"num_attackers must be in [0, {num_drones}], got {num_attackers}")
        self.names = vehicle_names(
            num_attackers, num_drones - num_attackers, attacker_name, defender_name, vehicles
        )
        self.step_tolerance_s, self.on_time_mismatch = float(step_tolerance_s), on_time_mismatch
        self.clock_speed, self.move_margin_s = float(clock_speed), float(move_margin_s)
        self._sim_speed = effective_clock_speed(self.clock_speed)  # what AirSim runs
        if self._sim_speed != self.clock_speed:
            log.warning("dynamics.clock_speed %g: AirSim runs a ClockSpeed above 1 at its whole "
                        "part, %g; each step asks for control_period / %g of its wall clock",
                        self.clock_speed, self._sim_speed, self._sim_speed)  # fmt: skip
        self.collided = torch.zeros(num_envs, num_drones, dtype=torch.bool, device=self.device)
        self.last_advance_s = float("nan")  # sim seconds the last step advanced
        self._due_ns = 0  # the sim time (ns) the env's clock is at: steps x period since reset
        self._ran_short = False  # a step has been run on for time it lacked (logged once)
        self._misplaced = False  # a drone read away from its placement (logged once)
        self.placement_error_m = 0.0  # m, the farthest a drone read from it at the last reset

        # Connect, check the vehicles and the clock, read the spawn points; then pause.
        self.client = AirSimClient(
            endpoints[0], connect_timeout_s=connect_timeout_s, timeout_s=timeout_s
        )
        try:
            self.client.require_vehicles(self.names)
            settings = self.client.settings()
            self._check_clock(settings)
            fallback = {k: [float(x) for x in v] for k, v in (spawn or {}).items()}
            self.spawn = spawn_offsets(settings, self.names, fallback)
            self.client.pause(True)
            for name in self.names:
                self.client.take_control(name)
            self._timestamp_ns = self._read("reading the drones after connecting")
            self._due_ns = self._timestamp_ns
        except BaseException:
            self.client.close()
            raise
        log.info("flying %s on %s (spawn NED %s)", ", ".join(self.names),
                 self.client.address, self.spawn)  # fmt: skip

    def _check_clock(self, settings: Mapping) -> None:
        clock = settings.get("ClockType")
        if isinstance(clock, str) and clock and clock != "SteppableClock":
            log.warning(
                "simulator at %s: ClockType %s keeps time while paused; lock-step flying wants "
                "SteppableClock (`python -m rlplat.airsim settings` writes it)",
                self.client.address, clock,
            )  # fmt: skip
        speed = settings.get("ClockSpeed")
        if isinstance(speed, (int, float)) and not math.isclose(speed, self.clock_speed):
            raise ConfigError(
                f"dynamics.clock_speed: {self.clock_speed:g}, the simulator at "
                f"{self.client.address} runs ClockSpeed {speed:g} (its settings.json)"
            )

    # The dynamics contract -------------------------------------------------------------

    def advance(self, command: Tensor, period: float) -> None:
        """Fly every drone for ``period`` sim seconds under its velocity command.

        Args:
            command: (1, D, 3) float32, goal velocity m/s ENU; clipped per axis to ±max_speed.
            period: control period in seconds (> 0).

        The step asks for the time that brings the sim clock to the env's (``period`` after
        the last step's due time): a simulator that runs whole physics ticks past a continue's
        time has the overshoot taken off the next step. A step that leaves the clock short of
        its due time by more than ``step_tolerance_s`` is run on for the time it lacks (up to
        ``TOP_UPS`` times, under the same commands, which last ``period + move_margin_s``):
        AirSim's ``simContinueForTime`` counts its wall clock, and a physics tick that runs
        long on a loaded machine is not made up.

        Raises:
            AirSimError: the simulator failed, or (``on_time_mismatch=error``) the sim clock
                ends the step more than ``step_tolerance_s`` from its due time (a mismatch
                that is only warned of makes the clock read the new due time).
        """
        if not period > 0:
            raise ValueError(f"period must be > 0, got {period!r}")
        self._check_shape("command", command, (self.num_envs, self.num_drones, 3))
        bound = self.max_speed.unsqueeze(-1)
        command = torch.clamp(command.detach().to(self.velocity), -bound, bound)
        ned = enu_rows_to_ned(command[0].tolist())
        for name, velocity in zip(self.names, ned, strict=True):
            self.client.move_velocity(name, velocity, period + self.move_margin_s)
        before, what = self._timestamp_ns, f"the drones after a step of {period:g} s"
        self._due_ns += round(period * 1e9)
        ask = max((self._due_ns - before) / 1e9, 0.5 * period)  # to the env's clock
        self._run(ask, period, what)
        hits = self.collided
        for _ in range(TOP_UPS):  # a collision any read reports counts (reported once)
            if not self._short():
                break
            lacking = (self._due_ns - self._timestamp_ns) / 1e9
            log.log(logging.DEBUG if self._ran_short else logging.WARNING,
                    "simulator at %s: a step of %g s ran %.4f s short (its simContinueForTime "
                    "counts wall time: a loaded machine, or a ClockSpeed other than "
                    "dynamics.clock_speed); such steps are run on for the time they lack",
                    self.client.address, period, lacking)  # fmt: skip
            self._ran_short = True
            self._run(lacking, period, what)
            hits = hits | self.collided
        self.collided = hits
        self._check_time(before, self._timestamp_ns, period)

    def _run(self, seconds: float, period: float, what: str) -> None:
        """Run the paused simulation ``seconds`` of sim time on and read the drones (again, if
        the read is short of the step's due time: :meth:`_read_again`)."""
        self.client.continue_for(seconds / self._sim_speed, f"a step of {period:g} s")
        self._timestamp_ns = self._read(what)
        if self._short():
            self._read_again(what)

    def _short(self) -> bool:
        """Whether the last read is short of the step's due time by more than the tolerance."""
        return (self._due_ns - self._timestamp_ns) / 1e9 > self.step_tolerance_s

    def _read_again(self, what: str) -> None:
        """After a read short of the period: a simulator whose ``simContinueForTime`` answers
        before its time has run (older AirSim) may have been read before it ran, and may be
        paused again by the time ``simIsPaused`` is asked. Wait for the pause and read again;
        a simulator that cannot say whether it is paused (no ``simIsPaused``) is read until
        the step's time has run, within ``timeout_s``. A collision any read reports counts
        (each contact is reported once)."""
        self.client.wait_paused(what)
        hits = self.collided
        self._timestamp_ns = self._read(what)
        hits = hits | self.collided
        if not getattr(self.client, "tells_pause", True):
            now = time.monotonic()
            deadline, last, since = now + self.client.timeout_s, self._timestamp_ns, now
            while time.monotonic() < deadline:
                if self._timestamp_ns >= self._due_ns - 1000:  # the whole step (within 1 us)
                    break
                if not self._short() and time.monotonic() - since >= STILL_S:
                    break  # within the tolerance, and the clock has stopped: paused there
                time.sleep(0.001)
                self._timestamp_ns = self._read(what)
                hits = hits | self.collided
                if self._timestamp_ns != last:
                    last, since = self._timestamp_ns, time.monotonic()
        self.collided = hits

    def _reset_internal(self, mask: Tensor) -> None:
        """Reset the simulation (every drone at rest), pause it, take control of the drones
        again, place them at ``position`` (set by ``reset``) and read back what the simulator
        reports; collision flags cleared."""
        if not bool(mask[0]):
            return
        self.client.reset()
        self.client.pause(True)
        world_ned = enu_to_ned(self.position[0].double().cpu())
        for i, name in enumerate(self.names):
            self.client.take_control(name)
            self.client.set_position(name, world_to_local(world_ned[i], self.spawn[name]).tolist())
        placed = self.position.clone()
        deadline = time.monotonic() + min(PLACEMENT_WAIT_S, self.client.timeout_s)
        while True:  # a simulator may apply a pose on its next frame (paused or not)
            self._timestamp_ns = self._due_ns = self._read("the drones after placing them")
            off = (self.position - placed).norm(dim=-1)[0]  # (drones,) m
            if not bool((off > PLACEMENT_TOLERANCE_M).any()) or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        self.placement_error_m = float(off.max())
        if not self._misplaced and self.placement_error_m > PLACEMENT_TOLERANCE_M:
            far = int(off.argmax())
            log.warning("simulator at %s: %s reads %.2f m from where it was placed (the "
                        "simulator applies poses late, or not at all); the episode starts "
                        "where the drones read",
                        self.client.address, self.names[far], float(off[far]))  # fmt: skip
            self._misplaced = True
        self.collided = torch.zeros_like(self.collided)

    # Helpers ---------------------------------------------------------------------------

    def _read(self, what: str) -> int:
        """Read every drone's state into ``position``/``velocity`` (ENU world) and their
        collision flags into ``collided``; returns the simulator's timestamp (ns)."""
        states, hits = self.client.read(self.names, what)
        # Python floats (float64) through the frames, then one float32 tensor each.
        spawn = [self.spawn[n] for n in self.names]
        position = ned_rows_to_enu([s.position for s in states], spawn)
        velocity = ned_rows_to_enu([s.velocity for s in states])
        self.position = torch.tensor([position], dtype=self.position.dtype, device=self.device)
        self.velocity = torch.tensor([velocity], dtype=self.velocity.dtype, device=self.device)
        self.collided = torch.tensor([hits], dtype=torch.bool, device=self.device)
        if any(hits):
            log.info(
                "collision reported for %s", [n for n, h in zip(self.names, hits, strict=True) if h]
            )
        stamps = {s.timestamp_ns for s in states}
        if len(stamps) > 1:
            log.debug("vehicles report different timestamps: %s", sorted(stamps))
        return states[0].timestamp_ns

    def _check_time(self, before: int, after: int, period: float) -> None:
        self.last_advance_s = (after - before) / 1e9
        gap = (after - self._due_ns) / 1e9
        if abs(gap) <= self.step_tolerance_s:
            return
        message = (
            f"simulator at {self.client.address}: a step advanced {self.last_advance_s:.4f} s of "
            f"sim time, the control period is {period:g} s ({gap:+.4f} s off the env's clock; "
            f"dynamics.step_tolerance_s={self.step_tolerance_s:g}; check dynamics.clock_speed "
            "against the simulator's ClockSpeed)"
        )
        if self.on_time_mismatch == "error":
            raise AirSimError(message)
        log.warning("%s", message)
        self._due_ns = after  # warned: the next step starts from the clock as it reads

    def close(self) -> None:
        """Close the connection to the simulator."""
        self.client.close()
