"""``python -m rlplat.scenarios out_dir=DIR [scenario.seed=7 scenario.n_train=2000 ...]``."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from rlplat.cli import hydra_main
from rlplat.errors import ConfigError
from rlplat.scenarios import ScenarioSpec, format_quality, write_scenario_set


def spec_of(cfg: DictConfig) -> ScenarioSpec:
    """The set a composed ``conf/scenarios.yaml`` asks for; one line if it cannot be made."""
    if OmegaConf.is_missing(cfg, "out_dir"):
        raise ConfigError("out_dir: missing (???); give out_dir=DIR, the folder for the set")
    return ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))


@hydra_main("scenarios", spec_of)
def main(cfg: DictConfig) -> None:
    spec = spec_of(cfg)
    manifest = write_scenario_set(spec, cfg.out_dir)
    counts = ", ".join(f"{s} {v['count']}" for s, v in manifest["splits"].items())
    print(f"scenario set (seed {spec.seed}): {counts} -> {cfg.out_dir}")
    print(format_quality(manifest["quality"]))


if __name__ == "__main__":
    main()
