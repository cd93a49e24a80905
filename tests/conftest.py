"""Fixtures shared by the test modules, and the suite's machine options.

``--torch-threads N`` runs the suite, and every command-line tool it starts in a subprocess,
with N torch CPU threads; under pytest-xdist (``make test`` runs ``pytest -n auto``) a worker
takes its share of the cores unless N is given. Which CPU kernels torch picks is set before
torch is imported, by the environment variable ``ATEN_CPU_CAPABILITY`` (e.g. ``avx2`` or
``default``), which the subprocesses inherit as they are; torch.compile's on-disk cache is kept
apart per capability.

A test that takes a ``device`` argument runs on the CPU and, where torch sees one, on a CUDA
device (``pytest -k cuda`` runs those alone on a GPU machine).
"""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from rlplat.experiment.config import compose_config
from rlplat.scenarios import ScenarioSet, ScenarioSpec, write_scenario_set

ROOT = Path(__file__).resolve().parent.parent

# The small scenario set most tests fly.
SIZES = ("scenario.n_train=64", "scenario.n_val=16", "scenario.n_test=16")

# A training run of a few seconds: small batches, short episodes, validation twice.
TINY = (
    "algo.num_envs=4",
    "algo.frames_per_batch=64",
    "algo.init_random_frames=64",
    "algo.batch_size=32",
    "algo.utd_ratio=0.1",
    "algo.actor_cells=[32,32]",
    "algo.critic_cells=[32,32]",
    "algo.compile=false",
    "train.total_frames=256",
    "train.eval_every_frames=128",
    "train.progress=false",
    "env.time_limit=3",
)

# An attacker starting within 15 m of the defender (5 m in altitude).
NEAR = (
    "scenario.params.attacker_dx.low=-15",
    "scenario.params.attacker_dx.high=15",
    "scenario.params.attacker_dy.low=-15",
    "scenario.params.attacker_dy.high=15",
    "scenario.params.attacker_dz.low=-5",
    "scenario.params.attacker_dz.high=5",
)

# An easy pursuit for the learning tests: a slow defender, a fast attacker starting within
# 15 m (episodes of 20 s are set by the tests).
EASY = (
    "scenario.n_train=512",
    "scenario.n_val=64",
    "scenario.n_test=64",
    "scenario.params.defender_max_speed.high=1.5",
    "scenario.params.attacker_max_speed.low=4",
    *NEAR,
)

# Where pure pursuit falls short and proportional navigation does not: an attacker about as fast
# as the defender (2-3 against 2.5-3.5 m/s per axis), starting within 15 m (episodes of 20 s are
# set by the tests). On its 128 validation scenarios pure pursuit captures 0.57 and proportional
# navigation 0.81.
CHASE = (
    "scenario.n_train=512",
    "scenario.n_val=128",
    "scenario.n_test=128",
    "scenario.params.defender_max_speed.low=2.5",
    "scenario.params.defender_max_speed.high=3.5",
    "scenario.params.attacker_max_speed.low=2",
    "scenario.params.attacker_max_speed.high=3",
    *NEAR,
)


# Machine options ---------------------------------------------------------------------------

#: A CUDA device, where torch sees one: the ``device`` tests run there as well as on the CPU.
CUDA = pytest.param(
    "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
)


def pytest_generate_tests(metafunc):
    # A test that takes ``device`` runs on the CPU and on a CUDA device (skipped without one).
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", ["cpu", CUDA])


def pytest_addoption(parser):
    parser.addoption(
        "--torch-threads",
        type=int,
        default=None,
        metavar="N",
        help="torch CPU threads for the tests and the command-line tools they start "
        "(default: torch's own default)",
    )


def pytest_configure(config):
    # torch.compile keeps what it compiled on disk for later processes, and that cache does not
    # tell CPU capabilities apart: code generated for AVX512 and loaded by a process started with
    # ATEN_CPU_CAPABILITY=avx2 crashes or computes NaN, code generated for avx2 fails to build
    # under =default. So one cache per capability, unless TORCHINDUCTOR_CACHE_DIR names another
    # directory than torch's default (importing tensordict sets it to the default); the
    # subprocesses inherit it.
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    if os.environ.get("TORCHINDUCTOR_CACHE_DIR", default_cache_dir()) == default_cache_dir():
        capability = torch.backends.cpu.get_cpu_capability().lower()
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = f"{default_cache_dir()}_{capability}"
    threads = config.getoption("--torch-threads")
    if threads is None:
        threads = _threads_per_worker()
    if threads is None:
        return
    if threads < 1:
        raise pytest.UsageError(f"--torch-threads: must be a positive integer, got {threads}")
    torch.set_num_threads(threads)
    # torch reads OMP_NUM_THREADS when it starts: the subprocesses (train.py, evaluate.py,
    # python -m rlplat...) inherit the environment and start with the same thread count.
    os.environ["OMP_NUM_THREADS"] = str(threads)


def _threads_per_worker() -> int | None:
    """Under ``pytest -n N`` (pytest-xdist, as ``make test`` runs the suite) each worker takes
    its share of the cores: N processes with torch's default thread count each would wait for
    each other on every small kernel. None outside xdist (torch's own default)."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers is None:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, (cores or 1) // int(workers))


@pytest.fixture(autouse=True)
def _torch_threads_restored():
    """A test that trains in-process with ``train.threads`` sets torch's thread count for the
    whole process; put it back, so that later tests (and their subprocesses) run as the suite
    was started. (A module-scoped fixture must not train that way: it runs before this.)"""
    threads = torch.get_num_threads()
    yield
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def pytest_report_header(config):
    return (
        f"torch {torch.__version__}: {torch.get_num_threads()} CPU threads, "
        f"CPU capability {torch.backends.cpu.get_cpu_capability()} "
        f"(ATEN_CPU_CAPABILITY={os.environ.get('ATEN_CPU_CAPABILITY', 'unset')}), "
        f"compiled code cached in {os.environ.get('TORCHINDUCTOR_CACHE_DIR')}"
    )


# Scenarios ---------------------------------------------------------------------------------


def spec_from(*overrides: str) -> ScenarioSpec:
    """Build a ScenarioSpec through real Hydra composition of conf/scenarios.yaml."""
    cfg = compose_config("scenarios", ["out_dir=unused", *overrides])
    return ScenarioSpec.from_dict(OmegaConf.to_container(cfg.scenario, resolve=True))


@pytest.fixture(scope="session")
def make_spec():
    """make_spec(*overrides) -> ScenarioSpec, composed from conf/scenarios.yaml."""
    return spec_from


@pytest.fixture(scope="session")
def small_sizes() -> tuple[str, ...]:
    """The split sizes of the small sets: 64 train, 16 val, 16 test scenarios."""
    return SIZES


@pytest.fixture(scope="session")
def write_small_set():
    """write_small_set(path, *overrides) -> ScenarioSet: a small set with ``overrides``,
    written to ``path`` and loaded back."""

    def write(path: Path, *overrides: str) -> ScenarioSet:
        write_scenario_set(spec_from(*SIZES, *overrides), path)
        return ScenarioSet.load(path)

    return write


@pytest.fixture(scope="session")
def rewrite_split():
    """rewrite_split(set_dir, split, edit): the records of ``split`` edited (``edit(records)
    -> records``, a string kept as a line) and the file hashed into the manifest again: a
    hand-made set, as the loader sees it."""

    def rewrite(where: Path, split: str, edit) -> None:
        path = where / f"{split}.jsonl"
        records = [json.loads(line) for line in path.read_text().splitlines()]
        text = "".join(line if isinstance(line, str) else json.dumps(line) + "\n"
                       for line in edit(records))  # fmt: skip
        path.write_text(text)
        manifest = json.loads((where / "manifest.json").read_text())
        manifest["splits"][split]["sha256"] = hashlib.sha256(text.encode()).hexdigest()
        (where / "manifest.json").write_text(json.dumps(manifest))

    return rewrite


@pytest.fixture(scope="session")
def scenarios(tmp_path_factory, write_small_set) -> ScenarioSet:
    """The default small set, written once per worker: read only (a test that edits a set
    writes its own)."""
    return write_small_set(tmp_path_factory.mktemp("scenarios"))


@pytest.fixture(scope="session")
def easy_pursuit() -> tuple[str, ...]:
    """Scenario overrides of an easy pursuit (see EASY)."""
    return EASY


@pytest.fixture(scope="session")
def chase_pursuit() -> tuple[str, ...]:
    """Scenario overrides of a chase that separates pure pursuit from PN (see CHASE)."""
    return CHASE


# Training ----------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def tiny() -> tuple[str, ...]:
    """The train.py overrides of a run of a few seconds."""
    return TINY


@pytest.fixture(scope="session")
def tiny_run():
    """tiny_run(scenarios, run_dir, *overrides) -> summary: a run of a few seconds, in-process."""
    from rlplat.experiment.training import train

    def run(scenarios: ScenarioSet, run_dir: Path, *overrides: str) -> dict:
        cfg = compose_config("train", [*TINY, f"scenarios_dir={scenarios.path}", *overrides])
        return train(cfg, run_dir=run_dir)

    return run


# Command-line tools ------------------------------------------------------------------------


def _run_python(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ},
        timeout=timeout,
    )


@pytest.fixture
def refused_in_process(monkeypatch, capsys):
    """refused_in_process(tool, *args, cwd=ROOT) -> stderr: ``python tool *args`` (a script in
    the repository root, or ``-m`` and a module) run in this process, for a command line the
    tool refuses before Hydra starts: it must exit with code 2 there (a command that gets
    further fails the test). The same code as in a process of its own, without the seconds
    of a new process's imports; a test per tool runs one refusal as a process."""
    import runpy

    import hydra

    def started(*args, **kwargs):
        raise AssertionError("the command line was not refused before Hydra started")

    def hydra_main(*args, **kwargs):  # the entry point, made at import, may not start
        return lambda fn: started

    def run(tool: str, *args: str, cwd: Path = ROOT) -> str:
        module = args[0] if tool == "-m" else None
        argv = list(args[1:] if module else args)
        monkeypatch.chdir(cwd)
        monkeypatch.setattr(sys, "argv", [module or str(ROOT / tool), *argv])
        monkeypatch.setattr(hydra, "main", hydra_main)
        with pytest.raises(SystemExit) as exit_:
            if module:
                sys.modules.pop(module + ".__main__", None)
                runpy.run_module(module, run_name="__main__", alter_sys=False)
            else:
                runpy.run_path(str(ROOT / tool), run_name="__main__")
        assert exit_.value.code == 2, exit_.value.code
        return capsys.readouterr().err

    return run


@pytest.fixture(scope="session")
def run_python():
    """run_python(*args, timeout=300): ``python *args`` in the repository root, output captured;
    it inherits the environment (thread count, CPU capability)."""
    return _run_python


@pytest.fixture(scope="session")
def train_cli():
    """train_cli(*overrides, timeout=300): ``python train.py *overrides``, as run_python."""

    def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return _run_python(str(ROOT / "train.py"), *args, timeout=timeout)

    return cli
