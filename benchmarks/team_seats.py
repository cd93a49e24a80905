"""Which seat of a team the learned correction helps: a policy trained alone, flown in every
seat of a team (``evaluate.py lone_in_team=true``), against variants where a seat flies only
the law its action corrects (a zero action).

A network defender sees only its nearest attacker, so the two seats of a 2-vs-1 team play
different parts: the nearer one is evaded, the farther one is not seen. Variants, each on the
whole split:

- ``policy``: every seat flies the checkpoint (the ``lone_in_team`` evaluation);
- ``far-law`` / ``near-law``: the seat farther from (nearer to) the defender flies the law;
- ``law``: every seat flies the law;
- ``near:D1:D2``: the correction is scaled by ``clamp((D2 - d) / (D2 - D1), 0, 1)``, d the
  seat's distance to the defender in m: whole within D1, none beyond D2 (a distance gate);
- ``head_off`` / ``far-head_off`` / ``near-head_off``: every seat (the farther, the nearer one)
  flies the checkpoint over the route law with ``unreachable=head_off``, the others with
  ``chase``, whichever the run was trained with (an ``action=route_law*`` run);
- ``home:R``: within R m of the defender a seat flies the law's homing (proportional
  navigation at the defender, no correction), farther the checkpoint over the law (a terminal
  phase; an ``action=route_law*`` run, on a set of one defender: the law's and the
  observation's distances are then to the same drone).
- ``far-offset:R:D`` / ``near-offset:R:D``: the seat farther from (nearer to) the defender
  flies, without a correction, proportional navigation aimed R m beside the defender (the
  side it flies towards) until within D m (``benchmarks/guidance_laws.py --offsets``), the
  other seats the checkpoint.

Team rules, each seat reading its team-mate's position from the team's observation (a
2-vs-1 set; the checkpoint flies every seat):

- ``apart:R:K``: each seat's command is pushed horizontally away from its team-mate, by
  ``K * (1 - s / R)`` times its maximum speed at a separation of s < R m (spacing);
- ``spread:A:K:D``: where the two seats see the defender within A degrees of each other
  (horizontally), each is pushed square to its line of sight, away from its team-mate, by up
  to K times its maximum speed (all of it where the bearings coincide, none at A), scaled
  down to none within D m of the defender (all of it from 2D): they come at it from apart;
- ``far-wait:D``: the seat farther from the defender flies, without a correction, to the
  defender's current setpoint of its route and waits there, until it is within D m of the
  defender; then the checkpoint (an ambush where the route takes the defender).

The pushes are added to the action (a correction of the law in units of ``action.scale``
times the maximum speed) and clipped to its bounds, so the route gate of ``attacker_v13``
and later applies to them as to the correction: they act where the defender leaves its
route.

Prints the capture rate of each variant, of the route flyers and of the network defenders.

    .venv/bin/python benchmarks/team_seats.py RUN_DIR --scenarios data/scenarios/pursuit2v1 \\
        [--split val] [--variants policy far-law near-law law near:10:20]
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import torch
from guidance_laws import aim_beside  # a script beside this one (benchmarks/)
from tensordict.nn import TensorDictModuleBase

from rlplat.agents.checkpoint import actor_from_state, load_checkpoint
from rlplat.agents.export import observation_key
from rlplat.envs.components import GuidedVelocityAction
from rlplat.envs.kinematics import pure_pursuit
from rlplat.errors import ConfigError
from rlplat.eval.episodes import evaluate
from rlplat.experiment.evaluation import check_policy_fits, checkpoint_path, load_run_config
from rlplat.experiment.factory import build_eval_env, eval_num_envs, resolve_scenarios
from rlplat.scenarios import STRATEGIES

#: The head-off variants: which seats fly the route law's ``unreachable=head_off``.
HEAD_OFF = {"head_off": "every", "far-head_off": "far", "near-head_off": "near"}


def nearest_seat(distance: torch.Tensor) -> torch.Tensor:
    """(*B, seats) bool: the seat nearest its defender (``distance``, (*B, seats) m; ties
    both), the one a network defender sees and evades."""
    return distance <= distance.amin(-1, keepdim=True)


class SeatVariant(TensorDictModuleBase):
    """The actor's action (*B, seats, A), each seat's correction scaled towards 0 (the law)
    as ``variant`` says; ``position`` is the slice of a seat's observation that holds the
    first defender's position relative to it (its distance decides the scale)."""

    def __init__(self, actor, variant: str, obs_key, action_key, position: slice,
                 mate: slice | None = None, scale: float = 1.0) -> None:  # fmt: skip
        super().__init__()
        self.actor, self.variant, self.position = actor, variant, position
        self.mate, self.action_scale = mate, scale  # the team-mate's relative position
        kind, *numbers = variant.split(":")
        self.rule = (kind, tuple(float(x) for x in numbers)) if kind in TEAM_RULES else None
        self.wait = float(numbers[0]) if kind == "far-wait" else None
        # near:D1:D2, read once (check_variant has checked it)
        self.gate = tuple(float(x) for x in variant.split(":")[1:]) if ":" in variant else None
        self.home = variant.startswith("home:")
        self.offset = variant.split(":")[0] if "-offset:" in variant else None
        self.obs_key, self.action_key = obs_key, action_key
        self.in_keys, self.out_keys = [obs_key], [action_key]

    def forward(self, td):
        td = self.actor(td)
        action = td.get(self.action_key)
        distance = td.get(self.obs_key)[..., self.position].norm(dim=-1)  # (*B, seats)
        nearest = nearest_seat(distance)
        if self.rule is not None:  # apart, spread: a push added to the action
            obs = td.get(self.obs_key)
            push = team_push(self.rule, obs[..., self.position], obs[..., self.mate])
            action = (action + push / self.action_scale).clamp(-1.0, 1.0)
            td.set(self.action_key, action)
            return td
        if self.variant == "policy":
            scale = torch.ones_like(distance)
        elif self.variant == "law":
            scale = torch.zeros_like(distance)
        elif self.variant == "far-law":
            scale = nearest.to(distance.dtype)
        elif self.variant == "near-law":
            scale = (~nearest).to(distance.dtype)
        elif self.offset is not None:  # the offset seat flies its law (seat_offset)
            scale = (nearest if self.offset == "far-offset" else ~nearest).to(distance.dtype)
        elif self.wait is not None:  # far-wait:D, the waiting seat flies its law (seat_wait)
            scale = (nearest | (distance <= self.wait)).to(distance.dtype)
        elif self.home:  # home:R, the law's homing within R (seat_home)
            scale = (distance >= self.gate[0]).to(distance.dtype)
        else:  # near:D1:D2
            low, high = self.gate
            scale = ((high - distance) / (high - low)).clamp(0.0, 1.0)
        td.set(self.action_key, action * scale.unsqueeze(-1))
        return td


#: The team rules that push each seat's command (``team_push``).
TEAM_RULES = ("apart", "spread")


def team_push(rule: tuple[str, tuple[float, ...]], rel: torch.Tensor, mate: torch.Tensor):
    """(*B, seats, 3) the push of a team rule, in units of the maximum speed, for seats whose
    defender is at ``rel`` and team-mate at ``mate`` (*B, seats, 3) m relative to them;
    horizontal, so that no rule flies a seat into the ground."""
    kind, numbers = rule
    rel, mate = rel[..., :2], mate[..., :2]
    own_to_mate = mate.norm(dim=-1, keepdim=True)
    if kind == "apart":
        radius, gain = numbers
        weight = gain * (1.0 - own_to_mate / radius).clamp_min(0.0)
        direction = -mate / own_to_mate.clamp_min(1e-6)
    else:  # spread
        angle, gain, near = numbers
        cos_a = math.cos(math.radians(angle))
        sight = rel / rel.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        mate_rel = rel - mate  # the defender relative to the team-mate
        mate_sight = mate_rel / mate_rel.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        aligned = ((sight * mate_sight).sum(-1, keepdim=True) - cos_a) / (1.0 - cos_a)
        distance = rel.norm(dim=-1, keepdim=True)
        weight = gain * aligned.clamp(0.0, 1.0) * ((distance - near) / near).clamp(0.0, 1.0)
        away = -mate - (-mate * sight).sum(-1, keepdim=True) * sight  # square to the sight line
        direction = away / away.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    push = weight * direction
    return torch.cat([push, torch.zeros_like(push[..., :1])], -1)


def seat_wait(env, within: float):
    """The action's guidance (``action_fn.guidance``'s signature) that, in the seat farther
    from its defender and farther than ``within`` m from it, flies to that defender's current
    setpoint (the law's gain per metre, clipped to the maximum speed per axis), and the
    action's own law in the others. Read from ``env`` (a 2-vs-1 env: one defender)."""
    action_fn = env.action_fn
    law = type(action_fn)

    def guidance(rel, v_other, max_speed, a_other=None, meeting=None):
        flown = law.guidance(action_fn, rel, v_other, max_speed, a_other, meeting)
        own = env.dynamics.position[:, env.attackers]
        setpoint = env._target()[0][:, :1].expand_as(own)
        command = pure_pursuit(own, setpoint, max_speed, action_fn.gain)  # m/s, saturated
        wait = command / max_speed.unsqueeze(-1).clamp_min(1e-6)
        distance = rel.norm(dim=-1)
        waits = ~nearest_seat(distance) & (distance > within)
        return torch.where(waits.unsqueeze(-1), wait, flown)

    return guidance


def seat_unreachable(action_fn, seats: str):
    """The route law's guidance (``action_fn.guidance``'s signature) that flies ``head_off``
    where no meeting point is reachable in ``seats`` (every, far or near: by the seat's distance
    to its defender) and ``chase`` in the others."""
    law, trained = type(action_fn), action_fn.unreachable

    def guidance(rel, v_other, max_speed, a_other=None, meeting=None):
        flown = {}
        for mode in ("chase", "head_off"):
            action_fn.unreachable = mode
            flown[mode] = law.guidance(action_fn, rel, v_other, max_speed, a_other, meeting)
        action_fn.unreachable = trained
        nearest = nearest_seat(rel.norm(dim=-1))
        heads_off = {"every": torch.ones_like(nearest), "far": ~nearest, "near": nearest}[seats]
        return torch.where(heads_off.unsqueeze(-1), flown["head_off"], flown["chase"])

    return guidance


def seat_home(action_fn, radius: float):
    """The route law's guidance (``action_fn.guidance``'s signature) that flies the law's
    homing (proportional navigation at the defender) in the seats within ``radius`` m of their
    defender and the law in the others."""
    law = type(action_fn)

    def guidance(rel, v_other, max_speed, a_other=None, meeting=None):
        flown = law.guidance(action_fn, rel, v_other, max_speed, a_other, meeting)
        homing = GuidedVelocityAction.guidance(action_fn, rel, v_other, max_speed)
        return torch.where((rel.norm(dim=-1) < radius).unsqueeze(-1), homing, flown)

    return guidance


def seat_offset(action_fn, seat: str, offset: float, within: float):
    """The action's guidance (``action_fn.guidance``'s signature) that, in the ``seat`` (far
    or near) farther from (nearer to) its defender, flies proportional navigation at a point
    ``offset`` m beside it (horizontally, square to the line of sight, on the side it flies
    towards) until within ``within`` m, and the action's own law in the others."""
    law = type(action_fn)

    def guidance(rel, v_other, max_speed, a_other=None, meeting=None):
        flown = law.guidance(action_fn, rel, v_other, max_speed, a_other, meeting)
        aim = aim_beside(rel, v_other, offset, within)
        beside = GuidedVelocityAction.guidance(action_fn, aim, v_other, max_speed)
        nearest = nearest_seat(rel.norm(dim=-1))
        flies = ~nearest if seat == "far" else nearest
        return torch.where(flies.unsqueeze(-1), beside, flown)

    return guidance


def check_variant(variant: str) -> str:
    if variant in ("policy", "law", "far-law", "near-law", *HEAD_OFF):
        return variant
    parts = variant.split(":")
    if parts[0] in ("far-offset", "near-offset"):
        try:
            offset, within = (float(x) for x in parts[1:])
        except ValueError:
            offset = within = float("nan")
        if not (0 < offset < float("inf") and 0 < within < float("inf")):
            raise argparse.ArgumentTypeError(
                f"variant: {parts[0]}:R:D with finite R, D > 0 m, got {variant!r}"
            )
        return variant
    rule = {"apart": ("R:K", 2), "spread": ("A:K:D", 3), "far-wait": ("D", 1)}.get(parts[0])
    if rule is not None:
        shape, count = rule
        try:
            numbers = [float(x) for x in parts[1:]]
        except ValueError:
            numbers = []
        if (
            len(numbers) != count
            or not all(0 < x < float("inf") for x in numbers)
            or (parts[0] == "spread" and not numbers[0] < 180)
        ):
            raise argparse.ArgumentTypeError(
                f"variant: {parts[0]}:{shape} with finite numbers > 0"
                f"{' (A < 180 degrees)' if parts[0] == 'spread' else ''}, got {variant!r}"
            )
        return variant
    if parts[0] == "home":
        try:
            radius = float(parts[1]) if len(parts) == 2 else float("nan")
        except ValueError:
            radius = float("nan")
        if not 0 < radius < float("inf"):
            raise argparse.ArgumentTypeError(f"variant: home:R with 0 < R < inf m, got {variant!r}")
        return variant
    try:
        low, high = (float(x) for x in parts[1:])
    except ValueError:
        low = high = float("nan")
    if parts[0] != "near" or len(parts) != 3 or not 0 <= low < high:
        raise argparse.ArgumentTypeError(
            f"variant: policy, law, far-law, near-law, {', '.join(HEAD_OFF)}, home:R, "
            "far-offset:R:D, near-offset:R:D, apart:R:K, spread:A:K:D, far-wait:D or "
            f"near:D1:D2 with 0 <= D1 < D2, got {variant!r}"
        )
    return variant


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a training run trained alone (one attacker)")
    parser.add_argument("--scenarios", required=True, help="a team's scenario set")
    parser.add_argument("--split", default="val", choices=("train", "val", "test"))
    parser.add_argument("--ckpt", default="best", choices=("best", "last"))
    parser.add_argument(
        "--variants", nargs="+", type=check_variant,
        default=["policy", "far-law", "near-law", "law"],
    )  # fmt: skip
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    cfg = load_run_config(args.run_dir)
    path = checkpoint_path(args.run_dir, args.ckpt)
    state = load_checkpoint(path)
    scenarios = resolve_scenarios(cfg, args.scenarios)
    n = len(scenarios.split(args.split))
    env = build_eval_env(cfg, scenarios=scenarios, split=args.split,
                         num_envs=eval_num_envs(cfg, n))  # fmt: skip
    if getattr(env.action_fn, "corrects", None) is None:
        raise SystemExit(f"team_seats: action={cfg.action.name} corrects no law")
    law_variants = [v for v in args.variants if v in HEAD_OFF or v.startswith("home:")]
    if law_variants and not hasattr(env.action_fn, "unreachable"):
        raise SystemExit(f"team_seats: {', '.join(law_variants)} need action=route_law*, "
                         f"got action={cfg.action.name}")  # fmt: skip
    try:
        features = check_policy_fits(state, cfg, env, path, lone_in_team=True)
    except ConfigError as error:
        raise SystemExit(f"team_seats: {error}") from None
    names = [f["name"] for f in env.obs_fn.features()]
    if "(p_opponent0 - p_own).x" not in names:
        raise SystemExit(f"team_seats: observation={cfg.observation.name} has no relative position")
    at = names.index("(p_opponent0 - p_own).x")
    team_rules = [v for v in args.variants if v.split(":")[0] in (*TEAM_RULES, "far-wait")]
    if team_rules and "(p_mate0 - p_own).x" not in names:
        raise SystemExit(
            f"team_seats: {', '.join(team_rules)} need a team (a team-mate's position in the "
            f"observation), got {env.num_attackers} attacker(s)"
        )
    mate = names.index("(p_mate0 - p_own).x") if team_rules else at
    actor = actor_from_state(state, env.drone_action_spec, "cpu", env.group, features)
    network = scenarios.split(args.split)["defender_strategy"][:, 0] == STRATEGIES.index("nn")

    route, nets = int((~network).sum()), int(network.sum())
    print(f"{cfg.drone.name} ({args.run_dir}, {args.ckpt}) in each of {env.num_attackers} "
          f"seats, {n} {args.split} scenarios of {args.scenarios}: "
          f"{route} route flyers, {nets} network defenders\n")  # fmt: skip
    print("| variant | captured | route flyers | network defenders |")
    print("|---|---|---|---|")
    for variant in args.variants:
        if variant in HEAD_OFF:  # the whole checkpoint, over a law that heads off in some seats
            env.action_fn.guidance = seat_unreachable(env.action_fn, HEAD_OFF[variant])
            results = evaluate(env, actor)
            del env.action_fn.guidance  # the class's again
        else:
            if variant.startswith("home:"):
                env.action_fn.guidance = seat_home(env.action_fn, float(variant.split(":")[1]))
            if variant.startswith("far-wait:"):
                env.action_fn.guidance = seat_wait(env, float(variant.split(":")[1]))
            if "-offset:" in variant:
                seat, offset, within = variant.split(":")
                env.action_fn.guidance = seat_offset(env.action_fn, seat.split("-")[0],
                                                     float(offset), float(within))  # fmt: skip
            module = SeatVariant(actor, variant, observation_key(env.group), env.action_key,
                                 slice(at, at + 3), slice(mate, mate + 3),
                                 env.action_fn.scale)  # fmt: skip
            results = evaluate(env, module)
            env.action_fn.__dict__.pop("guidance", None)  # the class's again
        captured = results.captured  # one row per scenario of the split, in order
        rates = [captured.float().mean(), captured[~network].float().mean(),
                 captured[network].float().mean()]  # fmt: skip
        print(f"| {variant} | " + " | ".join(f"{r:.4f}" for r in rates) + " |")
    env.close()


if __name__ == "__main__":
    main()
