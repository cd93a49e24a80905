"""Evaluation and validation: replay a split, metrics, reports, baselines, seed aggregation."""

__all__ = ["evaluate_from_config", "evaluate_run"]


def __getattr__(name: str):
    # Pulls in torchrl; imported on first use only (training imports the submodules directly).
    if name in __all__:
        from rlplat.eval import run

        return getattr(run, name)
    raise AttributeError(f"module 'rlplat.eval' has no attribute {name!r}")
