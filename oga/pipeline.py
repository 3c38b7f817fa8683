"""The whole job on plain inputs: toolpath text -> setpoints -> verified gain schedule.

Used by ``oga optimize``, ``oga batch`` and the REST workers, so every surface
runs exactly the same steps.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Callable

from feedplan.path import Path
from feedplan.read import read_toolpath
from feedplan.setpoints import Setpoints
from oga.machine import Machine
from oga.optimize import OptimizeResult, optimize
from oga.options import OptimizeOptions

__all__ = ["Job", "PLAN_SHARE", "plan_toolpath", "read_program", "run_job", "toolpath_sha256"]

#: Share of a job's progress fraction given to planning (measured: about a third of the time
#: of LinuxCNC's arcspiral goes to planning, the rest to the search).
PLAN_SHARE = 0.3


@dataclass(frozen=True, eq=False)
class Job:
    """A finished job: what went in and what came out.

    Attributes
    ----------
    path : Path
        The parsed toolpath.
    setpoints : Setpoints
        The planned motion.
    result : OptimizeResult
        The verified schedule (check ``result.status``).
    toolpath_sha256 : str
        Hash of the submitted toolpath text.
    """

    path: Path
    setpoints: Setpoints
    result: OptimizeResult
    toolpath_sha256: str

    def summary(self) -> dict:
        """The summary JSON of ``oga optimize --summary``."""
        return self.result.summary(toolpath=self.path.source, toolpath_sha256=self.toolpath_sha256)


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
) -> Job:
    """Read, plan and optimise one toolpath.

    Parameters
    ----------
    text : str
        The toolpath (G-code, CSV or JSON text).
    fmt : {"gcode", "csv", "json"}
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

    Raises
    ------
    InputError
        Bad toolpath, options or machine (message names line/field).
    PlanError, OptimizeError
        Planning or search failed.
    """
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
