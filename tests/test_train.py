import csv
import functools
import json
import logging
import os
import re
import shutil
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from rlplat.agents.checkpoint import load_checkpoint, load_policy
from rlplat.agents.policies import SHIPPED_DEFENDER, shipped_path
from rlplat.errors import ConfigError, DivergenceError, RlplatError
from rlplat.experiment.config import compose_config
from rlplat.scenarios import STRATEGIES


def test_cli_run_writes_the_run_directory(scenarios, tmp_path, tiny, train_cli):
    run = tmp_path / "run"
    # attacker_v4: a scripted start of proportional navigation
    res = train_cli(
        *tiny, "drone=attacker_v4", f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}"
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1].startswith("test capture rate ")
    assert str(run) in res.stdout
    summary = json.loads((run / "summary.json").read_text())
    for key in (
        "frames",
        "wall_time_s",
        "best_val_capture_rate",
        "test_capture_rate",
        "test_mean_return",
    ):
        assert key in summary
    assert summary["frames"] >= 256 and summary["scenario_digest"] == scenarios.digest
    assert 0.0 <= summary["reference_val_capture_rate"] <= 1.0
    assert summary["reference_policy"] == "proportional_navigation"
    assert summary["val_score"] == "capture_rate"
    assert (run / "checkpoints" / "best.pt").is_file()
    assert (run / "checkpoints" / "last.pt").is_file()
    assert (run / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"
    assert "observation" in (run / "config.yaml").read_text()
    scalars = run / "metrics" / "scalars"
    with open(scalars / "eval" / "capture_rate.csv") as f:
        rows = list(csv.reader(f))
    # validated at the start (after the 64 scripted frames), then every 128 frames
    assert [int(r[0]) for r in rows] == [64, 128, 256]
    for name in (
        "train/loss_qvalue",
        "time/frames_per_s",
        "train/updates",
        "reference/capture_rate",
    ):
        assert (scalars / f"{name}.csv").is_file(), name


@pytest.mark.parametrize(
    "overrides",
    [
        ("drone=attacker_v1",),
        ("drone=attacker_v2", "reward=sparse"),
        ("drone=attacker_v3", "dynamics=quadrotor", "env.time_limit=1"),
        ("algo=sac_paper", "algo.frames_per_batch=4", "algo.num_envs=4", "algo.utd_ratio=0.05"),
        ("algo.init_policy=random", "algo.action_margin=0", "algo.target_entropy=-5"),
    ],
    ids=["v1", "v2-sparse", "v3-quadrotor", "sac_paper", "random-start"],
)
def test_component_swaps_train(scenarios, tmp_path, overrides, tiny_run):
    summary = tiny_run(scenarios, tmp_path, *overrides)
    assert summary["updates"] > 0
    assert 0.0 <= summary["test_capture_rate"] <= 1.0
    state = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    drone = compose_config("train", list(overrides)).drone.name
    assert state["config"]["drone"]["name"] == drone


def test_a_compiled_run_is_tested_and_evaluated_on_the_eager_step(
    scenarios, tmp_path, tiny_run, monkeypatch
):
    """env.compile_step speeds up the run's collection and validations only: the final test,
    evaluate.py (and the ceilings it draws) fly the eager step, whose rounding every other
    evaluation shares, so no figure depends on how the run trained."""
    from rlplat.experiment.evaluation import evaluate_run

    compiled = []

    def spy(fn, *args, **kwargs):  # records which env's step is compiled, compiles nothing
        owner = getattr(fn, "__self__", None)
        if owner is not None and hasattr(owner, "split_name"):
            compiled.append(owner.split_name)
        return fn

    monkeypatch.setattr(torch, "compile", spy)
    summary = tiny_run(scenarios, tmp_path, "env.compile_step=true")
    # The default's gated action flies its reference on a second, plain-action val env.
    assert set(compiled) == {"train", "val"}
    compiled.clear()
    ev = evaluate_run(tmp_path, plots=False, trajectories=0)
    assert compiled == []
    assert ev.summary["capture_rate"] == summary["test_capture_rate"]
    assert ev.summary["ceiling"]["scenarios"] > 0  # the ceilings were flown, eagerly


def test_sac_paper_matches_the_paper(scenarios):
    # attacker_v3 (the paper's interface) sets no algo value of its own
    algo = compose_config("train", ["algo=sac_paper", "drone=attacker_v3"]).algo
    assert list(algo.actor_cells) == list(algo.critic_cells) == [64, 64]
    assert algo.activation == "relu" and algo.batch_size == 128 and algo.gamma == 0.99
    assert algo.actor_lr == algo.critic_lr == 1e-3 and algo.target_entropy == "auto"
    assert algo.num_envs == 1 and algo.utd_ratio == 1.0


@pytest.mark.parametrize("logger", ["wandb", "tensorboard"])
def test_loggers_write_inside_the_run_directory(scenarios, tmp_path, logger, monkeypatch, tiny_run):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    tiny_run(scenarios, tmp_path, f"logger={logger}")
    assert (tmp_path / "metrics" / "scalars" / "eval" / "capture_rate.csv").is_file()
    if logger == "wandb":
        runs = list((tmp_path / "wandb").glob("offline-run-*"))
        assert runs, "wandb runs offline by default"
    else:
        assert list((tmp_path / "tensorboard").rglob("events.out.tfevents.*"))


@pytest.mark.parametrize("field", ["logger.mode", "WANDB_MODE"])
def test_wandb_online_without_a_login_is_one_line_before_the_run_directory(
    scenarios, tmp_path, monkeypatch, field
):
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    for key in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_BASE_URL", "NETRC"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.netrc, no stored login
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "wandb-config"))
    run = tmp_path / "run"
    args = ["logger=wandb", f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}"]
    if field == "WANDB_MODE":  # where it is set, the mode wandb runs in
        monkeypatch.setenv("WANDB_MODE", "online")
    else:
        args.append("logger.mode=online")
    res = subprocess.run(  # no terminal: wandb may not ask for the login
        [sys.executable, str(root / "train.py"), *args],
        capture_output=True, text=True, cwd=root, stdin=subprocess.DEVNULL, timeout=300,
    )  # fmt: skip
    assert res.returncode == 2, res.stderr[-2000:]
    (line,) = res.stderr.strip().splitlines()
    assert line.startswith(f"error: {field}: online needs a W&B login on this machine (wandb: ")
    assert line.endswith(f"; {field}=offline logs without one")
    assert not run.exists()


def test_resume_continues_counters_and_refuses_another_interface(scenarios, tmp_path, tiny_run):
    v4 = "drone=attacker_v4"  # eq. 3: a capture pays 10
    first = tiny_run(scenarios, tmp_path, v4)
    saved = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    resumed = tiny_run(scenarios, tmp_path, v4, "resume=true", "train.total_frames=512")
    assert resumed["frames"] == first["frames"] + 256
    assert resumed["updates"] > first["updates"]
    assert resumed["wall_time_s"] > first["wall_time_s"]
    after = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert after["counters"]["frames"] > saved["counters"]["frames"]
    with pytest.raises(ConfigError, match=r"resume: the config differs .* drone\.name \("):
        tiny_run(scenarios, tmp_path, "resume=true", "drone=attacker_v1")
    # Not only the network interface: the episode's rules too, every differing key listed.
    with pytest.raises(
        ConfigError,
        match=r"in env\.capture_radius \(1\.2 -> 2\.0\), reward\.terms\.capture \(10\.0 -> 5\.0\);",
    ):
        tiny_run(scenarios, tmp_path, v4, "resume=true", "env.capture_radius=2.0",
                 "reward.terms.capture=5.0")  # fmt: skip
    with pytest.raises(ConfigError, match=r"resume: true, and .*elsewhere holds no run to "):
        tiny_run(scenarios, tmp_path / "elsewhere", v4, "resume=true")


def test_best_checkpoint_loads_as_a_deterministic_policy(scenarios, tmp_path, tiny_run):
    from rlplat import make_env
    from rlplat.eval.episodes import evaluate

    summary = tiny_run(scenarios, tmp_path)
    env = make_env("env.time_limit=3", scenarios=scenarios, split="test", num_envs=16)
    policy = load_policy(tmp_path / "checkpoints" / "best.pt", env.action_spec[0])
    a, b = evaluate(env, policy), evaluate(env, policy)
    assert a.capture_rate == b.capture_rate == pytest.approx(summary["test_capture_rate"])
    assert torch.equal(a.returns, b.returns)
    # Called as it is, outside any exploration context, it flies that deterministic action
    # too; deterministic=False samples, as the actor trained.
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        mean = policy(td.clone())["action"]
    assert torch.equal(policy(td.clone())["action"], mean)
    sampling = load_policy(tmp_path / "checkpoints" / "best.pt", env.action_spec[0],
                           deterministic=False)  # fmt: skip
    assert not torch.equal(sampling(td.clone())["action"], mean)


def test_keep_checkpoints_keeps_each_validations_policy(scenarios, tmp_path, tiny_run):
    from rlplat.experiment.evaluation import evaluate_run

    tiny_run(scenarios, tmp_path / "plain")
    assert not list((tmp_path / "plain" / "checkpoints").glob("val-*.pt"))
    summary = tiny_run(scenarios, tmp_path / "kept", "train.keep_checkpoints=true")
    ckpts = tmp_path / "kept" / "checkpoints"
    # validated at the start (after the 64 scripted frames), then every 128 frames
    kept = sorted(ckpts.glob("val-*.pt"))
    assert [p.name for p in kept] == ["val-0000064.pt", "val-0000128.pt", "val-0000256.pt"]
    states = {int(p.stem[4:]): load_checkpoint(p) for p in kept}
    assert all(s["counters"]["frames"] == frames for frames, s in states.items())
    last, best = load_checkpoint(ckpts / "last.pt"), load_checkpoint(ckpts / "best.pt")
    for kept_state, state in ((states[256], last), (states[summary["best_frames"]], best)):
        for key, value in state["actor"].items():
            assert torch.equal(kept_state["actor"][key], value), key
    # A kept checkpoint flies through evaluate.py's ckpt=PATH like best.pt
    path = ckpts / f"val-{summary['best_frames']:07d}.pt"
    ev = evaluate_run(tmp_path / "kept", ckpt=str(path), plots=False, trajectories=0)
    assert ev.summary["capture_rate"] == summary["test_capture_rate"]


@pytest.fixture
def sampler_weights(monkeypatch) -> list:
    """(n, weights) of every ScenarioSampler.set_weights call, in order."""
    from rlplat.envs.pursuit import ScenarioSampler

    given, set_weights = [], ScenarioSampler.set_weights

    def record(self, weights):
        given.append((self.n, weights))
        set_weights(self, weights)

    monkeypatch.setattr(ScenarioSampler, "set_weights", record)
    return given


def test_failure_weight_draws_the_references_failures_more_often(
    scenarios, tmp_path, tiny_run, caplog, sampler_weights
):
    from rlplat import make_env
    from rlplat.agents.policies import make_scripted_policy
    from rlplat.eval.episodes import evaluate

    given = sampler_weights
    with caplog.at_level("INFO", logger="rlplat.experiment.training"):
        tiny_run(scenarios, tmp_path, "algo.failure_weight=4", "env.time_limit=10")
    n = len(scenarios.split("train"))
    env = make_env("env.time_limit=10", "action=velocity", scenarios=scenarios, split="train",
                   num_envs=n)  # fmt: skip  # the reference's flight, as the run flies it
    law = evaluate(env, make_scripted_policy("proportional_navigation", env))
    failed = torch.zeros(n, dtype=torch.bool)
    failed[law.scenario_index] = ~law.captured
    k = int(failed.sum())
    assert 0 < k < n, "the set must hold failures and captures"
    # The training env's walk, and only it, becomes draws: 4 for each of the law's failures.
    assert len(given) == 1 and given[0][0] == n
    assert torch.equal(given[0][1], torch.where(failed, 4.0, 1.0))
    share = 100 * 4 * k / (4 * k + n - k)
    assert f"fails {k} of {n} train scenarios; drawn 4 times as often: {share:.0f} %" in (
        caplog.text
    )


def test_failure_evaders_only_draws_the_references_failures_against_the_network_more_often(
    scenarios, tmp_path, tiny_run, sampler_weights
):
    from rlplat import make_env
    from rlplat.agents.policies import make_scripted_policy
    from rlplat.eval.episodes import evaluate

    tiny_run(scenarios, tmp_path, "algo.failure_weight=4", "algo.failure_evaders_only=true",
             "env.time_limit=10")  # fmt: skip
    train = scenarios.split("train")
    n = len(train)
    env = make_env("env.time_limit=10", "action=velocity", scenarios=scenarios, split="train",
                   num_envs=n)  # fmt: skip
    law = evaluate(env, make_scripted_policy("proportional_navigation", env))
    failed = torch.zeros(n, dtype=torch.bool)
    failed[law.scenario_index] = ~law.captured
    evades = train["defender_strategy"][:, 0] == STRATEGIES.index("nn")
    assert (failed & evades).any() and (failed & ~evades).any(), "failures of both kinds"
    (weights,) = [w for count, w in sampler_weights if count == n]
    assert torch.equal(weights, torch.where(failed & evades, 4.0, 1.0))


def test_evader_weight_draws_the_network_defenders_more_often(
    scenarios, tmp_path, tiny_run, caplog, sampler_weights
):
    given = sampler_weights
    with caplog.at_level("INFO", logger="rlplat.experiment.training"):
        tiny_run(scenarios, tmp_path, "algo.evader_weight=3")
    train = scenarios.split("train")
    evades = train["defender_strategy"][:, 0] == STRATEGIES.index("nn")
    k, n = int(evades.sum()), len(train)
    assert 0 < k < n, "the set must hold both strategies"
    # The training env's walk, and only it, becomes draws: 3 for each network defender.
    assert len(given) == 1 and given[0][0] == n
    assert torch.equal(given[0][1], torch.where(evades, 3.0, 1.0))
    share = 100 * 3 * k / (3 * k + n - k)
    logged = f"{k} of {n} train scenarios have a network defender; drawn 3 times as often: "
    assert f"{logged}{share:.0f} % of episodes" in caplog.text


def test_evader_weight_needs_both_strategies_in_the_train_split(
    tmp_path, tiny_run, write_small_set, refused_in_process
):
    route_flyers = write_small_set(tmp_path / "set", "scenario.strategy_mix={setpoints: 1, nn: 0}")
    n = len(route_flyers.split("train"))
    with pytest.raises(ConfigError, match=rf"^algo\.evader_weight: 3 weights .* has 0 of {n}$"):
        tiny_run(route_flyers, tmp_path / "run", "algo.evader_weight=3")
    assert not (tmp_path / "run").exists()  # refused before any work
    # The command line refuses it before Hydra makes the run directory.
    cli = tmp_path / "cli"
    err = refused_in_process("train.py", f"scenarios_dir={route_flyers.path}",
                             "algo.evader_weight=3", f"hydra.run.dir={cli}")  # fmt: skip
    assert err.startswith("error: algo.evader_weight: 3 weights") and err.count("\n") == 1
    assert not cli.exists()


def test_actor_average_is_what_a_run_validates_checkpoints_and_resumes(
    scenarios, tmp_path, tiny_run
):
    average_on = ("algo.actor_average=0.05", "algo.actor_warmup_updates=0")  # the actor moves
    tiny_run(scenarios, tmp_path, *average_on)
    last = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    average, learned = last["agent"]["actor_average"], last["actor"]
    assert all(torch.equal(learned[k], average[k]) for k in average)  # the average is flown
    prefix = "actor_network_params."
    online = {k.removeprefix(prefix): v for k, v in last["agent"]["loss"].items()
              if k.startswith(prefix)}  # fmt: skip
    assert online.keys() == average.keys()
    assert not all(torch.equal(online[k], average[k]) for k in average)  # the learner moved on
    resumed = tiny_run(scenarios, tmp_path, *average_on, "resume=true", "train.total_frames=512")
    assert resumed["updates"] > last["counters"]["updates"]


def test_same_seed_same_training(scenarios, tmp_path, tiny_run):
    a = tiny_run(scenarios, tmp_path / "a", "seed=3")
    b = tiny_run(scenarios, tmp_path / "b", "seed=3")
    sa = load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")["actor"]
    sb = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")["actor"]
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a["test_mean_return"] == b["test_mean_return"]


def test_a_run_stopped_on_the_clock_says_so(scenarios, tmp_path, tiny_run, caplog):
    with caplog.at_level(logging.WARNING, logger="rlplat.experiment.training"):
        on_frames = tiny_run(scenarios, tmp_path / "frames")
    assert on_frames["frames"] >= 256 and "on the clock" not in caplog.text
    with caplog.at_level(logging.WARNING, logger="rlplat.experiment.training"):
        summary = tiny_run(
            scenarios, tmp_path / "clock", "train.total_frames=100000", "train.max_minutes=1e-6"
        )
    assert summary["frames"] < 100000
    assert f"reached at {summary['frames']} of train.total_frames=100000" in caplog.text
    assert "stopped on the clock" in caplog.text


def test_a_diverged_run_stops_at_once_with_its_checkpoints_from_before(
    scenarios, tmp_path, tiny_run, monkeypatch
):
    from rlplat.agents.sac import SACAgent

    update, calls = SACAgent.update_from, []

    def diverging(self, buffer):
        out = update(self, buffer)
        calls.append(out)
        if len(calls) >= 5:  # the critics' loss goes NaN from the fifth update on
            out = {**out, "loss_qvalue": torch.full_like(out["loss_qvalue"], float("nan"))}
        return out

    monkeypatch.setattr(SACAgent, "update_from", diverging)
    run = tmp_path / "run"
    with pytest.raises(DivergenceError, match=r"^train: loss_qvalue is nan in the updates up to"):
        tiny_run(scenarios, run, "train.total_frames=2048")
    assert len(calls) < 20  # stopped in the batch of updates where it happened
    assert not (run / "summary.json").exists()
    logged = (run / "metrics" / "scalars" / "train" / "loss_qvalue.csv").read_text().split()
    assert logged[-1].endswith(",nan")  # the log shows the batch where it diverged
    best = load_checkpoint(run / "checkpoints" / "best.pt")  # the policy as initialised
    assert all(torch.isfinite(v).all() for v in best["actor"].values())
    # It stopped before its first validation in the loop: it resumes from the one it made
    # as initialised (last.pt), and no other run goes into its directory.
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    assert all(torch.isfinite(v).all() for v in last["actor"].values())
    assert last["counters"]["wall_time_s"] > 0  # the time it ran counts on in a resume
    with pytest.raises(ConfigError, match=r"holds a run already; resume=true continues it"):
        tiny_run(scenarios, run, "train.total_frames=2048")
    monkeypatch.undo()
    resumed = tiny_run(scenarios, run, "train.total_frames=2048", "resume=true")
    assert resumed["frames"] >= 2048 and (run / "summary.json").is_file()


def test_a_run_that_stopped_before_its_first_checkpoint_is_neither_continued_nor_mixed(tmp_path):
    from rlplat.experiment.training import check_run_dir

    (tmp_path / "config.yaml").write_text("seed: 0\n")  # written before a run's first frame
    where = re.escape(str(tmp_path))
    for resume in (False, True):
        with pytest.raises(ConfigError, match=(
            rf"^{'resume: true, and ' if resume else ''}hydra.run.dir: {where} holds a run "
            r"that stopped before it saved a checkpoint to continue from \(no last.pt\); "
            r"another directory starts a new one$"
        )):  # fmt: skip
            check_run_dir(tmp_path, resume)
    check_run_dir(tmp_path / "new", resume=False)  # an empty one starts a run


def test_progress_counts_the_budget_nearest_its_end(monkeypatch):
    from rlplat.experiment import training
    from rlplat.experiment.training import Progress, RunState

    node = OmegaConf.create({"total_frames": 1000, "max_minutes": 10, "progress": True})
    start = time.perf_counter() - 30.0  # a resumed run: 5 % of its time gone
    bar = Progress(node, RunState(frames=250, wall_time_s=30.0), start)
    assert bar.bar.n == 25  # and a quarter of its frames
    # 420.5 s: (start + 420.0) - start may come back as 419.99999999998 (70 % truncated to 69)
    monkeypatch.setattr(training.time, "perf_counter", lambda: start + 420.5)
    bar.update(RunState(frames=300), last_val=0.5)
    assert bar.bar.n == 70  # the clock is further along
    bar.update(RunState(frames=2000), last_val=0.5)
    assert bar.bar.n == 100
    frames_only = Progress(OmegaConf.merge(node, {"max_minutes": None}), RunState(), start)
    frames_only.update(RunState(frames=300), last_val=0.5)
    assert frames_only.bar.n == 30
    bar.close()
    frames_only.close()


def test_correlated_noise_trains_reproducibly_and_explores_otherwise(scenarios, tmp_path, tiny_run):
    runs = {
        name: tiny_run(scenarios, tmp_path / name, "seed=3", *extra)
        for name, extra in (
            ("a", ["algo.noise_correlation=0.9"]),
            ("b", ["algo.noise_correlation=0.9"]),
            ("white", []),
        )
    }
    # The learner's whole state: its actor is held through the bundle's warm-up updates.
    agents = {
        n: load_checkpoint(tmp_path / n / "checkpoints" / "last.pt")["agent"]["loss"] for n in runs
    }
    assert agents["a"].keys() == agents["white"].keys()
    assert all(torch.equal(agents["a"][k], agents["b"][k]) for k in agents["a"])
    assert runs["a"]["test_mean_return"] == runs["b"]["test_mean_return"]
    # Other noise, other transitions, other critics.
    assert not all(torch.equal(agents["a"][k], agents["white"][k]) for k in agents["a"])


def test_self_imitation_bootstrapping_learns_from_the_episodes_the_time_limit_cuts(
    scenarios, tmp_path, tiny_run, monkeypatch
):
    """Every episode of a 3-s time limit is cut short: dropped, they leave self-imitation
    nothing to learn from; bootstrapped, they fill its store and it steps."""
    from rlplat.agents.self_imitation import SelfImitation

    seen, steps = [], []
    observe, step = SelfImitation.observe, SelfImitation.step

    def observed(self, batch):
        seen.append(self)
        return observe(self, batch)

    def stepped(self):
        steps.append(step(self))
        return steps[-1]

    monkeypatch.setattr(SelfImitation, "observe", observed)
    monkeypatch.setattr(SelfImitation, "step", stepped)
    common = ("algo.self_imitation=1e-3", "algo.self_imitation_every=1",
              "algo.actor_warmup_updates=0", "train.total_frames=640")  # fmt: skip
    for truncated in ("drop", "bootstrap"):
        seen.clear()
        steps.clear()
        tiny_run(scenarios, tmp_path / truncated, *common,
                 f"algo.self_imitation_truncated={truncated}")  # fmt: skip
        sil = seen[-1]
        assert steps, truncated
        if truncated == "drop":  # no episode of 3 s ends by itself here
            assert sil.size == sil.episodes == 0 and all(s == {} for s in steps)
        else:
            assert sil.episodes > 0 and sil.size >= sil.batch_size and any(steps)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.n_steps=0", "algo.n_steps: must be an integer >= 1, got 0"),
        ("algo.utd_ratio=0", "algo.utd_ratio: must be a finite number > 0, got 0"),
        ("algo.batch_size=-4", "algo.batch_size: must be an integer >= 1, got -4"),
        (
            "algo.init_policy=expert",
            "algo.init_policy: unknown 'expert'; valid: random, pure_pursuit, "
            "proportional_navigation",
        ),
        (
            "algo.init_policy=setpoint_follower",
            "algo.init_policy: 'setpoint_follower' flies the defender, drone.learner is the "
            "attacker; valid: random, pure_pursuit, proportional_navigation",
        ),
        ("algo.init_noise=-1", "algo.init_noise: must be a finite number >= 0, got -1"),
        (
            "algo.noise_correlation=1",
            r"algo.noise_correlation: must be a finite number in \[0, 1\), got 1$",
        ),
        ("train.threads=0", "train.threads: must be an integer >= 1 or null, got 0"),
        (
            "algo.action_margin=2",
            r"algo.action_margin: must be a finite number in \[0, 1\], got 2$",
        ),
        (
            "algo.actor_average=-0.1",
            r"algo.actor_average: must be a finite number in \[0, 1\], got -0.1$",
        ),
    ],
)
def test_bad_algo_values_are_refused_before_any_work(
    scenarios, tmp_path, override, message, tiny_run
):
    with pytest.raises(ConfigError, match=message):
        tiny_run(scenarios, tmp_path, override)
    assert not tmp_path.joinpath("config.yaml").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("train.total_frames=0",), "error: train.total_frames: must be an integer >= 1, got 0"),
        (
            ("train.max_minutes=-1",),
            "error: train.max_minutes: must be a finite number > 0 or null, got -1",
        ),
        (("algo.frames_per_batch=30",), "error: algo.frames_per_batch: 30 is not a multiple"),
        (("logger.backend=mlflow",), "error: logger.backend: unknown 'mlflow'; valid: csv"),
    ],
)
def test_cli_bad_input_is_one_line_before_any_work(
    scenarios, tmp_path, args, message, tiny, refused_in_process
):
    run = tmp_path / "run"
    stderr = refused_in_process(
        "train.py", *tiny, f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}", *args
    )
    assert stderr.strip().splitlines()[-1].startswith(message)
    assert not run.exists()


def test_a_budget_under_the_scripted_start_is_the_budget(scenarios, tmp_path, tiny_run, caplog):
    # train.total_frames bounds the run, the scripted start included: 256 frames, not 1,024.
    with caplog.at_level("WARNING", logger="rlplat.experiment.training"):
        summary = tiny_run(scenarios, tmp_path, "algo.init_random_frames=1024")
    assert summary["frames"] == 256 and summary["updates"] == 0
    assert "train.total_frames=256 is under algo.init_random_frames=1024" in caplog.text
    assert (tmp_path / "checkpoints" / "best.pt").is_file()
    assert (tmp_path / "checkpoints" / "last.pt").is_file()
    assert "test_capture_rate" in json.loads((tmp_path / "summary.json").read_text())


@pytest.mark.parametrize("empty", ["train", "val", "test"])
def test_a_set_with_an_empty_split_is_refused_before_any_work(
    tmp_path, write_small_set, empty, tiny, refused_in_process
):
    # A test-only set is a set (an evaluation flies it); training needs all three splits.
    held = write_small_set(tmp_path / "set", f"scenario.n_{empty}=0")
    train_cli = functools.partial(refused_in_process, "train.py")
    refusal = refused_before_any_work(train_cli, tmp_path / "run", *tiny,
                                      f"scenarios_dir={held.path}")  # fmt: skip
    assert refusal == (
        f"error: scenarios_dir: {held.path} has no {empty} scenarios; training needs the "
        "train/val/test splits"
    )


def refused_before_any_work(train_cli, run, *args: str) -> str:
    """``train.py *args`` into ``run`` (through ``train_cli``, or ``refused_in_process``):
    refused (exit code 2) before Hydra made ``run``; the last line of its stderr."""
    res = train_cli(*args, f"hydra.run.dir={run}")
    if isinstance(res, str):  # refused_in_process: exit code 2 is its own check
        stderr = res
    else:
        assert res.returncode == 2, res.stderr[-2000:]
        stderr = res.stderr
    assert not run.exists()
    return stderr.strip().splitlines()[-1]


def test_a_scenarios_dir_the_run_cannot_fly_is_one_line_before_any_work(
    tmp_path, scenarios, tiny, refused_in_process
):
    train_cli = functools.partial(refused_in_process, "train.py")
    run = tmp_path / "run"
    nowhere = tmp_path / "nowhere"
    assert refused_before_any_work(train_cli, run, *tiny, f"scenarios_dir={nowhere}") == (
        f"error: scenarios_dir: {nowhere / 'manifest.json'}: missing file of the scenario set"
    )
    # a set of one attacker, asked to fly two
    two = (*tiny, f"scenarios_dir={scenarios.path}", "env.attackers=2")
    refusal = refused_before_any_work(train_cli, run, *two)
    assert refusal == "error: env.attackers: 2, the scenarios have 1 (at most)"


def test_what_train_would_refuse_later_is_refused_before_any_work(
    tmp_path, scenarios, tiny, train_cli
):
    # Each used to pass the command line's check and fail once Hydra had made the run
    # directory (or, for a path that is not what it should be, with a traceback). The check
    # train.py runs before Hydra starts, in-process; one through the command line.
    from rlplat.experiment.command_line import check_command_line
    from rlplat.experiment.training import preflight

    run, tiny = tmp_path / "run", (*tiny, f"scenarios_dir={scenarios.path}")
    assert refused_before_any_work(train_cli, run, *tiny, "init_from=/nonexistent") == (
        "error: init_from: no checkpoint at /nonexistent (a run directory or a .pt file)"
    )
    a_file = scenarios.path / "manifest.json"
    controller = shipped_path(SHIPPED_DEFENDER)  # a controller file: an actor alone
    for args, refusal in (
        (["init_from=/nonexistent"], "init_from: no checkpoint at /nonexistent"),
        ([f"init_from={a_file}"], f"init_from: checkpoint: {a_file} is not an rlplat checkpoint"),
        ([f"init_from={controller}"], f"init_from: {controller} holds a policy alone"),
        (["env.defender_network=/nonexistent.pt"], "env.defender_network: checkpoint: no file"),
        (["algo.demonstrations=[/nonexistent.json]"], "algo.demonstrations: no plays file"),
        (["observation=relative_state"], "action.gate_high: the gate reads the route deviation"),
        ([f"scenarios_dir={a_file}"], f"scenarios_dir: {a_file}: not a directory"),
        (["train.device=meta"], "train.device: must be a torch device (cpu, cuda, cuda:1, mps)"),
    ):  # fmt: skip
        with pytest.raises(RlplatError) as refused:
            check_command_line("train", [*tiny, *args, f"hydra.run.dir={run}"],
                               validate_job=preflight)  # fmt: skip
        assert str(refused.value).startswith(refusal), args
    assert not run.exists()


def test_a_run_directory_holds_one_run(
    tmp_path, scenarios, tiny, tiny_run, refused_in_process, caplog
):
    run = tmp_path / "run"
    first = tiny_run(scenarios, run)
    metrics = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    tiny = (*tiny, f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}")
    refused = functools.partial(refused_in_process, "train.py")
    stderr = refused(*tiny, "seed=5")  # another run into it would mix their files
    assert stderr == (
        f"error: hydra.run.dir: {run} holds a run already; resume=true continues it, another "
        "directory starts a new one\n"
    )
    stderr = refused(*tiny, "resume=true", "reward=sparse")  # a resume of another config
    assert stderr.startswith("error: resume: the config differs")
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == metrics  # untouched
    assert refused_before_any_work(refused, tmp_path / "new", *tiny[:-1], "resume=true") == (
        f"error: resume: true, and hydra.run.dir={tmp_path / 'new'} holds no run to continue "
        "(no last.pt)"
    )
    # A sweep into a directory whose job 1 holds a run starts no job.
    sweep = tmp_path / "sweep"
    tiny_run(scenarios, sweep / "1")
    stderr = refused("-m", *tiny[:-1], "seed=0,1", f"hydra.sweep.dir={sweep}")
    assert not (sweep / "0").exists()
    assert stderr.startswith(f"error: hydra.sweep.dir: {sweep / '1'} holds a run already")
    # A resume whose budget the run has spent trains nothing, and says so.
    with caplog.at_level("WARNING", logger="rlplat.experiment.training"):
        again = tiny_run(scenarios, run, "resume=true", "train.total_frames=128")
    assert f"train.total_frames=128: the run has {first['frames']} frames already" in caplog.text
    assert (again["frames"], again["updates"]) == (first["frames"], first["updates"])


def test_a_resumed_runs_learning_curve_is_the_whole_run(tmp_path):
    from rlplat.experiment.logger import Metrics

    first = Metrics(tmp_path)
    for frames, rate in ((512, 0.2), (1024, 0.3), (1536, 0.4)):
        first.log({"eval/capture_rate": rate}, step=frames)
    first.close()
    assert not Metrics(tmp_path).history  # a run that does not resume starts its own
    # Resumed from the checkpoint at 1,024 frames: 1,536 is flown, and logged, again.
    resumed = Metrics(tmp_path, resume=True)
    assert resumed.history["eval/capture_rate"] == [(512, 0.2), (1024, 0.3), (1536, 0.4)]
    resumed.log({"eval/capture_rate": 0.5}, step=1536)
    resumed.log({"eval/capture_rate": 0.6}, step=2048)
    curve = [(512, 0.2), (1024, 0.3), (1536, 0.5), (2048, 0.6)]
    assert resumed.history["eval/capture_rate"] == curve
    resumed.close()
    # The CSV holds both attempts at 1,536 frames; a second resume reads the later one.
    assert Metrics(tmp_path, resume=True).history["eval/capture_rate"] == curve


def test_a_resume_keeps_the_record_of_how_the_run_was_launched(
    tmp_path, scenarios, tiny, train_cli
):
    run = tmp_path / "run"
    args = (*tiny, f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}", "seed=3")
    assert train_cli(*args).returncode == 0
    launched = (run / ".hydra" / "overrides.yaml").read_text()
    res = train_cli(*args, "resume=true", "train.total_frames=512")
    assert res.returncode == 0, res.stderr[-2000:]
    # aggregate names a run's variant by the overrides it was launched with
    assert (run / ".hydra" / "overrides.yaml").read_text() == launched
    resumed = OmegaConf.load(run / ".hydra" / "resume" / "overrides.yaml")
    assert "resume=true" in resumed and "train.total_frames=512" in resumed
    assert json.loads((run / "summary.json").read_text())["frames"] >= 512
    # Hydra's --cfg shows a resume's config too, the flag after the overrides or before them
    # (the record's override goes among the overrides, not after the flag)
    for flag_first in (False, True):
        command = [*args, "resume=true", "train.total_frames=1024"]
        command = ["--cfg", "job", *command] if flag_first else [*command, "--cfg", "job"]
        shown = train_cli(*command)
        assert shown.returncode == 0, shown.stderr[-2000:]
        assert OmegaConf.create(shown.stdout).train.total_frames == 1024


@pytest.mark.skipif(shutil.which("sbatch") is not None, reason="this machine has SLURM")
def test_the_cluster_launcher_without_slurm_is_refused_before_any_work(tmp_path, train_cli):
    res = train_cli("-m", "hydra/launcher=cluster", "seed=0,1", f"hydra.sweep.dir={tmp_path}/s")
    assert res.returncode == 2 and not (tmp_path / "s").exists()
    assert res.stderr.startswith("error: hydra/launcher=cluster: submits the jobs to SLURM")


def test_a_run_on_a_scenarios_dir_flies_and_records_the_sets_scenario(
    tmp_path, write_small_set, tiny_run, caplog
):
    # The composed scenario node is not what flies: the set's config is, the vision ellipsoid
    # its starts were drawn in included, and config.yaml says so.
    held = write_small_set(
        tmp_path / "set", "scenario.vision_semi_axes=[60.0,50.0,15.0]", "scenario.seed=3"
    )
    with caplog.at_level("WARNING", logger="rlplat.experiment.factory"):
        tiny_run(held, tmp_path / "run", "scenario=pursuit_2v1")
    assert f"scenario: the set in {held.path} was generated with another" in caplog.text
    assert "attackers, " in caplog.text and "vision_semi_axes" in caplog.text
    # how a team is drawn means nothing to the 1-vs-1 set: not named
    assert "min_separation" not in caplog.text and "defender_spread" not in caplog.text
    saved = OmegaConf.load(tmp_path / "run" / "config.yaml")
    assert saved.scenario.vision_semi_axes == [60.0, 50.0, 15.0]
    assert saved.scenario.seed == 3 and saved.scenario.attackers == 1
    assert saved.env.vision_semi_axes == [60.0, 50.0, 15.0]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["attackers"] == 1


def test_cli_unknown_override_is_refused_in_one_line_before_any_work(tmp_path, train_cli):
    run = tmp_path / "run"
    res = train_cli("algo.learning_rate=1", f"hydra.run.dir={run}")
    assert res.returncode == 2 and res.stderr.startswith("error: algo.learning_rate: no such ")
    res = train_cli("algo=ppo", f"hydra.run.dir={run}")
    assert res.returncode == 2
    assert res.stderr == "error: algo=ppo: no such option (valid: sac, sac_paper)\n"
    assert not run.exists()  # Hydra made no run directory


def test_a_sweep_with_one_bad_job_starts_none(tmp_path, refused_in_process):
    sweep = tmp_path / "sweep"
    stderr = refused_in_process("train.py", "-m", "seed=0,-1", f"hydra.sweep.dir={sweep}")
    assert stderr == (
        "error: seed: must be an integer in [0, 4294967295], got -1 (in the sweep's job seed=-1)\n"
    )
    assert not sweep.exists()
    # A glob over a config group is expanded as Hydra's sweeper does it (include, exclude),
    # and every job checked; an interval, which that sweeper refuses in a traceback, is a line.
    stderr = refused_in_process("train.py", "-m", "drone=glob(attacker_v1*,attacker_v10)",
                                "seed=0,abc", f"hydra.sweep.dir={sweep}")  # fmt: skip
    assert stderr == (
        "error: seed: must be an integer in [0, 4294967295], got 'abc' (in the sweep's job "
        "drone=attacker_v1 seed=abc)\n"
    )
    stderr = refused_in_process("train.py", "-m", "drone=glob(attacker_v1*,attacker_v1)",
                                "algo.gamma=2", f"hydra.sweep.dir={sweep}")  # fmt: skip
    assert stderr.endswith("(in the sweep's job drone=attacker_v10)\n"), stderr
    stderr = refused_in_process("train.py", "-m", "seed=interval(0,1)", f"hydra.sweep.dir={sweep}")
    assert stderr.startswith("error: seed=interval(0,1): an interval is sampled by an optimising")
    assert stderr.count("\n") == 1 and not sweep.exists()


def test_run_directories_that_no_run_can_have_are_refused_before_any_work(
    tmp_path, scenarios, tiny, refused_in_process
):
    # Jobs of a sweep sharing a directory (Hydra would rewrite the first run's .hydra/ record
    # before the second is refused), an empty run directory (the current one), one under a
    # file: each one line, nothing made.
    train_cli = functools.partial(refused_in_process, "train.py")
    tiny, sweep = (*tiny, f"scenarios_dir={scenarios.path}"), tmp_path / "sweep"
    err = train_cli("-m", *tiny, f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=s${seed}",
                    "seed=0", "algo.gamma=0.9,0.99")  # fmt: skip
    assert not sweep.exists()
    assert err == (
        "error: hydra.sweep.subdir: the sweep's jobs algo.gamma=0.9 and algo.gamma=0.99 share "
        f"the directory {sweep / 's0'}; a subdir that tells every job apart (the default, "
        "${hydra.job.num}) gives each its own\n"
    )
    assert train_cli(*tiny, "hydra.run.dir=").startswith("error: hydra.run.dir: empty, which")
    a_file = scenarios.path / "manifest.json"
    err = train_cli(*tiny, f"hydra.run.dir={a_file / 'run'}")
    assert err == f"error: hydra.run.dir: cannot write to {a_file / 'run'}: {a_file} is a file\n"
    # a sweep of another tool whose jobs write to one out_dir: the last would replace the first
    out = tmp_path / "set"
    err = refused_in_process("-m", "rlplat.scenarios", "-m", f"out_dir={out}", "scenario.seed=1,2")
    assert err == (
        f"error: out_dir: the sweep's jobs scenario.seed=1 and scenario.seed=2 both write to "
        f"{out}; give each its own (e.g. out_dir=DIR/${{hydra:job.num}}), or none\n"
    )
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["basic", "joblib"])
def test_multirun_sweeps_seeds(scenarios, tmp_path, launcher, tiny, train_cli):
    res = train_cli(
        "-m",
        *tiny,
        f"scenarios_dir={scenarios.path}",
        "seed=0,1",
        f"hydra/launcher={launcher}",
        f"hydra.sweep.dir={tmp_path}",
    )
    assert res.returncode == 0, res.stderr[-2000:]
    summaries = [json.loads((tmp_path / str(i) / "summary.json").read_text()) for i in (0, 1)]
    assert [s["seed"] for s in summaries] == [0, 1]


def test_cluster_launcher_config_composes(train_cli):
    res = train_cli("hydra/launcher=cluster", "--cfg", "hydra", "--package", "hydra.launcher")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "submitit_launcher.SlurmLauncher" in res.stdout and "timeout_min: 60" in res.stdout


def test_threads_option_sets_torchs_thread_count(scenarios, tmp_path, tiny_run):
    before = torch.get_num_threads()
    want = 1 if before > 1 else 2
    try:
        tiny_run(scenarios, tmp_path, f"train.threads={want}")
        assert torch.get_num_threads() == want
    finally:
        torch.set_num_threads(before)


def test_command_line_tools_run_with_the_suites_thread_count(run_python):
    # What `pytest --torch-threads N` sets, the train.py / evaluate.py subprocesses use too.
    res = run_python("-c", "import torch; print(torch.get_num_threads())")
    assert res.returncode == 0, res.stderr[-2000:]
    assert int(res.stdout) == torch.get_num_threads()


def test_a_job_hydra_moves_into_its_run_reads_paths_where_they_were_typed(
    tmp_path, scenarios, tiny, train_cli
):
    # hydra.job.chdir=true runs the job in its run directory; a relative scenarios_dir is
    # still where the command was typed (the repository root here), as Hydra users expect.
    run = tmp_path / "run"
    typed = os.path.relpath(scenarios.path, Path(__file__).resolve().parent.parent)
    res = train_cli(*tiny, f"scenarios_dir={typed}", "hydra.job.chdir=true", f"hydra.run.dir={run}")
    assert res.returncode == 0, res.stderr[-2000:]
    assert OmegaConf.load(run / "config.yaml").scenarios_dir == str(scenarios.path)


def test_a_run_records_its_paths_absolute_and_reads_from_anywhere(
    tmp_path, scenarios, tiny, monkeypatch
):
    # A path typed relative to where the run was launched: config.yaml records it absolute,
    # so evaluate.py reads the run from another working directory.
    from rlplat.experiment.evaluation import evaluate_run
    from rlplat.experiment.training import train

    monkeypatch.chdir(scenarios.path.parent)
    run = tmp_path / "run"
    train(compose_config("train", [*tiny, f"scenarios_dir={scenarios.path.name}"]), run_dir=run)
    saved = OmegaConf.load(run / "config.yaml")
    assert saved.scenarios_dir == str(scenarios.path)
    assert load_checkpoint(run / "checkpoints" / "best.pt")["config"]["scenarios_dir"] == (
        str(scenarios.path)
    )
    monkeypatch.chdir(tmp_path)
    ev = evaluate_run(run, split="val", plots=False)
    assert ev.summary["scenario_digest"] == scenarios.digest


def test_init_from_another_interface_is_refused_without_a_warning_about_its_route_path(
    scenarios, tmp_path, tiny_run, caplog
):
    # attacker_v3 reads no meeting point, so its checkpoint records no route path; starting
    # the default (which does) from it is refused for its observation, and that alone.
    v3 = tiny_run(scenarios, tmp_path / "v3", "drone=attacker_v3")
    refused = pytest.raises(ConfigError, match=r"^init_from: .* trained with observation.name=")
    with caplog.at_level(logging.WARNING), refused:
        tiny_run(scenarios, tmp_path / "v14", f"init_from={v3['run_dir']}")
    assert "route path" not in caplog.text
