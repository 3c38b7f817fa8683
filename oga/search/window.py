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

Several plants at once (:func:`mpc_multi_chunk`, the robust search's kernel,
:mod:`oga.search.robust.multi`): every plant's true state is carried along the one plan; steps 1-2
are made on every plant (the weighted Hessians and gradients summed), step 3 has every
plant's limit rows, step 4 the weighted exact cost and the largest excess over the plants.
:func:`mpc_chunk` is its one-plant case, with the arithmetic of the one-plant search.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from oga.model.contour import ce2_at, nearest_at
from oga.model.kinematics import eq2_excess
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM
from oga.search.paper import apply_gains
from oga.model.simulate import run
from oga.model.tangent import run_tangent

__all__ = ["mpc_chunk", "mpc_multi_chunk", "STAT_FALLBACK", "STAT_WINDOWS", "STAT_SCALED", "STAT_QP_SHORT"]

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
    act = np.empty(nv, dtype=np.int64)  # active rows
    sgn = np.empty(nv, dtype=np.int64)  # +1: a.x >= lo active, -1: a.x <= hi active
    g = np.empty((nv, nv))  # g[c] = P^-1 n_c, n_c = sgn_c a_act[c]
    u = np.zeros(nv)  # multipliers of the active rows (>= 0)
    gram = np.empty((nv, nv))  # N' P^-1 N of the active rows
    low_g = np.zeros((nv, nv))  # its Cholesky factor, valid in its first n_low rows
    n_low = 0
    gp = np.empty(nv)
    z = np.empty(nv)
    rowv = np.empty(nv)
    na = 0
    for _outer in range(10 * (m + nv) + 10):
        # step 1: the most violated row (s = n.x - b < 0)
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
        if pr < 0:
            return True
        rowv[:] = 0.0
        for i in range(c0[pr], c1[pr]):
            rowv[i] = ps * a[pr, i]
        bp = lo[pr] if ps > 0 else -hi[pr]
        _chol_solve(low, rowv, gp)
        up = 0.0
        for _inner in range(nv + 2):
            # step 2: r = (N' P^-1 N)^-1 N' P^-1 n_p, z = P^-1 n_p - P^-1 N r; the Gram
            # matrix N' P^-1 N of the active rows is kept up to date in gram
            r = np.zeros(na)
            if na > 0:
                rhs = np.empty(na)
                for c in range(na):
                    t = 0.0
                    for i in range(nv):
                        t += g[c, i] * rowv[i]  # n_c' P^-1 n_p = g_c . n_p (P symmetric)
                    rhs[c] = t
                while n_low < na:  # the rows added since the last step
                    _chol_row(gram, low_g, n_low)
                    n_low += 1
                for c in range(na):
                    if low_g[c, c] <= 1e-150:  # dependent active rows
                        return False
                _chol_solve(low_g[:na, :na], rhs, r)
            for i in range(nv):
                t = gp[i]
                for c in range(na):
                    t -= g[c, i] * r[c]
                z[i] = t
            t1 = np.inf  # partial step: a multiplier reaches zero
            k = -1
            for c in range(na):
                if r[c] > 1e-14:
                    ratio = u[c] / r[c]
                    if ratio < t1:
                        t1 = ratio
                        k = c
            zn = 0.0
            sp = -bp
            for i in range(nv):
                zn += z[i] * rowv[i]
                sp += rowv[i] * x[i]
            t2 = -sp / zn if zn > 1e-14 else np.inf  # full step: the row becomes met
            t = min(t1, t2)
            if t == np.inf:
                return False  # the rows cannot all be met
            if t2 < np.inf:
                for i in range(nv):
                    x[i] += t * z[i]
            for c in range(na):
                u[c] -= t * r[c]
            up += t
            if t2 <= t1:  # full step: add the row
                if na == nv:  # dependent rows: no room for another
                    return False
                act[na] = pr
                sgn[na] = ps
                u[na] = up
                for i in range(nv):
                    g[na, i] = gp[i]
                for c in range(na + 1):
                    t = 0.0
                    for i in range(nv):
                        t += rowv[i] * g[c, i]
                    gram[na, c] = t
                    gram[c, na] = t
                na += 1
                break
            # partial step: drop row k (the last active row takes its place)
            na -= 1
            n_low = min(n_low, k)  # the factor's rows from k on change
            act[k] = act[na]
            sgn[k] = sgn[na]
            u[k] = u[na]
            for i in range(nv):
                g[k, i] = g[na, i]
            for c in range(na):
                gram[k, c] = gram[na, c]
            for c in range(na):
                gram[c, k] = gram[k, c]
            if k < na:
                gram[k, k] = gram[na, na]
        else:
            return False
    return False


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
def _step_points(points, scale, x, nv, var_axis, var_gain, var_point, kp_lo, kp_hi, kf_lo, kf_hi):
    """Add ``scale * x`` to the free points in place, each held inside its gain's bounds."""
    for v in range(nv):
        a = var_axis[v]
        g = var_gain[v]
        jk = var_point[v]
        val = points[a, g, jk] + scale * x[v]
        if g == 0:
            val = min(max(val, kp_lo[a]), kp_hi[a])
        else:
            val = min(max(val, kf_lo[a]), kf_hi[a])
        points[a, g, jk] = val


@njit(cache=True, nogil=True)
def _plan_gains(points, a, w, kspace, kpa, kfa):
    """The plan's Kp (1/s) and Kf of axis ``a`` at every window sample, into ``kpa``, ``kfa``."""
    _gains(points, a, 0, w, kspace, kpa)
    _gains(points, a, 1, w, kspace, kfa)
    for i in range(w):
        kpa[i] *= _C


@njit(cache=True, nogil=True)
def _sim_plan(states, params, pdT, vdT, k, w, points, a, kspace, kpa, kfa, out_p, out_u, scratch):
    """Exact prediction of axis ``a`` over the window along the plan ``points``: positions
    into ``out_p``, commands into ``out_u``."""
    _plan_gains(points, a, w, kspace, kpa, kfa)
    scratch[:] = states[a]
    run(scratch, params[a], pdT[a, k:k + w], vdT[a, k:k + w], kpa, kfa, out_p, out_u)


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


@njit(cache=True, nogil=True)
def _eq2_rows(m, s, k, wk, moving, var_lo, var_hi, vmax, amax, jmax, te, live, u0, su, u_hist,
              trust, amat, alo, ahi, col0, col1):
    """Linearised eq. 2 rows (v, a, j at every live window sample) of plant ``s`` (its limits
    ``vmax[s]`` ...), from row ``m`` (kept where the trust region can reach a bound); returns the next free row."""
    for a in range(3):
        if not moving[a] or var_lo[a] == var_hi[a]:
            continue
        lims = (_LIN_MARGIN * vmax[s, a], _LIN_MARGIN * amax[s, a] * te,
                _LIN_MARGIN * jmax[s, a] * te * te)
        for r in range(3):
            for i in range(wk):
                if not live[k + i]:  # eq. 2 on every sample of the program
                    continue
                nominal = u0[s, a, i]
                if r >= 1:
                    nominal -= (1.0 if r == 1 else 2.0) * (u0[s, a, i - 1] if i >= 1 else u_hist[s, a, 0])
                if r == 2:
                    nominal += u0[s, a, i - 2] if i >= 2 else u_hist[s, a, 1 - i]
                scale = 1.0 / lims[r]
                reach = 0.0
                for v in range(var_lo[a], var_hi[a]):
                    cv = su[s, i, v]
                    if r >= 1 and i >= 1:
                        cv -= (1.0 if r == 1 else 2.0) * su[s, i - 1, v]
                    if r == 2 and i >= 2:
                        cv += su[s, i - 2, v]
                    amat[m, v] = cv * scale
                    reach += abs(cv * scale) * trust[v]
                m = _keep_row(m, -1.0 - nominal * scale, 1.0 - nominal * scale, reach,
                              var_lo[a], var_hi[a], alo, ahi, col0, col1)
    return m


@njit(cache=True, nogil=True)
def _ferror_rows(m, s, k, wk, moving, var_lo, var_hi, ferror_max, live, pdT, p0, sp, trust, amat,
                 alo, ahi, col0, col1):
    """Linearised following-error rows ``|pd - p0 - S d| <= margin * limit`` of plant ``s``
    (axes with a limit, live samples), from row ``m``; returns the next free row."""
    for a in range(3):
        if not moving[a] or var_lo[a] == var_hi[a] or not np.isfinite(ferror_max[s, a]):
            continue
        scale = 1.0 / ferror_max[s, a]
        for i in range(wk):
            if not live[k + i]:
                continue
            nominal = (pdT[a, k + i] - p0[s, a, i]) * scale
            reach = 0.0
            for v in range(var_lo[a], var_hi[a]):
                amat[m, v] = sp[s, i, v] * scale
                reach += abs(sp[s, i, v] * scale) * trust[v]
            m = _keep_row(m, nominal - _LIN_MARGIN, nominal + _LIN_MARGIN, reach,
                          var_lo[a], var_hi[a], alo, ahi, col0, col1)
    return m


@njit(cache=True, nogil=True)
def mpc_chunk(
    k0, k1, pd, pdT, vdT, params, states, kp, kf, adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi,
    kp_base, kf_base, vmax, amax, jmax, te, u_hist, w, kspace, commit, iters, trust_kp, trust_kf,
    lam, anchor, tree, win_lo, win_hi, moving, feed, live, points, kp_out, kf_out, u_out, stats,
    stop, settled, ferror_max, restore, tail,
):
    """Run the windowed full-mode search over samples k0 .. k1-1 in place, on one plant.

    :func:`mpc_multi_chunk` with that plant alone (weight 1; the same arithmetic, so the
    same schedule bit for bit as before the scenario dimension existed); the arguments as
    there, ``params`` (3, P), ``states`` (3, Z), ``u_hist`` (3, 2) and ``u_out`` (N, 3)
    without the plant axis (C-contiguous: they are viewed, not copied), the limits
    ``vmax``, ``amax``, ``jmax``, ``ferror_max`` (3,).
    """
    lims = np.empty((4, 1, 3))  # the limits as the one plant's
    for a in range(3):
        lims[0, 0, a] = vmax[a]
        lims[1, 0, a] = amax[a]
        lims[2, 0, a] = jmax[a]
        lims[3, 0, a] = ferror_max[a]
    mpc_multi_chunk(
        k0, k1, pd, pdT, vdT, params.reshape((1,) + params.shape),
        states.reshape((1,) + states.shape), kp, kf, adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi,
        kp_base, kf_base, lims[0], lims[1], lims[2], te, u_hist.reshape((1,) + u_hist.shape), w,
        kspace, commit, iters, trust_kp, trust_kf, lam, anchor, tree, win_lo, win_hi, moving,
        feed, live, points, kp_out, kf_out, u_out.reshape((1,) + u_out.shape), stats, stop,
        settled, lims[3], restore, tail, np.ones(1), False,
    )


@njit(cache=True, nogil=True)
def mpc_multi_chunk(
    k0, k1, pd, pdT, vdT, params, states, kp, kf, adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi,
    kp_base, kf_base, vmax, amax, jmax, te, u_hist, w, kspace, commit, iters, trust_kp, trust_kf,
    lam, anchor, tree, win_lo, win_hi, moving, feed, live, points, kp_out, kf_out, u_out, stats,
    stop, settled, ferror_max, restore, tail, weights, hold_in_rapids,
):
    """Run the windowed full-mode search over samples k0 .. k1-1 in place, on S plants at once.

    One gain plan is searched for S scenario plants of the same axes (the schedule is
    open-loop: every plant runs the same table). ``params`` (S, 3, P), ``states`` (S, 3, Z),
    ``u_hist`` (S, 3, 2) and ``u_out`` (S, N, 3) hold each plant's packed parameters, true
    states, command history and commands; ``kp_out``, ``kf_out`` (N, 3) the one schedule.
    The window's cost is the ``weights`` (S,) weighted sum of the plants' squared contour
    errors (linearised on each plant around its own prediction, the Hessian and gradient
    summed), the smoothness and anchor terms once; eq. 2 and the following-error limit are
    constraint rows per plant and, in the line search, the largest excess over the plants,
    with each plant's own limits: ``vmax``, ``amax``, ``jmax``, ``ferror_max`` (S, 3);
    an axis is idle when it is on every plant. The gain bounds are the caller's (the range
    stable on every plant).

    ``k1 - k0`` must be a multiple of ``commit`` unless ``k1`` is the program's end
    (ValueError otherwise): the plan carried to the next call is shifted by whole
    commits only.

    The arguments shared with :func:`oga.search.paper.search_chunk` mean the same there
    (``pdT``/``vdT`` padded by ``w + tail + 1`` samples past the end); ``kp_base``,
    ``kf_base`` (3,) are the baseline gains the anchor pulls to; ``w`` the window,
    ``kspace`` the samples between points, ``commit`` the samples applied per window
    (a multiple of ``kspace``), ``iters`` the iterations per window at most,
    ``trust_kp``/``trust_kf`` the trust region of one iteration's control-point change
    ((m/min)/mm, 1), ``tree, win_lo, win_hi`` the path's index and every sample's
    contour-error window (:func:`oga.model.contour.path_index`).
    ``points`` (3, 2, w // kspace) carries the plan between calls: the control points
    ``c_{-1}, c_0, ...`` of :func:`_plan_at` (the first two fixed: with them the
    applied gains and their slope, the rest free); it is shifted by ``commit``
    samples after each window. ``feed`` (bool, padded like ``pdT``) marks the samples where
    the contour error counts (feed moves; not rapids, not the padding), ``live`` (likewise)
    those where eq. 2 and the following-error limit apply: every sample of the program,
    rapids included, as in :mod:`oga.verify.replay` (not the padding); ``stop`` is
    :data:`oga.defaults.MPC_STOP`,
    ``settled`` :data:`oga.defaults.MPC_SETTLED_M`; ``ferror_max`` (S, 3) each plant's
    following-error limit per axis (m, ``inf``: none), kept at the window's live samples
    like eq. 2 (linearised rows, then the exact check of the line search); ``restore``
    is :data:`oga.defaults.MPC_RESTORE`; ``tail`` the samples a window whose adjusted
    axis comes to rest inside it looks further (:data:`oga.defaults.MPC_SETTLE_TAIL`,
    0: none); ``hold_in_rapids``: a window of rapid samples only commits the plan as it
    is, no step searched (the robust search, :mod:`oga.search.robust.multi`).
    """
    n_s = params.shape[0]
    if (k1 - k0) % commit != 0 and k1 < pd.shape[0]:
        # a call ending inside a commit would carry the plan shifted by part of an interval
        raise ValueError("mpc_chunk: k1 - k0 must be a multiple of commit, except at the end")
    nk = points.shape[2] - 2  # free control points per gain: indices 2 .. nk + 1
    var_axis = np.empty(6 * nk, dtype=np.int64)
    var_gain = np.empty(6 * nk, dtype=np.int64)
    var_point = np.empty(6 * nk, dtype=np.int64)
    var_prev = np.empty(6 * nk, dtype=np.int64)  # the same gain's previous free point, or -1
    var_start = np.empty(6 * nk, dtype=np.int64)  # first window sample its basis reaches
    # variables per axis in the order of their first sample (point, then gain): the order of
    # the tangent directions, so that run_tangent writes each axis's block of sp, su directly
    nv = 0
    for a in range(3):
        if not moving[a]:
            continue
        n_gain = 0
        for g in range(2):
            if (g == 0 and adj_kp[a]) or (g == 1 and adj_kf[a]):
                n_gain += 1
        for j in range(2, nk + 2):
            for g in range(2):
                if (g == 0 and adj_kp[a]) or (g == 1 and adj_kf[a]):
                    var_axis[nv] = a
                    var_gain[nv] = g
                    var_point[nv] = j
                    var_prev[nv] = nv - n_gain if j > 2 else -1
                    var_start[nv] = (j - 2) * kspace
                    nv += 1
    var_lo = np.zeros(3, dtype=np.int64)
    var_hi = np.zeros(3, dtype=np.int64)
    for v in range(nv - 1, -1, -1):
        var_lo[var_axis[v]] = v
    for v in range(nv):
        var_hi[var_axis[v]] = v + 1
    # the gain's change per unit of each free point: its B-spline basis function (Kp in 1/s
    # per (m/min)/mm), per window sample
    wmax = w + tail
    dir_kp = np.zeros((wmax, nv))
    dir_kf = np.zeros((wmax, nv))
    for v in range(nv):
        for i in range(wmax):
            b = _basis(var_point[v], i + 1, kspace, nk + 1)
            if var_gain[v] == 0:
                dir_kp[i, v] = _C * b
            else:
                dir_kf[i, v] = b
    mq = np.empty((3, wmax))
    spp_buf = np.empty(wmax * nv)  # sp's columns weighted by P's entries for one row axis
    proj = np.empty((3, 3, wmax))  # P = I - t t' per window sample
    p0 = np.empty((n_s, 3, wmax))
    u0 = np.empty((n_s, 3, wmax))
    sp = np.zeros((n_s, wmax, nv))  # d p0 / d point, m per unit, per plant, window sample, variable
    su = np.zeros((n_s, wmax, nv))  # d u0 / d point, m/s per unit
    kpa = np.empty(wmax)
    kfa = np.empty(wmax)
    scratch = np.empty(states.shape[2])
    tmp_u = np.empty(wmax)
    dq = np.empty((wmax, 3))
    tang = np.empty((wmax, 3))
    pmat = np.empty((nv, nv))
    qvec = np.empty(nv)
    max_rows = nv + 4 * 3 * wmax * n_s  # bounds; eq. 2 (v, a, j), following error per sample, plant
    amat = np.zeros((max_rows, nv))
    alo = np.empty(max_rows)
    ahi = np.empty(max_rows)
    col0 = np.empty(max_rows, dtype=np.int64)
    col1 = np.empty(max_rows, dtype=np.int64)
    x = np.zeros(nv)
    trust = np.empty(nv)
    trial = np.empty((n_s, 3, wmax))
    plan_kp = np.empty((3, wmax))
    plan_kf = np.empty((3, wmax))
    trial_points = points.copy()
    nominal_points = np.empty_like(points)  # per axis, the plan of its nominal p0, u0
    for s in range(n_s):
        for a in range(3):
            if not moving[a]:
                trial[s, a, :] = states[s, a, 0]
    idle = np.ones(3, dtype=np.bool_)
    k = k0
    while k < k1:
        # where an adjusted axis's setpoint comes to rest inside the window, look `tail`
        # samples further (the plan's last gains held) to see it settle
        wk = w
        for a in range(3):
            if moving[a] and var_lo[a] < var_hi[a] and vdT[a, k + w - 1] == 0.0:
                for i in range(w - 1):
                    if vdT[a, k + i] != 0.0:
                        wk = wmax
                        break
        for a in range(3):
            # idle: its setpoint stands over the window and the axis has settled on it (on
            # every plant)
            idle[a] = True
            for s in range(n_s):
                if abs(states[s, a, 0] - pdT[a, k]) > settled:
                    idle[a] = False
            if moving[a]:
                for i in range(wk):
                    if vdT[a, k + i] != 0.0 or pdT[a, k + i] != pdT[a, k]:
                        idle[a] = False
                        break
        hold = hold_in_rapids  # the plan as it is: every sample of the window a rapid's
        if hold:
            for i in range(wk):
                if feed[k + i] or not live[k + i]:
                    hold = False
                    break
        nominal_points[:] = np.nan  # a new window: no nominal yet (NaN equals no plan)
        widen = 1.0  # trust-region factor, grown while no step keeps eq. 2 over the window
        restored = 0
        for _it in range(0 if hold else iters + restore):
            # 1: nominal prediction along the plan and, in the same pass, its derivatives
            #    with respect to every free control point of the axis (forward mode)
            for a in range(3):
                if not moving[a]:
                    for s in range(n_s):
                        for i in range(wk):
                            p0[s, a, i] = states[s, a, 0]
                            u0[s, a, i] = 0.0
                    continue
                if _same_plan(points, nominal_points, a):
                    continue  # p0, u0 and the axis's columns of sp, su still hold
                nominal_points[a] = points[a]
                lo_v, hi_v = var_lo[a], var_hi[a]
                for s in range(n_s):
                    stats[STAT_WINDOWS] += 1
                    if idle[a] or lo_v == hi_v:
                        _sim_plan(states[s], params[s], pdT, vdT, k, wk, points, a, kspace, kpa,
                                  kfa, p0[s, a], u0[s, a], scratch)
                        sp[s, :, lo_v:hi_v] = 0.0
                        su[s, :, lo_v:hi_v] = 0.0
                        continue
                    _plan_gains(points, a, wk, kspace, kpa, kfa)
                    scratch[:] = states[s, a]
                    run_tangent(scratch, params[s, a], pdT[a, k:k + wk], vdT[a, k:k + wk], kpa,
                                kfa, dir_kp[:, lo_v:hi_v], dir_kf[:, lo_v:hi_v],
                                var_start[lo_v:hi_v], p0[s, a], u0[s, a], sp[s, :, lo_v:hi_v],
                                su[s, :, lo_v:hi_v])
            # 2: linearised contour error around each plant's nominal prediction, weighted
            nominal_d2 = 0.0  # the exact window cost of the plan (the line search's scale 0)
            for s in range(n_s):
                p0s = p0[s]
                sps = sp[s]
                wt = weights[s]
                j = -1
                d2_s = 0.0
                for i in range(wk):
                    if not feed[k + i]:  # weight 0, as in the metric
                        for a in range(3):
                            dq[i, a] = 0.0
                            tang[i, a] = 0.0
                        continue
                    c = k + i  # a feed sample: inside the program
                    j, t, d2 = nearest_at(pd, tree, win_lo[c], win_hi[c], c, p0s[0, i], p0s[1, i],
                                          p0s[2, i], j)
                    if j < 0:
                        for a in range(3):
                            dq[i, a] = p0s[a, i] - pd[c, a]
                            tang[i, a] = 0.0
                            d2_s += dq[i, a] ** 2
                        continue
                    d2_s += d2
                    sx = pd[j + 1, 0] - pd[j, 0]
                    sy = pd[j + 1, 1] - pd[j, 1]
                    sz = pd[j + 1, 2] - pd[j, 2]
                    inv = 1.0 / np.sqrt(sx * sx + sy * sy + sz * sz)
                    tang[i, 0], tang[i, 1], tang[i, 2] = sx * inv, sy * inv, sz * inv
                    dq[i, 0] = p0s[0, i] - (pd[j, 0] + t * sx)
                    dq[i, 1] = p0s[1, i] - (pd[j, 1] + t * sy)
                    dq[i, 2] = p0s[2, i] - (pd[j, 2] + t * sz)
                # cost |P (dq + S d)|^2 with P = I - t t' per sample: Hessian 2 S' P S and gradient
                # 2 S' P dq, one small matrix product per axis's block of rows
                for a in range(3):
                    for b in range(3):
                        for i in range(wk):
                            eye = 1.0 if a == b and feed[k + i] else 0.0
                            proj[a, b, i] = eye - tang[i, a] * tang[i, b]
                    for i in range(wk):
                        mq[a, i] = proj[a, 0, i] * dq[i, 0] + proj[a, 1, i] * dq[i, 1] + proj[a, 2, i] * dq[i, 2]
                for a in range(3):  # axis a's rows, from its own columns on: S_a' (P_a. o S_b)
                    lo_v, hi_v = var_lo[a], var_hi[a]
                    if lo_v == hi_v:
                        continue
                    spp = spp_buf[:wk * (nv - lo_v)].reshape((wk, nv - lo_v))
                    for i in range(wk):
                        for u_ in range(lo_v, nv):
                            spp[i, u_ - lo_v] = sps[i, u_] * proj[a, var_axis[u_], i]
                    s_a = np.ascontiguousarray(sps[:wk, lo_v:hi_v].T)
                    if s == 0:
                        pmat[lo_v:hi_v, lo_v:] = wt * np.dot(s_a, spp)
                        qvec[lo_v:hi_v] = wt * np.dot(s_a, mq[a, :wk])
                    else:
                        pmat[lo_v:hi_v, lo_v:] += wt * np.dot(s_a, spp)
                        qvec[lo_v:hi_v] += wt * np.dot(s_a, mq[a, :wk])
                nominal_d2 += wt * d2_s
            for v in range(nv):
                qvec[v] *= 2.0 * _M2_TO_UM2
                for u_ in range(v, nv):
                    pmat[v, u_] *= 2.0 * _M2_TO_UM2
                    pmat[u_, v] = pmat[v, u_]
            # smoothness (lam on steps between control points) and anchor (mean over them)
            for v in range(nv):
                a = var_axis[v]
                g = var_gain[v]
                jk = var_point[v]
                base = kp_base[a] if g == 0 else kf_base[a]
                kv = points[a, g, jk]
                step_prev = kv - points[a, g, jk - 1]
                pmat[v, v] += 2.0 * lam + 2.0 * anchor / nk
                qvec[v] += 2.0 * lam * step_prev + 2.0 * anchor * (kv - base) / nk
                vp = var_prev[v]
                if vp >= 0:  # the step from the previous free control point
                    pmat[v, vp] -= 2.0 * lam
                    pmat[vp, v] -= 2.0 * lam
                    pmat[vp, vp] += 2.0 * lam
                    qvec[vp] -= 2.0 * lam * step_prev
            # 3: constraints: gain bounds and trust region per control point; eq. 2 rows
            m = 0
            for v in range(nv):
                a = var_axis[v]
                g = var_gain[v]
                kv = points[a, g, var_point[v]]
                amat[m, v] = 1.0
                if g == 0:
                    lo_b, hi_b, tr = kp_lo[a] - kv, kp_hi[a] - kv, trust_kp * widen
                else:
                    lo_b, hi_b, tr = kf_lo[a] - kv, kf_hi[a] - kv, trust_kf * widen
                if idle[a]:
                    tr = 0.0
                alo[m] = max(lo_b, -tr)
                ahi[m] = min(hi_b, tr)
                col0[m] = v
                col1[m] = v + 1
                trust[v] = tr
                m += 1
            for s in range(n_s):
                m = _eq2_rows(m, s, k, wk, moving, var_lo, var_hi, vmax, amax, jmax, te, live,
                              u0, su, u_hist, trust, amat, alo, ahi, col0, col1)
            for s in range(n_s):  # following error |pd - p0 - S d| <= margin * limit
                m = _ferror_rows(m, s, k, wk, moving, var_lo, var_hi, ferror_max, live, pdT, p0,
                                 sp, trust, amat, alo, ahi, col0, col1)
            for v in range(nv):
                x[v] = 0.0
            if not _qp_active_set(pmat, qvec, amat, alo, ahi, m, col0, col1, x):
                stats[STAT_QP_SHORT] += 1
            # 4: exact line search along the step: 1, 1/2, 1/4, 0 (the current plan). Eq. 2
            #    (every sample of the program) must hold on the samples to be committed now;
            #    it should also hold on those committed next (the plan, shifted, is the next
            #    window's fallback) and over the whole window. Classes: 0 the whole window, 1 the next two
            #    commits, 2 this commit, 3 none (fallback); the least class wins, then the
            #    least cost (class 0) or the least excess over the window (1, 2) or commit (3)
            best_cls = 4
            best_key = np.inf
            best_scale = 0.0
            best_cost = np.inf
            held_cost = np.inf
            n_commit = min(commit, wk)
            n_next = min(2 * commit, wk)
            for t_ in range(4):  # the plan itself first (no simulation), then 1, 1/2, 1/4
                scale = 0.0 if t_ == 0 else 0.5 ** (t_ - 1)
                trial_points[:] = points
                _step_points(trial_points, scale, x, nv, var_axis, var_gain, var_point, kp_lo, kp_hi,
                            kf_lo, kf_hi)
                worst = 0.0  # over the window
                worst_n = 0.0  # over this commit and the next
                worst_c = 0.0  # over the samples to be committed
                for s in range(n_s):  # every plant: the largest excess
                    for a in range(3):
                        if not moving[a]:
                            continue
                        if scale == 0.0:  # the plan itself: its nominal prediction
                            tmp_u[:] = u0[s, a]
                        elif _same_plan(trial_points, points, a):  # the step leaves the axis as is
                            trial[s, a, :wk] = p0[s, a, :wk]
                            tmp_u[:wk] = u0[s, a, :wk]
                        else:
                            _sim_plan(states[s], params[s], pdT, vdT, k, wk, trial_points, a, kspace,
                                      kpa, kfa, trial[s, a], tmp_u, scratch)
                            stats[STAT_WINDOWS] += 1
                        fk = live[k:k + wk]
                        worst = max(worst, eq2_excess(tmp_u, u_hist[s, a, 0], u_hist[s, a, 1], vmax[s, a],
                                                       amax[s, a], jmax[s, a], te, wk, fk))
                        worst_n = max(worst_n, eq2_excess(tmp_u, u_hist[s, a, 0], u_hist[s, a, 1], vmax[s, a],
                                                           amax[s, a], jmax[s, a], te, n_next, fk))
                        worst_c = max(worst_c, eq2_excess(tmp_u, u_hist[s, a, 0], u_hist[s, a, 1], vmax[s, a],
                                                           amax[s, a], jmax[s, a], te, n_commit, fk))
                        if np.isfinite(ferror_max[s, a]):  # the following-error limit, as an excess
                            pos = p0[s, a] if scale == 0.0 else trial[s, a]
                            for i in range(wk):
                                ex = abs(pdT[a, k + i] - pos[i]) / ferror_max[s, a] - 1.0
                                if fk[i] and ex > 0.0:
                                    worst = max(worst, ex)
                                    if i < n_next:
                                        worst_n = max(worst_n, ex)
                                    if i < n_commit:
                                        worst_c = max(worst_c, ex)
                if scale == 0.0:
                    cost = nominal_d2 * _M2_TO_UM2
                else:
                    cost = 0.0
                    for s in range(n_s):
                        cost += weights[s] * _window_cost(pd, tree, win_lo, win_hi, k, wk,
                                                          trial[s], feed)
                for a in range(3):
                    if moving[a]:
                        for jk in range(2, nk + 2):
                            cost += anchor / nk * ((trial_points[a, 0, jk] - kp_base[a]) ** 2
                                                   + (trial_points[a, 1, jk] - kf_base[a]) ** 2)
                            cost += lam * ((trial_points[a, 0, jk] - trial_points[a, 0, jk - 1]) ** 2
                                           + (trial_points[a, 1, jk] - trial_points[a, 1, jk - 1]) ** 2)
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
            if best_cls == 3:
                stats[STAT_FALLBACK] += 1
            if best_scale < 1.0:
                stats[STAT_SCALED] += 1
            _step_points(points, best_scale, x, nv, var_axis, var_gain, var_point, kp_lo, kp_hi, kf_lo,
                        kf_hi)
            if best_cls > 0 and restored < restore:  # feasibility first: a wider step
                restored += 1
                widen *= _WIDEN
                continue
            if _it >= iters - 1:
                break
            if best_scale == 0.0 or (held_cost < np.inf and best_cost > (1.0 - stop) * held_cost):
                break
        # 5: commit the first `commit` samples of the plan, advance the true state
        stride = min(commit, k1 - k)
        for a in range(3):
            if moving[a]:
                _gains(points, a, 0, wk, kspace, plan_kp[a])
                _gains(points, a, 1, wk, kspace, plan_kf[a])
        for i in range(stride):
            for a in range(3):
                if moving[a]:
                    kp[a] = plan_kp[a, i]
                    kf[a] = plan_kf[a, i]
            for s in range(n_s):
                apply_gains(k + i, states[s], params[s], pdT, vdT, kp, kf, kp_out, kf_out,
                            u_out[s], u_hist[s])
        # the rest of the plan, shifted by the committed samples, starts the next window
        sh = stride // kspace
        trial_points[:] = points
        for a in range(3):
            for g in range(2):
                for jk in range(nk + 2):
                    points[a, g, jk] = trial_points[a, g, min(jk + sh, nk + 1)]
        k += stride
