"""Evaluate a training run: rebuild env and policy from its directory, replay a split, report.

``evaluate_run(run_dir, ...)`` is what ``evaluate.py`` calls; tests and notebooks call it the
same way. It writes ``<run_dir>/eval/<split>-<name>/``: ``episodes.csv`` (one row per
scenario), ``summary.json``, ``report.md`` and PNG plots.

``policy=onnx`` and ``policy=c`` fly the files ``export.py`` wrote for the checkpoint
(``<run_dir>/export/<ckpt>/``) instead of the torch actor: ONNX Runtime, or ``policy.c`` built
into a shared library and called through ctypes once per drone and step. The torch actor flies
the same scenarios too, and the summary lists the episodes whose outcome differs.
"""

from __future__ import annotations

import json
import logging
import shlex
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from rlplat.agents.checkpoint import (
    actor_from_state,
    check_route_path,
    load_checkpoint,
    saved_interface,
)
from rlplat.agents.export import ARTIFACTS, observation_key
from rlplat.agents.native import OnnxPolicy, artifact_module, build_library, find_compiler
from rlplat.agents.policies import POLICIES, MeanAction, make_scripted_policy, policies_for
from rlplat.envs.components import ACTIONS
from rlplat.envs.dynamics import DYNAMICS
from rlplat.envs.pursuit import ROLES, PursuitEnv, flown_attackers
from rlplat.errors import ConfigError
from rlplat.eval.ceiling import intercept_ceiling, route_flown
from rlplat.eval.compare import compare, evaluations_dir
from rlplat.eval.episodes import EpisodeResults, evaluate
from rlplat.eval.report import write_report
from rlplat.eval.summaries import run_overrides
from rlplat.eval.tables import differing_outcomes, episode_rows, summarize, write_csv
from rlplat.experiment.factory import (
    build_component,
    build_eval_env,
    eval_num_envs,
    require_scenarios,
    resolve_scenarios,
    warn_vision_apart,
)
from rlplat.experiment.schema import (
    config_diff,
    validate_dynamics_swap,
    validate_evaluate_config,
)
from rlplat.io import atomic_write_text, check_writable_dir, refuse_run_dir, sha256_bytes
from rlplat.scenarios import SPLITS, ScenarioSet

log = logging.getLogger(__name__)

#: ``policy=`` choices: the run's own checkpoint, its exported artifacts, or a scripted baseline.
EVAL_POLICIES = ("checkpoint", *ARTIFACTS, *POLICIES)
#: The files each artifact policy flies, in ``<run_dir>/export/<ckpt>/``.
ARTIFACT_FILES = {"onnx": ("policy.onnx",), "c": ("policy.h", "policy.c")}
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


def warn_replacing(out_dir: Path, digest: str) -> None:
    """Log that the evaluation in ``out_dir`` is about to be replaced by one flown on another
    scenario set (digest ``digest``): a run's own results, say, by those on a foreign set."""
    try:
        before = json.loads((Path(out_dir) / "summary.json").read_text()).get("scenario_digest")
    except (OSError, ValueError, AttributeError):
        return  # nothing there, or nothing that says which set it flew
    if isinstance(before, str) and before != digest:
        log.warning("out_dir: replacing %s, flown on another scenario set (digest %s..., this "
                    "one %s...); give each set its own out_dir", out_dir, before[:12],
                    digest[:12])  # fmt: skip


def checkpoint_label(run_dir: Path, ckpt: str, path: Path) -> str:
    """What the evaluations and exports of checkpoint ``ckpt`` (at ``path``) are named after:
    ``best``, ``last``, a file of the run's own ``checkpoints/`` by its name
    (``val-0204800``), another's by its run and name (``sel-s1-best``), so that another run's
    ``best.pt`` does not take the place of this run's own."""
    if ckpt in CHECKPOINT_NAMES:
        return ckpt
    if path.parent.resolve() == (run_dir / "checkpoints").resolve():
        return path.stem
    owner = path.parent.parent if path.parent.name == "checkpoints" else path.parent
    return f"{owner.resolve().name or 'root'}-{path.stem}"


def default_export_dir(run_dir: Path, ckpt: str, path: Path) -> Path:
    """Where ``export.py`` writes the artifacts of checkpoint ``ckpt`` (at ``path``)."""
    return run_dir / "export" / checkpoint_label(run_dir, ckpt, path)


def artifact_files(
    policy: str, run_dir: Path, ckpt: str, path: Path, where: Path
) -> dict[str, bytes]:
    """The exported files ``policy`` flies, from the export folder ``where``, checked against
    the export's card: they must be the ones exported from the checkpoint at ``path`` as it
    is now."""
    out = "" if where == default_export_dir(run_dir, ckpt, path) else f"out_dir={where}"
    words = ["python", "export.py", f"run_dir={run_dir}", f"ckpt={ckpt}"] + ([out] if out else [])
    command = shlex.join(words)
    card_path = where / "card.json"
    if not card_path.is_file():
        raise ConfigError(f"policy: {policy} needs the export in {where}; run `{command}` first")
    try:
        card = json.loads(card_path.read_text())
        exported_from = card["source"]["sha256"]
        hashes = {name: card["files"][name]["sha256"] for name in ARTIFACT_FILES[policy]}
    except (ValueError, KeyError, TypeError) as e:
        raise ConfigError(
            f"policy: {card_path} is not an export card ({type(e).__name__}: {e}); "
            f"run `{command}` again"
        ) from None
    if exported_from != sha256_bytes(path.read_bytes()):
        raise ConfigError(
            f"policy: the export in {where} is of another checkpoint than {path} (sha256 "
            f"{exported_from[:12]}); run `{command}` again"
        )
    files = {}
    for name in ARTIFACT_FILES[policy]:
        data = (where / name).read_bytes() if (where / name).is_file() else b""
        if sha256_bytes(data) != hashes[name]:
            raise ConfigError(
                f"policy: {where / name} is missing or not the file the card names; "
                f"run `{command}` again"
            )
        files[name] = data
    return files


def artifact_policy(
    policy: str,
    files: dict[str, bytes],
    state,
    env: PursuitEnv,
    compiler: str,
    features: Sequence[int] | None = None,
):
    """The exported artifact as a policy of ``env``'s learners (one C call per drone); with
    ``features``, fed only those features of each drone's observation."""
    dims = state["net"]["obs_dim"], state["net"]["action_dim"]
    if policy == "onnx":
        runner = OnnxPolicy(files["policy.onnx"], *dims)
    else:
        header, source = files["policy.h"].decode(), files["policy.c"].decode()
        runner, _ = build_library(header, source, *dims, compiler=compiler)
    return artifact_module(runner, observation_key(env.group), env.action_key, features)


def check_policy_fits(
    state: dict[str, Any],
    cfg: DictConfig,
    env: PursuitEnv,
    path,
    lone_in_team: bool = False,
    *,
    field: str = "ckpt",
    settings: str = "scenarios_dir, attackers, lone_in_team",
    job: str = "evaluation",
) -> list[int] | None:
    """Refuse a checkpoint whose team sizes, network sizes or drone interface differ from the
    env it would fly in (the run's config, on the scenarios and attackers asked for), or
    that was trained on another defender's route path than the env's meeting point uses.

    With ``lone_in_team`` the checkpoint must have been trained alone (one drone of the
    learning role) and the env must fly a team of that role against as many opponents; each
    drone then flies it on its observation's ``lone_features``, which this returns (None
    otherwise). A refusal names ``field`` (where the checkpoint came from) and, for team sizes,
    the ``settings`` of the command that choose them, and the ``job`` it would fly in."""
    interface = saved_interface(state)
    interface.pop("route_path", None)
    counts = {"attackers": env.num_attackers, "defenders": env.num_defenders}
    learners = "attackers" if ROLES[env.learner] == "attacker" else "defenders"
    saved_defenders = interface["defenders"]
    if lone_in_team:
        if interface[learners] != 1:
            raise ConfigError(
                f"lone_in_team: flies a checkpoint trained alone in each seat of a team; "
                f"{path} was trained in a team, with {learners}={interface[learners]}"
            )
        if counts[learners] < 2:
            chooses = "scenarios_dir, attackers" if learners == "attackers" else "scenarios_dir"
            raise ConfigError(
                f"lone_in_team: flies each seat of a team of {learners}, but this {job} "
                f"flies {learners}={counts[learners]}, no team ({chooses})"
            )
        counts[learners] = 1  # the team's size is checked; each seat flies alone
    for key, value in counts.items():
        saved = interface.pop(key)
        if saved != value:
            lone = key == learners and saved == 1 and "lone_in_team" in settings
            hint = "; lone_in_team=true flies it in each seat" if lone else ""
            skip = {"lone_in_team"} | ({"attackers"} if key == "defenders" else set())
            chosen = ", ".join(x for x in settings.split(", ") if x not in skip)
            raise ConfigError(
                f"{field}: {path} was trained with {key}={saved}, this {job} flies "
                f"{key}={value} ({chosen}{hint})"
            )
    # In-play flags come with more than one defender (caught one by one): a lone defender's
    # observation has none, a lone attacker's against two defenders has them.
    features = env.obs_fn.lone_features(saved_defenders > 1) if lone_in_team else None
    obs_dim = env.obs_fn.dim if features is None else len(features)
    sizes = {"obs_dim": obs_dim, "action_dim": env.action_fn.dim}
    for key, value in sizes.items():
        if state["net"][key] != value:
            raise ConfigError(
                f"{field}: {path} has {key}={state['net'][key]}, the run's drone config "
                f"(observation={cfg.observation.name}, action={cfg.action.name}) "
                f"gives {key}={value}"
            )
    for key, saved in interface.items():
        value = OmegaConf.select(cfg, key)
        if saved != value:
            raise ConfigError(
                f"{field}: {path} was trained with {key}={saved}, the run has {value}"
            )
    check_route_path(state, env, path, field)  # last: it may only warn, about a fitting one
    return features


def check_scenarios(
    scenarios: ScenarioSet,
    expected: str | None,
    strict: bool,
    source: str,
    doing: str = "evaluating",
) -> bool:
    """Whether the set is the one the run trained with (``expected`` digest); a difference is
    a warning (``doing`` anyway), or an error with ``strict``."""
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
    log.warning("%s; %s anyway", message, doing)
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
    compiler: str = "cc",
    dynamics: Mapping[str, Any] | None = None,
    ensemble: Sequence[str | Path] = (),
    lone_in_team: bool = False,
    eval_dir: str | Path | None = None,
    export_dir: str | Path | None = None,
) -> Evaluation:
    """Replay every scenario of ``split`` once, deterministically, with the run's policy.

    Args:
        run_dir: a training run directory (``config.yaml``, ``checkpoints/``, ``summary.json``).
        policy: ``checkpoint`` (the run's network), ``onnx`` or ``c`` (its export, see
            ``export.py``) or a scripted policy of ``POLICIES``.
        ckpt: ``best``, ``last`` or a checkpoint path (not for a scripted policy).
        split: ``test``, ``val`` or ``train``.
        strict_scenarios: refuse a scenario set whose digest differs from the run's.
        scenarios_dir: evaluate on this set instead of the run's.
        attackers: fly only the first this many attackers of each scenario (None: the run's
            ``env.attackers``), e.g. a 1-vs-1 run on the defenders of a 2-vs-1 set.
        out_dir: where to write; default ``<eval_dir>/<split>-<ckpt or policy>``.
        device: torch device of env and policy.
        trajectories: episodes drawn in 3D (half the fastest captures, half the worst misses).
        speed_ratio_bins: inner bin edges of attacker / defender maximum speed.
        plots: write the PNG plots and embed them in ``report.md``.
        compiler: the C compiler that builds ``policy.c`` (``policy=c``).
        dynamics: fly on this dynamics instead of the run's: a ``conf/dynamics/`` node (e.g.
            ``airsim`` with its ``endpoints``; on AirSim the split is flown in waves, one env
            per simulator); the default ``out_dir`` then ends in ``-<dynamics name>``.
        ensemble: more training runs of the same drone interface (observation and action
            components); their ``ckpt`` checkpoints and ``run_dir``'s fly together, the mean
            of their deterministic actions (:class:`rlplat.agents.policies.MeanAction`);
            ``policy=checkpoint`` only. The name gets ``-ensemble<size>``.
        lone_in_team: a checkpoint (or its export) trained with one drone of the learning
            role flies every drone of a larger team of that role, each on its own
            observation without its team-mates (``lone_features``): a team that does not
            coordinate. A scripted policy flies the team as always.
        eval_dir: the folder of the run's evaluations that the default ``out_dir`` is in
            (default ``<run_dir>/eval``), e.g. one per scenario set that the run is flown on.
        export_dir: ``policy=onnx`` or ``c``: the folder of the export to fly (default
            ``<run_dir>/export/<ckpt>``, where ``export.py`` writes without ``out_dir``).
    """
    # Everything is checked before any work starts.
    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)
    swapped = dynamics is not None
    if swapped:
        dynamics = OmegaConf.to_container(OmegaConf.create(dict(dynamics)), resolve=True)
        validate_dynamics_swap(dynamics, OmegaConf.to_container(cfg, resolve=True))
        cfg.dynamics = OmegaConf.create(dynamics)
    if policy not in EVAL_POLICIES:
        raise ConfigError(f"policy: unknown '{policy}'; valid: {', '.join(EVAL_POLICIES)}")
    if split not in SPLITS:
        raise ConfigError(f"split: unknown '{split}'; valid: {', '.join(SPLITS)}")
    if not isinstance(trajectories, int) or trajectories < 0:
        raise ConfigError(f"trajectories: must be an integer >= 0, got {trajectories}")
    edges = [float(e) for e in speed_ratio_bins]
    if not edges or any(e <= 0 for e in edges) or edges != sorted(set(edges)):
        raise ConfigError(f"speed_ratio_bins: must be increasing and > 0, got {edges}")
    learned = policy == "checkpoint" or policy in ARTIFACTS
    path = checkpoint_path(run_dir, ckpt) if learned else None
    name = checkpoint_label(run_dir, ckpt, path) if path else policy
    if export_dir is not None and policy not in ARTIFACTS:
        raise ConfigError(f"export_dir: is for policy=onnx or c, got policy={policy}")
    files = where = None
    if policy in ARTIFACTS:
        where = default_export_dir(run_dir, ckpt, path) if export_dir is None else Path(export_dir)
        files = artifact_files(policy, run_dir, ckpt, path, where)
    if policy == "c":
        compiler = find_compiler(compiler)
    if files is not None:
        name = f"{name}-{policy}"
    members = ensemble_members(cfg, policy, ckpt, ensemble, run_dir)
    if members:
        name = f"{name}-ensemble{len(members) + 1}"
    if out_dir is None:
        suffix = f"-{cfg.dynamics.name}" if swapped else ""
        out_dir = evaluations_dir(run_dir, eval_dir) / f"{split}-{name}{suffix}"
    refuse_run_dir(out_dir, "out_dir", "its summary.json would be replaced by the "
                   "evaluation's (choose a folder of its own, e.g. <run>/eval/NAME)")  # fmt: skip
    out_dir = check_writable_dir(out_dir, "out_dir")
    summary_path = run_dir / "summary.json"
    run_summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    state = load_checkpoint(path, "ckpt") if path else None

    # Rebuild the run's env on its scenario set (or the one asked for).
    scenarios = resolve_scenarios(cfg, scenarios_dir or cfg.get("scenarios_dir"))
    expected = run_summary.get("scenario_digest") or (state or {}).get("scenario_digest")
    source = "summary.json" if "scenario_digest" in run_summary else "checkpoint"
    # strict_scenarios refuses another set here; without it, the warning waits for the checks
    # below, so that a refused evaluation says one thing.
    same_set = check_scenarios(scenarios, expected, True, source) if strict_scenarios else None
    require_scenarios(scenarios, [split], "the evaluation")
    n = len(scenarios.split(split))
    # A baseline flies its own velocity commands (eq. 2), not through a learner's action.
    env_cfg = cfg if learned else plain_action(cfg)
    policy_args = {} if learned else baseline_args(policy, cfg)
    flown_attackers(attackers, scenarios, "attackers")  # named as this command's setting
    overrides = {} if attackers is None else {"attackers": attackers}
    env = build_eval_env(
        env_cfg, scenarios=scenarios, split=split, num_envs=eval_num_envs(cfg, n),
        device=device, **overrides,
    )  # fmt: skip
    try:
        if state is not None:
            features = check_policy_fits(state, cfg, env, path, lone_in_team)
            if features is not None:
                log.info("each of the %d %ss flies %s, trained alone, blind to its team-mates",
                         env.team_size, ROLES[env.learner], path)  # fmt: skip
            actor = actor_from_state(state, env.drone_action_spec, device, env.group, features)
            if members:
                actors = [actor]
                for member_path, member_cfg in members:
                    member = load_checkpoint(member_path, "ensemble")
                    check_policy_fits(member, member_cfg, env, member_path, lone_in_team,
                                      field="ensemble")  # fmt: skip
                    actors.append(
                        actor_from_state(member, env.drone_action_spec, device, env.group, features)
                    )
                actor = MeanAction(actors, env.action_key)
            if files is not None:
                torch_actor = actor
                actor = artifact_policy(policy, files, state, env, compiler, features)
        else:
            actor = make_scripted_policy(policy, env, **policy_args)
        # Checked: what it flies fits the env. Now what it flies on may differ from training.
        if same_set is None:
            same_set = check_scenarios(scenarios, expected, False, source)
        warn_vision_apart(cfg.env.vision_semi_axes, scenarios, "the run",
                          "; evaluating with the run's")  # fmt: skip

        # Replay.
        warn_replacing(out_dir, scenarios.digest)  # checked: it will be replaced
        t0 = time.perf_counter()
        results = evaluate(env, actor, record=plots and trajectories > 0)
        wall = time.perf_counter() - t0
        log.info("%s on %d %s scenarios in %.1f s", name, n, split, wall)

        routes = env.routes.cpu()
        bound, route_bound = split_ceiling(cfg, env, scenarios, split, device)
        rows = episode_rows(
            results, scenarios, split, routes, env.num_attackers, bound, route_bound
        )
        artifact = {}
        if files is not None:  # the torch actor on the same scenarios: which outcomes differ
            reference = evaluate(env, torch_actor)
            ref_rows = episode_rows(reference, scenarios, split, routes, env.num_attackers)
            differ = [
                {"scenario_id": d["scenario_id"], "torch": d["reference"], policy: d["outcome"]}
                for d in differing_outcomes(rows, ref_rows)
            ]
            flipped = [d for d in differ if d["torch"]["captured"] != d[policy]["captured"]]
            artifact = {
                "artifact": {
                    "dir": str(where),
                    "files": {k: sha256_bytes(v) for k, v in files.items()},
                },
                "torch_capture_rate": reference.capture_rate,
                "outcomes_differing_from_torch": len(differ),
                "captures_differing_from_torch": len(flipped),
                "differences_from_torch": differ,
            }
            log.info("%d of %d outcomes differ from the torch policy's (%d captures)",
                     len(differ), n, len(flipped))  # fmt: skip
    finally:
        env.close()  # a parallel env's workers, a simulator connection
    summary = {
        "policy": policy,
        "name": name,
        "checkpoint": str(path) if path else None,
        "policy_args": policy_args,
        "ensemble": [str(p) for p, _ in members],
        "lone_in_team": state is not None and lone_in_team,
        "split": split,
        "run_dir": str(run_dir),
        "run_overrides": run_overrides(run_dir),  # how the run was launched: pool's variants
        "drone": cfg.drone.name,
        "learner": cfg.drone.learner,
        "dynamics": cfg.dynamics.name,
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
        **artifact,
    }
    write_csv(out_dir / "episodes.csv", rows)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    write_report(out_dir, summary, rows, results, routes, run_dir, trajectories, plots)
    log.info("capture rate %.3f on %s; results in %s", summary["capture_rate"], split, out_dir)
    return Evaluation(rows, summary, results, out_dir)


def ensemble_members(
    cfg: DictConfig, policy: str, ckpt: str, runs: Sequence[str | Path], run_dir: Path
) -> list[tuple[Path, DictConfig]]:
    """The checkpoint and config of each further run of an ensemble, checked against the run
    of ``cfg`` (at ``run_dir``): the same learner, observation and action (what an action
    means), each run once and none of them ``run_dir`` (a run counted twice weighs double)."""
    if runs and policy != "checkpoint":
        raise ConfigError(f"ensemble: flies checkpoints (policy=checkpoint), got policy={policy}")
    if runs and ckpt not in CHECKPOINT_NAMES:
        raise ConfigError(
            f"ensemble: needs ckpt={' or '.join(CHECKPOINT_NAMES)} (each run's own), got {ckpt}"
        )
    members, seen = [], {Path(run_dir).resolve(): "is run_dir itself"}
    for run in runs:
        where = Path(run).resolve()
        if where in seen:
            raise ConfigError(f"ensemble: {run} {seen[where]}; each run flies once")
        seen[where] = "is named twice"
        try:
            member_cfg = load_run_config(run)
        except ConfigError as err:
            raise ConfigError(f"ensemble: {str(err).removeprefix('run_dir: ')}") from None
        for key in ("drone.learner", "observation", "action"):
            mine, theirs = (OmegaConf.select(c, key) for c in (cfg, member_cfg))
            if isinstance(mine, DictConfig):
                mine, theirs = (OmegaConf.to_container(x, resolve=True) for x in (mine, theirs))
            # A key added since one of the runs was saved counts with its neutral value.
            if config_diff({key: mine}, {key: theirs}, ()):
                raise ConfigError(f"ensemble: {run} has {key}={theirs}, run_dir has {key}={mine}")
        members.append((checkpoint_path(Path(run), ckpt), member_cfg))
    return members


def baseline_args(policy: str, cfg: DictConfig) -> dict[str, float | str]:
    """What the baseline ``policy`` takes from the run: ``route_intercept`` on a run that
    corrects the route-intercept law (``action=route_law``) flies that law (its ``homing_time``,
    ``start_lag``, ``horizon`` and ``unreachable``, those the run's config sets: one saved
    before a key existed flew its default), so the baseline is the learner's starting point."""
    action = cfg.get("action") or {}
    if policy != "route_intercept" or action.get("name") != "route_law":
        return {}
    law = ACTIONS["route_law"].law_args
    return {k: v if isinstance(v := action[k], str) else float(v)
            for k in law if action.get(k) is not None}  # fmt: skip


def flight_arguments(parser, split: str = "test") -> None:
    """The command-line arguments of :func:`flown_split` (an ``argparse`` parser's): the run
    directory, ``--scenarios``, ``--split`` (default ``split``), ``--ckpt`` and ``--policy``."""
    parser.add_argument("run_dir", type=Path, help="an attacker's training run")
    parser.add_argument("--scenarios", required=True, help="a scenario set")
    parser.add_argument("--split", default=split, choices=SPLITS)
    parser.add_argument("--ckpt", default="best", choices=("best", "last"))
    parser.add_argument(
        "--policy",
        default="checkpoint",
        choices=("checkpoint", "proportional_navigation", "pure_pursuit", "route_intercept"),
    )


def flown_split(
    run_dir: Path, scenarios_dir: str | Path, split: str, policy: str = "checkpoint",
    ckpt: str = "best",
) -> tuple[DictConfig, PursuitEnv, Any]:  # fmt: skip
    """A run's config, an eval env of a split of ``scenarios_dir`` (one env per scenario) and
    the policy that flies it, as ``evaluate.py`` flies them: the run's checkpoint (a policy
    trained alone in every seat of a team) or a baseline, which flies the plain velocity
    action (``route_intercept``: the run's law). For the analyses in ``benchmarks/``."""
    run_cfg = load_run_config(run_dir)
    cfg = run_cfg if policy == "checkpoint" else plain_action(run_cfg)
    scenarios = resolve_scenarios(cfg, scenarios_dir)
    n = len(scenarios.split(split))
    env = build_eval_env(cfg, scenarios=scenarios, split=split, num_envs=eval_num_envs(cfg, n))
    if policy != "checkpoint":
        return cfg, env, make_scripted_policy(policy, env, **baseline_args(policy, run_cfg))
    path = checkpoint_path(Path(run_dir), ckpt)
    state = load_checkpoint(path)
    lone = saved_interface(state)["attackers"] == 1 and env.num_attackers > 1
    features = check_policy_fits(state, cfg, env, path, lone_in_team=lone)
    return cfg, env, actor_from_state(state, env.drone_action_spec, "cpu", env.group, features)


def plain_action(cfg: DictConfig) -> DictConfig:
    """``cfg`` with the plain velocity action (eq. 2) in place of any other. A reward's
    ``action_sq`` prices a correction to a law; a plain command is none, so it is dropped."""
    if cfg.action.get("name") == "velocity":
        return cfg
    plain = OmegaConf.merge(cfg, {"action": None})
    plain.action = {"name": "velocity"}
    terms = plain.get("reward", {}).get("terms", {})
    if "action_sq" in terms:
        plain.reward.terms = {k: v for k, v in terms.items() if k != "action_sq"}
    return plain


#: The ceilings flown in this process, by what they depend on (:func:`split_ceiling`): the
#: policies of one comparison (``evaluate.py compare=true``, ``-m policy=...``) share them.
_CEILINGS: dict[tuple, tuple] = {}
_CEILINGS_KEPT = 8


def split_ceiling(cfg, env: PursuitEnv, scenarios, split: str, device):
    """The capture ceiling and the route ceiling of the split (:mod:`rlplat.eval.ceiling`),
    each (E,) or None where it is not defined: a defender learner, or dynamics that are not
    separable per axis. Flown once per set, split and config in a process."""
    if ROLES[env.learner] != "attacker" or cfg.dynamics.get("name") != "velocity":
        return None, None
    n = env.batch_size[0]
    key = (scenarios.digest, split, n, str(device), env.num_attackers, env.num_defenders,
           OmegaConf.to_yaml(plain_action(cfg), resolve=True))  # fmt: skip
    if key not in _CEILINGS:
        _CEILINGS[key] = _fly_ceilings(cfg, env, scenarios, split, device)
        while len(_CEILINGS) > _CEILINGS_KEPT:
            del _CEILINGS[next(iter(_CEILINGS))]  # the oldest
    ceiling, route = _CEILINGS[key]
    if env.num_defenders > 1 or not bool(ceiling.defined.any()):
        log.info("capture ceiling on %s: not defined (%s)", split,
                 "several defenders" if env.num_defenders > 1
                 else "no scenario with a route-flying defender")  # fmt: skip
    else:
        log.info("capture ceiling on %s: %.3f of %d scenarios with a route-flying defender",
                 split, ceiling.rate, int(ceiling.defined.sum()))  # fmt: skip
    if route is None:  # nothing reacts, or no ceiling
        return ceiling.interceptable.clone(), ceiling.interceptable.clone()
    log.info("route ceiling on %s: %.3f of %d scenarios, every defender flying its route",
             split, route.rate, int(route.defined.sum()))  # fmt: skip
    return ceiling.interceptable.clone(), route.interceptable.clone()


def _fly_ceilings(cfg, env: PursuitEnv, scenarios, split: str, device):
    """The split's capture ceiling, and its route ceiling where some defender reacts (else
    None), each flown with velocity commands on an env of its own."""
    n = env.batch_size[0]

    def plain_env(scenario_set) -> PursuitEnv:  # the split flown with velocity commands
        return build_eval_env(plain_action(cfg), scenarios=scenario_set, split=split,
                              num_envs=n, device=device, attackers=env.num_attackers)  # fmt: skip

    def ceiling_of(flown: PursuitEnv):
        dynamics = build_component(
            DYNAMICS, "dynamics", OmegaConf.to_container(cfg.dynamics, resolve=True),
            num_envs=n, num_drones=2, device=device,
        )  # fmt: skip
        return intercept_ceiling(flown, dynamics)

    ceiling = ceiling_of(plain_env(scenarios))
    if bool(ceiling.defined.all()) or env.num_defenders > 1:
        return ceiling, None
    return ceiling, ceiling_of(plain_env(route_flown(scenarios)))


def evaluate_from_config(cfg: DictConfig) -> list[str]:
    """What ``evaluate.py`` does with its config (conf/evaluate.yaml); returns the lines to
    print. With ``compare`` it also flies every baseline for the run's learner on the same
    split and writes ``compare-<split>.md`` beside their evaluations: in the run's ``eval/``,
    or in ``out_dir`` when given (a run flown on another scenario set or as a team needs no
    copy of the run)."""
    validate_evaluate_config(cfg)
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
        "compiler": cfg.compiler,
        "dynamics": cfg.get("dynamics"),
        "lone_in_team": bool(cfg.lone_in_team),
    }
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    policies = [cfg.policy]
    if cfg.compare:
        learner = load_run_config(cfg.run_dir).drone.learner
        policies += [k for k in policies_for(learner) if k != cfg.policy]
    lines = []
    for policy in policies:
        members = list(cfg.ensemble) if policy == cfg.policy else []
        where = {"eval_dir": cfg.out_dir} if cfg.compare else {"out_dir": cfg.out_dir}
        if policy == cfg.policy:
            where["export_dir"] = cfg.export_dir
        ev = evaluate_run(cfg.run_dir, policy=policy, ensemble=members, **where, **kwargs)
        s = ev.summary
        low, high = s["capture_rate_ci95"]
        differ = (
            f", {s['outcomes_differing_from_torch']} outcomes differ from the torch policy's "
            f"({s['captures_differing_from_torch']} in capture)"
            if "outcomes_differing_from_torch" in s
            else ""
        )
        lines.append(
            f"{s['name']}: capture rate {s['capture_rate']:.3f} [{low:.3f}, {high:.3f}] on "
            f"{s['scenarios']} {s['split']} scenarios{differ}, report {ev.out_dir / 'report.md'}"
        )
    if cfg.compare:
        lines.append(compare(cfg.run_dir, cfg.split, eval_dir=cfg.out_dir, plots=cfg.plots))
    return lines
