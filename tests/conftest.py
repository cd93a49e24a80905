import pytest
from omegaconf import OmegaConf

from rlplat.experiment.config import compose_config
from rlplat.scenarios import ScenarioSpec


def spec_from(*overrides: str) -> ScenarioSpec:
    """Build a ScenarioSpec through real Hydra composition of conf/scenarios.yaml."""
    cfg = compose_config("scenarios", ["out_dir=unused", *overrides])
    return ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))


@pytest.fixture
def make_spec():
    return spec_from
