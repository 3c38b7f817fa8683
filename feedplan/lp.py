"""Linear programs whose constraint rows each touch a few consecutive unknowns.

``min c.z  subject to  A z <= b,  lo <= z <= hi``, where every row of ``A`` has its non-zeros
among ``W`` consecutive columns (``W = val.shape[1]``; the speed profile's rows touch the two
unknowns of each end of one grid cell: ``W = 4``). Then ``A^T D A`` is a band matrix of
half-bandwidth ``W - 1`` and one Newton step of an interior point method costs ``O(n W^2)``:
the solve is linear in the number of unknowns (HiGHS, measured on the same programs, took
0.3-0.5 s per 1 000 grid nodes).

Method: Mehrotra's predictor-corrector primal-dual interior point method (infeasible start,
separate primal and dual step lengths), the Newton steps by a banded Cholesky factorisation
of the normal equations (tiny pivots, of dependent or inactive columns, are skipped as in
LIPSOL). Unknowns marked inactive keep their starting value (their columns must be zero).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["LPResult", "banded_lp"]

#: Status codes of :class:`LPResult`.
OPTIMAL, ITERATION_LIMIT, NUMERICAL = 0, 1, 2
_STATUS = ("optimal", "iteration limit", "numerical trouble")
#: Fraction of the distance to the boundary a step may go.
_ETA = 0.995
#: Relative dual residual accepted at the optimum (:func:`_interior_point`).
_DUAL_TOL = 1e-6


@dataclass(frozen=True)
class LPResult:
    """Solution of :func:`banded_lp`.

    Attributes
    ----------
    z : ndarray, shape (n,)
        The unknowns (the last iterate when not optimal).
    status : str
        "optimal", "iteration limit" or "numerical trouble".
    iterations : int
        Interior point iterations taken.
    """

    z: np.ndarray
    status: str
    iterations: int

    @property
    def ok(self) -> bool:
        return self.status == "optimal"


@njit(cache=True)
def _matvec(col0, val, z, out):
    """out = A z."""
    for r in range(col0.shape[0]):
        acc = 0.0
        c = col0[r]
        for p in range(val.shape[1]):
            acc += val[r, p] * z[c + p]
        out[r] = acc


@njit(cache=True)
def _rmatvec(col0, val, y, out):
    """out = A^T y."""
    out[:] = 0.0
    for r in range(col0.shape[0]):
        c = col0[r]
        for p in range(val.shape[1]):
            out[c + p] += val[r, p] * y[r]


@njit(cache=True)
def _factor(col0, val, d_row, d_var, active, band):
    """Banded Cholesky factor of ``A^T diag(d_row) A + diag(d_var)``: ``band[i, k]`` holds
    ``L[i, i - k]``. Inactive unknowns get a unit row; a pivot below 1e-30 of its diagonal
    (a column with no weight left) is made huge (its step is then 0)."""
    n, w = band.shape
    band[:, :] = 0.0
    for r in range(col0.shape[0]):
        c, d = col0[r], d_row[r]
        for p in range(w):
            a = val[r, p] * d
            if a == 0.0:
                continue
            for q in range(p + 1):
                band[c + p, p - q] += a * val[r, q]
    for i in range(n):
        if active[i]:
            band[i, 0] += d_var[i]
        else:
            band[i, 0] = 1.0
            for k in range(1, w):
                band[i, k] = 0.0
                if i + k < n:
                    band[i + k, k] = 0.0
    for i in range(n):
        diag0 = band[i, 0]
        for k in range(w - 1, 0, -1):
            j = i - k
            if j < 0:
                continue
            s = band[i, k]
            for q in range(k + 1, w):  # sum over L[i, j - (q - k)] L[j, j - (q - k)]
                if j - (q - k) < 0:
                    break
                s -= band[i, q] * band[j, q - k]
            band[i, k] = s / band[j, 0]
        s = band[i, 0]
        for k in range(1, w):
            s -= band[i, k] * band[i, k]
        if not s > 1e-30 * max(diag0, 1e-300):
            s = 1e128
        band[i, 0] = math.sqrt(s)


@njit(cache=True)
def _solve(band, rhs, out):
    """Solve L L^T out = rhs with :func:`_factor`'s band."""
    n, w = band.shape
    for i in range(n):
        s = rhs[i]
        for k in range(1, w):
            if i - k >= 0:
                s -= band[i, k] * out[i - k]
        out[i] = s / band[i, 0]
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(1, w):
            if i + k < n:
                s -= band[i + k, k] * out[i + k]
        out[i] = s / band[i, 0]


@njit(cache=True)
def _max_step(x, dx, mask):
    """Largest a <= 1 with x + a dx >= 0 where mask."""
    a = 1.0
    for i in range(x.shape[0]):
        if mask[i] and dx[i] < 0.0:
            a = min(a, -x[i] / dx[i])
    return a


@njit(cache=True)
def _directions(col0, val, rp, rd, rl, ru, s, y, wl, pl, wu, pu, hl, hu, active, band,
                rcs, rcl, rcu, dz, ds, dy, dwl, dpl, dwu, dpu, tmp_m, tmp_n):
    """The Newton direction for complementarity targets rcs, rcl, rcu (module docstring)."""
    m, n = s.shape[0], dz.shape[0]
    for r in range(m):
        tmp_m[r] = (rcs[r] + y[r] * rp[r]) / s[r]
    _rmatvec(col0, val, tmp_m, tmp_n)
    for i in range(n):
        v = -rd[i] - tmp_n[i]
        if hl[i]:
            v += (rcl[i] - pl[i] * rl[i]) / wl[i]
        if hu[i]:
            v -= (rcu[i] + pu[i] * ru[i]) / wu[i]
        tmp_n[i] = v if active[i] else 0.0
    _solve(band, tmp_n, dz)
    _matvec(col0, val, dz, ds)
    for r in range(m):
        ds[r] = -rp[r] - ds[r]
        dy[r] = (rcs[r] - y[r] * ds[r]) / s[r]
    for i in range(n):
        if hl[i]:
            dwl[i] = dz[i] + rl[i]
            dpl[i] = (rcl[i] - pl[i] * dwl[i]) / wl[i]
        else:
            dwl[i] = dpl[i] = 0.0
        if hu[i]:
            dwu[i] = -dz[i] - ru[i]
            dpu[i] = (rcu[i] - pu[i] * dwu[i]) / wu[i]
        else:
            dwu[i] = dpu[i] = 0.0


@njit(cache=True)
def _interior_point(c, col0, val, b, lo, hi, active, z0, tol, max_iter):
    m, n, w = b.shape[0], c.shape[0], val.shape[1]
    hl = active & (lo > -np.inf)
    hu = active & (hi < np.inf)
    z = z0.copy()
    for i in range(n):  # strictly inside the box
        if hl[i] and hu[i]:
            gap = hi[i] - lo[i]
            z[i] = min(max(z[i], lo[i] + 0.01 * gap), hi[i] - 0.01 * gap)
        elif hl[i]:
            z[i] = max(z[i], lo[i] + 1.0)
        elif hu[i]:
            z[i] = min(z[i], hi[i] - 1.0)
    az = np.empty(m)
    _matvec(col0, val, z, az)
    s, y = np.empty(m), np.ones(m)
    for r in range(m):
        s[r] = max(b[r] - az[r], 1.0)
    wl, pl, wu, pu = np.ones(n), np.zeros(n), np.ones(n), np.zeros(n)
    for i in range(n):
        if hl[i]:
            wl[i] = z[i] - lo[i]
            pl[i] = 1.0
        if hu[i]:
            wu[i] = hi[i] - z[i]
            pu[i] = 1.0
    nb = m + int(np.sum(hl)) + int(np.sum(hu))
    norm_b = 1.0 + np.max(np.abs(b)) if m else 1.0
    norm_c = 1.0 + np.max(np.abs(c))
    band = np.empty((n, w))
    rp, rd, rl, ru = np.empty(m), np.empty(n), np.zeros(n), np.zeros(n)
    d_row, d_var = np.empty(m), np.empty(n)
    rcs, rcl, rcu = np.empty(m), np.zeros(n), np.zeros(n)
    dz, ds, dy = np.empty(n), np.empty(m), np.empty(m)
    dwl, dpl, dwu, dpu = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    az_, ds_a, dy_a = np.empty(m), np.empty(m), np.empty(m)
    dwl_a, dpl_a, dwu_a, dpu_a = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    tmp_m, tmp_n = np.empty(m), np.empty(n)
    ones_m = np.ones(m, dtype=np.bool_)
    for it in range(max_iter):
        _matvec(col0, val, z, az_)
        _rmatvec(col0, val, y, rd)
        gap = 0.0
        for r in range(m):
            rp[r] = az_[r] + s[r] - b[r]
            gap += s[r] * y[r]
        for i in range(n):
            rd[i] = (c[i] + rd[i] - pl[i] + pu[i]) if active[i] else 0.0
            if hl[i]:
                rl[i] = z[i] - wl[i] - lo[i]
                gap += wl[i] * pl[i]
            if hu[i]:
                ru[i] = z[i] + wu[i] - hi[i]
                gap += wu[i] * pu[i]
        mu = gap / max(nb, 1)
        obj = 0.0
        for i in range(n):
            obj += c[i] * z[i]
        res_p = max(np.max(np.abs(rp)) if m else 0.0, np.max(np.abs(rl)), np.max(np.abs(ru)))
        res_d = np.max(np.abs(rd))
        # the dual residual stalls near 1e-8 on ill-conditioned programs (the normal
        # equations' rounding) while the iterate is primal feasible and the gap closed: the
        # objective is then within about res_d |z| of the optimum
        if res_p <= tol * norm_b and res_d <= _DUAL_TOL * norm_c and gap <= tol * (1.0 + abs(obj)):
            return z, OPTIMAL, it
        if not (math.isfinite(gap) and math.isfinite(res_p) and math.isfinite(res_d)):
            return z, NUMERICAL, it
        for r in range(m):
            d_row[r] = y[r] / s[r]
        for i in range(n):
            d_var[i] = (pl[i] / wl[i] if hl[i] else 0.0) + (pu[i] / wu[i] if hu[i] else 0.0)
        _factor(col0, val, d_row, d_var, active, band)
        # predictor (affine scaling)
        for r in range(m):
            rcs[r] = -s[r] * y[r]
        for i in range(n):
            rcl[i] = -wl[i] * pl[i] if hl[i] else 0.0
            rcu[i] = -wu[i] * pu[i] if hu[i] else 0.0
        _directions(col0, val, rp, rd, rl, ru, s, y, wl, pl, wu, pu, hl, hu, active, band,
                    rcs, rcl, rcu, dz, ds_a, dy_a, dwl_a, dpl_a, dwu_a, dpu_a, tmp_m, tmp_n)
        ap = min(_max_step(s, ds_a, ones_m), _max_step(wl, dwl_a, hl), _max_step(wu, dwu_a, hu))
        ad = min(_max_step(y, dy_a, ones_m), _max_step(pl, dpl_a, hl), _max_step(pu, dpu_a, hu))
        gap_a = 0.0
        for r in range(m):
            gap_a += (s[r] + ap * ds_a[r]) * (y[r] + ad * dy_a[r])
        for i in range(n):
            if hl[i]:
                gap_a += (wl[i] + ap * dwl_a[i]) * (pl[i] + ad * dpl_a[i])
            if hu[i]:
                gap_a += (wu[i] + ap * dwu_a[i]) * (pu[i] + ad * dpu_a[i])
        sigma = min((gap_a / gap) ** 3, 1.0)
        target = sigma * mu
        # corrector
        for r in range(m):
            rcs[r] = -s[r] * y[r] - ds_a[r] * dy_a[r] + target
        for i in range(n):
            rcl[i] = (-wl[i] * pl[i] - dwl_a[i] * dpl_a[i] + target) if hl[i] else 0.0
            rcu[i] = (-wu[i] * pu[i] - dwu_a[i] * dpu_a[i] + target) if hu[i] else 0.0
        _directions(col0, val, rp, rd, rl, ru, s, y, wl, pl, wu, pu, hl, hu, active, band,
                    rcs, rcl, rcu, dz, ds, dy, dwl, dpl, dwu, dpu, tmp_m, tmp_n)
        ap = _ETA * min(_max_step(s, ds, ones_m), _max_step(wl, dwl, hl), _max_step(wu, dwu, hu))
        ad = _ETA * min(_max_step(y, dy, ones_m), _max_step(pl, dpl, hl), _max_step(pu, dpu, hu))
        ap, ad = min(ap, 1.0), min(ad, 1.0)
        for i in range(n):
            if active[i]:
                z[i] += ap * dz[i]
            if hl[i]:
                wl[i] += ap * dwl[i]
                pl[i] += ad * dpl[i]
            if hu[i]:
                wu[i] += ap * dwu[i]
                pu[i] += ad * dpu[i]
        for r in range(m):
            s[r] += ap * ds[r]
            y[r] += ad * dy[r]
    return z, ITERATION_LIMIT, max_iter


def banded_lp(c, col0, val, b, lo, hi, *, active=None, z0=None, tol: float = 1e-9,
              max_iter: int = 200) -> LPResult:
    """Solve ``min c.z`` subject to ``A z <= b`` and ``lo <= z <= hi``.

    Parameters
    ----------
    c : ndarray, shape (n,)
        Cost of each unknown.
    col0 : ndarray of int, shape (m,)
        First column of each row's band: row ``r`` is ``val[r] . z[col0[r]:col0[r] + W]``
        (``col0[r] + W <= n``).
    val : ndarray, shape (m, W)
        The row's coefficients on those columns.
    b : ndarray, shape (m,)
        Right-hand sides.
    lo, hi : ndarray, shape (n,)
        Bounds of the unknowns (``-inf``/``inf``: none; ``lo < hi`` where active).
    active : ndarray of bool, shape (n,), optional
        Unknowns solved for (default all); the others keep ``z0``'s value (their columns in
        ``val`` must be zero).
    z0 : ndarray, shape (n,), optional
        Starting point (moved inside the bounds; default 0).
    tol : float
        Relative primal and dual residual and duality gap at which it stops.
    max_iter : int
        Most interior point iterations.

    Returns
    -------
    LPResult
    """
    c = np.ascontiguousarray(c, dtype=np.float64)
    n = c.shape[0]
    col0 = np.ascontiguousarray(col0, dtype=np.int64)
    val = np.ascontiguousarray(val, dtype=np.float64)
    b = np.ascontiguousarray(b, dtype=np.float64)
    lo = np.ascontiguousarray(np.broadcast_to(lo, (n,)), dtype=np.float64)
    hi = np.ascontiguousarray(np.broadcast_to(hi, (n,)), dtype=np.float64)
    act = np.ones(n, bool) if active is None else np.ascontiguousarray(active, dtype=np.bool_)
    start = np.zeros(n) if z0 is None else np.array(z0, dtype=np.float64)
    if val.ndim != 2 or col0.shape != b.shape or val.shape[0] != b.shape[0]:
        raise ValueError("banded_lp: col0 (m,), val (m, W) and b (m,) must agree")
    if b.size and (col0.min() < 0 or col0.max() + val.shape[1] > n):
        raise ValueError("banded_lp: a row's band reaches beyond the unknowns")
    if np.any(act & ~(lo < hi)):
        raise ValueError("banded_lp: lo < hi is required for every active unknown")
    z, status, it = _interior_point(c, col0, val, b, lo, hi, act, start, float(tol),
                                    int(max_iter))
    return LPResult(z, _STATUS[status], int(it))
