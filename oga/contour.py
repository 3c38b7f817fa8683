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
"""

from __future__ import annotations

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
    "ce_at",
    "path_index",
    "contour_error",
    "contour_error_of",
    "plane_axes",
]

#: Segments whose squared length (m^2) is at most this (1e-15 m) count as standing still.
_MIN_SEG2_M2 = 1e-30


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
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
    bi, bt, best = nearest_segment(pd, lo, hi, x, y, z)
    return _signed(pd, lo, hi, x, y, z, e1, e2, signed, bi, bt, best)


@njit(cache=True)
def _signed(pd, lo, hi, x, y, z, e1, e2, signed, bi, bt, best):
    """:func:`ce_point` from the nearest segment ``(bi, bt, best)`` of the window ``lo..hi``."""
    if bi < 0:  # standing still over the whole window
        rx = x - pd[lo, 0]
        ry = y - pd[lo, 1]
        rz = z - pd[lo, 2]
        return np.sqrt(rx * rx + ry * ry + rz * rz)
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


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
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
    n = pd.shape[0]
    centre, radius, lo, hi = path_index(pd, window)
    out = np.empty(n)
    for k in range(n):
        out[k] = ce_at(pd, centre, radius, lo[k], hi[k], k, pa[k, 0], pa[k, 1], pa[k, 2], e1,
                       e2, signed)
    return out


@njit(cache=True)
def path_index(pd, window):
    """What :func:`ce_at` needs besides the path ``pd`` (N, 3): ``(centre, radius, lo, hi)``,
    a bounding sphere per block of segments and every sample's :func:`window_bounds`
    (int arrays, shape (N,))."""
    centre, radius = _block_spheres(pd)
    count = moving_count(pd)
    lo = np.searchsorted(count, count - window, side="left")
    hi = np.searchsorted(count, count + window, side="right") - 1
    return centre, radius, lo, hi


@njit(cache=True)
def ce_at(pd, centre, radius, lo, hi, k, x, y, z, e1, e2, signed):
    """Contour error (m) of the point ``(x, y, z)`` (m) taken at sample ``k``, as in
    :func:`ce_series`; ``centre, radius`` and the window ``lo, hi`` of sample ``k``
    from :func:`path_index`."""
    bi, bt, best = _nearest_pruned(pd, centre, radius, lo, hi, k, x, y, z)
    return _signed(pd, lo, hi, x, y, z, e1, e2, signed, bi, bt, best)


#: Segments per block of :func:`_block_spheres`.
_BLOCK = 16


@njit(cache=True)
def _block_spheres(pd):
    """A sphere around each block of ``_BLOCK`` consecutive segments (their vertices).

    Returns ``(centre (B, 3), radius (B,))`` with block ``b`` holding the segments
    ``b * _BLOCK .. (b + 1) * _BLOCK - 1``. The radius is enlarged by a relative
    1e-9 and 1e-12 m, far above rounding, so the distance bound it gives is safe.
    """
    n_seg = max(pd.shape[0] - 1, 0)
    nb = (n_seg + _BLOCK - 1) // _BLOCK
    centre = np.empty((nb, 3))
    radius = np.empty(nb)
    for b in range(nb):
        i0 = b * _BLOCK
        i1 = min(i0 + _BLOCK, n_seg)  # last vertex of the block
        for a in range(3):
            lo_a = pd[i0, a]
            hi_a = pd[i0, a]
            for i in range(i0 + 1, i1 + 1):
                lo_a = min(lo_a, pd[i, a])
                hi_a = max(hi_a, pd[i, a])
            centre[b, a] = 0.5 * (lo_a + hi_a)
        r2 = 0.0
        for i in range(i0, i1 + 1):
            dx = pd[i, 0] - centre[b, 0]
            dy = pd[i, 1] - centre[b, 1]
            dz = pd[i, 2] - centre[b, 2]
            r2 = max(r2, dx * dx + dy * dy + dz * dz)
        radius[b] = np.sqrt(r2) * (1.0 + 1e-9) + 1e-12
    return centre, radius


@njit(cache=True)
def _nearest_pruned(pd, centre, radius, lo, hi, k, x, y, z):
    """:func:`nearest_segment` over ``lo..hi``, skipping blocks that provably hold no nearest segment.

    An upper bound of the least squared distance comes from the setpoint ``pd[k]``
    (a point of the path, where a moving segment of the window ends) and from the
    segments of the block holding vertex ``k``; a block whose sphere lies farther
    than the bound cannot hold the minimum and is skipped. The others are scanned in
    index order with the same strict comparison as :func:`nearest_segment`, so the
    answer is the same: the first segment with the least distance. Should the
    bound not be met (``pd[k]`` on no moving segment of the window), every block is
    scanned.
    """
    if hi <= lo:
        return -1, 0.0, np.inf
    kc = min(max(k, lo), hi)
    bound = (x - pd[kc, 0]) ** 2 + (y - pd[kc, 1]) ** 2 + (z - pd[kc, 2]) ** 2
    kb = min(kc, hi - 1) // _BLOCK
    _j, _t, d2 = nearest_segment(pd, max(lo, kb * _BLOCK), min(hi, (kb + 1) * _BLOCK), x, y, z)
    bound = min(bound, d2)
    best = np.inf
    bi = -1
    bt = 0.0
    reach = np.sqrt(bound)
    for b in range(lo // _BLOCK, (hi - 1) // _BLOCK + 1):
        dx = x - centre[b, 0]
        dy = y - centre[b, 1]
        dz = z - centre[b, 2]
        far = radius[b] + reach  # the sphere lies beyond the bound (no square root per block)
        if dx * dx + dy * dy + dz * dz > far * far:
            continue
        j, t, d2 = nearest_segment(pd, max(lo, b * _BLOCK), min(hi, (b + 1) * _BLOCK), x, y, z)
        if d2 < best:
            best = d2
            bi = j
            bt = t
            if d2 < bound:
                bound = d2
                reach = np.sqrt(d2)
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
    pd = np.ascontiguousarray(setpoints_pos, dtype=np.float64)
    pa = np.ascontiguousarray(actual_pos, dtype=np.float64)
    if pd.ndim != 2 or pd.shape[1:] != (3,) or pa.shape != pd.shape:
        raise InputError(
            f"contour_error: setpoints_pos {pd.shape} and actual_pos {pa.shape} "
            "must both have shape (N, 3)"
        )
    if not (np.isfinite(pd).all() and np.isfinite(pa).all()):
        raise InputError("contour_error: positions must be finite")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise OptionError(f"window: must be an integer >= 1 (samples), got {window!r}")
    e1, e2, signed = plane_axes(plane)
    return ce_series(pd, pa, int(window), e1, e2, signed)


def contour_error_of(
    setpoints: Setpoints, actual_pos: np.ndarray, *, window: int = CE_WINDOW_SAMPLES
) -> np.ndarray:
    """:func:`contour_error` of ``actual_pos`` (N, 3) against ``setpoints.pos`` in its plane."""
    return contour_error(setpoints.pos, actual_pos, setpoints.plane, window=window)
