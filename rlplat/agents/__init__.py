"""Learning agents: SAC from TorchRL parts and the training run."""

from rlplat.agents.train import train

__all__ = ["train"]
