"""Prioritized experience replay in plain torch: a sampler for TorchRL's replay buffers.

TorchRL's own ``PrioritizedSampler`` keeps its sum trees in TorchRL's C++ extension, which
loads only against the torch it was built for; a torch of another minor version leaves the
sampler unusable. :class:`PrioritySampler` holds the priorities in one CPU tensor, in blocks
of :data:`BLOCK` with each block's sum kept beside them, and draws with the global torch
generator (so the run's seed fixes its draws): a draw picks a block by the cumulative sum of
the block sums, then a row within it: a batch reads the N / BLOCK block sums once and BLOCK
priorities a row, in a few wide tensor operations (a sum tree reads log2 N a row, one level
at a time).
"""

from __future__ import annotations

from typing import Any

import torch
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from rlplat.errors import DivergenceError

#: Rows per block of priorities.
BLOCK = 64


class PrioritySampler(Sampler):
    """Draws transition i with probability ``P(i) = p_i / sum_j p_j``, where
    ``p_i = (|TD error_i| + eps) ** alpha`` (Schaul et al., 2016, proportional variant), and
    returns the importance weights ``(N P(i)) ** -beta`` as ``info["priority_weight"]``.

    A transition the buffer writes starts at the largest priority given so far (1 before any),
    so that it is drawn soon; :meth:`update_priority` sets a drawn one's from its new TD error.

    Args:
        capacity: the storage's size.
        alpha: how much the TD error counts (0: uniform draws).
        beta: the importance weights' exponent (0: none, 1: the full correction).
        eps: added to every |TD error|, so that a transition the critics fit is still drawn.
    """

    def __init__(self, capacity: int, alpha: float, beta: float, eps: float) -> None:
        if capacity < 1 or alpha < 0 or beta < 0 or eps <= 0:
            raise ValueError(
                f"PrioritySampler: capacity {capacity} >= 1, alpha {alpha} >= 0, "
                f"beta {beta} >= 0 and eps {eps} > 0 needed"
            )
        self.alpha, self.beta, self.eps = float(alpha), float(beta), float(eps)
        blocks = -(-int(capacity) // BLOCK)
        self.priority = torch.zeros(blocks * BLOCK, dtype=torch.float64)
        self.block_sum = torch.zeros(blocks, dtype=torch.float64)
        self.max_priority = 1.0

    def _set(self, index: torch.Tensor, value: torch.Tensor | float) -> None:
        self.priority[index] = value
        blocks = torch.unique(index // BLOCK)
        self.block_sum[blocks] = self.priority.view(-1, BLOCK)[blocks].sum(1)

    def extend(self, index: torch.Tensor) -> None:
        index = torch.as_tensor(index, dtype=torch.long, device="cpu").reshape(-1)
        self._set(index, self.max_priority)

    def add(self, index: int | torch.Tensor) -> None:
        self.extend(index)

    def mark_update(self, index: int | torch.Tensor, *, storage: Storage | None = None) -> None:
        # Written over by the writer (a full storage's oldest rows): a new transition.
        self.extend(index)

    @torch.no_grad()
    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict[str, Any]]:
        n = len(storage)
        if n == 0:
            raise RuntimeError("PrioritySampler: the storage is empty")
        sums = self.block_sum[: -(-n // BLOCK)]
        cumulative = torch.cumsum(sums, 0)
        total = cumulative[-1]
        mass = torch.rand(batch_size, dtype=torch.float64) * total
        block = torch.searchsorted(cumulative, mass, right=True).clamp_max_(len(sums) - 1)
        within = (mass - (cumulative[block] - sums[block])).unsqueeze(1)
        rows = torch.cumsum(self.priority.view(-1, BLOCK)[block], 1)
        row = torch.searchsorted(rows, within, right=True).squeeze(1)
        # Rounding may point past a block's last written row: take that row.
        index = torch.minimum(block * BLOCK + row, torch.clamp_max(block * BLOCK + BLOCK, n) - 1)
        weight = (n * self.priority[index] / total).pow(-self.beta)
        return index, {"priority_weight": weight}

    @torch.no_grad()
    def update_priority(
        self,
        index: int | torch.Tensor,
        priority: float | torch.Tensor,
        *,
        storage: Storage | None = None,
    ) -> None:
        """Set the priorities of rows ``index`` from their |TD error| ``priority``."""
        index = torch.as_tensor(index, dtype=torch.long, device="cpu").reshape(-1)
        priority = torch.as_tensor(priority).to("cpu", torch.float64)
        bad = int((~torch.isfinite(priority)).sum())
        if bad:
            # One NaN priority makes every later draw's cumulative sums NaN.
            raise DivergenceError(
                f"replay: {bad} of the {priority.numel()} TD errors given to the priority "
                "sampler are not finite: the critics diverged"
            )
        value = (priority.abs() + self.eps).pow(self.alpha)
        value = value.expand(index.shape) if value.numel() == 1 else value.reshape(-1)
        self._set(index, value)
        self.max_priority = max(self.max_priority, float(value.max()))

    @property
    def default_priority(self) -> float:
        return self.max_priority

    def state_dict(self) -> dict[str, Any]:
        return {"priority": self.priority.clone(), "max_priority": self.max_priority}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.priority.copy_(state_dict["priority"])
        self.block_sum.copy_(self.priority.view(-1, BLOCK).sum(1))
        self.max_priority = float(state_dict["max_priority"])

    def _empty(self) -> None:
        self.priority.zero_()
        self.block_sum.zero_()
        self.max_priority = 1.0

    def dumps(self, path) -> None:
        torch.save(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(torch.load(path))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(alpha={self.alpha}, beta={self.beta}, eps={self.eps})"
