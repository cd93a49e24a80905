"""Deterministic evaluation: one episode per scenario of a split, all in one batch."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlplat.envs.pursuit import PursuitEnv


@dataclass(frozen=True)
class EpisodeResults:
    """Per-episode outcomes of an evaluation, one row per scenario of the split (in order).

    Attributes:
        scenario_index: (E,) int64, row of the split.
        captured: (E,) bool, the episode ended in a capture.
        grounded: (E,) bool, the episode ended with a drone on the ground.
        returns: (E,) float32, undiscounted return.
        length: (E,) int64, steps.
        time_to_capture: (E,) float32 s, NaN where there was no capture.
        term_sums: per reward term, (E,) float32 episode sum.
    """

    scenario_index: torch.Tensor
    captured: torch.Tensor
    grounded: torch.Tensor
    returns: torch.Tensor
    length: torch.Tensor
    time_to_capture: torch.Tensor
    term_sums: dict[str, torch.Tensor]

    @property
    def capture_rate(self) -> float:
        return self.captured.float().mean().item()

    @property
    def mean_return(self) -> float:
        return self.returns.mean().item()

    def summary(self) -> dict[str, float]:
        """Scalars for a logger: capture rate, mean return and length, per-term means."""
        out = {
            "capture_rate": self.capture_rate,
            "mean_return": self.mean_return,
            "mean_length": self.length.float().mean().item(),
            "ground_rate": self.grounded.float().mean().item(),
        }
        if self.captured.any():
            out["mean_time_to_capture_s"] = self.time_to_capture[self.captured].mean().item()
        out.update({f"reward/{k}": v.mean().item() for k, v in self.term_sums.items()})
        return out


@torch.no_grad()
def evaluate(env: PursuitEnv, policy, *, deterministic: bool = True) -> EpisodeResults:
    """Fly every scenario of ``env``'s split once with ``policy``; no learning happens.

    ``env`` must have one env per scenario and walk its split sequentially (see
    :func:`make_eval_env`), so env ``i`` flies scenario ``i``. Each env runs until its first
    episode ends; envs that finish early keep stepping but their steps are not counted.
    """
    n = env.batch_size[0]
    if n != len(env.scenarios) or env.sampler.order != "sequential":
        raise ValueError(
            f"evaluate: needs one env per scenario ({len(env.scenarios)}) walked sequentially, "
            f"got num_envs={n}, order={env.sampler.order}"
        )
    kind = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    env.set_seed(0)  # restarts the sequential walk at scenario 0
    td = env.reset()
    index = td["scenario_index"].squeeze(-1).clone()
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    captured = torch.zeros_like(alive)
    grounded = torch.zeros_like(alive)
    returns = torch.zeros(n, device=env.device)
    length = torch.zeros(n, dtype=torch.int64, device=env.device)
    terms = {k: torch.zeros(n, device=env.device) for k in env.reward_fn.weights}
    with set_exploration_type(kind):
        while alive.any():
            td = env.step(policy(td))
            nxt: TensorDictBase = td["next"]
            a = alive.float()
            returns += nxt["reward"].squeeze(-1) * a
            for k in terms:
                terms[k] += nxt["reward_terms", k].squeeze(-1) * a
            length += alive.long()
            done = nxt["done"].squeeze(-1) & alive
            captured |= done & nxt["captured"].squeeze(-1)
            low = (nxt["positions"][..., 2] <= env.ground_altitude).any(-1)
            grounded |= done & low & ~nxt["captured"].squeeze(-1)
            alive &= ~done
            td = nxt.exclude("reward", "done", "terminated", "truncated")
    time_to_capture = torch.where(captured, length * env.control_period, float("nan"))
    return EpisodeResults(
        scenario_index=index.cpu(),
        captured=captured.cpu(),
        grounded=grounded.cpu(),
        returns=returns.cpu(),
        length=length.cpu(),
        time_to_capture=time_to_capture.float().cpu(),
        term_sums={k: v.cpu() for k, v in terms.items()},
    )
