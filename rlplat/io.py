"""Atomic file writes: a reader never sees a half-written file; and whether a folder can be
written before any work."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

from rlplat.errors import ConfigError


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same directory and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def check_writable_dir(path: str | os.PathLike, field: str) -> Path:
    """``path`` as a folder files can be written to, or made in: itself or its nearest
    existing parent must be a folder this process can write a file in (it makes one and removes
    it). Makes nothing else; a one-line :class:`ConfigError` naming ``field`` otherwise
    (before any work, not after it)."""
    path = Path(path)
    existing = next(p for p in (path, *path.parents) if p.exists() or p == p.parent)
    if not existing.is_dir():
        what = "is a file" if existing == path else f"{existing} is a file"
        raise ConfigError(f"{field}: cannot write to {path}: {what}")
    try:  # a file made and removed at once: what the permission bits do not say (/proc)
        with tempfile.NamedTemporaryFile(dir=existing, prefix=".rlplat-probe-"):
            pass
    except OSError as e:
        raise ConfigError(
            f"{field}: cannot write to {path}: {existing} is not writable ({e.strerror})"
        ) from None
    return path


def refuse_run_dir(path: str | os.PathLike, field: str, why: str) -> None:
    """A one-line :class:`ConfigError` naming ``field`` where ``path`` is a training run's own
    folder (its ``config.yaml`` and ``checkpoints/``); ``why`` says what writing there would
    do to the run."""
    path = Path(path)
    if (path / "config.yaml").is_file() and (path / "checkpoints").is_dir():
        raise ConfigError(f"{field}: {path} is a training run's directory; {why}")


def check_writable_file(path: str | os.PathLike, field: str) -> Path:
    """``path`` as a file that can be written (made, or replaced): not a folder, in a folder
    that :func:`check_writable_dir` accepts; a one-line :class:`ConfigError` naming ``field``
    otherwise, before any work."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{field}: cannot write the file {path}: it is a folder")
    check_writable_dir(path.parent, field)
    return path
