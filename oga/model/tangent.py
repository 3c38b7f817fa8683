"""Forward-mode derivatives of the axis simulation with respect to its gain sequences.

:func:`run_tangent` simulates one axis exactly as :func:`oga.model.simulate.run` does
(the same arithmetic: the same positions and commands to the last bit) and, in
the same pass, propagates ``D`` tangent directions: for a direction
``(dKp_k, dKf_k)`` over the samples, the derivatives of every measured position
``p_k`` and velocity command ``u_k`` along it. The full-mode search
(:mod:`oga.search.window`) needs exactly these (its sensitivities); one pass with the
directions side by side replaces a finite-difference re-simulation per direction.

The derivative follows the branch the nominal simulation takes at each period:

- the lifted linear map over Te (:func:`oga.model.simulate._lifted`), taken only where
  the friction force is provably constant over the period: its derivative there
  is zero, and the map is linear;
- the linear friction map over Te (:func:`oga.model.simulate._linear`, only on a machine that
  sets ``timing.friction_linear_below_m_s``): linear, the friction inside it;
- otherwise the sub-steps: the velocity PI (its derivative is zero while the force
  command is limited, the integral's while it is frozen by the anti-windup), the
  nonlinear friction through its slope ``dF_n/dv`` at each sub-step start, and the
  linear mechanics;
- ARX axes: the identified difference equation, the input-equivalent friction
  through its slope.

The derivative is exact for the computation performed (a piecewise-smooth
function: at a switch of the force limit or of the anti-windup it is one of the
one-sided derivatives). Only the gains are differentiated: the initial state and
the setpoints are data.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from oga.model.simulate import (
    _A_B0,
    _A_COEF,
    _A_FC,
    _A_INV_EPS,
    _A_NV,
    _A_NW,
    _A_TE,
    _A_VISC,
    _ARX,
    _DEAD,
    _F,
    _FRAC,
    _I,
    _KIND,
    _LIFTED,
    _LINE,
    _NSUB,
    _P,
    _V,
    _arx_drive,
    _delayed,
    _lifted,
    _lifted_guard,
    _linear,
    _linear_guard,
    _mechanics,
    _pi_coefs,
    _pi_substep,
    _smooth_sign_and_slope,
    _store_cascade,
    _substep_coefs,
    friction_and_slope,
)

__all__ = ["run_tangent", "friction_slope"]

#: Rows of the tangent block of :func:`run_tangent` (5, D): the derivatives of the position,
#: velocity, force, PI integral and applied command along each direction.
_DP, _DV, _DF, _DI, _DUD = 0, 1, 2, 3, 4


@njit(cache=True)
def friction_slope(params: np.ndarray, v: float) -> float:
    """Slope of the axis friction at velocity ``v`` (m/s).

    Cascade: ``dF_n/dv`` of :func:`oga.model.simulate.friction_nonlinear` (N s/m; the
    viscous part is in the linear mechanics); ARX: the derivative of
    :func:`oga.model.simulate.friction_command_m_s` ((m/s)/(m/s)).
    """
    if params[_KIND] == _ARX:
        inv_eps = params[_A_INV_EPS]
        _s, ds = _smooth_sign_and_slope(v * inv_eps)
        return params[_A_FC] * ds * inv_eps + params[_A_VISC]
    return friction_and_slope(params, v)[1]


@njit(cache=True)
def _substeps_tangent(params, x, ud, dx, nd, fn, slope):
    """:func:`oga.model.simulate._substeps` (no load) from ``x = (p, v, F, I)`` with the tangents
    ``dx`` (rows :data:`_DP` ..) of the first ``nd`` directions advanced in place; returns the
    nominal ``(p, v, F, I)``. ``fn, slope``: :func:`oga.model.simulate.friction_and_slope` at ``v``
    (the first sub-step's, already known to the caller)."""
    p, v, f, i = x
    dp, dv, df, di, dud = dx[_DP], dx[_DV], dx[_DF], dx[_DI], dx[_DUD]
    c = _substep_coefs(params)
    pi = _pi_coefs(params)
    kv, inv_tn, h, _flim = pi
    for j in range(int(params[_NSUB])):
        if j > 0:
            fn, slope = friction_and_slope(params, v)
        fc, i_next, linear, integrating = _pi_substep(ud, v, i, pi)
        kv_lin = kv if linear else 0.0  # a limited force command does not move
        h_int = h if integrating else 0.0  # nor does a frozen integral
        for d in range(nd):
            de = dud[d] - dv[d]
            dfc = kv_lin * (de + di[d] * inv_tn)
            di[d] += h_int * de
            dp[d], dv[d], df[d] = _mechanics(c, dp[d], dv[d], df[d], dfc, slope * dv[d])
        i = i_next
        p, v, f = _mechanics(c, p, v, f, fc, fn)
    return p, v, f, i


@njit(cache=True)
def _lifted_tangent(params, dp, dv, df, di, dud, nd):
    """The tangents of the first ``nd`` directions through the lifted map, in place
    (the friction force is constant there: its derivative is zero)."""
    for d in range(nd):
        dp[d], dv[d], df[d], di[d] = _lifted(params, dp[d], dv[d], df[d], di[d], dud[d], 0.0)


@njit(cache=True)
def _arx_tangent(state, params, dst, du, nd):
    """The tangent of :func:`oga.model.simulate._arx_drive` (no load) for the first ``nd``
    directions, in place: ``dst`` (S, D) holds the state's derivatives, ``du`` (D,) the
    command's. Call it before the nominal drive (it reads the state at the period's start)."""
    nv = int(params[_A_NV])
    nw = int(params[_A_NW])
    slope = friction_slope(params, state[1])
    b0 = params[_A_B0]
    te = params[_A_TE]
    for d in range(nd):
        dw = du[d] - slope * dst[1, d]
        dvel = b0 * dw
        for j in range(nv):
            dvel -= params[_A_COEF + j] * dst[1 + j, d]
        for j in range(nw):
            dvel += params[_A_COEF + nv + j] * dst[1 + nv + j, d]
        for j in range(nv - 1, 0, -1):
            dst[1 + j, d] = dst[j, d]
        dst[1, d] = dvel
        if nw > 0:
            for j in range(nw - 1, 0, -1):
                dst[1 + nv + j, d] = dst[nv + j, d]
            dst[1 + nv, d] = dw
        dst[0, d] += te * dvel


@njit(cache=True)
def run_tangent(state, params, drive, start, out):
    """:func:`oga.model.simulate.run` and its derivatives along ``D`` gain directions, in one pass.

    Parameters
    ----------
    state : ndarray, shape (state size,)
        Axis state at sample 0; on return the state at sample N (as ``run``).
    params : ndarray
        From :func:`oga.model.simulate.axis_params`.
    drive : tuple ``(pd, vd, kp_si, kf, dkp_si, dkf)``
        ``pd, vd, kp_si, kf`` (N,): setpoints (m, m/s) and the nominal gains (1/s, factor)
        per sample. ``dkp_si, dkf`` (N, D): the directions: per sample and direction the
        change of Kp (1/s per unit of the direction's parameter) and of Kf (per unit).
    start : ndarray of int, shape (D,)
        Non-decreasing; direction ``d`` is zero before sample ``start[d]`` (its
        derivatives are zero there and are not propagated: speed only).
    out : tuple ``(out_p, out_u, sp, su)``
        ``out_p, out_u`` (N,) receive the positions ``p_k`` (m) and commands ``u_k`` (m/s),
        the same bits as ``run``; ``sp, su`` (N, D) receive ``dp_k/dtheta_d`` (m per unit)
        and ``du_k/dtheta_d`` (m/s per unit).
    """
    out_p, out_u, su = out[0], out[1], out[3]
    n = drive[0].shape[0]
    nd_all = start.shape[0]
    nd = 0  # active directions: start[d] <= k
    if params[_KIND] == _ARX:
        dst = np.zeros((state.shape[0], nd_all))
        for k in range(n):
            out_p[k] = state[_P]
            out_u[k], nd = _record(k, nd, start, state[_P], dst[0], drive, out)
            _arx_tangent(state, params, dst, su[k], nd)
            _arx_drive(state, params, out_u[k], 0.0)
        return
    dead = int(params[_DEAD])
    frac = params[_FRAC]
    lifted = params[_LIFTED] != 0.0
    dx = np.zeros((5, nd_all))  # the tangents of p, v, F, I and the applied command
    dp, dv, df, di, dud = dx[_DP], dx[_DV], dx[_DF], dx[_DI], dx[_DUD]
    p, v, f, i = state[_P], state[_V], state[_F], state[_I]
    for k in range(n):
        out_p[k] = p
        out_u[k], nd = _record(k, nd, start, p, dp, drive, out)
        m = k - dead  # the command applied now is u_m; the line's initial commands are data
        if m >= 0:
            ud = out_u[m]
            for d in range(nd):
                dud[d] = su[m, d]
        else:
            ud = state[_LINE + dead - 1 - k]
            for d in range(nd):
                dud[d] = 0.0
        if frac != 0.0:  # a fractional dead time: with the next command (issued: m + 1 <= k)
            if m + 1 >= 0:
                ud = _delayed(params, ud, out_u[m + 1])
                for d in range(nd):
                    dud[d] = frac * dud[d] + (1.0 - frac) * su[m + 1, d]
            else:
                ud = _delayed(params, ud, state[_LINE + dead - 2 - k])
                for d in range(nd):
                    dud[d] = frac * dud[d]
        if _linear_guard(params, v, f, i, ud, 0.0):  # as :func:`oga.model.simulate._advance`
            for d in range(nd):
                dp[d], dv[d], df[d], di[d] = _linear(params, dp[d], dv[d], df[d], di[d], dud[d],
                                                     0.0)
            p, v, f, i = _linear(params, p, v, f, i, ud, 0.0)
            continue
        fn, slope = friction_and_slope(params, v)
        if lifted and _lifted_guard(params, v, f, i, ud, fn):
            _lifted_tangent(params, dp, dv, df, di, dud, nd)
            p, v, f, i = _lifted(params, p, v, f, i, ud, fn)
        else:  # the sub-steps (also at rest, where they change nothing: the same bits as run)
            p, v, f, i = _substeps_tangent(params, (p, v, f, i), ud, dx, nd, fn, slope)
    _store_cascade(state, dead, out_u, n, p, v, f, i)


@njit(cache=True, inline="always")
def _record(k, nd, start, p, dpos, drive, out):
    """Sample ``k`` of :func:`run_tangent` (``drive``, ``out`` as there): the directions active
    from it on, the measured position's derivatives ``dpos`` into ``sp[k]`` and the command's
    into ``su[k]`` (zero for the directions not yet started). Returns ``(u_k, active
    directions)``."""
    pd, vd, kp_si, kf, dkp_si, dkf = drive
    sp, su = out[2], out[3]
    nd_all = start.shape[0]
    while nd < nd_all and start[nd] <= k:
        nd += 1
    e = pd[k] - p
    for d in range(nd):
        sp[k, d] = dpos[d]
        su[k, d] = dkp_si[k, d] * e - kp_si[k] * dpos[d] + dkf[k, d] * vd[k]
    for d in range(nd, nd_all):
        sp[k, d] = 0.0
        su[k, d] = 0.0
    return kp_si[k] * e + kf[k] * vd[k], nd
