"""Env throughput: env.step through the TorchRL API with random actions.

Prints, per dynamics, step mode and batch size N, env steps/s and agent-steps/s (steps/s x N),
the time of one step, the peak resident memory of the process and, on a GPU, the peak memory
allocated on the device while that row ran. The reference of each row is the bare dynamics
advance (the physics alone) measured in the same run, so the ratio column shows what the env
adds on top of the simulator. Modes: ``eager`` (the default env) and ``compiled``
(``env.compile_step=true``: the step's numerical work as one ``torch.compile`` program; the
``compile s`` column is the time of the first steps, compilation included). The actions are
drawn from the action spec before timing (64 of them, cycled), so a policy's cost is not
counted; done envs are reset as a collector would. ``--teams 1v1 2v1`` runs every row for each
team size (k attackers vs m defenders, a scenario set of each); ``agent-steps/s`` counts env
steps (one per pursuit), ``drone-steps/s`` every learning drone's step.

    .venv/bin/python benchmarks/env_throughput.py [--device cuda] [--sizes 1 4096] [--teams 1v1 2v1]
"""

from __future__ import annotations

import argparse
import resource
import time

import torch

from rlplat import make_env

MODES = {"eager": "false", "compiled": "true"}  # mode -> env.compile_step


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def peak_gpu_mib(device: str) -> str:
    if not device.startswith("cuda"):
        return "-"
    return f"{torch.cuda.max_memory_allocated() / 2**20:.0f}"


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_steps(env, steps: int, device: str) -> tuple[float, float]:
    """Seconds of the 5 warm-up steps (compilation included) and per step after them."""
    actions = [env.full_action_spec.rand() for _ in range(64)]
    td = env.reset()
    t0 = time.perf_counter()
    for i in range(5):
        td = env.step_and_maybe_reset(td.update(actions[i]))[1]
    sync(device)
    warmup = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(steps):
        td = env.step_and_maybe_reset(td.update(actions[i % len(actions)]))[1]
    sync(device)
    return warmup, (time.perf_counter() - t0) / steps


def time_physics(env, steps: int, device: str) -> float:
    """Seconds per dynamics.advance of one control period (the physics alone)."""
    cmd = torch.zeros_like(env.dynamics.position)
    for _ in range(3):
        env.dynamics.advance(cmd, env.control_period)
    sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        env.dynamics.advance(cmd, env.control_period)
    sync(device)
    return (time.perf_counter() - t0) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 256, 4096])
    parser.add_argument("--dynamics", nargs="+", default=["velocity", "quadrotor"])
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--seconds", type=float, default=3.0, help="time budget per row")
    parser.add_argument("--teams", nargs="+", default=["1v1"], help="KvM: k attackers, m defenders")
    parser.add_argument(
        "overrides", nargs="*", help="Hydra overrides, e.g. scenario.strategy_mix.nn=0"
    )
    args = parser.parse_args()
    teams = {}
    for team in args.teams:
        k, _, m = team.partition("v")
        if not (k.isdigit() and m.isdigit()):
            parser.error(f"--teams: expected KvM such as 2v1, got {team!r}")
        sizes = (f"scenario.attackers={k}", f"scenario.defenders={m}")
        teams[team] = (sizes, make_env(*args.overrides, *sizes, num_envs=1).scenario_set)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {args.device}")
    print(
        f"{'team':<5} {'dynamics':<10} {'mode':<9} {'N':>7} {'compile s':>10} {'step ms':>9} "
        f"{'steps/s':>9} {'agent-steps/s':>14} {'drone-steps/s':>14} {'physics ms':>11} "
        f"{'env/physics':>12} {'peak RSS MiB':>13} {'peak GPU MiB':>13}"
    )
    rows = [(t, d, mode, n) for t in teams for d in args.dynamics for mode in args.modes
            for n in args.sizes]  # fmt: skip
    for team, dyn, mode, n in rows:
        sizes, scenarios = teams[team]
        if args.device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        env = make_env(
            *args.overrides,
            *sizes,
            f"dynamics={dyn}",
            f"env.compile_step={MODES[mode]}",
            num_envs=n,
            scenarios=scenarios,
            device=args.device,
        )
        warmup, probe = time_steps(env, 3, args.device)
        steps = max(10, int(args.seconds / probe))
        step_s = time_steps(env, steps, args.device)[1]
        phys_s = time_physics(env, max(10, steps // 2), args.device)
        compile_s = f"{warmup:.1f}" if mode == "compiled" else "-"
        print(
            f"{team:<5} {dyn:<10} {mode:<9} {n:>7} {compile_s:>10} {step_s * 1e3:>9.3f} "
            f"{1 / step_s:>9.0f} {n / step_s:>14,.0f} "
            f"{n * env.team_size / step_s:>14,.0f} {phys_s * 1e3:>11.3f} "
            f"{step_s / phys_s:>12.2f} {peak_rss_mib():>13.0f} "
            f"{peak_gpu_mib(args.device):>13}"
        )


if __name__ == "__main__":
    main()
