"""Self-imitation: the actor also learns the actions of its own episodes where they did better
than its critics expected (Oh et al., "Self-Imitation Learning", ICML 2018).

SAC learns from every transition through its critics, which must first learn that a long chase
ends in a capture; a rare capture, tens of seconds after the actions that made it, moves them
little. :class:`SelfImitation` keeps the episodes the collector flies, each step with its
discounted return to the episode's end (with SAC's entropy bonus, as the critics' soft values
hold it), and in its own step pulls the actor's deterministic action towards the action
taken, weighted by how much that return exceeds the critics' value of the action,
``max(G - min_i Q_i(s, a), 0)``: only where the episode did better than the critics believe
is anything imitated.

Every episode that ends by itself (a capture or a crash, ``terminated``) is kept, not only the
capturing ones: a return drawn among captures alone exceeds the critics' expectation almost
everywhere (the critics average over the episodes that went on to miss). An episode cut short
(``truncated``: the time limit, or the defender's route flown) is dropped by default: its
return stops where the critics' value goes on, and would beat it wherever the rest of the
chase costs. With ``bootstrap=True`` it is kept, its return closed at the cut by the critics'
soft value of the state it was cut in (as SAC's target closes a cut-short step, there with the
target critics, here with the critics the imitation step compares against), so the store holds
the misses as well as the captures.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import Tensor


class SelfImitation:
    """The store of episodes and the imitation step.

    Args:
        agent: the :class:`rlplat.agents.sac.SACAgent` whose actor imitates (its loss's
            actor parameters; its critics give the values).
        num_envs: the collector's envs (episodes are gathered per env across batches).
        gamma: the discount of the returns.
        capacity: transitions kept (the oldest are replaced).
        batch_size: transitions per imitation step.
        lr: the imitation step's Adam learning rate (its own optimiser).
        every_episode: keep every episode that ends by itself (False: only captures).
        bootstrap: keep the episodes cut short too, each return closed by the critics' soft
            value of the state at the cut (with ``every_episode`` only).
        device: where the store lives.
    """

    def __init__(
        self,
        agent,
        *,
        num_envs: int,
        gamma: float,
        capacity: int = 200_000,
        batch_size: int = 256,
        lr: float = 1e-4,
        every_episode: bool = True,
        bootstrap: bool = False,
        device: torch.device | str = "cpu",
    ) -> None:
        self.agent, self.gamma, self.batch_size = agent, float(gamma), int(batch_size)
        if bootstrap and not every_episode:
            raise ValueError("bootstrap keeps the episodes cut short: it needs every_episode=True")
        self.every_episode, self.bootstrap = bool(every_episode), bool(bootstrap)
        net = agent.net
        self.obs = torch.zeros(capacity, net.obs_dim, device=device)
        self.action = torch.zeros(capacity, net.action_dim, device=device)
        self.ret = torch.zeros(capacity, device=device)
        self.size = self.pos = 0
        self.episodes = 0
        self._open: list[list[tuple[Tensor, Tensor, Tensor]]] = [[] for _ in range(num_envs)]
        params = agent.loss.actor_network_params.values(True, True)
        self.optimizer = torch.optim.Adam(params, lr)

    def observe(self, batch) -> None:
        """Gather a collected ``(envs, T)`` batch's steps; store the episodes that ended in it
        by themselves (with ``every_episode=False`` those that ended in a capture; with
        ``bootstrap`` those cut short too)."""
        obs, action = batch["observation"], batch["action"]
        reward = batch["next", "reward"].reshape(obs.shape[:2])
        done = batch["next", "done"].reshape(obs.shape[:2])
        terminated = batch["next", "terminated"].reshape(obs.shape[:2])
        captured = batch["next", "captured"].reshape(obs.shape[:2])
        after = batch["next", "observation"] if self.bootstrap else None
        steps = obs.shape[1]
        for e in range(obs.shape[0]):
            start = 0
            for t in done[e].nonzero().flatten().tolist():
                self._open[e].append((obs[e, start : t + 1], action[e, start : t + 1],
                                      reward[e, start : t + 1]))  # fmt: skip
                kept = bool(captured[e, t]) or (self.every_episode and bool(terminated[e, t]))
                if kept:
                    self._store(self._open[e])
                elif self.bootstrap:  # cut short: the critics' value of where it was cut
                    self._store(self._open[e], cut=after[e, t])
                self._open[e], start = [], t + 1
            if start < steps:
                self._open[e].append((obs[e, start:], action[e, start:], reward[e, start:]))

    def _store(
        self, chunks: list[tuple[Tensor, Tensor, Tensor]], cut: Tensor | None = None
    ) -> None:
        obs, action, reward = (torch.cat(x) for x in zip(*chunks, strict=True))
        tail = 0.0 if cut is None else float(self.soft_value(cut[None])[0])
        ret = self.soft_return(obs, reward, tail).to(self.ret)
        n, cap = len(ret), len(self.ret)
        rows = (self.pos + torch.arange(n)) % cap
        self.obs[rows], self.action[rows], self.ret[rows] = obs, action, ret
        self.pos, self.size = (self.pos + n) % cap, min(cap, self.size + n)
        self.episodes += 1

    def _policy(self, td: TensorDict):
        """The actor's action distribution at ``td``'s observations (its current parameters)."""
        loss = self.agent.loss
        with loss.actor_network_params.to_module(loss.actor_network, preserve_module_state=False):
            return loss.actor_network.get_dist(td)

    #: Draws of the policy per state that estimate its entropy.
    ENTROPY_DRAWS = 8

    @torch.no_grad()
    def soft_value(self, obs: Tensor) -> Tensor:
        """The critics' soft value of states, ``E_a~pi[min_i Q_i(s, a) - alpha log pi(a | s)]``
        (the form of the value SAC's target closes a step with), over draws of the policy."""
        loss, draws, n = self.agent.loss, self.ENTROPY_DRAWS, len(obs)
        td = TensorDict({"observation": obs}, [n])
        dist = self._policy(td)
        actions = dist.sample((draws,))  # (draws, n, action)
        log_prob = dist.log_prob(actions)
        pairs = TensorDict(
            {"observation": obs.expand(draws, *obs.shape).flatten(0, 1),
             "action": actions.flatten(0, 1)},
            [draws * n],
        )  # fmt: skip
        q = loss._vmap_qnetworkN0(pairs, loss.qvalue_network_params)
        q = q.get("state_action_value").squeeze(-1).amin(0).view(draws, n)
        return (q - loss.log_alpha.exp() * log_prob).mean(0)

    @torch.no_grad()
    def soft_return(self, obs: Tensor, reward: Tensor, tail: float = 0.0) -> Tensor:
        """An episode's discounted return to its end, each step's, with the entropy bonus the
        critics' soft values hold: ``G_t = r_t + gamma (G_t+1 + alpha H(pi(. | s_t+1)))``
        (SAC's target along the episode, the entropy estimated from draws of the policy; it
        and ``alpha`` as they are now). Without the bonus, a return falls short of the
        critics' value by its sum over the horizon, whatever the episode did. ``tail`` is
        the soft value after the last step (0 where the episode ended by itself)."""
        loss = self.agent.loss
        td = TensorDict({"observation": obs}, [len(obs)])
        dist = self._policy(td)
        draws = dist.sample((self.ENTROPY_DRAWS,))
        entropy = -dist.log_prob(draws).mean(0)
        bonus = (loss.log_alpha.exp() * entropy).tolist()
        rewards, out = reward.tolist(), [0.0] * len(reward)
        acc = 0.0
        for t in range(len(rewards) - 1, -1, -1):
            after = self.gamma * (acc + bonus[t + 1]) if t + 1 < len(rewards) else self.gamma * tail
            acc = out[t] = rewards[t] + after
        return torch.tensor(out)

    def step(self) -> dict[str, float]:
        """One imitation step on a batch drawn from the store; empty before there is one."""
        if self.size < self.batch_size:
            return {}
        loss = self.agent.loss
        rows = torch.randint(self.size, (self.batch_size,), device=self.obs.device)
        td = TensorDict(
            {"observation": self.obs[rows], "action": self.action[rows]}, [self.batch_size]
        )
        with torch.no_grad():  # both critics at once, as SACLoss evaluates them
            q = loss._vmap_qnetworkN0(td.clone(), loss.qvalue_network_params)
            value = q.get("state_action_value").squeeze(-1).amin(0)
        advantage = (self.ret[rows] - value).clamp(min=0.0)
        better = advantage > 0
        if not bool(better.any()):
            return {"sil/better": 0.0}
        dist = self._policy(td)
        # The deterministic action before its clamp onto [-1, 1]: where the action taken is a
        # bound, any action in the margin beyond it flies the same and costs nothing.
        taken, flown = dist.deterministic_sample, td["action"]
        gap = taken - flown
        gap = torch.where(flown >= 1.0, gap.clamp(max=0.0), gap)
        gap = torch.where(flown <= -1.0, gap.clamp(min=0.0), gap)
        error = gap.pow(2).sum(-1)
        objective = (advantage * error).sum() / advantage.sum()
        self.optimizer.zero_grad(set_to_none=True)
        objective.backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        return {
            "sil/loss": float(objective.detach()),
            "sil/better": float(better.float().mean()),
            "sil/advantage": float(advantage[better].mean()),
        }
