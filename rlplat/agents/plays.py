"""Aim plays: open-loop attacker plays of the form the search over plays finds.

A play gives each attacker, for each of ``S`` equal parts of the episode, an offset from the
(first) defender's current position and a fraction of its maximum speed: the attacker flies
towards ``defender + offset`` (raised to ``LOWEST_AIM`` at least) with a command of ``GAIN``
per metre, clamped per axis to its maximum speed and scaled by the fraction. A zero offset at
full speed is pure pursuit; other offsets lead, flank or wait for the defender, a low
fraction holds back. ``benchmarks/team_search.py`` searches such plays against the defender
network; ``algo.demonstrations`` (``rlplat.experiment.training``) flies the plays a search
wrote through the learner's own action and stores the episodes that capture in the replay
buffer.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict.nn import TensorDictModuleBase

from rlplat.errors import ConfigError

GAIN = 2.0  # 1/s, the command towards the aim point per metre of distance to it
LOWEST_AIM = 1.0  # m, aim points are raised to this altitude at least (not into the ground)


class AimPlay(TensorDictModuleBase):
    """Each attacker flies towards ``defender + offset`` at ``fraction`` of its maximum speed,
    both per part of the episode: ``offset`` (N, S, k, 3) m, ``fraction`` (N, S, k).

    With ``env`` (the env that flies it), the play is flown through that env's guided action
    (a correction to a law, :class:`rlplat.envs.components.GuidedVelocityAction`): the action
    is the correction that makes the law's action plus it the play's command
    (``action_fn.inverse`` under :meth:`rlplat.envs.pursuit.PursuitEnv.law_action`). Behind a
    shut gate (``action.gate_high > 0``) the env flies its law instead, so the episode may
    leave the play. Without ``env``, or with an env whose action corrects no law, the action
    is the plain velocity command (eq. 2).

    The play counts its own calls as the episode's steps: one episode per env, from a reset.
    """

    def __init__(
        self,
        offset: torch.Tensor,
        fraction: torch.Tensor,
        max_speed: torch.Tensor,
        steps_per_part: int,
        k: int,
        key,
        env=None,
    ) -> None:
        super().__init__()
        self.offset, self.fraction, self.max_speed = offset, fraction, max_speed
        self.steps_per_part, self.k, self.key, self.env = steps_per_part, k, key, env
        self.in_keys, self.out_keys = ["positions"], [key]
        self.step = 0

    def forward(self, td):
        part = min(self.step // self.steps_per_part, self.offset.shape[1] - 1)
        self.step += 1
        p = td.get("positions")  # (N, drones, 3): attackers first, then defenders
        own, defender = p[:, : self.k], p[:, self.k : self.k + 1]
        aim = defender + self.offset[:, part]
        aim[..., 2] = aim[..., 2].clamp_min(LOWEST_AIM)
        command = GAIN * (aim - own) / self.max_speed.unsqueeze(-1)
        action = command.clamp(-1.0, 1.0) * self.fraction[:, part].unsqueeze(-1)  # (N, k, 3)
        if self.env is not None and getattr(self.env.action_fn, "guided", False):
            action = self.env.action_fn.inverse(action, self.env.law_action())
        return td.set(self.key, action if isinstance(self.key, tuple) else action[:, 0])


@dataclass(frozen=True)
class Plays:
    """The plays of a search's ``--out`` file: one per scenario of ``split``.

    Attributes:
        path: the file.
        split: the split the plays were searched on.
        scenario_ids: (N,) the scenarios.
        offset: (N, S, k, 3) m; fraction: (N, S, k).
        captured: (N,) bool, whether the play captured when the search flew it again.
    """

    path: Path
    split: str
    scenario_ids: list[str]
    offset: torch.Tensor
    fraction: torch.Tensor
    captured: torch.Tensor

    def capturing(self) -> Plays:
        """Only the plays that captured."""
        keep = self.captured.nonzero().flatten()
        ids = [self.scenario_ids[i] for i in keep.tolist()]
        return Plays(self.path, self.split, ids, self.offset[keep], self.fraction[keep],
                     self.captured[keep])  # fmt: skip


def load_plays(path: str | Path, field: str = "algo.demonstrations") -> Plays:
    """Read a plays file (``benchmarks/team_search.py --out``); a one-line ``ConfigError``
    naming ``field`` for a missing or malformed file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{field}: no plays file {path}")
    try:
        doc = json.loads(path.read_text())
        plays = doc["plays"]
        split = doc.get("split", "train")
        ids = sorted(plays)
        offset = torch.tensor([plays[i]["offset_m"] for i in ids], dtype=torch.float32)
        fraction = torch.tensor([plays[i]["fraction"] for i in ids], dtype=torch.float32)
        captured = torch.tensor([plays[i]["captured_at_s"] is not None for i in ids])
        gain = float(doc.get("gain", GAIN))
    except (ValueError, KeyError, TypeError) as error:
        raise ConfigError(f"{field}: {path} is not a plays file ({error!r})") from None
    if ids and (offset.ndim != 4 or offset.shape[-1] != 3 or fraction.shape != offset.shape[:-1]):
        raise ConfigError(f"{field}: {path} is not a plays file (offsets {tuple(offset.shape)}, "
                          f"fractions {tuple(fraction.shape)})")  # fmt: skip
    if not math.isclose(gain, GAIN):
        raise ConfigError(f"{field}: {path} was searched with gain {gain:g}, plays fly {GAIN:g}")
    if not ids:
        offset, fraction = torch.zeros(0, 1, 1, 3), torch.zeros(0, 1, 1)
    return Plays(path, split, ids, offset, fraction, captured)
