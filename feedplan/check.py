"""Independent check of planned setpoints: limits by finite differences, exact geometry.

:func:`check_setpoints` measures what a controller would see: per-axis velocity,
acceleration and jerk as backward finite differences of the float64 positions
(``v_k = (p_k - p_{k-1}) / dt``, then ``a`` and ``j`` by further backward
differences; the machine is taken at rest before the first and after the last
sample), the path speed against the programmed feed of the move each sample belongs to
(its own source line's, where it lies on it: :func:`move_hint`, :func:`_sample_feeds`), and
the distance of every feed sample to the programmed lines and arcs (exact: distance to the
circle or helix, not to a chord). :func:`deviation_m` is the geometric part, shared with
the planner's check-and-slow-down loop.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.limits import AxisLimits
from feedplan.path import PLANES, Arc, Path, Segment
from feedplan.setpoints import AXES, Setpoints
from oga.defaults import TOL_M

__all__ = [
    "SPEED_MARGIN",
    "PlanCheck",
    "check_setpoints",
    "deviation_m",
    "finite_differences",
    "move_hint",
    "point_segment_distance",
    "segment_table",
]

#: Path speed allowed above the programmed feed, as a fraction (issue 2: 1.005 F).
SPEED_MARGIN = 0.005
#: Programmed moves searched on each side of the previous sample's nearest move.
_SEARCH_WINDOW = 64
#: Consecutive moves whose balls are tested together first (aligned on multiples of it).
_GROUP = 8
#: Moves on each side of the tracked one tested one by one before all the others at once.
_NEAR = 2
#: Largest distance of the first/last sample from the programmed start/end, metres.
_END_TOL_M = 1e-9

#: The programmed moves as arrays (:func:`segment_table`); a tuple, so compiled code takes it
#: as one argument.
SegmentTable = namedtuple("SegmentTable", "kind a b c ax geo rapid sphere groups ahead behind")


def segment_table(segments: tuple[Segment, ...] | list[Segment]) -> SegmentTable:
    """The programmed moves as arrays for :func:`deviation_m` (build once, measure often).

    Parameters
    ----------
    segments : sequence of Line or Arc

    Returns
    -------
    SegmentTable
        kind (n,) 0 line / 1 arc; start, end, centre (n, 3) m; plane axes (n, 3);
        radius m, start angle rad, sweep rad, rise m (n, 4); rapid flags (n,);
        a ball holding each move, centre and radius m (n, 4); balls holding groups of
        moves (:func:`_group_balls`) and, per move, those ahead and behind it in the
        search window (:func:`_window_balls`).
    """
    n = len(segments)
    arcs = np.fromiter((isinstance(s, Arc) for s in segments), np.bool_, n)
    kind = arcs.astype(np.int64)
    a = np.array([s.start for s in segments], dtype=np.float64).reshape(n, 3)
    b = np.array([s.end for s in segments], dtype=np.float64).reshape(n, 3)
    c = np.zeros((n, 3))
    ax = np.zeros((n, 3), np.int64)
    geo = np.zeros((n, 4))  # radius, start angle, sweep, rise
    rapid = np.fromiter((s.rapid for s in segments), np.bool_, n)
    # a ball holding the move: centre, radius
    length = np.fromiter((s.length for s in segments), np.float64, n)
    sphere = np.column_stack([0.5 * (a + b), 0.5 * length]).reshape(n, 4)
    for k in np.flatnonzero(arcs):
        s = segments[k]
        c[k] = s.center
        ax[k] = PLANES[s.plane]
        geo[k] = (s.radius, s.start_angle, s.sweep_rad, s.rise)
        if abs(s.sweep_rad) <= np.pi:
            mid = s.point(0.5)
            reach = max(np.linalg.norm(mid - s.start), np.linalg.norm(mid - s.end))
            reach += abs(s.rise)
        else:
            mid, reach = s.center, np.hypot(s.radius, s.rise) + abs(s.rise)
        sphere[k] = (*mid, reach)
    use = ~rapid
    groups = _group_balls(sphere, use)
    ahead = _window_balls(sphere, use, _NEAR + 1, _SEARCH_WINDOW)
    behind = _window_balls(sphere, use, -_SEARCH_WINDOW, -_NEAR - 1)
    return SegmentTable(kind, a, b, c, ax, geo, rapid, sphere, groups, ahead, behind)


@njit(cache=True)
def _psd(p0, p1, p2, a0, a1, a2, b0, b1, b2):
    """:func:`point_segment_distance` of scalars (no array views in hot loops)."""
    ab0, ab1, ab2 = b0 - a0, b1 - a1, b2 - a2
    ap0, ap1, ap2 = p0 - a0, p1 - a1, p2 - a2
    den = ab0 * ab0 + ab1 * ab1 + ab2 * ab2
    f = 0.0
    if den > 0.0:
        f = min(1.0, max(0.0, (ap0 * ab0 + ap1 * ab1 + ap2 * ab2) / den))
    d0, d1, d2 = ap0 - f * ab0, ap1 - f * ab1, ap2 - f * ab2
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(cache=True)
def point_segment_distance(p, a, b):
    """Distance (m) from point ``p`` to the straight segment ``a``-``b`` (each shape (3,))."""
    return _psd(p[0], p[1], p[2], a[0], a[1], a[2], b[0], b[1], b[2])


@njit(cache=True)
def _dist_arc(pos, k, s, a, b, c, ax, geo):
    """Distance of point pos[k] to arc s (rows read in place: no array views)."""
    i, j, n = ax[s, 0], ax[s, 1], ax[s, 2]
    radius, th0, sweep, rise = geo[s, 0], geo[s, 1], geo[s, 2], geo[s, 3]
    best = 1e300
    for q in range(2):  # the two ends (no tuple of arrays: it costs every caller)
        e = a if q == 0 else b
        d0, d1, d2 = pos[k, 0] - e[s, 0], pos[k, 1] - e[s, 1], pos[k, 2] - e[s, 2]
        best = min(best, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
    dx, dy = pos[k, i] - c[s, i], pos[k, j] - c[s, j]
    rho = np.hypot(dx, dy)
    span = abs(sweep)
    sgn = 1.0 if sweep >= 0.0 else -1.0
    delta = ((np.arctan2(dy, dx) - th0) * sgn) % (2.0 * np.pi)
    while delta <= span:
        zn = a[s, n] + rise * delta / span
        d = np.hypot(rho - radius, pos[k, n] - zn)
        if d < best:
            best = d
        delta += 2.0 * np.pi
    return best


@njit(cache=True)
def _line_dist(pos, k, s, a, b):
    """Distance of point pos[k] to line s (rows read in place: no array views)."""
    return _psd(pos[k, 0], pos[k, 1], pos[k, 2], a[s, 0], a[s, 1], a[s, 2],
                b[s, 0], b[s, 1], b[s, 2])


@njit(cache=True)
def _seg_dist(pos, k, s, kind, a, b, c, ax, geo):
    """Distance of point pos[k] to move s."""
    if kind[s] == 0:
        return _line_dist(pos, k, s, a, b)
    return _dist_arc(pos, k, s, a, b, c, ax, geo)


@njit(cache=True)
def _ball_of(sphere, use, first, last, out, row):
    """out[row] = a ball (centre, radius; m) holding the balls of the measured moves
    first..last, radius -inf if there is none. Centre: the middle of their bounding box;
    the radius has a margin of 1e-9 relative plus 1 nm over float rounding, so a point
    this ball is farther from than ``best`` is also farther from each of theirs."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for t in range(first, last + 1):
        if use[t]:
            for i in range(3):
                lo[i] = min(lo[i], sphere[t, i])
                hi[i] = max(hi[i], sphere[t, i])
    if not lo[0] <= hi[0]:
        out[row, 3] = -np.inf
        return
    for i in range(3):
        out[row, i] = 0.5 * (lo[i] + hi[i])
    r = 0.0
    for t in range(first, last + 1):
        if use[t]:
            e0 = sphere[t, 0] - out[row, 0]
            e1 = sphere[t, 1] - out[row, 1]
            e2 = sphere[t, 2] - out[row, 2]
            r = max(r, np.sqrt(e0 * e0 + e1 * e1 + e2 * e2) + sphere[t, 3])
    out[row, 3] = r * (1.0 + 1e-9) + 1e-9


@njit(cache=True)
def _group_balls(sphere, use):
    """Per :data:`_GROUP` consecutive moves (aligned), a ball holding those measured, shape
    (ceil(n / _GROUP), 4) (:func:`_ball_of`)."""
    n = sphere.shape[0]
    out = np.zeros(((n + _GROUP - 1) // _GROUP, 4))
    for g in range(out.shape[0]):
        _ball_of(sphere, use, g * _GROUP, min(n, (g + 1) * _GROUP) - 1, out, g)
    return out


@njit(cache=True)
def _window_balls(sphere, use, lo, hi):
    """Per move s, a ball holding the measured moves s + lo .. s + hi, shape (n, 4)
    (:func:`_ball_of`)."""
    n = sphere.shape[0]
    out = np.zeros((n, 4))
    for s in range(n):
        _ball_of(sphere, use, max(s + lo, 0), min(s + hi, n - 1), out, s)
    return out


@njit(cache=True)
def _far(pos, k, balls, i, best):
    """Ball i (centre, radius) cannot hold a point nearer to pos[k] than ``best``."""
    e0 = pos[k, 0] - balls[i, 0]
    e1 = pos[k, 1] - balls[i, 1]
    e2 = pos[k, 2] - balls[i, 2]
    return np.sqrt(e0 * e0 + e1 * e1 + e2 * e2) - balls[i, 3] >= best


@njit(cache=True)
def _track(pos, skip, hint, table, use, window):
    """:func:`deviation_m` of a :class:`SegmentTable` (``use``: its feed moves)."""
    kind, a, b, c, ax, geo = table.kind, table.a, table.b, table.c, table.ax, table.geo
    sphere, groups, ahead, behind = table.sphere, table.groups, table.ahead, table.behind
    n_pts, n_seg = pos.shape[0], kind.shape[0]
    # no arcs: the distance of lines alone (with the arc's code beside it, the compiled loop
    # computes parts of it for every line too: 15x slower)
    lines = not np.any(kind != 0)
    dist = np.zeros(n_pts)
    near = np.zeros(n_pts, np.int64)
    cur = 0
    while not use[cur]:
        cur += 1
    for k in range(n_pts):
        if hint[k] >= 0 and (k == 0 or hint[k] != hint[k - 1]):
            cur = hint[k]  # the sample's own move (its source line): the tracker starts there
        if skip[k]:
            near[k] = cur
            continue
        # true minimum over the window; the tracked move changes only for a gain
        # above 1 nm, looking forward first (retraced moves do not pull it back)
        if lines:
            best = _line_dist(pos, k, cur, a, b)
        else:
            best = _seg_dist(pos, k, cur, kind, a, b, c, ax, geo)
        held, arg = best, cur
        step = 1
        while step <= 2 * window:
            # past the _NEAR moves on either side: all the others at once, when none of
            # them can be nearer (as each would be passed below; the same result)
            if step == _NEAR + 1 and step <= window and _far(pos, k, ahead, cur, best):
                step = window + 1
                continue
            if step == window + _NEAR + 1 and _far(pos, k, behind, cur, best):
                break
            forward = step <= window
            s = cur + step if forward else cur + window - step
            # a whole group of moves inside the window, none of which can be nearer: each
            # would be passed by its own ball below (same order, same result)
            first = s if forward else s - _GROUP + 1
            last = first + _GROUP - 1
            if (first % _GROUP == 0 and first >= max(cur - window, 0)
                    and last <= min(cur + window, n_seg - 1) and (last < cur or first > cur)
                    and _far(pos, k, groups, first // _GROUP, best)):
                step += _GROUP
                continue
            step += 1
            if s < 0 or s >= n_seg or not use[s]:
                continue
            if _far(pos, k, sphere, s, best):
                continue  # cannot be nearer (and best <= held)
            if lines:
                d = _line_dist(pos, k, s, a, b)
            else:
                d = _seg_dist(pos, k, s, kind, a, b, c, ax, geo)
            best = min(best, d)
            if d < held - 1e-9:
                held, arg = d, s
        dist[k], near[k] = best, arg
        cur = arg
    return dist, near


@njit(cache=True)
def _dist_to(pos, move, kind, a, b, c, ax, geo):
    """Distance of each point pos[k] to its own move ``move[k]`` (inf where -1)."""
    out = np.full(pos.shape[0], np.inf)
    for k in range(pos.shape[0]):
        if move[k] >= 0:
            out[k] = _seg_dist(pos, k, move[k], kind, a, b, c, ax, geo)
    return out


def deviation_m(pos: np.ndarray, table: tuple, skip: np.ndarray | None = None,
                hint: np.ndarray | None = None):
    """Distance of each point to the programmed feed geometry, following the path.

    Parameters
    ----------
    pos : ndarray, shape (N, 3)
        Points in path order, metres.
    table : SegmentTable
        :func:`segment_table` of the programmed moves (rapids are not distance targets).
    skip : ndarray of bool, shape (N,), optional
        Points not measured (distance 0), e.g. rapid samples.
    hint : ndarray of int, shape (N,), optional
        The move each point belongs to, where known (-1 where not): where it changes, the
        tracking restarts there (:func:`move_hint`), so that a stretch retraced many times
        (back-and-forth passes) cannot leave the tracking behind.

    Returns
    -------
    dist : ndarray, shape (N,)
        Exact distance (m) to the nearest feed line or arc among the 64 moves on
        each side of the tracked move (helical arcs: distance to the helix point at
        the same angle, an upper bound).
    tracked : ndarray of int, shape (N,)
        The move each point is attributed to (index in the table): the previous
        point's move unless another is nearer by more than 1 nm, moves ahead
        tried first, so that a retraced stretch does not pull the tracking back.
    """
    skip = np.zeros(len(pos), np.bool_) if skip is None else np.asarray(skip, np.bool_)
    hint = (np.full(len(pos), -1, np.int64) if hint is None
            else np.ascontiguousarray(hint, dtype=np.int64))
    use = ~table.rapid
    if not use.any():
        return np.zeros(len(pos)), np.zeros(len(pos), np.int64)
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    return _track(pos, skip, hint, table, use, _SEARCH_WINDOW)


def move_hint(block: np.ndarray, rapid: np.ndarray, segments) -> np.ndarray:
    """Per sample, the feed move it belongs to by its source line (-1 where unknown).

    Samples and moves are both in program order: each run of feed samples with one source
    line (``block``) gets the first feed move of that line at or after the previous run's
    (a line's moves repeat in program order only through subroutines and loops). Rapid
    samples get -1.

    Parameters
    ----------
    block : ndarray of int, shape (N,)
        :attr:`Setpoints.block`.
    rapid : ndarray of bool, shape (N,)
        :attr:`Setpoints.rapid`.
    segments : sequence of Line or Arc
        The moves of the table the hint indexes.

    Returns
    -------
    ndarray of int, shape (N,)
    """
    hint = np.full(len(block), -1, np.int64)
    lines = np.fromiter((-1 if s.rapid else s.line for s in segments), np.int64, len(segments))
    feed = np.flatnonzero(~np.asarray(rapid, np.bool_))
    if not len(feed) or not len(lines):
        return hint
    runs = np.flatnonzero(np.diff(block[feed]) != 0) + 1
    starts = np.concatenate([[0], runs])
    ends = np.concatenate([runs, [len(feed)]])
    where: dict[int, np.ndarray] = {}  # line -> its feed moves, in order
    order = np.argsort(lines, kind="stable")
    keys, first = np.unique(lines[order], return_index=True)
    bounds = dict(zip(keys.tolist(), zip(first.tolist(), [*first[1:].tolist(), len(order)])))
    at = 0
    for lo, hi in zip(starts, ends):
        line = int(block[feed[lo]])
        if line not in bounds or line < 0:
            continue
        if line not in where:
            where[line] = order[slice(*bounds[line])]
        moves = where[line]
        k = int(np.searchsorted(moves, at))
        if k == len(moves):  # none ahead: the line's first move
            k = 0
        at = int(moves[k])
        hint[feed[lo:hi]] = at
    return hint


def finite_differences(pos: np.ndarray, dt: float):
    """Backward differences of positions held at rest before and after.

    Parameters
    ----------
    pos : ndarray, shape (N, 3)
        Positions, metres, sampled every ``dt`` seconds.
    dt : float
        Sample period, seconds.

    Returns
    -------
    vel, acc, jerk : ndarray, shape (N + 3, 3)
        m/s, m/s^2, m/s^3; row ``k`` ends at ``pos[k]`` (rows past N: the rest after the end).
    """
    p = np.concatenate([np.repeat(pos[:1], 3, axis=0), pos, np.repeat(pos[-1:], 3, axis=0)])
    v = np.diff(p, axis=0) / dt
    acc = np.diff(v, axis=0) / dt
    jerk = np.diff(acc, axis=0) / dt
    return v[2:], acc[1:], jerk


@dataclass(frozen=True)
class PlanCheck:
    """What the finite-difference and geometry check found.

    Attributes
    ----------
    max_vel_m_s, max_acc_m_s2, max_jerk_m_s3 : ndarray, shape (3,)
        Largest |v|, |a|, |j| per axis (x, y, z) by backward finite differences.
    vel_ratio, acc_ratio, jerk_ratio : ndarray, shape (3,)
        Those over the axis limits (``inf`` when an axis with limit 0 moves).
    speed_ratio : float
        Largest path speed of a feed sample over its programmed feed (or the override).
    max_deviation_m : float
        Largest distance of a feed sample to the programmed lines and arcs.
    start_error_m, end_error_m : float
        Distance of the first/last sample to the programmed start/end.
    ends_at_rest : bool
        The last three samples coincide (zero velocity and acceleration at the end).
    ok : bool
        Every requirement met.
    violations : tuple of str
        Each unmet requirement, in words.
    limits : AxisLimits
        The limits checked against.
    """

    max_vel_m_s: np.ndarray
    max_acc_m_s2: np.ndarray
    max_jerk_m_s3: np.ndarray
    vel_ratio: np.ndarray
    acc_ratio: np.ndarray
    jerk_ratio: np.ndarray
    speed_ratio: float
    max_deviation_m: float
    start_error_m: float
    end_error_m: float
    ends_at_rest: bool
    ok: bool
    violations: tuple[str, ...]
    limits: AxisLimits

    def axes_dict(self) -> dict[str, dict[str, float]]:
        """Per axis that may move or moved: its largest |v|, |a|, |j| and their limits (SI)."""
        lim = self.limits
        return {
            name: {
                "max_vel_m_s": float(self.max_vel_m_s[k]),
                "vmax_m_s": float(lim.vmax_m_s[k]),
                "max_acc_m_s2": float(self.max_acc_m_s2[k]),
                "amax_m_s2": float(lim.amax_m_s2[k]),
                "max_jerk_m_s3": float(self.max_jerk_m_s3[k]),
                "jmax_m_s3": float(lim.jmax_m_s3[k]),
            }
            for k, name in enumerate(AXES)
            if lim.present[k] or self.max_vel_m_s[k] > 0
        }


def _sample_feeds(pos, table, dist, near, hint, feed) -> np.ndarray:
    """The programmed feed (m/s) of each sample: that of the move it belongs to.

    That is its own move (``hint``: its source line's, :func:`move_hint`) where the sample
    lies on it as nearly as on any move (within 1 nm of ``dist``): so a stretch retraced at
    another feed (back-and-forth passes) cannot lend its feed. Elsewhere (the plan's corner
    blends and the boundary between two moves, smeared over the plan's averaging window) the
    sample follows the moves nearest to it: the fastest of the tracked move (``near``) and its
    own move's neighbours in the program, among those as near as ``dist``.
    """
    kind, a, b, c, ax, geo, rapid = table[:7]
    pc = np.ascontiguousarray(pos)
    allowed = feed[near]
    known = hint >= 0
    if not known.any():
        return allowed
    n = len(feed)
    for step in (-1, 1):
        move = np.where(known, hint + step, -1)
        move[(move < 0) | (move >= n)] = -1
        move[move >= 0] = np.where(rapid[move[move >= 0]], -1, move[move >= 0])
        on = _dist_to(pc, move, kind, a, b, c, ax, geo) <= dist + 1e-9
        allowed = np.where(on, np.maximum(allowed, feed[np.maximum(move, 0)]), allowed)
    own = _dist_to(pc, hint, kind, a, b, c, ax, geo) <= dist + 1e-9
    return np.where(own, feed[np.maximum(hint, 0)], allowed)


def _ratio(value: np.ndarray, limit: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        moving_absent = np.where(value > 0, np.inf, 0.0)
        return np.where(limit > 0, value / np.where(limit > 0, limit, 1.0), moving_absent)


def _feed_and_geometry(sp: Setpoints, path: Path, vel: np.ndarray, feed_m_s):
    """Largest path speed over the feed of each sample's move, largest distance of a feed
    sample to the programmed geometry (m), and the measured moves (longer than 1 pm)."""
    pos = sp.pos
    segs = [s for s in path.segments if s.length > 1e-12]
    table = segment_table(segs)
    hint = move_hint(sp.block, sp.rapid, segs)
    dist, near = deviation_m(pos, table, skip=sp.rapid, hint=hint)
    feed = np.array([np.inf if s.rapid else (feed_m_s or s.feed_m_s) for s in segs] or [np.inf])
    speed = np.linalg.norm(vel[: len(pos)], axis=1)
    fs = ~sp.rapid
    allowed = _sample_feeds(pos, table, dist, near, hint, feed)
    speed_ratio = float((speed[fs] / allowed[fs]).max()) if fs.any() else 0.0
    max_dev = float(dist[fs].max()) if fs.any() else 0.0
    return speed_ratio, max_dev, segs


def _limit_violations(ratios, maxima) -> list[str]:
    """A sentence per axis and quantity (velocity, acceleration, jerk) above its limit."""
    bad: list[str] = []
    for name, r, m, unit in zip(("velocity", "acceleration", "jerk"), ratios, maxima,
                                ("m/s", "m/s^2", "m/s^3")):
        for k in np.flatnonzero(r > 1.0):
            bad.append(f"axis {AXES[k]} {name} {m[k]:.6g} {unit} is {r[k]:.4f} x its limit")
    return bad


def check_setpoints(
    sp: Setpoints,
    path: Path,
    limits: AxisLimits,
    *,
    feed_m_s: float | None = None,
    tol_m: float = TOL_M,
) -> PlanCheck:
    """Check setpoints against the limits, the feed and the programmed geometry.

    Parameters
    ----------
    sp : Setpoints
        The planned setpoints (float64 positions are used, nothing else).
    path : Path
        The programmed path they were planned from.
    limits : AxisLimits
        Axis limits.
    feed_m_s : float, optional
        Feed override (m/s) the plan used; default: each move's programmed feed.
    tol_m : float
        Largest allowed distance of a feed sample to the programmed geometry, metres.

    Returns
    -------
    PlanCheck
    """
    pos = sp.pos
    vel, acc, jerk = finite_differences(pos, sp.dt)
    mv, ma, mj = (np.abs(x).max(axis=0) for x in (vel, acc, jerk))
    rv = _ratio(mv, limits.vmax_m_s)
    ra = _ratio(ma, limits.amax_m_s2)
    rj = _ratio(mj, limits.jmax_m_s3)
    speed_ratio, max_dev, segs = _feed_and_geometry(sp, path, vel, feed_m_s)
    end = segs[-1].end if segs else path.start
    start_err = float(np.linalg.norm(pos[0] - path.start))
    end_err = float(np.linalg.norm(pos[-1] - end))
    at_rest = bool(len(pos) >= 3 and np.all(pos[-3:] == pos[-1]))
    bad = _limit_violations((rv, ra, rj), (mv, ma, mj))
    if speed_ratio > 1.0 + SPEED_MARGIN:
        bad.append(f"path speed reaches {speed_ratio:.4f} x the programmed feed")
    if max_dev > tol_m:
        bad.append(
            f"deviation from the programmed path {max_dev * 1e6:.2f} um "
            f"exceeds {tol_m * 1e6:.2f} um"
        )
    if start_err > _END_TOL_M:
        bad.append(f"first sample is {start_err * 1e6:.3f} um from the programmed start")
    if end_err > _END_TOL_M:
        bad.append(f"last sample is {end_err * 1e6:.3f} um from the programmed end")
    if not at_rest:
        bad.append("the setpoints do not end at rest")
    return PlanCheck(
        max_vel_m_s=mv,
        max_acc_m_s2=ma,
        max_jerk_m_s3=mj,
        vel_ratio=rv,
        acc_ratio=ra,
        jerk_ratio=rj,
        speed_ratio=speed_ratio,
        max_deviation_m=max_dev,
        start_error_m=start_err,
        end_error_m=end_err,
        ends_at_rest=at_rest,
        ok=not bad,
        violations=tuple(bad),
        limits=limits,
    )
