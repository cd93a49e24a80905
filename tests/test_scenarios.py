import dataclasses
import json
import logging
import math
import re
import subprocess
import sys
import warnings
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
    ScenarioSpec,
    format_quality,
    generate,
    write_scenario_set,
)
from rlplat.scenarios.generator import grid_keys, offsets_out_of_view
from rlplat.scenarios.quality import quality_report

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


def test_writing_another_set_over_one_says_so(make_spec, tmp_path, caplog):
    with caplog.at_level("WARNING", logger="rlplat.scenarios.store"):
        write_scenario_set(make_spec(*SMALL), tmp_path)
        write_scenario_set(make_spec(*SMALL), tmp_path)  # the same set again: nothing to say
        assert not caplog.text
        write_scenario_set(make_spec(*SMALL, "scenario.seed=1"), tmp_path)
    assert f"replacing the scenario set in {tmp_path} (manifest sha256 " in caplog.text


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


def _speed_bins(spec, splits) -> list[str]:
    """The attacker speed bins the quality report finds missing."""
    missing = quality_report(spec, splits)["completeness"]["missing"]
    return [m for m in missing if "attacker_max_speed" in m]


def _val_speeds_kept(spec, splits, keep) -> None:
    """Keep only the val scenarios whose attacker speed ``keep(speeds)`` (a mask) keeps."""
    val = splits["val"]
    mask = keep(val.values[:, spec.param_names.index("attacker_max_speed")])
    splits["val"] = dataclasses.replace(
        val, ids=[x for x, k in zip(val.ids, mask, strict=True) if k],
        values=val.values[mask], route=val.route[mask], strategy=val.strategy[mask],
    )  # fmt: skip


def test_quality_report_asks_only_for_bins_that_hold_a_grid_value(make_spec):
    # Speeds 3.0-3.1 on a 0.1 grid: two values, ten bins. The eight bins between them can never
    # be filled, so the speed is complete once both values occur; a bin that holds a value and
    # no scenario still counts as missing.
    narrow = ("low=3.0", "high=3.1", "resolution=0.1")
    spec = make_spec("scenario.n_train=200", "scenario.n_val=50", "scenario.n_test=50",
                     *(f"scenario.params.attacker_max_speed.{x}" for x in narrow))  # fmt: skip
    splits = generate(spec)
    assert _speed_bins(spec, splits) == []
    _val_speeds_kept(spec, splits, lambda v: v < 3.05)  # drop every val scenario at 3.1
    assert _speed_bins(spec, splits) == ["val: attacker_max_speed bin [3.09, 3.1]"]


def test_quality_report_asks_a_gaussian_only_for_the_bins_its_draws_reach(make_spec):
    # Attacker speeds gaussian at 3.0 +- 0.2 m/s on [1, 5]: the bins 5 to 10 std from the mean
    # expect no draw in a split of this size and are not asked for (they made every such set
    # INCOMPLETE); a bin the split would fill is still reported when it holds no scenario.
    narrow = ("dist=gaussian", "mean=3.0", "std=0.2")
    spec = make_spec("scenario.n_train=400", "scenario.n_val=200", "scenario.n_test=200",
                     *(f"scenario.params.attacker_max_speed.{x}" for x in narrow))  # fmt: skip
    splits = generate(spec)
    assert _speed_bins(spec, splits) == []
    _val_speeds_kept(spec, splits, lambda v: (v < 2.6) | (v >= 3.0))  # empty [2.6, 3.0)
    assert _speed_bins(spec, splits) == ["val: attacker_max_speed bin [2.6, 3]"]


def test_a_gaussian_drawn_mostly_outside_its_range_is_logged(make_spec, caplog):
    # Draws outside [low, high] land on the ends; the quality report cannot show it, the
    # generator says so (and nothing for a gaussian that stays inside).
    wide = ("dist=gaussian", "mean=2.0", "std=10")
    spec = make_spec("scenario.n_train=40", "scenario.n_val=10", "scenario.n_test=10",
                     *(f"scenario.params.attacker_max_speed.{x}" for x in wide))  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="rlplat.scenarios.generator"):
        generate(spec)
    [record] = caplog.records
    assert record.getMessage().startswith("scenario.params.attacker_max_speed: the gaussian")
    assert "46 % of its draws below low 1 and 38 % above high 5" in record.getMessage()
    caplog.clear()
    narrow = ("dist=gaussian", "mean=3.0", "std=0.8")
    spec = make_spec("scenario.n_train=40", "scenario.n_val=10", "scenario.n_test=10",
                     *(f"scenario.params.attacker_max_speed.{x}" for x in narrow))  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="rlplat.scenarios.generator"):
        generate(spec)
    assert not caplog.records


def test_a_teams_gaussian_is_logged_once_under_its_config_field(make_spec, caplog):
    # The extra drones' columns (attacker1_max_speed, defender1_dx, ...) are drawn from their
    # first drone's field: the warning names that field, once, as the config spells it.
    wide = ("dist=gaussian", "mean=2.0", "std=10")
    spread = ("dist=gaussian", "mean=0", "std=50")
    spec = make_spec(*_team(3, 2, "scenario.n_train=40", "scenario.n_val=10",
                            "scenario.n_test=10",
                            *(f"scenario.params.attacker_max_speed.{x}" for x in wide),
                            *(f"scenario.defender_spread.{x}" for x in spread)))  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="rlplat.scenarios.generator"):
        generate(spec)
    fields = [r.getMessage().split(":")[0] for r in caplog.records]
    assert fields == ["scenario.params.attacker_max_speed", "scenario.defender_spread"]


def test_a_resolution_of_the_whole_range_draws_both_ends(make_spec):
    # 5.0 - 4.9 is 0.0999999... in floating point: a step of 0.1 is the whole range, not more.
    ends = ("low=4.9", "high=5.0", "resolution=0.1")
    spec = make_spec("scenario.n_train=40", "scenario.n_val=10", "scenario.n_test=10",
                     *(f"scenario.params.attacker_max_speed.{x}" for x in ends))  # fmt: skip
    i = spec.param_names.index("attacker_max_speed")
    drawn = {v for cols in generate(spec).values() for v in cols.values[:, i].tolist()}
    assert drawn == {4.9, 5.0}


def test_a_fine_grid_counts_every_value_up_to_its_high_end(make_spec):
    # high - low divided by the step in floats falls short of a whole number (26.99999...) on
    # such ranges: counted so, the high end was never drawn, and a one-step range was refused.
    from decimal import Decimal

    from rlplat.scenarios.spec import ParamSpec

    rng = np.random.default_rng(0)
    for _ in range(2000):
        res = float(rng.choice([1e-6, 2e-6, 5e-6, 1e-5, 0.001, 0.1, 0.3]))
        low = round(float(rng.uniform(-1e5, 1e5 - 1)), 6)
        high = round(low + res * int(rng.integers(1, 1000)), 6)
        exact = int((Decimal(str(high)) - Decimal(str(low))) // Decimal(str(res))) + 1
        assert ParamSpec(low=low, high=high, resolution=res).levels == exact, (low, high, res)
    one_step = ("low=91206.854378", "high=91206.854379", "resolution=0.000001")
    spec = make_spec(*(f"scenario.params.defender_max_speed.{x}" for x in one_step))
    assert spec.params["defender_max_speed"].levels == 2
    fine = ("low=79.667471", "high=79.667497", "resolution=0.000001")
    spec = make_spec("scenario.n_train=200", "scenario.n_val=50", "scenario.n_test=50",
                     *(f"scenario.params.defender_max_speed.{x}" for x in fine))  # fmt: skip
    i = spec.param_names.index("defender_max_speed")
    drawn = {v for cols in generate(spec).values() for v in cols.values[:, i].tolist()}
    assert max(drawn) == 79.667497 and len(drawn) == 27
    # The quality report names such a grid's bins apart (they read [79.67, 79.67] to 4 digits).
    from rlplat.scenarios import quality_report

    splits = generate(spec)
    val = splits["val"]
    keep = val.values[:, i] < 79.667495  # empty the last bin of the val split
    splits["val"] = dataclasses.replace(
        val, ids=[x for x, k in zip(val.ids, keep, strict=True) if k],
        values=val.values[keep], route=val.route[keep], strategy=val.strategy[keep],
    )  # fmt: skip
    report = quality_report(spec, splits)["completeness"]
    missing = [m for m in report["missing"] if m.startswith("val: defender_max_speed")]
    low, high = (float(x) for x in re.findall(r"\[(.*), (.*)\]", missing[0])[0])
    assert len(missing) == 1 and low < 79.667497 == high, missing
    # Bins finer than the grid read apart too, and no edge reads -0.
    from rlplat.scenarios.quality import _edge

    assert [_edge(x, 0.01) for x in (1.0, 1.01, -1e-12)] == ["1", "1.01", "0"]


def test_quality_report_is_complete_when_every_grid_value_occurs(make_spec):
    # Speeds 0.2-1.2 on a 0.1 grid, one value per bin: 0.3 is written as 0.3, below the edge
    # 0.30000000000000004 that the unrounded grid put it above (a bin reported missing).
    from rlplat.scenarios import quality_report

    wide = ("low=0.2", "high=1.2", "resolution=0.1")
    spec = make_spec("scenario.n_train=300", "scenario.n_val=300", "scenario.n_test=300",
                     *(f"scenario.params.attacker_max_speed.{x}" for x in wide))  # fmt: skip
    splits = generate(spec)
    i = spec.param_names.index("attacker_max_speed")
    for cols in splits.values():
        assert len(set(cols.values[:, i].tolist())) == 11  # every grid value occurs
    comp = quality_report(spec, splits)["completeness"]
    assert not [m for m in comp["missing"] if "attacker_max_speed" in m], comp["missing"]


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
    # Every entry carries the drone dimension, also for 1 vs 1.
    assert ss.attackers == 1 and ss.defenders == 1
    assert test["attacker_start"].shape == (90, 1, 3)
    assert test["attacker_start"].dtype == torch.float32
    assert test["defender_start"].shape == (90, 1, 3)
    assert test["route"].shape == test["defender_strategy"].shape == (90, 1)
    assert test["attacker_max_speed"].shape == test["defender_max_speed"].shape == (90, 1)
    first = json.loads((tmp_path / "test.jsonl").read_text().splitlines()[0])
    assert ss.ids["test"][0] == first["id"]
    assert test["attacker_start"][0, 0].tolist() == pytest.approx(first["attacker_start"])
    assert STRATEGIES[test["defender_strategy"][0, 0]] == first["defender_strategy"]
    assert ss.routes.shape == (4, 18, 3)
    assert ss.spec.seed == 0 and len(ss.digest) == 64
    with pytest.raises(ScenarioFileError, match="unknown split 'dev'"):
        ss.split("dev")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("scenario.n_val=-5",), r"scenario.n_val: count must be >= 0, got -5"),
        (("scenario.seed=-5",), r"scenario.seed: must be an integer >= 0, got -5"),
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
            r"scenario: 3500 scenarios requested \(n_train \+ n_val \+ n_test\) but only 512 "
            r"distinct combinations exist at the configured resolution",
        ),
        (("+scenario.strategy_mix.mixed=1",), r"unknown strategy 'mixed'; valid: setpoints, nn"),
        (("scenario.attackers=0",), r"scenario.attackers: must be in \[1, 32\], got 0"),
        (("scenario.defenders=33",), r"scenario.defenders: must be in \[1, 32\], got 33"),
        (
            ("scenario.n_train=100000000",),
            r"scenario: n_train \+ n_val \+ n_test must be at most 1,000,000, got 100,002,500",
        ),
        (("scenario.attackers=1.5",), r"scenario.attackers: expected an integer, got 1.5"),
        (("scenario.defenders=-2",), r"scenario.defenders: must be in \[1, 32\], got -2"),
        (
            ("scenario.min_separation=-1",),
            r"scenario.min_separation: must be a finite distance >= 0 m, got -1.0",
        ),
        (
            ("scenario.defender_spread.low=5", "scenario.defender_spread.high=-5"),
            r"scenario.defender_spread: empty or inverted range \[low=5.0, high=-5.0\]",
        ),
        (
            ("scenario.params.attacker_max_speed.low=0",),
            r"scenario.params.attacker_max_speed.low: a maximum speed must be > 0 m/s, got 0.0",
        ),
        (
            ("scenario.params.defender_max_speed.dist=gaussian",
             "scenario.params.defender_max_speed.mean=nan"),
            r"scenario.params.defender_max_speed.mean: expected a finite number, got nan",
        ),
        (
            ("scenario.params.defender_max_speed.dist=gaussian",
             "scenario.params.defender_max_speed.mean=abc"),
            r"scenario.params.defender_max_speed.mean: expected a finite number, got 'abc'",
        ),
        (
            ("scenario.params.attacker_max_speed.dist=gaussian",
             "scenario.params.attacker_max_speed.mean=40"),
            r"scenario.params.attacker_max_speed.mean: must lie in \[low=.*, high=.*\], got 40.0",
        ),
        (("scenario.min_distance=nan",), r"scenario.min_distance: expected a finite number"),
        (("scenario.min_altitude=abc",), r"scenario.min_altitude: expected a finite number, got"),
        (("scenario.strategy_mix.nn=abc",), r"scenario.strategy_mix.nn: expected a finite number"),
        # a number, not what float() also takes: true is no 1.0, and a quoted "7.5" no 7.5
        (
            ("scenario.min_distance=true",),
            r"scenario.min_distance: expected a finite number, got True",
        ),
        (("scenario.min_separation=true",), r"scenario.min_separation: expected a finite number"),
        (("scenario.strategy_mix.nn=true",), r"scenario.strategy_mix.nn: expected a finite number"),
        (
            ("scenario.min_distance='7.5'",),
            r"scenario.min_distance: expected a finite number, got '7.5'",
        ),
        (
            ("scenario.vision_semi_axes=[true,40,13]",),
            r"scenario.vision_semi_axes: expected 3 finite numbers",
        ),
        (
            ("scenario.params.defender_max_speed.resolution='0.1'",),
            r"scenario.params.defender_max_speed.resolution: expected a finite number, got '0.1'",
        ),
        # a string's characters are no list ('985' was read as [9, 8, 5])
        (("scenario.vision_semi_axes='985'",), r"scenario.vision_semi_axes: expected 3 numbers"),
        (("scenario.routes=[5]",), r"scenario.routes\[0\]: expected a list of \[x, y, z\]"),
        # float32 overflows such a route or ellipsoid (the flight used to stop on an inf action)
        (
            ("scenario.routes=[[[1,0,10],[1e39,0,10]]]",),
            r"scenario.routes\[0\]\[1\]: setpoint must lie within \[-100000, 100000\] m per "
            r"axis, got \[1e\+39, 0.0, 10.0\]",
        ),
        (
            ("scenario.vision_semi_axes=[48,1e39,13]",),
            r"scenario.vision_semi_axes: must be at most 100000 m, got \[48.0, 1e\+39, 13.0\]",
        ),
        (("scenario.routes=5",), r"scenario.routes: expected a list of routes"),
        (
            ("scenario.routes=[[[1,0,10],[2,0,10]],[[0,1,10]]]",),
            r"scenario.routes: all routes need the same number of setpoints, got \[2, 1\]",
        ),
        # Starts on or under the ground would end (or not) at the first step.
        (("scenario.min_altitude=0",), r"scenario.min_altitude: starts are above the ground"),
        (
            ("scenario.params.defender_z.low=-5",),
            r"scenario.params.defender_z.low: starts are above the ground \(0 m\), got -5.0",
        ),
        # A grid finer than the files keep, or too large to bin.
        (
            ("scenario.params.defender_z.resolution=1e-9",),
            r"scenario.params.defender_z.resolution: 1e-09 is finer than the files keep "
            r"\(6 decimals\); at least 3e-06$",
        ),
        (
            ("scenario.params.defender_z.high=1e5", "scenario.params.defender_z.resolution=0.001"),
            r"makes more than 10,000,000 values in \[low=6, high=100000\]; at least 0.01$",
        ),
        # Values the files or the float32 simulator cannot keep: a set its loader would refuse,
        # grid values that collide once rounded, or positions whose squares overflow.
        (
            ("scenario.params.attacker_max_speed.low=0.0000001",
             "scenario.params.attacker_max_speed.high=1.0000001"),
            r"scenario.params.attacker_max_speed.low: at most 6 decimals \(what the files keep\), "
            r"got 1e-07",
        ),
        (
            ("scenario.params.attacker_max_speed.low=1.0000005",
             "scenario.params.attacker_max_speed.high=1.0000115",
             "scenario.params.attacker_max_speed.resolution=0.000001"),
            r"scenario.params.attacker_max_speed.low: at most 6 decimals",
        ),
        (
            ("scenario.params.attacker_max_speed.resolution=0.12345678",),
            r"scenario.params.attacker_max_speed.resolution: at most 6 decimals",
        ),
        (
            ("scenario.params.attacker_max_speed.high=1e39",),
            r"scenario.params.attacker_max_speed.high: must lie in \[-100000, 100000\], got 1e\+39",
        ),
        # A billion bins used to allocate gigabytes for the report.
        (("scenario.quality_bins=0",), r"scenario.quality_bins: must be in \[1, 10000\], got 0"),
        (
            ("scenario.quality_bins=1000000000",),
            r"scenario.quality_bins: must be in \[1, 10000\], got 1000000000",
        ),
        (
            ("scenario.params.defender_z.std=-1",),
            r"scenario.params.defender_z.std: only dist=gaussian has a std; dist=uniform, got -1",
        ),
    ],
)  # fmt: skip
def test_bad_config_is_refused_with_one_line(make_spec, overrides, message):
    with pytest.raises(ConfigError, match=message) as e:
        make_spec(*overrides)
    assert "\n" not in str(e.value)


def test_a_small_vision_ellipsoid_under_the_default_offsets_is_drawn(make_spec):
    # Most draws fall outside a 10/10/5 m ellipsoid (offsets up to 48 m): 1 vs 1 keeps its
    # batch sizes for as many rounds as ever (the same files), then grows them with the rejection.
    spec = make_spec("scenario.vision_semi_axes=[10,10,5]", "scenario.n_train=300",
                     "scenario.n_val=100", "scenario.n_test=100")  # fmt: skip
    splits = generate(spec)
    assert sum(len(c.ids) for c in splits.values()) == 500
    # Its report asks only for the offset bins the ellipsoid reaches: the x offsets lie in
    # [-10, 10], so of [-48, 48]'s ten bins the four from -19.2 to 19.2 m.
    missing = quality_report(spec, splits)["completeness"]["missing"]
    offsets = [m for m in missing if "attacker_d" in m]
    assert offsets and all(
        float(low) < axis and float(high) > -axis
        for m in offsets
        for (low, high), axis in [(m.split("[")[1].rstrip("]").split(", "),
                                   {"dx": 10, "dy": 10, "dz": 5}[m.split("attacker_")[1][:2]])]
    ), offsets  # fmt: skip


def test_unsatisfiable_constraints_are_refused(make_spec):
    # The grid holds enough combinations, but the altitude constraint rules all of them out.
    spec = make_spec(*SMALL, "scenario.min_altitude=50", "scenario.vision_semi_axes=[40,42,13]")
    n = spec.n_total
    with pytest.raises(ConfigError) as e:
        generate(spec)
    message = str(e.value)
    assert message.startswith(f"scenario: 0 distinct scenarios of the {n} requested ")
    # The offsets that reach out of view are named: the x range passes the 40-m semi-axis.
    assert "narrow the offsets out of view (attacker_dx [-48, 48] beyond 40 m), " in message
    assert "\n" not in message
    assert offsets_out_of_view(make_spec()) == []  # the default ranges are the ellipsoid's


def test_starts_beyond_what_the_files_hold_are_not_drawn(make_spec, tmp_path):
    # An altitude plus an attacker's offset can pass 1e5 m, which no scenario file may hold: such
    # draws are not kept (the set loads), and where none is left the refusal names the rule.
    z = ("low=99980", "high=99999", "resolution=1")
    spec = make_spec("scenario.n_train=60", "scenario.n_val=20", "scenario.n_test=20",
                     *(f"scenario.params.defender_z.{x}" for x in z))  # fmt: skip
    write_scenario_set(spec, tmp_path / "high")
    starts = ScenarioSet.load(tmp_path / "high").split("train")["attacker_start"][..., 2]
    assert starts.max() <= 1e5 and starts.max() > 99_990  # the rule binds, and only there
    dz = ("low=6", "high=13")
    spec = make_spec("scenario.n_train=6", "scenario.n_val=2", "scenario.n_test=2",
                     *(f"scenario.params.defender_z.{x}" for x in ("low=99995", "high=99999")),
                     *(f"scenario.params.attacker_dz.{x}" for x in dz))  # fmt: skip
    with pytest.raises(ConfigError, match=r"starts within ±100000 m\)$"):
        generate(spec)


def test_quality_report_asks_no_bin_the_least_altitude_rules_out(make_spec):
    # Defenders at 2-4 m, attackers at least 1 m up: an attacker offset below -3 m is never
    # drawn, so the three lowest of attacker_dz's ten bins on [-13, 13] are not asked for.
    z = ("low=2", "high=4")
    spec = make_spec("scenario.n_train=300", "scenario.n_val=100", "scenario.n_test=100",
                     *(f"scenario.params.defender_z.{x}" for x in z))  # fmt: skip
    splits = generate(spec)
    i = spec.param_names.index("attacker_dz")
    assert min(c.values[:, i].min() for c in splits.values()) >= -3.0
    missing = quality_report(spec, splits)["completeness"]["missing"]
    assert not [m for m in missing if re.search(r"attacker_dz bin \[-(13|10.4|7.8),", m)]


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlplat.scenarios", *args], cwd=cwd, capture_output=True, text=True
    )


def test_cli_writes_a_loadable_set_and_prints_the_report(tmp_path):
    r = _cli("out_dir=set", "scenario.seed=7", *SMALL, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "independence      independent" in r.stdout and "KS   attacker_dx" in r.stdout
    manifest = json.loads((tmp_path / "set" / "manifest.json").read_text())
    assert manifest["seed"] == 7 and manifest["splits"]["val"]["count"] == 60
    assert len(manifest["config"]["routes"]) == 4
    assert ScenarioSet.load(tmp_path / "set").split("train").batch_size == torch.Size([300])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]  # nothing else written


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("scenario.n_train=-1",), "error: scenario.n_train: count must be >= 0, got -1"),
        (("scenario.n_train=${nope}",), "error: scenario.n_train: Interpolation key 'nope' not"),
        (("scenario.n_trian=5",), "error: scenario.n_trian: no such setting (did you mean "),
        (("scenario=nope",), "error: scenario=nope: no such option (valid: pursuit, pursuit_2v1)"),
    ],
)
def test_cli_bad_input_exits_nonzero_and_writes_nothing(
    tmp_path, args, message, refused_in_process
):
    stderr = refused_in_process("-m", "rlplat.scenarios", "out_dir=set", *args, cwd=tmp_path)
    assert stderr.strip().startswith(message) and len(stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_cli_a_set_that_cannot_be_drawn_exits_nonzero_and_writes_nothing(tmp_path):
    # Refused as the job draws it (after Hydra started), in a process of its own.
    r = _cli("out_dir=set", "scenario.min_altitude=50", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.startswith("error: scenario: 0 distinct scenarios of the ")
    assert len(r.stderr.strip().splitlines()) == 1 and list(tmp_path.iterdir()) == []


def test_cli_without_an_out_dir_is_one_line(tmp_path):
    r = _cli(cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr == "error: out_dir: missing (???); give out_dir=DIR, the folder for the set\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("value", "shown"), [("", "''"), ("null", "None"), ("123", "123"), ("' '", "' '")]
)
def test_cli_an_out_dir_that_is_no_folder_name_is_one_line(
    tmp_path, value, shown, refused_in_process
):
    # out_dir= would write the set into the working directory; null or a number is no path.
    stderr = refused_in_process("-m", "rlplat.scenarios", f"out_dir={value}", *SMALL, cwd=tmp_path)
    assert stderr == (
        f"error: out_dir: must be a non-empty string, got {shown}; give out_dir=DIR, the folder "
        "for the set\n"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("marker", ["config.yaml", "checkpoints", "episodes.csv"])
def test_cli_an_out_dir_that_holds_a_run_is_refused(tmp_path, marker, refused_in_process):
    # A set's files would land among a run's own (and its manifest.json beside them).
    run = tmp_path / "run"
    run.mkdir()
    if marker == "checkpoints":
        (run / marker).mkdir()
    else:
        (run / marker).write_text("seed: 0\n")
    before = sorted(p.name for p in run.iterdir())
    stderr = refused_in_process("-m", "rlplat.scenarios", f"out_dir={run}", *SMALL, cwd=tmp_path)
    assert stderr == f"error: out_dir: {run} holds a run ({marker}); give the set its own folder\n"
    assert sorted(p.name for p in run.iterdir()) == before


@pytest.mark.parametrize("inside", ["checkpoints", "checkpoints/sets/new", "eval"])
def test_cli_an_out_dir_inside_a_run_is_refused(tmp_path, inside, refused_in_process):
    # A run's checkpoints/ (or a new folder under it) is no place for a set either.
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best.pt").write_bytes(b"")
    (run / "config.yaml").write_text("seed: 0\n")
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    out = run / inside
    stderr = refused_in_process("-m", "rlplat.scenarios", f"out_dir={out}", *SMALL, cwd=tmp_path)
    assert stderr == f"error: out_dir: {out} lies in the run {run}; give the set its own folder\n"
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before


def test_cli_an_out_dir_that_cannot_be_made_is_one_line_before_any_work(tmp_path):
    (tmp_path / "a-file").write_text("")
    r = _cli("out_dir=a-file/set", *SMALL, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip() == (
        "error: out_dir: cannot write the scenario set to a-file/set: Not a directory"
    )


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


def test_a_count_that_is_not_an_integer_is_named_as_such(make_spec, tmp_path):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    count = manifest["splits"]["test"]["count"]
    manifest["splits"]["test"]["count"] = str(count)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(
        ScenarioFileError, match=rf"the manifest's count must be an integer, got '{count}'$"
    ):
        ScenarioSet.load(tmp_path)


def _first(**change):
    def edit(records):
        rec = records[0]
        for key, value in change.items():
            if value is _first:
                del rec[key]
            else:
                rec[key] = value
        return records

    return edit


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (_first(attacker_max_speed=_first), r"test.jsonl:1: missing field 'attacker_max_speed'"),
        (_first(attacker_max_speed=float("nan")),
         r"test.jsonl:1: attacker_max_speed must be a number in \[1e-06, 100000\] \(m/s\), "
         r"got nan"),
        (_first(defender_max_speed=-2.0), r"test.jsonl:1: defender_max_speed must be a number in"),
        (_first(attacker_max_speed="fast"), r"test.jsonl:1: attacker_max_speed must be a number"),
        # finite, but not in float32: nothing the simulator can fly
        (_first(defender_max_speed=1e-300), r"test.jsonl:1: defender_max_speed must be a number"),
        (_first(attacker_max_speed=1e39), r"test.jsonl:1: attacker_max_speed must be a number"),
        (_first(attacker_start=[1.0, 2.0]),
         r"test.jsonl:1: attacker_start must be 3 numbers \[x, y, z\] m in \[-100000, 100000\], "
         r"got \[1.0, 2.0\]"),
        (_first(attacker_start=[1e39, 0.0, 20.0]),
         r"test.jsonl:1: attacker_start must be 3 numbers"),
        (_first(route=7), r"test.jsonl:1: route must be a route index in \[0, 3\]"),
        (_first(defender_strategy="zigzag"),
         r"test.jsonl:1: defender_strategy 'zigzag' is unknown; valid: setpoints, nn"),
        (_first(speed=3.0), r"test.jsonl:1: unknown field 'speed'; valid: id, "),
        (lambda r: [*r[:-1], r[0]], r"test.jsonl:\d+: id 'test-000000' repeats line 1"),
        (lambda r: r[:-1], r"test.jsonl: \d+ scenarios, the manifest's count says \d+"),
        (lambda r: ["{not json\n", *r[1:]], r"test.jsonl:1: not a JSON record"),
    ],
)  # fmt: skip
def test_a_hand_made_set_is_checked_record_by_record(
    make_spec, tmp_path, rewrite_split, edit, message
):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    rewrite_split(tmp_path, "test", edit)
    with pytest.raises(ScenarioFileError, match=message) as e:
        ScenarioSet.load(tmp_path)
    assert "\n" not in str(e.value)


def test_a_hand_made_set_may_hold_blank_lines(make_spec, tmp_path, rewrite_split):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    before = ScenarioSet.load(tmp_path)
    rewrite_split(tmp_path, "test", lambda r: [r[0], "\n", *r[1:], "  \n"])
    after = ScenarioSet.load(tmp_path)
    assert after.ids["test"] == before.ids["test"]
    assert (after.split("test") == before.split("test")).all()


def test_a_manifest_that_is_not_json_or_lacks_a_split_is_one_line(make_spec, tmp_path):
    write_scenario_set(make_spec(*SMALL), tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    del manifest["splits"]["val"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ScenarioFileError, match=r"manifest.json: splits.val must name its file"):
        ScenarioSet.load(tmp_path)
    (tmp_path / "manifest.json").write_text("{")
    with pytest.raises(ScenarioFileError, match=r"manifest.json: not JSON"):
        ScenarioSet.load(tmp_path)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        # a file name that is no name, or one outside the set's own directory
        ({"file": 5}, r"splits.test.file must name a file of the set's own directory, got 5"),
        ({"file": None}, r"splits.test.file must name a file of the set's own directory"),
        ({"file": ["test.jsonl"]}, r"splits.test.file must name a file of the set's own"),
        ({"file": "../test.jsonl"}, r"splits.test.file must name a file of the set's own"),
        ({"file": "ABS"}, r"splits.test.file must name a file of the set's own"),
        ({"file": ".."}, r"splits.test.file must name a file of the set's own"),
    ],
)  # fmt: skip
def test_a_manifest_edited_by_hand_is_refused_in_one_line(make_spec, tmp_path, edit, message):
    set_dir = tmp_path / "set"
    write_scenario_set(make_spec(*SMALL), set_dir)
    manifest = json.loads((set_dir / "manifest.json").read_text())
    if edit.get("file") == "ABS":  # the same bytes, named by an absolute path
        edit = {"file": str(set_dir / "test.jsonl")}
    manifest["splits"]["test"].update(edit)
    (set_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ScenarioFileError, match=message) as e:
        ScenarioSet.load(set_dir)
    assert "\n" not in str(e.value)


def test_a_manifest_whose_config_miscounts_a_split_is_refused(make_spec, tmp_path):
    # A run records the set's size from its config: the two must agree.
    write_scenario_set(make_spec(*SMALL), tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["config"]["n_test"] = 91
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(
        ScenarioFileError, match=r"splits.test holds 90 scenarios, config.n_test says 91"
    ):
        ScenarioSet.load(tmp_path)


# k attackers vs m defenders -------------------------------------------------------------

TEAMS = [(1, 1), (2, 1), (1, 2), (2, 2)]
TINY = ("scenario.n_train=200", "scenario.n_val=40", "scenario.n_test=40")
BASE_KEYS = [
    "id",
    "defender_start",
    "attacker_start",
    "route",
    "defender_strategy",
    "defender_max_speed",
    "attacker_max_speed",
]


def _team(k: int, m: int, *overrides: str) -> tuple[str, ...]:
    return (f"scenario.attackers={k}", f"scenario.defenders={m}", *overrides)


def _drones(rec: dict) -> tuple[np.ndarray, np.ndarray]:
    """Start positions of a JSONL record: attackers (k, 3), defenders (m, 3)."""
    att = [rec["attacker_start"], *(a["start"] for a in rec.get("extra_attackers", []))]
    dfd = [rec["defender_start"], *(d["start"] for d in rec.get("extra_defenders", []))]
    return np.array(att), np.array(dfd)


@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_team_sets_meet_every_pairwise_constraint(make_spec, tmp_path, k, m):
    # A wide same-team separation, so that constraint rejects candidates too.
    spec = make_spec(*TINY, *_team(k, m, "scenario.min_separation=12"))
    write_scenario_set(spec, tmp_path)
    a, b, c = spec.vision_semi_axes
    for split in SPLITS:
        for line in (tmp_path / f"{split}.jsonl").read_text().splitlines():
            rec = json.loads(line)
            extra = [key for key in ("extra_attackers", "extra_defenders") if key in rec]
            assert list(rec) == BASE_KEYS + extra  # a 1-vs-1 record has the historical keys
            assert len(rec.get("extra_attackers", [])) == k - 1
            assert len(rec.get("extra_defenders", [])) == m - 1
            att, dfd = _drones(rec)
            assert dfd[0, 0] == 0 and dfd[0, 1] == 0
            assert (dfd[:, 2] >= 6).all() and (dfd[:, 2] <= 30).all()
            assert (np.abs(dfd[1:, :2]) <= 15).all()  # defender_spread
            for p in att:
                assert p[2] >= spec.min_altitude - 1e-9
                for d in dfd:
                    off = d - p
                    assert (off[0] / a) ** 2 + (off[1] / b) ** 2 + (off[2] / c) ** 2 <= 1 + 1e-6
                    assert np.linalg.norm(off) >= spec.min_distance - 1e-6
            for team in (att, dfd):
                for i in range(len(team)):
                    for j in range(i):
                        assert np.linalg.norm(team[i] - team[j]) >= 12 - 1e-6
            speeds = [rec["attacker_max_speed"], rec["defender_max_speed"]]
            speeds += [x["max_speed"] for key in extra for x in rec[key]]
            for v in speeds:
                assert 1.0 <= v <= 5.0 and math.isclose(v * 10, round(v * 10), abs_tol=1e-6)
            for x in rec.get("extra_defenders", []):
                assert x["route"] in range(4) and x["defender_strategy"] in STRATEGIES


@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_team_tensors_have_the_drone_dimension_and_match_the_files(make_spec, tmp_path, k, m):
    write_scenario_set(make_spec(*TINY, *_team(k, m)), tmp_path)
    ss = ScenarioSet.load(tmp_path)
    assert (ss.attackers, ss.defenders) == (k, m)
    for split in SPLITS:
        t = ss.split(split)
        records = [json.loads(x) for x in (tmp_path / f"{split}.jsonl").read_text().splitlines()]
        n = len(records)
        shapes = {
            "attacker_start": (n, k, 3),
            "defender_start": (n, m, 3),
            "route": (n, m),
            "defender_strategy": (n, m),
            "attacker_max_speed": (n, k),
            "defender_max_speed": (n, m),
        }
        assert {key: tuple(v.shape) for key, v in t.items()} == shapes
        assert t["route"].dtype == t["defender_strategy"].dtype == torch.int64
        assert t["attacker_start"].dtype == t["defender_max_speed"].dtype == torch.float32
        expected = {key: [] for key in shapes}
        for r in records:
            att, dfd = r.get("extra_attackers", []), r.get("extra_defenders", [])
            expected["attacker_start"].append([r["attacker_start"], *(x["start"] for x in att)])
            expected["defender_start"].append([r["defender_start"], *(x["start"] for x in dfd)])
            expected["route"].append([r["route"], *(x["route"] for x in dfd)])
            strategies = [r["defender_strategy"], *(x["defender_strategy"] for x in dfd)]
            expected["defender_strategy"].append([STRATEGIES.index(x) for x in strategies])
            v_a = [r["attacker_max_speed"], *(x["max_speed"] for x in att)]
            expected["attacker_max_speed"].append(v_a)
            v_d = [r["defender_max_speed"], *(x["max_speed"] for x in dfd)]
            expected["defender_max_speed"].append(v_d)
        for key, value in expected.items():
            assert t[key].numpy() == pytest.approx(np.array(value).reshape(shapes[key]), abs=1e-5)


def test_team_set_same_seed_gives_byte_identical_files(make_spec, tmp_path):
    spec = make_spec(*TINY, *_team(2, 2))
    write_scenario_set(spec, tmp_path / "a")
    write_scenario_set(spec, tmp_path / "b")
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert a == b and b"extra_attackers" in a["val.jsonl"] and b"extra_defenders" in a["val.jsonl"]
    write_scenario_set(make_spec(*TINY, *_team(2, 2), "scenario.seed=1"), tmp_path / "c")
    c = _files(tmp_path / "c")
    assert all(a[f] != c[f] for f in a)


def test_team_columns_and_combinations(make_spec):
    spec = make_spec(*_team(2, 2))
    assert spec.param_names == (
        *PARAM_NAMES,
        "attacker1_dx",
        "attacker1_dy",
        "attacker1_dz",
        "attacker1_max_speed",
        "defender1_dx",
        "defender1_dy",
        "defender1_z",
        "defender1_max_speed",
    )
    assert spec.categorical_names == (
        "route",
        "defender_strategy",
        "defender1_route",
        "defender1_strategy",
    )
    by_name = dict(zip(spec.param_names, spec.param_specs, strict=True))
    assert by_name["attacker1_dy"] == spec.params["attacker_dy"]
    assert by_name["defender1_dx"] == by_name["defender1_dy"] == spec.defender_spread
    assert by_name["defender1_z"] == spec.params["defender_z"]
    assert make_spec().param_names == PARAM_NAMES
    # Two grid levels per column: every column and every defender's route and strategy count.
    counts = ("scenario.n_train=10", "scenario.n_val=0", "scenario.n_test=0")
    coarse = (*COARSE[1:], "scenario.defender_spread.resolution=30", *counts)
    assert make_spec(*coarse).max_combinations() == 2**6 * 4 * 2
    assert make_spec(*coarse, *_team(2, 1)).max_combinations() == 2**10 * 4 * 2
    assert make_spec(*coarse, *_team(1, 2)).max_combinations() == 2**10 * (4 * 2) ** 2


def test_team_fields_are_optional_and_left_out_of_a_one_vs_one_config(make_spec):
    spec = make_spec()
    d = spec.to_dict()
    assert not {"attackers", "defenders", "min_separation", "defender_spread"} & set(d)
    assert ScenarioSpec.from_dict(d) == spec  # optional, with the defaults
    assert (spec.attackers, spec.defenders, spec.min_separation) == (1, 1, 3.0)
    team = make_spec(*_team(2, 1), "scenario.min_separation=4.5")
    d = team.to_dict()
    assert (d["attackers"], d["defenders"], d["min_separation"]) == (2, 1, 4.5)
    assert d["defender_spread"]["low"] == -15.0
    assert ScenarioSpec.from_dict(json.loads(json.dumps(d))) == team


def test_team_quality_report_covers_the_extra_columns(make_spec, tmp_path):
    spec = make_spec("scenario.n_train=300", "scenario.n_val=3", "scenario.n_test=60", *_team(2, 2))
    manifest = write_scenario_set(spec, tmp_path)
    q = manifest["quality"]
    assert set(q["representativeness"]["ks"]) == set(spec.param_names)
    assert set(q["representativeness"]["ks"]["defender1_z"]) == {
        "train-val",
        "train-test",
        "val-test",
    }
    assert set(q["representativeness"]["chi2"]) == set(spec.categorical_names)
    # Three val scenarios cannot fly all four routes: the extra defender's missing route and
    # the empty bins of extra columns are listed.
    missing = q["completeness"]["missing"]
    assert not q["completeness"]["complete"]
    assert any(x.startswith("val: defender1_route ") for x in missing)
    assert any(x.startswith("val: attacker1_dx bin ") for x in missing)
    assert any(x.startswith("val: defender1_max_speed bin ") for x in missing)
    assert q["independence"]["independent"]
    splits = generate(spec)
    keys = np.concatenate([grid_keys(spec, c.values, c.route, c.strategy) for c in splits.values()])
    assert keys.shape == (363, len(spec.param_names) + 4)
    assert len(np.unique(keys, axis=0)) == len(keys)
    text = format_quality(q)
    assert "KS   attacker1_max_speed" in text and "chi2 defender1_strategy" in text


def test_two_vs_one_scenario_config_is_pursuit_with_two_attackers(make_spec):
    two = make_spec("scenario=pursuit_2v1")
    assert (two.attackers, two.defenders) == (2, 1)
    assert dataclasses.replace(two, attackers=1) == make_spec()


def test_a_set_written_with_more_bins_than_a_new_one_may_have_still_loads(make_spec, tmp_path):
    # The bound on quality_bins guards generation; a set written with more has its report.
    write_scenario_set(make_spec("scenario.n_train=20", "scenario.n_val=5", "scenario.n_test=5"),
                       tmp_path)  # fmt: skip
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["config"]["quality_bins"] = 20_000
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    assert ScenarioSet.load(tmp_path).spec.quality_bins == 20_000


def test_a_set_written_before_the_generators_newer_rules_still_loads(make_spec, tmp_path):
    # A mean on a uniform parameter (which draws nothing from it), a gaussian mean outside the
    # range and a grid of more values than the generator now takes were written by earlier
    # versions with the same schema: the rules guard generation, the set loads.
    write_scenario_set(make_spec("scenario.n_train=20", "scenario.n_val=5", "scenario.n_test=5"),
                       tmp_path)  # fmt: skip
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    params = manifest["config"]["params"]
    params["attacker_max_speed"]["mean"] = 3.0
    params["defender_max_speed"].update(dist="gaussian", mean=7.0, std=1.0)
    params["defender_z"].update(high=1e5, resolution=0.001)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    spec = ScenarioSet.load(tmp_path).spec
    assert spec.params["attacker_max_speed"].mean is None
    assert spec.params["defender_max_speed"].mean == 7.0
    assert spec.params["defender_z"].levels > 10_000_000


def test_a_manifest_the_loader_refuses_names_scenarios_dir(make_spec, tmp_path):
    from rlplat.experiment.config import compose_config
    from rlplat.experiment.factory import resolve_scenarios

    write_scenario_set(make_spec("scenario.n_train=20", "scenario.n_val=5", "scenario.n_test=5"),
                       tmp_path)  # fmt: skip
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["config"]["params"]["defender_z"]["std"] = -1.0
    manifest["config"]["params"]["defender_z"]["dist"] = "gaussian"
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ConfigError, match=r"^scenarios_dir: .*manifest.json: config.params"):
        resolve_scenarios(compose_config("train", []), tmp_path)


def test_a_set_of_one_split_reports_no_pair_to_compare(make_spec, tmp_path):
    spec = make_spec("scenario.n_train=50", "scenario.n_val=0", "scenario.n_test=0")
    quality = write_scenario_set(spec, tmp_path)["quality"]
    assert all(not by_pair for by_pair in quality["representativeness"]["ks"].values())
    text = format_quality(quality)
    assert "representativeness    one non-empty split: no pair to compare" in text
    assert "KS " not in text and "chi2 " not in text


def test_an_empty_split_keeps_the_drone_dimension(make_spec, tmp_path):
    spec = make_spec("scenario.n_train=50", "scenario.n_val=0", "scenario.n_test=5", *_team(2, 2))
    manifest = write_scenario_set(spec, tmp_path)
    assert manifest["quality"]["independence"]["independent"]
    val = ScenarioSet.load(tmp_path).split("val")
    assert val["attacker_start"].shape == (0, 2, 3) and val["route"].shape == (0, 2)


def test_a_cache_that_cannot_be_written_names_rlplat_cache(tmp_path, monkeypatch):
    # A run without scenarios_dir caches its set; a cache no set can be written to is the
    # environment's RLPLAT_CACHE, not an out_dir the user never set.
    from rlplat.experiment.config import compose_config
    from rlplat.experiment.factory import resolve_scenarios

    a_file = tmp_path / "file"
    a_file.write_text("")
    monkeypatch.setattr("rlplat.experiment.factory.CACHE_DIR", a_file)
    cfg = compose_config("train", ["scenario.n_train=8", "scenario.n_val=4", "scenario.n_test=4"])
    with pytest.raises(ConfigError, match=rf"^RLPLAT_CACHE: the configured scenario set is cached "
                       rf"under {re.escape(str(a_file))}, and cannot write"):  # fmt: skip
        resolve_scenarios(cfg, None)


def test_a_small_set_writes_its_report_without_a_library_warning(make_spec, tmp_path):
    # scipy's exact KS p-value gives up on small splits and says so on stderr; the report
    # takes its asymptotic one, and the command line stays clean.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        manifest = write_scenario_set(
            make_spec("scenario.n_train=20", "scenario.n_val=5", "scenario.n_test=5",
                      "scenario.quality_bins=10000"),
            tmp_path,
        )  # fmt: skip
    assert [str(w.message) for w in caught if "ks_2samp" in str(w.message)] == []
    assert manifest["quality"]["representativeness"]
