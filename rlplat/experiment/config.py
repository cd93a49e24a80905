"""Where the Hydra configs live, and composing them outside ``@hydra.main`` (notebooks, tests)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from rlplat.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def sweep_dir(run_dir: str | None, folder: str, otherwise: str) -> str:
    """``hydra.sweep.dir`` of ``evaluate.py`` and ``export.py`` (``${rlplat.sweep_dir:...}``):
    ``<run_dir>/<folder>`` for a sweep of one run; for a sweep over runs (``run_dir`` swept,
    so unset in the sweep's own config) or over controller files, ``otherwise``: Hydra's own
    ``multirun/${now:...}``, whose time Hydra keeps for the whole sweep. Either way each job
    writes in its own run's folder."""
    return otherwise if run_dir is None else str(Path(run_dir) / folder)


if not OmegaConf.has_resolver("rlplat.sweep_dir"):
    OmegaConf.register_new_resolver("rlplat.sweep_dir", sweep_dir)


def compose_config(
    config_name: str, overrides: Sequence[str] = (), hydra: bool = False
) -> DictConfig:
    """Compose ``conf/<config_name>.yaml`` with command-line style ``overrides`` (with
    ``hydra``, also Hydra's own ``hydra`` node); inside an entry point's ``@hydra.main``
    (whose search path is this ``conf/``) through its Hydra."""
    check_group_choices(overrides)
    args = {"config_name": config_name, "overrides": list(overrides), "return_hydra_config": hydra}
    if GlobalHydra.instance().is_initialized():
        return compose(**args)
    # The job is named after its config, as under the entry point (${hydra.job.name}).
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name=config_name):
        return compose(**args)


def group_options(group: str) -> list[str] | None:
    """The options of a config group of conf/ (its files' names), None for another group
    (Hydra's own, whose plugins add options: ``hydra/launcher``)."""
    group = group.lstrip("+")
    folder = CONF_DIR / group
    if group.split("/")[0] == "hydra" or not folder.is_dir():
        return None
    return sorted(p.stem for p in folder.glob("*.yaml"))


def check_group_choices(overrides: Sequence[str]) -> None:
    """Each of conf/'s groups set on the command line picks one option: Hydra would compose a
    list's options on top of each other (``drone=[attacker_v13,attacker_v1]``: neither bundle)
    and fail on ``null`` with a traceback.

    Raises:
        ConfigError: one line naming the group, what it was given and its options.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except OverrideParseException:
        return  # Hydra's to refuse, in its words
    for o in parsed:
        options = group_options(o.key_or_group)
        if options is None or o.is_delete() or o.is_sweep_override():
            continue
        value = o.value()
        if value is None or not isinstance(value, str):
            raise ConfigError(
                f"{o.key_or_group.lstrip('+')}={o.get_value_element_as_str()}: a config group "
                f"takes one option (valid: {', '.join(sorted(options, key=natural))})"
            )


def natural(name: str) -> list[Any]:
    """Sort key that puts attacker_v2 before attacker_v10."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]
