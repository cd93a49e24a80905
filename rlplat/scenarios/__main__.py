"""``python -m rlplat.scenarios out_dir=DIR [scenario.seed=7 scenario.n_train=2000 ...]``."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from rlplat.cli import exit_on_error
from rlplat.experiment.config import CONF_DIR
from rlplat.scenarios import ScenarioSpec, format_quality, write_scenario_set


@hydra.main(config_path=str(CONF_DIR), config_name="scenarios", version_base="1.3")
@exit_on_error
def main(cfg: DictConfig) -> None:
    spec = ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))
    manifest = write_scenario_set(spec, cfg.out_dir)
    counts = ", ".join(f"{s} {v['count']}" for s, v in manifest["splits"].items())
    print(f"scenario set (seed {spec.seed}): {counts} -> {cfg.out_dir}")
    print(format_quality(manifest["quality"]))


if __name__ == "__main__":
    main()
