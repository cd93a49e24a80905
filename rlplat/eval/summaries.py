"""What the tables of evaluations share: which summary is a run's own network, and a cell."""

from __future__ import annotations

from typing import Any

from rlplat.agents.export import ARTIFACTS


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
