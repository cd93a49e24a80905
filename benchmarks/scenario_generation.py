"""Time scenario generation: draw + dedupe + stratify, quality report, write, load.

.venv/bin/python benchmarks/scenario_generation.py [N]
"""

from __future__ import annotations

import sys
import tempfile
import time

from omegaconf import OmegaConf

from rlplat.experiment.config import compose_config
from rlplat.scenarios import ScenarioSet, ScenarioSpec, generate, quality_report, write_scenario_set


def main(n: int = 100_000) -> None:
    n_val = n_test = n // 10
    cfg = compose_config(
        "scenarios",
        [
            "out_dir=unused",
            f"scenario.n_train={n - n_val - n_test}",
            f"scenario.n_val={n_val}",
            f"scenario.n_test={n_test}",
        ],
    )
    spec = ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))
    rows = []
    t = time.perf_counter()
    splits = generate(spec)
    rows.append(("generate (draw, dedupe, stratify)", time.perf_counter() - t))
    t = time.perf_counter()
    quality_report(spec, splits)
    rows.append(("quality report", time.perf_counter() - t))
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        write_scenario_set(spec, d)
        rows.append(("generate + quality + write (the CLI's work)", time.perf_counter() - t))
        t = time.perf_counter()
        ScenarioSet.load(d)
        rows.append(("load (hash check + tensors)", time.perf_counter() - t))
    print(f"{n} scenarios")
    print(f"{'stage':<46}{'seconds':>10}")
    for name, s in rows:
        print(f"{name:<46}{s:>10.2f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000)
