"""Build envs from the composed Hydra config: scenario sets, components, the defender network.

The env knows no learner: the network its ``nn`` defenders fly is loaded here and injected.
With ``dynamics=airsim`` an env batch is one env per simulator, in parallel worker processes."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from rlplat.agents.policies import load_controller
from rlplat.envs.components import ACTIONS, OBSERVATIONS, Reward
from rlplat.envs.dynamics import DYNAMICS, DroneDynamics
from rlplat.envs.parallel import PursuitParallelEnv, worker_env
from rlplat.envs.pursuit import PursuitEnv, flown_attackers
from rlplat.errors import ConfigError, ScenarioFileError
from rlplat.experiment.rules import keyword_parameters
from rlplat.scenarios import STRATEGIES, ScenarioSet, ScenarioSpec, write_scenario_set

log = logging.getLogger(__name__)

#: Where generated default scenario sets are cached (overridable by RLPLAT_CACHE).
CACHE_DIR = Path(os.environ.get("RLPLAT_CACHE", Path.home() / ".cache" / "rlplat"))


def checked_kwargs(
    fn: Callable[..., Any], node: Mapping[str, Any], where: str, reserved: tuple[str, ...] = ()
) -> dict[str, Any]:
    """``node`` as keyword arguments of ``fn``; an unknown key fails naming the valid ones."""
    params = list(keyword_parameters(fn))
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


def resolve_scenarios(
    cfg: DictConfig,
    scenarios: ScenarioSet | str | os.PathLike | None,
    field: str = "scenarios_dir",
):
    """A loaded set, a directory to load (an error names ``field``, what the user set), or
    (None) the configured set, generated and cached."""
    if isinstance(scenarios, ScenarioSet):
        return scenarios
    if scenarios is not None:
        try:
            return ScenarioSet.load(scenarios)
        except (ScenarioFileError, ConfigError) as e:  # the field set, then what is wrong there
            raise type(e)(f"{field}: {e}") from None
    spec = ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))
    key = hashlib.sha256(json.dumps(spec.to_dict(), sort_keys=True).encode()).hexdigest()[:16]
    path = CACHE_DIR / "scenarios" / key
    if not (path / "manifest.json").exists():
        log.info("generating the configured scenario set into %s", path)
        try:
            write_scenario_set(spec, path)
        except ConfigError as e:  # not the user's out_dir: the cache, and how to move it
            if not str(e).startswith("out_dir: "):
                raise
            raise ConfigError(
                f"RLPLAT_CACHE: the configured scenario set is cached under {CACHE_DIR}, and "
                f"{str(e).removeprefix('out_dir: ')} (set RLPLAT_CACHE to a writable folder, "
                "or pass scenarios_dir=)"
            ) from None
    return ScenarioSet.load(path)


def with_set_scenario(cfg: DictConfig, scenarios: ScenarioSet) -> DictConfig:
    """``cfg`` with its ``scenario`` node replaced by the config ``scenarios`` was generated
    with (a set loaded from ``scenarios_dir``), so that what reads it (``env.vision_semi_axes``,
    the run's ``config.yaml``) follows the set flown; a composed ``scenario`` that differs is
    not flown, and a warning names how it differs; an ``env.vision_semi_axes`` set apart
    from the set's is a warning too. ``cfg`` itself is left as it is."""
    if scenarios.spec is None:
        return cfg
    spec = ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))
    flown, composed = dataclasses.asdict(scenarios.spec), dataclasses.asdict(spec)
    # How a team is drawn (its separation, its defenders' spread) means nothing to a 1-vs-1
    # set: with one, only the team's sizes differ.
    teams = all(s.attackers > 1 or s.defenders > 1 for s in (scenarios.spec, spec))
    skip = set() if teams else {"min_separation", "defender_spread"}
    differ = sorted(k for k in flown if k not in skip and flown[k] != composed[k])
    if differ:  # a set's own seed and split sizes are what a set is drawn with, not a misfit
        sized = set(differ) <= {"seed", "n_train", "n_val", "n_test"}
        log.log(
            logging.INFO if sized else logging.WARNING,
            "scenario: the set in %s was generated with another scenario config (%s differ); "
            "its config is flown and recorded, not the composed one",
            scenarios.path, ", ".join(differ),
        )  # fmt: skip
    cfg = cfg.copy()
    with open_dict(cfg):  # every field, the team ones of a 1-vs-1 set too, as composed
        cfg.scenario = OmegaConf.create(json.loads(json.dumps(dataclasses.asdict(scenarios.spec))))
    warn_vision_apart(cfg.env.vision_semi_axes, scenarios, "the env")  # set apart from it
    return cfg


def warn_vision_apart(
    sees: Sequence[float], scenarios: ScenarioSet, who: str, flown: str = ""
) -> None:
    """A warning where the vision ellipsoid ``who`` sees within differs from the one the
    set's starts were drawn in (``flown``: what is then done, appended)."""
    drawn = None if scenarios.spec is None else list(scenarios.spec.vision_semi_axes)
    if drawn is not None and list(sees) != drawn:
        log.warning("env.vision_semi_axes: %s sees within %s m, the set's starts were drawn "
                    "within %s m%s", who, list(sees), drawn, flown)  # fmt: skip


def require_scenarios(
    scenarios: ScenarioSet, splits: Sequence[str], needed_by: str, field: str = "scenarios_dir"
) -> None:
    """Refuse, in one line naming ``field``, a set with no scenario in one of ``splits`` (a
    set may leave a split empty, e.g. a test-only set; what flies it may not)."""
    for split in splits:
        if len(scenarios.split(split)) == 0:
            raise ConfigError(
                f"{field}: {scenarios.path} has no {split} scenarios; {needed_by} needs "
                f"the {'/'.join(splits)} split{'s' if len(splits) > 1 else ''}"
            )


def build_env(
    cfg: DictConfig,
    *,
    scenarios: ScenarioSet,
    split: str = "train",
    num_envs: int = 1,
    device: str | torch.device = "cpu",
    **env_overrides: Any,
) -> PursuitEnv | PursuitParallelEnv:
    """The env described by ``cfg`` (groups dynamics/observation/action/reward/drone, node env).

    ``env_overrides`` replace keys of the ``env`` node (e.g. ``scenario_order="sequential"`` for
    an evaluation env). With ``dynamics=airsim`` each env flies on one simulator of
    ``dynamics.endpoints`` (``num_envs`` must be their number): one is a PursuitEnv, several a
    :class:`~rlplat.envs.parallel.PursuitParallelEnv` of batch [num_envs] (one worker process
    per simulator, stepped at once).
    """
    if num_envs < 1:
        raise ConfigError(f"num_envs: must be >= 1, got {num_envs}")
    c = OmegaConf.to_container(cfg, resolve=True)
    if c["dynamics"].get("name") != "airsim":
        return _pursuit_env(c, scenarios, split, num_envs, device, env_overrides)
    endpoints = c["dynamics"].get("endpoints") or []
    if isinstance(endpoints, str) or num_envs != len(endpoints):
        raise ConfigError(
            f"num_envs: {num_envs}, dynamics.endpoints names {len(endpoints)} simulator(s) "
            f"(one env per simulator): {endpoints!r}"
        )
    if {**c["env"], **env_overrides}.get("compile_step"):
        raise ConfigError("env.compile_step: true, must be false with dynamics=airsim")
    if num_envs == 1:
        return _pursuit_env(c, scenarios, split, 1, device, env_overrides)
    # Every simulator is checked here first (one line per fault, before any worker starts).
    k = flown_attackers({**c["env"], **env_overrides}.get("attackers"), scenarios)
    for endpoint in endpoints[1:]:  # the first is connected below, for the specs
        _dynamics({**c["dynamics"], "endpoints": [endpoint]}, 1, k, scenarios.defenders,
                  device).close()  # fmt: skip
    placeholder = DroneDynamics(
        num_envs=num_envs, num_drones=k + scenarios.defenders, device=device, physics_dt=1.0
    )
    template = _pursuit_env(c, scenarios, split, num_envs, device, env_overrides, placeholder)
    workers = [
        {
            "config": {**c, "dynamics": {**c["dynamics"], "endpoints": [endpoint]}},
            "scenarios": scenarios,
            "split": split,
            "device": str(device),
            "env_overrides": {**env_overrides, "scenario_share": (i, num_envs)},
        }
        for i, endpoint in enumerate(endpoints)
    ]
    log.info("flying %d envs on the simulators %s", num_envs, ", ".join(endpoints))
    return PursuitParallelEnv(
        airsim_worker, workers, template=template, device=device, mp_start_method="spawn"
    )


def airsim_worker(
    config: dict[str, Any],
    scenarios: ScenarioSet,
    split: str,
    device: str,
    env_overrides: dict[str, Any],
    fault_path: str | None,
):
    """One worker of an AirSim parallel env: the single-env pursuit on its simulator."""
    env = _pursuit_env(config, scenarios, split, 1, device, env_overrides)
    return worker_env(env, fault_path)


def _dynamics(node: Mapping[str, Any], num_envs: int, k: int, m: int, device) -> DroneDynamics:
    """The configured dynamics model for envs of ``k`` attackers and ``m`` defenders."""
    extra = {"num_attackers": k} if node.get("name") == "airsim" else {}
    return build_component(
        DYNAMICS, "dynamics", node, num_envs=num_envs, num_drones=k + m, device=device, **extra
    )


def _pursuit_env(
    c: dict[str, Any],
    scenarios: ScenarioSet,
    split: str,
    num_envs: int,
    device: str | torch.device,
    env_overrides: Mapping[str, Any],
    dynamics: DroneDynamics | None = None,
) -> PursuitEnv:
    """The batched PursuitEnv of the resolved config ``c`` (its dynamics built unless given)."""
    env_node = {**c["env"], **env_overrides}
    k, m = flown_attackers(env_node.get("attackers"), scenarios), scenarios.defenders
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
    observation = build_component(
        OBSERVATIONS, "observation", c["observation"], opponents=opponents, mates=team - 1,
        in_play=m > 1,
    )  # fmt: skip
    action = build_component(ACTIONS, "action", c["action"])
    if dynamics is None:  # last: a simulator is connected only once the rest is checked
        dynamics = _dynamics(c["dynamics"], num_envs, k, m, device)
    return PursuitEnv(
        scenarios=scenarios,
        dynamics=dynamics,
        observation=observation,
        action=action,
        reward=reward,
        split=split,
        learner=c["drone"]["learner"],
        device=device,
        **env_kwargs,
    )


def build_eval_env(
    cfg: DictConfig,
    *,
    scenarios: ScenarioSet,
    split: str,
    num_envs: int,
    device: str | torch.device = "cpu",
    **env_overrides: Any,
) -> PursuitEnv | PursuitParallelEnv:
    """The env an evaluation flies: ``split`` walked in order (what
    :func:`rlplat.eval.episodes.evaluate` needs) on the eager step, whatever ``env.compile_step``
    says. Compiled kernels round differently and flip a few closed-loop episodes, so no figure
    depends on how a run trained; a run's validation passes ``compile_step`` to compile it.
    ``env_overrides`` as in :func:`build_env`."""
    overrides = {"scenario_order": "sequential", "compile_step": False, **env_overrides}
    return build_env(
        cfg, scenarios=scenarios, split=split, num_envs=num_envs, device=device, **overrides
    )


def eval_num_envs(cfg: DictConfig, scenarios: int) -> int:
    """How many envs fly an evaluation of ``scenarios`` scenarios: all at once on an embedded
    model; on AirSim, one per simulator (the split flown in waves)."""
    if cfg.dynamics.name == "airsim":
        return len(cfg.dynamics.endpoints)
    return scenarios


def _defender_network(path: str | None, scenarios: ScenarioSet, split: str, learner: str):
    """The network that flies the split's ``nn`` defenders (``env.defender_network``; null =
    the shipped one); None where no scripted defender needs one."""
    nn_rows = scenarios.split(split)["defender_strategy"] == STRATEGIES.index("nn")  # (n, m)
    if learner != "attacker" or not bool(nn_rows.any()):
        return None
    return load_controller(path, "defender", "env.defender_network")
