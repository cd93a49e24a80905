"""AirSim overhead: what rlplat's client side costs per env step against the loopback test server.

Every simulator is a separate process (``python -m rlplat.airsim serve``), so its work is not
counted in this process. Part 1, per team (1 v 1, 2 v 1), one simulator, one env
(``rlplat.make_env("dynamics=airsim", "dynamics.endpoints=[...]", num_envs=1, split="test")``),
ms per step of:

- ``env.step, airsim``: the whole env step (the policy's actions drawn before timing);
- ``dynamics.advance, airsim``: the AirSim step alone (commands, continue, state reads);
- ``the same calls, bare wire``: those calls over a minimal blocking msgpack-rpc client (two
  writes and two reads per step, no client library, no tensors): what the protocol itself costs
  in Python, the floor of any client;
- ``env.step, velocity``: the same env on the embedded model (rlplat's env logic alone).

Columns: ``wall``; ``client CPU``, the CPU time this process spent (rlplat and the client
library); ``server CPU``, the CPU time of the simulator process (``/proc/<pid>/stat``, Linux),
its RPC handling included; ``wall - server``, what is left once the simulator's work is taken
out (the client's work and the round trips' latency, scheduling included).

Every row times its steps after ``--warmup`` untimed ones of the same kind (the first hundreds of
steps of a fresh env or connection cost more: allocations, caches, the first episode's reset).
Resets are not timed (episodes that end are reset between timed steps). Part 2: env steps/s
(summed over the envs) with 1, 2 and 4 simulators, ``env.rollout`` with random actions: one
simulator is the single env above; several are a TorchRL ParallelEnv, one worker process per
simulator (``main CPU``: this process's CPU time per batch step). Run it niced when the
machine has other work:

    nice -n 10 .venv/bin/python benchmarks/airsim_overhead.py \
        [--steps 1000] [--warmup 200] [--servers 1 2 4]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import torch

from rlplat import make_env

TEAMS = {"1v1": (), "2v1": ("scenario=pursuit_2v1",)}
TICK_S = 1 / os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) * TICK_S


def start_servers(count: int, overrides: tuple[str, ...]) -> list[tuple[subprocess.Popen, str]]:
    """``count`` test servers for the team of ``overrides``, each in its own process."""
    servers = []
    for _ in range(count):
        port = free_port()
        proc = subprocess.Popen(
            [sys.executable, "-m", "rlplat.airsim", "serve", "--port", str(port), *overrides],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        servers.append((proc, f"127.0.0.1:{port}"))
    deadline = time.monotonic() + 120
    for proc, address in servers:
        host, _, port = address.rpartition(":")
        while True:
            try:
                socket.create_connection((host, int(port)), 1).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"test server at {address} did not start") from None
                time.sleep(0.2)
    return servers


def stop_servers(servers) -> None:
    for proc, _ in servers:
        proc.terminate()
    for proc, _ in servers:
        proc.wait(30)


class Meter:
    """Wall time, this process's CPU time and (``server_pid``) the server's CPU time of the
    spans between ``start()`` and ``stop()``, summed (seconds)."""

    def __init__(self, server_pid: int | None = None) -> None:
        self.pid, self.spans = server_pid, 0
        self.wall = self.cpu = self.server = 0.0

    def start(self) -> None:
        self._s = cpu_seconds(self.pid) if self.pid else 0.0
        self._c, self._w = time.process_time(), time.perf_counter()

    def stop(self) -> None:
        self.wall += time.perf_counter() - self._w
        self.cpu += time.process_time() - self._c
        self.server += (cpu_seconds(self.pid) - self._s) if self.pid else 0.0
        self.spans += 1

    def row(self, team: str, what: str) -> str:
        ms = {k: getattr(self, k) / self.spans * 1e3 for k in ("wall", "cpu", "server")}
        server = f"{ms['server']:>14.3f}" if self.pid else f"{'-':>14}"
        rest = f"{ms['wall'] - ms['server']:>17.3f}" if self.pid else f"{'-':>17}"
        return f"{team:<5} {what:<26} {ms['wall']:>8.3f} {ms['cpu']:>14.3f} {server} {rest}"


def time_env(env, steps: int, warmup: int, server_pid: int | None = None) -> Meter:
    """``env.step`` with random actions drawn before timing; episodes that end are reset
    outside the timed spans."""
    actions = [env.full_action_spec.rand() for _ in range(64)]
    td = env.reset()
    for i in range(warmup):
        td = env.step_and_maybe_reset(td.update(actions[i % len(actions)]))[1]
    meter = Meter(server_pid)
    for i in range(steps):
        td.update(actions[i % len(actions)])
        meter.start()
        out = env.step(td)
        meter.stop()
        td = out["next"].exclude("reward", "done", "terminated", "truncated")
        if out["next", "done"].any():
            td = env.reset()
    return meter


def time_advance(env, steps: int, warmup: int, server_pid: int) -> Meter:
    """``dynamics.advance`` alone (a hover command): the AirSim step without the env."""
    env.reset()
    hover = torch.zeros_like(env.dynamics.position)
    for _ in range(warmup):
        env.dynamics.advance(hover, env.control_period)
    meter = Meter(server_pid)
    for _ in range(steps):
        meter.start()
        env.dynamics.advance(hover, env.control_period)
        meter.stop()
    return meter


def time_wire(
    address: str, names: list[str], period: float, steps: int, warmup: int, pid: int
) -> Meter:
    """The calls of one lock-step step over a minimal blocking msgpack-rpc client: every
    move and the continue in one write, every state and collision read in another; the
    answers unpacked, the positions and velocities taken out as floats. What the protocol
    costs in Python, whatever the client library."""
    host, _, port = address.rpartition(":")
    sock = socket.create_connection((host, int(port)), 10)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    unpacker, answers, ids = msgpack.Unpacker(raw=False), {}, iter(range(1 << 30))

    def send(calls) -> list[int]:
        sent = [(next(ids), method, params) for method, params in calls]
        sock.sendall(b"".join(msgpack.packb([0, i, m, p]) for i, m, p in sent))
        return [i for i, _, _ in sent]

    def wait(wanted: list[int]) -> list:
        while not all(i in answers for i in wanted):
            unpacker.feed(sock.recv(1 << 16))
            for _, msgid, error, result in unpacker:
                answers[msgid] = (error, result)
        out = [answers.pop(i) for i in wanted]
        if any(error for error, _ in out):
            raise RuntimeError(f"the test server refused a call: {out}")
        return [result for _, result in out]

    wait(send([("simPause", [True])]))
    for name in names:
        wait(send([("enableApiControl", [True, name]), ("armDisarm", [True, name])]))
    yaw = {"is_rate": True, "yaw_or_rate": 0.0}
    meter = Meter(pid)
    for k in range(steps + warmup):
        if k == warmup:
            meter = Meter(pid)  # after a warm-up
        meter.start()
        moves = [("moveByVelocity", [0.0, 0.0, 0.0, period + 0.1, 0, yaw, n]) for n in names]
        (cont,) = send([*moves, ("simContinueForTime", [period])])[-1:]
        wait([cont])
        reads = [("getMultirotorState", [n]) for n in names]
        reads += [("simGetCollisionInfo", [n]) for n in names]
        results = wait(send(reads))
        for state in results[: len(names)]:
            kin, _ = state["kinematics_estimated"], int(state["timestamp"])
            _ = [float(kin[k][f"{a}_val"]) for k in ("position", "linear_velocity") for a in "xyz"]
        _ = [bool(hit["has_collided"]) for hit in results[len(names) :]]
        meter.stop()
        answers.clear()  # the moves' answers (each cancelled by the next)
    sock.close()
    return meter


def overhead(steps: int, warmup: int) -> None:
    print("Part 1: one simulator, one env; ms per step")
    print(
        f"{'team':<5} {'what':<26} {'wall ms':>8} {'client CPU ms':>14} {'server CPU ms':>14} "
        f"{'wall - server ms':>17}"
    )
    for team, overrides in TEAMS.items():
        servers = start_servers(1, overrides)
        try:
            ((proc, address),) = servers
            env = make_env(*overrides, "dynamics=airsim", f"dynamics.endpoints=[{address}]",
                           num_envs=1, split="test")  # fmt: skip
            print(time_env(env, steps, warmup, proc.pid).row(team, "env.step, airsim"), flush=True)
            advance = time_advance(env, steps, warmup, proc.pid)
            print(advance.row(team, "dynamics.advance, airsim"))
            names, period = list(env.dynamics.names), env.control_period
            env.close()
            wire = time_wire(address, names, period, steps, warmup, proc.pid)
            print(wire.row(team, "the same calls, bare wire"))
        finally:
            stop_servers(servers)
        embedded = time_env(make_env(*overrides, num_envs=1, split="test"), steps, warmup)
        print(embedded.row(team, "env.step, velocity"), flush=True)


def parallel(counts: list[int], steps: int) -> None:
    print("Part 2: N simulators, one env each (1 v 1; N > 1: a ParallelEnv of N worker processes)")
    print(f"{'N':>3} {'env steps/s':>12} {'ms per batch step':>18} {'main CPU ms':>12}")
    servers = start_servers(max(counts), ())
    try:
        for n in counts:
            endpoints = ",".join(address for _, address in servers[:n])
            env = make_env("dynamics=airsim", f"dynamics.endpoints=[{endpoints}]",
                           "env.time_limit=1000", num_envs=n, split="test")  # fmt: skip
            env.rollout(5, break_when_any_done=False)  # warm-up (workers started)
            meter = Meter()
            meter.start()
            env.rollout(steps, break_when_any_done=False)
            meter.stop()
            env.close()
            wall, cpu = meter.wall / steps, meter.cpu / steps
            print(f"{n:>3} {n / wall:>12.0f} {wall * 1e3:>18.2f} {cpu * 1e3:>12.2f}", flush=True)
    finally:
        stop_servers(servers)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000, help="timed env steps per row")
    parser.add_argument("--warmup", type=int, default=200, help="untimed steps before each row")
    parser.add_argument("--servers", type=int, nargs="+", default=[1, 2, 4])
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, {os.cpu_count()} CPUs")
    overhead(args.steps, args.warmup)
    parallel(args.servers, max(50, args.steps // 4))


if __name__ == "__main__":
    main()
