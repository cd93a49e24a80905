"""Protocol conformance of the loopback AirSim test server (rlplat.envs.airsim.testserver).

Driven by the real Cosys-AirSim Python client (``cosysairsim``, the ``airsim`` extra) and by raw
msgpack-rpc where the client hides the wire (pipelining, notifications). These tests prove that
the server speaks AirSim's protocol and timing (names, argument counts, rpclib's error texts,
map-structs, pause/continue, moves completing in sim time, per-vehicle frames, the collision
latch, faults); they say nothing of how well its simple physics matches AirSim's.
"""

import asyncio
import json
import math
import socket
import threading
import time

import msgpack
import pytest

from rlplat.envs.airsim import make_settings, vehicle_names
from rlplat.envs.airsim.testserver import TestServer

airsim = pytest.importorskip("cosysairsim")
rpc_error = pytest.importorskip("msgpackrpc.error")

# Attacker at the origin, Defender spawned 10 m north (NED X = 10).
SETTINGS = make_settings(vehicle_names(1, 1), {"Attacker": (0, 0, 0), "Defender": (0, 10, 0)})
NS = 1_000_000_000


@pytest.fixture
def server():
    with TestServer(SETTINGS) as srv:
        yield srv


def connect(port: int, timeout: int = 5):
    return airsim.MultirotorClient(port=port, timeout_value=timeout)


@pytest.fixture
def event_loop_per_test():
    # The client runs tornado on the thread's asyncio loop: give each test its own.
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    yield loop
    asyncio.set_event_loop(None)
    loop.close()


@pytest.fixture
def client(server, event_loop_per_test):
    c = connect(server.port)
    yield c
    c.client.close()


def ready(c, *names: str) -> None:
    """Pause, then enable API control and arm each vehicle."""
    c.simPause(True)
    for name in names:
        c.enableApiControl(True, name)
        assert c.armDisarm(True, name) is True


def position(c, name: str) -> tuple[float, float, float]:
    p = c.getMultirotorState(name).kinematics_estimated.position
    return (p.x_val, p.y_val, p.z_val)


def velocity(c, name: str) -> tuple[float, float, float]:
    v = c.getMultirotorState(name).kinematics_estimated.linear_velocity
    return (v.x_val, v.y_val, v.z_val)


def rpc_message(excinfo) -> str:
    return str(excinfo.value.args[0])


# Connection, discovery ------------------------------------------------------------------------


def test_conformance_ping_and_confirm_connection(client, capsys):
    assert client.ping() is True
    client.confirmConnection()
    out = capsys.readouterr()
    assert "Connected!" in out.out and "older version" not in out.out + out.err
    assert client.getServerVersion() >= client.getMinRequiredServerVersion()
    assert client.getMinRequiredClientVersion() <= client.getClientVersion()


def test_conformance_list_vehicles_and_settings_string(client):
    assert client.listVehicles() == ["Attacker", "Defender"]
    assert json.loads(client.getSettingsString()) == SETTINGS


# rpclib's errors ------------------------------------------------------------------------------


def test_conformance_unknown_function_error_is_rpclibs(client):
    with pytest.raises(rpc_error.RPCError) as err:
        client.client.call("simFlyToTheMoon", 1.0, "Attacker")
    assert rpc_message(err) == (
        "rpclib: server could not find function 'simFlyToTheMoon' with argument count 2."
    )


def test_conformance_wrong_argument_count_error_is_rpclibs(client):
    # rpclib prints its two numbers swapped: "Expected" is the count given.
    with pytest.raises(rpc_error.RPCError) as err:
        client.client.call("moveByVelocity", 1.0, 0.0, 0.0, 1.0)
    assert rpc_message(err) == (
        "rpclib: Function 'moveByVelocity' was called with an invalid number of arguments. "
        "Expected: 4, got: 7"
    )


def test_conformance_wrong_argument_type_is_a_bad_cast(client):
    with pytest.raises(rpc_error.RPCError) as err:
        client.client.call("simPause", 1.5)
    assert rpc_message(err) == (
        "rpclib: function 'simPause' (called with 1 arg(s)) threw an exception. "
        "The exception contained this information: std::bad_cast."
    )
    with pytest.raises(rpc_error.RPCError, match="std::bad_cast"):
        client.client.call("simSetVehiclePose", [1, 2, 3], True, "Attacker")  # not a map


def test_conformance_unknown_vehicle_error_is_airsims(client):
    with pytest.raises(rpc_error.RPCError) as err:
        client.enableApiControl(True, "Ghost")
    assert rpc_message(err) == (
        "rpclib: function 'enableApiControl' (called with 2 arg(s)) threw an exception. "
        "The exception contained this information: Vehicle API for 'Ghost' is not available. "
        "This could either because this is simulation-only API or this vehicle does not exist."
    )
    with pytest.raises(rpc_error.RPCError, match="Vehicle Sim-API for 'Ghost' is not available"):
        client.simGetCollisionInfo("Ghost")


def test_conformance_empty_vehicle_name_is_the_first_vehicle(client):
    client.enableApiControl(True)
    assert client.isApiControlEnabled("Attacker") is True
    assert client.isApiControlEnabled("Defender") is False


def test_conformance_motion_needs_api_control_and_arming(client):
    client.simPause(True)
    with pytest.raises(rpc_error.RPCError, match="requestApiControl\\(\\) must be called"):
        client.moveByVelocityAsync(1.0, 0.0, 0.0, 1.0, vehicle_name="Attacker").get()
    assert client.armDisarm(True, "Attacker") is False  # as AirSim: False, no exception
    client.enableApiControl(True, "Attacker")
    with pytest.raises(rpc_error.RPCError, match="'Attacker' is not armed"):
        client.hoverAsync("Attacker").get()
    assert client.armDisarm(True, "Attacker") is True
    client.reset()  # clears API control and arming, as AirSim
    assert client.isApiControlEnabled("Attacker") is False


# Sim time ---------------------------------------------------------------------------------------


def test_conformance_continue_for_time_advances_exactly_and_stays_paused(client):
    client.simPause(True)
    assert client.simIsPause() is True
    t0 = client.getMultirotorState("Attacker").timestamp
    client.simContinueForTime(0.1)
    t1 = client.getMultirotorState("Attacker").timestamp
    assert t1 - t0 == NS // 10  # exact, though 0.1 s is not a whole number of 3 ms steps
    assert client.simIsPause() is True
    time.sleep(0.05)
    assert client.getMultirotorState("Defender").timestamp == t1  # frozen while paused
    client.simContinueForFrames(5)
    assert client.getMultirotorState("Attacker").timestamp - t1 == 5 * 3_000_000


def test_conformance_continue_for_time_counts_wall_seconds_times_clock_speed(event_loop_per_test):
    with TestServer({**SETTINGS, "ClockSpeed": 4.0}) as srv:
        c = connect(srv.port)
        c.simPause(True)
        t0 = c.getMultirotorState("Attacker").timestamp
        c.simContinueForTime(0.025)  # 0.025 wall s at ClockSpeed 4 = 0.1 sim s
        assert c.getMultirotorState("Attacker").timestamp - t0 == NS // 10
        c.client.close()


def test_conformance_a_clock_speed_above_1_runs_at_its_whole_part(event_loop_per_test):
    # AirSim keeps its 3-ms step and divides its loop's period by int(ClockSpeed).
    for speed, sim in ((2.5, 2), (0.5, 0.5)):
        with TestServer({**SETTINGS, "ClockSpeed": speed}) as srv:
            c = connect(srv.port)
            c.simPause(True)
            t0 = c.getMultirotorState("Attacker").timestamp
            c.simContinueForTime(0.3)
            assert c.getMultirotorState("Attacker").timestamp - t0 == round(0.3 * sim * NS)
            c.client.close()


def test_conformance_realtime_continue_takes_its_wall_time(event_loop_per_test):
    with TestServer({**SETTINGS, "ClockSpeed": 2.0}, realtime=True) as srv:
        c = connect(srv.port)
        c.simPause(True)
        t0, w0 = c.getMultirotorState("Attacker").timestamp, time.monotonic()
        c.simContinueForTime(0.2)  # 0.2 wall s = 0.4 sim s
        wall = time.monotonic() - w0
        assert c.getMultirotorState("Attacker").timestamp - t0 == 4 * NS // 10
        assert 0.19 < wall < 1.0 and c.simIsPause() is True
        c.client.close()


def test_conformance_unpaused_clock_follows_the_wall_clock(client):
    t0, w0 = client.getMultirotorState("Attacker").timestamp, time.monotonic()
    time.sleep(0.3)
    t1, w1 = client.getMultirotorState("Attacker").timestamp, time.monotonic()
    assert client.simIsPause() is False
    assert 0.5 * (w1 - w0) < (t1 - t0) / NS < w1 - w0 + 0.05


def test_conformance_a_move_issued_while_paused_does_not_advance(client):
    ready(client, "Attacker")
    move = client.moveByVelocityAsync(2.0, 0.0, 0.0, 0.5, vehicle_name="Attacker")
    t0 = client.getMultirotorState("Attacker").timestamp
    time.sleep(0.2)
    state = client.getMultirotorState("Attacker")
    assert state.timestamp == t0
    assert position(client, "Attacker") == (0.0, 0.0, 0.0)
    client.simContinueForTime(0.6)
    move.join()
    assert move.result is True
    assert position(client, "Attacker")[0] > 0.1


def test_conformance_a_new_move_cancels_the_previous_one(client):
    ready(client, "Attacker")
    first = client.moveByVelocityAsync(1.0, 0.0, 0.0, 5.0, vehicle_name="Attacker")
    client.simContinueForTime(0.1)
    second = client.moveByVelocityAsync(0.0, 1.0, 0.0, 0.2, vehicle_name="Attacker")
    first.join()
    assert first.result is False  # interrupted, as AirSim's waiter reports it
    client.simContinueForTime(0.3)
    second.join()
    assert second.result is True
    # A move on another vehicle does not cancel this one.
    ready(client, "Defender")
    third = client.moveByVelocityAsync(0.0, 0.0, -1.0, 0.2, vehicle_name="Attacker")
    other = client.moveByVelocityAsync(0.0, 0.0, -1.0, 0.2, vehicle_name="Defender")
    client.simContinueForTime(0.25)
    third.join()
    other.join()
    assert (third.result, other.result) == (True, True)


def test_conformance_pipelined_requests_are_answered_out_of_order(server):
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
        unpacker = msgpack.Unpacker(raw=False)

        def send(msg):
            sock.sendall(msgpack.packb(msg, use_bin_type=True))

        def receive():
            while True:
                for msg in unpacker:
                    return msg
                unpacker.feed(sock.recv(65536))

        yaw = {"is_rate": True, "yaw_or_rate": 0.0}
        send([2, "simPause", [True]])  # a notification: run, never answered
        send([0, 1, "enableApiControl", [True, "Attacker"]])
        send([0, 2, "armDisarm", [True, "Attacker"]])
        send([0, 3, "moveByVelocity", [1.0, 0.0, 0.0, 0.3, 0, yaw, "Attacker"]])
        send([0, 4, "simIsPaused", []])
        send([0, 5, "simContinueForTime", [0.2]])
        replies = [receive() for _ in range(4)]
        assert replies == [[1, 1, None, None], [1, 2, None, True], [1, 4, None, True]] + [
            [1, 5, None, None]
        ]
        send([0, 6, "simContinueForTime", [0.2]])  # the move ends within this one
        assert sorted(map(tuple, [receive(), receive()])) == [
            (1, 3, None, True),
            (1, 6, None, None),
        ]


# Frames and state -------------------------------------------------------------------------------


def test_conformance_positions_are_relative_to_each_spawn_point(client, server):
    # The Defender is spawned at NED X = 10 and reads 0 there.
    assert position(client, "Defender") == (0.0, 0.0, 0.0)
    pose = client.simGetVehiclePose("Defender")
    assert (pose.position.x_val, pose.position.y_val, pose.position.z_val) == (0.0, 0.0, 0.0)
    assert pose.orientation.w_val == 1.0
    client.simPause(True)
    client.simSetVehiclePose(airsim.Pose(airsim.Vector3r(1.0, 2.0, -3.0)), True, "Defender")
    assert position(client, "Defender") == (1.0, 2.0, -3.0)
    assert server.snapshot()["vehicles"]["Defender"]["position"] == [11.0, 2.0, -3.0]
    kin = client.simGetGroundTruthKinematics("Defender")
    assert (kin.position.x_val, kin.position.z_val) == (1.0, -3.0)


def test_conformance_multirotor_state_fields(client):
    client.simPause(True)
    state = client.getMultirotorState("Attacker")
    assert state.landed_state == airsim.LandedState.Landed
    assert not state.collision.has_collided and state.collision.object_id == -1
    assert math.isclose(state.gps_location.latitude, 47.641468)
    assert state.rc_data.is_valid is False
    assert isinstance(state.timestamp, int)
    client.simSetVehiclePose(airsim.Pose(airsim.Vector3r(0.0, 0.0, -5.0)), True, "Attacker")
    state = client.getMultirotorState("Attacker")
    assert state.landed_state == airsim.LandedState.Flying
    assert math.isclose(state.gps_location.altitude, 127.0)


def test_conformance_collision_latch_clears_on_read(client):
    ready(client)
    # Attacker 0.3 m from the Defender (world NED (10, 0, -2) and (10, 0, -2.3)).
    client.simSetVehiclePose(airsim.Pose(airsim.Vector3r(10.0, 0.0, -2.0)), True, "Attacker")
    client.simSetVehiclePose(airsim.Pose(airsim.Vector3r(0.0, 0.0, -2.3)), True, "Defender")
    assert client.simGetCollisionInfo("Attacker").has_collided is False  # placed, not stepped
    client.simContinueForTime(0.01)
    info = client.simGetCollisionInfo("Attacker")
    assert info.has_collided is True and info.object_name == "Defender"
    assert info.penetration_depth > 0.1
    assert client.simGetCollisionInfo("Attacker").has_collided is False  # cleared by the read
    assert client.getMultirotorState("Defender").collision.has_collided is False  # never filled
    assert client.simGetCollisionInfo("Defender").object_name == "Attacker"


def test_conformance_hitting_the_ground_is_a_collision(client):
    ready(client, "Attacker")
    client.simSetVehiclePose(airsim.Pose(airsim.Vector3r(0.0, 0.0, -0.2)), True, "Attacker")
    client.moveByVelocityAsync(0.0, 0.0, 2.0, 1.0, vehicle_name="Attacker")
    client.simContinueForTime(0.5)
    assert position(client, "Attacker")[2] == 0.0  # stopped by the ground
    assert client.simGetCollisionInfo("Attacker").object_name == "Ground"


def test_conformance_vehicle_holds_position_after_its_move_lapses(client):
    ready(client, "Attacker")
    client.simSetVehiclePose(airsim.Pose(airsim.Vector3r(0.0, 0.0, -5.0)), True, "Attacker")
    client.moveByVelocityAsync(0.0, 3.0, 0.0, 0.5, vehicle_name="Attacker")
    client.simContinueForTime(0.54)  # the command still applies 0.06 s after the move ends
    speed_at_lapse = velocity(client, "Attacker")[1]
    client.simContinueForTime(0.1)  # now holding: braking
    assert velocity(client, "Attacker")[1] < speed_at_lapse
    client.simContinueForTime(4.0)
    y = position(client, "Attacker")[1]
    # Had the command persisted, it would be ~10 m out; it holds near where it began to hold.
    assert 0.3 < y < 1.5
    assert abs(velocity(client, "Attacker")[1]) < 0.1
    assert abs(position(client, "Attacker")[2] + 5.0) < 0.05


def test_conformance_takeoff_completes_in_sim_time(client):
    ready(client, "Attacker")
    done = client.takeoffAsync(20, "Attacker")
    client.simContinueForTime(8.0)
    done.join()
    assert done.result is True
    assert abs(position(client, "Attacker")[2] + 3.0) <= 0.1


# Faults and lifecycle ---------------------------------------------------------------------------


def test_conformance_stalled_server_times_the_client_out(server, event_loop_per_test):
    c = connect(server.port, timeout=1)
    assert c.ping() is True
    server.stall()
    start = time.monotonic()
    with pytest.raises(rpc_error.TimeoutError):
        c.ping()
    assert time.monotonic() - start < 4
    server.unstall()
    assert c.ping() is True
    c.client.close()


def test_conformance_dropped_connection_fails_the_call_in_flight(server, event_loop_per_test):
    c = connect(server.port, timeout=1)
    ready(c, "Attacker")
    move = c.moveByVelocityAsync(1.0, 0.0, 0.0, 1.0, vehicle_name="Attacker")
    c.ping()  # the move is on the wire and pending (paused)
    server.drop_connections()
    # The client sees the lost reply as a timeout, then reconnects on its next call.
    with pytest.raises(rpc_error.RPCError):
        move.get()
    assert c.ping() is True
    c.client.close()


def test_conformance_restart_on_the_same_port_and_no_leaked_threads(event_loop_per_test):
    before = set(threading.enumerate())
    srv = TestServer(SETTINGS).start()
    port = srv.port
    c = connect(port, timeout=2)
    assert c.ping() is True
    srv.stop()
    srv = TestServer(SETTINGS, port=port).start()
    assert srv.port == port
    c2 = connect(port, timeout=2)
    assert c2.listVehicles() == ["Attacker", "Defender"]
    srv.stop()
    c.client.close()
    c2.client.close()
    assert set(threading.enumerate()) == before


def test_conformance_a_busy_port_is_a_clear_error(server):
    with pytest.raises(OSError, match=f"could not listen on 127.0.0.1:{server.port}"):
        TestServer(SETTINGS, port=server.port).start()


# The simulated world ----------------------------------------------------------------------------


def test_world_flies_the_embedded_velocity_model():
    # Not AirSim fidelity: the server's world is dynamics=velocity (no drag, same constants),
    # so a client can compare trajectories. Random commands, 0.1 s control period, 5 s.
    import torch

    from rlplat.envs.airsim import enu_to_ned, ned_to_enu
    from rlplat.envs.airsim.simworld import Physics, SimWorld
    from rlplat.envs.dynamics import VelocityDynamics

    world = SimWorld(make_settings(["A"], {"A": (0.0, 0.0, 5.0)}), Physics(), start_ns=0)
    veh = world.vehicles["A"]
    embedded = VelocityDynamics(num_envs=1, num_drones=1, physics_dt=0.003, drag_xy=0, drag_z=0)
    start = torch.tensor([[[0.0, 0.0, 5.0]]])
    embedded.reset(
        torch.ones(1, dtype=torch.bool), start, torch.zeros(1, 1, 3), torch.full((1, 1), 9.0)
    )
    gen = torch.Generator().manual_seed(0)
    gap = 0.0
    for _ in range(50):
        command = torch.rand(3, generator=gen) * 10 - 5
        embedded.advance(command.view(1, 1, 3), 0.1)
        world.move_by_velocity(veh, enu_to_ned(tuple(command.tolist())), 0.2, lambda ok: None)
        world.advance(NS // 10)
        here = ned_to_enu(tuple(veh.p))
        there = embedded.position[0, 0].tolist()
        gap = max(gap, *(abs(a - b) for a, b in zip(here, there, strict=True)))
    assert gap < 1e-3


def test_recording_keeps_every_call_and_the_state_after_each_continue(server, client, tmp_path):
    from rlplat.envs.airsim.testserver import write_recording

    ready(client, "Attacker")
    server.start_recording()
    client.moveByVelocityAsync(1.0, 0.0, -1.0, 0.5, vehicle_name="Attacker")
    client.simContinueForTime(0.1)
    client.simContinueForTime(0.1)
    records = server.take_recording()
    calls = [r for r in records if "call" in r]
    states = [r for r in records if "vehicles" in r]
    expected = ["moveByVelocity", "simContinueForTime", "simContinueForTime"]
    assert [r["call"] for r in calls] == expected
    assert calls[0]["params"][:4] == [1.0, 0.0, -1.0, 0.5] and calls[0]["params"][6] == "Attacker"
    assert len(states) == 2 and states[1]["t_ns"] - states[0]["t_ns"] == NS // 10
    assert (
        states[1]["vehicles"]["Attacker"]["position"]
        == server.snapshot()["vehicles"]["Attacker"]["position"]
    )
    assert server.take_recording() == []  # recording stopped
    path = write_recording(tmp_path / "run.jsonl", records)
    assert [json.loads(line) for line in path.read_text().splitlines()] == records
