"""``dynamics=airsim`` against the loopback AirSim test server, through the real client library.

These tests prove protocol conformance of the client side (the calls, their arguments and
timing, frames, faults, the wiring into envs, training and evaluation): the test server's
physics is a small first-order model, so nothing here says how well rlplat flies in Unreal.
"""

import json
import math
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from rlplat import make_env, make_gym_env
from rlplat.agents.checkpoint import load_checkpoint
from rlplat.envs.airsim import enu_to_ned, make_settings, vehicle_names
from rlplat.envs.airsim.client import AirSimClient, AirSimError, parse_endpoint, plain
from rlplat.envs.airsim.dynamics import AirSimDynamics
from rlplat.envs.airsim.testserver import TestServer
from rlplat.envs.dynamics import VelocityDynamics
from rlplat.envs.parallel import WorkerFault
from rlplat.errors import ConfigError
from rlplat.experiment.evaluation import evaluate_run

pytest.importorskip("cosysairsim")

REPO = Path(__file__).resolve().parent.parent
PERIOD = 0.1  # s, env.control_period
# Spawn points away from the origin (ENU world): every position crosses a vehicle's own frame.
SPAWN_ENU = {"Attacker": (30.0, -20.0, 0.0), "Defender": (-10.0, 5.0, 0.0)}
SETTINGS = make_settings(vehicle_names(1, 1), SPAWN_ENU)


def serve(**kwargs) -> TestServer:
    return TestServer(SETTINGS, **kwargs).start()


@pytest.fixture
def server():
    srv = serve()
    yield srv
    srv.stop()


def airsim(*endpoints: str, **knobs) -> list[str]:
    """The overrides of ``dynamics=airsim`` on ``endpoints`` (short waits for the tests)."""
    knobs = {"connect_timeout_s": 2.0, "timeout_s": 1.0, **knobs}
    return [
        "dynamics=airsim",
        f"dynamics.endpoints=[{','.join(endpoints)}]",
        *(f"dynamics.{k}={v}" for k, v in knobs.items()),
    ]


def airsim_env(scenarios, *endpoints: str, split="test", **knobs):
    return make_env(*airsim(*endpoints, **knobs), scenarios=scenarios, split=split,
                    num_envs=len(endpoints))  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# Wire values and addresses -----------------------------------------------------------------


def test_plain_turns_numpy_and_torch_scalars_into_python_ones():
    values = plain([np.float32(1.5), np.int64(3), torch.tensor(2.0), np.bool_(True), "x", 4])
    assert values == [1.5, 3, 2.0, True, "x", 4]
    assert [type(v) for v in values] == [float, int, float, bool, str, int]


@pytest.mark.parametrize("bad", ["foo", "127.0.0.1:0", "host:99999", ":41451", "h:p", 41451])
def test_a_bad_endpoint_is_a_one_line_error_naming_the_field(bad):
    with pytest.raises(ConfigError, match=r"^dynamics\.endpoints: .* is not host:port"):
        parse_endpoint(bad)
    assert parse_endpoint("localhost:41451") == ("localhost", 41451)


def test_importing_the_envs_does_not_import_the_client_library():
    code = (
        "import sys, rlplat.envs.pursuit, rlplat.experiment.factory, rlplat.experiment.schema\n"
        "from rlplat.envs.dynamics import DYNAMICS\n"
        "assert DYNAMICS['airsim'].__name__ == 'AirSimDynamics'\n"
        "print(sorted(m for m in sys.modules if 'airsim' in m and 'rlplat' not in m))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_calls_sent_together_go_out_in_one_write_and_the_first_failure_in_order_is_the_error(
    server,
):
    class Counted:  # the connection's socket, its sends recorded
        def __init__(self, sock) -> None:
            self.sock, self.sent = sock, []

        def send(self, data) -> int:
            self.sent.append(bytes(data))
            return self.sock.send(data)

        def __getattr__(self, name):
            return getattr(self.sock, name)

    client = AirSimClient(server.address, connect_timeout_s=2.0, timeout_s=1.0)
    stream = client._api.client._transport._sockets[0]._stream
    stream.socket = Counted(stream.socket)
    writes = stream.socket.sent
    calls = [("getMultirotorState", "Attacker"), ("getMultirotorState", "Ghost"),
             ("simGetCollisionInfo", "Ghost")]  # fmt: skip
    futures = [client.send(method, name) for method, name in calls]
    assert writes == []  # nothing goes out until something is awaited
    with pytest.raises(AirSimError) as info:
        client.gather(futures, [method for method, _ in calls], "the test")
    assert len(writes) == 1
    message = str(info.value)
    assert message.startswith(f"simulator at {server.address} refused getMultirotorState (the")
    assert "'Ghost' is not available" in message
    assert client.vehicles() == ["Attacker", "Defender"]  # the session goes on
    client.close()


class RawSimulator:
    """One connection of a hand-written msgpack-rpc server: ``reply(msgid, method, params)``
    gives the messages to send for each request (bytes go as msgpack bin), or "close" to hang
    up."""

    def __init__(self, reply) -> None:
        import threading

        self.reply = reply
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = f"127.0.0.1:{self.listener.getsockname()[1]}"
        self.thread = threading.Thread(target=self.serve, daemon=True)
        self.thread.start()

    def serve(self) -> None:
        import msgpack

        conn, _ = self.listener.accept()
        unpacker = msgpack.Unpacker(raw=False)
        with conn:
            while data := conn.recv(65536):
                unpacker.feed(data)
                for _, msgid, method, params in unpacker:
                    out = self.reply(msgid, method, params)
                    if out == "close":
                        return
                    conn.sendall(b"".join(msgpack.packb(m) for m in out))

    def close(self) -> None:
        self.thread.join(timeout=5)
        self.listener.close()


def test_notifications_and_server_requests_are_skipped_and_a_non_message_fails_at_once():
    def reply(msgid, method, params):
        if method == "ping":
            return [[1, msgid, None, True]]
        if method == "listVehicles":  # msgpack-rpc lets a server notify, or call, at will
            return [[2, "surprise", []], [0, 99, "hello", []], [1, msgid, None, ["Attacker"]]]
        return [[7, "not msgpack-rpc"]]  # anything else: not a message

    sim = RawSimulator(reply)
    client = AirSimClient(sim.address, connect_timeout_s=2.0, timeout_s=5.0)
    assert client.vehicles() == ["Attacker"]
    t0 = time.monotonic()
    with pytest.raises(AirSimError) as info:
        client.settings()
    assert time.monotonic() - t0 < 2.0  # at once, not after timeout_s
    message = str(info.value)
    assert "sent an answer that is not msgpack-rpc while waiting for getSettingsString" in message
    assert "[7, 'not msgpack-rpc']" in message and "\n" not in message
    with pytest.raises(AirSimError, match="the connection is closed"):
        client.vehicles()
    client.close()
    sim.close()


STATE = {  # a getMultirotorState answer as AirSim's rpclib adaptor packs it (the fields read)
    "kinematics_estimated": {
        "position": {"x_val": 1, "y_val": 2.5, "z_val": -3},  # integers where floats are usual
        "linear_velocity": {"x_val": 0.0, "y_val": 0.0, "z_val": 0.0},
    },
    "timestamp": 123_000_000,
}
VELOCITY = STATE["kinematics_estimated"]["linear_velocity"]


@pytest.mark.parametrize(
    ("state", "collision", "expected"),
    [
        ({**STATE, "timestamp": None}, {"has_collided": False}, "timestamp is None, not a number"),
        (
            {"kinematics_estimated": {"linear_velocity": VELOCITY}, "timestamp": 1},
            {"has_collided": False},
            "getMultirotorState for Attacker (the test) has no kinematics_estimated.position.x_val",
        ),
        (None, {"has_collided": False}, "has no kinematics_estimated.position.x_val"),
        (STATE, {}, "simGetCollisionInfo for Attacker (the test) has no has_collided flag"),
        (STATE, None, "has no has_collided flag"),
    ],
)  # fmt: skip
def test_an_answer_that_lacks_a_field_names_it_and_is_never_filled_with_a_default(
    state, collision, expected
):
    def reply(msgid, method, params):
        answers = {"ping": True, "getMultirotorState": state, "simGetCollisionInfo": collision}
        return [[1, msgid, None, answers[method]]]

    sim = RawSimulator(reply)
    client = AirSimClient(sim.address, connect_timeout_s=2.0, timeout_s=2.0)
    with pytest.raises(AirSimError) as info:
        client.read(["Attacker"], "the test")
    assert expected in str(info.value) and "\n" not in str(info.value)
    client.close()
    sim.close()


def bin_keys(d: dict) -> dict:
    """``d`` with every map key packed as msgpack bin (bytes)."""
    return {k.encode(): bin_keys(v) if isinstance(v, dict) else v for k, v in d.items()}


def test_integers_bin_strings_and_integer_keys_are_read_and_error_texts_are_one_line(caplog):
    def reply(msgid, method, params):
        answers = {
            "ping": [1, msgid, None, True],
            "listVehicles": [1, msgid, None, [b"Attacker", b"Defender"]],  # bin, not str
            "getMultirotorState": [1, msgid, None, bin_keys(STATE)],
            "simGetCollisionInfo": [1, msgid, None, {b"has_collided": 0, 7: "extra"}],
            "getSettingsString": [1, msgid, "first line\n  second line", None],
        }
        return [answers[method]]

    sim = RawSimulator(reply)
    client = AirSimClient(sim.address, connect_timeout_s=2.0, timeout_s=2.0)
    assert client.vehicles() == ["Attacker", "Defender"]
    states, hits = client.read(["Attacker"], "the test")
    assert states[0].position == (1.0, 2.5, -3.0) and states[0].timestamp_ns == 123_000_000
    assert hits == [False]
    with caplog.at_level("WARNING", logger="rlplat.envs.airsim.client"):
        assert client.settings() == {}  # a call that only checks: refused, it checks nothing
    assert "has no getSettingsString (it answered: first line second line)" in caplog.text
    client.close()
    sim.close()


def test_a_client_connects_where_no_event_loop_is_set_without_a_warning(server):
    # Where no asyncio loop was ever set, Python 3.12 and 3.13 warn when asked for the current
    # one (3.14 refuses): a client makes its thread's own, in the main thread as in any other.
    script = f"""
import threading
from rlplat.envs.airsim.client import AirSimClient

def connect_twice():  # a reconnect in the same thread
    for _ in range(2):
        client = AirSimClient({server.address!r}, connect_timeout_s=2.0, timeout_s=1.0)
        assert client.vehicles() == ["Attacker", "Defender"]
        client.close()

connect_twice()
failed = []
def worker():
    try:
        connect_twice()
    except BaseException as e:
        failed.append(repr(e))
thread = threading.Thread(target=worker)
thread.start()
thread.join(30)
assert not failed and not thread.is_alive(), failed
"""
    done = subprocess.run(
        [sys.executable, "-W", "error", "-c", script], cwd=REPO, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stderr == ""


def test_a_listener_that_hangs_up_before_answering_is_not_called_absent():
    sim = RawSimulator(lambda msgid, method, params: "close")
    with pytest.raises(AirSimError) as info:
        AirSimClient(sim.address, connect_timeout_s=2.0, timeout_s=1.0)
    message = str(info.value)
    assert message.startswith(f"{sim.address} closed the connection before answering ping")
    assert "no simulator" not in message and "\n" not in message
    sim.close()


def test_a_move_the_simulator_refuses_stops_the_step(server):
    client = AirSimClient(server.address, connect_timeout_s=2.0, timeout_s=1.0)
    client.pause(True)
    client.move_velocity("Attacker", (1.0, 0.0, 0.0), 0.2)  # no API control taken: refused
    client.continue_for(0.1, "the test")
    with pytest.raises(AirSimError) as info:
        client.read(["Attacker"], "the test")
    message = str(info.value)
    assert message.startswith(f"simulator at {server.address} refused moveByVelocity for Attacker")
    assert "requestApiControl()" in message and "\n" not in message
    client.take_control("Attacker")
    client.move_velocity("Attacker", (1.0, 0.0, 0.0), 0.2)
    client.continue_for(0.1, "the test")
    (state,), _ = client.read(["Attacker"], "the test")  # a later move that flies: no error
    assert state.velocity[0] > 0.0
    # Integers given by a caller go out as the floats AirSim's parameters are.
    server.start_recording()
    client.move_velocity("Attacker", (1, 0, 0), 1)
    client.set_position("Attacker", (0, 0, -2))
    client.continue_for(0.1, "the test")
    calls = {r["call"]: r["params"] for r in server.take_recording() if "call" in r}
    assert [type(x) for x in calls["moveByVelocity"][:4]] == [float] * 4
    assert all(type(v) is float for v in calls["simSetVehiclePose"][0]["position"].values())
    client.close()


# The env on one simulator ------------------------------------------------------------------


def test_protocol_conformance_check_env_specs_and_a_rollout(server, scenarios):
    env = airsim_env(scenarios, server.address)
    assert env.batch_size == torch.Size([1])
    check_env_specs(env, seed=0)
    server.start_recording()
    td = env.rollout(20, break_when_any_done=False)
    calls = [r for r in server.take_recording() if "call" in r]
    assert td.batch_size == torch.Size([1, 20]) and torch.isfinite(td["next", "positions"]).all()
    moves = [c["params"] for c in calls if c["call"] == "moveByVelocity"]
    continues = [c["params"] for c in calls if c["call"] == "simContinueForTime"]
    assert len(continues) == 20 and len(moves) == 40  # every drone commanded every step
    assert all(p == [PERIOD] for p in continues)
    assert all(type(x) is float for p in moves for x in p[:4])  # plain floats on the wire
    assert all(p[3] == pytest.approx(PERIOD + 0.1) for p in moves)  # outlasts the step
    assert {p[-1] for p in moves} == {"Attacker", "Defender"}
    assert server.snapshot()["paused"]
    env.close()


def test_frames_end_to_end_drones_spawned_away_from_the_origin_start_where_the_scenario_says(
    server, scenarios
):
    env = airsim_env(scenarios, server.address)
    td = env.reset()
    index = int(td["scenario_index"])
    sc = env.scenarios[index]
    want_enu = torch.cat([sc["attacker_start"], sc["defender_start"]])  # (2, 3) world ENU
    torch.testing.assert_close(td["positions"][0], want_enu, atol=1e-4, rtol=0)
    world = server.snapshot()["vehicles"]  # the server's own truth: NED world
    for i, name in enumerate(("Attacker", "Defender")):
        assert world[name]["position"] == pytest.approx(enu_to_ned(want_enu[i].tolist()), abs=1e-4)
    # Flying east (ENU +x) is flying NED +y in the server's world, from each spawn point alike.
    before = server.snapshot()["vehicles"]
    for _ in range(10):
        env.dynamics.advance(torch.tensor([[[2.0, 0.0, 0.0], [2.0, 0.0, 0.0]]]), PERIOD)
    after = server.snapshot()["vehicles"]
    for i, name in enumerate(("Attacker", "Defender")):
        moved = np.subtract(after[name]["position"], before[name]["position"])
        assert moved[1] > 0.5 and abs(moved[0]) < 1e-6 and abs(moved[2]) < 1e-6
        got = env.dynamics.position[0, i].tolist()
        assert got == pytest.approx(list(enu_to_ned(after[name]["position"])), abs=1e-4)
    env.close()


def test_same_commands_fly_the_same_trajectory_as_dynamics_velocity_with_the_servers_constants(
    server,
):
    # The test server's world is the velocity model (drag 0 by default) sub-stepped at 3 ms; the
    # embedded model with the same constants splits each 0.1 s period into 34 equal sub-steps
    # instead of 33 of 3 ms and one of 1 ms. The first-order part is integrated exactly either
    # way, so the trajectories differ only by the trapezoidal position update over different
    # sub-steps (O(dt^2) per step, < 1e-5 m here) and float32 rounding of positions of ~30 m
    # (~4e-6 m a step): 1 mm over 6 s of flight bounds both with a wide margin.
    names = dict(num_envs=1, num_drones=2)
    sim = AirSimDynamics(**names, endpoints=[server.address], timeout_s=1.0)
    ref = VelocityDynamics(**names, physics_dt=0.003, drag_xy=0.0, drag_z=0.0)
    start = torch.tensor([[[3.0, -4.0, 12.0], [-6.0, 2.0, 20.0]]])
    for dyn in (sim, ref):
        dyn.reset(torch.tensor([True]), start, torch.zeros_like(start), torch.full((1, 2), 4.0))
    gen = torch.Generator().manual_seed(0)
    gap = 0.0
    for step in range(60):
        if step % 10 == 0:  # a new command every second, some beyond max_speed (clipped)
            command = (torch.rand(1, 2, 3, generator=gen) - 0.5) * 12.0
        for dyn in (sim, ref):
            dyn.advance(command, PERIOD)
        gap = max(gap, (sim.position - ref.position).abs().max().item())
        assert sim.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
    assert gap < 1e-3
    assert (sim.position - start).norm(dim=-1).min() > 2.0  # they did fly
    sim.close()


def test_two_attackers_fly_as_numbered_vehicles(tmp_path, write_small_set):
    team = write_small_set(tmp_path / "2v1", "scenario=pursuit_2v1")
    names = vehicle_names(2, 1)
    assert names == ["Attacker", "Attacker2", "Defender"]
    spawn = {n: (5.0 * i, 0.0, 0.0) for i, n in enumerate(names)}
    with TestServer(make_settings(names, spawn)) as srv:
        env = airsim_env(team, srv.address)
        check_env_specs(env, seed=0)
        td = env.reset()
        sc = env.scenarios[int(td["scenario_index"])]
        starts = torch.cat([sc["attacker_start"], sc["defender_start"]])
        torch.testing.assert_close(td["positions"][0], starts, atol=1e-4, rtol=0)
        world = srv.snapshot()["vehicles"]
        for i, name in enumerate(names):
            assert world[name]["position"] == pytest.approx(
                enu_to_ned(starts[i].tolist()), abs=1e-4
            )
        env.close()


def test_a_team_flies_vehicles_named_in_a_list(tmp_path, write_small_set):
    team = write_small_set(tmp_path / "2v1", "scenario=pursuit_2v1")
    names = ["Drone1", "Drone2", "Drone3"]  # attackers first, then the defender
    spawn = {n: (5.0 * i, 0.0, 0.0) for i, n in enumerate(names)}
    with TestServer(make_settings(names, spawn)) as srv:
        env = airsim_env(team, srv.address, vehicles="[Drone1,Drone2,Drone3]")
        td = env.reset()
        sc = env.scenarios[int(td["scenario_index"])]
        starts = torch.cat([sc["attacker_start"], sc["defender_start"]])
        world = srv.snapshot()["vehicles"]
        for i, name in enumerate(names):
            assert world[name]["position"] == pytest.approx(
                enu_to_ned(starts[i].tolist()), abs=1e-4
            )
        env.close()
        # As many names as drones, checked before any call to the simulator.
        srv.start_recording()
        with pytest.raises(ConfigError, match=r"^dynamics.vehicles: must name the 2 attacker"):
            airsim_env(team, srv.address, vehicles="[Drone1,Drone3]")
        assert srv.take_recording() == []
    # Not a list of distinct names: refused by the config's check.
    with pytest.raises(ConfigError, match=r"^dynamics.vehicles: must be null or a list"):
        airsim_env(team, "127.0.0.1:1", vehicles="[Drone1,Drone1,Drone2]")


def test_the_gymnasium_adapter_flies_on_the_simulator(server, scenarios):
    env = make_gym_env(*airsim(server.address), scenarios=scenarios, split="test")
    obs, _ = env.reset(seed=0)
    for _ in range(5):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
    assert obs.shape == env.observation_space.shape and np.isfinite(obs).all()
    assert server.snapshot()["paused"]
    env.close()


# Timing -----------------------------------------------------------------------------------


def test_a_step_off_the_control_period_is_an_error_or_a_warning(scenarios, caplog):
    # The simulator runs twice as fast as its settings say: each step advances 0.2 s.
    with TestServer(SETTINGS, clock_speed=2.0) as srv:
        env = airsim_env(scenarios, srv.address)
        env.reset()
        with pytest.raises(AirSimError, match=r"advanced 0\.2000 s of sim time.*period is 0\.1"):
            env.rand_step()
        env.close()
        env = airsim_env(scenarios, srv.address, on_time_mismatch="warn")
        env.reset()
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.dynamics"):
            env.rand_step()
            env.rand_step()
        assert sum("advanced 0.2000 s" in r.message for r in caplog.records) == 2
        env.close()


def first_step_continue(env, srv) -> list:
    """The arguments of the simContinueForTime of ``env``'s first step after a reset."""
    env.reset()
    srv.start_recording()
    env.rand_step()
    calls = [r for r in srv.take_recording() if r.get("call") == "simContinueForTime"]
    return calls[0]["params"]


def test_clock_speed_asks_for_period_over_k_of_the_simulators_wall_clock(scenarios):
    settings = {**SETTINGS, "ClockSpeed": 4.0}
    with TestServer(settings) as srv:
        env = airsim_env(scenarios, srv.address, clock_speed=4.0)
        assert first_step_continue(env, srv) == [pytest.approx(PERIOD / 4.0)]
        assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        env.close()
        with pytest.raises(ConfigError, match=r"dynamics.clock_speed: 1, .* ClockSpeed 4"):
            airsim_env(scenarios, srv.address)


def test_a_fractional_clock_speed_above_1_is_stepped_at_its_whole_part(scenarios, caplog):
    # AirSim runs ClockSpeed 2.5 at 2: a step asks for half the period, and says so once.
    with TestServer({**SETTINGS, "ClockSpeed": 2.5}) as srv:
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.dynamics"):
            env = airsim_env(scenarios, srv.address, clock_speed=2.5)
        assert [r.message for r in caplog.records if "clock_speed 2.5" in r.message] == [
            "dynamics.clock_speed 2.5: AirSim runs a ClockSpeed above 1 at its whole part, 2; "
            "each step asks for control_period / 2 of its wall clock"
        ]
        assert first_step_continue(env, srv) == [pytest.approx(PERIOD / 2.0)]
        assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        env.close()


def test_a_step_that_runs_short_is_run_on_for_the_time_it_lacks(scenarios, caplog):
    # AirSim's simContinueForTime counts wall time; on a loaded machine its physics ticks run
    # long and the step advances less sim time than asked. The step is run on, not refused.
    with TestServer(SETTINGS, continue_runs=0.6) as srv:
        env = airsim_env(scenarios, srv.address)  # on_time_mismatch: error, tolerance 0.02 s
        env.reset()
        srv.start_recording()
        ran = []
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.dynamics"):
            for _ in range(3):
                env.rand_step()
                ran.append(env.dynamics.last_advance_s)
                # within the tolerance of the env's clock: the next step asks for the rest
                assert abs(sum(ran) - len(ran) * PERIOD) <= 0.02
        assert ran[0] == pytest.approx(0.084, abs=1e-6)  # 0.06 s, then 0.6 of the 0.04 it lacks
        assert ran[1] == pytest.approx(0.4 * 0.6 * 0.116 + 0.6 * 0.116, abs=1e-6)  # 0.016 more
        calls = [r.get("call") for r in srv.take_recording()]
        assert calls.count("simContinueForTime") == 6
        assert caplog.text.count("a step of 0.1 s ran 0.0400 s short") == 1  # once
        env.close()
    with TestServer(SETTINGS, continue_runs=0.1) as srv:  # three more runs leave it short
        env = airsim_env(scenarios, srv.address)
        env.reset()
        with pytest.raises(AirSimError, match=r"a step advanced 0\.0344 s of sim time"):
            env.rand_step()
        env.close()


def test_a_simulator_that_runs_whole_physics_ticks_keeps_to_the_envs_clock(scenarios):
    # AirSim ends a continue at the first 3-ms physics tick at or past its time: 0.102 s for
    # 0.1 s. Each step asks for the period less what the clock has run over, so the episode's
    # sim time stays within a tick of steps x period instead of drifting 2 % a step.
    with TestServer(SETTINGS, whole_ticks=True) as srv:
        env = airsim_env(scenarios, srv.address)
        env.reset()
        dyn = env.dynamics
        srv.start_recording()
        ran = []
        for _ in range(30):
            dyn.advance(torch.zeros(1, dyn.num_drones, 3), PERIOD)
            ran.append(dyn.last_advance_s)
        asked = [r["params"][0] for r in srv.take_recording()
                 if r.get("call") == "simContinueForTime"]  # fmt: skip
        assert asked[:3] == [pytest.approx(PERIOD), pytest.approx(0.098), pytest.approx(0.099)]
        assert {round(t, 6) for t in ran} == {0.099, 0.102}
        assert abs(sum(ran) - 30 * PERIOD) <= 0.003 + 1e-9
        env.close()


def test_a_simulator_whose_continue_answers_before_its_time_has_run_is_waited_for(
    scenarios, caplog
):
    # Older AirSim's continueForTime starts the simulation and answers at once; the step
    # reads the drones when simIsPaused says the period has run, and then only.
    settings = {**SETTINGS, "ClockType": "ScalableClock"}
    with TestServer(settings, realtime=True, continue_answers_at_once=True) as srv:
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.dynamics"):
            env = airsim_env(scenarios, srv.address)
        assert "ClockType ScalableClock keeps time while paused" in caplog.text
        env.reset()
        srv.start_recording()
        for _ in range(3):
            env.rand_step()
            assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        calls = [r.get("call") for r in srv.take_recording()]
        assert calls.count("simContinueForTime") == 3 and "simIsPaused" in calls
        env.close()


def test_an_early_answering_simulator_without_simispaused_is_read_until_its_step_has_run(
    scenarios, caplog
):
    # Nothing tells when the simulation pauses again: the drones are read until the step's
    # sim time has run (within dynamics.timeout_s), not refused as a step of 0 s.
    with TestServer(SETTINGS, realtime=True, continue_answers_at_once=True) as srv:
        del srv._methods["simIsPaused"]
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.client"):
            env = airsim_env(scenarios, srv.address)
            env.reset()
            for _ in range(3):
                env.rand_step()
                assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        assert caplog.text.count("has no simIsPaused") == 1
        env.close()


class _ReadBeforeItRan:
    """A client whose simContinueForTime answered at once and whose simulator was read before
    it ran (the drones as before the step, with a contact whose flag that read clears), then
    paused again before simIsPaused was asked."""

    def __init__(self, client):
        self._client, self._last, self._stale = client, None, False

    def __getattr__(self, name):
        return getattr(self._client, name)

    def continue_for(self, seconds, what):
        self._client.continue_for(seconds, what)
        self._stale = True

    def wait_paused(self, what):
        return False  # paused again when asked: it never saw the simulation run

    def read(self, names, what):
        if self._stale:
            self._stale = False
            return self._last[0], [True] + [False] * (len(names) - 1)
        self._last = self._client.read(names, what)
        return self._last


def test_a_read_before_the_simulator_ran_is_read_again_and_keeps_its_collision(scenarios):
    with TestServer(SETTINGS) as srv:
        env = airsim_env(scenarios, srv.address)
        env.dynamics.client = _ReadBeforeItRan(env.dynamics.client)
        td = env.rand_step(env.reset())
        assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        assert env.dynamics.collided.tolist() == [[True, False]]  # the first read's contact
        assert td["next", "collided"].tolist() == [[True, False]]  # and the step's output's
        assert td["collided"].tolist() == [[False, False]]  # placed at the reset: cleared
        assert not torch.equal(td["next", "positions"], td["positions"])
        env.close()


@pytest.mark.parametrize("stays", [False, True], ids=["cleared-on-read", "kept"])
def test_a_contact_is_reported_in_the_steps_it_lasts_whether_or_not_the_flag_clears(stays):
    # Cosys-AirSim clears the collision flag it reports; AirSim's getCollisionInfo keeps it set
    # (with the contact's time_stamp) until the next contact: both read the same.
    with TestServer(SETTINGS, collision_stays=stays) as srv:
        dyn = AirSimDynamics(num_envs=1, num_drones=2, endpoints=[srv.address],
                             connect_timeout_s=2.0, timeout_s=1.0)  # fmt: skip
        start = torch.tensor([[[0.0, 0.0, 10.0], [0.3, 0.0, 10.0]]])  # within the 0.5-m radius
        dyn.reset(torch.ones(1, dtype=torch.bool), start, torch.zeros(1, 2, 3),
                  torch.full((1, 2), 5.0))  # fmt: skip
        apart = torch.tensor([[[-5.0, 0.0, 0.0], [5.0, 0.0, 0.0]]])
        hits, gaps = [], []
        for command in [apart] * 3 + [-apart] * 8:  # part, then meet again
            dyn.advance(command, PERIOD)
            hits.append(dyn.collided[0].tolist())
            gaps.append(float((dyn.position[0, 0] - dyn.position[0, 1]).norm()))
        touching = [hit == [True, True] for hit in hits]
        assert touching == [True, True] + [False] * 6 + [True] * 3
        assert min(gaps[2:8]) > 0.5 and gaps[9] < 0.5  # apart in between, then in contact
        dyn.close()


def test_a_simulator_without_the_checking_calls_flies_with_a_warning(scenarios, caplog):
    # listVehicles and simIsPaused only check; a simulator that lacks them still flies.
    with TestServer(SETTINGS) as srv:
        del srv._methods["listVehicles"], srv._methods["simIsPaused"]
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.client"):
            env = airsim_env(scenarios, srv.address)
            env.reset()
            env.rand_step()
        assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        assert "has no listVehicles: vehicles Attacker, Defender not checked" in caplog.text
        assert caplog.text.count("has no simIsPaused") == 1
        env.close()


def test_a_checking_call_refused_in_other_words_than_rpclibs_flies_with_a_warning(
    scenarios, caplog
):
    # A stand-in that words a missing method its own way: the checks are skipped, not fatal.
    def missing():
        raise ValueError("Method not found")

    with TestServer(SETTINGS) as srv:
        for name in ("listVehicles", "getSettingsString", "simIsPaused"):
            srv._methods[name] = ((), missing)
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.client"):
            env = airsim_env(scenarios, srv.address)
            env.reset()
            env.rand_step()
        assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        for name in ("listVehicles", "getSettingsString", "simIsPaused"):
            assert f"has no {name} (it answered: " in caplog.text
        assert "Method not found" in caplog.text
        env.close()


def test_a_simulator_without_ping_or_collision_reports_flies_with_a_warning(scenarios, caplog):
    # ping only checks the connection (an answer, even a refusal, shows a server is there);
    # the collision flag only feeds `collided`: a stand-in without them still flies.
    with TestServer(SETTINGS) as srv:
        del srv._methods["ping"], srv._methods["simGetCollisionInfo"]
        with caplog.at_level("WARNING", logger="rlplat.envs.airsim.client"):
            env = airsim_env(scenarios, srv.address)
            td = env.rollout(3)
            env.rollout(2)
        assert env.dynamics.last_advance_s == pytest.approx(PERIOD, abs=1e-9)
        assert not td["next", "positions"][:, -1].equal(td["positions"][:, 0])  # it flew
        assert not td["next", "collided"].any()
        assert caplog.text.count("has no ping: connected without it") == 1  # the env's client
        assert caplog.text.count("has no simGetCollisionInfo: no collisions are reported") == 1
        env.close()


# Faults: one line each, within a bounded time ----------------------------------------------


def test_no_simulator_at_the_address_names_it_and_how_to_start_one(scenarios):
    port = free_port()
    t0 = time.monotonic()
    with pytest.raises(AirSimError) as info:
        airsim_env(scenarios, f"127.0.0.1:{port}")
    message = str(info.value)
    assert time.monotonic() - t0 < 2.0 + 1.0  # connect_timeout_s, and then some
    assert f"no simulator at 127.0.0.1:{port}" in message and "\n" not in message
    assert "settings.json" in message and "python -m rlplat.airsim serve" in message
    with pytest.raises(AirSimError, match=rf"^no simulator at \[::1\]:{port}\b"):
        AirSimClient(f"[::1]:{port}", connect_timeout_s=2.0)  # IPv6, named in brackets
    # A host name that does not resolve (.invalid never does) says so, at once.
    t0 = time.monotonic()
    with pytest.raises(AirSimError) as info:
        AirSimClient("no-such-host.invalid:41451", connect_timeout_s=5.0)
    assert time.monotonic() - t0 < 1.0
    assert str(info.value).startswith(
        "no simulator at no-such-host.invalid:41451: the host name does not resolve ("
    )


def test_training_without_a_simulator_is_refused_before_the_run_directory(
    scenarios, tiny, tmp_path, refused_in_process
):
    # train.py's preflight asks each endpoint before Hydra makes the run directory.
    port, run = free_port(), tmp_path / "run"
    err = refused_in_process(
        "train.py", *tiny, *airsim(f"127.0.0.1:{port}"), "algo.num_envs=1",
        f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}",
    )  # fmt: skip
    assert err.startswith(f"error: dynamics.endpoints: no simulator at 127.0.0.1:{port} ")
    assert err.count("\n") == 1 and not run.exists()
    # A vehicle list of another length than the team is refused there too, before asking.
    err = refused_in_process(
        "train.py", *tiny, *airsim(f"127.0.0.1:{port}"), "algo.num_envs=1",
        "dynamics.vehicles=[Drone1]", f"scenarios_dir={scenarios.path}", f"hydra.run.dir={run}",
    )  # fmt: skip
    assert err.startswith("error: dynamics.vehicles: must name the 1 attacker(s), then the 1 ")
    assert err.count("\n") == 1 and not run.exists()


def test_a_simulator_that_accepts_but_never_answers_fails_within_the_connect_timeout(
    server, scenarios
):
    server.stall()
    t0 = time.monotonic()
    with pytest.raises(AirSimError, match=r"no answer to ping .* within 2 s .*connect_timeout_s"):
        airsim_env(scenarios, server.address)
    assert 1.9 < time.monotonic() - t0 < 4.0
    server.unstall()


def test_a_simulator_that_stops_answering_fails_after_timeout_s_naming_the_call(server, scenarios):
    env = airsim_env(scenarios, server.address)
    env.reset()
    env.rand_step()
    server.stall()
    t0 = time.monotonic()
    with pytest.raises(AirSimError) as info:
        env.rand_step()
    waited = time.monotonic() - t0
    server.unstall()
    assert 0.9 < waited < 2.5
    message = str(info.value)
    assert f"simulator at {server.address} stopped answering" in message
    assert "simContinueForTime" in message and "dynamics.timeout_s" in message
    # The moves of the step wait beside it: a server serving fewer calls at once hangs so too.
    assert "2 moveByVelocity calls were still open" in message and "fewer than 3 calls" in message
    env.close()


def test_a_pose_applied_a_few_frames_late_is_waited_for(server, scenarios, caplog):
    # An older simulator applies a pose on a later frame, paused as it is: the env reads again
    # until the drones are where it placed them, and the episode starts there.
    args, place = server._methods["simSetVehiclePose"]
    state_args, state = server._methods["getMultirotorState"]
    poses, reads = [], [0]

    def later(*params):  # held, applied after a few reads
        poses.append(params)
        reads[0] = 0

    def read(*params):
        reads[0] += 1
        if reads[0] > 4:
            for pose in poses:
                place(*pose)
            poses.clear()
        return state(*params)

    env = airsim_env(scenarios, server.address)
    env.reset()
    server._methods["simSetVehiclePose"] = (args, later)
    server._methods["getMultirotorState"] = (state_args, read)
    with caplog.at_level("WARNING", logger="rlplat.envs.airsim.dynamics"):
        td = env.reset()
        env.rand_step(td)
    assert "from where it was placed" not in caplog.text
    assert env.dynamics.placement_error_m <= 0.1
    env.close()


def test_a_drone_read_away_from_its_placement_is_logged_once(server, scenarios, caplog):
    env = airsim_env(scenarios, server.address)
    with caplog.at_level("WARNING", logger="rlplat.envs.airsim.dynamics"):
        env.reset()
        assert "from where it was placed" not in caplog.text  # placed where it reads
        # A simulator that applies a pose late (older AirSim) reads the drones where they were.
        args, _ = server._methods["simSetVehiclePose"]
        server._methods["simSetVehiclePose"] = (args, lambda *_: None)
        env.reset()
        env.reset()
    assert caplog.text.count("from where it was placed") == 1
    assert f"simulator at {server.address}: " in caplog.text
    env.close()


def test_an_unknown_vehicle_lists_the_simulators_vehicles(server, scenarios):
    with pytest.raises(AirSimError) as info:
        airsim_env(scenarios, server.address, attacker_name="Hunter")
    message = str(info.value)
    assert "no vehicle 'Hunter'" in message and "its vehicles: Attacker, Defender" in message


def test_a_connection_lost_mid_run_is_that_error_at_once(server, scenarios):
    env = airsim_env(scenarios, server.address, timeout_s=30.0)
    env.reset()
    env.rand_step()
    server.drop_connections()
    t0 = time.monotonic()
    with pytest.raises(
        AirSimError, match=f"lost the connection to the simulator at {server.address}"
    ):
        env.rand_step()
    assert time.monotonic() - t0 < 5.0  # not the 30 s timeout
    with pytest.raises(AirSimError, match="connection is closed"):  # no silent reconnect
        env.rand_step()
    env.close()


def test_num_envs_must_match_the_endpoints(scenarios):
    with pytest.raises(ConfigError, match=r"^num_envs: 2, dynamics.endpoints names 1 simulator"):
        make_env(*airsim("127.0.0.1:41451"), scenarios=scenarios, num_envs=2)


# Several simulators: a TorchRL ParallelEnv of batch [N] -----------------------------------


@pytest.mark.slow
def test_two_simulators_step_in_parallel_as_one_env_of_batch_2_and_a_fault_names_its_worker(
    scenarios,
):
    # Real-time servers at a quarter of real time: a step's simContinueForTime(0.1 / 0.25) takes
    # 0.4 s of wall time, so 5 steps take ~2 s when the two simulators are stepped at once and
    # >= 4 s one after the other (the margin absorbs a loaded machine's per-step overhead).
    slow = {**SETTINGS, "ClockSpeed": 0.25}
    servers = [TestServer(slow, realtime=True).start() for _ in range(2)]
    try:
        env = airsim_env(scenarios, *(s.address for s in servers), clock_speed=0.25)
        assert env.batch_size == torch.Size([2])
        check_env_specs(env, seed=0)
        env.set_seed(0)  # restarts the walks: from one random state, each its share of it
        first, second = env.sampler_state()
        assert torch.equal(first, second)
        td = env.reset()
        assert td["scenario_index"].view(-1).tolist() == [0, 1]  # each its share of the split
        clocks = [s.snapshot()["t_ns"] for s in servers]
        t0 = time.monotonic()
        out = env.rollout(5, auto_reset=False, tensordict=td, break_when_any_done=False)
        wall = time.monotonic() - t0
        assert out.batch_size == torch.Size([2, 5])
        advanced = [s.snapshot()["t_ns"] - c for s, c in zip(servers, clocks, strict=True)]
        assert advanced == [pytest.approx(5 * PERIOD * 1e9, abs=10)] * 2
        assert 2.0 <= wall < 3.5
        # A simulator lost: the worker's one line (an RlplatError: exit code 2 in a CLI).
        servers[1].drop_connections()
        with pytest.raises(WorkerFault) as info:
            env.rand_step()
        assert str(info.value).startswith("env worker 1: lost the connection to the simulator")
        assert "\n" not in str(info.value)
        env.close()
    finally:
        for s in servers:
            s.stop()


# Training and evaluation through the command line -----------------------------------------


@pytest.mark.slow
def test_a_trained_checkpoint_is_evaluated_on_the_test_server_through_evaluate_py(
    scenarios, tiny_run, run_python, tmp_path
):
    run_dir = tmp_path / "run"
    tiny_run(scenarios, run_dir)  # on the embedded velocity model
    with TestServer(SETTINGS) as srv:
        res = run_python(
            "evaluate.py", f"run_dir={run_dir}", *airsim(srv.address), "plots=false",
            "threads=1",
        )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    out = run_dir / "eval" / "test-best-airsim"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dynamics"] == "airsim" and summary["scenarios"] == 16
    rows = (out / "episodes.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 16
    assert "capture rate" in res.stdout and "16 test scenarios" in res.stdout
    assert math.isfinite(summary["mean_return"])
    assert "dynamics `airsim`" in (out / "report.md").read_text()
    # Any other model swaps in the same way, here in-process.
    swapped = evaluate_run(run_dir, dynamics={"name": "quadrotor"}, plots=False)
    assert swapped.out_dir == run_dir / "eval" / "test-best-quadrotor"
    assert swapped.summary["dynamics"] == "quadrotor" and len(swapped.rows) == 16
    with pytest.raises(ConfigError, match=r"^dynamics.endpoints: 'nowhere' is not host:port"):
        evaluate_run(run_dir, dynamics={"name": "airsim", "endpoints": ["nowhere"]})


@pytest.mark.slow
def test_training_on_airsim_stops_on_a_lost_simulator_and_resumes_once_it_is_back(
    scenarios, tiny, train_cli, tmp_path
):
    port = free_port()
    run_dir = tmp_path / "run"
    overrides = [
        *tiny,
        *airsim(f"127.0.0.1:{port}", timeout_s=2.0),
        "algo.num_envs=1",
        f"scenarios_dir={scenarios.path}",
        f"hydra.run.dir={run_dir}",
        "train.threads=1",
        "train.eval_every_frames=64",
    ]
    last = run_dir / "checkpoints" / "last.pt"
    srv = TestServer(SETTINGS, port=port).start()
    proc = subprocess.Popen(
        [sys.executable, "train.py", *overrides, "train.total_frames=100000"],
        cwd=REPO,
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not last.is_file() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert last.is_file(), "no checkpoint written"
        srv.stop()  # the simulator goes away mid-run
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.stop()
    assert proc.returncode == 2
    assert (
        err.strip()
        .splitlines()[-1]
        .startswith(f"error: lost the connection to the simulator at 127.0.0.1:{port}")
    )
    frames = load_checkpoint(last)["counters"]["frames"]  # still loadable
    assert frames >= 64

    with TestServer(SETTINGS, port=port):  # back on the same address
        res = train_cli(*overrides, "resume=true", f"train.total_frames={frames + 64}")
    assert res.returncode == 0, res.stderr[-2000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] >= frames + 64


@pytest.mark.slow
def test_training_on_two_simulators_collects_from_both_and_checkpoints_their_walks(
    scenarios, tiny_run, tmp_path
):
    servers = [serve(), serve()]
    try:
        clocks = [s.snapshot()["t_ns"] for s in servers]
        summary = tiny_run(
            scenarios, tmp_path / "run", *airsim(*(s.address for s in servers)),
            "algo.num_envs=2", "train.threads=1",
        )  # fmt: skip
        flown = [s.snapshot()["t_ns"] - c for s, c in zip(servers, clocks, strict=True)]
    finally:
        for s in servers:
            s.stop()
    assert summary["frames"] >= 256 and summary["test_scenarios"] == 16
    # 256 frames, half on each simulator (the validation flies the embedded model).
    assert all(t >= round(128 * PERIOD * 1e9) for t in flown)
    state = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    assert state["scenario_rng"].shape[0] == 2  # one scenario walk per worker
