"""The two gain-table controllers of the comparison: ``fixed`` and ``oga``.

Both are the machine's own P + feed-forward position loop with a table of gains
(no firmware access): ``fixed`` the best equal fixed gains of the toolpath
(:func:`oga.search.ranges.gain_ranges`), ``oga`` the schedule exported by
:func:`oga.optimize.optimize` (the baseline's fixed gains when the search did not
beat them), both as replayed by :func:`oga.verify.verify` / :func:`oga.model.response.simulate`.
"""

from __future__ import annotations

import numpy as np

from feedplan.setpoints import Setpoints
from oga.controllers.base import ControllerRun, best_fixed, check_parameters
from oga.errors import OptionError
from oga.model.machine import Machine
from oga.options import OptimizeOptions

__all__ = ["FIXED_PARAMETERS", "OGA_PARAMETERS", "run_fixed", "run_oga"]

FIXED_PARAMETERS = ("kp_m_min_per_mm", "kf")
#: The options of :func:`oga.optimize.optimize` (feed and tolerance belong to the planning).
OGA_PARAMETERS = tuple(f for f in OptimizeOptions.model_fields
                       if f not in ("feed_mm_per_min", "tolerance_mm"))


def _no_load(name: str, load_n) -> None:
    if load_n is not None:
        raise OptionError(f"{name}: load_n is not supported (a gain table is replayed by "
                          "oga.model.response.simulate, which has no load input)")


def run_fixed(setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True,
              **parameters) -> ControllerRun:
    """The best equal fixed gains (Kp, Kf) of the toolpath, or the gains given.

    ``tune`` has no effect: the best fixed gains are this controller's definition
    (themselves the result of a grid over Kp and Kf on the toolpath).

    Raises
    ------
    OptionError
        Unknown parameter, a load given, or no fixed gains meet the limits.
    """
    from oga.model.response import simulate

    check_parameters("fixed", parameters, FIXED_PARAMETERS)
    _no_load("fixed", load_n)
    kp, kf = parameters.get("kp_m_min_per_mm"), parameters.get("kf")
    notes = ()
    if kp is None or kf is None:
        best = best_fixed(setpoints, machine)
        kp = next(iter(best.kp.values())) if kp is None else kp
        kf = next(iter(best.kf.values())) if kf is None else kf
        notes = ("the best equal fixed gains on this toolpath (oga.search.ranges.gain_ranges)",)
    sim = simulate(setpoints, machine, kp, kf)
    return ControllerRun(name="fixed", pos=sim.pos, u=sim.u, needs_firmware=False,
                         parameters={"kp_m_min_per_mm": float(kp), "kf": float(kf)},
                         notes=notes)


def run_oga(setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True,
            **parameters) -> ControllerRun:
    """The exported schedule of :func:`oga.optimize.optimize`, as its verification replayed it.

    ``parameters`` are the optimisation options (:data:`OGA_PARAMETERS`); ``tune`` has
    no effect (the search is the tuning). The search is nominal unless ``nominal=False``
    is given: the controllers are compared on the nominal model, against the nominal best
    fixed gains (``oga optimize`` searches robustly where the machine has an uncertainty set).

    Raises
    ------
    OptionError
        Unknown or invalid option, a load given, or no feasible baseline.
    """
    from oga.optimize import optimize

    check_parameters("oga", parameters, OGA_PARAMETERS)
    _no_load("oga", load_n)
    res = optimize(setpoints, machine, {"nominal": True, **parameters})
    kp, kf = res.schedule.kp_m_min_per_mm, res.schedule.kf
    moving = list(setpoints.moving_axes)
    notes = [f"options: mode {res.options.mode}, gains {','.join(res.options.gains)}, "
             f"adjusted axes {','.join(res.adjusted)}"]
    if res.kept_baseline:
        notes.append("the search did not beat the baseline: the table is the baseline's "
                     "fixed gains")
    if res.status != "ok":
        notes.append("verification failed: " + "; ".join(res.optimized.violations))
    params = {
        "mode": res.options.mode,
        "baseline_kp_m_min_per_mm": res.baseline_kp,
        "baseline_kf": res.baseline_kf,
        "kp_m_min_per_mm_range": [float(np.min(kp[:, moving])), float(np.max(kp[:, moving]))],
        "kf_range": [float(np.min(kf[:, moving])), float(np.max(kf[:, moving]))],
        "kept_baseline": res.kept_baseline,
        "search_time_s": res.optimize_time_s,
    }
    return ControllerRun(name="oga", pos=res.optimized.pos, u=res.optimized.u,
                         needs_firmware=False, parameters=params, notes=tuple(notes))
