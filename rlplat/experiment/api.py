"""Notebook-friendly entry points, composed from the same Hydra config as ``train.py``."""

from __future__ import annotations

import os

import torch

from rlplat.envs.gym import PursuitGymEnv
from rlplat.envs.pursuit import PursuitEnv
from rlplat.errors import ConfigError
from rlplat.experiment.config import compose_config
from rlplat.experiment.factory import (
    build_env,
    require_scenarios,
    resolve_scenarios,
    with_set_scenario,
)
from rlplat.experiment.rules import COUNT, Choice, show
from rlplat.experiment.rules import device as device_rule
from rlplat.experiment.schema import validate_train_config
from rlplat.scenarios import SPLITS, ScenarioSet


def make_env(
    *overrides: str,
    num_envs: int = 1,
    scenarios: ScenarioSet | str | os.PathLike | None = None,
    split: str = "train",
    device: str | torch.device = "cpu",
    share: tuple[int, int] = (0, 1),
) -> PursuitEnv:
    """The batched TorchRL pursuit env: the one ``train.py`` builds from the same overrides
    and scenario set, after the same checks (one line naming the field, before any work).

    Args:
        *overrides: Hydra overrides, e.g. ``"drone=attacker_v1", "reward=sparse"``
            (``"scenarios_dir=DIR"`` as for ``train.py``).
        num_envs: batch size N.
        scenarios: a loaded set or its directory; None: the override's ``scenarios_dir``, or
            else the configured set, generated once into a cache directory. A set flies with
            the scenario config it was generated with (its vision ellipsoid, ...), as in
            training.
        split: ``train``, ``val`` or ``test``.
        device: torch device of the env's tensors.
        share: ``(i, c)``: this env is the i-th of c that split one walk of the split, each
            taking every c-th scenario from the i-th on, as one batch of c envs would; for the
            c workers of a TorchRL ``SerialEnv``/``ParallelEnv`` (``make_env(num_envs=1,
            share=(i, c))`` in worker i), which otherwise all fly the same scenarios.
    """
    if not (
        isinstance(share, tuple | list)
        and len(share) == 2
        and all(isinstance(x, int) and not isinstance(x, bool) for x in share)
        and 0 <= share[0] < share[1]
    ):
        raise ConfigError(f"share: must be (index, count) with 0 <= index < count, got {share!r}")
    for name, value, rule in (
        ("num_envs", num_envs, COUNT),
        ("split", split, Choice(SPLITS)),
        ("device", str(device) if isinstance(device, torch.device) else device, device_rule),
    ):
        if (problem := rule(value)) is not None:
            raise ConfigError(f"{name}: {problem}")
    if scenarios is not None and not isinstance(scenarios, ScenarioSet | str | os.PathLike):
        raise ConfigError(
            f"scenarios: must be a ScenarioSet, a directory or None, got {show(scenarios)}"
        )
    cfg = compose_config("train", overrides)
    if scenarios is not None and cfg.scenarios_dir is not None:
        raise ConfigError(
            f"scenarios: given with scenarios_dir={cfg.scenarios_dir} too; pass one of them"
        )
    checked = cfg
    if scenarios is not None:  # checked as the set in scenarios_dir it stands for
        checked = cfg.copy()
        checked.scenarios_dir = str(
            scenarios.path if isinstance(scenarios, ScenarioSet) else scenarios
        )
    validate_train_config(checked, env_batch=num_envs)  # the env's checks, not training's
    given = scenarios is not None
    source, field = (scenarios, "scenarios") if given else (cfg.scenarios_dir, "scenarios_dir")
    loaded = resolve_scenarios(cfg, source, field)
    require_scenarios(loaded, [split], "the env", field)
    if source is not None:
        cfg = with_set_scenario(cfg, loaded)  # the set's config: what training flies
    return build_env(cfg, scenarios=loaded, split=split, num_envs=num_envs, device=device,
                     scenario_share=tuple(share))  # fmt: skip


def make_gym_env(
    *overrides: str,
    scenarios: ScenarioSet | str | os.PathLike | None = None,
    split: str = "train",
) -> PursuitGymEnv:
    """A ``gymnasium.Env`` of one pursuit, for Gymnasium tools such as Stable-Baselines3.

    Takes the same arguments as :func:`make_env` (one env); the adapter wraps that env.
    """
    return PursuitGymEnv(make_env(*overrides, num_envs=1, scenarios=scenarios, split=split))
