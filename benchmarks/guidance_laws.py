"""How good can a guidance law get on a scenario set: a grid of proportional-navigation laws.

Flies every law of a grid (gain x lead x longest prediction x acceleration lead,
:class:`ProportionalNavigation`; lead 0 is pure pursuit, an acceleration lead above 0 the
augmented law that aims with the target's velocity ``v + accel_lead * a``) over the validation
and the test split of the configured set, on the run's plain velocity action, and prints one
markdown table:

- each law's capture rate on both splits, overall and per defender strategy (``setpoints``:
  the defender flies its route; ``nn``: the defender network reacts to the attacker);
- the law with the best validation capture rate, flown on test (a law chosen on validation: what
  tuning a closed-form law buys, measured on scenarios it was not chosen on);
- the union: the scenarios that some law of the grid captures. No single policy is bound by it,
  but it is reachable scenario by scenario (each of its captures was flown), so it bounds the
  best achievable rate from below: on route-flying defenders next to the capture ceiling
  (:mod:`rlplat.eval.ceiling`, the bound from above), on network defenders where no ceiling is
  defined.

- with ``--offsets R:D ...``, the default law flown off to one side (:class:`Offset`): aimed
  R m beside the defender, on the side it flies towards, until within D m, then the law itself.
  The searched plays of ``team_search.py`` that capture network defenders fly so (fast, at a
  point a median 15 m from the defender horizontally); this is one law of that shape.

    .venv/bin/python benchmarks/guidance_laws.py [overrides ...] [--gains 1 2 5] \
        [--leads 0.5 0.75 1 1.5] [--horizons 4 8 16] [--accel-leads 0 0.9] [--offsets 10:12]

Overrides are ``train.py``'s (e.g. ``scenarios_dir=DIR``, ``scenario=pursuit_2v1``). About 10 s
per law on one CPU thread for the default set (2,000 validation and 500 test scenarios).
"""

from __future__ import annotations

import argparse
import itertools
import math
import subprocess

import torch
from tensordict.nn import TensorDictModule

from rlplat.agents.policies import ProportionalNavigation, make_scripted_policy
from rlplat.envs.kinematics import gather_drones, intercept_action
from rlplat.eval.episodes import evaluate
from rlplat.experiment.config import compose_config
from rlplat.experiment.evaluation import plain_action, split_ceiling
from rlplat.experiment.factory import build_env, resolve_scenarios
from rlplat.scenarios import STRATEGIES

SPLITS = ("val", "test")


class Offset(ProportionalNavigation):
    """Proportional navigation at a point ``offset`` m beside each attacker's nearest defender
    (horizontally, square to the line of sight, on the side the defender flies towards); the
    law itself within ``within`` m of the defender. Where the defender hovers or flies along the
    line of sight, the side is the attacker's left (counter-clockwise seen from above)."""

    def __init__(self, *, offset: float, within: float, **law) -> None:
        super().__init__(**law)
        self.offset, self.within = offset, within

    def forward(self, positions, velocities, max_speed, caught):
        own, speed, near = self._nearest(positions, max_speed, caught)
        rel = gather_drones(positions[:, self.others], near) - own
        v_other = gather_drones(velocities[:, self.others], near)
        aim = aim_beside(rel, v_other, self.offset, self.within)
        action = intercept_action(aim, v_other, speed, self.gain, self.lead, self.max_lead_time)
        return self._action(action)


def aim_beside(rel: torch.Tensor, v_other: torch.Tensor, offset: float, within: float):
    """The defender's position relative to the attacker (``rel``, (..., 3)) moved ``offset`` m
    beside it (:class:`Offset`), where it is ``within`` m or farther; ``rel`` nearer."""
    side = torch.stack([-rel[..., 1], rel[..., 0], torch.zeros_like(rel[..., 0])], -1)
    side = side / side.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    side = torch.where((side * v_other).sum(-1, keepdim=True) < 0, -side, side)
    far = rel.norm(dim=-1, keepdim=True) >= within
    return torch.where(far, rel + offset * side, rel)


def captures(
    env,
    gain: float,
    lead: float,
    horizon: float,
    accel: float,
    offset: float = 0.0,
    within: float = 0.0,
) -> torch.Tensor:
    """(E,) bool per scenario of ``env``'s split: captured by the law."""
    args = {"gain": gain, "lead": lead, "max_lead_time": horizon, "accel_lead": accel}
    if offset:
        module = Offset(offset=offset, within=within, learner="attacker",
                        attackers=env.num_attackers, defenders=env.num_defenders,
                        team=env.group is not None, **args)  # fmt: skip
        law = TensorDictModule(module, in_keys=list(module.in_keys), out_keys=[env.action_key])
    else:
        law = make_scripted_policy("proportional_navigation", env, **args)
    result = evaluate(env, law)
    out = torch.zeros(len(env.scenarios), dtype=torch.bool)
    out[result.scenario_index] = result.captured
    return out


def rates(captured: torch.Tensor, network: torch.Tensor) -> str:
    """``all / setpoints / nn`` capture rates."""
    parts = [captured, captured[~network], captured[network]]
    return " | ".join(f"{p.float().mean().item():.3f}" for p in parts)


def offset_arg(text: str) -> tuple[float, float]:
    """``R:D`` of ``--offsets``: metres beside the defender, and beyond how far."""
    try:
        offset, within = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give R:D, e.g. 10:12") from None
    if not (0 < offset < math.inf and 0 < within < math.inf):
        raise argparse.ArgumentTypeError(f"{text!r}: R and D finite metres > 0")
    return offset, within


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="train.py overrides")
    parser.add_argument("--gains", type=float, nargs="+", default=[1.0, 2.0, 5.0])
    parser.add_argument("--leads", type=float, nargs="+", default=[0.5, 0.75, 1.0, 1.5])
    parser.add_argument("--horizons", type=float, nargs="+", default=[4.0, 8.0, 16.0])
    parser.add_argument("--accel-leads", type=float, nargs="+", default=[0.0])
    parser.add_argument(
        "--offsets",
        type=offset_arg,
        nargs="+",
        default=[],
        help="R:D, the default law aimed R m beside the defender beyond D m",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)

    cfg = plain_action(compose_config("train", args.overrides))
    scenarios = resolve_scenarios(cfg, cfg.scenarios_dir)
    envs, network = {}, {}
    for split in SPLITS:
        n = len(scenarios.split(split))
        envs[split] = build_env(cfg, scenarios=scenarios, split=split, num_envs=n,
                                scenario_order="sequential")  # fmt: skip
        strategy = scenarios.split(split)["defender_strategy"]
        network[split] = (strategy == STRATEGIES.index("nn")).any(-1)

    default = (float(cfg.env.pursuit_gain), 0.5, 4.0, 0.0, 0.0, 0.0)
    grid = itertools.product(args.gains, args.leads, args.horizons, args.accel_leads, [0.0], [0.0])
    laws = [default] + [law for law in grid if law != default]
    laws += [(*default[:4], offset, within) for offset, within in args.offsets]
    table = {law: {s: captures(envs[s], *law) for s in SPLITS} for law in laws}

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    print(f"commit {commit}; {len(laws)} laws; scenario set {scenarios.digest[:12]}; "
          f"capture rate: all | setpoints | nn\n")  # fmt: skip
    print(
        "| gain [1/s] | lead | longest prediction [s] | acceleration lead [s] | beside [m] "
        "(beyond [m]) | validation: all | setpoints | nn | test: all | setpoints | nn |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for law, caps in table.items():
        tag = " (the default law)" if law == default else ""
        beside = f"{law[4]:g} ({law[5]:g})" if law[4] else "–"
        print(
            f"| {law[0]:g} | {law[1]:g} | {law[2]:g} | {law[3]:g}{tag} | {beside} | "
            f"{rates(caps['val'], network['val'])} | {rates(caps['test'], network['test'])} |"
        )

    best = max(laws, key=lambda law: table[law]["val"].float().mean().item())
    print(f"\nChosen on validation: gain {best[0]:g}, lead {best[1]:g}, longest prediction "
          f"{best[2]:g} s, acceleration lead {best[3]:g} s, beside {best[4]:g} m; "
          f"on test: {rates(table[best]['test'], network['test'])}")  # fmt: skip
    for split in SPLITS:
        union = torch.stack([table[law][split] for law in laws]).any(0)
        ceiling, _ = split_ceiling(cfg, envs[split], scenarios, split, "cpu")
        print(
            f"Union of the grid on {split}: {rates(union, network[split])}; capture ceiling "
            f"on route-flying defenders {ceiling[~network[split]].mean().item():.3f}"
        )


if __name__ == "__main__":
    main()
