"""Checkpoints: what a run saves, how a resume checks it, and how a policy is loaded back."""

from __future__ import annotations

import io
import logging
import random
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torchrl.envs.utils import ExplorationType

from rlplat.agents.sac import NetSpec, SelectFeatures, actor_body, make_actor
from rlplat.errors import ConfigError
from rlplat.io import atomic_write_bytes

FORMAT_VERSION = 1

log = logging.getLogger(__name__)


def rng_state() -> dict[str, Any]:
    return {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` (plus the format version) atomically to ``path``."""
    buffer = io.BytesIO()
    torch.save({"format_version": FORMAT_VERSION, **payload}, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_checkpoint(path: str | Path, field: str = "checkpoint") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`; a clear error if it is not one,
    naming ``field``, the setting that gave the path."""
    path = Path(path)
    if path.is_dir():
        best = path / "checkpoints" / "best.pt"
        hint = f"; a run's best is {best}" if best.is_file() else ""
        raise ConfigError(f"{field}: {path} is a folder, not a checkpoint file{hint}")
    if not path.is_file():
        raise ConfigError(f"{field}: no file at {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except OSError as e:
        raise ConfigError(f"{field}: {path} cannot be read ({e.strerror or e})") from None
    except Exception as e:  # noqa: BLE001 - whatever the file is, it is not a checkpoint
        why = " ".join(str(e).split())[:120]
        raise ConfigError(
            f"{field}: {path} is not an rlplat checkpoint ({type(e).__name__}: {why})"
        ) from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise ConfigError(f"{field}: {path} is not an rlplat checkpoint (format 1)")
    return state


def saved_interface(state: dict[str, Any]) -> dict[str, Any]:
    """The drone interface a checkpoint was trained with; one written before teams existed
    flew 1 attacker against 1 defender."""
    return {"attackers": 1, "defenders": 1, **state.get("interface", {})}


def route_path_interface(env) -> dict[str, float] | None:
    """The defender's path an env's meeting point assumes, the attacker's start-up lag it
    allows for and how far ahead it looks (the setting: None, the env's time limit, whatever
    that is; None for the whole: it computes none)."""
    if not env.computes_meeting:
        return None
    lag, horizon = env.meeting_lag, env.law_horizon
    return {**asdict(env.route_flight), "start_lag": lag, "horizon": horizon}


def check_route_path(state: dict[str, Any], env, path, where: str) -> None:
    """Refuse a checkpoint trained on another route path than the env's meeting point uses;
    one that saved none (written before checkpoints recorded it) is flown with a warning."""
    now = route_path_interface(env)
    if now is None:
        return
    saved = saved_interface(state).get("route_path")
    if saved is not None:  # saved before the start-up lag, the look-ahead were settings
        saved = {**saved, "start_lag": saved.get("start_lag", 0.0)}
        saved["horizon"] = saved.get("horizon")  # the time limit
    if saved is None:
        log.warning("%s: %s saved no route path; its meeting point is flown with %s, which may "
                    "not be the one it was trained with", where, path, now)  # fmt: skip
    elif saved != now:
        raise ConfigError(
            f"{where}: {path} was trained with the defender's route path {saved}, this env's "
            f"meeting point uses {now}"
        )


def check_compatible(state: dict[str, Any], net: NetSpec, interface: dict[str, Any], path) -> None:
    """Refuse to continue from a checkpoint whose networks or drone interface differ."""
    check_same_net(state, net.as_dict(), path, "resume")
    check_same_interface(saved_interface(state), interface, path, "resume")


def check_same_net(state: dict[str, Any], sizes: dict[str, Any], path, where: str) -> None:
    """Refuse a checkpoint whose networks differ in one of ``sizes`` (``NetSpec`` fields)."""
    for key, value in sizes.items():
        if state["net"][key] != value:
            raise ConfigError(
                f"{where}: {path} has {key}={state['net'][key]}, this run has {key}={value}"
            )


def check_same_interface(
    saved: dict[str, Any], interface: dict[str, Any], path, where: str
) -> None:
    """Refuse a checkpoint trained with another value of one of ``interface``'s keys."""
    for key, value in interface.items():
        if saved.get(key) != value:
            raise ConfigError(
                f"{where}: {path} was trained with {key}={saved.get(key)}, "
                f"this run has {key}={value}"
            )


def load_policy(
    path: str | Path, action_spec, device: torch.device | str = "cpu", *, deterministic=True
):
    """The actor saved in a checkpoint (``best.pt`` or ``last.pt``), flying the deterministic
    action (tanh of the mean: what evaluation, the controller file and the export fly) unless
    an ``ExplorationType`` is set around the call; ``deterministic=False`` samples, as the
    actor trained."""
    actor = actor_from_state(load_checkpoint(path), action_spec, device)
    if deterministic:
        actor.module[-1].default_interaction_type = ExplorationType.DETERMINISTIC
    return actor


def saved_net(state: dict[str, Any]) -> NetSpec:
    """The network sizes a loaded checkpoint was trained with."""
    return NetSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in state["net"].items()})


def actor_from_state(
    state: dict[str, Any],
    action_spec,
    device: torch.device | str = "cpu",
    group: str | None = None,
    features: Sequence[int] | None = None,
):
    """The actor of a loaded checkpoint (see :func:`load_checkpoint`); with ``group``, reading
    and writing that group's entries (a team flying the shared network); with ``features``,
    reading only those features of the observation (a network trained alone flying each
    drone of a team: the observation's ``lone_features``)."""
    net = saved_net(state)
    actor = make_actor(net, action_spec, device)
    actor.load_state_dict(state["actor"])
    if group is None and features is None:
        return actor
    body = actor_body(actor)
    if features is not None:
        body = nn.Sequential(SelectFeatures(features, device), body)
    return make_actor(net, action_spec, device, group=group, body=body)


def embedded_networks(
    state: dict[str, Any], net: NetSpec, features: Sequence[int]
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """A checkpoint's networks laid out for networks ``net`` whose observation holds the
    checkpoint's at ``features``, in its order: a team drone's ``lone_features``, or every
    feature for the same observation. Returns the SAC loss's entries (actor, critics, target
    critics, entropy coefficient) and the actor the checkpoint flies (its ``actor``: the
    moving average where the run kept one), as ``actor.state_dict()`` entries. The first
    layers read those features, with their weights rescaled to ``net``'s observation scale,
    and give every other feature a zero weight; the critics' action inputs stay last. The
    networks so compute what they computed for the checkpoint. Input scales (``inv_scale``),
    discount and entropy target are not returned: the new run's stay."""
    saved, loss = state["net"], state["agent"]["loss"]
    saved_dim, index = saved["obs_dim"], torch.tensor(list(features), dtype=torch.long)
    # A network reads observation / scale: a column moves with the ratio of the two scales.
    ratio = torch.tensor(net.obs_scale)[index] / torch.tensor(saved["obs_scale"])

    def embed(key: str, value: torch.Tensor) -> torch.Tensor:
        if not key.endswith("body.0.weight"):
            return value
        extra = value.shape[-1] - saved_dim  # first layer: (..., out, observation [+ action])
        first = value.new_zeros(*value.shape[:-1], net.obs_dim + extra)
        first[..., index] = value[..., :saved_dim] * ratio.to(value)
        first[..., net.obs_dim :] = value[..., saved_dim:]
        return first

    entries = {
        key: embed(key, value)
        for key, value in loss.items()
        if key.split(".", 1)[0] in _NETWORK_ENTRIES and not key.endswith("inv_scale")
    }
    flown = {k: embed(k, v) for k, v in state["actor"].items() if not k.endswith("inv_scale")}
    return entries, flown


#: The SAC loss's entries a warm start takes from a checkpoint (``embedded_networks``).
_NETWORK_ENTRIES = (
    "actor_network_params",
    "qvalue_network_params",
    "target_qvalue_network_params",
    "log_alpha",
)
