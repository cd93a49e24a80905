import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from rlplat.errors import ConfigError, ScenarioFileError
from rlplat.scenarios import (
    PARAM_NAMES,
    SPLITS,
    STRATEGIES,
    ScenarioSet,
    generate,
    write_scenario_set,
)
from rlplat.scenarios.generator import grid_keys

ROOT = Path(__file__).resolve().parent.parent
SMALL = ("scenario.n_train=300", "scenario.n_val=60", "scenario.n_test=90")
# Two grid levels per continuous parameter: 2**6 * 4 routes * 2 strategies = 512 combinations.
COARSE = (
    "scenario.n_train=1000",
    *(
        f"scenario.params.{name}.resolution={res}"
        for name, res in [
            ("defender_z", 24),
            ("attacker_dx", 96),
            ("attacker_dy", 84),
            ("attacker_dz", 26),
            ("defender_max_speed", 4),
            ("attacker_max_speed", 4),
        ]
    ),
)


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


def test_same_seed_gives_byte_identical_files(make_spec, tmp_path):
    spec = make_spec(*SMALL)
    write_scenario_set(spec, tmp_path / "a")
    write_scenario_set(spec, tmp_path / "b")
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert set(a) == {"train.jsonl", "val.jsonl", "test.jsonl", "manifest.json"}
    assert a == b
    write_scenario_set(make_spec(*SMALL, "scenario.seed=1"), tmp_path / "c")
    c = _files(tmp_path / "c")
    assert all(a[f] != c[f] for f in a)


def test_no_duplicates_and_split_counts(make_spec):
    spec = make_spec("scenario.n_train=20000", "scenario.n_val=3000", "scenario.n_test=5000")
    splits = generate(spec)
    assert {s: len(c) for s, c in splits.items()} == {"train": 20000, "val": 3000, "test": 5000}
    keys = np.concatenate([grid_keys(spec, c.values, c.route, c.strategy) for c in splits.values()])
    assert len(np.unique(keys, axis=0)) == len(keys)
    ids = [i for c in splits.values() for i in c.ids]
    assert len(set(ids)) == len(ids)


def test_every_sample_meets_every_constraint(make_spec, tmp_path):
    spec = make_spec("scenario.n_train=4000", "scenario.n_val=500", "scenario.n_test=500")
    write_scenario_set(spec, tmp_path)
    a, b, c = spec.vision_semi_axes
    for split in SPLITS:
        for line in (tmp_path / f"{split}.jsonl").read_text().splitlines():
            s = json.loads(line)
            d = np.array(s["defender_start"])
            p = np.array(s["attacker_start"])
            assert d[0] == 0 and d[1] == 0 and 6 <= d[2] <= 30
            off = d - p
            assert (off[0] / a) ** 2 + (off[1] / b) ** 2 + (off[2] / c) ** 2 <= 1 + 1e-9
            assert np.linalg.norm(off) >= 7.5 and p[2] >= spec.min_altitude > 0
            assert s["route"] in range(4) and s["defender_strategy"] in STRATEGIES
            for k in ("defender_max_speed", "attacker_max_speed"):
                assert 1.0 <= s[k] <= 5.0
                assert math.isclose(s[k] * 10, round(s[k] * 10), abs_tol=1e-6)  # on the grid
            assert s["id"].startswith(split)


def test_splits_have_alike_distributions_on_a_large_set(make_spec):
    spec = make_spec("scenario.n_train=20000", "scenario.n_val=5000", "scenario.n_test=5000")
    splits = generate(spec)
    from rlplat.scenarios import quality_report

    q = quality_report(spec, splits)
    assert q["completeness"]["complete"], q["completeness"]["missing"]
    assert q["independence"]["independent"]
    for name in PARAM_NAMES:
        for pair, r in q["representativeness"]["ks"][name].items():
            assert r["statistic"] < 0.04, (name, pair, r)  # 95 % critical value is ~0.022
    # Categoricals are stratified: each (route, strategy) stratum is shared out in proportion.
    for s, cols in splits.items():
        share = len(cols) / spec.n_total
        for r in range(4):
            for k in spec.strategy_levels:
                n_all = sum(((c.route == r) & (c.strategy == k)).sum() for c in splits.values())
                n_here = ((cols.route == r) & (cols.strategy == k)).sum()
                assert abs(n_here - share * n_all) <= 2, (s, r, k)


def test_quality_report_lists_missing_bins_of_a_tiny_split(make_spec, tmp_path):
    manifest = write_scenario_set(
        make_spec("scenario.n_train=200", "scenario.n_val=3", "scenario.n_test=3"), tmp_path
    )
    comp = manifest["quality"]["completeness"]
    assert not comp["complete"]
    assert any(m.startswith("val: ") for m in comp["missing"])
    assert manifest["quality"]["independence"]["duplicates_across"] == {
        "train-val": 0,
        "train-test": 0,
        "val-test": 0,
    }


def test_gaussian_is_selectable_per_parameter(make_spec):
    spec = make_spec(
        *SMALL,
        "scenario.params.attacker_max_speed.dist=gaussian",
        "scenario.params.attacker_max_speed.mean=4.0",
        "scenario.params.attacker_max_speed.std=0.3",
    )
    values = np.concatenate([c.values for c in generate(spec).values()])
    va, vd = values[:, 5], values[:, 4]
    assert abs(va.mean() - 4.0) < 0.1 and va.std() < 0.4 and va.min() >= 1.0
    assert vd.std() > 1.0  # the other speed stays uniform on [1, 5]


def test_strategy_mix_weights(make_spec):
    only = make_spec(*SMALL, "scenario.strategy_mix.nn=0")
    assert all((c.strategy == 0).all() for c in generate(only).values())
    for overrides, share in (((), 0.5), (("scenario.strategy_mix.nn=1.5",), 0.75)):
        spec = make_spec(*SMALL, *overrides)  # default setpoints 0.5 : nn 0.5, then 0.5 : 1.5
        strategy = np.concatenate([c.strategy for c in generate(spec).values()])
        assert abs((strategy == STRATEGIES.index("nn")).mean() - share) < 0.06


def test_load_returns_tensors_matching_files(make_spec, tmp_path):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    ss = ScenarioSet.load(tmp_path)
    test = ss.split("test")
    assert test.batch_size == torch.Size([90])
    assert test["attacker_start"].shape == (90, 3) and test["attacker_start"].dtype == torch.float32
    first = json.loads((tmp_path / "test.jsonl").read_text().splitlines()[0])
    assert ss.ids["test"][0] == first["id"]
    assert test["attacker_start"][0].tolist() == pytest.approx(first["attacker_start"])
    assert STRATEGIES[test["defender_strategy"][0]] == first["defender_strategy"]
    assert ss.routes.shape == (4, 18, 3)
    assert ss.spec.seed == 0 and len(ss.digest) == 64
    with pytest.raises(ScenarioFileError, match="unknown split 'dev'"):
        ss.split("dev")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("scenario.n_val=-5",), r"scenario.n_val: count must be >= 0, got -5"),
        (
            ("scenario.params.defender_z.low=30", "scenario.params.defender_z.high=6"),
            r"scenario.params.defender_z: empty or inverted range \[low=30.0, high=6.0\]",
        ),
        (
            ("scenario.params.defender_z.low=6", "scenario.params.defender_z.high=6"),
            r"scenario.params.defender_z: empty or inverted range",
        ),
        (
            ("scenario.params.attacker_dx.dist=beta",),
            r"scenario.params.attacker_dx.dist: unknown distribution 'beta'; "
            r"valid: uniform, gaussian",
        ),
        (("scenario.min_distance=60",), r"scenario.min_distance: 60.0 m cannot be met"),
        (
            COARSE,
            r"scenario: 1700 scenarios requested \(n_train \+ n_val \+ n_test\) but only 512 "
            r"distinct combinations exist at the configured resolution",
        ),
        (("+scenario.strategy_mix.mixed=1",), r"unknown strategy 'mixed'; valid: setpoints, nn"),
    ],
)
def test_bad_config_is_refused_with_one_line(make_spec, overrides, message):
    with pytest.raises(ConfigError, match=message) as e:
        make_spec(*overrides)
    assert "\n" not in str(e.value)


def test_unsatisfiable_constraints_are_refused(make_spec):
    # The grid holds enough combinations, but the altitude constraint rules all of them out.
    with pytest.raises(ConfigError, match=r"only 0 distinct scenarios meet the constraints"):
        generate(make_spec(*SMALL, "scenario.min_altitude=50"))


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlplat.scenarios", *args], cwd=cwd, capture_output=True, text=True
    )


def test_cli_writes_a_loadable_set_and_prints_the_report(tmp_path):
    r = _cli("out_dir=set", "scenario.seed=7", *SMALL, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "independence      independent" in r.stdout and "KS attacker_dx" in r.stdout
    manifest = json.loads((tmp_path / "set" / "manifest.json").read_text())
    assert manifest["seed"] == 7 and manifest["splits"]["val"]["count"] == 60
    assert len(manifest["config"]["routes"]) == 4
    assert ScenarioSet.load(tmp_path / "set").split("train").batch_size == torch.Size([300])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]  # nothing else written


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("scenario.n_train=-1",), "error: scenario.n_train: count must be >= 0, got -1"),
        (("scenario.min_altitude=50",), "error: scenario: only 0 distinct scenarios"),
    ],
)
def test_cli_bad_input_exits_nonzero_and_writes_nothing(tmp_path, args, message):
    r = _cli("out_dir=set", *args, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().startswith(message) and len(r.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def _tamper(path: Path, how: str) -> None:
    if how == "truncate":
        path.write_bytes(path.read_bytes()[:-40])
    else:
        path.write_text(path.read_text().replace('"route": 1', '"route": 2', 1))


@pytest.mark.parametrize("how", ["truncate", "edit"])
def test_tampered_file_is_refused(make_spec, tmp_path, how):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    _tamper(tmp_path / "train.jsonl", how)
    with pytest.raises(ScenarioFileError, match=r"train.jsonl: sha256 differs from the manifest"):
        ScenarioSet.load(tmp_path)


def test_missing_file_and_other_schema_are_refused(make_spec, tmp_path):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    (tmp_path / "val.jsonl").unlink()
    with pytest.raises(ScenarioFileError, match=r"val.jsonl: missing file"):
        ScenarioSet.load(tmp_path)
    manifest["schema_version"] = 99
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ScenarioFileError, match=r"schema_version 99 is not supported"):
        ScenarioSet.load(tmp_path)
    with pytest.raises(ScenarioFileError, match=r"manifest.json: missing file"):
        ScenarioSet.load(tmp_path / "nowhere")
