"""Shared behaviour of the command-line entry points."""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from rlplat.errors import RlplatError

T = TypeVar("T")


def exit_on_error(fn: Callable[..., T]) -> Callable[..., T]:
    """Turn an :class:`RlplatError` into one line on stderr and exit code 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except RlplatError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)

    return wrapper


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser with its errors in one line, ``error: PROG: MESSAGE (see --help)``,
    exit code 2 (argparse's own prints the usage first)."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message} (see --help)\n")


def name_arg(value: str) -> str:
    """An argument that names something (a folder, a file, a policy): an empty one is refused,
    not read as the current folder or as no option given."""
    if not value.strip():
        raise argparse.ArgumentTypeError(f"must not be empty, got {value!r}")
    return value


def path_arg(value: str) -> Path:
    """A path argument, refused empty (``Path('')`` is the current folder)."""
    return Path(name_arg(value))
