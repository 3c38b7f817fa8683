"""Prototype of the robust search: the existing search on a *design machine*, certified.

The nominal search (:func:`oga.optimize.optimize`) is run unchanged on a design machine:
the nominal dynamics, with

- the Kp bounds cut to the stable range common to every plant of the scenario set (the
  least ``kp_max`` and largest ``kp_min`` over the plants and the moving axes), so the
  stability bound holds on every plant;
- the acceleration and jerk limits (and any following-error limit) scaled by a reserve
  ``r <= 1``: a plant's velocity command differs from the nominal one, and the reserve
  is what the worst plant needs. ``r`` starts at 1 and, after each round, shrinks by the
  largest excess over 1 of a limit on any plant (the baseline's or the schedule's) and a
  margin that doubles each round (a fixed gain's excess is not linear in ``r``).

The baseline is the best equal fixed gains of the design machine
(:func:`oga.ranges.best_fixed_gains`), the reserve shrunk in rounds until they keep the
limits on every plant: the best equal gains (in nominal MSE) feasible and stable on every
plant of the set. The schedule is then searched from that baseline on the design machine
(more reserve while it breaks a limit on a plant where the baseline keeps it).

The nominal search fits the nominal friction glitch and dead time sharply; on a plant with
another dead time or a faster loop its pulses overshoot. The prototype therefore keeps a
share ``alpha`` of the schedule's departure from the baseline, ``K = Kb + alpha (Ks - Kb)``
(one share for Kp, one for Kf),
chosen on a small scenario set: the least median ratio over a few typical plants among the
shares whose worst ratio over the plants where the full schedule does worst stays within a
goal (the issue's 0.9), the set refreshed with the plants where the chosen one does worst on
the whole set. The result is certified on the whole set.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.errors import OptionError
from oga.machine import Machine, machine_from_dict
from oga.optimize import GainSchedule, OptimizeResult, optimize
from oga.ranges import best_fixed_gains
from oga.options import OptimizeOptions, options_from_dict
from oga.robust.certificate import Certificate, certify, plant_bounds
from oga.robust.plants import ScenarioSet, scenario_set
from oga.verify import verify

__all__ = ["RobustResult", "design_machine", "robust_optimize"]


@dataclass(frozen=True, eq=False)
class RobustResult:
    """What :func:`robust_optimize` found.

    Attributes
    ----------
    status : {"ok", "failed"}
        ``"ok"`` when the certificate of the shrunk schedule passed; otherwise the
        exported gains are the robust baseline's.
    schedule : GainSchedule
        The gains to export (the shrunk schedule, or the baseline's when failed).
    result : OptimizeResult
        The last search, on the design machine.
    certificate : Certificate
        The searched schedule against the robust baseline on the whole set.
    reserve : float
        The limit reserve ``r`` of the design machine.
    kp_max : float
        The Kp bound common to every plant, (m/min)/mm.
    rounds : int
        Searches run.
    alpha : (float, float)
        Shares of the searched schedule's departure from the baseline that are kept, Kp and Kf.
    """

    status: str
    schedule: GainSchedule
    result: OptimizeResult
    certificate: Certificate
    reserve: float
    kp_max: float
    rounds: int
    alpha: tuple[float, float]


def design_machine(machine: Machine, reserve: float, kp_bounds: tuple[float, float]) -> Machine:
    """``machine`` with acceleration, jerk and following-error limits times ``reserve`` and
    its configured Kp bounds cut to ``kp_bounds``; no uncertainty section."""
    data = machine.model_dump(mode="json", exclude_none=True)
    for ax in data["axes"].values():
        ax.pop("uncertainty", None)
        lim = ax["limits"]
        for k in ("amax_m_s2", "jmax_m_s3", "ferror_max_m"):
            if k in lim:
                lim[k] = lim[k] * reserve
    lo, hi = data["gains"]["kp_bounds_m_min_per_mm"]
    data["gains"]["kp_bounds_m_min_per_mm"] = [max(lo, kp_bounds[0]), min(hi, kp_bounds[1])]
    data["name"] = f"{machine.name}-design"
    return machine_from_dict(data, where="design machine")


def _excess(verifications) -> float:
    """Largest limit ratio (eq. 2 and following error) over some replays."""
    worst = 0.0
    for v in verifications:
        worst = max(worst, float(np.max(v.command_ratio)),
                    float(np.nanmax(np.append(v.ferror_ratio, 0.0))))
    return worst


def robust_optimize(
    setpoints: Setpoints,
    machine: Machine,
    options: OptimizeOptions | dict | None = None,
    scenarios: ScenarioSet | None = None,
) -> RobustResult:
    """The robust schedule of ``setpoints`` over ``machine``'s uncertainty set (module doc).

    Parameters
    ----------
    setpoints : Setpoints
    machine : Machine
        With an uncertainty section.
    options : OptimizeOptions or dict, optional
        Full-mode options; ``baseline`` is set by the robust search.
    scenarios : ScenarioSet, optional
        Default :func:`oga.robust.plants.scenario_set` of ``machine``.

    Returns
    -------
    RobustResult

    Raises
    ------
    OptionError
        No equal fixed gains keep the limits on every plant.
    """
    if not isinstance(options, OptimizeOptions):
        options = options_from_dict(options)
    if scenarios is None:
        scenarios = scenario_set(machine)
    moving = tuple(AXES[i] for i in setpoints.moving_axes)
    bounds = plant_bounds(scenarios, moving)
    kp_lo = max(b[a][0] for b in bounds for a in moving)
    kp_hi = min(b[a][1] for b in bounds for a in moving)
    n = len(setpoints)
    reserve, base = 1.0, None
    for k in range(defaults.ROBUST_ROUNDS):
        best = best_fixed_gains(setpoints, design_machine(machine, reserve, (kp_lo, kp_hi)))
        if best is None:
            break
        kp0, kf0 = float(best.kp[moving[0]]), float(best.kf[moving[0]])
        bkp, bkf = np.full((n, 3), kp0), np.full((n, 3), kf0)
        over = _excess(verify(setpoints, p, bkp, bkf, b)
                       for p, b in zip(scenarios.plants, bounds))
        if over <= 1.0:
            base = (kp0, kf0)
            break
        reserve /= over * (1.0 + defaults.ROBUST_RESERVE_MARGIN * 2**k)
    if base is None:
        raise OptionError("baseline: no equal fixed gains keep the limits on every plant "
                          "of the uncertainty set")
    bkp, bkf = np.full((n, 3), base[0]), np.full((n, 3), base[1])
    rounds = 0
    for rounds in range(1, defaults.ROBUST_ROUNDS + 1):
        design = design_machine(machine, reserve, (kp_lo, kp_hi))
        res = optimize(setpoints, design, options.model_copy(update={"baseline": base}))
        s = res.searched_schedule
        cert = certify(setpoints, machine, s.kp_m_min_per_mm, s.kf, bkp, bkf, scenarios, bounds)
        if not cert.breaks("schedule-only"):
            break
        reserve /= max(_excess(p.schedule for p in cert.plants), 1.0) * (
            1.0 + defaults.ROBUST_RESERVE_MARGIN * 2 ** (rounds - 1))
    alpha, cert = _shrink(setpoints, machine, res.searched_schedule, bkp, bkf, scenarios,
                          bounds, cert)
    ok = cert.status == "ok" and res.searched.ok
    kp, kf = _shrunk(res.searched_schedule, bkp, bkf, alpha) if ok else (bkp, bkf)
    return RobustResult(status="ok" if ok else "failed",
                        schedule=GainSchedule(kp_m_min_per_mm=kp, kf=kf), result=res,
                        certificate=cert,
                        reserve=reserve, kp_max=kp_hi, rounds=rounds, alpha=alpha)


def _subset(scenarios: ScenarioSet, bounds, keep) -> tuple[ScenarioSet, tuple]:
    keep = sorted(set(keep))
    return (ScenarioSet(status=scenarios.status, nominal=scenarios.nominal,
                        plants=tuple(scenarios.plants[i] for i in keep),
                        labels=tuple(scenarios.labels[i] for i in keep),
                        draws=tuple(scenarios.draws[i] for i in keep), seed=scenarios.seed,
                        n_monte_carlo=0, n_corners=0),
            tuple(bounds[i] for i in keep))


def _shrunk(schedule, bkp, bkf, alpha):
    a_kp, a_kf = alpha
    return bkp + a_kp * (schedule.kp_m_min_per_mm - bkp), bkf + a_kf * (schedule.kf - bkf)


def _shrink(setpoints, machine, schedule, bkp, bkf, scenarios, bounds, cert):
    """The schedule ``Kb + alpha (Ks - Kb)`` (``alpha`` one share for Kp, one for Kf, on
    :data:`oga.defaults.ROBUST_KP_ALPHAS` x :data:`oga.defaults.ROBUST_ALPHAS`), chosen on a
    small scenario set: the plants where the full schedule does worst (refreshed with those
    where the chosen one does worst on the whole set) and the first Monte Carlo plants (typical
    ones). Of the shares whose worst ratio on the worst plants is within
    :data:`oga.defaults.ROBUST_WORST_GOAL` (and break no check the baseline keeps), the one of
    least median ratio on the typical plants; if none, the one of least worst ratio. Then
    certified on the whole set. Returns (alpha, certificate)."""
    worst = [int(i) for i in np.argsort(cert.ratio)[::-1][:defaults.ROBUST_SUBSET]]
    typical = list(range(min(defaults.ROBUST_SUBSET, scenarios.n_monte_carlo)))
    best = ((1.0, 1.0), cert)
    for _ in range(defaults.ROBUST_ROUNDS):
        keep = sorted(set(worst) | set(typical))
        sub, sub_bounds = _subset(scenarios, bounds, keep)
        w_rows = [keep.index(i) for i in worst]
        t_rows = [keep.index(i) for i in typical] or w_rows
        trials = []
        for alpha in itertools.product(defaults.ROBUST_KP_ALPHAS, defaults.ROBUST_ALPHAS):
            c = certify(setpoints, machine, *_shrunk(schedule, bkp, bkf, alpha), bkp, bkf, sub,
                        sub_bounds)
            w = c.ratio[w_rows].max() if not c.breaks("schedule-only") else np.inf
            trials.append((w > defaults.ROBUST_WORST_GOAL,
                           w if w > defaults.ROBUST_WORST_GOAL else np.median(c.ratio[t_rows]),
                           alpha))
        alpha = min(trials)[2]
        full = certify(setpoints, machine, *_shrunk(schedule, bkp, bkf, alpha), bkp, bkf,
                       scenarios, bounds)
        if full.worst < best[1].worst or best[1].status != "ok":
            best = (alpha, full)
        if full.status == "ok":
            break
        more = [int(i) for i in np.argsort(full.ratio)[::-1][:defaults.ROBUST_SUBSET]]
        if set(more) <= set(worst):
            break
        worst += more
    return best
