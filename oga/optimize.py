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
from oga.search.result import GainSchedule, OptimizeResult, hold_baseline, setpoints_digest
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
    from oga.search.paper import Gains

    n = len(setpoints)
    machine = plant.machine
    pd = np.ascontiguousarray(setpoints.pos)
    params = plant.search_params()
    states = np.stack([rest_state(params[i], pd[0, i]) for i in range(3)])
    progress, share = report
    lim = machine.axis_limits()  # the same arrays (read-only) the compiled searches take
    limits = (lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3)
    is_moving = np.array([a in moving for a in AXES])
    kp_base, kf_base, gain_bounds = box
    gains = Gains(*gain_bounds, kp_base, kf_base)
    make = _paper_search if options.mode == "paper" else _window_search
    advance, chunk, run, stat_keys = make(setpoints, (params, states), options, gains,
                                          (limits, is_moving, machine.ferror_limits()))
    for k0 in range(0, n, chunk):
        advance(k0, min(k0 + chunk, n))
        if progress is not None:
            progress(share + (1.0 - share) * min(k0 + chunk, n) / n)
    hold_baseline(setpoints, run.kp_out, run.kf_out, kp_base, kf_base)
    for arr in (run.kp_out, run.kf_out):
        arr.flags.writeable = False
    return run.kp_out, run.kf_out, (run.stats[stat_keys[0]], run.stats[stat_keys[1]])


def _paper_search(setpoints, plant, options, gains, checks):
    """``(advance(k0, k1), chunk, state, (STAT_FALLBACK, STAT_WINDOWS))`` of the paper mode
    (:func:`oga.search.paper.paper_search`) on ``plant``: ``(params, states)`` (3, P),
    (3, Z)."""
    from oga.search.paper import (STAT_FALLBACK, STAT_WINDOWS, Axes, paper_search,
                                  paper_settings_of, state_of)

    params, states = plant
    pd = np.ascontiguousarray(setpoints.pos)
    pdT = np.ascontiguousarray(setpoints.pos.T)
    vdT = np.ascontiguousarray(setpoints.vel.T)
    (vmax, amax, jmax), is_moving, ferror_max = checks
    axes = Axes(params, vmax, amax, jmax, ferror_max)
    cfg = paper_settings_of(options, setpoints.dt)
    st = state_of(states, gains.kp_base, gains.kf_base, len(setpoints))

    def advance(k0, k1):
        paper_search(k0, k1, pd, pdT, vdT, is_moving, axes, gains, cfg, st)

    return advance, _CHUNK, st, (STAT_FALLBACK, STAT_WINDOWS)


def _window_search(setpoints, plant, options, gains, checks):
    """``(advance(k0, k1), chunk, carry, (STAT_FALLBACK, STAT_WINDOWS))`` of the full mode's
    windowed search (:func:`oga.search.window.window_search`) on ``plant``: ``(params,
    states)`` (3, P), (3, Z)."""
    from oga.search.window import (STAT_FALLBACK, STAT_WINDOWS, carry_of, chunk_of, one_plant,
                                   program_of, settings_of, window_search)

    params, states = plant
    limits, is_moving, ferror_max = checks
    cfg = settings_of(options, setpoints.dt)
    prog = program_of(setpoints, is_moving, cfg)
    plants = one_plant(params, *limits, ferror_max)
    carry = carry_of(states[None], gains.kp_base, gains.kf_base, cfg, len(setpoints))

    def advance(k0, k1):
        window_search(k0, k1, prog, plants, gains, cfg, carry)

    # every call ends after a whole number of commits
    return advance, chunk_of(cfg, _CHUNK), carry, (STAT_FALLBACK, STAT_WINDOWS)


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
        status=optimized.status, setpoints=setpoints, machine=machine, options=res.options,
        schedule=schedule, baseline_kp=dict(res.baseline_kp), baseline_kf=dict(res.baseline_kf),
        baseline=baseline, optimized=optimized, searched_schedule=searched_schedule,
        searched=searched, kept_baseline=kept_baseline, adjusted=res.adjusted,
        kp_bounds=res.kp_bounds, optimize_time_s=time.perf_counter() - t0,
        fallbacks=res.fallbacks, windows=res.windows, certificate=rob.certificate,
        refusal=refusal)
