"""How well pursuit_conform tells route flyers from evaders: the route lag fitted to the route
flyers, and the route deviation the observation reports for each kind of defender.

Every scenario of a split is flown by the route-intercept law (``drone=attacker_v11``'s env).
Per axis, the route flyers' mean acceleration over each control period is fitted by least
squares to ``rate * (c - v)``, c the setpoint follower's command and v the velocity at the
period's start; the lag of a first-order lag with that mean rate is ``-dt / ln(1 - rate dt)``.
Then the observation's ``route_deviation`` (feature 17) is summarised, by percentiles, for the
route flyers and the network defenders in play, after the take-off (from step 20).

    .venv/bin/python benchmarks/route_conformity.py [--scenarios DIR] [--split val]
"""

from __future__ import annotations

import argparse
import math

import torch

from rlplat import make_env
from rlplat.agents.policies import make_scripted_policy
from rlplat.envs.kinematics import follow_route
from rlplat.scenarios import ScenarioSet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default="data/scenarios/pursuit")
    parser.add_argument("--split", default="val")
    parser.add_argument("--steps", type=int, default=250)
    args = parser.parse_args()

    scenarios = ScenarioSet.load(args.scenarios)
    n = len(scenarios.split(args.split))
    env = make_env("drone=attacker_v11", scenarios=scenarios, split=args.split, num_envs=n)
    if env.num_attackers != 1 or env.num_defenders != 1:
        raise SystemExit("route_conformity: needs a 1-vs-1 scenario set")
    law, dt = make_scripted_policy("route_intercept", env), env.control_period
    td = env.reset()
    network = env.nn_defender[:, 0].clone()
    error, accel, deviation, playing = [], [], [], []
    ended = torch.zeros(n, dtype=torch.bool)  # the episode is over: the rest is not counted
    for _ in range(args.steps):
        p, v = td["positions"][:, 1], td["velocities"][:, 1]
        command = follow_route(p, td["setpoints"][:, 0], td["route_done"][:, 0],
                               td["max_speed"][:, 1], env.setpoint_gain)  # fmt: skip
        live = ~ended & ~td["caught"][:, 0]
        td = env.step(law(td))["next"]
        ended = ended | td["done"][:, 0]
        error.append(command - v)
        accel.append(td["accelerations"][:, 1])
        deviation.append(td["observation"][:, 17])
        playing.append(live)
    error, accel = torch.stack(error, 1), torch.stack(accel, 1)
    deviation, playing = torch.stack(deviation, 1), torch.stack(playing, 1)

    route = playing & ~network.unsqueeze(1)
    print(f"{n} scenarios of {args.scenarios} ({args.split}), {int((~network).sum())} route "
          f"flyers; configured route_lag {list(env.obs_fn.route_lag)} s\n")  # fmt: skip
    print("| axis | fitted mean rate [1/s] | lag [s] |\n|---|---|---|")
    for axis, name in enumerate("xyz"):
        e, a = error[..., axis][route], accel[..., axis][route]
        rate = float((e * a).sum() / (e * e).sum())
        lag = -dt / math.log(1.0 - rate * dt) if 0 < rate * dt < 1 else float("nan")
        print(f"| {name} | {rate:.3f} | {lag:.2f} |")
    # The percentiles a gate on the deviation (action.gate_low, gate_high) is set from.
    levels = (0.1, 0.25, 0.5, 0.9, 0.99, 0.999)
    header = " | ".join(f"p{100 * q:g}" for q in levels)
    print(f"\nroute_deviation [m/s^2] by percentile\n\n| defender | {header} |")
    print("|---|" + "---|" * len(levels))
    for kind, rows in (("route flyer", ~network), ("network", network)):
        seen = deviation[:, 20:][(playing & rows.unsqueeze(1))[:, 20:]]
        if seen.numel():
            q = torch.quantile(seen, torch.tensor(levels))
            print(f"| {kind} | " + " | ".join(f"{x:.2f}" for x in q.tolist()) + " |")


if __name__ == "__main__":
    main()
