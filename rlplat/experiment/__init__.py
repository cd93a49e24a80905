"""The wiring layer: the only code that reads a Hydra ``cfg``.

It composes and checks configs (:mod:`~rlplat.experiment.config`), builds scenario sets, envs,
policies and loggers (:mod:`~rlplat.experiment.factory`, :mod:`~rlplat.experiment.logger`), and
runs training (:func:`train`), evaluation (:func:`evaluate_run`), controller files and exports
(:mod:`~rlplat.experiment.export`: ONNX and C). Nothing below this package sees a
``DictConfig``; the entry points (``train.py``, ``evaluate.py``, ``export.py``) only call it.
"""

__all__ = ["evaluate_from_config", "evaluate_run", "train"]


def __getattr__(name: str):
    # These pull in torchrl; import them on first use only, so that `python -m rlplat.scenarios`
    # (which reads the config directory from this package) stays light.
    if name == "train":
        from rlplat.experiment.training import train

        return train
    if name in ("evaluate_run", "evaluate_from_config"):
        from rlplat.experiment import evaluation

        return getattr(evaluation, name)
    raise AttributeError(f"module 'rlplat.experiment' has no attribute {name!r}")
