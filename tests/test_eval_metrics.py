import csv
import math

import numpy as np
import pytest

from rlplat.eval.metrics import (
    Z95,
    iqm,
    outcome_stats,
    speed_ratio,
    speed_ratio_bin,
    speed_ratio_labels,
    stratified_bootstrap_ci,
    wilson_interval,
)
from rlplat.eval.report import pick_episodes
from rlplat.eval.tables import write_csv


@pytest.mark.parametrize(
    ("k", "n", "expected"),
    [
        (8, 10, (0.4902, 0.9433)),
        (0, 10, (0.0, 0.2775)),
        (10, 10, (0.7225, 1.0)),
        (50, 100, (0.4038, 0.5962)),
        (1, 3, (0.0615, 0.7923)),
    ],
)
def test_wilson_interval_known_values(k, n, expected):
    assert wilson_interval(k, n) == pytest.approx(expected, abs=1e-4)


def test_the_written_out_normal_quantile_is_scipys():
    from scipy import stats

    assert float(stats.norm.ppf(0.975)) == Z95


def test_wilson_interval_edges():
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    with pytest.raises(ValueError, match=r"successes must be in \[0, 5\], got 6"):
        wilson_interval(6, 5)


def test_iqm_is_the_mean_of_the_middle_half():
    assert iqm(np.arange(1, 9)) == pytest.approx(4.5)  # mean of 3, 4, 5, 6
    assert iqm([0, 0, 0, 0, 1, 1, 1, 100]) == pytest.approx(0.5)  # the outlier is cut
    assert iqm([[1.0, 3.0], [5.0, 7.0]]) == pytest.approx(4.0)  # all runs x tasks together


def test_bootstrap_of_two_seeds_has_the_exact_percentiles():
    # Resampled means of [0, 1] are 0, 0.5, 1 with probabilities 1/4, 1/2, 1/4.
    point, low, high = stratified_bootstrap_ci([0.0, 1.0], np.mean, reps=4000, seed=1)
    assert (point, low, high) == (0.5, 0.0, 1.0)


def test_bootstrap_matches_the_normal_interval_for_many_seeds():
    x = np.r_[np.ones(120), np.zeros(280)]  # p = 0.3, n = 400
    point, low, high = stratified_bootstrap_ci(x, np.mean, reps=4000, seed=0)
    half = 1.96 * math.sqrt(0.3 * 0.7 / 400)
    assert point == pytest.approx(0.3)
    assert low == pytest.approx(0.3 - half, abs=0.01) and high == pytest.approx(
        0.3 + half, abs=0.01
    )


def test_bootstrap_resamples_within_each_task():
    # Each task's runs agree: every stratified resample has the same pooled mean. A bootstrap
    # that pooled the tasks would mix them and give a wide interval.
    scores = np.array([[0.0, 1.0]] * 5)
    assert stratified_bootstrap_ci(scores, np.mean, reps=500) == (0.5, 0.5, 0.5)
    varied = np.array([[0.1, 0.9], [0.3, 0.5], [0.2, 0.6], [0.4, 0.8]])
    a = stratified_bootstrap_ci(varied, reps=500, seed=3)
    assert a == stratified_bootstrap_ci(varied, reps=500, seed=3)  # fixed seed, same interval
    assert a[1] < a[0] < a[2] and a != stratified_bootstrap_ci(varied, reps=500, seed=4)


def test_speed_ratio_bins_and_labels():
    edges = (0.5, 0.8, 1.0, 1.25, 2.0)
    assert speed_ratio_bin([0.4, 0.5, 0.99, 1.0, 3.0], edges).tolist() == [0, 1, 2, 3, 5]
    assert speed_ratio_labels(edges) == ["<0.5", "0.5-0.8", "0.8-1", "1-1.25", "1.25-2", ">=2"]
    # Speeds fly as float32: 1.5 / 1.2 is 1.25 as written, on the edge, so in the bin above.
    a, d = (float(np.float32(v)) for v in (1.5, 1.2))
    assert a / d < 1.25 and speed_ratio(a, d) == 1.25
    assert speed_ratio_bin([speed_ratio(a, d)], edges).tolist() == [4]


def test_outcome_stats_average_time_over_captures_only():
    s = outcome_stats(
        captured=np.array([True, False, True, True]),
        time_to_capture=np.array([2.0, np.nan, 4.0, 9.0]),
        returns=np.array([1.0, -3.0, 1.0, 1.0]),
        visible_fraction=np.array([1.0, 0.5, 1.0, 1.0]),
        min_distance=np.array([1.0, 9.0, 1.0, 1.0]),
    )
    assert (s["n"], s["captured"], s["capture_rate"]) == (4, 3, 0.75)
    assert s["capture_rate_ci95"] == pytest.approx(wilson_interval(3, 4))
    assert s["mean_time_to_capture_s"] == 5.0 and s["median_time_to_capture_s"] == 4.0
    assert s["mean_return"] == 0.0 and s["mean_visible_fraction"] == 0.875


def test_a_summarys_times_are_the_ones_its_episodes_csv_holds():
    # The env's times are float32 (12.3 is 12.3000002); pool reads them back from
    # episodes.csv (6 significant digits). Both means are of the same numbers, so compare's
    # table (from the summary) and pool's give one time for one evaluation.
    steps = np.random.default_rng(0).integers(20, 600, size=500)
    times = steps.astype(np.float32) * np.float32(0.1)
    ones = np.ones(500)
    s = outcome_stats(np.ones(500, dtype=bool), times, ones, ones, ones)
    from_csv = np.array([float(f"{float(t):.6g}") for t in times])
    assert s["mean_time_to_capture_s"] == from_csv.mean()
    assert s["median_time_to_capture_s"] == np.median(from_csv)


def test_episodes_csv_keeps_a_scenarios_values_to_the_files_six_decimals(tmp_path):
    # A fine grid's speeds 1.249999 and 1.0 m/s: the summary bins the ratio below 1.25; read
    # back from episodes.csv (pool) it must bin there too, so the scenario's columns are
    # written as the scenario files hold them, and what was measured to 6 significant digits.
    def f32(v: float) -> float:  # values fly as float32
        return float(np.float32(v))

    a, d = f32(1.249999), f32(1.0)
    row = {"scenario_id": "test-000000", "attacker_start_x": f32(-1000.125),
           "attacker_start_z": f32(1000.123), "attacker_max_speed": a, "defender_max_speed": d,
           "speed_ratio": speed_ratio(a, d), "team_speed_ratio": speed_ratio(a, d),
           "time_to_capture_s": f32(59.9), "min_distance_m": f32(3.14159274)}  # fmt: skip
    write_csv(tmp_path / "episodes.csv", [row])
    with open(tmp_path / "episodes.csv", newline="") as f:
        [back] = csv.DictReader(f)
    assert back["attacker_max_speed"] == back["speed_ratio"] == "1.249999"
    assert back["team_speed_ratio"] == "1.249999" and back["defender_max_speed"] == "1"
    assert (back["attacker_start_x"], back["attacker_start_z"]) == ("-1000.125", "1000.123")
    assert (back["time_to_capture_s"], back["min_distance_m"]) == ("59.9", "3.14159")
    edges = (0.5, 0.8, 1.0, 1.25, 2.0)
    binned = speed_ratio_bin([row["speed_ratio"], float(back["speed_ratio"])], edges)
    assert binned.tolist() == [3, 3]


def test_pick_episodes_takes_fastest_captures_and_worst_misses():
    rows = [
        {"captured": True, "time_to_capture_s": 5.0, "min_distance_m": 1.0},
        {"captured": False, "time_to_capture_s": None, "min_distance_m": 3.0},
        {"captured": True, "time_to_capture_s": 2.0, "min_distance_m": 1.1},
        {"captured": False, "time_to_capture_s": None, "min_distance_m": 30.0},
        {"captured": True, "time_to_capture_s": 9.0, "min_distance_m": 1.0},
    ]
    assert pick_episodes(rows, 4) == [(2, "best"), (0, "best"), (3, "worst"), (1, "worst")]
    assert pick_episodes(rows, 5) == [(2, "best"), (0, "best"), (4, "best"), (3, "worst"),
                                      (1, "worst")]  # fmt: skip
    caught = [rows[0], rows[2], rows[4]]
    assert pick_episodes(caught, 3) == [(1, "best"), (0, "best"), (2, "worst")]  # slowest
    assert pick_episodes(rows[:1], 3) == [(0, "best")]
    assert pick_episodes(rows, 0) == []


def test_pool_counts_every_episode_of_every_run(tmp_path):
    import json

    from rlplat.eval.pool import markdown, pooled_rows

    def evaluation(run, name, policy, captured, times, bound):
        out = tmp_path / run / "eval" / f"test-{name}"
        out.mkdir(parents=True)
        summary = {"policy": policy, "name": name, "drone": "attacker_v4"}
        (out / "summary.json").write_text(json.dumps(summary))
        rows = ["scenario_id,interceptable,captured,time_to_capture_s"]
        cells = zip(captured, times, bound, strict=True)
        rows += [f"s{i},{b},{c},{t}" for i, (c, t, b) in enumerate(cells)]
        (out / "episodes.csv").write_text("\n".join(rows) + "\n")

    bound = ["1", "0", ""]  # an intercept exists, none exists, not defined (nn defender)
    evaluation("s0", "best", "checkpoint", [1, 0, 1], ["10", "", "20"], bound)
    evaluation("s1", "best", "checkpoint", [1, 0, 0], ["30", "", ""], bound)
    evaluation("s0", "proportional_navigation", "proportional_navigation", [1, 0, 0],
               ["5", "", ""], bound)  # fmt: skip
    rows = pooled_rows([tmp_path / "s0", tmp_path / "s1"])
    learned, pn = rows
    assert learned["policy"] == "attacker_v4 (best)" and learned["runs"] == 2
    assert learned["episodes"] == 6 and learned["capture_rate"] == 3 / 6
    assert learned["mean_time_to_capture_s"] == 20.0 and learned["median_time_to_capture_s"] == 20
    assert learned["ceiling"] == 0.5 and learned["capture_rate_covered"] == 2 / 4
    assert pn["episodes"] == 3 and pn["capture_rate"] == 1 / 3
    assert "| attacker_v4 (best) | 2 | 6 | 0.500 [" in markdown(rows)


def _headroom_evaluation(root, run, name, policy, captured, bounded=True, times=None, **summary):
    """An evaluation of five scenarios as evaluate.py writes it (the columns pool reads); a
    capture takes 9 s unless ``times`` says otherwise."""
    import json

    out = root / run / "eval" / f"test-{name}"
    out.mkdir(parents=True)
    summary = {"policy": policy, "name": name, "drone": "attacker_v8", "scenario_digest": "d0",
               "speed_ratio_bins": [1.0], "attackers": 1, "dynamics": "velocity",
               **summary}  # fmt: skip
    (out / "summary.json").write_text(json.dumps(summary))
    rows = ["scenario_id,defender_strategy,speed_ratio,interceptable,captured,time_to_capture_s"]
    scenarios = [("nn", 0.5, ""), ("nn", 2.0, ""), ("setpoints", 0.5, "1"),
                 ("setpoints", 0.5, "0"), ("setpoints", 1.0, "1")]  # fmt: skip
    times = times or [9] * len(scenarios)
    cells = zip(scenarios, captured, times, strict=True)
    for i, ((strategy, ratio, bound), c, t) in enumerate(cells):
        bound = bound if bounded else ""  # e.g. dynamics without a ceiling
        rows.append(f"s{i},{strategy},{ratio},{bound},{c},{t if c else ''}")
    (out / "episodes.csv").write_text("\n".join(rows) + "\n")


def test_headroom_splits_the_scenarios_and_counts_a_capture_of_any_policy(tmp_path, capsys):
    from rlplat.eval.pool import headroom_rows, main

    # The first evaluation read records no ceiling: the ceiling comes from the others.
    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1], bounded=False)
    _headroom_evaluation(tmp_path, "s1", "best", "checkpoint", [0, 1, 0, 0, 1])
    _headroom_evaluation(tmp_path, "s1", "proportional_navigation", "proportional_navigation",
                         [0, 1, 1, 0, 0])  # fmt: skip
    pooled = headroom_rows([tmp_path / "s0", tmp_path / "s1"])
    rows = {(r["defender"], r["speed_ratio"]): r for r in pooled}
    groups = [("all", "all"), ("nn", "all"), ("nn", "<1"), ("nn", ">=1"),
              ("setpoints", "all"), ("setpoints", "<1"), ("setpoints", ">=1")]  # fmt: skip
    assert list(rows) == groups
    everything, slow = rows["all", "all"], rows["setpoints", "<1"]
    assert everything["scenarios"] == 5 and everything["ceiling"] is None  # nn: no ceiling
    assert "route_ceiling" not in everything  # no evaluation recorded one
    assert everything["any"] == 4 / 5  # only s3 was never captured
    assert everything["rates"] == {"attacker_v8 (best)": 5 / 10, "proportional_navigation": 2 / 5}
    assert slow["scenarios"] == 2 and slow["ceiling"] == 0.5 and slow["any"] == 0.5
    assert slow["rates"]["attacker_v8 (best)"] == 0.0 and rows["nn", "<1"]["any"] == 1.0
    assert (
        rows["setpoints", ">=1"]["ceiling"] == 1.0 and rows["setpoints", "all"]["ceiling"] == 2 / 3
    )
    main([str(tmp_path / "s1"), "--headroom"])
    assert "| setpoints | <1 | 2 | 0.500 | 0.500 | 0.000 | 0.500 |" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("summary", "message"),
    [
        ({"scenario_digest": "d1"}, "2 scenario sets"),
        ({"attackers": 2}, "2 team sizes"),
        ({"dynamics": "quadrotor"}, "2 dynamics"),
        ({"speed_ratio_bins": [0.5, 1.0]}, "bin differently"),
        ({"learner": "defender"}, "a defender"),
        ({"policy": "setpoint_follower"}, "a defender"),  # a defender learner's baseline
    ],
)
def test_headroom_pools_only_what_one_attacker_table_can_hold(tmp_path, summary, message):
    from rlplat.errors import ConfigError
    from rlplat.eval.pool import headroom_rows

    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1])
    summary = dict(summary)
    policy = summary.pop("policy", "checkpoint")
    _headroom_evaluation(tmp_path, "s1", "best", policy, [1, 1, 1, 1, 1], **summary)
    with pytest.raises(ConfigError, match=message):
        headroom_rows([tmp_path / "s0", tmp_path / "s1"])


def test_headroom_bins_a_team_by_its_fastest_attacker_when_asked(tmp_path, capsys):
    from rlplat.errors import ConfigError
    from rlplat.eval.pool import headroom_rows, main

    runs = []
    for run, captured in (("s0", [1, 1, 0, 1, 1]), ("s1", [0, 1, 1, 0, 1])):
        _headroom_evaluation(tmp_path, run, "best", "checkpoint", captured, attackers=2)
        path = tmp_path / run / "eval" / "test-best" / "episodes.csv"
        # The second attacker is the faster one in s0 (0.5 -> 2.0), s3 (0.5 -> 1.5) and s4.
        lines = path.read_text().splitlines()
        team = ["team_speed_ratio", "2.0", "2.0", "0.5", "1.5", "1.2"]
        # The route ceiling: s0's network defender could be met on its route, s1's not.
        route = ["route_interceptable", "1", "0", "1", "0", "1"]
        cells = zip(lines, team, route, strict=True)
        path.write_text("\n".join(",".join(c) for c in cells) + "\n")
        runs.append(tmp_path / run)

    def groups(ratio):
        rows = headroom_rows(runs, ratio=ratio)
        return {(r["defender"], r["speed_ratio"]): r["scenarios"] for r in rows}

    first, team = groups("first"), groups("team")
    assert first["setpoints", "<1"] == 2 and first["setpoints", ">=1"] == 1
    assert team["setpoints", "<1"] == 1 and team["setpoints", ">=1"] == 2
    assert first["nn", "<1"] == first["nn", ">=1"] == 1
    assert ("nn", "<1") not in team and team["nn", ">=1"] == 2
    slow = {(r["defender"], r["speed_ratio"]): r for r in headroom_rows(runs, ratio="team")}
    assert slow["setpoints", ">=1"]["rates"] == {"attacker_v8 (best)": 3 / 4}
    assert slow["nn", "all"]["route_ceiling"] == 0.5 and slow["nn", "all"]["ceiling"] is None
    assert slow["setpoints", "all"]["route_ceiling"] == slow["setpoints", "all"]["ceiling"] == 2 / 3
    main([str(r) for r in runs] + ["--headroom", "--ratio", "team"])
    out = capsys.readouterr().out
    assert "| defender | team speed ratio | scenarios | ceiling | route ceiling |" in out
    assert "| nn | all | 2 | – | 0.500 | 1.000 | 0.750 |" in out  # any; the learner's 3 of 4
    _headroom_evaluation(tmp_path, "s1", "pure_pursuit", "pure_pursuit", [1] * 5, attackers=2)
    with pytest.raises(ConfigError, match="pure_pursuit have no team_speed_ratio column"):
        headroom_rows(runs, ratio="team")
    headroom_rows(runs)  # the first attacker's ratio needs no such column
    with pytest.raises(ConfigError, match="--ratio: unknown 'fastest'; valid: first, team"):
        headroom_rows(runs, ratio="fastest")
    with pytest.raises(SystemExit):  # one line on stderr, and no table before it
        main([str(runs[0]), "--headroom", "--ratio", "fastest"])
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1 and "valid: first, team" in out.err


def test_against_sets_each_policy_against_the_reference_scenario_by_scenario(tmp_path, capsys):
    from rlplat.errors import ConfigError
    from rlplat.eval.pool import main, paired_markdown, paired_rows

    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1],
                         times=[8, 10, 0, 0, 20])  # fmt: skip
    _headroom_evaluation(tmp_path, "s1", "best", "checkpoint", [0, 1, 0, 0, 1],
                         times=[0, 12, 0, 0, 30])  # fmt: skip
    _headroom_evaluation(tmp_path, "s1", "proportional_navigation", "proportional_navigation",
                         [0, 1, 1, 0, 0], times=[0, 14, 5, 0, 0])  # fmt: skip
    (row,) = paired_rows([tmp_path / "s0", tmp_path / "s1"], "proportional_navigation")
    # Per scenario the learner's fraction over its two runs: 0.5, 1, 0, 0, 1; the law's 0, 1,
    # 1, 0, 0. The differences 0.5, 0, -1, 0, 1: mean 0.1, sample variance 2.2 / 4.
    assert row["policy"] == "attacker_v8 (best)" and row["runs"] == 2 and row["scenarios"] == 5
    assert row["gain"] == pytest.approx(0.1) and row["sd"] == pytest.approx(0.55**0.5)
    half = 1.96 * 0.55**0.5 / 5**0.5
    assert row["ci95"] == pytest.approx((0.1 - half, 0.1 + half))
    assert (row["gained"], row["lost"]) == (2, 1)
    # Only s1 was captured by both: the learner in 11 s on average, the law in 14 s.
    assert row["both_captured"] == 1 and row["time_delta_s"] == pytest.approx(-3.0)
    # Each run against the law: s0 gains 1 + 0 - 1 + 0 + 1 of 5, s1 0 + 0 - 1 + 0 + 1. Their
    # mean is the pooled gain; with two runs the t interval has 1 degree of freedom (12.706).
    assert row["run_gains"] == pytest.approx([0.2, 0.0]) and row["runs_sd"] == pytest.approx(
        0.02**0.5
    )
    half = 12.7062 * 0.02**0.5 / 2**0.5  # 1.27: the interval is what a gain can be, [-1, 1]
    assert 0.1 - half < -1 and 0.1 + half > 1 and row["runs_ci95"] == (-1.0, 1.0)
    main([str(tmp_path / "s0"), str(tmp_path / "s1"), "--against", "proportional_navigation"])
    out = capsys.readouterr().out
    assert "| attacker_v8 (best) | 2 | 5 | +0.100 [" in out
    assert "| +0.200, +0.000; +0.100 [-1.000, +1.000] |" in out
    one = {k: v for k, v in row.items() if not k.startswith("runs_")}
    one |= {"scenarios": 1, "gain": 1.0, "ci95": (float("nan"),) * 2, "gained": 1, "lost": 0,
            "both_captured": 0, "time_delta_s": None, "run_gains": [1.0]}  # fmt: skip
    # One run: no column of runs (compare's table of one run has none).
    assert paired_markdown([one]).endswith("| attacker_v8 (best) | 2 | 1 | +1.000 | 1 / 0 | – |")
    # A run that flew other scenarios than the reference is refused, naming it.
    csv_path = tmp_path / "s1" / "eval" / "test-best" / "episodes.csv"
    lines = csv_path.read_text().splitlines()
    csv_path.write_text("\n".join(lines[:-1]) + "\n")
    _headroom_evaluation(tmp_path, "s2", "best", "checkpoint", [0, 1, 0, 0, 1])
    with pytest.raises(ConfigError, match=r"\(best\) in .*s1/eval/test-best flew 4 scenarios"):
        paired_rows([tmp_path / r for r in ("s0", "s1", "s2")], "proportional_navigation")


def test_pool_reads_evaluation_directories_as_it_reads_runs(tmp_path, capsys):
    """An evaluate.py out_dir (a run flown on another scenario set, a baseline evaluated once)
    pools as the same evaluation under a run's eval/ does; one of another split is refused."""
    from rlplat.errors import ConfigError
    from rlplat.eval.pool import main, paired_rows, pooled_rows

    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1],
                         times=[8, 10, 0, 0, 20], split="test")  # fmt: skip
    _headroom_evaluation(tmp_path, "s1", "best", "checkpoint", [0, 1, 0, 0, 1],
                         times=[0, 12, 0, 0, 30], split="test")  # fmt: skip
    _headroom_evaluation(tmp_path, "s1", "proportional_navigation", "proportional_navigation",
                         [0, 1, 1, 0, 0], times=[0, 14, 5, 0, 0], split="test")  # fmt: skip
    runs = [tmp_path / "s0", tmp_path / "s1"]
    evaluations = [
        tmp_path / "s0" / "eval" / "test-best",
        *sorted((tmp_path / "s1" / "eval").iterdir()),
    ]
    assert pooled_rows(evaluations) == pooled_rows(runs)
    # A folder of evaluations (evaluate.py compare=true out_dir=) pools as its run does.
    assert pooled_rows([runs[0], tmp_path / "s1" / "eval"]) == pooled_rows(runs)
    with pytest.raises(ConfigError, match=r"^pool: .*nowhere is not a directory"):
        pooled_rows([tmp_path / "nowhere"])
    # An evaluation named twice (itself and its run) counts once.
    assert pooled_rows([*runs, evaluations[0], tmp_path / "s0" / ".." / "s0"]) == pooled_rows(runs)
    (row,) = paired_rows(evaluations, "proportional_navigation")
    assert row == paired_rows(runs, "proportional_navigation")[0] and row["runs"] == 2
    with pytest.raises(ConfigError, match="evaluates the test split, not val; pass --split test"):
        pooled_rows(evaluations, split="val")
    with pytest.raises(SystemExit):  # one line on stderr, and no table before it
        main([*map(str, evaluations), "--split", "val"])
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1


def test_against_refuses_an_unknown_reference_and_different_scenarios(tmp_path, capsys, caplog):
    from rlplat.errors import ConfigError
    from rlplat.eval.pool import main, paired_rows, pooled_rows

    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1])
    _headroom_evaluation(tmp_path, "s0", "pure_pursuit", "pure_pursuit", [1, 1, 0, 0, 1])
    runs = [tmp_path / "s0"]
    with pytest.raises(ConfigError, match="'proportional_navigation'.*valid: attacker_v8"):
        paired_rows(runs, "proportional_navigation")
    with pytest.raises(SystemExit):  # one line on stderr, and no table before it
        main([str(tmp_path / "s0"), "--against", "proportional_navigation"])
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1 and "valid:" in out.err
    _headroom_evaluation(tmp_path, "s1", "best", "checkpoint", [1, 1, 0, 0, 1],
                         scenario_digest="d1")  # fmt: skip
    with pytest.raises(ConfigError, match="2 scenario sets"):
        paired_rows([*runs, tmp_path / "s1"], "pure_pursuit")
    with caplog.at_level("WARNING", logger="rlplat.eval.pool"):  # a plain table says so
        pooled_rows([*runs, tmp_path / "s1"])
    assert "the evaluations flew 2 scenario sets (d0, d1)" in caplog.text
    caplog.clear()
    _headroom_evaluation(tmp_path, "q1", "best", "checkpoint", [1, 1, 0, 0, 1],
                         dynamics="quadrotor")  # fmt: skip
    with caplog.at_level("WARNING", logger="rlplat.eval.pool"):  # the command too, and dynamics
        main([*map(str, runs), str(tmp_path / "s1"), str(tmp_path / "q1")])
    assert "flew 2 scenario sets (d0, d1)" in caplog.text
    assert "flew 2 dynamics (quadrotor, velocity)" in caplog.text
    _headroom_evaluation(tmp_path, "d0", "best", "checkpoint", [1, 1, 0, 0, 1], learner="defender")
    _headroom_evaluation(tmp_path, "d0", "pure_pursuit", "pure_pursuit", [1, 1, 0, 0, 1])
    with pytest.raises(ConfigError, match="a defender; the gain is an attacker's"):
        paired_rows([tmp_path / "d0"], "pure_pursuit")
    episodes = tmp_path / "s0" / "eval" / "test-pure_pursuit" / "episodes.csv"
    episodes.write_text("".join(episodes.read_text().splitlines(keepends=True)[:-1]))
    with pytest.raises(ConfigError, match="flew 5 scenarios, pure_pursuit 4"):
        paired_rows(runs, "pure_pursuit")


def test_compare_sets_policies_against_the_law_only_where_one_game_was_flown(tmp_path):
    import json

    from rlplat.eval.compare import _paired_section

    run = tmp_path / "s0"
    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1])
    _headroom_evaluation(tmp_path, "s0", "proportional_navigation", "proportional_navigation",
                         [0, 1, 1, 0, 0])  # fmt: skip

    def summaries():
        return [json.loads(p.read_text()) for p in sorted(run.glob("eval/test-*/summary.json"))]

    section = _paired_section(run / "eval", summaries(), "test")
    assert "## Against proportional navigation" in section
    assert "| attacker_v8 (best) | 1 | 5 | +0.200 [" in section and "| 2 / 1 |" in section
    # The same run flown on other dynamics too (a dynamics swap's evaluation, same scenarios):
    # no pairing across two games, and no error either.
    _headroom_evaluation(tmp_path, "s0", "best-airsim", "checkpoint", [1, 1, 0, 0, 1],
                         dynamics="airsim")  # fmt: skip
    assert _paired_section(run / "eval", summaries(), "test") == ""


def test_route_labels_name_each_routes_direction_also_for_one_setpoint():
    import torch

    from rlplat.eval.tables import route_labels

    two = torch.tensor(
        [[[8.0, 5.0, 20.0], [144.0, -5.0, 18.0]], [[5.0, -8.0, 9.0], [-5.0, -144.0, 8.0]]]
    )
    assert route_labels(two) == ["+X", "-Y"]
    one = torch.tensor([[[-3.0, -4.0, 10.0]], [[50.0, 2.0, 10.0]]])  # from the origin
    assert route_labels(one) == ["-Y", "+X"]
    # A loop back to its start goes where its farthest setpoint is (it was "+X" whatever
    # its shape); a route that stays over its start has no horizontal direction.
    loops = torch.tensor(
        [
            [[0.0, 0.0, 10.0], [3.0, -20.0, 10.0], [-2.0, -30.0, 10.0], [0.0, 0.0, 10.0]],
            [[1.0, 1.0, 10.0], [1.0, 1.0, 20.0], [1.0, 1.0, 30.0], [1.0, 1.0, 10.0]],
        ]
    )
    assert route_labels(loops) == ["-Y", "Z"]


def test_pool_tells_runs_launched_with_other_overrides_apart(tmp_path, caplog):
    """Runs of one drone launched differently are different policies, not more seeds of one:
    each is labelled by the overrides that set it apart (an older evaluation by its run's
    .hydra/ record)."""
    from omegaconf import OmegaConf

    from rlplat.eval.pool import paired_rows, pooled_rows

    common = ["train.progress=false"]
    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [1, 1, 0, 0, 1],
                         run_overrides=common)  # fmt: skip
    _headroom_evaluation(tmp_path, "s1", "best", "checkpoint", [0, 1, 0, 0, 1],
                         run_overrides=common)  # fmt: skip
    _headroom_evaluation(tmp_path, "s1", "proportional_navigation", "proportional_navigation",
                         [0, 1, 1, 0, 0])  # fmt: skip
    # an evaluation written before run_overrides was recorded: its run's record is read
    (tmp_path / "g0" / ".hydra").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create(["seed=0", *common, "algo.gamma=0.998"]),
                   tmp_path / "g0" / ".hydra" / "overrides.yaml")  # fmt: skip
    _headroom_evaluation(tmp_path, "g0", "best", "checkpoint", [1, 1, 1, 0, 1],
                         run_dir=str(tmp_path / "g0"))  # fmt: skip
    runs = [tmp_path / r for r in ("s0", "s1", "g0")]
    rows = {r["policy"]: r for r in pooled_rows(runs)}
    assert list(rows) == ["attacker_v8 (best) default", "attacker_v8 (best) algo.gamma=0.998",
                          "proportional_navigation"]  # fmt: skip
    assert rows["attacker_v8 (best) default"]["runs"] == 2
    assert rows["attacker_v8 (best) algo.gamma=0.998"]["capture_rate"] == 4 / 5
    paired = {r["policy"]: r for r in paired_rows(runs, "proportional_navigation")}
    assert paired["attacker_v8 (best) default"]["run_gains"] == [0.2, 0.0]  # each run, learned
    # one launch: one policy, as before, whatever else the runs recorded
    assert [r["policy"] for r in pooled_rows(runs[:2])][0] == "attacker_v8 (best)"
    # a run with no record pools under the plain label, and says the runs cannot all be told apart
    _headroom_evaluation(tmp_path, "x0", "best", "checkpoint", [1, 1, 0, 0, 1])
    with caplog.at_level("WARNING", logger="rlplat.eval.pool"):
        labels = [r["policy"] for r in pooled_rows([*runs, tmp_path / "x0"])]
    assert "attacker_v8 (best)" in labels and "have no record of their overrides" in caplog.text


def test_a_gains_interval_stays_within_what_a_difference_of_fractions_can_be(tmp_path):
    from rlplat.eval.pool import paired_rows

    # Five scenarios: the law captures all but one, the run none: gain -0.8, and a normal
    # interval of 1.96 standard errors would reach below -1.
    _headroom_evaluation(tmp_path, "s0", "best", "checkpoint", [0, 0, 0, 0, 0])
    _headroom_evaluation(tmp_path, "s0", "proportional_navigation", "proportional_navigation",
                         [1, 1, 1, 1, 0])  # fmt: skip
    (row,) = paired_rows([tmp_path / "s0"], "proportional_navigation")
    assert row["gain"] == pytest.approx(-0.8)
    assert row["ci95"][0] == -1.0 and row["ci95"][1] < -0.4


@pytest.mark.parametrize(
    "module, argv, message",
    [
        ("rlplat.eval.compare", [], "the following arguments are required: run_dir"),
        ("rlplat.eval.compare", ["x", "--nope"], "unrecognized arguments: --nope"),
        ("rlplat.eval.aggregate", ["x", "--reps", "many"], "argument --reps: invalid int value"),
        ("rlplat.eval.pool", [], "the following arguments are required: run_dirs"),
        ("rlplat.experiment.controller", ["x", "y.pt", "--ckpt", "bset"],
         "argument --ckpt: invalid choice: 'bset'"),
        ("rlplat.envs.airsim.testserver", ["--port", "abc"], "argument --port: invalid int"),
        # An empty path is not the current folder, nor an empty option no option.
        ("rlplat.eval.compare", [""], "argument run_dir: must not be empty, got ''"),
        ("rlplat.eval.compare", ["x", "--eval-dir", ""], "argument --eval-dir: must not be empty"),
        ("rlplat.eval.pool", ["x", ""], "argument run_dirs: must not be empty"),
        ("rlplat.eval.pool", ["x", "--against", " "], "argument --against: must not be empty"),
        ("rlplat.eval.aggregate", [""], "argument sweep_dir: must not be empty"),
        ("rlplat.experiment.controller", ["x", ""], "argument out: must not be empty"),
        ("rlplat.envs.airsim.testserver", ["--settings", ""], "argument --settings: must not be"),
    ],
)  # fmt: skip
def test_an_argument_tool_refuses_in_one_line_naming_itself(module, argv, message, capsys):
    import importlib

    main = importlib.import_module(module).main
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("error: python -m ") and message in err[0], err
    assert err[0].endswith("(see --help)")
