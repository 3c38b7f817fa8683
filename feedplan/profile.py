"""The time-optimal jerk-limited speed profile along a curve.

Along a curve ``r(u)`` (:class:`feedplan.fit.Curve`), the motion ``u(t)`` from rest to rest is described on a grid of nodes ``u_k`` by
``x_k = udot^2`` and its slope ``g_k = dx/du``; on each cell ``x(u)`` is the cubic Hermite of
them. Then ``udot = sqrt(x)``, ``uddot = x' / 2``, ``udddot = sqrt(x) x'' / 2`` and per axis

- velocity ``r' sqrt(x)``, path speed ``|r'| sqrt(x)`` (at most the feed): bounds of ``x``;
- acceleration ``r'' x + r' x' / 2``: linear in the unknowns;
- jerk ``sqrt(x) (r''' x + 1.5 r'' x' + 0.5 r' x'')``: the bracket is linear, and the
  constraint ``|bracket| <= J / sqrt(x)`` is kept by replacing the convex ``J / sqrt(x)`` by
  its tangent at the previous iterate (below it: every iterate keeps the true constraint),
  taken at the faster end of the cell (a node slowed on purpose does not loosen its
  neighbours').

Each limit is imposed at both ends and the middle of every cell (the jerk's ``r'''`` on the
side of the cell: it steps at a spline's knots, which are nodes, as are the pieces' ends).
The first and last cells are pure-jerk cells from rest (``x ~ u^(4/3)``, a jerk-limited start
and stop), the tangential jerk bounding their speed. Maximising the speed where the time is
most sensitive to it (the time's gradient at the previous iterate) is then a linear program
whose rows touch the unknowns of one cell: :func:`feedplan.lp.banded_lp` solves it in time
linear in the grid's length. A few such programs (sequential linear programming) converge to
the profile, where tangential and centripetal jerk share each axis's limit sample by sample
(no fixed shares).

Joints (piece boundaries where the curvature jumps or the tangent kinks) are nodes, the
acceleration is imposed on both sides of a jump, and the jumps' steps are left to averages
of the samples that follow (:func:`spread_samples`, :func:`spread_cap`: the planner's), which
turn them into ramps of bounded jerk, with the speed at each joint capped to fit.

The motion is sampled exactly: each cell's duration is the integral of ``du / sqrt(x)``
(Gauss-Legendre; the rest cells in closed form) and each sample's ``u`` solves that integral
by Newton's method to rounding, so the sampled positions' finite differences are averages of
the continuous profile's derivatives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.lp import banded_lp

__all__ = ["Profile", "grid", "solve", "sample", "cell_times", "joints", "spread_cap", "GRID_M",
           "REST_M"]

#: Largest cell of the grid, metres.
GRID_M = 0.2e-3
#: First and last cell (pure jerk from rest), metres; cells double from there to GRID_M.
REST_M = 0.02e-3
#: Fewest cells per piece of the curve (a short corner blend is resolved).
PIECE_CELLS = 4
#: Share of the limits the profile is planned to (the sampled check then has room).
LIMIT_SHARE = 0.995
#: Share of the jerk limit: the position loop's command needs a reserve above the setpoints'
#: jerk where a profile holds it for long (a line keeps 0.9 of it, in ruckig). At 0.995 the
#: fixed gains Kp 3 / Kf 0.8 drove short_xz's command to 1.0004x the axis jerk at its start;
#: 0.95 keeps them (line-contouring-xz 20.621 s; at 0.9 20.844 s).
JERK_SHARE = 0.95
#: Most sequential linear programs, and the relative change of the time that ends them.
SLP_ROUNDS, SLP_TOL = 12, 3e-4
#: Interior point tolerance and iteration limit per linear program.
LP_TOL, LP_ITER = 1e-8, 120
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
_TINY = 1e-300
#: A scaled row whose bound exceeds this is dropped (:func:`solve`).
_FAR = 1e6
#: Geometry of a cell's end is taken this far inside it, m (:func:`_rows`).
_NUDGE_M = 1e-11
#: Rows whose slack at the previous profile exceeds this share of their size are left out of
#: the next program (:func:`solve`), and the most re-solves putting broken ones back.
_SCREEN, _SCREEN_ROUNDS = 0.5, 6
#: Rows are left out once a round changed the time by less than this; with a broken row, the
#: rows of this many cells on either side are put back.
_SCREEN_CHANGE, _SCREEN_REACH = 0.02, 8
#: Fractions of each cell, besides its ends, where the limits are imposed (the middle alone
#: before; the quarter points came with the jerk tangent's fix in :func:`_program`, their own
#: share of its effect not measured apart).
_INNER = (0.25, 0.5, 0.75)
#: Least share of its chord (the line between its end values) ``x`` keeps at those fractions.
_DIP_SHARE = 0.25
#: Least share of the iterate's x a program may go down to.
_TRUST = 0.5
#: Least jump of the curvature vector (1/m: a 1 km radius; below, the float noise of a corner
#: blend's curvature where it meets a line) and of the unit tangent that is a joint.
_JUMP_MIN_PER_M, _KINK_MIN = 1e-3, 1e-9
#: Share of each axis's jerk (and acceleration) a joint's step may take once averaged
#: (:func:`spread_cap`; the rest is the profile's own jerk around it), and of the tolerance
#: the average's rounding may take.
JOINT_SHARE, ROUND_SHARE = 0.5, 0.9


@dataclass(frozen=True, eq=False)
class Profile:
    """A speed profile along a curve.

    Attributes
    ----------
    u : ndarray, shape (n + 1,)
        Nodes, m (``u[0] = 0``, ``u[-1]`` the curve's length).
    x, g : ndarray, shape (n + 1,)
        ``udot^2`` (m^2/s^2) and ``dx/du`` (m/s^2) at the nodes (0 at both ends; ``g`` of the
        first and last node unused: those cells are pure jerk from rest).
    duration : float
        Time from rest to rest, s.
    status : str
        "optimal", or why the last linear program stopped ("iteration limit", ...).
    rounds : int
        Linear programs solved.
    """

    u: np.ndarray
    x: np.ndarray
    g: np.ndarray
    duration: float
    status: str
    rounds: int


def grid(curve, spacing_m: float = GRID_M, rest_m: float = REST_M) -> np.ndarray:
    """Nodes along ``curve`` (m): its pieces' ends and its splines' knots, at most
    ``spacing_m`` apart, at least :data:`PIECE_CELLS` cells per piece, halving towards both
    ends down to ``rest_m`` (at most a sixteenth of the curve, and within the first and last
    piece: a rest cell is pure tangential jerk, its constraint taken at its inner node only,
    so a piece inside it went unchecked: 18x the jerk limit sampled on a 1.2 mm block ending
    in a 4 um move, blended)."""
    L = curve.length
    u0 = curve.u0
    base = [u0]
    for p in np.flatnonzero(curve.kind == 2):
        t = np.unique(curve.splines[int(curve.org[p, 0])].t)
        length = u0[p + 1] - u0[p]
        base.append(u0[p] + t[(t > 0.0) & (t < length)])
    base = np.unique(np.concatenate(base))
    piece = np.clip(np.searchsorted(u0, base[:-1], side="right") - 1, 0, len(u0) - 2)
    h = np.minimum(spacing_m, (u0[piece + 1] - u0[piece]) / PIECE_CELLS)
    gaps = np.diff(base)
    cells = np.maximum(1, np.ceil(gaps / h - 1e-9)).astype(np.int64)
    nodes = [base]
    for c in np.unique(cells):
        sel = cells == c
        frac = np.arange(1, c) / c
        nodes.append((base[:-1][sel, None] + gaps[sel, None] * frac).ravel())
    rests = [min(rest_m, L / 16.0, piece) for piece in (u0[1] - u0[0], u0[-1] - u0[-2])]
    for rest, side in zip(rests, (1.0, -1.0)):
        steps, w = [0.0], rest
        while steps[-1] + w < min(spacing_m, L / 4.0):
            steps.append(steps[-1] + w)
            w *= 2.0
        nodes.append(0.5 * (1.0 - side) * L + side * np.array(steps[1:]))
    u = np.unique(np.clip(np.concatenate(nodes), 0.0, L))
    # no cell shorter than a thousandth of the rest cell (a knot next to a fill node):
    # drop the later node of such a pair unless it is a piece's end
    keep = np.ones(u.size, bool)
    short = np.flatnonzero(np.diff(u) < 1e-3 * min(rests)) + 1
    keep[short] = False
    keep[np.searchsorted(u, u0)] = True
    keep[0] = keep[-1] = True
    u = u[keep]
    # the first and last cells are the rest cells: nothing inside them
    first = np.searchsorted(u, rests[0] * (1 - 1e-9))
    last = np.searchsorted(u, L - rests[1] * (1 - 1e-9), side="right")
    return np.concatenate([[0.0], u[max(first, 1):min(last, u.size - 1)], [L]])


def joints(curve):
    """Piece boundaries of ``curve`` where the curvature vector ``d2r/du2`` jumps (u (J,) m,
    jump (J, 3) 1/m) and where the unit tangent turns (u (K,) m, its jump (K, 3))."""
    u_b = curve.u0[1:-1]
    right, left = curve.evaluate(u_b, order=2), curve.evaluate(u_b, left=True, order=2)
    d_kappa = right[2] - left[2]
    d_tan = right[1] / np.linalg.norm(right[1], axis=1)[:, None]
    d_tan -= left[1] / np.linalg.norm(left[1], axis=1)[:, None]
    jumps = np.linalg.norm(d_kappa, axis=1) > _JUMP_MIN_PER_M
    kinks = np.linalg.norm(d_tan, axis=1) > _KINK_MIN
    return u_b[jumps], d_kappa[jumps], u_b[kinks], d_tan[kinks]


def spread_cap(curve, u: np.ndarray, limits, spread: tuple[int, int], dt: float,
               tol_m: float) -> np.ndarray:
    """Upper bounds of ``x`` (m^2/s^2) at the nodes ``u`` of a profile whose samples (period
    ``dt``) are then averaged over ``m1`` and again over ``m2`` samples (``spread``,
    ``T1 = m1 dt >= T2 = m2 dt``), shape (n + 1,).

    The averages spread a curvature jump's acceleration step ``x |d kappa_i|`` into a ramp
    over ``T1``: a jerk ``x |d kappa_i| / T1``, kept within :data:`JOINT_SHARE` of each axis's
    ``J``; a kink's velocity step ``sqrt(x) |d tan_i|`` into a trapezoid of acceleration
    ``sqrt(x) |d tan_i| / T1`` (within that share of ``A``) whose ramps last ``T2`` (one
    sample if ``m2 = 1``): a jerk ``sqrt(x) |d tan_i| / (T1 T2)``; its corner cut, at most
    ``sqrt(x) (T1 + T2) |d tan| / 8``, within :data:`ROUND_SHARE` of the tolerance left by
    the curve's own deviation; and every node's rounding of the curve,
    ``x kappa (T1^2 + T2^2) / 24``, within that share too. ``m1 = 1``: no average (a joint:
    a stop)."""
    cap = np.full(u.size, np.inf)
    ax = limits.present
    J = JOINT_SHARE * LIMIT_SHARE * limits.jmax_m_s3[ax]
    A = JOINT_SHARE * LIMIT_SHARE * limits.amax_m_s2[ax]
    m1, m2 = spread
    t1 = m1 * dt if m1 > 1 else 0.0
    t2 = m2 * dt if m1 > 1 else 0.0
    piece = np.clip(np.searchsorted(curve.u0, u, side="right") - 1, 0, len(curve.dev) - 1)
    room = ROUND_SHARE * np.maximum(tol_m - curve.dev[piece], 0.0)
    u_jump, d_kappa, u_kink, d_tan = joints(curve)
    kappa = np.maximum(*(np.linalg.norm(curve.evaluate(u, left=s, order=2)[2], axis=1)
                         for s in (False, True)))
    if t1 > 0.0:
        with np.errstate(divide="ignore"):
            cap = np.minimum(cap, 24.0 * room / (kappa * (t1 * t1 + t2 * t2)))
    at = np.clip(np.searchsorted(u, u_jump), 0, u.size - 1)
    np.minimum.at(cap, at, _per_axis(J * t1, d_kappa[:, ax]))
    at = np.clip(np.searchsorted(u, u_kink), 0, u.size - 1)
    v = _per_axis(np.minimum(J * t1 * (t2 if m2 > 1 else dt), A * t1), d_tan[:, ax])
    if t1 > 0.0:
        v = np.minimum(v, 8.0 * room[at] / ((t1 + t2) * np.linalg.norm(d_tan, axis=1)))
    np.minimum.at(cap, at, v * v)
    return cap


def _per_axis(bound: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Least ``bound_i / |step_i|`` over the axes (inf on the axes that do not step), (J,)."""
    mag = np.abs(step)
    safe = np.where(mag > 0.0, mag, 1.0)
    return np.min(np.where(mag > 0.0, bound / safe, np.inf), axis=1, initial=np.inf)


def spread_samples(curve, limits, dt: float, tol_m: float) -> tuple[int, int]:
    """Samples ``(m1, m2)`` to average a profile's samples over (:func:`spread_cap`) along a
    curve with joints, ``(1, 1)`` without. ``T1``: where a curvature jump's cap from its step
    equals the rounding's cap (a jump ``d kappa`` between curvatures up to ``kappa``:
    ``T1^3 = 24 tol |d kappa_i| / (share J_i kappa)``), the median over the jumps. With kinks,
    ``T2`` where a kink's caps from its jerk and its corner cut meet,
    ``share J T1 T2 (T1 + T2) = 8 tol`` (``T1 = T2`` without jumps); else ``m2 = 1``."""
    u_jump, d_kappa, u_kink, _ = joints(curve)
    if u_jump.size + u_kink.size == 0:
        return 1, 1
    ax = limits.present
    J = JOINT_SHARE * LIMIT_SHARE * limits.jmax_m_s3[ax]
    room = ROUND_SHARE * max(tol_m - float(np.max(curve.dev)), 0.0)
    j_min = float(np.min(J))
    if u_jump.size:
        kappa = np.maximum(*(np.linalg.norm(curve.evaluate(u_jump, left=s, order=2)[2], axis=1)
                             for s in (False, True)))
        s_jump = 1.0 / _per_axis(J, d_kappa[:, ax])
        t1 = float(np.median(np.cbrt(24.0 * room * s_jump / np.maximum(kappa, 1e-300))))
    else:
        t1 = math.cbrt(4.0 * room / j_min)
    m1 = max(2, round(t1 / dt))
    if u_kink.size == 0:
        return m1, 1
    t1 = m1 * dt  # T2 (T1 + T2) = c: the positive root
    c = 8.0 * room / (j_min * t1)
    t2 = 0.5 * (math.sqrt(t1 * t1 + 4.0 * c) - t1)
    return m1, min(m1, max(1, round(t2 / dt)))


@dataclass(frozen=True, eq=False)
class _Rows:
    """The linear program's rows that do not depend on the iterate, and the jerk rows'
    bracket (its tangent term is added per round)."""

    col0: np.ndarray  # (m,)
    val: np.ndarray  # (m, 4)
    b: np.ndarray  # (m,)
    j_col0: np.ndarray  # (mj,) jerk rows: first column
    j_val: np.ndarray  # (mj, 4) the bracket, signed
    j_q: np.ndarray  # (mj,) column offset (0..3) of the x the tangent is taken at
    j_node: np.ndarray  # (mj,) ... and its node, or -1: the faster end of the cell
    j_cell: np.ndarray  # (mj,) the cell
    j_lim: np.ndarray  # (mj,) JERK_SHARE * J of the row's axis
    j_x: np.ndarray  # (mj, 4) x at the row's point (zero for the rest cells' rows)


def _hermite(H: np.ndarray, t: float):
    """Per cell (length H), at the fraction ``t`` of it: the coefficients of x, x', x'' on
    (x_k, g_k, x_k+1, g_k+1); shape (3 orders, cells, 4)."""
    one = np.ones_like(H)
    t2, t3 = t * t, t * t * t
    x = ((2 * t3 - 3 * t2 + 1) * one, (t3 - 2 * t2 + t) * H, (3 * t2 - 2 * t3) * one,
         (t3 - t2) * H)
    x1 = ((6 * t2 - 6 * t) / H, (3 * t2 - 4 * t + 1) * one, (6 * t - 6 * t2) / H,
          (3 * t2 - 2 * t) * one)
    x2 = ((12 * t - 6) / H**2, (6 * t - 4) / H, (6 - 12 * t) / H**2, (6 * t - 2) / H)
    return np.array([np.stack(o, axis=1) for o in (x, x1, x2)])


def _rows(curve, u: np.ndarray, ub: np.ndarray, ub_mid: np.ndarray, limits) -> _Rows:
    n = len(u) - 1
    # cells (index into ``cells`` below) ending at a curvature jump: the acceleration there
    # on the side of the cell too (the next cell's start has the other side's)
    u_jump = joints(curve)[0]
    ends_jump = np.searchsorted(u, u_jump) - 2
    ends_jump = ends_jump[(ends_jump >= 0) & (ends_jump < n - 3)]
    h = np.diff(u)
    ax = np.flatnonzero(limits.present)
    A = LIMIT_SHARE * limits.amax_m_s2
    J = JERK_SHARE * limits.jmax_m_s3
    cells = np.arange(1, n - 1)  # the Hermite cells
    H = h[cells]
    geo, coef = _cell_points(curve, u, cells, H)
    # which axes move in this block at all
    moving = [i for i in ax if any(np.any(g[d][:, i] != 0.0) for g in geo for d in (1, 2, 3))]
    col0, val, b = [], [], []
    j_col0, j_val, j_q, j_node, j_cell, j_lim, j_x = [], [], [], [], [], [], []
    c0 = 2 * cells
    last = len(geo) - 1
    for p, (_, r1, r2, r3) in enumerate(geo):
        cx, cx1, cx2 = coef[p]
        for i in moving:
            # the acceleration at the start and inside each cell (x is C1: a cell's end
            # is the next one's start), at the end of the last and of those ending at a jump
            at = slice(None) if p < last else np.r_[ends_jump, n - 3]
            acc = (r2[:, i, None] * cx + 0.5 * r1[:, i, None] * cx1)[at]
            for sg in (1.0, -1.0):
                col0.append(c0[at])
                val.append(sg * acc)
                b.append(np.full(acc.shape[0], A[i]))
            jerk = r3[:, i, None] * cx + 1.5 * r2[:, i, None] * cx1 + 0.5 * r1[:, i, None] * cx2
            for sg in (1.0, -1.0):
                j_col0.append(c0)
                j_val.append(sg * jerk)
                j_q.append(np.full(cells.size, -1))
                j_node.append(np.full(cells.size, -1))
                j_cell.append(cells)
                j_lim.append(np.full(cells.size, J[i]))
                j_x.append(cx)
    col0.append(c0)  # the path speed in the middle of each cell
    val.append(_hermite(H, 0.5)[0])
    b.append(ub_mid[cells])
    # inside each cell x stays above a share of its chord: the cubic may not dip to rest
    # between two moving nodes (the time's integral of du / sqrt(x) would blow up)
    for t, (cx, _, _) in zip(_INNER, coef[1:-1]):
        col0.append(c0)
        val.append(-cx + _DIP_SHARE * np.array([1.0 - t, 0.0, t, 0.0]))
        b.append(np.zeros(cells.size))
    # the rest cells: x = x_1 (u / h)^(4/3) from the start, mirrored at the end; their inner
    # node's g is 4 x / (3 h) (folded into x below), x'' = 4 x / (9 h^2) at the inner node
    for node, side, hh, sgn in ((1, True, h[0], 1.0), (n - 1, False, h[-1], -1.0)):
        inward = (1.0 if node == 1 else -1.0) * min(_NUDGE_M, 1e-4 * hh)
        _, r1, r2, r3 = curve.evaluate(np.array([u[node] - inward]), left=side)
        for i in moving:
            e_acc = r2[0, i] + sgn * (2.0 / 3.0) * r1[0, i] / hh
            e_jerk = r3[0, i] + sgn * 2.0 * r2[0, i] / hh + (2.0 / 9.0) * r1[0, i] / hh**2
            for sg in (1.0, -1.0):
                col0.append(np.array([2 * node]))
                val.append(np.array([[sg * e_acc, 0.0, 0.0, 0.0]]))
                b.append(np.array([A[i]]))
                j_col0.append(np.array([2 * node]))
                j_val.append(np.array([[sg * e_jerk, 0.0, 0.0, 0.0]]))
                j_q.append(np.array([0]))
                j_node.append(np.array([node]))
                j_cell.append(np.array([0 if node == 1 else n - 1]))
                j_lim.append(np.array([J[i]]))
                j_x.append(np.zeros((1, 4)))
    rows = _Rows(np.concatenate(col0), np.vstack(val), np.concatenate(b),
                 np.concatenate(j_col0), np.vstack(j_val), np.concatenate(j_q),
                 np.concatenate(j_node), np.concatenate(j_cell), np.concatenate(j_lim),
                 np.vstack(j_x))
    for col, vals in ((rows.col0, rows.val), (rows.j_col0, rows.j_val), (rows.j_col0, rows.j_x)):
        _fold_rest_slopes(col, vals, h)
    return rows


def _cell_points(curve, u: np.ndarray, cells: np.ndarray, H: np.ndarray):
    """The curve's derivatives (``curve.evaluate``'s tuple) and :func:`_hermite`'s coefficients
    at each cell's start, :data:`_INNER` fractions and end. Each end is taken inside its cell:
    a node at a spline's knot, u0 + t rounded, may fall a few ulps on the other side of it,
    where d3r/du3 is the neighbouring cell's."""
    nudge = np.minimum(_NUDGE_M, 1e-4 * H)
    start = curve.evaluate(u[cells] + nudge)
    end = curve.evaluate(u[cells + 1] - nudge, left=True)
    inner = [curve.evaluate(u[cells] + t * H) for t in _INNER]
    return (start, *inner, end), [_hermite(H, t) for t in (0.0, *_INNER, 1.0)]


def _fold_rest_slopes(col: np.ndarray, vals: np.ndarray, h: np.ndarray) -> None:
    """Fold g_1 = 4 x_1 / (3 h_0) and g_n-1 = -4 x_n-1 / (3 h_n-1) (the rest cells' slopes)
    into the x_1 and x_n-1 coefficients of rows (first column ``col``, coefficients ``vals``
    (m, 4), changed in place)."""
    n = h.size
    at = col == 2  # cells starting at node 1: g_1 in column offset 1
    vals[at, 0] += 4.0 / (3.0 * h[0]) * vals[at, 1]
    vals[at, 1] = 0.0
    at = col == 2 * (n - 2)  # cells ending at node n - 1: g_n-1 in column offset 3
    vals[at, 2] += -4.0 / (3.0 * h[-1]) * vals[at, 3]
    vals[at, 3] = 0.0


def _rest_ub(curve, u: np.ndarray, limits) -> tuple[float, float]:
    """Largest x at the inner node of each rest cell: pure jerk at the tangential limit."""
    out = []
    ax = limits.present
    J = JERK_SHARE * limits.jmax_m_s3[ax]
    for a, b_ in ((u[0], u[1]), (u[-2], u[-1])):
        d1 = curve.evaluate(np.linspace(a, b_, 9), order=2)[1][:, ax]
        with np.errstate(divide="ignore"):
            jt = float(np.min(J / np.maximum(np.max(np.abs(d1), axis=0), 1e-300)))
        out.append(jt ** (2.0 / 3.0) * (6.0 * (b_ - a)) ** (4.0 / 3.0) / 4.0)
    return out[0], out[1]


def _upper(curve, u: np.ndarray, feed: np.ndarray, limits) -> np.ndarray:
    """Largest x at each ``u`` from the axis velocities and the feed (both sides)."""
    ax = limits.present
    V = limits.vmax_m_s[ax]
    out = np.full(u.size, np.inf)
    for left in (False, True):
        d1 = curve.evaluate(u, left=left, order=2)[1]
        with np.errstate(divide="ignore"):
            out = np.minimum(out, np.min((V / np.abs(d1[:, ax])) ** 2, axis=1))
            out = np.minimum(out, (feed / np.linalg.norm(d1, axis=1)) ** 2)
    return out


@njit(cache=True)
def _hermite_x(x0, g0, x1, g1, H, s):
    t = s / H
    t2 = t * t
    t3 = t2 * t
    return ((2 * t3 - 3 * t2 + 1) * x0 + (t3 - 2 * t2 + t) * H * g0 + (3 * t2 - 2 * t3) * x1
            + (t3 - t2) * H * g1)


@njit(cache=True)
def _partial(x0, g0, x1, g1, H, s, gx, gw):
    """Integral of du / sqrt(x) over the first s of a Hermite cell (Gauss-Legendre)."""
    half = 0.5 * s
    acc = 0.0
    for q in range(gx.shape[0]):
        xq = _hermite_x(x0, g0, x1, g1, H, half * (gx[q] + 1.0))
        acc += gw[q] / math.sqrt(max(xq, _TINY))
    return acc * half


@njit(cache=True)
def _cell_times(u, x, g, gx, gw):
    n = u.shape[0] - 1
    tau = np.empty(n)
    for k in range(n):
        H = u[k + 1] - u[k]
        if k == 0:
            tau[k] = 3.0 * H / math.sqrt(max(x[1], _TINY))
        elif k == n - 1:
            tau[k] = 3.0 * H / math.sqrt(max(x[n - 1], _TINY))
        else:
            tau[k] = _partial(x[k], g[k], x[k + 1], g[k + 1], H, H, gx, gw)
    return tau


def cell_times(u: np.ndarray, x: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Duration of each cell of a profile, s, shape (n,)."""
    return _cell_times(u, x, g, _GL_X, _GL_W)


@njit(cache=True)
def _sample(u, x, g, tau, dt, count, gx, gw):
    n = u.shape[0] - 1
    tk = np.zeros(n + 1)
    for k in range(n):
        tk[k + 1] = tk[k] + tau[k]
    total = tk[n]
    out = np.empty(count)
    c = 0
    s = 0.0
    for k in range(count):
        t = k * dt
        if t >= total:
            out[k] = u[n]
            continue
        while c < n - 1 and t >= tk[c + 1]:
            c += 1
            s = 0.0
        H = u[c + 1] - u[c]
        if c == 0:
            out[k] = u[0] + t**3 * max(x[1], 0.0) ** 1.5 / (27.0 * H * H)
            continue
        if c == n - 1:
            r = total - t
            out[k] = u[n] - r**3 * max(x[n - 1], 0.0) ** 1.5 / (27.0 * H * H)
            continue
        target = t - tk[c]
        lo, hi = 0.0, H
        x0, g0, x1, g1 = x[c], g[c], x[c + 1], g[c + 1]
        s = min(max(s + dt * math.sqrt(max(_hermite_x(x0, g0, x1, g1, H, s), 0.0)), 0.0), H)
        for _ in range(60):
            f = _partial(x0, g0, x1, g1, H, s, gx, gw) - target
            if f > 0.0:
                hi = s
            else:
                lo = s
            step = f * math.sqrt(max(_hermite_x(x0, g0, x1, g1, H, s), _TINY))
            new = s - step
            if not (lo < new < hi):
                new = 0.5 * (lo + hi)
            if abs(new - s) <= 1e-16 * (abs(u[c]) + H):
                s = new
                break
            s = new
        out[k] = min(u[c] + s, u[c + 1])
    return out


def sample(prof: Profile, dt: float, extra: int = 3) -> np.ndarray:
    """The curve parameter every ``dt`` (m), from rest to rest, and ``extra`` samples at the
    end after the motion ends; shape (ceil(duration / dt) + extra,)."""
    tau = cell_times(prof.u, prof.x, prof.g)
    count = math.ceil(float(np.sum(tau)) / dt - 1e-9) + extra
    return _sample(prof.u, prof.x, prof.g, tau, dt, count, _GL_X, _GL_W)


def _weights(u: np.ndarray, x: np.ndarray) -> np.ndarray:
    """-d(time)/dx at each node (the rest cells' exactly, the others by the trapezoid rule),
    the rest cells' inner nodes capped at the largest other weight (they start nearly at rest
    and would take the whole objective). The slow nodes inside the curve are what the time
    hinges on and are not capped (capped at the 95th percentile, a node nearly stopped in a
    fitted spline's tight bend was never raised: line-contouring-xz's block of line 1304,
    1.197 s against 1.131 uncapped)."""
    n = len(u) - 1
    h = np.diff(u)
    v = np.sqrt(np.maximum(x, 1e-12))
    w = np.zeros(n + 1)
    cell = h[1:-1] / (v[1:-2] + v[2:-1]) ** 2
    w[1:-2] += cell / v[1:-2]
    w[2:-1] += cell / v[2:-1]
    w[1] += 1.5 * h[0] / v[1] ** 3
    w[n - 1] += 1.5 * h[-1] / v[n - 1] ** 3
    w[1:n] = np.minimum(w[1:n], np.max(w[2:n - 1], initial=0.0))
    w[0] = w[n] = 0.0
    return w


def _initial(curve, u: np.ndarray, ub: np.ndarray, limits) -> np.ndarray:
    """A slow start: the constant-speed acceleration and jerk ceilings, then speed changes at a
    tenth of the least acceleration limit."""
    ax = limits.present
    _, _, d2, d3 = curve.evaluate(u)
    with np.errstate(divide="ignore"):
        x = np.minimum(ub, np.min(0.5 * limits.amax_m_s2[ax] / np.abs(d2[:, ax]), axis=1))
        x = np.minimum(x, np.min((0.5 * limits.jmax_m_s3[ax] / np.abs(d3[:, ax])) ** (2 / 3),
                                 axis=1))
    acc = 0.1 * float(np.min(limits.amax_m_s2[ax]))
    du = np.diff(u)
    x[0] = x[-1] = 0.0
    for k in range(1, len(u)):
        x[k] = min(x[k], x[k - 1] + 2 * acc * du[k - 1])
    for k in range(len(u) - 2, -1, -1):
        x[k] = min(x[k], x[k + 1] + 2 * acc * du[k])
    return x


def _program(rows: _Rows, x: np.ndarray, g: np.ndarray, xs: float, scale: np.ndarray):
    """The linear program's rows at the iterate ``x, g``: the jerk rows' tangent at the faster
    end of each cell (the inner node of a rest cell), or at the row's own point where the
    iterate is faster there than at both ends (inside a cell where the speed peaks: the end's
    tangent would let the jerk through, measured 1 % above the limit on a 1.2 mm block), every
    row in the unknowns scaled by ``scale`` and divided by its largest coefficient; rows that
    cannot bind dropped."""
    xq_hat = np.maximum(x, 1e-6 * xs)
    cell = rows.j_cell
    faster = np.where(xq_hat[cell] >= xq_hat[np.minimum(cell + 1, x.size - 1)], 0, 2)
    q = np.where(rows.j_node >= 0, 0, faster)
    node = np.where(rows.j_node >= 0, rows.j_node, cell + q // 2)
    xh = xq_hat[node]
    z = np.empty(2 * x.size)
    z[0::2], z[1::2] = x, g
    at = np.minimum(2 * cell[:, None] + np.arange(4), z.size - 1)
    x_row = np.einsum("rw,rw->r", rows.j_x, z[at])
    inner = x_row > xh
    jv = rows.j_val.copy()
    jv[np.arange(len(q)), q] += np.where(inner, 0.0, 0.5 * rows.j_lim / xh**1.5)
    x_in = np.where(inner, x_row, 1.0)
    jv += np.where(inner, 0.5 * rows.j_lim / x_in**1.5, 0.0)[:, None] * rows.j_x
    jb = 1.5 * rows.j_lim / np.sqrt(np.where(inner, x_in, xh))
    keep = np.any(rows.j_val != 0.0, axis=1)  # an axis idle there: no jerk of its own
    col0 = np.concatenate([rows.col0, rows.j_col0[keep]])
    val = np.vstack([rows.val, jv[keep]])
    b = np.concatenate([rows.b, jb[keep]])
    val = val * scale[col0[:, None] + np.arange(4)]
    norm = np.max(np.abs(val), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        b = b / norm
    # a row whose bound is far beyond what its unknowns (of order 1 once scaled) reach
    # cannot bind (a nearly idle axis's rounding noise): kept, it would ruin the numerics
    ok = (norm > 0.0) & (b < _FAR)
    return col0[ok], val[ok] / norm[ok, None], b[ok]


def solve(curve, feed: np.ndarray, limits, *, u: np.ndarray | None = None,
          cap: np.ndarray | None = None, start: Profile | None = None,
          rounds: int = SLP_ROUNDS) -> Profile:
    """The jerk-limited time-optimal profile along ``curve`` from rest to rest.

    Parameters
    ----------
    curve : feedplan.fit.Curve
        Its joints' steps are not bounded here: see :func:`spread_cap`.
    feed : callable
        ``feed(u)``: the path speed allowed at each parameter (m/s), array in, array out.
    limits : AxisLimits
        Per-axis limits (the profile keeps :data:`LIMIT_SHARE` of them, :data:`JERK_SHARE` of
        the jerk).
    u : ndarray, optional
        The grid (default :func:`grid`).
    cap : ndarray, shape (n + 1,), optional
        Further upper bounds of ``x`` at the nodes (a slow-down).
    start : Profile, optional
        A profile on the same grid to start from.
    rounds : int
        Most linear programs.

    Returns
    -------
    Profile
    """
    u = grid(curve) if u is None else u
    n = len(u) - 1
    ub, ub_mid = _speed_bounds(curve, u, feed, limits, cap)
    rows = _rows(curve, u, ub, ub_mid, limits)
    active, lo, hi, hn = _unknowns(u, ub)
    N = 2 * (n + 1)
    if start is not None:
        x = np.minimum(start.x, ub)
        g = start.g.copy()
    else:
        x = _initial(curve, u, ub, limits)
        g = np.zeros(n + 1)
    x[0] = x[n] = 0.0
    # x, g: the iterate; feasible: it is a solution of an earlier program (then each program
    # contains it, its rows' tangents being taken there)
    feasible = False
    t_cur = math.inf
    status, done = "optimal", 0
    change = math.inf
    for rnd in range(rounds):
        xs = max(float(np.max(x)), float(np.max(ub[np.isfinite(ub)], initial=0.0)), 1e-12)
        scale = np.empty(N)
        scale[0::2] = xs
        scale[1::2] = xs / hn
        col0, val, b = _program(rows, x, g, xs, scale)
        z0 = np.zeros(N)
        z0[0::2], z0[1::2] = x / xs, g / scale[1::2]
        w = np.zeros(N)
        w[0::2] = _weights(u, x)
        c = -w * scale
        c /= max(float(np.max(np.abs(c))), 1e-300)
        lo_s = lo / scale
        if feasible:  # the linearised time is trusted down to half the speed squared
            lo_s[0::2] = np.minimum(_TRUST * x, 0.5 * ub) / xs
        res, broken = _screened_lp(c, (col0, val, b), lo_s, hi / scale, active, z0,
                                   feasible and change < _SCREEN_CHANGE)
        done = rnd + 1
        if not res.ok or broken:
            status = res.status if not res.ok else "rows left out broken"
            break
        step = _step(u, x, g, res.z * scale, ub, t_cur if feasible else None)
        if step is None:
            break
        x_new, g_new, t_new = step
        change = abs(t_cur - t_new) / t_new
        x, g, t_cur, feasible = x_new, g_new, t_new, True
        if change <= SLP_TOL:
            break
    if not feasible:
        zero = np.zeros(n + 1)
        return Profile(u, zero, zero.copy(), math.inf, status, done)
    return Profile(u, x, g, t_cur, status, done)


def _speed_bounds(curve, u: np.ndarray, feed, limits, cap) -> tuple[np.ndarray, np.ndarray]:
    """Upper bounds of ``x`` at the nodes (0 at both ends) and at the cells' middles: the
    feed, the axes' velocity, the rest cells' jerk-limited speed and ``cap``."""
    n = len(u) - 1
    ub = _upper(curve, u, feed(u), limits)
    um = 0.5 * (u[:-1] + u[1:])
    ub_mid = _upper(curve, um, feed(um), limits)
    r0, r1 = _rest_ub(curve, u, limits)
    ub[1], ub[n - 1] = min(ub[1], r0), min(ub[n - 1], r1)
    if cap is not None:  # a cell's middle: the mean of its ends' caps (their least forced a
        # cap set at a rising profile down to each cell's slower end: line-contouring-xz's block
        # at line 379 1.681 -> 1.984 s in one slow-down round)
        ub = np.minimum(ub, cap)
        ub_mid = np.minimum(ub_mid, 0.5 * (cap[:-1] + cap[1:]))
    ub[0] = ub[n] = 0.0
    return ub, ub_mid


def _unknowns(u: np.ndarray, ub: np.ndarray):
    """The linear programs' unknowns ``(x_0, g_0, x_1, g_1, ...)``: which are solved for (not
    the ends' and the rest cells' fixed ones), their bounds, and each node's shorter cell."""
    n = len(u) - 1
    h = np.diff(u)
    N = 2 * (n + 1)
    active = np.ones(N, bool)
    active[[0, 1, 3, 2 * n - 1, 2 * n, 2 * n + 1]] = False
    lo = np.full(N, -np.inf)
    hi = np.full(N, np.inf)
    lo[0::2], hi[0::2] = 0.0, np.maximum(ub, 1e-300)
    hn = np.minimum(np.r_[h[0], h], np.r_[h, h[-1]])
    return active, lo, hi, hn


def _screened_lp(c, program, lo, hi, active, z0, screen: bool):
    """Solve one scaled program ``(col0, val, b)``; with ``screen``, first without the rows far
    from binding at ``z0``, putting back those the solution breaks (and their neighbours').
    Returns the :class:`feedplan.lp.LPResult` and whether rows left out stay broken."""
    col0, val, b = program
    N = c.size
    at = col0[:, None] + np.arange(4)
    sel = np.ones(b.size, bool)
    if screen:
        az = np.einsum("rw,rw->r", val, z0[at])
        sel = b - az <= _SCREEN * (np.abs(b) + np.abs(az))
    for _ in range(_SCREEN_ROUNDS):
        res = banded_lp(c, col0[sel], val[sel], b[sel], lo, hi,
                        active=active, z0=z0, tol=LP_TOL, max_iter=LP_ITER)
        if not res.ok:
            return res, False
        over = (np.einsum("rw,rw->r", val, res.z[at]) - b > LP_TOL * (1.0 + np.abs(b)))
        if not over.any():
            return res, False
        near = np.zeros(N + 1, np.int64)
        np.add.at(near, np.clip(col0[over] - 2 * _SCREEN_REACH, 0, N), 1)
        np.add.at(near, np.clip(col0[over] + 2 * _SCREEN_REACH + 1, 0, N), -1)
        sel |= over | (np.cumsum(near)[col0] > 0)
    return res, True


def _step(u, x, g, z, ub, t_cur):
    """The next iterate ``(x, g, time)`` from a program's solution ``z`` (unscaled), or None
    when neither it nor a point on the segment to it beats the time ``t_cur`` of the
    iterate ``x, g`` (None: no iterate yet, any solution is taken)."""
    n = len(u) - 1
    h0, h1 = u[1] - u[0], u[n] - u[n - 1]
    x_new = np.clip(z[0::2], 0.0, ub)
    g_new = z[1::2]
    g_new[1] = 4.0 * x_new[1] / (3.0 * h0)
    g_new[n - 1] = -4.0 * x_new[n - 1] / (3.0 * h1)
    g_new[0] = g_new[n] = 0.0
    t_new = float(np.sum(cell_times(u, x_new, g_new)))
    if t_cur is None or t_new < t_cur:
        return x_new, g_new, t_new
    # the linearised time misled: the best point of the segment (in the program's
    # feasible set, as both ends are), or the iterate itself
    for a in (0.5, 0.25, 0.125):
        xa, ga = x + a * (x_new - x), g + a * (g_new - g)
        ta = float(np.sum(cell_times(u, xa, ga)))
        if ta < t_cur:
            return xa, ga, ta
    return None
