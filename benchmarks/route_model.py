"""How well the route path predicts a route-flying defender: median and 90th-percentile error.

Every scenario of a split is flown with the attackers holding still, so the defenders of the
``setpoints`` strategy fly their routes undisturbed. From each start time, the defender's path
is predicted from its position, velocity and route ahead (``rlplat.envs.kinematics.route_path``)
and compared with where it was after each horizon (defenders caught by then are left out):

- ``no lags``: full speed per axis from setpoint to setpoint;
- ``lags``: the law's model, ``setpoint_flight`` (velocity lag ``ROUTE_TAU``, the env's setpoint
  gain and acceptance radius).

    .venv/bin/python benchmarks/route_model.py [--scenarios data/scenarios/pursuit] [--split val]
"""

from __future__ import annotations

import argparse

import torch

from rlplat import make_env
from rlplat.envs.kinematics import route_ahead, route_path, setpoint_flight
from rlplat.scenarios import ScenarioSet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default="data/scenarios/pursuit")
    parser.add_argument("--split", default="val")
    parser.add_argument("--starts", type=float, nargs="+", default=[0.0, 10.0, 20.0])
    parser.add_argument("--horizons", type=float, nargs="+", default=[2.0, 5.0, 15.0, 30.0])
    args = parser.parse_args()

    scenarios = ScenarioSet.load(args.scenarios)
    n = len(scenarios.split(args.split))
    env = make_env("drone=attacker_v3", scenarios=scenarios, split=args.split, num_envs=n)
    k, dt = env.num_attackers, env.control_period
    td, hold = env.reset(), torch.zeros(env.action_spec.shape)
    position, velocity, waypoint, caught = [], [], [], []

    def keep() -> None:
        position.append(env.dynamics.position[:, k].clone())
        velocity.append(env.dynamics.velocity[:, k].clone())
        waypoint.append(env.waypoint.clone())
        caught.append(env.caught[:, 0].clone())

    keep()
    for _ in range(env.max_steps):
        td = env.step(td.set("action", hold))["next"]
        keep()
    position, velocity = torch.stack(position, 1), torch.stack(velocity, 1)
    caught = torch.stack(caught, 1)
    route_flyer, speed = ~env.nn_defender[:, 0], env.max_speed[:, k]
    models = {
        "no lags": {},
        "lags": {"flight": setpoint_flight(env.setpoint_gain, env.setpoint_acceptance)},
    }
    times = torch.tensor(args.horizons)
    first = torch.zeros(n, 1, dtype=torch.long)
    print(f"{args.scenarios} {args.split}: {int(route_flyer.sum())} route flyers, "
          f"starts {args.starts} s; error in m, median / 90th percentile")  # fmt: skip
    print("| model | " + " | ".join(f"{h:g} s" for h in args.horizons) + " |")
    print("|---" * (len(args.horizons) + 1) + "|")
    for name, kwargs in models.items():
        errors: list[list[torch.Tensor]] = [[] for _ in args.horizons]
        for start in args.starts:
            i = round(start / dt)
            ahead = route_ahead(env.routes[env.route], waypoint[i], first)[:, 0]
            vel = velocity[:, i] if kwargs else None
            path = route_path(position[:, i], ahead, speed, times, velocity=vel, **kwargs)
            for j, h in enumerate(args.horizons):
                end = i + round(h / dt)
                if end >= position.shape[1]:
                    continue
                ok = route_flyer & ~caught[:, end]
                errors[j].append((path[:, j] - position[:, end]).norm(dim=-1)[ok])
        cells = []
        for e in errors:
            e = torch.cat(e)
            cells.append(f"{e.median():.1f} / {e.quantile(0.9):.1f}")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
