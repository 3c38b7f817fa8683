"""Contour error (paper eq. 1): signed shortest distance from the actual point to the path.

The desired path is the polyline through the setpoints ``pd[0], pd[1], ...``.
For sample ``k`` the actual point ``pa[k]`` is compared with the segments
``pd[i] pd[i+1]`` whose indices lie in a window around ``k`` only (``window``
moving segments each side; standing-still samples do not count), so a path
that comes back near itself is never confused with its other passes, and the
cost per sample is bounded.

Sign
----
For a planar path (plane ``"xy"``, ``"zx"`` or ``"yz"``, see
:data:`feedplan.path.PLANES`) the contour error is positive to the LEFT of the
direction of travel in the plane's own orientation, i.e. on the side of
``normal x tangent``; for a non-planar path (plane ``None``) it is unsigned
(>= 0). The distance itself is always the 3-D distance.

Where the nearest point of the path is a vertex (a corner), the side is taken
from the sum of the unit directions of the non-degenerate segments entering
and leaving that vertex (the 2-D pseudo-normal), which is consistent on both
sides of a corner, even a sharp reversal. Zero-length segments (the path
standing still, repeated setpoints at start and end) have no direction and
are skipped: their point is shared with the neighbouring moving segments.

Speed
-----
:func:`ce_series` (and :func:`ce_at` in other compiled loops) finds each sample's
nearest segment from the previous sample's: an index of the path
(:func:`path_index`: bounding spheres and clearances of segments, leaves of 4 and
blocks of 16) proves that no other segment of the window can be nearer, usually by
looking at three segments. The answer is exactly that of the plain scan of
:func:`nearest_segment` over the window (the same segment, the same bits).
"""

from __future__ import annotations

import weakref

import numpy as np
from numba import njit

from feedplan.path import PLANES
from feedplan.setpoints import Setpoints
from oga.defaults import CE_WINDOW_SAMPLES
from oga.errors import InputError, OptionError

__all__ = [
    "nearest_segment",
    "ce_point",
    "moving_count",
    "window_bounds",
    "ce_series",
    "ce_indexed",
    "ce_at",
    "ce2_at",
    "nearest_at",
    "path_index",
    "contour_error",
    "contour_error_of",
    "plane_axes",
]

#: Segments whose squared length (m^2) is at most this (1e-15 m) count as standing still.
_MIN_SEG2_M2 = 1e-30


@njit(cache=True, nogil=True)
def _travel_dir(pd, j, stop, step):
    """Unit travel direction of the first moving segment next to vertex ``j``.

    Walks from vertex ``j`` by ``step`` (+1: the segment leaving ``j``; -1: the
    segment entering it) up to vertex ``stop``, skipping zero-length segments.
    Returns ``(dx, dy, dz)``, all zero when no moving segment is found.
    """
    a = j
    while a != stop:
        b = a + step
        dx = pd[b, 0] - pd[a, 0]
        dy = pd[b, 1] - pd[a, 1]
        dz = pd[b, 2] - pd[a, 2]
        l2 = dx * dx + dy * dy + dz * dz
        if l2 > _MIN_SEG2_M2:
            inv = step / np.sqrt(l2)
            return dx * inv, dy * inv, dz * inv
        a = b
    return 0.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def nearest_segment(pd, lo, hi, x, y, z):
    """Nearest moving segment of the polyline ``pd[lo..hi]`` to the point (x, y, z).

    Usable from other ``@njit`` code (no allocation). Zero-length segments are skipped.

    Parameters
    ----------
    pd : ndarray, shape (N, 3), float64
        Polyline vertices (setpoints), metres.
    lo, hi : int
        First and last vertex index of the window, ``0 <= lo <= hi < N``; the
        segments searched are ``pd[i] pd[i+1]`` for ``lo <= i < hi``.
    x, y, z : float
        The point, metres.

    Returns
    -------
    i : int
        Index of the segment ``pd[i] pd[i+1]``; -1 if every segment of the window
        has zero length (the path stands still).
    t : float
        Parameter in [0, 1] of the nearest point ``pd[i] + t (pd[i+1] - pd[i])``.
    d2 : float
        Squared distance, m^2 (``inf`` when ``i == -1``).
    """
    best = np.inf
    bi = -1
    bt = 0.0
    for i in range(lo, hi):
        dx = pd[i + 1, 0] - pd[i, 0]
        dy = pd[i + 1, 1] - pd[i, 1]
        dz = pd[i + 1, 2] - pd[i, 2]
        l2 = dx * dx + dy * dy + dz * dz
        if l2 <= _MIN_SEG2_M2:
            continue
        wx = x - pd[i, 0]
        wy = y - pd[i, 1]
        wz = z - pd[i, 2]
        t = (wx * dx + wy * dy + wz * dz) / l2
        if t < 0.0:
            t = 0.0
        elif t > 1.0:
            t = 1.0
        rx = wx - t * dx
        ry = wy - t * dy
        rz = wz - t * dz
        d2 = rx * rx + ry * ry + rz * rz
        if d2 < best:
            best = d2
            bi = i
            bt = t
    return bi, bt, best


@njit(cache=True, nogil=True)
def ce_point(pd, lo, hi, x, y, z, e1, e2, signed):
    """Contour error of one point against the polyline ``pd[lo..hi]``.

    Usable from other ``@njit`` code (no allocation).

    Parameters
    ----------
    pd : ndarray, shape (N, 3), float64
        Desired positions (setpoints), metres.
    lo, hi : int
        First and last vertex index of the window, ``0 <= lo <= hi < N``; the
        segments searched are ``pd[i] pd[i+1]`` for ``lo <= i < hi``.
    x, y, z : float
        The actual point, metres.
    e1, e2 : int
        Axis indices of the plane's (e1, e2) (see :data:`feedplan.path.PLANES`);
        ignored when ``signed`` is False.
    signed : bool
        True: positive to the left of travel in the plane; False: unsigned.

    Returns
    -------
    float
        Contour error in metres. If every segment of the window has zero length
        (the path stands still), the distance to ``pd[lo]``, positive.
    """
    return _signed(pd, lo, hi, x, y, z, (e1, e2, signed), nearest_segment(pd, lo, hi, x, y, z))


@njit(cache=True, inline="always")
def _point_d2(pd, i, x, y, z):
    """Squared distance (m^2) from the point (x, y, z) to the vertex ``pd[i]``."""
    rx = x - pd[i, 0]
    ry = y - pd[i, 1]
    rz = z - pd[i, 2]
    return rx * rx + ry * ry + rz * rz


@njit(cache=True, nogil=True)
def _signed(pd, lo, hi, x, y, z, axes, near):
    """:func:`ce_point` from the nearest segment ``near = (i, t, d2)`` of the window ``lo..hi``
    (:func:`nearest_segment`), ``axes = (e1, e2, signed)``."""
    bi, bt, best = near
    e1, e2, signed = axes
    if bi < 0:  # standing still over the whole window
        return np.sqrt(_point_d2(pd, lo, x, y, z))
    dist = np.sqrt(best)
    if not signed or dist == 0.0:
        return dist
    # the nearest point q and the in-plane travel direction there
    if bt == 0.0 or bt == 1.0:
        j = bi if bt == 0.0 else bi + 1
        ix, iy, iz = _travel_dir(pd, j, lo, -1)  # entering the vertex
        ox, oy, oz = _travel_dir(pd, j, hi, 1)  # leaving it
        tx = ix + ox
        ty = iy + oy
        tz = iz + oz
        qx = pd[j, 0]
        qy = pd[j, 1]
        qz = pd[j, 2]
    else:
        tx = pd[bi + 1, 0] - pd[bi, 0]
        ty = pd[bi + 1, 1] - pd[bi, 1]
        tz = pd[bi + 1, 2] - pd[bi, 2]
        qx = pd[bi, 0] + bt * tx
        qy = pd[bi, 1] + bt * ty
        qz = pd[bi, 2] + bt * tz
    t3 = (tx, ty, tz)
    r3 = (x - qx, y - qy, z - qz)
    # left of travel: (normal x t) . r = t_e1 * r_e2 - t_e2 * r_e1
    side = t3[e1] * r3[e2] - t3[e2] * r3[e1]
    return -dist if side < 0.0 else dist


@njit(cache=True, nogil=True)
def moving_count(pd):
    """Prefix count of moving (non-zero-length) segments: ``c[i]`` = those before vertex ``i``.

    Parameters
    ----------
    pd : ndarray, shape (N, 3), float64
        Polyline vertices, metres.

    Returns
    -------
    ndarray of int64, shape (N,)
        Non-decreasing; ``c[0] = 0``.
    """
    n = pd.shape[0]
    c = np.zeros(n, dtype=np.int64)
    for i in range(n - 1):
        dx = pd[i + 1, 0] - pd[i, 0]
        dy = pd[i + 1, 1] - pd[i, 1]
        dz = pd[i + 1, 2] - pd[i, 2]
        c[i + 1] = c[i] + (dx * dx + dy * dy + dz * dz > _MIN_SEG2_M2)
    return c


@njit(cache=True, nogil=True)
def window_bounds(count, k, window):
    """Vertex window ``(lo, hi)`` around sample ``k`` holding ``window`` moving segments each side.

    Standing-still samples (zero-length segments) do not use up the window, so a
    lag that persists while the setpoints wait (at the end of the path, at an
    exact stop) still reaches the last moving segments.

    Parameters
    ----------
    count : ndarray of int64, shape (N,)
        From :func:`moving_count`.
    k : int
        Sample index.
    window : int
        Moving segments searched before and after vertex ``k``.

    Returns
    -------
    (int, int)
        First and last vertex index for :func:`ce_point` / :func:`nearest_segment`.
    """
    lo = np.searchsorted(count, count[k] - window, side="left")
    hi = np.searchsorted(count, count[k] + window, side="right") - 1
    return lo, hi


@njit(cache=True, nogil=True)
def _windows(count, window):
    """:func:`window_bounds` of every sample, ``(lo, hi)`` int arrays of shape (N,), in one
    merge-like pass (``count`` and so both bounds are non-decreasing in ``k``)."""
    n = count.shape[0]
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    a = 0  # first index with count >= count[k] - window
    b = 0  # first index with count > count[k] + window
    for k in range(n):
        while a < n and count[a] < count[k] - window:
            a += 1
        while b < n and count[b] <= count[k] + window:
            b += 1
        lo[k] = a
        hi[k] = b - 1
    return lo, hi


@njit(cache=True, nogil=True)
def ce_series(pd, pa, window, e1, e2, signed):
    """Contour error of every sample ``pa[k]`` against ``pd`` near ``k``.

    Parameters
    ----------
    pd, pa : ndarray, shape (N, 3), float64
        Desired and actual positions, metres.
    window : int
        Moving segments searched before and after sample ``k`` (:func:`window_bounds`).
    e1, e2 : int
        Plane axes (see :func:`ce_point`).
    signed : bool
        Signed (planar path) or unsigned.

    Returns
    -------
    ndarray, shape (N,)
        Contour error in metres.
    """
    tree, lo, hi = path_index(pd, window)
    return ce_indexed(pd, pa, tree, lo, hi, e1, e2, signed)


@njit(cache=True, nogil=True)
def ce_indexed(pd, pa, tree, lo, hi, e1, e2, signed):
    """:func:`ce_series` with the path's index given: ``(tree, lo, hi)`` of
    :func:`path_index` (built once per path, used by every run on it)."""
    n = pd.shape[0]
    out = np.empty(n)
    near = -1
    axes = (e1, e2, signed)
    for k in range(n):
        out[k], near = ce_at(pd, tree, lo[k], hi[k], k, pa[k, 0], pa[k, 1], pa[k, 2], axes, near)
    return out


@njit(cache=True, nogil=True)
def path_index(pd, window):
    """What :func:`ce_at` needs besides the path: ``(tree, lo, hi)``.

    Parameters
    ----------
    pd : ndarray, shape (N, 3), float64
        Polyline vertices (setpoints), metres.
    window : int
        Moving segments searched before and after each sample (:func:`window_bounds`).

    Returns
    -------
    tree : tuple
        ``(segs, leaves, blocks, span)``: per segment, per leaf of ``_LEAF`` segments
        and per block of ``_BLOCK`` segments, a bounding sphere and a clearance, arrays of
        shape (n, 5) holding the centre, the radius and the clearance, metres
        (:func:`_spheres`, :func:`_clearance`); ``span`` (int) the block distance the
        clearances cover.
    lo, hi : ndarray of int64, shape (N,)
        Every sample's :func:`window_bounds`.
    """
    lo, hi = _windows(moving_count(pd), window)
    span = 0  # blocks between the first and the last block of a sample's window
    for k in range(pd.shape[0]):
        if hi[k] > lo[k]:
            span = max(span, (hi[k] - 1) // _BLOCK - lo[k] // _BLOCK)
    span = min(span, _CLEAR_BLOCKS)
    blocks = _spheres(pd, _BLOCK)
    _clearance(blocks, blocks[:0], span)
    leaves = _spheres(pd, _LEAF)
    _clearance(leaves, blocks, 2 * _FAN - 1)
    segs = _spheres(pd, 1)
    _clearance(segs, leaves, 2 * _FAN - 1)
    return (segs, leaves, blocks, span), lo, hi


@njit(cache=True, inline="always")
def ce_at(pd, tree, lo, hi, k, x, y, z, axes, hint):
    """Contour error of the point ``(x, y, z)`` taken at sample ``k``, as :func:`ce_series`.

    The result does not depend on ``hint``, only the time it takes: pass the segment
    this function returned for a nearby point (the previous sample's), or -1.

    Parameters
    ----------
    pd : ndarray, shape (N, 3), float64
        Desired positions (setpoints), metres.
    tree : tuple
        From :func:`path_index`.
    lo, hi : int
        Window of sample ``k`` from :func:`path_index`.
    k : int
        Sample index.
    x, y, z : float
        The actual point, metres.
    axes : (int, int, bool)
        ``(e1, e2, signed)``: plane axes and signing (see :func:`ce_point`,
        :func:`plane_axes`).
    hint : int
        A segment index likely to be the nearest (any value is safe), -1 for none.

    Returns
    -------
    ce : float
        Contour error, metres (as :func:`ce_point` over ``lo..hi``).
    i : int
        The nearest segment (the first of least distance, as :func:`nearest_segment`),
        -1 if the window stands still: the hint for the next sample.
    """
    near = nearest_at(pd, tree, lo, hi, k, x, y, z, hint)
    return _signed(pd, lo, hi, x, y, z, axes, near), near[0]


@njit(cache=True, inline="always")
def ce2_at(pd, tree, lo, hi, k, x, y, z, hint):
    """Squared contour error of the point ``(x, y, z)`` taken at sample ``k``, cheaper than
    squaring :func:`ce_at` (no sign, no square root).

    The squared distance that :func:`ce_at` takes the root of: ``ce_at(...)[0] ** 2``
    up to the rounding of the root and the square (2 ulp). Arguments as :func:`ce_at`.

    Returns
    -------
    ce2 : float
        Squared contour error, m^2.
    i : int
        The nearest segment as :func:`ce_at` returns it (the hint for the next sample).
    """
    bi, _bt, best = nearest_at(pd, tree, lo, hi, k, x, y, z, hint)
    if bi < 0:  # standing still over the whole window
        return _point_d2(pd, lo, x, y, z), bi
    return best, bi


#: Nodes per node of the next level of the path index: level 0 the segments, level 1
#: the leaves of ``_LEAF`` segments, level 2 the blocks of ``_BLOCK`` segments.
_FAN = 4
_LEAF = _FAN
_BLOCK = _FAN * _FAN
#: Largest block distance the clearances cover (bounds their cost on long windows).
_CLEAR_BLOCKS = 64
#: Relative and absolute (m) enlargement of every sphere and shrinking of every
#: clearance: far above the rounding of the distances compared, so every test is safe.
_REL = 1e-9
_ABS = 1e-12


@njit(cache=True, nogil=True)
def _spheres(pd, size):
    """A sphere around each run of ``size`` consecutive segments (their vertices).

    Returns an array of shape (B, 5): centre (3), radius, and a clearance column (set by
    :func:`_clearance`), metres; row ``b`` holds the segments ``b * size .. (b + 1) *
    size - 1``. The radius is enlarged by ``_REL`` and ``_ABS``, so the distance bound
    it gives is safe.
    """
    n_seg = max(pd.shape[0] - 1, 0)
    nb = (n_seg + size - 1) // size
    out = np.empty((nb, 5))
    for b in range(nb):
        i0 = b * size
        i1 = min(i0 + size, n_seg)  # last vertex of the run
        for a in range(3):
            lo_a = pd[i0, a]
            hi_a = pd[i0, a]
            for i in range(i0 + 1, i1 + 1):
                lo_a = min(lo_a, pd[i, a])
                hi_a = max(hi_a, pd[i, a])
            out[b, a] = 0.5 * (lo_a + hi_a)
        r2 = 0.0
        for i in range(i0, i1 + 1):
            r2 = max(r2, _point_d2(pd, i, out[b, 0], out[b, 1], out[b, 2]))
        out[b, 3] = np.sqrt(r2) * (1.0 + _REL) + _ABS
        out[b, 4] = np.inf
    return out


@njit(cache=True, nogil=True)
def _clearance(nodes, parent, reach):
    """Fill ``nodes[:, 4]`` with each node's clearance, metres.

    The clearance of node ``a`` of a level is a lower bound of the distance from its
    segments to every segment of the path outside nodes ``a - 1 .. a + 1``, up to
    ``span`` blocks away (:func:`path_index`): a point within ``r`` of a segment of
    node ``a`` whose clearance exceeds ``2 r`` is farther than ``r`` from all of them.
    Top level (the blocks, ``parent`` empty): from the spheres of the blocks 2 to
    ``reach`` away. Lower levels (``parent`` the level above, already filled, and
    ``reach = 2 _FAN - 1``): the parent's clearance (the segments outside the parent
    and its two neighbours), lowered with the spheres of the nodes 2 or more away
    inside those three parents. Shrunk by ``_REL`` and ``_ABS``; ``inf`` when there is
    no such segment, 0 when one touches.
    """
    n = nodes.shape[0]
    top = parent.shape[0] == 0
    if not top:
        for a in range(n):
            nodes[a, 4] = parent[a // _FAN, 4]
    for d in range(2, reach + 1):  # nearest first: most farther pairs skip the root
        for a in range(n - d):
            b = a + d
            if not top and b // _FAN - a // _FAN > 1:
                continue
            ra = nodes[a, 3] + nodes[b, 3]
            cut = max(nodes[a, 4], nodes[b, 4]) + ra
            d2 = _point_d2(nodes, a, nodes[b, 0], nodes[b, 1], nodes[b, 2])
            if d2 >= cut * cut:  # lowers neither clearance
                continue
            g = np.sqrt(d2) - ra
            nodes[a, 4] = min(nodes[a, 4], g)
            nodes[b, 4] = min(nodes[b, 4], g)
    for a in range(n):
        g = nodes[a, 4]
        nodes[a, 4] = g * (1.0 - _REL) - _ABS if g > 0.0 else 0.0


@njit(cache=True, inline="always")
def _scan_leaves(pd, segs, leaves, a0, a1, lo, hi, p, near):
    """Fold the segments of leaves ``a0 .. a1`` in the window ``lo..hi`` into the nearest so
    far ``near = (bound, bi, bt, best)``, in index order with :func:`nearest_segment`'s strict
    comparison; ``p = (x, y, z)`` the point, metres.

    A leaf, and inside a leaf a segment, whose sphere lies farther than ``sqrt(bound)`` (an
    upper bound of the least squared distance, lowered by every distance found) is skipped
    (no distance computed: it cannot be the nearest). Returns ``(bound, bi, bt, best)``.
    """
    x, y, z = p
    bound, bi, bt, best = near
    reach = np.sqrt(bound)
    for a in range(max(a0, lo // _LEAF), min(a1, (hi - 1) // _LEAF) + 1):
        far = leaves[a, 3] + reach
        if _point_d2(leaves, a, x, y, z) > far * far:  # no root per leaf
            continue
        for i in range(max(lo, a * _LEAF), min(hi, (a + 1) * _LEAF)):
            far = segs[i, 3] + reach
            if _point_d2(segs, i, x, y, z) > far * far:
                continue
            j, t, d2 = nearest_segment(pd, i, i + 1, x, y, z)
            if d2 < best:
                best = d2
                bi = j
                bt = t
                if d2 < bound:
                    bound = d2
                    reach = np.sqrt(d2)
    return bound, bi, bt, best


@njit(cache=True, nogil=True)
def _scan_blocks(pd, segs, leaves, blocks, b0, b1, lo, hi, p, bound):
    """:func:`_scan_leaves` over the blocks ``b0 .. b1`` whose sphere lies within
    ``sqrt(bound)`` of the point; returns ``(bound, bi, bt, best)``."""
    x, y, z = p
    bi = -1
    bt = 0.0
    best = np.inf
    reach = np.sqrt(bound)
    for b in range(max(b0, lo // _BLOCK), min(b1, (hi - 1) // _BLOCK) + 1):
        far = blocks[b, 3] + reach
        if _point_d2(blocks, b, x, y, z) > far * far:
            continue
        was = bound
        bound, bi, bt, best = _scan_leaves(pd, segs, leaves, b * _FAN, (b + 1) * _FAN - 1, lo,
                                           hi, p, (bound, bi, bt, best))
        if bound < was:
            reach = np.sqrt(bound)
    return bound, bi, bt, best


@njit(cache=True, inline="always")
def nearest_at(pd, tree, lo, hi, k, x, y, z, hint):
    """:func:`nearest_segment` over ``lo..hi``, scanning only the segments that may be nearest.

    The nearest segment the contour error of sample ``k`` is measured against: returns
    ``(i, t, d2)`` exactly as ``nearest_segment(pd, lo, hi, x, y, z)`` (``tree``, ``lo``,
    ``hi`` from :func:`path_index`; ``hint`` as in :func:`ce_at`).

    With a ``hint`` segment of the window at distance ``r``: at the lowest level
    (segment, leaf, block) where the clearance of the hint's node exceeds ``2 r`` (and
    covers the window), every segment of the window outside that node and the two
    next to it is farther than ``r`` (:func:`_clearance`), and only those are
    scanned. Otherwise every block of the window is, with an upper bound of the least
    squared distance from the hint, from the setpoint ``pd[k]`` (a point of the path,
    where a moving segment of the window ends) and, without a hint, from the block
    holding vertex ``k``. A block or leaf whose sphere lies farther than the bound
    cannot hold the minimum and is skipped; the others are scanned in index order
    with :func:`nearest_segment`'s strict comparison, so the answer is the same
    whatever the hint: the first segment with the least distance. Should the bound
    not be met (``pd[k]`` on no moving segment of the window), every segment is
    scanned.
    """
    if hi <= lo:
        return -1, 0.0, np.inf
    segs, leaves, blocks, span = tree
    kc = min(max(k, lo), hi)
    if lo <= hint < hi:
        _j, _t, d2 = nearest_segment(pd, hint, hint + 1, x, y, z)
        blk = hint // _BLOCK
        if d2 < np.inf and lo // _BLOCK >= blk - span and (hi - 1) // _BLOCK <= blk + span:
            far2 = 4.0 * d2 * (1.0 + _REL)
            if segs[hint, 4] ** 2 > far2:  # the hint or a segment next to it
                return nearest_segment(pd, max(lo, hint - 1), min(hi, hint + 2), x, y, z)
            leaf = hint // _LEAF
            if leaves[leaf, 4] ** 2 > far2:
                _b, bi, bt, best = _scan_leaves(pd, segs, leaves, leaf - 1, leaf + 1, lo, hi,
                                                (x, y, z), (d2, -1, 0.0, np.inf))
                return bi, bt, best
            if blocks[blk, 4] ** 2 > far2:
                _b, bi, bt, best = _scan_blocks(pd, segs, leaves, blocks, blk - 1, blk + 1, lo, hi,
                                                (x, y, z), d2)
                return bi, bt, best
    else:
        kb = min(kc, hi - 1) // _BLOCK
        _j, _t, d2 = nearest_segment(pd, max(lo, kb * _BLOCK), min(hi, (kb + 1) * _BLOCK),
                                     x, y, z)
    bound = min(_point_d2(pd, kc, x, y, z), d2)
    bound, bi, bt, best = _scan_blocks(pd, segs, leaves, blocks, 0, blocks.shape[0], lo, hi,
                                       (x, y, z), bound)
    if best > bound:  # the bound was not a distance to the window's path: no pruning
        return nearest_segment(pd, lo, hi, x, y, z)
    return bi, bt, best


def plane_axes(plane: str | None) -> tuple[int, int, bool]:
    """``(e1, e2, signed)`` for the kernels from a plane name or None (unsigned).

    Raises
    ------
    OptionError
        Unknown plane name.
    """
    if plane is None:
        return 0, 1, False
    try:
        e1, e2, _ = PLANES[plane]
    except KeyError:
        raise OptionError(
            f"plane: unknown plane {plane!r}; use one of {', '.join(PLANES)} or None"
        ) from None
    return e1, e2, True


def contour_error(
    setpoints_pos: np.ndarray,
    actual_pos: np.ndarray,
    plane: str | None,
    *,
    window: int = CE_WINDOW_SAMPLES,
) -> np.ndarray:
    """Contour error of every sample (paper eq. 1).

    Parameters
    ----------
    setpoints_pos : array_like, shape (N, 3)
        Desired positions pd (x, y, z), metres.
    actual_pos : array_like, shape (N, 3)
        Actual positions pa, metres.
    plane : {"xy", "zx", "yz"} or None
        Plane of the path: signed error, positive left of travel in the plane's
        orientation; None: unsigned.
    window : int, optional
        Half-width of the index window searched around each sample, counted in
        moving samples (standing-still samples are passed over); must exceed the
        tracking lag in samples (``|pd - pa| / (v Te)``), default
        :data:`oga.defaults.CE_WINDOW_SAMPLES`.

    Returns
    -------
    ndarray, shape (N,)
        Contour error in metres.

    Raises
    ------
    InputError
        Shapes differ or are not (N, 3), or values are not finite.
    OptionError
        Unknown plane or window < 1.
    """
    pd, pa, window = _inputs(setpoints_pos, actual_pos, window)
    return ce_series(pd, pa, window, *plane_axes(plane))


def _inputs(setpoints_pos, actual_pos, window, *, path_checked: bool = False):
    """The checked inputs of :func:`contour_error`: ``(pd, pa, window)`` as C-contiguous float64
    arrays and an int (``path_checked``: the setpoints were found finite before)."""
    pd = np.ascontiguousarray(setpoints_pos, dtype=np.float64)
    pa = np.ascontiguousarray(actual_pos, dtype=np.float64)
    if pd.ndim != 2 or pd.shape[1:] != (3,) or pa.shape != pd.shape:
        raise InputError(
            f"contour_error: setpoints_pos {pd.shape} and actual_pos {pa.shape} "
            "must both have shape (N, 3)"
        )
    if not ((path_checked or np.isfinite(pd).all()) and np.isfinite(pa).all()):
        raise InputError("contour_error: positions must be finite")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise OptionError(f"window: must be an integer >= 1 (samples), got {window!r}")
    return pd, pa, int(window)


def contour_error_of(
    setpoints: Setpoints, actual_pos: np.ndarray, *, window: int = CE_WINDOW_SAMPLES
) -> np.ndarray:
    """:func:`contour_error` of ``actual_pos`` (N, 3) against ``setpoints.pos`` in its plane.

    The same numbers; the path's index (:func:`path_index`) is built once per setpoints and
    window and kept while the setpoints live (they are frozen: their positions read-only).
    """
    memo = _INDEX.get(setpoints) if not setpoints.pos.flags.writeable else None
    pd, pa, window = _inputs(setpoints.pos, actual_pos, window, path_checked=bool(memo))
    axes = plane_axes(setpoints.plane)
    if memo is None:
        if setpoints.pos.flags.writeable:  # not frozen positions: nothing to keep
            return ce_series(pd, pa, window, *axes)
        memo = _INDEX[setpoints] = {}
    if window not in memo:
        memo[window] = path_index(pd, window)
    return ce_indexed(pd, pa, *memo[window], *axes)


#: The path index of :func:`contour_error_of` per setpoints (while they live) and window.
_INDEX: "weakref.WeakKeyDictionary[Setpoints, dict]" = weakref.WeakKeyDictionary()


@njit(cache=True, inline="always")
def contour_offset(pd, tree, lo, hi, k, ref, pos, hint, total):
    """The linearised contour error of the point ``pos`` (3,) at sample ``k``: its offset from
    the nearest path point and that segment's unit tangent.

    The segment is the one the replay measures against (:func:`nearest_at` over ``lo..hi``,
    ``hint`` as there); where the path stands still over the window (no segment), the offset
    is from vertex ``ref`` (a vertex of that window) and the tangent zero. Returns
    ``(j, total, dx, dy, dz, tx, ty, tz)``: the segment (-1: none), ``total`` plus the
    squared distance (m^2), the offset (m) and the tangent. The window search
    (:mod:`oga.search.window`) and the law's gradient (:mod:`oga.law.gradient`) share it.
    """
    j, t, d2 = nearest_at(pd, tree, lo, hi, k, pos[0], pos[1], pos[2], hint)
    if j < 0:
        dx = pos[0] - pd[ref, 0]
        dy = pos[1] - pd[ref, 1]
        dz = pos[2] - pd[ref, 2]
        total += dx ** 2
        total += dy ** 2
        total += dz ** 2
        return j, total, dx, dy, dz, 0.0, 0.0, 0.0
    total += d2
    sx = pd[j + 1, 0] - pd[j, 0]
    sy = pd[j + 1, 1] - pd[j, 1]
    sz = pd[j + 1, 2] - pd[j, 2]
    inv = 1.0 / np.sqrt(sx * sx + sy * sy + sz * sz)
    return (j, total, pos[0] - (pd[j, 0] + t * sx), pos[1] - (pd[j, 1] + t * sy),
            pos[2] - (pd[j, 2] + t * sz), sx * inv, sy * inv, sz * inv)
