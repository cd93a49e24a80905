"""Deterministic evaluation: one episode per scenario of a split, in one batch or in waves."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlplat.envs.pursuit import PursuitEnv

#: The score a learner of each role maximises: an attribute of :class:`EpisodeResults`.
SCORE_NAME = {"attacker": "capture_rate", "defender": "evasion_score"}


@dataclass(frozen=True)
class EpisodeResults:
    """Per-episode outcomes of an evaluation, one row per scenario of the split (in order).

    Attributes:
        scenario_index: (E,) int64, row of the split.
        captured: (E,) bool, the episode ended in a capture (of every defender).
        grounded: (E,) bool, the episode ended with a drone on the ground.
        returns: (E,) float32, undiscounted return.
        length: (E,) int64, steps.
        time_to_capture: (E,) float32 s, NaN where there was no capture.
        term_sums: per reward term, (E,) float32 episode sum.
        min_distance: (E,) float32 m, least attacker-defender distance at the start or at the
            end of a step (a capture is decided on the closest approach during a step, so a
            captured episode can show slightly more than the capture radius).
        visible_fraction: (E,) float32, fraction of the episode's steps that ended with the
            defender inside the attacker's vision ellipsoid.
        defender_route_fraction: (E, m) float32, fraction of its route's setpoints each
            defender reached.
        defender_caught: (E, m) bool, which defenders were caught by the episode's end.
        attacker_separation: (E,) float32 m, least distance between two attackers in play (not
            down) at the start or at the end of a step: how near team-mates came to each
            other, which the embedded simulator does not stop; NaN where one attacker flies.
        positions: (E, T + 1, D, 3) float32 m, every drone (attackers, then defenders) at the start
            and after every step, T the longest episode; an episode that ended earlier repeats
            its final positions. None unless ``evaluate(..., record=True)``.
    """

    scenario_index: torch.Tensor
    captured: torch.Tensor
    grounded: torch.Tensor
    returns: torch.Tensor
    length: torch.Tensor
    time_to_capture: torch.Tensor
    term_sums: dict[str, torch.Tensor]
    min_distance: torch.Tensor
    visible_fraction: torch.Tensor
    defender_route_fraction: torch.Tensor
    defender_caught: torch.Tensor
    attacker_separation: torch.Tensor | None = None
    positions: torch.Tensor | None = None

    @property
    def capture_rate(self) -> float:
        return self.captured.float().mean().item()

    @property
    def mean_return(self) -> float:
        return self.returns.mean().item()

    @property
    def route_fraction(self) -> torch.Tensor:
        """(E,) the fraction of its route a defender reached, the mean over the defenders."""
        return self.defender_route_fraction.mean(-1)

    @property
    def evasion(self) -> torch.Tensor:
        """(E,) the fraction of its route a defender flew without being caught: its route
        fraction, 0 if it was caught or the episode crashed; the mean over the defenders."""
        out = self.defender_caught | self.grounded.unsqueeze(-1)
        return self.defender_route_fraction.masked_fill(out, 0.0).mean(-1)

    @property
    def evasion_score(self) -> float:
        """The defender's goal in one number: the mean of :attr:`evasion`."""
        return self.evasion.mean().item()

    def score(self, role: str) -> float:
        """What a learner of ``role`` maximises (:data:`SCORE_NAME`); validation keeps the
        checkpoint with the highest."""
        return getattr(self, SCORE_NAME[role])

    def summary(self) -> dict[str, float]:
        """Scalars for a logger: capture rate, mean return and length, visibility, per-term
        means."""
        out = {
            "capture_rate": self.capture_rate,
            "mean_return": self.mean_return,
            "mean_length": self.length.float().mean().item(),
            "ground_rate": self.grounded.float().mean().item(),
            "visible_fraction": self.visible_fraction.mean().item(),
            "mean_min_distance": self.min_distance.mean().item(),
            "route_fraction": self.route_fraction.mean().item(),
            "evasion_score": self.evasion_score,
        }
        if self.captured.any():
            out["mean_time_to_capture_s"] = self.time_to_capture[self.captured].mean().item()
        out.update({f"reward/{k}": v.mean().item() for k, v in self.term_sums.items()})
        return out


@torch.no_grad()
def evaluate(
    env: PursuitEnv, policy, *, deterministic: bool = True, record: bool = False
) -> EpisodeResults:
    """Fly every scenario of ``env``'s split once with ``policy``; no learning happens.

    ``env`` must walk its split sequentially (``scenario_order="sequential"``): with one env per
    scenario, env ``i`` flies scenario ``i``; with fewer envs (one per simulator on AirSim) the
    split is flown in waves, env ``i`` of wave ``w`` flying scenario ``w * num_envs + i`` (the
    last wave's envs beyond the split fly again and are not counted). Each env runs until its
    first episode of the wave ends; envs that finish early keep stepping but their steps are not
    counted. With ``record`` the drones' positions at every step are kept (``positions``).
    """
    n, total = env.batch_size[0], len(env.scenarios)
    if env.sampler.order != "sequential":
        raise ValueError(
            f"evaluate: needs the split walked sequentially, got order={env.sampler.order}"
        )
    env.set_seed(0)  # restarts the sequential walk at scenario 0
    waves = [_fly(env, policy, deterministic, record) for _ in range(math.ceil(total / n))]
    if record:  # episodes of different waves have different lengths: repeat the final positions
        longest = max(w["positions"].shape[1] for w in waves)
        for w in waves:
            p = w["positions"]
            w["positions"] = torch.cat([p, p[:, -1:].expand(-1, longest - p.shape[1], -1, -1)], 1)
    out = {k: torch.cat([w[k] for w in waves])[:total] for k in waves[0] if k != "terms"}
    terms = {k: torch.cat([w["terms"][k] for w in waves])[:total] for k in waves[0]["terms"]}
    captured, length = out["captured"], out["length"]
    time_to_capture = torch.where(captured, length * env.control_period, float("nan"))
    return EpisodeResults(
        scenario_index=out["index"],
        captured=captured,
        grounded=out["grounded"],
        returns=out["returns"],
        length=length,
        time_to_capture=time_to_capture.float(),
        term_sums=terms,
        min_distance=out["min_distance"],
        visible_fraction=(out["visible_steps"] / length.clamp_min(1)).float(),
        defender_route_fraction=out["waypoint"].float() / env.routes.shape[1],
        defender_caught=out["caught"],
        attacker_separation=out["separation"],
        positions=out.get("positions"),
    )


def _fly(env: PursuitEnv, policy, deterministic: bool, record: bool) -> dict:
    """One wave: reset every env, fly until each one's episode ends; per-env tallies (CPU)."""
    n, attackers = env.batch_size[0], env.num_attackers
    kind = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    td = env.reset()
    index = td["scenario_index"].squeeze(-1).clone()
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    captured = torch.zeros_like(alive)
    grounded = torch.zeros_like(alive)
    returns = torch.zeros(n, device=env.device)
    length = torch.zeros(n, dtype=torch.int64, device=env.device)
    terms = {k: torch.zeros(n, device=env.device) for k in env.reward_fn.weights}
    min_distance = td["distance"].squeeze(-1).clone()
    separation = _separation(td, attackers, env.ground_altitude)
    visible_steps = torch.zeros(n, device=env.device)
    positions = [td["positions"]] if record else None
    waypoint = td["waypoint"].clone()  # (n, m)
    caught = td["caught"].clone()
    with set_exploration_type(kind):
        while alive.any():
            td = env.step(policy(td))
            nxt: TensorDictBase = td["next"]
            a = alive.float()
            returns += nxt["reward"].squeeze(-1) * a
            for k in terms:
                terms[k] += nxt["reward_terms", k].squeeze(-1) * a
            length += alive.long()
            d = nxt["distance"].squeeze(-1)
            min_distance = torch.where(alive, min_distance.minimum(d), min_distance)
            step_separation = _separation(nxt, attackers, env.ground_altitude)
            separation = torch.where(alive, separation.fmin(step_separation), separation)
            waypoint = torch.where(alive.unsqueeze(-1), nxt["waypoint"], waypoint)
            caught = torch.where(alive.unsqueeze(-1), nxt["caught"], caught)
            visible_steps += nxt["visible"].squeeze(-1) * a
            if positions is not None:
                keep = alive.view(n, 1, 1)
                positions.append(torch.where(keep, nxt["positions"], positions[-1]))
            done = nxt["done"].squeeze(-1) & alive
            captured |= done & nxt["captured"].squeeze(-1)
            # A crash ends the episode as the env ends one: a defender on the ground, or every
            # attacker (the first drones); a team's downed attacker alone is no crash.
            low = nxt["positions"][..., 2] <= env.ground_altitude
            crashed = low[:, :attackers].all(-1) | low[:, attackers:].any(-1)
            grounded |= done & crashed & ~nxt["captured"].squeeze(-1)
            alive &= ~done
            td = nxt.exclude("reward", "done", "terminated", "truncated")
    out = {
        "index": index,
        "captured": captured,
        "grounded": grounded,
        "returns": returns,
        "length": length,
        "min_distance": min_distance,
        "separation": separation,
        "visible_steps": visible_steps,
        "waypoint": waypoint,
        "caught": caught,
        "terms": {k: v.cpu() for k, v in terms.items()},
    }
    if positions is not None:
        out["positions"] = torch.stack(positions, 1)
    return {k: v if k == "terms" else v.cpu() for k, v in out.items()}


def _separation(td: TensorDictBase, k: int, ground: float) -> torch.Tensor:
    """(n,) least distance between two of the ``k`` attackers in play in ``td``: not down (the
    env's ``("attacker", "down")`` where it has one, else above ``ground``); NaN with fewer
    than two in play."""
    attackers = td["positions"][:, :k]  # (n, k, 3)
    n = attackers.shape[0]
    if k < 2:
        return torch.full((n,), float("nan"), device=attackers.device)
    d = (attackers.unsqueeze(2) - attackers.unsqueeze(1)).norm(dim=-1)  # (n, k, k)
    down = td.get(("attacker", "down"), None)
    up = attackers[..., 2] > ground if down is None else ~down.squeeze(-1)
    pair = up.unsqueeze(-1) & up.unsqueeze(-2) & ~torch.eye(k, dtype=torch.bool, device=d.device)
    least = d.masked_fill(~pair, float("inf")).flatten(1).amin(-1)
    return least.masked_fill(least.isinf(), float("nan"))


@torch.no_grad()
def rollout_observations(
    env: PursuitEnv, policy, key: str | tuple[str, ...], *, deterministic: bool = True
) -> torch.Tensor:
    """Every observation ``key`` a learning drone acted on while its episode ran, flying each
    scenario of ``env``'s split once with ``policy`` as :func:`evaluate` does: (R, obs_dim)
    float32 on the CPU, in step order (a team's drones one row each).

    With ``deterministic=False`` the policy samples its actions (torch's global generator),
    which visits states near the deterministic episodes'.
    """
    n = env.batch_size[0]
    if n != len(env.scenarios) or env.sampler.order != "sequential":
        raise ValueError(
            f"rollout_observations: needs one env per scenario ({len(env.scenarios)}) walked "
            f"sequentially, got num_envs={n}, order={env.sampler.order}"
        )
    kind = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    env.set_seed(0)
    td = env.reset()
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    rows = []
    with set_exploration_type(kind):
        while alive.any():
            obs = td[key]
            rows.append(obs[alive].reshape(-1, obs.shape[-1]).cpu())
            td = env.step(policy(td))
            nxt: TensorDictBase = td["next"]
            alive &= ~nxt["done"].squeeze(-1)
            td = nxt.exclude("reward", "done", "terminated", "truncated")
    return torch.cat(rows)
