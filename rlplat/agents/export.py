"""A trained actor as artifacts that leave the platform: ONNX and dependency-free C99.

- :class:`DeterministicActor`: the action the evaluator flies (``ExplorationType.DETERMINISTIC``
  of :func:`rlplat.agents.sac.make_actor`) as a plain module ``observation -> action``: the
  observation scaling, the MLP, the squashed mean ``(1 + margin) * tanh(loc)`` clamped onto
  [-1, 1]. Only the mean's outputs of the last layer matter; the spread of the trained
  stochastic policy is computed (torch, ONNX) or skipped (C), never used.
- :func:`onnx_bytes`: that module as an ONNX model (``torch.onnx.export(dynamo=True)``), one
  input ``observation`` (batch, obs_dim) and one output ``action`` (batch, action_dim), checked
  with the ONNX checker and stripped of what would differ between two exports of the same
  network (source locations, doc strings).
- :func:`c_sources`: ``policy.h`` and ``policy.c``, C99 with the weights as ``static const``
  arrays, no heap and no library function but ``tanhf``/``expm1f`` of libm; the API is
  ``void rlplat_policy(const float obs[RLPLAT_OBS_DIM], float action[RLPLAT_ACT_DIM])``
  (another ``prefix`` than ``rlplat`` renames the function, the macros and the guard).

The generator knows the layers in :data:`C_LAYERS`; any other layer is refused, naming it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import textwrap
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torchrl.data import Bounded

from rlplat.agents.checkpoint import actor_from_state
from rlplat.errors import ConfigError

#: ``evaluate.py policy=`` choices that fly an exported artifact instead of the torch actor.
ARTIFACTS = ("onnx", "c")
#: Layers the C generator can write, by class.
C_LAYERS: dict[type[nn.Module], str] = {
    nn.Linear: "Linear",
    nn.ReLU: "ReLU",
    nn.Tanh: "Tanh",
    nn.ELU: "ELU",
}
#: The ONNX opset the models are written in.
ONNX_OPSET = 20
#: The prefix of the C names unless the export says otherwise.
C_PREFIX = "rlplat"
#: A prefix: lowercase words joined by single underscores. Lowercase, so that two prefixes
#: never give one uppercase guard (``Attacker`` and ``attacker``: ``ATTACKER_POLICY_H``); no
#: leading, trailing or double underscore, names C reserves (``__POLICY_H``).
_C_PREFIX = re.compile(r"[a-z][a-z0-9]*(?:_[a-z0-9]+)*")
_C_PREFIX_MAX = 24
#: Names the C standard library reserves (C11 7.31, future library directions), by the header
#: that reserves them: a prefix that starts one of them in lower or upper case is refused.
_C_RESERVED = (
    (re.compile(r"E[0-9A-Z]"), "errno.h"),
    (re.compile(r"(is|to)[a-z]"), "ctype.h"),
    (re.compile(r"LC_[A-Z]"), "locale.h"),
    (re.compile(r"SIG[A-Z_]"), "signal.h"),
    (re.compile(r"(str|mem|wcs)[a-z]"), "string.h, stdlib.h"),
    (re.compile(r"(PRI|SCN)[a-zX]"), "inttypes.h"),
    (re.compile(r"FE_[A-Z]"), "fenv.h"),
    (re.compile(r"(atomic_|memory_order_)[a-z]|ATOMIC_[A-Z]"), "stdatomic.h"),
    (re.compile(r"(cnd|mtx|thrd|tss)_[a-z]"), "threads.h"),
    (re.compile(r"TIME_[A-Z]"), "time.h"),
)


def c_api(prefix: str = C_PREFIX) -> str:
    """The one function ``policy.h`` declares, its names starting with ``prefix``."""
    p = prefix.upper()
    return f"void {prefix}_policy(const float obs[{p}_OBS_DIM], float action[{p}_ACT_DIM]);"


def check_prefix(prefix: Any, field: str = "prefix") -> str:
    """``prefix`` if it starts C names that no other prefix shares (lowercase letters and
    digits, words joined by single ``_``, starting with a letter; at most 24 characters);
    otherwise a one-line :class:`ConfigError` naming ``field``."""
    if (
        not isinstance(prefix, str)
        or len(prefix) > _C_PREFIX_MAX
        or not _C_PREFIX.fullmatch(prefix)
    ):
        raise ConfigError(
            f"{field}: {prefix!r} does not start C names (lowercase letters and digits, words "
            f"joined by single _, starting with a letter; at most {_C_PREFIX_MAX} characters)"
        )
    for name in c_names(prefix):
        for pattern, where in _C_RESERVED:
            if pattern.match(name):
                other = f"drone_{prefix}"
                example = f", e.g. {other!r}" if len(other) <= _C_PREFIX_MAX else ""
                raise ConfigError(
                    f"{field}: {prefix!r} makes {name}, a name C reserves ({where}); choose "
                    f"another prefix{example}"
                )
    return prefix


def c_names(prefix: str) -> list[str]:
    """The external and macro names, and the first table's, that ``prefix`` starts."""
    p = prefix.upper()
    return [f"{prefix}_policy", f"{prefix}_inv_scale", f"{p}_OBS_DIM", f"{p}_POLICY_H"]


def observation_key(group: str | None) -> str | tuple[str, str]:
    """The env's observation key of a lone learner (None) or of a team's ``group``."""
    return "observation" if group is None else (group, "observation")


class DeterministicActor(nn.Module):
    """The deterministic action of a :func:`~rlplat.agents.sac.make_actor` actor, as a plain
    module.

    ``forward(observation)``: observation (*B, obs_dim) float32, raw as the env emits it (m,
    m/s) -> action (*B, action_dim) float32 in [-1, 1], ``clamp((1 + margin) * tanh(loc))``
    with ``loc`` the first ``action_dim`` outputs of ``mlp(observation * inv_scale)``.

    Args:
        mlp: the actor's MLP (``nn.Sequential`` of layers), outputs (loc, raw scale).
        inv_scale: (obs_dim,) float32, 1 / the observation's typical magnitudes.
        action_dim: the action's size.
        action_margin: the tanh squashes onto the bounds widened by this fraction.
    """

    def __init__(
        self, *, mlp: nn.Sequential, inv_scale: Tensor, action_dim: int, action_margin: float
    ) -> None:
        super().__init__()
        self.mlp = mlp
        self.register_buffer("inv_scale", inv_scale.detach().clone())
        self.action_dim, self.action_margin = int(action_dim), float(action_margin)
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> DeterministicActor:
        """The actor of a loaded checkpoint or controller file."""
        dim = state["net"]["action_dim"]
        actor = actor_from_state(state, Bounded(-1.0, 1.0, shape=(dim,)))
        scaled = actor.module[0].module[0]  # Scaled(MLP): observation -> (loc, raw scale)
        margin = float(state["net"].get("action_margin", 0.0))
        return cls(
            mlp=scaled.body, inv_scale=scaled.inv_scale, action_dim=dim, action_margin=margin
        )

    @property
    def obs_dim(self) -> int:
        return self.inv_scale.shape[0]

    def forward(self, observation: Tensor) -> Tensor:
        loc = self.mlp(observation * self.inv_scale)[..., : self.action_dim]
        return ((1.0 + self.action_margin) * torch.tanh(loc)).clamp(-1.0, 1.0)

    def layers(self) -> list[dict[str, Any]]:
        """The MLP as the C generator sees it: ``{"type", "in", "out"}`` per Linear,
        ``{"type"}`` per activation (``alpha`` for ELU), checked.

        Raises:
            ConfigError: a layer the C generator does not know, or an MLP whose shape is not
                Linear ... Linear from obs_dim to 2 x action_dim.
        """
        out, width = [], self.obs_dim
        for i, layer in enumerate(self.mlp):
            kind = C_LAYERS.get(type(layer))
            if kind is None:
                raise ConfigError(
                    f"export: actor layer {i} is {type(layer).__name__}, which the C generator "
                    f"does not know; it supports {', '.join(C_LAYERS.values())}"
                )
            if kind == "Linear":
                if layer.in_features != width or layer.bias is None:
                    raise ConfigError(
                        f"export: actor layer {i} is Linear({layer.in_features}, "
                        f"{layer.out_features}, bias={layer.bias is not None}); the C generator "
                        f"expects {width} inputs and a bias"
                    )
                width = layer.out_features
                out.append({"type": kind, "in": layer.in_features, "out": width})
            elif kind == "ELU":
                out.append({"type": kind, "alpha": float(layer.alpha)})
            else:
                out.append({"type": kind})
        if not out or out[-1]["type"] != "Linear" or width != 2 * self.action_dim:
            raise ConfigError(
                f"export: the actor must end with a Linear layer of {2 * self.action_dim} outputs "
                f"(mean and spread of {self.action_dim} actions), got {out[-1] if out else 'none'}"
            )
        return out


# ONNX ---------------------------------------------------------------------------------------


#: Loggers of the exporter and its graph optimiser: they report each pass they run and warn
#: about optional packages that do not concern the model.
EXPORTER_LOGGERS = ("torch.onnx", "onnxscript", "onnx_ir")


@contextlib.contextmanager
def _quiet_exporter():
    """Keep the exporter's progress messages and warnings out of the user's log while it runs
    (its errors still show)."""
    loggers = [logging.getLogger(name) for name in EXPORTER_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


def onnx_bytes(actor: DeterministicActor, metadata: Mapping[str, str] | None = None) -> bytes:
    """``actor`` as a serialised ONNX model with a dynamic batch dimension, checked with the
    ONNX checker (full check: shapes inferred); two exports of one network are byte-identical.
    ``metadata`` becomes the model's ``metadata_props`` (what ONNX Runtime's
    ``get_modelmeta().custom_metadata_map`` reads), in key order.
    """
    import onnx

    example = torch.zeros(1, actor.obs_dim)
    with _quiet_exporter():
        program = torch.onnx.export(
            actor,
            (example,),
            dynamo=True,
            input_names=["observation"],
            output_names=["action"],
            dynamic_shapes={"observation": {0: torch.export.Dim("batch")}},
            opset_version=ONNX_OPSET,
            optimize=True,
            verbose=False,
        )
    model = program.model_proto
    # What varies with where and how the exporter ran (source paths, stack traces) goes.
    del model.metadata_props[:]
    for key, value in sorted((metadata or {}).items()):
        model.metadata_props.add(key=key, value=value)
    model.doc_string = model.graph.doc_string = ""
    for node in model.graph.node:
        del node.metadata_props[:]
        node.doc_string = ""
    model.producer_name, model.producer_version = "rlplat", f"torch {torch.__version__}"
    onnx.checker.check_model(model, full_check=True)
    return model.SerializeToString(deterministic=True)


# C ------------------------------------------------------------------------------------------


def _c_float(x: float) -> str:
    """A float32 as a C literal that reads back to the same float (9 significant digits)."""
    if not math.isfinite(x):
        raise ConfigError(f"export: the network holds a non-finite weight ({x})")
    text = f"{x:.9g}"
    if not any(c in text for c in ".e"):
        text += ".0"
    return text + "f"


def _c_array(values: np.ndarray, indent: str = "    ", per_line: int = 6) -> str:
    """The body of a C initialiser: nested braces for a 2-D array, ``per_line`` values a line."""
    if values.ndim == 2:
        rows = [f"{indent}{{\n{_c_array(row, indent * 2, per_line)}\n{indent}}}" for row in values]
        return ",\n".join(rows)
    items = [_c_float(float(v)) for v in values]
    lines = [", ".join(items[i : i + per_line]) for i in range(0, len(items), per_line)]
    return ",\n".join(indent + line for line in lines)


def _comment(lines: Sequence[str]) -> str:
    """A C block comment of ``lines``; a ``*/`` or ``/*`` in them (a drone's name, say) is
    broken up, so that it neither ends the comment nor nests one."""
    lines = [line.replace("*/", "* /").replace("/*", "/ *") for line in lines]
    return "/*\n" + "".join(f" * {line}".rstrip() + "\n" for line in lines) + " */\n"


def _c_dense(x: str, y: str, w: str, n: int, width: int, unroll: int = 4) -> list[str]:
    """C lines of ``y[j] += sum_i w[i][j] x[i]``, the inputs taken ``unroll`` at a time: one
    pass over ``y`` per ``unroll`` inputs (a quarter of the loads and stores), the terms added
    left to right, so that every sum is the same as one input at a time."""
    lines, full = [], n - n % unroll
    if full:
        names = ", ".join(f"a{u} = {x}[i + {u}]" if u else f"a0 = {x}[i]" for u in range(unroll))
        terms = [f"{w}[i + {u}][j] * a{u}" if u else f"{w}[i][j] * a0" for u in range(unroll)]
        half = (unroll + 1) // 2
        lines += [
            f"    for (i = 0; i < {full}; i += {unroll}) {{",
            f"        const float {names};",
            f"        for (j = 0; j < {width}; ++j)",
            f"            {y}[j] = {y}[j] + {' + '.join(terms[:half])}",
            f"                + {' + '.join(terms[half:])};",
            "    }",
        ]
    if n % unroll:
        lines += [
            f"    for (i = {full}; i < {n}; ++i) {{",
            f"        const float xi = {x}[i];",
            f"        for (j = 0; j < {width}; ++j) {y}[j] += {w}[i][j] * xi;",
            "    }",
        ]
    return lines


#: What ``rlplat_policy``'s action is, in the header, for an action that is the velocity command.
VELOCITY_ACTION = "in [-1, 1]; times the drone's maximum speed per axis, the velocity command."


def c_sources(
    actor: DeterministicActor,
    describe: Sequence[str] = (),
    action: str = VELOCITY_ACTION,
    prefix: str = C_PREFIX,
) -> tuple[str, str]:
    """``policy.h`` and ``policy.c`` of ``actor``: C99, weights as ``static const float``, no
    heap, only ``tanhf``/``expm1f`` from libm. ``describe``: comment lines for the header (the
    observation layout, where the network came from); ``action``: what the action is, next to
    the function's declaration; ``prefix``: of the external names (``<prefix>_policy``, the
    macros ``<PREFIX>_OBS_DIM``, ``<PREFIX>_ACT_DIM`` and the include guard), so that two
    controllers link into one program.

    Each Linear layer computes ``y[j] = b[j] + sum_i W[i][j] x[i]`` with the weights stored
    input-major, so that the inner loop runs over contiguous outputs (which compilers
    vectorise without reordering any sum); of the last layer only the mean's outputs are kept.

    Raises:
        ConfigError: a layer the generator does not know (see :meth:`DeterministicActor.layers`).
    """
    layers = actor.layers()
    obs_dim, act_dim = actor.obs_dim, actor.action_dim
    p = check_prefix(prefix).upper()
    widths = [obs_dim] + [spec["out"] for spec in layers if spec["type"] == "Linear"]
    widths[-1] = act_dim  # the last Linear keeps the mean's outputs only
    stack = 4 * sum(widths)
    libm = "tanhf, expm1f" if any(spec["type"] == "ELU" for spec in layers) else "tanhf"
    shared = f"{p}_OBS_DIM" if obs_dim >= act_dim else f"{p}_ACT_DIM"
    contract = (
        f"The call is reentrant and keeps no state: no initialisation, no global written, "
        f"no heap; about {stack} bytes of stack for the layer buffers. obs and action may be "
        f"the same array (obs is read whole before action is written; an array of "
        f"{shared} floats then). Link with -lm. The tables are static, their names start "
        f"with {prefix}_, so two controllers of different prefixes build as two files or as one."
    )
    header = (
        _comment(
            [
                "policy.h: the deterministic policy of an rlplat controller (generated; do not",
                f"edit). C99, no heap, no library but libm ({libm}).",
                "Checked against the network built with cc -O2 -std=c99 -ffp-contract=off: fused",
                "multiply-adds, x87 or -ffast-math maths round differently (about 1e-5 of action).",
                "",
                *describe,
            ]
        )
        + f"#ifndef {p}_POLICY_H\n#define {p}_POLICY_H\n\n"
        f"#define {p}_OBS_DIM  {obs_dim}   /* the run's observation size */\n"
        f"#define {p}_ACT_DIM  {act_dim}\n\n"
        '#ifdef __cplusplus\nextern "C" {\n#endif\n\n'
        "/* obs: the observation exactly as the env emits it (SI units, the order above).\n"
        + "".join(f" * {line}\n" for line in textwrap.wrap(contract, 76))
        + " *\n"
        + "".join(f" * {line}\n" for line in textwrap.wrap(f"action: {action}", 76))
        + " * A NaN observation gives NaN actions (an infinite one may), as the torch actor\n"
        " * does: check them before flying the command (not so under -ffast-math, which\n"
        " * may turn them into finite actions: check the observation there). */\n"
        f"{c_api(prefix)}\n\n"
        f"#ifdef __cplusplus\n}}\n#endif\n\n#endif /* {p}_POLICY_H */\n"
    )

    tables = [
        "/* 1 / the observation's typical magnitudes: the network sees obs * inv_scale */\n"
        f"static const float {prefix}_inv_scale[{p}_OBS_DIM] = {{\n"
        f"{_c_array(actor.inv_scale.numpy())}\n}};\n"
    ]
    body = [f"    for (i = 0; i < {obs_dim}; ++i) x0[i] = obs[i] * {prefix}_inv_scale[i];"]
    buffers = [f"    float x0[{obs_dim}];"]
    linears = [m for m in actor.mlp if isinstance(m, nn.Linear)]
    k, n = 0, obs_dim  # the current buffer and its width
    for spec in layers:
        kind = spec["type"]
        x = f"x{k}"
        if kind == "Linear":
            layer = linears[k]
            last = k == len(linears) - 1
            width = act_dim if last else spec["out"]
            w = layer.weight.detach()[:width].T.contiguous().numpy()  # (in, width)
            b = layer.bias.detach()[:width].numpy()
            note = f", its first {width} outputs (the mean)" if last else ""
            k += 1
            tables.append(
                f"/* layer {k}: Linear {spec['in']} -> {spec['out']}{note}; {prefix}_w{k}[i][j] "
                f"weighs input i in output j */\n"
                f"static const float {prefix}_w{k}[{spec['in']}][{width}] = "
                f"{{\n{_c_array(w)}\n}};\n"
                f"static const float {prefix}_b{k}[{width}] = {{\n{_c_array(b)}\n}};\n"
            )
            y = f"x{k}"
            buffers.append(f"    float {y}[{width}];")
            body += [
                f"    /* Linear {spec['in']} -> {spec['out']} */",
                f"    for (j = 0; j < {width}; ++j) {y}[j] = {prefix}_b{k}[j];",
                *_c_dense(x, y, f"{prefix}_w{k}", n, width),
            ]
            n = width
        elif kind == "ReLU":
            # written so that NaN passes through, as torch's relu lets it
            body.append(f"    for (j = 0; j < {n}; ++j) {x}[j] = {x}[j] < 0.0f ? 0.0f : {x}[j];")
        elif kind == "Tanh":
            body.append(f"    for (j = 0; j < {n}; ++j) {x}[j] = tanhf({x}[j]);")
        else:  # ELU
            alpha = _c_float(np.float32(spec["alpha"]).item())
            body.append(
                f"    for (j = 0; j < {n}; ++j) "
                f"{x}[j] = {x}[j] > 0.0f ? {x}[j] : {alpha} * expm1f({x}[j]);"
            )
    gain = _c_float(np.float32(1.0 + actor.action_margin).item())
    body += [
        f"    /* the squashed mean: clamp({gain} * tanh(loc), -1, 1) */",
        f"    for (j = 0; j < {p}_ACT_DIM; ++j) {{",
        f"        const float a = {gain} * tanhf(x{k}[j]);",
        "        action[j] = a < -1.0f ? -1.0f : (a > 1.0f ? 1.0f : a);",
        "    }",
    ]
    source = (
        _comment(
            [
                "policy.c: the deterministic policy of an rlplat controller (generated; do not",
                "edit). See policy.h for the interface.",
            ]
        )
        + "#if !defined(__cplusplus) && \\\n"
        "    (!defined(__STDC_VERSION__) || __STDC_VERSION__ < 199901L)\n"
        '#error "policy.c needs C99 or later (tanhf, expm1f): -std=c99 (MSVC: /std:c11)"\n'
        "#endif\n\n"
        '#include <math.h>\n\n#include "policy.h"\n\n'
        + "\n".join(tables)
        + f"\n{c_api(prefix)[:-1]}\n{{\n"
        + "\n".join(buffers)
        + "\n    int i, j;\n\n"
        + "\n".join(body)
        + "\n}\n"
    )
    return header, source
