"""Metrics of a run: TorchRL loggers (CSV always, plus the configured one)."""

from __future__ import annotations

import csv
import logging
import os
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from torchrl.record.loggers import CSVLogger, Logger, TensorboardLogger, WandbLogger

from rlplat.errors import ConfigError

log = logging.getLogger(__name__)

BACKENDS = ("csv", "wandb", "tensorboard")


def make_logger(
    node: Mapping[str, Any], run_dir: Path, exp_name: str, config: dict
) -> Logger | None:
    """The configured TorchRL logger writing inside ``run_dir``; None for ``csv`` (always on)."""
    backend = node["backend"]
    if backend == "csv":
        return None
    if backend == "tensorboard":
        return TensorboardLogger(exp_name="tensorboard", log_dir=str(run_dir))
    if backend == "wandb":
        mode, _ = wandb_mode(node)
        logger = WandbLogger(
            exp_name=exp_name,
            offline=mode == "offline",  # other modes are read by wandb from WANDB_MODE
            save_dir=str(run_dir),
            project=node.get("project", "rlplat"),
            log_env_packages=False,
        )
        logger.log_hparams(config)
        return logger
    raise ConfigError(f"logger.backend: unknown '{backend}'; valid: {', '.join(BACKENDS)}")


def wandb_mode(node: Mapping[str, Any]) -> tuple[str, str]:
    """The mode wandb runs in and the setting that chose it: ``WANDB_MODE`` where it is set,
    else ``logger.mode``."""
    if "WANDB_MODE" in os.environ:
        return os.environ["WANDB_MODE"], "WANDB_MODE"
    return node.get("mode", "offline"), "logger.mode"


def check_logger(node: Mapping[str, Any]) -> None:
    """Refuse, before any work, a wandb logger set online on a machine without a W&B login:
    wandb would stop the run at its start, its folder made. Where it may ask (a terminal),
    wandb asks for the login here."""
    if node["backend"] != "wandb":
        return
    mode, field = wandb_mode(node)
    if mode != "online":
        return
    import wandb

    try:
        wandb.login(verify=False)  # the credentials on this machine; nothing sent
    except wandb.errors.UsageError as e:
        raise ConfigError(
            f"{field}: online needs a W&B login on this machine (wandb: {e}); "
            f"{field}=offline logs without one"
        ) from None


class Metrics:
    """Sends scalars to every logger and keeps their history for the learning curve.

    CSV files (one per metric, ``<run>/metrics/scalars/<namespace>/<name>.csv``) are always
    written; ``extra`` is the configured logger when it is not CSV.
    """

    def __init__(self, run_dir: Path, extra: Logger | None = None, resume: bool = False) -> None:
        self.history: dict[str, list[tuple[int, float]]] = defaultdict(list)
        if resume:
            self._read_history(Path(run_dir) / "metrics" / "scalars")
        self.loggers: list[Logger] = [CSVLogger(exp_name="metrics", log_dir=str(run_dir))]
        if extra is not None:
            self.loggers.append(extra)

    def _read_history(self, scalars: Path) -> None:
        """A resumed run's history so far, from its CSV files (the learning curve is the whole
        run's)."""
        for path in sorted(scalars.rglob("*.csv")) if scalars.is_dir() else []:
            name = path.relative_to(scalars).with_suffix("").as_posix()
            with open(path, newline="") as f:
                rows = [r for r in csv.reader(f) if len(r) == 2]
            try:
                points = [(int(float(s)), float(v)) for s, v in rows]
            except ValueError:  # not a file of ours: left out of the curve
                continue
            for step, value in points:
                self._append(name, step, value)

    def _append(self, name: str, step: int, value: float) -> None:
        """Add a point to the history; a resume logs again from its checkpoint's frames on,
        and the points it flies again replace the earlier attempt's."""
        points = self.history[name]
        while points and points[-1][0] >= step:
            points.pop()
        points.append((step, value))

    def log(self, values: Mapping[str, float], step: int) -> None:
        for name, value in values.items():
            value = float(value)
            self._append(name, step, value)
            for logger in self.loggers:
                logger.log_scalar(name, value, step=step)

    def close(self) -> None:
        for logger in self.loggers:
            experiment = getattr(logger, "experiment", None)
            finish = getattr(experiment, "finish", None) or getattr(experiment, "close", None)
            if callable(finish):
                finish()
