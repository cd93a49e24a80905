"""Frame conversions and settings.json for the AirSim backend (rlplat.envs.airsim)."""

import json
import logging

import numpy as np
import pytest
import torch

from rlplat.envs.airsim import (
    enu_to_ned,
    local_to_world,
    make_settings,
    ned_to_enu,
    spawn_offsets,
    vehicle_names,
    world_to_local,
    write_settings,
)
from rlplat.envs.airsim.frames import enu_rows_to_ned, ned_rows_to_enu
from rlplat.errors import ConfigError

# ENU <-> NED ----------------------------------------------------------------------------------


def test_enu_to_ned_swaps_horizontal_axes_and_flips_z():
    # 1 m east, 2 m north, 3 m up = 2 m north, 1 m east, 3 m up (z down = -3).
    assert enu_to_ned((1.0, 2.0, 3.0)) == (2.0, 1.0, -3.0)
    assert ned_to_enu((2.0, 1.0, -3.0)) == (1.0, 2.0, 3.0)


def test_round_trips_keep_the_input_kind():
    t = torch.randn(4, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = enu_to_ned(t)
    assert isinstance(out, torch.Tensor) and out.shape == t.shape and out.dtype == t.dtype
    assert torch.equal(ned_to_enu(out), t)
    assert torch.equal(enu_to_ned(ned_to_enu(t)), t)
    a = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    b = enu_to_ned(a)
    assert isinstance(b, np.ndarray) and b.dtype == np.float32
    np.testing.assert_array_equal(ned_to_enu(b), a)
    p = [0.5, -1.25, 7]
    q = enu_to_ned(p)
    assert q == (-1.25, 0.5, -7.0) and all(type(v) is float for v in q)
    assert ned_to_enu(q) == (0.5, -1.25, 7.0)


def test_ground_level_has_no_negative_zero():
    assert str(enu_to_ned((0.0, 0.0, 0.0))) == "(0.0, 0.0, 0.0)"


def test_rows_of_floats_convert_bit_for_bit_as_their_float64_tensors():
    g = torch.Generator().manual_seed(1)
    rows = torch.randn(3, 3, dtype=torch.float64, generator=g)
    rows[0] = torch.tensor([0.0, -0.0, 0.0])  # zeros keep the sign the tensor path gives them
    spawn = torch.randn(3, 3, dtype=torch.float64, generator=g)
    spawn[0] = 0.0
    cases = [
        (enu_rows_to_ned(rows.tolist()), enu_to_ned(rows)),
        (ned_rows_to_enu(rows.tolist()), ned_to_enu(rows)),
        (ned_rows_to_enu(rows.tolist(), spawn.tolist()), ned_to_enu(local_to_world(rows, spawn))),
    ]
    for got, want in cases:
        assert all(type(v) is float for row in got for v in row)
        bits = torch.tensor(got, dtype=torch.float64).view(torch.int64)
        assert torch.equal(bits, want.view(torch.int64))


def test_a_last_axis_other_than_three_is_refused():
    with pytest.raises(ValueError, match="size 3"):
        enu_to_ned(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="size 3"):
        ned_to_enu(np.zeros(2))


# Spawn-relative frames ------------------------------------------------------------------------


def test_a_vehicle_spawned_away_from_the_origin_reads_local_positions():
    # Spawned 10 m north, 5 m west, 2 m up (NED: (10, -5, -2)).
    spawn = enu_to_ned((-5.0, 10.0, 2.0))
    assert spawn == (10.0, -5.0, -2.0)
    # At its spawn point the vehicle reads local 0.
    assert world_to_local(spawn, spawn) == (0.0, 0.0, 0.0)
    # A world point 20 m up from the world origin.
    world = enu_to_ned((0.0, 0.0, 20.0))
    local = world_to_local(world, spawn)
    assert local == (-10.0, 5.0, -18.0)
    assert ned_to_enu(local_to_world(local, spawn)) == (0.0, 0.0, 20.0)


def test_local_frames_broadcast_over_batches():
    spawns = torch.tensor([[10.0, 0.0, 0.0], [0.0, -3.0, -1.0]])
    p = torch.randn(8, 2, 3, generator=torch.Generator().manual_seed(0))
    local = world_to_local(p, spawns)
    assert torch.equal(local[:, 1], p[:, 1] - spawns[1])
    assert torch.allclose(local_to_world(local, spawns), p, atol=1e-5)  # float32 rounding
    arr = np.zeros((3, 3))
    np.testing.assert_array_equal(local_to_world(arr, (1.0, 2.0, 3.0))[2], [1.0, 2.0, 3.0])


# spawn_offsets --------------------------------------------------------------------------------

SETTINGS = {
    "Vehicles": {
        "Attacker": {"VehicleType": "SimpleFlight", "X": 10, "Y": -2.5, "Z": -1},
        "Defender": {"VehicleType": "SimpleFlight", "Y": 4},
    }
}


def test_spawn_offsets_read_settings_and_a_partial_position_is_the_origin(caplog):
    # AirSim places a vehicle at its settings' X/Y/Z only when all three are given: the
    # Defender's Y alone is ignored, it spawns at its PlayerStart, the origin.
    with caplog.at_level(logging.WARNING, logger="rlplat.envs.airsim.frames"):
        got = spawn_offsets(SETTINGS, ["Defender", "Attacker"])
    assert got == {"Defender": (0.0, 0.0, 0.0), "Attacker": (10.0, -2.5, -1.0)}
    assert list(got) == ["Defender", "Attacker"]
    [record] = caplog.records
    assert "'Defender'" in record.getMessage() and "no X/Z" in record.getMessage()
    assert "the origin" in record.getMessage()


def test_spawn_offsets_fallback_places_vehicles_the_settings_do_not():
    fallback = {"Defender": (1.0, 2.0, 3.0), "Defender2": (7.0, 8.0, 9.0),
                "Attacker": (5.0, 5.0, 5.0)}  # fmt: skip
    got = spawn_offsets(SETTINGS, ["Defender", "Defender2", "Attacker"], fallback)
    # A whole position in the settings wins; a partial one or none takes the whole fallback.
    assert got == {"Defender": (1.0, 2.0, 3.0), "Defender2": (7.0, 8.0, 9.0),
                   "Attacker": (10.0, -2.5, -1.0)}  # fmt: skip


def test_spawn_offsets_of_a_vehicle_the_settings_do_not_place_is_the_origin(caplog):
    # AirSim spawns a vehicle its settings give no X/Y/Z at its PlayerStart, the origin; the
    # warning lists the vehicles the settings do place.
    with caplog.at_level(logging.WARNING, logger="rlplat.envs.airsim.frames"):
        got = spawn_offsets(SETTINGS, ["Attacker", "Attacker2"])
    assert got == {"Attacker": (10.0, -2.5, -1.0), "Attacker2": (0.0, 0.0, 0.0)}
    [record] = caplog.records
    assert "'Attacker2'" in record.getMessage() and "Attacker, Defender" in record.getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="rlplat.envs.airsim.frames"):
        assert spawn_offsets({}, ["Attacker"]) == {"Attacker": (0.0, 0.0, 0.0)}
    assert "its vehicles: none" in caplog.text


def test_spawn_offsets_refuse_a_non_numeric_coordinate():
    with pytest.raises(ConfigError, match=r"Vehicles\.Attacker\.X"):
        spawn_offsets({"Vehicles": {"Attacker": {"X": "ten"}}}, ["Attacker"])


# vehicle_names --------------------------------------------------------------------------------


def test_vehicle_names_number_extra_team_members():
    assert vehicle_names(1, 1) == ["Attacker", "Defender"]
    assert vehicle_names(2, 1) == ["Attacker", "Attacker2", "Defender"]
    assert vehicle_names(1, 3, attacker="Red", defender="Blue") == ["Red", "Blue", "Blue2", "Blue3"]
    assert vehicle_names(0, 2) == ["Defender", "Defender2"]


@pytest.mark.parametrize(
    ("args", "field"),
    [((-1, 1), "attackers"), ((1, 1.5), "defenders"), ((1, 1, ""), "attacker vehicle name")],
)
def test_vehicle_names_refuse_bad_input(args, field):
    with pytest.raises(ConfigError, match=field):
        vehicle_names(*args)


def test_vehicle_names_take_a_list_of_every_vehicle():
    assert vehicle_names(2, 1, names=["Drone1", "Drone2", "Drone3"]) == [
        "Drone1",
        "Drone2",
        "Drone3",
    ]
    for names in (["Drone1", "Drone2"], ["Drone1", "", "Drone3"], "Drone1"):
        with pytest.raises(ConfigError, match=r"dynamics.vehicles: must name the 2 attacker\(s\)"):
            vehicle_names(2, 1, names=names)
    with pytest.raises(ConfigError, match="'D' is repeated"):
        vehicle_names(1, 1, names=["D", "D"])


def test_vehicle_names_refuse_clashing_names():
    with pytest.raises(ConfigError, match="'Drone2' is repeated"):
        vehicle_names(2, 1, attacker="Drone", defender="Drone2")


# make_settings / write_settings ---------------------------------------------------------------


def test_make_settings_builds_simpleflight_vehicles_in_ned():
    names = vehicle_names(2, 1)
    spawn = {"Attacker": (0.0, 0.0, 0.0), "Attacker2": (5.0, 0.0, 0.0), "Defender": (10, 2, 3)}
    s = make_settings(names, spawn, clock_speed=2.0)
    assert s["SettingsVersion"] == 1.2
    assert s["SimMode"] == "Multirotor"
    assert s["ClockType"] == "SteppableClock"
    assert s["ClockSpeed"] == 2.0
    assert list(s["Vehicles"]) == names
    for name in names:
        v = s["Vehicles"][name]
        assert v["VehicleType"] == "SimpleFlight" and v["AutoCreate"] is True
        assert (v["X"], v["Y"], v["Z"]) == enu_to_ned(spawn[name])
    assert s["Vehicles"]["Defender"] == {
        "VehicleType": "SimpleFlight",
        "AutoCreate": True,
        "X": 2.0,
        "Y": 10.0,
        "Z": -3.0,
    }
    # The spawn offsets the backend reads back are the spawn points, in NED.
    offsets = spawn_offsets(s, names)
    assert {n: ned_to_enu(p) for n, p in offsets.items()} == {
        n: tuple(float(v) for v in p) for n, p in spawn.items()
    }


@pytest.mark.parametrize(
    ("names", "spawn", "clock", "match"),
    [
        ([], {}, 1.0, "at least one"),
        (["A"], {"A": (0, 0, 0)}, 0.0, "clock_speed"),
        (["A"], {"A": (0, 0, 0)}, float("nan"), "clock_speed"),
        (["A"], {"A": (0, 0, 0)}, 2.5, r"^clock_speed: AirSim .*\(ClockSpeed 2\.5 runs at 2\)"),
        (["A", "B"], {"A": (0, 0, 0)}, 1.0, r"missing \['B'\]"),
        (["A"], {"A": (0, 0, 0), "C": (1, 1, 1)}, 1.0, r"unknown \['C'\]"),
        (["A"], {"A": (0, 0)}, 1.0, r"spawn_enu\['A'\]"),
        (["A"], {"A": (0, float("inf"), 0)}, 1.0, r"spawn_enu\['A'\]"),
        (["A", "A"], {"A": (0, 0, 0)}, 1.0, "repeated"),
    ],
)
def test_make_settings_refuses_bad_input(names, spawn, clock, match):
    with pytest.raises(ConfigError, match=match):
        make_settings(names, spawn, clock_speed=clock)


def test_write_settings_is_atomic_json_with_stable_bytes(tmp_path):
    names = vehicle_names(1, 1)
    s = make_settings(names, {"Attacker": (0, 0, 0), "Defender": (5, 0, 0)})
    path = write_settings(tmp_path / "sub" / "settings.json", s)
    assert path == tmp_path / "sub" / "settings.json"
    text = path.read_text()
    assert json.loads(text) == s
    assert text.endswith("}\n") and text.startswith('{\n  "SettingsVersion": 1.2,')
    # Same settings, same bytes; no temporary file left behind.
    first = path.read_bytes()
    write_settings(path, make_settings(names, {"Attacker": (0, 0, 0), "Defender": (5, 0, 0)}))
    assert path.read_bytes() == first
    assert sorted(p.name for p in path.parent.iterdir()) == ["settings.json"]


def test_write_settings_refuses_what_json_cannot_carry(tmp_path):
    with pytest.raises(ConfigError, match="JSON"):
        write_settings(tmp_path / "s.json", {"ClockSpeed": float("nan")})
    assert not (tmp_path / "s.json").exists()
