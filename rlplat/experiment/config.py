"""Where the Hydra configs live, and composing them outside ``@hydra.main`` (notebooks, tests)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


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
