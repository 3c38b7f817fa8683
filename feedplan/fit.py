"""Smooth curves between exact stops: the geometry the feed planner moves along.

A :class:`~feedplan.path.Path` is cut into :class:`Block` s, each planned from
rest to rest:

* every rapid (G0) line is a block of its own (rapid/feed transitions are exact stops:
  a rapid is planned time-optimally on its own, and the approach to the part is not cut);
* feed moves are chained through their corners: a kink of more than
  :data:`BLEND_MIN_TURN_RAD` is replaced by a curvature-continuous blend within the
  tolerance (:mod:`feedplan.blend`, G64), unless the move ending there was programmed
  under G61 (every kink an exact stop), the turn exceeds :data:`BLEND_MAX_TURN_RAD`, no
  blend keeps within the tolerance, or the blend would be passed slower than
  :data:`~oga.defaults.BLEND_MIN_SPEED_SHARE` of the speed a stop costs (then it is no
  faster than the stop); without blending (no :class:`Blending`), corners up to
  :data:`CORNER_ANGLE_RAD` are passed as kinks and sharper ones are exact stops;
* runs of at least :data:`MICRO_RUN_MIN` consecutive short G1 lines (each shorter than
  :data:`MICRO_SEGMENT_M`), as CAM posts write freeform surfaces, are replaced by a
  cubic B-spline (curvature-continuous): first a smoothing fit (least squares plus a
  penalty on the squared third derivative, :func:`_smooth_fit`: the curvature the jerk
  limit sees stays smooth where the CAM's chords ripple), else a least-squares fit.
  Every fit is measured both ways against the programmed polyline (each spline point to
  the polyline, each programmed vertex to the spline); where the smoothing fit deviates
  by more than ``fit_tol_m`` it is pulled there (data weights up, penalty down), where the
  least-squares one does knots are added there, and a stretch that still fails with a
  knot at every vertex is split at its sharpest vertex (blended as a corner is, or an
  exact stop). The fit is local (knots start :data:`FIT_KNOT_SPACING_M` apart and are
  refined only where the deviation requires), so a sharp feature never produces the
  overshoot of a global interpolating spline;
* under blending, runs of at least :data:`MICRO_RUN_MIN` consecutive G1 lines each shorter
  than :data:`CHORD_SEGMENT_M` and turning at most :data:`CORNER_ANGLE_RAD` from one to
  the next (a CAM's chords of a curve, longer than micro-segments) are fitted the same
  way (their corners are not blended one by one), and so are micro-segments turning more
  where their vertex lies within ``fit_tol_m`` of the chord of its neighbours (a jitter
  of the CAM's rounding: micrometre moves turning tens of degrees). A chain of blends
  within a few micrometres of millimetre chords concentrates each chord's turn in a short
  blend, whose curvature rate lets the jerk limit pass it at a fraction of the speed the
  curve the chords follow allows.

A run to be fitted whose vertices all lie within :data:`COLLINEAR_TOL_SHARE` of
``fit_tol_m`` of the chord from its first vertex to its last, each further along it
(:func:`collinear_run`: a straight move the CAM cut into pieces), is that chord, a line: a
block of it alone is planned as a straight block (ruckig), not as a curve.
Lines and arcs are kept exact (but for the ends a blend replaces). A block's
:class:`Curve` is parametrised by ``u`` in metres: arc length for lines and arcs, chord
length of the programmed vertices for fitted splines (``|dr/du|`` within a few per mille
of 1); a blend's ``|dr/du|`` is 1 at both ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import sparse
from scipy.interpolate import BSpline, make_lsq_spline
from scipy.linalg import solveh_banded

try:  # scipy's own QR steps (private), for a linear-time make_lsq_spline: see _lsq_coefficients
    from scipy.interpolate import _dierckx

    _BANDED_QR = all(hasattr(_dierckx, f) for f in ("data_matrix", "qr_reduce", "fpback"))
except ImportError:  # pragma: no cover - a scipy without it: make_lsq_spline itself
    _BANDED_QR = False

from feedplan.blend import Blend, bezier, corner_blend, corner_speed_m_s
from feedplan.check import point_segment_distance, segment_table
from feedplan.limits import AxisLimits
from feedplan.path import PLANES, Arc, Line, Path
from oga.defaults import BLEND_MIN_SPEED_SHARE

__all__ = [
    "CORNER_ANGLE_RAD",
    "BLEND_MIN_TURN_RAD",
    "BLEND_MAX_TURN_RAD",
    "MICRO_SEGMENT_M",
    "MICRO_RUN_MIN",
    "CHORD_SEGMENT_M",
    "COLLINEAR_TOL_SHARE",
    "FIT_KNOT_SPACING_M",
    "Curve",
    "Block",
    "Blending",
    "fit_polyline",
    "collinear_run",
    "polyline_fit_deviation",
    "blocks_of",
]

#: Largest tangent turn between two feed moves taken without an exact stop, rad.
CORNER_ANGLE_RAD = 0.2
#: G1 lines shorter than this are CAM micro-segments (fitted by a spline), metres.
MICRO_SEGMENT_M = 1e-3
#: Fewest consecutive micro-segments that are fitted (shorter runs stay lines).
MICRO_RUN_MIN = 4
#: G1 lines shorter than this, turning at most CORNER_ANGLE_RAD from one to the next, are
#: chords of a curve (fitted, not blended vertex by vertex), metres.
CHORD_SEGMENT_M = 2.5e-3
#: A run of micro-segments within this share of the fit tolerance of its chord is that
#: line (:func:`collinear_run`): a straight move cut into pieces, its vertices rounded by the
#: CAM (1 um at most of the default 10 um), not a curve bending by a few micrometres (kept
#: a spline: as a line it turns more at its ends, measured 8 samples slower on
#: line-contouring-xz at the whole fit tolerance).
COLLINEAR_TOL_SHARE = 0.1
#: Largest knot spacing of a micro-segment fit before refinement, metres.
FIT_KNOT_SPACING_M = 0.5e-3
#: Corners turning more than this are blended (G64); smaller kinks are passed as kinks.
BLEND_MIN_TURN_RAD = 1e-3
#: Corners turning more than this are exact stops whatever the path control (a reversal).
BLEND_MAX_TURN_RAD = 0.95 * np.pi
#: Least turn of the unit tangent (rad) and jump of the curvature vector (1/m: a radius of
#: 1 km) where two pieces meet that is blended (:func:`_costly_joint`); below, a piece's float
#: noise at its end.
JOINT_MIN_TURN_RAD, JOINT_MIN_JUMP_PER_M = 1e-9, 1e-3
#: A tangent joint with a jump of curvature is blended where a sampled plan would pass it
#: slower than this share of the feed (:func:`_costly_joint`). Measured on ucp710: plasmatest's
#: 0.75 mm corner arcs at F5840 (about 0.14 of it) and 3.85 mm ones (0.31) blended, 1.0 %
#: faster than the 0.75 mm ones alone (share 0.3); reference_xz's 3.5-10 mm arcs at F3000
#: (0.44-0.98) kept (blended: 1.7 % slower, the planner's own rounding of such a joint costs
#: less than a blend taking its share of the tolerance).
JOINT_BLEND_SPEED_SHARE = 0.4
#: Largest number of knot refinements of one fit.
_FIT_ROUNDS = 12
#: Smoothing length of a fit, in mean chords of the run (the cut-off wavelength of the
#: third-derivative penalty, :func:`_smooth_fit`).
FIT_SMOOTH_LENGTH_CHORDS = 4.0
#: Rounds of a smoothing fit's reweighting, the weight factor per round near a vertex out of
#: tolerance, and the share of the tolerance it aims at.
_SMOOTH_ROUNDS, _SMOOTH_WEIGHT_STEP, _SMOOTH_TOL_SHARE = 10, 4.0, 0.98

_LINE, _ARC, _SPLINE, _QUINTIC = 0, 1, 2, 3


@njit(cache=True)
def _interval(t, x, prev):
    """scipy's ``_find_interval`` for a cubic: l with t[l] <= x < t[l + 1] (hint ``prev``)."""
    k, n = 3, t.shape[0] - 4
    ell = prev if k < prev < n else k
    while x < t[ell] and ell != k:
        ell -= 1
    ell += 1
    while x >= t[ell] and ell != n:
        ell += 1
    return ell - 1


@njit(cache=True)
def _de_boor_step(t, x, ell, j, m, h, hh):
    """One iteration ``j`` of scipy's ``_deBoor_D``: a value step (m < 0) or a step of
    derivative ``m``, on the non-zero B-splines h[0..j] (hh: scratch)."""
    for q in range(j):
        hh[q] = h[q]
    h[0] = 0.0
    for n in range(1, j + 1):
        xb, xa = t[ell + n], t[ell + n - j]
        if xb == xa:
            h[n if m < 0 else m] = 0.0
            continue
        if m < 0:
            w = hh[n - 1] / (xb - xa)
            h[n - 1] += w * (xb - x)
            h[n] = w * (x - xa)
        else:
            w = j * hh[n - 1] / (xb - xa)
            h[n - 1] -= w
            h[n] = w


@njit(cache=True)
def _spline_values(t, c, x, order):
    """A cubic spline and its derivatives up to ``order`` at the sorted or unsorted ``x``,
    bit for bit as scipy's BSpline (the same de Boor steps and sums), in one pass: shape
    (order + 1, N, dim). The value steps shared by the derivatives are done once."""
    out = np.empty((order + 1, x.shape[0], c.shape[1]))
    h, hh, saved = np.empty(4), np.empty(4), np.empty((4, 4))
    ell = 3
    for i in range(x.shape[0]):
        ell = _interval(t, x[i], ell)
        h[0] = 1.0
        for j in range(1, 4):  # value steps; derivative nu starts after step 3 - nu
            if 4 - j <= order:
                for q in range(j):
                    saved[4 - j, q] = h[q]
            _de_boor_step(t, x[i], ell, j, -1, h, hh)
        for q in range(4):
            saved[0, q] = h[q]
        for nu in range(order + 1):
            for q in range(4):
                h[q] = saved[nu, q]
            for j in range(4 - nu, 4):
                _de_boor_step(t, x[i], ell, j, nu, h, hh)
            for col in range(c.shape[1]):
                acc = 0.0
                for a in range(4):
                    acc += c[ell + a - 3, col] * h[a]
                out[nu, i, col] = acc
    return out


@njit(cache=True)
def _bases_d2(t, x, ell):
    """The four cubic B-splines of the interval ``ell`` at ``x`` and their first and second
    derivatives, three 4-tuples: :func:`_spline_values`'s de Boor steps for ``order`` 2
    unrolled (the same operations in the same order), where ``t[ell] < t[ell + 1]`` (then no
    step meets a repeated knot)."""
    # value steps j = 1, 2 (saved for the derivatives), then j = 3
    w = 1.0 / (t[ell + 1] - t[ell])
    a0, a1 = 0.0 + w * (t[ell + 1] - x), w * (x - t[ell])
    w = a0 / (t[ell + 1] - t[ell - 1])
    b0, b1 = 0.0 + w * (t[ell + 1] - x), w * (x - t[ell - 1])
    w = a1 / (t[ell + 2] - t[ell])
    b1, b2 = b1 + w * (t[ell + 2] - x), w * (x - t[ell])
    w = b0 / (t[ell + 1] - t[ell - 2])
    v0, v1 = 0.0 + w * (t[ell + 1] - x), w * (x - t[ell - 2])
    w = b1 / (t[ell + 2] - t[ell - 1])
    v1, v2 = v1 + w * (t[ell + 2] - x), w * (x - t[ell - 1])
    w = b2 / (t[ell + 3] - t[ell])
    v2, v3 = v2 + w * (t[ell + 3] - x), w * (x - t[ell])
    # first derivative: step j = 3 on (b0, b1, b2); second: j = 2 on (a0, a1), then j = 3
    w = 2 * a0 / (t[ell + 1] - t[ell - 1])
    e0, e1 = 0.0 - w, w
    w = 2 * a1 / (t[ell + 2] - t[ell])
    return ((v0, v1, v2, v3), _derivative_step3(t, ell, b0, b1, b2),
            _derivative_step3(t, ell, e0, e1 - w, w))


@njit(cache=True)
def _derivative_step3(t, ell, h0, h1, h2):
    """De Boor's derivative step j = 3 on (h0, h1, h2): a 4-tuple."""
    w = 3 * h0 / (t[ell + 1] - t[ell - 2])
    g0, g1 = 0.0 - w, w
    w = 3 * h1 / (t[ell + 2] - t[ell - 1])
    g1, g2 = g1 - w, w
    w = 3 * h2 / (t[ell + 3] - t[ell])
    return g0, g1, g2 - w, w


@njit(cache=True)
def _dot4(c, row, col, b):
    """``sum(c[row + a, col] * b[a])`` summed as :func:`_spline_values` sums it."""
    acc = 0.0
    acc += c[row, col] * b[0]
    acc += c[row + 1, col] * b[1]
    acc += c[row + 2, col] * b[2]
    acc += c[row + 3, col] * b[3]
    return acc


@njit(cache=True)
def _spline_values_d2(t, c, x):
    """:func:`_spline_values` with ``order`` 2, bit for bit, about 2x faster (the de Boor
    steps unrolled where no knot repeats next to ``x``: every interval inside the curve)."""
    out = np.empty((3, x.shape[0], c.shape[1]))
    ell = 3
    for i in range(x.shape[0]):
        ell = _interval(t, x[i], ell)
        if not t[ell] < t[ell + 1]:
            one = _spline_values(t, c, x[i:i + 1], 2)
            for nu in range(3):
                for col in range(c.shape[1]):
                    out[nu, i, col] = one[nu, 0, col]
            continue
        b0, b1, b2 = _bases_d2(t, x[i], ell)
        for col in range(c.shape[1]):
            out[0, i, col] = _dot4(c, ell - 3, col, b0)
            out[1, i, col] = _dot4(c, ell - 3, col, b1)
            out[2, i, col] = _dot4(c, ell - 3, col, b2)
    return out


def _spline_eval(t, c, x, order):
    """:func:`_spline_values`, by the unrolled kernel for ``order`` 2 (the planner's rounds)."""
    return _spline_values_d2(t, c, x) if order == 2 else _spline_values(t, c, x, order)


@dataclass(frozen=True, eq=False)
class Curve:
    """A chain of pieces (lines, arcs, cubic splines) continuous in position.

    Attributes
    ----------
    u0 : ndarray, shape (P + 1,)
        Parameter (metres) where each piece starts; ``u0[-1]`` is the total.
    kind : ndarray of int, shape (P,)
        0 line, 1 arc, 2 spline, 3 corner blend (a quintic Bezier).
    org, e1, e2, e3 : ndarray, shape (P, 3)
        Line: start, unit direction, 0, 0. Arc: centre, ``R`` times the plane's
        first and second axis, helical rise per metre of ``u`` along the normal.
    th0, w : ndarray, shape (P,)
        Arc start angle (rad) and angular rate (rad per metre of ``u``).
    corr : ndarray, shape (P, 3)
        Arc end correction per metre of ``u`` (the programmed end minus the
        exact circle end, spread linearly; below the reader's arc tolerance).
    splines : tuple of scipy.interpolate.BSpline
        Cubic splines of the pieces of kind 2 (``org[p, 0]`` indexes them); their
        parameter starts at 0.
    ctrl : ndarray, shape (Q, 6, 3)
        Control points of the quintics of the pieces of kind 3 (``org[p, 0]`` indexes them).
    dev : ndarray, shape (P,)
        Largest distance of each piece from the programmed moves, m (0 for lines and arcs).
    """

    u0: np.ndarray
    kind: np.ndarray
    org: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    e3: np.ndarray
    th0: np.ndarray
    w: np.ndarray
    corr: np.ndarray
    splines: tuple
    ctrl: np.ndarray
    dev: np.ndarray

    @property
    def length(self) -> float:
        """Parameter length in metres."""
        return float(self.u0[-1])

    @property
    def is_line(self) -> bool:
        """One line piece (``org[0]`` its start, ``e1[0]`` its direction)."""
        return self.kind.size == 1 and self.kind[0] == _LINE

    def evaluate(self, u: np.ndarray, left: bool = False, order: int = 3):
        """Position and derivatives with respect to ``u``.

        Parameters
        ----------
        u : ndarray, shape (N,)
            Parameters in [0, length], metres.
        left : bool
            At a piece boundary, evaluate the piece that ends there (default:
            the one that starts there).
        order : {3, 2}
            Highest derivative returned (2: no ``d3``, which costs a spline evaluation).

        Returns
        -------
        p, d1, d2, d3 : ndarray, shape (N, 3)
            Position (m), dr/du (1), d2r/du2 (1/m), d3r/du3 (1/m^2); ``d3`` only if
            ``order`` is 3.
        """
        u = np.asarray(u, dtype=np.float64)
        if self.kind.size == 1 and self.kind[0] == _SPLINE:  # one fitted run: no piece lookup
            spl = self.splines[0]
            return tuple(_spline_eval(spl.t, spl.c, u - self.u0[0], order))
        side = "left" if left else "right"
        idx = np.clip(np.searchsorted(self.u0, u, side=side) - 1, 0, len(self.kind) - 1)
        ul = (u - self.u0[idx])[:, None]
        kind = self.kind[idx]
        p = np.empty((u.size, 3))
        d1 = np.zeros((u.size, 3))
        d2 = np.zeros((u.size, 3))
        d3 = np.zeros((u.size, 3))
        m = kind == _LINE
        if m.any():
            i = idx[m]
            p[m] = self.org[i] + ul[m] * self.e1[i]
            d1[m] = self.e1[i]
        m = kind == _ARC
        if m.any():
            i = idx[m]
            w = self.w[i][:, None]
            th = self.th0[i][:, None] + w * ul[m]
            c, s = np.cos(th), np.sin(th)
            e1, e2 = self.e1[i], self.e2[i]
            p[m] = self.org[i] + c * e1 + s * e2 + ul[m] * (self.e3[i] + self.corr[i])
            d1[m] = w * (c * e2 - s * e1) + self.e3[i] + self.corr[i]
            d2[m] = -w * w * (c * e1 + s * e2)
            d3[m] = -w**3 * (c * e2 - s * e1)
        m = kind == _QUINTIC
        if m.any():
            i = idx[m]
            q = self.org[i, 0].astype(np.int64)
            p[m], d1[m], d2[m], d3[m] = bezier(self.ctrl[q], self.u0[i + 1] - self.u0[i],
                                               ul[m, 0])
        at = np.flatnonzero(kind == _SPLINE)
        if at.size:
            sid = self.org[idx[at], 0].astype(np.int64)
            at = at[np.argsort(sid, kind="stable")]  # grouped by spline: O(N log N), not O(N S)
            ids, first = np.unique(np.sort(sid), return_index=True)
            for k, mk in zip(ids, np.split(at, first[1:])):
                spl = self.splines[k]
                val = _spline_eval(spl.t, spl.c, ul[mk, 0], order)
                p[mk], d1[mk], d2[mk] = val[0], val[1], val[2]
                if order == 3:
                    d3[mk] = val[3]
        return (p, d1, d2, d3) if order == 3 else (p, d1, d2)


@dataclass(frozen=True, eq=False)
class Block:
    """Moves planned from rest to rest along one curve.

    Attributes
    ----------
    curve : Curve
        The geometry to follow.
    rapid : bool
        True for a rapid (G0) line, planned at the axis limits.
    segments : ndarray of int, shape (n,)
        Indices into ``Path.segments`` of the programmed moves of this block.
    seg_u0 : ndarray, shape (n + 1,)
        Parameter ``u`` of the curve where each programmed move starts (last: the end).
    fit_deviation_m : float
        Largest deviation of a fitted spline from its programmed polyline (0 if none).
    """

    curve: Curve
    rapid: bool
    segments: np.ndarray
    seg_u0: np.ndarray
    fit_deviation_m: float


# --------------------------------------------------------------------------- fitting


@njit(cache=True)
def _two_way_deviation(verts, dense, per, reach):
    """Per vertex, the larger of: vertex to the dense curve, and dense curve
    points of the adjacent intervals to the polyline (each within ``reach`` intervals)."""
    n = verts.shape[0] - 1
    out = np.zeros(n + 1)
    for j in range(n + 1):
        # vertex -> dense polyline of the curve around it
        best = 1e300
        lo = max(0, (j - reach) * per)
        hi = min(dense.shape[0] - 1, (j + reach) * per)
        for q in range(lo, hi):
            d = point_segment_distance(verts[j], dense[q], dense[q + 1])
            if d < best:
                best = d
        out[j] = best
    for q in range(dense.shape[0]):
        j = min(q // per, n - 1)
        best = 1e300
        for s in range(max(0, j - reach), min(n, j + reach + 1)):
            d = point_segment_distance(dense[q], verts[s], verts[s + 1])
            if d < best:
                best = d
        # charge it to the nearer end vertex of its interval
        jj = j + 1 if (q - j * per) * 2 > per else j
        if best > out[jj]:
            out[jj] = best
    return out


_DENSE_PER_SEGMENT = 8


def polyline_fit_deviation(spline: BSpline, verts: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Two-way deviation of a fitted curve from the polyline it replaces.

    Parameters
    ----------
    spline : BSpline
        Curve of parameter ``u`` (metres).
    verts : ndarray, shape (n + 1, 3)
        Programmed vertices, metres.
    u : ndarray, shape (n + 1,)
        Parameter of each vertex (chord length).

    Returns
    -------
    ndarray, shape (n + 1,)
        Per vertex, metres: the larger of its distance to the curve and the
        largest distance to the polyline of the curve points on the intervals
        charged to it. The maximum is the Hausdorff-type deviation of the fit.
    """
    per = _DENSE_PER_SEGMENT
    f = np.arange(per) / per
    x = np.append((u[:-1, None] + f * np.diff(u)[:, None]).ravel(), u[-1])
    dense = spline(x)
    return _two_way_deviation(np.ascontiguousarray(verts), np.ascontiguousarray(dense), per, 3)


#: Rows of the QR reduction per call of scipy's qr_reduce span this many coefficients.
_QR_BAND = 16


def _lsq_coefficients(x: np.ndarray, y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``make_lsq_spline(x, y, t, k=3).c`` bit for bit, in time linear in ``len(x)``.

    scipy's QR reduction (1.15-1.17) rotates every data row against every coefficient
    row up to the last (O(m nc): 7 s for 100k micro-segments); once a sorted data row
    has passed the ``k + 1`` coefficient rows of its support it is exactly zero and the
    remaining rotations are the identity (``c = 1, s = 0``). Here scipy's own steps run
    on stretches of rows whose offsets span at most :data:`_QR_BAND` coefficients, each
    told that the coefficients end just after its support: the same rotations on the
    same numbers, without the identities.

    Parameters
    ----------
    x : ndarray, shape (m,)
        Sorted abscissas.
    y : ndarray, shape (m, 3)
        Ordinates.
    t : ndarray, shape (nc + 4,)
        Knots of the cubic.

    Returns
    -------
    ndarray, shape (nc, 3)
        The coefficients.
    """
    if not _BANDED_QR:  # pragma: no cover
        return make_lsq_spline(x, y, t, k=3).c
    k = 3
    w = np.ones_like(x)
    y_w = y * w[:, None]
    a, offset, nc = _dierckx.data_matrix(x, t, k, w)
    starts = np.searchsorted(offset, np.arange(_QR_BAND, nc, _QR_BAND))
    bounds = np.unique(np.clip(np.concatenate([[1], starts, [x.size]]), 1, x.size))
    for r0, r1 in zip(bounds[:-1], bounds[1:]):
        nc_seen = min(nc, int(offset[r1 - 1]) + k + 1)
        _dierckx.qr_reduce(a[:r1], offset[:r1], nc_seen, y_w[:r1], int(r0))
    c, _, _ = _dierckx.fpback(a, nc, x, y, t, k, w, y_w)
    return c


def _lsq(verts: np.ndarray, u: np.ndarray, knots_at: np.ndarray) -> BSpline:
    """Least-squares cubic through vertices and chord midpoints, clamped on the ends."""
    mid_u = 0.5 * (u[:-1] + u[1:])
    mid_p = 0.5 * (verts[:-1] + verts[1:])
    x = np.empty(2 * u.size - 1)
    y = np.empty((x.size, 3))
    x[0::2], x[1::2] = u, mid_u
    y[0::2], y[1::2] = verts, mid_p
    t = np.concatenate([[u[0]] * 4, u[knots_at], [u[-1]] * 4])
    c = _lsq_coefficients(x, y, t)
    c[0], c[-1] = verts[0], verts[-1]
    return BSpline(t, c, 3)


def _derivative_operator(t: np.ndarray, k: int, n: int) -> sparse.csr_array:
    """The map of a degree-``k`` spline's ``n`` coefficients (knots ``t``) to those of its
    derivative (knots ``t[1:-1]``): ``d_i = k (c_{i+1} - c_i) / (t_{i+k+1} - t_{i+1})``, 0 over
    a knot span of zero length."""
    span = t[k + 1 : k + n] - t[1:n]
    f = np.divide(k, span, out=np.zeros_like(span), where=span > 0)
    return sparse.diags_array([-f, f], offsets=[0, 1], shape=(n - 1, n), format="csr")


def _jerk_penalty(t: np.ndarray, n: int) -> sparse.csr_array:
    """``P`` with ``c^T P c`` the integral of the squared third derivative of the cubic of
    knots ``t`` and coefficients ``c`` (one column), shape (n, n): the third derivative is
    constant on each knot span."""
    d3 = (_derivative_operator(t[2:-2], 1, n - 2) @ _derivative_operator(t[1:-1], 2, n - 1)
          @ _derivative_operator(t, 3, n))
    return (d3.T @ sparse.diags_array(np.diff(t[3:-3])) @ d3).tocsr()


def _penalised(x, y, w, t, penalty, lam, ends) -> np.ndarray:
    """Coefficients of the cubic of knots ``t`` that minimises the weighted squared
    residuals ``w |r(x) - y|^2`` plus ``lam`` times the integral of the squared third
    derivative, its end coefficients fixed to ``ends`` (shape (2, 3)): one banded
    symmetric solve (bandwidth 3). Shape (n, 3)."""
    b = BSpline.design_matrix(x, t, 3).tocsr()
    n = b.shape[1]
    a = (b.T @ b.multiply(w[:, None]).tocsr() + lam * penalty).tocsc()
    rhs = b.T @ (w[:, None] * y)
    inner = slice(1, n - 1)
    rhs = rhs[inner] - a[inner, [0]].toarray() @ ends[:1] - a[inner, [n - 1]].toarray() @ ends[1:]
    sub = a[inner, inner].todia()
    band = np.zeros((4, n - 2))
    for k in range(4):  # upper form of solveh_banded
        band[3 - k, k:] = sub.diagonal(k)
    c = np.empty((n, 3))
    c[0], c[-1] = ends
    c[inner] = solveh_banded(band, rhs, check_finite=False)
    return c


def _smooth_fit(verts: np.ndarray, u: np.ndarray, knots_at: np.ndarray, fit_tol_m: float):
    """A smooth cubic within the tolerance, or the last try: (spline, deviation per vertex, m).

    A least-squares fit through vertices and chord midpoints follows each chord of a
    CAM's tessellation, so its curvature ripples at the chord length (line-contouring's
    16 mm arcs in 1.3 mm chords: curvature 62 +- 60 1/m, which the jerk limit passes at a
    fraction of the arc's speed). Here the squared third derivative is penalised, over a
    smoothing length of :data:`FIT_SMOOTH_LENGTH_CHORDS` mean chords, and the data weights
    raised (and the penalty lowered) where the two-way deviation exceeds the tolerance,
    :data:`_SMOOTH_ROUNDS` times at most; where it still does, :func:`fit_polyline` fits
    without the penalty. Measured on line-contouring-xz: 31.4 -> 25.6 s planned.
    """
    mid_u = 0.5 * (u[:-1] + u[1:])
    x = np.empty(2 * u.size - 1)
    y = np.empty((x.size, 3))
    x[0::2], x[1::2] = u, mid_u
    y[0::2], y[1::2] = verts, 0.5 * (verts[:-1] + verts[1:])
    t = np.concatenate([[u[0]] * 4, u[knots_at], [u[-1]] * 4])
    n = t.size - 4
    penalty = _jerk_penalty(t, n)
    density = x.size / u[-1]  # data points per metre
    ell = FIT_SMOOTH_LENGTH_CHORDS * u[-1] / (u.size - 1)
    lam = density * (ell / (2.0 * np.pi)) ** 6  # cut-off wavelength ell of the smoother
    w = np.ones(x.size)
    ends = np.vstack([verts[0], verts[-1]])
    for _ in range(_SMOOTH_ROUNDS):
        spl = BSpline(t, _penalised(x, y, w, t, penalty, lam, ends), 3)
        dev = polyline_fit_deviation(spl, verts, u)
        bad = np.flatnonzero(dev > _SMOOTH_TOL_SHARE * fit_tol_m)
        if bad.size == 0:
            break
        near = np.unique(np.clip(2 * bad[:, None] + np.arange(-3, 4), 0, x.size - 1))
        w[near] *= _SMOOTH_WEIGHT_STEP
        lam /= _SMOOTH_WEIGHT_STEP
    return spl, dev


def fit_polyline(verts: np.ndarray, fit_tol_m: float) -> list[tuple[int, int, BSpline, float]]:
    """Fit a run of micro-segments with cubic splines within a tolerance.

    Parameters
    ----------
    verts : ndarray, shape (n + 1, 3)
        Vertices of the run, metres (n >= 1 segments of non-zero length).
    fit_tol_m : float
        Largest two-way deviation allowed, metres.

    Returns
    -------
    list of (first, last, spline, deviation_m)
        Consecutive stretches ``verts[first..last]``, each fitted by a spline whose
        parameter is the chord length from ``verts[first]`` (starting at 0) and
        which passes exactly through both end vertices. Stretches meet at a vertex
        where no single fit met the tolerance (an exact stop there).
    """
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(verts, axis=0), axis=1))])
    n = u.size - 1
    if n == 1:  # one segment: the straight cubic
        c = verts[0] + np.linspace(0.0, 1.0, 4)[:, None] * (verts[1] - verts[0])
        return [(0, 1, BSpline(np.r_[[0.0] * 4, [u[1]] * 4], c, 3), 0.0)]
    step = max(1, int(round(FIT_KNOT_SPACING_M / (u[-1] / n))))
    knots = set(range(step, n, step))
    spl, dev = _smooth_fit(verts, u, np.array(sorted(knots), dtype=np.int64), fit_tol_m)
    bad = np.flatnonzero(dev > fit_tol_m)
    if bad.size == 0:
        return [(0, n, spl, float(dev.max()))]
    for _ in range(_FIT_ROUNDS):
        idx = np.array(sorted(knots), dtype=np.int64)
        spl = _lsq(verts, u, idx)
        dev = polyline_fit_deviation(spl, verts, u)
        bad = np.flatnonzero(dev > fit_tol_m)
        if bad.size == 0:
            return [(0, n, spl, float(dev.max()))]
        bounds = np.concatenate([[0], idx, [n]])
        grown = False
        for b in bad:
            k = min(np.searchsorted(bounds, b, side="right"), len(bounds) - 1)
            for lo, hi in ((bounds[k - 1], bounds[k]), (bounds[max(k - 2, 0)], bounds[k - 1])):
                if hi - lo > 1:
                    knots.add(int((lo + hi) // 2))
                    grown = True
        if not grown:
            break
    # split at the sharpest vertex among the failing ones
    d = np.diff(verts, axis=0)
    d /= np.linalg.norm(d, axis=1)[:, None]
    turn = np.zeros(n + 1)
    turn[1:-1] = np.arccos(np.clip(np.sum(d[:-1] * d[1:], axis=1), -1.0, 1.0))
    cand = bad[(bad > 0) & (bad < n)]
    j = int(cand[np.argmax(turn[cand])]) if cand.size else n // 2
    left = fit_polyline(verts[: j + 1], fit_tol_m)
    right = fit_polyline(verts[j:], fit_tol_m)
    return left + [(a + j, b + j, s, e) for a, b, s, e in right]


def _line_distances(verts: np.ndarray) -> np.ndarray:
    """Distance of each vertex from the line through the first and last, m."""
    d = verts[-1] - verts[0]
    d = d / np.linalg.norm(d)
    rel = verts - verts[0]
    return np.linalg.norm(rel - (rel @ d)[:, None] * d, axis=1)


def collinear_run(verts: np.ndarray, fit_tol_m: float) -> tuple[np.ndarray, float] | None:
    """Where a run of micro-segments is one straight move: the parameter (m along the chord
    from ``verts[0]``) of each vertex and the largest distance of one from the chord, or None.

    Straight: every vertex within ``fit_tol_m`` of the chord from the first vertex to the
    last, and each one further along it than the one before (no move backwards). The chord
    then stays within ``fit_tol_m`` of the polyline both ways (a point of either lies
    between two consecutive vertices, each within ``fit_tol_m`` of the other curve), as a
    fitted spline must; a spline along it would be the same line, planned as a curve.

    Parameters
    ----------
    verts : ndarray, shape (n + 1, 3)
        Vertices of the run, m.
    fit_tol_m : float
        Largest deviation allowed, m.

    Returns
    -------
    (along, deviation_m) or None
        ``along``, shape (n + 1,), increasing from 0 to the chord's length (m); the largest
        distance of a vertex from the chord (m).
    """
    d = verts[-1] - verts[0]
    length = float(np.linalg.norm(d))
    if length <= 0.0:
        return None
    dev = float(_line_distances(verts).max())
    if dev > fit_tol_m:
        return None
    along = (verts - verts[0]) @ (d / length)
    along[0], along[-1] = 0.0, length
    return (along, dev) if bool(np.all(np.diff(along) > 0.0)) else None


# --------------------------------------------------------------------------- blocks


def _tangents(seg) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangent at the start and at the end of a programmed move."""
    if isinstance(seg, Line):
        t = (seg.end - seg.start) / seg.length
        return t, t
    i, j, n = PLANES[seg.plane]
    out = []
    for u in (0.0, 1.0):
        th = seg.start_angle + u * seg.sweep_rad
        t = np.zeros(3)
        t[i] = -np.sin(th) * seg.radius * seg.sweep_rad
        t[j] = np.cos(th) * seg.radius * seg.sweep_rad
        t[n] = seg.rise
        out.append(t / np.linalg.norm(t))
    return out[0], out[1]


def _turn(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))


class _CurveBuilder:
    """Pieces of one curve (rows of :class:`Curve`'s columns, then its deviation), and the
    programmed moves along it: their indices, where each starts (u, m), the fits' deviation."""

    def __init__(self) -> None:
        self.rows: list[list] = []
        self.splines: list[BSpline] = []
        self.quintics: list[np.ndarray] = []
        self.seg_ids: list[int] = []
        self.seg_u: list[float] = [0.0]
        self.fit_dev = 0.0
        self.length = 0.0  # parameter length of the rows, m

    def _append(self, row: list) -> None:
        self.rows.append(row)
        self.length += row[0]

    def line(self, a: np.ndarray, b: np.ndarray, dev: float = 0.0) -> None:
        L = float(np.linalg.norm(b - a))
        z = np.zeros(3)
        self._append([L, _LINE, a, (b - a) / L, z, z, 0.0, 0.0, z, dev])

    def arc(self, seg: Arc) -> None:
        i, j, n = PLANES[seg.plane]
        L, R = seg.length, seg.radius
        e1, e2, e3 = np.zeros(3), np.zeros(3), np.zeros(3)
        e1[i], e2[j], e3[n] = R, R, seg.rise / L
        center = seg.center.copy()
        exact_end = seg.point(1.0)
        corr = (seg.end - exact_end) / L
        self._append([L, _ARC, center, e1, e2, e3, seg.start_angle, seg.sweep_rad / L, corr, 0.0])

    def spline(self, spl: BSpline, L: float, dev: float) -> None:
        z = np.zeros(3)
        org = np.array([len(self.splines), 0.0, 0.0])
        self.splines.append(spl)
        self._append([L, _SPLINE, org, z, z, z, 0.0, 0.0, z, dev])

    def quintic(self, blend: Blend) -> None:
        z = np.zeros(3)
        org = np.array([len(self.quintics), 0.0, 0.0])
        self.quintics.append(blend.ctrl)
        self._append([blend.length, _QUINTIC, org, z, z, z, 0.0, 0.0, z, blend.deviation_m])

    def trim_start(self, cut: float) -> None:
        """Drop the first ``cut`` metres of parameter of the first piece."""
        row = self.rows[0]
        row[0] -= cut
        self.length -= cut
        if row[1] == _LINE:
            row[2] = row[2] + cut * row[3]
        elif row[1] == _ARC:
            row[6] += row[7] * cut
            row[2] = row[2] + cut * (row[5] + row[8])
        else:
            k = int(row[2][0])
            spl = self.splines[k]
            self.splines[k] = BSpline(spl.t - cut, spl.c, spl.k)

    def piece_curve(self, index: int) -> Curve:
        """A curve of one piece alone (the last, -1, or the first, 0: for its end points
        and derivatives)."""
        one = _CurveBuilder()
        row = list(self.rows[index])
        if row[1] == _SPLINE:
            one.splines = [self.splines[int(row[2][0])]]
            row[2] = np.zeros(3)
        one._append(row)
        return one.build()

    def build(self) -> Curve:
        cols = list(zip(*self.rows))
        return Curve(
            u0=np.concatenate([[0.0], np.cumsum(cols[0])]),
            kind=np.array(cols[1], dtype=np.int64),
            org=np.array(cols[2]),
            e1=np.array(cols[3]),
            e2=np.array(cols[4]),
            e3=np.array(cols[5]),
            th0=np.array(cols[6]),
            w=np.array(cols[7]),
            corr=np.array(cols[8]),
            splines=tuple(self.splines),
            ctrl=np.array(self.quintics).reshape(-1, 6, 3),
            dev=np.array(cols[9], dtype=np.float64),
        )

    def block(self) -> Block:
        return Block(self.build(), False, np.array(self.seg_ids, dtype=np.int64),
                     np.array(self.seg_u), self.fit_dev)


def _is_micro(seg) -> bool:
    return isinstance(seg, Line) and not seg.rapid and seg.length < MICRO_SEGMENT_M


@dataclass(frozen=True, eq=False)
class Blending:
    """How corners are blended (:mod:`feedplan.blend`).

    Attributes
    ----------
    tol_m : float
        Largest distance of a blend from the programmed moves, m.
    limits : AxisLimits, optional
        Axis limits: a corner whose blend cannot be passed at
        :data:`~oga.defaults.BLEND_MIN_SPEED_SHARE` of the feed stays an exact stop (none:
        every blend within ``tol_m`` is kept).
    feeds : ndarray, shape (n_segments,), optional
        Feed of every move, m/s (default: as programmed).
    """

    tol_m: float
    limits: AxisLimits | None = None
    feeds: np.ndarray | None = None

    def feed(self, path: Path, k: int) -> float:
        return float(path.segments[k].feed_m_s if self.feeds is None else self.feeds[k])


def _blendable(path: Path, k: int, blending: Blending | None) -> bool:
    """Whether the corner at the end of feed move ``k`` may be blended (not G61, a tolerance)."""
    return blending is not None and blending.tol_m > 0 and path.segments[k].blend_tol_m != 0


def _corner_turn(path: Path, k: int) -> float:
    """Tangent turn from move ``k - 1`` to move ``k``, rad."""
    return _turn(_tangents(path.segments[k - 1])[1], _tangents(path.segments[k])[0])


def _feed_chains(path: Path, idx: list[int], blending: Blending | None) -> list[tuple]:
    """Split consecutive feed moves at exact stops: every kink above
    :data:`BLEND_MIN_TURN_RAD` at the end of a move under G61, corners above
    :data:`CORNER_ANGLE_RAD` without blending or turning more than :data:`BLEND_MAX_TURN_RAD`.

    Returns a list of (moves, turns): the move indices of each chain and the tangent turn
    (rad) into each of them from the previous one (0 for the first).
    """
    chains: list[tuple] = []
    for k in idx:
        if chains and chains[-1][0][-1] == k - 1:
            turn = _corner_turn(path, k)
            if turn <= BLEND_MIN_TURN_RAD or (path.segments[k - 1].blend_tol_m != 0 and (
                turn <= CORNER_ANGLE_RAD
                or (turn <= BLEND_MAX_TURN_RAD and _blendable(path, k - 1, blending))
            )):
                chains[-1][0].append(k)
                chains[-1][1].append(turn)
                continue
        chains.append(([k], [0.0]))
    return chains


def _chord_stretches(verts: np.ndarray, fit_tol_m: float) -> list[tuple[int, int]]:
    """Consecutive stretches ``verts[first..last]`` of a short run of micro-segments, each as
    long as its vertices stay within ``fit_tol_m`` of its chord (:func:`collinear_run`): a
    CAM's jitter of micrometre moves dropped, the corners between stretches kept."""
    out, first, n = [], 0, len(verts) - 1
    while first < n:
        last = first + 1
        while last < n and collinear_run(verts[first:last + 2], fit_tol_m) is not None:
            last += 1
        out.append((first, last))
        first = last
    return out


def _add_run(out: list, run_ids: list[int], verts: np.ndarray, fit_tol_m: float) -> None:
    """Append a run of at least :data:`MICRO_RUN_MIN` micro-segments to the last curve of
    ``out``: its chord where straight, else its fitted splines (a new curve where a fit
    splits, an exact stop unless blended)."""
    b = out[-1][0]
    straight = collinear_run(verts, COLLINEAR_TOL_SHARE * fit_tol_m)
    if straight is not None:  # a straight run: the line itself (ruckig plans it alone)
        along, dev = straight
        base = b.seg_u[-1]
        b.line(verts[0], verts[-1], dev)
        b.seg_ids.extend(run_ids)
        b.seg_u.extend(base + along[1:])
        b.fit_dev = max(b.fit_dev, dev)
        return
    for first, last, spl, dev in fit_polyline(verts, fit_tol_m):
        if first > 0:
            out.append((_CurveBuilder(), True))
            b = out[-1][0]
        chord = np.linalg.norm(np.diff(verts[first : last + 1], axis=0), axis=1)
        base = b.seg_u[-1]
        b.spline(spl, float(chord.sum()), dev)
        b.seg_ids.extend(run_ids[first:last])
        b.seg_u.extend(base + np.cumsum(chord))
        b.fit_dev = max(b.fit_dev, dev)


def _pieces(path: Path, ids: list[int], fit_tol_m: float, fitted: set[int],
            blending: Blending | None) -> list[tuple[_CurveBuilder, bool]]:
    """Curves of consecutive moves without a blended corner between them, each with whether
    an exact stop separates it from the previous one unless blended (a fit's split,
    :func:`_chain_blocks`) or not (a joint: passed as it is unless blended).

    ``fitted``: the moves whose corner with the previous move lies inside a fitted run
    (:func:`_fitted_corners`). Where the move before may be blended (:func:`_blendable`),
    every move or run starts a curve of its own, so that a tangent joint with a jump of
    curvature (a line into an arc) or of the tangent (a spline's end into a line) is blended
    too; a run of fewer than :data:`MICRO_RUN_MIN` fitted micro-segments is then cut into
    stretches within ``fit_tol_m`` of their chords (:func:`_chord_stretches`), one line each.
    """
    segs = path.segments
    out = [(_CurveBuilder(), False)]
    k = 0
    while k < len(ids):
        run = k + 1
        while run < len(ids) and ids[run] in fitted:
            run += 1
        split = _blendable(path, ids[k - 1], blending) if k > 0 else False
        if split:
            out.append((_CurveBuilder(), False))
        run_ids = ids[k:run]
        verts = np.vstack([segs[run_ids[0]].start] + [segs[i].end for i in run_ids])
        if run - k >= MICRO_RUN_MIN:
            _add_run(out, run_ids, verts, fit_tol_m)
            k = run
            continue
        stretches = _chord_stretches(verts, fit_tol_m) if blending is not None else [(0, 1)]
        for j, (first, last) in enumerate(stretches):
            if j > 0:
                out.append((_CurveBuilder(), False))
            b, seg = out[-1][0], segs[run_ids[first]]
            if last - first > 1:
                along, dev = collinear_run(verts[first:last + 1], fit_tol_m)
                b.line(verts[first], verts[last], dev)
                b.seg_u.extend(b.seg_u[-1] + along[1:])
                b.fit_dev = max(b.fit_dev, dev)
            elif isinstance(seg, Line):
                b.line(seg.start, seg.end)
                b.seg_u.append(b.seg_u[-1] + seg.length)
            else:
                b.arc(seg)
                b.seg_u.append(b.seg_u[-1] + seg.length)
            b.seg_ids.extend(run_ids[first:last])
        k += stretches[-1][1]
    return out


def _blend(a: _CurveBuilder, b: _CurveBuilder, path: Path, blending: Blending) -> Blend | None:
    """The blend of the end of ``a`` into the start of ``b``, or None if none keeps within
    the tolerance or is fast enough."""
    end, start = a.piece_curve(-1), b.piece_curve(0)
    cut_max = 0.5 * min(end.length, start.length)
    if not cut_max > 0:
        return None
    def table(cut):
        # the programmed moves within the cut on either side (walking from the corner):
        # only those, so that the deviation's tracking starts on the move the blend leaves
        k = len(a.seg_ids) - 1
        while k > 0 and a.seg_u[k] > a.length - cut:
            k -= 1
        near = a.seg_ids[k:]
        k = 0
        while k < len(b.seg_ids) and b.seg_u[k] < cut:
            k += 1
        near += b.seg_ids[:max(k, 1)]
        return segment_table([path.segments[i] for i in near])

    def left(cut):
        p, d1, d2, _ = end.evaluate(np.array([end.length - cut]))
        return p[0], d1[0], d2[0]

    def right(cut):
        p, d1, d2, _ = start.evaluate(np.array([cut]))
        return p[0], d1[0], d2[0]

    blend = corner_blend(left, right, cut_max, table, blending.tol_m)
    if blend is None or blending.limits is None:
        return blend
    # the speed a stop there would cost: the feed, or what the shorter piece lets the axes
    # reach from rest (about sqrt(A L), (J L^2)^(1/3) for the least limits)
    lim = blending.limits
    amax, jmax = lim.amax_m_s2[lim.present], lim.jmax_m_s3[lim.present]
    L = 2.0 * cut_max
    reach = min(math.sqrt(float(np.min(amax)) * L), math.cbrt(float(np.min(jmax)) * L * L))
    feed = min(blending.feed(path, a.seg_ids[-1]), blending.feed(path, b.seg_ids[0]), reach)
    if corner_speed_m_s(blend, lim.amax_m_s2, lim.jmax_m_s3) < BLEND_MIN_SPEED_SHARE * feed:
        return None
    return blend


def _costly_joint(a: _CurveBuilder, b: _CurveBuilder, path: Path, blending: Blending) -> bool:
    """Whether the end of ``a`` meets the start of ``b`` at a joint worth blending: a kink of
    more than :data:`BLEND_MIN_TURN_RAD`, or a jump of the curvature vector ``d kappa`` (above
    :data:`JOINT_MIN_JUMP_PER_M`) that slows a sampled plan below
    :data:`JOINT_BLEND_SPEED_SHARE` of the feed: spread over the time ``T`` of a filter rounding
    the curve by the tolerance, ``T^3 = 24 tol / J``, the acceleration step ``v^2 |d kappa_i|``
    is a jerk within ``J_i`` up to ``v = sqrt(J_i T / |d kappa_i|)`` (the least over the axes).
    Where it passes faster, the planner's own rounding of the joint costs little, and a blend
    taking its share of the tolerance costs more (measured on reference_xz: 2 % slower).
    Without limits every joint is worth it."""
    end, start = a.piece_curve(-1), b.piece_curve(0)
    _, t0, k0, _ = end.evaluate(np.array([end.length]), left=True)
    _, t1, k1, _ = start.evaluate(np.array([0.0]))
    turn = _turn(t0[0] / np.linalg.norm(t0[0]), t1[0] / np.linalg.norm(t1[0]))
    jump = np.abs(k1[0] - k0[0])
    jumps = float(np.linalg.norm(jump)) > JOINT_MIN_JUMP_PER_M
    if turn > BLEND_MIN_TURN_RAD:
        return True
    if blending.limits is None:
        return jumps or turn > JOINT_MIN_TURN_RAD
    if not jumps:
        return False
    lim = blending.limits
    jmax = lim.jmax_m_s3[lim.present]
    t = math.cbrt(24.0 * blending.tol_m / float(np.min(jmax)))
    with np.errstate(divide="ignore"):
        v = float(np.sqrt(np.min(jmax * t / jump[lim.present])))
    feed = min(blending.feed(path, a.seg_ids[-1]), blending.feed(path, b.seg_ids[0]))
    return v < JOINT_BLEND_SPEED_SHARE * feed


def _merge(a: _CurveBuilder, b: _CurveBuilder, blend: Blend | None) -> None:
    """Append ``b`` to ``a``, through ``blend`` (None: as they meet)."""
    cut = 0.0 if blend is None else blend.cut_m
    a.rows[-1][0] -= cut
    a.length -= cut
    base = mid = offset = a.length
    if blend is not None:
        mid = base + 0.5 * blend.length
        a.quintic(blend)
        b.trim_start(cut)
        offset = base + blend.length - cut
        a.fit_dev = max(a.fit_dev, blend.deviation_m)
    first = {_SPLINE: len(a.splines), _QUINTIC: len(a.quintics)}
    for row in b.rows:
        if row[1] in first:
            row[2] = row[2] + np.array([first[row[1]], 0.0, 0.0])
        a._append(row)
    a.splines.extend(b.splines)
    a.quintics.extend(b.quintics)
    # programmed moves meet at the blend's middle (moves shorter than the cut end there)
    a.seg_u[-1] = mid
    k = len(a.seg_u) - 2
    while k >= 0 and a.seg_u[k] > mid:
        a.seg_u[k] = mid
        k -= 1
    a.seg_u += [max(u + offset, mid) for u in b.seg_u[1:]]
    a.seg_ids += b.seg_ids
    a.fit_dev = max(a.fit_dev, b.fit_dev)


def _chord_runs(path: Path, chain: list[int], turns: list[float]) -> list[list[int]]:
    """Runs of at least :data:`MICRO_RUN_MIN` consecutive lines of a chain, each shorter than
    :data:`CHORD_SEGMENT_M`, turning at most :data:`CORNER_ANGLE_RAD` between them."""
    segs = path.segments
    runs: list[list[int]] = []
    cur: list[int] = []
    for k, turn in zip(chain, turns):
        chord = isinstance(segs[k], Line) and segs[k].length < CHORD_SEGMENT_M
        if chord and cur and turn <= CORNER_ANGLE_RAD:
            cur.append(k)
            continue
        if len(cur) >= MICRO_RUN_MIN:
            runs.append(cur)
        cur = [k] if chord else []
    if len(cur) >= MICRO_RUN_MIN:
        runs.append(cur)
    return runs


def _fitted_corners(path: Path, chain: list[int], turns: list[float], fit_tol_m: float,
                    blending: Blending | None) -> set[int]:
    """The moves of a chain whose corner with the previous move lies inside a fit: between
    two micro-segments turning at most :data:`CORNER_ANGLE_RAD` or (under blending) whose
    common vertex lies within ``fit_tol_m`` of the chord joining their other ends (dropped,
    it would leave the polyline within the fit's tolerance: a jitter of the CAM's rounding,
    not a corner), and (under blending) inside a run of chords (:func:`_chord_runs`)."""
    segs = path.segments
    out = set()
    for j, k, turn in zip(chain, chain[1:], turns[1:]):
        if not (_is_micro(segs[j]) and _is_micro(segs[k])):
            continue
        if turn <= CORNER_ANGLE_RAD or (blending is not None and point_segment_distance(
                segs[j].end, segs[j].start, segs[k].end) <= fit_tol_m):
            out.add(k)
    if blending is None:
        return out
    for run in _chord_runs(path, chain, turns):
        out.update(run[1:])
    return out


def _chain_blocks(path: Path, chain: list[int], turns: list[float], fit_tol_m: float,
                  blending: Blending | None) -> list[Block]:
    """Blocks of one chain of feed moves.

    Corners above :data:`BLEND_MIN_TURN_RAD` are blended (unless inside a fitted run,
    :func:`_fitted_corners`); where no blend keeps within the tolerance at speed, a kink up to
    :data:`CORNER_ANGLE_RAD` is passed as it is, a sharper corner is an exact stop. A vertex
    where a fit splits is blended like a corner, or an exact stop where no blend will do.
    """
    fitted = _fitted_corners(path, chain, turns, fit_tol_m, blending)
    runs: list[list[int]] = [[chain[0]]]
    into: list[float] = [0.0]  # turn into each run
    for k, turn in zip(chain[1:], turns[1:]):
        if k not in fitted and (turn > CORNER_ANGLE_RAD or (
            turn > BLEND_MIN_TURN_RAD and _blendable(path, k - 1, blending))):
            runs.append([k])
            into.append(turn)
        else:
            runs[-1].append(k)
    blocks: list[Block] = []
    cur: _CurveBuilder | None = None
    for run, turn in zip(runs, into):
        for i, (part, stop) in enumerate(_pieces(path, run, fit_tol_m, fitted, blending)):
            if cur is None:
                cur = part
                continue
            if i == 0:  # a corner between runs: blended, or a kink, or an exact stop
                blend = _blend(cur, part, path, blending)
                keep = blend is not None or turn <= CORNER_ANGLE_RAD
            else:  # a fit's split (blended or an exact stop) or a joint (blended or kept)
                blend = (_blend(cur, part, path, blending)
                         if _blendable(path, cur.seg_ids[-1], blending)
                         and (stop or _costly_joint(cur, part, path, blending))
                         else None)
                keep = blend is not None or not stop
            if keep:
                _merge(cur, part, blend)
            else:
                blocks.append(cur.block())
                cur = part
    blocks.append(cur.block())
    return blocks


def blocks_of(path: Path, fit_tol_m: float, blending: Blending | None = None) -> list[Block]:
    """Cut a path into rest-to-rest blocks of smooth geometry.

    Parameters
    ----------
    path : Path
        The programmed moves; moves of zero length are skipped.
    fit_tol_m : float
        Deviation allowed to the spline fits of micro-segment runs, metres.
    blending : Blending, optional
        How corners are blended; none: every corner above :data:`CORNER_ANGLE_RAD` is an
        exact stop, as under G61.

    Returns
    -------
    list of Block
        In program order; consecutive blocks meet at rest at a programmed point.
    """
    out: list[Block] = []
    feed: list[int] = []

    def flush() -> None:
        for chain, turns in _feed_chains(path, feed, blending):
            out.extend(_chain_blocks(path, chain, turns, fit_tol_m, blending))

    for k, seg in enumerate(path.segments):
        if seg.length <= 1e-12:
            continue
        if not seg.rapid:
            feed.append(k)
            continue
        flush()
        feed = []
        b = _CurveBuilder()
        b.line(seg.start, seg.end)
        out.append(Block(b.build(), True, np.array([k]), np.array([0.0, seg.length]), 0.0))
    flush()
    return out
