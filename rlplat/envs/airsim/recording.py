"""Recorded lock-step episodes (velocity commands and the states they led to), and their replay
through an embedded dynamics model.

A recording is a list of :class:`Episode`. On disk it is a CSV file, one row per vehicle and
step (:data:`COLUMNS`, ENU world frame, SI units)::

    episode,step,t_s,vehicle,x,y,z,vx,vy,vz,cmd_x,cmd_y,cmd_z,max_speed

- ``episode``: a label (a scenario id, a step test); rows of one episode are contiguous;
- ``step``: 0 for the state the episode starts from, k for the state after k control periods;
- ``t_s``: sim seconds since the episode's first state (the simulator's clock);
- ``x``..``vz``: the vehicle's position (m) and velocity (m/s) at that step;
- ``cmd_x``..``cmd_z``: the velocity command (m/s) flown from this step to the next, as sent
  (already clipped to ``max_speed``); empty on an episode's last step;
- ``max_speed``: m/s, the per-axis bound the command was clipped to (empty: none).

:class:`Recorder` writes one while a dynamics model flies (an AirSim evaluation:
``python -m rlplat.airsim sim2sim``); :func:`read_recording` also reads the JSON lines of the
loopback test server (``TestServer.take_recording`` / ``write_recording``, NED world frame): the
state after each continue is a step, the last ``moveByVelocity`` of each vehicle before it is
that step's command, and ``reset`` or ``simSetVehiclePose`` starts a new episode at the next
state (so an episode's first command, sent before any continue, is not in it).

:func:`replay` flies each episode's commands through a model started from its first recorded
state and measures how far the replayed positions fall from the recorded ones.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlplat.envs.airsim.frames import ned_to_enu
from rlplat.envs.dynamics import DroneDynamics
from rlplat.errors import ConfigError
from rlplat.io import atomic_write_text

log = logging.getLogger(__name__)

COLUMNS = (
    "episode", "step", "t_s", "vehicle", "x", "y", "z", "vx", "vy", "vz",
    "cmd_x", "cmd_y", "cmd_z", "max_speed",
)  # fmt: skip


@dataclass
class Episode:
    """One recorded episode of D vehicles and K control periods (ENU world, SI units).

    Attributes:
        name: the episode's label.
        vehicles: the D vehicle names.
        t: (K + 1,) float64 s, sim time of each state since the first.
        position: (K + 1, D, 3) float64 m.
        velocity: (K + 1, D, 3) float64 m/s.
        command: (K, D, 3) float64 m/s, the command flown from state k to state k + 1.
        max_speed: (D,) float64 m/s per axis (inf: no bound recorded).
    """

    name: str
    vehicles: list[str]
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    command: np.ndarray
    max_speed: np.ndarray

    @property
    def steps(self) -> int:
        """K, the control periods flown."""
        return len(self.command)

    @property
    def periods(self) -> np.ndarray:
        """(K,) float64 s, the sim time of each control period."""
        return np.diff(self.t)


# Writing ------------------------------------------------------------------------------------


def _num(value: float) -> str:
    return "" if not math.isfinite(value) else f"{value + 0.0:.9g}"


def recording_csv(episodes: Iterable[Episode]) -> str:
    """The CSV text of ``episodes`` (see the module docstring)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for ep in episodes:
        for k in range(ep.steps + 1):
            for d, name in enumerate(ep.vehicles):
                cmd = ep.command[k, d] if k < ep.steps else (math.nan,) * 3
                writer.writerow([
                    ep.name, k, _num(ep.t[k]), name,
                    *map(_num, ep.position[k, d]), *map(_num, ep.velocity[k, d]),
                    *map(_num, cmd), _num(ep.max_speed[d]),
                ])  # fmt: skip
    return buffer.getvalue()


def write_recording_csv(path: str | Path, episodes: Iterable[Episode]) -> Path:
    """Write ``episodes`` as a recording CSV, atomically; returns the path."""
    path = Path(path)
    atomic_write_text(path, recording_csv(episodes))
    return path


# Reading ------------------------------------------------------------------------------------


def read_recording(path: str | Path) -> list[Episode]:
    """The episodes of a recording CSV, or of the test server's JSON lines (``.jsonl``,
    ``.json``); a file that is neither is a one-line :class:`ConfigError` naming it."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"recording: cannot read {path}: {err.strerror or err}") from None
    if path.suffix in (".jsonl", ".json"):
        try:
            records = [json.loads(line) for line in text.splitlines() if line.strip()]
        except ValueError as err:
            raise ConfigError(f"recording: {path} is not JSON lines: {err}") from None
        episodes = from_server_records(records, str(path))
    else:
        episodes = _from_csv(text, str(path))
    if not episodes:
        raise ConfigError(f"recording: {path} holds no episode with a control period flown")
    return episodes


def _from_csv(text: str, where: str) -> list[Episode]:
    reader = csv.DictReader(io.StringIO(text))
    missing = [c for c in COLUMNS if c not in (reader.fieldnames or ())]
    if missing:
        raise ConfigError(f"recording: {where} is not a recording CSV (no column {missing[0]})")
    groups: dict[str, list[dict[str, str]]] = {}
    for row in reader:
        groups.setdefault(row["episode"], []).append(row)
    episodes = []
    for name, rows in groups.items():
        try:
            episodes.append(_episode_from_rows(name, rows))
        except (ValueError, KeyError) as err:
            raise ConfigError(f"recording: {where}, episode {name!r}: {err}") from None
    return [ep for ep in episodes if ep.steps > 0]


def _episode_from_rows(name: str, rows: list[dict[str, str]]) -> Episode:
    vehicles = list(dict.fromkeys(r["vehicle"] for r in rows))
    steps = 1 + max(int(r["step"]) for r in rows)
    table = {(int(r["step"]), r["vehicle"]): r for r in rows}
    if len(table) != steps * len(vehicles) or len(rows) != len(table):
        raise ValueError(f"needs one row per step 0..{steps - 1} and vehicle {vehicles}")

    def floats(k: int, keys: Sequence[str], last_empty: bool = False) -> list[list[float]]:
        out = []
        for v in vehicles:
            cells = [table[(k, v)][c] for c in keys]
            if last_empty and k == steps - 1:
                out.append([math.nan] * len(keys))
                continue
            out.append([float(c) for c in cells])
        return out

    t = np.array([float(table[(k, vehicles[0])]["t_s"]) for k in range(steps)])
    position = np.array([floats(k, ("x", "y", "z")) for k in range(steps)])
    velocity = np.array([floats(k, ("vx", "vy", "vz")) for k in range(steps)])
    command = np.array([floats(k, ("cmd_x", "cmd_y", "cmd_z"), True) for k in range(steps)])
    bound = [table[(0, v)]["max_speed"] for v in vehicles]
    if steps > 1 and not (np.diff(t) > 0).all():
        raise ValueError("t_s must increase from step to step")
    return Episode(
        name=name,
        vehicles=vehicles,
        t=t - t[0],
        position=position,
        velocity=velocity,
        command=command[:-1].reshape(steps - 1, len(vehicles), 3),
        max_speed=np.array([float(b) if b else math.inf for b in bound]),
    )


def from_server_records(records: Sequence[Mapping[str, Any]], where: str = "records"):
    """The episodes of the test server's records (see the module docstring), ENU world."""
    episodes: list[Episode] = []
    moves: dict[str, tuple[tuple[float, float, float], int]] = {}  # name -> (velocity, until)
    states: list[Mapping[str, Any]] = []
    commands: list[dict[str, tuple[float, float, float]]] = []

    def close() -> None:
        if len(states) > 1:
            episodes.append(_server_episode(str(len(episodes) + 1), states, commands))
        states.clear()
        commands.clear()

    for rec in records:
        call = rec.get("call")
        if call in ("reset", "simSetVehiclePose"):
            close()
        elif call == "moveByVelocity":
            vx, vy, vz, duration, *_, name = rec["params"]
            moves[name] = ((vx, vy, vz), rec["t_ns"] + round(duration * 1e9))
        elif "vehicles" in rec:
            if states:
                t_ns = rec["t_ns"]
                lapsed = [n for n, (_, until) in moves.items() if until < t_ns]
                if lapsed:
                    raise ConfigError(
                        f"recording: {where}: the command of {lapsed} lapsed before the state "
                        f"at t_ns={t_ns} (a move shorter than the step): not a lock-step run"
                    )
                commands.append({n: v for n, (v, _) in moves.items()})
            states.append(rec)
    close()
    return episodes


def _server_episode(name: str, states, commands) -> Episode:
    flown = list(dict.fromkeys(n for c in commands for n in c))
    vehicles = [n for n in flown if all(n in c for c in commands)]
    if not vehicles:
        raise ConfigError(f"recording: episode {name}: no vehicle was commanded at every step")

    def enu(key: str) -> np.ndarray:
        return np.array([[ned_to_enu(s["vehicles"][n][key]) for n in vehicles] for s in states])

    t = np.array([s["t_ns"] for s in states], dtype=np.int64)
    command = np.array([[ned_to_enu(c[n]) for n in vehicles] for c in commands])
    return Episode(
        name=name,
        vehicles=vehicles,
        t=(t - t[0]) / 1e9,
        position=enu("position"),
        velocity=enu("velocity"),
        command=command.reshape(len(commands), len(vehicles), 3),
        max_speed=np.full(len(vehicles), math.inf),
    )


# Recording while a model flies --------------------------------------------------------------


class Recorder:
    """Records what env ``env_index`` of ``dynamics`` flies: the state after every reset of
    that env (a new episode) and after every ``advance``, and the command of each advance
    (clipped to ``max_speed`` as the models clip it). The measured sim time of a step is the
    model's ``last_advance_s`` where it has one (``AirSimDynamics``), else the period.

    It wraps the instance's ``reset`` and ``advance`` until :meth:`detach`.

    Args:
        dynamics: the model to watch.
        names: the vehicle names (default: the model's ``names``, else ``drone0``...).
        env_index: which env of the batch to record.
    """

    def __init__(
        self, dynamics: DroneDynamics, names: Sequence[str] | None = None, env_index: int = 0
    ) -> None:
        self.dynamics, self.env_index = dynamics, int(env_index)
        default = getattr(dynamics, "names", None) or [
            f"drone{i}" for i in range(dynamics.num_drones)
        ]
        self.names = list(names or default)
        self._reset, self._advance = dynamics.reset, dynamics.advance
        dynamics.reset, dynamics.advance = self._on_reset, self._on_advance
        self._episodes: list[dict[str, list]] = []

    def _state(self) -> tuple[np.ndarray, np.ndarray]:
        i = self.env_index
        pos = self.dynamics.position[i].detach().double().cpu().numpy()
        return pos, self.dynamics.velocity[i].detach().double().cpu().numpy()

    def _on_reset(self, mask: torch.Tensor, *args: Any, **kwargs: Any) -> None:
        self._reset(mask, *args, **kwargs)
        if bool(mask[self.env_index]):
            pos, vel = self._state()
            bound = self.dynamics.max_speed[self.env_index].double().cpu().numpy()
            self._episodes.append(
                {"t": [0.0], "p": [pos], "v": [vel], "cmd": [], "max_speed": bound}
            )

    def _on_advance(self, command: torch.Tensor, period: float) -> None:
        self._advance(command, period)
        if not self._episodes:
            return
        ep = self._episodes[-1]
        bound = torch.as_tensor(ep["max_speed"], dtype=torch.float64).unsqueeze(-1)
        cmd = command[self.env_index].detach().double().cpu()
        ep["cmd"].append(torch.clamp(cmd, -bound, bound).numpy())
        dt = getattr(self.dynamics, "last_advance_s", math.nan)
        ep["t"].append(ep["t"][-1] + (dt if math.isfinite(dt) else period))
        pos, vel = self._state()
        ep["p"].append(pos)
        ep["v"].append(vel)

    def episodes(self, labels: Sequence[str] | None = None) -> list[Episode]:
        """The episodes recorded so far that flew at least one step, labelled by ``labels``
        (in order; default 1, 2, ...)."""
        flown = [ep for ep in self._episodes if ep["cmd"]]
        if labels is not None and len(labels) != len(flown):
            raise ValueError(f"{len(labels)} labels for {len(flown)} recorded episodes")
        d = len(self.names)
        return [
            Episode(
                name=str(labels[i]) if labels is not None else str(i + 1),
                vehicles=self.names,
                t=np.array(ep["t"]),
                position=np.stack(ep["p"]),
                velocity=np.stack(ep["v"]),
                command=np.stack(ep["cmd"]).reshape(-1, d, 3),
                max_speed=np.asarray(ep["max_speed"], dtype=np.float64),
            )
            for i, ep in enumerate(flown)
        ]

    def detach(self) -> None:
        """Give the model its own ``reset`` and ``advance`` back."""
        self.dynamics.__dict__.pop("reset", None)
        self.dynamics.__dict__.pop("advance", None)


# Replay -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Replay:
    """Per-step position error of a replay.

    Attributes:
        rows: one per (episode, step >= 1, vehicle): ``episode``, ``step``, ``t_s``,
            ``vehicle``, ``error_m`` and the recorded and replayed positions.
        vehicles: the vehicle names, in order of first appearance.
    """

    rows: list[dict[str, Any]]
    vehicles: list[str]

    def errors(self, vehicle: str | None = None) -> np.ndarray:
        """The per-step position errors (m), of one vehicle or of all."""
        return np.array(
            [r["error_m"] for r in self.rows if vehicle is None or r["vehicle"] == vehicle]
        )

    def summary(self) -> dict[str, dict[str, float]]:
        """Per vehicle (and ``all``): steps, mean, p95 and max position error (m)."""
        out = {}
        for name in [*self.vehicles, None]:
            e = self.errors(name)
            out[name or "all"] = {
                "steps": int(e.size),
                "mean_m": float(e.mean()),
                "p95_m": float(np.percentile(e, 95)),
                "max_m": float(e.max()),
            }
        return out


def replay(episodes: Sequence[Episode], make_model: Callable[[int], DroneDynamics]) -> Replay:
    """Fly every episode's recorded commands through a fresh model from ``make_model(D)``
    (one env of D drones), started from the episode's first recorded state, each command held
    for its recorded period; compare positions step by step.
    """
    rows, vehicles = [], []
    for ep in episodes:
        vehicles.extend(v for v in ep.vehicles if v not in vehicles)
        model = make_model(len(ep.vehicles))
        f32 = dict(dtype=torch.float32)
        model.reset(
            torch.ones(1, dtype=torch.bool),
            torch.as_tensor(ep.position[:1], **f32),
            torch.as_tensor(ep.velocity[:1], **f32),
            torch.as_tensor(ep.max_speed[None], **f32),
        )
        for k, period in enumerate(ep.periods):
            model.advance(torch.as_tensor(ep.command[k : k + 1], **f32), float(period))
            got = model.position[0].double().numpy()
            want = ep.position[k + 1]
            err = np.linalg.norm(got - want, axis=-1)
            for d, name in enumerate(ep.vehicles):
                rows.append({
                    "episode": ep.name, "step": k + 1, "t_s": float(ep.t[k + 1]),
                    "vehicle": name, "error_m": float(err[d]),
                    **{f"recorded_{a}": float(want[d, i]) for i, a in enumerate("xyz")},
                    **{f"replayed_{a}": float(got[d, i]) for i, a in enumerate("xyz")},
                })  # fmt: skip
    if not rows:
        raise ConfigError("recording: no control period to replay")
    return Replay(rows, vehicles)
