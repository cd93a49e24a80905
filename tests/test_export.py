"""Export: a trained policy leaves as ONNX and C99, verified against the torch actor on rollout
observations, timed, and flown through the evaluator (``policy=onnx``, ``policy=c``)."""

import itertools
import json
import logging
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from torch import nn

import rlplat.experiment.export as export_module
from rlplat.agents import sac
from rlplat.agents.checkpoint import actor_from_state, load_checkpoint, save_checkpoint
from rlplat.agents.export import DeterministicActor, c_sources
from rlplat.agents.native import C_FLAGS, OnnxPolicy, build_library
from rlplat.agents.policies import SHIPPED_DEFENDER, shipped_path
from rlplat.errors import ConfigError, ExportError
from rlplat.eval.episodes import rollout_observations
from rlplat.eval.tables import differing_outcomes
from rlplat.experiment.config import compose_config
from rlplat.experiment.evaluation import evaluate_run, load_run_config
from rlplat.experiment.export import export_run, torch_actions
from rlplat.experiment.factory import build_env
from rlplat.experiment.schema import validate_evaluate_config, validate_export_config
from rlplat.experiment.training import train
from rlplat.io import sha256_bytes
from rlplat.scenarios import ScenarioSet

ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = ("policy.onnx", "policy.h", "policy.c")

# A short pursuit (the attacker is fast and starts close) so that some episodes end early, and
# a run of a few seconds with episodes of 5 s: the suite's shared settings (conftest), resized.
SIZES = ("scenario.n_train=64", "scenario.n_val=16", "scenario.n_test=256")
# Quick exports where the figures are not what a test checks.
QUICK = {"min_observations": 1000, "timing_calls": 1000}


@pytest.fixture(scope="module")
def write_set(write_small_set, easy_pursuit):
    """write_set(path, *overrides) -> ScenarioSet: the short pursuit, 256 test scenarios."""
    return lambda path, *overrides: write_small_set(path, *easy_pursuit, *SIZES, *overrides)


@pytest.fixture(scope="module")
def short_run(tiny):
    """short_run(scenarios, run_dir, *overrides) -> run_dir: a tiny run, episodes of 5 s."""

    def run(scenarios: ScenarioSet, run_dir: Path, *overrides: str) -> Path:
        overrides = (*tiny, "env.time_limit=5", f"scenarios_dir={scenarios.path}", *overrides)
        train(compose_config("train", list(overrides)), run_dir=run_dir)
        return run_dir

    return run


@pytest.fixture(scope="module", autouse=True)
def one_thread(request):
    """One torch thread unless the run asks for a count (``--torch-threads``): the networks
    here are tiny, and on a CPU shared with other jobs two threads wait on each other (a small
    layer then takes milliseconds instead of microseconds)."""
    if request.config.getoption("--torch-threads", default=None) is not None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def scenarios(tmp_path_factory, write_set) -> ScenarioSet:
    return write_set(tmp_path_factory.mktemp("scenarios"))


@pytest.fixture(scope="module")
def run(scenarios, tmp_path_factory, short_run) -> Path:
    # The paper's interface (eq. 1, 2): the network's output is the velocity command.
    return short_run(scenarios, tmp_path_factory.mktemp("run"), "drone=attacker_v3")


@pytest.fixture(scope="module")
def exported(run) -> dict:
    """The run's best checkpoint exported with the default figures (>= 10,000 observations,
    100,000 timed C calls)."""
    return export_run(run)


# The export -------------------------------------------------------------------------------


def test_export_writes_verified_artifacts_and_their_card(run, exported):
    out = run / "export" / "best"
    assert exported["out_dir"] == str(out)
    card = json.loads((out / "card.json").read_text())
    for name in ARTIFACTS:
        assert card["files"][name]["sha256"] == sha256_bytes((out / name).read_bytes())
    assert card["source"]["sha256"] == sha256_bytes((run / "checkpoints/best.pt").read_bytes())
    assert (
        card["source"]["scenario_digest"]
        == json.loads((run / "summary.json").read_text())["scenario_digest"]
    )
    eq = card["equivalence"]
    assert eq["observations"]["count"] >= 10_000 and eq["observations"]["split"] == "test"
    assert eq["observations"]["deterministic_pass"] > 0 and eq["observations"]["scenarios"] == 256
    diffs = eq["max_abs_action_difference"]
    assert set(diffs) == {"torch_vs_onnx", "torch_vs_c", "onnx_vs_c"}
    assert all(0 <= d <= 1e-5 for d in diffs.values()), diffs
    c = card["timing"]["c"]
    assert c["calls"] >= 100_000 and 0 < c["median_us"] <= c["p99_us"] <= c["max_us"]
    assert c["max_over_median"] == pytest.approx(c["max_us"] / c["median_us"], rel=0.01)
    assert 0 <= c["calls_over_3x_median"] < c["calls"] // 2
    for key in ("onnxruntime_per_call", "onnxruntime_per_batch_1024"):
        assert card["timing"][key]["median_us"] > 0
    assert card["machine"]["cpu"] and card["machine"]["compiler"]
    # The interface: what the C function reads, feature by feature.
    obs = card["interface"]["observation"]
    assert obs["name"] == "relative_state" and obs["dim"] == len(obs["features"]) == 9
    assert obs["features"][0] == {"name": "v_own.x", "unit": "m/s", "scale": 5.0}
    assert card["interface"]["frame"].startswith("world frame ENU (x east, y north, z up")
    assert [layer["type"] for layer in card["network"]["layers"]] == [
        "Linear", "ReLU", "Linear", "ReLU", "Linear",
    ]  # fmt: skip
    # The ONNX file passes the checker and takes any batch size.
    model = onnx.load(str(out / "policy.onnx"))
    onnx.checker.check_model(model, full_check=True)
    assert model.graph.input[0].type.tensor_type.shape.dim[0].dim_param
    # It says itself what it reads and where it came from, as ONNX Runtime reads it.
    import onnxruntime

    session = onnxruntime.InferenceSession(str(out / "policy.onnx"))
    meta = session.get_modelmeta().custom_metadata_map
    assert meta["rlplat.source_sha256"] == card["source"]["sha256"]
    assert meta["rlplat.scenario_digest"] == card["source"]["scenario_digest"]
    assert (meta["rlplat.drone"], meta["rlplat.learner"]) == ("attacker_v3", "attacker")
    interface = {k: v for k, v in card["interface"].items() if k != "c_api"}
    assert json.loads(meta["rlplat.interface"]) == interface
    # The C header declares exactly the API.
    header = (out / "policy.h").read_text()
    assert "#define RLPLAT_OBS_DIM  9" in header and "#define RLPLAT_ACT_DIM  3" in header
    assert (
        "void rlplat_policy(const float obs[RLPLAT_OBS_DIM], float action[RLPLAT_ACT_DIM]);"
        in header
    )
    assert "action: in [-1, 1]; times the drone's maximum speed per axis, the velocity" in header
    assert f"Frame: {card['interface']['frame']}." in header  # NED swaps x, y and negates z
    assert "from NED: (x, y, z) = (y_ned, x_ned, -z_ned)" in card["interface"]["frame"]


def test_the_written_files_compute_the_torch_actions(run, exported, scenarios, tmp_path):
    out = run / "export" / "best"
    source = (out / "policy.c").read_text()
    # Dependency-free C99: no heap, no header but libm's; compiles without a warning.
    assert not any(word in source for word in ("malloc", "free(", "stdio", "stdlib"))
    assert [line for line in source.splitlines() if line.startswith("#include")] == [
        "#include <math.h>",
        '#include "policy.h"',
    ]
    shutil.copy(out / "policy.h", tmp_path)
    shutil.copy(out / "policy.c", tmp_path)
    res = subprocess.run(
        ["cc", *C_FLAGS, "-Werror", "-c", "policy.c", "-o", "policy.o"],
        cwd=tmp_path, capture_output=True, text=True,
    )  # fmt: skip
    assert res.returncode == 0 and not res.stderr, res.stderr
    # Before C99 tanhf is undeclared (an implicit int: wrong actions without a word): refused.
    res = subprocess.run(["cc", "-std=c89", "-c", "policy.c", "-o", "old.o"], cwd=tmp_path,
                         capture_output=True, text=True)  # fmt: skip
    assert res.returncode != 0 and "policy.c needs C99 or later" in res.stderr
    # The files themselves, on the observations of the deterministic test-split rollout.
    cfg = load_run_config(run)
    env = build_env(cfg, scenarios=scenarios, split="test", num_envs=256,
                    scenario_order="sequential")  # fmt: skip
    state = load_checkpoint(run / "checkpoints" / "best.pt")
    obs = rollout_observations(env, actor_from_state(state, env.drone_action_spec), "observation")
    expected = torch_actions(state, obs)
    header = (out / "policy.h").read_text()
    c_policy, _ = build_library(header, source, 9, 3)
    onnx_policy = OnnxPolicy((out / "policy.onnx").read_bytes(), 9, 3)
    for got in (c_policy(obs.numpy()), onnx_policy(obs.numpy())):
        assert got.shape == expected.shape and np.abs(got - expected).max() <= 1e-5
    # The card's reference pairs: rollout observations (the first is the rollout's) and the
    # torch actions, which the C computes from the exact values written.
    pairs = exported["equivalence"]["samples"]
    assert len(pairs) == 16 and pairs[0]["observation"] == obs[0].tolist()
    reference = np.array([p["observation"] for p in pairs], dtype=np.float32)
    assert np.abs(c_policy(reference) - np.array([p["action"] for p in pairs])).max() <= 1e-5
    assert np.abs(expected).max() <= 1.0
    # A NaN observation gives NaN actions in C as in torch, not a finite made-up command.
    bad = obs[:4].clone()
    bad[:, 0] = float("nan")
    assert np.isnan(torch_actions(state, bad)).all() and np.isnan(c_policy(bad.numpy())).all()


@pytest.mark.parametrize("policy", ["onnx", "c"])
def test_the_artifacts_fly_the_evaluation_with_the_torch_outcomes(run, exported, policy):
    ev = evaluate_run(run, policy=policy, plots=False)
    s = ev.summary
    assert ev.out_dir == run / "eval" / f"test-best-{policy}"
    for name in ("episodes.csv", "summary.json", "report.md"):
        assert (ev.out_dir / name).is_file()
    assert s["scenarios"] == 256 and s["policy"] == policy and s["name"] == f"best-{policy}"
    assert s["outcomes_differing_from_torch"] == 0 and s["differences_from_torch"] == []
    assert s["capture_rate"] == s["torch_capture_rate"]
    assert (
        "outcomes differing from the torch policy on the same scenarios: **0**,"
        in (ev.out_dir / "report.md").read_text()
    )


def test_outcome_differences_are_listed_by_scenario_id():
    rows = [
        {"scenario_id": "a", "captured": True, "grounded": False, "steps": 40},
        {"scenario_id": "b", "captured": False, "grounded": False, "steps": 100},
    ]
    other = [dict(rows[0]), {**rows[1], "steps": 99}]
    assert differing_outcomes(rows, [dict(r) for r in rows]) == []
    assert differing_outcomes(rows, other) == [
        {
            "scenario_id": "b",
            "outcome": {"captured": False, "grounded": False, "steps": 100},
            "reference": {"captured": False, "grounded": False, "steps": 99},
        }
    ]
    with pytest.raises(ValueError):
        differing_outcomes(rows, other[::-1])


def test_a_second_export_through_the_cli_is_byte_identical(run, exported, tmp_path):
    out = tmp_path / "again"
    res = subprocess.run(
        [sys.executable, str(ROOT / "export.py"), f"run_dir={run}", f"out_dir={out}",
         "min_observations=1", "timing_calls=1000", f"threads={torch.get_num_threads()}"],
        capture_output=True, text=True, cwd=tmp_path, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert "max |action difference|" in res.stdout and str(out) in res.stdout
    for name in ARTIFACTS:
        assert (out / name).read_bytes() == (run / "export" / "best" / name).read_bytes(), name
    assert sorted(p.name for p in out.iterdir()) == sorted([*ARTIFACTS, "card.json"])


def test_a_second_export_keeps_the_card_of_the_same_artifacts_on_this_machine(
    run, exported, tmp_path, monkeypatch
):
    # Timing is the card's only measurement that varies from one export to the next: a second
    # export of the same checkpoint into the same place keeps the timing of the card it
    # replaces, so that every file is byte-identical; retime=True measures again.
    out = tmp_path / "best"
    shutil.copytree(run / "export" / "best", out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    timed = []
    measure = export_module.measure_timing
    monkeypatch.setattr(
        export_module, "measure_timing", lambda *a, **k: timed.append(1) or measure(*a, **k)
    )
    export_run(run, out_dir=out)
    assert not timed
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # The card's load is the one the timing ran beside: sampled after it, not before.
    loads = itertools.chain([[0.0, 0.0, 0.0]], itertools.repeat([7.0, 7.0, 7.0]))
    monkeypatch.setattr(export_module, "load_average", lambda: next(loads))
    card = export_run(run, out_dir=out, retime=True)
    assert len(timed) == 1
    assert card["machine"]["load_average"] == [7.0, 7.0, 7.0]
    assert card["timing"]["c"]["calls"] == exported["timing"]["c"]["calls"]
    for name in ARTIFACTS:
        assert (out / name).read_bytes() == before[name], name
    # Another number of timed calls is another measurement: timed again.
    export_run(run, out_dir=out, timing_calls=1000)
    assert len(timed) == 2


# Bad input --------------------------------------------------------------------------------


def _one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    return message


def test_bad_input_is_one_line_and_writes_nothing(run, tmp_path, monkeypatch):
    out = tmp_path / "out"
    state = load_checkpoint(run / "checkpoints" / "best.pt")
    with pytest.raises(ConfigError) as e:
        export_run(run, ckpt=str(tmp_path / "missing.pt"), out_dir=out)
    assert _one_line(e).startswith("ckpt: no checkpoint at")
    empty = tmp_path / "run-without-checkpoints"
    empty.mkdir()
    shutil.copy(run / "config.yaml", empty)
    with pytest.raises(ConfigError, match="ckpt: no checkpoint at .*best.pt"):
        export_run(empty)
    # A checkpoint of another interface: a network of the absolute observation (R^12).
    other = dict(state, config={**state["config"], "observation": {"name": "absolute"}})
    other["interface"] = {**state["interface"], "observation.name": "absolute"}
    net = sac.NetSpec(**{**_net(state), "obs_dim": 12, "obs_scale": (50.0,) * 6 + (5.0,) * 6})
    other["net"] = {**state["net"], "obs_dim": 12, "obs_scale": list(net.obs_scale)}
    other["actor"] = sac.make_actor(net, _spec()).state_dict()
    save_checkpoint(tmp_path / "other.pt", other)
    with pytest.raises(ConfigError) as e:
        export_run(run, ckpt=str(tmp_path / "other.pt"), out_dir=out)
    assert "obs_dim=12" in _one_line(e)
    # A layer the C generator does not know.
    monkeypatch.setitem(sac.ACTIVATIONS, "silu", nn.SiLU)
    silu = dict(state, net={**state["net"], "activation": "silu"})
    silu["actor"] = sac.make_actor(sac.NetSpec(**{**_net(state), "activation": "silu"}),
                                   _spec()).state_dict()  # fmt: skip
    save_checkpoint(tmp_path / "silu.pt", silu)
    with pytest.raises(ConfigError) as e:
        export_run(run, ckpt=str(tmp_path / "silu.pt"), out_dir=out)
    assert _one_line(e) == (
        "export: actor layer 1 is SiLU, which the C generator does not know; it supports "
        "Linear, ReLU, Tanh, ELU"
    )
    with pytest.raises(ConfigError) as e:
        export_run(run, out_dir=out, compiler="no-such-cc")
    assert _one_line(e).startswith("compiler: no C compiler 'no-such-cc' on PATH")
    # Before any rollout: a compiler that builds nothing, an out_dir that cannot be written.
    monkeypatch.setattr(export_module, "collect_observations", _no_work)
    fake = tmp_path / "fake-cc"
    fake.write_text("#!/bin/sh\nexit 0\n")
    fake.chmod(0o755)
    with pytest.raises(ConfigError) as e:
        export_run(run, out_dir=out, compiler=str(fake))
    assert _one_line(e) == (
        f"compiler: {fake} builds no loadable shared library from C99 (no file written)"
    )
    # A compiler that warns before the error that fails it: the error is what is said.
    fake.write_text(
        "#!/bin/sh\necho \"cc1plus: warning: '-std=c99' is valid for C\" >&2\n"
        'echo "probe.c:2: error: invalid conversion" >&2\nexit 1\n'
    )
    with pytest.raises(ConfigError) as e:
        export_run(run, out_dir=out, compiler=str(fake))
    assert _one_line(e) == (
        f"compiler: {fake} failed on probe.c: probe.c:2: error: invalid conversion"
    )
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    for where, reason in ((a_file, "is a file"), (a_file / "out", f"{a_file} is a file")):
        with pytest.raises(ConfigError) as e:
            export_run(run, out_dir=where)
        assert _one_line(e) == f"out_dir: cannot write to {where}: {reason}"
        with pytest.raises(ConfigError, match=f"^out_dir: cannot write to {where}: "):
            evaluate_run(run, out_dir=where, plots=False)
    before = sorted(p.name for p in Path(run).iterdir())
    with pytest.raises(ConfigError) as e:  # the files would mix with the run's own
        export_run(run, out_dir=run)
    assert _one_line(e) == (
        f"out_dir: {run} is a training run's directory; the export's files would mix with the "
        "run's (choose a folder of its own, e.g. <run>/export/NAME)"
    )
    assert sorted(p.name for p in Path(run).iterdir()) == before
    assert not out.exists()


def _no_work(*args, **kwargs):
    raise AssertionError("the export started its rollouts")


def _net(state: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in state["net"].items()}


def _spec():
    from torchrl.data import Bounded

    return Bounded(-1.0, 1.0, shape=(3,))


@pytest.mark.parametrize(
    "drone,action_name,unit,header,obs_dim",
    [
        ("attacker_v4", "guided_velocity", "a correction to proportional navigation",
         "CORRECTION to proportional navigation", 10),
        ("attacker_v5", "guidance_law", "the parameters of proportional navigation",
         "SETS proportional navigation's parameters", 10),
        ("attacker_v10", "route_law", "a correction to the route-intercept law",
         "CORRECTION to the route-intercept law", 20),
        ("attacker_v11", "route_law", "a correction to the route-intercept law",
         "CORRECTION to the route-intercept law", 24),
        ("attacker_v12", "route_law", "a correction to the route-intercept law",
         "CORRECTION to the route-intercept law", 24),
        ("attacker_v13", "route_law", "a correction to the route-intercept law, gated on the "
         "defender's route deviation", "GATED: the correction is multiplied by", 24),
        ("attacker_v14", "route_law", "a correction to the route-intercept law, gated on the "
         "defender's route deviation", "flies to where the route puts the defender at the "
         "horizon's end and holds.", 24),
    ],
)  # fmt: skip
def test_a_guided_controller_exports_with_its_guidance(
    scenarios, tmp_path, short_run, caplog, drone, action_name, unit, header, obs_dim
):
    # attacker_v4 learns a correction to proportional navigation, attacker_v5 the law's
    # parameters, attacker_v10 a correction to the route-intercept law (attacker_v11 seeing
    # how the defender keeps its route): the artifacts compute the action, the card and header
    # say what the env makes of it (for v10 and v11, also the path model its meeting point
    # assumes; for v11 how the route features are computed), and the C controller flies the
    # evaluation with the torch outcomes.
    run = short_run(scenarios, tmp_path / "run", f"drone={drone}")
    export_run(run, ckpt="last", **QUICK)
    out = run / "export" / "last"
    card = json.loads((out / "card.json").read_text())
    action = card["interface"]["action"]
    assert action["name"] == action_name and action["guidance"]["lead"] == 0.5
    assert unit in action["unit"]
    assert card["interface"]["observation"]["dim"] == obs_dim
    path = card["interface"].get("route_path")
    assert (path is not None) == (action_name == "route_law")
    if path is not None:
        assert path["lag"] == 0.9 and path["gain"] == 1.0 and path["acceptance"] == 1.0
        law = action["guidance"]  # attacker_v12's law allows for the attacker's start-up
        lagged = drone in ("attacker_v12", "attacker_v13", "attacker_v14")
        assert path["start_lag"] == law["start_lag"] == (0.5 if lagged else 0)
        # attacker_v14's law heads the defender off where no meeting point is reachable
        assert law["unreachable"] == ("head_off" if drone == "attacker_v14" else "chase")
    conformity = card["interface"].get("route_conformity")  # what the caller keeps per defender
    assert (conformity is not None) == (obs_dim == 24)
    if conformity is not None:
        assert conformity["route_lag"] == [0.9, 0.9, 0.35] and conformity["control_period"] == 0.1
    assert header in (out / "policy.h").read_text()
    # The numbers a host needs to compute the inputs are in the header, not only in the card.
    text = " ".join(line.lstrip(" *") for line in (out / "policy.h").read_text().splitlines())
    assert ("route_path, computed by the host:" in text) == (path is not None)
    if path is not None:
        assert f"lag 0.9, gain 1, acceptance 1, start_lag {path['start_lag']:g}, horizon" in text
        # how the meeting point is searched, and what it is where none can be reached
        assert path["resolution_s"] == 0.25 and path["reach_m"] == 1.2
        assert "resolution_s 0.25, reach_m 1.2." in text and "Unreachable: where no" in text
    assert ("route_conformity, computed by the host:" in text) == (conformity is not None)
    if conformity is not None:
        assert "route_lag 0.9 0.9 0.35, conformity_time 1, control_period 0.1" in text
    # The route's setpoints the observation reads (attacker_v10 on), and how they move on.
    setpoint = card["interface"].get("route_setpoint")
    assert (setpoint is not None) == (obs_dim >= 20)
    assert ("route_setpoint, computed by the host:" in text) == (setpoint is not None)
    if action_name == "guidance_law":  # the command the parameters make, in both files
        assert "velocity command = pn x max speed per axis" in action["unit"]
        assert "The velocity command = pn x max speed per axis" in text
        assert "pn = clamp(gain * (r + lead * u * t_go) / V, -1, 1) per axis" in text
    # Next to the declaration too: the action is not the velocity command.
    assert "action: in [-1, 1]; not the velocity command itself" in (out / "policy.h").read_text()
    ev = evaluate_run(run, policy="c", ckpt="last", plots=False)
    assert ev.summary["outcomes_differing_from_torch"] == 0
    if path is not None:  # the route_intercept baseline flies the law the run corrects
        baseline = evaluate_run(run, policy="route_intercept", plots=False).summary
        assert baseline["policy_args"] == {
            k: law[k] for k in ("homing_time", "start_lag", "unreachable")
        }  # the horizon: null, the time limit
        # A checkpoint trained on another route path is refused.
        ckpt = run / "checkpoints" / "last.pt"
        state = torch.load(ckpt, weights_only=False)
        state["interface"]["route_path"]["lag"] = 0.0
        torch.save(state, ckpt)
        with pytest.raises(ConfigError, match=r"trained with the defender's route path .*'lag': 0"):
            evaluate_run(run, ckpt="last", plots=False)
        # Saved before the start-up lag was recorded: the law had none.
        del state["interface"]["route_path"]["start_lag"]
        state["interface"]["route_path"]["lag"] = 0.9
        torch.save(state, ckpt)
        if lagged:
            with pytest.raises(
                ConfigError, match=r"'start_lag': 0.0}, this env's .*'start_lag': 0.5"
            ):
                evaluate_run(run, ckpt="last", plots=False)
        else:
            assert "capture_rate" in evaluate_run(run, ckpt="last", plots=False).summary
        # A checkpoint of another drone is refused in one line, with no warning before it
        # about the route path it saved none of.
        caplog.clear()
        with caplog.at_level(logging.WARNING), pytest.raises(ConfigError) as e:
            export_run(run, ckpt=str(shipped_path(SHIPPED_DEFENDER)), **QUICK)
        assert _one_line(e).startswith("ckpt: ") and not caplog.records, caplog.text


def _path_from_the_card(p, v, speed, t, lag, gain, acceptance):
    """ROUTE_PATH_FORMULA, step by step as the card words it, in plain Python."""
    n_legs = len(p) - 1
    d = [max(abs(p[i][k] - p[i - 1][k]) for k in range(3)) for i in range(1, n_legs + 1)]
    lags = [lag if di > 0 else 0.0 for di in d]
    first = [p[1][k] - p[0][k] for k in range(3)]
    axis = max(range(3), key=lambda k: (abs(first[k]), -k))  # the first longest axis
    u = v[axis] * math.copysign(1.0, first[axis]) if first[axis] else 0.0
    lags[0] *= min(max(1 - u / speed, 0.0), 1.0)
    near = max(speed / gain, acceptance)
    approach = [
        0.0
        if math.isinf(gain)
        else max(0.0, max(di - near, 0) / speed
                 + math.log(max(min(di, near), acceptance) / acceptance) / gain - di / speed)
        for di in d
    ]  # fmt: skip
    arrive = list(itertools.accumulate(lags[i] + d[i] / speed + approach[i] for i in range(n_legs)))
    leg = next((i for i in range(n_legs) if arrive[i] > t), n_legs - 1)
    start = (arrive[leg - 1] if leg else 0.0) + lags[leg]
    a, b = p[leg], p[leg + 1]
    flown = max(t - start, 0.0) * speed
    return [a[k] + math.copysign(min(abs(b[k] - a[k]), flown), b[k] - a[k]) for k in range(3)]


@pytest.mark.parametrize("gain", [1.0, math.inf])
def test_the_cards_route_path_formula_is_the_path_the_law_flies(gain):
    # A host computes the meeting point's path from the card alone: its formula, followed
    # step by step, gives the positions rlplat.envs.kinematics.route_path gives.
    from rlplat.envs.kinematics import SetpointFlight, route_path
    from rlplat.experiment.export import ROUTE_PATH_FORMULA

    assert "ln(max(min(d_i, n), acceptance) / acceptance)" in ROUTE_PATH_FORMULA
    flight = SetpointFlight(0.9, gain, 1.0 if math.isfinite(gain) else 0.0)
    gen = torch.Generator().manual_seed(0)
    times = torch.linspace(0.0, 60.0, 97, dtype=torch.float64)
    for _ in range(20):
        position = torch.rand(3, generator=gen, dtype=torch.float64) * 20 - 10
        route = torch.rand(5, 3, generator=gen, dtype=torch.float64) * 60 - 30
        route[-1] = route[-2]  # a route flown to its end repeats its last setpoint
        velocity = torch.rand(3, generator=gen, dtype=torch.float64) * 6 - 3
        speed = float(torch.rand((), generator=gen)) * 4 + 1
        got = route_path(position, route, torch.tensor(speed, dtype=torch.float64), times,
                         velocity=velocity, flight=flight)  # fmt: skip
        points = [position.tolist(), *route.tolist()]
        for t, row in zip(times.tolist(), got.tolist(), strict=True):
            want = _path_from_the_card(points, velocity.tolist(), speed, t, flight.lag,
                                       flight.gain, flight.acceptance)  # fmt: skip
            assert row == pytest.approx(want, abs=1e-5), t  # float32 lags in route_path


def test_the_cards_reachable_rule_is_the_one_the_meeting_point_search_uses():
    # A host searches the meeting point by the card's rule; a point the attacker's start-up lag
    # would make "reachable" sooner than now (t < start_lag) is not: max(t - start_lag, 0).
    from rlplat.envs.kinematics import route_intercept
    from rlplat.experiment.export import REACHABLE_RULE

    assert "max_speed * max(t - start_lag, 0) + reach_m" in REACHABLE_RULE
    times = torch.arange(1, 241, dtype=torch.float64) * 0.25  # resolution 0.25 s, 60 s
    gen = torch.Generator().manual_seed(1)
    cases = [((1.0, 1.0, 0.5), 4.0, 0.5)]  # 1.5 m away: due at 0.25 s; t - start_lag says 0.5
    for _ in range(30):
        offset = (torch.rand(3, generator=gen, dtype=torch.float64) * 8 - 4).tolist()
        speed, lag = float(torch.rand((), generator=gen)) * 4 + 0.5, 0.5
        cases.append((offset, speed, lag))
    for offset, speed, lag in cases:  # a defender holding still: its path is its position
        other = torch.tensor([offset], dtype=torch.float64)  # a batch of one
        _, due, found = route_intercept(
            torch.zeros(1, 3, dtype=torch.float64), torch.tensor([speed], dtype=torch.float64),
            other, other.unsqueeze(1).expand(1, 3, 3), torch.ones(1, dtype=torch.float64),
            times=times, lag=lag, reach=1.2,
        )  # fmt: skip
        gap = max(abs(x) for x in offset)
        want = next((t for t in times.tolist() if gap <= speed * max(t - lag, 0.0) + 1.2), None)
        assert bool(found) == (want is not None) and (want is None or float(due) == want)


def _pn_from_the_card(r, u, speed, gain, lead, max_lead_time):
    """The card's pn formula, step by step in plain Python, one attacker."""
    closing = [speed - math.copysign(1.0, r[k]) * u[k] if r[k] else speed for k in range(3)]
    t_i = [abs(r[k]) / closing[k] if closing[k] > 1e-6 else max_lead_time for k in range(3)]
    t_go = min(max(t_i), max_lead_time)
    return [min(max(gain * (r[k] + lead * u[k] * t_go) / speed, -1.0), 1.0) for k in range(3)]


@pytest.mark.parametrize("unreachable", ["chase", "head_off"])
def test_the_cards_law_formulas_are_the_law_the_env_flies(unreachable):
    # A host builds the velocity command from the card: the law's formula, followed as worded,
    # gives the guidance the env adds the correction to (route law and its pn homing).
    from rlplat.envs.components import RouteLawAction

    law = RouteLawAction(homing_time=0.5, start_lag=0.5, unreachable=unreachable)
    words = law.card()["guidance"]["formula"]
    assert "law = clamp(gain * m / V, -1, 1) per axis" in words
    assert "t_i = |r_i| / (V - sign(r_i) * u_i)" in words and "world frame" in words
    assert ("wherever none is" in words) == (unreachable == "chase")
    gen = torch.Generator().manual_seed(2)
    n = 400
    rel = torch.rand(n, 3, generator=gen) * 60 - 30
    rel[:20, 1] = 0.0  # an axis already closed
    v_other = torch.rand(n, 3, generator=gen) * 8 - 4
    speed = torch.rand(n, generator=gen) * 4 + 0.5
    aim = torch.rand(n, 3, generator=gen) * 60 - 30
    due = torch.rand(n, generator=gen) * 2  # across homing_time
    reachable = torch.rand(n, generator=gen) > 0.3
    got = law.guidance(rel, v_other, speed, meeting=(aim, due, reachable))
    for i in range(n):
        pn = _pn_from_the_card(rel[i].tolist(), v_other[i].tolist(), float(speed[i]),
                               law.gain, law.lead, law.max_lead_time)  # fmt: skip
        homes = float(due[i]) <= law.homing_time or (
            unreachable == "chase" and not bool(reachable[i])
        )
        fly_to = [min(max(law.gain * a / float(speed[i]), -1.0), 1.0) for a in aim[i].tolist()]
        assert got[i].tolist() == pytest.approx(pn if homes else fly_to, abs=1e-5), i


@pytest.mark.parametrize(
    "drone,defenders", [("defender_v1", 1), ("attacker_v10", 1), ("attacker_v10", 2)]
)
def test_the_cards_setpoint_rule_is_the_setpoint_the_observation_reads(
    write_small_set, tmp_path, drone, defenders
):
    # A host builds the observation's setpoint features from the card's rule: followed as
    # worded along flown episodes (the defender's positions after each step, its route), it
    # gives the setpoint the env's observation reads, for a defender (its own) and for an
    # attacker that sees the route ahead (the first defender's, and the one after it; with two
    # defenders, the first's also once it is caught).
    from torchrl.envs.utils import step_mdp

    from rlplat.agents.policies import make_scripted_policy

    route_flyers = write_small_set(tmp_path, "scenario.strategy_mix.nn=0",
                                   f"scenario.defenders={defenders}")  # fmt: skip
    env = build_env(compose_config("train", [f"drone={drone}"]), scenarios=route_flyers,
                    split="test", num_envs=16)  # fmt: skip
    model = export_module.host_models(env)["route_setpoint"]
    assert "within acceptance m of it (Euclidean distance)" in model["rule"]
    assert model["defender"] == ("the drone itself" if drone == "defender_v1" else
                                 "the observation's setpoint features: the scenario's first "
                                 "defender, for every attacker, caught or not; route_path: "
                                 "each defender's own")  # fmt: skip
    flies = "setpoint_follower" if drone == "defender_v1" else "route_intercept"
    policy = make_scripted_policy(flies, env)
    names = [f["name"] for f in env.obs_fn.features()]
    own = names.index("(setpoint - p_own).x")  # where each 3-vector starts
    ahead = names.index("(next_setpoint - p_own).x") if drone == "attacker_v10" else None
    td = env.reset()
    route = env.routes[env.route[:, 0]]  # (N, S, 3): each env's first defender's route
    rows, last = torch.arange(16), route.shape[1] - 1
    w = torch.zeros(16, dtype=torch.long)  # the rule's setpoint index
    going = torch.ones(16, dtype=torch.bool)
    first = env.num_attackers  # the first defender's drone index
    me = first if drone == "defender_v1" else 0  # whose position the features are relative to
    caught_going = torch.zeros(16, dtype=torch.bool)  # the first caught, the episode going on
    for _ in range(400):
        p = td["positions"]
        obs = td["observation"]
        for at, k in ((own, 0), (ahead, 1)):
            if at is not None:
                got = obs[:, at : at + 3] + p[:, me]
                want = route[rows, (w + k).clamp(max=last)]
                assert torch.allclose(got[going], want[going], atol=1e-4)
        caught = td["caught"][:, 0].clone()  # before the step
        caught_going |= caught & going
        td = step_mdp(env.step(policy(td)))
        after = td["positions"][:, first]
        near = (route[rows, w.clamp(max=last)] - after).norm(dim=-1) <= model["acceptance"]
        w = w + (near & (w <= last) & going & ~caught)
        going &= ~td["done"].squeeze(-1)
        if not going.any():
            break
    assert (w > 2).any()  # the rule was followed past several setpoints
    assert caught_going.any() == (defenders == 2)  # and past a capture of the first


def test_implementations_that_differ_fail_the_export_and_write_nothing(run, tmp_path):
    with pytest.raises(ExportError) as e:
        export_run(run, out_dir=tmp_path / "out", tolerance=1e-12, **QUICK)
    assert "tolerance=1e-12; nothing written" in _one_line(e)
    assert not (tmp_path / "out").exists()


def test_configs_name_the_offending_field():
    def check(*overrides):
        validate_export_config(compose_config("export", list(overrides)))

    check("run_dir=runs/x")
    check("controller=rlplat/agents/weights/defender_v1.pt", "out_dir=x")
    with pytest.raises(ConfigError, match="^run_dir: set run_dir=DIR"):
        check()
    with pytest.raises(ConfigError, match="^out_dir: a controller export needs out_dir"):
        check("controller=x.pt")
    with pytest.raises(ConfigError, match="^tolerance: must be a finite number > 0"):
        check("run_dir=x", "tolerance=0")
    validate_evaluate_config(compose_config("evaluate", ["run_dir=x", "policy=c", "ckpt=last"]))


def test_evaluating_an_artifact_needs_its_export_as_written(run, exported, tmp_path):
    copy = tmp_path / "a run"  # the command to run is quoted for a shell
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval", "export"))
    with pytest.raises(ConfigError) as e:
        evaluate_run(copy, policy="onnx", ckpt="last")
    assert _one_line(e).endswith(f"run `python export.py 'run_dir={copy}' ckpt=last` first")
    shutil.copytree(run / "export", copy / "export")
    source = copy / "export" / "best" / "policy.c"
    source.write_text(source.read_text().replace("1.20000005f", "1.0f"))
    with pytest.raises(ConfigError, match="policy.c is missing or not the file the card names"):
        evaluate_run(copy, policy="c")
    card = copy / "export" / "best" / "card.json"
    for text in ("{not json", '{"source": {}}'):
        card.write_text(text)
        with pytest.raises(ConfigError) as e:
            evaluate_run(copy, policy="c")
        assert f"policy: {card} is not an export card" in _one_line(e)
    assert not (copy / "eval").exists()


def test_an_export_written_elsewhere_flies_from_export_dir(run, exported, tmp_path):
    out = tmp_path / "elsewhere"  # with its own C names, which the evaluator calls
    card = export_run(run, out_dir=out, prefix="pursuer", min_observations=1000,
                      timing_calls=1000)  # fmt: skip
    assert card["out_dir"] == str(out) and card["interface"]["c_api"].startswith(
        "void pursuer_policy(const float obs[PURSUER_OBS_DIM]"
    )
    ev = evaluate_run(run, policy="c", export_dir=out, plots=False, out_dir=tmp_path / "ev")
    assert ev.summary["artifact"]["dir"] == str(out)
    assert ev.summary["outcomes_differing_from_torch"] == 0
    with pytest.raises(ConfigError) as e:
        evaluate_run(run, policy="c", export_dir=tmp_path / "none", plots=False)
    assert _one_line(e).endswith(
        f"run `python export.py run_dir={run} ckpt=best out_dir={tmp_path / 'none'}` first"
    )
    with pytest.raises(ConfigError, match=r"^export_dir: is for policy=onnx or c"):
        evaluate_run(run, policy="checkpoint", export_dir=out)


def test_flying_the_onnx_export_without_onnxruntime_is_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails: not installed
    with pytest.raises(ConfigError) as e:
        OnnxPolicy(b"", 9, 3)
    assert _one_line(e) == (
        "policy: onnx needs onnxruntime, which is not installed; pip install 'rlplat[export]'"
    )


# Every learner ----------------------------------------------------------------------------


def test_an_actor_with_one_action_everywhere_is_exported_with_a_warning(run, tmp_path, caplog):
    # An output layer still at zero (a run that stopped before actor_warmup_updates) makes the
    # three implementations agree trivially: the export says so instead of passing in silence.
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("export", "eval"))
    path = copy / "checkpoints" / "best.pt"
    state = torch.load(path, weights_only=False)
    last = max(k for k in state["actor"] if k.endswith(".weight"))
    state["actor"][last].zero_()
    state["actor"][last.replace(".weight", ".bias")].zero_()
    torch.save(state, path)
    with caplog.at_level(logging.WARNING, logger="rlplat.experiment.export"):
        export_run(copy, **QUICK)
    assert "the actor gives one action, [0.0, 0.0, 0.0], on all" in caplog.text
    assert "tests no network" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="rlplat.experiment.export"):
        export_run(run, out_dir=tmp_path / "trained", **QUICK)
    assert "tests no network" not in caplog.text


def test_an_export_on_another_set_warns_in_its_own_words(run, write_set, tmp_path, caplog):
    other = write_set(tmp_path / "other", "scenario.seed=5")
    with caplog.at_level(logging.WARNING, logger="rlplat.experiment.evaluation"):
        card = export_run(run, scenarios_dir=other.path, out_dir=tmp_path / "out", **QUICK)
    assert f"the set at {other.path} has digest {other.digest[:12]}" in caplog.text
    assert "; exporting anyway" in caplog.text and "evaluating" not in caplog.text
    flown = card["equivalence"]["observations"]
    assert flown["scenario_digest"] == other.digest and flown["scenario_digest_matches"] is False


def test_the_shipped_defender_network_exports(scenarios, tmp_path):
    path = shipped_path(SHIPPED_DEFENDER)
    out = tmp_path / "defender"
    card = export_run(controller=path, out_dir=out, scenarios_dir=scenarios.path, **QUICK)
    assert card["source"]["sha256"] == sha256_bytes(path.read_bytes())
    assert card["source"]["learner"] == "defender"
    assert card["interface"]["observation"]["name"] == "route_state"
    assert all(d <= 1e-5 for d in card["equivalence"]["max_abs_action_difference"].values())
    assert "#define RLPLAT_OBS_DIM  12" in (out / "policy.h").read_text()
    # The C file computes the shipped controller's own actions (NetworkController's formula).
    actor = DeterministicActor.from_state(load_checkpoint(path))
    header, source = c_sources(actor)
    assert source == (out / "policy.c").read_text()
    x = torch.randn(256, 12) * 10
    c_policy, _ = build_library((out / "policy.h").read_text(), source, 12, 3)
    assert np.abs(c_policy(x.numpy()) - actor(x).numpy()).max() <= 1e-5


def _tiny_actor(obs_dim: int, action_dim: int, activation: nn.Module) -> DeterministicActor:
    torch.manual_seed(0)
    mlp = nn.Sequential(nn.Linear(obs_dim, 6), activation, nn.Linear(6, 2 * action_dim))
    return DeterministicActor(mlp=mlp, inv_scale=torch.ones(obs_dim), action_dim=action_dim,
                              action_margin=0.2)  # fmt: skip


def test_the_header_holds_any_description_and_names_what_it_needs(tmp_path):
    # A description line (a drone's name, say) that holds a comment's end or start: the header
    # still compiles without a warning, and the text survives, broken up.
    actor = _tiny_actor(4, 3, nn.ReLU())
    header, source = c_sources(actor, describe=["drone a */ b", "see /* here"])
    (tmp_path / "policy.h").write_text(header)
    (tmp_path / "policy.c").write_text(source)
    subprocess.run(["cc", *C_FLAGS, "-Werror", "-c", "policy.c"], cwd=tmp_path, check=True)
    assert "drone a * / b" in header and "see / * here" in header
    c_policy, _ = build_library(header, source, 4, 3)
    x = torch.randn(64, 4)
    assert np.abs(c_policy(x.numpy()) - actor(x).numpy()).max() <= 1e-5
    # libm: what the network calls (expm1f only for an ELU layer).
    assert "no library but libm (tanhf)." in header
    elu_header, elu_source = c_sources(_tiny_actor(4, 3, nn.ELU()))
    assert "no library but libm (tanhf, expm1f)." in elu_header and "expm1f(" in elu_source

    # One array for obs and action holds the larger of the two.
    def flat(text: str) -> str:  # the header's comments as one line
        return " ".join(text.replace("\n * ", " ").split())

    assert "an array of RLPLAT_OBS_DIM floats then" in flat(header)
    wide = c_sources(_tiny_actor(2, 3, nn.ReLU()))[0]
    assert "an array of RLPLAT_ACT_DIM floats then" in flat(wide)
    # A reserved prefix's suggested replacement is one that check_prefix takes.
    with pytest.raises(ConfigError, match=r"choose another prefix, e\.g\. 'drone_strike'$"):
        c_sources(actor, prefix="strike")
    with pytest.raises(ConfigError, match=r"choose another prefix$"):
        c_sources(actor, prefix="memo" + "x" * 19)


TWO_CONTROLLERS = r"""#include <stdio.h>
#include "attacker/policy.h"
#include "defender/policy.h"

int main(void)
{
    float a_obs[ATTACKER_OBS_DIM], a_act[ATTACKER_ACT_DIM];
    float d_obs[DEFENDER_OBS_DIM], d_act[DEFENDER_ACT_DIM];
    int i;
    for (i = 0; i < ATTACKER_OBS_DIM; ++i) a_obs[i] = (float)(i % 5) - 2.0f;
    for (i = 0; i < DEFENDER_OBS_DIM; ++i) d_obs[i] = 3.0f - (float)(i % 7);
    attacker_policy(a_obs, a_act);
    defender_policy(d_obs, d_act);
    for (i = 0; i < ATTACKER_ACT_DIM; ++i) printf("%.9g\n", a_act[i]);
    for (i = 0; i < DEFENDER_ACT_DIM; ++i) printf("%.9g\n", d_act[i]);
    return 0;
}
"""


def test_two_controllers_with_their_own_prefixes_link_into_one_program(run, tmp_path):
    # An attacker and the shipped defender, side by side in one C program, as generated.
    actors = {
        "attacker": DeterministicActor.from_state(load_checkpoint(run / "checkpoints/best.pt")),
        "defender": DeterministicActor.from_state(load_checkpoint(shipped_path(SHIPPED_DEFENDER))),
    }
    objects = []
    for prefix, actor in actors.items():
        header, source = c_sources(actor, prefix=prefix)
        assert f"void {prefix}_policy(const float obs[{prefix.upper()}_OBS_DIM]" in header
        assert "rlplat_policy" not in header + source and "RLPLAT_" not in header + source
        (tmp_path / prefix).mkdir()
        (tmp_path / prefix / "policy.h").write_text(header)
        (tmp_path / prefix / "policy.c").write_text(source)
        objects.append(f"{prefix}.o")
        subprocess.run(["cc", *C_FLAGS, "-Werror", "-c", f"{prefix}/policy.c", "-o", objects[-1]],
                       cwd=tmp_path, check=True)  # fmt: skip
    (tmp_path / "main.c").write_text(TWO_CONTROLLERS)
    subprocess.run(["cc", *C_FLAGS, "-Werror", "main.c", *objects, "-lm", "-o", "both"],
                   cwd=tmp_path, check=True)  # fmt: skip
    out = subprocess.run([str(tmp_path / "both")], capture_output=True, text=True, check=True)
    got = np.array([float(v) for v in out.stdout.split()])
    a_obs = torch.tensor([float(i % 5) - 2.0 for i in range(actors["attacker"].obs_dim)])
    d_obs = torch.tensor([3.0 - float(i % 7) for i in range(actors["defender"].obs_dim)])
    expected = torch.cat([actors["attacker"](a_obs[None])[0], actors["defender"](d_obs[None])[0]])
    assert got.shape == expected.shape and np.abs(got - expected.numpy()).max() <= 1e-5
    # One translation unit holding both (a unity build): no name of one is the other's.
    unity = '#include "attacker/policy.c"\n#include "defender/policy.c"\n' + TWO_CONTROLLERS
    (tmp_path / "unity.c").write_text(unity)
    subprocess.run(["cc", *C_FLAGS, "-Werror", "unity.c", "-lm", "-o", "unity"],
                   cwd=tmp_path, check=True)  # fmt: skip
    out = subprocess.run([str(tmp_path / "unity")], capture_output=True, text=True, check=True)
    assert np.array([float(v) for v in out.stdout.split()]).tolist() == got.tolist()
    # Prefixes whose names would clash with another's (one uppercase guard for two cases) or
    # that C reserves (a leading or double underscore).
    for bad in ("9lives", "Attacker", "_", "__x", "a__b", "a_", "a-b", "x" * 25):
        with pytest.raises(ConfigError, match=rf"^prefix: '{bad}' does not start C names"):
            c_sources(actors["attacker"], prefix=bad)
    assert "void blue_2_policy(" in c_sources(actors["attacker"], prefix="blue_2")[0]
    # Names the C library reserves: E and a capital (errno.h), to, is, str and a lowercase
    # letter (ctype.h, string.h), SIG and a capital (signal.h).
    for bad, name in (("evader", "EVADER_OBS_DIM"), ("token", "token_policy"),
                      ("island", "island_policy"), ("strike", "strike_policy"),
                      ("signal", "SIGNAL_OBS_DIM")):  # fmt: skip
        with pytest.raises(ConfigError, match=rf"^prefix: '{bad}' makes {name}, a name C "):
            c_sources(actors["attacker"], prefix=bad)
    assert "void drone_evader_policy(" in c_sources(actors["attacker"], prefix="drone_evader")[0]


def test_a_team_run_exports_and_flies_one_call_per_drone(tmp_path, write_set, short_run):
    team_set = write_set(tmp_path / "scenarios", "scenario.attackers=2", "scenario.n_test=32")
    run = short_run(team_set, tmp_path / "run")
    card = export_run(run, **QUICK)
    assert card["interface"]["team"]["drones_sharing_the_policy"] == 2
    assert all(d <= 1e-5 for d in card["equivalence"]["max_abs_action_difference"].values())
    ev = evaluate_run(run, policy="c", plots=False)
    assert ev.summary["attackers"] == 2 and ev.summary["outcomes_differing_from_torch"] == 0


def test_a_defender_run_exports_and_flies_the_evaluation(tmp_path, write_set, short_run):
    # A trained defender bundle: its observation is the route's, its artifacts fly the defender
    # through the evaluator against the scripted attacker with the torch outcomes.
    defender_set = write_set(tmp_path / "scenarios", "scenario.n_test=32")
    run = short_run(defender_set, tmp_path / "run", "drone=defender_v1")
    card = export_run(run, **QUICK)
    assert card["source"]["learner"] == "defender"
    assert card["interface"]["observation"]["name"] == "route_state"
    # Its setpoint feature: which setpoint, and when it moves on, in the card and the header.
    assert card["interface"]["route_setpoint"]["defender"] == "the drone itself"
    header = " ".join(
        line.lstrip(" *") for line in (run / "export/best/policy.h").read_text().splitlines()
    )
    assert "route_setpoint, computed by the host:" in header and "acceptance 1." in header
    assert all(d <= 1e-5 for d in card["equivalence"]["max_abs_action_difference"].values())
    for policy in ("c", "onnx"):
        ev = evaluate_run(run, policy=policy, plots=False)
        assert ev.summary["learner"] == "defender", policy
        assert ev.summary["outcomes_differing_from_torch"] == 0, policy


def test_a_folder_is_checked_by_writing_in_it_not_by_its_permission_bits(tmp_path):
    from rlplat.io import check_writable_dir

    assert check_writable_dir(tmp_path / "a" / "b", "out_dir") == tmp_path / "a" / "b"
    assert list(tmp_path.iterdir()) == []  # nothing made, the probe removed
    if Path("/proc/self").is_dir():  # writable by its bits for root, yet no file can be made
        with pytest.raises(ConfigError, match=r"^out_dir: cannot write to /proc/x: /proc is not"):
            check_writable_dir("/proc/x", "out_dir")
