"""Train a drone controller: ``python train.py drone=attacker_v3 reward=shaped``.

Every config group can be swapped from the command line (see conf/train.yaml); ``-m`` sweeps.
"""

from pathlib import Path

from omegaconf import DictConfig

from rlplat.experiment.command_line import hydra_main


def check(cfg: DictConfig, run_dir: Path | None, field: str) -> None:
    from rlplat.experiment.training import preflight

    preflight(cfg, run_dir, field)  # before Hydra makes the run directory


@hydra_main("train", validate_job=check, resume_subdir=".hydra/resume")
def main(cfg: DictConfig) -> None:
    from rlplat.experiment import train

    summary = train(cfg)
    score = (
        ""
        if summary["val_score"] == "capture_rate"
        else (f"{summary['val_score'].replace('_', ' ')} {summary['test_score']:.3f}, ")
    )
    print(
        f"test {score}capture rate {summary['test_capture_rate']:.3f} "
        f"({summary['test_scenarios']} scenarios), run directory {summary['run_dir']}"
    )


if __name__ == "__main__":
    main()
