"""Scenario sets on disk (JSON Lines + manifest) and in memory (tensors for a batched env)."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from rlplat.errors import ScenarioFileError
from rlplat.io import atomic_write_bytes, atomic_write_text, sha256_bytes
from rlplat.scenarios.generator import SPLITS, SplitColumns, generate
from rlplat.scenarios.quality import quality_report
from rlplat.scenarios.spec import STRATEGIES, ScenarioSpec

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"


def _jsonl(cols: SplitColumns) -> bytes:
    lines = []
    for i, sid in enumerate(cols.ids):
        z, dx, dy, dz, vd, va = cols.values[i].tolist()
        rec = {
            "id": sid,
            "defender_start": [0.0, 0.0, z],
            "attacker_start": [dx, dy, round(z + dz, 6)],
            "route": int(cols.route[i]),
            "defender_strategy": STRATEGIES[cols.strategy[i]],
            "defender_max_speed": vd,
            "attacker_max_speed": va,
        }
        lines.append(json.dumps(rec))
    return "".join(line + "\n" for line in lines).encode("utf-8")


def _to_tensors(records: list[dict[str, Any]]) -> TensorDict:
    n = len(records)

    def col(key: str, dtype: torch.dtype, shape=()) -> torch.Tensor:
        return torch.tensor([r[key] for r in records], dtype=dtype).reshape(n, *shape)

    return TensorDict(
        {
            "defender_start": col("defender_start", torch.float32, (3,)),
            "attacker_start": col("attacker_start", torch.float32, (3,)),
            "route": col("route", torch.int64),
            "defender_strategy": torch.tensor(
                [STRATEGIES.index(r["defender_strategy"]) for r in records], dtype=torch.int64
            ),
            "defender_max_speed": col("defender_max_speed", torch.float32),
            "attacker_max_speed": col("attacker_max_speed", torch.float32),
        },
        batch_size=[n],
    )


@dataclass
class ScenarioSet:
    """A loaded scenario set.

    Attributes:
        path: directory it was loaded from.
        manifest: the parsed ``manifest.json``.
        spec: the generator spec it was made with.
        ids: per split, the scenario ids in file order.
        splits: per split, a TensorDict with batch size ``[n]``: ``defender_start`` and
            ``attacker_start`` (n, 3) float32 m ENU, ``route`` (n,) int64,
            ``defender_strategy`` (n,) int64 index into ``STRATEGIES``, ``defender_max_speed``
            and ``attacker_max_speed`` (n,) float32 m/s.
        routes: (n_routes, n_setpoints, 3) float32 route setpoints, m ENU.
    """

    path: Path
    manifest: dict[str, Any]
    spec: ScenarioSpec
    ids: dict[str, list[str]]
    splits: dict[str, TensorDict]
    routes: torch.Tensor

    @property
    def digest(self) -> str:
        """SHA-256 of the manifest: identifies the set (recorded by training runs)."""
        return sha256_bytes((self.path / MANIFEST).read_bytes())

    def split(self, name: str) -> TensorDict:
        """The tensors of one split; an unknown name lists the valid ones."""
        if name not in self.splits:
            raise ScenarioFileError(f"split: unknown split '{name}'; valid: {', '.join(SPLITS)}")
        return self.splits[name]

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
            splits[split] = _to_tensors(records)
        spec = ScenarioSpec.from_dict(manifest["config"], where=f"{path / MANIFEST}: config")
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
    files = {split: _jsonl(cols) for split, cols in splits.items()}
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
