"""rlplat: scenarios, training and validation of RL drone controllers on TorchRL + Hydra."""

__version__ = "0.1.0"
