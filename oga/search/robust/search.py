"""The robust search: a schedule searched on several plants of the uncertainty set at once.

1. **Kp range**: the stable range common to every plant of the scenario set and the
   nominal plant (the least ``kp_max``, the largest ``kp_min`` over them and the moving
   axes).
2. **Baseline** (:func:`oga.search.robust.baseline.robust_baseline`): the equal fixed gains of least
   geometric-mean MSE(CE) over the set's Monte Carlo plants among those that keep every
   plant's limits and stable range (checked on the plants themselves). Its replays on the
   set are kept: every certificate below reuses them.
3. **Rounds** (:data:`oga.defaults.ROBUST_ROUNDS` at most; on the set's first
   :data:`oga.defaults.ROBUST_SEARCH_PLANTS` Monte Carlo plants and its corners, the kept
   round's table then certified on the whole set) of the multi-scenario search
   (:func:`oga.search.robust.multi.multi_search`): the first on the nominal plant alone, each
   next one on the nominal plant and the plants of the set where the previous schedule
   did worst (the set refreshed round by round, :data:`oga.defaults.ROBUST_ACTIVE` plants
   at most, the oldest leaving; a round whose search collapsed after a plant joined, the
   median ratio more than doubled, is searched again once at a reserve cut by the margin
   (:func:`_retried`: the window search is bistable in the reserve), and where that
   collapses too the plant leaves for good), the acceleration, jerk and following-error
   limits times a reserve (1 at first), cut after a round whose schedule breaks a limit on
   a plant where the baseline keeps it (by the largest such excess, and a margin doubling
   per cut; floored on each searched plant near the baseline's own peak there, and sample
   by sample at its own command, :func:`oga.search.robust.multi.multi_search`). Each schedule
   is certified on those plants
   (:func:`oga.verify.certificate.certify`), the first round's on a screen first (the
   corners and typical plants: where it fails there, as the nominal plant's schedule
   does, the whole set's certificate would fail too, :class:`_Round`; the exported
   table's certificate is always the whole set's); the rounds stop at the first that breaks
   no such limit and meets the goals, from round :data:`oga.defaults.ROBUST_MIN_ROUNDS` on
   (an earlier one goes on as if it had broken a check, :func:`_next`) (:data:`oga.defaults.ROBUST_MEDIAN_GOAL`,
   ``ROBUST_P90_GOAL``, ``ROBUST_WORST_GOAL``: the issue's 0.3, 0.5, 0.9), or where the next
   round would search the same plants with the same limits (it would repeat this one, bit
   for bit: helix_r20 ran its third round three times; where that round is the best so far,
   fails on no plant and its limit ratio leaves room, it is first searched once more at its reserve raised by
   the margin, :func:`_stalls_best`); else the best round is kept
   (goals met first, then the fewest plants where it fails: worse than the baseline or
   breaking a check the baseline keeps, then the least worst ratio).
4. **Repair, shrink** (only when the kept schedule's certificate fails): every round's table
   that fails by breaks alone (no plant worse than the baseline) faded back to the baseline
   around the samples where it breaks (:mod:`oga.search.robust.repair`), the best repair that
   passes kept (:func:`_repaired_round`); where none passes, ``K = Kb + alpha (Ks - Kb)``,
   the largest share ``alpha`` (one for Kp and Kf) whose certificate passes, by bisection
   (:func:`_shrink`): it moves continuously with the machine. Where no share of the kept
   round's table passes, the other rounds' tables are shrunk in the rounds' order of
   preference, each different table once, until a share of one passes (:func:`_shrunk_round`).
   Where none does and no anchor was given, steps 3 and 4 run again at each of
   :data:`oga.defaults.ROBUST_ANCHOR_RETRY` (:func:`_searched`).
5. The table exported is the schedule when its certificate passes (worst ratio <= 1, no
   plant where it alone breaks a check) and its nominal replay passes; else the baseline.

Why rounds and not a set refreshed inside a run, why the mean, why a reserve: measured
in :mod:`oga.search.robust.multi`'s doc.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.errors import OptionError
from oga.model.machine import Machine
from oga.search.result import GainSchedule, OptimizeResult
from oga.options import OptimizeOptions, options_from_dict
from oga.parallel import resolve_threads
from oga.search.robust.baseline import BaselineResult, common_kp_range, robust_baseline
from oga.verify.certificate import Certificate, certify, plant_bounds
from oga.search.robust.multi import multi_search
from oga.search.robust.repair import repaired
from oga.search.robust.plants import ScenarioSet, perturbed_machine, scenario_set
from oga.verify.replay import verify

__all__ = ["RobustResult", "robust_optimize"]

_log = logging.getLogger(__name__)


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
        The search on the nominal machine: baseline and exported table replayed there
        (``searched_schedule`` is the exported one).
    certificate : Certificate
        The exported schedule (before the fall-back to the baseline) against the robust
        baseline on the whole set.
    reserve : float
        The limit reserve of the kept round's search.
    kp_max : float
        The Kp bound common to every plant, (m/min)/mm.
    rounds : int
        Searches run.
    alpha : (float, float)
        Shares of the searched schedule's departure from the baseline that are kept, Kp and Kf.
    baseline : BaselineResult
        The robust baseline (:func:`oga.search.robust.baseline.robust_baseline`).
    active : tuple of str
        Labels of the plants the kept round searched on besides the nominal one.
    """

    status: str
    schedule: GainSchedule
    result: OptimizeResult
    certificate: Certificate
    reserve: float
    kp_max: float
    rounds: int
    alpha: tuple[float, float]
    baseline: BaselineResult | None = None
    active: tuple = ()


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
    progress: Callable[[float], None] | None = None,
    threads: int | None = None,
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
        Default :func:`oga.search.robust.plants.scenario_set` of ``machine`` with ``options.certify``
        Monte Carlo plants.
    progress : callable, optional
        Called with the fraction done (0..1, never falling) after each replay or search step:
        the stable ranges, the baseline (:data:`PROGRESS_BASELINE`), then the rounds.
    threads : int, optional
        Threads for independent replays (default ``options.threads``, else the available
        cores); the result is the same for any count.

    Returns
    -------
    RobustResult

    Raises
    ------
    OptionError
        Not the full mode, or no equal fixed gains keep the limits on every plant.
    """
    t0 = time.perf_counter()
    if not isinstance(options, OptimizeOptions):
        options = options_from_dict(options)
    if options.mode != "full":
        raise OptionError(f"mode: the robust search is the full mode's (got {options.mode!r}); "
                          "the paper's search runs on the nominal model only (--nominal)")
    if scenarios is None:
        scenarios = scenario_set(machine, n=options.certify or defaults.ROBUST_MC_PLANTS)
    moving = tuple(AXES[i] for i in setpoints.moving_axes)
    if not moving:
        raise OptionError("toolpath: no axis moves; nothing to optimise")
    report = _Progress(progress)
    threads = resolve_threads(options.threads if threads is None else threads)
    bounds = plant_bounds(scenarios, moving, threads)
    kp_lo, kp_hi = common_kp_range(machine, bounds, moving)
    report(PROGRESS_BOUNDS)
    base = robust_baseline(setpoints, machine, scenarios, bounds, (kp_lo, kp_hi), threads=threads,
                           progress=report.between(PROGRESS_BOUNDS, PROGRESS_BASELINE))
    if not base.ok:
        raise OptionError(base.message)
    ctx = _Context.of(setpoints, machine, options, scenarios, bounds, base, (kp_lo, kp_hi),
                      threads)
    ctx, kept, rounds, alpha, cert = _searched(ctx, report)
    found = kept.found
    searched_schedule = GainSchedule(kp_m_min_per_mm=found.kp, kf=found.kf)
    result = _result(ctx, _shrunk(searched_schedule, ctx.bkp, ctx.bkf, alpha), cert, moving,
                     found, t0)
    return RobustResult(status="failed" if result.kept_baseline else "ok",
                        schedule=result.schedule, result=result, certificate=cert,
                        reserve=kept.reserve, kp_max=kp_hi, rounds=rounds, alpha=alpha,
                        baseline=base,
                        active=tuple(ctx.scenarios.labels[i] for i in kept.active))


@dataclass(frozen=True, eq=False)
class _Context:
    """What every round of :func:`robust_optimize` shares: the rounds search and judge on the
    set's first Monte Carlo plants and its corners (``scenarios``, ``bounds`` and the
    baseline's ``base_replays`` there, indices ``keep`` of the whole set ``full``); the kept
    table is certified on the whole set (module doc)."""

    setpoints: Setpoints
    machine: Machine
    options: OptimizeOptions
    nominal: Machine
    base: BaselineResult
    bkp: np.ndarray  # (N, 3) the baseline's gains, read-only
    bkf: np.ndarray
    kp_range: tuple[float, float]
    full: ScenarioSet
    full_bounds: tuple
    keep: list
    scenarios: ScenarioSet
    bounds: tuple
    base_replays: tuple
    threads: int

    @classmethod
    def of(cls, setpoints, machine, options, full, full_bounds, base, kp_range, threads):
        keep = _search_plants(full)
        scenarios, bounds = _subset(full, full_bounds, keep)
        n = len(setpoints)
        bkp, bkf = np.full((n, 3), base.kp), np.full((n, 3), base.kf)
        for arr in (bkp, bkf):
            arr.flags.writeable = False
        return cls(setpoints, machine, options, perturbed_machine(machine, {}, 0, machine.name),
                   base, bkp, bkf, kp_range, full, full_bounds, keep, scenarios, bounds,
                   tuple(base.replays[i] for i in keep), threads)

    def certify(self, found, keep, progress=None, schedule_replays=None) -> Certificate:
        """``found``'s certificate on the plants ``keep`` of the rounds' set."""
        if len(keep) == len(self.scenarios):
            sub, sub_bounds, sub_base = self.scenarios, self.bounds, self.base_replays
        else:
            sub, sub_bounds = _subset(self.scenarios, self.bounds, keep)
            sub_base = tuple(self.base_replays[i] for i in keep)
        return certify(self.setpoints, self.machine, found.kp, found.kf, self.bkp, self.bkf,
                       sub, sub_bounds, sub_base, schedule_replays=schedule_replays,
                       progress=progress, threads=self.threads)


def _rounds(ctx: _Context, report) -> tuple[_Round, int]:
    """The rounds (module doc, step 3): each searches (:func:`_search`), is certified
    (:func:`_judged`), and chooses the next round's plants and reserve (:func:`_next`).
    Returns the kept round (:func:`_kept`) and the rounds run."""
    active: list[int] = []  # plants of the set searched on besides the nominal one
    rejected: set[int] = set()  # plants whose joining made the schedule worse
    reserve, last, raised = 1.0, None, False
    tried: list[_Round] = []
    step = (PROGRESS_ROUNDS - PROGRESS_BASELINE) / defaults.ROBUST_ROUNDS
    for rounds in range(1, defaults.ROBUST_ROUNDS + 1):
        lo = PROGRESS_BASELINE + step * (rounds - 1)
        report(lo)
        found = _search(ctx, active, reserve)
        report(lo + 0.5 * step)
        done = _judged(ctx, found, active, reserve, last, report, (lo, step))
        _logged(rounds, done)
        if _collapsed(done, last):
            tried.append(done)
            done = _retried(ctx, done, last, rounds, report, (lo, step))
            reserve = done.reserve
        tried.append(done)
        met = done.key[:2] == (False, 0)  # goals met, no plant fails
        if met and rounds >= defaults.ROBUST_MIN_ROUNDS:
            break
        active, reserve = _next(done, last, active, rejected, reserve, rounds, met)
        last = done
        if (tuple(active), reserve) == (done.active, done.reserve):
            # the same plants and limits: the next round's search would repeat this one
            if raised or not _stalls_best(done, tried):
                break
            raised, reserve = True, reserve * (1.0 + defaults.ROBUST_RESERVE_MARGIN)
    return _kept(ctx, tried), rounds, tried


def _searched(ctx: _Context, report) -> tuple:
    """The rounds (:func:`_rounds`) and the shrink (:func:`_shrunk_round`) at the options'
    anchor; where no share of any round's table passes and the anchor is the default, the
    same again at each of :data:`oga.defaults.ROBUST_ANCHOR_RETRY` in turn, until one passes.
    Returns ``(context, kept round, rounds run, alpha, certificate)``: the context of the
    anchor kept (its options name it), else the default's.

    Why: a stronger anchor keeps the windows' gains nearer the baseline, so what the searched
    plants gain holds on the others; on most programs it costs median ratio (ucp710 at
    anchor 3000 against 30: helix_r20 0.502 against 0.331, circle_r50_f3000 0.530 against
    0.363), but where the default's tables fail on every share it can certify one:
    51MeanderAve's default keeps its baseline (worst 2.982), at 3000 median 0.261, p90 0.359,
    worst 0.436. Not monotone in between (300: worst 1.154, baseline kept), so one strong
    anchor, not a bisection."""
    retries = defaults.ROBUST_ANCHOR_RETRY if ctx.options.anchor is None else ()
    rounds, first = 0, None
    for run in [ctx] + [replace(ctx, options=ctx.options.model_copy(update={"anchor": a}))
                        for a in retries]:
        kept, n, tried = _rounds(run, report)
        report(PROGRESS_ROUNDS)
        kept, alpha, cert = _shrunk_round(run, kept, tried)
        rounds += n
        if cert.status == "ok":
            return run, kept, rounds, alpha, cert
        first = first or (run, kept, alpha, cert)
    run, kept, alpha, cert = first
    return run, kept, rounds, alpha, cert


def _shrunk_round(ctx: _Context, kept: _Round, tried) -> tuple:
    """The kept round's table where its certificate passes; else every round's table
    repaired (:func:`_repaired_round`), the best that passes; else the kept round's table
    shrunk (:func:`_shrink`), where no share of it passes the other rounds' tables in the
    rounds' order of preference (each different table once), until a share of one passes.
    Returns ``(round, alpha, certificate)``: the kept round, ``(0, 0)`` and its certificate
    where none passes.

    Why the other rounds: the rounds prefer a table that fails on fewer plants, not one that
    shrinks or repairs better. On plasmatest (ucp710) rounds 2-5 searched one table (the
    limit floor held their reserve, :func:`oga.search.robust.multi.multi_search`) that broke
    the jerk limit on 15 plants at every share; round 1's (nominal plant alone; 40 plants
    failing on its screen) passes at share 0.211: median 0.725, worst 0.847."""
    rounds = []
    for done in [kept] + sorted((r for r in tried if r is not kept), key=lambda r: r.key):
        if not _same_table(done, rounds):
            rounds.append(done)
    certs: dict[int, Certificate] = {}

    def cert_of(done: _Round) -> Certificate:  # on the whole set, once per round
        if id(done) not in certs:
            done.complete(ctx)
            certs[id(done)] = _certified_on_all(ctx, done)
        return certs[id(done)]

    if cert_of(kept).status == "ok":
        return kept, (1.0, 1.0), cert_of(kept)
    fixed = _repaired_round(ctx, rounds, cert_of)
    if fixed is not None:
        return fixed
    first = None
    for done in rounds:
        alpha, cert = _shrink(ctx.setpoints, ctx.machine,
                              GainSchedule(kp_m_min_per_mm=done.found.kp, kf=done.found.kf),
                              ctx.bkp, ctx.bkf, ctx.full, ctx.full_bounds, cert_of(done),
                              ctx.base.replays, ctx.threads)
        first = first or (done, alpha, cert)
        if cert.status == "ok":
            return done, alpha, cert
    return first


def _repaired_round(ctx: _Context, rounds, cert_of):
    """Every round's table (``rounds``; ``cert_of(round)`` its certificate on the whole set)
    repaired where it breaks a limit (:func:`oga.search.robust.repair.repaired`); the one of
    least key (goals missed, worst ratio) that passes, as ``(round, (1, 1), certificate)``,
    its ``found`` the repaired table; None where none passes. A round already worse than the
    baseline on a plant it was judged on is passed over uncertified (the repair refuses it)."""
    best = None
    for done in rounds:
        if done.cert.worst > 1.0:
            continue
        fix = repaired(ctx.setpoints, ctx.machine, (done.found.kp, done.found.kf),
                       (ctx.bkp, ctx.bkf), ctx.full, ctx.full_bounds, cert_of(done),
                       ctx.base.replays, ctx.threads)
        if fix is None:
            continue
        key = (not _meets_goals(fix[2]), fix[2].worst)
        if best is None or key < best[0]:
            best = (key, done, fix)
    if best is None:
        return None
    _, done, (kp, kf, cert) = best
    done.found = replace(done.found, kp=kp, kf=kf)
    return done, (1.0, 1.0), cert


def _same_table(done: _Round, seen) -> bool:
    """Whether a round of ``seen`` searched the same table as ``done``, bit for bit."""
    return any(np.array_equal(done.found.kp, o.found.kp)
               and np.array_equal(done.found.kf, o.found.kf) for o in seen)


def _stalls_best(done: _Round, tried) -> bool:
    """The rounds would stop at ``done`` (the next would repeat it), it is the best round so
    far, and its reserve was cut: it is searched once more on the same plants at its reserve
    raised by :data:`oga.defaults.ROBUST_RESERVE_MARGIN` (the first cut's margin), and the
    better of the two is kept.

    Why: a round's figures are steep and not monotone in the reserve (cncjs_toolpath on
    ucp710, round 2's plants: median 0.633 / 0.615 / 0.572 / 0.544 and worst 1.008 / 0.916 /
    0.776 / 0.721 at reserve 0.72 / 0.73 / 0.74 / 0.75), and the first cut follows round 1's
    peak on an unsearched corner, which a 1e-3 change of the machine moves by 3 %
    (Z's Kv x 1.001: 1.3425 against 1.3060, reserve 0.7303 against 0.7507). Where the next
    round adds a plant, its reserve is not probed again (ucp710's round 2 is kept there);
    where the rounds stalled, the table stayed at the reserve of that one peak (worst ratio
    0.917 against 0.717). Only where the round's largest limit ratio leaves room for the
    raise (at most ``1 / (1 + margin)``: cncjs 0.967): on helix_r20 (0.998) the raised round
    broke a limit, was cut back to 0.707 and two rounds were spent for the same table.
    And only where the round fails on no plant (more reserve makes the table bolder, not
    safer: circle_r50_f3000's round 4, failing on 2 plants, worst 1.206, gave 1.501 raised)."""
    room = _excess(p.schedule for p in done.cert.plants) * (1.0 + defaults.ROBUST_RESERVE_MARGIN)
    return (done.reserve < 1.0 and room <= 1.0 and done.key[1] == 0
            and min(tried, key=lambda r: r.key) is done)


def _logged(rounds, done) -> None:
    """Log a round's reserve, plants and certificate (debug level)."""
    if _log.isEnabledFor(logging.DEBUG):
        c = done.cert
        _log.debug("round %d: reserve %.4f, active %s, %s, median %.4f p90 %.4f worst %.4f, "
                   "failing %d, limit ratio %.4f", rounds, done.reserve, list(done.active),
                   "full" if done.full else "screen", c.median, c.p90, c.worst,
                   int(c.failures().sum()), _excess(p.schedule for p in c.plants))


def _collapsed(done, last) -> bool:
    """The round's search collapsed: a plant joined and the median ratio more than doubled."""
    return last is not None and bool(done.active) and _median_jump(done.ratio, last.ratio)


def _retried(ctx: _Context, done, last, rounds, report, span) -> _Round:
    """The round ``done`` whose search collapsed, searched again on the same plants at a
    reserve cut by the margin (as :func:`_next` cuts it); the retry where it did not
    collapse, else ``done``.

    Why: the multi-plant window search is bistable. Where a window lowers Kf on a
    stretch whose lag lies along the path (no contour error), raising it again at speed
    needs jerk the reserve no longer leaves, and Kf stays low for the rest of the program
    (measured on freeform_xz, round 3, nominal plant and two corners: from sample 1321 Kf
    0.78 -> 0.1, median ratio 5.5; at reserve 0.780 and 0.826 Kf stays 0.51-1, median
    0.196). Which reserves fall in that trap depends on the machine's fifth digit
    (0.793-0.817 there); dropping the joined plant after a collapse made the table jump
    (worst ratio 0.639 on ucp710, 0.742 on its Kv x 1.0001)."""
    lo, step = span
    reserve = done.reserve / (1.0 + defaults.ROBUST_RESERVE_MARGIN * 2 ** (rounds - 1))
    found = _search(ctx, list(done.active), reserve)
    again = _judged(ctx, found, done.active, reserve, last, report, (lo + 0.5 * step, 0.5 * step))
    _logged(rounds, again)
    return done if _collapsed(again, last) else again


def _search(ctx: _Context, active, reserve):
    """One round's multi-plant search: the nominal plant and the ``active`` ones."""
    return multi_search(ctx.setpoints,
                        (ctx.nominal,) + tuple(ctx.scenarios.plants[i] for i in active),
                        (ctx.base.nominal,) + tuple(ctx.base_replays[i] for i in active),
                        ctx.options, ctx.base.kp, ctx.base.kf, ctx.kp_range, reserve)


def _judged(ctx: _Context, found, active, reserve, last, report, span) -> _Round:
    """The round of ``found``, certified on its screen (:func:`_screen`) and, where it passes
    there, on the rounds' whole set."""
    lo, step = span
    done = _screened(ctx, found, active, reserve, _screen(ctx.scenarios, last),
                     report.between(lo + 0.5 * step, lo + 0.75 * step))
    if not done.fails_screen:
        done.complete(ctx, report.between(lo + 0.75 * step, lo + step))
    return done


def _screened(ctx: _Context, found, active, reserve, keep, progress=None) -> _Round:
    """The :class:`_Round` of ``found`` certified on the plants ``keep`` of the rounds' set."""
    return _Round(found, tuple(active), reserve, len(ctx.scenarios), keep,
                  ctx.certify(found, keep, progress))


def _next(done, last, active, rejected, reserve, rounds, met=False):
    """The next round's plants and reserve after ``done``: a plant whose joining doubled the
    median ratio leaves for good; the reserve is cut where the schedule alone broke a check,
    or where it met the goals before :data:`oga.defaults.ROBUST_MIN_ROUNDS` (``met``) as if
    it had broken one at a ratio of 1; the plant of largest ratio (not rejected) joins, the
    oldest leaving. Updates ``rejected``; returns ``(active, reserve)``.

    Why ``met`` cuts: whether such a round breaks a check on a plant is decided by the
    machine's fifth digit (freeform_xz's round 2: largest limit ratio 0.89-1.045 over
    machines 1e-4 apart), and the next round must not depend on it (on ucp710 it stopped
    there, median 0.179, worst 0.732; on X's Kv x 1.0001 it broke, and round 3 gave median
    0.117, worst 0.455)."""
    ratio = done.ratio
    active = list(active)
    if _collapsed(done, last):
        # the plant that joined last made the typical plants much worse, also at the
        # retry's reserve (:func:`_retried`): it leaves for good
        rejected.add(active.pop())
    only = [p for p in done.cert.plants if p.schedule_only_break]
    if only or met:  # more limit reserve (the prototype's rule for the baseline)
        over = max(_excess(p.schedule for p in only), 1.0)
        reserve /= over * (1.0 + defaults.ROBUST_RESERVE_MARGIN * 2 ** (rounds - 1))
    order = [int(i) for i in np.argsort(-np.nan_to_num(ratio, nan=-np.inf), kind="stable")]
    worst = next((i for i in order if i not in rejected and not np.isnan(ratio[i])), None)
    if worst is not None and worst not in active:  # the worst plant joins the search
        active = (active + [worst])[-(defaults.ROBUST_ACTIVE - 1):]
    return active, reserve


def _kept(ctx: _Context, tried) -> _Round:
    """The best round (the first of the least key), certified on the rounds' whole set."""
    while True:
        kept = min(tried, key=lambda r: r.key)
        if kept.full:
            return kept
        kept.complete(ctx)


def _certified_on_all(ctx: _Context, kept: _Round) -> Certificate:
    """The kept round's certificate on the whole set, the rounds' replays reused."""
    if len(ctx.keep) == len(ctx.full):
        return kept.cert
    return certify(ctx.setpoints, ctx.machine, kept.found.kp, kept.found.kf, ctx.bkp, ctx.bkf,
                   ctx.full, ctx.full_bounds, ctx.base.replays,
                   schedule_replays={ctx.keep[j]: p.schedule
                                     for j, p in enumerate(kept.cert.plants)},
                   threads=ctx.threads)


def _result(ctx: _Context, gains, cert, moving, found, t0) -> OptimizeResult:
    """The :class:`OptimizeResult` of the shrunk schedule ``gains`` (Kp, Kf) with its
    certificate ``cert``: the schedule where its certificate and its replay on the machine
    itself pass, else the baseline."""
    setpoints, machine, options = ctx.setpoints, ctx.machine, ctx.options
    kp, kf = gains
    kp_bounds = {a: ctx.kp_range for a in moving}
    # the result's nominal figures on the machine itself: the exact kernel (the plants, the
    # nominal one included, take the linear friction map at standstill: oga.search.robust.plants)
    searched = verify(setpoints, machine, kp, kf, kp_bounds)
    base_exact = verify(setpoints, machine, ctx.bkp, ctx.bkf, kp_bounds)
    ok = cert.status == "ok" and searched.ok
    if not ok:
        kp, kf = ctx.bkp, ctx.bkf
    return OptimizeResult(
        status=searched.status if ok else base_exact.status,
        setpoints=setpoints, machine=machine, options=options,
        schedule=GainSchedule(kp_m_min_per_mm=kp, kf=kf),
        baseline_kp={a: ctx.base.kp for a in AXES}, baseline_kf={a: ctx.base.kf for a in AXES},
        baseline=base_exact, optimized=searched if ok else base_exact,
        searched_schedule=GainSchedule(kp_m_min_per_mm=_frozen(kp), kf=_frozen(kf)),
        searched=searched, kept_baseline=not ok,
        adjusted=moving if options.adjust is None else tuple(options.adjust),
        kp_bounds=kp_bounds, optimize_time_s=time.perf_counter() - t0,
        fallbacks=found.fallbacks, windows=found.windows,
    )


#: Progress fractions at the end of the stable ranges, of the baseline and of the rounds
#: (the shrink and the final replay take the rest).
PROGRESS_BOUNDS, PROGRESS_BASELINE, PROGRESS_ROUNDS = 0.05, 0.35, 0.95


class _Progress:
    """A progress callback that never falls (or does nothing without one)."""

    def __init__(self, callback: Callable[[float], None] | None):
        self._callback, self._done = callback, 0.0

    def __call__(self, fraction: float) -> None:
        if self._callback is not None and fraction > self._done:
            self._done = min(fraction, 1.0)
            self._callback(self._done)

    def between(self, lo: float, hi: float) -> Callable[[float], None]:
        """A callback mapping 0..1 onto ``lo..hi`` of this one."""
        return lambda f: self(lo + (hi - lo) * f)


class _Round:
    """One round: its search, and its certificate on a screen of the plants or, once
    :meth:`complete`, on the whole set.

    A screen stands for the whole set only where it fails: its worst ratio above
    :data:`oga.defaults.ROBUST_WORST_GOAL` or a plant where the schedule alone breaks a check
    (the whole set's worst ratio and breaks are at least the screen's), so such a round
    is not the last; any other is certified on the whole set before it is judged.

    Attributes
    ----------
    found : MultiSearch
    active : tuple of int
        The plants searched on besides the nominal one.
    reserve : float
        The round's limit reserve.
    keep : tuple of int
        The plants of the set ``cert`` replayed (all of them once ``full``).
    cert : Certificate
        On those plants.
    full : bool
        ``cert`` is on the whole set.
    """

    def __init__(self, found, active, reserve, n_plants, keep, cert):
        self.found, self.active, self.reserve = found, active, reserve
        self.n_plants, self.keep, self.cert = n_plants, keep, cert
        self.full = len(keep) == n_plants

    @property
    def fails_screen(self) -> bool:
        """A goal or check missed on the plants replayed (so on the whole set)."""
        return self.cert.worst > defaults.ROBUST_WORST_GOAL or bool(
            self.cert.breaks("schedule-only"))

    @property
    def key(self) -> tuple:
        """Goals missed, plants where the schedule fails (worse than the baseline, or a check
        broken that the baseline keeps), worst ratio (a screen's: goals missed, the rest a
        lower bound of the whole set's). Counting the failing plants, not only the breaks: a
        round whose line search collapsed (median 5.1, worst 36.5, no break) was kept over one
        of median 0.89 with 5 breaks, and no share of it passed."""
        missed = not self.full or not _meets_goals(self.cert)
        return (missed, int(self.cert.failures().sum()), self.cert.worst)

    @property
    def ratio(self) -> np.ndarray:
        """The ratio per plant of the set, shape (P,) (``nan`` where not replayed)."""
        out = np.full(self.n_plants, np.nan)
        out[list(self.keep)] = self.cert.ratio
        return out

    def complete(self, ctx: _Context, progress=None) -> None:
        """Certify on the rounds' whole set, the screen's replays reused."""
        if self.full:
            return
        self.cert = ctx.certify(self.found, range(self.n_plants), progress,
                                {i: p.schedule for i, p in zip(self.keep, self.cert.plants)})
        self.keep, self.full = tuple(range(self.n_plants)), True


def _screen(scenarios: ScenarioSet, last: _Round | None) -> tuple[int, ...]:
    """The plants a round's schedule is screened on: in the first round (the nominal plant's
    search: it fails on the set's extremes) the corners and the first
    :data:`oga.defaults.ROBUST_SUBSET` Monte Carlo plants (typical ones); later, every plant.

    Later rounds are not screened: the plant that joins the search next is the one of
    largest ratio over the whole set, and a screen of the last round's worst plants misses
    it (measured on helix_r20: the Monte Carlo plant of largest ratio in round 2 was in no
    such screen, a typical one joined instead and took two more rounds, worst ratio 0.729
    against 0.614).
    """
    if last is not None:
        return tuple(range(len(scenarios)))
    return tuple(sorted({*range(min(defaults.ROBUST_SUBSET, scenarios.n_monte_carlo)),
                         *range(scenarios.n_monte_carlo, len(scenarios))}))


def _median_jump(ratio: np.ndarray, last: np.ndarray) -> bool:
    """The median ratio more than doubled since the last round, over the plants both
    replayed (the whole set when both were certified on it)."""
    both = ~np.isnan(ratio) & ~np.isnan(last)
    return bool(both.any()) and np.median(ratio[both]) > 2.0 * np.median(last[both])


def _meets_goals(cert: Certificate) -> bool:
    """The certificate's ratios within :data:`oga.defaults.ROBUST_WORST_GOAL`,
    ``ROBUST_MEDIAN_GOAL`` and ``ROBUST_P90_GOAL``."""
    return (cert.worst <= defaults.ROBUST_WORST_GOAL and cert.median <= defaults.ROBUST_MEDIAN_GOAL
            and cert.p90 <= defaults.ROBUST_P90_GOAL)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a)
    a.flags.writeable = False
    return a


def _subset(scenarios: ScenarioSet, bounds, keep) -> tuple[ScenarioSet, tuple]:
    """The plants ``keep`` of ``scenarios`` (sorted) and their bounds; its Monte Carlo plants
    and corners counted as such where they stay the set's first and last."""
    keep = sorted(set(keep))
    n_mc = sum(i < scenarios.n_monte_carlo for i in keep)
    n_corners = sum(i >= scenarios.n_monte_carlo for i in keep)
    ordered = (keep[:n_mc] == list(range(n_mc))
               and n_corners in (0, scenarios.n_corners) and n_mc + n_corners == len(keep))
    return (ScenarioSet(status=scenarios.status, nominal=scenarios.nominal,
                        plants=tuple(scenarios.plants[i] for i in keep),
                        labels=tuple(scenarios.labels[i] for i in keep),
                        draws=tuple(scenarios.draws[i] for i in keep), seed=scenarios.seed,
                        n_monte_carlo=n_mc if ordered else 0,
                        n_corners=n_corners if ordered else 0),
            tuple(bounds[i] for i in keep))


def _search_plants(scenarios: ScenarioSet) -> list[int]:
    """The plants the rounds search and judge on: the first
    :data:`oga.defaults.ROBUST_SEARCH_PLANTS` Monte Carlo plants and the corners."""
    n_mc = min(scenarios.n_monte_carlo, defaults.ROBUST_SEARCH_PLANTS)
    return [*range(n_mc), *range(scenarios.n_monte_carlo, len(scenarios))]


def _shrunk(schedule, bkp, bkf, alpha):
    a_kp, a_kf = alpha
    return bkp + a_kp * (schedule.kp_m_min_per_mm - bkp), bkf + a_kf * (schedule.kf - bkf)


def _failing(cert: Certificate) -> set[int]:
    """The plants of ``cert`` where its schedule fails: ratio above 1, or a check broken that
    the baseline keeps."""
    return {int(i) for i in np.flatnonzero(cert.failures())}


def _shrink(setpoints, machine, schedule, bkp, bkf, scenarios, bounds, cert, base_replays,
            threads=1):
    """The largest share ``alpha`` of the schedule's departure from the baseline, ``K = Kb +
    alpha (Ks - Kb)`` (one share for Kp and Kf), whose certificate passes, to
    ``2^-ROBUST_SHRINK_STEPS`` (:data:`oga.defaults.ROBUST_SHRINK_STEPS`).

    Bisection on the plants where a share failed (those of the whole schedule first): a share
    that passes there is certified on the whole set once the bisection ends; where that fails,
    its failing plants join and the bisection goes on below it. The share moves continuously
    with the schedule's ratios (a grid of shares, or a trigger below a goal, made the table
    jump with the fifth digit of the machine). Returns ``(alpha, certificate)``: ``(0, cert)``
    (the baseline; ``cert`` the whole schedule's) when no share passes.
    """
    hard = _failing(cert)
    lo, hi = 0.0, 1.0  # lo passes (0: the baseline itself), hi fails
    while True:
        keep = sorted(hard)
        sub, sub_bounds = _subset(scenarios, bounds, keep)
        sub_base = tuple(base_replays[i] for i in keep)
        while hi - lo > 2.0 ** -defaults.ROBUST_SHRINK_STEPS:
            mid = 0.5 * (lo + hi)
            c = certify(setpoints, machine, *_shrunk(schedule, bkp, bkf, (mid, mid)), bkp, bkf,
                        sub, sub_bounds, sub_base, threads=threads)
            lo, hi = (mid, hi) if c.status == "ok" else (lo, mid)
        if lo == 0.0:
            return (0.0, 0.0), cert
        full = certify(setpoints, machine, *_shrunk(schedule, bkp, bkf, (lo, lo)), bkp, bkf,
                       scenarios, bounds, base_replays, threads=threads)
        if full.status == "ok":
            return (lo, lo), full
        hard |= _failing(full)
        lo, hi = 0.0, lo
