"""Build envs from the composed Hydra config: scenario sets, components, the defender network.

The env knows no learner: the network its ``nn`` defenders fly is loaded here and injected."""

from __future__ import annotations

import hashlib
import inspect
import json
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from rlplat.agents.policies import load_controller
from rlplat.envs.components import ACTIONS, OBSERVATIONS, Reward
from rlplat.envs.dynamics import DYNAMICS
from rlplat.envs.pursuit import PursuitEnv, flown_attackers
from rlplat.errors import ConfigError
from rlplat.scenarios import STRATEGIES, ScenarioSet, ScenarioSpec, write_scenario_set

log = logging.getLogger(__name__)

#: Where generated default scenario sets are cached (overridable by RLPLAT_CACHE).
CACHE_DIR = Path(os.environ.get("RLPLAT_CACHE", Path.home() / ".cache" / "rlplat"))


def checked_kwargs(
    fn: Callable[..., Any], node: Mapping[str, Any], where: str, reserved: tuple[str, ...] = ()
) -> dict[str, Any]:
    """``node`` as keyword arguments of ``fn``; an unknown key fails naming the valid ones."""
    target = fn.__init__ if inspect.isclass(fn) else fn
    params = list(inspect.signature(target).parameters)
    if inspect.isclass(fn):
        params = params[1:]  # self
    valid = [p for p in params if p not in reserved]
    for key in node:
        if key not in valid:
            raise ConfigError(f"{where}.{key}: unknown option; valid: {', '.join(valid)}")
    return dict(node)


def build_component(registry: Mapping[str, Callable[..., Any]], group: str, node, **extra):
    """Instantiate ``registry[node.name]`` with the node's other keys (checked) and ``extra``."""
    node = dict(node)
    name = node.pop("name", None)
    if name not in registry:
        raise ConfigError(f"{group}.name: unknown {group} '{name}'; valid: {', '.join(registry)}")
    cls = registry[name]
    return cls(**checked_kwargs(cls, node, group, reserved=tuple(extra)), **extra)


def resolve_scenarios(cfg: DictConfig, scenarios: ScenarioSet | str | os.PathLike | None):
    """A loaded set, a directory to load, or (None) the configured set, generated and cached."""
    if isinstance(scenarios, ScenarioSet):
        return scenarios
    if scenarios is not None:
        return ScenarioSet.load(scenarios)
    spec = ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))
    key = hashlib.sha256(json.dumps(spec.to_dict(), sort_keys=True).encode()).hexdigest()[:16]
    path = CACHE_DIR / "scenarios" / key
    if not (path / "manifest.json").exists():
        log.info("generating the configured scenario set into %s", path)
        write_scenario_set(spec, path)
    return ScenarioSet.load(path)


def build_env(
    cfg: DictConfig,
    *,
    scenarios: ScenarioSet,
    split: str = "train",
    num_envs: int = 1,
    device: str | torch.device = "cpu",
    **env_overrides: Any,
) -> PursuitEnv:
    """The env described by ``cfg`` (groups dynamics/observation/action/reward/drone, node env).

    ``env_overrides`` replace keys of the ``env`` node (e.g. ``scenario_order="sequential"`` for
    an evaluation env).
    """
    if num_envs < 1:
        raise ConfigError(f"num_envs: must be >= 1, got {num_envs}")
    c = OmegaConf.to_container(cfg, resolve=True)
    env_node = {**c["env"], **env_overrides}
    k, m = flown_attackers(env_node.get("attackers"), scenarios), scenarios.defenders
    dynamics = build_component(
        DYNAMICS, "dynamics", c["dynamics"], num_envs=num_envs, num_drones=k + m, device=device
    )
    # What each learner sees: every opponent and every team-mate.
    team, opponents = (k, m) if c["drone"]["learner"] == "attacker" else (m, k)
    reward = Reward(**checked_kwargs(Reward, c["reward"], "reward"))
    env_kwargs = checked_kwargs(
        PursuitEnv,
        env_node,
        "env",
        reserved=(
            "scenarios",
            "dynamics",
            "observation",
            "action",
            "reward",
            "split",
            "learner",
            "device",
        ),
    )
    network = _defender_network(
        env_kwargs.get("defender_network"), scenarios, split, c["drone"]["learner"]
    )
    env_kwargs["defender_network"] = None if network is None else network.to(device)
    return PursuitEnv(
        scenarios=scenarios,
        dynamics=dynamics,
        observation=build_component(
            OBSERVATIONS,
            "observation",
            c["observation"],
            opponents=opponents,
            mates=team - 1,
            in_play=m > 1,
        ),  # fmt: skip
        action=build_component(ACTIONS, "action", c["action"]),
        reward=reward,
        split=split,
        learner=c["drone"]["learner"],
        device=device,
        **env_kwargs,
    )


def _defender_network(path: str | None, scenarios: ScenarioSet, split: str, learner: str):
    """The network that flies the split's ``nn`` defenders (``env.defender_network``; null =
    the shipped one); None where no scripted defender needs one."""
    nn_rows = scenarios.split(split)["defender_strategy"] == STRATEGIES.index("nn")  # (n, m)
    if learner != "attacker" or not bool(nn_rows.any()):
        return None
    return load_controller(path, "defender", "env.defender_network")
