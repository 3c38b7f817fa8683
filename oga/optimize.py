"""``optimize``: the gain schedule of a toolpath, searched, verified and summarised.

The stages: the allowed gain ranges (stability per axis, and the best fixed
gains when the baseline is ``"best"``), the receding-horizon search
(:mod:`oga.search.paper`), then a replay of both the baseline and the schedule from
scratch (:mod:`oga.verify.replay`). Every figure of the result comes from the replays.

Where the machine has an uncertainty set (and the ``nominal`` option is off, the
default), the search is the robust one (:func:`oga.search.robust.robust_optimize`): the table is
the robust schedule only if its certificate passes (worst MSE ratio <= 1 over the set's
plants, no plant where it alone breaks a limit), else the robust baseline's fixed gains,
exactly as a nominal schedule that fails its replay is refused (``kept_baseline``).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.errors import MachineError, OptionError
from oga.model.machine import Machine
from oga.model.plant import plant_of
from oga.options import OptimizeOptions, options_from_dict
from oga.search.result import GainSchedule, OptimizeResult, setpoints_digest
from oga.verify.replay import verify

__all__ = ["GainSchedule", "OptimizeResult", "optimize", "setpoints_digest"]

#: Samples per compiled call between two progress reports (full mode: rounded down to
#: whole commits of the window).
_CHUNK = 2000
#: Share of the progress fraction given to the search of the best fixed gains (measured: about
#: 20 s of a 30 s optimisation of LinuxCNC's arcspiral).
_BASELINE_SHARE = 0.5


def _kp_bounds(machine, options, moving, adjusted) -> dict[str, tuple[float, float]]:
    """Allowed Kp per contouring axis: its stable range, or ``kp_range`` for adjusted axes."""
    from oga.model.stability import stable_range

    bounds = {}
    for a in moving:
        rng = stable_range(machine, a)
        if not rng.ok:  # the stability margins, not the kinematics, rule every Kp out
            raise MachineError(
                f"machine {machine.name} [gains]: {rng.message} (m/min)/mm: no gain is stable "
                "enough; lower pm_min_deg / gm_min_db or widen kp_bounds_m_min_per_mm"
            )
        lo, hi = rng.kp_min, rng.kp_max
        if options.kp_range is not None and a in adjusted:
            rlo, rhi = options.kp_range
            if rlo < lo - 1e-9 or rhi > hi + 1e-9:
                raise OptionError(
                    f"kp_range: [{rlo}, {rhi}] leaves the stable range [{lo}, {hi}] "
                    f"(m/min)/mm of axis {a}"
                )
            lo, hi = rlo, rhi
        bounds[a] = (float(lo), float(hi))
    return bounds


def _baseline(setpoints, machine, options, moving, progress=None):
    if options.baseline == "best":
        from oga.search.ranges import best_fixed_gains
        from oga.model.stability import stable_range

        best = best_fixed_gains(setpoints, machine, progress=progress)
        if best is None:
            stable = {a: stable_range(machine, a) for a in moving}
            if max(r.kp_min for r in stable.values()) > min(r.kp_max for r in stable.values()):
                spans = ", ".join(f"{a} [{r.kp_min}, {r.kp_max}]" for a, r in stable.items())
                raise MachineError(
                    f"machine {machine.name} [gains]: the stable Kp ranges of the contouring "
                    f"axes do not overlap ({spans} (m/min)/mm): no equal fixed gains are stable "
                    "on all of them; give --baseline KP,KF"
                )
            raise OptionError(
                "baseline: no equal fixed gains meet the kinematic limits (and the "
                "following-error limits, where the machine sets them) at every sample of "
                "this toolpath; give --baseline KP,KF"
            )
        kp = {a: float(best.kp[a]) for a in moving}
        kf = {a: float(best.kf[a]) for a in moving}
        kp0, kf0 = kp[moving[0]], kf[moving[0]]
    else:
        kp0, kf0 = options.baseline
        kp = {a: float(kp0) for a in moving}
        kf = {a: float(kf0) for a in moving}
    # axes that do not move keep the same (common) fixed gains
    for a in AXES:
        kp.setdefault(a, float(kp0))
        kf.setdefault(a, float(kf0))
    return kp, kf


def optimize(
    setpoints: Setpoints,
    machine: Machine,
    options: OptimizeOptions | dict | None = None,
    *,
    progress: Callable[[float], None] | None = None,
) -> OptimizeResult:
    """Search the gain schedule of ``setpoints`` on ``machine`` and verify it.

    Parameters
    ----------
    setpoints : Setpoints
        Planned motion (its period must be the machine's Te).
    machine : Machine
        The machine.
    options : OptimizeOptions or dict, optional
        Search options (CLI/API names); default the full mode: best fixed
        baseline, every contouring axis, Kp and Kf.
    progress : callable, optional
        Called with the fraction done (0..1): during the search of the best fixed gains
        (the first :data:`_BASELINE_SHARE`), then between chunks of samples.

    Returns
    -------
    OptimizeResult
        ``status`` tells whether the exported schedule passed verification: the
        searched one, or the baseline's fixed gains when the search failed or did
        not beat them, or (robust search) its certificate failed (``kept_baseline``).

    Raises
    ------
    OptionError
        Inconsistent options (an adjusted axis that does not move, a Kp range
        outside the stable range, no feasible baseline; with the robust search, the
        paper mode or an explicit baseline).
    """
    if not isinstance(options, OptimizeOptions):
        options = options_from_dict(options)
    t0 = time.perf_counter()
    _check_window(options)
    moving, adjusted = _axes(setpoints, machine, options)
    kp_bounds = _kp_bounds(machine, options, moving, adjusted)
    if not options.nominal:  # the checks above hold for the robust search too
        from oga.search.robust.plants import uncertain_axes

        if uncertain_axes(machine):
            return _robust(setpoints, machine, options, progress, t0)
    plant = plant_of(machine)
    share = _BASELINE_SHARE if options.baseline == "best" else 0.0
    base_kp, base_kf = _baseline(setpoints, plant, options, moving,
                                 None if progress is None else lambda f: progress(share * f))
    box = _gain_box(plant, options, (base_kp, base_kf), kp_bounds, adjusted)
    n = len(setpoints)
    fixed_kp = np.tile([base_kp[a] for a in AXES], (n, 1))
    fixed_kf = np.tile([base_kf[a] for a in AXES], (n, 1))
    for arr in (fixed_kp, fixed_kf):
        arr.flags.writeable = False
    baseline = verify(setpoints, plant, fixed_kp, fixed_kf, kp_bounds)
    kp_out, kf_out, stats = _search(setpoints, plant, options, box, moving, (progress, share))
    searched = verify(setpoints, plant, kp_out, kf_out, kp_bounds)
    searched_schedule = GainSchedule(kp_m_min_per_mm=kp_out, kf=kf_out)
    kept_baseline = not (searched.ok and searched.metrics.mse_m2 < baseline.metrics.mse_m2)
    if kept_baseline:
        schedule, optimized = GainSchedule(kp_m_min_per_mm=fixed_kp, kf=fixed_kf), baseline
    else:
        schedule, optimized = searched_schedule, searched
    return OptimizeResult(
        status=optimized.status, setpoints=setpoints, machine=machine, options=options,
        schedule=schedule, baseline_kp=base_kp, baseline_kf=base_kf, baseline=baseline,
        optimized=optimized, searched_schedule=searched_schedule, searched=searched,
        kept_baseline=kept_baseline, adjusted=adjusted, kp_bounds=kp_bounds,
        optimize_time_s=time.perf_counter() - t0, fallbacks=int(stats[0]),
        windows=int(stats[1]))


def _check_window(options: OptimizeOptions) -> None:
    """OptionError where the full mode's window or knot spacing cannot work."""
    if options.mode == "full" and options.np_value < defaults.MPC_MIN_NP:
        raise OptionError(
            f"np: full mode needs a window of at least {defaults.MPC_MIN_NP} samples "
            f"(got {options.np_value}); a shorter one cannot see the jerk limit coming"
        )
    if options.mode == "full" and options.np_value // options.knot_value < 3:
        raise OptionError(
            f"knot: the {options.np_value}-sample window needs at least 3 spline intervals "
            f"(knot <= {options.np_value // 3}, got {options.knot_value})"
        )


def _axes(setpoints, machine, options) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(moving, adjusted)`` axes, checked: something moves, every adjusted axis moves, and
    the machine has every moving one."""
    moving = tuple(AXES[i] for i in setpoints.moving_axes)
    if not moving:
        raise OptionError("toolpath: no axis moves; nothing to optimise")
    adjusted = moving if options.adjust is None else tuple(options.adjust)
    still = [a for a in adjusted if a not in moving]
    if still:
        raise OptionError(f"adjust: axis {', '.join(still)} does not move on this toolpath")
    for a in moving:
        machine.axis(a)
    return moving, adjusted


def _gain_box(plant, options, base, kp_bounds, adjusted) -> tuple:
    """``(kp_base, kf_base, gain_bounds)``: the baseline gains per axis x, y, z and the
    search's ``(adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi)``; OptionError where the
    baseline's Kp of an adjusted axis leaves its range."""
    base_kp, base_kf = base
    kp = np.array([base_kp[a] for a in AXES])
    kf = np.array([base_kf[a] for a in AXES])
    adj = np.array([a in adjusted for a in AXES])
    adj_kp = adj & ("kp" in options.gains)
    adj_kf = adj & ("kf" in options.gains)
    kp_lo = np.array([kp_bounds.get(a, (kp[i], kp[i]))[0] for i, a in enumerate(AXES)])
    kp_hi = np.array([kp_bounds.get(a, (kp[i], kp[i]))[1] for i, a in enumerate(AXES)])
    kf_lo = np.full(3, plant.machine.gains.kf_range[0])
    kf_hi = np.full(3, plant.machine.gains.kf_range[1])
    for i, a in enumerate(AXES):
        if adj[i] and not kp_lo[i] <= kp[i] <= kp_hi[i]:
            raise OptionError(
                f"baseline: Kp {kp[i]} of axis {a} lies outside its range "
                f"[{kp_lo[i]}, {kp_hi[i]}] (m/min)/mm"
            )
    return kp.copy(), kf.copy(), (adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi)


def _search(setpoints, plant, options, box, moving, report):
    """Run the chunked search (paper mode or the windowed search) from rest with the
    baseline gains, ``report = (progress, share done before)``; returns the searched
    ``(kp, kf)`` (N, 3), read-only, and ``(fallbacks, windows)``."""
    from oga.model.simulate import rest_state

    n = len(setpoints)
    machine = plant.machine
    pd = np.ascontiguousarray(setpoints.pos)
    present = [AXES.index(a) for a in AXES if a in machine.axes]
    params = np.stack([plant.params[i if a in machine.axes else present[0]]
                       for i, a in enumerate(AXES)])
    states = np.stack([rest_state(params[i], pd[0, i]) for i in range(3)])
    kp_base, kf_base, _bounds = box
    progress, share = report
    lim = machine.axis_limits()  # the same arrays (read-only) the compiled searches take
    limits = (lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3)
    is_moving = np.array([a in moving for a in AXES])
    make = _paper_advance if options.mode == "paper" else _window_advance
    advance, chunk, stat_keys = make(setpoints, params, options, box,
                                     (limits, is_moving, machine.ferror_limits()))
    # the search state: axis states, gains, command history, outputs, counters
    run = (states.copy(), kp_base.copy(), kf_base.copy(), np.zeros((3, 2)),
           np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.zeros(4, dtype=np.int64))
    for k0 in range(0, n, chunk):
        advance(k0, min(k0 + chunk, n), run)
        if progress is not None:
            progress(share + (1.0 - share) * min(k0 + chunk, n) / n)
    kp_out, kf_out, stats = run[4], run[5], run[7]
    for arr in (kp_out, kf_out):
        arr.flags.writeable = False
    return kp_out, kf_out, (stats[stat_keys[0]], stats[stat_keys[1]])


def _paper_advance(setpoints, params, options, box, checks):
    """``(advance(k0, k1, run), chunk, (STAT_FALLBACK, STAT_WINDOWS))`` of the paper mode
    (:func:`oga.search.paper.search_chunk`)."""
    from oga.search.paper import STAT_FALLBACK, STAT_WINDOWS, search_chunk

    pd = np.ascontiguousarray(setpoints.pos)
    pdT = np.ascontiguousarray(setpoints.pos.T)
    vdT = np.ascontiguousarray(setpoints.vel.T)
    kp_base, kf_base, gain_bounds = box
    (vmax, amax, jmax), is_moving, ferror_max = checks
    te = setpoints.dt

    def advance(k0, k1, run):
        search_chunk(k0, k1, pd, pdT, vdT, params, *run[:3], *gain_bounds, vmax, amax, jmax, te,
                     run[3], options.np_value, options.lam_value, options.anchor_value, kp_base,
                     kf_base, defaults.A1, defaults.A2, defaults.CE_WINDOW_SAMPLES,
                     is_moving, *run[4:], ferror_max)

    return advance, _CHUNK, (STAT_FALLBACK, STAT_WINDOWS)


def _window_advance(setpoints, params, options, box, checks):
    """``(advance(k0, k1, run), chunk, (STAT_FALLBACK, STAT_WINDOWS))`` of the full mode's
    windowed search (:func:`oga.search.window.mpc_chunk`)."""
    from oga.model.contour import path_index
    from oga.search.window import STAT_FALLBACK, STAT_WINDOWS, mpc_chunk

    n = len(setpoints)
    pd = np.ascontiguousarray(setpoints.pos)
    pdT = np.ascontiguousarray(setpoints.pos.T)
    vdT = np.ascontiguousarray(setpoints.vel.T)
    kp_base, kf_base, gain_bounds = box
    (vmax, amax, jmax), is_moving, ferror_max = checks
    te = setpoints.dt
    wlen = options.np_value
    kspace = options.knot_value
    # whole spline intervals, so that the shifted plan is the same gain trajectory
    commit = max(min(defaults.MPC_COMMIT_INTERVALS, wlen // kspace // 2), 1) * kspace
    # every call ends after a whole number of commits: the plan carried to the next
    # call is shifted by whole spline intervals only
    chunk = max(_CHUNK // commit, 1) * commit
    pad = wlen + defaults.MPC_SETTLE_TAIL + 1
    pdT_pad = np.ascontiguousarray(np.hstack([pdT, np.repeat(pdT[:, -1:], pad, axis=1)]))
    vdT_pad = np.ascontiguousarray(np.hstack([vdT, np.zeros((3, pad))]))
    feed_pad = np.concatenate([~setpoints.rapid, np.zeros(pad, dtype=bool)])
    # eq. 2 and the following-error limit: every sample of the program, not the padding
    live_pad = np.concatenate([np.ones(n, dtype=bool), np.zeros(pad, dtype=bool)])
    # the contour error's index and windows, as the replay measures it
    tree, win_lo, win_hi = path_index(pd, defaults.CE_WINDOW_SAMPLES)
    # the plan's spline control points per axis and gain, carried across chunks (as many
    # as leave the plan at rest over the window's last interval, checked against eq. 2)
    points = np.repeat(np.stack([kp_base, kf_base], axis=1)[:, :, None], wlen // kspace,
                       axis=2)

    def advance(k0, k1, run):
        mpc_chunk(k0, k1, pd, pdT_pad, vdT_pad, params, *run[:3], *gain_bounds, kp_base,
                  kf_base, vmax, amax, jmax, te, run[3], wlen, kspace, commit,
                  defaults.MPC_ITERATIONS, *defaults.MPC_TRUST, options.lam_value,
                  options.anchor_value, tree, win_lo, win_hi, is_moving,
                  feed_pad, live_pad, points, *run[4:], defaults.MPC_STOP,
                  defaults.MPC_SETTLED_M, ferror_max, defaults.MPC_RESTORE,
                  defaults.MPC_SETTLE_TAIL)

    return advance, chunk, (STAT_FALLBACK, STAT_WINDOWS)


def _robust(setpoints, machine, options, progress, t0) -> OptimizeResult:
    """:func:`optimize` by the robust search: its schedule if certified, else its baseline,
    verified on the nominal machine (the same replays and summary as the nominal path)."""
    from oga.search.robust.search import robust_optimize

    for field, given, why in (
            ("mode", options.mode != "full", "the paper's search sees the nominal model only"),
            ("baseline", options.baseline != "best",
             "the robust search picks the equal fixed gains that keep the limits on every "
             "plant of the set")):
        if given:
            raise OptionError(
                f"{field}: {why}; machine {machine.name} has an uncertainty set, so the search "
                "is robust: add nominal (--nominal) to search its nominal model only")
    if progress is not None:
        progress(0.0)
    rob = robust_optimize(setpoints, machine, options, progress=progress)
    res = rob.result
    n = len(setpoints)
    fixed_kp = np.tile([res.baseline_kp[a] for a in AXES], (n, 1))
    fixed_kf = np.tile([res.baseline_kf[a] for a in AXES], (n, 1))
    searched_schedule = rob.schedule if rob.status == "ok" else res.searched_schedule
    for arr in (fixed_kp, fixed_kf, searched_schedule.kp_m_min_per_mm, searched_schedule.kf):
        arr.flags.writeable = False
    # robust_optimize replayed both on the nominal plant (the machine without its set):
    # when the certificate failed, the searched schedule it returns is the baseline
    baseline = res.baseline
    searched = res.searched if rob.status == "ok" else res.baseline
    refusal = () if rob.status == "ok" else (rob.certificate.reasons or (
        "the robust search found no schedule that passes its checks: "
        + "; ".join(res.searched.violations or ("see its certificate",)),))
    kept_baseline = bool(refusal) or not (searched.ok
                                          and searched.metrics.mse_m2 < baseline.metrics.mse_m2)
    if kept_baseline:
        schedule, optimized = GainSchedule(kp_m_min_per_mm=fixed_kp, kf=fixed_kf), baseline
    else:
        schedule, optimized = searched_schedule, searched
    if progress is not None:
        progress(1.0)
    return OptimizeResult(
        status=optimized.status, setpoints=setpoints, machine=machine, options=options,
        schedule=schedule, baseline_kp=dict(res.baseline_kp), baseline_kf=dict(res.baseline_kf),
        baseline=baseline, optimized=optimized, searched_schedule=searched_schedule,
        searched=searched, kept_baseline=kept_baseline, adjusted=res.adjusted,
        kp_bounds=res.kp_bounds, optimize_time_s=time.perf_counter() - t0,
        fallbacks=res.fallbacks, windows=res.windows, certificate=rob.certificate,
        refusal=refusal)
