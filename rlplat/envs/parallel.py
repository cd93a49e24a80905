"""Single-env pursuits stepped in parallel worker processes, shaped like one batched env.

An env whose dynamics live elsewhere (``dynamics=airsim``: one simulator per env) flies one
scenario at a time; N of them run in N worker processes of a TorchRL
:class:`~torchrl.envs.ParallelEnv`, which steps them at once. :class:`PursuitParallelEnv` makes
that parallel env look like a batched :class:`~rlplat.envs.pursuit.PursuitEnv` of batch [N] to
collectors, evaluation, policies and checkpoints:

- each worker's (1,)-batched env is seen unbatched (:func:`worker_env`), so the stack of N is
  [N], not [N, 1];
- what every worker has alike (scenarios, components, team layout, control period...) is read
  from a ``template``: a PursuitEnv of the same config and batch N, built in this process, that
  never steps;
- ``sampler`` fans out to the workers' scenario walks (each worker takes its share of the walk,
  see :class:`~rlplat.envs.pursuit.ScenarioSampler`);
- a worker that fails leaves its error's one line in a file; the parallel env raises it (an
  :class:`~rlplat.errors.RlplatError` stays one) instead of TorchRL's "worker dead".
"""

from __future__ import annotations

import shutil
import tempfile
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.envs import EnvBase, ParallelEnv, TransformedEnv
from torchrl.envs.transforms import BatchSizeTransform

from rlplat.envs.pursuit import PursuitEnv
from rlplat.errors import RlplatError

#: Attributes a PursuitParallelEnv answers from its template: the same in every worker.
SHARED = (
    "scenarios",
    "scenario_set",
    "split_name",
    "routes",
    "obs_fn",
    "action_fn",
    "reward_fn",
    "group",
    "team_size",
    "learner",
    "num_attackers",
    "num_defenders",
    "attackers",
    "defenders",
    "team",
    "opponents",
    "control_period",
    "max_steps",
    "capture_radius",
    "ground_altitude",
    "semi_axes",
    "terminate_out_of_view",
    "setpoint_acceptance",
    "setpoint_gain",
    "pursuit_gain",
    "route_flight",
    "meeting_lag",
    "meeting_horizon",
    "law_horizon",
    "computes_meeting",
    "defender_network",
    "drone_action_spec",
)


class WorkerFault(RlplatError):
    """A worker of a parallel env stopped on an rlplat error (its one line, and which worker)."""


def squeeze_batch(data: Any) -> Any:
    """(1, ...) -> (...): a worker's batch of one as an unbatched env (tensordicts and specs)."""
    return data.squeeze(0)


class _Worker(TransformedEnv):
    """A worker's env: its (1,)-batched PursuitEnv seen unbatched; an exception on the way
    out of a step or reset leaves its one line in ``fault_path`` for the parent to raise."""

    def __init__(self, env: PursuitEnv, fault_path: str | None) -> None:
        super().__init__(env, BatchSizeTransform(reshape_fn=squeeze_batch))
        self.__dict__["_fault_path"] = fault_path

    def _report(self, e: BaseException) -> None:
        if self._fault_path is not None:
            kind = "rlplat" if isinstance(e, RlplatError) else "other"
            line = str(e).splitlines()[0] if str(e) else type(e).__name__
            if kind == "other":
                line = "".join(traceback.format_exception_only(type(e), e)).strip()
            tmp = Path(self._fault_path + ".tmp")
            tmp.write_text(f"{kind}\n{line}\n")
            tmp.replace(self._fault_path)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        try:
            return super()._step(tensordict)
        except BaseException as e:
            self._report(e)
            raise

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        try:
            return super()._reset(tensordict, **kwargs)
        except BaseException as e:
            self._report(e)
            raise


def worker_env(env: PursuitEnv, fault_path: str | None = None) -> EnvBase:
    """A (1,)-batched PursuitEnv as a worker of :class:`PursuitParallelEnv` (unbatched)."""
    if env.batch_size != torch.Size([1]):
        raise ValueError(f"a worker env has batch size [1], got {list(env.batch_size)}")
    return _Worker(env, fault_path)


class _WorkerSamplers:
    """The workers' scenario walks as one: ``order`` and ``n`` are shared; the random state is
    the (N, L) stack of the workers' (a checkpoint's ``scenario_rng``)."""

    def __init__(self, env: PursuitParallelEnv) -> None:
        self._env = env
        self.n, self.order = env.template.sampler.n, env.template.sampler.order

    def get_state(self) -> Tensor:
        return torch.stack(list(self._env.sampler_state()))

    def set_state(self, state: Tensor) -> None:
        if state.dim() != 2 or state.shape[0] != self._env.num_workers:
            raise ValueError(
                f"scenario walk state: one row per worker ({self._env.num_workers}), "
                f"got shape {tuple(state.shape)}"
            )
        self._env.sampler_set_state(state)


class PursuitParallelEnv(ParallelEnv):
    """N single-env PursuitEnvs in N worker processes, as one env of batch [N].

    Args:
        create_env_fn: picklable function building worker ``i``'s env from its kwargs (a
            :func:`worker_env`); it is also called once in this process for the specs.
        create_env_kwargs: one kwargs dict per worker; each gets ``fault_path`` added.
        template: a PursuitEnv of the same config with batch N that never steps: what every
            worker has alike is read from it (``SHARED``).
        **kwargs: more :class:`~torchrl.envs.ParallelEnv` options.
    """

    def __init__(
        self,
        create_env_fn: Callable[..., EnvBase],
        create_env_kwargs: Sequence[dict[str, Any]],
        *,
        template: PursuitEnv,
        **kwargs: Any,
    ) -> None:
        n = len(create_env_kwargs)
        if template.batch_size != torch.Size([n]):
            raise ValueError(f"template: batch size [{n}], got {list(template.batch_size)}")
        fault_dir = tempfile.mkdtemp(prefix="rlplat-workers-")
        faults = [str(Path(fault_dir) / f"worker-{i}.err") for i in range(n)]
        kwargs_list = [{**kw, "fault_path": None} for kw in create_env_kwargs]
        super().__init__(n, create_env_fn, create_env_kwargs=kwargs_list, **kwargs)
        # The specs came from an env built here; the workers report their faults.
        for kw, path in zip(self.create_env_kwargs, faults, strict=True):
            kw["fault_path"] = path
        self.__dict__["template"] = template
        self.__dict__["_fault_dir"] = fault_dir
        self.__dict__["_fault_paths"] = faults

    def __getattr__(self, attr: str) -> Any:
        if attr in SHARED:
            return getattr(self.__dict__["template"], attr)
        if attr == "sampler":
            return _WorkerSamplers(self)
        return super().__getattr__(attr)

    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """Seed every worker alike, whatever ``static_seed``: the workers split one scenario
        walk (each its share of it), which they draw from the same random state, as one
        batched env of N draws its walk from one seed. Returns ``seed``."""
        return super().set_seed(seed, static_seed=True)

    def sampler_state(self) -> list[Tensor]:
        """Each worker's scenario walk state."""
        return self._dispatch(("sampler", "get_state"))

    def sampler_set_state(self, state: Tensor) -> None:
        """Set each worker's scenario walk state from the (N, L) stack."""
        self._dispatch(("sampler", "set_state"), state)

    def _dispatch(self, attr: tuple[str, ...], *args: Any) -> list[Any]:
        if self.is_closed:
            self.start()
        return super().__getattr__(attr[0]).__getattr__(attr[1])(*args)

    def _wait_for_workers(self, workers_range) -> None:
        try:
            super()._wait_for_workers(workers_range)
        except RuntimeError as e:
            raise self._fault() or e from None

    def _fault(self) -> BaseException | None:
        """The first worker fault on file, as the exception to raise."""
        for i, path in enumerate(self.__dict__["_fault_paths"]):
            if Path(path).is_file():
                kind, line = Path(path).read_text().splitlines()[:2]
                if kind == "rlplat":
                    return WorkerFault(f"env worker {i}: {line}")
                return RuntimeError(f"env worker {i} failed: {line}")
        return None

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Shut the workers down; after a worker fault (already reported) the others are
        terminated without a second error."""
        try:
            super().close(raise_if_closed=raise_if_closed)
        except RuntimeError:
            if self._fault() is None:
                raise
            self.is_closed = True
        finally:
            shutil.rmtree(self.__dict__.get("_fault_dir", ""), ignore_errors=True)
