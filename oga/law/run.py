"""Programs in, a certified gain law out: the library's entry point of :mod:`oga.law`."""

from __future__ import annotations

from collections.abc import Callable

from feedplan.path import Path
from oga import defaults
from oga.errors import OptionError
from oga.law.law import check_kind
from oga.law.override import check_overrides, plan_override
from oga.law.search import LawResult, Program, search_law
from oga.model.machine import Machine
from oga.search.robust.plants import ScenarioSet

__all__ = ["law_optimize"]


def law_optimize(
    paths: list[tuple[str, Path]],
    machine: Machine,
    kind: str = "lincurve",
    points: int | None = None,
    *,
    overrides=defaults.LAW_OVERRIDES,
    tol_m: float = defaults.TOL_M,
    scenarios: ScenarioSet | None = None,
    threads: int | None = None,
    progress: Callable[[float], None] | None = None,
) -> LawResult:
    """One gain law for every program of ``paths``, searched and certified at every feed
    override on ``machine``'s uncertainty set (:func:`oga.law.search.search_law`).

    Parameters
    ----------
    paths : list of (str, Path)
        Each program's name and parsed toolpath.
    machine : Machine
        With an uncertainty set (the law is certified on it).
    kind : {"mac", "pl", "lincurve", "lincurve-sa"}
    points : int, optional
        Support points per input (default per kind).
    overrides : sequence of float
        Feed overrides (shares), 1.0 among them; default 0.5, 0.8, 1.0, 1.2.
    tol_m : float
        Path tolerance of the plans, m.
    scenarios : ScenarioSet, optional
    threads : int, optional
        Threads of the robust baselines' search (default: the available cores).
    progress : callable, optional
        Called with the fraction done (planning: the first 10 %).

    Returns
    -------
    LawResult

    Raises
    ------
    OptionError
        Bad kind, points or overrides (named as the CLI's flags), no program, or a machine
        without an uncertainty set.
    """
    check_kind(kind, points)
    overrides = check_overrides(overrides)
    if not paths:
        raise OptionError("programs: a law needs at least one program")
    if not any(ax.uncertainty is not None for ax in machine.axes.values()):
        raise OptionError(f"--machine: {machine.name!r} has no uncertainty set; a law is "
                          "certified on one (add [axes.*.uncertainty], or oga identify)")
    names = [n for n, _ in paths]
    if len(set(names)) != len(names):
        raise OptionError(f"programs: each program once (got {names})")
    report = progress or (lambda f: None)
    programs, total, done = [], len(paths) * len(overrides), 0
    for name, path in paths:
        sps = {}
        for o in overrides:
            sps[o] = plan_override(path, machine, o, tol_m)
            done += 1
            report(0.1 * done / total)
        programs.append(Program(name, sps))
    return search_law(programs, machine, kind, points, scenarios=scenarios, threads=threads,
                      progress=lambda f: report(0.1 + 0.9 * f))
