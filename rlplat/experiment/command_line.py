"""The command lines of the Hydra entry points (``train.py``, ``evaluate.py``, ``export.py``,
``python -m rlplat.scenarios``): checked before Hydra starts, so that a mistake is one line."""

from __future__ import annotations

import difflib
import functools
import itertools
import math
import os
import re
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import open_dict

from rlplat.cli import exit_on_error
from rlplat.errors import ConfigError, RlplatError
from rlplat.experiment.config import CONF_DIR, compose_config, group_options, natural
from rlplat.io import check_writable_dir

T = TypeVar("T")


def hydra_main(
    config_name: str,
    validate: Callable[[Any], None] | None = None,
    validate_job: Callable[[Any, Path | None, str], None] | None = None,
    resume_subdir: str | None = None,
) -> Callable[[Callable[[Any], T]], Callable[..., T | None]]:
    """``@hydra.main`` on ``conf/<config_name>.yaml``, whose bad command lines are one line.

    Before Hydra starts, the command line's overrides are composed here, once for each job of
    a ``-m`` sweep, and each composed config is checked with ``validate``: an unknown key, an
    option a group does not have, an override Hydra cannot parse or a value ``validate``
    refuses ends the program with one line on stderr and exit code 2, before Hydra makes a
    run directory or starts the first job. The function's own :class:`RlplatError` is one
    line too (:func:`exit_on_error`). ``HYDRA_FULL_ERROR=1`` shows Hydra's own report.

    ``validate_job(cfg, job_dir, field)`` checks a job against the directory Hydra will make
    for it (``hydra.run.dir``, or a sweep's ``hydra.sweep.dir``/``subdir``, named by
    ``field``; a ``${now:...}`` name resolves to the time of the check, a fresh directory;
    None where the name is not known before Hydra starts, e.g. past the jobs checked one by
    one). ``resume_subdir``: with ``resume=true`` on the command line, Hydra writes its record
    of the job there (``hydra.output_subdir``), leaving the run's own ``.hydra/`` as it was
    launched."""

    def decorate(fn: Callable[[Any], T]) -> Callable[..., T | None]:
        import hydra

        run = hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base="1.3")(
            exit_on_error(fn)
        )

        @functools.wraps(fn)
        def entry(cfg_passthrough: Any = None) -> T | None:
            if cfg_passthrough is not None:  # called with a composed config, as hydra.main allows
                return run(cfg_passthrough)
            if os.environ.get("HYDRA_FULL_ERROR") != "1":  # as Hydra reads it
                try:
                    check_command_line(config_name, sys.argv[1:], validate, validate_job)
                except RlplatError as e:
                    print(f"error: {e}", file=sys.stderr)
                    sys.exit(2)
                except Exception:  # noqa: BLE001 - not ours to word: Hydra reports it, as before
                    pass
            if resume_subdir is not None and _resumes(sys.argv[1:]):
                # The run's .hydra/ stays as it was launched (what aggregate names a variant
                # by); the resume's own goes beside it.
                # Beside the other overrides: Hydra reads them as one run of arguments, and
                # right after a flag (`--cfg job`) it would be read as the flag's value.
                at = next(i for i, a in enumerate(sys.argv[1:], 1) if _is_override(a))
                sys.argv.insert(at, f"hydra.output_subdir={resume_subdir}")
            return run()

        return entry

    return decorate


def _is_override(arg: str) -> bool:
    """Whether a command-line argument is an override (``key=value``), not a flag or a flag's
    value."""
    return not arg.startswith("-") and "=" in arg


def _resumes(argv: Sequence[str]) -> bool:
    """Whether a command line resumes a run (and sets no ``hydra.output_subdir`` itself)."""
    keys = {a.split("=", 1)[0].lstrip("+") for a in argv}
    return "resume=true" in {a.lower() for a in argv} and "hydra.output_subdir" not in keys


#: Sweeps of more jobs than this are checked one swept value at a time (the others at their first).
MAX_CHECKED_JOBS = 64


def check_command_line(
    config_name: str,
    argv: Sequence[str],
    validate: Callable[[Any], None] | None = None,
    validate_job: Callable[[Any, Path | None, str], None] | None = None,
) -> None:
    """Compose ``conf/<config_name>.yaml`` with the overrides of a command line (each job of
    a ``-m`` sweep, or of ``hydra.mode=MULTIRUN``) and check each config with ``validate``
    (not with ``--cfg``, which shows a config as it is). A ``glob(...)`` or interval sweep is
    left to Hydra, and Hydra's own questions (``--help``, ``--info``, another config) too.

    Raises:
        ConfigError: one line naming the override, and the valid keys or options.
    """
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import ValueType
    from hydra.errors import OverrideParseException

    args, unknown = get_args_parser().parse_known_args(list(argv))
    if unknown:  # Hydra's parser would print its usage, then this
        raise ConfigError(
            f"{unknown[0]}: not an option of this command; overrides are KEY=VALUE (see --help)"
            if unknown[0].startswith("-")
            else f"{unknown[0]}: the overrides go together, all before or all after the flags"
        )
    modes = [flag for flag, on in (("--run", args.run), ("--multirun", args.multirun),
             ("--cfg", args.cfg), ("--info", args.info),
             ("--shell-completion", args.shell_completion)) if on]  # fmt: skip
    if len(modes) > 1:  # Hydra's refusal of these is a traceback
        raise ConfigError(f"{' '.join(modes)}: one of them at a time (see --help)")
    if any(
        getattr(args, flag, None)
        for flag in (
            "help",
            "hydra_help",
            "info",
            "shell_completion",
            "config_path",
            "config_name",
            "experimental_rerun",
        )  # fmt: skip
    ):
        return  # not a job of this config: Hydra answers these itself
    try:
        parsed = OverridesParser.create().parse_overrides(args.overrides)
    except OverrideParseException as e:
        raise ConfigError(f"{e.override}: {_one_line(e.message)}") from None
    extra: list[str] = []  # --config-dir DIR: its groups are composed as Hydra will
    if args.config_dir is not None:
        where = os.path.abspath(args.config_dir)
        if (
            not os.path.isdir(where)
            or "${" in where  # an interpolation inside the quoted override below
            or any(o.get_key_element() == "hydra.searchpath" for o in parsed)
        ):
            return  # a missing dir is Hydra's to refuse; a search path of its own too
        extra = [f"hydra.searchpath=[{_quoted(f'file://{where}')}]"]  # commas, brackets
    if args.cfg:
        validate = validate_job = None  # show the config, however incomplete; keys still count
    cluster = any(  # conf/hydra/launcher/cluster.yaml submits with SLURM's sbatch
        o.key_or_group == "hydra/launcher" and o.get_value_element_as_str() == "cluster"
        for o in parsed
    )
    if cluster and not args.cfg and shutil.which("sbatch") is None:
        raise ConfigError(
            "hydra/launcher=cluster: submits the jobs to SLURM, and this machine has no "
            "sbatch (hydra/launcher=basic or joblib run them here)"
        )
    multirun = args.multirun or any(
        o.key_or_group == "hydra.mode" and o.get_value_element_as_str() == "MULTIRUN"
        for o in parsed
    )
    interval = next((o for o in parsed if o.value_type == ValueType.INTERVAL_SWEEP), None)
    sweeper = any(o.key_or_group == "hydra/sweeper" for o in parsed)  # one that may sample
    if multirun and interval is not None and not sweeper:  # the basic one's refusal: a traceback
        raise ConfigError(
            f"{interval.input_line}: an interval is sampled by an optimising sweeper; the basic "
            "sweeper here runs lists, range(...) and glob(...) of a config group"
        )
    if not multirun:
        jobs = [list(args.overrides)]
    elif any(
        o.value_type == ValueType.GLOB_CHOICE_SWEEP and group_options(o.key_or_group) is None
        for o in parsed
    ):
        return  # a glob over a group that is not ours (Hydra's plugins): the sweeper expands it
    else:
        jobs = _sweep_jobs(parsed)
    exact = not multirun or math.prod(
        len(_swept_values(o)) if o.is_sweep_override() else 1 for o in parsed
    ) == len(jobs)  # fmt: skip
    swept = {o.get_key_element() for o in parsed if o.is_sweep_override()}
    field = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    dirs: dict[Path, str] = {}  # each job's directory, and the job that has it
    outs: dict[Path, str] = {}  # each tool job's out_dir, and the job that writes there
    for num, overrides in enumerate(jobs):
        cfg = _compose(config_name, [*overrides, *extra])
        job_dir = _job_dir(cfg, multirun, num if exact else None)
        job = " ".join(o for o in overrides if o.split("=", 1)[0] in swept)
        out = _out_dir(cfg) if multirun and job_dir is not None else None
        with open_dict(cfg):
            del cfg["hydra"]
        try:
            if job_dir is not None and validate_job is not None:  # a job that writes there
                check_writable_dir(job_dir, field)
            if validate is not None:
                validate(cfg)
            if validate_job is not None:
                validate_job(cfg, job_dir, field)
        except RlplatError as e:
            if not swept:
                raise
            raise type(e)(f"{e} (in the sweep's job {job})") from None
        if job_dir is not None and multirun and validate_job is not None:
            other = dirs.setdefault(job_dir.resolve(), job)
            if other != job:  # Hydra would write the second's record into the first's run
                raise ConfigError(
                    f"hydra.sweep.subdir: the sweep's jobs {other} and {job} share the directory "
                    f"{job_dir}; a subdir that tells every job apart (the default, "
                    "${hydra.job.num}) gives each its own"
                )
        if out is not None:
            other = outs.setdefault(Path(str(out)).resolve(), job)
            if other != job:  # the second job's files would replace the first's
                raise ConfigError(
                    f"out_dir: the sweep's jobs {other} and {job} both write to {out}; give "
                    "each its own (e.g. out_dir=DIR/${hydra:job.num}), or none"
                )


def _job_dir(cfg: Any, multirun: bool, num: int | None) -> Path | None:
    """The directory Hydra makes for a job (``num``: its number in a sweep, None: unknown),
    or None where it cannot be named before Hydra starts."""
    from omegaconf.errors import OmegaConfBaseException

    try:
        if not multirun:
            if not str(cfg.hydra.run.dir).strip():  # Path("") is the current directory
                raise ConfigError(
                    "hydra.run.dir: empty, which would write the run into the current "
                    "directory; name a directory"
                )
            return Path(str(cfg.hydra.run.dir))
        if num is None:
            return None
        with open_dict(cfg):
            cfg.hydra.job.num = num
        return Path(str(cfg.hydra.sweep.dir)) / str(cfg.hydra.sweep.subdir)
    except OmegaConfBaseException:
        return None


def _out_dir(cfg: Any) -> str | None:
    """Where a tool's job writes (its ``out_dir``, resolved as in the job), if it names one;
    None for a folder of evaluations (``evaluate.py compare=true``: one per split and policy)."""
    from omegaconf.errors import OmegaConfBaseException

    try:
        if cfg.get("compare"):
            return None
        out = cfg.get("out_dir")
    except OmegaConfBaseException:  # interpolates what only the job knows
        return None
    return None if out is None else str(out)


def _sweep_jobs(parsed: Sequence[Any]) -> list[list[str]]:
    """The override lists of a ``-m`` sweep's jobs, as Hydra's basic sweeper makes them (every
    combination); past :data:`MAX_CHECKED_JOBS`, each swept value once with the others' first."""
    choices: dict[str, list[str]] = {}
    for o in parsed:
        key = o.get_key_element()
        if o.is_sweep_override():
            choices[key] = [f"{key}={v}" for v in _swept_values(o)]
        else:
            value = o.get_value_element_as_str()
            choices[key] = [key if value is None else f"{key}={value}"]
    lists = list(choices.values())
    if math.prod(len(v) for v in lists) <= MAX_CHECKED_JOBS:
        return [list(job) for job in itertools.product(*lists)]
    first = [v[0] for v in lists]
    return [first[:i] + [value] + first[i + 1 :] for i, v in enumerate(lists) for value in v]


def _swept_values(o: Any) -> list[str]:
    """A sweep override's values: a glob's as Hydra expands it, on the group's options."""
    from hydra.core.override_parser.types import ValueType

    if o.value_type == ValueType.GLOB_CHOICE_SWEEP:
        return list(o.value().filter(group_options(o.key_or_group)))
    return list(o.sweep_string_iterator())


def _compose(config_name: str, overrides: list[str]) -> Any:
    """The job's config, its ``hydra`` node included; Hydra's composition errors as one line."""
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import OmegaConfBaseException

    try:
        cfg = compose_config(config_name, overrides, hydra=True)
    except MissingConfigException as e:
        if not (e.missing_cfg_file and e.options is not None):
            raise ConfigError(_one_line(str(e))) from None
        group, _, name = e.missing_cfg_file.rpartition("/")
        options = ", ".join(sorted(e.options, key=natural))
        raise ConfigError(f"{group}={name}: no such option (valid: {options})") from None
    except HydraException as e:
        cause = e.__cause__
        if isinstance(cause, OmegaConfBaseException) and "not in struct" in str(cause):
            raise ConfigError(_unknown_key(cause)) from None
        if isinstance(cause, OmegaConfBaseException) and str(cause).strip():  # say why
            why = str(cause).strip().splitlines()[0]
            raise ConfigError(f"{_one_line(str(e))}: {why}") from None
        raise ConfigError(_one_line(str(e))) from None
    return cfg


def _unknown_key(cause: Any) -> str:
    """One line for a key no config has: the nearest keys of its node, or all of them."""
    from omegaconf import DictConfig

    key, parent = cause.full_key, cause.parent_node
    where = key.rpartition(".")[0]
    keys = [str(k) for k in parent if k != "hydra"] if isinstance(parent, DictConfig) else []
    if not keys:  # a value, not a node of settings
        return f"{key}: no such setting ({where or 'the config'} has none)"
    close = [f"{where}.{k}" if where else k for k in difflib.get_close_matches(cause.key, keys)]
    if close:
        hint = f"did you mean {' or '.join(close)}?"
    else:
        hint = f"{where or 'the config'} has {', '.join(keys)}"
    if key.startswith("hydra."):  # Hydra's own config takes new keys
        hint += f"; +{key}=VALUE adds one"
    return f"{key}: no such setting ({hint})"


def _quoted(text: str) -> str:
    """``text`` as a quoted value of Hydra's override grammar: a quote is escaped with a
    backslash, and backslashes are doubled only before a quote or the closing one."""
    body = re.sub(r"(\\+)(?='|$)", lambda m: m.group(1) * 2, text).replace("'", "\\'")
    return f"'{body}'"


def _one_line(text: str) -> str:
    """Hydra's message in one line: its lines joined, its pointers to the docs dropped."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return " ".join(ln for ln in lines if not ln.startswith(("See https://", "Config search path")))
