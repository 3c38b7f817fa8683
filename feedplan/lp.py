"""Linear programs whose constraint rows each touch a few consecutive unknowns.

``min c.z  subject to  A z <= b,  lo <= z <= hi``, where every row of ``A`` has its non-zeros
among ``W`` consecutive columns (``W = val.shape[1]``; the speed profile's rows touch the two
unknowns of each end of one grid cell: ``W = 4``). Then ``A^T D A`` is a band matrix of
half-bandwidth ``W - 1`` and one Newton step of an interior point method costs ``O(n W^2)``:
the solve is linear in the number of unknowns.

Why not a library: the project uses a well-kept solver where one serves. HiGHS
(:func:`scipy.optimize.linprog`, sparse, scipy 1.17) was measured on the very programs the
planner builds (``bench/bench_lp.py``: every LP of 200 grid nodes or more planning
freeform_xz, micro_2k, line-contouring-xz, plasmatest, 51MeanderAve and a 9 000-segment
micro program; CPU time of the solves, shared host): its dual simplex took 4.9-9.1x this
solver's time per program (line-contouring-xz's 52 LPs of 280-398 nodes 8.8 s against 1.0 s,
plasmatest's 57 of 253-499 nodes 5.9 s against 1.0 s, the 3 000-node block's 3 LPs 3.2 s
against 0.52 s), its interior point 11-19x: line-contouring-xz's planning (4.6 s CPU) would
about triple. Both agree with this solver: the objectives within 6e-6 relative (4.5e-4 on one
line-contouring-xz LP that stopped at the iteration limit here), HiGHS's solutions breaking
rows by up to 1e-7 (its feasibility tolerance). OSQP (first-order, about 1e-4 accuracy)
was not tried.

Method: Mehrotra's predictor-corrector primal-dual interior point method (infeasible start,
separate primal and dual step lengths), the Newton steps by a banded Cholesky factorisation
of the normal equations (tiny pivots, of dependent or inactive columns, are skipped as in
LIPSOL). Unknowns marked inactive keep their starting value (their columns must be zero).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

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


class _Band(NamedTuple):
    """The constraint matrix ``A``: row ``r`` is ``val[r] . z[col0[r]:col0[r] + W]``."""

    col0: np.ndarray
    val: np.ndarray


class _Masks(NamedTuple):
    """Which unknowns have a lower bound (``hl``), an upper bound (``hu``), are solved for."""

    hl: np.ndarray
    hu: np.ndarray
    active: np.ndarray
    rows: np.ndarray  # all True, one per row


class _Point(NamedTuple):
    """An iterate: unknowns ``z``, row slacks ``s`` and duals ``y``, bound slacks ``wl``,
    ``wu`` and their duals ``pl``, ``pu`` (a direction has the same layout)."""

    z: np.ndarray
    s: np.ndarray
    y: np.ndarray
    wl: np.ndarray
    pl: np.ndarray
    wu: np.ndarray
    pu: np.ndarray


class _Residuals(NamedTuple):
    """Primal rows ``rp``, dual ``rd``, lower ``rl`` and upper bound ``ru`` residuals."""

    rp: np.ndarray
    rd: np.ndarray
    rl: np.ndarray
    ru: np.ndarray


class _Targets(NamedTuple):
    """Complementarity targets of the rows (``rcs``) and of the bounds (``rcl``, ``rcu``)."""

    rcs: np.ndarray
    rcl: np.ndarray
    rcu: np.ndarray


@njit(cache=True)
def _point(m, n):
    """An uninitialised :class:`_Point` (or direction)."""
    return _Point(np.empty(n), np.empty(m), np.empty(m), np.empty(n), np.empty(n),
                  np.empty(n), np.empty(n))


@njit(cache=True)
def _directions(A, res, p, masks, band, t, d, tmp_m, tmp_n):
    """The Newton direction ``d`` at ``p`` for the complementarity targets ``t`` (module
    docstring); ``band`` is :func:`_factor`'s, ``tmp_m``, ``tmp_n`` scratch of m and n."""
    m, n = p.s.shape[0], d.z.shape[0]
    hl, hu = masks.hl, masks.hu
    for r in range(m):
        tmp_m[r] = (t.rcs[r] + p.y[r] * res.rp[r]) / p.s[r]
    _rmatvec(A.col0, A.val, tmp_m, tmp_n)
    for i in range(n):
        v = -res.rd[i] - tmp_n[i]
        if hl[i]:
            v += (t.rcl[i] - p.pl[i] * res.rl[i]) / p.wl[i]
        if hu[i]:
            v -= (t.rcu[i] + p.pu[i] * res.ru[i]) / p.wu[i]
        tmp_n[i] = v if masks.active[i] else 0.0
    _solve(band, tmp_n, d.z)
    _matvec(A.col0, A.val, d.z, d.s)
    for r in range(m):
        d.s[r] = -res.rp[r] - d.s[r]
        d.y[r] = (t.rcs[r] - p.y[r] * d.s[r]) / p.s[r]
    for i in range(n):
        if hl[i]:
            d.wl[i] = d.z[i] + res.rl[i]
            d.pl[i] = (t.rcl[i] - p.pl[i] * d.wl[i]) / p.wl[i]
        else:
            d.wl[i] = d.pl[i] = 0.0
        if hu[i]:
            d.wu[i] = -d.z[i] - res.ru[i]
            d.pu[i] = (t.rcu[i] - p.pu[i] * d.wu[i]) / p.wu[i]
        else:
            d.wu[i] = d.pu[i] = 0.0


@njit(cache=True)
def _start(A, b, lo, hi, masks, z0):
    """The starting point: ``z0`` moved strictly inside the box, slacks at least 1, duals 1."""
    m, n = b.shape[0], z0.shape[0]
    hl, hu = masks.hl, masks.hu
    z = z0.copy()
    for i in range(n):
        if hl[i] and hu[i]:
            gap = hi[i] - lo[i]
            z[i] = min(max(z[i], lo[i] + 0.01 * gap), hi[i] - 0.01 * gap)
        elif hl[i]:
            z[i] = max(z[i], lo[i] + 1.0)
        elif hu[i]:
            z[i] = min(z[i], hi[i] - 1.0)
    az = np.empty(m)
    _matvec(A.col0, A.val, z, az)
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
    return _Point(z, s, y, wl, pl, wu, pu)


@njit(cache=True)
def _residuals(c, A, b, lo, hi, masks, p, res):
    """Fill ``res`` at ``p``; return the duality gap."""
    m, n = b.shape[0], c.shape[0]
    hl, hu = masks.hl, masks.hu
    az = np.empty(m)
    _matvec(A.col0, A.val, p.z, az)
    _rmatvec(A.col0, A.val, p.y, res.rd)
    gap = 0.0
    for r in range(m):
        res.rp[r] = az[r] + p.s[r] - b[r]
        gap += p.s[r] * p.y[r]
    for i in range(n):
        res.rd[i] = (c[i] + res.rd[i] - p.pl[i] + p.pu[i]) if masks.active[i] else 0.0
        if hl[i]:
            res.rl[i] = p.z[i] - p.wl[i] - lo[i]
            gap += p.wl[i] * p.pl[i]
        if hu[i]:
            res.ru[i] = p.z[i] + p.wu[i] - hi[i]
            gap += p.wu[i] * p.pu[i]
    return gap


@njit(cache=True)
def _status(c, b, p, res, gap, tol):
    """OPTIMAL or NUMERICAL when the iteration ends at ``p``, else -1."""
    m = b.shape[0]
    norm_b = 1.0 + np.max(np.abs(b)) if m else 1.0
    norm_c = 1.0 + np.max(np.abs(c))
    obj = 0.0
    for i in range(c.shape[0]):
        obj += c[i] * p.z[i]
    res_p = max(np.max(np.abs(res.rp)) if m else 0.0, np.max(np.abs(res.rl)),
                np.max(np.abs(res.ru)))
    res_d = np.max(np.abs(res.rd))
    # the dual residual stalls near 1e-8 on ill-conditioned programs (the normal
    # equations' rounding) while the iterate is primal feasible and the gap closed: the
    # objective is then within about res_d |z| of the optimum
    if res_p <= tol * norm_b and res_d <= _DUAL_TOL * norm_c and gap <= tol * (1.0 + abs(obj)):
        return OPTIMAL
    if not (math.isfinite(gap) and math.isfinite(res_p) and math.isfinite(res_d)):
        return NUMERICAL
    return -1


@njit(cache=True)
def _normal_matrix(A, masks, p, d_row, d_var, band):
    """Factor the Newton steps' normal matrix at ``p`` into ``band`` (:func:`_factor`)."""
    hl, hu = masks.hl, masks.hu
    for r in range(d_row.shape[0]):
        d_row[r] = p.y[r] / p.s[r]
    for i in range(d_var.shape[0]):
        d_var[i] = (p.pl[i] / p.wl[i] if hl[i] else 0.0) + (p.pu[i] / p.wu[i] if hu[i] else 0.0)
    _factor(A.col0, A.val, d_row, d_var, masks.active, band)


@njit(cache=True)
def _step_lengths(p, d, masks):
    """The largest primal and dual steps along ``d`` that keep ``p``'s slacks and duals >= 0."""
    ap = min(_max_step(p.s, d.s, masks.rows), _max_step(p.wl, d.wl, masks.hl),
             _max_step(p.wu, d.wu, masks.hu))
    ad = min(_max_step(p.y, d.y, masks.rows), _max_step(p.pl, d.pl, masks.hl),
             _max_step(p.pu, d.pu, masks.hu))
    return ap, ad


@njit(cache=True)
def _predictor(p, masks, t):
    """The affine scaling targets: complementarity 0."""
    hl, hu = masks.hl, masks.hu
    for r in range(p.s.shape[0]):
        t.rcs[r] = -p.s[r] * p.y[r]
    for i in range(p.z.shape[0]):
        t.rcl[i] = -p.wl[i] * p.pl[i] if hl[i] else 0.0
        t.rcu[i] = -p.wu[i] * p.pu[i] if hu[i] else 0.0


@njit(cache=True)
def _corrector(p, da, masks, gap, nb, t):
    """Mehrotra's targets from the affine direction ``da``: centring ``sigma mu`` with
    ``sigma`` the cube of the gap ratio the affine step reaches, and the second-order term."""
    hl, hu = masks.hl, masks.hu
    ap, ad = _step_lengths(p, da, masks)
    gap_a = 0.0
    for r in range(p.s.shape[0]):
        gap_a += (p.s[r] + ap * da.s[r]) * (p.y[r] + ad * da.y[r])
    for i in range(p.z.shape[0]):
        if hl[i]:
            gap_a += (p.wl[i] + ap * da.wl[i]) * (p.pl[i] + ad * da.pl[i])
        if hu[i]:
            gap_a += (p.wu[i] + ap * da.wu[i]) * (p.pu[i] + ad * da.pu[i])
    sigma = min((gap_a / gap) ** 3, 1.0)
    target = sigma * (gap / max(nb, 1))
    for r in range(p.s.shape[0]):
        t.rcs[r] = -p.s[r] * p.y[r] - da.s[r] * da.y[r] + target
    for i in range(p.z.shape[0]):
        t.rcl[i] = (-p.wl[i] * p.pl[i] - da.wl[i] * da.pl[i] + target) if hl[i] else 0.0
        t.rcu[i] = (-p.wu[i] * p.pu[i] - da.wu[i] * da.pu[i] + target) if hu[i] else 0.0


@njit(cache=True)
def _move(p, d, masks):
    """Step from ``p`` along ``d``, :data:`_ETA` of the way to the boundary (at most 1)."""
    ap, ad = _step_lengths(p, d, masks)
    ap, ad = min(_ETA * ap, 1.0), min(_ETA * ad, 1.0)
    hl, hu = masks.hl, masks.hu
    for i in range(p.z.shape[0]):
        if masks.active[i]:
            p.z[i] += ap * d.z[i]
        if hl[i]:
            p.wl[i] += ap * d.wl[i]
            p.pl[i] += ad * d.pl[i]
        if hu[i]:
            p.wu[i] += ap * d.wu[i]
            p.pu[i] += ad * d.pu[i]
    for r in range(p.s.shape[0]):
        p.s[r] += ap * d.s[r]
        p.y[r] += ad * d.y[r]


@njit(cache=True)
def _interior_point(c, A, b, lo, hi, masks, z0, tol, max_iter):
    """Mehrotra's predictor-corrector iteration (module docstring): (z, status, iterations)."""
    m, n, w = b.shape[0], c.shape[0], A.val.shape[1]
    p = _start(A, b, lo, hi, masks, z0)
    nb = m + int(np.sum(masks.hl)) + int(np.sum(masks.hu))
    band = np.empty((n, w))
    res = _Residuals(np.empty(m), np.empty(n), np.zeros(n), np.zeros(n))
    t = _Targets(np.empty(m), np.zeros(n), np.zeros(n))
    d_row, d_var, tmp_m, tmp_n = np.empty(m), np.empty(n), np.empty(m), np.empty(n)
    da, d = _point(m, n), _point(m, n)
    for it in range(max_iter):
        gap = _residuals(c, A, b, lo, hi, masks, p, res)
        status = _status(c, b, p, res, gap, tol)
        if status >= 0:
            return p.z, status, it
        _normal_matrix(A, masks, p, d_row, d_var, band)
        _predictor(p, masks, t)
        _directions(A, res, p, masks, band, t, da, tmp_m, tmp_n)
        _corrector(p, da, masks, gap, nb, t)
        _directions(A, res, p, masks, band, t, d, tmp_m, tmp_n)
        _move(p, d, masks)
    return p.z, ITERATION_LIMIT, max_iter


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
    masks = _Masks(act & (lo > -np.inf), act & (hi < np.inf), act,
                   np.ones(b.shape[0], dtype=np.bool_))
    z, status, it = _interior_point(c, _Band(col0, val), b, lo, hi, masks, start, float(tol),
                                    int(max_iter))
    return LPResult(z, _STATUS[status], int(it))
