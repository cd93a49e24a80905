"""The default SAC learns: an easy pursuit, a fixed bar, a few minutes of CPU."""

import pytest
from omegaconf import OmegaConf

from rlplat.agents import train
from rlplat.config import compose_config
from rlplat.scenarios import ScenarioSet, ScenarioSpec, write_scenario_set

# A slow defender, a fast attacker starting within 15 m, episodes of 20 s.
EASY = (
    "scenario.n_train=512",
    "scenario.n_val=64",
    "scenario.n_test=64",
    "scenario.params.defender_max_speed.high=1.5",
    "scenario.params.attacker_max_speed.low=4",
    "scenario.params.attacker_dx.low=-15",
    "scenario.params.attacker_dx.high=15",
    "scenario.params.attacker_dy.low=-15",
    "scenario.params.attacker_dy.high=15",
    "scenario.params.attacker_dz.low=-5",
    "scenario.params.attacker_dz.high=5",
)
THRESHOLD = 0.6  # validation capture rate the default SAC must pass


@pytest.mark.slow
def test_default_sac_learns_an_easy_pursuit(tmp_path):
    spec_cfg = compose_config("scenarios", ["out_dir=unused", *EASY])
    write_scenario_set(ScenarioSpec.from_dict(OmegaConf.to_container(spec_cfg.scenario)), tmp_path)
    cfg = compose_config(
        "train",
        [
            f"scenarios_dir={tmp_path}",
            "env.time_limit=20",
            "train.max_minutes=2.5",
            "train.total_frames=60000",
            "train.eval_every_frames=8192",
            "train.progress=false",
        ],
    )
    summary = train(cfg, run_dir=tmp_path / "run")
    first = _first_validation(tmp_path / "run")
    assert first < THRESHOLD, "the task should not be solved before learning"
    assert summary["best_val_capture_rate"] >= THRESHOLD, summary
    assert summary["test_capture_rate"] >= THRESHOLD - 0.15, summary
    assert ScenarioSet.load(tmp_path).digest == summary["scenario_digest"]


def _first_validation(run_dir) -> float:
    with open(run_dir / "metrics" / "scalars" / "eval" / "capture_rate.csv") as f:
        return float(f.readline().split(",")[1])
