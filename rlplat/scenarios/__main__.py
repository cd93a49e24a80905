"""``python -m rlplat.scenarios out_dir=DIR [scenario.seed=7 scenario.n_train=2000 ...]``."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rlplat.errors import ConfigError
from rlplat.experiment.command_line import hydra_main
from rlplat.experiment.rules import Text
from rlplat.scenarios import ScenarioSpec, format_quality, write_scenario_set

#: What marks a folder as a training run's, or an evaluation's: no place for a scenario set.
RUN_FILES = ("config.yaml", "summary.json", "checkpoints", "episodes.csv")


def spec_of(cfg: DictConfig) -> ScenarioSpec:
    """The set a composed ``conf/scenarios.yaml`` asks for; one line if it cannot be made."""
    if OmegaConf.is_missing(cfg, "out_dir"):
        raise ConfigError("out_dir: missing (???); give out_dir=DIR, the folder for the set")
    problem = Text()(cfg.out_dir)  # out_dir= would write the set into the working directory
    if problem:
        raise ConfigError(f"out_dir: {problem}; give out_dir=DIR, the folder for the set")
    held = [name for name in RUN_FILES if (Path(cfg.out_dir) / name).exists()]
    if held:  # a set's four files would land among a run's own
        raise ConfigError(
            f"out_dir: {cfg.out_dir} holds a run ({held[0]}); give the set its own folder"
        )
    run = next((up for up in Path(cfg.out_dir).absolute().parents if _is_run(up)), None)
    if run is not None:  # e.g. a run's checkpoints/ or eval/ folder
        raise ConfigError(
            f"out_dir: {cfg.out_dir} lies in the run {run}; give the set its own folder"
        )
    try:
        scenario = OmegaConf.to_container(cfg.scenario, resolve=True)
    except OmegaConfBaseException as e:  # an interpolation that does not resolve
        raise ConfigError(f"{e.full_key}: {str(e).splitlines()[0]}") from None
    return ScenarioSpec.from_dict(scenario)


def _is_run(folder: Path) -> bool:
    """Whether ``folder`` is a training run's: its config.yaml beside its checkpoints or summary."""
    return (folder / "config.yaml").is_file() and (
        (folder / "checkpoints").is_dir() or (folder / "summary.json").is_file()
    )


@hydra_main("scenarios", spec_of)
def main(cfg: DictConfig) -> None:
    spec = spec_of(cfg)
    manifest = write_scenario_set(spec, cfg.out_dir)
    counts = ", ".join(f"{s} {v['count']}" for s, v in manifest["splits"].items())
    print(f"scenario set (seed {spec.seed}): {counts} -> {cfg.out_dir}")
    print(format_quality(manifest["quality"]))


if __name__ == "__main__":
    main()
