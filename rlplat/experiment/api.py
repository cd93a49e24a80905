"""Notebook-friendly entry points, composed from the same Hydra config as ``train.py``."""

from __future__ import annotations

import os

import torch

from rlplat.envs.gym import PursuitGymEnv
from rlplat.envs.pursuit import PursuitEnv
from rlplat.experiment.config import compose_config
from rlplat.experiment.factory import build_env, resolve_scenarios
from rlplat.scenarios import ScenarioSet


def make_env(
    *overrides: str,
    num_envs: int = 1,
    scenarios: ScenarioSet | str | os.PathLike | None = None,
    split: str = "train",
    device: str | torch.device = "cpu",
) -> PursuitEnv:
    """The batched TorchRL pursuit env.

    Args:
        *overrides: Hydra overrides, e.g. ``"drone=attacker_v1", "reward=sparse"``.
        num_envs: batch size N.
        scenarios: a loaded set or its directory; None generates the configured set once into a
            cache directory.
        split: ``train``, ``val`` or ``test``.
        device: torch device of the env's tensors.
    """
    cfg = compose_config("train", overrides)
    return build_env(
        cfg,
        scenarios=resolve_scenarios(cfg, scenarios),
        split=split,
        num_envs=num_envs,
        device=device,
    )


def make_gym_env(
    *overrides: str,
    scenarios: ScenarioSet | str | os.PathLike | None = None,
    split: str = "train",
) -> PursuitGymEnv:
    """A ``gymnasium.Env`` of one pursuit, for Gymnasium tools such as Stable-Baselines3.

    Takes the same arguments as :func:`make_env` (one env); the adapter wraps that env.
    """
    return PursuitGymEnv(make_env(*overrides, num_envs=1, scenarios=scenarios, split=split))
