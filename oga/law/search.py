"""The law search: support values optimised on the contour error of whole programs, at every
feed override, on several plants of the machine's set at once.

A **case** is one program planned at one feed override (:mod:`oga.law.override`). The
cost of a law is the weighted mean, over the cases and the searched plants, of the
replay's MSE(CE) over the baseline's (:mod:`oga.law.baseline`) on that plant and case (the
certificate's ratio; the nominal plant weighs :data:`oga.defaults.ROBUST_NOMINAL_WEIGHT`,
the others share the rest, every case alike), plus, on every searched plant and case whose
ratio is above :data:`oga.defaults.LAW_WORST_RATIO`, :data:`oga.defaults.LAW_WORST_WEIGHT`
times the excess squared (with the mean alone one searched plant stayed above its baseline:
helix_r20 at 50 % feed, worst 1.09-1.60 in every round, no law certified; with it, certified
in the fourth round). A law has a few dozen support values at
most, so the search is a Gauss-Newton sequential QP over the whole programs:

1. every case is replayed on every searched plant with the derivatives of its positions
   and velocity commands along every support value (one forward-mode pass per axis,
   :mod:`oga.law.gradient`), the contour error linearised around the replay;
2. the step minimises the Gauss-Newton model of the cost subject to: every support value
   inside its range (Kp inside the range stable on every plant of the set, Kf inside the
   machine's range: the law's gains are convex combinations of support values, so they
   stay inside at every sample), a trust region, and paper eq. 2 (and the following-error
   limit) linearised at the samples near a limit (:data:`oga.defaults.LAW_ROWS` local
   peaks per case, plant, axis and limit of ratio at least
   :data:`oga.defaults.LAW_ROW_SHARE`), solved exactly by the window search's dual
   active-set QP;
3. the exact line search replays every case on every searched plant (:func:`oga.model.simulate.
   simulate`, every sample) for the step scaled 1, 1/2, 1/4 and takes the first that lowers
   the cost and keeps eq. 2 and the following-error limit at every sample, each within
   ``max(reserve x limit, the baseline's own peak on that plant and case)`` (velocity at
   the full limit); the trust region grows after a full step and shrinks after none.

**Rounds** (:data:`oga.defaults.LAW_ROUNDS` at most), as the robust table's: the first
searches the nominal plant, each next one adds the plant of the set where the last law did
worst (the nominal plant and :data:`oga.defaults.ROBUST_ACTIVE` - 1 others at most), and
cuts the reserve (1 at first, as the robust table's) where the law breaks a limit that the
baseline keeps. Each round's law, rounded to its controller's resolution, is certified
(:mod:`oga.law.certificate`) on every case: first on a screen of the set (its 32 corners
and 8 Monte Carlo plants: a screen that fails proves the whole set fails), then on the
whole set; where it fails, its shrinks towards the baseline
(:data:`oga.defaults.LAW_ALPHAS`) are. The rounds stop at the first whose own law is
certified; of every certified law the one of least mean median ratio over the cases is
kept. If none is, the law is the baseline itself (a constant law: status ``"failed"``, with
the reason).

Why whole programs and not windows: a law's support values act on every sample at once, so
a receding window cannot commit them. Why derivatives: one tangent pass per case and plant
replaces ``2 x (support values)`` finite-difference replays per step; a derivative-free
search over full replays took 1-37 s per law on the short programs and 395 s on cncjs
(issue 34's measurement; ``bench/bench_law.py`` prints ours).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.model.contour import contour_error_of, path_index
from oga.errors import OptionError
from oga.law.baseline import joint_program_baseline, program_baseline
from oga.law.certificate import LawCertificate, certify_law
from oga.law.gradient import axis_tangent, ce_offsets, gauss_newton
from oga.law.law import (AxisLaw, Law, basis, check_kind, curve_basis, law_gains, quantized,
                         signed_acc, signed_support_points, support_points)
from oga.model.machine import Machine
from oga.model.metrics import track_max
from oga.search.window import _qp_active_set
from oga.parallel import resolve_threads
from oga.search.robust.baseline import BaselineResult, common_kp_range
from oga.verify.certificate import plant_bounds
from oga.search.robust.plants import ScenarioSet, perturbed_machine, scenario_set
from oga.model.response import simulate
from oga.verify.replay import command_ratios, ferror_ratios, verify

__all__ = ["Program", "LawResult", "search_law"]

_log = logging.getLogger(__name__)

#: Share of the allowed limits the linearised rows may use (the exact check uses 1): at a
#: peak already at its limit (the baseline's own, in a rapid), the linear model's error
#: alone broke the exact check by 0.3-1.6 % (reference_xz, mac law).
_LIN_MARGIN = 0.97
#: QP solves per step at most (rows the last solution's prediction breaks join each next one).
_QP_PASSES = 6
#: Coefficients of the k-th backward difference (commands before the start are zero).
_DIFF = ((1.0,), (1.0, -1.0), (1.0, -2.0, 1.0))


@dataclass(frozen=True, eq=False)
class Program:
    """One program of a law: its name and its setpoints at each feed override.

    Attributes
    ----------
    name : str
    setpoints : dict of float to Setpoints
        Per override (1.0 among them).
    """

    name: str
    setpoints: dict[float, Setpoints]


@dataclass(frozen=True, eq=False)
class LawResult:
    """What :func:`search_law` found.

    Attributes
    ----------
    status : {"ok", "failed"}
        ``"ok"``: the law is certified on every program at every override; ``"failed"``:
        ``law`` is the baseline (constant), ``reason`` says why.
    law : Law
        The law to export (rounded to its controller's resolution).
    certificate : LawCertificate
        The exported law's certificate (the searched law's when the baseline is kept; the
        baseline's own where no round's search moved off it).
    baselines : dict of str to BaselineResult
        The baseline the law is judged against, by program (module :mod:`oga.law.baseline`:
        its own for one program, the joint one for several).
    rounds : int
    reserve : float
        The kept round's limit reserve.
    active : tuple of str
        The plants the kept round searched on besides the nominal one.
    alpha : float
        Share of the searched law's departure from the baseline kept (1: no shrink; 0: the
        baseline kept).
    nominal_ratio : dict of (str, float) to float
        Per program and override, MSE(CE) of the law over the baseline's on the nominal plant.
    search_s, certify_s : float
        CPU time of the search and of the certificates (process time).
    iterations : int
        Gauss-Newton steps taken over all rounds.
    reason : str
        Why the baseline was kept ("" when ok).
    """

    status: str
    law: Law
    certificate: LawCertificate
    baselines: dict[str, BaselineResult]
    rounds: int
    reserve: float
    active: tuple[str, ...]
    alpha: float
    nominal_ratio: dict[tuple[str, float], float]
    search_s: float
    certify_s: float
    iterations: int
    reason: str = ""

    def summary(self) -> dict:
        """The result as the summary JSON holds it."""
        return {
            "status": self.status,
            "reason": self.reason,
            "law": self.law.summary(),
            "baselines": {p: {"kp_m_min_per_mm": b.kp, "kf": b.kf, "mse_m2": b.mse_m2}
                          for p, b in self.baselines.items()},
            "rounds": self.rounds,
            "reserve": self.reserve,
            "active": list(self.active),
            "alpha": self.alpha,
            "nominal_ratio": [{"program": p, "override": o, "ratio": r}
                              for (p, o), r in self.nominal_ratio.items()],
            "search_cpu_s": self.search_s,
            "certify_cpu_s": self.certify_s,
            "iterations": self.iterations,
            "certificate": self.certificate.summary(),
        }


@dataclass(eq=False)
class _Case:
    """One program at one override, with what the search reuses."""

    program: str
    override: float
    sp: Setpoints
    base: BaselineResult
    moving: tuple[int, ...]
    feed: np.ndarray
    index: tuple
    weights: dict[int, tuple[np.ndarray, np.ndarray]]  # axis -> (W_kp, W_kf)
    base_replays: dict[int, object] = field(default_factory=dict)  # plant key -> Verification


class _Layout:
    """The parameter vector: per law axis, its Kp support values then its Kf ones."""

    def __init__(self, kind, axes: dict[str, AxisLaw]):
        self.kind, self.axes = kind, axes
        self.cols, self.kp_cols, self.kf_cols, start = {}, {}, {}, 0
        for a, ax in axes.items():
            nkp, nkf = ax.kp_m_min_per_mm.size, ax.kf.size
            i = AXES.index(a)
            self.cols[i] = slice(start, start + nkp + nkf)
            self.kp_cols[i] = slice(start, start + nkp)
            self.kf_cols[i] = slice(start + nkp, start + nkp + nkf)
            start += nkp + nkf
        self.n = start

    def law(self, theta: np.ndarray, fixed_kp: dict, fixed_kf: dict) -> Law:
        axes = {}
        for a, ax in self.axes.items():
            i = AXES.index(a)
            axes[a] = AxisLaw(v_m_s=ax.v_m_s, a_m_s2=ax.a_m_s2,
                              kp_m_min_per_mm=theta[self.kp_cols[i]].reshape(
                                  ax.kp_m_min_per_mm.shape).copy(),
                              kf=theta[self.kf_cols[i]].reshape(ax.kf.shape).copy())
        return Law(kind=self.kind, axes=axes, fixed_kp=dict(fixed_kp), fixed_kf=dict(fixed_kf))

    def constant(self, kp: float, kf: float) -> np.ndarray:
        """The parameters of the constant law ``(kp, kf)`` on every axis."""
        out = np.empty(self.n)
        for i in self.cols:
            out[self.kp_cols[i]], out[self.kf_cols[i]] = kp, kf
        return out


def _law_shape(kind: str, n: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """(Kp table shape, Kf table shape) of a law of ``kind`` with ``n`` points per input."""
    if kind == "mac":
        return (n, n), (n, n)
    if kind == "pl":
        return (1, n), (1, 1)
    return (1, n), (1, n)


def _start_law(kind, n, programs, law_axes, kp0, kf0, fixed_kp, fixed_kf) -> Law:
    """The constant law ``(kp0, kf0)`` on support points placed over every program's
    feed samples at every override (:func:`oga.law.law.support_points`)."""
    kp_shape, kf_shape = _law_shape(kind, n)
    axes = {}
    for a in law_axes:
        i = AXES.index(a)
        sps = [sp for p in programs for sp in p.setpoints.values()]
        vs = [np.abs(sp.vel[~sp.rapid, i]) for sp in sps]
        v = support_points(vs, n, positive=(kind == "pl"))
        if kind == "mac":
            acc = support_points([np.abs(sp.acc[~sp.rapid, i]) for sp in sps], n)
        elif kind == "lincurve-sa":
            acc = signed_support_points([sp.acc[~sp.rapid, i] for sp in sps], n)
        else:
            acc = np.zeros(1)
        axes[a] = AxisLaw(v_m_s=v, a_m_s2=acc, kp_m_min_per_mm=np.full(kp_shape, kp0),
                          kf=np.full(kf_shape, kf0))
    return Law(kind=kind, axes=axes, fixed_kp=fixed_kp, fixed_kf=fixed_kf)


class _Plants:
    """The nominal plant (key -1) and the set's plants (keys 0..P-1)."""

    def __init__(self, machine: Machine, scenarios: ScenarioSet):
        self.nominal = perturbed_machine(machine, {}, 0, machine.name)
        self.scenarios = scenarios

    def __getitem__(self, key: int) -> Machine:
        return self.nominal if key < 0 else self.scenarios.plants[key]

    def label(self, key: int) -> str:
        return "nominal" if key < 0 else self.scenarios.labels[key]


def search_law(
    programs: list[Program],
    machine: Machine,
    kind: str = "lincurve",
    points: int | None = None,
    *,
    scenarios: ScenarioSet | None = None,
    baselines: dict[str, BaselineResult] | None = None,
    threads: int | None = None,
    progress: Callable[[float], None] | None = None,
) -> LawResult:
    """One law for ``programs`` at all their overrides, robust over ``machine``'s set
    (module doc).

    Parameters
    ----------
    programs : list of Program
        Each with its setpoints at every override (the same overrides for all).
    machine : Machine
        With an uncertainty set.
    kind : {"mac", "pl", "lincurve", "lincurve-sa"}
    points : int, optional
        Support points per input (default per kind, :data:`oga.defaults.LAW_POINTS`).
    scenarios : ScenarioSet, optional
        Default :func:`oga.search.robust.plants.scenario_set` of ``machine``.
    baselines : dict of str to BaselineResult, optional
        The programs' robust baseline when already found, by program (several programs:
        their joint one, :func:`oga.law.baseline.joint_program_baseline`, the same gains
        for every program).
    threads : int, optional
        Threads of the baselines' search (default: the available cores; the result does
        not depend on it).
    progress : callable, optional
        Called with the fraction done (0..1).

    Returns
    -------
    LawResult

    Raises
    ------
    OptionError
        Bad kind or points, no program, programs at different overrides, no axis moving,
        or no robust baseline (the robust search's message).
    """
    t_start = time.process_time()
    report = progress or (lambda f: None)
    ctx, theta0, baselines = _context(programs, machine, kind, points, scenarios, baselines,
                                      resolve_threads(threads))
    report(0.1)
    run = _Rounds(search_s=time.process_time() - t_start)
    _search_rounds(run, ctx, theta0, machine, ctx.plants.scenarios, report)
    status, reason, alpha, law, cert, reserve_kept, active_kept = _chosen(run, ctx, theta0)
    report(1.0)
    return LawResult(status=status, law=law, certificate=cert, baselines=baselines,
                     rounds=run.rounds, reserve=reserve_kept,
                     active=tuple(ctx.plants.label(i) for i in active_kept), alpha=alpha,
                     nominal_ratio=_nominal_ratios(ctx, law), search_s=run.search_s,
                     certify_s=run.certify_s, iterations=run.iterations, reason=reason)


def _context(programs, machine, kind, points, scenarios, baselines, threads):
    """``(context, start, baselines)``: the search's cases, plants and layout
    (:class:`_Context`), the start's support values (of the programs' baselines, the constant
    law that keeps the limits, then of least cost, on the nominal plant) and every program's
    robust baseline."""
    n_pts = check_kind(kind, points)
    overrides = _check_programs(programs)
    if scenarios is None:
        scenarios = scenario_set(machine)
    plants = _Plants(machine, scenarios)
    baselines, bounds_of, moving_all = _baselines(programs, machine, scenarios,
                                                  dict(baselines or {}), threads)
    law_axes = tuple(AXES[i] for i in sorted(moving_all))
    (kp_lo, kp_hi), (kf_lo, kf_hi) = (_common_range(programs, machine, scenarios, bounds_of),
                                      machine.gains.kf_range)
    first = baselines[programs[0].name]
    fixed_kp = {a: first.kp for a in AXES if a not in law_axes}
    fixed_kf = {a: first.kf for a in AXES if a not in law_axes}
    # support points over every case; the start: of the programs' baselines, the constant
    # law that keeps the limits (then of least cost) on the nominal plant
    start_law = _start_law(kind, n_pts, programs, law_axes, first.kp, first.kf,
                           fixed_kp, fixed_kf)
    layout = _Layout(kind, start_law.axes)
    cases = _cases(programs, overrides, law_axes, start_law, baselines)
    lo, hi = layout.constant(kp_lo, kf_lo), layout.constant(kp_hi, kf_hi)
    ctx = _Context(cases, plants, layout, lo, hi, fixed_kp, fixed_kf, bounds_of)
    theta0 = min((layout.constant(b.kp, b.kf) for b in baselines.values()),
                 key=ctx.start_key)
    return ctx, theta0, baselines


def _chosen(run: _Rounds, ctx: "_Context", theta0):
    """``(status, reason, alpha, law, certificate, reserve, active)``: of the certified laws,
    the least mean median ratio over the cases; none: the start law, failed, with the first
    failed certificate."""
    if run.certified:
        _m, _r, alpha, law, cert, reserve, active = min(run.certified, key=lambda t: t[0])
        return "ok", "", alpha, law, cert, reserve, active
    law = quantized(ctx.layout.law(theta0, ctx.fixed_kp, ctx.fixed_kf))
    reasons = list(run.first_failed.reasons)
    if run.stalled:
        reasons.append(f"round {run.rounds}'s search stayed at the baseline (no step lowered "
                       "the cost within the limits on the searched plants)")
    return ("failed", "; ".join(reasons), 0.0, law, run.first_failed, run.reserve,
            tuple(run.active))


def _nominal_ratios(ctx: "_Context", law: Law) -> dict[tuple[str, float], float]:
    """The law's MSE over the baseline's on the nominal plant, per (program, override)."""
    out = {}
    for c in ctx.cases:
        kp, kf = law_gains(law, c.sp)
        out[(c.program, c.override)] = ctx.exact(c, -1, kp, kf)[0] / ctx.base_mse(c, -1)
    return out


def _common_range(programs, machine, scenarios, bounds_of) -> tuple[float, float]:
    """The Kp range (lo, hi) common to every program's plants."""
    ranges = [common_kp_range(machine, bounds_of[p.name],
                              tuple(AXES[i] for i in p.setpoints[1.0].moving_axes))
              for p in programs]
    return max(r[0] for r in ranges), min(r[1] for r in ranges)


def _check_programs(programs: list[Program]) -> tuple[float, ...]:
    """The overrides common to every program (1.0 among them), else OptionError."""
    if not programs:
        raise OptionError("programs: a law needs at least one program")
    overrides = tuple(sorted(programs[0].setpoints))
    if any(tuple(sorted(p.setpoints)) != overrides for p in programs) or 1.0 not in overrides:
        raise OptionError("overrides: every program needs its setpoints at the same overrides, "
                          "1.0 among them")
    return overrides


def _baselines(programs, machine, scenarios, baselines: dict, threads):
    """``(baselines, bounds_of, moving_all)``: the programs' robust baseline (one program: its
    own; several: their joint one, :func:`oga.law.baseline.joint_program_baseline`), searched
    unless given in ``baselines``, each program's plants' bounds, and the axes any program
    moves."""
    moving_of = {}
    for p in programs:
        moving = tuple(AXES[i] for i in p.setpoints[1.0].moving_axes)
        if not moving:
            raise OptionError(f"{p.name}: no axis moves; nothing to adapt")
        moving_of[p.name] = moving
    union = tuple(a for a in AXES if any(a in m for m in moving_of.values()))
    bounds = plant_bounds(scenarios, union, threads)
    bounds_of = {name: tuple({a: b[a] for a in m} for b in bounds)
                 for name, m in moving_of.items()}
    missing = [p for p in programs if p.name not in baselines]
    if len(programs) == 1 and missing:
        p = programs[0]
        baselines[p.name] = program_baseline(p.name, p.setpoints[1.0], machine, scenarios,
                                             bounds_of[p.name], threads=threads)
    elif missing:
        if len(missing) < len(programs):
            raise OptionError(f"baselines: given for some programs, not for "
                              f"{', '.join(p.name for p in missing)} (one law for several "
                              "programs is judged against their joint baseline: give it for "
                              "all or none)")
        baselines.update(joint_program_baseline({p.name: p.setpoints[1.0] for p in programs},
                                                machine, scenarios, bounds, threads=threads))
    if len({(baselines[p.name].kp, baselines[p.name].kf) for p in programs}) > 1:
        raise OptionError("baselines: one law for several programs is judged against their "
                          "joint baseline (the same fixed gains on every program: "
                          "oga.law.baseline.joint_program_baseline); these differ")
    moving_all = {AXES.index(a) for a in union}
    return baselines, bounds_of, moving_all


def _cases(programs, overrides, law_axes, start_law: Law, baselines) -> list[_Case]:
    """One case per program and override: its setpoints, baseline, and the law's basis
    weights of its moving law axes."""
    cases: list[_Case] = []
    for p in programs:
        for o in overrides:
            sp = p.setpoints[o]
            w = {}
            for a in law_axes:
                i = AXES.index(a)
                if i not in sp.moving_axes:
                    continue
                ax = start_law.axes[a]
                w[i] = (basis(ax, ax.kp_m_min_per_mm.shape, sp.vel[:, i], sp.acc[:, i]),
                        curve_basis(ax.a_m_s2, signed_acc(sp.vel[:, i], sp.acc[:, i]))
                        if start_law.kind == "lincurve-sa" else
                        basis(ax, ax.kf.shape, sp.vel[:, i], sp.acc[:, i]))
            base = baselines[p.name]
            case = _Case(program=p.name, override=o, sp=sp, base=base,
                         moving=tuple(sp.moving_axes), feed=sp.counted,
                         index=path_index(np.ascontiguousarray(sp.pos), defaults.CE_WINDOW_SAMPLES),
                         weights=w)
            if o == 1.0:
                case.base_replays.update(enumerate(base.replays))
                case.base_replays[-1] = base.nominal
            cases.append(case)
    return cases


@dataclass
class _Rounds:
    """The state of the search's rounds (:func:`_search_rounds`)."""

    search_s: float
    certify_s: float = 0.0
    iterations: int = 0
    rounds: int = 0
    reserve: float = 1.0  # the rounds' limit reserve starts where the robust table's does
    active: list = field(default_factory=list)
    certified: list = field(default_factory=list)  # (mean median, round, alpha, law, cert,
    #                                                reserve, active)
    first_failed: object = None
    stalled: bool = False  # a round's search stayed at the baseline (the rounds ended)


def _search_rounds(run: _Rounds, ctx: "_Context", theta0, machine, scenarios, report) -> None:
    """Search and certify round by round (``run`` updated): each round's law, else its
    shrinks towards ``theta0``, certified on the whole set; a round that fails adds limit
    reserve and the worst plant to the active ones."""
    # the first round searches the nominal plant and the first Monte Carlo plants (typical
    # ones: the nominal plant alone is not the set's median plant)
    run.active = list(range(min(defaults.LAW_TYPICAL_PLANTS, scenarios.n_monte_carlo)))
    layout, fixed_kp, fixed_kf = ctx.layout, ctx.fixed_kp, ctx.fixed_kf
    info = [(c.program, c.override, c.sp, c.base, c.base_replays, ctx.bounds_of[c.program])
            for c in ctx.cases]
    base = quantized(layout.law(theta0, fixed_kp, fixed_kf))
    for rounds in range(1, defaults.LAW_ROUNDS + 1):
        run.rounds = rounds
        t0 = time.process_time()
        theta, its = ctx.search(theta0, (-1, *run.active), run.reserve)
        run.iterations += its
        t1 = time.process_time()
        run.search_s += t1 - t0
        cert, moved = None, False
        for a in (1.0, *defaults.LAW_ALPHAS):  # the round's law, else its shrinks
            law = quantized(layout.law(theta0 + a * (theta - theta0), fixed_kp, fixed_kf))
            if _same_law(law, base):  # the baseline itself is no law found (nor its shrinks)
                break
            c = certify_law(law, info, machine, scenarios)
            cert, moved = cert or c, True
            _log.debug("round %d, reserve %.4f, active %s, alpha %g: %s; %s", rounds,
                       run.reserve, run.active, a, c.status, "; ".join(
                           f"{p} {o:g} median {x.median:.4f} worst {x.worst:.4f} only "
                           f"{len(x.breaks('schedule-only'))}"
                           for (p, o), x in c.cases.items()))
            if c.status == "ok":
                run.certified.append((float(np.mean([x.median for x in c.cases.values()])),
                                      rounds, a, law, c, run.reserve, tuple(run.active)))
                break
        run.certify_s += time.process_time() - t1
        report(0.1 + 0.8 * rounds / defaults.LAW_ROUNDS)
        if not moved:  # the search stayed at the baseline: more rounds start from there too
            _log.debug("round %d: the law stayed at the baseline", rounds)
            run.stalled = True
            if run.first_failed is None and not run.certified:  # the exported law's figures
                run.first_failed = certify_law(base, info, machine, scenarios)
            break
        run.first_failed = run.first_failed or (cert if cert.status != "ok" else None)
        if cert.status == "ok":  # the round's own law certified: more plants only cost
            break
        only = cert.schedule_only_excess()
        if only > 1.0:  # more limit reserve
            run.reserve /= only * (1.0 + defaults.ROBUST_RESERVE_MARGIN * 2 ** (rounds - 1))
        worst = cert.worst_plants()
        new = next((i for i in worst if i not in run.active), None)
        if new is not None:
            run.active = (run.active + [new])[-(defaults.ROBUST_ACTIVE - 1):]


def _same_law(a: Law, b: Law) -> bool:
    """Whether two laws give the same gains (the same support values on every axis)."""
    return a.axes.keys() == b.axes.keys() and all(
        np.array_equal(a.axes[k].kp_m_min_per_mm, b.axes[k].kp_m_min_per_mm)
        and np.array_equal(a.axes[k].kf, b.axes[k].kf) for k in a.axes)


class _Context:
    """The cases, plants and parameter layout of one law search, and its steps."""

    def __init__(self, cases, plants, layout, lo, hi, fixed_kp, fixed_kf, bounds_of):
        self.cases, self.plants, self.layout = cases, plants, layout
        self.lo, self.hi = lo, hi
        self.fixed_kp, self.fixed_kf, self.bounds_of = fixed_kp, fixed_kf, bounds_of

    # --- the baseline on a plant, and the limits a law keeps there ---------------------
    def base_replay(self, case: _Case, key: int):
        if key not in case.base_replays:
            n = len(case.sp)
            moving = tuple(AXES[i] for i in case.moving)
            bnd = (self.bounds_of[case.program][key] if key >= 0 else
                   {a: (self.lo.min(), self.hi.max()) for a in moving})
            case.base_replays[key] = verify(case.sp, self.plants[key],
                                            np.full((n, 3), case.base.kp),
                                            np.full((n, 3), case.base.kf), bnd, series=False)
        return case.base_replays[key]

    def base_mse(self, case: _Case, key: int) -> float:
        return self.base_replay(case, key).metrics.mse_m2

    def allowed(self, case: _Case, key: int, reserve: float) -> tuple[np.ndarray, np.ndarray]:
        """The ratios (eq. 2 (3, 3), following error (3,)) a law may reach on this plant and
        case: ``max(share, the baseline's own)`` (share 1 for velocity, else ``reserve``)."""
        b = self.base_replay(case, key)
        share = np.array([1.0, reserve, reserve])[None, :]
        return (np.maximum(share, b.command_ratio),
                np.maximum(reserve, np.nan_to_num(b.ferror_ratio, nan=0.0)))

    # --- exact replay ---------------------------------------------------------------------
    def exact(self, case: _Case, key: int, kp: np.ndarray, kf: np.ndarray):
        """(MSE(CE) m^2, eq. 2 ratios (3, 3), following-error ratios (3,)) of a replay."""
        plant = self.plants[key]
        sim = simulate(case.sp, plant, kp, kf)
        ce = contour_error_of(case.sp, sim.pos)
        mse = float(np.mean(ce[case.feed] ** 2))
        fer = np.nan_to_num(ferror_ratios(track_max(case.sp.pos, sim.pos), plant), nan=0.0)
        return mse, command_ratios(sim.u, case.sp, plant), fer

    def weights(self, keys) -> dict[int, float]:
        n = len(keys)
        if n == 1:
            return {keys[0]: 1.0}
        w = {keys[0]: defaults.ROBUST_NOMINAL_WEIGHT}
        w.update({k: (1.0 - defaults.ROBUST_NOMINAL_WEIGHT) / (n - 1) for k in keys[1:]})
        return w

    def evaluate(self, theta, keys, reserve, stop_above=np.inf):
        """(cost, violation): the weighted mean ratio and the largest excess over the
        allowed ratios (0: feasible), over the cases and the plants ``keys``. Stops early
        once the violation exceeds ``stop_above``."""
        law = self.layout.law(theta, self.fixed_kp, self.fixed_kf)
        w = self.weights(keys)
        cost, viol = 0.0, 0.0
        for c in self.cases:
            kp, kf = law_gains(law, c.sp)
            for key in keys:
                mse, cr, fr = self.exact(c, key, kp, kf)
                acr, afr = self.allowed(c, key, reserve)
                ratio = mse / self.base_mse(c, key)
                cost += (w[key] * ratio + defaults.LAW_WORST_WEIGHT
                         * max(ratio - defaults.LAW_WORST_RATIO, 0.0) ** 2) / len(self.cases)
                viol = max(viol, float(np.max(cr / acr)) - 1.0, float(np.max(fr / afr)) - 1.0)
                if viol > stop_above:
                    return cost, viol
        return cost, max(viol, 0.0) if viol > 1e-9 else 0.0

    def start_key(self, theta) -> tuple:
        cost, viol = self.evaluate(theta, (-1,), 1.0)
        return (viol > 0.0, viol, cost)

    # --- one Gauss-Newton step ------------------------------------------------------------
    def linearise(self, theta, keys, reserve):
        """The QP of a step: Hessian, gradient, the linearised limits (:class:`_Check`) and
        the model's cost."""
        nv = self.layout.n
        law = self.layout.law(theta, self.fixed_kp, self.fixed_kf)
        w = self.weights(keys)
        h, g = np.zeros((nv, nv)), np.zeros(nv)
        checks = []
        cost = 0.0
        for c in self.cases:
            kp, kf = law_gains(law, c.sp)
            n = len(c.sp)
            te = c.sp.dt
            pd = np.ascontiguousarray(c.sp.pos)
            for key in keys:
                plant = self.plants[key]
                pos = pd.copy()
                sens, sens_u = {}, {}
                us = {}
                for i in c.moving:
                    if i not in c.weights:
                        continue
                    p, u, sp_, su = axis_tangent(plant, AXES[i], i, pd, c.sp.vel, kp[:, i],
                                                 kf[:, i], *c.weights[i])
                    pos[:, i] = p
                    sens[i], sens_u[i], us[i] = sp_, su, u
                dq, tang = np.empty((n, 3)), np.empty((n, 3))
                tree, win_lo, win_hi = c.index
                ce_offsets(pd, tree, win_lo, win_hi, c.feed, pos, dq, tang)
                hh, gg, ss = gauss_newton(dq, tang, c.feed, sens, self.layout.cols, nv)
                per = 1.0 / (int(c.feed.sum()) * self.base_mse(c, key))  # ratio per ss
                scale = w[key] / len(self.cases) * per
                h += 2.0 * scale * hh
                g += 2.0 * scale * gg
                cost += scale * ss
                _worst_penalty(h, g, ss * per, 2.0 * per * gg, 2.0 * per * hh,
                               1.0 / len(self.cases))
                acr, afr = self.allowed(c, key, reserve)
                lim = plant.axis_limits()
                flim = plant.ferror_limits()
                for i, u in us.items():
                    cols = self.layout.cols[i]
                    limits = (float(lim.vmax_m_s[i]), float(lim.amax_m_s2[i]) * te,
                              float(lim.jmax_m_s3[i]) * te * te)
                    checks.append(_Check(u, sens_u[i].astype(np.float32), cols,
                                         tuple(limits[k] * acr[i, k] for k in range(3)), nv))
                    if np.isfinite(flim[i]):
                        checks.append(_Check(pd[:, i] - pos[:, i], (-sens[i]).astype(np.float32),
                                             cols, (flim[i] * afr[i],), nv))
        return h, g, checks, cost

    def search(self, theta0, keys, reserve) -> tuple[np.ndarray, int]:
        """The Gauss-Newton SQP from ``theta0`` on the plants ``keys`` (module doc)."""
        theta = theta0.copy()
        cost, viol = self.evaluate(theta, keys, reserve)
        trust = self.layout.constant(*defaults.LAW_TRUST)
        its = 0
        qp = None
        for _ in range(defaults.LAW_ITERATIONS):
            if qp is None:  # a rejected step keeps its linearisation
                qp = self.linearise(theta, keys, reserve)
            h, g, checks, _model = qp
            d = _qp_step(h, g, checks, np.maximum(self.lo - theta, -trust),
                         np.minimum(self.hi - theta, trust))
            taken = None
            for s in (1.0, 0.5, 0.25):
                trial = np.clip(theta + s * d, self.lo, self.hi)
                c2, v2 = self.evaluate(trial, keys, reserve, stop_above=max(viol, 0.0))
                if (viol == 0.0 and v2 == 0.0 and c2 < cost) or (viol > 0.0 and v2 < viol):
                    taken = (s, trial, c2, v2)
                    break
            its += 1
            if taken is None:
                trust *= 0.25
                if trust.max() < 1e-4:
                    break
                continue
            s, trial, c2, v2 = taken
            qp = None
            gain = (cost - c2) / cost if viol == 0.0 else np.inf
            theta, cost, viol = trial, c2, v2
            trust *= 2.0 if s == 1.0 else 0.5
            trust = np.minimum(trust, 4.0 * self.layout.constant(*defaults.LAW_TRUST))
            if gain < defaults.LAW_STOP:
                break
        return theta, its



def _worst_penalty(h, g, ratio, grad, hess, share) -> None:
    """Add the Gauss-Newton model of ``share * LAW_WORST_WEIGHT * max(0, ratio -
    LAW_WORST_RATIO)^2`` at a plant and case whose ``ratio`` (its gradient and Hessian model
    ``grad``, ``hess``) is above :data:`oga.defaults.LAW_WORST_RATIO` to ``h`` and ``g`` (in
    place); below it the term is flat (the line search's exact cost has it where a step
    crosses)."""
    excess = ratio - defaults.LAW_WORST_RATIO
    if excess <= 0.0:
        return
    mu = share * defaults.LAW_WORST_WEIGHT
    g += 2.0 * mu * excess * grad
    h += 2.0 * mu * (np.outer(grad, grad) + excess * hess)


@dataclass(eq=False)
class _Check:
    """One linearised limit of one case, plant and axis: ``|D^k (val + mat d)| <= limits[k]``
    for ``k`` = 0, 1, 2 (the value, its first and second differences from rest: eq. 2's
    velocity, acceleration and jerk of the command, times Te^k), or the following error
    (one limit, ``k`` = 0 only). ``mat`` (N, D) float32 (rows are picked with it, the exact
    replay decides), ``cols`` the columns of ``d`` it acts on."""

    val: np.ndarray
    mat: np.ndarray
    cols: slice
    limits: tuple
    nv: int
    seen: set = field(default_factory=set)  # (limit, sample) rows already taken

    def rows(self, d: np.ndarray | None, rows, rlo, rhi) -> int:
        """Add the rows of the samples whose ratio, predicted at step ``d`` (None: now), is at
        least :data:`oga.defaults.LAW_ROW_SHARE` (:data:`oga.defaults.LAW_ROWS` per limit at
        most, largest first; in a jerk-limited phase every sample is near the peak, so none
        is left out for being next to a larger one), scaled to unit bounds within
        :data:`_LIN_MARGIN`. Returns how many rows were added."""
        val = self.val
        pred = val if d is None else val + self.mat @ d[self.cols].astype(np.float32)
        mat = None
        added = 0
        for k, limit in enumerate(self.limits):
            if k:
                val, pred = np.diff(val, prepend=0.0), np.diff(pred, prepend=0.0)
            r = np.abs(pred) / limit
            cand = np.flatnonzero(r >= (defaults.LAW_ROW_SHARE if d is None else _LIN_MARGIN))
            if cand.size == 0:
                continue
            cand = cand[np.argsort(-r[cand], kind="stable")[:defaults.LAW_ROWS]]
            for j in cand:
                if (k, j) in self.seen:
                    continue
                self.seen.add((k, j))
                if mat is None:
                    mat = self.mat.astype(np.float64)
                row = sum(c * mat[j - i] for i, c in enumerate(_DIFF[k]) if j - i >= 0)
                full = np.zeros(self.nv)
                full[self.cols] = row / limit
                rows.append(full)
                rlo.append(min(-_LIN_MARGIN - val[j] / limit, 0.0))
                rhi.append(max(_LIN_MARGIN - val[j] / limit, 0.0))
                added += 1
        return added


def _qp_step(h, g, checks, dlo, dhi) -> np.ndarray:
    """The step ``d`` minimising ``d'Hd/2 + g'd`` within ``dlo <= d <= dhi`` and the
    linearised limits: the rows near a limit now, then, solved again (a few times at most),
    those the last solution's prediction takes past :data:`_LIN_MARGIN` (a law's kinks,
    where its support points or ``|a| = 0`` are crossed, make jerk spikes of the command
    where the constant start had none)."""
    nv = len(g)
    ridge = 1e-9 * max(float(np.trace(h)) / nv, 1e-30)
    p = h + np.diag(ridge + 1e-6 * np.diag(h))
    rows, rlo, rhi = [], [], []
    for c in checks:
        c.seen.clear()
        c.rows(None, rows, rlo, rhi)
    x = np.zeros(nv)
    for _ in range(_QP_PASSES):
        a = np.vstack([np.eye(nv)] + ([np.array(rows)] if rows else []))
        lo = np.concatenate([dlo, np.array(rlo)])
        hi = np.concatenate([dhi, np.array(rhi)])
        m = a.shape[0]
        x = np.zeros(nv)
        _qp_active_set(p, g.copy(), np.ascontiguousarray(a), lo, hi, m,
                       np.zeros(m, dtype=np.int64), np.full(m, nv, dtype=np.int64), x)
        x = np.clip(x, dlo, dhi)
        if sum(c.rows(x, rows, rlo, rhi) for c in checks) == 0:
            break
    return x
