"""Train a drone controller: ``python train.py drone=attacker_v3 reward=shaped``.

Every config group can be swapped from the command line (see conf/train.yaml); ``-m`` sweeps.
"""

import hydra
from omegaconf import DictConfig

from rlplat.cli import exit_on_error


@hydra.main(config_path="conf", config_name="train", version_base="1.3")
@exit_on_error
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
