"""Scenario generation (paper §3.1): parameters of every episode, split, checked and stored."""

from rlplat.scenarios.generator import SPLITS, SplitColumns, feasible, generate
from rlplat.scenarios.quality import format_quality, quality_report
from rlplat.scenarios.spec import PARAM_NAMES, STRATEGIES, ParamSpec, ScenarioSpec
from rlplat.scenarios.store import SCHEMA_VERSION, ScenarioSet, write_scenario_set

__all__ = [
    "PARAM_NAMES",
    "SCHEMA_VERSION",
    "SPLITS",
    "STRATEGIES",
    "ParamSpec",
    "ScenarioSet",
    "ScenarioSpec",
    "SplitColumns",
    "feasible",
    "format_quality",
    "generate",
    "quality_report",
    "write_scenario_set",
]
