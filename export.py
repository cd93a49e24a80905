"""Export a training run's policy: ``python export.py run_dir=DIR [ckpt=best|last|PATH]``.

Writes ``DIR/export/<ckpt>/``: ``policy.onnx``, ``policy.h`` + ``policy.c`` (C99) and
``card.json`` (interface, equivalence of torch, ONNX Runtime and C on rollout observations,
timing); see conf/export.yaml. ``controller=FILE out_dir=DIR`` exports a controller file.
"""

from omegaconf import DictConfig

from rlplat.experiment.command_line import hydra_main


def check(cfg: DictConfig) -> None:
    from rlplat.experiment.schema import validate_export_config

    validate_export_config(cfg)


@hydra_main("export", check)
def main(cfg: DictConfig) -> None:
    from rlplat.experiment.export import export_from_config

    for line in export_from_config(cfg):
        print(line)


if __name__ == "__main__":
    main()
