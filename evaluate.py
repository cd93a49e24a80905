"""Evaluate a training run: ``python evaluate.py run_dir=DIR [policy=...] [ckpt=...]``.

Rebuilds env and policy from the run directory and replays every scenario of the split; see
conf/evaluate.yaml. ``compare=true`` also flies the classical baselines and writes the table.
"""

from omegaconf import DictConfig

from rlplat.experiment.command_line import hydra_main


def check(cfg: DictConfig) -> None:
    from rlplat.experiment.schema import validate_evaluate_config

    validate_evaluate_config(cfg)


@hydra_main("evaluate", check)
def main(cfg: DictConfig) -> None:
    from rlplat.experiment.evaluation import evaluate_from_config

    for line in evaluate_from_config(cfg):
        print(line)


if __name__ == "__main__":
    main()
