import pytest
from omegaconf import OmegaConf

from rlplat.config import compose_config
from rlplat.scenarios import ScenarioSpec


@pytest.fixture
def make_spec():
    """Build a ScenarioSpec through real Hydra composition of conf/scenarios.yaml."""

    def _make(*overrides: str) -> ScenarioSpec:
        cfg = compose_config("scenarios", ["out_dir=unused", *overrides])
        return ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))

    return _make
