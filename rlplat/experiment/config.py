"""Where the Hydra configs live, and composing them outside ``@hydra.main`` (notebooks, tests)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

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
    args = {"config_name": config_name, "overrides": list(overrides), "return_hydra_config": hydra}
    if GlobalHydra.instance().is_initialized():
        return compose(**args)
    # The job is named after its config, as under the entry point (${hydra.job.name}).
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name=config_name):
        return compose(**args)
