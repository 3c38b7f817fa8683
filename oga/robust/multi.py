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
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.contour import ce2_at, path_index
from oga.kinematics import command_peaks
from oga.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.mpc import STAT_FALLBACK, STAT_WINDOWS, mpc_multi_chunk
from oga.options import OptimizeOptions
from oga.simulate import axis_params, rest_state, run

__all__ = ["MultiSearch", "multi_search"]

_C = KP_SI_PER_M_MIN_PER_MM


class MultiSearch:
    """What :func:`multi_search` found (plain data).

    Attributes
    ----------
    kp, kf : ndarray, shape (N, 3)
        The searched schedule, Kp in (m/min)/mm.
    fallbacks, windows : int
        Kernel counters (:mod:`oga.mpc`).
    active : list of tuple of int
        Pool indices of the active plants per refresh interval (nominal first).
    time_s : float
        Wall time of the search.
    """

    def __init__(self, kp, kf, fallbacks, windows, active, time_s):
        self.kp, self.kf = kp, kf
        self.fallbacks, self.windows = fallbacks, windows
        self.active, self.time_s = active, time_s


@njit(cache=True)
def _advance_pool(states, params, pdT, vdT, kp_out, kf_out, k0, k1, moving, pd, tree, win_lo,
                  win_hi, feed, vmax, amax, jmax, ferror_max, te, u_hist, sse, excess):
    """Advance every pool plant over samples ``k0 .. k1 - 1`` along the committed gains.

    ``states`` (P, 3, Z) and ``u_hist`` (P, 3, 2) in place; ``sse`` (P,) receives each
    plant's squared contour error over the feed samples (m^2), ``excess`` (P,) its largest
    ratio to a limit (eq. 2 with the two previous commands, following error) minus 1.
    Axes that do not move stay at their setpoint (at rest).
    """
    n = k1 - k0
    p_act = np.empty((3, n))
    u = np.empty((3, n + 2))
    kp_si = np.empty(n)
    kf = np.empty(n)
    check = np.ones(n + 2, dtype=np.bool_)
    check[0] = False
    check[1] = False
    for p in range(states.shape[0]):
        worst = 0.0
        for a in range(3):
            if not moving[a]:
                p_act[a, :] = pdT[a, k0:k1]
                continue
            for i in range(n):
                kp_si[i] = kp_out[k0 + i, a] * _C
                kf[i] = kf_out[k0 + i, a]
            u[a, 0] = u_hist[p, a, 1]
            u[a, 1] = u_hist[p, a, 0]
            run(states[p, a], params[p, a], pdT[a, k0:k1], vdT[a, k0:k1], kp_si, kf, p_act[a],
                u[a, 2:])
            v_pk, a_pk, j_pk = command_peaks(u[a], check, te)
            worst = max(worst, v_pk / vmax[a] - 1.0, a_pk / amax[a] - 1.0, j_pk / jmax[a] - 1.0)
            if ferror_max[a] < np.inf:
                for i in range(n):
                    worst = max(worst, abs(pdT[a, k0 + i] - p_act[a, i]) / ferror_max[a] - 1.0)
            u_hist[p, a, 0] = u[a, n + 1]
            u_hist[p, a, 1] = u[a, n]
        s = 0.0
        j = -1
        for i in range(n):
            c = k0 + i
            if feed[c]:
                d2, j = ce2_at(pd, tree, win_lo[c], win_hi[c], c, p_act[0, i], p_act[1, i],
                               p_act[2, i], j)
                s += d2
        sse[p] = s
        excess[p] = worst


def multi_search(
    setpoints: Setpoints,
    pool: tuple[Machine, ...],
    base_ce2: np.ndarray,
    options: OptimizeOptions,
    base_kp: float,
    base_kf: float,
    kp_bounds: tuple[float, float],
    reserve: float,
    n_active: int = defaults.ROBUST_ACTIVE,
) -> MultiSearch:
    """Search one schedule on the plants of ``pool`` (module doc).

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples).
    pool : tuple of Machine
        The plants the active set is drawn from; ``pool[0]`` is the nominal plant (always
        active, and its limits are the ones kept).
    base_ce2 : ndarray, shape (P, N)
        The fixed baseline's squared contour error per pool plant and sample (0 off feed).
    options : OptimizeOptions
        Full-mode options (window, knot, lam, anchor, adjusted axes and gains).
    base_kp, base_kf : float
        The equal fixed baseline gains (the search starts and is anchored there).
    kp_bounds : (float, float)
        Kp range stable on every plant, (m/min)/mm.
    reserve : float
        Share of the acceleration, jerk and following-error limits the search may use.
    n_active : int
        Active plants S (the nominal one included).

    Returns
    -------
    MultiSearch
    """
    t0 = time.perf_counter()
    n = len(setpoints)
    te = setpoints.dt
    moving_names = tuple(AXES[i] for i in setpoints.moving_axes)
    adjusted = moving_names if options.adjust is None else tuple(options.adjust)
    nominal = pool[0]
    pd = np.ascontiguousarray(setpoints.pos)
    pdT = np.ascontiguousarray(setpoints.pos.T)
    vdT = np.ascontiguousarray(setpoints.vel.T)
    present = [a for a in AXES if a in nominal.axes]
    params = np.stack([np.stack([axis_params(m, a if a in m.axes else present[0]) for a in AXES])
                       for m in pool])
    # plants of more dead time have longer states: every one padded to the longest (a shorter
    # state leaves its tail zero, as the axes of one machine do)
    rest = [[rest_state(params[p, i], pd[0, i]) for i in range(3)] for p in range(len(pool))]
    states = np.zeros((len(pool), 3, max(r.size for rs in rest for r in rs)))
    for p, rs in enumerate(rest):
        for i, r in enumerate(rs):
            states[p, i, :r.size] = r
    u_hist = np.zeros((len(pool), 3, 2))
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
    refresh = max(defaults.ROBUST_REFRESH // commit, 1) * commit
    pad = wlen + defaults.MPC_SETTLE_TAIL + 1
    pdT_pad = np.ascontiguousarray(np.hstack([pdT, np.repeat(pdT[:, -1:], pad, axis=1)]))
    vdT_pad = np.ascontiguousarray(np.hstack([vdT, np.zeros((3, pad))]))
    feed = ~setpoints.rapid
    feed_pad = np.concatenate([feed, np.zeros(pad, dtype=bool)])
    live_pad = np.concatenate([np.ones(n, dtype=bool), np.zeros(pad, dtype=bool)])
    tree, win_lo, win_hi = path_index(pd, defaults.CE_WINDOW_SAMPLES)
    points = np.repeat(np.stack([kp0, kf0], axis=1)[:, :, None], wlen // kspace, axis=2)
    n_act = min(n_active, len(pool))
    base_mse = np.maximum(base_ce2.sum(axis=1), 1e-300)
    kp, kf = kp0.copy(), kf0.copy()
    kp_out, kf_out = np.empty((n, 3)), np.empty((n, 3))
    u_out = np.empty((n_act, n, 3))
    stats = np.zeros(4, dtype=np.int64)
    sse = np.zeros(len(pool))
    excess = np.zeros(len(pool))
    # running squared errors of the schedule and of the baseline per pool plant (decayed)
    run_s = np.zeros(len(pool))
    run_b = np.zeros(len(pool))
    # before any sample: the plants where the baseline's error is largest relative to the
    # nominal one (the plants furthest from the nominal behaviour)
    score = base_mse / base_mse[0]
    active_log = []
    for k0 in range(0, n, refresh):
        k1 = min(k0 + refresh, n)
        others = np.argsort(-score[1:], kind="stable")[:n_act - 1] + 1
        act = np.concatenate([[0], others]).astype(np.int64)
        active_log.append(tuple(int(i) for i in act))
        w = np.empty(n_act)
        w[0] = defaults.ROBUST_NOMINAL_WEIGHT if n_act > 1 else 1.0
        w[1:] = (1.0 - defaults.ROBUST_NOMINAL_WEIGHT) / max(n_act - 1, 1) * (
            base_mse[0] / base_mse[act[1:]])
        st = np.ascontiguousarray(states[act])
        uh = np.ascontiguousarray(u_hist[act])
        mpc_multi_chunk(k0, k1, pd, pdT_pad, vdT_pad, np.ascontiguousarray(params[act]), st, kp,
                        kf, adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi, kp0, kf0, vmax, amax,
                        jmax, te, uh, wlen, kspace, commit, defaults.MPC_ITERATIONS,
                        *defaults.MPC_TRUST, options.lam_value, options.anchor_value, tree,
                        win_lo, win_hi, is_moving, feed_pad, live_pad, points, kp_out, kf_out,
                        u_out, stats, defaults.MPC_STOP, defaults.MPC_SETTLED_M, ferror_max,
                        defaults.MPC_RESTORE, defaults.MPC_SETTLE_TAIL, w)
        # every pool plant along the committed gains (the active ones too: one code path)
        _advance_pool(states, params, pdT, vdT, kp_out, kf_out, k0, k1, is_moving, pd, tree,
                      win_lo, win_hi, feed, np.asarray(lim.vmax_m_s, dtype=np.float64),
                      np.asarray(lim.amax_m_s2, dtype=np.float64),
                      np.asarray(lim.jmax_m_s3, dtype=np.float64), nominal.ferror_limits(), te,
                      u_hist, sse, excess)
        decay = defaults.ROBUST_SCORE_DECAY
        run_s = decay * run_s + sse
        run_b = decay * run_b + base_ce2[:, k0:k1].sum(axis=1)
        floor = 1e-6 * base_mse.max() / n * refresh  # chunks with (almost) no error: no signal
        score = (run_s + floor) / (run_b + floor)
        score = np.where(excess > 0.0, 1e6 * (1.0 + excess), score)  # a broken limit first
    return MultiSearch(kp=kp_out, kf=kf_out, fallbacks=int(stats[STAT_FALLBACK]),
                       windows=int(stats[STAT_WINDOWS]), active=active_log,
                       time_s=time.perf_counter() - t0)
