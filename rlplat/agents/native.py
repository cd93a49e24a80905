"""Running the exported artifacts: the C policy compiled and called through ctypes, the ONNX
model in ONNX Runtime, their timing, and both as policies the evaluator flies.

- :func:`find_compiler`, :func:`build_library`: ``policy.c`` built with the system C compiler
  (``cc -O2 -std=c99 -ffp-contract=off -shared -fPIC ... -lm``) into a shared library, loaded
  as a :class:`CPolicy` that calls ``rlplat_policy`` (or ``<prefix>_policy``, as its
  ``policy.h`` declares) once per observation row, the way
  firmware calls it.
- :class:`OnnxPolicy`: an ONNX Runtime session on one CPU thread, batched.
- :func:`time_c`: a generated C ``main`` that times single calls with ``clock_gettime``
  after a warm-up (ctypes would add more than the call costs); :func:`time_onnx` times
  ``session.run`` from Python per call and per batch.
- :func:`artifact_module`: either one as a ``TensorDictModule`` on the env's observation and
  action keys (a team's (N, K, obs_dim) rows are one call each).
"""

from __future__ import annotations

import ctypes
import platform
import re
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import Tensor, nn

from rlplat.agents.sac import SelectFeatures
from rlplat.errors import ConfigError

#: Flags of every build: optimised, strict C99, no fused multiply-adds or other math shortcuts
#: (each sum is rounded as written).
C_FLAGS = ("-O2", "-std=c99", "-ffp-contract=off", "-Wall", "-Wextra", "-pedantic")


def c_prefix(header: str) -> str:
    """The prefix of the C names a generated ``policy.h`` declares (``rlplat`` unless the
    export named another): its one function is ``<prefix>_policy``."""
    found = re.search(r"^void (\w+)_policy\(const float obs\[", header, re.MULTILINE)
    if found is None:
        raise ConfigError("policy.h: declares no <prefix>_policy function (not an rlplat export)")
    return found.group(1)


#: What :func:`find_compiler` builds to see that a compiler works: C99 that calls ``tanhf``.
_PROBE = "#include <math.h>\nfloat rlplat_probe(float x) { return tanhf(x); }\n"


def find_compiler(compiler: str = "cc") -> str:
    """The path of the C compiler ``compiler``, once it has built and loaded a shared library
    from a line of C99 with the flags of every build; a one-line error if there is none or it
    builds nothing (before any work: the checks it serves come after minutes of rollouts)."""
    path = shutil.which(compiler)
    if path is None:
        raise ConfigError(
            f"compiler: no C compiler '{compiler}' on PATH; install one (e.g. gcc) or name it "
            "with compiler=..."
        )
    with tempfile.TemporaryDirectory(prefix="rlplat-c-") as tmp:
        source, library = Path(tmp) / "probe.c", Path(tmp) / "libprobe.so"
        source.write_text(_PROBE)
        _compile(path, [source], library, "-shared", "-fPIC")
        _load(library, f"compiler: {compiler} builds no loadable shared library from C99")
    return path


def _load(library: Path, what: str) -> ctypes.CDLL:
    """``library`` loaded; a one-line :class:`ConfigError` starting with ``what`` if it is
    missing or not a library (a "compiler" that exits 0 and writes nothing)."""
    try:
        return ctypes.CDLL(str(library))
    except OSError as e:
        reason = "no file written" if not library.is_file() else str(e).rsplit(": ", 1)[-1]
        raise ConfigError(f"{what} ({reason})") from None


def compiler_version(compiler: str) -> str:
    """The first line of ``compiler --version``."""
    out = subprocess.run([compiler, "--version"], capture_output=True, text=True, check=False)
    return (out.stdout or out.stderr).splitlines()[0].strip() if out.returncode == 0 else "?"


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _compile(compiler: str, sources: list[Path], out: Path, *extra: str) -> str:
    """Run the compiler; returns its diagnostics (empty for a clean build)."""
    cmd = [compiler, *C_FLAGS, *extra, "-o", str(out), *map(str, sources), "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        error = _first_error(res.stderr)
        raise ConfigError(f"compiler: {compiler} failed on {sources[0].name}: {error}")
    return res.stderr.strip()


def _first_error(stderr: str) -> str:
    """The first diagnostic line that names an error, else the first line: a compiler's
    warnings (e.g. a C++ compiler's about ``-std=c99``) come before the error that failed it."""
    lines = stderr.strip().splitlines() or ["no message"]
    return next((line for line in lines if re.search(r"\berror\b", line, re.I)), lines[0])


def write_sources(directory: Path, header: str, source: str) -> Path:
    """``policy.h`` and ``policy.c`` into ``directory``; returns the path of ``policy.c``."""
    (directory / "policy.h").write_text(header)
    path = directory / "policy.c"
    path.write_text(source)
    return path


class CPolicy:
    """``<prefix>_policy`` of a compiled ``policy.c``, called through ctypes.

    ``policy(obs)``: obs (B, obs_dim) float32 -> actions (B, action_dim) float32, one C call
    per row.
    """

    def __init__(
        self, library: Path, obs_dim: int, action_dim: int, prefix: str = "rlplat"
    ) -> None:
        self._lib = _load(library, f"compiler: {library.name} cannot be loaded")
        self._fn = getattr(self._lib, f"{prefix}_policy")
        self._fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self._fn.restype = None
        self.obs_dim, self.action_dim = obs_dim, action_dim

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.ascontiguousarray(obs, dtype=np.float32).reshape(-1, self.obs_dim)
        out = np.empty((obs.shape[0], self.action_dim), dtype=np.float32)
        fn, src, dst = self._fn, obs.ctypes.data, out.ctypes.data
        step_in, step_out = obs.strides[0], out.strides[0]
        for row in range(obs.shape[0]):
            fn(src + row * step_in, dst + row * step_out)
        return out


def build_library(
    header: str, source: str, obs_dim: int, action_dim: int, compiler: str = "cc"
) -> tuple[CPolicy, str]:
    """Compile the C sources into a shared library (in a temporary directory, removed at once:
    the loaded library stays mapped) and load it. Returns the policy and the compiler's
    diagnostics (empty for a clean build)."""
    with tempfile.TemporaryDirectory(prefix="rlplat-c-") as tmp:
        c_file = write_sources(Path(tmp), header, source)
        library = Path(tmp) / "libpolicy.so"
        diagnostics = _compile(compiler, [c_file], library, "-shared", "-fPIC")
        return CPolicy(library, obs_dim, action_dim, c_prefix(header)), diagnostics


#: The timing harness: every call timed alone with CLOCK_MONOTONIC after a warm-up, cycling
#: through the given observations; then as many empty timer pairs (the timer's own cost).
TIMING_MAIN = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "policy.h"

static long long now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (long long)t.tv_sec * 1000000000LL + t.tv_nsec;
}

int main(int argc, char **argv)
{
    /* usage: timing OBS_FILE N_OBS WARMUP CALLS OUT_FILE */
    long n, warmup, calls, k;
    float *obs;
    long long *ns;
    float action[RLPLAT_ACT_DIM];
    volatile float sink = 0.0f;
    FILE *f;
    if (argc != 6) return 2;
    n = atol(argv[2]);
    warmup = atol(argv[3]);
    calls = atol(argv[4]);
    obs = malloc(sizeof(float) * RLPLAT_OBS_DIM * n);
    ns = malloc(sizeof(long long) * 2 * calls);
    if (!obs || !ns || !(f = fopen(argv[1], "rb"))) return 3;
    if (fread(obs, sizeof(float) * RLPLAT_OBS_DIM, n, f) != (size_t)n) return 4;
    fclose(f);
    for (k = 0; k < warmup; ++k) {
        rlplat_policy(obs + (k % n) * RLPLAT_OBS_DIM, action);
        sink += action[0];
    }
    for (k = 0; k < calls; ++k) {
        const float *x = obs + (k % n) * RLPLAT_OBS_DIM;
        long long t0 = now_ns();
        rlplat_policy(x, action);
        ns[k] = now_ns() - t0;
        sink += action[0];
    }
    for (k = 0; k < calls; ++k) {
        long long t0 = now_ns();
        ns[calls + k] = now_ns() - t0;
    }
    if (!(f = fopen(argv[5], "wb"))) return 5;
    if (fwrite(ns, sizeof(long long), 2 * calls, f) != (size_t)(2 * calls)) return 6;
    fclose(f);
    return 0;
}
"""


def _stats_us(ns: np.ndarray) -> dict[str, float]:
    """Median, p99 and max of per-call times given in ns, in microseconds, and how many calls
    took more than 3 x the median."""
    med, p99 = np.percentile(ns, [50, 99])
    return {
        "median_us": round(float(med) / 1e3, 4),
        "p99_us": round(float(p99) / 1e3, 4),
        "max_us": round(float(ns.max()) / 1e3, 4),
        "max_over_median": round(float(ns.max()) / max(float(med), 1e-9), 2),
        "calls_over_3x_median": int((ns > 3 * med).sum()),
    }


def time_c(
    header: str,
    source: str,
    obs: np.ndarray,
    *,
    calls: int = 100_000,
    warmup: int = 10_000,
    compiler: str = "cc",
) -> dict[str, Any]:
    """Per-call time of ``rlplat_policy``: a generated ``main`` linked with ``policy.c`` (the
    same flags as the library, no ``-fPIC``) times each of ``calls`` calls on its own, single
    thread, after ``warmup`` calls, cycling through the rows of ``obs``. Every call counts:
    outliers from the OS (interrupts, preemption) stay in p99 and max. The figures include one
    ``clock_gettime`` (its median cost is ``timer_overhead_us``)."""
    obs = np.ascontiguousarray(obs, dtype=np.float32)
    with tempfile.TemporaryDirectory(prefix="rlplat-timing-") as tmp:
        tmp = Path(tmp)
        c_file = write_sources(tmp, header, source)
        prefix = c_prefix(header)
        main = TIMING_MAIN.replace("rlplat_policy", f"{prefix}_policy")
        (tmp / "timing.c").write_text(main.replace("RLPLAT_", f"{prefix.upper()}_"))
        _compile(compiler, [tmp / "timing.c", c_file], tmp / "timing")
        obs.tofile(tmp / "obs.bin")
        args = [tmp / "timing", tmp / "obs.bin", len(obs), warmup, calls, tmp / "ns.bin"]
        res = subprocess.run(list(map(str, args)), capture_output=True, check=False)
        if res.returncode != 0:
            raise RuntimeError(f"the timing harness failed with exit code {res.returncode}")
        ns = np.fromfile(tmp / "ns.bin", dtype=np.int64)
    per_call, timer = ns[:calls], ns[calls:]
    return {
        "calls": calls,
        "warmup_calls": warmup,
        **_stats_us(per_call),
        "timer_overhead_us": round(float(np.median(timer)) / 1e3, 4),
        "flags": " ".join(C_FLAGS),
    }


class OnnxPolicy:
    """An ONNX model in an ONNX Runtime session on one CPU thread.

    ``policy(obs)``: obs (B, obs_dim) float32 -> actions (B, action_dim) float32, one batched
    run.
    """

    def __init__(self, model: bytes, obs_dim: int, action_dim: int) -> None:
        try:
            import onnxruntime as ort
        except ImportError:
            raise ConfigError(
                "policy: onnx needs onnxruntime, which is not installed; "
                "pip install 'rlplat[export]'"
            ) from None
        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1
        options.log_severity_level = 3
        self.session = ort.InferenceSession(
            model, sess_options=options, providers=["CPUExecutionProvider"]
        )
        self.obs_dim, self.action_dim = obs_dim, action_dim

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.ascontiguousarray(obs, dtype=np.float32).reshape(-1, self.obs_dim)
        return self.session.run(["action"], {"observation": obs})[0]


def time_onnx(
    policy: OnnxPolicy, obs: np.ndarray, *, batch: int, calls: int, warmup: int = 100
) -> dict[str, Any]:
    """Time of one ``session.run`` on ``batch`` observations (rows of ``obs``, cycled), from
    Python, one thread, after ``warmup`` runs: median, p99 and max over ``calls`` runs."""
    obs = np.ascontiguousarray(obs, dtype=np.float32)
    reps = -(-batch // len(obs))
    pool = np.concatenate([obs] * reps)[: max(batch, len(obs))]
    starts = [(k * batch) % (len(pool) - batch + 1) for k in range(calls + warmup)]
    ns = np.empty(calls, dtype=np.int64)
    for k, s in enumerate(starts):
        x = pool[s : s + batch]
        t0 = time.perf_counter_ns()
        policy(x)
        if k >= warmup:
            ns[k - warmup] = time.perf_counter_ns() - t0
    return {"batch": batch, "calls": calls, "warmup_calls": warmup, **_stats_us(ns)}


class _Rows(nn.Module):
    """A numpy policy of rows as a torch module: (*B, obs_dim) -> (*B, action_dim)."""

    def __init__(self, fn: Callable[[np.ndarray], np.ndarray], action_dim: int) -> None:
        super().__init__()
        self.fn, self.action_dim = fn, action_dim

    def forward(self, observation: Tensor) -> Tensor:
        x = observation.detach().to("cpu", torch.float32).numpy()
        y = torch.from_numpy(self.fn(x.reshape(-1, x.shape[-1])))
        return y.reshape(*observation.shape[:-1], self.action_dim).to(observation.device)


def artifact_module(
    policy: CPolicy | OnnxPolicy,
    obs_key: Any,
    action_key: Any,
    features: Sequence[int] | None = None,
) -> TensorDictModule:
    """An artifact as a policy the evaluator flies: reads the env's ``obs_key`` (N, obs_dim) or
    a team's (N, K, obs_dim), writes ``action_key`` in [-1, 1]; with ``features``, feeds the
    artifact only those features (an artifact trained alone flying each drone of a team)."""
    rows = _Rows(policy, policy.action_dim)
    module = rows if features is None else nn.Sequential(SelectFeatures(features), rows)
    return TensorDictModule(module, in_keys=[obs_key], out_keys=[action_key])
