"""Whether the network defender is mirror-symmetric: its command in a mirrored state against the
mirror of its command, on the states it meets on a split.

The embedded dynamics (per axis, the same limits on both horizontal axes), the attacker's vision
ellipsoid (axis-aligned), the route follower and the route-intercept law all commute with
mirroring the world in x or in y, so a transition mirrored in x or y is one the env could have
made, except where a drone flies the defender network: there it is one only if the network
commutes too. This flies a split (as ``benchmarks/defender_stalls.py``: a run's checkpoint in
every seat, or a baseline), records every ``--every``-th step's states of the defenders flying
the network (route not done, episode going on), and for each mirror ``g`` compares the network's
command ``a(s)`` with ``g^-1 a(g s)``: the median and 90th percentile of their horizontal
difference relative to the command's horizontal size, and the fraction of states where they
differ by more than ``--tolerance`` of the defender's maximum speed. The x-y swap is shown for
the network alone: the ellipsoid's semi-axes differ in x and y, so it is no symmetry of the env.

    .venv/bin/python benchmarks/defender_symmetry.py RUN_DIR --scenarios data/scenarios/pursuit \\
        [--split val] [--policy checkpoint|proportional_navigation|pure_pursuit|route_intercept]
        [--every 10] [--tolerance 0.1]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging

import torch
from torch import Tensor, nn

from rlplat.envs.components import DroneView
from rlplat.envs.pursuit import ROLES
from rlplat.errors import RlplatError
from rlplat.eval.episodes import evaluate
from rlplat.experiment.evaluation import flight_arguments, flown_split

#: name: (signs of x, y, z; the axes' order), each its own inverse
MIRRORS = {
    "x -> -x": ((-1.0, 1.0, 1.0), (0, 1, 2)),
    "y -> -y": ((1.0, -1.0, 1.0), (0, 1, 2)),
    "x, y -> -x, -y": ((-1.0, -1.0, 1.0), (0, 1, 2)),
    "x <-> y": ((1.0, 1.0, 1.0), (1, 0, 2)),
}


def tensors(view: DroneView) -> dict[str, Tensor]:
    """The view's tensor fields by name (the unset ones, None, left out)."""
    fields = ((f.name, getattr(view, f.name)) for f in dataclasses.fields(view))
    return {name: value for name, value in fields if isinstance(value, Tensor)}


def mirror(view: DroneView, signs: Tensor, order: list[int]) -> DroneView:
    """The view with every world-frame 3-vector mirrored (scalars as they are)."""
    vectors = {k: v[..., order] * signs for k, v in tensors(view).items() if v.shape[-1:] == (3,)}
    return dataclasses.replace(view, **vectors)


class Recorder(nn.Module):
    """The env's defender network, recording every ``every``-th call's views of the rows whose
    defender flies it (its route not done) in an episode that goes on; the network's output is
    returned unchanged."""

    def __init__(self, network: nn.Module, env, every: int) -> None:
        super().__init__()
        self.network, self.every = network, every
        # (N,) bool: a network defender flying it (its route not done) in an episode that goes
        # on; read at each call (the env replaces these tensors as it steps)
        self.flies = lambda: env.nn_defender[:, 0] & ~env._target()[1][:, 0] & ~env.ended
        self.views: list[DroneView] = []
        self.calls = 0

    def forward(self, view: DroneView) -> Tensor:
        if self.calls % self.every == 0:
            rows = self.flies()
            kept = {k: v[rows].clone() for k, v in tensors(view).items()}
            self.views.append(dataclasses.replace(view, **kept))
        self.calls += 1
        return self.network(view)


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def fraction(text: str) -> float:
    value = float(text)
    if not 0 < value <= 2:
        raise argparse.ArgumentTypeError(f"must be a number in (0, 2], got {text!r}")
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    flight_arguments(parser, split="val")
    parser.add_argument("--every", type=positive_int, default=10, help="record every n-th step")
    parser.add_argument(
        "--tolerance", type=fraction, default=0.1, help="of the maximum speed, per command"
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    try:  # a bad run, set or policy: one line
        _, env, policy = flown_split(args.run_dir, args.scenarios, args.split, args.policy,
                                     args.ckpt)  # fmt: skip
    except RlplatError as e:
        raise SystemExit(f"defender_symmetry: {e}") from None
    n = env.batch_size[0]
    if ROLES[env.learner] != "attacker":
        raise SystemExit(f"defender_symmetry: {args.run_dir} trains a {ROLES[env.learner]}")
    if env.num_defenders != 1:
        raise SystemExit(f"defender_symmetry: one defender per scenario, got {env.num_defenders}")
    if env.defender_network is None:
        raise SystemExit(f"defender_symmetry: no defender of {args.scenarios} flies the network")
    network = env.defender_network
    recorder = Recorder(network, env, args.every)
    env.defender_network = recorder
    evaluate(env, policy)
    env.close()

    views = recorder.views
    recorded = [tensors(v) for v in views]
    view = dataclasses.replace(
        views[0], **{k: torch.cat([r[k] for r in recorded]) for k in recorded[0]}
    )
    with torch.no_grad():
        command = network(view)[..., :2]  # (S, 2), fractions of the maximum speed
        size = command.norm(dim=-1)
        kept = size > 1e-3
        flown = f"{args.run_dir}, {args.ckpt}" if args.policy == "checkpoint" else args.run_dir
        print(
            f"{args.policy} ({flown}) on {n} {args.split} scenarios of {args.scenarios}: "
            f"{len(size)} states of the network defenders (every {args.every}th step)\n"
        )
        print("| mirror | |a(s) - g^-1 a(g s)| / |a(s)|, median / p90 (horizontal) | "
              f"differ by more than {args.tolerance:g} of the maximum speed |")  # fmt: skip
        print("|---|---|---|")
        for name, (signs, order) in MIRRORS.items():
            s = torch.tensor(signs)
            mirrored = network(mirror(view, s, list(order)))
            back = (mirrored[..., list(order)] * s)[..., :2]  # g^-1: same signs, same swap
            diff = (back - command).norm(dim=-1)
            rel = (diff[kept] / size[kept]).quantile(torch.tensor([0.5, 0.9]))
            far = (diff > args.tolerance).float().mean()
            print(f"| {name} | {rel[0]:.2f} / {rel[1]:.2f} | {far:.3f} |")


if __name__ == "__main__":
    main()
