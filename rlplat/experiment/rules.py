"""Rules of a config table: each takes a value and says what is wrong with it (None: nothing).

A table maps dotted keys to rules; :func:`check_table` applies one to a resolved config: every
key it names must be set (but those whose rule is :class:`Opt`) and pass its rule, and a node
that holds table keys refuses a key the table does not name. Messages are one line that names
the field and quotes the value, e.g. ``algo.actor_lr: must be a finite number > 0, got nan``.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import torch

from rlplat.errors import ConfigError

#: A rule takes a value and returns what is wrong with it (None: nothing).
Rule = Callable[[Any], "str | None"]

#: What :func:`lookup` returns for a key that is not set.
MISSING = object()


def show(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _fmt(bound: float) -> str:
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


@dataclass(frozen=True)
class Num:
    """A finite number (``integer``: an int) within the bounds given; ``null``: or None;
    ``words``: or one of these strings (e.g. ``auto``)."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    integer: bool = False
    null: bool = False
    words: tuple[str, ...] = ()

    def __call__(self, value: Any) -> str | None:
        if (value is None and self.null) or value in self.words or self.fits(value):
            return None
        return f"must be {self.text()}, got {show(value)}"

    def fits(self, v: Any) -> bool:
        if isinstance(v, bool) or not isinstance(v, int if self.integer else (int, float)):
            return False
        return math.isfinite(v) and not (
            (self.gt is not None and v <= self.gt)
            or (self.ge is not None and v < self.ge)
            or (self.lt is not None and v >= self.lt)
            or (self.le is not None and v > self.le)
        )

    def text(self, plural: bool = False) -> str:
        if self.integer:
            kind = "integers" if plural else "an integer"
        else:
            kind = "finite numbers" if plural else "a finite number"
        low = (">", self.gt) if self.gt is not None else (">=", self.ge)
        high = ("<", self.lt) if self.lt is not None else ("<=", self.le)
        if low[1] is not None and high[1] is not None:
            left, right = "(" if low[0] == ">" else "[", ")" if high[0] == "<" else "]"
            kind += f" in {left}{_fmt(low[1])}, {_fmt(high[1])}{right}"
        else:
            kind += "".join(f" {op} {_fmt(b)}" for op, b in (low, high) if b is not None)
        words = "".join(f"'{w}' or " for w in self.words)
        return words + kind + (" or null" if self.null else "")


@dataclass(frozen=True)
class Seq:
    """A non-empty list of ``item`` numbers: exactly ``n`` of them, or strictly increasing."""

    item: Num
    n: int | None = None
    increasing: bool = False

    def __call__(self, value: Any) -> str | None:
        ok = (
            isinstance(value, list)
            and len(value) > 0
            and (self.n is None or len(value) == self.n)
            and all(self.item.fits(x) for x in value)
            and (not self.increasing or all(a < b for a, b in zip(value, value[1:], strict=False)))
        )
        if ok:
            return None
        size = str(self.n) if self.n else "a non-empty list of"
        order = " increasing" if self.increasing else ""
        return f"must be {size}{order} {self.item.text(plural=True)}, got {show(value)}"


@dataclass(frozen=True)
class Choice:
    """One of ``names``: a registry's keys, or a function that gives them (imported on use)."""

    names: Iterable[str] | Callable[[], Iterable[str]]
    null: bool = False

    def __call__(self, value: Any) -> str | None:
        names = list(self.names() if callable(self.names) else self.names)
        if (value is None and self.null) or (isinstance(value, str) and value in names):
            return None
        return f"unknown {show(value)}; valid: {', '.join(names)}"


@dataclass(frozen=True)
class Text:
    """A non-empty string (a name or a path); ``null``: or None."""

    null: bool = False

    def __call__(self, value: Any) -> str | None:
        if (value is None and self.null) or (isinstance(value, str) and value.strip()):
            return None
        return f"must be a non-empty string{' or null' * self.null}, got {show(value)}"


@dataclass(frozen=True)
class TextList:
    """A list (empty allowed) of non-empty strings, e.g. paths."""

    def __call__(self, value: Any) -> str | None:
        if isinstance(value, list) and all(isinstance(x, str) and x.strip() for x in value):
            return None
        return f"must be a list of non-empty strings, got {show(value)}"


def flag(value: Any) -> str | None:
    """true or false."""
    return None if isinstance(value, bool) else f"must be true or false, got {show(value)}"


def device(value: Any) -> str | None:
    """A torch device string, of a device this machine has."""
    try:
        dev = torch.device(value) if isinstance(value, str) else None
    except RuntimeError:
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda", "mps"):
        return f"must be a torch device (cpu, cuda, cuda:1, mps), got {show(value)}"
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if not count:
            return f"{show(value)} is not available on this machine (torch sees no CUDA device)"
        if dev.index is not None and dev.index >= count:
            return f"{show(value)} is not available on this machine ({count} CUDA device(s))"
    if dev.type == "mps" and not torch.backends.mps.is_available():
        return f"{show(value)} is not available on this machine (no MPS)"
    return None


@dataclass(frozen=True)
class Opt:
    """A key the config may leave out (a default applies); set, it follows ``rule``."""

    rule: Rule

    def __call__(self, value: Any) -> str | None:
        return self.rule(value)


POSITIVE = Num(gt=0)
NON_NEGATIVE = Num(ge=0)
FINITE = Num()
COUNT = Num(integer=True, ge=1)
THREADS = Num(integer=True, ge=1, null=True)


def lookup(c: Mapping[str, Any], key: str) -> Any:
    """The value at dotted ``key`` ('' is ``c`` itself), or ``MISSING``."""
    node: Any = c
    parts = key.split(".") if key else []
    for i, part in enumerate(parts):
        if not isinstance(node, Mapping):
            where = ".".join(parts[:i])
            raise ConfigError(f"{where}: must be a mapping, got {show(node)}")
        node = node.get(part, MISSING)
        if node is MISSING:
            break
    return node


def _nodes(keys: Iterable[str]) -> dict[str, list[str]]:
    """Each node that holds table keys ('' is the root) -> the keys it may hold."""
    nodes: dict[str, list[str]] = {}
    for key in keys:
        parts = key.split(".")
        for i in range(len(parts)):
            valid = nodes.setdefault(".".join(parts[:i]), [])
            if parts[i] not in valid:
                valid.append(parts[i])
    return nodes


def check_table(c: Mapping[str, Any], rules: Mapping[str, Rule]) -> None:
    """Apply the table ``rules`` to the resolved config ``c``, in table order, then refuse the
    keys no rule names; raises :class:`ConfigError` at the first problem."""
    for key, rule in rules.items():
        value = lookup(c, key)
        if value is MISSING:
            if isinstance(rule, Opt):
                continue
            raise ConfigError(f"{key}: missing; the config must set it")
        if value == "???":
            raise ConfigError(f"{key}: missing (???); give {key}=...")
        problem = rule(value)
        if problem:
            raise ConfigError(f"{key}: {problem}")
    for node, valid in _nodes(rules).items():
        found = lookup(c, node)
        if not isinstance(found, Mapping):
            continue
        for key in found:
            if key not in valid:
                where = f"{node}.{key}" if node else str(key)
                raise ConfigError(f"{where}: unknown key; valid: {', '.join(valid)}")


def keyword_parameters(fn: Callable[..., Any]) -> dict[str, inspect.Parameter]:
    """The named parameters of ``fn`` (of a class: its ``__init__``'s, and its bases' as long
    as each passes ``**kwargs`` on), in order."""
    out: dict[str, inspect.Parameter] = {}
    for target in fn.__mro__ if inspect.isclass(fn) else (fn,):
        init = target.__init__ if inspect.isclass(fn) else target
        if init is object.__init__:
            break
        params = inspect.signature(init).parameters.values()
        for p in params:
            if p.name != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
                out.setdefault(p.name, p)
        if not any(p.kind == p.VAR_KEYWORD for p in params):
            break
    return out
