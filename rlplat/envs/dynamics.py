"""Batched drone dynamics in torch, vectorised over (num_envs, num_drones).

World frame ENU (z up), SI units. Every model holds ``position`` and ``velocity`` as
(N, D, 3) float32 tensors and exposes the same two methods:

- ``reset(mask, position, velocity, max_speed)`` re-initialises the envs where ``mask`` is True;
- ``advance(command, period)`` flies every drone for one control period under a velocity command
  (N, D, 3) m/s, held over the period and sub-stepped at ``physics_dt``
  (``ceil(period / physics_dt)`` equal sub-steps).

Commands are clipped per axis to ``±max_speed`` of their drone. The ground is the plane z = 0:
position z is clamped at 0 and downward velocity is zeroed there (contact is the env's business).
``advance`` and ``reset`` replace ``position``/``velocity`` by new tensors, so a reference taken
before a call stays a valid snapshot. Until its first reset a drone rests at the origin with
``max_speed`` 0. The integration runs under ``torch.no_grad``: not differentiable.

Models (registry ``DYNAMICS``):

- ``velocity``: ``VelocityDynamics``, a reduced-order fit of AirSim simple_flight (first-order
  velocity tracking with acceleration limits and quadratic drag).
- ``quadrotor``: ``QuadrotorDynamics``, a 6-DoF X-quadrotor under a batched cascaded controller
  modelled on simple_flight (velocity -> tilt -> body rate -> rotor thrust).
- ``airsim``: ``rlplat.envs.airsim.dynamics.AirSimDynamics``, the drones of one env flown in an
  AirSim-protocol simulator over RPC, in lock step (imported on first use).

``WholeTicks`` wraps a model so that each step flies whole physics ticks, as AirSim's clock
does (a sim-to-sim reference).
"""

from __future__ import annotations

import importlib
import logging
import math
from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import Tensor

from rlplat.errors import ConfigError

log = logging.getLogger(__name__)


def _require_positive(**values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise ConfigError(f"{name} must be > 0, got {value!r}")


def _require_non_negative(**values: float) -> None:
    for name, value in values.items():
        if not value >= 0:
            raise ConfigError(f"{name} must be >= 0, got {value!r}")


class DroneDynamics:
    """Interface and shared state of the dynamics models: ``position``, ``velocity`` (N, D, 3)
    float32 and ``max_speed`` (N, D) float32 tensors, ``reset`` and ``advance``."""

    def __init__(
        self,
        *,
        num_envs: int,
        num_drones: int,
        device: torch.device | str,
        physics_dt: float,
    ) -> None:
        _require_positive(num_envs=num_envs, num_drones=num_drones, physics_dt=physics_dt)
        self.num_envs = int(num_envs)
        self.num_drones = int(num_drones)
        self.device = torch.device(device)
        self.physics_dt = float(physics_dt)
        shape = (self.num_envs, self.num_drones)
        self.position = torch.zeros(*shape, 3, device=self.device)
        self.velocity = torch.zeros(*shape, 3, device=self.device)
        self.max_speed = torch.zeros(*shape, device=self.device)

    def _const(self, *values: float) -> Tensor:
        return torch.tensor(values, dtype=torch.float32, device=self.device)

    def _check_shape(self, name: str, value: Tensor, shape: tuple[int, ...]) -> None:
        if tuple(value.shape) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {tuple(value.shape)}")

    def reset(self, mask: Tensor, position: Tensor, velocity: Tensor, max_speed: Tensor) -> None:
        """Re-initialise the envs where ``mask`` is True; the other rows are untouched.

        Args:
            mask: (N,) bool, envs to reset.
            position: (N, D, 3) float32, metres ENU; read at the masked rows only.
            velocity: (N, D, 3) float32, m/s ENU; read at the masked rows only.
            max_speed: (N, D) float32, m/s, per-drone bound on each command (and velocity) axis.
        """
        n, d = self.num_envs, self.num_drones
        self._check_shape("mask", mask, (n,))
        self._check_shape("position", position, (n, d, 3))
        self._check_shape("velocity", velocity, (n, d, 3))
        self._check_shape("max_speed", max_speed, (n, d))
        mask = mask.to(device=self.device, dtype=torch.bool)
        rows = mask.view(n, 1, 1)
        self.position = torch.where(rows, position.to(self.position), self.position)
        self.velocity = torch.where(rows, velocity.to(self.velocity), self.velocity)
        self.max_speed = torch.where(mask.view(n, 1), max_speed.to(self.max_speed), self.max_speed)
        self._reset_internal(mask)

    def advance(self, command: Tensor, period: float) -> None:
        """Fly every drone for ``period`` seconds under a constant velocity command.

        Args:
            command: (N, D, 3) float32, goal velocity m/s ENU; clipped per axis to ±max_speed.
            period: control period in seconds (> 0), split into ``ceil(period / physics_dt)``
                equal physics sub-steps.
        """
        if not period > 0:
            raise ValueError(f"period must be > 0, got {period!r}")
        self._check_shape("command", command, (self.num_envs, self.num_drones, 3))
        steps = max(1, math.ceil(period / self.physics_dt - 1e-9))
        bound = self.max_speed.unsqueeze(-1)
        command = torch.clamp(command.to(self.velocity), -bound, bound)
        with torch.no_grad():
            self._integrate(command, steps, period / steps)

    def _reset_internal(self, mask: Tensor) -> None:
        """Reset model-specific state where ``mask`` (N,) bool is True."""

    def _integrate(self, command: Tensor, steps: int, dt: float) -> None:
        """Run ``steps`` sub-steps of ``dt`` s under the clipped (N, D, 3) command."""
        raise NotImplementedError


def _ground(position: Tensor, velocity: Tensor, floor: Tensor) -> tuple[Tensor, Tensor]:
    """Clamp position to ``floor`` (-inf on x, y; 0 on z) and zero downward velocity there."""
    position = torch.maximum(position, floor)
    return position, torch.where(position <= floor, velocity.clamp(min=0.0), velocity)


class VelocityDynamics(DroneDynamics):
    """Reduced-order fit of AirSim simple_flight's response to velocity commands.

    Per axis, the velocity tracks the command with time constant ``tau`` (first order); the
    change in a sub-step is clipped to the acceleration limits times the sub-step (each horizontal
    axis separately, as simple_flight clips roll and pitch separately; vertical
    ``[-a_down_max, a_up_max]``), then quadratic drag ``-c * v * |v| / mass`` is applied. The
    first-order part is integrated exactly (``dv = (v_cmd - v) (1 - exp(-dt / tau))``), so the
    response does not depend on ``physics_dt`` while the limits are not active and a coarse
    sub-step (default 0.05 s, two per control period) is accurate; position advances with the
    mean of the velocities at both ends of the sub-step. After each sub-step every velocity
    component is clamped to ±max_speed of its drone. A 0 -> 5 m/s horizontal step reaches 63 % in
    0.9 s and settles about 0.15 m/s short of the command (drag).

    Args:
        num_envs: N, parallel environments.
        num_drones: D, drones per environment.
        device: torch device of every state tensor.
        physics_dt: s, physics sub-step.
        mass: kg, airframe mass (drag force -> acceleration).
        tau_xy: s, horizontal velocity time constant.
        tau_z: s, vertical velocity time constant.
        a_xy_max: m/s^2, limit of the commanded acceleration on each horizontal axis.
        a_up_max: m/s^2, limit of the commanded upward acceleration.
        a_down_max: m/s^2, limit of the commanded downward acceleration (positive number).
        drag_xy: N/(m/s)^2, quadratic drag coefficient on each horizontal axis.
        drag_z: N/(m/s)^2, quadratic drag coefficient on the vertical axis.
    """

    def __init__(
        self,
        *,
        num_envs: int,
        num_drones: int,
        device: torch.device | str = "cpu",
        physics_dt: float = 0.05,
        mass: float = 1.0,
        tau_xy: float = 0.9,
        tau_z: float = 0.08,
        a_xy_max: float = 6.3,
        a_up_max: float = 6.9,
        a_down_max: float = 4.8,
        drag_xy: float = 0.0066,
        drag_z: float = 0.135,
    ) -> None:
        super().__init__(
            num_envs=num_envs, num_drones=num_drones, device=device, physics_dt=physics_dt
        )
        _require_positive(mass=mass, tau_xy=tau_xy, tau_z=tau_z)
        _require_positive(a_xy_max=a_xy_max, a_up_max=a_up_max, a_down_max=a_down_max)
        _require_non_negative(drag_xy=drag_xy, drag_z=drag_z)
        self._tau = self._const(tau_xy, tau_xy, tau_z)
        self._a_min = self._const(-a_xy_max, -a_xy_max, -a_down_max)
        self._a_max = self._const(a_xy_max, a_xy_max, a_up_max)
        self._neg_drag = -self._const(drag_xy, drag_xy, drag_z) / mass
        self._floor = self._const(-math.inf, -math.inf, 0.0)
        log.debug("VelocityDynamics N=%d D=%d dt=%.4f s", num_envs, num_drones, physics_dt)

    def _integrate(self, command: Tensor, steps: int, dt: float) -> None:
        bound = self.max_speed.unsqueeze(-1)
        low = -bound
        gain = -torch.expm1(-dt / self._tau)  # 1 - exp(-dt / tau), per axis
        dv_min, dv_max = self._a_min * dt, self._a_max * dt
        drag = self._neg_drag * dt
        p, v = self.position.clone(), self.velocity.clone()
        dv, half = torch.empty_like(v), 0.5 * dt
        pz, vz = p[..., 2], v[..., 2]
        for _ in range(steps):
            p.add_(v, alpha=half)
            torch.sub(command, v, out=dv)
            dv.mul_(gain).clamp_(dv_min, dv_max)
            dv.addcmul_(v.abs().mul_(drag), v)
            v.add_(dv).clamp_(low, bound)
            p.add_(v, alpha=half)
            # Ground: z stays >= 0 and a drone on the ground cannot move down.
            grounded = pz <= 0.0
            pz.clamp_(min=0.0)
            vz.masked_fill_(grounded & (vz < 0.0), 0.0)
        self.position, self.velocity = p, v


def _attitude_basis() -> tuple[Tensor, Tensor]:
    """Constant maps from quaternion products to rotation entries and to the quaternion rate.

    Returns:
        (16, 7) float32 ``K`` with ``outer(q, q).flatten() @ K`` = (R21, -R20, R02, R12, R22, R10,
        R00) of the body-to-world rotation of unit ``q = (w, x, y, z)``: roll, pitch and yaw
        (Z-Y-X) follow from them and (R02, R12, R22) is the world direction of body z; and
        (12, 4) ``E`` with ``outer(q, omega).flatten() @ E`` = dq/dt = q * (0, omega) / 2.
    """
    w, x, y, z = range(4)
    rotation = [  # (i, j, coefficient of q_i q_j) per output column
        [(w, x, 2), (y, z, 2)],
        [(w, y, 2), (x, z, -2)],
        [(x, z, 2), (w, y, 2)],
        [(y, z, 2), (w, x, -2)],
        [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
        [(w, z, 2), (x, y, 2)],
        [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)],
    ]
    p, q, r = range(3)
    quat_rate = [  # (i, j, coefficient of q_i omega_j) per component of dq/dt
        [(x, p, -0.5), (y, q, -0.5), (z, r, -0.5)],
        [(w, p, 0.5), (y, r, 0.5), (z, q, -0.5)],
        [(w, q, 0.5), (z, p, 0.5), (x, r, -0.5)],
        [(w, r, 0.5), (x, q, 0.5), (y, p, -0.5)],
    ]
    k, e = torch.zeros(4, 4, 7), torch.zeros(4, 3, 4)
    for table, out in ((rotation, k), (quat_rate, e)):
        for col, entries in enumerate(table):
            for i, j, c in entries:
                out[i, j, col] = c
    return k.reshape(16, 7), e.reshape(12, 4)


class QuadrotorDynamics(DroneDynamics):
    """6-DoF X-quadrotor flown by a batched cascaded controller modelled on simple_flight.

    Body frame FLU (x forward, y left, z up); attitude as a unit quaternion (w, x, y, z),
    renormalised after every control period; yaw is held at 0. At every physics sub-step:

    1. velocity loop: tilt goal per horizontal axis ``clip(tilt_gain * (v_cmd - v), ±1) *
       max_tilt`` (x -> pitch, y -> -roll, yaw goal 0); vertical PI on v_z (the integral is
       frozen while the goal or the rotors saturate) gives an acceleration goal clipped to
       ``[-a_down_max, a_up_max]``, turned into tilt-compensated collective thrust;
    2. attitude loop: P on the roll/pitch/yaw error, rate goal clipped to ±max_angle_rate;
    3. rate loop: P on body rates -> torques ``inertia * rate_gain * (rate_goal - omega)``;
    4. mixer: thrust and torques -> 4 rotor thrusts; when a rotor would exceed
       max_rotor_thrust, collective thrust is given up first (torques kept), then each thrust
       is clipped to [0, max_rotor_thrust];
    5. rotor thrusts follow their command with a first-order lag ``motor_time_constant``;
    6. rigid body: thrust along body z, gravity, quadratic drag per world axis, Euler's equations
       with diagonal inertia; semi-implicit Euler.

    Rotors (X): front-right, rear-left, front-left, rear-right at ``arm_length`` from the centre,
    the first two spinning one way and the last two the other. Inertia defaults are those of a
    ~1 kg, 45 cm quad (AirSim "Generic"-like). The velocity is not clamped: its bound comes from
    the clipped command through the controller; under random command switching a vertical
    overshoot of a few percent of max_speed occurs (< 10 % in the tests). Defaults reproduce
    simple_flight's horizontal step (63 % in ~0.9 s, 90 % in ~1.9 s).

    Args:
        num_envs: N, parallel environments.
        num_drones: D, drones per environment.
        device: torch device of every state tensor.
        physics_dt: s, physics and controller sub-step.
        gravity: m/s^2, magnitude of gravity.
        mass: kg, airframe mass.
        arm_length: m, distance from the centre to each rotor.
        inertia_xx: kg m^2, moment of inertia about body x (roll).
        inertia_yy: kg m^2, moment of inertia about body y (pitch).
        inertia_zz: kg m^2, moment of inertia about body z (yaw).
        max_rotor_thrust: N, maximum thrust of one rotor.
        motor_time_constant: s, first-order lag of each rotor thrust.
        yaw_torque_coefficient: m, rotor reaction torque per newton of thrust.
        drag_xy: N/(m/s)^2, quadratic drag coefficient on each horizontal axis.
        drag_z: N/(m/s)^2, quadratic drag coefficient on the vertical axis.
        tilt_gain: 1/(m/s), horizontal velocity error -> fraction of max_tilt.
        max_tilt: rad, largest roll or pitch goal.
        vz_p_gain: 1/s, vertical velocity error -> acceleration goal.
        vz_i_gain: 1/s^2, integral of the vertical velocity error -> acceleration goal.
        vz_i_limit: m/s^2, bound on the integral term's contribution.
        a_up_max: m/s^2, limit of the commanded upward acceleration.
        a_down_max: m/s^2, limit of the commanded downward acceleration (positive number).
        angle_gain: 1/s, angle error -> angle rate goal.
        max_angle_rate: rad/s, limit of the angle rate goal.
        rate_gain: 1/s, body rate error -> angular acceleration goal.
    """

    def __init__(
        self,
        *,
        num_envs: int,
        num_drones: int,
        device: torch.device | str = "cpu",
        physics_dt: float = 0.003,
        gravity: float = 9.81,
        mass: float = 1.0,
        arm_length: float = 0.2275,
        inertia_xx: float = 0.0067,
        inertia_yy: float = 0.0067,
        inertia_zz: float = 0.012,
        max_rotor_thrust: float = 4.18,
        motor_time_constant: float = 0.005,
        yaw_torque_coefficient: float = 0.0133,
        drag_xy: float = 0.0066,
        drag_z: float = 0.135,
        tilt_gain: float = 0.2,
        max_tilt: float = 0.571,
        vz_p_gain: float = 12.5,
        vz_i_gain: float = 1.0,
        vz_i_limit: float = 3.0,
        a_up_max: float = 6.9,
        a_down_max: float = 4.8,
        angle_gain: float = 6.0,
        max_angle_rate: float = 2.5,
        rate_gain: float = 25.0,
    ) -> None:
        super().__init__(
            num_envs=num_envs, num_drones=num_drones, device=device, physics_dt=physics_dt
        )
        _require_positive(mass=mass, arm_length=arm_length, max_rotor_thrust=max_rotor_thrust)
        _require_positive(inertia_xx=inertia_xx, inertia_yy=inertia_yy, inertia_zz=inertia_zz)
        _require_positive(motor_time_constant=motor_time_constant, max_tilt=max_tilt)
        _require_positive(yaw_torque_coefficient=yaw_torque_coefficient, a_up_max=a_up_max)
        _require_positive(tilt_gain=tilt_gain, vz_p_gain=vz_p_gain, a_down_max=a_down_max)
        _require_positive(angle_gain=angle_gain, max_angle_rate=max_angle_rate, rate_gain=rate_gain)
        _require_non_negative(drag_xy=drag_xy, drag_z=drag_z)
        _require_non_negative(gravity=gravity, vz_i_gain=vz_i_gain, vz_i_limit=vz_i_limit)
        if max_tilt >= math.pi / 2:
            raise ConfigError(f"max_tilt must be < pi/2, got {max_tilt!r}")
        if mass * gravity >= 4 * max_rotor_thrust:
            raise ConfigError(f"max_rotor_thrust too small to hover, got {max_rotor_thrust!r}")
        self.mass, self.gravity = float(mass), float(gravity)
        self.hover_thrust = self.mass * self.gravity / 4
        self.max_rotor_thrust = float(max_rotor_thrust)
        # Internal state is component-first, (C, B) with B = N * D, for fast small-tensor ops.
        gain = tilt_gain * max_tilt
        self._error_to_angle = self._const(0, -gain, 0, gain, 0, 0, 0, 0, 0).view(3, 3)
        self._angle_max = self._const(max_tilt, max_tilt, 0.0).view(3, 1)
        self._angle_min = -self._angle_max
        self._vz_p, self._vz_i, self._vz_i_limit = float(vz_p_gain), float(vz_i_gain), vz_i_limit
        self._a_up, self._a_down = float(a_up_max), float(a_down_max)
        self._angle_gain, self._max_rate = self._const(angle_gain), float(max_angle_rate)
        self._motor_tau = float(motor_time_constant)
        self._g = self._const(self.gravity)
        self._gravity_vec = self._const(0.0, 0.0, -self.gravity).view(3, 1)
        self._neg_drag = -self._const(drag_xy, drag_xy, drag_z).view(3, 1) / mass
        self._max_thrust = self._const(self.max_rotor_thrust)
        self._floor = self._const(-math.inf, -math.inf, 0.0).view(3, 1)
        # Mixer M: rotor thrusts f -> (T, tau_x, tau_y, tau_z), folded with mass and inertia:
        # f = _unmix @ (a_collective, rate error) and _mix @ f = (T / mass, tau / inertia).
        a, k = arm_length / math.sqrt(2.0), yaw_torque_coefficient
        mix = torch.tensor(
            [[1, 1, 1, 1], [-a, a, a, -a], [-a, a, -a, a], [k, k, -k, -k]], dtype=torch.float64
        )
        inertia = torch.tensor([inertia_xx, inertia_yy, inertia_zz], dtype=torch.float64)
        scale = torch.cat([torch.tensor([mass], dtype=torch.float64), inertia * rate_gain])
        self._unmix = (torch.linalg.inv(mix) * scale).to(self.velocity)
        self._mix = (mix / torch.cat([scale[:1], inertia]).unsqueeze(-1)).to(self.velocity)
        ix, iy, iz = inertia_xx, inertia_yy, inertia_zz
        self._gyro = self._const((iy - iz) / ix, (iz - ix) / iy, (ix - iy) / iz).view(3, 1)
        basis, rate = _attitude_basis()
        self._basis, self._quat_rate = basis.T.to(self.velocity), rate.T.to(self.velocity)
        b = self.num_envs * self.num_drones
        self._level = self._const(1.0, 0.0, 0.0, 0.0).view(4, 1)
        self._p = torch.zeros(3, b, device=self.device)
        self._v = torch.zeros(3, b, device=self.device)
        self._q = self._level.expand(4, b).clone()
        self._omega = torch.zeros(3, b, device=self.device)
        self._rotor = torch.full((4, b), self.hover_thrust, device=self.device)
        self._vz_integral = torch.zeros(b, device=self.device)
        log.debug("QuadrotorDynamics N=%d D=%d dt=%.4f s", num_envs, num_drones, physics_dt)

    def _unpack(self, state: Tensor) -> Tensor:
        """(C, N * D) internal layout -> (N, D, C) float32, a copy."""
        shape = (self.num_envs, self.num_drones, -1)
        return state.T.reshape(shape).clone(memory_format=torch.contiguous_format)

    @property
    def quaternion(self) -> Tensor:
        """(N, D, 4) float32, body-to-world attitude (w, x, y, z)."""
        return self._unpack(self._q)

    @property
    def angular_velocity(self) -> Tensor:
        """(N, D, 3) float32, body rates rad/s (FLU)."""
        return self._unpack(self._omega)

    def _reset_internal(self, mask: Tensor) -> None:
        """Level attitude, zero body rates, rotors at hover thrust, cleared integrator."""
        rows = mask.repeat_interleave(self.num_drones)
        self._p = self.position.reshape(-1, 3).T.contiguous()
        self._v = self.velocity.reshape(-1, 3).T.contiguous()
        self._q = torch.where(rows, self._level, self._q)
        self._omega = torch.where(rows, 0.0, self._omega)
        self._rotor = torch.where(rows, self.hover_thrust, self._rotor)
        self._vz_integral = torch.where(rows, 0.0, self._vz_integral)

    def _integrate(self, command: Tensor, steps: int, dt: float) -> None:
        command = command.reshape(-1, 3).T.contiguous()
        blend = 1.0 - math.exp(-dt / self._motor_tau)
        for _ in range(steps):
            self._substep(command, dt, blend)
        self._q = self._q * (self._q * self._q).sum(dim=0).rsqrt()
        self.position, self.velocity = self._unpack(self._p), self._unpack(self._v)

    def _substep(self, command: Tensor, dt: float, blend: float) -> None:
        q, omega, v = self._q, self._omega, self._v
        quad = self._basis @ (q.unsqueeze(1) * q.unsqueeze(0)).view(16, -1)
        roll_num, sin_pitch, _, _, cos_tilt, yaw_num, yaw_den = quad.unbind(0)
        roll, yaw = torch.atan2(roll_num, cos_tilt), torch.atan2(yaw_num, yaw_den)
        angles = torch.stack([roll, torch.asin(sin_pitch.clamp(-1.0, 1.0)), yaw])
        thrust_dir = quad[2:5]

        # Velocity loop: attitude goal and vertical acceleration goal (PI)
        error = command - v
        angle_goal = torch.clamp(self._error_to_angle @ error, self._angle_min, self._angle_max)
        accel_raw = torch.add(self._vz_integral, error[2], alpha=self._vz_p)
        accel_z = accel_raw.clamp(-self._a_down, self._a_up)
        collective = (accel_z + self._g) / cos_tilt.clamp(min=0.5)

        # Attitude loop -> body rate goal; rate loop and mixer (attitude first) -> rotor goals
        rate_goal = ((angle_goal - angles) * self._angle_gain).clamp(
            -self._max_rate, self._max_rate
        )
        rotor_goal = self._unmix @ torch.cat([collective.unsqueeze(0), rate_goal - omega])
        excess = rotor_goal.amax(dim=0) - self._max_thrust
        rotor_goal = (rotor_goal - excess.clamp(min=0.0)).clamp(0.0, self.max_rotor_thrust)

        # The integral is frozen while the acceleration goal or the rotors saturate.
        free = (accel_z == accel_raw) & (excess <= 0.0)
        integral = torch.add(self._vz_integral, error[2] * free, alpha=self._vz_i * dt)
        self._vz_integral = integral.clamp(-self._vz_i_limit, self._vz_i_limit)
        self._rotor = torch.lerp(self._rotor, rotor_goal, blend)

        # Rigid body: Euler's equations, thrust + gravity + drag, quaternion kinematics
        wrench = self._mix @ self._rotor
        spin = omega.roll(-1, 0) * omega.roll(-2, 0) * self._gyro
        self._omega = torch.add(omega, wrench[1:] + spin, alpha=dt)
        accel = torch.addcmul(self._gravity_vec, thrust_dir, wrench[:1])
        accel = torch.addcmul(accel, v * self._neg_drag, v.abs())
        v = torch.add(v, accel, alpha=dt)
        q_dot = self._quat_rate @ (q.unsqueeze(1) * self._omega.unsqueeze(0)).view(12, -1)
        self._q = torch.add(q, q_dot, alpha=dt)
        self._p, self._v = _ground(torch.add(self._p, v, alpha=dt), v, self._floor)


class WholeTicks:
    """An embedded model stepped in whole physics ticks, as AirSim steps.

    AirSim ends a ``simContinueForTime`` at the first physics tick at or past its time, and
    ``dynamics=airsim`` asks each step for the time that brings the sim clock to the env's
    (``steps x period`` since the reset, at least half a period): with 3-ms ticks a 0.1-s step
    flies 0.102 s, then 0.099 s, 0.099 s, 0.102 s, ... Wrapped around ``inner``, each
    ``advance(command, period)`` asks and flies the same way: the first whole ``tick`` at or
    past that time, in one ``inner.advance``. That way an embedded reference flies the steps a
    simulator flew (``python -m rlplat.airsim sim2sim ... reference_tick=0.003``).

    The clock restarts when every env is reset at once (an evaluation's wave; one env per
    simulator on AirSim). An env reset alone keeps the others' clock: its steps still keep
    within a tick of its own time, in another phase of the pattern.

    Everything else (``position``, ``velocity``, ``max_speed``, ``reset``...) is ``inner``'s.
    ``last_advance_s`` is the time the last step flew.
    """

    def __init__(self, inner: DroneDynamics, tick: float) -> None:
        _require_positive(tick=tick)
        self.inner = inner
        self.tick_ns = max(1, round(tick * 1e9))
        self._due_ns = self._clock_ns = 0  # the env's time and the ticks flown since the reset
        self.last_advance_s = float("nan")

    def __getattr__(self, name: str) -> Any:  # what the env reads of the model: inner's
        if name == "inner" or name.startswith("__"):  # a copy under construction has no inner
            raise AttributeError(name)
        return getattr(self.inner, name)

    def reset(self, mask: Tensor, position: Tensor, velocity: Tensor, max_speed: Tensor) -> None:
        self.inner.reset(mask, position, velocity, max_speed)
        if bool(mask.all()):
            self._due_ns = self._clock_ns = 0

    def advance(self, command: Tensor, period: float) -> None:
        if not period > 0:
            raise ValueError(f"period must be > 0, got {period!r}")
        self._due_ns += round(period * 1e9)
        ask = max(self._due_ns - self._clock_ns, round(0.5 * period * 1e9))
        flown = -(-ask // self.tick_ns) * self.tick_ns  # the first whole tick at or past it
        self.inner.advance(command, flown / 1e9)
        self._clock_ns += flown
        self.last_advance_s = flown / 1e9


class Registry(Mapping[str, type[DroneDynamics]]):
    """Models by name. An entry given as ``"package.module:Class"`` is imported when it is
    first looked up: ``airsim``, whose module builds on this one (and whose client library is
    needed only when it flies)."""

    def __init__(self, entries: Mapping[str, type[DroneDynamics] | str]) -> None:
        self._entries = dict(entries)

    def __getitem__(self, name: str) -> type[DroneDynamics]:
        entry = self._entries[name]
        if isinstance(entry, str):
            module, _, attr = entry.partition(":")
            entry = self._entries[name] = getattr(importlib.import_module(module), attr)
        return entry

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


DYNAMICS = Registry(
    {
        "velocity": VelocityDynamics,
        "quadrotor": QuadrotorDynamics,
        "airsim": "rlplat.envs.airsim.dynamics:AirSimDynamics",
    }
)
