"""The project's exception tree.

Every error a user can cause is an :class:`OgaError`; each also subclasses the
built-in it refines, so ``except ValueError`` keeps working for callers that do
not know the project. Backend exceptions (ruckig, scipy, numba, sqlite) are
wrapped in these, never leaked.
"""

from __future__ import annotations

__all__ = [
    "OgaError",
    "InputError",
    "GcodeError",
    "ToolpathError",
    "MachineError",
    "OptionError",
    "PlanError",
    "OptimizeError",
    "TuneError",
]


class OgaError(Exception):
    """Base class of every error raised by oga."""


class InputError(OgaError, ValueError):
    """Something a user submitted is invalid (exit code 2 at the CLI, 4xx at the API)."""


class GcodeError(InputError):
    """A G-code program cannot be read or is outside the supported dialect.

    Parameters
    ----------
    message : str
        What is wrong, without the location.
    line, column : int
        1-based line and column of the offending word in the program text.
    source : str, optional
        Name of the program (file name) for the message.
    """

    def __init__(self, message: str, line: int, column: int, source: str = "") -> None:
        self.message = message
        self.line = int(line)
        self.column = int(column)
        self.source = source
        where = f"{source}:" if source else "line "
        super().__init__(f"{where}{self.line}:{self.column}: {message}")


class ToolpathError(InputError):
    """A CSV/JSON polyline or a parsed path is invalid (row or field named in the message).

    Parameters
    ----------
    message : str
        What is wrong.
    line : int, optional
        1-based row or line of the input where it is wrong (0 when not applicable).
    column : int, optional
        1-based column, or 0.
    source : str, optional
        Name of the input (file name), put first in the message.
    """

    def __init__(self, message: str, line: int = 0, column: int = 0, source: str = "") -> None:
        self.message = message
        self.line = int(line)
        self.column = int(column)
        self.source = source
        at = (f"{line}:{column}" if column else f"{line}") if line else ""
        if source:
            where = f"{source}:{at}: " if at else f"{source}: "
        else:
            where = f"line {at}: " if at else ""
        super().__init__(f"{where}{message}")


class MachineError(InputError):
    """A machine description is invalid or unknown (the field is named in the message)."""


class OptionError(InputError):
    """An option is unknown, out of range or inconsistent (the option is named)."""


class PlanError(OgaError, RuntimeError):
    """The feed planner could not produce setpoints that meet every limit."""


class OptimizeError(OgaError, RuntimeError):
    """The gain search or its verification failed."""


class TuneError(OgaError, RuntimeError):
    """No setting of a comparison controller's tuning grid meets the axis limits (paper eq. 2)."""
