"""Controller files: a run's policy as the small file the package ships (the network, its
interface and where it came from), with its card.

``python -m rlplat.experiment.controller RUN_DIR OUT.pt`` exports a run's best policy as such a file
and writes its card, ``OUT.json``: the policy and the scripted baselines of its drone evaluated
on the test split.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from rlplat.agents.checkpoint import load_checkpoint, save_checkpoint
from rlplat.agents.policies import policies_for
from rlplat.cli import ArgumentParser, exit_on_error, path_arg
from rlplat.errors import ConfigError
from rlplat.experiment.evaluation import evaluate_run, load_run_config
from rlplat.io import atomic_write_text, check_writable_dir

log = logging.getLogger(__name__)


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
            "run_dir": run_dir.resolve().name,  # "." names the folder it is
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
    card = make_card(run_dir, out, ckpt, split)
    save_card(card, out)
    return card


def save_card(card: dict, out: str | Path) -> None:
    """Write ``card`` next to the controller file ``out``, as ``<out>.json``."""
    path = Path(out).with_suffix(".json")
    atomic_write_text(path, json.dumps(card, indent=2) + "\n")
    log.info("wrote %s", path)


def make_card(run_dir: str | Path, out: str | Path, ckpt: str = "best", split: str = "test"):
    """The card of :func:`write_card`, not written."""
    role = load_run_config(run_dir).drone.learner
    policies = {"nn" if role == "defender" else "learned": "checkpoint"}
    policies.update({k: k for k in policies_for(role)})
    results = {}
    for name, policy in policies.items():
        summary = evaluate_run(run_dir, policy=policy, ckpt=ckpt, split=split, plots=False).summary
        results[name] = {k: summary.get(k) for k in CARD_KEYS}
    run_summary = Path(run_dir) / "summary.json"
    trained = json.loads(run_summary.read_text()) if run_summary.is_file() else {}
    card = {
        "controller": Path(out).name,
        "role": role,
        "command": f"python -m rlplat.experiment.controller {run_dir} {out} --ckpt {ckpt}",
        "training": {
            k: trained.get(k)
            for k in ("drone", "seed", "frames", "updates", "wall_time_s", "best_frames")
        },
        "opponent": "pure_pursuit" if role == "defender" else "the scenarios' defenders",
        "split": split,
        "scenario_digest": summary["scenario_digest"],
        split: results,
    }
    return card


def check_out(out: str | Path) -> Path:
    """``out`` as a controller file that can be written (and its card beside it): a one-line
    :class:`ConfigError` for a folder, or a place no file can be made, before any work."""
    out = Path(out)
    if out.is_dir():
        raise ConfigError(f"out: {out} is a directory; name the controller file (e.g. {out}/x.pt)")
    if out.suffix != ".pt":
        raise ConfigError(f"out: a controller file ends in .pt (its card: <out>.json), got {out}")
    if out.exists() and not _is_controller(out):  # a run's checkpoint, or any other file
        raise ConfigError(f"out: {out} exists and is no controller file; not replacing it")
    card = out.with_suffix(".json")
    if card.exists() and not _is_card(card, out):  # a run's summary.json, or any other file
        raise ConfigError(f"out: {card} (its card) exists and is no card of {out.name}; not "
                          "replacing it")  # fmt: skip
    check_writable_dir(out.parent, "out")
    return out


def _is_card(path: Path, out: Path) -> bool:
    """Whether ``path`` holds the card of the controller file ``out`` (:func:`make_card`)."""
    try:
        card = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(card, dict) and card.get("controller") == out.name


def _is_controller(path: Path) -> bool:
    """Whether ``path`` holds a controller file (:func:`export_controller`), which an export
    may replace: an rlplat checkpoint with a source and no training state."""
    try:
        state = load_checkpoint(path)
    except ConfigError:
        return False
    return "source" in state and "counters" not in state


@exit_on_error
def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="python -m rlplat.experiment.controller",
        description=" ".join(__doc__.split("\n\n")[0].split()),
    )
    parser.add_argument("run_dir", type=path_arg, help="a training run directory")
    parser.add_argument("out", type=path_arg, help="the controller file to write (.pt)")
    parser.add_argument("--ckpt", default="best", choices=("best", "last"))
    parser.add_argument(
        "--no-card", action="store_true", help="skip the test-split evaluation (<out>.json)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = check_out(args.out)
    # The card's evaluations first: a run they cannot fly leaves no controller file behind.
    card = None if args.no_card else make_card(args.run_dir, out, args.ckpt)
    export_controller(args.run_dir, out, args.ckpt)
    if card is not None:
        save_card(card, out)


if __name__ == "__main__":
    main()
