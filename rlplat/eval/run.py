"""Evaluate a training run: rebuild env and policy from its directory, replay a split, report.

``evaluate_run(run_dir, ...)`` is what ``evaluate.py`` calls; tests and notebooks call it the
same way. It writes ``<run_dir>/eval/<split>-<name>/``: ``episodes.csv`` (one row per
scenario), ``summary.json``, ``report.md`` and PNG plots.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from rlplat.agents.checkpoint import actor_from_state, load_checkpoint, saved_interface
from rlplat.config import checked_threads
from rlplat.envs.factory import build_env, resolve_scenarios
from rlplat.envs.pursuit import PursuitEnv
from rlplat.errors import ConfigError
from rlplat.eval.baselines import BASELINES, make_baseline
from rlplat.eval.episodes import EpisodeResults, evaluate
from rlplat.eval.metrics import breakdown, outcome_stats, speed_ratio_bin, speed_ratio_labels
from rlplat.io import atomic_write_text
from rlplat.scenarios import SPLITS, STRATEGIES, ScenarioSet

log = logging.getLogger(__name__)

#: ``policy=`` choices: the run's own checkpoint, or a classical baseline.
POLICIES = ("checkpoint", *BASELINES)
#: ``ckpt=`` names that mean a checkpoint of the run (anything else is a path).
CHECKPOINT_NAMES = ("best", "last")


@dataclass(frozen=True)
class Evaluation:
    """What one evaluation produced: per-episode table, summary, and the recorded episodes."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    results: EpisodeResults
    out_dir: Path


def load_run_config(run_dir: str | Path) -> DictConfig:
    """The resolved config a training run saved (``config.yaml``); a clear error if absent."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"run_dir: no run directory at {run_dir}")
    path = run_dir / "config.yaml"
    if not path.is_file():
        raise ConfigError(f"run_dir: {run_dir} has no config.yaml (not a training run directory)")
    return OmegaConf.load(path)


def checkpoint_path(run_dir: Path, ckpt: str) -> Path:
    """``best``/``last`` in the run's ``checkpoints/``, or a path; it must exist."""
    path = run_dir / "checkpoints" / f"{ckpt}.pt" if ckpt in CHECKPOINT_NAMES else Path(ckpt)
    if not path.is_file():
        names = " or ".join(CHECKPOINT_NAMES)
        hint = "" if ckpt in CHECKPOINT_NAMES else f" ({names}, or the path of a checkpoint)"
        raise ConfigError(f"ckpt: no checkpoint at {path}{hint}")
    return path


def check_policy_fits(state: dict[str, Any], cfg: DictConfig, env: PursuitEnv, path) -> None:
    """Refuse a checkpoint whose team sizes, network sizes or drone interface differ from the
    env it would fly in (the run's config, on the scenarios and attackers asked for)."""
    interface = saved_interface(state)
    for key, value in (("attackers", env.num_attackers), ("defenders", env.num_defenders)):
        saved = interface.pop(key)
        if saved != value:
            raise ConfigError(
                f"ckpt: {path} was trained with {key}={saved}, this evaluation flies "
                f"{key}={value} (scenarios_dir, attackers)"
            )
    sizes = {"obs_dim": env.obs_fn.dim, "action_dim": env.action_fn.dim}
    for key, value in sizes.items():
        if state["net"][key] != value:
            raise ConfigError(
                f"ckpt: {path} has {key}={state['net'][key]}, the run's drone config "
                f"(observation={cfg.observation.name}, action={cfg.action.name}) "
                f"gives {key}={value}"
            )
    for key, saved in interface.items():
        value = OmegaConf.select(cfg, key)
        if saved != value:
            raise ConfigError(f"ckpt: {path} was trained with {key}={saved}, the run has {value}")


def check_scenarios(
    scenarios: ScenarioSet, expected: str | None, strict: bool, source: str
) -> bool:
    """Whether the set is the one the run trained with (``expected`` digest); a difference is
    a warning, or an error with ``strict``."""
    if expected is None:
        log.warning("the run records no scenario digest; cannot check the scenario set")
        return False
    if scenarios.digest == expected:
        return True
    message = (
        f"scenarios: the set at {scenarios.path} has digest {scenarios.digest[:12]}, "
        f"the run trained with {expected[:12]} ({source})"
    )
    if strict:
        raise ConfigError(message + "; strict_scenarios=true refuses it")
    log.warning("%s; evaluating anyway", message)
    return False


def evaluate_run(
    run_dir: str | Path,
    *,
    policy: str = "checkpoint",
    ckpt: str = "best",
    split: str = "test",
    strict_scenarios: bool = False,
    scenarios_dir: str | Path | None = None,
    attackers: int | None = None,
    out_dir: str | Path | None = None,
    device: str = "cpu",
    trajectories: int = 6,
    speed_ratio_bins: Sequence[float] = (0.5, 0.8, 1.0, 1.25, 2.0),
    plots: bool = True,
) -> Evaluation:
    """Replay every scenario of ``split`` once, deterministically, with the run's policy.

    Args:
        run_dir: a training run directory (``config.yaml``, ``checkpoints/``, ``summary.json``).
        policy: ``checkpoint`` (the run's network) or a baseline of ``BASELINES``.
        ckpt: ``best``, ``last`` or a checkpoint path (``policy=checkpoint`` only).
        split: ``test``, ``val`` or ``train``.
        strict_scenarios: refuse a scenario set whose digest differs from the run's.
        scenarios_dir: evaluate on this set instead of the run's.
        attackers: fly only the first this many attackers of each scenario (None: the run's
            ``env.attackers``), e.g. a 1-vs-1 run on the defenders of a 2-vs-1 set.
        out_dir: where to write; default ``<run_dir>/eval/<split>-<ckpt or policy>``.
        device: torch device of env and policy.
        trajectories: episodes drawn in 3D (half the fastest captures, half the worst misses).
        speed_ratio_bins: inner bin edges of attacker / defender maximum speed.
        plots: write the PNG plots and embed them in ``report.md``.
    """
    # Everything is checked before any work starts.
    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)
    if policy not in POLICIES:
        raise ConfigError(f"policy: unknown '{policy}'; valid: {', '.join(POLICIES)}")
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    if not isinstance(trajectories, int) or trajectories < 0:
        raise ConfigError(f"trajectories: must be an integer >= 0, got {trajectories}")
    edges = [float(e) for e in speed_ratio_bins]
    if not edges or any(e <= 0 for e in edges) or edges != sorted(set(edges)):
        raise ConfigError(f"speed_ratio_bins: must be increasing and > 0, got {edges}")
    path = checkpoint_path(run_dir, ckpt) if policy == "checkpoint" else None
    name = (ckpt if ckpt in CHECKPOINT_NAMES else path.stem) if path else policy
    out_dir = Path(out_dir) if out_dir is not None else run_dir / "eval" / f"{split}-{name}"
    summary_path = run_dir / "summary.json"
    run_summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    state = load_checkpoint(path) if path else None

    # Rebuild the run's env on its scenario set (or the one asked for).
    scenarios = resolve_scenarios(cfg, scenarios_dir or cfg.get("scenarios_dir"))
    expected = run_summary.get("scenario_digest") or (state or {}).get("scenario_digest")
    source = "summary.json" if "scenario_digest" in run_summary else "checkpoint"
    same_set = check_scenarios(scenarios, expected, strict_scenarios, source)
    n = len(scenarios.split(split))
    env = build_env(
        cfg, scenarios=scenarios, split=split, num_envs=n, device=device,
        scenario_order="sequential",
        **({} if attackers is None else {"attackers": attackers}),
    )  # fmt: skip
    if state is not None:
        check_policy_fits(state, cfg, env, path)
        actor = actor_from_state(state, env.drone_action_spec, device, env.group)
    else:
        actor = make_baseline(policy, env)

    # Replay.
    t0 = time.perf_counter()
    results = evaluate(env, actor, record=plots and trajectories > 0)
    wall = time.perf_counter() - t0
    log.info("%s on %d %s scenarios in %.1f s", name, n, split, wall)

    routes = env.routes.cpu()
    rows = episode_rows(results, scenarios, split, routes, env.num_attackers)
    summary = {
        "policy": policy,
        "name": name,
        "checkpoint": str(path) if path else None,
        "split": split,
        "run_dir": str(run_dir),
        "drone": cfg.drone.name,
        "seed": cfg.seed,
        "scenarios": n,
        "attackers": env.num_attackers,
        "defenders": env.num_defenders,
        "scenario_dir": str(scenarios.path),
        "scenario_digest": scenarios.digest,
        "run_scenario_digest": expected,
        "scenario_digest_matches": same_set,
        **summarize(rows, list(env.reward_fn.weights), edges),
        "eval_wall_time_s": round(wall, 3),
    }
    _write_csv(out_dir / "episodes.csv", rows)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    from rlplat.eval.report import write_report

    write_report(out_dir, summary, rows, results, routes, run_dir, trajectories, plots)
    log.info("capture rate %.3f on %s; results in %s", summary["capture_rate"], split, out_dir)
    return Evaluation(rows, summary, results, out_dir)


def route_labels(routes: torch.Tensor) -> list[str]:
    """A direction per route from its last setpoint: ``+X``, ``-X``, ``+Y`` or ``-Y``."""
    out = []
    for route in routes:
        end = route[-1, :2] - route[0, :2]
        axis = int(end.abs().argmax())
        out.append(("+" if end[axis] >= 0 else "-") + "XY"[axis])
    return out


def episode_rows(
    results: EpisodeResults,
    scenarios: ScenarioSet,
    split: str,
    routes: torch.Tensor,
    attackers: int | None = None,
) -> list[dict[str, Any]]:
    """One row per scenario (in split order): its id and parameters, then its outcome.

    The parameter columns describe the first attacker and defender (index 0 of the drone
    dimension); a set with k > 1 attackers or m > 1 defenders adds ``attacker{i}_start_x/y/z``
    and ``attacker{i}_max_speed`` per extra attacker i, ``defender{j}_route``,
    ``defender{j}_route_direction``, ``defender{j}_strategy``, ``defender{j}_start_x/y/z`` and
    ``defender{j}_max_speed`` per extra defender j and ``defenders_caught``, after
    ``speed_ratio``. ``attackers``: how many of each scenario's attackers flew
    (``env.attackers``; None: all).
    """
    sc = {k: v.tolist() for k, v in scenarios.split(split).items()}
    ids = scenarios.ids[split]
    directions = route_labels(routes)
    keys = ("scenario_index", "captured", "grounded", "time_to_capture", "length")
    keys += ("min_distance", "visible_fraction", "route_fraction", "evasion", "returns")
    out = {k: getattr(results, k).tolist() for k in keys}
    terms = {k: v.tolist() for k, v in results.term_sums.items()}
    caught_count = results.defender_caught.sum(-1).tolist()
    rows = []
    for e, i in enumerate(out["scenario_index"]):
        v_a, v_d = sc["attacker_max_speed"][i], sc["defender_max_speed"][i]
        starts_a, starts_d = sc["attacker_start"][i], sc["defender_start"][i]
        routes_d, strategies_d = sc["route"][i], sc["defender_strategy"][i]
        captured = out["captured"][e]
        extra: dict[str, Any] = {}
        for a in range(1, len(v_a) if attackers is None else attackers):
            extra.update(_xyz(f"attacker{a}_start", starts_a[a]))
            extra[f"attacker{a}_max_speed"] = v_a[a]
        for d in range(1, len(v_d)):
            extra[f"defender{d}_route"] = routes_d[d]
            extra[f"defender{d}_route_direction"] = directions[routes_d[d]]
            extra[f"defender{d}_strategy"] = STRATEGIES[strategies_d[d]]
            extra.update(_xyz(f"defender{d}_start", starts_d[d]))
            extra[f"defender{d}_max_speed"] = v_d[d]
        if len(v_d) > 1:
            extra["defenders_caught"] = caught_count[e]
        route = routes_d[0]
        row = {
            "scenario_id": ids[i],
            "route": route,
            "route_direction": directions[route],
            "defender_strategy": STRATEGIES[strategies_d[0]],
            **_xyz("defender_start", starts_d[0]),
            **_xyz("attacker_start", starts_a[0]),
            "defender_max_speed": v_d[0],
            "attacker_max_speed": v_a[0],
            "speed_ratio": v_a[0] / v_d[0],
            **extra,
            "captured": captured,
            "grounded": out["grounded"][e],
            "time_to_capture_s": out["time_to_capture"][e] if captured else None,
            "steps": out["length"][e],
            "min_distance_m": out["min_distance"][e],
            "visible_fraction": out["visible_fraction"][e],
            "route_fraction": out["route_fraction"][e],
            "evasion": out["evasion"][e],
            "return": out["returns"][e],
            **{f"reward_{k}": v[e] for k, v in terms.items()},
        }
        rows.append(row)
    return rows


def summarize(rows: list[dict[str, Any]], terms: list[str], edges: list[float]) -> dict:
    """Overall and per-group outcome statistics of a per-episode table (see
    :func:`episode_rows`): what ``summary.json`` holds, computed from the rows alone."""

    def col(key: str) -> np.ndarray:
        return np.array([np.nan if r[key] is None else r[key] for r in rows], dtype=float)

    columns = {
        "captured": col("captured").astype(bool),
        "time_to_capture": col("time_to_capture_s"),
        "returns": col("return"),
        "visible_fraction": col("visible_fraction"),
        "min_distance": col("min_distance_m"),
        "route_fraction": col("route_fraction"),
        "evasion": col("evasion"),
    }
    routes = sorted({(r["route"], r["route_direction"]) for r in rows})
    strategies = {i: s for i, s in enumerate(STRATEGIES)}
    labels = speed_ratio_labels(edges)
    return {
        **outcome_stats(**columns),
        "ground_rate": float(np.mean(col("grounded"))),
        "mean_steps": float(np.mean(col("steps"))),
        "reward_terms": {k: float(np.mean(col(f"reward_{k}"))) for k in terms},
        "speed_ratio_bins": edges,
        "by_strategy": breakdown(
            np.array([STRATEGIES.index(r["defender_strategy"]) for r in rows]),
            strategies,
            columns,
        ),
        "by_route": breakdown(
            col("route").astype(int), {i: f"{i} ({d})" for i, d in routes}, columns
        ),
        "by_speed_ratio": breakdown(
            speed_ratio_bin(col("speed_ratio"), edges), dict(enumerate(labels)), columns
        ),
    }


def _xyz(name: str, value: list[float]) -> dict[str, float]:
    return {f"{name}_{a}": v for a, v in zip("xyz", value, strict=True)}


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(v) for k, v in row.items()})
    atomic_write_text(path, buffer.getvalue())


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def evaluate_from_config(cfg: DictConfig) -> list[str]:
    """What ``evaluate.py`` does with its config (conf/evaluate.yaml); returns the lines to
    print. With ``compare`` it also flies every baseline for the run's learner on the same
    split and writes ``eval/compare-<split>.md``."""
    kwargs = {
        "ckpt": str(cfg.ckpt),
        "split": cfg.split,
        "strict_scenarios": bool(cfg.strict_scenarios),
        "scenarios_dir": cfg.scenarios_dir,
        "attackers": cfg.attackers,
        "device": cfg.device,
        "trajectories": cfg.trajectories,
        "speed_ratio_bins": list(cfg.speed_ratio_bins),
        "plots": bool(cfg.plots),
    }
    threads = checked_threads(cfg.threads, "threads")
    if threads is not None:
        torch.set_num_threads(threads)
    policies = [cfg.policy]
    if cfg.compare:
        if cfg.out_dir is not None:
            raise ConfigError("out_dir: must be null with compare=true (each policy has its own)")
        learner = load_run_config(cfg.run_dir).drone.learner
        policies += [k for k, b in BASELINES.items() if b.role == learner and k != cfg.policy]
    lines = []
    for policy in policies:
        ev = evaluate_run(cfg.run_dir, policy=policy, out_dir=cfg.out_dir, **kwargs)
        s = ev.summary
        low, high = s["capture_rate_ci95"]
        lines.append(
            f"{s['name']}: capture rate {s['capture_rate']:.3f} [{low:.3f}, {high:.3f}] on "
            f"{s['scenarios']} {s['split']} scenarios, report {ev.out_dir / 'report.md'}"
        )
    if cfg.compare:
        from rlplat.eval.compare import compare

        lines.append(compare(cfg.run_dir, cfg.split))
    return lines
