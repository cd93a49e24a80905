"""rlplat: scenarios, training and validation of RL drone controllers on TorchRL + Hydra."""

__version__ = "0.1.0"
__all__ = ["make_env", "make_gym_env"]


def __getattr__(name: str):
    # The env entry points pull in torchrl; import them on first use only, so that
    # `python -m rlplat.scenarios` stays light.
    if name in __all__:
        from rlplat.experiment import api

        return getattr(api, name)
    raise AttributeError(f"module 'rlplat' has no attribute {name!r}")
