"""Scripted reference policies: what a learned controller must beat on the same scenarios."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rlplat.envs.pursuit import PursuitEnv


class PurePursuitPolicy:
    """Fly the learner straight at its opponent's current position (the pure-pursuit law).

    A TorchRL-style policy for :func:`rlplat.eval.episodes.evaluate`: reads the env's
    ``positions``, writes ``action``, the command ``gain * (p_other - p_own)`` saturated at the
    learner's maximum speed per axis, expressed in the action's [-1, 1] units.

    Args:
        env: the env the policy flies in (its learner index and per-env maximum speeds).
        gain: 1/s, command per metre of separation; None takes the env's ``pursuit_gain``.
    """

    def __init__(self, env: PursuitEnv, gain: float | None = None) -> None:
        self.env = env
        self.gain = env.pursuit_gain if gain is None else float(gain)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        me = self.env.learner
        p = td["positions"]
        rel = p[:, 1 - me] - p[:, me]
        speed = self.env.max_speed[:, me].unsqueeze(-1)
        return td.set("action", (self.gain * rel / speed).clamp(-1.0, 1.0))


class NoisyPolicy:
    """A scripted policy with Gaussian exploration: ``clamp(action + noise_std * N(0, 1))``.

    Fills a replay buffer with a classical controller's experience, widened by noise so that
    the critic sees actions around the controller's too. Draws from torch's global generator
    (seeded by the run).
    """

    def __init__(self, policy, noise_std: float) -> None:
        self.policy = policy
        self.noise_std = float(noise_std)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td)
        action = td["action"]
        noise = torch.randn(action.shape, device=action.device, dtype=action.dtype)
        return td.set("action", (action + self.noise_std * noise).clamp(-1.0, 1.0))
