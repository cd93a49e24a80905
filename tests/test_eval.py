import csv
import inspect
import json
import logging
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from rlplat.agents.policies import make_scripted_policy
from rlplat.errors import ConfigError
from rlplat.eval.ceiling import intercept_ceiling
from rlplat.eval.episodes import evaluate
from rlplat.eval.metrics import wilson_interval
from rlplat.eval.tables import episode_rows, summarize
from rlplat.experiment.config import compose_config
from rlplat.experiment.evaluation import evaluate_from_config, evaluate_run
from rlplat.experiment.export import export_run
from rlplat.experiment.factory import build_env
from rlplat.scenarios import ScenarioSet

ROOT = Path(__file__).resolve().parent.parent

# Dynamics without lag, acceleration limit or drag: a drone flies at its command at once.
IDEAL = (
    "dynamics.tau_xy=1e-4",
    "dynamics.tau_z=1e-4",
    "dynamics.a_xy_max=1e6",
    "dynamics.a_up_max=1e6",
    "dynamics.a_down_max=1e6",
    "dynamics.drag_xy=0",
    "dynamics.drag_z=0",
)


# Hand-made scenarios with a known outcome ----------------------------------------------


def hovering_defender_set(tmp_path, attacker_x: list[float], attacker_speed: float) -> ScenarioSet:
    """Defenders hovering at (0, 0, 10): a route of 1000 setpoints at their start, so the route
    lasts 1000 steps and the command is zero. Attackers at (x, 0, 10)."""
    n = len(attacker_x)
    split = TensorDict(
        {
            "defender_start": torch.tensor([[[0.0, 0.0, 10.0]]] * n),
            "attacker_start": torch.tensor([[[x, 0.0, 10.0]] for x in attacker_x]),
            "route": torch.zeros(n, 1, dtype=torch.int64),
            "defender_strategy": torch.zeros(n, 1, dtype=torch.int64),
            "defender_max_speed": torch.full((n, 1), 1.0),
            "attacker_max_speed": torch.full((n, 1), attacker_speed),
        },
        batch_size=[n],
    )
    ids = {s: [f"{s}-{i}" for i in range(n)] for s in ("train", "val", "test")}
    routes = torch.tensor([[[0.0, 0.0, 10.0]] * 1000])
    splits = {s: split.clone() for s in ids}
    return ScenarioSet(tmp_path, {}, None, ids, splits, routes)


def test_hovering_defender_is_captured_at_the_computed_time(tmp_path):
    v, dt, physics_dt, radius = 2.0, 0.1, 0.05, 1.2
    d0 = [10.1, 60.1]
    sset = hovering_defender_set(tmp_path, [-x for x in d0], v)
    cfg = compose_config("train", ["drone=attacker_v4", *IDEAL, "env.time_limit=10"])  # eq. 3
    env = build_env(cfg, scenarios=sset, split="test", num_envs=2, scenario_order="sequential")
    results = evaluate(env, make_scripted_policy("pure_pursuit", env), record=True)

    # The attacker flies at v from the first sub-step on (its start averages 0 and v), so after
    # k steps it is d0 - v dt k + v physics_dt / 2 away.
    def distance(x0, k):
        return x0 - v * dt * k + v * physics_dt / 2

    k_capture = math.ceil((d0[0] + v * physics_dt / 2 - radius) / (v * dt))
    assert k_capture == 45
    assert results.captured.tolist() == [True, False]
    assert results.length.tolist() == [k_capture, 100]
    assert results.time_to_capture[0].item() == pytest.approx(k_capture * dt)
    assert results.min_distance.tolist() == pytest.approx(
        [distance(d0[0], k_capture), distance(d0[1], 100)], abs=1e-3
    )
    # The far attacker sees the defender once within the 48 m semi-axis.
    far = np.array([distance(d0[1], k) for k in range(1, 101)])
    assert results.visible_fraction.tolist() == pytest.approx([1.0, np.mean(far <= 48.0)])
    assert results.visible_fraction[1].item() == pytest.approx(0.40)
    near = np.array([distance(d0[0], k) for k in range(1, k_capture)])
    in_view = -2 * (near / 60) ** 2 - 0.1
    far_reward = np.where(far <= 48.0, -2 * (far / 60) ** 2 - 0.1, -1.0)
    assert results.returns.tolist() == pytest.approx([10 + in_view.sum(), far_reward.sum()], 1e-3)
    assert results.term_sums["capture"].tolist() == [10.0, 0.0]
    # Recorded paths: the starts, then frozen once an episode has ended.
    pos = results.positions
    assert pos.shape == (2, 101, 2, 3)
    assert pos[:, 0, 0, 0].tolist() == pytest.approx([-d0[0], -d0[1]])
    assert torch.equal(pos[0, k_capture:], pos[0, k_capture].expand(101 - k_capture, 2, 3))
    assert torch.allclose(pos[:, :, 1], torch.tensor([0.0, 0.0, 10.0]))  # hovering

    # The evaluator's table and summary of the same episodes.
    rows = episode_rows(results, sset, "test", env.routes)
    assert [r["scenario_id"] for r in rows] == ["test-0", "test-1"]
    assert rows[0]["time_to_capture_s"] == pytest.approx(4.5) and rows[1]["captured"] is False
    assert rows[0]["speed_ratio"] == 2.0 and rows[0]["route_direction"] == "Z"  # it hovers
    summary = summarize(rows, list(env.reward_fn.weights), [0.5, 1.0, 2.5])
    assert summary["capture_rate"] == 0.5
    assert summary["capture_rate_ci95"] == pytest.approx(wilson_interval(1, 2))
    assert summary["mean_time_to_capture_s"] == pytest.approx(4.5)
    assert list(summary["by_speed_ratio"]) == ["1-2.5"]


def test_setpoint_follower_flies_the_defender_like_the_scripted_one(write_small_set, tmp_path):
    """Attacker learns + pure pursuit policy == defender learns + setpoint-follower policy:
    both fly pure pursuit against the route follower (on setpoint-strategy scenarios)."""
    setpoint_only = write_small_set(tmp_path, "scenario.strategy_mix.nn=0")

    def fly(learner, policy):
        # eq. 1 and 2 for either learner (attacker_v4's guided action flies attackers only),
        # each with its side's reward (which changes no flight)
        reward = "evasion" if learner == "defender" else "shaped"
        cfg = compose_config("train", ["drone=attacker_v3", f"drone.learner={learner}",
                                       f"reward={reward}", "env.time_limit=20"])  # fmt: skip
        env = build_env(cfg, scenarios=setpoint_only, split="test", num_envs=16)
        return evaluate(env, make_scripted_policy(policy, env))

    a = fly("attacker", "pure_pursuit")
    d = fly("defender", "setpoint_follower")
    assert a.captured.any() and torch.equal(a.captured, d.captured)
    assert torch.allclose(a.min_distance, d.min_distance, atol=1e-3)
    assert torch.equal(a.length, d.length)


def test_baseline_registry_errors(scenarios):
    cfg = compose_config("train", [])
    env = build_env(cfg, scenarios=scenarios, split="test", num_envs=16)
    with pytest.raises(ConfigError, match=r"policy: unknown baseline 'lqr'; valid: pure_pursuit"):
        make_scripted_policy("lqr", env)
    with pytest.raises(
        ConfigError,
        match=r"policy: setpoint_follower flies the defender, this run's learner is the "
        r"attacker; valid: pure_pursuit, proportional_navigation, route_intercept$",
    ):
        make_scripted_policy("setpoint_follower", env)


# A trained run, through the CLI ----------------------------------------------------------


@pytest.fixture(scope="module")
def trained_run(scenarios, tmp_path_factory, tiny, run_python):
    run = tmp_path_factory.mktemp("run")
    # attacker_v4: pursuit_state (R^10) and a guided_velocity action (a correction of scale 1)
    res = run_python(
        "train.py", *tiny, "drone=attacker_v4", "env.time_limit=20",
        f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return run


def read_episodes(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_cli_train_evaluate_compare_round_trip(trained_run, scenarios, run_python):
    run = trained_run
    policies = "checkpoint,pure_pursuit,proportional_navigation"
    res = run_python("evaluate.py", "-m", f"run_dir={run}", f"policy={policies}")
    assert res.returncode == 0, res.stderr[-2000:]
    trained = json.loads((run / "summary.json").read_text())
    for name in ("best", "pure_pursuit", "proportional_navigation"):
        out = run / "eval" / f"test-{name}"
        assert f"report {out / 'report.md'}" in res.stdout
        rows = read_episodes(out / "episodes.csv")
        s = json.loads((out / "summary.json").read_text())
        assert [r["scenario_id"] for r in rows] == scenarios.ids["test"] and s["scenarios"] == 16
        # The summary is what the table implies.
        captured = np.array([r["captured"] == "1" for r in rows])
        times = np.array([float(r["time_to_capture_s"]) for r in rows if r["captured"] == "1"])
        assert s["captured"] == captured.sum() and s["capture_rate"] == captured.mean()
        assert s["capture_rate_ci95"] == pytest.approx(wilson_interval(captured.sum(), 16))
        returns = np.array([float(r["return"]) for r in rows])
        terms = sum(np.array([float(r[f"reward_{k}"]) for r in rows]) for k in s["reward_terms"])
        assert returns == pytest.approx(terms, abs=1e-3)
        assert s["mean_return"] == pytest.approx(returns.mean(), rel=1e-5)
        if len(times):
            assert s["mean_time_to_capture_s"] == pytest.approx(times.mean(), rel=1e-5)
            assert s["median_time_to_capture_s"] == pytest.approx(np.median(times), rel=1e-5)
        visible = np.array([float(r["visible_fraction"]) for r in rows])
        assert s["mean_visible_fraction"] == pytest.approx(visible.mean(), rel=1e-5)
        for key in ("by_route", "by_speed_ratio", "by_strategy"):
            assert sum(g["n"] for g in s[key].values()) == 16
            assert sum(g["captured"] for g in s[key].values()) == captured.sum()
        assert s["scenario_digest"] == trained["scenario_digest"] and s["scenario_digest_matches"]
        report = (out / "report.md").read_text()
        for png in ("learning_curve", "capture_vs_speed_ratio", "capture_by_route", "trajectories"):
            assert (out / f"{png}.png").read_bytes()[:4] == b"\x89PNG", png
            assert f"({png}.png)" in report
    # The evaluator replays what training's own test of the best checkpoint flew.
    best = json.loads((run / "eval" / "test-best" / "summary.json").read_text())
    assert best["capture_rate"] == pytest.approx(trained["test_capture_rate"])
    assert best["mean_return"] == pytest.approx(trained["test_mean_return"], rel=1e-5)

    res = run_python("-m", "rlplat.eval.compare", str(run))
    assert res.returncode == 0, res.stderr[-2000:]
    assert [line.split(" | ")[0] for line in res.stdout.splitlines()[2:]] == [
        "| attacker_v4 (best)",
        "| pure_pursuit",
        "| proportional_navigation",
    ]
    with open(run / "eval" / "compare-test.csv") as f:
        table = list(csv.DictReader(f))
    rates = [json.loads((run / "eval" / f"test-{n}" / "summary.json").read_text())["capture_rate"]
             for n in ("best", "pure_pursuit", "proportional_navigation")]  # fmt: skip
    assert [float(r["capture_rate"]) for r in table] == pytest.approx(rates)
    assert (run / "eval" / "compare-test.png").read_bytes()[:4] == b"\x89PNG"


def test_compare_on_a_set_without_route_flyers_has_no_capture_ceiling_section(
    trained_run, tmp_path, write_small_set
):
    # The capture ceiling covers route-flying defenders: on a set of network defenders alone it
    # is not defined, and the report says nothing of it rather than "nan of 0".
    held = write_small_set(
        tmp_path / "set", "scenario.strategy_mix.nn=1.0", "scenario.strategy_mix.setpoints=0.0"
    )
    cfg = compose_config("evaluate", [
        f"run_dir={trained_run}", f"scenarios_dir={held.path}", "split=val", "compare=true",
        "plots=false", f"out_dir={tmp_path / 'ev'}",
    ])  # fmt: skip
    evaluate_from_config(cfg)
    report = (tmp_path / "ev" / "compare-val.md").read_text()
    assert "## Against the capture ceiling" not in report and "nan" not in report
    route = report.split("## Against the route ceiling")[1].split("\n## ")[0]
    table = [line for line in route.splitlines() if line.startswith("|")]
    assert table[0] == "| defender | all | nn |" and table[1] == "|---|---|---|"
    assert all(line.count("|") == 4 for line in table), table


def test_compare_mode_flies_every_baseline_in_one_command(trained_run):
    cfg = compose_config(
        "evaluate", [f"run_dir={trained_run}", "split=val", "compare=true", "plots=false"]
    )
    lines = evaluate_from_config(cfg)
    assert [line.split(":")[0] for line in lines[:4]] == [
        "best",
        "pure_pursuit",
        "proportional_navigation",
        "route_intercept",
    ]
    assert "| pure_pursuit | 16 |" in lines[4]
    table, rest = (
        (trained_run / "eval" / "compare-val.md")
        .read_text()
        .split("## Against the capture ceiling")
    )
    ceiling, rest = rest.split("## Against the route ceiling")
    route, paired = rest.split("## Against proportional navigation, scenario by scenario")
    assert table.count("\n| ") == 5  # the header and one row per policy
    # the ceiling table: its header, the scenarios it covers, the ceiling, one row per policy
    assert ceiling.count("\n| ") == 7 and "\n| proportional_navigation |" in ceiling
    # the route ceiling covers every scenario, per defender strategy: the same rows
    assert route.count("\n| ") == 7 and "| defender | all | setpoints | nn |" in route
    with open(trained_run / "eval" / "val-best" / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["defender_strategy"] for r in rows} == {"setpoints", "nn"}
    for r in rows:  # defined everywhere; for a route flyer, its capture ceiling
        assert r["route_interceptable"] in ("0", "1")
        assert r["interceptable"] == (
            r["route_interceptable"] if r["defender_strategy"] == "setpoints" else ""
        )
    law = json.loads((trained_run / "eval" / "val-route_intercept" / "summary.json").read_text())
    assert law["policy_args"] == {}  # attacker_v4 corrects no route law: the law's defaults
    summary = json.loads((trained_run / "eval" / "val-best" / "summary.json").read_text())
    assert summary["route_ceiling"]["scenarios"] == 16
    assert (
        summary["by_strategy"]["setpoints"]["route_ceiling"]
        == summary["by_strategy"]["setpoints"]["ceiling"]
    )
    # every other policy against the law, on the 16 validation scenarios
    assert paired.count("\n| ") == 4 and "| pure_pursuit | 1 | 16 | " in paired
    assert not list((trained_run / "eval" / "val-best").glob("*.png"))  # plots=false


def test_compare_mode_writes_under_out_dir_and_leaves_the_run_alone(
    trained_run, tmp_path, capsys, monkeypatch
):
    from rlplat.experiment import evaluation

    before = sorted(p.relative_to(trained_run) for p in trained_run.rglob("*"))
    out = tmp_path / "flown-elsewhere"
    cfg = compose_config(
        "evaluate",
        [f"run_dir={trained_run}", "split=val", "compare=true", "plots=false", f"out_dir={out}"],
    )
    flown = []  # the ceilings are flown once for the four policies: capture, then route
    monkeypatch.setattr(evaluation, "_CEILINGS", {})
    monkeypatch.setattr(evaluation, "intercept_ceiling",
                        lambda *a: flown.append(1) or intercept_ceiling(*a))  # fmt: skip
    lines = evaluate_from_config(cfg)
    assert len(flown) == 2
    assert sorted(p.name for p in out.iterdir()) == [
        "compare-val.csv", "compare-val.md",  # plots=false: no PNG
        "val-best", "val-proportional_navigation", "val-pure_pursuit", "val-route_intercept",
    ]  # fmt: skip
    assert sorted(p.relative_to(trained_run) for p in trained_run.rglob("*")) == before
    ceilings = {  # each policy's episodes hold the same ceilings
        json.dumps([(r["interceptable"], r["route_interceptable"])
                    for r in read_episodes(d / "episodes.csv")])
        for d in out.iterdir() if d.is_dir()
    }  # fmt: skip
    assert len(ceilings) == 1 and '"1"' in ceilings.pop()
    for line in lines[:4]:  # each policy's report is under out_dir
        assert f"report {out}/val-" in line
    table = (out / "compare-val.md").read_text()
    assert f"(evaluations in `{out}`)" in table.splitlines()[0]
    assert "## Against proportional navigation, scenario by scenario" in table
    assert "compare-val.png" not in table
    # the module's command line rewrites the same table from that folder (in this process: the
    # round trip runs it as a process)
    from rlplat.eval.compare import load_summaries, main

    capsys.readouterr()
    main([str(trained_run), "--split", "val", "--eval-dir", str(out), "--no-plots"])
    assert capsys.readouterr().out.strip() == lines[4].strip()
    assert (out / "compare-val.md").read_text() == table
    # Evaluations binned otherwise do not line up in the tables per bin: one line.

    other = tmp_path / "binned-otherwise"
    shutil.copytree(out, other)
    path = other / "val-pure_pursuit" / "summary.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "speed_ratio_bins": [1.0]}))
    with pytest.raises(ConfigError, match=r"^compare: the evaluations bin speed ratios "
                       r"differently \(.*pure_pursuit: \[1.0\]"):  # fmt: skip
        load_summaries(trained_run, "val", eval_dir=other)


def test_last_checkpoint_and_a_path(trained_run):
    last = evaluate_run(trained_run, ckpt="last", split="val", plots=False, trajectories=0)
    assert last.out_dir == trained_run / "eval" / "val-last"
    assert last.summary["learner"] == "attacker"
    path = trained_run / "checkpoints" / "last.pt"
    other = tmp = trained_run / "elsewhere"
    tmp.mkdir(exist_ok=True)
    again = evaluate_run(trained_run, ckpt=str(path), split="val", out_dir=other, plots=False)
    assert again.summary["name"] == "last" and again.summary["checkpoint"] == str(path)
    assert torch.equal(last.results.returns, again.results.returns)  # deterministic replay
    # Another run's best.pt is named after that run: it does not replace this run's val-best.
    foreign = trained_run.parent / "other-run" / "checkpoints" / "best.pt"
    foreign.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(path, foreign)
    flown = evaluate_run(trained_run, ckpt=str(foreign), split="val", plots=False, trajectories=0)
    assert flown.out_dir == trained_run / "eval" / "val-other-run-best"


@pytest.mark.parametrize("policy", ["checkpoint", "proportional_navigation"])
def test_the_analyses_fly_a_split_as_evaluate_does(trained_run, scenarios, tmp_path, policy):
    # benchmarks/defender_stalls.py and defender_symmetry.py fly their split through
    # flown_split: the same episodes as evaluate.py's (the baseline on the plain action).
    from rlplat.experiment.evaluation import flown_split

    cfg, env, flier = flown_split(trained_run, scenarios.path, "val", policy, "last")
    assert (cfg.action.name == "velocity") == (policy != "checkpoint")
    flown = evaluate(env, flier)
    ev = evaluate_run(trained_run, policy=policy, ckpt="last", split="val", plots=False,
                      trajectories=0, out_dir=tmp_path / policy)  # fmt: skip
    assert torch.equal(flown.returns, ev.results.returns)


def test_an_ensemble_flies_the_mean_action_of_its_members(trained_run, tmp_path):
    from rlplat.agents.policies import MeanAction

    # Two members of constant actions: the ensemble flies their mean.
    def constant(value):
        return TensorDictModule(
            lambda obs: torch.full((obs.shape[0], 3), value), ["observation"], ["action"]
        )

    td = TensorDict({"observation": torch.zeros(4, 10)}, batch_size=[4])
    mean = MeanAction([constant(0.5), constant(-0.1)], "action")(td)["action"]
    torch.testing.assert_close(mean, torch.full((4, 3), 0.2))

    # A run and its copy: the mean of two equal actions is the run's own policy.
    copy = tmp_path / "copy"
    shutil.copytree(trained_run, copy, ignore=shutil.ignore_patterns("eval"))
    alone = evaluate_run(trained_run, split="val", plots=False, trajectories=0)
    both = evaluate_run(trained_run, split="val", plots=False, ensemble=[copy])
    assert both.out_dir == trained_run / "eval" / "val-best-ensemble2"
    assert both.summary["name"] == "best-ensemble2"
    assert both.summary["ensemble"] == [str(copy / "checkpoints" / "best.pt")]
    torch.testing.assert_close(both.results.returns, alone.results.returns)
    assert torch.equal(both.results.captured, alone.results.captured)


def test_an_ensemble_refuses_a_member_of_another_interface(trained_run, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(trained_run, other, ignore=shutil.ignore_patterns("eval"))
    cfg = OmegaConf.load(other / "config.yaml")
    cfg.action.scale = 1.0
    OmegaConf.save(cfg, other / "config.yaml")
    with pytest.raises(ConfigError, match=r"ensemble: .*other has action=.*run_dir has action="):
        evaluate_run(trained_run, split="val", plots=False, ensemble=[other])
    # A run saved before a key was added (schema.ADDED_KEYS) has the same interface.
    del cfg.action.accel_lead
    cfg.action.scale = OmegaConf.load(trained_run / "config.yaml").action.scale
    OmegaConf.save(cfg, other / "config.yaml")
    both = evaluate_run(trained_run, split="val", plots=False, trajectories=0, ensemble=[other])
    assert both.summary["ensemble"] == [str(other / "checkpoints" / "best.pt")]
    with pytest.raises(ConfigError, match=r"ensemble: flies checkpoints"):
        evaluate_run(trained_run, policy="pure_pursuit", ensemble=[other])
    path = str(trained_run / "checkpoints" / "last.pt")
    with pytest.raises(ConfigError, match=r"ensemble: needs ckpt=best or last .*got /"):
        evaluate_run(trained_run, ckpt=path, ensemble=[other])
    with pytest.raises(ConfigError, match=r"ensemble: no run directory at .*nowhere$"):
        evaluate_run(trained_run, ensemble=[tmp_path / "nowhere"])
    # Each run flies once: the run itself, or a run named twice, would weigh double.
    itself = f"{trained_run}/../{trained_run.name}"  # the same folder, spelled otherwise
    with pytest.raises(ConfigError, match=r"^ensemble: .* is run_dir itself; each run flies once$"):
        evaluate_run(trained_run, ensemble=[itself])
    twice = f"{tmp_path}/./../{tmp_path.name}/other"
    with pytest.raises(ConfigError, match=r"^ensemble: .*other is named twice; each run flies"):
        evaluate_run(trained_run, ensemble=[other, twice])


def test_a_file_that_is_no_checkpoint_is_blamed_on_the_setting_that_named_it(trained_run, tmp_path):
    text = tmp_path / "README.md"
    text.write_text("# not a checkpoint\n")
    with pytest.raises(ConfigError, match=r"^ckpt: .*README.md is not an rlplat checkpoint"):
        evaluate_run(trained_run, ckpt=str(text), split="val", plots=False)
    with pytest.raises(ConfigError, match=r"^ckpt: .*README.md is not an rlplat checkpoint"):
        export_run(trained_run, ckpt=str(text), out_dir=tmp_path / "out")
    assert not (tmp_path / "out").exists()


# Bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"ckpt": "middle"}, r"ckpt: no checkpoint at middle \(best or last, or the path of a"),
        (
            {"policy": "lqr"},
            r"policy: unknown 'lqr'; valid: checkpoint, onnx, c, pure_pursuit, "
            r"proportional_navigation",
        ),
        ({"split": "holdout"}, r"split: unknown 'holdout'; valid: train, val, test"),
        ({"trajectories": -1}, r"trajectories: must be an integer >= 0, got -1"),
        ({"speed_ratio_bins": [2.0, 1.0]}, r"speed_ratio_bins: must be increasing and > 0"),
        ({"policy": "setpoint_follower"}, r"policy: setpoint_follower flies the defender"),
    ],
)
def test_bad_arguments_are_refused_before_any_work(trained_run, kwargs, message):
    with pytest.raises(ConfigError, match=message):
        evaluate_run(trained_run, out_dir=trained_run / "bad", **{"split": "val", **kwargs})
    assert not (trained_run / "bad").exists()


def test_compare_over_two_dynamics_says_which_row_flew_which(trained_run, tmp_path, caplog):
    # evaluate.py compare=true dynamics=quadrotor beside the run's velocity evaluations: the
    # quadrotor's summaries have no capture ceiling, which the bound tables used to index.
    from rlplat.eval.compare import compare

    out = tmp_path / "ev"
    evaluate_run(trained_run, split="val", plots=False, eval_dir=out)
    evaluate_run(
        trained_run, split="val", plots=False, eval_dir=out, dynamics={"name": "quadrotor"}
    )
    with caplog.at_level("WARNING", logger="rlplat.eval.compare"):
        table = compare(trained_run, "val", eval_dir=out, plots=False)
    assert "| attacker_v4 (best) (velocity, 1 attacker) |" in table
    assert "| attacker_v4 (best) (quadrotor, 1 attacker) |" in table
    assert "compare: the evaluations fly 2 games" in caplog.text
    assert "## Against the capture ceiling" in (out / "compare-val.md").read_text()


def test_an_out_dir_that_is_a_run_is_refused_and_the_runs_summary_kept(trained_run):
    before = (trained_run / "summary.json").read_bytes()
    with pytest.raises(ConfigError, match=r"^out_dir: .* is a training run's directory; its "):
        evaluate_run(trained_run, out_dir=trained_run, split="val", plots=False)
    assert (trained_run / "summary.json").read_bytes() == before


def test_an_empty_split_is_refused_before_any_work(trained_run, tmp_path, write_small_set):
    held = write_small_set(tmp_path / "set", "scenario.n_val=0")
    with pytest.raises(ConfigError) as e:
        evaluate_run(trained_run, scenarios_dir=held.path, split="val", out_dir=tmp_path / "ev")
    assert str(e.value) == (
        f"scenarios_dir: {held.path} has no val scenarios; the evaluation needs the val split"
    )
    assert not (tmp_path / "ev").exists()


def test_missing_run_directory(tmp_path):
    with pytest.raises(ConfigError, match=r"run_dir: no run directory at .*nowhere"):
        evaluate_run(tmp_path / "nowhere")
    with pytest.raises(ConfigError, match=r"has no config.yaml \(not a training run directory\)"):
        evaluate_run(tmp_path)


def test_checkpoint_that_does_not_fit_the_drone_config(trained_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(trained_run, run, ignore=shutil.ignore_patterns("eval"))
    cfg = OmegaConf.load(run / "config.yaml")
    cfg.observation.name = "absolute"  # R^12, the checkpoint was trained on R^10
    OmegaConf.save(cfg, run / "config.yaml")
    with pytest.raises(
        ConfigError,
        match=r"ckpt: .*best.pt has obs_dim=10, the run's drone config \(observation=absolute, "
        r"action=guided_velocity\) gives obs_dim=12",
    ):
        evaluate_run(run)
    assert not (run / "eval").exists()


def test_another_scenario_set_warns_or_is_refused(trained_run, write_small_set, tmp_path, caplog):
    other = tmp_path / "other"
    write_small_set(other, "scenario.seed=5")
    with caplog.at_level(logging.WARNING, logger="rlplat.eval.run"):
        ev = evaluate_run(trained_run, split="val", scenarios_dir=other, out_dir=tmp_path / "w",
                          plots=False)  # fmt: skip
    assert "the run trained with" in caplog.text and "evaluating anyway" in caplog.text
    assert "env.vision_semi_axes" not in caplog.text  # drawn in the ellipsoid the run sees
    assert ev.summary["scenario_digest_matches"] is False
    # The same out_dir flown again on the run's own set: the results of the other are
    # replaced, and that is said; flown once more on the same set, nothing is said.
    said = []
    for _ in range(2):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            evaluate_run(trained_run, split="val", out_dir=tmp_path / "w", plots=False)
        said.append([r.message for r in caplog.records if "replacing" in r.message])
    assert len(said[0]) == 1 and said[1] == []
    assert said[0][0].startswith(f"out_dir: replacing {tmp_path / 'w'}, flown on another scenario")
    wide = tmp_path / "wide"
    write_small_set(wide, "scenario.vision_semi_axes=[60.0,50.0,15.0]")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="rlplat.eval.run"):
        evaluate_run(trained_run, split="val", scenarios_dir=wide, out_dir=tmp_path / "v",
                     plots=False)  # fmt: skip
    assert (
        "env.vision_semi_axes: the run sees within [48.0, 42.0, 13.0] m, the set's starts were "
        "drawn within [60.0, 50.0, 15.0] m; evaluating with the run's"
    ) in caplog.text
    with pytest.raises(ConfigError, match=r"scenarios: the set at .*other has digest .* the run "
                       r"trained with .*strict_scenarios=true refuses it"):  # fmt: skip
        evaluate_run(
            trained_run, scenarios_dir=other, strict_scenarios=True, out_dir=tmp_path / "s"
        )
    assert not (tmp_path / "s").exists()


def test_a_sweep_over_a_missing_run_or_checkpoint_is_refused_before_hydra_writes(
    trained_run, tmp_path, refused_in_process
):
    # Hydra writes a sweep's record (multirun.yaml) into <run_dir>/eval before its first job,
    # and each job flies on its own: the run and each job's checkpoint are checked first.
    nowhere = tmp_path / "nowhere"
    policies = "policy=pure_pursuit,proportional_navigation"
    err = refused_in_process("evaluate.py", "-m", f"run_dir={nowhere}", policies)
    assert err == f"error: run_dir: no run directory at {nowhere} (in the sweep's job " \
                  "policy=pure_pursuit)\n"  # fmt: skip
    assert not nowhere.exists()
    missing = tmp_path / "x.pt"
    err = refused_in_process("evaluate.py", "-m", f"run_dir={trained_run}", f"ckpt=best,{missing}")
    assert err.startswith(f"error: ckpt: no checkpoint at {missing}") and err.count("\n") == 1
    for args in ([f"run_dir={nowhere}", "ckpt=best,last"], [f"controller={missing}",
                 f"out_dir={tmp_path / 'e'}", "split=val,test"]):  # fmt: skip
        err = refused_in_process("export.py", "-m", *args, cwd=tmp_path)
        assert err.startswith(("error: run_dir: no run directory", "error: controller: no file"))
        assert list(tmp_path.iterdir()) == []  # no multirun/ folder in the working directory


def test_a_sweep_over_runs_evaluates_each_in_its_own_folder(trained_run, tmp_path):
    # The sweep's record goes where one run's sweeps keep it (<run_dir>/eval) only when the
    # sweep has one run; over runs, run_dir is unset in the sweep's own config (Hydra's
    # multirun/<date>/<time> in the working directory), each job flying its own run.
    copy = tmp_path / "copy"
    shutil.copytree(trained_run, copy, ignore=shutil.ignore_patterns("eval"))
    res = subprocess.run(
        [sys.executable, str(ROOT / "evaluate.py"), "-m", f"run_dir={trained_run},{copy}",
         "policy=pure_pursuit", "split=val", "plots=false", "trajectories=0"],
        capture_output=True, text=True, cwd=tmp_path, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    flown = [json.loads((run / "eval" / "val-pure_pursuit" / "summary.json").read_text())
             for run in (trained_run, copy)]  # fmt: skip
    assert flown[0]["captured"] == flown[1]["captured"]
    records = [p.relative_to(tmp_path).parts for p in tmp_path.rglob("multirun.yaml")]
    assert len(records) == 1 and records[0][0] == "multirun", records
    # One folder for the sweep, however long its jobs take (Hydra keeps its time).
    assert [p for p in (tmp_path / "multirun").glob("*/*")] == [tmp_path.joinpath(*records[0][:3])]


def test_cli_bad_input_is_one_line(tmp_path, run_python):
    res = run_python("evaluate.py", f"run_dir={tmp_path / 'nowhere'}")
    assert res.returncode == 2
    assert (
        res.stderr.strip().splitlines()[-1]
        == f"error: run_dir: no run directory at {tmp_path / 'nowhere'}"
    )


def test_bad_thread_count_is_refused(trained_run):
    cfg = compose_config("evaluate", [f"run_dir={trained_run}", "threads=0"])
    with pytest.raises(ConfigError, match=r"threads: must be an integer >= 1 or null, got 0"):
        evaluate_from_config(cfg)


def test_evaluate_yaml_is_evaluate_run_with_its_defaults():
    yaml = OmegaConf.load(ROOT / "conf" / "evaluate.yaml")
    params = inspect.signature(evaluate_run).parameters
    keys = set(yaml) - {"defaults", "hydra", "compare", "threads"}  # entry-point options
    # eval_dir is out_dir's meaning with compare=true (the folder of every policy's evaluation)
    assert keys == set(params) - {"dynamics", "eval_dir"}
    assert {"dynamics": None} in yaml.defaults  # a config group, chosen on the command line
    for key in keys - {"run_dir"}:
        default = params[key].default
        assert yaml[key] == (list(default) if isinstance(default, tuple) else default), key
    # The policy: line's comment lists every name evaluate.py flies.
    from rlplat.agents.policies import POLICIES

    (line,) = [x for x in (ROOT / "conf" / "evaluate.yaml").read_text().splitlines()
               if x.startswith("policy:")]  # fmt: skip
    comment = re.sub(r"\([^)]*\)", "", line.split("#", 1)[1])  # less its asides
    listed = {name.strip() for name in comment.split("|")}
    assert listed == {"checkpoint", "onnx", "c", *POLICIES}, line
    cfg = compose_config("evaluate", ["run_dir=x"])
    assert (cfg.policy, cfg.ckpt, cfg.split, cfg.strict_scenarios) == (
        "checkpoint",
        "best",
        "test",
        False,
    )


def test_a_scenario_id_with_a_line_break_keeps_the_report_table_whole(
    trained_run, write_small_set, rewrite_split, tmp_path
):
    # Ids are any non-empty JSON strings: a hand-made set may hold "a|b" or a line break.
    held = write_small_set(tmp_path / "set")
    rewrite_split(
        held.path, "val", lambda recs: [{**r, "id": f"hand\nmade|{i}"} for i, r in enumerate(recs)]
    )
    ev = evaluate_run(trained_run, split="val", scenarios_dir=held.path, out_dir=tmp_path / "ev",
                      plots=False)  # fmt: skip
    report = (ev.out_dir / "report.md").read_text().split("## Chosen episodes")[1]
    rows = report.strip().splitlines()[2:]
    assert rows and all(line.startswith("| ") and line.endswith(" |") for line in rows)
    assert all("| hand\\nmade\\|" in line for line in rows[1:])
