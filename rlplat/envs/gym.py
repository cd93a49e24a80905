"""Gymnasium adapter with the paper API: init(env), reset(), step(action), close()."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from rlplat.envs.pursuit import PursuitEnv
from rlplat.errors import ConfigError


class PursuitGymEnv(gym.Env):
    """One pursuit of a given :class:`PursuitEnv` (a batch of one, one learning drone) as a
    ``gymnasium.Env``, for SB3 and other Gymnasium tools.

    Observation: ``Box(-inf, inf, (obs_dim,), float32)`` from the env's observation.
    Action: ``Box(-1, 1, (action_dim,), float32)``.
    ``info`` carries ``scenario_id``, ``distance``, ``visible`` and ``captured``.
    ``step()`` before the first ``reset()``, or after a step that ended the episode
    (terminated or truncated), raises Gymnasium's ``ResetNeeded``.
    """

    metadata = {"render_modes": []}

    def __init__(self, env: PursuitEnv) -> None:
        if not isinstance(env, PursuitEnv):
            raise ConfigError(
                f"gym adapter: wraps a PursuitEnv (rlplat.make_env(...)), got "
                f"{type(env).__name__}; a transform's work goes in a gymnasium wrapper instead"
            )
        if env.batch_size != torch.Size([1]):
            raise ConfigError(
                f"gym adapter: flies a batch of one env, got num_envs={env.batch_size[0]}"
            )
        if env.group is not None:
            field = "env.attackers" if env.group == "attacker" else "scenario.defenders"
            raise ConfigError(
                f"gym adapter: flies one learning drone, the scenarios give the "
                f"{env.group}s {env.team_size} ({field}: valid 1)"
            )
        self.env = env
        self.ids = env.scenario_set.ids[env.split_name]
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim = env.action_spec.shape[-1]
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)
        self._needs_reset = True

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Load the next scenario of the split (a seed restarts the walk of the split)."""
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        td = self.env.reset()
        self._needs_reset = False
        return self._obs(td), self._info(td)

    def step(self, action):
        if self._needs_reset:
            raise gym.error.ResetNeeded(
                "Cannot call env.step() before calling env.reset() (nor after an episode ends)"
            )
        action = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(1, -1)
        td = self.env.step(TensorDict(action=action, batch_size=[1]))["next"]
        terminated, truncated = bool(td["terminated"]), bool(td["truncated"])
        self._needs_reset = terminated or truncated
        return self._obs(td), float(td["reward"]), terminated, truncated, self._info(td)

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
