"""Trained controllers as plain torch modules: a checkpoint's deterministic policy, flown by the
env for a drone that does not learn (the defender's ``nn`` strategy), and the small files the
package ships them in.

``python -m rlplat.agents.controller RUN_DIR OUT.pt`` exports a run's best policy as such a file
and writes its card, ``OUT.json``: the policy and the scripted baselines of its drone evaluated
on the test split.
"""

from __future__ import annotations

import argparse
import json
import logging
from importlib import resources
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torchrl.data import Bounded

from rlplat.agents.checkpoint import (
    actor_from_state,
    load_checkpoint,
    save_checkpoint,
    saved_interface,
)
from rlplat.envs.components import OBSERVATIONS, DroneView
from rlplat.errors import ConfigError
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)

#: The defender network the package ships: ``nn`` defenders fly it unless the config names
#: another checkpoint (``env.defender_network``). Its evaluation is in ``defender_v1.json``.
SHIPPED_DEFENDER = "defender_v1.pt"


def shipped_path(name: str) -> Path:
    """Path of a controller file shipped in ``rlplat/agents/weights/``."""
    return Path(str(resources.files("rlplat.agents") / "weights" / name))


class NetworkController(nn.Module):
    """A trained actor's deterministic action as a function of what its drone sees.

    ``forward(view)`` builds the observation the network was trained on (the checkpoint's
    ``observation`` config) from a :class:`DroneView` and returns the action (N, action_dim) in
    [-1, 1]: the squashed mean of the actor's ``TanhNormal``, as ``ExplorationType.DETERMINISTIC``
    gives it, without tensordicts, so that it runs inside a compiled env step.

    Args:
        state: a loaded checkpoint (:func:`rlplat.agents.checkpoint.load_checkpoint`) of a run
            or an exported controller.
        role: the drone it must have been trained to fly.
        where: the config field named in errors.
    """

    def __init__(self, state: dict[str, Any], role: str, where: str) -> None:
        super().__init__()
        interface = saved_interface(state)
        learner = interface.get("drone.learner")
        if learner != role:
            raise ConfigError(f"{where}: the checkpoint flies the {learner}, not the {role}")
        team = interface["attackers"], interface["defenders"]
        if team != (1, 1):
            raise ConfigError(
                f"{where}: the network was trained with {team[0]} attackers and {team[1]} "
                "defenders; a scripted drone flies a 1-vs-1 network (it sees its nearest opponent)"
            )
        node = dict(state["config"]["observation"])
        name = node.pop("name")
        if name not in OBSERVATIONS:
            raise ConfigError(f"{where}: unknown observation '{name}' in the checkpoint")
        self.observation = OBSERVATIONS[name](**node)
        if self.observation.dim != state["net"]["obs_dim"]:
            raise ConfigError(
                f"{where}: observation '{name}' has {self.observation.dim} features, the "
                f"network takes {state['net']['obs_dim']}"
            )
        dim = state["net"]["action_dim"]
        actor = actor_from_state(state, Bounded(-1.0, 1.0, shape=(dim,)))
        self.body = actor.module[0].module[0]  # Scaled(MLP): observation -> (loc, raw scale)
        self.dim, self.margin = dim, float(state["net"].get("action_margin", 0.0))
        self.requires_grad_(False)

    def forward(self, view: DroneView) -> Tensor:
        loc = self.body(self.observation(view))[..., : self.dim]
        return ((1.0 + self.margin) * torch.tanh(loc)).clamp(-1.0, 1.0)


def load_controller(path: str | Path | None, role: str, where: str) -> NetworkController:
    """The controller in checkpoint ``path`` (None = the shipped one of ``role``)."""
    if path is None:
        if role != "defender":
            raise ConfigError(f"{where}: no controller is shipped for the {role}")
        path = shipped_path(SHIPPED_DEFENDER)
        if not path.is_file():
            raise ConfigError(f"{where}: the shipped defender network {path} is missing")
    try:
        state = load_checkpoint(path)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    return NetworkController(state, role, where)


def export_controller(run_dir: str | Path, out: str | Path, ckpt: str = "best") -> dict:
    """Write the policy of ``run_dir/checkpoints/<ckpt>.pt`` as a small controller file: the
    network, its interface and observation config, and where it came from (no critic, no
    optimiser, no replay state). Returns what was written, less the weights."""
    run_dir = Path(run_dir)
    state = load_checkpoint(run_dir / "checkpoints" / f"{ckpt}.pt")
    config = state["config"]
    meta = {
        "net": state["net"],
        "interface": state["interface"],
        "config": {k: config[k] for k in ("drone", "observation", "action", "seed")},
        "source": {
            "run_dir": run_dir.name,
            "checkpoint": ckpt,
            "frames": state["counters"]["frames"],
            "best": state["best"],
            "scenario_digest": state["scenario_digest"],
        },
    }
    save_checkpoint(Path(out), {**meta, "actor": state["actor"]})
    log.info("wrote %s: the %s policy of %s", out, ckpt, run_dir)
    return meta


#: What a controller card reports of each evaluation (``rlplat.eval`` summary keys).
CARD_KEYS = (
    "n",
    "capture_rate",
    "capture_rate_ci95",
    "mean_time_to_capture_s",
    "mean_route_fraction",
    "evasion_score",
    "mean_return",
)


def write_card(run_dir: str | Path, out: str | Path, ckpt: str = "best", split: str = "test"):
    """Evaluate the run's ``ckpt`` policy and the scripted baselines of its drone on ``split``
    (``rlplat.eval.evaluate_run``) and write the numbers next to the controller file, as
    ``<out>.json``. Returns the card."""
    from rlplat.eval.baselines import BASELINES  # the evaluator imports the env factory
    from rlplat.eval.run import evaluate_run, load_run_config

    role = load_run_config(run_dir).drone.learner
    policies = {"nn" if role == "defender" else "learned": "checkpoint"}
    policies.update({k: k for k, b in BASELINES.items() if b.role == role})
    results = {}
    for name, policy in policies.items():
        summary = evaluate_run(run_dir, policy=policy, ckpt=ckpt, split=split, plots=False).summary
        results[name] = {k: summary.get(k) for k in CARD_KEYS}
    run_summary = Path(run_dir) / "summary.json"
    trained = json.loads(run_summary.read_text()) if run_summary.is_file() else {}
    card = {
        "controller": Path(out).name,
        "role": role,
        "command": f"python -m rlplat.agents.controller {run_dir} {out} --ckpt {ckpt}",
        "training": {
            k: trained.get(k)
            for k in ("drone", "seed", "frames", "updates", "wall_time_s", "best_frames")
        },
        "opponent": "pure_pursuit" if role == "defender" else "the scenarios' defenders",
        "split": split,
        "scenario_digest": summary["scenario_digest"],
        split: results,
    }
    path = Path(out).with_suffix(".json")
    atomic_write_text(path, json.dumps(card, indent=2) + "\n")
    log.info("wrote %s", path)
    return card


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a training run directory")
    parser.add_argument("out", help="the controller file to write (.pt)")
    parser.add_argument("--ckpt", default="best", choices=("best", "last"))
    parser.add_argument(
        "--no-card", action="store_true", help="skip the test-split evaluation (<out>.json)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    export_controller(args.run_dir, args.out, args.ckpt)
    if not args.no_card:
        write_card(args.run_dir, args.out, args.ckpt)


if __name__ == "__main__":
    main()
