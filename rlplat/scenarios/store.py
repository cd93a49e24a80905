"""Scenario sets on disk (JSON Lines + manifest) and in memory (tensors for a batched env)."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from rlplat.errors import ScenarioFileError
from rlplat.io import atomic_write_bytes, atomic_write_text, sha256_bytes
from rlplat.scenarios.generator import (
    SPLITS,
    SplitColumns,
    generate,
    max_speeds,
    start_positions,
)
from rlplat.scenarios.quality import quality_report
from rlplat.scenarios.spec import STRATEGIES, ScenarioSpec

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
        manifest = json.loads(_read(path / MANIFEST))
        version = manifest.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ScenarioFileError(
                f"{path / MANIFEST}: schema_version {version!r} is not supported "
                f"(this rlplat reads {SCHEMA_VERSION})"
            )
        spec = ScenarioSpec.from_dict(manifest["config"], where=f"{path / MANIFEST}: config")
        ids, splits = {}, {}
        for split in SPLITS:
            entry = manifest["splits"][split]
            data = _read(path / entry["file"])
            if sha256_bytes(data) != entry["sha256"]:
                raise ScenarioFileError(
                    f"{path / entry['file']}: sha256 differs from the manifest "
                    "(file truncated or edited since generation)"
                )
            records = [json.loads(line) for line in data.decode("utf-8").splitlines()]
            ids[split] = [r["id"] for r in records]
            splits[split] = _to_tensors(records, spec, path / entry["file"])
        routes = torch.tensor(spec.routes, dtype=torch.float32)
        return cls(path, manifest, spec, ids, splits, routes)


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ScenarioFileError(f"{path}: missing file of the scenario set") from None


def write_scenario_set(spec: ScenarioSpec, out_dir: str | os.PathLike) -> dict[str, Any]:
    """Generate ``spec`` and write it to ``out_dir``; return the manifest.

    Everything is generated and checked in memory first; each file is then written atomically,
    the manifest last, so an interrupted write never leaves a set that loads.
    """
    splits = generate(spec)
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
    out = Path(out_dir)
    for split, data in files.items():
        atomic_write_bytes(out / f"{split}.jsonl", data)
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    log.info("wrote %d scenarios to %s", spec.n_total, out)
    return manifest
