"""What the tables of evaluations share: which summary is a run's own network, and a cell."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from rlplat.agents.export import ARTIFACTS


def run_overrides(run_dir: str | Path) -> list[str] | None:
    """The overrides a training run was launched with, other than ``seed`` (its
    ``.hydra/overrides.yaml``); None where the run directory has no such record."""
    path = Path(run_dir) / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return None
    found = [str(o) for o in OmegaConf.load(path)]
    return [o for o in found if not o.split("=", 1)[0].lstrip("+~").startswith("seed")]


def launch_overrides(summary: dict[str, Any]) -> list[str] | None:
    """An evaluation's record of how its run was launched (``run_overrides``), or, for an
    evaluation written before it was recorded, :func:`run_overrides` of its ``run_dir``."""
    if "run_overrides" in summary:
        return summary["run_overrides"]
    return run_overrides(summary["run_dir"]) if summary.get("run_dir") else None


def is_learned(summary: dict[str, Any]) -> bool:
    """A run's own network (its checkpoint, or an export of it), not a scripted baseline."""
    return summary["policy"] == "checkpoint" or summary["policy"] in ARTIFACTS


def num(v: float | None, digits: int = 3) -> str:
    """A table cell: ``v`` with ``digits`` decimals, or a dash where there is no value."""
    return "–" if v is None else f"{v:.{digits}f}"


def policy_label(summary: dict[str, Any]) -> str:
    """How the tables name an evaluated policy: ``drone (checkpoint)`` for a run's own network
    (e.g. ``attacker_v8 (best)``), the policy's name for a baseline."""
    return f"{summary['drone']} ({summary['name']})" if is_learned(summary) else summary["policy"]
