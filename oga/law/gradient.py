"""The derivatives of a program's replay with respect to a law's support values.

A law's gain at sample ``k`` is a fixed convex combination of its support values
(:func:`oga.law.law.basis`: the weights depend only on the planned ``|v|``, ``|a|``), so
the derivative of every replayed position and velocity command with respect to one
support value is the forward-mode tangent of the simulation along that weight sequence
(:func:`oga.model.tangent.run_tangent`, the window search's sensitivities, here over the whole
program in one pass: the same positions and commands as :func:`oga.model.response.simulate`,
to the bit).

The contour error is linearised as the window search does (:mod:`oga.search.window`): at each feed
sample, the distance to the nearest path segment the replay measures against
(:func:`oga.model.contour.nearest_at`), through the projection ``P = I - t t'`` off that segment's
tangent ``t``: ``|CE|^2 ~ |P (dq + S d)|^2``, ``dq`` the offset from the nearest point and
``S`` the positions' sensitivities. :func:`gauss_newton` sums the Gauss-Newton Hessian
``S' P S`` and gradient ``S' P dq`` over the samples.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from oga.model.contour import contour_offset
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM
from oga.model.simulate import axis_params, rest_state
from oga.model.tangent import run_tangent

__all__ = ["ce_offsets", "axis_tangent", "gauss_newton"]


@njit(cache=True)
def ce_offsets(pd, tree, win_lo, win_hi, feed, pos, dq, tang):
    """Per sample ``k`` of ``feed``: ``dq[k]`` the offset of ``pos[k]`` from its nearest path
    point, ``tang[k]`` the unit tangent of that segment (zero where the path stands still
    over the window; both zero off ``feed``). Returns the sum of the squared contour errors
    (m^2) of the feed samples, as :func:`oga.model.contour.contour_error_of` measures them."""
    n = pd.shape[0]
    j = -1
    total = 0.0
    for k in range(n):
        for a in range(3):
            dq[k, a] = 0.0
            tang[k, a] = 0.0
        if not feed[k]:
            continue
        j, total, dq[k, 0], dq[k, 1], dq[k, 2], tang[k, 0], tang[k, 1], tang[k, 2] = \
            contour_offset(pd, tree, win_lo[k], win_hi[k], k, win_lo[k], pos[k], j, total)
    return total


def axis_tangent(plant, axis: str, i: int, pd: np.ndarray, vd: np.ndarray, kp: np.ndarray,
                 kf: np.ndarray, w_kp: np.ndarray, w_kf: np.ndarray):
    """Replay one axis of ``plant`` from rest with gains ``kp`` ((m/min)/mm), ``kf`` (N,) and
    the derivatives along its law's support values.

    Parameters
    ----------
    pd, vd : ndarray, shape (N, 3)
        Setpoints (m, m/s); column ``i`` is the axis's.
    w_kp, w_kf : ndarray, shape (N, nkp), (N, nkf)
        The law's weights (:func:`oga.law.law.basis`) of its Kp and Kf support values.

    Returns
    -------
    p, u : ndarray, shape (N,)
        Positions (m) and velocity commands (m/s), the bits of :func:`oga.model.response.simulate`.
    sp, su : ndarray, shape (N, nkp + nkf)
        Their derivatives per support value (Kp's first, per (m/min)/mm; then Kf's).
    """
    n, nkp, nkf = len(pd), w_kp.shape[1], w_kf.shape[1]
    d = nkp + nkf
    params = axis_params(plant, axis)
    state = rest_state(params, float(pd[0, i]))
    dkp = np.zeros((n, d))
    dkp[:, :nkp] = w_kp * KP_SI_PER_M_MIN_PER_MM
    dkf = np.zeros((n, d))
    dkf[:, nkp:] = w_kf
    p, u = np.empty(n), np.empty(n)
    sp, su = np.empty((n, d)), np.empty((n, d))
    run_tangent(state, params, (np.ascontiguousarray(pd[:, i]), np.ascontiguousarray(vd[:, i]),
                np.ascontiguousarray(kp * KP_SI_PER_M_MIN_PER_MM), np.ascontiguousarray(kf),
                dkp, dkf), np.zeros(d, dtype=np.int64), (p, u, sp, su))
    return p, u, sp, su


def gauss_newton(dq: np.ndarray, tang: np.ndarray, feed: np.ndarray, sens: dict[int, np.ndarray],
                 cols: dict[int, slice], nv: int) -> tuple[np.ndarray, np.ndarray, float]:
    """``H = sum S' P S``, ``g = sum S' P dq`` and ``sum |P dq|^2`` over the feed samples.

    Parameters
    ----------
    dq, tang : ndarray, shape (N, 3)
        From :func:`ce_offsets`.
    feed : ndarray of bool, shape (N,)
    sens : dict of int to ndarray (N, D_i)
        Per moving axis ``i``, its positions' sensitivities (:func:`axis_tangent`).
    cols : dict of int to slice
        The columns of axis ``i``'s support values in the parameter vector.
    nv : int
        Parameters in all.
    """
    h, g = np.zeros((nv, nv)), np.zeros(nv)
    f = feed.astype(np.float64)
    pdq = dq * f[:, None] - tang * np.einsum("ka,ka->k", tang, dq)[:, None]
    for a, sa in sens.items():
        g[cols[a]] += sa.T @ pdq[:, a]
        for b, sb in sens.items():
            pab = (f if a == b else 0.0) - tang[:, a] * tang[:, b]
            h[cols[a], cols[b]] += sa.T @ (sb * pab[:, None])
    return h, g, float(np.sum(pdq * pdq))
