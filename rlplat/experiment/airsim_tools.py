"""The AirSim tools of ``python -m rlplat.airsim``: the configured team's settings.json, a
loopback test server for it, and the calibration, replay and sim-to-sim verbs (their work is in
:mod:`rlplat.envs.airsim.calibration`, :mod:`rlplat.envs.airsim.recording` and
:mod:`rlplat.experiment.sim2sim`; here their options and config).

The team comes from the train config: ``scenario.attackers`` (or ``env.attackers`` when set)
and ``scenario.defenders``; its vehicle names from ``dynamics.attacker_name`` and
``dynamics.defender_name`` when the dynamics has them (``dynamics=airsim``), else ``Attacker``
and ``Defender``; spawn points
from ``dynamics.spawn`` (``{vehicle: [x, y, z]}``, NED metres as settings.json X/Y/Z) where it
gives them, else on a line along east, ``SPAWN_SPACING`` metres apart at ground level; the
``ClockSpeed`` from ``dynamics.clock_speed`` (else 1).
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rlplat.envs.airsim import make_settings, ned_to_enu, vehicle_names, write_settings
from rlplat.envs.airsim.client import AirSimError, parse_endpoint
from rlplat.errors import ConfigError
from rlplat.experiment.command_line import check_command_line
from rlplat.experiment.config import CONF_DIR, compose_config
from rlplat.experiment.rules import Num
from rlplat.experiment.schema import validate_train_config, vehicle_list
from rlplat.io import atomic_write_text, check_writable_file

SPAWN_SPACING = 5.0  # m between default spawn points (ten times the contact radius of a quad)


def compose_train(overrides: Sequence[str]) -> DictConfig:
    """The train config with command-line ``overrides``; a bad override is a one-line error
    (as train.py's: the key or option it names, with the nearest valid ones)."""
    check_command_line("train", list(overrides))
    try:
        cfg = compose_config("train", overrides)
    except HydraException as err:
        message = " ".join(str(err).split())
        raise ConfigError(f"overrides {list(overrides)}: {message}") from None
    try:  # an interpolation that does not resolve is named here, not deep in a verb
        OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as err:
        raise ConfigError(f"{err.full_key}: {str(err).splitlines()[0]}") from None
    return cfg


def compose_team(overrides: Sequence[str]) -> DictConfig:
    """The train config whose team ``settings`` and ``serve`` write, checked as an env of one
    env per simulator (a value no run would accept, ``algo.gamma=abc``, is refused here too)."""
    cfg = compose_train(overrides)
    endpoints = cfg.dynamics.get("endpoints")  # not a list: the schema's rule names it
    simulators = len(endpoints) if OmegaConf.is_list(endpoints) else 1
    validate_train_config(cfg, env_batch=simulators if cfg.dynamics.name == "airsim" else 1)
    return cfg


def team_settings(cfg: DictConfig, api_server_port: int | None = None) -> dict[str, Any]:
    """The settings.json dict for the team of ``cfg`` (see the module docstring), with
    ``ApiServerPort`` when ``api_server_port`` is given."""
    scenario, dynamics = cfg.scenario, cfg.dynamics
    for field in ("attackers", "defenders"):
        count = scenario.get(field)
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ConfigError(f"scenario.{field} must be an integer >= 1, got {count!r}")
    attackers = cfg.env.get("attackers") or scenario.attackers
    if not isinstance(attackers, int) or not 1 <= attackers <= scenario.attackers:
        raise ConfigError(f"env.attackers must be in [1, {scenario.attackers}], got {attackers}")
    names = vehicle_names(
        attackers,
        scenario.defenders,
        attacker=dynamics.get("attacker_name", "Attacker"),
        defender=dynamics.get("defender_name", "Defender"),
        names=dynamics.get("vehicles"),
    )
    spawn_ned = dynamics.get("spawn") or {}
    spawn_ned = OmegaConf.to_container(spawn_ned) if not isinstance(spawn_ned, dict) else spawn_ned
    if not isinstance(spawn_ned, dict):
        raise ConfigError(f"dynamics.spawn must map vehicles to [x, y, z], got {spawn_ned!r}")
    unknown = sorted(set(spawn_ned) - set(names))
    if unknown:
        raise ConfigError(f"dynamics.spawn names {unknown}, not vehicles of the team {names}")
    spawn_enu = {}
    for i, name in enumerate(names):
        point = spawn_ned.get(name)
        if point is None:
            spawn_enu[name] = (SPAWN_SPACING * i, 0.0, 0.0)
            continue
        if not _triple(point):
            raise ConfigError(f"dynamics.spawn.{name} must be [x, y, z] in metres, got {point!r}")
        spawn_enu[name] = ned_to_enu(tuple(float(v) for v in point))
    settings = make_settings(names, spawn_enu, clock_speed=dynamics.get("clock_speed", 1.0))
    if api_server_port is not None:
        settings["ApiServerPort"] = int(api_server_port)
    return settings


def _triple(point: Any) -> bool:
    if isinstance(point, (str, bytes)) or not hasattr(point, "__len__") or len(point) != 3:
        return False
    return all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in point
    )


def settings_command(args: Sequence[str]) -> str:
    """``settings out=PATH [port=P] [overrides]``: write the team's settings.json (with
    ``ApiServerPort`` P when given: one file per simulator of ``dynamics.endpoints``); returns
    a summary."""
    outs = [a for a in args if a.startswith("out=")]
    ports = [a for a in args if a.startswith("port=")]
    overrides = [a for a in args if not a.startswith(("out=", "port="))]
    if len(outs) != 1 or not outs[0][4:]:
        raise ConfigError(f"settings needs exactly one out=PATH, got {outs or 'none'}")
    if len(ports) > 1:
        raise ConfigError(f"settings takes at most one port=P, got {ports}")
    port = parse_endpoint(f"127.0.0.1:{ports[0][5:]}", "port")[1] if ports else None
    out = check_writable_file(outs[0][4:], "out")
    settings = team_settings(compose_team(overrides), api_server_port=port)
    path = write_settings(out, settings)
    vehicles = ", ".join(settings["Vehicles"])
    at = f", ApiServerPort {port}" if port is not None else ""
    return f"settings.json for {vehicles} (ClockSpeed {settings['ClockSpeed']:g}{at}) -> {path}"


def serve_command(args: Sequence[str]) -> int:
    """``serve [--settings FILE] [--port P] [server flags] [overrides]``: serve a test server
    until interrupted, for ``FILE`` or else for the team of the train config."""
    from rlplat.envs.airsim.testserver import main

    flags = [a for a in args if a.startswith("-") or "=" not in a]
    overrides = [a for a in args if a not in flags]
    if any(f == "--settings" or f.startswith("--settings=") for f in flags):
        if overrides:
            raise ConfigError(f"serve: overrides {overrides} do not apply with --settings")
        settings = None
    else:
        settings = team_settings(compose_team(overrides))
    try:
        return main(flags, settings=settings)
    except OSError as err:  # a host that does not resolve, a port in use
        raise AirSimError(str(err)) from None


# Options of the verbs ---------------------------------------------------------------------


def split_options(
    args: Sequence[str], names: Sequence[str], prefix: str | None = None
) -> tuple[dict[str, Any], list[str], list[str]]:
    """Split a verb's ``args`` into its options ``name=value`` (values parsed as YAML), its
    ``prefix.key=value`` overrides (kept as ``key=value``) and the rest (Hydra overrides)."""
    options: dict[str, Any] = {}
    prefixed, rest = [], []
    for arg in args:
        key, eq, value = arg.partition("=")
        if eq and key in names:
            try:
                options[key] = OmegaConf.to_container(OmegaConf.from_dotlist([f"v={value}"]))["v"]
            except Exception as err:  # OmegaConf's grammar errors have no common base
                raise ConfigError(f"{key}: cannot parse {value!r}: {err}") from None
        elif eq and prefix is not None and key.startswith(prefix + "."):
            prefixed.append(arg[len(prefix) + 1 :])
        else:
            rest.append(arg)
    return options, rest, prefixed


def _number(options: Mapping[str, Any], key: str, default: float) -> float:
    value = options.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{key}: must be a number, got {value!r}")
    return float(value)


def _list(options: Mapping[str, Any], key: str, default: Sequence[Any]) -> list[Any]:
    value = options.get(key, default)
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        raise ConfigError(f"{key}: must be a list, e.g. {key}=[{', '.join(map(str, default))}]")
    return list(value)


def dynamics_node(name: str, overrides: Sequence[str], field: str) -> dict[str, Any]:
    """The ``conf/dynamics/<name>.yaml`` node with ``key=value`` ``overrides`` (one-line errors
    naming ``field``)."""
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{field}: must name a conf/dynamics file, got {name!r}")
    try:
        cfg = compose_config("train", [f"dynamics={name}", *(f"dynamics.{o}" for o in overrides)])
    except HydraException as err:
        message = " ".join(str(err).split()).replace("dynamics", field)
        raise ConfigError(f"{field}: {message}") from None
    return OmegaConf.to_container(cfg.dynamics, resolve=True)


def _usable_as(path: Path) -> str:
    """How a written conf/dynamics file is picked: ``dynamics=NAME`` (and a search path)."""
    where = path.resolve().parent
    if where == (CONF_DIR / "dynamics").resolve():
        return f"dynamics={path.stem}"
    if where.name == "dynamics":
        return f"hydra.searchpath=[file://{where.parent}] dynamics={path.stem}"
    return f"dynamics={path.stem} once it is in conf/dynamics/"


# calibrate --------------------------------------------------------------------------------

CALIBRATE_OPTIONS = (
    "out", "vehicle", "velocity", "recording", "record", "max_speed", "amplitudes", "axes",
    "period", "settle_s", "hold_s", "rest_s", "altitude",
)  # fmt: skip


def calibrate_command(args: Sequence[str]) -> str:
    """``calibrate [dynamics.endpoints=[host:port]] [out=FILE] [options] [overrides]``: fly
    velocity step responses on the simulator (or read them: ``recording=FILE``), fit the
    ``velocity`` constants, write a conf/dynamics file; returns the summary to print."""
    from rlplat.envs.airsim.calibration import StepPlan, fit_velocity, fly_steps, velocity_yaml
    from rlplat.envs.airsim.recording import read_recording, replay, write_recording_csv
    from rlplat.envs.dynamics import DYNAMICS, VelocityDynamics
    from rlplat.experiment.factory import build_component

    options, overrides, velocity_overrides = split_options(args, CALIBRATE_OPTIONS, "velocity")
    cfg = compose_train(["dynamics=airsim", *overrides])
    if cfg.dynamics.name != "airsim":
        raise ConfigError(f"dynamics: calibrate flies dynamics=airsim, got {cfg.dynamics.name}")
    start = dynamics_node(options.get("velocity", "velocity"), velocity_overrides, "velocity")
    if start.pop("name") != "velocity":
        raise ConfigError(f"velocity: {options['velocity']!r} is not a velocity dynamics file")
    out = Path(str(options.get("out", CONF_DIR / "dynamics" / "velocity_calibrated.yaml")))
    if out.suffix != ".yaml":
        raise ConfigError(f"out: a conf/dynamics file ends in .yaml, got {out}")
    check_writable_file(out, "out")  # both before anything is flown
    if "record" in options:
        check_writable_file(str(options["record"]), "record")
    params = cfg.scenario.params
    top = max(params.attacker_max_speed.high, params.defender_max_speed.high)
    default_plan = StepPlan()
    plan = StepPlan(
        max_speed=_number(options, "max_speed", top),
        amplitudes=tuple(_list(options, "amplitudes", default_plan.amplitudes)),
        axes=tuple(_list(options, "axes", default_plan.axes)),
        period=_number(options, "period", cfg.env.control_period),
        settle_s=_number(options, "settle_s", default_plan.settle_s),
        hold_s=_number(options, "hold_s", default_plan.hold_s),
        rest_s=_number(options, "rest_s", default_plan.rest_s),
        altitude=_number(options, "altitude", default_plan.altitude),
    )
    command = shlex.join(["python", "-m", "rlplat.airsim", "calibrate", *args])

    # The step responses: flown now, or read from a recording.
    if "recording" in options:
        episodes = read_recording(str(options["recording"]))
        source = f"the recording {options['recording']} ({len(episodes)} episodes)"
    else:
        node = OmegaConf.to_container(cfg.dynamics, resolve=True)
        listed = node.get("vehicles")
        problem = vehicle_list(listed)
        if problem:
            raise ConfigError(f"dynamics.vehicles: {problem}")
        first = listed[0] if listed else node["attacker_name"]
        vehicle = str(options.get("vehicle", first))
        node["attacker_name"], node["vehicles"] = vehicle, None
        sim = build_component(
            DYNAMICS, "dynamics", node, num_envs=1, num_drones=1, device="cpu", num_attackers=1
        )
        try:
            spawn = ned_to_enu(tuple(sim.spawn[vehicle]))
            episodes = fly_steps(sim, plan, spawn)
        finally:
            sim.close()
        speeds = ", ".join(f"{a * plan.max_speed:g}" for a in plan.amplitudes)
        source = (
            f"the simulator at {node['endpoints'][0]} (vehicle {vehicle}): {len(episodes)} "
            f"velocity steps ({', '.join(plan.axes)}; {speeds} m/s; both directions) from "
            f"hover, control period {plan.period:g} s"
        )
        if "record" in options:
            write_recording_csv(str(options["record"]), episodes)

    # The fit, checked by replaying the episodes through VelocityDynamics with it.
    fit = fit_velocity(episodes, start)
    check = replay(episodes, lambda d: VelocityDynamics(num_envs=1, num_drones=d, **fit.params))
    err = check.summary()["all"]
    fitted = [k for k in fit.params if k not in fit.kept and k in ("tau_xy", "tau_z", "a_xy_max",
              "a_up_max", "a_down_max", "drag_xy", "drag_z")]  # fmt: skip
    base = options.get("velocity", "velocity")
    header = [
        f"Velocity dynamics calibrated against {source}.",
        f"Command: {command}",
        f"Fit: least squares of the velocity after each control period ({fit.samples} vehicle "
        "states) on the velocity model itself;",
        f"  RMS residual {fit.rms['xy']:.4f} m/s horizontal, {fit.rms['z']:.4f} m/s vertical "
        f"(with conf/dynamics/{base}.yaml: {fit.rms_start['xy']:.4f}, {fit.rms_start['z']:.4f});",
        f"  replayed positions off by {err['mean_m']:.4f} m on average, {err['max_m']:.4f} m at "
        "most.",
        f"Kept from conf/dynamics/{base}.yaml: "
        + ", ".join([k for k in fit.params if k not in fitted]),
    ]
    atomic_write_text(out, velocity_yaml(fit.params, header, fitted))
    values = ", ".join(f"{k}={fit.params[k]:.4g}" for k in fitted)
    return (
        f"calibrated velocity dynamics -> {out}: {values}; RMS velocity residual "
        f"{fit.rms['xy']:.4f} m/s horizontal, {fit.rms['z']:.4f} m/s vertical; use it as "
        f"{_usable_as(out)}"
    )


# replay -----------------------------------------------------------------------------------


def replay_command(args: Sequence[str]) -> str:
    """``replay recording=FILE [out=CSV] [overrides]``: fly a recording's commands through the
    configured embedded dynamics; returns the error table to print."""
    from rlplat.envs.airsim.recording import read_recording, replay
    from rlplat.envs.dynamics import DYNAMICS
    from rlplat.eval.tables import write_csv
    from rlplat.experiment.factory import build_component

    options, overrides, _ = split_options(args, ("recording", "out"))
    if "recording" not in options:
        raise ConfigError("recording: replay needs recording=FILE (a recording CSV or JSON lines)")
    cfg = compose_train(overrides)
    if cfg.dynamics.get("name") == "airsim":  # before the schema's rules of an airsim run
        raise ConfigError("dynamics: replay flies an embedded model (velocity, quadrotor)")
    validate_train_config(cfg)
    node = OmegaConf.to_container(cfg.dynamics, resolve=True)
    path = Path(str(options["recording"]))
    out = check_writable_file(options.get("out", path.with_name(f"{path.stem}.replay.csv")), "out")
    episodes = read_recording(path)
    result = replay(
        episodes,
        lambda d: build_component(
            DYNAMICS, "dynamics", node, num_envs=1, num_drones=d, device="cpu"
        ),
    )
    write_csv(out, result.rows)
    knobs = ", ".join(f"{k}={v}" for k, v in node.items() if k != "name")
    lines = [
        f"replay of {len(episodes)} episodes from {path} through dynamics={node['name']} "
        f"({knobs}): position error per step",
        f"{'vehicle':<12} {'steps':>6} {'mean m':>9} {'p95 m':>9} {'max m':>9}",
    ]
    for name, s in result.summary().items():
        lines.append(
            f"{name:<12} {s['steps']:>6} {s['mean_m']:>9.4f} {s['p95_m']:>9.4f} {s['max_m']:>9.4f}"
        )
    lines.append(f"per step: {out}")
    return "\n".join(lines)


# sim2sim ----------------------------------------------------------------------------------

SIM2SIM_OPTIONS = (
    "run_dir", "split", "ckpt", "out", "reference", "scenarios_dir", "attackers", "device",
    "record", "reference_tick",
)  # fmt: skip


def sim2sim_command(args: Sequence[str]) -> str:
    """``sim2sim run_dir=DIR dynamics.endpoints=[...] [split=test] [reference=NAME]
    [reference.KEY=VALUE] [options]``: the run's policy on its embedded dynamics (or
    ``reference``) and on the simulator; returns the summary to print."""
    from rlplat.experiment.evaluation import load_run_config
    from rlplat.experiment.sim2sim import sim2sim

    options, overrides, reference_overrides = split_options(args, SIM2SIM_OPTIONS, "reference")
    if "run_dir" not in options:
        raise ConfigError("run_dir: sim2sim needs run_dir=DIR (a training run directory)")
    stray = [o for o in overrides if not o.startswith("dynamics")]
    if stray:
        raise ConfigError(
            f"sim2sim: {stray[0]!r}: only dynamics.* (the simulator) and reference.* overrides "
            "apply; the run's own config is flown"
        )
    airsim = OmegaConf.to_container(compose_train(["dynamics=airsim", *overrides]).dynamics)
    run_dir = Path(str(options["run_dir"]))
    if "reference" in options:
        reference = dynamics_node(str(options["reference"]), reference_overrides, "reference")
    else:
        reference = OmegaConf.to_container(load_run_config(run_dir).dynamics, resolve=True)
        try:
            patch = OmegaConf.from_dotlist(reference_overrides)
        except Exception as err:  # OmegaConf's grammar errors have no common base
            raise ConfigError(f"reference: cannot parse {reference_overrides}: {err}") from None
        reference = {**reference, **OmegaConf.to_container(patch)}
    attackers = options.get("attackers")
    problem = None if attackers is None else Num(integer=True, ge=1)(attackers)
    if problem:
        raise ConfigError(f"attackers: {problem}")
    result = sim2sim(
        run_dir,
        airsim=airsim,
        reference=reference,
        ckpt=str(options.get("ckpt", "best")),
        split=str(options.get("split", "test")),
        out_dir=options.get("out"),
        scenarios_dir=options.get("scenarios_dir"),
        attackers=attackers,
        device=str(options.get("device", "cpu")),
        record=bool(options.get("record", True)),
        reference_tick=options.get("reference_tick"),
        command=shlex.join(["python", "-m", "rlplat.airsim", "sim2sim", *args]),
    )
    s = result.summary
    differ = f" ({', '.join(s['differing_scenarios'])})" if s["differing_scenarios"] else ""
    return (
        f"{s['reference']['name']} against airsim on {s['scenarios']} {s['split']} scenarios: "
        f"capture rate {s['reference_capture_rate']:.3f} / {s['airsim_capture_rate']:.3f}, "
        f"{s['outcomes_differing']} outcomes differ{differ}, largest position gap "
        f"{s['max_gap_m']:.4f} m ({s['max_gap_scenario']}); report {result.out_dir / 'report.md'}"
    )
