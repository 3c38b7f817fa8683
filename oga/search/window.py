"""Full mode: the gain trajectory over a moving window, planned by sequential QP, compiled.

The paper's search (:mod:`oga.search.paper`) tries five increments per sample, each
held over the horizon. On jerk-limited setpoints that held-gain prediction
misleads it: it moves a gain far while an axis is idle (the kinematic bound is
void there), then cannot bring it back once the axis moves (the bound is tight
there). Full mode instead plans each adjusted gain as a *trajectory* over a
window of ``w`` samples: a quadratic B-spline with control points ``kspace``
samples apart, continuous in value and slope with the gains already applied (a
slope that jumps is a jerk spike of the command ``Kf vd + Kp e`` at speed; with
piecewise-linear gains the MSE ratios were 1.4 to 30 times higher on the team's
contours), coming to rest one interval before the window's end, and recedes:

1. from the current true state, simulate each axis over the window along the
   current plan on the exact nonlinear model (the nominal prediction) and, in the
   same pass, the derivatives of its predicted positions and velocity commands with
   respect to every free control point of its gains (forward mode,
   :func:`oga.model.tangent.run_tangent`; one pass instead of a re-simulation per point)
   (an axis whose setpoint stands still over the whole window and which has settled
   on it, :data:`oga.defaults.MPC_SETTLED_M`, is not adjusted); where an adjusted
   axis's setpoint comes to rest inside the window, the prediction runs ``tail``
   samples further (:data:`oga.defaults.MPC_SETTLE_TAIL`), the plan's last gains held
   there, and everything below (cost, constraints, line search) covers those samples
   too: the error of an axis settling after a stop is decided by the gains before it
   (on a corner of 25 um segments the ratio fell from 0.51 to 0.30 with it);
2. the predicted contour error of the window's feed samples (those the metric counts:
   not rapids, nothing past the program's end) is linearised around the nominal prediction
   (distance to the line of the nearest path segment, as in :mod:`oga.search.paper`;
   that segment, here and in the line search's exact cost, is the one the replay
   measures against: the exact nearest over the sample's contour-error window,
   :func:`oga.model.contour.nearest_at`. A local walk from the previous sample's segment,
   as this search once did, is not enough: where the planner stops at a sharp
   corner, the standstill's zero-length segments fill the neighbourhood and a point
   leaving along the next segment was measured against the line of the last one,
   an error growing with the travel while the point is on the path; the search then
   held one axis's gains at their bounds and could not raise them again at speed
   within the jerk limit),
   giving a quadratic cost in the control-point changes ``d``:
   ``|E(d)|^2 + lam |steps between points|^2 + anchor mean |c - K_baseline|^2`` (um^2);
3. constraints: every control point inside its gain bounds (the spline is a convex
   combination of them, so the gains stay inside) and inside a trust region
   where the linearisation holds, and eq. 2 on the linearised velocity command
   over the whole window (with a small margin), and likewise the machine's
   following-error limit on the linearised positions where it sets one (below,
   "eq. 2" includes it), at every sample of the program the window covers: rapids and
   dwells too (no contour error counts there, so the cost leaves the gains to the
   smoothness and anchor terms, but the machine runs the table through them); the QP
   is solved exactly by the dual active-set method of Goldfarb and Idnani;
4. exact line search: the full step is simulated exactly from the true state and
   taken if its velocity command meets eq. 2 over the whole window and it lowers the
   window's exact cost below the current plan's (the usual case); otherwise the steps
   scaled by 1/2 and 1/4 are simulated too and, among the scales (0: the current plan)
   whose command meets eq. 2 over the whole window, the one with the least exact cost
   is taken, so an iteration never makes the exact prediction worse; where none does,
   a scale that keeps eq. 2 over the samples committed now and next (the next window's
   fallback), at least now, with the least excess beyond;
5. steps 1-4 are repeated ``iters`` times at most (sequential QP, each linearised
   around the last plan), until the line search keeps the plan or an iteration
   lowers the window's exact cost by less than ``stop``; but while no step keeps
   eq. 2 over the whole window (a limit ahead that the plan cannot meet within the
   trust region: with the trust region alone, such a window could only postpone the
   problem until eq. 2 broke inside a commit), up to ``restore`` more iterations are
   taken, each with a trust region three times wider;
6. the first ``commit`` samples of the plan are applied, the true state is
   advanced with the exact kernel, and the rest of the plan, shifted, starts the
   next window.

Planning a whole window and committing a part of it costs a few window
simulations per sample where re-planning every sample cost about fifty, and the
iterations converge the plan where a single linearised step per sample could not.
Every figure a user sees still comes from the replay in :mod:`oga.verify.replay`.

Several plants at once (:func:`window_search` on a batch of :class:`Plants`, the robust search,
:mod:`oga.search.robust.multi`): every plant's true state is carried along the one plan; steps 1-2
are made on every plant (the weighted Hessians and gradients summed), step 3 has every
plant's limit rows, step 4 the weighted exact cost and the largest excess over the plants.
One plant (:func:`one_plant`) is its case S = 1, with the arithmetic of the one-plant search.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from oga import defaults
from oga.model.contour import ce2_at, contour_offset, path_index
from oga.model.kinematics import eq2_excess
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM
from oga.search.paper import Gains, apply_gains
from oga.model.simulate import run
from oga.model.tangent import run_tangent

__all__ = ["window_search", "program_of", "settings_of", "chunk_of", "one_plant", "carry_of",
           "Program", "Plants", "Gains", "Settings", "Carry", "STAT_FALLBACK", "STAT_WINDOWS",
           "STAT_SCALED", "STAT_QP_SHORT"]

STAT_FALLBACK = 0  # iterations where no step kept eq. 2 on the samples to be committed
STAT_WINDOWS = 1  # window simulations
STAT_SCALED = 2  # iterations whose QP step was scaled down by the exact check
STAT_QP_SHORT = 3  # iterations whose QP stopped short of the optimum (the line search decides)

_C = KP_SI_PER_M_MIN_PER_MM
_M2_TO_UM2 = 1e12
#: Share of the eq. 2 limits the linearised constraints may use (the exact check uses 1).
_LIN_MARGIN = 0.95
#: Growth of the trust region per restoring iteration (:data:`oga.defaults.MPC_RESTORE`).
_WIDEN = 3.0


@njit(cache=True, nogil=True)
def _chol(a):
    """Lower Cholesky factor of a symmetric positive definite matrix (a copy)."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        _chol_row(a, low, i)
    return low


@njit(cache=True, inline="always")
def _chol_row(a, low, i):
    """Row ``i`` of the lower Cholesky factor of ``a`` (lower triangle read) into ``low``,
    from its rows ``0 .. i - 1``: a factor grows by a row as its matrix by a row and a
    column, and a row depends on nothing below it."""
    for j in range(i):
        s = a[i, j]
        for k in range(j):
            s -= low[i, k] * low[j, k]
        low[i, j] = s / low[j, j]
    s = a[i, i]
    for k in range(i):
        s -= low[i, k] * low[i, k]
    low[i, i] = np.sqrt(max(s, 1e-300))


@njit(cache=True, nogil=True)
def _chol_solve(low, b, out):
    """Solve ``L L' out = b``."""
    n = low.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= low[i, k] * out[k]
        out[i] = s / low[i, i]
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, n):
            s -= low[k, i] * out[k]
        out[i] = s / low[i, i]


class _Active(NamedTuple):
    """The working set of :func:`_qp_active_set` (``nv`` variables, at most ``nv`` rows)."""

    low: np.ndarray  # (nv, nv) Cholesky factor of P
    act: np.ndarray  # (nv,) active rows
    sgn: np.ndarray  # (nv,) +1: a.x >= lo active, -1: a.x <= hi active
    g: np.ndarray  # (nv, nv) g[c] = P^-1 n_c, n_c = sgn_c a_act[c]
    u: np.ndarray  # (nv,) multipliers of the active rows (>= 0)
    gram: np.ndarray  # (nv, nv) N' P^-1 N of the active rows
    low_g: np.ndarray  # (nv, nv) its Cholesky factor, valid in its first n_low rows
    gp: np.ndarray  # (nv,) P^-1 n_p of the row being added
    z: np.ndarray  # (nv,) the primal step direction
    rowv: np.ndarray  # (nv,) n_p, the row being added (signed)


@njit(cache=True, nogil=True)
def _qp_active_set(p, q, a, lo, hi, m, c0, c1, x):
    """Minimise ``x'Px/2 + q'x`` subject to ``lo <= A x <= hi`` (first ``m`` rows of A).

    Row ``r`` of A is read only in columns ``c0[r] .. c1[r] - 1``: its other entries are
    taken as zero, whatever the array holds there.

    The dual active-set method of Goldfarb and Idnani (1983): start from the
    unconstrained minimum, take the most violated row, and move primal and dual
    variables together (partial steps drop a row whose multiplier reaches zero,
    a full step adds the violated row) until no row is violated. Every step is
    computed through ``P^-1`` on one Cholesky factor. Rows should be scaled to
    unit-order bounds.

    Returns True with the optimum in ``x``; False if the rows cannot all be met
    (or the iteration limit is hit), ``x`` then holding the last iterate. The caller
    only proposes that step: the exact line search on the model decides.
    """
    nv = p.shape[0]
    if nv == 0:
        return True
    low = _chol(p)
    nq = np.empty(nv)
    for i in range(nv):
        nq[i] = -q[i]
    _chol_solve(low, nq, x)  # unconstrained minimum
    st = _Active(low, np.empty(nv, dtype=np.int64), np.empty(nv, dtype=np.int64),
                 np.empty((nv, nv)), np.zeros(nv), np.empty((nv, nv)), np.zeros((nv, nv)),
                 np.empty(nv), np.empty(nv), np.empty(nv))
    na = 0
    n_low = 0
    for _outer in range(10 * (m + nv) + 10):
        pr, ps = _most_violated(a, lo, hi, m, c0, c1, x)
        if pr < 0:
            return True
        st.rowv[:] = 0.0
        for i in range(c0[pr], c1[pr]):
            st.rowv[i] = ps * a[pr, i]
        bp = lo[pr] if ps > 0 else -hi[pr]
        _chol_solve(low, st.rowv, st.gp)
        na, n_low = _add_row(st, x, pr, ps, bp, na, n_low)
        if na < 0:
            return False
    return False


@njit(cache=True, nogil=True)
def _most_violated(a, lo, hi, m, c0, c1, x):
    """The most violated row (``s = n.x - b < 0``) and its side (+1 ``lo``, -1 ``hi``), or
    ``(-1, 0)`` when every row holds."""
    pr = -1
    ps = 0
    worst = -1e-10
    for r in range(m):
        t = 0.0
        for i in range(c0[r], c1[r]):
            t += a[r, i] * x[i]
        if t - lo[r] < worst:
            worst = t - lo[r]
            pr = r
            ps = 1
        if hi[r] - t < worst:
            worst = hi[r] - t
            pr = r
            ps = -1
    return pr, ps


@njit(cache=True, nogil=True)
def _add_row(st, x, pr, ps, bp, na, n_low):
    """Move primal and dual variables until row ``pr`` (side ``ps``, bound ``bp``) is met
    and joins the ``na`` active rows, dropping those whose multiplier reaches zero on the
    way. Returns ``(na, n_low)``, ``na`` -1 where the rows cannot all be met."""
    nv = x.shape[0]
    up = 0.0
    for _inner in range(nv + 2):
        r, n_low = _dual_step(st, na, n_low)
        if n_low < 0:
            return -1, 0
        t1 = np.inf  # partial step: a multiplier reaches zero
        k = -1
        for c in range(na):
            if r[c] > 1e-14:
                ratio = st.u[c] / r[c]
                if ratio < t1:
                    t1 = ratio
                    k = c
        zn = 0.0
        sp = -bp
        for i in range(nv):
            zn += st.z[i] * st.rowv[i]
            sp += st.rowv[i] * x[i]
        t2 = -sp / zn if zn > 1e-14 else np.inf  # full step: the row becomes met
        t = min(t1, t2)
        if t == np.inf:
            return -1, 0  # the rows cannot all be met
        if t2 < np.inf:
            for i in range(nv):
                x[i] += t * st.z[i]
        for c in range(na):
            st.u[c] -= t * r[c]
        up += t
        if t2 <= t1:  # full step: add the row
            if na == nv:  # dependent rows: no room for another
                return -1, 0
            _append_row(st, pr, ps, up, na)
            return na + 1, n_low
        na -= 1  # partial step: drop row k
        n_low = min(n_low, k)  # the factor's rows from k on change
        _drop_row(st, k, na)
    return -1, 0


@njit(cache=True, nogil=True)
def _dual_step(st, na, n_low):
    """``r = (N' P^-1 N)^-1 N' P^-1 n_p`` and, into ``st.z``, ``P^-1 n_p - P^-1 N r``; the
    Gram matrix's factor brought up to date. Returns ``(r, n_low)``, ``n_low`` -1 where the
    active rows are dependent."""
    nv = st.z.shape[0]
    r = np.zeros(na)
    if na > 0:
        rhs = np.empty(na)
        for c in range(na):
            t = 0.0
            for i in range(nv):
                t += st.g[c, i] * st.rowv[i]  # n_c' P^-1 n_p = g_c . n_p (P symmetric)
            rhs[c] = t
        while n_low < na:  # the rows added since the last step
            _chol_row(st.gram, st.low_g, n_low)
            n_low += 1
        for c in range(na):
            if st.low_g[c, c] <= 1e-150:  # dependent active rows
                return r, -1
        _chol_solve(st.low_g[:na, :na], rhs, r)
    for i in range(nv):
        t = st.gp[i]
        for c in range(na):
            t -= st.g[c, i] * r[c]
        st.z[i] = t
    return r, n_low


@njit(cache=True, nogil=True)
def _append_row(st, pr, ps, up, na):
    """Row ``pr`` (side ``ps``, multiplier ``up``) becomes active row ``na``."""
    nv = st.z.shape[0]
    st.act[na] = pr
    st.sgn[na] = ps
    st.u[na] = up
    for i in range(nv):
        st.g[na, i] = st.gp[i]
    for c in range(na + 1):
        t = 0.0
        for i in range(nv):
            t += st.rowv[i] * st.g[c, i]
        st.gram[na, c] = t
        st.gram[c, na] = t


@njit(cache=True, nogil=True)
def _drop_row(st, k, na):
    """Drop active row ``k``: the last active row (now index ``na``) takes its place."""
    nv = st.z.shape[0]
    st.act[k] = st.act[na]
    st.sgn[k] = st.sgn[na]
    st.u[k] = st.u[na]
    for i in range(nv):
        st.g[k, i] = st.g[na, i]
    for c in range(na):
        st.gram[k, c] = st.gram[na, c]
    for c in range(na):
        st.gram[c, k] = st.gram[k, c]
    if k < na:
        st.gram[k, k] = st.gram[na, na]


@njit(cache=True, nogil=True)
def _plan_at(points, a, g, tau, kspace):
    """Gain ``g`` (0 Kp, 1 Kf) of axis ``a`` at ``tau`` samples after the last applied one.

    A uniform quadratic B-spline (continuous value and slope) whose control points
    ``c_{-1}, c_0, c_1, ...`` are ``points[a, g, 0], points[a, g, 1], ...``, ``kspace``
    samples apart, the last one repeated beyond the array (the plan comes to rest).
    """
    last = points.shape[2] - 1
    j0, j1, j2, w0, w1, w2 = _spline_weights(tau, kspace, last)
    return w0 * points[a, g, j0] + w1 * points[a, g, j1] + w2 * points[a, g, j2]


@njit(cache=True, inline="always")
def _spline_weights(tau, kspace, last):
    """The three control points (indices, the last one repeated beyond ``last``) and their
    weights in the uniform quadratic B-spline of :func:`_plan_at` at ``tau``."""
    m = tau // kspace
    f = (tau - m * kspace) / kspace
    return (min(m, last), min(m + 1, last), min(m + 2, last),
            0.5 * (1.0 - f) ** 2, 0.5 + f - f * f, 0.5 * f * f)


@njit(cache=True, nogil=True)
def _gains(points, a, g, w, kspace, out):
    """The plan's gain at every window sample ``i`` (``tau = i + 1``) into ``out[:w]``."""
    for i in range(w):
        out[i] = _plan_at(points, a, g, i + 1, kspace)


@njit(cache=True, nogil=True)
def _basis(jk, tau, kspace, last):
    """Weight of control point ``jk`` in :func:`_plan_at` at ``tau`` (the derivative of the
    gain with respect to that point)."""
    j0, j1, j2, w0, w1, w2 = _spline_weights(tau, kspace, last)
    return w0 * (j0 == jk) + w1 * (j1 == jk) + w2 * (j2 == jk)


@njit(cache=True, inline="always")
def _same_plan(points, other, a):
    """Whether axis ``a``'s control points are the same in both plans (bit for bit): its
    prediction from the same state is then the same too, and need not be simulated again."""
    for g in range(2):
        for j in range(points.shape[2]):
            if points[a, g, j] != other[a, g, j]:
                return False
    return True


@njit(cache=True, inline="always")
def _keep_row(m, lo_r, hi_r, reach, c0, c1, alo, ahi, col0, col1):
    """Keep constraint row ``m`` (its coefficients already in place) with bounds ``lo_r <=
    row . d <= hi_r`` over columns ``c0 .. c1 - 1`` if the trust region can reach a bound
    (``reach``: the row's largest change over it); returns the next free row."""
    if reach > min(-lo_r, hi_r) * (1.0 - 1e-12):
        alo[m] = lo_r
        ahi[m] = hi_r
        col0[m] = c0
        col1[m] = c1
        return m + 1
    return m


@njit(cache=True, nogil=True)
def _window_cost(pd, tree, win_lo, win_hi, k, w, trial, feed):
    """Squared contour error (um^2) of the predicted positions ``trial`` (3, w), summed
    over the window's feed samples (the metric's: no rapid, nothing past the end)."""
    cost = 0.0
    j = -1
    for i in range(w):
        c = k + i
        if feed[c]:
            d2, j = ce2_at(pd, tree, win_lo[c], win_hi[c], c, trial[0, i], trial[1, i],
                           trial[2, i], j)
            cost += d2
    return cost * _M2_TO_UM2



class Program(NamedTuple):
    """The program every plant runs, padded by ``w + tail + 1`` samples past its end.

    ``pd`` (N, 3) the setpoints; ``pdT``, ``vdT`` (3, N + pad) positions and velocities per
    axis; ``tree, win_lo, win_hi`` the path's index and every sample's contour-error window
    (:func:`oga.model.contour.path_index`); ``moving`` (3,) bool the axes that move; ``feed``
    (bool, padded) the samples where the contour error counts (feed moves; not rapids, not
    the padding), ``live`` (likewise) those where eq. 2 and the following-error limit apply
    (every sample of the program, rapids included, as in :mod:`oga.verify.replay`).
    """

    pd: np.ndarray
    pdT: np.ndarray
    vdT: np.ndarray
    tree: tuple
    win_lo: np.ndarray
    win_hi: np.ndarray
    moving: np.ndarray
    feed: np.ndarray
    live: np.ndarray


class Plants(NamedTuple):
    """``S`` scenario plants of the same axes: ``params`` (S, 3, P) the packed kernel
    parameters (:func:`oga.model.simulate.axis_params`); ``vmax``, ``amax``, ``jmax``,
    ``ferror_max`` (S, 3) each plant's limits (``inf``: no following-error limit);
    ``weights`` (S,) the cost's weight of each; ``floor`` (S, 3, 2, M) per program sample
    the least acceleration and jerk limit (m/s^2, m/s^3) each plant keeps at that sample,
    whatever ``amax``, ``jmax`` (the robust search's baseline there; M = 0: none)."""

    params: np.ndarray
    vmax: np.ndarray
    amax: np.ndarray
    jmax: np.ndarray
    ferror_max: np.ndarray
    weights: np.ndarray
    floor: np.ndarray


class Settings(NamedTuple):
    """The search's scalars (see :func:`window_search`, built by :func:`settings_of`)."""

    te: float
    w: int
    kspace: int
    commit: int
    iters: int
    trust_kp: float
    trust_kf: float
    lam: float
    anchor: float
    stop: float
    settled: float
    restore: int
    tail: int
    hold_in_rapids: bool


class Carry(NamedTuple):
    """What the search changes in place and carries between calls: ``states`` (S, 3, Z),
    ``kp``, ``kf`` (3,) the gains applied last, ``u_hist`` (S, 3, 2), ``points`` the plan's
    control points (3, 2, w // kspace), ``kp_out``, ``kf_out`` (N, 3) the schedule,
    ``u_out`` (S, N, 3) the commands, ``stats`` (4,) int64 the counters (``STAT_*``)."""

    states: np.ndarray
    kp: np.ndarray
    kf: np.ndarray
    u_hist: np.ndarray
    points: np.ndarray
    kp_out: np.ndarray
    kf_out: np.ndarray
    u_out: np.ndarray
    stats: np.ndarray


class Work(NamedTuple):
    """One search's layout of free control points and its work buffers (:func:`_workspace`).

    Free point ``v`` (``nv`` of them, ``nk`` per gain) is point ``point[v]`` of gain
    ``gain[v]`` (0 Kp, 1 Kf) of axis ``axis[v]``; ``prev[v]`` the same gain's previous free
    point or -1, ``start[v]`` the first window sample its basis reaches; an axis's points
    are ``lo[a] .. hi[a] - 1``; ``dir_kp``, ``dir_kf`` (wmax, nv) the gains' change per unit
    of each point, per window sample."""

    w: int
    wmax: int
    kspace: int
    nk: int
    nv: int
    axis: np.ndarray
    gain: np.ndarray
    point: np.ndarray
    prev: np.ndarray
    start: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    dir_kp: np.ndarray
    dir_kf: np.ndarray
    idle: np.ndarray  # (3,) bool: the axis is not adjusted in this window
    p0: np.ndarray  # (S, 3, wmax) nominal positions along the plan
    u0: np.ndarray  # (S, 3, wmax) nominal commands
    sp: np.ndarray  # (S, wmax, nv) d p0 / d point, m per unit
    su: np.ndarray  # (S, wmax, nv) d u0 / d point, m/s per unit
    nominal_points: np.ndarray  # per axis, the plan of its nominal p0, u0 (NaN: none)
    trial: np.ndarray  # (S, 3, wmax) positions of a line-search step
    trial_points: np.ndarray
    mq: np.ndarray  # (3, wmax) P dq per axis
    spp_buf: np.ndarray  # sp's columns weighted by P's entries for one row axis
    proj: np.ndarray  # (3, 3, wmax) P = I - t t' per window sample
    dq: np.ndarray  # (wmax, 3) offset from the nearest path point
    tang: np.ndarray  # (wmax, 3) unit tangent of the nearest segment
    pmat: np.ndarray  # (nv, nv) the QP's Hessian
    qvec: np.ndarray  # (nv,) its gradient
    amat: np.ndarray  # (rows, nv) constraint rows
    alo: np.ndarray
    ahi: np.ndarray
    col0: np.ndarray
    col1: np.ndarray
    x: np.ndarray  # (nv,) the QP's step
    trust: np.ndarray  # (nv,) the trust region per point
    kpa: np.ndarray  # (3, wmax) each axis's gains along the plan simulated
    kfa: np.ndarray
    scratch: np.ndarray  # (S, 3, Z) one state per simulation
    tmp_u: np.ndarray  # (S, 3, wmax) commands of a line-search step
    plan_kp: np.ndarray  # (3, wmax) the gains committed
    plan_kf: np.ndarray
    runs: np.ndarray  # (3,) int64 the axes simulated by a parallel pass
    cost_s: np.ndarray  # (S,) each plant's window cost of a line-search step



@njit(cache=True, nogil=True)
def _step_points(points, scale, x, work, gains):
    """Add ``scale * x`` to the free points in place, each held inside its gain's bounds."""
    for v in range(work.nv):
        a = work.axis[v]
        g = work.gain[v]
        jk = work.point[v]
        val = points[a, g, jk] + scale * x[v]
        if g == 0:
            val = min(max(val, gains.kp_lo[a]), gains.kp_hi[a])
        else:
            val = min(max(val, gains.kf_lo[a]), gains.kf_hi[a])
        points[a, g, jk] = val


@njit(cache=True, nogil=True)
def _plan_gains(points, a, w, kspace, kpa, kfa):
    """The plan's Kp (1/s) and Kf of axis ``a`` at every window sample, into ``kpa``, ``kfa``."""
    _gains(points, a, 0, w, kspace, kpa)
    _gains(points, a, 1, w, kspace, kfa)
    for i in range(w):
        kpa[i] *= _C


@njit(cache=True, nogil=True)
def _sim_axis(k, wk, a, s, sp_v, plants, work, states, out_p, out_u):
    """Exact prediction of axis ``a`` of plant ``s`` (from ``states[s]``) over the window
    along the gains ``work.kpa[a]``, ``work.kfa[a]`` (``sp_v``: the program's ``(pdT, vdT)``):
    positions into ``out_p``, commands into ``out_u``."""
    work.scratch[s, a] = states[s, a]
    run(work.scratch[s, a], plants.params[s, a], sp_v[0][a, k:k + wk], sp_v[1][a, k:k + wk],
        work.kpa[a], work.kfa[a], out_p, out_u)


@njit(cache=True, nogil=True)
def _predict_one(k, wk, a, s, sp_v, plants, work, states):
    """Plant ``s``'s nominal prediction of axis ``a`` and its derivatives (:func:`_predict`)."""
    lo_v, hi_v = work.lo[a], work.hi[a]
    if work.idle[a] or lo_v == hi_v:
        _sim_axis(k, wk, a, s, sp_v, plants, work, states, work.p0[s, a], work.u0[s, a])
        work.sp[s, :, lo_v:hi_v] = 0.0
        work.su[s, :, lo_v:hi_v] = 0.0
        return
    work.scratch[s, a] = states[s, a]
    run_tangent(work.scratch[s, a], plants.params[s, a],
                (sp_v[0][a, k:k + wk], sp_v[1][a, k:k + wk], work.kpa[a], work.kfa[a],
                 work.dir_kp[:, lo_v:hi_v], work.dir_kf[:, lo_v:hi_v]),
                work.start[lo_v:hi_v],
                (work.p0[s, a], work.u0[s, a], work.sp[s, :, lo_v:hi_v], work.su[s, :, lo_v:hi_v]))


@njit(cache=True, nogil=True)
def _each_run(k, wk, prog, plants, work, states, n_run, nominal):
    """The simulations of one pass, every plant's of the axes ``work.runs[:n_run]``:
    ``nominal`` the predictions and derivatives of :func:`_predict`, else the line-search
    step's (:func:`_trial_excess`).

    One thread: a window's work (a few plants and axes of 200 samples) is too small for
    numba's parallel loops, whose launches cost more than they saved (ucp710, the nominal
    search on 2 threads against 1: 1.2-1.8x the wall time on the six benchmark programs; the
    robust search's window phase 1.1-2.0x), and the serial kernel is as fast as the parallel
    one on one thread or faster (helix_r20 0.31 -> 0.25 s, cncjs_toolpath 2.38 -> 2.28 s)."""
    n_s = states.shape[0]
    pdT, vdT = prog.pdT, prog.vdT
    for item in range(n_run * n_s):
        a = work.runs[item // n_s]
        s = item % n_s
        if nominal:
            _predict_one(k, wk, a, s, (pdT, vdT), plants, work, states)
        else:
            _sim_axis(k, wk, a, s, (pdT, vdT), plants, work, states, work.trial[s, a],
                      work.tmp_u[s, a])


@njit(cache=True, nogil=True)
def _each_cost(k, wk, pd, tree, win_lo, win_hi, feed, trial, cost_s):
    """Every plant's window cost of the line-search step's ``trial`` (S, 3, wmax) into
    ``cost_s`` (S,) (the caller sums them in the plants' order)."""
    for s in range(trial.shape[0]):
        cost_s[s] = _window_cost(pd, tree, win_lo, win_hi, k, wk, trial[s], feed)


@njit(cache=True, nogil=True)
def _layout(prog, gains, cfg, nk):
    """The free control points' layout of :class:`Work`: ``(nv, axis, gain, point, prev,
    start, lo, hi, dir_kp, dir_kf)``."""
    var_axis = np.empty(6 * nk, dtype=np.int64)
    var_gain = np.empty(6 * nk, dtype=np.int64)
    var_point = np.empty(6 * nk, dtype=np.int64)
    var_prev = np.empty(6 * nk, dtype=np.int64)
    var_start = np.empty(6 * nk, dtype=np.int64)
    # variables per axis in the order of their first sample (point, then gain): the order of
    # the tangent directions, so that run_tangent writes each axis's block of sp, su directly
    nv = 0
    for a in range(3):
        if not prog.moving[a]:
            continue
        n_gain = 0
        for g in range(2):
            if (g == 0 and gains.adj_kp[a]) or (g == 1 and gains.adj_kf[a]):
                n_gain += 1
        for j in range(2, nk + 2):
            for g in range(2):
                if (g == 0 and gains.adj_kp[a]) or (g == 1 and gains.adj_kf[a]):
                    var_axis[nv] = a
                    var_gain[nv] = g
                    var_point[nv] = j
                    var_prev[nv] = nv - n_gain if j > 2 else -1
                    var_start[nv] = (j - 2) * cfg.kspace
                    nv += 1
    var_lo = np.zeros(3, dtype=np.int64)
    var_hi = np.zeros(3, dtype=np.int64)
    for v in range(nv - 1, -1, -1):
        var_lo[var_axis[v]] = v
    for v in range(nv):
        var_hi[var_axis[v]] = v + 1
    # the gain's change per unit of each free point: its B-spline basis function (Kp in 1/s
    # per (m/min)/mm), per window sample
    wmax = cfg.w + cfg.tail
    dir_kp = np.zeros((wmax, nv))
    dir_kf = np.zeros((wmax, nv))
    for v in range(nv):
        for i in range(wmax):
            b = _basis(var_point[v], i + 1, cfg.kspace, nk + 1)
            if var_gain[v] == 0:
                dir_kp[i, v] = _C * b
            else:
                dir_kf[i, v] = b
    return (nv, var_axis, var_gain, var_point, var_prev, var_start, var_lo, var_hi, dir_kp,
            dir_kf)


@njit(cache=True, nogil=True)
def _workspace(prog, plants, gains, cfg, carry):
    """The layout of the free control points and the work buffers of one search."""
    points = carry.points
    nk = points.shape[2] - 2  # free control points per gain: indices 2 .. nk + 1
    nv, axis, gain, point, prev, start, lo, hi, dir_kp, dir_kf = _layout(prog, gains, cfg, nk)
    n_s = plants.params.shape[0]
    wmax = cfg.w + cfg.tail
    max_rows = nv + 4 * 3 * wmax * n_s  # bounds; eq. 2 (v, a, j), following error per sample, plant
    trial = np.empty((n_s, 3, wmax))
    for s in range(n_s):
        for a in range(3):
            if not prog.moving[a]:
                trial[s, a, :] = carry.states[s, a, 0]
    return Work(
        cfg.w, wmax, cfg.kspace, nk, nv, axis, gain, point, prev, start, lo, hi, dir_kp, dir_kf,
        np.ones(3, dtype=np.bool_), np.empty((n_s, 3, wmax)), np.empty((n_s, 3, wmax)),
        np.zeros((n_s, wmax, nv)), np.zeros((n_s, wmax, nv)), np.empty_like(points), trial,
        points.copy(), np.empty((3, wmax)), np.empty(wmax * nv), np.empty((3, 3, wmax)),
        np.empty((wmax, 3)), np.empty((wmax, 3)), np.empty((nv, nv)), np.empty(nv),
        np.zeros((max_rows, nv)), np.empty(max_rows), np.empty(max_rows),
        np.empty(max_rows, dtype=np.int64), np.empty(max_rows, dtype=np.int64), np.zeros(nv),
        np.empty(nv), np.empty((3, wmax)), np.empty((3, wmax)),
        np.empty((n_s, 3, carry.states.shape[2])), np.empty((n_s, 3, wmax)), np.empty((3, wmax)),
        np.empty((3, wmax)), np.zeros(3, dtype=np.int64), np.empty(n_s),
    )


@njit(cache=True, nogil=True)
def _window_len(k, prog, work):
    """The samples window ``k`` covers: ``w``, or ``wmax`` where an adjusted axis's setpoint
    comes to rest inside it (look ``tail`` samples further, the plan's last gains held, to
    see it settle)."""
    w = work.w
    for a in range(3):
        if prog.moving[a] and work.lo[a] < work.hi[a] and prog.vdT[a, k + w - 1] == 0.0:
            for i in range(w - 1):
                if prog.vdT[a, k + i] != 0.0:
                    return work.wmax
    return w


@njit(cache=True, nogil=True)
def _mark_idle(k, wk, prog, cfg, carry, idle):
    """``idle[a]``: axis ``a``'s setpoint stands over the window and the axis has settled on
    it on every plant (:data:`oga.defaults.MPC_SETTLED_M`); it is not adjusted."""
    states = carry.states
    for a in range(3):
        idle[a] = True
        for s in range(states.shape[0]):
            if abs(states[s, a, 0] - prog.pdT[a, k]) > cfg.settled:
                idle[a] = False
        if prog.moving[a]:
            for i in range(wk):
                if prog.vdT[a, k + i] != 0.0 or prog.pdT[a, k + i] != prog.pdT[a, k]:
                    idle[a] = False
                    break


@njit(cache=True, nogil=True)
def _holds(k, wk, prog, cfg):
    """Whether the window commits the plan as it is: ``hold_in_rapids`` and every sample
    of the window a rapid's."""
    if not cfg.hold_in_rapids:
        return False
    for i in range(wk):
        if prog.feed[k + i] or not prog.live[k + i]:
            return False
    return True


@njit(cache=True, nogil=True)
def _predict(k, wk, prog, plants, work, carry):
    """Step 1: every plant's nominal prediction along the plan and, in the same pass, its
    derivatives with respect to every free control point of the axis (forward mode);
    an axis whose plan is unchanged since its last prediction keeps it."""
    points, states = carry.points, carry.states
    n_run = 0
    for a in range(3):
        if not prog.moving[a]:
            for s in range(states.shape[0]):
                for i in range(wk):
                    work.p0[s, a, i] = states[s, a, 0]
                    work.u0[s, a, i] = 0.0
            continue
        if _same_plan(points, work.nominal_points, a):
            continue  # p0, u0 and the axis's columns of sp, su still hold
        work.nominal_points[a] = points[a]
        _plan_gains(points, a, wk, work.kspace, work.kpa[a], work.kfa[a])
        work.runs[n_run] = a
        n_run += 1
    carry.stats[STAT_WINDOWS] += n_run * states.shape[0]
    _each_run(k, wk, prog, plants, work, states, n_run, True)


@njit(cache=True, nogil=True)
def _offsets(k, wk, prog, p0s, work):
    """Offsets ``work.dq`` of the predicted positions ``p0s`` (3, wk) from their nearest path
    points and that segment's tangents ``work.tang`` (zero off the feed samples: weight 0,
    as in the metric); returns the squared contour error summed (m^2)."""
    pd = prog.pd
    j = -1
    d2_s = 0.0
    for i in range(wk):
        c = k + i
        if not prog.feed[c]:
            for a in range(3):
                work.dq[i, a] = 0.0
                work.tang[i, a] = 0.0
            continue
        j, d2_s, dx, dy, dz, tx, ty, tz = contour_offset(pd, prog.tree, prog.win_lo[c],
                                                         prog.win_hi[c], c, c, p0s[:, i], j, d2_s)
        work.dq[i, 0], work.dq[i, 1], work.dq[i, 2] = dx, dy, dz
        work.tang[i, 0], work.tang[i, 1], work.tang[i, 2] = tx, ty, tz
    return d2_s


@njit(cache=True, nogil=True)
def _gauss_newton(k, wk, prog, s, wt, work):
    """Add plant ``s``'s weighted Hessian ``2 S' P S`` and gradient ``2 S' P dq`` of its
    linearised cost ``|P (dq + S d)|^2`` (P = I - t t' per sample; one small matrix product
    per axis's block of rows; the factor 2 and the unit applied by the caller)."""
    proj, mq, dq, tang = work.proj, work.mq, work.dq, work.tang
    sps = work.sp[s]
    nv = work.nv
    for a in range(3):
        for b in range(3):
            for i in range(wk):
                eye = 1.0 if a == b and prog.feed[k + i] else 0.0
                proj[a, b, i] = eye - tang[i, a] * tang[i, b]
        for i in range(wk):
            mq[a, i] = proj[a, 0, i] * dq[i, 0] + proj[a, 1, i] * dq[i, 1] + proj[a, 2, i] * dq[i, 2]
    for a in range(3):  # axis a's rows, from its own columns on: S_a' (P_a. o S_b)
        lo_v, hi_v = work.lo[a], work.hi[a]
        if lo_v == hi_v:
            continue
        spp = work.spp_buf[:wk * (nv - lo_v)].reshape((wk, nv - lo_v))
        for i in range(wk):
            for u_ in range(lo_v, nv):
                spp[i, u_ - lo_v] = sps[i, u_] * proj[a, work.axis[u_], i]
        s_a = np.ascontiguousarray(sps[:wk, lo_v:hi_v].T)
        if s == 0:
            work.pmat[lo_v:hi_v, lo_v:] = wt * np.dot(s_a, spp)
            work.qvec[lo_v:hi_v] = wt * np.dot(s_a, mq[a, :wk])
        else:
            work.pmat[lo_v:hi_v, lo_v:] += wt * np.dot(s_a, spp)
            work.qvec[lo_v:hi_v] += wt * np.dot(s_a, mq[a, :wk])


@njit(cache=True, nogil=True)
def _linearise(k, wk, prog, plants, work):
    """Step 2: the contour error linearised around each plant's nominal prediction, the
    weighted Gauss-Newton Hessian and gradient summed into ``work.pmat``, ``work.qvec``
    (um^2). Returns the plan's weighted exact window cost (m^2, the line search's scale 0)."""
    nominal_d2 = 0.0
    for s in range(plants.params.shape[0]):
        d2_s = _offsets(k, wk, prog, work.p0[s], work)
        _gauss_newton(k, wk, prog, s, plants.weights[s], work)
        nominal_d2 += plants.weights[s] * d2_s
    nv = work.nv
    for v in range(nv):
        work.qvec[v] *= 2.0 * _M2_TO_UM2
        for u_ in range(v, nv):
            work.pmat[v, u_] *= 2.0 * _M2_TO_UM2
            work.pmat[u_, v] = work.pmat[v, u_]
    return nominal_d2


@njit(cache=True, nogil=True)
def _regularise(points, gains, cfg, work):
    """The smoothness (``lam`` on the steps between control points) and anchor (mean over
    them, to the baseline gains) terms of the QP's cost."""
    lam, anchor, nk = cfg.lam, cfg.anchor, work.nk
    pmat, qvec = work.pmat, work.qvec
    for v in range(work.nv):
        a = work.axis[v]
        g = work.gain[v]
        jk = work.point[v]
        base = gains.kp_base[a] if g == 0 else gains.kf_base[a]
        kv = points[a, g, jk]
        step_prev = kv - points[a, g, jk - 1]
        pmat[v, v] += 2.0 * lam + 2.0 * anchor / nk
        qvec[v] += 2.0 * lam * step_prev + 2.0 * anchor * (kv - base) / nk
        vp = work.prev[v]
        if vp >= 0:  # the step from the previous free control point
            pmat[v, vp] -= 2.0 * lam
            pmat[vp, v] -= 2.0 * lam
            pmat[vp, vp] += 2.0 * lam
            qvec[vp] -= 2.0 * lam * step_prev


@njit(cache=True, nogil=True)
def _bound_rows(widen, gains, cfg, work, points):
    """Rows 0 .. nv - 1: every free point inside its gain's bounds and the trust region
    (``widen`` times the base one; none for an idle axis), into ``work.trust`` too."""
    for v in range(work.nv):
        a = work.axis[v]
        g = work.gain[v]
        kv = points[a, g, work.point[v]]
        work.amat[v, v] = 1.0
        if g == 0:
            lo_b, hi_b, tr = gains.kp_lo[a] - kv, gains.kp_hi[a] - kv, cfg.trust_kp * widen
        else:
            lo_b, hi_b, tr = gains.kf_lo[a] - kv, gains.kf_hi[a] - kv, cfg.trust_kf * widen
        if work.idle[a]:
            tr = 0.0
        work.alo[v] = max(lo_b, -tr)
        work.ahi[v] = min(hi_b, tr)
        work.col0[v] = v
        work.col1[v] = v + 1
        work.trust[v] = tr
    return work.nv


@njit(cache=True, nogil=True)
def _limit_at(plants, s, a, r, k):
    """Plant ``s``'s eq. 2 limit ``r`` (0 velocity, 1 acceleration, 2 jerk; SI) of axis ``a``
    at program sample ``k``: its ``vmax``, ``amax``, ``jmax``, raised to its floor there."""
    if r == 0:
        return plants.vmax[s, a]
    lim = plants.amax[s, a] if r == 1 else plants.jmax[s, a]
    if k < plants.floor.shape[3]:
        lim = max(lim, plants.floor[s, a, r - 1, k])
    return lim


@njit(cache=True, nogil=True)
def _excess_at(u, hist, plants, s, a, k, te, n, check):
    """:func:`oga.model.kinematics.eq2_excess` of plant ``s``'s axis ``a`` over the window at
    ``k`` (commands ``u``, the two before it ``hist``), at its limits per sample
    (:func:`_limit_at`) where it has a floor."""
    if plants.floor.shape[3] == 0:
        return eq2_excess(u, hist[0], hist[1], plants.vmax[s, a], plants.amax[s, a],
                          plants.jmax[s, a], te, n, check)
    worst, u1, u2 = 0.0, hist[0], hist[1]
    for i in range(n):
        if check[i]:
            worst = max(worst, abs(u[i]) / plants.vmax[s, a] - 1.0,
                        abs(u[i] - u1) / (_limit_at(plants, s, a, 1, k + i) * te) - 1.0,
                        abs(u[i] - 2.0 * u1 + u2) / (_limit_at(plants, s, a, 2, k + i) * te * te)
                        - 1.0)
        u2, u1 = u1, u[i]
    return worst


@njit(cache=True, nogil=True)
def _eq2_rows(m, s, k, wk, prog, plants, te, work, u_hist):
    """Linearised eq. 2 rows (v, a, j at every live window sample) of plant ``s`` (its limits
    ``plants.vmax[s]`` ...), from row ``m`` (kept where the trust region can reach a bound);
    returns the next free row."""
    u0, su, amat, trust = work.u0, work.su, work.amat, work.trust
    for a in range(3):
        lo_v, hi_v = work.lo[a], work.hi[a]
        if not prog.moving[a] or lo_v == hi_v:
            continue
        for r in range(3):
            for i in range(wk):
                if not prog.live[k + i]:  # eq. 2 on every sample of the program
                    continue
                lim = _LIN_MARGIN * _limit_at(plants, s, a, r, k + i)
                for _ in range(r):  # the rows compare |du| with A Te, |d2u| with J Te^2
                    lim *= te
                nominal = u0[s, a, i]
                if r >= 1:
                    nominal -= (1.0 if r == 1 else 2.0) * (u0[s, a, i - 1] if i >= 1 else u_hist[s, a, 0])
                if r == 2:
                    nominal += u0[s, a, i - 2] if i >= 2 else u_hist[s, a, 1 - i]
                scale = 1.0 / lim
                reach = 0.0
                for v in range(lo_v, hi_v):
                    cv = su[s, i, v]
                    if r >= 1 and i >= 1:
                        cv -= (1.0 if r == 1 else 2.0) * su[s, i - 1, v]
                    if r == 2 and i >= 2:
                        cv += su[s, i - 2, v]
                    amat[m, v] = cv * scale
                    reach += abs(cv * scale) * trust[v]
                m = _keep_row(m, -1.0 - nominal * scale, 1.0 - nominal * scale, reach, lo_v, hi_v,
                              work.alo, work.ahi, work.col0, work.col1)
    return m


@njit(cache=True, nogil=True)
def _ferror_rows(m, s, k, wk, prog, plants, work):
    """Linearised following-error rows ``|pd - p0 - S d| <= margin * limit`` of plant ``s``
    (axes with a limit, live samples), from row ``m``; returns the next free row."""
    ferror_max, p0, sp, amat, trust = plants.ferror_max, work.p0, work.sp, work.amat, work.trust
    for a in range(3):
        lo_v, hi_v = work.lo[a], work.hi[a]
        if not prog.moving[a] or lo_v == hi_v or not np.isfinite(ferror_max[s, a]):
            continue
        scale = 1.0 / ferror_max[s, a]
        for i in range(wk):
            if not prog.live[k + i]:
                continue
            nominal = (prog.pdT[a, k + i] - p0[s, a, i]) * scale
            reach = 0.0
            for v in range(lo_v, hi_v):
                amat[m, v] = sp[s, i, v] * scale
                reach += abs(sp[s, i, v] * scale) * trust[v]
            m = _keep_row(m, nominal - _LIN_MARGIN, nominal + _LIN_MARGIN, reach, lo_v, hi_v,
                          work.alo, work.ahi, work.col0, work.col1)
    return m


@njit(cache=True, nogil=True)
def _constraints(k, wk, widen, prog, plants, gains, cfg, work, carry):
    """Step 3: the QP's rows: gain bounds and trust region per control point, then every
    plant's eq. 2 rows, then its following-error rows. Returns the number of rows."""
    m = _bound_rows(widen, gains, cfg, work, carry.points)
    for s in range(plants.params.shape[0]):
        m = _eq2_rows(m, s, k, wk, prog, plants, cfg.te, work, carry.u_hist)
    for s in range(plants.params.shape[0]):  # following error |pd - p0 - S d| <= margin * limit
        m = _ferror_rows(m, s, k, wk, prog, plants, work)
    return m


@njit(cache=True, nogil=True)
def _trial_excess(k, wk, scale, prog, plants, cfg, work, carry):
    """Simulate the trial plan ``work.trial_points`` (scale 0: the plan itself, its nominal
    prediction) on every plant; returns the largest eq. 2 and following-error excess over
    the window, over this commit and the next, and over this commit."""
    n_commit = min(cfg.commit, wk)
    n_next = min(2 * cfg.commit, wk)
    te, u_hist = cfg.te, carry.u_hist
    if scale != 0.0:  # simulate the axes the step changes, on every plant
        n_run = 0
        for a in range(3):
            if prog.moving[a] and not _same_plan(work.trial_points, carry.points, a):
                _plan_gains(work.trial_points, a, wk, work.kspace, work.kpa[a], work.kfa[a])
                work.runs[n_run] = a
                n_run += 1
        carry.stats[STAT_WINDOWS] += n_run * plants.params.shape[0]
        _each_run(k, wk, prog, plants, work, carry.states, n_run, False)
    worst = 0.0  # over the window
    worst_n = 0.0  # over this commit and the next
    worst_c = 0.0  # over the samples to be committed
    fk = prog.live[k:k + wk]
    for s in range(plants.params.shape[0]):  # every plant: the largest excess
        for a in range(3):
            if not prog.moving[a]:
                continue
            tmp_u = work.tmp_u[s, a]  # simulated above
            if scale == 0.0:  # the plan itself: its nominal prediction
                tmp_u = work.u0[s, a]
            elif _same_plan(work.trial_points, carry.points, a):  # the step leaves the axis as is
                work.trial[s, a, :wk] = work.p0[s, a, :wk]
                tmp_u = work.u0[s, a]
            hist = (u_hist[s, a, 0], u_hist[s, a, 1])
            worst = max(worst, _excess_at(tmp_u, hist, plants, s, a, k, te, wk, fk))
            worst_n = max(worst_n, _excess_at(tmp_u, hist, plants, s, a, k, te, n_next, fk))
            worst_c = max(worst_c, _excess_at(tmp_u, hist, plants, s, a, k, te, n_commit, fk))
            fmax = plants.ferror_max[s, a]
            if np.isfinite(fmax):  # the following-error limit, as an excess
                pos = work.p0[s, a] if scale == 0.0 else work.trial[s, a]
                for i in range(wk):
                    ex = abs(prog.pdT[a, k + i] - pos[i]) / fmax - 1.0
                    if fk[i] and ex > 0.0:
                        worst = max(worst, ex)
                        if i < n_next:
                            worst_n = max(worst_n, ex)
                        if i < n_commit:
                            worst_c = max(worst_c, ex)
    return worst, worst_n, worst_c


@njit(cache=True, nogil=True)
def _trial_cost(k, wk, scale, nominal_d2, prog, plants, gains, cfg, work):
    """The exact window cost (um^2) of the trial plan ``work.trial_points`` simulated by
    :func:`_trial_excess`: weighted squared contour error, anchor and smoothness terms."""
    if scale == 0.0:
        cost = nominal_d2 * _M2_TO_UM2
    else:
        _each_cost(k, wk, prog.pd, prog.tree, prog.win_lo, prog.win_hi, prog.feed, work.trial,
                   work.cost_s)
        cost = 0.0
        for s in range(plants.params.shape[0]):
            cost += plants.weights[s] * work.cost_s[s]
    nk, tp = work.nk, work.trial_points
    for a in range(3):
        if prog.moving[a]:
            for jk in range(2, nk + 2):
                cost += cfg.anchor / nk * ((tp[a, 0, jk] - gains.kp_base[a]) ** 2
                                           + (tp[a, 1, jk] - gains.kf_base[a]) ** 2)
                cost += cfg.lam * ((tp[a, 0, jk] - tp[a, 0, jk - 1]) ** 2
                                   + (tp[a, 1, jk] - tp[a, 1, jk - 1]) ** 2)
    return cost


@njit(cache=True, nogil=True)
def _line_search(k, wk, nominal_d2, prog, plants, gains, cfg, work, carry):
    """Step 4: exact line search along the QP's step ``work.x``: the plan itself (scale 0, no
    simulation), then 1, 1/2, 1/4. Eq. 2 (every sample of the program) must hold on the
    samples to be committed now; it should also hold on those committed next (the plan,
    shifted, is the next window's fallback) and over the whole window. Classes: 0 the
    whole window, 1 the next two commits, 2 this commit, 3 none (fallback); the least class
    wins, then the least cost (class 0) or the least excess over the window (1, 2) or commit
    (3). Returns ``(class, scale, cost, held_cost)`` of the best (cost ``inf`` unless class
    0; ``held_cost`` the plan's own, ``inf`` unless class 0)."""
    best_cls = 4
    best_key = np.inf
    best_scale = 0.0
    best_cost = np.inf
    held_cost = np.inf
    for t_ in range(4):
        scale = 0.0 if t_ == 0 else 0.5 ** (t_ - 1)
        work.trial_points[:] = carry.points
        _step_points(work.trial_points, scale, work.x, work, gains)
        worst, worst_n, worst_c = _trial_excess(k, wk, scale, prog, plants, cfg, work, carry)
        cost = _trial_cost(k, wk, scale, nominal_d2, prog, plants, gains, cfg, work)
        if worst <= 1e-9:
            cls, key = 0, cost
        elif worst_n <= 1e-9:
            cls, key = 1, worst
        elif worst_c <= 1e-9:
            cls, key = 2, worst
        else:
            cls, key = 3, worst_c
        if scale == 0.0:
            held_cost = cost if cls == 0 else np.inf
        if cls < best_cls or (cls == best_cls and key < best_key):
            best_cls, best_key, best_scale = cls, key, scale
            best_cost = cost if cls == 0 else np.inf
        if scale == 1.0 and cls == 0 and cost < held_cost:
            break  # the full step keeps eq. 2 and lowers the exact cost: taken
    return best_cls, best_scale, best_cost, held_cost


@njit(cache=True, nogil=True)
def _plan_window(k, wk, prog, plants, gains, cfg, work, carry):
    """Steps 1-4 of window ``k`` (``wk`` samples), repeated: the plan ``carry.points``
    improved in place by sequential QP (see the module's docstring, step 5)."""
    work.nominal_points[:] = np.nan  # a new window: no nominal yet (NaN equals no plan)
    widen = 1.0  # trust-region factor, grown while no step keeps eq. 2 over the window
    restored = 0
    hold = _holds(k, wk, prog, cfg)  # the plan as it is: every sample of the window a rapid's
    stats = carry.stats
    for _it in range(0 if hold else cfg.iters + cfg.restore):
        _predict(k, wk, prog, plants, work, carry)
        nominal_d2 = _linearise(k, wk, prog, plants, work)
        _regularise(carry.points, gains, cfg, work)
        m = _constraints(k, wk, widen, prog, plants, gains, cfg, work, carry)
        work.x[:] = 0.0
        if not _qp_active_set(work.pmat, work.qvec, work.amat, work.alo, work.ahi, m, work.col0,
                              work.col1, work.x):
            stats[STAT_QP_SHORT] += 1
        best_cls, best_scale, best_cost, held_cost = _line_search(k, wk, nominal_d2, prog, plants,
                                                                  gains, cfg, work, carry)
        if best_cls == 3:
            stats[STAT_FALLBACK] += 1
        if best_scale < 1.0:
            stats[STAT_SCALED] += 1
        _step_points(carry.points, best_scale, work.x, work, gains)
        if best_cls > 0 and restored < cfg.restore:  # feasibility first: a wider step
            restored += 1
            widen *= _WIDEN
            continue
        if _it >= cfg.iters - 1:
            break
        if best_scale == 0.0 or (held_cost < np.inf and best_cost > (1.0 - cfg.stop) * held_cost):
            break


@njit(cache=True, nogil=True)
def _commit(k, k1, wk, prog, plants, cfg, work, carry):
    """Step 6: apply the first ``commit`` samples of the plan (at most up to ``k1``), advance
    every plant's true state, and shift the rest of the plan to start the next window.
    Returns the samples committed."""
    points, kp, kf = carry.points, carry.kp, carry.kf
    stride = min(cfg.commit, k1 - k)
    for a in range(3):
        if prog.moving[a]:
            _gains(points, a, 0, wk, work.kspace, work.plan_kp[a])
            _gains(points, a, 1, wk, work.kspace, work.plan_kf[a])
    for i in range(stride):
        for a in range(3):
            if prog.moving[a]:
                kp[a] = work.plan_kp[a, i]
                kf[a] = work.plan_kf[a, i]
        for s in range(plants.params.shape[0]):
            apply_gains(k + i, carry.states[s], plants.params[s], prog.pdT, prog.vdT, kp, kf,
                        (carry.kp_out, carry.kf_out, carry.u_out[s]), carry.u_hist[s])
    sh = stride // work.kspace
    work.trial_points[:] = points
    nk = work.nk
    for a in range(3):
        for g in range(2):
            for jk in range(nk + 2):
                points[a, g, jk] = work.trial_points[a, g, min(jk + sh, nk + 1)]
    return stride


@njit(cache=True, nogil=True)
def window_search(k0, k1, prog, plants, gains, cfg, carry):
    """Run the windowed full-mode search over samples k0 .. k1-1 in place, on S plants at once.

    One gain plan is searched for the S scenario plants of ``plants`` (the schedule is
    open-loop: every plant runs the same table; one plant: S = 1, weight 1). The window's
    cost is the weighted sum of the plants' squared contour errors (linearised on each plant
    around its own prediction, the Hessian and gradient summed), the smoothness and anchor
    terms once; eq. 2 and the following-error limit are constraint rows per plant and, in
    the line search, the largest excess over the plants, with each plant's own limits; an
    axis is idle when it is on every plant. The gain bounds (``gains``) are the caller's
    (the range stable on every plant).

    Parameters
    ----------
    k0, k1 : int
        Sample range of this call; ``k1 - k0`` must be a multiple of ``cfg.commit`` unless
        ``k1`` is the program's end (ValueError otherwise): the plan carried to the next
        call is shifted by whole commits only.
    prog : Program
        The program (:func:`program_of`).
    plants : Plants
        The plants and their limits (:func:`one_plant` for one).
    gains : oga.search.paper.Gains
        The gains searched, their bounds and the baseline the anchor pulls to.
    cfg : Settings
        The scalars (:func:`settings_of`): ``w`` the window, ``kspace`` the samples between
        control points, ``commit`` the samples applied per window (a multiple of
        ``kspace``), ``iters`` the iterations per window at most, ``trust_kp``,
        ``trust_kf`` the trust region of one iteration's control-point change
        ((m/min)/mm, 1), ``stop``, ``settled``, ``restore``, ``tail`` (the samples a
        window whose adjusted axis comes to rest inside it looks further) as
        :data:`oga.defaults.MPC_STOP` etc.; ``hold_in_rapids``: a window of rapid samples
        only commits the plan as it is, no step searched (the robust search).
    carry : Carry
        Changed in place (:func:`carry_of`); ``points`` carries the plan between calls:
        the control points ``c_{-1}, c_0, ...`` of :func:`_plan_at` (the first two fixed:
        with them the applied gains and their slope, the rest free), shifted by ``commit``
        samples after each window.
    """
    if (k1 - k0) % cfg.commit != 0 and k1 < prog.pd.shape[0]:
        # a call ending inside a commit would carry the plan shifted by part of an interval
        raise ValueError("window_search: k1 - k0 must be a multiple of commit, except at the "
                         "end")
    work = _workspace(prog, plants, gains, cfg, carry)
    k = k0
    while k < k1:
        wk = _window_len(k, prog, work)
        _mark_idle(k, wk, prog, cfg, carry, work.idle)
        _plan_window(k, wk, prog, plants, gains, cfg, work, carry)
        k += _commit(k, k1, wk, prog, plants, cfg, work, carry)


def settings_of(options, te, hold_in_rapids=False) -> Settings:
    """The search's scalars from the full-mode ``options`` (window, knot spacing, lam,
    anchor) and the period ``te`` (s), the rest :mod:`oga.defaults`; ``commit`` whole
    spline intervals (so that the shifted plan is the same gain trajectory)."""
    w, kspace = int(options.np_value), int(options.knot_value)
    commit = max(min(defaults.MPC_COMMIT_INTERVALS, w // kspace // 2), 1) * kspace
    trust_kp, trust_kf = defaults.MPC_TRUST
    # the scalars typed once: the kernel is compiled once whatever number types are given
    return Settings(float(te), w, kspace, int(commit), int(defaults.MPC_ITERATIONS),
                    float(trust_kp), float(trust_kf), float(options.lam_value),
                    float(options.anchor_value), float(defaults.MPC_STOP),
                    float(defaults.MPC_SETTLED_M), int(defaults.MPC_RESTORE),
                    int(defaults.MPC_SETTLE_TAIL), bool(hold_in_rapids))


def chunk_of(cfg: Settings, samples: int) -> int:
    """The samples per call: about ``samples``, a whole number of commits (the plan carried
    to the next call is shifted by whole spline intervals only)."""
    return max(samples // cfg.commit, 1) * cfg.commit


def program_of(setpoints, moving, cfg: Settings) -> Program:
    """The :class:`Program` of ``setpoints`` (N samples) padded by ``w + tail + 1`` samples
    at rest; ``moving`` (3,) bool the axes that move. Eq. 2 and the following-error limit
    apply on every sample of the program (not the padding), the contour error on its feed
    samples, measured as the replay does."""
    n = len(setpoints)
    pad = cfg.w + cfg.tail + 1
    pd = np.ascontiguousarray(setpoints.pos)
    pdT = np.ascontiguousarray(setpoints.pos.T)
    vdT = np.ascontiguousarray(setpoints.vel.T)
    pdT_pad = np.ascontiguousarray(np.hstack([pdT, np.repeat(pdT[:, -1:], pad, axis=1)]))
    vdT_pad = np.ascontiguousarray(np.hstack([vdT, np.zeros((3, pad))]))
    feed = np.concatenate([setpoints.counted, np.zeros(pad, dtype=bool)])
    live = np.concatenate([np.ones(n, dtype=bool), np.zeros(pad, dtype=bool)])
    tree, win_lo, win_hi = path_index(pd, defaults.CE_WINDOW_SAMPLES)
    return Program(pd, pdT_pad, vdT_pad, tree, win_lo, win_hi, np.asarray(moving, dtype=bool),
                   feed, live)


def one_plant(params, vmax, amax, jmax, ferror_max) -> Plants:
    """:class:`Plants` of one plant: ``params`` (3, P) and its limits (3,) given the plant
    axis (copies), weight 1: the same arithmetic as the one-plant search."""
    lims = np.empty((4, 1, 3))
    lims[0, 0], lims[1, 0], lims[2, 0], lims[3, 0] = vmax, amax, jmax, ferror_max
    return Plants(params.reshape((1,) + params.shape), lims[0], lims[1], lims[2], lims[3],
                  np.ones(1), np.zeros((1, 3, 2, 0)))


def carry_of(states, kp, kf, cfg: Settings, n) -> Carry:
    """The search's :class:`Carry` at the program's start: the plants' ``states`` (S, 3, Z)
    (changed in place), copies of the gains ``kp``, ``kf`` (3,), no command history, the
    plan at those gains over the window, outputs for ``n`` samples, zero counters."""
    n_s = states.shape[0]
    points = np.repeat(np.stack([kp, kf], axis=1)[:, :, None], cfg.w // cfg.kspace, axis=2)
    return Carry(states, kp.copy(), kf.copy(), np.zeros((n_s, 3, 2)), points,
                 np.empty((n, 3)), np.empty((n, 3)), np.empty((n_s, n, 3)),
                 np.zeros(4, dtype=np.int64))
