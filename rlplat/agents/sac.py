"""Soft Actor-Critic from TorchRL parts: actor, twin critics, loss and optimisers."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import (
    LazyTensorStorage,
    RandomSampler,
    ReplayBuffer,
    TensorDictReplayBuffer,
    TensorSpec,
    TensorStorage,
)
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate

from rlplat.agents.compiled import PRIORITY, CompiledUpdate, compiled_update_keys
from rlplat.agents.replay import PrioritySampler
from rlplat.errors import ConfigError

ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU}

#: Added to every |TD error| before the exponent of prioritized replay: a transition the critics
#: already fit (error ~0) is still drawn now and then, and gets a fresh priority when it is.
PRIORITY_EPS = 1e-2


@dataclass(frozen=True)
class NetSpec:
    """What fixes the shapes of a policy: a checkpoint only loads into the same ``NetSpec``."""

    obs_dim: int
    action_dim: int
    actor_cells: tuple[int, ...]
    critic_cells: tuple[int, ...]
    activation: str
    obs_scale: tuple[float, ...]  # the networks see observation / obs_scale
    action_margin: float = 0.0  # the tanh squashes onto the bounds widened by this fraction

    def as_dict(self) -> dict[str, Any]:
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "obs_scale": list(self.obs_scale),
            "actor_cells": list(self.actor_cells),
            "critic_cells": list(self.critic_cells),
            "activation": self.activation,
            "action_margin": self.action_margin,
        }


class Scaled(nn.Module):
    """``body(cat(observation / scale, *rest))``: fixed input scaling in front of an MLP.

    With ``clamp``, each further input (the critic's action) is first clamped to
    ``[-clamp, clamp]``: what the env does to an action, so Q is flat past the bounds.
    """

    def __init__(
        self, body: nn.Module, scale: tuple[float, ...], device=None, clamp: float | None = None
    ) -> None:
        super().__init__()
        self.body = body
        self.clamp = clamp
        self.register_buffer("inv_scale", 1.0 / torch.tensor(scale, device=device))

    def forward(self, observation: torch.Tensor, *rest: torch.Tensor) -> torch.Tensor:
        if self.clamp is not None:
            rest = tuple(x.clamp(-self.clamp, self.clamp) for x in rest)
        return self.body(torch.cat([observation * self.inv_scale, *rest], -1))


class SelectFeatures(nn.Module):
    """``observation[..., features]``: the features a network was trained on, taken from a
    larger observation (a policy trained alone flying a seat of a team)."""

    def __init__(self, features: Sequence[int], device=None) -> None:
        super().__init__()
        self.register_buffer("features", torch.tensor(list(features), device=device))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:  # an artifact's is on the CPU
        return observation.index_select(-1, self.features.to(observation.device))


def make_actor(
    net: NetSpec,
    action_spec: TensorSpec,
    device: torch.device | str = "cpu",
    *,
    group: str | None = None,
    body: nn.Module | None = None,
):
    """Gaussian policy squashed by tanh into the action bounds (TorchRL ``TanhNormal``).

    Reads ``observation``, writes ``loc``, ``scale`` and ``action``; with ``group``, the same
    entries under the group key (``(group, "observation")`` (N, K, obs_dim) and so on: TorchRL's
    multi-agent layout), so that every drone of a team flies the one shared network. ``body``
    (the ``actor_body`` of another actor) shares that actor's parameters. Under
    ``ExplorationType.DETERMINISTIC`` the action is the distribution's deterministic sample
    (tanh of the mean).

    A tanh never reaches its bounds, and SAC's entropy bonus keeps the mean away from them, so
    a full-scale command (every axis at maximum speed, what a pursuit needs) is out of reach.
    With ``net.action_margin = m`` the tanh squashes onto the bounds widened by ``m`` of their
    half-width and the written action is clamped back onto the spec (``safe``): a whole band
    of pre-clamp values means full scale, which the policy reaches with finite means and
    without paying entropy. The critic clamps its action input the same way.
    """
    if body is None:
        mlp = MLP(
            in_features=net.obs_dim,
            out_features=2 * net.action_dim,
            num_cells=list(net.actor_cells),
            activation_class=ACTIVATIONS[net.activation],
            device=device,
        )
        body = nn.Sequential(
            Scaled(mlp, net.obs_scale, device),
            NormalParamExtractor(scale_mapping="biased_softplus_1.0"),
        )

    def key(name: str):
        return name if group is None else (group, name)

    module = TensorDictModule(
        body, in_keys=[key("observation")], out_keys=[key("loc"), key("scale")]
    )
    low, high = action_spec.space.low, action_spec.space.high
    pad = net.action_margin * (high - low) / 2
    return ProbabilisticActor(
        module,
        in_keys=[key("loc"), key("scale")],
        out_keys=[key("action")],
        spec=action_spec,
        safe=net.action_margin > 0,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": low - pad, "high": high + pad},
        default_interaction_type=ExplorationType.RANDOM,
        return_log_prob=False,
    )


class CorrelatedNoise:
    """Standard normal draws correlated in time: an AR(1) process.

    Each call returns ``rho * last + sqrt(1 - rho^2) * fresh`` (``fresh`` from torch's global
    generator), so every draw is N(0, 1) as before and successive draws keep a correlation of
    ``rho`` per step (``1 / (1 - rho)`` steps of memory). ``rho = 0`` returns the fresh draw
    itself: independent noise, the same numbers as ``torch.randn``. A call with another shape
    (a new batch of envs) starts a new process.
    """

    def __init__(self, rho: float) -> None:
        if not 0.0 <= rho < 1.0:
            raise ConfigError(f"algo.noise_correlation: must be in [0, 1), got {rho}")
        self.rho = float(rho)
        self.last: torch.Tensor | None = None

    def __call__(self, like: torch.Tensor) -> torch.Tensor:
        fresh = torch.randn(like.shape, device=like.device, dtype=like.dtype)
        if self.rho == 0.0 or self.last is None or self.last.shape != fresh.shape:
            self.last = fresh
        else:
            self.last = self.rho * self.last + math.sqrt(1.0 - self.rho**2) * fresh
        return self.last


class CorrelatedExploration(TensorDictModuleBase):
    """An actor of :func:`make_actor` sampled with noise correlated in time.

    SAC samples its squashed Gaussian afresh at every step; at 10 steps per second a drone's
    velocity lag averages such noise away, and a play that holds an offset for seconds is
    never tried. This flies ``tanh(loc + scale * e_t)`` mapped onto the actor's bounds (and
    clamped as the actor clamps), with ``e_t`` from :class:`CorrelatedNoise`: per step the same
    distribution as the actor's own sample, correlated from one step to the next. Only what is
    collected changes; the loss still samples the actor itself.
    """

    def __init__(self, actor, net: NetSpec, action_spec: TensorSpec, rho: float) -> None:
        super().__init__()
        self.actor = actor
        self.params_module = actor[0]  # observation -> loc, scale
        self.in_keys = list(self.params_module.in_keys)
        self.out_keys = list(actor.out_keys)
        self.loc_key, self.scale_key = self.params_module.out_keys
        self.action_key = actor[-1].out_keys[0]  # the distribution module writes the action
        self.noise = CorrelatedNoise(rho)
        low, high = action_spec.space.low, action_spec.space.high
        pad = net.action_margin * (high - low) / 2
        self.register_buffer("low", low)
        self.register_buffer("high", high)
        self.register_buffer("centre", (high + low) / 2)
        self.register_buffer("reach", (high - low) / 2 + pad)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        td = self.params_module(td)
        loc, scale = td.get(self.loc_key), td.get(self.scale_key)
        squashed = torch.tanh(loc + scale * self.noise(loc))
        action = self.centre + self.reach * squashed
        action = torch.maximum(torch.minimum(action, self.high), self.low)  # as the actor clamps
        return td.set(self.action_key, action)


def actor_body(actor) -> nn.Module:
    """The parameterised part of an actor of :func:`make_actor` (observation -> loc, scale)."""
    return actor.module[0].module


def make_critic(net: NetSpec, device: torch.device | str = "cpu") -> ValueOperator:
    """Q(s, a): reads ``observation`` and ``action``, writes ``state_action_value``."""
    body = MLP(
        in_features=net.obs_dim + net.action_dim,
        out_features=1,
        num_cells=list(net.critic_cells),
        activation_class=ACTIVATIONS[net.activation],
        device=device,
    )
    clamp = 1.0 if net.action_margin > 0 else None  # actions are in [-1, 1] (eq. 2)
    return ValueOperator(
        Scaled(body, net.obs_scale, device, clamp=clamp), in_keys=["observation", "action"]
    )


class FusedSoftUpdate(SoftUpdate):
    """TorchRL's ``SoftUpdate`` whose step is one fused ``lerp`` over every target parameter.

    ``SoftUpdate.step`` walks the parameter tensordicts in Python, which costs as much as a
    few percent of a small network's whole update; the pairs of (target, source) leaves are
    the same tensors for the life of the loss module, so they are collected once.
    """

    def init_(self) -> None:
        super().init_()
        keys = list(self._sources.keys(True, True))
        self._targets_flat = [
            self._targets.get(("target_" + k[0], *k[1:])).data for k in map(_as_tuple, keys)
        ]
        self._sources_flat = [self._sources.get(k).data for k in keys]
        #: (target, source) with each source as the loss holds it (a trained parameter or a
        #: buffer), for a compiled step that also updates the parameters.
        sources = [self._sources.get(k) for k in keys]
        self.pairs = list(zip(self._targets_flat, sources, strict=True))

    def step(self) -> None:
        torch._foreach_lerp_(self._targets_flat, self._sources_flat, 1.0 - self.eps)


def _as_tuple(key: str | tuple[str, ...]) -> tuple[str, ...]:
    return key if isinstance(key, tuple) else (key,)


class AnchoredSACLoss(SACLoss):
    """``SACLoss`` whose actor loss also pays ``anchor_weight * |loc|^2`` per state, ``loc``
    being the actor's pre-tanh mean: the deterministic action is held at zero, which under a
    guided action is the guidance law, unless the critics' gradient outweighs the pull (a
    behaviour-regularised actor, as in TD3+BC, with the law as the behaviour)."""

    def __init__(self, *args: Any, anchor_weight: float, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.anchor_weight = float(anchor_weight)

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        loss, metadata = super().actor_loss(tensordict)
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            loc = self.actor_network.get_dist(tensordict).loc
        return loss + self.anchor_weight * loc.pow(2).sum(-1).mean(), metadata


class SACAgent:
    """SAC with automatic entropy tuning: TorchRL ``SACLoss`` (two Q nets), ``SoftUpdate``.

    Args:
        net: network shapes.
        action_spec: the env's action spec (bounds of the tanh squashing).
        gamma: discount.
        tau: soft target update rate (target <- (1 - tau) target + tau online).
        actor_lr, critic_lr, alpha_lr: Adam learning rates.
        alpha_init: initial entropy coefficient.
        target_entropy: ``"auto"`` (minus the action dimension) or a number.
        loss_function: critic regression loss, ``l2`` or ``smooth_l1``.
        compile: run the update compiled (:class:`rlplat.agents.compiled.CompiledUpdate`: the
            same losses, Adam steps and soft update as the eager update, in one compiled
            graph).
        actor_average: with a rate r > 0, an exponential moving average of the actor's
            weights, ``avg <- (1 - r) avg + r actor`` after each :meth:`average_actor`: the
            policy the run validates, checkpoints and flies (``flown_actor``); 0 = the actor.
        noise_correlation: the correlation per step of the noise that ``collect_policy``
            samples the actor with (:class:`CorrelatedExploration`); 0 = the actor itself,
            SAC's independent draws.
        group: the env's group key of a team of learners (None for a lone learner). The loss
            trains on one drone's transitions at a time (flat keys, see
            :func:`rlplat.agents.transitions.agent_rows`); ``policy`` flies the whole team with
            the same parameters.
        device: where the networks live.
    """

    def __init__(
        self,
        net: NetSpec,
        action_spec: TensorSpec,
        *,
        gamma: float,
        tau: float,
        actor_lr: float,
        critic_lr: float,
        alpha_lr: float,
        alpha_init: float = 1.0,
        target_entropy: str | float = "auto",
        loss_function: str = "l2",
        anchor_weight: float = 0.0,
        actor_average: float = 0.0,
        compile: bool = False,
        noise_correlation: float = 0.0,
        group: str | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        self.net = net
        self.actor = make_actor(net, action_spec, device)
        self.policy = (
            self.actor
            if group is None
            else make_actor(net, action_spec, device, group=group, body=actor_body(self.actor))
        )
        # What the collector flies: the team policy, sampled with correlated noise if asked.
        self.collect_policy = (
            self.policy
            if noise_correlation == 0.0
            else CorrelatedExploration(self.policy, net, action_spec, noise_correlation)
        )
        # The weight average: a second actor (and its team policy) that the actor's weights
        # are folded into; without one, the actor is what is flown.
        self.average_rate = float(actor_average)
        self.flown_actor, self.flown_policy = self.actor, self.policy
        if self.average_rate > 0:
            self.flown_actor = make_actor(net, action_spec, device)
            self.flown_policy = (
                self.flown_actor
                if group is None
                else make_actor(
                    net, action_spec, device, group=group, body=actor_body(self.flown_actor)
                )
            )
            self._average_pairs = (
                [p.data for p in actor_body(self.flown_actor).parameters()],
                [p.data for p in actor_body(self.actor).parameters()],
            )
            self.restart_average()
        critic = make_critic(net, device)
        anchored = {"anchor_weight": anchor_weight} if anchor_weight > 0 else {}
        self.loss = (AnchoredSACLoss if anchored else SACLoss)(
            **anchored,
            actor_network=self.actor,
            qvalue_network=critic,
            num_qvalue_nets=2,
            loss_function=loss_function,
            alpha_init=alpha_init,
            target_entropy=target_entropy,
            action_spec=action_spec,
            delay_actor=False,
            delay_qvalue=True,
        )
        self.loss.make_value_estimator(gamma=gamma)
        # SACLoss registers its target-entropy buffer on first use (a checkpoint's state_dict
        # does that too); do it now, so that a compiled update never sees the module change.
        _ = self.loss.target_entropy
        self.target_updater = FusedSoftUpdate(self.loss, tau=tau)
        self.optimizers = {
            "actor": torch.optim.Adam(self.loss.actor_network_params.values(True, True), actor_lr),
            "critic": torch.optim.Adam(
                self.loss.qvalue_network_params.values(True, True), critic_lr
            ),
            "alpha": torch.optim.Adam([self.loss.log_alpha], alpha_lr),
        }
        self._compiled = (
            CompiledUpdate(
                self.loss,
                self.optimizers,
                self.target_updater.pairs,
                1.0 - self.target_updater.eps,  # FusedSoftUpdate's weight, to the last bit
            )
            if compile
            else None
        )
        self._columns: tuple | None = None  # the storage update_from read last, and how

    #: Compiled updates run with guard checks for this many calls, then without.
    WARMUP_CALLS = CompiledUpdate.WARMUP_CALLS

    def update(
        self, batch: TensorDictBase, weights: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """One gradient step on every loss, then the soft target update; returns the losses.

        ``weights`` (one per row of ``batch``) weight each row's losses, as prioritized
        replay's importance weights do, and each row's priority, SACLoss's ``td_error``, is
        left in ``batch``; None: every row counts the same.
        """
        if self._compiled is None:
            if weights is not None:
                batch.set(self.loss.tensor_keys.priority_weight, weights)
            out = self._update_eager(batch)
            self.target_updater.step()
            return out
        keys = self._batch_keys(batch)
        out = self._compiled(keys, [batch.get(k) for k in keys], None, weights)
        if weights is not None:
            batch.set(self.loss.tensor_keys.priority, out.pop(PRIORITY))
        return out

    def update_from(self, buffer: ReplayBuffer) -> dict[str, torch.Tensor]:
        """:meth:`update` on a batch drawn from ``buffer`` by its sampler.

        With a :class:`~rlplat.agents.replay.PrioritySampler` the rows' losses are weighted by
        its importance weights (TorchRL's losses take the weighted mean, so a batch keeps the
        scale of a uniform draw) and the rows' priorities are set from the update's
        ``td_error`` afterwards. Compiled, the rows are gathered from the storage inside the
        compiled update, so that no batch ``TensorDict`` is built in Python.
        """
        storage, sampler = buffer.storage, buffer.sampler
        prioritized = isinstance(sampler, PrioritySampler)
        rows = getattr(storage, "_storage", None)  # a TensorStorage's preallocated tensors
        gathered = (
            self._compiled is not None
            and isinstance(storage, TensorStorage)
            and isinstance(rows, TensorDictBase)
            and type(sampler) in (RandomSampler, PrioritySampler)
        )
        if not prioritized and not gathered:
            return self.update(buffer.sample())
        index, info = sampler.sample(storage, buffer.batch_size)
        device = self.loss.log_alpha.device
        weights = info["priority_weight"].to(device, torch.float32) if prioritized else None
        if gathered:
            if self._columns is None or self._columns[0] is not rows:
                keys = self._batch_keys(rows)
                self._columns = (rows, keys, [rows.get(k) for k in keys])
            _, keys, columns = self._columns
            out = self._compiled(keys, columns, index.to(columns[0].device), weights)
            priority = out.pop(PRIORITY, None)
        else:
            batch = storage[index]
            out = self.update(batch, weights)
            priority = batch.get(self.loss.tensor_keys.priority)
        if prioritized:
            sampler.update_priority(index, priority)
        return out

    def load_networks(
        self, entries: Mapping[str, torch.Tensor], flown: Mapping[str, torch.Tensor]
    ) -> None:
        """Start the networks at a checkpoint's (:func:`rlplat.agents.checkpoint.
        embedded_networks`): the loss's ``entries`` (actor, critics, target critics, entropy
        coefficient), and the actor it flew, ``flown``, which this agent flies from here: as
        the start of its moving average, or, without one, as its actor. The optimisers start
        afresh."""
        if self.average_rate == 0:
            entries = {**entries, **{f"actor_network_params.{k}": v for k, v in flown.items()}}
        self.loss.load_state_dict({**self.loss.state_dict(), **entries})
        if self.average_rate > 0:
            self.flown_actor.load_state_dict({**self.flown_actor.state_dict(), **flown})
        if self._compiled is not None:
            self._compiled.bind()

    def restart_average(self) -> None:
        """Start the moving average at the actor's weights as they are now."""
        if self.average_rate > 0:
            self.flown_actor.load_state_dict(self.actor.state_dict())

    def average_actor(self) -> None:
        """Fold the actor's weights into their moving average (no-op without one)."""
        if self.average_rate > 0:
            torch._foreach_lerp_(*self._average_pairs, self.average_rate)

    def _batch_keys(self, batch: TensorDictBase) -> tuple:
        """The entries of ``batch`` the loss reads (:func:`compiled_update_keys`)."""
        return compiled_update_keys(self.loss, lambda key: key in batch.keys(True, True))

    def _update_eager(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        losses = self.loss(batch)
        total = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        total.backward()
        for opt in self.optimizers.values():
            opt.step()
        return {
            "loss_actor": losses["loss_actor"].detach(),
            "loss_qvalue": losses["loss_qvalue"].detach(),
            "loss_alpha": losses["loss_alpha"].detach(),
            "alpha": losses["alpha"].detach(),
            "entropy": losses["entropy"].detach(),
        }

    # Checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        state = {
            "loss": self.loss.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
        }
        if self.average_rate > 0:
            state["actor_average"] = self.flown_actor.state_dict()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.loss.load_state_dict(state["loss"])
        if self.average_rate > 0:
            self.flown_actor.load_state_dict(state["actor_average"])
        for k, o in self.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        if self._compiled is not None:
            self._compiled.bind()  # the optimisers' state tensors are new ones


def make_replay_buffer(algo: Mapping[str, Any], device="cpu") -> TensorDictReplayBuffer:
    """The run's replay buffer (``algo.buffer_size`` transitions, batches of
    ``algo.batch_size``): drawn uniformly, or, with ``algo.priority_alpha`` > 0, in proportion
    to ``(|TD error| + PRIORITY_EPS) ** priority_alpha``, each row's losses weighted by the
    importance weight ``(N P(i)) ** -priority_beta``
    (:class:`~rlplat.agents.replay.PrioritySampler`)."""
    storage = LazyTensorStorage(algo["buffer_size"], device=device)
    sampler = (
        PrioritySampler(
            algo["buffer_size"], algo["priority_alpha"], algo["priority_beta"], PRIORITY_EPS
        )
        if algo["priority_alpha"] > 0
        else RandomSampler()
    )
    return TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=algo["batch_size"])


def net_spec(obs_scale: Sequence[float], action_dim: int, algo: Mapping[str, Any]) -> NetSpec:
    """The ``NetSpec`` of ``algo`` (the ``algo`` config node) for an observation whose features
    have the typical magnitudes ``obs_scale``, checked."""
    act = algo["activation"]
    if act not in ACTIVATIONS:
        raise ConfigError(f"algo.activation: unknown '{act}'; valid: {', '.join(ACTIVATIONS)}")
    for key in ("actor_cells", "critic_cells"):
        cells = algo[key]
        if not isinstance(cells, Sequence) or not cells or any(int(c) < 1 for c in cells):
            raise ConfigError(f"algo.{key}: a non-empty list of positive widths, got {cells}")
    margin = float(algo.get("action_margin", 0.0))
    if not 0.0 <= margin <= 1.0:
        raise ConfigError(f"algo.action_margin: must be in [0, 1], got {margin}")
    return NetSpec(
        obs_dim=len(obs_scale),
        obs_scale=tuple(float(x) for x in obs_scale),
        action_dim=int(action_dim),
        actor_cells=tuple(int(c) for c in algo["actor_cells"]),
        critic_cells=tuple(int(c) for c in algo["critic_cells"]),
        activation=act,
        action_margin=margin,
    )
