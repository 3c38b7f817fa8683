"""Forward-mode derivatives of a cascade axis's simulated positions with respect to its plant
parameters: the fit's Jacobian in one pass instead of a re-simulation per parameter.

:func:`positions_and_sensitivities` simulates the axis exactly as
:func:`oga.model.simulate.simulate_axis` does (the same arithmetic: the same positions to the last
bit) and carries, beside the state ``(p, v, F, I)`` and the dead-time line, its derivatives
along ``D`` directions of the packed parameters (:func:`oga.model.simulate.axis_params`): the
sub-step mechanics' coefficients, ``Kv``, ``1/Tn``, the friction's ``Fc``, ``Fs - Fc`` and
``1/vs``, the lifted map over Te (and the linear friction map, on a machine that sets
``timing.friction_linear_below_m_s``; identification's do not). The derivative follows
the branch the nominal simulation takes at each period (the lifted map where it is exact,
else the sub-steps with the velocity PI, its force limit and anti-windup, and the friction
through its slope), as :mod:`oga.model.tangent` does for the gains; it is exact for the
computation performed, except where the axis sticks (the friction's slope there limited:
see :func:`_advance_sens`).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from oga.model.simulate import (
    _DEAD,
    _DFS,
    _FC,
    _FRAC,
    _INV_EPS,
    _INV_TN,
    _INV_VS,
    _KV,
    _LIFTED,
    _NSUB,
    _delayed,
    _lifted,
    _lifted_guard,
    _linear,
    _linear_guard,
    _mechanics,
    _pi_coefs,
    _pi_substep,
    _same,
    _smooth_sign,
    _substep_coefs,
    friction_and_slope,
)

__all__ = ["positions_and_sensitivities", "forces_and_sensitivities"]


@njit(cache=True, inline="always")
def _friction_terms(params, v):
    """``(ds, dx, dv)``: the Coulomb + Stribeck force's derivative at ``v`` (velocity held) is
    ``ds dFc + dx d(Fs - Fc) + dv d(1/vs)``. The Stribeck term's derivative is taken even
    where its value is cut (there it is below an ulp of the force, or the term is zero)."""
    s = _smooth_sign(v * params[_INV_EPS])
    r = v * params[_INV_VS]
    r2 = r * r
    ex = math.exp(-r2) if r2 < 700.0 else 0.0
    return s, s * ex, -2.0 * r * v * params[_DFS] * s * ex


#: The setpoints of one axis for :func:`_run_sens`: ``pd``, ``vd``, ``kp_si``, ``kf`` (N,)
#: (m, m/s, 1/s, factor), float64, contiguous.
Command = namedtuple("Command", ["pd", "vd", "kp_si", "kf"])

#: The outputs :func:`_run_sens` fills: ``p`` (N,) positions (m), ``dp`` (N, D), ``f`` (N,)
#: forces (N), ``df`` (N, D).
Sensitivities = namedtuple("Sensitivities", ["p", "dp", "f", "df"])


@njit(cache=True)
def _advance_sens(params, dpar, dc, state, ud, tangents, dud, memo, replay):
    """:func:`oga.model.simulate._advance` (no load) of one Te from ``state`` ``(p, v, f, i)``;
    the tangents ``tangents`` (4, D) (rows p, v, f, i) advanced in place; ``dud`` (D,) the
    derivatives of the command ``ud``; ``dc`` (D, 10) the directions'
    :func:`oga.model.simulate._substep_coefs`. Returns the next state. ``memo`` (NSUB + 1,
    12): the nominal sub-steps' values the tangents use (:func:`_nominal_substeps`), its last
    row's first entry 1 where they were taken; ``replay``: the last period had this state and
    ``ud`` and left the state as it was (so takes the same path to the same values): its
    sub-steps' values are read from ``memo`` instead of computed again."""
    p, v, f, i = state
    dp, dv, df, di = tangents[0], tangents[1], tangents[2], tangents[3]
    nd = dpar.shape[0]
    nsub = int(params[_NSUB])
    if replay and memo[nsub, 0] == 1.0:
        _tangent_substeps(params, dpar, dc, tangents, dud, memo)
        return p, v, f, i
    memo[nsub, 0] = 0.0
    if v == 0.0 and f == 0.0 and i == 0.0 and ud == 0.0:
        return p, v, f, i  # at rest and not driven: nothing moves (as the simulator)
    if _linear_guard(params, v, f, i, ud, 0.0):  # linear friction map (a machine setting)
        for d in range(nd):
            lp, lv, lf, li = _linear(params, dp[d], dv[d], df[d], di[d], dud[d], 0.0)
            cp, cv, cf, ci = _linear(dpar[d], 0.0, v, f, i, ud, 0.0)  # its coefficients moved
            dp[d], dv[d], df[d], di[d] = lp + cp, lv + cv, lf + cf, li + ci
        return _linear(params, p, v, f, i, ud, 0.0)
    fn, slope = friction_and_slope(params, v)
    fs, fx, fv = _friction_terms(params, v)
    if params[_LIFTED] != 0.0 and _lifted_guard(params, v, f, i, ud, fn):
        for d in range(nd):
            q = dpar[d]
            dfn = slope * dv[d] + fs * q[_FC] + fx * q[_DFS] + fv * q[_INV_VS]
            lp, lv, lf, li = _lifted(params, dp[d], dv[d], df[d], di[d], dud[d], dfn)
            cp, cv, cf, ci = _lifted(q, 0.0, v, f, i, ud, fn)  # its coefficients moved
            dp[d], dv[d], df[d], di[d] = lp + cp, lv + cv, lf + cf, li + ci
        return _lifted(params, p, v, f, i, ud, fn)
    out = _nominal_substeps(params, state, ud, fn, slope, (fs, fx, fv), memo)
    memo[nsub, 0] = 1.0
    _tangent_substeps(params, dpar, dc, tangents, dud, memo)
    return out


@njit(cache=True)
def _nominal_substeps(params, state, ud, fn, slope, terms, memo):
    """The sub-steps of one Te from ``state`` (``fn``, ``slope``, ``terms`` the friction's
    at its velocity): returns the next state; row ``j`` of ``memo`` gets what the tangents
    use of sub-step ``j``: ``(slope, fs, fx, fv, linear, integrating, I, e + I/Tn, v, F,
    F_cmd, F_n)``."""
    p, v, f, i = state
    fs, fx, fv = terms
    c = _substep_coefs(params)
    pi = _pi_coefs(params)
    inv_tn = pi[1]
    # the friction's slope is steep near v = 0 (Fc / smoothing velocity): held over a sub-step
    # it makes the nominal velocity chatter about 0 (bounded by the friction itself) and the
    # tangent grow without bound. Limited to the slope that stops the velocity's tangent in
    # one sub-step (v's factor c2 + c8 slope = 0): the derivative of an axis that sticks.
    stick = c[2] / -c[8]
    for j in range(int(params[_NSUB])):
        if j > 0:
            fn, slope = friction_and_slope(params, v)
            fs, fx, fv = _friction_terms(params, v)
        fc, i_next, linear, integrating = _pi_substep(ud, v, i, pi)
        row = memo[j]
        row[0], row[1], row[2], row[3] = min(slope, stick), fs, fx, fv
        row[4], row[5] = 1.0 if linear else 0.0, 1.0 if integrating else 0.0
        row[6], row[7], row[8], row[9], row[10], row[11] = i, (ud - v) + i * inv_tn, v, f, fc, fn
        i = i_next
        p, v, f = _mechanics(c, p, v, f, fc, fn)
    return p, v, f, i


@njit(cache=True)
def _tangent_substeps(params, dpar, dc, tangents, dud, memo):
    """The tangents (4, D) through the sub-steps whose nominal values ``memo`` holds
    (:func:`_nominal_substeps`), in place."""
    dp, dv, df, di = tangents[0], tangents[1], tangents[2], tangents[3]
    c = _substep_coefs(params)
    kv, inv_tn, h, _flim = _pi_coefs(params)
    for j in range(int(params[_NSUB])):
        slope, fs, fx, fv, linear, integrating, i, w, v, f, fc, fn = memo[j]
        for d in range(dpar.shape[0]):
            q = dpar[d]
            dfn = slope * dv[d] + fs * q[_FC] + fx * q[_DFS] + fv * q[_INV_VS]
            de = dud[d] - dv[d]
            dfc = 0.0  # a limited force command does not move
            if linear != 0.0:
                dfc = kv * (de + di[d] * inv_tn + i * q[_INV_TN]) + q[_KV] * w
            if integrating != 0.0:  # a frozen integral does not move either
                di[d] += h * de
            k = dc[d]
            p0, v0, f0 = dp[d], dv[d], df[d]
            dp[d] = (p0 + c[0] * v0 + c[1] * f0 + c[5] * dfc + c[6] * dfn
                     + k[0] * v + k[1] * f + k[5] * fc + k[6] * fn)
            dv[d] = (c[2] * v0 + c[3] * f0 + c[7] * dfc + c[8] * dfn
                     + k[2] * v + k[3] * f + k[7] * fc + k[8] * fn)
            df[d] = c[4] * f0 + c[9] * dfc + k[4] * f + k[9] * fc


@njit(cache=True, inline="always")
def _all_same(a, b) -> bool:
    """Every entry of ``a`` the same float64 as ``b``'s (:func:`oga.model.simulate._same`)."""
    for j in range(a.shape[0]):
        if not _same(a[j], b[j]):
            return False
    return True


@njit(cache=True, inline="always")
def _state_same(before, state) -> bool:
    """The period left the state ``(p, v, F, I)`` as ``before[:4]`` held it, to the bit."""
    for j in range(4):
        if not _same(state[j], before[j]):
            return False
    return True


@njit(cache=True)
def _run_sens(params, dpar, p0, cmd, out):
    """Simulate one axis from rest at ``p0`` on the :data:`Command` ``cmd`` with the
    tangents along the directions ``dpar`` (D, P); fills the :data:`Sensitivities` ``out``."""
    pd, vd, kp_si, kf = cmd.pd, cmd.vd, cmd.kp_si, cmd.kf
    out_p, out_dp, out_f, out_df = out.p, out.dp, out.f, out.df
    dead = int(params[_DEAD])
    n = pd.shape[0]
    nd = dpar.shape[0]
    dc = np.empty((nd, 10))
    for d in range(nd):
        k = _substep_coefs(dpar[d])
        for j in range(10):
            dc[d, j] = k[j]
    frac = params[_FRAC]
    u_hist = np.empty(n)
    du_hist = np.empty((n, nd))
    tangents = np.zeros((4, nd))
    dp, df = tangents[0], tangents[2]
    dud = np.zeros(nd)
    state = (p0, 0.0, 0.0, 0.0)
    # as the simulator skips a period that provably changes nothing (its state a floating-point
    # fixed point under the same command), so here, where the tangents and their command are
    # fixed points too: the same inputs, the same period (the axis standing, stuck in its
    # friction, while another axis moves)
    # the nominal state alone a fixed point (``fixed``): the period's nominal sub-steps are
    # the last one's, read back from ``memo`` (the tangents still move)
    still, fixed, ud_still = False, False, 0.0
    memo = np.zeros((int(params[_NSUB]) + 1, 12))
    dud_still = np.zeros(nd)
    before = np.empty(4 + 4 * nd)
    for k in range(n):
        p, f = state[0], state[2]
        out_p[k] = p
        out_f[k] = f
        u_hist[k] = kp_si[k] * (pd[k] - p) + kf[k] * vd[k]
        for d in range(nd):
            out_dp[k, d] = dp[d]
            out_df[k, d] = df[d]
            du_hist[k, d] = -kp_si[k] * dp[d]
        m = k - dead
        ud = u_hist[m] if m >= 0 else 0.0  # the dead-time line starts empty (at rest)
        for d in range(nd):
            dud[d] = du_hist[m, d] if m >= 0 else 0.0
        if frac != 0.0:  # fractional: f u_m + (1 - f) u_{m+1}, f a parameter too
            newer = u_hist[m + 1] if m + 1 >= 0 else 0.0
            for d in range(nd):
                dnewer = du_hist[m + 1, d] if m + 1 >= 0 else 0.0
                dud[d] = frac * dud[d] + (1.0 - frac) * dnewer + dpar[d, _FRAC] * (ud - newer)
            ud = _delayed(params, ud, newer)
        if still and _same(ud, ud_still) and _all_same(dud, dud_still):
            continue  # a fixed point under the same inputs: this period changes nothing
        replay = fixed and _same(ud, ud_still)
        before[:4] = state
        before[4:] = tangents.ravel()
        state = _advance_sens(params, dpar, dc, state, ud, tangents, dud, memo, replay)
        fixed = _state_same(before, state)
        still = fixed and _all_same(tangents.ravel(), before[4:])
        ud_still = ud
        dud_still[:] = dud


def positions_and_sensitivities(params: np.ndarray, dparams: np.ndarray, p0: float, pd, vd,
                                kp_si, kf) -> tuple[np.ndarray, np.ndarray]:
    """Simulate a cascade axis from rest at ``p0`` and the derivatives of its positions.

    Parameters
    ----------
    params : ndarray
        :func:`oga.model.simulate.axis_params` of a cascade axis (its dead time included).
    dparams : ndarray, shape (D, len(params))
        Directions in the packed parameters (e.g. their derivatives with respect to D
        fitted quantities); only the entries the kernel uses matter (mechanics, PI,
        friction, lifted map), the others (limits, guards, sizes) are ignored.
    p0 : float
    pd, vd, kp_si, kf : ndarray, shape (N,), float64, contiguous
        Setpoints (m, m/s) and gains (1/s, factor) per sample.

    Returns
    -------
    p : ndarray, shape (N,)
        Positions, m (equal to :func:`oga.model.simulate.simulate_axis`'s).
    dp : ndarray, shape (N, D)
        Their derivatives along each direction, m per unit of the direction.
    """
    p, dp, _, _ = forces_and_sensitivities(params, dparams, p0, pd, vd, kp_si, kf)
    return p, dp


def forces_and_sensitivities(params: np.ndarray, dparams: np.ndarray, p0: float, pd, vd,
                             kp_si, kf):
    """:func:`positions_and_sensitivities` with the drive force (the force lag's output, as
    :func:`oga.identify.sim.simulate_forces` records it) and its derivatives too.

    Returns
    -------
    p, dp, f, df : ndarray, shapes (N,), (N, D), (N,), (N, D)
        Positions (m), forces (N) and their derivatives along each direction.
    """
    n, nd = pd.shape[0], dparams.shape[0]
    out_p, out_dp = np.empty(n), np.empty((n, nd))
    out_f, out_df = np.empty(n), np.empty((n, nd))
    _run_sens(params, np.ascontiguousarray(dparams, dtype=np.float64), float(p0),
              Command(pd, vd, kp_si, kf), Sensitivities(out_p, out_dp, out_f, out_df))
    return out_p, out_dp, out_f, out_df
