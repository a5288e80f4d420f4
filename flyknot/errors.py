"""One error family for everything flyknot raises on purpose.

Messages name the bad field and, where there is a finite set, list the valid choices.
"""

from __future__ import annotations

from collections.abc import Iterable


class FlyknotError(Exception):
    """Base class of every error flyknot raises on purpose."""


class ConfigError(FlyknotError, ValueError):
    """A parameter, scenario field or command-line value is invalid."""

    def __init__(self, field: str, problem: str, choices: Iterable[object] | None = None):
        self.field = field
        self.problem = problem
        self.choices = None if choices is None else list(choices)
        msg = f"{field}: {problem}"
        if self.choices is not None:
            msg += f" (valid choices: {', '.join(str(c) for c in self.choices)})"
        super().__init__(msg)

    def __reduce__(self):
        """Rebuild from the constructor's arguments (an error raised in a worker process)."""
        return (type(self), (self.field, self.problem, self.choices))


class CommandError(FlyknotError, ValueError):
    """A joint command is malformed (shape, NaN, rate, file format)."""


class RecordError(FlyknotError):
    """A trial record or demonstration file is malformed or incomplete."""


class SolverError(FlyknotError):
    """A numerical solver failed; ``status`` carries the solver's own status text."""

    def __init__(self, solver: str, status: str, detail: str = ""):
        self.solver = solver
        self.status = status
        msg = f"{solver} failed with status {status!r}"
        if detail:
            msg += f": {detail}"
        self.detail = detail
        super().__init__(msg)

    def __reduce__(self):
        """Rebuild from the constructor's arguments (an error raised in a worker process)."""
        return (type(self), (self.solver, self.status, self.detail))


class RenderError(FlyknotError):
    """No picture can be drawn here: no offscreen OpenGL context (EGL, OSMesa) to be had."""


class HardwareError(FlyknotError):
    """The real robot or motion capture refused or failed a request."""


def check_choice(field: str, value: object, choices: Iterable[object]) -> None:
    """Raise :class:`ConfigError` if ``value`` is not one of ``choices``."""
    choices = list(choices)
    if value not in choices:
        raise ConfigError(field, f"unknown value {value!r}", choices)


def check_positive(field: str, value: float) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a finite number > 0."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and value == value and 0 < value < float("inf")):
        raise ConfigError(field, f"must be a finite number > 0, got {value!r}")


def check_nonnegative(field: str, value: float) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a finite number >= 0."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and value == value and 0 <= value < float("inf")):
        raise ConfigError(field, f"must be a finite number >= 0, got {value!r}")


def check_share(field: str, value: float) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a number in [0, 1]."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and 0 <= value <= 1):
        raise ConfigError(field, f"must be a number in [0, 1], got {value!r}")


def check_int(field: str, value: object, minimum: int = 0) -> None:
    """Raise :class:`ConfigError` unless ``value`` is an integer (not a bool) >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(field, f"must be an integer >= {minimum}, got {value!r}")
