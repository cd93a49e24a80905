"""The capture ceiling: in which scenarios an intercept exists at all.

A defender that flies its route from setpoint to setpoint ignores the attacker, so its whole
path is known in advance. An attacker whose dynamics are separable per axis (the ``velocity``
model: first-order tracking, acceleration limits and drag per axis, commands bounded per axis
by its maximum speed) can be, at time ``t``, anywhere in a box around its start: per axis,
between the positions reached by flying that axis at full speed in the negative and in the
positive direction from rest (the reachable set of a monotone system under a bounded command
is an interval per axis; the ground bounds it below). An intercept exists if, at some step
before the episode ends, the defender is within the capture radius of that box.

This is an upper bound for any attacker policy of those dynamics, computed at the control
steps (the env also counts a closest approach between steps, so a policy can very rarely
capture where the bound, checked at step ends only, says no). It is not defined for defenders
that react to the attacker (``nn``) nor for episodes that need every one of several
defenders caught; those scenarios get NaN.

The **route ceiling** is the same computation on :func:`route_flown`, a copy of the set whose
defenders all fly their routes: for a reacting defender, whether an intercept would exist had
it kept to its route. That is not a bound (the defender leaves its route only to evade, which
can also slow it down or turn it towards an attacker), but it separates the scenarios a
network defender wins by running away along its route from those it wins by evading.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from rlplat.envs.dynamics import DroneDynamics
from rlplat.envs.pursuit import PursuitEnv
from rlplat.eval.episodes import evaluate
from rlplat.scenarios import STRATEGIES, ScenarioSet


@dataclass(frozen=True)
class Ceiling:
    """Per scenario of a split (in order).

    Attributes:
        interceptable: (E,) float32: 1 where an intercept exists, 0 where none does, NaN where
            the bound is not defined (a reacting defender, or several defenders).
        earliest: (E,) float32 s, the first time an intercept is possible (NaN if none is).
    """

    interceptable: Tensor
    earliest: Tensor

    @property
    def defined(self) -> Tensor:
        """(E,) bool, the scenarios the bound covers."""
        return ~self.interceptable.isnan()

    @property
    def rate(self) -> float:
        """The fraction of the covered scenarios where an intercept exists."""
        covered = self.interceptable[self.defined]
        return covered.mean().item() if covered.numel() else float("nan")


class _Hold(torch.nn.Module):
    """Every attacker holds still (a zero velocity command): flies the defenders' paths."""

    def __init__(self, key, shape_tail: tuple[int, ...]) -> None:
        super().__init__()
        self.key, self.shape_tail = key, shape_tail

    def forward(self, td):
        return td.set(self.key, torch.zeros(*td.batch_size, *self.shape_tail, device=td.device))


@torch.no_grad()
def intercept_ceiling(env: PursuitEnv, dynamics: DroneDynamics) -> Ceiling:
    """The capture ceiling of ``env``'s split (one env per scenario, walked sequentially, as
    :func:`rlplat.eval.episodes.evaluate` needs).

    Args:
        env: the attacker-learning env of the split.
        dynamics: a fresh model of the env's dynamics with ``num_envs`` = scenarios and 2
            drones (the reach envelope flies each attacker twice); it must be separable per
            axis (``velocity``) for the bound to hold.
    """
    k = env.num_attackers
    spec = env.full_action_spec[env.action_key]
    hold = _Hold(env.action_key, tuple(spec.shape[1:]))
    if getattr(env.action_fn, "guided", False):  # a zero correction still flies guidance
        raise ValueError("intercept_ceiling: needs an env with a plain velocity action")
    path = evaluate(env, hold, record=True)  # the defenders' paths (attackers holding)
    positions = path.positions  # (E, T + 1, D, 3)
    steps = positions.shape[1] - 1
    start = positions[:, 0, :k]  # (E, k, 3)
    speed = env.scenarios["attacker_max_speed"][:, :k].cpu()  # (E, k)

    # The reach envelope of each attacker: full speed on every axis, each way, from rest.
    lo_steps, hi_steps = _envelope(dynamics, start, speed, steps, env.control_period)
    lo = torch.cat([start.unsqueeze(1), lo_steps], 1)  # (E, T + 1, k, 3)
    hi = torch.cat([start.unsqueeze(1), hi_steps], 1)
    lo[..., 2] = lo[..., 2].clamp_min(env.ground_altitude)

    defender = positions[:, :, k]  # (E, T + 1, 3): the first defender
    gap = torch.maximum(lo - defender.unsqueeze(2), defender.unsqueeze(2) - hi).clamp_min(0)
    near = gap.norm(dim=-1).amin(-1) <= env.capture_radius  # (E, T + 1), any attacker
    alive = torch.arange(steps + 1).unsqueeze(0) <= path.length.unsqueeze(1)
    near &= alive
    possible = near.any(1) | path.captured
    first = torch.where(possible, near.float().argmax(1) * env.control_period, float("nan"))

    setpoints = env.scenarios["defender_strategy"][:, 0].cpu() == STRATEGIES.index("setpoints")
    covered = setpoints & torch.tensor(env.num_defenders == 1)
    interceptable = torch.where(covered, possible.float(), float("nan"))
    return Ceiling(interceptable, torch.where(covered, first.float(), float("nan")))


def _envelope(
    dynamics: DroneDynamics, start: Tensor, speed: Tensor, steps: int, period: float
) -> tuple[Tensor, Tensor]:
    """Positions (E, steps, k, 3) of each attacker flying -max and +max speed on every axis."""
    n, k = start.shape[:2]
    if tuple(dynamics.position.shape[:2]) != (n, 2):
        raise ValueError(f"intercept_ceiling: dynamics must fly ({n}, 2) drones")
    lo, hi = [], []
    everyone = torch.ones(n, dtype=torch.bool)
    for a in range(k):
        p0 = start[:, a : a + 1].expand(n, 2, 3).contiguous()
        v_max = speed[:, a : a + 1].expand(n, 2).contiguous()
        dynamics.reset(everyone, p0.to(dynamics.device), torch.zeros_like(p0), v_max)
        command = torch.stack([-v_max[:, 0], v_max[:, 0]], 1).unsqueeze(-1).expand(n, 2, 3)
        low, high = [], []
        for _ in range(steps):
            dynamics.advance(command.to(dynamics.device), period)
            low.append(dynamics.position[:, 0].cpu())
            high.append(dynamics.position[:, 1].cpu())
        lo.append(torch.stack(low, 1))
        hi.append(torch.stack(high, 1))
    return torch.stack(lo, 2), torch.stack(hi, 2)


def route_flown(scenarios: ScenarioSet) -> ScenarioSet:
    """A copy of ``scenarios`` in which every defender flies its route (strategy ``setpoints``),
    the rest unchanged: on it :func:`intercept_ceiling` gives the route ceiling."""
    setpoints = STRATEGIES.index("setpoints")
    splits = {
        name: td.clone().set(
            "defender_strategy", torch.full_like(td["defender_strategy"], setpoints)
        )
        for name, td in scenarios.splits.items()
    }
    return dataclasses.replace(scenarios, splits=splits)
