"""Calibrate the embedded ``velocity`` dynamics against a simulator: fly velocity step
responses, then fit the model's constants to them.

:func:`fly_steps` flies a :class:`StepPlan` with one vehicle in lock step (through
``AirSimDynamics``: the simulation paused between control periods): for each axis (x, y, z),
amplitude and direction, the vehicle is placed at rest ``altitude`` metres above its spawn
point, hovers (zero command) for ``settle_s``, holds the step command for ``hold_s`` and the
zero command again for ``rest_s``; the state is read after every control period. The result is
a recording (:class:`~rlplat.envs.airsim.recording.Episode` per step test).

:func:`fit_velocity` fits ``tau_xy``, ``a_xy_max``, ``drag_xy``, ``tau_z``, ``a_up_max``,
``a_down_max`` and ``drag_z`` to any recording by least squares on the measured velocities:
every candidate is scored by flying the recorded commands through
:class:`~rlplat.envs.dynamics.VelocityDynamics` itself (all episodes at once, one env each,
open loop from their first recorded state), so the fitted constants are those of the model the
env flies, with no second implementation to drift from it. The solver is scipy's bounded
trust-region least squares with finite-difference Jacobians (the model's acceleration limits
are clips: piecewise smooth, without useful gradients where inactive). The horizontal and the
vertical constants act on separate axes of the model, so each group is judged on its own
residual.

Identifiability: an acceleration limit the steps never reach, or a drag the data cannot tell
from the configured one, does not show in the residual. Each limit and drag is therefore
probed: set back to its configured value (the others as fitted), if its group's RMS residual
grows by less than :data:`KEEP_RELATIVE` (and :data:`KEEP_ABSOLUTE` m/s), the configured
value is kept and the rest refitted with it fixed. ``physics_dt`` and ``mass`` are always kept
(``mass`` only scales the drag).
"""

from __future__ import annotations

import logging
import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from rlplat.envs.airsim.client import AirSimError
from rlplat.envs.airsim.dynamics import PLACEMENT_TOLERANCE_M
from rlplat.envs.airsim.recording import Episode
from rlplat.envs.dynamics import DroneDynamics, VelocityDynamics
from rlplat.errors import ConfigError

log = logging.getLogger(__name__)

#: The fitted constants and the axis group each acts on.
FITTED = {
    "tau_xy": "xy", "a_xy_max": "xy", "drag_xy": "xy",
    "tau_z": "z", "a_up_max": "z", "a_down_max": "z", "drag_z": "z",
}  # fmt: skip
#: Those kept at their configured value when the data do not determine them.
PROBED = ("a_xy_max", "a_up_max", "a_down_max", "drag_xy", "drag_z")
#: Bounds of the search (SI units).
BOUNDS = {"tau": (0.005, 20.0), "a": (0.05, 200.0), "drag": (0.0, 10.0)}
#: A probed constant is kept when setting it back changes its group's RMS residual by less
#: than this fraction and this many m/s.
KEEP_RELATIVE, KEEP_ABSOLUTE = 0.02, 1e-3
AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class StepPlan:
    """The step responses :func:`fly_steps` flies (SI units, ENU).

    Args:
        max_speed: m/s, the vehicle's largest speed per axis; amplitudes are fractions of it.
        amplitudes: fractions of ``max_speed`` in (0, 1], each flown in both directions.
        axes: which of ``x``, ``y``, ``z`` to step.
        period: s, control period (one command and one state read each).
        settle_s: s of zero command (hover) before each step.
        hold_s: s the step command is held.
        rest_s: s of zero command after it.
        altitude: m above the vehicle's spawn point where each step starts; must leave room
            for the downward steps.
    """

    max_speed: float = 5.0
    amplitudes: tuple[float, ...] = (0.2, 0.5, 1.0)
    axes: tuple[str, ...] = ("x", "y", "z")
    period: float = 0.1
    settle_s: float = 0.5
    hold_s: float = 4.0
    rest_s: float = 2.0
    altitude: float = 40.0

    def __post_init__(self) -> None:
        for name in ("max_speed", "period", "hold_s", "altitude"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}: must be a number > 0, got {value!r}")
        for name in ("settle_s", "rest_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name}: must be a number >= 0, got {value!r}")
        if not self.amplitudes or not all(0 < a <= 1 for a in self.amplitudes):
            raise ConfigError(
                f"amplitudes: fractions of max_speed in (0, 1], got {self.amplitudes}"
            )
        if not self.axes or not set(self.axes) <= set(AXES) or len(set(self.axes)) < len(self.axes):
            raise ConfigError(f"axes: distinct ones of x, y, z, got {list(self.axes)}")
        drop = self.max_speed * (self.hold_s + 1.0) + 2.0  # a downward step and its stop
        if "z" in self.axes and self.altitude < drop:
            raise ConfigError(
                f"altitude: {self.altitude:g} m leaves no room for a downward step of "
                f"{self.max_speed:g} m/s held {self.hold_s:g} s (needs >= {drop:g} m)"
            )

    def tests(self) -> list[tuple[str, float]]:
        """(axis, signed speed m/s) of every step test, in flying order."""
        return [
            (axis, sign * fraction * self.max_speed)
            for axis in self.axes
            for fraction in self.amplitudes
            for sign in (1.0, -1.0)
        ]

    def commands(self, axis: str, speed: float) -> np.ndarray:
        """(K, 3) float64, the command of every control period of one test."""
        n = [round(s / self.period) for s in (self.settle_s, self.hold_s, self.rest_s)]
        out = np.zeros((sum(n), 3))
        out[n[0] : n[0] + n[1], AXES[axis]] = speed
        return out


def fly_steps(dynamics: DroneDynamics, plan: StepPlan, spawn_enu: Sequence[float]) -> list[Episode]:
    """Fly ``plan`` with the one drone of ``dynamics`` (an ``AirSimDynamics`` of one env and one
    drone) and record each test as an episode named like ``x+2.5``.

    Args:
        dynamics: the connected model; its ``reset`` places the drone, ``advance`` flies it.
        plan: the step tests.
        spawn_enu: (x, y, z) m, the drone's spawn point in the world (ENU); tests start
            ``plan.altitude`` above it.
    """
    if dynamics.num_envs != 1 or dynamics.num_drones != 1:
        raise ValueError("fly_steps: needs a model of one env and one drone")
    start = torch.tensor([[[spawn_enu[0], spawn_enu[1], spawn_enu[2] + plan.altitude]]])
    bound = torch.full((1, 1), float(plan.max_speed))
    name = (getattr(dynamics, "names", None) or ["drone0"])[0]
    episodes = []
    for axis, speed in plan.tests():
        commands = plan.commands(axis, speed)
        dynamics.reset(torch.ones(1, dtype=torch.bool), start, torch.zeros(1, 1, 3), bound)
        off = float((dynamics.position[0, 0] - start[0, 0]).norm())
        if off > PLACEMENT_TOLERANCE_M:  # a fit from where it did not start would be wrong
            raise AirSimError(
                f"calibrate: {name} reads {off:.2f} m from where it was placed for the step "
                f"test {axis}{speed:+g} (a simulator that applies poses late, or not at all); "
                "a fit from there would be wrong, so none is made"
            )
        t, p, v = [0.0], [dynamics.position[0].double().numpy()], [dynamics.velocity[0]]
        for cmd in commands:
            dynamics.advance(torch.tensor(cmd, dtype=torch.float32).view(1, 1, 3), plan.period)
            dt = getattr(dynamics, "last_advance_s", math.nan)
            t.append(t[-1] + (dt if math.isfinite(dt) else plan.period))
            p.append(dynamics.position[0].double().numpy())
            v.append(dynamics.velocity[0])
        episodes.append(
            Episode(
                name=f"{axis}{speed:+g}",
                vehicles=[name],
                t=np.array(t),
                position=np.stack(p),
                velocity=torch.stack(v).double().numpy(),
                command=commands.reshape(-1, 1, 3),
                max_speed=np.array([float(plan.max_speed)]),
            )
        )
        log.info("step %s%+g m/s: %d control periods flown", axis, speed, len(commands))
    return episodes


# Fitting -------------------------------------------------------------------------------------


class _Batch:
    """Episodes padded into one batch of N envs x D drones x K periods for VelocityDynamics."""

    def __init__(self, episodes: Sequence[Episode]) -> None:
        n, d = len(episodes), max(len(ep.vehicles) for ep in episodes)
        k = max(ep.steps for ep in episodes)
        # Each step is simulated at its own period: a simulator that runs whole physics ticks
        # steps 0.102 s, 0.099 s, ... for 0.1 s, the same from every reset. The episodes must
        # agree on it step by step (within 1 ms).
        table = np.full((n, k), np.nan)
        for i, ep in enumerate(episodes):
            table[i, : ep.steps] = ep.periods
        self.periods = [float(x) for x in np.nanmedian(table, axis=0)]
        spread = np.nanmax(np.abs(table - np.asarray(self.periods)), axis=0)
        if spread.max() > 1e-3:
            at = int(spread.argmax())
            raise ConfigError(
                f"recording: episodes of different control periods at step {at + 1} "
                f"({np.nanmin(table[:, at]):g}..{np.nanmax(table[:, at]):g} s); fit them "
                "separately"
            )
        self.start_p, self.start_v = torch.zeros(n, d, 3), torch.zeros(n, d, 3)
        self.max_speed = torch.full((n, d), math.inf)
        self.commands = torch.zeros(k, n, d, 3)
        self.measured = torch.zeros(k, n, d, 3, dtype=torch.float64)
        self.mask = torch.zeros(k, n, d, dtype=torch.bool)
        for i, ep in enumerate(episodes):
            m, s = len(ep.vehicles), ep.steps
            self.start_p[i, :m] = torch.as_tensor(ep.position[0])
            self.start_v[i, :m] = torch.as_tensor(ep.velocity[0])
            self.max_speed[i, :m] = torch.as_tensor(ep.max_speed)
            self.commands[:s, i, :m] = torch.as_tensor(ep.command)
            self.measured[:s, i, :m] = torch.as_tensor(ep.velocity[1:])
            self.mask[:s, i, :m] = True
        self.samples = int(self.mask.sum())

    def simulate(self, base: Mapping[str, float], params: Mapping[str, float]) -> torch.Tensor:
        """(K, N, D, 3) float64, the velocity after each period under ``params``."""
        model = VelocityDynamics(
            num_envs=self.start_p.shape[0], num_drones=self.start_p.shape[1], **{**base, **params}
        )
        model.reset(
            torch.ones(model.num_envs, dtype=torch.bool),
            self.start_p, self.start_v, self.max_speed,
        )  # fmt: skip
        out = []
        for cmd, period in zip(self.commands, self.periods, strict=True):
            model.advance(cmd, period)
            out.append(model.velocity)
        return torch.stack(out).double()

    def residuals(self, velocity: torch.Tensor) -> dict[str, np.ndarray]:
        """Velocity errors (m/s) per group: ``xy`` (x and y axes) and ``z``."""
        err = (velocity - self.measured)[self.mask]  # (S, 3)
        return {"xy": err[:, :2].reshape(-1).numpy(), "z": err[:, 2].numpy()}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x))) if x.size else 0.0


@dataclass(frozen=True)
class Fit:
    """The outcome of :func:`fit_velocity`.

    Attributes:
        params: every knob of the ``velocity`` model: fitted, or kept from the start.
        kept: the fitted constants kept at their configured value (not identifiable).
        rms: m/s, RMS velocity residual per group (``xy``, ``z``) with the fitted constants.
        rms_start: m/s, the same with the configured (start) constants.
        samples: control periods of vehicle state the fit used.
    """

    params: dict[str, float]
    kept: list[str] = field(default_factory=list)
    rms: dict[str, float] = field(default_factory=dict)
    rms_start: dict[str, float] = field(default_factory=dict)
    samples: int = 0


def _bounds(name: str) -> tuple[float, float]:
    return BOUNDS["tau" if name.startswith("tau") else "a" if name.startswith("a_") else "drag"]


def fit_velocity(
    episodes: Sequence[Episode],
    start: Mapping[str, float],
    groups: Sequence[str] | None = None,
) -> Fit:
    """Fit the ``velocity`` constants to ``episodes`` (see the module docstring).

    Args:
        episodes: recorded episodes, all of one control period.
        start: every knob of the ``velocity`` model (no ``name``): the starting point, and the
            value of every constant that is not fitted.
        groups: which groups to fit (``xy``: horizontal, ``z``: vertical); the constants of a
            group left out are kept. None: the groups the episodes command motion on.
    """
    from scipy.optimize import least_squares

    if not episodes:
        raise ConfigError("recording: no episode to fit")
    base = {k: float(v) for k, v in start.items()}
    missing = [k for k in FITTED if k not in base]
    if missing:
        raise ConfigError(f"velocity: the starting constants lack {', '.join(missing)}")
    batch = _Batch(episodes)
    if groups is None:
        moved = batch.commands.abs().amax(dim=(0, 1, 2)) > 0
        groups = [g for g, on in (("xy", bool(moved[:2].any())), ("z", bool(moved[2]))) if on]

    def score(params: Mapping[str, float]) -> dict[str, np.ndarray]:
        return batch.residuals(batch.simulate(base, params))

    def solve(free: list[str], fixed: Mapping[str, float]) -> dict[str, float]:
        if not free:
            return dict(fixed)
        x0 = np.array([fixed[k] for k in free])
        lo, hi = np.array([_bounds(k) for k in free]).T
        x0 = np.clip(x0, lo, hi)
        scale = np.maximum(np.abs(x0), [0.01 if k == "drag_xy" else 0.1 for k in free])
        used = sorted({FITTED[k] for k in free})

        def fun(x: np.ndarray) -> np.ndarray:
            res = score({**fixed, **dict(zip(free, x.tolist(), strict=True))})
            return np.concatenate([res[g] for g in used])

        sol = least_squares(
            fun, x0, bounds=(lo, hi), x_scale=scale, diff_step=1e-3, xtol=1e-10, ftol=1e-12,
            gtol=1e-12, max_nfev=200 * len(free),
        )  # fmt: skip
        log.debug("least squares on %s: %s (%d evaluations)", free, sol.message, sol.nfev)
        return {**fixed, **dict(zip(free, sol.x.tolist(), strict=True))}

    configured = {k: base[k] for k in FITTED}
    free = [k for k in FITTED if FITTED[k] in groups]
    fitted = solve(free, configured)
    rms = {g: _rms(r) for g, r in score(fitted).items()}
    kept = []
    for name in PROBED:
        if name not in free:
            continue
        group = FITTED[name]
        probe = _rms(score({**fitted, name: configured[name]})[group])
        if probe - rms[group] < max(KEEP_RELATIVE * rms[group], KEEP_ABSOLUTE):
            kept.append(name)
    if kept:
        log.info("kept at their configured values (the steps do not determine them): %s", kept)
        fixed = {**fitted, **{k: configured[k] for k in kept}}
        fitted = solve([k for k in free if k not in kept], fixed)
    rms = {g: _rms(r) for g, r in score(fitted).items()}
    rms_start = {g: _rms(r) for g, r in score(configured).items()}
    return Fit(
        params={**base, **fitted},
        kept=[k for k in FITTED if k not in free] + kept,
        rms=rms,
        rms_start=rms_start,
        samples=batch.samples,
    )


#: One comment per knob of the written file (as conf/dynamics/velocity.yaml).
KNOB_NOTES = {
    "physics_dt": "s, physics sub-step (first-order part integrated exactly)",
    "mass": "kg, airframe mass (drag force -> acceleration)",
    "tau_xy": "s, horizontal velocity time constant",
    "tau_z": "s, vertical velocity time constant",
    "a_xy_max": "m/s^2, commanded acceleration limit per horizontal axis",
    "a_up_max": "m/s^2, commanded upward acceleration limit",
    "a_down_max": "m/s^2, commanded downward acceleration limit (positive number)",
    "drag_xy": "N/(m/s)^2, quadratic drag coefficient per horizontal axis",
    "drag_z": "N/(m/s)^2, quadratic drag coefficient on the vertical axis",
}


def _wrap(text: str) -> list[str]:
    return textwrap.wrap(
        text, 96, subsequent_indent="  ", break_long_words=False, break_on_hyphens=False
    )


def velocity_yaml(params: Mapping[str, float], header: Sequence[str], fitted: Sequence[str]) -> str:
    """A complete ``conf/dynamics/`` file of the ``velocity`` model: ``header`` as comment
    lines, ``name: velocity``, then every knob with its comment (``fitted`` ones marked)."""
    lines = [f"# {line}" for h in header for line in _wrap(h)]
    lines.append(f"{'name: velocity':<24}# registry key (rlplat.envs.dynamics.DYNAMICS)")
    for key, value in params.items():
        note = KNOB_NOTES.get(key, "")
        mark = "fitted; " if key in fitted else ""
        number = f"{float(value):.5g}"
        text = f"{key}: {number if any(c in number for c in '.en') else number + '.0'}"
        lines.append(f"{text:<24}# {mark}{note}".rstrip())
    return "\n".join(lines) + "\n"
