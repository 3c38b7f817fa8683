"""The multi-scenario window search: one gain plan searched on several plants at once.

:func:`multi_search` runs the full-mode window search (:func:`oga.search.window.window_search`) on
S plants at once, the nominal one first: every plant's true state is carried along the
committed gains (the table is open-loop: every plant runs the same gains), each window's
plan is linearised on every plant around its own prediction, and

- the window's cost is a weighted **mean** over the plants of the squared contour error,
  each plant's divided by the fixed baseline's MSE on that plant (so the cost is a mean
  of the certificate's ratios, not dominated by the plants of largest error): the nominal
  plant with weight :data:`oga.defaults.ROBUST_NOMINAL_WEIGHT`, the others sharing the
  rest. The caller (:func:`oga.search.robust.search.robust_optimize`) puts into the set the
  plants where the previous schedule did worst, so the mean over them is a CVaR of the
  set's tail, in a smooth form the sequential QP handles (a max or a true CVaR over the
  plants is non-smooth in the gains: the linearised QP would chase the active plant);
  the nominal share keeps the typical plants, the certificate's median, good;
- eq. 2 and the following-error limit hold on every plant of the set (linearised rows per
  plant, the largest exact excess in the line search), the acceleration, jerk and
  following-error limits times a ``reserve`` (<= 1) that covers the plants outside the
  set, but at every sample at least the plant's baseline's own acceleration and jerk
  command there (:func:`_baseline_floor`: the baseline's plan, where every window starts,
  stays feasible); the Kp bounds are the range stable on every plant of the whole scenario
  set.
- a window whose samples are all a rapid's commits the plan as it is, no step searched
  (``hold_in_rapids`` of :func:`oga.search.window.window_search`): no contour error counts there,
  and in a long rapid at a low Kf the following error is 15-25 mm, so a gain change at
  speed moves the command by dKp times that; where the windows searched there, on
  LinuxCNC's plasmatest (baseline Kp 1.6, Kf 0) the second round raised Kp 1.07 -> 1.62
  and Kf 0 -> 1 at speed and broke vmax 1.56x on the nominal plant itself, and
  51MeanderAve's table broke vmax on all 96 plants (now certified: median 0.046, worst
  0.056). On cncjs_toolpath the table changed (median 0.269 -> 0.278, p90 0.397 -> 0.342,
  worst 0.683 -> 0.556, a third round); the other benchmark programs' are bit-identical.
  Not solved: the windows that reach past a rapid's end still search while the axis is
  at speed (plasmatest: jerk 2.4x in a rapid's last 112 samples, on every plant); holding
  every commit of rapid samples instead (no search before the feed starts) missed the
  median goal elsewhere (0.378 on cncjs_toolpath, 0.420 on arcspiral[:40]).

Measured on reference_xz (ucp710, baseline Kp 1.3, Kf 0.9, replayed on the nominal
plant, the 32 corners and 8 (first and last item) or 24 Monte Carlo plants; ratios median /
p90 / worst, limit breaks of the schedule, which the baseline keeps everywhere):

- nominal plant alone: 0.554 / 0.997 / 1.132, 13 breaks;
- nominal + the two corners of the worst ratio (friction-lo mass-lo kv-hi tn-lo, dead
  time +0 and +1): 0.154 / 0.329 / 0.444, at reserve 1.0 24 breaks, 0.9: 4, 0.82: 2,
  0.75: 0 (0.147 / 0.330 / 0.446); at 0.68 the ratios grow (0.224 / 0.436 / 0.633);
- adding instead the plant where the schedule breaks a limit most (slow loop, more
  mass) made everything worse (median 1.75): the line search then ranks most steps by
  that plant's limit excess, not by cost. Limits are the reserve's job, not the set's;
- refreshing the set *inside* a run (every 200 samples, the plants of largest running
  ratio, states carried along the committed gains): 0.53 / 1.07 / 1.48 with 4 plants: a
  plant entering mid-run does so in a state the plan never constrained, and its eq. 2
  rows push the line search into its feasibility classes. The set is refreshed between
  runs instead (the caller's rounds).

Not solved: on freeform_xz (baseline Kp 1.5, Kf 0.9) the nominal plant alone gives ratio
0.002 on it, the corner friction-lo mass-lo kv-hi tn-lo dead-lo alone 0.001 on it, but the
two together 1.64 and 4.14 (Kf pulled down to 0.07, Kp to both bounds, 95 um peaks), for
any corner weight from 1.2 down to 0.06 (fine at 0.0025), with or without the restoring
iterations: the receding windows walk away from both plants' optimum. The caller drops a
plant whose joining makes the median ratio much worse.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.model.kinematics import command_rates
from oga.model.machine import Machine
from oga.model.plant import plant_of
from oga.model.response import simulate_si
from oga.model.simulate import rest_state
from oga.options import OptimizeOptions
from oga.search.paper import Gains
from oga.search.result import hold_baseline
from oga.search.window import (STAT_FALLBACK, STAT_WINDOWS, Plants, carry_of, chunk_of,
                               program_of, settings_of, window_search)
from oga.verify.replay import ReplayGains, Verification

__all__ = ["MultiSearch", "multi_search"]

#: Samples per kernel call (as :mod:`oga.optimize` chunks; the result does not depend on it).
_CHUNK = 2000


@dataclass(frozen=True, eq=False)
class MultiSearch:
    """What :func:`multi_search` found (the schedule is judged by its certificate, not here).

    Attributes
    ----------
    kp, kf : ndarray, shape (N, 3)
        The searched schedule, Kp in (m/min)/mm.
    fallbacks, windows : int
        Kernel counters (:mod:`oga.search.window`).
    time_s : float
        Wall time of the search.
    """

    kp: np.ndarray
    kf: np.ndarray
    fallbacks: int
    windows: int
    time_s: float


def multi_search(
    setpoints: Setpoints,
    plants: tuple[Machine, ...],
    baselines: tuple[Verification, ...],
    options: OptimizeOptions,
    base_kp: float,
    base_kf: float,
    kp_bounds: tuple[float, float],
    reserve: float,
) -> MultiSearch:
    """Search one schedule on ``plants`` at once (module doc).

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples).
    plants : tuple of Machine
        The active plants; ``plants[0]`` is the nominal one (its limits are kept on all).
    baselines : tuple of Verification
        The fixed baseline's replay on each plant: its MSE(CE) normalises the plant's cost,
        and its peaks floor the plant's limits (below).
    options : OptimizeOptions
        Full-mode options (window, knot, lam, anchor, adjusted axes and gains).
    base_kp, base_kf : float
        The equal fixed baseline gains (the search starts and is anchored there).
    kp_bounds : (float, float)
        Kp range stable on every plant, (m/min)/mm.
    reserve : float
        Share of the acceleration, jerk and following-error limits the search may use on
        each plant, but never less than :data:`oga.defaults.ROBUST_BASELINE_FLOOR` of the
        baseline's own peak there (the baseline's plan, where every window starts, must stay
        nearly feasible: further below, the line search ranks every step by its excess, not
        its cost, and the search collapses; measured on freeform_xz, nominal plant and the
        corner friction-lo mass-lo kv-hi tn-lo dead-hi, no floor: reserve 0.78: ratios
        0.227 / 0.437 / 0.725 and 2 schedule-only breaks, 0.72 (0.88 of the baseline's jerk
        peak on x): 0.228 / 0.440 / 0.721 and none, 0.66 (0.80 of it): 1.68 / 3.38 / 6.29).

    Returns
    -------
    MultiSearch
    """
    t0 = time.perf_counter()
    moving_names = tuple(AXES[i] for i in setpoints.moving_axes)
    is_moving = np.array([a in moving_names for a in AXES])
    cfg = settings_of(options, setpoints.dt, hold_in_rapids=True)
    prog = program_of(setpoints, is_moving, cfg)
    params, states = _packed_plants(plants, prog.pd[0])
    packed = Plants(params, *_plant_limits(plants[0], baselines, reserve), _weights(baselines),
                    _baseline_floor(setpoints, plants, base_kp, base_kf, prog.live.size))
    gains = _gains(options, plants[0], (moving_names, is_moving), (base_kp, base_kf), kp_bounds)
    n = len(setpoints)
    carry = carry_of(states, gains.kp_base, gains.kf_base, cfg, n)
    chunk = chunk_of(cfg, _CHUNK)
    for k0 in range(0, n, chunk):
        window_search(k0, min(k0 + chunk, n), prog, packed, gains, cfg, carry)
    hold_baseline(setpoints, carry.kp_out, carry.kf_out, gains.kp_base, gains.kf_base)
    return MultiSearch(kp=carry.kp_out, kf=carry.kf_out,
                       fallbacks=int(carry.stats[STAT_FALLBACK]),
                       windows=int(carry.stats[STAT_WINDOWS]),
                       time_s=time.perf_counter() - t0)


def _gains(options, nominal, moving, base, kp_bounds):
    """The :class:`oga.search.paper.Gains` searched: the options' adjusted axes and gains
    (``moving``: the moving axes' names and (3,) mask), Kp within ``kp_bounds`` on the moving
    axes (held at the baseline elsewhere), Kf within the ``nominal`` machine's range, the
    anchor at ``base`` (Kp, Kf)."""
    moving_names, is_moving = moving
    kp0, kf0 = np.full(3, float(base[0])), np.full(3, float(base[1]))
    adjusted = moving_names if options.adjust is None else tuple(options.adjust)
    adj = np.array([a in adjusted for a in AXES])
    kp_lo, kp_hi = (np.where(is_moving, v, kp0) for v in kp_bounds)
    kf_lo, kf_hi = (np.full(3, v) for v in nominal.gains.kf_range)
    return Gains(adj & ("kp" in options.gains), adj & ("kf" in options.gains), kp_lo, kp_hi,
                 kf_lo, kf_hi, kp0, kf0)


def _packed_plants(plants, p0):
    """Every plant's packed parameters (S, 3, P) and rest state at ``p0`` (3,) (S, 3, L):
    plants of more dead time have longer states, every one padded to the longest (a shorter
    state leaves its tail zero, as the axes of one machine do)."""
    params = np.stack([plant_of(m).search_params() for m in plants])
    rest = [[rest_state(params[p, i], p0[i]) for i in range(3)] for p in range(len(plants))]
    states = np.zeros((len(plants), 3, max(r.size for rs in rest for r in rs)))
    for p, rs in enumerate(rest):
        for i, r in enumerate(rs):
            states[p, i, :r.size] = r
    return params, states


def _plant_limits(nominal, baselines, reserve):
    """The nominal machine's limits per plant, ``(vmax, amax, jmax, ferror_max)`` each (S, 3):
    limit x max(share, a share of the baseline's peak ratio there) (``multi_search``'s
    ``reserve``)."""
    lim = nominal.axis_limits()
    limits = np.stack([np.asarray(lim.vmax_m_s, dtype=np.float64),
                       np.asarray(lim.amax_m_s2, dtype=np.float64),
                       np.asarray(lim.jmax_m_s3, dtype=np.float64), nominal.ferror_limits()])
    share = np.array([1.0, reserve, reserve, reserve])[:, None]
    floor = defaults.ROBUST_BASELINE_FLOOR
    return (np.ascontiguousarray(x) for x in np.stack([
        limits * np.maximum(share, floor * np.vstack([b.command_ratio.T,
                                                      np.nan_to_num(b.ferror_ratio)]))
        for b in baselines], axis=1))


def _baseline_floor(setpoints, plants, base_kp, base_kf, m):
    """Per sample, each plant's acceleration and jerk limit raised to its baseline's own
    command there (the largest within :data:`oga.defaults.ROBUST_FLOOR_SAMPLES`), (S, 3, 2,
    ``m``), m/s^2 and m/s^3, zero past the program's end (:class:`oga.search.window.Plants`).

    Why: below the baseline's own command the baseline's plan, where every window starts, is
    infeasible, and the windows escape by cutting Kf. cncjs_toolpath (ucp710, the nominal
    plant and a fast corner, reserve 0.6): ratios 0.575 / 0.763 on them with the floor,
    0.620 / 1.207 without; its robust table's median 0.538 -> 0.363. Not every program
    gains (the searched plants may now use the baseline's own peaks): short_segments 0.376
    -> 0.535 (docs/explanation/certificate.md)."""
    n = len(setpoints)
    gains = ReplayGains.of(setpoints, np.full((n, 3), base_kp), np.full((n, 3), base_kf))
    floor = np.zeros((len(plants), 3, 2, m))
    size = 2 * defaults.ROBUST_FLOOR_SAMPLES + 1
    for s, machine in enumerate(plants):
        _, u = simulate_si(setpoints, plant_of(machine), gains.kp_si, gains.kf)
        for r, rate in enumerate(command_rates(u, setpoints.dt)):
            floor[s, :, r, :n] = maximum_filter1d(rate.T, size, axis=1)
    return floor


def _weights(baselines):
    """Each plant's weight in the cost (S,): the nominal one (first)
    :data:`oga.defaults.ROBUST_NOMINAL_WEIGHT` (1 alone), the others share the rest, each over
    its baseline MSE relative to the nominal one's."""
    n_s = len(baselines)
    weights = np.empty(n_s)
    weights[0] = defaults.ROBUST_NOMINAL_WEIGHT if n_s > 1 else 1.0
    base_mse = np.array([b.metrics.mse_m2 for b in baselines])
    weights[1:] = (1.0 - defaults.ROBUST_NOMINAL_WEIGHT) / max(n_s - 1, 1) * (
        base_mse[0] / base_mse[1:])
    return weights
