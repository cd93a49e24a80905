"""Scenario sets on disk (JSON Lines + manifest) and in memory (tensors for a batched env)."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from rlplat.errors import ConfigError, ScenarioFileError
from rlplat.io import atomic_write_bytes, atomic_write_text, sha256_bytes
from rlplat.scenarios.generator import (
    SPLITS,
    SplitColumns,
    generate,
    max_speeds,
    start_positions,
)
from rlplat.scenarios.quality import quality_report
from rlplat.scenarios.spec import MAX_MAGNITUDE, MIN_RESOLUTION, STRATEGIES, ScenarioSpec

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"


def _jsonl(spec: ScenarioSpec, cols: SplitColumns) -> bytes:
    """One JSON record per scenario: the first attacker and defender at the top level, then
    ``extra_attackers`` (k > 1) and ``extra_defenders`` (m > 1)."""
    attackers, defenders = start_positions(spec, cols.values)
    v_att, v_def = max_speeds(spec, cols.values)
    attackers = [[[x, y, round(z, 6)] for x, y, z in row] for row in attackers.tolist()]
    defenders = defenders.tolist()
    v_att, v_def = v_att.tolist(), v_def.tolist()
    route, strategy = cols.route.tolist(), cols.strategy.tolist()
    lines = []
    for i, sid in enumerate(cols.ids):
        rec = {
            "id": sid,
            "defender_start": defenders[i][0],
            "attacker_start": attackers[i][0],
            "route": route[i][0],
            "defender_strategy": STRATEGIES[strategy[i][0]],
            "defender_max_speed": v_def[i][0],
            "attacker_max_speed": v_att[i][0],
        }
        if spec.attackers > 1:
            rec["extra_attackers"] = [
                {"start": p, "max_speed": v}
                for p, v in zip(attackers[i][1:], v_att[i][1:], strict=True)
            ]
        if spec.defenders > 1:
            rec["extra_defenders"] = [
                {"start": p, "route": r, "defender_strategy": STRATEGIES[s], "max_speed": v}
                for p, r, s, v in zip(
                    defenders[i][1:], route[i][1:], strategy[i][1:], v_def[i][1:], strict=True
                )
            ]
        lines.append(json.dumps(rec))
    return "".join(line + "\n" for line in lines).encode("utf-8")


#: The fields of a record, and of its extra drones' entries.
RECORD_FIELDS = ("id", "defender_start", "attacker_start", "route", "defender_strategy",
                 "defender_max_speed", "attacker_max_speed")  # fmt: skip
EXTRA_ATTACKER_FIELDS = ("start", "max_speed")
EXTRA_DEFENDER_FIELDS = ("start", "route", "defender_strategy", "max_speed")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_fields(rec: Any, fields: Sequence[str], optional: Sequence[str], at: str) -> None:
    if not isinstance(rec, dict):
        raise ScenarioFileError(f"{at}: not a JSON object: {rec!r:.60}")
    missing = [f for f in fields if f not in rec]
    if missing:
        raise ScenarioFileError(f"{at}: missing field {missing[0]!r}")
    unknown = [f for f in rec if f not in fields and f not in optional]
    if unknown:
        raise ScenarioFileError(
            f"{at}: unknown field {unknown[0]!r}; valid: {', '.join((*fields, *optional))}"
        )


def _check_drone(rec: dict, start: str, speed: str, at: str, n_routes: int | None = None,
                 route: str = "route", strategy: str = "defender_strategy") -> None:  # fmt: skip
    """One drone's start (3 numbers within ±MAX_MAGNITUDE m), maximum speed (in
    [MIN_RESOLUTION, MAX_MAGNITUDE] m/s) and, for a defender (``n_routes``), route index and
    strategy name."""
    p = rec[start]
    if not (
        isinstance(p, list)
        and len(p) == 3
        and all(_number(x) and abs(x) <= MAX_MAGNITUDE for x in p)
    ):
        raise ScenarioFileError(
            f"{at}: {start} must be 3 numbers [x, y, z] m in [-{MAX_MAGNITUDE:g}, "
            f"{MAX_MAGNITUDE:g}], got {p!r:.60}"
        )
    v = rec[speed]
    if not (_number(v) and MIN_RESOLUTION <= v <= MAX_MAGNITUDE):
        raise ScenarioFileError(
            f"{at}: {speed} must be a number in [{MIN_RESOLUTION:g}, {MAX_MAGNITUDE:g}] (m/s), "
            f"got {v!r:.30}"
        )
    if n_routes is None:
        return
    r = rec[route]
    if not (isinstance(r, int) and not isinstance(r, bool) and 0 <= r < n_routes):
        raise ScenarioFileError(
            f"{at}: {route} must be a route index in [0, {n_routes - 1}] (the manifest's "
            f"config.routes), got {r!r:.30}"
        )
    if rec[strategy] not in STRATEGIES:
        raise ScenarioFileError(
            f"{at}: {strategy} {rec[strategy]!r:.30} is unknown; valid: {', '.join(STRATEGIES)}"
        )


def check_record(rec: Any, spec: ScenarioSpec, at: str) -> None:
    """A scenario record as :func:`_jsonl` writes it for ``spec``'s k attackers and m
    defenders: its fields, no others, each of the right type and range.

    Raises:
        ScenarioFileError: one line naming ``at`` (file:line), the field and its value.
    """
    k, m, n_routes = spec.attackers, spec.defenders, len(spec.routes)
    optional = (("extra_attackers",) if k > 1 else ()) + (("extra_defenders",) if m > 1 else ())
    _check_fields(rec, RECORD_FIELDS + optional, (), at)
    if not isinstance(rec["id"], str) or not rec["id"]:
        raise ScenarioFileError(f"{at}: id must be a non-empty string, got {rec['id']!r:.30}")
    _check_drone(rec, "attacker_start", "attacker_max_speed", at)
    _check_drone(rec, "defender_start", "defender_max_speed", at, n_routes)
    for key, count, fields in (("extra_attackers", k - 1, EXTRA_ATTACKER_FIELDS),
                               ("extra_defenders", m - 1, EXTRA_DEFENDER_FIELDS)):  # fmt: skip
        if not count:
            continue
        extra = rec[key]
        if not isinstance(extra, list) or len(extra) != count:
            got = len(extra) if isinstance(extra, list) else repr(extra)[:30]
            raise ScenarioFileError(
                f"{at}: {key} must list {count} drone(s) (the manifest's config has "
                f"{k} attacker(s) and {m} defender(s)), got {got}"
            )
        for j, drone in enumerate(extra):
            where = f"{at}: {key}[{j}]"
            _check_fields(drone, fields, (), where)
            _check_drone(drone, "start", "max_speed", where,
                         n_routes if key == "extra_defenders" else None)  # fmt: skip


def _records(data: bytes, spec: ScenarioSpec, where: Path, count: Any) -> list[dict[str, Any]]:
    """The checked records of one split's file (blank lines skipped): valid JSON, every
    record as :func:`check_record` wants it, ids unique, as many as the manifest's ``count``."""
    try:
        lines = data.decode("utf-8").splitlines()
    except UnicodeDecodeError as e:
        raise ScenarioFileError(f"{where}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    records, seen = [], {}
    for number, line in enumerate(lines, 1):
        if not line.strip():  # a blank line holds no record
            continue
        at = f"{where}:{number}"
        try:
            rec = json.loads(line)
        except ValueError as e:
            raise ScenarioFileError(f"{at}: not a JSON record ({e})") from None
        check_record(rec, spec, at)
        if rec["id"] in seen:
            raise ScenarioFileError(f"{at}: id {rec['id']!r} repeats line {seen[rec['id']]}")
        seen[rec["id"]] = number
        records.append(rec)
    if isinstance(count, bool) or not isinstance(count, int):
        raise ScenarioFileError(f"{where}: the manifest's count must be an integer, got {count!r}")
    if count != len(records):
        raise ScenarioFileError(
            f"{where}: {len(records)} scenarios, the manifest's count says {count!r}"
        )
    return records


def _to_tensors(records: list[dict[str, Any]], spec: ScenarioSpec, where: Path) -> TensorDict:
    """Records of a k-vs-m set as tensors with batch size [n] and a drone dimension."""
    n, k, m = len(records), spec.attackers, spec.defenders
    a_start, a_speed, d_start, d_speed, route, strategy = ([] for _ in range(6))
    for line, r in enumerate(records, 1):
        extra_a, extra_d = r.get("extra_attackers", []), r.get("extra_defenders", [])
        if len(extra_a) != k - 1 or len(extra_d) != m - 1:
            raise ScenarioFileError(
                f"{where}:{line}: {1 + len(extra_a)} attacker(s) and {1 + len(extra_d)} "
                f"defender(s), the manifest's config has {k} and {m}"
            )
        a_start.append([r["attacker_start"], *(a["start"] for a in extra_a)])
        a_speed.append([r["attacker_max_speed"], *(a["max_speed"] for a in extra_a)])
        d_start.append([r["defender_start"], *(d["start"] for d in extra_d)])
        d_speed.append([r["defender_max_speed"], *(d["max_speed"] for d in extra_d)])
        route.append([r["route"], *(d["route"] for d in extra_d)])
        names = [r["defender_strategy"], *(d["defender_strategy"] for d in extra_d)]
        strategy.append([STRATEGIES.index(s) for s in names])

    def tensor(rows: list, dtype: torch.dtype, *shape: int) -> torch.Tensor:
        return torch.tensor(rows, dtype=dtype).reshape(n, *shape)

    return TensorDict(
        {
            "defender_start": tensor(d_start, torch.float32, m, 3),
            "attacker_start": tensor(a_start, torch.float32, k, 3),
            "route": tensor(route, torch.int64, m),
            "defender_strategy": tensor(strategy, torch.int64, m),
            "defender_max_speed": tensor(d_speed, torch.float32, m),
            "attacker_max_speed": tensor(a_speed, torch.float32, k),
        },
        batch_size=[n],
    )


@dataclass
class ScenarioSet:
    """A loaded scenario set of k attackers and m defenders per scenario.

    Attributes:
        path: directory it was loaded from.
        manifest: the parsed ``manifest.json``.
        spec: the generator spec it was made with.
        ids: per split, the scenario ids in file order.
        splits: per split, a TensorDict with batch size ``[n]`` whose entries always carry the
            drone dimension (also for 1 vs 1; index 0 is the first attacker / defender):
            ``attacker_start`` (n, k, 3) and ``defender_start`` (n, m, 3) float32 m ENU,
            ``route`` (n, m) int64, ``defender_strategy`` (n, m) int64 index into
            ``STRATEGIES``, ``attacker_max_speed`` (n, k) and ``defender_max_speed`` (n, m)
            float32 m/s.
        routes: (n_routes, n_setpoints, 3) float32 route setpoints, m ENU.
    """

    path: Path
    manifest: dict[str, Any]
    spec: ScenarioSpec
    ids: dict[str, list[str]]
    splits: dict[str, TensorDict]
    routes: torch.Tensor

    @property
    def attackers(self) -> int:
        """Attackers per scenario, k (from the spec; from the tensors of a set without one)."""
        if self.spec is not None:
            return self.spec.attackers
        return next(iter(self.splits.values()))["attacker_start"].shape[1]

    @property
    def defenders(self) -> int:
        """Defenders per scenario, m (from the spec; from the tensors of a set without one)."""
        if self.spec is not None:
            return self.spec.defenders
        return next(iter(self.splits.values()))["defender_start"].shape[1]

    @property
    def digest(self) -> str:
        """SHA-256 of the manifest: identifies the set (recorded by training runs)."""
        return sha256_bytes((self.path / MANIFEST).read_bytes())

    def split(self, name: str) -> TensorDict:
        """The tensors of one split; an unknown name lists the valid ones."""
        if name not in self.splits:
            raise ScenarioFileError(f"split: unknown split '{name}'; valid: {', '.join(SPLITS)}")
        return self.splits[name]

    def picked(self, name: str, rows: torch.Tensor) -> ScenarioSet:
        """A set holding only split ``name``'s rows ``rows`` (int64, in that order, repeats
        allowed): an env of ``len(rows)`` envs walking it flies row ``rows[i]`` in env ``i``."""
        ids = [self.ids[name][i] for i in rows.tolist()]
        return replace(self, splits={name: self.split(name)[rows]}, ids={name: ids})

    @classmethod
    def load(cls, path: str | os.PathLike) -> ScenarioSet:
        """Read a set written by :func:`write_scenario_set`, checking schema version and hashes.

        Raises:
            ScenarioFileError: a missing file, another schema version, or a file whose SHA-256
                differs from the manifest (truncated or edited).
        """
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise ScenarioFileError(f"{path}: not a directory (a scenario set is the directory "
                                    f"that holds {MANIFEST})")  # fmt: skip
        try:
            manifest = json.loads(_read(path / MANIFEST))
        except ValueError as e:
            raise ScenarioFileError(f"{path / MANIFEST}: not JSON ({e})") from None
        if not isinstance(manifest, dict):
            raise ScenarioFileError(f"{path / MANIFEST}: not a JSON object")
        version = manifest.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ScenarioFileError(
                f"{path / MANIFEST}: schema_version {version!r} is not supported "
                f"(this rlplat reads {SCHEMA_VERSION})"
            )
        for key in ("config", "splits"):
            if not isinstance(manifest.get(key), dict):
                raise ScenarioFileError(f"{path / MANIFEST}: missing {key}")
        spec = ScenarioSpec.from_dict(
            manifest["config"], where=f"{path / MANIFEST}: config", written=True
        )
        ids, splits = {}, {}
        for split in SPLITS:
            entry = manifest["splits"].get(split)
            if not (isinstance(entry, dict) and {"file", "sha256", "count"} <= entry.keys()):
                raise ScenarioFileError(
                    f"{path / MANIFEST}: splits.{split} must name its file, sha256 and count, "
                    f"got {entry!r:.80}"
                )
            name = entry["file"]
            if not (isinstance(name, str) and name not in (".", "..") and Path(name).name == name):
                raise ScenarioFileError(
                    f"{path / MANIFEST}: splits.{split}.file must name a file of the set's own "
                    f"directory, got {name!r:.80}"
                )
            data = _read(path / name)
            if sha256_bytes(data) != entry["sha256"]:
                raise ScenarioFileError(
                    f"{path / name}: sha256 differs from the manifest "
                    "(file truncated or edited since generation)"
                )
            records = _records(data, spec, path / name, entry["count"])
            if len(records) != spec.counts[split]:  # what a run records as the set's size
                raise ScenarioFileError(
                    f"{path / MANIFEST}: splits.{split} holds {len(records)} scenarios, "
                    f"config.n_{split} says {spec.counts[split]}"
                )
            ids[split] = [r["id"] for r in records]
            splits[split] = _to_tensors(records, spec, path / name)
        routes = torch.tensor(spec.routes, dtype=torch.float32)
        return cls(path, manifest, spec, ids, splits, routes)


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ScenarioFileError(f"{path}: missing file of the scenario set") from None
    except OSError as e:  # a directory in its place, no permission, ...
        raise ScenarioFileError(f"{path}: cannot be read ({e.strerror})") from None


def write_scenario_set(spec: ScenarioSpec, out_dir: str | os.PathLike) -> dict[str, Any]:
    """Generate ``spec`` and write it to ``out_dir``; return the manifest.

    Everything is generated and checked in memory first; each file is then written atomically,
    the manifest last, so an interrupted write never leaves a set that loads.
    """
    out = Path(out_dir)
    made = [p for p in (out, *out.parents) if not p.exists()]
    try:  # before any work: a folder that cannot be made is one line
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(
            f"out_dir: cannot write the scenario set to {out}: {e.strerror}"
        ) from None
    try:
        splits = generate(spec)
    except BaseException:
        for p in made:  # nothing left behind: the folders this call made, still empty
            with contextlib.suppress(OSError):
                p.rmdir()
        raise
    files = {split: _jsonl(spec, cols) for split, cols in splits.items()}
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "seed": spec.seed,
        "config": spec.to_dict(),
        "splits": {
            split: {
                "file": f"{split}.jsonl",
                "count": len(splits[split]),
                "sha256": sha256_bytes(b),
            }
            for split, b in files.items()
        },
        "quality": quality_report(spec, splits),
    }
    text = json.dumps(manifest, indent=2) + "\n"
    before = (out / MANIFEST).read_bytes() if (out / MANIFEST).is_file() else None
    if before is not None and before != text.encode():  # runs may cite the one replaced
        log.warning("replacing the scenario set in %s (manifest sha256 %s) by another",
                    out, sha256_bytes(before)[:16])  # fmt: skip
    try:
        for split, data in files.items():
            atomic_write_bytes(out / f"{split}.jsonl", data)
        atomic_write_text(out / MANIFEST, text)
    except OSError as e:
        raise ConfigError(
            f"out_dir: cannot write the scenario set to {out}: {e.strerror}"
        ) from None
    log.info("wrote %d scenarios to %s", spec.n_total, out)
    return manifest
