"""The whole job on plain inputs: toolpath text -> setpoints -> verified gain schedule.

Used by ``oga optimize``, ``oga batch`` and the REST workers, so every surface
runs exactly the same steps. A job's input may instead be setpoints another interpolator
produced (format ``setpoints-csv``, ``setpoints-halsampler``, ``setpoints-twincat``:
:mod:`oga.recorded`), optimised on as they are.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from feedplan.path import Path
from feedplan.read import read_toolpath
from feedplan.setpoints import Setpoints
from oga.model.machine import Machine
from oga.optimize import OptimizeResult, optimize
from oga.options import OptimizeOptions

if TYPE_CHECKING:
    from oga.recorded import RecordedSetpoints

__all__ = ["Job", "PLAN_SHARE", "SETPOINTS_PREFIX", "plan_toolpath", "read_program", "run_job",
           "stored_options", "toolpath_sha256"]

#: Input format of a job whose input is recorded setpoints: this prefix and the file's format
#: (``setpoints-csv``, ``setpoints-halsampler``, ``setpoints-twincat``).
SETPOINTS_PREFIX = "setpoints-"

#: Share of a job's progress fraction given to planning (measured: about a third of the time
#: of LinuxCNC's arcspiral goes to planning, the rest to the search).
PLAN_SHARE = 0.3


@dataclass(frozen=True, eq=False)
class Job:
    """A finished job: what went in and what came out.

    Attributes
    ----------
    path : Path or None
        The parsed toolpath (None for recorded setpoints).
    setpoints : Setpoints
        The planned (or recorded) motion.
    result : OptimizeResult
        The verified schedule (check ``result.status``).
    toolpath_sha256 : str
        Hash of the submitted text (the toolpath's, or the setpoints file's).
    recorded : RecordedSetpoints or None
        The recorded setpoints optimised on, and where they came from.
    """

    path: Path | None
    setpoints: Setpoints
    result: OptimizeResult
    toolpath_sha256: str
    recorded: RecordedSetpoints | None = None

    def summary(self) -> dict:
        """The summary JSON of ``oga optimize --summary`` (recorded setpoints: their file,
        format, SHA-256 and reading under ``setpoints_source``)."""
        out = self.result.summary(toolpath=self.setpoints.source if self.path is None
                                  else self.path.source, toolpath_sha256=self.toolpath_sha256)
        if self.recorded is not None:
            out["setpoints_source"] = dict(self.recorded.source)
        return out

    @property
    def warnings(self) -> tuple[str, ...]:
        """Non-fatal remarks of the reader and the planner."""
        return (*(self.path.warnings if self.path is not None else ()), *self.setpoints.warnings)


def stored_options(stored: dict, **overrides) -> tuple[OptimizeOptions, dict | None]:
    """A stored job's options (API, batch): the search options (``overrides`` given over the
    stored ones, as :func:`oga.options.options_from_dict` takes them), and the reading options
    of recorded setpoints (stored under ``setpoints``; None for a toolpath)."""
    from oga.options import options_from_dict

    rest = dict(stored)
    read = rest.pop("setpoints", None)
    return options_from_dict(rest, **overrides), read


def toolpath_sha256(text: str) -> str:
    """Hash of a toolpath's text (UTF-8, hex), as summaries and tables record it."""
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def read_program(text: str, fmt: str, machine: Machine, options: OptimizeOptions, *,
                 source: str = "") -> Path:
    """The path of a toolpath as the job reads it: G-code through ``options.reader``, with the
    machine's home positions and work offsets and ``options.tool_table``."""
    setup = machine.gcode_setup(options.tool_table) if fmt == "gcode" else None
    return read_toolpath(text, fmt, source=source, reader=options.reader, setup=setup)


def plan_toolpath(
    path: Path, machine: Machine, *, feed_m_s: float | None, tol_m: float, dt: float | None = None,
    progress: Callable[[float], None] | None = None,
) -> Setpoints:
    """Setpoints of ``path`` on ``machine``: planned within its planning limits.

    The interpolator keeps the machine's reserve (:meth:`Machine.planning_limits`) so that
    the position loop's velocity command can meet the full axis limits (paper eq. 2).
    ``dt`` defaults to the machine's Te; ``progress`` is called with the fraction planned.
    """
    from feedplan.plan import plan

    return plan(path, machine.planning_limits(), feed_m_s=feed_m_s, tol_m=tol_m,
                dt=machine.te if dt is None else dt, progress=progress)


def run_job(
    text: str,
    fmt: str,
    machine: Machine,
    options: OptimizeOptions,
    *,
    source: str = "",
    progress: Callable[[float], None] | None = None,
    setpoints_options: dict | None = None,
) -> Job:
    """Read, plan and optimise one toolpath (or optimise recorded setpoints).

    Parameters
    ----------
    text : str
        The toolpath (G-code, CSV or JSON text), or the setpoints file.
    fmt : {"gcode", "csv", "json"} or ``SETPOINTS_PREFIX`` + a setpoints format
        Its format.
    machine : Machine
        The machine.
    options : OptimizeOptions
        Search and planning options (feed override, tolerance).
    source : str
        Name of the program, for messages.
    progress : callable, optional
        Called with the fraction done (0..1): planning the first :data:`PLAN_SHARE`, then
        the search.
    setpoints_options : dict, optional
        Recorded setpoints: ``columns``, ``units``, ``error_previous_target`` of
        :func:`oga.recorded.read_setpoints`.

    Raises
    ------
    InputError
        Bad toolpath, options or machine (message names line/field).
    PlanError, OptimizeError
        Planning or search failed.
    """
    if fmt.startswith(SETPOINTS_PREFIX):
        from oga.recorded import read_setpoints

        if options.feed_m_s is not None:
            from oga.errors import OptionError

            raise OptionError("feed: recorded setpoints are optimised as recorded (their "
                              "interpolator applied its feeds); record them at the feed wanted")
        rec = read_setpoints(text, machine, fmt.removeprefix(SETPOINTS_PREFIX), source=source,
                             **(setpoints_options or {}))
        result = optimize(rec.setpoints, machine, options, progress=progress)
        return Job(path=None, setpoints=rec.setpoints, result=result,
                   toolpath_sha256=toolpath_sha256(text), recorded=rec)
    if setpoints_options:
        from oga.errors import OptionError

        raise OptionError("setpoints options apply to recorded setpoints only")
    path = read_program(text, fmt, machine, options, source=source)
    if progress is None:
        plan_progress = search_progress = None
    else:
        def plan_progress(f: float) -> None:
            progress(PLAN_SHARE * f)

        def search_progress(f: float) -> None:
            progress(PLAN_SHARE + (1.0 - PLAN_SHARE) * f)
    sp = plan_toolpath(path, machine, feed_m_s=options.feed_m_s, tol_m=options.tol_m,
                       progress=plan_progress)
    result = optimize(sp, machine, options, progress=search_progress)
    return Job(path=path, setpoints=sp, result=result, toolpath_sha256=toolpath_sha256(text))
