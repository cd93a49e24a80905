"""Evaluate a training run: ``python evaluate.py run_dir=DIR [policy=...] [ckpt=...]``.

Rebuilds env and policy from the run directory and replays every scenario of the split; see
conf/evaluate.yaml. ``compare=true`` also flies the classical baselines and writes the table.
"""

from pathlib import Path

from omegaconf import DictConfig

from rlplat.experiment.command_line import hydra_main


def check(cfg: DictConfig) -> None:
    """Each job's config, then the run (and its checkpoint) it flies: before Hydra makes a
    sweep's folder in that run (``<run_dir>/eval``), or the first job starts."""
    from rlplat.agents.export import ARTIFACTS
    from rlplat.experiment.evaluation import checkpoint_path, load_run_config
    from rlplat.experiment.schema import validate_evaluate_config

    validate_evaluate_config(cfg)  # the fields first, then what they name
    load_run_config(cfg.run_dir)
    if cfg.policy == "checkpoint" or cfg.policy in ARTIFACTS:
        checkpoint_path(Path(cfg.run_dir), cfg.ckpt)


@hydra_main("evaluate", check)
def main(cfg: DictConfig) -> None:
    from rlplat.experiment.evaluation import evaluate_from_config

    for line in evaluate_from_config(cfg):
        print(line)


if __name__ == "__main__":
    main()
