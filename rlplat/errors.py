"""Errors that rlplat reports to users as one line: before any work starts, or (a diverged
training run) as soon as the work cannot go on."""


class RlplatError(Exception):
    """Base of the errors that entry points turn into a one-line message and exit code 2."""


class ConfigError(RlplatError, ValueError):
    """A configuration value is invalid; the message names the field and the value."""


class ScenarioFileError(RlplatError):
    """A scenario set on disk is missing, truncated, edited or of another schema version."""


class ExportError(RlplatError):
    """An exported artifact does not compute what the network it came from computes."""


class DivergenceError(RlplatError, FloatingPointError):
    """A training run's losses or TD errors stopped being finite; the run stops at once."""
