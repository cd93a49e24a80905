"""Behaviour of the batched drone dynamics (rlplat.envs.dynamics) and their config group."""

import inspect
import math

import pytest
import torch
from omegaconf import OmegaConf

from rlplat.envs.dynamics import (
    DYNAMICS,
    QuadrotorDynamics,
    VelocityDynamics,
    WholeTicks,
    _attitude_basis,
)
from rlplat.errors import ConfigError
from rlplat.experiment.config import CONF_DIR

PERIOD = 0.1  # s, control period used throughout
# The models that fly in torch (``airsim`` needs a simulator: tests/test_airsim_env.py).
EMBEDDED = {name: DYNAMICS[name] for name in DYNAMICS if name != "airsim"}


def make(cls, n=1, d=1, position=(0.0, 0.0, 10.0), velocity=(0.0, 0.0, 0.0), max_speed=5.0):
    """A model with every drone reset to the same state."""
    dyn = cls(num_envs=n, num_drones=d)
    dyn.reset(
        torch.ones(n, dtype=torch.bool),
        torch.tensor(position).expand(n, d, 3).clone(),
        torch.tensor(velocity).expand(n, d, 3).clone(),
        torch.full((n, d), max_speed),
    )
    return dyn


def rollout(dyn, command, seconds, period=PERIOD):
    """Velocities (T, N, D, 3) and positions (T, N, D, 3) after each period, from t = 0."""
    vel, pos = [dyn.velocity], [dyn.position]
    for _ in range(round(seconds / period)):
        dyn.advance(command, period)
        vel.append(dyn.velocity)
        pos.append(dyn.position)
    return torch.stack(vel), torch.stack(pos)


def first_time(values, threshold, period=PERIOD):
    """Seconds until ``values`` (T,) first reaches ``threshold`` (inf if never)."""
    hits = (values >= threshold).nonzero()
    return hits[0].item() * period if len(hits) else math.inf


# Config group and registry


def test_registry_matches_conf_group():
    stems = {p.stem for p in (CONF_DIR / "dynamics").glob("*.yaml")}
    assert set(DYNAMICS) == stems


@pytest.mark.parametrize("name", sorted(DYNAMICS))
def test_yaml_keys_are_the_constructor_kwargs_with_their_defaults(name):
    cfg = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "dynamics" / f"{name}.yaml"))
    assert cfg.pop("name") == name
    params = inspect.signature(DYNAMICS[name]).parameters
    factory = ("num_envs", "num_drones", "num_attackers", "device")  # the env factory's
    knobs = {k: p for k, p in params.items() if k not in factory}
    assert set(cfg) == set(knobs)
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in params.values())
    defaults = {k: p.default for k, p in knobs.items()}
    if name not in EMBEDDED:  # a simulator's endpoints and names, not physics
        assert {k: list(v) if isinstance(v, tuple) else v for k, v in defaults.items()} == cfg
        return
    assert defaults == pytest.approx(cfg)
    dyn = DYNAMICS[name](num_envs=2, num_drones=3, **cfg)
    assert dyn.position.shape == (2, 3, 3)


@pytest.mark.parametrize(
    ("cls", "kwargs", "field"),
    [
        (VelocityDynamics, {"physics_dt": 0.0}, "physics_dt"),
        (VelocityDynamics, {"num_envs": 0}, "num_envs"),
        (VelocityDynamics, {"tau_xy": -0.9}, "tau_xy"),
        (VelocityDynamics, {"drag_z": -1.0}, "drag_z"),
        (QuadrotorDynamics, {"physics_dt": -0.003}, "physics_dt"),
        (QuadrotorDynamics, {"inertia_zz": 0.0}, "inertia_zz"),
        (QuadrotorDynamics, {"max_rotor_thrust": 2.0}, "max_rotor_thrust"),
        (QuadrotorDynamics, {"max_tilt": 2.0}, "max_tilt"),
    ],
)
def test_constructor_rejects_bad_values(cls, kwargs, field):
    args = {"num_envs": 1, "num_drones": 1, **kwargs}
    with pytest.raises(ValueError, match=field):
        cls(**args)


# Interface shared by every model


@pytest.mark.parametrize("cls", EMBEDDED.values())
def test_advance_rejects_bad_period_and_shape(cls):
    dyn = make(cls, n=2)
    with pytest.raises(ValueError, match="period"):
        dyn.advance(torch.zeros(2, 1, 3), 0.0)
    with pytest.raises(ValueError, match="command"):
        dyn.advance(torch.zeros(2, 3), PERIOD)


@pytest.mark.parametrize("cls", EMBEDDED.values())
def test_reset_touches_only_masked_envs(cls):
    dyn = make(cls, n=4, d=2)
    rollout(dyn, torch.ones(4, 2, 3), 0.5)
    before_pos, before_vel = dyn.position, dyn.velocity
    mask = torch.tensor([True, False, True, False])
    new_pos = torch.arange(24, dtype=torch.float32).view(4, 2, 3)
    new_vel = -torch.ones(4, 2, 3)
    dyn.reset(mask, new_pos, new_vel, torch.full((4, 2), 2.0))
    assert dyn.position.dtype == torch.float32 and dyn.position.shape == (4, 2, 3)
    assert torch.equal(dyn.position[mask], new_pos[mask])
    assert torch.equal(dyn.velocity[mask], new_vel[mask])
    assert torch.equal(dyn.position[~mask], before_pos[~mask])
    assert torch.equal(dyn.velocity[~mask], before_vel[~mask])
    assert torch.equal(dyn.max_speed, torch.tensor([2.0, 5.0, 2.0, 5.0]).unsqueeze(-1).expand(4, 2))
    snapshot = dyn.position
    dyn.advance(torch.ones(4, 2, 3), PERIOD)
    assert torch.equal(snapshot[mask], new_pos[mask])  # earlier references are not mutated
    assert not torch.equal(dyn.position, snapshot)


@pytest.mark.parametrize("cls", EMBEDDED.values())
def test_commands_are_clipped_to_max_speed(cls):
    limits = torch.tensor([1.5, 4.0]).view(2, 1)
    far, at_limit = make(cls, n=2, max_speed=0.0), make(cls, n=2, max_speed=0.0)
    for dyn in (far, at_limit):
        dyn.reset(torch.ones(2, dtype=torch.bool), dyn.position, dyn.velocity, limits)
    direction = torch.tensor([1.0, -1.0, 1.0]).expand(2, 1, 3)
    far_vel, _ = rollout(far, 10.0 * direction, 1.0)
    limit_vel, _ = rollout(at_limit, direction * limits.unsqueeze(-1), 1.0)
    assert torch.equal(far_vel, limit_vel)


@pytest.mark.parametrize("cls", EMBEDDED.values())
def test_ground_stops_descent(cls):
    dyn = make(cls, n=2, d=2, position=(3.0, -2.0, 0.5))
    vel, pos = rollout(dyn, torch.tensor([1.0, 0.0, -5.0]).expand(2, 2, 3), 2.0)
    assert (pos[..., 2] >= 0.0).all()
    assert torch.all(pos[-1, ..., 2] == 0.0)
    assert torch.all(vel[-1, ..., 2] == 0.0)
    assert torch.all(pos[-1, ..., 0] > 3.5)  # still flies horizontally along the ground


# VelocityDynamics: the reduced-order fit of simple_flight


def test_velocity_step_reaches_63_percent_in_tau():
    dyn = make(VelocityDynamics)
    vel, _ = rollout(dyn, torch.tensor([[[5.0, 0.0, 0.0]]]), 10.0, period=0.01)
    assert first_time(vel[:, 0, 0, 0], 0.63 * 5.0, period=0.01) == pytest.approx(0.9, abs=0.15)
    assert 0.1 <= 5.0 - vel[-1, 0, 0, 0].item() <= 0.2  # drag lag at 5 m/s
    assert torch.all(vel[..., 1:] == 0.0)


def test_velocity_vertical_acceleration_limits():
    dyn = make(VelocityDynamics, n=2)
    command = torch.tensor([0.0, 0.0, 5.0]).view(1, 1, 3) * torch.tensor([1.0, -1.0]).view(2, 1, 1)
    dyn.advance(command, PERIOD)
    up, down = dyn.velocity[:, 0, 2].tolist()
    assert 0.9 * 6.9 * PERIOD <= up <= 6.9 * PERIOD + 1e-6
    assert -4.8 * PERIOD - 1e-6 <= down <= -0.9 * 4.8 * PERIOD


def test_velocity_stays_within_max_speed_per_axis():
    gen = torch.Generator().manual_seed(0)
    n, d = 32, 2
    bound = (1.0 + 4.0 * torch.rand(n, d, generator=gen)).unsqueeze(-1)
    dyn = make(VelocityDynamics, n=n, d=d, position=(0.0, 0.0, 50.0))
    too_fast = 2.0 * bound * torch.randn(n, d, 3, generator=gen).sign()
    dyn.reset(torch.ones(n, dtype=torch.bool), dyn.position, too_fast, bound.squeeze(-1))
    dyn.advance(torch.zeros(n, d, 3), 0.01)
    assert torch.all(dyn.velocity.abs() <= bound + 1e-6)  # clamped from the first sub-step
    peak = torch.zeros(n, d, 3)
    for k in range(200):
        if k % 40 == 0:  # hold each random command for 2 s, up to 3x the bound
            command = (2 * torch.rand(n, d, 3, generator=gen) - 1) * 3 * bound
        dyn.advance(command, 0.05)
        peak = torch.maximum(peak, dyn.velocity.abs())
    assert torch.all(peak <= bound + 1e-6)
    assert (peak / bound).max() > 0.95  # the commands do push against the bound


def test_velocity_substeps_cover_a_period_that_is_not_a_multiple():
    dyn = VelocityDynamics(num_envs=1, num_drones=1, drag_xy=0.0, drag_z=0.0)
    velocity = torch.tensor([[[2.0, -1.0, 0.5]]])
    dyn.reset(
        torch.tensor([True]), torch.tensor([[[0.0, 0.0, 10.0]]]), velocity, torch.ones(1, 1) * 3
    )
    dyn.advance(velocity, 0.025)
    expected = torch.tensor([0.0, 0.0, 10.0]) + 0.025 * velocity[0, 0]
    torch.testing.assert_close(dyn.position[0, 0], expected)
    torch.testing.assert_close(dyn.velocity, velocity)


# QuadrotorDynamics: the 6-DoF rigid body under the cascaded controller

QUAD_CASES = {  # case: (initial position, initial velocity, command), max_speed 5
    "hover": ((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    "recover": ((0.0, 0.0, 10.0), (1.5, -1.0, 0.5), (0.0, 0.0, 0.0)),
    "step_x": ((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), (3.0, 0.0, 0.0)),
    "step_y": ((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), (0.0, -3.0, 0.0)),
    "climb": ((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), (0.0, 0.0, 2.0)),
    "sink": ((0.0, 0.0, 20.0), (0.0, 0.0, 0.0), (0.0, 0.0, -2.0)),
}


@pytest.fixture(scope="module")
def quad_run():
    """5 s of every QUAD_CASES case, side by side: (velocity, position) each (T, case, 3)."""
    n = len(QUAD_CASES)
    dyn = make(QuadrotorDynamics, n=n)
    position, velocity, command = (
        torch.tensor(x).view(n, 1, 3) for x in zip(*QUAD_CASES.values(), strict=True)
    )
    dyn.reset(torch.ones(n, dtype=torch.bool), position, velocity, dyn.max_speed)
    vel, pos = rollout(dyn, command, 5.0)
    return {name: (vel[:, i, 0], pos[:, i, 0]) for i, name in enumerate(QUAD_CASES)}


def test_quadrotor_hovers_in_place(quad_run):
    vel, pos = quad_run["hover"]
    assert torch.isfinite(pos).all()
    assert (pos - torch.tensor([0.0, 0.0, 10.0])).norm(dim=-1).max() < 0.2


def test_quadrotor_recovers_to_hover(quad_run):
    vel, pos = quad_run["recover"]
    assert vel[-1].norm() < 0.1
    assert vel[0].norm() > 1.5


@pytest.mark.parametrize(("case", "axis", "goal"), [("step_x", 0, 3.0), ("step_y", 1, -3.0)])
def test_quadrotor_tracks_horizontal_step(quad_run, case, axis, goal):
    vel, pos = quad_run[case]
    assert first_time(vel[:, axis] / goal, 0.9) <= 3.0
    assert first_time(vel[:, axis] / goal, 0.63) == pytest.approx(0.9, abs=0.2)
    assert (vel[:, axis] / goal).max() < 1.02
    assert (pos[:, 2] - 10.0).abs().max() < 0.2  # altitude held while tilting


@pytest.mark.parametrize(("case", "goal"), [("climb", 2.0), ("sink", -2.0)])
def test_quadrotor_tracks_vertical_command(quad_run, case, goal):
    vel, pos = quad_run[case]
    assert first_time(vel[:, 2] / goal, 0.9) <= 0.6
    assert (vel[-1, 2] - goal).abs() < 0.1
    assert pos[:, :2].abs().max() < 0.05
    assert (pos[-1, 2] - pos[0, 2]).item() == pytest.approx(goal * 5.0, abs=1.0)


@pytest.mark.parametrize("command", [(3.0, 0.0, 0.0), (2.0, -2.0, 1.0)])
def test_quadrotor_agrees_with_velocity_model(command):
    """Velocity trajectories over the first 5 s agree within 0.25 m/s RMS and 0.6 m/s at worst.

    The velocity model is a first-order fit; the quadrotor adds the attitude loop's second-order
    response (it takes ~0.2 s to tilt, then converges slightly faster), which measures at about
    0.12 m/s RMS and 0.37 m/s peak on a 3 m/s step; the bounds leave a factor of ~2 for gains or
    constants tuned through the YAML while still catching a sign, axis or time-scale error.
    """
    goal = torch.tensor(command).view(1, 1, 3)
    reduced, _ = rollout(make(VelocityDynamics), goal, 5.0)
    rigid, _ = rollout(make(QuadrotorDynamics), goal, 5.0)
    error = (reduced - rigid)[:, 0, 0]
    assert error.norm(dim=-1).pow(2).mean().sqrt() < 0.25
    assert error.abs().max() < 0.6


def test_quaternion_maps_match_rotation_matrix_and_kinematics():
    """The constant maps of the quadrotor reproduce R(q) entries and dq/dt = q * (0, omega) / 2."""
    gen = torch.Generator().manual_seed(2)
    q = torch.randn(8, 4, generator=gen)
    q = q / q.norm(dim=-1, keepdim=True)
    omega = torch.randn(8, 3, generator=gen)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    p, r, s = omega.unbind(-1)
    q_dot = 0.5 * torch.stack(
        [
            -x * p - y * r - z * s,
            w * p + y * s - z * r,
            w * r + z * p - x * s,
            w * s + x * r - y * p,
        ],
        -1,
    )
    basis, rate = _attitude_basis()
    entries = (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2) @ basis
    expected = [rot[:, 2, 1], -rot[:, 2, 0], rot[:, 0, 2], rot[:, 1, 2], rot[:, 2, 2]]
    expected += [rot[:, 1, 0], rot[:, 0, 0]]
    torch.testing.assert_close(entries, torch.stack(expected, -1))
    torch.testing.assert_close((q.unsqueeze(-1) * omega.unsqueeze(-2)).flatten(-2) @ rate, q_dot)


def test_quadrotor_attitude_integrates_its_body_rates():
    """During a pure pitch manoeuvre the pitch angle is the time integral of the body y rate."""
    dyn = make(QuadrotorDynamics)
    dt, pitch_from_rates = dyn.physics_dt, 0.0
    for _ in range(100):
        dyn.advance(torch.tensor([[[3.0, 0.0, 0.0]]]), dt)
        pitch_from_rates += dyn.angular_velocity[0, 0, 1].item() * dt
    w, x, y, z = dyn.quaternion[0, 0].tolist()
    pitch = math.asin(2 * (w * y - x * z))
    assert pitch > 0.2  # nose down to accelerate towards +x
    assert pitch == pytest.approx(pitch_from_rates, rel=0.02)


@pytest.mark.slow
def test_quadrotor_long_random_rollout_is_stable():
    """2000 control periods (200 s) of random commands at N=64, D=2, with partial resets."""
    gen = torch.Generator().manual_seed(1)
    n, d = 64, 2
    max_speed = 1.0 + 4.0 * torch.rand(n, d, generator=gen)
    start = torch.rand(n, d, 3, generator=gen) * torch.tensor([20.0, 20.0, 30.0])
    dyn = QuadrotorDynamics(num_envs=n, num_drones=d)
    dyn.reset(torch.ones(n, dtype=torch.bool), start, torch.zeros(n, d, 3), max_speed)
    peak_ratio, peak_rate, lowest = 0.0, 0.0, math.inf
    for k in range(2000):
        if k % 100 == 99:
            dyn.reset(torch.rand(n, generator=gen) < 0.25, start, torch.zeros(n, d, 3), max_speed)
        command = (2 * torch.rand(n, d, 3, generator=gen) - 1) * 2 * max_speed.unsqueeze(-1)
        dyn.advance(command, PERIOD)
        peak_ratio = max(peak_ratio, (dyn.velocity.abs() / max_speed.unsqueeze(-1)).max().item())
        lowest = min(lowest, dyn.position[..., 2].min().item())
        if k % 50 == 0:
            peak_rate = max(peak_rate, dyn.angular_velocity.abs().max().item())
    assert torch.isfinite(dyn.position).all() and torch.isfinite(dyn.velocity).all()
    torch.testing.assert_close(dyn.quaternion.norm(dim=-1), torch.ones(n, d))
    assert lowest >= 0.0
    assert peak_ratio < 1.1  # the controller keeps each axis near the clipped command
    assert peak_rate < 5.0


def test_whole_ticks_fly_the_steps_airsim_flies_and_keep_to_the_envs_clock():
    # AirSim runs a continue to the first 3-ms tick at or past its time, and each step asks for
    # the time to the env's clock: 0.102 s, 0.099 s, 0.099 s, 0.102 s, ... in sum within a tick
    # of steps x period. The wrapped model flies exactly those periods, nothing else changes.
    n, d = 3, 2
    start = torch.tensor([[[0.0, 0.0, 10.0], [5.0, -2.0, 12.0]]]).expand(n, d, 3)
    speed = torch.full((n, d), 4.0)
    command = torch.tensor([[[3.0, -4.0, 1.0], [-2.0, 1.0, -0.5]]]).expand(n, d, 3)
    everyone = torch.ones(n, dtype=torch.bool)
    ticked = WholeTicks(VelocityDynamics(num_envs=n, num_drones=d, physics_dt=0.003), 0.003)
    plain = VelocityDynamics(num_envs=n, num_drones=d, physics_dt=0.003)
    for model in (ticked, plain):
        model.reset(everyone, start, torch.zeros_like(start), speed)
    flown = []
    for step in range(1, 32):
        ticked.advance(command, 0.1)
        flown.append(ticked.last_advance_s)
        plain.advance(command, flown[-1])
        assert abs(sum(flown) - step * 0.1) < 0.003 + 1e-9
        assert torch.equal(ticked.position, plain.position)  # inner's state, read through
    assert flown[:4] == [pytest.approx(t) for t in (0.102, 0.099, 0.099, 0.102)]
    assert {round(t, 6) for t in flown} == {0.099, 0.102}
    # A reset of one env keeps the clock (the pattern goes on); a reset of all restarts it.
    ticked.reset(torch.tensor([True, False, False]), start, torch.zeros_like(start), speed)
    ticked.advance(command, 0.1)
    assert ticked.last_advance_s == pytest.approx(0.099)  # to 3.2 s from 3.102 s
    ticked.reset(everyone, start, torch.zeros_like(start), speed)
    ticked.advance(command, 0.1)
    assert ticked.last_advance_s == pytest.approx(0.102)
    with pytest.raises(ConfigError, match="tick must be > 0"):
        WholeTicks(plain, 0.0)
