"""The AirSim tools against the loopback test server, through the real client library:
calibration of the velocity dynamics, replay of recorded episodes, the sim-to-sim report.

The test server's world is the velocity model (no drag by default) stepped every 3 ms: these
tests prove that the tools recover, reproduce and compare what a simulator flies, not how well
the velocity model matches Unreal.
"""

import json
import math
import re

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from rlplat.airsim import main as airsim_main
from rlplat.envs.airsim import make_settings, vehicle_names
from rlplat.envs.airsim.client import AirSimError
from rlplat.envs.airsim.recording import (
    COLUMNS,
    Recorder,
    read_recording,
    recording_csv,
    replay,
    write_recording_csv,
)
from rlplat.envs.airsim.testserver import TestServer, write_recording
from rlplat.envs.dynamics import VelocityDynamics
from rlplat.errors import ConfigError
from rlplat.experiment.airsim_tools import calibrate_command, replay_command, sim2sim_command
from rlplat.experiment.config import compose_config
from rlplat.experiment.schema import validate_train_config

pytest.importorskip("cosysairsim")

# Spawn points away from the origin: every state crosses a vehicle's own frame.
SPAWN_ENU = {"Attacker": (30.0, -20.0, 0.0), "Defender": (-10.0, 5.0, 0.0)}
SETTINGS = make_settings(vehicle_names(1, 1), SPAWN_ENU)
# The test server's physics, not the velocity defaults (tau_xy 0.9, a_xy_max 6.3, tau_z 0.08,
# a_down_max 4.8, drag 0.0066 and 0.135).
SERVER = {"tau_xy": 0.6, "a_xy_max": 4.0, "tau_z": 0.15, "a_down_max": 3.5, "drag_xy": 0.01}
# dynamics=velocity as the server flies without drag: its constants and its 3 ms sub-step.
AS_SERVER = (
    *(f"dynamics.{k}={v}" for k, v in SERVER.items() if k != "drag_xy"),
    "dynamics.drag_xy=0",
    "dynamics.drag_z=0",
    "dynamics.physics_dt=0.003",
)
PERIOD = 0.1


def server(**physics) -> TestServer:
    return TestServer(SETTINGS, **{**SERVER, **physics})


def endpoint(srv: TestServer) -> str:
    return f"dynamics.endpoints=[{srv.address}]"


# Calibration --------------------------------------------------------------------------------


def test_calibrate_recovers_the_servers_constants_into_a_usable_dynamics_file(tmp_path):
    out = tmp_path / "conf" / "dynamics" / "velocity_fit.yaml"
    steps = tmp_path / "steps.csv"
    # Two amplitudes of the 5 m/s max speed, both directions, x, y and z: 12 step responses.
    plan = ("amplitudes=[0.5,1.0]", "hold_s=2.5", "rest_s=0.5", "settle_s=0.2")
    with server() as srv:
        srv.start_recording()
        message = calibrate_command([endpoint(srv), f"out={out}", f"record={steps}", *plan])
        calls = [r for r in srv.take_recording() if "call" in r]
    # Lock step: one continue of one control period per state read, the simulation paused.
    continues = [c["params"] for c in calls if c["call"] == "simContinueForTime"]
    assert len(continues) == 12 * 32 and all(p == [PERIOD] for p in continues)
    assert str(out) in message and "dynamics=velocity_fit" in message

    # Recovered: time constants and acceleration limits within 1 %, drag within 0.001.
    node = OmegaConf.load(out)
    for key in ("tau_xy", "a_xy_max", "tau_z", "a_down_max"):
        assert node[key] == pytest.approx(SERVER[key], rel=0.01), key
    assert node.drag_xy == pytest.approx(SERVER["drag_xy"], abs=1e-3)
    assert node.drag_z == pytest.approx(0.0, abs=1e-3)
    # a_up_max: the server's equals the configured one, so the steps cannot tell them apart.
    assert node.a_up_max == 6.9
    assert (node.physics_dt, node.mass, node.name) == (0.05, 1.0, "velocity")

    # A complete conf/dynamics file with its provenance, usable as dynamics=velocity_fit.
    text = out.read_text()
    velocity = OmegaConf.load("conf/dynamics/velocity.yaml")
    assert list(node) == list(velocity)
    assert f"the simulator at {srv.address} (vehicle Attacker)" in text
    assert "Command: python -m rlplat.airsim calibrate" in text and "RMS residual" in text
    assert not re.search(r"\d{4}-\d\d-\d\d|\d\d:\d\d:\d\d", text)  # no date: reproducible
    cfg = compose_config(
        "train", [f"hydra.searchpath=[file://{tmp_path / 'conf'}]", "dynamics=velocity_fit"]
    )
    validate_train_config(cfg)
    assert cfg.dynamics.tau_xy == node.tau_xy

    # The recorded step responses replay through the fitted model within centimetres.
    episodes = read_recording(steps)
    assert len(episodes) == 12 and {e.name for e in episodes} >= {"x+2.5", "z-5"}
    fitted = {k: v for k, v in node.items() if k != "name"}
    check = replay(episodes, lambda d: VelocityDynamics(num_envs=1, num_drones=d, **fitted))
    assert check.summary()["all"]["max_m"] < 0.01


def test_calibrate_on_whole_physics_ticks_fits_each_step_at_the_time_it_ran(tmp_path):
    # AirSim steps whole 3-ms ticks: the steps run 0.102, 0.099, 0.099, ... s for 0.1 s (the
    # same from every placement), and each is simulated at what it ran.
    out = tmp_path / "fit.yaml"
    plan = ("amplitudes=[0.5,1.0]", "hold_s=2.5", "rest_s=0.5", "settle_s=0.2")
    with server(whole_ticks=True) as srv:
        calibrate_command([endpoint(srv), f"out={out}", f"record={tmp_path / 'steps.csv'}", *plan])
    periods = read_recording(tmp_path / "steps.csv")[0].periods
    assert {round(float(t), 6) for t in periods} == {0.099, 0.102}
    node = OmegaConf.load(out)
    for key in ("tau_xy", "a_xy_max", "tau_z", "a_down_max"):
        assert node[key] == pytest.approx(SERVER[key], rel=0.01), key


def test_calibrate_flies_the_first_listed_vehicle_and_refuses_a_list_that_is_none(tmp_path):
    out = tmp_path / "fit.yaml"
    with pytest.raises(ConfigError, match=r"^dynamics\.vehicles: must be null or a list of"):
        calibrate_command(["dynamics.endpoints=[127.0.0.1:1]", "dynamics.vehicles=Drone1"])
    plan = ("amplitudes=[1.0]", "axes=[x]", "hold_s=1.0", "rest_s=0.5", "settle_s=0.2")
    with server() as srv:
        calibrate_command([endpoint(srv), "dynamics.vehicles=[Defender,Attacker]", f"out={out}",
                           *plan])  # fmt: skip
    assert f"the simulator at {srv.address} (vehicle Defender)" in out.read_text()


def test_calibrate_refuses_to_fit_from_where_the_drone_was_not_placed(tmp_path):
    out = tmp_path / "fit.yaml"
    with server() as srv:  # a simulator that never applies a pose: the drone stays at spawn
        args, _ = srv._methods["simSetVehiclePose"]
        srv._methods["simSetVehiclePose"] = (args, lambda *_: None)
        with pytest.raises(AirSimError) as info:
            calibrate_command([endpoint(srv), f"out={out}", "axes=[x]", "amplitudes=[1.0]"])
    message = str(info.value)
    assert re.match(r"calibrate: Attacker reads \d+\.\d\d m from where it was placed", message)
    assert "step test x+5" in message and "\n" not in message
    assert not out.exists()


def test_calibrate_fits_a_recording_offline_and_keeps_what_it_cannot_see(tmp_path):
    # Horizontal steps only, within the acceleration limit: tau_xy is fitted; a_xy_max is
    # never reached and every vertical constant is unseen, so they are kept.
    steps = tmp_path / "steps.csv"
    plan = ("axes=[x]", "amplitudes=[0.3]", "hold_s=3.0", "rest_s=0.5", "settle_s=0.2")
    with server(a_xy_max=20.0, drag_xy=0.0) as srv:
        calibrate_command([endpoint(srv), f"out={tmp_path / 'a.yaml'}", f"record={steps}", *plan])
    out = tmp_path / "b.yaml"
    calibrate_command([f"recording={steps}", f"out={out}", "velocity.drag_xy=0.0"])
    node = OmegaConf.load(out)
    assert node.tau_xy == pytest.approx(0.6, rel=0.01)
    kept = (node.a_xy_max, node.drag_xy, node.tau_z, node.a_up_max, node.a_down_max, node.drag_z)
    assert kept == (6.3, 0.0, 0.08, 6.9, 4.8, 0.135)
    assert f"against the recording {steps}" in " ".join(out.read_text().replace("#", "").split())


def test_calibrate_without_a_simulator_is_one_line_naming_the_address(tmp_path, capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "velocity_calibrated.yaml"
    with pytest.raises(SystemExit) as info:
        airsim_main(["calibrate", f"dynamics.endpoints=[127.0.0.1:{port}]", f"out={out}"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: no simulator at 127.0.0.1:{port}")
    assert not out.exists()
    with pytest.raises(ConfigError, match=r"^dynamics\.endpoints: 'nohost' is not host:port"):
        calibrate_command(["dynamics.endpoints=[nohost]", f"out={out}"])
    with pytest.raises(ConfigError, match=r"^altitude: 10 m leaves no room"):
        calibrate_command(["altitude=10", f"out={out}"])


def test_a_tool_refuses_what_it_cannot_write_or_read_before_any_work(
    tiny_run_dir, tmp_path, capsys
):
    import socket

    with socket.socket() as s:  # nothing listens there: any flight would fail on it first
        s.bind(("127.0.0.1", 0))
        nowhere = f"dynamics.endpoints=[127.0.0.1:{s.getsockname()[1]}]"
    folder = tmp_path / "a_folder"
    folder.mkdir()
    cases = [
        (["settings", "out=/proc/rlplat/s.json"], r"out: cannot write to /proc/rlplat: "),
        (["settings", f"out={folder}"], rf"out: cannot write the file {folder}: it is a folder$"),
        (["settings", f"out={tmp_path / 's.json'}", "seed=${nope}"],
         r"seed: Interpolation key 'nope' not found$"),
        (["settings", f"out={tmp_path / 's.json'}", "scenari=pursuit_2v1"],
         r"scenari: no such setting \(did you mean scenario or scenarios_dir\?\)$"),
        (["serve", "--port", "0", "--host", "no.such.host.invalid"],
         r"test server could not listen on no\.such\.host\.invalid:0: "),
        (["calibrate", nowhere, "out=/proc/rlplat/v.yaml"], r"out: cannot write to /proc/rlplat"),
        (["calibrate", nowhere, f"out={tmp_path / 'v.yaml'}", "record=/proc/rlplat/r.csv"],
         r"record: cannot write to /proc/rlplat"),
        (["sim2sim", f"run_dir={tiny_run_dir}", nowhere, "attackers=abc"],
         r"attackers: must be an integer >= 1, got 'abc'$"),
        # A value no run would take is refused by settings and serve too, not written down.
        (["settings", f"out={tmp_path / 's.json'}", "algo.gamma=abc"],
         r"algo\.gamma: must be a finite number in \[0, 1\), got 'abc'$"),
        (["serve", "--port", "0", "env.control_period=-1"], r"env\.control_period: must be "),
        (["settings", f"out={tmp_path / 's.json'}", "dynamics=airsim", "dynamics.endpoints=null"],
         r"dynamics\.endpoints: must be a non-empty list of host:port, got None$"),
        # replay names its own rule first, and its out= before it reads anything.
        (["replay", f"recording={tmp_path / 'r.csv'}", "dynamics=airsim"],
         r"dynamics: replay flies an embedded model"),
        (["replay", f"recording={tmp_path / 'r.csv'}", "out=/proc/rlplat/r.csv"],
         r"out: cannot write to /proc/rlplat"),
    ]  # fmt: skip
    for args, message in cases:
        with pytest.raises(SystemExit) as info:
            airsim_main(args)
        err = capsys.readouterr().err.strip().splitlines()
        assert info.value.code == 2, args
        assert len(err) == 1 and re.match("error: " + message, err[0]), (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_folder"]  # nothing written


# Recordings and replay ----------------------------------------------------------------------


def fly_random(srv: TestServer, steps: int, seed: int = 0):
    """Two drones under random commands (a new one every 0.5 s) from rest, lock step."""
    from rlplat.envs.airsim.dynamics import AirSimDynamics

    sim = AirSimDynamics(num_envs=1, num_drones=2, endpoints=[srv.address], timeout_s=2.0)
    start = torch.tensor([[[3.0, -4.0, 25.0], [-6.0, 2.0, 30.0]]])
    gen = torch.Generator().manual_seed(seed)
    try:
        sim.reset(torch.tensor([True]), start, torch.zeros_like(start), torch.full((1, 2), 5.0))
        for k in range(steps):
            if k % 5 == 0:
                command = (torch.rand(1, 2, 3, generator=gen) - 0.5) * 12.0  # some clipped
            sim.advance(command, PERIOD)
    finally:
        sim.close()


def test_replay_of_a_server_recording_matches_the_servers_constants_and_not_the_defaults(
    tmp_path,
):
    with server(drag_xy=0.0) as srv:
        srv.start_recording()
        fly_random(srv, 60)
        path = write_recording(tmp_path / "run.jsonl", srv.take_recording())
    episodes = read_recording(path)
    assert len(episodes) == 1 and episodes[0].vehicles == ["Attacker", "Defender"]
    assert episodes[0].steps == 59  # the first command precedes the first recorded state
    assert np.allclose(episodes[0].periods, PERIOD)

    table = replay_command([f"recording={path}", *AS_SERVER])
    rows = (tmp_path / "run.replay.csv").read_text().splitlines()
    assert len(rows) == 1 + 59 * 2 and rows[0].startswith("episode,step,t_s,vehicle,error_m")
    errors = np.array([float(r.split(",")[4]) for r in rows[1:]])
    # With the server's constants: within a centimetre over 6 s (different sub-steps: 34 of
    # 2.94 ms against 33 of 3 ms and one of 1 ms, float32 positions).
    assert errors.max() < 0.01
    assert "Attacker" in table and "Defender" in table and "p95 m" in table
    # With the velocity defaults (tau_xy 0.9 s, a_xy_max 6.3, drag): metres apart.
    replay_command([f"recording={path}", f"out={tmp_path / 'defaults.csv'}"])
    rows = (tmp_path / "defaults.csv").read_text().splitlines()[1:]
    default_errors = np.array([float(r.split(",")[4]) for r in rows])
    assert default_errors.max() > 0.5 and default_errors.mean() > 20 * errors.mean()


def test_a_recording_csv_round_trips_and_a_recorder_records_what_a_model_flies(tmp_path):
    model = VelocityDynamics(num_envs=2, num_drones=2)
    recorder = Recorder(model, names=["A", "B"], env_index=1)
    start = torch.tensor([[0.0, 0.0, 10.0], [5.0, 0.0, 12.0]]).expand(2, 2, 3)
    model.reset(
        torch.ones(2, dtype=torch.bool), start, torch.zeros(2, 2, 3), torch.full((2, 2), 3.0)
    )
    for _ in range(4):
        model.advance(torch.tensor([4.0, -1.0, 0.5]).expand(2, 2, 3), PERIOD)  # 4 > 3: clipped
    model.reset(torch.tensor([True, False]), start, torch.zeros(2, 2, 3), torch.ones(2, 2))
    model.advance(torch.zeros(2, 2, 3), PERIOD)  # env 1 still in its first episode
    last = model.position[1].double().numpy()
    recorder.detach()
    model.advance(torch.zeros(2, 2, 3), PERIOD)  # not recorded
    (ep,) = recorder.episodes(["first"])
    assert ep.steps == 5 and ep.vehicles == ["A", "B"]
    assert np.allclose(ep.command[0, 0], [3.0, -1.0, 0.5])  # as clipped
    assert np.allclose(ep.position[-1], last) and np.allclose(ep.t, np.arange(6) * PERIOD)
    path = write_recording_csv(tmp_path / "rec.csv", [ep])
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    (back,) = read_recording(path)
    assert back.name == "first" and back.vehicles == ["A", "B"]
    for key in ("t", "position", "velocity", "command", "max_speed"):
        np.testing.assert_allclose(getattr(back, key), getattr(ep, key), rtol=1e-7, atol=1e-9)
    # Replaying a model's own recording through the same model is exact.
    same = replay([back], lambda d: VelocityDynamics(num_envs=1, num_drones=d))
    assert same.summary()["all"]["max_m"] < 1e-5
    assert recording_csv([ep]).count("\n") == 1 + 6 * 2


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("a,b\n1,2\n", "is not a recording CSV"),
        (",".join(COLUMNS) + "\ne,0,0,A,0,0,1,0,0,0,x,0,0,\ne,1,0.1,A,0,0,1,0,0,0,,,,\n", "'e'"),
    ],
)
def test_a_bad_recording_is_one_line_naming_the_file(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        read_recording(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    with pytest.raises(ConfigError, match=r"^recording: replay needs recording=FILE"):
        replay_command([])


# Sim-to-sim ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_run_dir(scenarios, tiny_run, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("sim2sim") / "run"
    # On the embedded velocity model, with the paper's interface: its command is a smooth
    # function of the state. attacker_v4 adds proportional navigation, whose per-axis
    # saturation and largest-gap time to go switch on the last bits of a position, so the two
    # simulators' float32 and float64 states part by centimetres instead of micrometres.
    tiny_run(scenarios, run_dir, "drone=attacker_v3")
    return run_dir


@pytest.mark.slow
def test_sim2sim_on_the_servers_constants_agrees_and_reports_per_scenario(tiny_run_dir, tmp_path):
    out = tmp_path / "s2s"
    with TestServer(SETTINGS) as srv:  # the velocity defaults, without drag
        message = sim2sim_command(
            [
                f"run_dir={tiny_run_dir}", endpoint(srv), f"out={out}",
                "reference.drag_xy=0", "reference.drag_z=0", "reference.physics_dt=0.003",
            ]
        )  # fmt: skip
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenarios"] == 16 and summary["split"] == "test"
    assert summary["outcomes_differing"] == 0 and summary["differing_scenarios"] == []
    # The same trajectories within a centimetre (float32 positions, different sub-steps).
    assert summary["max_gap_m"] < 0.01
    assert summary["reference_capture_rate"] == summary["airsim_capture_rate"]
    assert "0 outcomes differ" in message and "largest position gap" in message
    rows = (out / "scenarios.csv").read_text().splitlines()
    assert len(rows) == 1 + 16 and "max_gap_m" in rows[0] and "airsim_outcome" in rows[0]
    report = (out / "report.md").read_text()
    assert "Outcomes differing: 0 of 16" in report and "Largest position gap" in report

    # What the AirSim leg flew, per scenario: it replays through the same model exactly, and
    # through the velocity defaults (tau 0.9 s, drag) metres apart.
    recording = out / "airsim_recording.csv"
    episodes = read_recording(recording)
    assert [e.name for e in episodes] == [r.split(",")[0] for r in rows[1:]]
    matched = replay_command(
        [f"recording={recording}", "dynamics.drag_xy=0", "dynamics.drag_z=0",
         "dynamics.physics_dt=0.003", f"out={tmp_path / 'same.csv'}"]
    )  # fmt: skip
    assert matched.splitlines()[-2].split()[0] == "all"
    same = float(matched.splitlines()[-2].split()[-1])
    assert same < 0.01
    table = replay_command([f"recording={recording}", f"out={tmp_path / 'defaults.csv'}"])
    assert float(table.splitlines()[-2].split()[-1]) > 10 * max(same, 1e-3)


@pytest.mark.slow
def test_sim2sim_against_whole_physics_ticks_agrees_with_a_reference_stepped_in_ticks(
    tiny_run_dir, tmp_path
):
    # A simulator that runs whole 3-ms ticks (as AirSim does) flies 0.102 s, 0.099 s, ... a
    # step: a reference that flies 0.1 s parts from it by millimetres a step, one that flies
    # the same ticks (reference_tick) agrees as with the exact server.
    same = ["reference.drag_xy=0", "reference.drag_z=0", "reference.physics_dt=0.003"]
    summaries = {}
    with TestServer(SETTINGS, whole_ticks=True) as srv:
        for name, extra in (("period", []), ("ticks", ["reference_tick=0.003"])):
            out = tmp_path / name
            sim2sim_command([f"run_dir={tiny_run_dir}", endpoint(srv), f"out={out}",
                             "record=false", *same, *extra])  # fmt: skip
            summaries[name] = json.loads((out / "summary.json").read_text())
    period, ticks = summaries["period"], summaries["ticks"]
    assert period["reference_tick"] is None and ticks["reference_tick"] == 0.003
    assert ticks["outcomes_differing"] == 0 and ticks["max_gap_m"] < 0.01
    assert period["median_max_gap_m"] > 10 * max(ticks["median_max_gap_m"], 1e-4)
    assert "stepped in whole ticks of 0.003 s" in (tmp_path / "ticks" / "report.md").read_text()
    bad = r"^reference_tick: must be a finite number in \(0, 0\.1\], got 0\.5 \(the run's"
    with pytest.raises(ConfigError, match=bad):
        sim2sim_command([f"run_dir={tiny_run_dir}", endpoint(srv), "reference_tick=0.5"])


def test_sim2sim_without_a_simulator_stops_before_the_embedded_leg(tiny_run_dir, tmp_path):
    # The reference leg flies first: a simulator not started must not cost its minutes.
    import socket
    import time

    from rlplat.envs.airsim.client import AirSimError

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out, t0 = tmp_path / "s2s", time.monotonic()
    with pytest.raises(
        AirSimError, match=rf"^dynamics.endpoints: no simulator at 127.0.0.1:{port} "
    ):
        sim2sim_command([f"run_dir={tiny_run_dir}", f"dynamics.endpoints=[127.0.0.1:{port}]",
                         "dynamics.connect_timeout_s=2", f"out={out}"])  # fmt: skip
    assert time.monotonic() - t0 < 10 and not out.exists()
    with pytest.raises(ConfigError, match=r"^out_dir: cannot write to .*: is a file"):
        sim2sim_command([f"run_dir={tiny_run_dir}", f"dynamics.endpoints=[127.0.0.1:{port}]",
                         f"out={tiny_run_dir / 'config.yaml'}"])  # fmt: skip


def test_position_gaps_count_the_steps_both_episodes_ran():
    from rlplat.experiment.sim2sim import position_gaps

    a = torch.zeros(2, 5, 2, 3)
    b = a.clone()
    b[0, 2, 1, 0] = 0.3  # episode 0, step 2, drone 1
    b[0, 4, 0, 2] = 9.0  # beyond the shorter episode: not counted
    b[1, 1:, 0, 1] = 0.1
    gaps = position_gaps(a, b, torch.tensor([3, 4]))
    assert gaps["max"].tolist() == pytest.approx([0.3, 0.1])
    assert gaps["step"].tolist() == [2, 1] and gaps["drone"].tolist() == [1, 0]
    assert gaps["mean"][0].item() == pytest.approx(0.3 / 8)  # 4 steps x 2 drones
    assert math.isclose(gaps["mean"][1].item(), 0.4 / 10, rel_tol=1e-6)


def test_sim2sim_refuses_overrides_that_are_not_the_simulators_in_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"^run_dir: sim2sim needs run_dir=DIR"):
        sim2sim_command([])
    with pytest.raises(ConfigError, match=r"^sim2sim: 'env.time_limit=5': only dynamics"):
        sim2sim_command([f"run_dir={tmp_path}", "env.time_limit=5"])
