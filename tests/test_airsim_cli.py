"""``python -m rlplat.airsim``: settings.json for the configured team, and the test server."""

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest

from rlplat.envs.airsim import make_settings, spawn_offsets
from rlplat.errors import ConfigError
from rlplat.experiment.airsim_tools import compose_train, team_settings

ROOT = Path(__file__).resolve().parent.parent


def airsim_cli(*args: str, **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "rlplat.airsim", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        **kwargs,
    )


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        ((), ["Attacker", "Defender"]),
        (("scenario=pursuit_2v1",), ["Attacker", "Attacker2", "Defender"]),
    ],
)
def test_settings_command_writes_the_teams_settings(tmp_path, overrides, names):
    out = tmp_path / "airsim" / "settings.json"
    run = airsim_cli("settings", f"out={out}", *overrides)
    assert run.returncode == 0, run.stderr
    assert str(out) in run.stdout and ", ".join(names) in run.stdout
    settings = json.loads(out.read_text())
    # On a line along east, 5 m apart at ground level.
    spawn = {name: (5.0 * i, 0.0, 0.0) for i, name in enumerate(names)}
    assert settings == make_settings(names, spawn, clock_speed=1.0)
    assert list(settings["Vehicles"]) == names


@pytest.mark.parametrize("verb", ["", "settings", "calibrate", "replay", "sim2sim"])
def test_help_of_each_verb_exits_zero_and_does_nothing(verb, capsys, tmp_path, monkeypatch):
    from rlplat.airsim import main

    monkeypatch.chdir(tmp_path)  # nothing may be written here
    assert main([*([verb] if verb else []), "--help"]) == 0
    out = capsys.readouterr().out
    if verb:
        assert out.startswith(f"python -m rlplat.airsim {verb} ") and "Verbs" not in out
        others = tuple(
            v for v in ("settings", "serve", "calibrate", "replay", "sim2sim") if v != verb
        )
        assert not any(line.startswith(others) for line in out.splitlines()), out
    else:
        assert "Verbs:" in out and all(v in out for v in ("calibrate", "sim2sim", "serve"))
    assert list(tmp_path.iterdir()) == []


def test_settings_command_refuses_an_unknown_override_in_one_line(tmp_path):
    out = tmp_path / "settings.json"
    run = airsim_cli("settings", f"out={out}", "scenario.bogus=3")
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "scenario.bogus" in lines[0]
    assert not out.exists()


def test_settings_for_a_second_simulator_carry_its_port_and_a_bad_port_is_one_line(tmp_path):
    out = tmp_path / "settings.json"
    run = airsim_cli("settings", f"out={out}", "port=41452")
    assert run.returncode == 0, run.stderr
    assert json.loads(out.read_text())["ApiServerPort"] == 41452
    assert "ApiServerPort 41452" in run.stdout
    bad = airsim_cli("settings", f"out={tmp_path / 'other.json'}", "port=99999")
    lines = bad.stderr.strip().splitlines()
    assert bad.returncode == 2 and len(lines) == 1 and "port" in lines[0] and "99999" in lines[0]
    assert not (tmp_path / "other.json").exists()


def test_team_settings_read_names_spawn_and_clock_speed_from_the_config():
    cfg = compose_train(
        [
            "scenario=pursuit_2v1",
            "+dynamics.attacker_name=Red",
            "+dynamics.defender_name=Blue",
            "+dynamics.spawn={Red2: [1.0, 2.0, -3.0]}",
            "+dynamics.clock_speed=2.0",
        ]
    )
    settings = team_settings(cfg)
    assert list(settings["Vehicles"]) == ["Red", "Red2", "Blue"]
    assert settings["ClockSpeed"] == 2.0
    offsets = spawn_offsets(settings, ["Red", "Red2", "Blue"])
    assert offsets == {"Red": (0.0, 0.0, 0.0), "Red2": (1.0, 2.0, -3.0), "Blue": (0.0, 10.0, 0.0)}
    # A list names every vehicle, attackers first.
    listed = compose_train(["scenario=pursuit_2v1", "+dynamics.vehicles=[Drone1,Drone2,Drone3]"])
    assert list(team_settings(listed)["Vehicles"]) == ["Drone1", "Drone2", "Drone3"]
    # Only the attackers the env flies.
    assert list(
        team_settings(compose_train(["scenario=pursuit_2v1", "env.attackers=1"]))["Vehicles"]
    ) == [
        "Attacker",
        "Defender",
    ]


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["+dynamics.spawn={Ghost: [0, 0, 0]}"], "not vehicles of the team"),
        (["+dynamics.spawn={Attacker: [0, 0]}"], r"dynamics\.spawn\.Attacker"),
        (["+dynamics.clock_speed=0"], "clock_speed"),
        (["scenario.defenders=0"], "scenario.defenders"),
    ],
)
def test_team_settings_refuse_bad_values(overrides, match):
    with pytest.raises(ConfigError, match=match):
        team_settings(compose_train(overrides))


def test_serve_command_serves_the_team_until_terminated():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "rlplat.airsim", "serve", "--port", "0", "scenario=pursuit_2v1"],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 60
        port = None
        while port is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            found = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
            port = int(found.group(1)) if found else None
            assert line or proc.poll() is None, "server exited"
        assert port is not None
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            sock.sendall(msgpack.packb([0, 7, "listVehicles", []]))
            reply = msgpack.Unpacker(raw=False)
            reply.feed(sock.recv(65536))
            assert next(reply) == [1, 7, None, ["Attacker", "Attacker2", "Defender"]]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        assert "stopped" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_serve_command_refuses_overrides_with_a_settings_file(tmp_path):
    run = airsim_cli("serve", "--settings", str(tmp_path / "s.json"), "scenario=pursuit_2v1")
    assert run.returncode == 2
    assert "do not apply with --settings" in run.stderr
