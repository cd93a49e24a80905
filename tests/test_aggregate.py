import csv
import json
import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from rlplat.errors import ConfigError


def fake_sweep(root: Path, scores: dict[str, list[tuple[int, float, float]]]) -> None:
    """Run directories as `train.py -m` leaves them: config.yaml, summary.json, overrides."""
    job = 0
    for variant, runs in scores.items():
        for seed, rate, ret in runs:
            run = root / str(job)
            (run / ".hydra").mkdir(parents=True)
            (run / "config.yaml").write_text(f"seed: {seed}\n")
            overrides = [f"seed={seed}", "train.max_minutes=1"]
            overrides += [variant] if variant != "default" else []
            OmegaConf.save(OmegaConf.create(overrides), run / ".hydra" / "overrides.yaml")
            summary = {"seed": seed, "test_capture_rate": rate, "test_mean_return": ret}
            (run / "summary.json").write_text(json.dumps(summary))
            job += 1


def test_cli_aggregates_seeds_per_configuration(tmp_path, run_python):
    fake_sweep(
        tmp_path,
        {
            "default": [(0, 0.2, -50.0), (1, 0.4, -40.0), (2, 0.6, -30.0), (3, 0.8, -20.0)],
            "drone=attacker_v1": [(0, 0.1, -90.0), (1, 0.3, -80.0)],
        },
    )
    (tmp_path / "0" / "eval" / "test-best").mkdir(parents=True)  # evaluations are not runs
    (tmp_path / "0" / "eval" / "test-best" / "summary.json").write_text("{}")
    res = run_python("-m", "rlplat.eval.aggregate", str(tmp_path), "--reps", "500")
    assert res.returncode == 0, res.stderr[-2000:]
    summary = json.loads((tmp_path / "aggregate" / "summary.json").read_text())
    assert summary["common_overrides"] == ["train.max_minutes=1"]  # not a variant's name
    assert list(summary["variants"]) == ["default", "drone=attacker_v1"]
    default = summary["variants"]["default"]["test_capture_rate"]
    assert default["iqm"] == pytest.approx(0.5)  # mean of the middle two seeds
    assert default["mean"] == pytest.approx(0.5)
    assert 0.2 <= default["iqm_ci95"][0] < 0.5 < default["iqm_ci95"][1] <= 0.8
    v1 = summary["variants"]["drone=attacker_v1"]["test_mean_return"]
    assert v1["iqm"] == pytest.approx(-85.0) and v1["mean_ci95"] == pytest.approx([-90, -80])
    with open(tmp_path / "aggregate" / "seeds.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["variant"], r["seed"]) for r in rows][:2] == [("default", "0"), ("default", "1")]
    assert len(rows) == 6
    assert "| **IQM** [95 % CI] | | 0.500 [" in res.stdout
    assert (tmp_path / "aggregate" / "seeds.png").read_bytes()[:4] == b"\x89PNG"


def test_aggregate_of_nothing_is_a_clear_error(tmp_path):
    from rlplat.eval.aggregate import aggregate

    with pytest.raises(ConfigError, match=r"sweep_dir: no finished training run under"):
        aggregate(tmp_path)


def test_a_job_that_did_not_finish_is_named_not_dropped_silently(tmp_path, caplog):
    from rlplat.eval.aggregate import collect

    fake_sweep(tmp_path, {"default": [(0, 0.2, -50.0), (1, 0.4, -40.0)]})
    (tmp_path / "1" / "summary.json").unlink()  # job 1 stopped before its test
    with caplog.at_level("WARNING", logger="rlplat.eval.aggregate"):
        groups, _ = collect(tmp_path)
    assert [r["seed"] for r in groups["default"]] == [0]
    assert f"1 job(s) of {tmp_path} did not finish (no summary.json) and are left out: 1" in (
        caplog.text
    )


def test_a_summary_that_is_not_one_and_a_bad_seed_are_one_line(tmp_path):
    from rlplat.eval.aggregate import aggregate

    fake_sweep(tmp_path, {"default": [(0, 0.2, -50.0), (1, 0.4, -40.0)]})
    with pytest.raises(ConfigError, match=r"^seed: must be an integer >= 0, got -1$"):
        aggregate(tmp_path, seed=-1)
    path = tmp_path / "1" / "summary.json"
    for text, error in (
        ("{not json", r"cannot be read as JSON \("),
        ('{"seed": 1, "test_capture_rate": null, "test_mean_return": 1}',
         r"test_capture_rate is None, not a finite number"),
        ('{"seed": 1, "test_capture_rate": NaN, "test_mean_return": 1}',
         r"test_capture_rate is nan, not a finite number"),
    ):  # fmt: skip
        path.write_text(text)
        with pytest.raises(ConfigError, match=rf"^{path}: {error}"):
            aggregate(tmp_path)
    assert not (tmp_path / "aggregate").exists()  # nothing written


def test_a_seed_twice_in_a_variant_is_named(tmp_path, caplog):
    from rlplat.eval.aggregate import collect

    fake_sweep(tmp_path, {"default": [(0, 0.2, -50.0), (0, 0.2, -50.0), (1, 0.4, -40.0)]})
    with caplog.at_level("WARNING", logger="rlplat.eval.aggregate"):
        groups, _ = collect(tmp_path)
    assert len(groups["default"]) == 3  # counted as they are, and said
    assert "variant default has seed(s) [0] more than once (0, 1)" in caplog.text


def test_the_spread_of_one_seed_is_undefined_not_zero():
    from rlplat.eval.aggregate import aggregate_scores

    one = aggregate_scores([{"test_capture_rate": 0.5, "test_mean_return": -10.0}], reps=100)
    assert one["test_capture_rate"]["std"] is None and one["test_capture_rate"]["iqm"] == 0.5
    two = aggregate_scores(
        [
            {"test_capture_rate": 0.4, "test_mean_return": -10.0},
            {"test_capture_rate": 0.6, "test_mean_return": -20.0},
        ],
        reps=100,
    )
    assert two["test_capture_rate"]["std"] == pytest.approx(0.1414, abs=1e-4)


def test_a_defender_sweep_is_scored_by_its_evasion_not_by_the_captures(tmp_path):
    from rlplat.eval.aggregate import aggregate

    fake_sweep(
        tmp_path,
        {
            "drone=defender_v1": [(0, 0.3, 5.0), (1, 0.5, 4.0)],
            "default": [(0, 0.8, -20.0), (1, 0.9, -10.0)],
        },
    )
    for job, evasion in (("0", 0.61), ("1", 0.43)):  # the defender's jobs
        path = tmp_path / job / "summary.json"
        summary = json.loads(path.read_text())
        path.write_text(json.dumps(summary | {"val_score": "evasion_score", "test_score": evasion}))
    table = aggregate(tmp_path, reps=200)
    summary = json.loads((tmp_path / "aggregate" / "summary.json").read_text())
    defender = summary["variants"]["drone=defender_v1"]
    assert defender["test_evasion_score"]["mean"] == pytest.approx(0.52)
    assert defender["test_capture_rate"]["mean"] == pytest.approx(0.4)  # kept beside it
    assert "test_evasion_score" not in summary["variants"]["default"]  # an attacker's has none
    assert "| seed | run | test evasion score | test capture rate | test mean return |" in table
    assert "| 0 | 0 | 0.610 | 0.300 | 5.00 |" in table
    with open(tmp_path / "aggregate" / "seeds.csv") as f:
        rows = {(r["variant"], r["seed"]): r for r in csv.DictReader(f)}
    assert rows[("default", "0")]["test_evasion_score"] == ""  # one table, the column left empty
    assert rows[("drone=defender_v1", "1")]["test_evasion_score"] == "0.43"
    assert (tmp_path / "aggregate" / "seeds.png").read_bytes()[:4] == b"\x89PNG"


def test_a_defenders_summary_without_its_score_or_a_variant_of_two_roles_is_one_line(tmp_path):
    from rlplat.eval.aggregate import aggregate

    fake_sweep(tmp_path, {"default": [(0, 0.3, 5.0), (1, 0.5, 4.0)]})
    path = tmp_path / "0" / "summary.json"
    summary = json.loads(path.read_text()) | {"val_score": "evasion_score"}
    for extra, error in (
        ({}, "missing test_score (its val_score is evasion_score)"),
        ({"test_score": None}, "test_score is None, not a finite number"),
        ({"val_score": "speed", "test_score": 1.0},
         "val_score 'speed' is none of capture_rate, evasion_score"),
    ):  # fmt: skip
        path.write_text(json.dumps(summary | extra))
        with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: {re.escape(error)}$"):
            aggregate(tmp_path)
    path.write_text(json.dumps(summary | {"test_score": 0.5}))  # job 1 stays an attacker's
    with pytest.raises(ConfigError, match=r"^sweep_dir: variant default mixes runs scored "):
        aggregate(tmp_path)
    assert not (tmp_path / "aggregate").exists()  # nothing written
