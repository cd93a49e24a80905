"""Export a training run's policy: ``python export.py run_dir=DIR [ckpt=best|last|PATH]``.

Writes ``DIR/export/<ckpt>/``: ``policy.onnx``, ``policy.h`` + ``policy.c`` (C99) and
``card.json`` (interface, equivalence of torch, ONNX Runtime and C on rollout observations,
timing); see conf/export.yaml. ``controller=FILE out_dir=DIR`` exports a controller file.
"""

from pathlib import Path

from omegaconf import DictConfig

from rlplat.experiment.command_line import hydra_main


def check(cfg: DictConfig) -> None:
    """The run and checkpoint (or the controller file) each job exports exists, before the
    first job of a sweep starts (Hydra writes the sweep's record first)."""
    from rlplat.errors import ConfigError
    from rlplat.experiment.evaluation import checkpoint_path, load_run_config
    from rlplat.experiment.schema import validate_export_config

    validate_export_config(cfg)  # the fields first, then what they name
    if cfg.run_dir is not None:
        load_run_config(cfg.run_dir)
        checkpoint_path(Path(cfg.run_dir), cfg.ckpt)
    elif not Path(cfg.controller).is_file():
        raise ConfigError(f"controller: no file at {cfg.controller}")


@hydra_main("export", check)
def main(cfg: DictConfig) -> None:
    from rlplat.experiment.export import export_from_config

    for line in export_from_config(cfg):
        print(line)


if __name__ == "__main__":
    main()
