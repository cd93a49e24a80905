"""The route-intercept meeting point's cost in an evaluation: full search against the search in
blocks and the skip of ended episodes, with the captures they give.

An env whose action or observation reads the meeting point (``attacker_v10`` on) searches, for
every attacker and every step, the defender's route path at every instant up to the time
limit (``rlplat.envs.kinematics.route_intercept``). Three ways, timed in the same run:

- ``full``: every instant for every env (no env skipped: the reference, and the default off
  the CPU, ``kinematics.blocked_search``);
- ``blocks``: the instants in blocks (``SEARCH_BLOCKS``), a block searched only by the
  pursuers without a point yet;
- ``blocks + skip``: as well, an env stepped past its episode's end (an evaluation's wave
  flies until its last episode ends) keeps its last point (the default on the CPU).

Each replays the split (``rlplat.eval.episodes.evaluate``) with the checkpoint of ``--run-dir``
(or the route-intercept law, without one) and must give the same episodes as ``full``.

    .venv/bin/python benchmarks/meeting_point.py [--run-dir runs/v11-s0] [--scenarios
        data/scenarios/pursuit] [--split val] [--drone attacker_v11] [--repeat 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import hashlib
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from rlplat import make_env
from rlplat.agents.checkpoint import actor_from_state, load_checkpoint
from rlplat.agents.policies import make_scripted_policy
from rlplat.envs import kinematics, pursuit
from rlplat.envs.pursuit import PursuitEnv
from rlplat.eval.episodes import evaluate
from rlplat.experiment.factory import build_eval_env
from rlplat.scenarios import ScenarioSet

SKIP, BLOCKED = PursuitEnv.meeting, kinematics.blocked_search


def blocks(on: bool):
    """``kinematics.blocked_search`` answering ``on`` on every device (uncompiled)."""
    return lambda device: on and not torch.compiler.is_compiling()


def no_skip(self, p, v, running=None):
    """:meth:`PursuitEnv.meeting` searching every env, whether its episode has ended or not."""
    return SKIP(self, p, v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, default=None, help="a trained run to fly")
    parser.add_argument("--scenarios", default="data/scenarios/pursuit")
    parser.add_argument("--split", default="val")
    parser.add_argument("--drone", default="attacker_v11", help="the law's env, without --run-dir")
    parser.add_argument("--repeat", type=int, default=2, help="replays per way (the least)")
    parser.add_argument("--device", default="cpu", help="torch device of the env and the policy")
    args = parser.parse_args()
    device = torch.device(args.device)

    scenarios = ScenarioSet.load(args.scenarios)
    n = len(scenarios.split(args.split))
    if args.run_dir is None:
        env = make_env(f"drone={args.drone}", "env.scenario_order=sequential", device=device,
                       scenarios=scenarios, split=args.split, num_envs=n)  # fmt: skip
        policy, name = make_scripted_policy("route_intercept", env), "route_intercept"
    else:  # the run's own env (as evaluate.py builds it) and its best checkpoint
        cfg = OmegaConf.load(args.run_dir / "config.yaml")
        env = build_eval_env(cfg, scenarios=scenarios, split=args.split, num_envs=n, device=device)
        state = load_checkpoint(args.run_dir / "checkpoints" / "best.pt")
        policy = actor_from_state(state, env.drone_action_spec, device, env.group)
        name = f"{args.run_dir}/checkpoints/best.pt"
    ways = {"full": (blocks(False), no_skip), "blocks": (blocks(True), no_skip),
            "blocks + skip": (blocks(True), SKIP)}  # fmt: skip
    print(f"{args.scenarios} {args.split}: {n} envs, {name}, {device}, "
          f"{torch.get_num_threads()} threads")  # fmt: skip
    print(
        f"| search | replay s (least of {args.repeat}) | against full | capture rate | episodes |"
    )
    print("|---|---|---|---|---|")
    reference, digest = None, None
    for way, (blocked, meeting) in ways.items():
        kinematics.blocked_search = pursuit.blocked_search = blocked
        PursuitEnv.meeting = meeting
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            with torch.no_grad():
                results = evaluate(env, policy)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            times.append(time.perf_counter() - t)
        h = hashlib.sha256()
        for key in ("captured", "returns", "length", "min_distance"):
            h.update(getattr(results, key).cpu().numpy().tobytes())
        digest = digest or h.hexdigest()
        reference = reference or min(times)
        same = "same" if h.hexdigest() == digest else "DIFFERENT"
        print(f"| {way} | {min(times):.2f} | {reference / min(times):.2f}x | "
              f"{results.captured.float().mean():.4f} | {same} |")  # fmt: skip
    kinematics.blocked_search = pursuit.blocked_search = BLOCKED
    PursuitEnv.meeting = SKIP
    print(f"default on {device}: {'blocks + skip' if BLOCKED(device) else 'full'}")


if __name__ == "__main__":
    main()
