"""Sim-to-sim: a training run's policy on the same scenarios on an embedded dynamics model and on
an AirSim-protocol simulator, episode by episode.

``sim2sim(run_dir, airsim=..., reference=...)`` is what ``python -m rlplat.airsim sim2sim``
runs. Both legs go through the evaluator (:func:`rlplat.eval.episodes.evaluate`, positions
recorded): the run's own config and checkpoint, only the ``dynamics`` node swapped. It writes
``<run_dir>/eval/sim2sim-<split>-<ckpt>/``:

- ``scenarios.csv``: one row per scenario: each leg's outcome (capture, crash, steps) and the
  position gap between the two trajectories (largest and mean over the steps both episodes ran,
  the largest over every drone, with the step and drone where it occurs);
- ``summary.json`` and ``report.md``: the capture rate on each, how many outcomes differ
  (listed by scenario id) and the largest gap (per scenario and overall);
- ``airsim_recording.csv``: with one simulator, what the AirSim leg flew (commands and states
  per step, :mod:`rlplat.envs.airsim.recording`), for ``python -m rlplat.airsim replay``.
"""

from __future__ import annotations

import copy
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from rlplat.agents.checkpoint import actor_from_state, load_checkpoint
from rlplat.envs.airsim.client import check_simulators
from rlplat.envs.airsim.recording import Recorder, write_recording_csv
from rlplat.envs.dynamics import WholeTicks
from rlplat.envs.pursuit import PursuitEnv
from rlplat.errors import ConfigError
from rlplat.eval.episodes import EpisodeResults, evaluate
from rlplat.eval.tables import differing_outcomes, episode_rows, write_csv
from rlplat.experiment.evaluation import (
    check_policy_fits,
    checkpoint_label,
    checkpoint_path,
    load_run_config,
)
from rlplat.experiment.factory import build_env, eval_num_envs, resolve_scenarios
from rlplat.experiment.rules import Num
from rlplat.experiment.schema import validate_dynamics_swap
from rlplat.io import atomic_write_text, check_writable_dir
from rlplat.scenarios import SPLITS, ScenarioSet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sim2Sim:
    """What a sim-to-sim comparison produced."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    out_dir: Path


@dataclass(frozen=True)
class _Leg:
    results: EpisodeResults
    rows: list[dict[str, Any]]
    recorded: list | None


def position_gaps(a: torch.Tensor, b: torch.Tensor, length: torch.Tensor) -> dict[str, Any]:
    """Distances between two recordings of the same episodes.

    Args:
        a, b: (E, T + 1, D, 3) positions (m) of the two legs (padded by repeating the end).
        length: (E,) int, steps both legs ran (the shorter episode): steps 0..length count.

    Returns:
        ``max`` (E,) m, largest distance of any drone at any counted step, ``step`` and
        ``drone`` (E,) where it occurs, ``mean`` (E,) m, the mean over counted steps and drones.
    """
    t = min(a.shape[1], b.shape[1])
    gap = (a[:, :t] - b[:, :t]).norm(dim=-1)  # (E, t, D)
    counted = torch.arange(t).view(1, t) <= length.view(-1, 1)  # (E, t)
    gap = torch.where(counted.unsqueeze(-1), gap, torch.zeros_like(gap))
    flat = gap.flatten(1)
    largest, where = flat.max(dim=1)
    d = gap.shape[-1]
    mean = gap.sum(dim=(1, 2)) / (counted.sum(1) * d)
    return {"max": largest, "step": where // d, "drone": where % d, "mean": mean}


def _fly(
    cfg: DictConfig,
    node: Mapping[str, Any],
    scenarios: ScenarioSet,
    split: str,
    state: dict[str, Any],
    path: Path,
    attackers: int | None,
    device: str,
    record: bool,
    tick: float | None = None,
) -> _Leg:
    """One leg: the run's env on ``node``'s dynamics, the checkpoint's actor, every scenario;
    with ``tick``, the model stepped in whole ticks of that many seconds (:class:`WholeTicks`)."""
    cfg = copy.deepcopy(cfg)
    cfg.dynamics = OmegaConf.create(dict(node))
    n = len(scenarios.split(split))
    overrides: dict[str, Any] = {} if attackers is None else {"attackers": attackers}
    if node["name"] == "airsim" or tick is not None:
        overrides["compile_step"] = False  # calls to the simulator; a clock kept in Python
    env = build_env(
        cfg, scenarios=scenarios, split=split, num_envs=eval_num_envs(cfg, n), device=device,
        scenario_order="sequential", **overrides,
    )  # fmt: skip
    if tick is not None:
        env.dynamics = WholeTicks(env.dynamics, tick)
    recorder = None
    try:
        check_policy_fits(state, cfg, env, path)
        actor = actor_from_state(state, env.drone_action_spec, device, env.group)
        if record and isinstance(env, PursuitEnv) and node["name"] == "airsim":
            recorder = Recorder(env.dynamics)
        elif record and node["name"] == "airsim":
            log.info("no AirSim recording: several simulators fly in worker processes")
        results = evaluate(env, actor, record=True)
        rows = episode_rows(results, scenarios, split, env.routes.cpu(), env.num_attackers)
    finally:
        if recorder is not None:
            recorder.detach()
        env.close()
    recorded = None
    if recorder is not None:
        try:
            recorded = recorder.episodes([r["scenario_id"] for r in rows])
        except ValueError as err:  # not one recorded episode per scenario: numbered instead
            log.warning("AirSim recording: %s; its episodes are numbered", err)
            recorded = recorder.episodes()
    return _Leg(results, rows, recorded)


def _outcome(row: Mapping[str, Any]) -> str:
    return "capture" if row["captured"] else "crash" if row["grounded"] else "no capture"


def compare(reference: _Leg, airsim: _Leg) -> list[dict[str, Any]]:
    """One row per scenario: both outcomes and the position gap along the trajectories."""
    length = torch.minimum(reference.results.length, airsim.results.length)
    gaps = position_gaps(reference.results.positions, airsim.results.positions, length)
    differ = {d["scenario_id"] for d in differing_outcomes(airsim.rows, reference.rows)}
    rows = []
    for e, (ref, air) in enumerate(zip(reference.rows, airsim.rows, strict=True)):
        rows.append({
            "scenario_id": ref["scenario_id"],
            "reference_outcome": _outcome(ref),
            "airsim_outcome": _outcome(air),
            "reference_steps": ref["steps"],
            "airsim_steps": air["steps"],
            "outcome_differs": ref["scenario_id"] in differ,
            "max_gap_m": float(gaps["max"][e]),
            "max_gap_step": int(gaps["step"][e]),
            "max_gap_drone": int(gaps["drone"][e]),
            "mean_gap_m": float(gaps["mean"][e]),
            "reference_min_distance_m": ref["min_distance_m"],
            "airsim_min_distance_m": air["min_distance_m"],
        })  # fmt: skip
    return rows


def sim2sim(
    run_dir: str | Path,
    *,
    airsim: Mapping[str, Any],
    reference: Mapping[str, Any] | None = None,
    ckpt: str = "best",
    split: str = "test",
    out_dir: str | Path | None = None,
    scenarios_dir: str | Path | None = None,
    attackers: int | None = None,
    device: str = "cpu",
    record: bool = True,
    reference_tick: float | None = None,
    command: str | None = None,
) -> Sim2Sim:
    """Fly the run's policy on ``reference`` and on ``airsim``; compare per scenario.

    Args:
        run_dir: a training run directory.
        airsim: the ``dynamics=airsim`` node (``endpoints``...): the simulator leg.
        reference: an embedded dynamics node; None: the run's own dynamics.
        ckpt: ``best``, ``last`` or a checkpoint path.
        split: ``test``, ``val`` or ``train``.
        out_dir: where to write; default ``<run_dir>/eval/sim2sim-<split>-<ckpt>``.
        scenarios_dir: fly this scenario set instead of the run's.
        attackers: fly only the first this many attackers of each scenario.
        device: torch device of env and policy.
        record: write what the AirSim leg flew (one simulator only).
        reference_tick: s, the reference flies each step in whole physics ticks of this
            length, as AirSim does (its 3-ms ticks: 0.003); None: exactly the control period.
        command: the command line, for the report.
    """
    # Everything is checked before any work starts.
    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)
    run = OmegaConf.to_container(cfg, resolve=True)
    airsim = OmegaConf.to_container(OmegaConf.create(dict(airsim)), resolve=True)
    reference = run["dynamics"] if reference is None else dict(reference)
    reference = OmegaConf.to_container(OmegaConf.create(reference), resolve=True)
    if airsim.get("name") != "airsim":
        raise ConfigError(f"dynamics.name: sim2sim flies airsim, got {airsim.get('name')!r}")
    if reference.get("name") == "airsim":
        raise ConfigError(
            "reference: must be an embedded dynamics model, got airsim (the run's own "
            "dynamics unless given): reference=velocity or another conf/dynamics model"
        )
    validate_dynamics_swap(airsim, run)
    validate_dynamics_swap(reference, run)
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    if reference_tick is not None:
        problem = Num(gt=0, le=float(cfg.env.control_period))(reference_tick)
        if problem:
            raise ConfigError(f"reference_tick: {problem} (the run's env.control_period)")
    path = checkpoint_path(run_dir, ckpt)
    name = checkpoint_label(run_dir, ckpt, path)
    out_dir = Path(out_dir) if out_dir else run_dir / "eval" / f"sim2sim-{split}-{name}"
    check_writable_dir(out_dir, "out_dir")
    state = load_checkpoint(path, "ckpt")
    scenarios = resolve_scenarios(cfg, scenarios_dir or cfg.get("scenarios_dir"))
    check_simulators(airsim)  # before the embedded leg's minutes: a simulator not started

    # The two legs: the same scenarios, policy and config; only the dynamics differ.
    legs = {
        leg: _fly(cfg, node, scenarios, split, state, path, attackers, device, record, tick)
        for leg, node, tick in (("reference", reference, reference_tick), ("airsim", airsim, None))
    }
    rows = compare(legs["reference"], legs["airsim"])
    differ = [r["scenario_id"] for r in rows if r["outcome_differs"]]
    worst = max(rows, key=lambda r: r["max_gap_m"])
    summary = {
        "run_dir": str(run_dir),
        "checkpoint": str(path),
        "split": split,
        "scenarios": len(rows),
        "scenario_digest": scenarios.digest,
        "reference": reference,
        "reference_tick": reference_tick,
        "airsim": airsim,
        "command": command,
        "reference_capture_rate": legs["reference"].results.capture_rate,
        "airsim_capture_rate": legs["airsim"].results.capture_rate,
        "outcomes_differing": len(differ),
        "differing_scenarios": differ,
        "max_gap_m": worst["max_gap_m"],
        "max_gap_scenario": worst["scenario_id"],
        "median_max_gap_m": float(np.median([r["max_gap_m"] for r in rows])),
        "mean_gap_m": float(np.mean([r["mean_gap_m"] for r in rows])),
    }
    write_csv(out_dir / "scenarios.csv", rows)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    atomic_write_text(out_dir / "report.md", report(summary, rows))
    recorded = legs["airsim"].recorded
    if recorded:
        write_recording_csv(out_dir / "airsim_recording.csv", recorded)
    log.info("%d of %d outcomes differ; largest position gap %.3f m (%s); results in %s",
             len(differ), len(rows), worst["max_gap_m"], worst["scenario_id"], out_dir)  # fmt: skip
    return Sim2Sim(rows, summary, out_dir)


def _node(node: Mapping[str, Any]) -> str:
    return ", ".join(f"{k}={json.dumps(v)}" for k, v in node.items())


def report(summary: Mapping[str, Any], rows: list[dict[str, Any]]) -> str:
    """The markdown report of a sim-to-sim comparison."""
    s = summary
    lines = [
        f"# Sim-to-sim: {s['reference']['name']} against airsim ({s['split']} split)",
        "",
        f"Run `{s['run_dir']}`, checkpoint `{s['checkpoint']}`, {s['scenarios']} scenarios "
        f"(set {s['scenario_digest'][:12]}).",
        "",
        f"- reference: {_node(s['reference'])}",
        f"- airsim: {_node(s['airsim'])}",
    ]
    if s.get("reference_tick") is not None:
        lines.insert(-1, f"  stepped in whole ticks of {s['reference_tick']:g} s, as AirSim steps")
    if s.get("command"):
        lines += ["", f"Command: `{s['command']}`"]
    lines += [
        "",
        "| | reference | airsim |",
        "|---|---|---|",
        f"| capture rate | {s['reference_capture_rate']:.3f} | {s['airsim_capture_rate']:.3f} |",
        "",
        f"**Outcomes differing: {s['outcomes_differing']} of {s['scenarios']}**"
        + (f" ({', '.join(s['differing_scenarios'])})." if s["differing_scenarios"] else "."),
        "An outcome is the capture, the crash and the episode length (steps).",
        "",
        f"**Largest position gap: {s['max_gap_m']:.4f} m** ({s['max_gap_scenario']}); "
        f"median of the per-scenario largest gaps {s['median_max_gap_m']:.4f} m, mean gap "
        f"{s['mean_gap_m']:.4f} m. A gap is the distance between a drone's positions on the "
        "two simulators at the same step, over the steps both episodes ran.",
        "",
        "| scenario | reference | airsim | steps | largest gap m (step, drone) | mean gap m |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        flag = " **differs**" if r["outcome_differs"] else ""
        lines.append(
            f"| {r['scenario_id']} | {r['reference_outcome']} | {r['airsim_outcome']}{flag} | "
            f"{r['reference_steps']} / {r['airsim_steps']} | {r['max_gap_m']:.4f} "
            f"({r['max_gap_step']}, {r['max_gap_drone']}) | {r['mean_gap_m']:.4f} |"
        )
    return "\n".join(lines) + "\n"
