"""Gymnasium adapter with the paper API: init(scenarios), reset(), step(action), close()."""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from rlplat.errors import ConfigError
from rlplat.scenarios import ScenarioSet


class PursuitGymEnv(gym.Env):
    """One pursuit (a batch of one) as a ``gymnasium.Env``, for SB3 and other Gymnasium tools.

    Observation: ``Box(-inf, inf, (obs_dim,), float32)`` from the configured observation.
    Action: ``Box(-1, 1, (action_dim,), float32)``.
    ``info`` carries ``scenario_id``, ``distance``, ``visible`` and ``captured``.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        scenarios: ScenarioSet | str | os.PathLike | None = None,
        *overrides: str,
        split: str = "train",
    ) -> None:
        from rlplat.config import compose_config
        from rlplat.envs.factory import build_env, resolve_scenarios

        cfg = compose_config("train", overrides)
        self.scenario_set = resolve_scenarios(cfg, scenarios)
        self.env = build_env(cfg, scenarios=self.scenario_set, split=split, num_envs=1)
        if self.env.group is not None:
            field = "env.attackers" if self.env.group == "attacker" else "scenario.defenders"
            raise ConfigError(
                f"gym adapter: flies one learning drone, the scenarios give the "
                f"{self.env.group}s {self.env.team_size} ({field}: valid 1)"
            )
        self.ids = self.scenario_set.ids[split]
        obs_dim = self.env.observation_spec["observation"].shape[-1]
        act_dim = self.env.action_spec.shape[-1]
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Load the next scenario of the split (a seed restarts the walk of the split)."""
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        td = self.env.reset()
        return self._obs(td), self._info(td)

    def step(self, action):
        action = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(1, -1)
        td = self.env.step(TensorDict(action=action, batch_size=[1]))["next"]
        return (
            self._obs(td),
            float(td["reward"]),
            bool(td["terminated"]),
            bool(td["truncated"]),
            self._info(td),
        )

    def close(self) -> None:
        self.env.close()

    @staticmethod
    def _obs(td: TensorDict) -> np.ndarray:
        return td["observation"][0].cpu().numpy().astype(np.float32)

    def _info(self, td: TensorDict) -> dict[str, Any]:
        return {
            "scenario_id": self.ids[int(td["scenario_index"])],
            "distance": float(td["distance"]),
            "visible": bool(td["visible"]),
            "captured": bool(td["captured"]),
        }
