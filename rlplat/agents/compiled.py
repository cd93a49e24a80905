"""The compiled SAC update: TorchRL's ``SACLoss``, its gradients, Adam and the soft target
update in one compiled graph.

A gradient update of small networks costs little arithmetic; what ``torch.compile`` must remove
is everything around it. :class:`CompiledUpdate` makes one compiled call per update, a single
graph (``fullgraph=True``) that

- gathers the batch rows from the replay storage's own tensors and builds the batch
  ``TensorDict`` inside the graph,
- runs ``SACLoss`` on it and takes the gradients of the summed losses with
  ``torch.autograd.grad`` (traced into the graph: ``torch._dynamo.config.trace_autograd_ops``;
  a torch without that option breaks the graph there, into a loss graph and a step graph),
- applies ``torch.optim.adam.adam`` (the function ``Adam.step`` calls) for each optimiser's
  parameters and then the soft target update (``lerp``).

No autograd graph, ``.grad`` or optimiser call is left in Python. The optimisers stay
``torch.optim.Adam`` objects (their state dicts, hence checkpoints, are unchanged); the graph
reads their state tensors, collected once by :meth:`CompiledUpdate.bind`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence

import torch
from tensordict import TensorDict
from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files
from torch.optim.adam import adam

LOSS_NAMES = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")
#: The entry of an update's result that holds each row's priority (|TD error|, SACLoss's).
PRIORITY = "td_error"

#: Inductor options of the compiled update. Dynamo's guards already pin every input's shape and
#: stride while they are evaluated (the warm-up), so the generated code's own checks of each
#: input on every call are dropped.
OPTIONS = {"size_asserts": False, "alignment_asserts": False}

#: Whether Dynamo can trace ``torch.autograd.grad`` (an option of recent torch versions).
TRACE_GRAD = hasattr(torch._dynamo.config, "trace_autograd_ops")

_aten = torch.ops.aten


class ReluGradAsProduct(CustomGraphPass):
    """Inductor joint-graph pass: ReLU's backward as ``grad * sign(relu(x))``.

    For a torch that cannot trace ``autograd.grad`` (the update is then a forward graph with its
    backward, and a step graph). Autograd writes ReLU's backward ``where(relu(x) <= 0, 0,
    grad)``, and where only that mask is needed later (a critic evaluated with detached
    parameters, as in the actor loss), the partitioner saves the boolean mask for the backward.
    Inductor's CPU code stores a vector of booleans through a scalar loop, which made those
    kernels about ten times slower than the rest of the update. ``sign(relu(x))`` is 1 where
    ``relu(x) > 0`` and 0 elsewhere, so the gradient is the same (up to the sign of a zero); the
    graph keeps float tensors only. Within one graph no mask is saved, and the pass is not used.
    """

    def __call__(self, graph: torch.fx.Graph) -> None:
        for le in list(graph.nodes):
            if le.op != "call_function" or le.target is not _aten.le.Scalar or le.args[1] != 0:
                continue
            relu = le.args[0]
            while getattr(relu, "target", None) in (_aten.alias.default, _aten.view.default):
                relu = relu.args[0]
            if getattr(relu, "target", None) is not _aten.relu.default:
                continue
            users = list(le.users)
            if not users or not all(_is_select_zero(u, le) for u in users):
                continue
            for where in users:
                with graph.inserting_before(where):
                    sign = graph.call_function(_aten.sign.default, (le.args[0],))
                    product = graph.call_function(_aten.mul.Tensor, (where.args[2], sign))
                sign.meta = dict(le.args[0].meta)
                product.meta = dict(where.meta)
                where.replace_all_uses_with(product)
                graph.erase_node(where)
            graph.erase_node(le)

    def uuid(self) -> bytes:
        return get_hash_for_files((__file__,))


def _is_select_zero(node: torch.fx.Node, mask: torch.fx.Node) -> bool:
    """Whether ``node`` is ``where(mask, 0, x)``."""
    if node.target is not _aten.where.self or node.args[0] is not mask:
        return False
    zero = node.args[1]
    if isinstance(zero, int | float):
        return zero == 0
    target = getattr(zero, "target", None)
    if target is _aten.full.default:
        return zero.args[1] == 0
    if target is _aten.scalar_tensor.default:
        return zero.args[0] == 0
    return False


def init_adam_state(opt: torch.optim.Adam) -> None:
    """Create the state ``Adam.step`` creates on its first call (zero moments, step 0) for
    every trainable parameter that has none, so that a compiled step can read it."""
    for group in opt.param_groups:
        if group["amsgrad"] or group["fused"] or group["capturable"]:
            raise ValueError("compiled update: plain Adam only (no amsgrad, fused, capturable)")
        for p in group["params"]:
            if p.requires_grad and not opt.state[p]:
                opt.state[p]["step"] = torch.tensor(0.0, dtype=_scalar_dtype())
                opt.state[p]["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                opt.state[p]["exp_avg_sq"] = torch.zeros_like(
                    p, memory_format=torch.preserve_format
                )


def _scalar_dtype() -> torch.dtype:
    # What Adam keeps its step count in (torch.optim.optimizer._get_scalar_dtype).
    return torch.float64 if torch.get_default_dtype() == torch.float64 else torch.float32


class CompiledUpdate:
    """One SAC gradient update as one compiled call; see the module docstring.

    Args:
        loss: the ``SACLoss``.
        optimizers: its ``torch.optim.Adam`` optimisers (any split of its parameters).
        soft_pairs: ``(target, source)`` tensors of the soft target update.
        tau: the soft update rate (target <- target + tau * (source - target)).
    """

    #: Compiled calls run with guard checks until then; later batches have the same keys,
    #: shapes and dtypes (one replay buffer, one batch size), so the guards are skipped.
    WARMUP_CALLS = 3

    def __init__(
        self,
        loss: torch.nn.Module,
        optimizers: Mapping[str, torch.optim.Adam],
        soft_pairs: Sequence[tuple[torch.Tensor, torch.Tensor]],
        tau: float,
    ) -> None:
        self.loss, self.optimizers, self.tau = loss, dict(optimizers), tau
        self._soft_pairs = list(soft_pairs)
        self.keys: tuple = ()
        self._weighted: bool | None = None  # whether the last call weighted its rows
        options = dict(OPTIONS)
        if not TRACE_GRAD:
            options["joint_custom_pre_pass"] = ReluGradAsProduct()
        # Static shapes: a second run in one process with other network widths compiles its
        # own graph (a dynamic-shape recompile of the update crashes in inductor).
        self._update = torch.compile(
            self._update_eager, fullgraph=TRACE_GRAD, dynamic=False, options=options
        )
        self.bind()

    def bind(self) -> None:
        """Collect the parameters, the optimisers' state and hyperparameters, and the soft
        update's pairs; again after the optimisers' or the loss's state was loaded. The next
        calls evaluate their guards again."""
        self._params: list[torch.Tensor] = []
        self._exp_avgs: list[torch.Tensor] = []
        self._exp_avg_sqs: list[torch.Tensor] = []
        self._steps: list[torch.Tensor] = []
        self._groups: list[tuple[int, dict]] = []  # (number of parameters, hyperparameters)
        for opt in self.optimizers.values():
            init_adam_state(opt)
            for group in opt.param_groups:
                params = [p for p in group["params"] if p.requires_grad]
                self._params += params
                self._exp_avgs += [opt.state[p]["exp_avg"] for p in params]
                self._exp_avg_sqs += [opt.state[p]["exp_avg_sq"] for p in params]
                self._steps += [opt.state[p]["step"] for p in params]
                hyper = {k: group[k] for k in ("lr", "eps", "weight_decay", "maximize")}
                beta1, beta2 = group["betas"]
                hyper.update(beta1=beta1, beta2=beta2)
                hyper["decoupled_weight_decay"] = group.get("decoupled_weight_decay", False)
                self._groups.append((len(params), hyper))
        # A soft-update source that is a trained parameter is read as that parameter (one
        # graph input, not an alias of it); the others (buffers) as they are.
        position = {id(p): i for i, p in enumerate(self._params)}
        pairs = self._soft_pairs
        self._soft_trained = [(t, position[id(s)]) for t, s in pairs if id(s) in position]
        self._soft_other = [(t, s) for t, s in pairs if id(s) not in position]
        self._state = (
            self._params,
            self._exp_avgs,
            self._exp_avg_sqs,
            self._steps,
            [t for t, _ in self._soft_trained],
            [t for t, _ in self._soft_other],
            [s for _, s in self._soft_other],
        )
        self._calls = 0

    def __call__(
        self,
        keys: tuple,
        columns: Sequence[torch.Tensor],
        index: torch.Tensor | None,
        weights: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """One update on rows ``index`` of ``columns`` (the batch entries ``keys``, in that
        order; all rows when ``index`` is None); returns the detached losses. With ``weights``
        (prioritized replay's importance weights, one per row) each row's losses are weighted
        and the result also holds each row's ``td_error`` (the loss's priority); without, the
        graph is the unweighted update's alone."""
        weighted = weights is not None
        if (keys, weighted) != (self.keys, self._weighted):  # another layout: compile, guarded
            self.keys, self._weighted, self._calls = keys, weighted, 0
        args = (tuple(columns), index, weights, *self._state)
        if self._calls < self.WARMUP_CALLS:
            self._calls += 1
            with _tracing_grad():
                values = self._update(*args)
        else:
            # Guard evaluation costs as much as a small kernel; skipping it is sound while
            # every call looks like the warm-up ones (same keys, shapes, dtypes, optimiser
            # state tensors).
            with torch.compiler.set_stance("default", skip_guard_eval_unsafe=True):
                values = self._update(*args)
        names = LOSS_NAMES if weights is None else (*LOSS_NAMES, PRIORITY)
        return dict(zip(names, values, strict=True))

    def _update_eager(self, columns, index, weights, params, exp_avgs, exp_avg_sqs, steps, *soft):
        total, values = self._losses_eager(columns, index, weights)
        grads = torch.autograd.grad(total, params)
        self._step_eager(params, list(grads), exp_avgs, exp_avg_sqs, steps, *soft)
        return values

    def _losses_eager(self, columns, index, weights):
        batch = TensorDict(batch_size=columns[0].shape[:1] if index is None else index.shape)
        for key, column in zip(self.keys, columns, strict=True):
            batch.set(key, column if index is None else column[index])
        if weights is not None:
            batch.set(self.loss.tensor_keys.priority_weight, weights)
        losses = self.loss(batch)
        total = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
        values = tuple(losses[k].detach() for k in LOSS_NAMES)
        if weights is None:
            return total, values
        return total, (*values, batch.get(self.loss.tensor_keys.priority).detach())

    @torch.no_grad()
    def _step_eager(self, params, grads, exp_avgs, exp_avg_sqs, steps, targets, other, sources):
        start = 0
        for size, hyper in self._groups:
            end = start + size
            adam(
                params[start:end],
                grads[start:end],
                exp_avgs[start:end],
                exp_avg_sqs[start:end],
                [],
                steps[start:end],
                foreach=False,
                amsgrad=False,
                **hyper,
            )
            start = end
        trained = [params[i] for _, i in self._soft_trained]
        torch._foreach_lerp_([*targets, *other], [*trained, *sources], self.tau)


def _tracing_grad() -> contextlib.AbstractContextManager:
    """Dynamo traces ``torch.autograd.grad`` while this is open (where torch can)."""
    if TRACE_GRAD:
        return torch._dynamo.config.patch(trace_autograd_ops=True)
    return contextlib.nullcontext()


def compiled_update_keys(loss: torch.nn.Module, has: Callable[[object], bool]) -> tuple:
    """The batch entries an ``SACLoss`` reads: its ``in_keys`` and, when the batch has it
    (n-step transitions), the value estimator's ``steps_to_next_obs``."""
    keys = list(loss.in_keys)
    steps = loss.value_estimator.tensor_keys.steps_to_next_obs
    if has(steps):
        keys.append(steps)
    return tuple(keys)
