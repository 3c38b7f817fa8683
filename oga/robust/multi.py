"""The multi-scenario window search: one gain plan searched on several plants at once.

:func:`multi_search` runs the full-mode window search (:func:`oga.mpc.mpc_multi_chunk`) on
S *active* scenario plants at once: the nominal plant and the S - 1 plants of a *pool*
where the plan being built does worst, refreshed every :data:`oga.defaults.ROBUST_REFRESH`
samples as the search goes:

- every pool plant is carried along the committed gains (its true state advanced by the
  exact kernel, :func:`oga.simulate.run`), and its squared contour error over the last
  samples is compared with the fixed baseline's on the same plant (the cached baseline
  replays): the plants of largest ratio (a limit broken there ranks first) become the
  active set of the next samples, their states taken from the pool;
- the window's cost is a weighted *mean* over the active plants of the squared contour
  error, each plant's normalised by its baseline's MSE (so the cost is a mean of the
  certificate's ratios, not dominated by the plants of largest error): the nominal plant
  with weight :data:`oga.defaults.ROBUST_NOMINAL_WEIGHT`, the worst plants sharing the
  rest. Since the worst plants are chosen into the set, the mean over them is a CVaR of
  the pool's tail (the mean over its S - 1 worst members), held in a QP-friendly smooth
  form (a true CVaR or max over the plants is non-smooth in the gains, which the
  sequential QP's linearisation does not handle); the nominal share keeps the typical
  plants (the certificate's median) good;
- eq. 2 and the following-error limit hold on every active plant (linearised rows per
  plant, the largest exact excess in the line search), with the limits times a
  ``reserve`` (<= 1) for the plants of the set outside the active one; the Kp bounds are
  the range stable on every plant of the set.
"""

from __future__ import annotations

import time

import numpy as np
from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.contour import path_index
from oga.machine import Machine
from oga.mpc import STAT_FALLBACK, STAT_WINDOWS, mpc_multi_chunk
from oga.options import OptimizeOptions
from oga.simulate import axis_params, rest_state

__all__ = ["MultiSearch", "multi_search"]

#: Samples per kernel call (as :mod:`oga.optimize` chunks; the result does not depend on it).
_CHUNK = 2000


class MultiSearch:
    """What :func:`multi_search` found (plain data).

    Attributes
    ----------
    kp, kf : ndarray, shape (N, 3)
        The searched schedule, Kp in (m/min)/mm.
    fallbacks, windows : int
        Kernel counters (:mod:`oga.mpc`).
    time_s : float
        Wall time of the search.
    """

    def __init__(self, kp, kf, fallbacks, windows, time_s):
        self.kp, self.kf = kp, kf
        self.fallbacks, self.windows = fallbacks, windows
        self.time_s = time_s


def multi_search(
    setpoints: Setpoints,
    plants: tuple[Machine, ...],
    base_mse: np.ndarray,
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
    base_mse : ndarray, shape (S,)
        The fixed baseline's MSE(CE) on each plant, m^2 (the cost's normalisation).
    options : OptimizeOptions
        Full-mode options (window, knot, lam, anchor, adjusted axes and gains).
    base_kp, base_kf : float
        The equal fixed baseline gains (the search starts and is anchored there).
    kp_bounds : (float, float)
        Kp range stable on every plant, (m/min)/mm.
    reserve : float
        Share of the acceleration, jerk and following-error limits the search may use.

    Returns
    -------
    MultiSearch
    """
    t0 = time.perf_counter()
    n = len(setpoints)
    te = setpoints.dt
    moving_names = tuple(AXES[i] for i in setpoints.moving_axes)
    adjusted = moving_names if options.adjust is None else tuple(options.adjust)
    nominal = plants[0]
    pd = np.ascontiguousarray(setpoints.pos)
    pdT = np.ascontiguousarray(setpoints.pos.T)
    vdT = np.ascontiguousarray(setpoints.vel.T)
    present = [a for a in AXES if a in nominal.axes]
    params = np.stack([np.stack([axis_params(m, a if a in m.axes else present[0]) for a in AXES])
                       for m in plants])
    # plants of more dead time have longer states: every one padded to the longest (a shorter
    # state leaves its tail zero, as the axes of one machine do)
    rest = [[rest_state(params[p, i], pd[0, i]) for i in range(3)] for p in range(len(plants))]
    states = np.zeros((len(plants), 3, max(r.size for rs in rest for r in rs)))
    for p, rs in enumerate(rest):
        for i, r in enumerate(rs):
            states[p, i, :r.size] = r
    u_hist = np.zeros((len(plants), 3, 2))
    kp0 = np.full(3, float(base_kp))
    kf0 = np.full(3, float(base_kf))
    adj = np.array([a in adjusted for a in AXES])
    adj_kp = adj & ("kp" in options.gains)
    adj_kf = adj & ("kf" in options.gains)
    is_moving = np.array([a in moving_names for a in AXES])
    kp_lo = np.where(is_moving, kp_bounds[0], kp0)
    kp_hi = np.where(is_moving, kp_bounds[1], kp0)
    kf_lo = np.full(3, nominal.gains.kf_range[0])
    kf_hi = np.full(3, nominal.gains.kf_range[1])
    lim = nominal.axis_limits()
    vmax = np.asarray(lim.vmax_m_s, dtype=np.float64)
    amax = np.asarray(lim.amax_m_s2, dtype=np.float64) * reserve
    jmax = np.asarray(lim.jmax_m_s3, dtype=np.float64) * reserve
    ferror_max = nominal.ferror_limits() * reserve
    wlen, kspace = options.np_value, options.knot_value
    commit = max(min(defaults.MPC_COMMIT_INTERVALS, wlen // kspace // 2), 1) * kspace
    pad = wlen + defaults.MPC_SETTLE_TAIL + 1
    pdT_pad = np.ascontiguousarray(np.hstack([pdT, np.repeat(pdT[:, -1:], pad, axis=1)]))
    vdT_pad = np.ascontiguousarray(np.hstack([vdT, np.zeros((3, pad))]))
    feed = ~setpoints.rapid
    feed_pad = np.concatenate([feed, np.zeros(pad, dtype=bool)])
    live_pad = np.concatenate([np.ones(n, dtype=bool), np.zeros(pad, dtype=bool)])
    tree, win_lo, win_hi = path_index(pd, defaults.CE_WINDOW_SAMPLES)
    points = np.repeat(np.stack([kp0, kf0], axis=1)[:, :, None], wlen // kspace, axis=2)
    n_s = len(plants)
    weights = np.empty(n_s)
    weights[0] = defaults.ROBUST_NOMINAL_WEIGHT if n_s > 1 else 1.0
    weights[1:] = (1.0 - defaults.ROBUST_NOMINAL_WEIGHT) / max(n_s - 1, 1) * (
        base_mse[0] / np.asarray(base_mse[1:]))
    kp, kf = kp0.copy(), kf0.copy()
    kp_out, kf_out = np.empty((n, 3)), np.empty((n, 3))
    u_out = np.empty((n_s, n, 3))
    stats = np.zeros(4, dtype=np.int64)
    chunk = max(_CHUNK // commit, 1) * commit
    for k0 in range(0, n, chunk):
        mpc_multi_chunk(k0, min(k0 + chunk, n), pd, pdT_pad, vdT_pad, params, states, kp, kf,
                        adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi, kp0, kf0, vmax, amax, jmax,
                        te, u_hist, wlen, kspace, commit, defaults.MPC_ITERATIONS,
                        *defaults.MPC_TRUST, options.lam_value, options.anchor_value, tree,
                        win_lo, win_hi, is_moving, feed_pad, live_pad, points, kp_out, kf_out,
                        u_out, stats, defaults.MPC_STOP, defaults.MPC_SETTLED_M, ferror_max,
                        defaults.MPC_RESTORE, defaults.MPC_SETTLE_TAIL, weights)
    return MultiSearch(kp=kp_out, kf=kf_out, fallbacks=int(stats[STAT_FALLBACK]),
                       windows=int(stats[STAT_WINDOWS]),
                       time_s=time.perf_counter() - t0)
