"""What the learner trains on: potential-based shaping and n-step transitions of a batch."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase


def shape_rewards(batch: TensorDictBase, key: str, weight: float, gamma: float) -> TensorDictBase:
    """Potential-based shaping: ``("next", "reward")`` + gamma * Phi(s') - Phi(s).

    ``Phi = weight * batch[key]`` (e.g. ``key="distance"``, ``weight=-1``: one unit of reward per
    metre gained on the opponent), and ``Phi = 0`` on a terminal state (``("next",
    "terminated")``: after a capture or a crash nothing follows). Shaping of this form leaves the
    optimal policy of the discounted episodic task unchanged (Ng, Harada and Russell, 1999):
    every episode's shaped return is its return minus ``Phi(s_0)``. It only makes progress
    visible at once instead of through many bootstraps. A truncated step keeps ``Phi(s')``: the
    learner bootstraps there. Returns a shallow copy; ``weight == 0`` returns the batch itself.
    What the runs report (returns, capture rates) stays the env's own reward.
    """
    if weight == 0:
        return batch
    terminal = batch["next", "terminated"].view_as(batch["next", key])
    phi = weight * batch[key]
    phi_next = (weight * batch["next", key]).masked_fill(terminal, 0.0)
    reward = batch["next", "reward"] + (gamma * phi_next - phi).view_as(batch["next", "reward"])
    out = batch.clone(False)
    out["next"] = out["next"].clone(False).set("reward", reward)
    return out


def n_step_transitions(batch: TensorDictBase, n: int, gamma: float) -> TensorDictBase:
    """Turn one-step transitions into n-step ones, in place of ``("next", ...)``.

    ``batch`` has batch shape ``(envs, T)`` (a collector's output), with ``("next", "reward")``,
    ``("next", "done")`` and ``("next", "terminated")``. Each transition t keeps its observation
    and action and looks ahead k = min(n, steps to the end of its episode, steps left in the
    batch) steps: its reward becomes ``sum_{i<k} gamma^i r_{t+i}``, its ``("next", ...)``
    entries those of step ``t + k - 1`` (so ``terminated`` says whether the episode ended inside
    the window), and ``steps_to_next_obs`` is k, which TorchRL's TD(0) estimator reads to
    discount the bootstrap by ``gamma^k``. ``n = 1`` returns the batch unchanged.
    """
    if n == 1:
        return batch
    envs, T = batch.shape
    reward = batch["next", "reward"]
    done = batch["next", "done"].squeeze(-1)
    t = torch.arange(T, device=done.device)
    last = t.expand(envs, T).clone()  # index of the window's last step
    total = reward.clone()
    open_ = ~done  # the window can still grow
    for i in range(1, n):
        step = (t + i).clamp(max=T - 1).expand(envs, T)
        grow = open_ & (t + i < T)
        total = total + torch.where(
            grow.unsqueeze(-1), gamma**i * reward.gather(1, step.unsqueeze(-1)), 0.0
        )
        last = torch.where(grow, step, last)
        open_ = grow & ~done.gather(1, step)
    out = batch.clone(False)
    nxt = batch["next"]
    gathered = nxt.apply(lambda x: x.gather(1, _expand_index(last, x)))
    gathered.set("reward", total)
    out.set("next", gathered)
    out.set("steps_to_next_obs", (last - t + 1).unsqueeze(-1))
    return out


def _expand_index(index: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return index.reshape(*index.shape, *([1] * (like.ndim - 2))).expand_as(like)


def agent_rows(batch: TensorDictBase, group: str) -> TensorDictBase:
    """One row of transitions per drone of a team: what a shared policy's SAC loss trains on.

    ``batch`` is a collector's ``(envs, T)`` batch of an env whose learners sit under ``group``
    with an agent dimension K (``(group, "observation")`` (envs, T, K, obs_dim) and so on). The
    result has batch shape ``(envs * K, T)`` and the flat keys of a lone learner's batch:
    ``observation``, ``action`` and ``distance`` of each drone, ``("next", ...)`` its next
    observation, reward and distance, and the env's ``done`` and ``terminated`` (the team's
    episode ends at once). Each row is one drone's trajectory, so the n-step and shaping steps
    apply unchanged. A team whose drones can leave play (``(group, "caught")`` of defenders,
    ``(group, "down")`` of attackers on the ground) ends a drone's own episode when it leaves
    (``terminated``); ``alive`` (envs * K, T, 1) says which transitions start with the drone
    still in play (the others are not its to learn).
    """
    envs, steps = batch.shape
    team, nxt = batch[group], batch["next"]
    agents = team.shape[-1]

    def shared(x: torch.Tensor) -> torch.Tensor:  # (envs, T, 1) -> (envs, T, K, 1)
        return x.unsqueeze(2).expand(envs, steps, agents, *x.shape[2:])

    done, terminated = shared(nxt["done"]), shared(nxt["terminated"])
    alive = torch.ones_like(done)
    for key in ("caught", "down"):
        if key in team.keys():  # noqa: SIM118 (a tensordict's own keys, not nested ones)
            out = nxt[group, key]
            done, terminated, alive = done | out, terminated | out, ~team[key]
    rows = TensorDict(
        {
            "observation": team["observation"],
            "action": team["action"],
            "distance": team["distance"],
            "alive": alive,
            "next": {
                "observation": nxt[group, "observation"],
                "reward": nxt[group, "reward"],
                "distance": nxt[group, "distance"],
                "done": done,
                "terminated": terminated,
            },
        },
        batch_size=(envs, steps, agents),
        device=batch.device,
    )
    return rows.permute(0, 2, 1).contiguous().reshape(envs * agents, steps)


#: What the replay buffer keeps of each transition.
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


def replay_rows(
    batch: TensorDictBase,
    *,
    group: str | None,
    potential_key: str,
    potential_weight: float,
    gamma: float,
    n_steps: int,
) -> TensorDictBase:
    """A collected ``(envs, T)`` batch as the flat transitions the learner trains on: a row
    per drone of a team (:func:`agent_rows`), shaped rewards (:func:`shape_rewards`), n-step
    targets (:func:`n_step_transitions`), only :data:`TRANSITION_KEYS` (and
    ``steps_to_next_obs`` for n > 1); a team drone's transitions after it left play (caught,
    down) are left out."""
    keep = (*TRANSITION_KEYS, "steps_to_next_obs") if n_steps > 1 else TRANSITION_KEYS
    if group is not None:
        batch = agent_rows(batch, group)
    transitions = shape_rewards(batch, potential_key, potential_weight, gamma)
    transitions = n_step_transitions(transitions, n_steps, gamma)
    if group is None:
        return transitions.select(*keep).reshape(-1)
    flat = transitions.select(*keep, "alive").reshape(-1)
    return flat[flat["alive"].squeeze(-1)].exclude("alive")
