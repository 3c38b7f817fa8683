"""Full mode: receding-horizon gain search as a small model-predictive problem, compiled.

The paper's search (:mod:`oga.search`) tries five increments per sample, each
held over the horizon. On jerk-limited setpoints that held-gain prediction
misleads it: it moves a gain far while an axis is idle (the kinematic bound is
void there), then cannot bring it back once the axis moves (the bound is tight
there). Full mode instead plans a whole gain *trajectory* over the horizon and
re-plans as it recedes:

1. every ``replan`` samples, from the current true state, simulate each axis
   over ``Np`` samples on the exact nonlinear model with the gains held
   (the nominal prediction), and once more per adjusted gain and per move
   block with that gain raised by a small step from the block on: finite-difference
   sensitivities of the predicted positions and velocity commands to a gain
   trajectory that may step at the start of each of ``blocks`` blocks (each
   simulated from its block's start on; an axis whose setpoint stands still over
   the whole horizon is not adjusted there);
2. the predicted contour error is linearised around the nominal prediction
   (distance to the line of the nearest path segment, as in :mod:`oga.search`),
   giving a quadratic cost in the block increments ``d``:
   ``|E(d)|^2 + lam |d|^2 + anchor |K(d) - K_baseline|^2`` (um^2);
3. constraints: every gain inside its bounds in every block, and eq. 2 on the
   linearised velocity command over the whole horizon (with a small margin);
   each block step stays inside a trust region where the linearisation holds;
   the QP is solved exactly by the dual active-set method of Goldfarb and Idnani;
4. exact line search: the planned trajectory scaled by 1, 1/2, 1/4, 1/8 and 0
   (holding the gains) is simulated exactly from the true state; among the
   scales whose velocity command meets eq. 2 over the whole horizon, the one
   with the least exact contour-error cost is taken (so a step never makes the
   exact prediction worse than holding, and never breaks eq. 2 in it);
5. the first ``replan`` samples of the plan are applied and the true state is
   advanced with the exact kernel.

Every figure a user sees still comes from the replay in :mod:`oga.verify`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from oga.contour import nearest_segment, window_bounds
from oga.kinematics import eq2_excess
from oga.machine import KP_SI_PER_M_MIN_PER_MM
from oga.search import apply_gains
from oga.simulate import run

__all__ = ["mpc_chunk", "STAT_FALLBACK", "STAT_WINDOWS", "STAT_SCALED", "STAT_QP_SHORT"]

STAT_FALLBACK = 0  # re-plans where even the held gains broke eq. 2 over the horizon
STAT_WINDOWS = 1  # horizon simulations
STAT_SCALED = 2  # re-plans whose increments were scaled down by the exact check
STAT_QP_SHORT = 3  # re-plans whose QP stopped short of the optimum (the line search decides)

_C = KP_SI_PER_M_MIN_PER_MM
_M2_TO_UM2 = 1e12
#: Finite-difference step of the sensitivities: (m/min)/mm for Kp, 1 for Kf.
_H = 1e-3
#: Share of the eq. 2 limits the linearised constraints may use (the exact check uses 1).
_LIN_MARGIN = 0.95


@njit(cache=True)
def _chol(a):
    """Lower Cholesky factor of a symmetric positive definite matrix (a copy)."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        low[j, j] = np.sqrt(max(s, 1e-300))
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= low[i, k] * low[j, k]
            low[i, j] = s / low[j, j]
    return low


@njit(cache=True)
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


@njit(cache=True)
def _qp_active_set(p, q, a, lo, hi, m, x):
    """Minimise ``x'Px/2 + q'x`` subject to ``lo <= A x <= hi`` (first ``m`` rows of A).

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
            for i in range(nv):
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
        for i in range(nv):
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
                try:
                    r = np.linalg.solve(gram[:na, :na], rhs)
                except Exception:
                    return False
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


@njit(cache=True)
def _nearest(pd, count, ce_window, c, j_prev, x, y, z):
    """Nearest segment of the path to (x, y, z) for window sample ``c``: ``(j, t, d2)``.

    Searches a few segments around ``j_prev`` (the previous window sample's
    answer) and falls back to the full window of :func:`oga.contour.window_bounds`
    when there is no previous answer or the nearest point lies on the edge of
    the local search.
    """
    n = pd.shape[0]
    if j_prev >= 0:
        lo = max(j_prev - 3, 0)
        hi = min(j_prev + 8, n - 1)
        j, t, d2 = nearest_segment(pd, lo, hi, x, y, z)
        if j > lo and j < hi - 1:
            return j, t, d2
    lo, hi = window_bounds(count, c, ce_window)
    return nearest_segment(pd, lo, hi, x, y, z)


@njit(cache=True)
def _simulate(state, params, pd, vd, k, n, kp_si, kf, scratch, out_p, out_u):
    """Exact prediction from ``state`` at sample k over n samples with per-sample gains.

    ``pd``/``vd`` are padded past the end (last position held, zero velocity), so
    the slices always exist. ``out_p[i]`` is the measured position at sample k+i.
    """
    scratch[:] = state
    run(scratch, params, pd[k:k + n], vd[k:k + n], kp_si, kf, out_p, out_u)


@njit(cache=True)
def _plan_gains(a, scale, x, nv, var_axis, var_gain, var_blk, blen, kp, kf, kp_lo, kp_hi,
                kf_lo, kf_hi, n_pred, plan_kp, plan_kf, kpa, kfa):
    """Gain trajectory of axis ``a`` over the horizon for block steps ``scale * x``.

    Fills ``plan_kp[a]``, ``plan_kf[a]`` ((m/min)/mm, 1) and the kernel's ``kpa`` (1/s), ``kfa``.
    """
    for i in range(n_pred):
        plan_kp[a, i] = kp[a]
        plan_kf[a, i] = kf[a]
    for v in range(nv):
        if var_axis[v] != a:
            continue
        for i in range(var_blk[v] * blen, n_pred):
            if var_gain[v] == 0:
                plan_kp[a, i] += scale * x[v]
            else:
                plan_kf[a, i] += scale * x[v]
    for i in range(n_pred):
        plan_kp[a, i] = min(max(plan_kp[a, i], kp_lo[a]), kp_hi[a])
        plan_kf[a, i] = min(max(plan_kf[a, i], kf_lo[a]), kf_hi[a])
        kpa[i] = plan_kp[a, i] * _C
        kfa[i] = plan_kf[a, i]


@njit(cache=True)
def mpc_chunk(
    k0, k1, pd, pdT, vdT, params, states, kp, kf, adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi,
    kp_base, kf_base, vmax, amax, jmax, te, u_hist, n_pred, n_blocks, trust_kp, trust_kf, replan,
    lam, anchor,
    ce_window, count, moving, kp_out, kf_out, u_out, stats,
):
    """Run the full-mode search over samples ``k0 .. k1 - 1`` in place.

    Parameters are those of :func:`oga.search.search_chunk`, plus: ``pdT``/``vdT``
    padded by ``n_pred`` samples past the end (shape (3, N + n_pred)); ``kp_base``,
    ``kf_base`` (3,) the baseline gains the anchor pulls to; ``n_blocks`` move
    blocks over the horizon; ``trust_kp``, ``trust_kf`` the trust region of one block
    step ((m/min)/mm, 1), where the linearisation is trusted; ``replan`` samples between two plans (``k0`` must be
    a multiple of it); ``anchor`` weight; ``count`` from
    :func:`oga.contour.moving_count` for the nearest-point window.
    """
    n_total = pd.shape[0]
    blen = max(n_pred // n_blocks, 1)
    # variables: (axis, gain, block) for adjusted gains
    var_axis = np.empty(12 * n_blocks, dtype=np.int64)
    var_gain = np.empty(12 * n_blocks, dtype=np.int64)  # 0 kp, 1 kf
    var_blk = np.empty(12 * n_blocks, dtype=np.int64)
    nv = 0
    for a in range(3):
        if not moving[a]:
            continue
        for g in range(2):
            if (g == 0 and adj_kp[a]) or (g == 1 and adj_kf[a]):
                for b in range(n_blocks):
                    var_axis[nv] = a
                    var_gain[nv] = g
                    var_blk[nv] = b
                    nv += 1
    var_lo = np.zeros(3, dtype=np.int64)  # variables of axis a: var_lo[a] .. var_hi[a]-1
    var_hi = np.zeros(3, dtype=np.int64)
    for v in range(nv - 1, -1, -1):
        var_lo[var_axis[v]] = v
    for v in range(nv):
        var_hi[var_axis[v]] = v + 1
    mq = np.empty(n_pred)
    wgt = np.empty(n_pred)
    p0 = np.empty((3, n_pred))
    u0 = np.empty((3, n_pred))
    sp = np.zeros((nv, n_pred))  # position sensitivities
    su = np.zeros((nv, n_pred))  # command sensitivities
    kpa = np.empty(n_pred)
    kfa = np.empty(n_pred)
    scratch = np.empty(states.shape[1])
    tmp_p = np.empty(n_pred)
    tmp_u = np.empty(n_pred)
    dq = np.empty((n_pred, 3))
    tang = np.empty((n_pred, 3))
    pmat = np.empty((nv, nv))
    qvec = np.empty(nv)
    max_rows = 2 * nv + 3 * 3 * n_pred
    amat = np.zeros((max_rows, nv))
    alo = np.empty(max_rows)
    ahi = np.empty(max_rows)
    x = np.zeros(nv)
    trust = np.empty(nv)
    plan_kp = np.empty((3, n_pred))
    plan_kf = np.empty((3, n_pred))
    trial = np.empty((3, n_pred))
    block_state = np.empty((3, n_blocks, states.shape[1]))
    idle = np.ones(3, dtype=np.bool_)
    for k in range(k0, k1, replan):
        # 1: nominal predictions (held gains), keeping the state at every block start,
        #    then the sensitivities, each simulated from its block's start only
        for a in range(3):
            idle[a] = True
            if not moving[a]:
                for i in range(n_pred):
                    p0[a, i] = states[a, 0]
                    u0[a, i] = 0.0
                continue
            scratch[:] = states[a]
            for b in range(n_blocks):
                i0 = b * blen
                i1 = n_pred if b == n_blocks - 1 else i0 + blen
                block_state[a, b, :] = scratch
                for i in range(i0, i1):
                    kpa[i] = kp[a] * _C
                    kfa[i] = kf[a]
                run(scratch, params[a], pdT[a, k + i0:k + i1], vdT[a, k + i0:k + i1],
                    kpa[i0:i1], kfa[i0:i1], p0[a, i0:i1], u0[a, i0:i1])
            stats[STAT_WINDOWS] += 1
            for i in range(n_pred):  # does the axis's setpoint move within the horizon?
                if vdT[a, k + i] != 0.0 or pdT[a, k + i] != pdT[a, k]:
                    idle[a] = False
                    break
        for v in range(nv):
            a = var_axis[v]
            start = var_blk[v] * blen
            for i in range(n_pred):
                sp[v, i] = 0.0
                su[v, i] = 0.0
            if idle[a]:  # no gain can matter to an axis standing still: no sensitivity
                continue
            for i in range(start, n_pred):
                kpa[i] = kp[a] * _C
                kfa[i] = kf[a]
                if var_gain[v] == 0:
                    kpa[i] += _H * _C
                else:
                    kfa[i] += _H
            scratch[:] = block_state[a, var_blk[v], :]
            run(scratch, params[a], pdT[a, k + start:k + n_pred], vdT[a, k + start:k + n_pred],
                kpa[start:], kfa[start:], tmp_p[start:], tmp_u[start:])
            stats[STAT_WINDOWS] += 1
            for i in range(start, n_pred):
                sp[v, i] = (tmp_p[i] - p0[a, i]) / _H
                su[v, i] = (tmp_u[i] - u0[a, i]) / _H
        # 2: linearised contour error around the nominal prediction
        j = -1
        for i in range(n_pred):
            c = min(k + i, n_total - 1)
            j, t, _d2 = _nearest(pd, count, ce_window, c, j, p0[0, i], p0[1, i], p0[2, i])
            if j < 0:  # the path stands still around this sample: distance to its point
                for a in range(3):
                    dq[i, a] = p0[a, i] - pd[c, a]
                    tang[i, a] = 0.0
                continue
            sx = pd[j + 1, 0] - pd[j, 0]
            sy = pd[j + 1, 1] - pd[j, 1]
            sz = pd[j + 1, 2] - pd[j, 2]
            inv = 1.0 / np.sqrt(sx * sx + sy * sy + sz * sz)
            tang[i, 0], tang[i, 1], tang[i, 2] = sx * inv, sy * inv, sz * inv
            dq[i, 0] = p0[0, i] - (pd[j, 0] + t * sx)
            dq[i, 1] = p0[1, i] - (pd[j, 1] + t * sy)
            dq[i, 2] = p0[2, i] - (pd[j, 2] + t * sz)
        # quadratic cost: sum_i (dq_i + S_i x)' M_i (dq_i + S_i x), M = I - t t'; the
        # variables of one axis are contiguous, so each axis pair is one weighted product
        for a in range(3):
            va0, va1 = var_lo[a], var_hi[a]
            if va0 == va1:
                continue
            for i in range(n_pred):
                t = 0.0
                for b in range(3):
                    t += ((1.0 if a == b else 0.0) - tang[i, a] * tang[i, b]) * dq[i, b]
                mq[i] = t
            qvec[va0:va1] = (2.0 * _M2_TO_UM2) * (sp[va0:va1] @ mq)
            for b in range(3):
                vb0, vb1 = var_lo[b], var_hi[b]
                if vb0 == vb1:
                    continue
                for i in range(n_pred):
                    wgt[i] = ((1.0 if a == b else 0.0) - tang[i, a] * tang[i, b]) * (
                        2.0 * _M2_TO_UM2)
                pmat[va0:va1, vb0:vb1] = (sp[va0:va1] * wgt) @ sp[vb0:vb1].T
        for v in range(nv):
            a = var_axis[v]
            pmat[v, v] += 2.0 * lam
            # anchor on the gain of every block from this variable's block on
            base = kp_base[a] if var_gain[v] == 0 else kf_base[a]
            cur = kp[a] if var_gain[v] == 0 else kf[a]
            for w in range(nv):
                if var_axis[w] == a and var_gain[w] == var_gain[v]:
                    shared = n_blocks - max(var_blk[v], var_blk[w])
                    pmat[v, w] += 2.0 * anchor * shared / n_blocks
            qvec[v] += 2.0 * anchor * (cur - base) * (n_blocks - var_blk[v]) / n_blocks
        # 3: constraints: gain bounds per block, a trust region per step, eq. 2 rows
        m = 0
        for v in range(nv):
            a = var_axis[v]
            for w in range(nv):
                same = var_axis[w] == a and var_gain[w] == var_gain[v]
                amat[m, w] = 1.0 if same and var_blk[w] <= var_blk[v] else 0.0
                amat[m + 1, w] = 1.0 if w == v else 0.0
            if var_gain[v] == 0:
                alo[m] = kp_lo[a] - kp[a]
                ahi[m] = kp_hi[a] - kp[a]
                tr = trust_kp
            else:
                alo[m] = kf_lo[a] - kf[a]
                ahi[m] = kf_hi[a] - kf[a]
                tr = trust_kf
            if idle[a]:
                tr = 0.0
            alo[m + 1] = -tr
            ahi[m + 1] = tr
            trust[v] = tr
            m += 2
        for a in range(3):
            if not moving[a]:
                continue
            lims = (_LIN_MARGIN * vmax[a], _LIN_MARGIN * amax[a] * te,
                    _LIN_MARGIN * jmax[a] * te * te)
            for r in range(3):
                for i in range(n_pred):
                    # the r-th difference of u at window sample i (history before i = 0)
                    nominal = u0[a, i]
                    if r >= 1:
                        nominal -= (1.0 if r == 1 else 2.0) * (u0[a, i - 1] if i >= 1 else u_hist[a, 0])
                    if r == 2:
                        nominal += u0[a, i - 2] if i >= 2 else u_hist[a, 1 - i]
                    scale = 1.0 / lims[r]
                    for v in range(nv):
                        cv = 0.0
                        if var_axis[v] == a:
                            cv = su[v, i]
                            if r >= 1 and i >= 1:
                                cv -= (1.0 if r == 1 else 2.0) * su[v, i - 1]
                            if r == 2 and i >= 2:
                                cv += su[v, i - 2]
                        amat[m, v] = cv * scale
                    alo[m] = -1.0 - nominal * scale
                    ahi[m] = 1.0 - nominal * scale
                    # a row that no step inside the trust region can break is left out
                    reach = 0.0
                    for v in range(nv):
                        reach += abs(amat[m, v]) * trust[v]
                    if reach > min(-alo[m], ahi[m]) * (1.0 - 1e-12):
                        m += 1
        if not _qp_active_set(pmat, qvec, amat, alo, ahi, m, x):
            stats[STAT_QP_SHORT] += 1
        # 4: exact line search: the plan scaled by 1, 1/2, 1/4, 1/8 and 0 (hold), each
        #    simulated exactly; the least exact window cost among those meeting eq. 2 wins
        best_cost = np.inf
        best_scale = -1.0
        least_excess = np.inf
        least_scale = 0.0
        for t_ in range(5):
            scale = 0.0 if t_ == 4 else 0.5**t_
            worst = 0.0
            for a in range(3):
                if not moving[a]:
                    for i in range(n_pred):
                        trial[a, i] = states[a, 0]
                    continue
                _plan_gains(a, scale, x, nv, var_axis, var_gain, var_blk, blen, kp, kf, kp_lo,
                            kp_hi, kf_lo, kf_hi, n_pred, plan_kp, plan_kf, kpa, kfa)
                _simulate(states[a], params[a], pdT[a], vdT[a], k, n_pred, kpa, kfa, scratch,
                          trial[a], tmp_u)
                stats[STAT_WINDOWS] += 1
                worst = max(worst, eq2_excess(tmp_u, u_hist[a, 0], u_hist[a, 1], vmax[a],
                                               amax[a], jmax[a], te, n_pred))
            cost = 0.0
            j = -1
            for i in range(n_pred):
                c = min(k + i, n_total - 1)
                j, _t, d2 = _nearest(pd, count, ce_window, c, j, trial[0, i], trial[1, i],
                                     trial[2, i])
                if j < 0:
                    d2 = ((trial[0, i] - pd[c, 0]) ** 2 + (trial[1, i] - pd[c, 1]) ** 2
                          + (trial[2, i] - pd[c, 2]) ** 2)
                cost += d2
            cost *= _M2_TO_UM2
            for a in range(3):
                if moving[a]:
                    cost += anchor * ((plan_kp[a, n_pred - 1] - kp_base[a]) ** 2
                                      + (plan_kf[a, n_pred - 1] - kf_base[a]) ** 2)
            if worst <= 1e-9 and cost < best_cost:
                best_cost = cost
                best_scale = scale
            if worst < least_excess:
                least_excess = worst
                least_scale = scale
        if best_scale < 0.0:  # nothing meets eq. 2: take the least violating
            stats[STAT_FALLBACK] += 1
            best_scale = least_scale
        if best_scale < 1.0:
            stats[STAT_SCALED] += 1
        for a in range(3):
            if moving[a]:
                _plan_gains(a, best_scale, x, nv, var_axis, var_gain, var_blk, blen, kp, kf,
                            kp_lo, kp_hi, kf_lo, kf_hi, n_pred, plan_kp, plan_kf, kpa, kfa)
        # 5: apply the first `replan` samples of the plan and advance the true state
        for i in range(min(replan, k1 - k)):
            for a in range(3):
                if moving[a]:
                    kp[a] = plan_kp[a, i]
                    kf[a] = plan_kf[a, i]
            apply_gains(k + i, states, params, pdT, vdT, kp, kf, kp_out, kf_out, u_out, u_hist)
