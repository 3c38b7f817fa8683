"""Jerk-limited feed planning: a path in, uniformly sampled setpoints out.

Method
------
The path is cut into rest-to-rest blocks (:func:`feedplan.fit.blocks_of`: rapids,
chains of lines, arcs, fitted micro-segment splines and the corner blends between them;
exact stops only where G61 asks or a blend would not be faster). The tolerance is
``G64 P`` where the program sets one, ``tol_m`` elsewhere, the least of them for the
whole plan (:func:`program_tolerance_m`); blends get :data:`~oga.defaults.BLEND_TOL_FRACTION` of it,
the filter's rounding the rest.

*Straight blocks* (rapids, and feed blocks of one line) are planned exactly: the
per-axis limits are projected on the line, the path speed capped at the feed (at
the axis limits for rapids), and ruckig computes the time-optimal jerk-limited 1-D
profile (one ``calculate()`` per block, no waypoints); its seven phases are
evaluated in closed form at every sample.

Feeds above what the axes allow along a move are capped there first (a warning
says so); the motion time is estimated before planning and bounded while planning
(:data:`~oga.defaults.MAX_MOTION_S`, :data:`~oga.defaults.MAX_SAMPLES`).

*Other feed blocks* are planned in two stages, the classic "acceleration-limited profile
plus FIR filter" of industrial interpolators:

1. an acceleration-limited time-optimal speed profile along the curve: a speed
   ceiling on a grid of about :data:`GRID_M` (programmed feed, axis velocities,
   centripetal acceleration, the arc rounding of stage 2, and jerk-derived
   ceilings where the curvature jumps or the tangent kinks between pieces), then
   compiled forward/backward passes with a tangential acceleration limit ``A_t``
   (a share of ``J T``, less on curves, where a changing speed changes the centripetal
   acceleration too, and near curvature jumps; on each axis what the centripetal
   acceleration at the ceiling leaves of its limit, projected on the tangent: the whole
   limit on straight stretches, at least ``1 - _CENTRIPETAL_SHARE`` of it on curves).
   Cells are crossed at constant acceleration, those starting or ending at rest
   time-optimally (so a slow feed pays no cell's worth of time per block). The positions ``r(u(t))`` are
   sampled every ``dt``;
2. a moving average of ``M`` samples (``T = M dt``) over these positions, the same
   on every axis so the axes stay synchronised. In finite differences the filtered
   jerk is exactly ``(a_k - a_{k-M}) / T`` of the unfiltered accelerations, and the
   filtered velocity and acceleration are averages of unfiltered ones: a bounded
   acceleration change over ``T`` gives a bounded jerk, with no jerk spike where the
   curvature jumps (line to arc). The price is a rounding of the contour, about
   ``v^2 T^2 kappa / 24`` on an arc; it is optionally pre-compensated (the
   unfiltered samples are pushed outwards by that amount, smoothed, see
   :func:`_rounding_compensation`), which lets small arcs run at the feed.
   Where the tolerance forces a short ``T`` (tight curves, curvature jumps), the curve
   parameter ``u(t)`` is first averaged over ``T_u`` (the rest of ``sqrt(F / J)``): that
   average keeps the exact geometry and smooths the tangential acceleration alone, so
   ``A_t`` is a share of ``J max(T, T_u)`` instead of ``J T``; the speed ceiling's low
   stretches are widened by ``ceil T_u / 2`` (the stretch that average mixes in).

A check-and-slow-down loop then measures the filtered float64 setpoints as
:mod:`feedplan.check` does (finite differences against every axis limit, path speed
against the feed, exact distance to the programmed lines and arcs) and, where a
sample fails, lowers the ceiling (and ``A_t``) over the stretch of the curve that
sample averages, and replans, until clean. Per block a few filter lengths ``T`` up
to the 1-D jerk-optimal ``sqrt(F / J)``, each with and without the compensation
(:data:`_VARIANTS`), are tried and the fastest clean plan is kept; a variant is
abandoned as soon as it is slower than the best so far.

Why not toppra: in the first stage the only constraint left to the parametrisation
is the scalar tangential limit ``A_t`` (axis velocities and centripetal
accelerations are in the ceiling, everything is re-checked after filtering), and
for that toppra's per-grid-point LP reduces to the closed-form forward/backward pass
written here. toppra would add a matplotlib import and an LP solve per grid point,
and its profile would still need the same jerk treatment afterwards.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from ruckig import InputParameter, Result, Ruckig, RuckigError, Trajectory

from feedplan.blend import BLEND_CENTRIPETAL_SHARE
from feedplan.check import SPEED_MARGIN, deviation_m, finite_differences, segment_table
from feedplan import profile
from feedplan.fit import Block, Blending, blocks_of
from feedplan.limits import AxisLimits
from feedplan.path import PLANES, Arc, Line, Path
from feedplan.setpoints import AXES, Setpoints
from oga.defaults import (
    BLEND_TOL_FRACTION,
    DT_RANGE_S,
    DT_S,
    MAX_COORD_M,
    MAX_MOTION_S,
    MAX_SAMPLES,
    TOL_M,
    TOL_RANGE_M,
)
from oga.errors import OptionError, PlanError, ToolpathError

__all__ = ["plan", "least_motion_s", "move_times_s", "program_tolerance_m", "plane_of",
           "derivatives", "GRID_M", "FIT_TOL_FRACTION"]

#: Spacing of the speed-profile grid along the path, metres.
GRID_M = 0.25e-3
#: Share of the tolerance given to the spline fits of micro-segments.
FIT_TOL_FRACTION = 0.5
#: Filter lengths tried, as fractions of the 1-D jerk-optimal sqrt(F / J); each also with the
#: curve parameter averaged over the rest of sqrt(F / J) first (:func:`_run_filter`).
_T_FRACTIONS = (1.0, 0.75, 0.55, 0.4, 0.3, 0.22, 0.15, 0.1)
#: Limits are met with this relative margin (float noise of the checks).
_MARGIN = 1e-3
#: Variants tried per filter length: (share, compensate). The initial ceiling on curves
#: keeps the uncompensated rounding ``v^2 T^2 kappa / 24`` of the filter within ``share``
#: times the tolerance left after the fit; with the rounding compensation on, most of it
#: is cancelled (the check-and-slow-down loop handles the rest). Short arcs between kinks
#: fare better without it.
_VARIANTS = ((0.98, False), (2.0, True), (2.5, True), (3.0, True))
#: Largest share of an axis's acceleration limit taken by the centripetal acceleration
#: (the speed ceiling on curves); the rest, at least, is left to the tangential one.
_CENTRIPETAL_SHARE = BLEND_CENTRIPETAL_SHARE
#: Share of the jerk limit given to the tangential acceleration ``A_t`` (its change over T, and
#: on curves the change ``2 v A_t d2r/du2`` of the centripetal acceleration it makes); the
#: rest is left to curvature changes.
_AT_SHARE = 0.9
#: Least share of J T left to the tangential acceleration within reach of a curvature jump
#: (the rest goes to the step of centripetal acceleration there at the jump's own ceiling;
#: > 0 so that speed can change). Where a lower ceiling (the feed) crosses the jump, the
#: tangential acceleration gets what the step leaves, up to :data:`_AT_SHARE`.
_JUMP_AT_SHARE = 0.1
#: Largest ceiling factor applied where a sample fails: 2 % slower per round, 5 % after
#: :data:`_GENTLE_ROUNDS` rounds (the last stubborn samples).
_STEP = (0.98, 0.95)
_GENTLE_ROUNDS = 10
#: Largest number of check-and-slow-down rounds per filter length.
_ROUNDS = 60
#: Most check-and-slow-down rounds of a block planned along its exact curve.
_PROFILE_ROUNDS = 20
#: A profile's check-and-slow-down rounds end (the filter plans the block) once it is this much
#: slower than its first solve: each round caps every node, so it only loses from there
#: (line-contouring-xz: 4.2 -> 17.4 CPU s in rounds that all lost to the filter).
_PROFILE_GIVE_UP = 1.1
#: Most grid nodes of a block planned along its exact curve (longer ones: the filter). The
#: 100k micro-segment program's one fitted block of 5.47 m has 33 341 (a spline's knots are
#: nodes): planned along its curve 121.279 -> 110.723 s, 3.4 s more CPU, 0.75 GB at the peak.
_PROFILE_NODES = 40_000
#: A block with joints (long runs of lines) above this many nodes gets a coarser grid of 0.8 of it.
_JOINTED_NODES = 4000
#: Most speed-profile grid nodes of one block (a longer block gets a coarser grid).
_MAX_NODES = 1_000_000
#: Most turns of one arc (a helix of hand-built paths; G-code arcs turn once at most).
_MAX_TURNS = 1000
#: Moving averages costing more additions than this are running sums (O(n), not O(n m)).
_EXACT_SUM_OPS = 200_000_000
#: Moving means summed side by side (a block that stays in the first-level cache).
_SUM_BLOCK = 512


# --------------------------------------------------------------------------- straight blocks


def _straight(seg: Line, limits: AxisLimits, dt: float, budget: int, feed_m_s: float):
    """Samples of a lone line, rest to rest: positions (n, 3) m and source lines (n,).

    ruckig's time-optimal jerk-limited 1-D profile along the line (the axis limits
    projected on it, path speed at most ``feed_m_s``; ``inf`` for a rapid), evaluated
    in closed form at every sample: exact, so finite differences of the samples
    (averages of the profile's derivatives) stay within the limits. ``budget`` is the
    number of samples left (:data:`~oga.defaults.MAX_SAMPLES`).
    """
    L = seg.length
    d = (seg.end - seg.start) / L
    m = (np.abs(d) > 1e-15) & limits.present  # an absent axis moves at most 1e-12 m
    # the jerk a feed line gets for its tangential motion (_AT_SHARE): at the full jerk,
    # ruckig's long constant-jerk phases made the position loop's command overshoot the
    # axis jerk limit (1.04-1.10x with the best fixed gains on real programs)
    lim = [
        (1.0 - _MARGIN) * float(np.min(x[m] / np.abs(d[m])))
        for x in (limits.vmax_m_s, limits.amax_m_s2, limits.jmax_m_s3 * _AT_SHARE)
    ]
    lim[0] = min(lim[0], feed_m_s)
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [L]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [lim[0]], [lim[1]], [lim[2]]
    traj = Trajectory(1)
    try:
        res = Ruckig(1).calculate(inp, traj)
    except RuckigError as err:
        raise PlanError(f"line {seg.line}: line of {L * 1e3:.4g} mm: ruckig: {err}") from err
    if res not in (Result.Working, Result.Finished):
        raise PlanError(f"line {seg.line}: line of {L * 1e3:.4g} mm: ruckig returned {res}")
    prof = traj.profiles[0][0]
    tb = np.concatenate([[0.0], np.cumsum(prof.t)])
    n = math.ceil(traj.duration / dt - 1e-9)
    if n + 3 > budget:
        raise _too_long(seg.line, dt)
    t = np.minimum(np.arange(n + 3) * dt, tb[-1])
    ph = np.clip(np.searchsorted(tb, t, side="right") - 1, 0, 6)
    tau = t - tb[ph]
    j, a0 = np.array(prof.j)[ph], np.array(prof.a)[ph]
    v0, p0 = np.array(prof.v)[ph], np.array(prof.p)[ph]
    s = p0 + tau * (v0 + tau * (a0 / 2 + tau * j / 6))
    pos = seg.start + s[:, None] * d
    pos[n:] = seg.end
    return pos, np.full(len(t), seg.line)


def _one_line(blk, seg_feed: np.ndarray) -> bool:
    """A block that is one line at one feed: a rapid, a lone feed line, or a straight run of
    micro-segments (:func:`blocks_of`)."""
    feeds = seg_feed[blk.segments]
    return blk.curve.is_line and bool(np.all(feeds == feeds[0]))  # a rapid's: inf


def _straight_run(blk, path: Path, limits: AxisLimits, dt: float, budget: int,
                  seg_feed: np.ndarray):
    """:func:`_straight` of a block that is one line (:func:`_one_line`) from its first move's
    start to its last move's end, each sample's source line that of the move it lies on."""
    curve, ids = blk.curve, blk.segments
    first, last = path.segments[ids[0]], path.segments[ids[-1]]
    pos, _ = _straight(Line(first.start, last.end, first.feed_m_s, line=first.line), limits,
                       dt, budget, float(seg_feed[ids[0]]))
    u = (pos - first.start) @ curve.e1[0]
    at = np.clip(np.searchsorted(blk.seg_u0, u, side="right") - 1, 0, len(ids) - 1)
    return pos, np.array([path.segments[i].line for i in ids])[at]


# --------------------------------------------------------------------------- feed blocks


@njit(cache=True)
def _forward_backward(u, ceil, acc):
    """Largest speeds under the ceiling with |dv^2/du| <= 2 acc per cell, rest at both ends."""
    n = u.shape[0]
    v2 = ceil * ceil
    v2[0] = 0.0
    v2[n - 1] = 0.0
    for k in range(n - 1):
        v2[k + 1] = min(v2[k + 1], v2[k] + 2.0 * acc[k] * (u[k + 1] - u[k]))
    for k in range(n - 2, -1, -1):
        v2[k] = min(v2[k], v2[k + 1] + 2.0 * acc[k] * (u[k + 1] - u[k]))
    return np.sqrt(v2)


@njit(cache=True)
def _cells(u, v, ceil, acc):
    """Motion through each grid cell: accelerate, cruise, decelerate.

    A cell that starts or ends at rest, under a ceiling (the lower of its nodes') above
    both end speeds, is crossed time-optimally: at ``acc`` from ``v[k]`` up to the
    ceiling (or as high as the cell's length allows), at that speed, then at ``-acc``
    down to ``v[k + 1]`` (a constant acceleration there would cost about
    ``GRID_M / F`` at a slow feed ``F``). Elsewhere the cell is crossed at the
    constant acceleration joining its end speeds (spread over the cell: inside a
    block, where speeds follow a varying ceiling, that spreading keeps the filtered
    jerk lower than bursts of ``acc``; measured: freeform_xz 4.46 s against 4.60 s).

    Returns
    -------
    ndarray, shape (n - 1, 6)
        Per cell: start speed, first acceleration, its time, peak speed, cruise time,
        final deceleration (the time of the last phase follows); m/s, m/s^2, s.
    """
    n = u.shape[0]
    out = np.zeros((n - 1, 6))
    for k in range(n - 1):
        length = u[k + 1] - u[k]
        v0, v1, a = v[k], v[k + 1], acc[k]
        vc = min(ceil[k], ceil[k + 1])
        if min(v0, v1) == 0.0 and vc >= max(v0, v1) and vc > 0.0 and a > 0.0:
            vp = max(math.sqrt(min(vc * vc, a * length + 0.5 * (v0 * v0 + v1 * v1))), v0, v1)
            cruise = length - (2.0 * vp * vp - v0 * v0 - v1 * v1) / (2.0 * a)
            out[k] = (v0, a, (vp - v0) / a, vp, max(cruise, 0.0) / vp, a)
        else:
            a1 = (v1 * v1 - v0 * v0) / (2.0 * length)
            out[k] = (v0, a1, 2.0 * length / (v0 + v1), v1, 0.0, 0.0)
    return out


@njit(cache=True)
def _profile_s(u, v, ceil, acc):
    """Duration (s) of the motion through the cells of :func:`_cells`."""
    cells = _cells(u, v, ceil, acc)
    total = 0.0
    for k in range(u.shape[0] - 1):
        t1, vp, t2, a3 = cells[k, 2], cells[k, 3], cells[k, 4], cells[k, 5]
        total += t1 + t2 + ((vp - v[k + 1]) / a3 if a3 > 0.0 else 0.0)
    return total


@njit(cache=True)
def _sample(u, v, ceil, acc, dt, budget):
    """Parameter u and its rate du/dt every dt through the cells of :func:`_cells`.

    Returns empty arrays when ``budget`` samples or more (or an endless time) would
    be needed.
    """
    n = u.shape[0]
    cells = _cells(u, v, ceil, acc)
    tn = np.zeros(n)
    for k in range(n - 1):
        t1, vp, t2, a3 = cells[k, 2], cells[k, 3], cells[k, 4], cells[k, 5]
        t3 = (vp - v[k + 1]) / a3 if a3 > 0.0 else 0.0
        tn[k + 1] = tn[k] + t1 + t2 + t3
    total = tn[n - 1] / dt
    if not total < budget:  # also nan and inf
        return np.empty(0), np.empty(0)
    ns = int(np.ceil(total - 1e-9)) + 1
    us, ud = np.empty(ns), np.zeros(ns)
    c = 0
    for k in range(ns):
        t = k * dt
        if t >= tn[n - 1]:
            us[k] = u[n - 1]
            continue
        while t >= tn[c + 1]:
            c += 1
        v0, a1, t1 = cells[c, 0], cells[c, 1], cells[c, 2]
        vp, t2, a3 = cells[c, 3], cells[c, 4], cells[c, 5]
        tau = t - tn[c]
        if tau < t1:
            x, rate = v0 * tau + 0.5 * a1 * tau * tau, v0 + a1 * tau
        else:
            x = v0 * t1 + 0.5 * a1 * t1 * t1
            tau -= t1
            if tau < t2:
                x, rate = x + vp * tau, vp
            else:
                tau -= t2
                x, rate = x + vp * t2 + vp * tau - 0.5 * a3 * tau * tau, vp - a3 * tau
        us[k] = min(u[c] + x, u[c + 1])
        ud[k] = max(rate, 0.0)
    us[ns - 1] = u[n - 1]
    return us, ud


@njit(cache=True)
def _moving_average(x, m, extra):
    """Mean of the last m samples (x held before its start and after its end).

    Each mean summed afresh while that costs at most :data:`_EXACT_SUM_OPS` additions;
    beyond, a running sum, summed afresh every m samples (its rounding stays that of m
    additions): O(n) whatever m. The fresh sums add the same numbers in the same order
    for every mean, :data:`_SUM_BLOCK` means at a time (so they run side by side).
    """
    n = x.shape[0]
    total = n + m - 1 + extra
    out = np.empty((total, x.shape[1]))
    exact = total * m <= _EXACT_SUM_OPS
    # xs[i] = x[i - m + 1] - x[0] (held at the ends): the mean at k sums xs[k .. k + m - 1]
    xs = np.empty(total + m - 1)
    acc = np.empty(_SUM_BLOCK)
    for c in range(x.shape[1]):
        ref = x[0, c]
        for i in range(total + m - 1):
            xs[i] = x[min(max(i - m + 1, 0), n - 1), c] - ref
        if exact:
            for k0 in range(0, total, _SUM_BLOCK):
                kb = min(_SUM_BLOCK, total - k0)
                acc[:kb] = 0.0
                for q in range(m):
                    src = xs[k0 + q : k0 + q + kb]
                    for i in range(kb):
                        acc[i] += src[i]
                for i in range(kb):
                    out[k0 + i, c] = ref + acc[i] / m
            continue
        run = 0.0
        for k in range(total):
            if k % m == 0:
                run = 0.0
                for q in range(m):
                    run += xs[k + q]
            else:
                run += xs[k + m - 1] - xs[k - 1]
            out[k, c] = ref + run / m
    for k in range(n + m - 2, total):
        out[k] = x[n - 1]
    return out


@njit(cache=True)
def _lower(u_nodes, u_pre, lo, hi, factor, scale):
    """Lower ``scale`` to ``factor[i]`` on the nodes over u_pre[lo[i]]..u_pre[hi[i]] (+1 node)."""
    for i in range(lo.shape[0]):
        a = np.searchsorted(u_nodes, u_pre[lo[i]]) - 1
        b = np.searchsorted(u_nodes, u_pre[hi[i]]) + 1
        for k in range(max(a, 0), min(b, u_nodes.shape[0] - 1) + 1):
            if factor[i] < scale[k]:
                scale[k] = factor[i]


@dataclass(frozen=True, eq=False)
class _Feed:
    """What every planning round of one feed block needs."""

    block: Block
    first: np.ndarray  # programmed start and end, (3,) m
    last: np.ndarray
    nodes: np.ndarray  # grid along u, (G,) m
    seg_feed: np.ndarray  # feed of each programmed move, (n,) m/s
    seg_lines: np.ndarray  # its source line, (n,)
    table: tuple  # feedplan.check.segment_table of the moves
    limits: AxisLimits
    tol_m: float
    dt: float
    budget: int  # samples left for this block (ToolpathError beyond)
    spacing: float  # of the grid, m


@dataclass(frozen=True, eq=False)
class _Attempt:
    """Filtered positions (n, 3) m, duration s; curve parameter u (m) of the unfiltered
    samples and the filter length m (the source lines of the kept one: :func:`_lines`)."""

    pos: np.ndarray
    duration: float
    u: np.ndarray
    m: int


def _lines(fb: "_Feed", att: _Attempt) -> np.ndarray:
    """Source line of each filtered sample: that of the move at the centre of its window."""
    centre = np.clip(np.arange(len(att.pos)) - (att.m - 1) // 2, 0, len(att.u) - 1)
    seg_at = np.searchsorted(fb.block.seg_u0, att.u[centre], side="right") - 1
    return fb.seg_lines[np.clip(seg_at, 0, len(fb.seg_lines) - 1)]


def _grid(block: Block) -> tuple[np.ndarray, float]:
    """Nodes (G,) m about :data:`GRID_M` apart (at most :data:`_MAX_NODES`), and that spacing."""
    u0 = block.curve.u0
    spacing = max(GRID_M, 2.0 * float(u0[-1]) / _MAX_NODES)
    cells = [max(2, math.ceil((u0[k + 1] - u0[k]) / spacing)) for k in range(len(u0) - 1)]
    nodes = [np.linspace(u0[k], u0[k + 1], c + 1) for k, c in enumerate(cells)]
    return np.unique(np.concatenate(nodes)), spacing


def _static_limits(fb: _Feed):
    """Per node: speed ceiling (m/s) independent of T, |unit tangent| per axis, curvature
    (1/m), feed (m/s), and the largest |d2r/du2| per axis (1/m; shape (G, 3))."""
    nodes, seg_u0 = fb.nodes, fb.block.seg_u0
    ceil = np.full(nodes.size, np.inf)
    tan = np.zeros((nodes.size, 3))
    kappa = np.zeros(nodes.size)
    curv = np.zeros((nodes.size, 3))
    last = len(fb.seg_feed) - 1
    k_right = np.clip(np.searchsorted(seg_u0, nodes, side="right") - 1, 0, last)
    k_left = np.clip(np.searchsorted(seg_u0, nodes, side="left") - 1, 0, last)
    feed = np.minimum(fb.seg_feed[k_right], fb.seg_feed[k_left])
    ax = fb.limits.present
    vmax, amax = fb.limits.vmax_m_s[ax], fb.limits.amax_m_s2[ax]
    with np.errstate(divide="ignore"):
        for left in (False, True):
            _, d1, d2, _ = fb.block.curve.evaluate(nodes, left=left)
            speed = np.linalg.norm(d1, axis=1)
            ceil = np.minimum(ceil, feed / speed)
            ceil = np.minimum(ceil, np.min(vmax / np.abs(d1[:, ax]), axis=1))
            ceil = np.minimum(
                ceil, np.sqrt(np.min(_CENTRIPETAL_SHARE * amax / np.abs(d2[:, ax]), axis=1)))
            tan = np.maximum(tan, np.abs(d1 / speed[:, None]))
            kappa = np.maximum(kappa, np.linalg.norm(d2, axis=1) / speed**2)
            curv = np.maximum(curv, np.abs(d2))
    return ceil, tan, kappa, feed, curv


@njit(cache=True)
def _centred_mean(x, m):
    """Centred moving average over m (odd) samples, zero outside; shape of x (N, 3).

    A running sum over the zero-padded samples, differenced (one pass, no padded copy).
    """
    n, h = x.shape[0], m // 2
    total = n + 2 * h + 1  # zeros (h + 1), x, zeros (h)
    out = np.empty_like(x)
    for col in range(x.shape[1]):
        c = np.empty(total)
        acc = 0.0
        for i in range(total):
            j = i - h - 1
            acc = acc + (x[j, col] if 0 <= j < n else 0.0) if i > 0 else 0.0
            c[i] = acc
        for k in range(n):
            out[k, col] = (c[k + m] - c[k]) / m
    return out


@njit(cache=True)
def _compensation(d1, d2, ud, coef, m):
    """:func:`_rounding_compensation` after its scalar ``coef = -s2 / 2``, compiled."""
    n = d1.shape[0]
    off = np.empty((n, 3))
    for k in range(n):
        speed = math.sqrt(d1[k, 0] * d1[k, 0] + d1[k, 1] * d1[k, 1] + d1[k, 2] * d1[k, 2])
        t0, t1, t2 = d1[k, 0] / speed, d1[k, 1] / speed, d1[k, 2] / speed
        dot = 0.0
        dot += d2[k, 0] * t0
        dot += d2[k, 1] * t1
        dot += d2[k, 2] * t2
        w = coef * (ud[k] * ud[k])
        off[k, 0] = w * (d2[k, 0] - dot * t0)
        off[k, 1] = w * (d2[k, 1] - dot * t1)
        off[k, 2] = w * (d2[k, 2] - dot * t2)
    odd = m | 1
    off = _centred_mean(_centred_mean(off, odd), odd)
    for k in range(n):
        if 2 * m <= k <= n - 1 - 2 * m:  # the ramp is 1 there: the factor is 1.0
            continue
        ramp = min(max(min(k, n - 1 - k) / (2.0 * m), 0.0), 1.0)
        f = ramp * ramp * (3.0 - 2.0 * ramp)
        for i in range(3):
            off[k, i] = off[k, i] * f
    return off


def _rounding_compensation(d1, d2, ud, m: int, dt: float) -> np.ndarray:
    """Offset (N, 3) m of the unfiltered samples that cancels the filter's contour rounding.

    A centred mean over ``m`` samples turns a smooth motion ``p(t)`` into ``p + s2/2 p''``
    plus higher orders, ``s2 = (m^2 - 1) dt^2 / 12``; the normal part of ``p''`` (the
    centripetal acceleration) moves the filtered point inside curves. Subtracting
    ``s2/2`` of it beforehand keeps arcs on their radius. The offset is smoothed twice
    over the filter length, so it adds no jerk step where the curvature jumps, and it
    fades in and out over the first and last ``2 m`` samples (at rest at both ends).
    """
    s2 = (m * m - 1) * dt * dt / 12.0
    return _compensation(d1, d2, ud, -0.5 * s2, m)


def _run_filter(fb: _Feed, ceil: np.ndarray, acc_t: np.ndarray, m: int, m_u: int,
                compensate: bool, beat: float = math.inf):
    """Plan with one ceiling and filter lengths (rounding compensation on or off), check it.

    The sampled curve parameter is first averaged over ``m_u`` samples (exact geometry: it
    smooths the tangential acceleration alone), the positions then over ``m``. The duration
    is known once sampled: at ``beat`` (s) or longer, None (nothing evaluated nor checked).

    Returns
    -------
    attempt : _Attempt
    f_speed, f_acc : ndarray, shape (n + 3,)
        Per filtered sample (and the 3 at rest after it), the factor to apply to the
        speed ceiling and to ``A_t`` where it is averaged (1 where clean).
    u : ndarray
        Curve parameter of each sample before both averages, m.
    """
    lim, dt = fb.limits, fb.dt
    v = _forward_backward(fb.nodes, ceil, acc_t)
    u_raw, ud = _sample(fb.nodes, v, ceil, acc_t, dt, fb.budget - m - m_u - 3)
    if u_raw.size == 0:
        raise _too_long(int(fb.seg_lines[0]), dt)
    # samples: u_raw, + m_u - 1 by the parameter's average, + m - 1 + 3 by the positions'
    if (u_raw.size + m + m_u) * dt >= beat:
        return None
    u = u_raw
    if m_u > 1:
        both = _moving_average(np.stack((u_raw, ud), axis=1), m_u, 0)
        u, ud = np.minimum(both[:, 0], u_raw[-1]), both[:, 1]
        u[-1] = u_raw[-1]
    p, d1, d2 = fb.block.curve.evaluate(u, order=2)
    p[0], p[-1] = fb.first, fb.last
    if compensate:
        p += _rounding_compensation(d1, d2, ud, m, dt)
    pos = _moving_average(p, m, 3)
    dist, near = deviation_m(pos, fb.table)
    n = len(pos)
    axes = lim.present  # the others do not move (checked before planning)
    f_speed, f_acc = _factors(pos, dt, lim.vmax_m_s[axes], lim.amax_m_s2[axes],
                              lim.jmax_m_s3[axes], np.flatnonzero(axes), dist,
                              fb.seg_feed[near] * (1.0 + SPEED_MARGIN), fb.tol_m, 1.0 - _MARGIN)
    return _Attempt(pos, (n - 1) * dt, u, m), f_speed, f_acc, u_raw


@njit(cache=True)
def _factors(pos, dt, vmax, amax, jmax, axes, dist, feed, tol, ok):
    """Per filtered sample (and the 3 at rest after it), the factors of the speed ceiling
    and of ``A_t`` that would bring it within the limits (1 where clean).

    The finite differences of :func:`feedplan.check.finite_differences` and the worst
    ratio over the axes ``axes`` (limits ``vmax``, ``amax``, ``jmax`` of those axes) of
    velocity, acceleration and jerk; the path speed over ``feed`` (the feed with its
    margin, per sample); the distance ``dist`` over ``tol``. Speed enters velocities
    linearly, rounding and accelerations about quadratically, the jerk of curvature
    changes cubically; ``A_t`` enters accelerations and jerk about linearly.
    """
    n = pos.shape[0]
    rows = n + 3
    f_speed, f_acc = np.empty(rows), np.empty(rows)
    # p: pos held 3 samples before and after; v, a, j as numpy's diff of it over dt
    v = np.empty((rows + 2, 3))
    a = np.empty((rows + 1, 3))
    for i in range(rows + 2):
        for c in range(3):
            v[i, c] = (pos[min(max(i - 2, 0), n - 1), c] - pos[min(max(i - 3, 0), n - 1), c]) / dt
    for i in range(rows + 1):
        for c in range(3):
            a[i, c] = (v[i + 1, c] - v[i, c]) / dt
    for k in range(rows):
        r_v = r_a = r_j = -np.inf
        for q in range(axes.shape[0]):
            c = axes[q]
            r_v = max(r_v, abs(v[k + 2, c]) / vmax[q])
            r_a = max(r_a, abs(a[k + 1, c]) / amax[q])
            r_j = max(r_j, abs((a[k + 1, c] - a[k, c]) / dt) / jmax[q])
        r_s = r_d = 0.0
        if k < n:
            sq = 0.0
            sq += v[k + 2, 0] * v[k + 2, 0]
            sq += v[k + 2, 1] * v[k + 2, 1]
            sq += v[k + 2, 2] * v[k + 2, 2]
            r_s = math.sqrt(sq) / feed[k]
            r_d = dist[k] / tol
        fa = ok / max(max(r_a, r_j), ok)
        fs = ok / max(max(r_v, r_s), ok)  # <= 1: the roots below are 1 where r <= ok
        # accelerations grow with the speed squared, jerks (curvature changes) cubed
        if r_d > ok:
            fs = min(fs, math.sqrt(ok / r_d))
        if r_a > ok:
            fs = min(fs, math.sqrt(ok / r_a))
        if r_j > ok:
            fs = min(fs, (ok / r_j) ** (1.0 / 3.0))
        f_acc[k], f_speed[k] = fa, fs
    return f_speed, f_acc


def _converge(
    fb: _Feed, ceil: np.ndarray, acc_t: np.ndarray, m: int, m_u: int, compensate: bool,
    beat: float
):
    """Check-and-slow-down rounds for one filter length.

    Returns a clean attempt faster than ``beat`` (s), or None.
    """
    for rnd in range(_ROUNDS):
        # the filtered duration, known before sampling: the profile's and both averages' lags
        v = _forward_backward(fb.nodes, ceil, acc_t)
        if _profile_s(fb.nodes, v, ceil, acc_t) + (m + m_u) * fb.dt >= beat:
            return None
        run = _run_filter(fb, ceil, acc_t, m, m_u, compensate, beat)
        if run is None:  # rounds only slow down: give up
            return None
        att, f_speed, f_acc, u = run
        bad = np.flatnonzero((f_speed < 1.0) | (f_acc < 1.0))
        if bad.size == 0:
            return att
        # filtered sample k averages unfiltered k - m - m_u + 2 .. k (its differences: 3 more)
        lo = np.clip(bad - m - (m_u - 1) - 3, 0, len(u) - 1)
        hi = np.clip(bad, 0, len(u) - 1)
        s_node = np.ones(fb.nodes.size)
        _lower(fb.nodes, u, lo, hi, np.minimum(f_speed[bad], _STEP[rnd >= _GENTLE_ROUNDS]), s_node)
        a_node = np.ones(fb.nodes.size)
        _lower(fb.nodes, u, lo, hi, f_acc[bad], a_node)
        ceil = ceil * s_node
        acc_t = acc_t * np.minimum(a_node[:-1], a_node[1:])
    return None


def _joints(curve):
    """Where pieces meet with a jump of curvature or a kink of the tangent.

    Returns
    -------
    u_jump : ndarray, shape (J,)
        Parameters (m) of curvature jumps (line to arc, arc to arc); the acceleration
        steps by ``v^2 d_kappa`` there, which the filter spreads over ``T``.
    d_kappa : ndarray, shape (J, 3)
        Jump of the curvature vector ``d2r/du2``, 1/m.
    u_kink : ndarray, shape (K,)
        Parameters (m) of kinks (tangent turns up to the corner angle); the velocity
        turns by ``v d_tan`` within one sample there, a jerk ``v |d_tan_i| / (T dt)``
        after filtering.
    d_tan : ndarray, shape (K, 3)
        Jump of the unit tangent.
    """
    return profile.joints(curve)


def _near(nodes: np.ndarray, u: float, reach: float) -> np.ndarray:
    """Indices of the sorted ``nodes`` where ``abs(nodes - u) <= reach``, found by bisection
    (not a pass over every node per joint: blocks of many arcs or kinks)."""
    pad = 1e-12 * (abs(u) + reach)  # beyond it the float difference cannot be within reach
    lo, hi = np.searchsorted(nodes, (u - reach - pad, u + reach + pad))
    return lo + np.flatnonzero(np.abs(nodes[lo:hi] - u) <= reach)


@dataclass(frozen=True, eq=False)
class _Reach:
    """What a feed block's geometry allows, before any filter length is chosen."""

    ceil: np.ndarray  # speed ceiling at each node, (G,) m/s
    tan: np.ndarray  # unit tangent, (G, 3)
    kappa: np.ndarray  # curvature, (G,) 1/m
    curv: np.ndarray  # curvature vector's components, (G, 3) 1/m
    j_path: np.ndarray  # path jerk the axes allow along the tangent, (G,) m/s^3
    a_path: np.ndarray  # path acceleration left by the centripetal one, (G,) m/s^2
    v_top: float  # fastest speed the block reaches, m/s
    t_opt: float  # filter length from it, s
    dev_node: np.ndarray  # the geometry's own deviation (fits, blends) at each node, (G,) m


def _feed_block(block: Block, path: Path, limits: AxisLimits, feeds: np.ndarray, tol_m: float,
                dt: float, budget: int) -> _Feed:
    """The planning rounds' view of a feed block (:class:`_Feed`)."""
    segs = [path.segments[i] for i in block.segments]
    nodes, spacing = _grid(block)
    return _Feed(
        block=block,
        first=segs[0].start,
        last=segs[-1].end,
        nodes=nodes,
        seg_feed=feeds[block.segments],
        seg_lines=np.array([s.line for s in segs], dtype=np.int64),
        table=segment_table(segs),
        limits=limits,
        tol_m=tol_m,
        dt=dt,
        budget=budget,
        spacing=spacing,
    )


def _reach(fb: _Feed) -> _Reach:
    """The block's speed ceiling, path acceleration and jerk, top speed and filter length."""
    ceil0, tan, kappa, _, curv = _static_limits(fb)
    limits = fb.limits
    ax = limits.present
    jmax, amax = limits.jmax_m_s3[ax], limits.amax_m_s2[ax]
    # each axis's acceleration left by the centripetal one at the ceiling (a bound of it at
    # any speed the profile reaches), projected on the tangent: the whole limit on straight
    # stretches, at least 1 - _CENTRIPETAL_SHARE of it on curves
    with np.errstate(invalid="ignore"):  # inf * 0 where no ceiling binds on a line
        centripetal = np.nan_to_num(ceil0[:, None] ** 2 * curv[:, ax], nan=0.0)
    spare = np.maximum(amax - centripetal, (1.0 - _CENTRIPETAL_SHARE) * amax)
    with np.errstate(divide="ignore", over="ignore"):  # a tangent component of 0 or ~1e-300
        j_path = np.min(jmax / tan[:, ax], axis=1)
        a_path = np.min(spare / tan[:, ax], axis=1)
    moving = np.any(tan[:, ax] > 1e-12, axis=0)
    # the filter's length from the speed the block can reach, not from the programmed feed
    v_top = float(np.max(_forward_backward(fb.nodes, ceil0,
                                           np.minimum(a_path[:-1], a_path[1:]))))
    t_opt = math.sqrt(v_top / float(np.min(jmax[moving])))
    curve = fb.block.curve
    piece = np.clip(np.searchsorted(curve.u0, fb.nodes, side="right") - 1, 0,
                    len(curve.dev) - 1)
    return _Reach(ceil=ceil0, tan=tan, kappa=kappa, curv=curv, j_path=j_path, a_path=a_path,
                  v_top=v_top, t_opt=t_opt, dev_node=curve.dev[piece])


def _least_s(fb: _Feed, r: _Reach, m: int, m_u: int) -> float:
    """A lower bound of the duration (s) of every variant of filter lengths ``m`` and ``m_u``:
    the profile under the static ceiling and the largest ``A_t`` they allow, and their lags."""
    with np.errstate(divide="ignore"):
        acc = np.minimum(r.a_path, _AT_SHARE * r.j_path * max(m, m_u) * fb.dt)
    acc = np.minimum(acc[:-1], acc[1:])
    v = _forward_backward(fb.nodes, r.ceil, acc)
    return _profile_s(fb.nodes, v, r.ceil, acc) + (m + m_u) * fb.dt


def _variant_limits(fb: _Feed, r: _Reach, joints, m: int, m_u: int, share: float,
                    compensate: bool, near_of: dict):
    """Speed ceiling (G,) m/s and tangential acceleration (G - 1,) m/s^2 for filter length
    ``m`` samples and rounding ``share`` of the tolerance, or None where this variant would
    plan as the first one did (its rounding bounds no speed). ``near_of`` keeps the nodes
    near each joint per reach (the same for every variant of one filter length)."""
    dt, tol_m, spacing = fb.dt, fb.tol_m, fb.spacing
    ax = fb.limits.present
    jmax = fb.limits.jmax_m_s3[ax]
    u_jump, d_kappa, u_kink, d_tan = joints
    T = m * dt
    T_t = max(m, m_u) * dt  # what the two averages make of a step of A_t
    rounding_m = (tol_m - r.dev_node) * share
    with np.errstate(divide="ignore"):
        v_round = np.sqrt(24.0 * rounding_m / (r.kappa * T * T))
    if (share, compensate) != _VARIANTS[0] and np.all(
        v_round >= r.ceil * math.sqrt(share / _VARIANTS[0][0])
    ):
        return None  # the filter's rounding bounds no speed even at the least share: as tried
    ceil = np.minimum(r.ceil, v_round)
    # per axis, the filtered jerk of A_t: its change over T along the tangent, and the
    # change of the centripetal acceleration v^2 d2r/du2 while the speed changes,
    # 2 v A_t |d2r/du2| at the ceiling
    v_c = np.where(np.isfinite(ceil), ceil, r.v_top)
    with np.errstate(divide="ignore"):  # an axis neither moving nor turning
        a_jerk = np.min(
            _AT_SHARE * jmax / (r.tan[:, ax] / T_t + 2.0 * v_c[:, None] * r.curv[:, ax]), axis=1)
    acc_node = np.minimum(a_jerk, r.a_path)
    reach = r.v_top * T  # the filter window around a jump
    if ("jump", m) not in near_of:  # node ranges (contiguous: the nodes are sorted)
        near = [_near(fb.nodes, ub, reach) for ub in u_jump]
        near_of["jump", m] = (np.array([n[0] if n.size else 0 for n in near], dtype=np.int64),
                              np.array([n[-1] + 1 if n.size else 0 for n in near], dtype=np.int64))
    if "kink" not in near_of:  # the speed while crossing it
        near_of["kink"] = [_near(fb.nodes, uk, spacing) for uk in u_kink]
    # jerk share per (m/s)^2 crossing each jump
    step = np.max(np.abs(d_kappa[:, ax]) / jmax, axis=1, initial=0.0) / T
    _jump_limits(ceil, acc_node, r.j_path * T_t, *near_of["jump", m], step)
    for near, d in zip(near_of["kink"], d_tan):
        with np.errstate(divide="ignore"):
            v_jerk = np.min(jmax * T * dt / np.abs(d[ax]))
        v_cut = 8.0 * tol_m / (T * np.linalg.norm(d))  # corner cut ~ v T |dt| / 8
        ceil[near] = np.minimum(ceil[near], min(v_jerk, v_cut))
    if m_u > 1:  # the parameter's average runs a window of about ceil T_u around each node
        ceil = _spread_minima(fb.nodes, ceil, 0.5 * m_u * dt)
    return ceil, np.minimum(acc_node[:-1], acc_node[1:])


@njit(cache=True)
def _jump_limits(ceil, acc_node, jt, lo, hi, step):
    """Ceiling (G,) m/s and ``A_t`` (G,) m/s^2 lowered, in place, on the nodes ``lo[i]:hi[i]``
    of each curvature jump of ``step[i]`` (s^2/m^2: its share of the jerk per (m/s)^2)."""
    for i in range(lo.shape[0]):
        if step[i] > 0.0:  # a jump on no axis that moves: no ceiling
            cap = math.sqrt((1.0 - _JUMP_AT_SHARE) / step[i])
            for k in range(lo[i], hi[i]):
                ceil[k] = min(ceil[k], cap)
        fastest = 0.0
        for k in range(lo[i], hi[i]):
            fastest = max(fastest, ceil[k])
        # what the step leaves of the jerk at the fastest crossing the ceiling allows
        share = min(max(_JUMP_AT_SHARE, 1.0 - step[i] * fastest * fastest), _AT_SHARE)
        for k in range(lo[i], hi[i]):
            acc_node[k] = min(acc_node[k], share * jt[k])


@njit(cache=True)
def _spread_minima(u, ceil, half_t):
    """Each node's ceiling (m/s) also over the nodes within ``ceil * half_t`` of it (the
    stretch the average of the curve parameter mixes into that node's speed)."""
    out = ceil.copy()
    n = u.shape[0]
    for k in range(n):
        c = ceil[k]
        if not c < np.inf:
            continue
        reach = c * half_t
        j = k - 1
        while j >= 0 and u[k] - u[j] <= reach:
            out[j] = min(out[j], c)
            j -= 1
        j = k + 1
        while j < n and u[j] - u[k] <= reach:
            out[j] = min(out[j], c)
            j += 1
    return out


def _feed_at(fb: _Feed):
    """``feed(u)``: the feed (m/s) at each parameter of the block's curve, the lower of the
    moves meeting there."""
    seg_u0, last = fb.block.seg_u0, len(fb.seg_feed) - 1

    def feed(u: np.ndarray) -> np.ndarray:
        right = np.clip(np.searchsorted(seg_u0, u, side="right") - 1, 0, last)
        left = np.clip(np.searchsorted(seg_u0, u, side="left") - 1, 0, last)
        return np.minimum(fb.seg_feed[right], fb.seg_feed[left])

    return feed


def _plan_profile(fb: _Feed, u: np.ndarray):
    """Samples of a feed block along its exact curve: the jerk-limited profile of
    :mod:`feedplan.profile` (with joints, averaged over :func:`profile.spread_samples` samples
    and capped by :func:`profile.spread_cap`), checked as :func:`_run_filter` checks and,
    where a sample fails, capped there (:data:`_STEP`) and solved again. Returns (positions
    (n, 3) m, source lines (n,)), or None when no clean profile is found (the filter plans
    the block)."""
    curve, lim, dt = fb.block.curve, fb.limits, fb.dt
    feed = _feed_at(fb)
    m, m2 = spread = profile.spread_samples(curve, lim, dt, fb.tol_m)
    cap = None if m == 1 else profile.spread_cap(curve, u, lim, spread, dt, fb.tol_m)
    prof = None
    axes = lim.present
    for rnd in range(_PROFILE_ROUNDS):
        prof = profile.solve(curve, feed, lim, u=u, cap=cap, start=prof)
        first = prof.duration if rnd == 0 else first
        if not math.isfinite(prof.duration) or prof.duration > _PROFILE_GIVE_UP * first:
            return None
        if not prof.duration / dt + m + m2 + 4 < fb.budget:  # the filter's rounds decide
            return None
        us = profile.sample(prof, dt)
        pos = curve.evaluate(us, order=2)[0]
        pos[0] = fb.first
        pos[us >= curve.length] = fb.last
        if m > 1:
            pos = _moving_average(pos, m, 0 if m2 > 1 else 3)
            if m2 > 1:
                pos = _moving_average(pos, m2, 3)
            us = us[np.clip(np.arange(len(pos)) - (m + m2) // 2, 0, len(us) - 1)]
        dist, near = deviation_m(pos, fb.table)
        f_speed, _ = _factors(pos, dt, lim.vmax_m_s[axes], lim.amax_m_s2[axes],
                              lim.jmax_m_s3[axes], np.flatnonzero(axes), dist,
                              fb.seg_feed[near] * (1.0 + SPEED_MARGIN), fb.tol_m, 1.0 - _MARGIN)
        bad = np.flatnonzero(f_speed < 1.0)
        if bad.size == 0:
            seg_at = np.searchsorted(fb.block.seg_u0, us, side="right") - 1
            return pos, fb.seg_lines[np.clip(seg_at, 0, len(fb.seg_lines) - 1)]
        if m == 1 and np.any(dist > fb.tol_m):  # off the curve: slower would not help
            return None
        # sample k differences samples k - 3 .. k, each a mean of m + m2: cap x on the nodes
        lo = np.clip(bad - 3 - (m + m2) // 2, 0, len(us) - 1)
        hi = np.clip(bad + (m + m2) // 2, 0, len(us) - 1)
        scale = np.ones(u.size)
        _lower(u, us, lo, hi, np.minimum(f_speed[bad], _STEP[rnd >= _GENTLE_ROUNDS]) ** 2, scale)
        # every node capped at the last profile (the failed samples' nodes alone: line-contouring-xz
        # 20.963 -> 20.623 s, but its robust table then broke the jerk limit on 88 of 96 plants
        # and short_xz's two-point law lost its certificate: too little reserve for the loop)
        cap = np.minimum(cap if cap is not None else np.inf, scale * prof.x)
    return None


def _plan_feed(
    block: Block,
    path: Path,
    limits: AxisLimits,
    feeds: np.ndarray,
    tol_m: float,
    dt: float,
    budget: int,
    progress: Callable[[float], None],
):
    """Samples of a feed block: positions (n, 3) m and source lines (n,).

    Every filter length and rounding variant is tried (:func:`_variant_limits`, then the
    check-and-slow-down rounds of :func:`_converge`); the fastest clean one is kept.
    ``budget`` is the number of samples left; ``progress`` gets the fraction of the
    block's variants tried.
    """
    fb = _feed_block(block, path, limits, feeds, tol_m, dt, budget)
    joints = _joints(block.curve)
    u = profile.grid(block.curve)  # the profile along the exact curve competes
    if u.size > _JOINTED_NODES and (joints[0].size or joints[2].size):  # long runs of lines
        u = profile.grid(block.curve, spacing_m=profile.GRID_M * u.size / (0.8 * _JOINTED_NODES))
    exact = _plan_profile(fb, u) if u.size <= _PROFILE_NODES else None
    r = _reach(fb)
    best = None
    m_opt, near_of = max(1, round(r.t_opt / dt)), {}
    lengths = sorted({max(1, round(r.t_opt * f / dt)) for f in _T_FRACTIONS}, reverse=True)
    pairs = [(m, m_u) for m in lengths for m_u in sorted({1, max(1, m_opt - m)})]
    variants = [(m, m_u, v) for m, m_u in pairs for v in _VARIANTS]
    for tried, (m, m_u, (share, compensate)) in enumerate(variants):
        progress(tried / len(variants))
        beat = math.inf if best is None else best.duration
        if exact is not None:
            beat = min(beat, (len(exact[0]) - 1) * dt)
        if _least_s(fb, r, m, m_u) >= beat:
            continue
        bounds = _variant_limits(fb, r, joints, m, m_u, share, compensate, near_of)
        if bounds is None:
            continue
        att = _converge(fb, *bounds, m, m_u, compensate, beat)
        if att is not None:
            best = att
    if exact is not None and (best is None or best.duration >= (len(exact[0]) - 1) * dt):
        return exact
    if best is None:
        raise PlanError(
            f"line {path.segments[block.segments[0]].line}: no plan within the limits and "
            f"the tolerance after {_ROUNDS} slow-down rounds"
        )
    return best.pos, _lines(fb, best)


# --------------------------------------------------------------------------- entry point


def _too_long(line: int, dt: float) -> ToolpathError:
    return ToolpathError(f"the plan exceeds the limits of one plan ({MAX_MOTION_S:g} s of motion, "
                         f"{MAX_SAMPLES} samples; dt {dt:g} s)", line)


def _axis_speed_m_s(seg, vmax: np.ndarray) -> float:
    """Largest path speed (m/s) at which the axes can follow ``seg`` somewhere along it."""
    if isinstance(seg, Arc):
        i, j, n = PLANES[seg.plane]
        L, a = seg.length, seg.radius * abs(seg.sweep_rad)
        lo, hi = sorted((seg.start_angle, seg.start_angle + seg.sweep_rad))
        # the speed allowed by the in-plane axes peaks at an end of the sweep or where
        # both are loaded alike (vmax_i |cos| = vmax_j |sin|)
        cross = math.atan2(vmax[i], vmax[j])
        th = np.array([lo, hi, *(c + k * math.pi for c in (cross, -cross) for k in range(-4, 5))])
        th = th[(th >= lo) & (th <= hi)]
        with np.errstate(divide="ignore"):
            v = np.minimum(vmax[i] * L / (a * np.abs(np.sin(th))),
                           vmax[j] * L / (a * np.abs(np.cos(th))))
            rise = abs(seg.rise)
            v_n = vmax[n] * L / rise if rise > 0 and vmax[n] > 0 else np.inf
        return float(min(np.max(v), v_n))
    d = np.abs(seg.end - seg.start) / seg.length
    m = (d > 0) & (vmax > 0)  # an absent axis moves at most 1e-12 m (checked)
    return float(np.min(vmax[m] / d[m])) if m.any() else math.inf


def _allowed_speeds(segs, vmax: np.ndarray) -> np.ndarray:
    """:func:`_axis_speed_m_s` of every move (inf for a move of length 0), lines at once."""
    n = len(segs)
    length = np.fromiter((s.length for s in segs), float, n)
    arc = np.fromiter((isinstance(s, Arc) for s in segs), bool, n)
    allowed = np.full(n, np.inf)
    for k in np.flatnonzero(arc & (length > 0)):
        allowed[k] = _axis_speed_m_s(segs[k], vmax)
    lines = np.flatnonzero(~arc & (length > 0))
    start, end = _line_arrays(segs, lines)
    d = np.abs(end - start) / length[lines, None]
    with np.errstate(divide="ignore", invalid="ignore"):  # 0 / 0 where masked
        allowed[lines] = np.min(np.where((d > 0) & (vmax > 0), vmax / d, np.inf), axis=1)
    return allowed


def _feeds(path: Path, limits: AxisLimits, feed_m_s: float | None):
    """Feed of every move (m/s; rapids inf), capped at what the axes allow along it.

    Returns
    -------
    feeds : ndarray, shape (n,)
    allowed : ndarray, shape (n,)
        Largest path speed the axes allow somewhere along each move, m/s.
    warnings : list of str
    """
    segs = path.segments
    n = len(segs)
    allowed = _allowed_speeds(segs, limits.vmax_m_s)
    rapid = np.fromiter((s.rapid for s in segs), bool, n)
    if feed_m_s is not None:
        out = np.full(n, float(feed_m_s))
    else:
        out = np.fromiter((s.feed_m_s for s in segs), float, n)
        for k in np.flatnonzero(~rapid & ~(np.isfinite(out) & (out > 0)))[:1]:
            where = f"line {segs[k].line}" if segs[k].line else f"move {k + 1}"
            raise OptionError(f"{where}: no feed programmed (F); give feed_m_s")
    out[rapid] = np.inf
    over = np.flatnonzero(~rapid & (out > allowed))
    out[over] = allowed[over]
    warnings = []
    if over.size:
        k = over[0]
        seg = path.segments[k]
        given = feed_m_s if feed_m_s is not None else seg.feed_m_s
        where = f"line {seg.line}" if seg.line else f"move {k + 1}"
        warnings.append(
            f"{where}: feed {given * 60e3:.6g} mm/min is above what the axes allow "
            f"({allowed[k] * 60e3:.6g} mm/min); planned at what the axes allow"
            + (f" (also on {len(over) - 1} more moves)" if len(over) > 1 else ""))
    return out, allowed, warnings


def _move_times(path: Path, feeds: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """Least motion time of each move, s: at its feed or the axis speed, no ramps."""
    length = np.fromiter((s.length for s in path.segments), float, len(path.segments))
    with np.errstate(over="ignore"):
        return length / np.minimum(feeds, allowed)


def move_times_s(path: Path, limits: AxisLimits, feed_m_s: float | None = None) -> np.ndarray:
    """Least motion time of each move, seconds, shape (n_segments,): every move at its feed
    (or ``feed_m_s``) capped at what the axes allow along it, rapids at the axis speed, no
    ramps. Their sum is a lower bound of the plan's duration, what :func:`plan` checks
    against :data:`~oga.defaults.MAX_MOTION_S` before planning. Cheap (no allocation per
    sample).

    Raises
    ------
    OptionError
        A feed move without a feed and no ``feed_m_s``.
    """
    feeds, allowed, _ = _feeds(path, limits, feed_m_s)
    with np.errstate(over="ignore"):
        return _move_times(path, feeds, allowed)


def least_motion_s(path: Path, limits: AxisLimits, feed_m_s: float | None = None) -> float:
    """Least motion time of a path, seconds: the sum of :func:`move_times_s`."""
    with np.errstate(over="ignore"):
        return float(np.sum(move_times_s(path, limits, feed_m_s)))


def _estimate(path: Path, feeds: np.ndarray, allowed: np.ndarray, dt: float) -> np.ndarray:
    """:func:`_move_times`, checked.

    Raises ToolpathError naming the slowest move when the sum exceeds
    :data:`~oga.defaults.MAX_MOTION_S` or :data:`~oga.defaults.MAX_SAMPLES` samples.
    """
    t = _move_times(path, feeds, allowed)
    with np.errstate(over="ignore"):
        total = float(np.sum(t))
    if total > MAX_MOTION_S or total / dt > MAX_SAMPLES:
        k = int(np.argmax(t))
        seg = path.segments[k]
        what = (f"a rapid of {seg.length * 1e3:.6g} mm" if seg.rapid
                else f"{seg.length * 1e3:.6g} mm at F{feeds[k] * 60e3:.6g} mm/min")
        where = f"line {seg.line}" if seg.line else f"move {k + 1}"
        raise ToolpathError(
            f"program would take {total:.3g} s of motion, {total / dt:.3g} samples of {dt:g} s "
            f"(limits {MAX_MOTION_S:g} s, {MAX_SAMPLES} samples): {where} moves {what}",
            source=path.source)
    return t


def program_tolerance_m(path: Path, tol_m: float) -> float:
    """The plan's tolerance, metres: the least, over the feed moves, of their ``G64 P``
    where one is programmed and ``tol_m`` elsewhere (every sample is held to it), within
    :data:`~oga.defaults.TOL_RANGE_M`."""
    each = [s.blend_tol_m or tol_m for s in path.segments if not s.rapid]
    return float(np.clip(min(each, default=tol_m), *TOL_RANGE_M))


def _line_arrays(segs, idx: np.ndarray):
    """Start and end points (len(idx), 3) m of the lines ``segs[idx]``."""
    start = np.array([segs[k].start for k in idx]).reshape(-1, 3)
    end = np.array([segs[k].end for k in idx]).reshape(-1, 3)
    return start, end


def _to_inspect(segs, present: np.ndarray) -> list:
    """The moves :func:`_validate` must look at one by one, in order: arcs, and the lines
    that fail its checks (a point beyond the bounds or not finite, a move of an absent
    axis), found for all lines at once."""
    arc = np.fromiter((isinstance(s, Arc) for s in segs), bool, len(segs))
    lines = np.flatnonzero(~arc)
    start, end = _line_arrays(segs, lines)
    ok = np.all((np.abs(start) <= MAX_COORD_M) & (np.abs(end) <= MAX_COORD_M), axis=1)
    ok &= ~np.any((np.abs(end - start) > 1e-12) & ~present, axis=1)
    arc[lines[~ok]] = True
    return [segs[k] for k in np.flatnonzero(arc)]


def _validate(path: Path, limits: AxisLimits, feed_m_s, tol_m: float, dt: float) -> None:
    if feed_m_s is not None and not (math.isfinite(feed_m_s) and feed_m_s > 0):
        raise OptionError(f"feed_m_s must be a positive finite number, got {feed_m_s!r}")
    if not (TOL_RANGE_M[0] <= tol_m <= TOL_RANGE_M[1]):
        raise OptionError(f"tol_m must be in [{TOL_RANGE_M[0]:g}, {TOL_RANGE_M[1]:g}] m, "
                          f"got {tol_m!r}")
    if not (DT_RANGE_S[0] <= dt <= DT_RANGE_S[1]):
        raise OptionError(f"dt must be in [{DT_RANGE_S[0]:g}, {DT_RANGE_S[1]:g}] s, got {dt!r}")
    present = limits.present
    for s in _to_inspect(path.segments, present):
        pts = np.concatenate([s.start, s.end, s.center if isinstance(s, Arc) else ()])
        if not np.all(np.abs(pts) <= MAX_COORD_M):  # also nan (paths built by hand)
            raise ToolpathError(f"a point beyond {MAX_COORD_M:g} m or not finite", line=s.line)
        if isinstance(s, Arc) and not abs(s.sweep_rad) <= 2.0 * math.pi * _MAX_TURNS:
            raise ToolpathError(f"arc sweep {s.sweep_rad:.6g} rad: more than {_MAX_TURNS} turns",
                                line=s.line)
        span = np.abs(s.end - s.start)
        if isinstance(s, Arc) and s.length > 1e-12:
            i, j, _ = PLANES[s.plane]
            span[i] = span[j] = s.radius
        for k in np.flatnonzero((span > 1e-12) & ~present):
            raise ToolpathError(
                f"moves axis {AXES[k]}, which the machine lacks (0 limits: it must not move)",
                line=s.line,
            )
    if not any(s.length > 1e-12 for s in path.segments):
        raise ToolpathError(f"no motion in {path.source or 'the toolpath'}")


def plane_of(pos: np.ndarray, rapid: np.ndarray, preferred: str):
    """The coordinate plane (``preferred`` first) holding every feed sample of ``pos``
    (its normal coordinate within 1 nm), or None."""
    feed = pos[~rapid]
    if len(feed) == 0:
        return None
    span = feed.max(axis=0) - feed.min(axis=0)
    for name in (preferred, *[p for p in PLANES if p != preferred]):
        if span[PLANES[name][2]] <= 1e-9:
            return name
    return None


def derivatives(pos: np.ndarray, dt: float):
    """Centred differences of positions at rest before and after: v, a at sample k, j at k + 1/2.

    Each is a backward difference shifted by at most two samples, so it obeys
    the same limits as the finite-difference check.
    """
    p = np.concatenate([np.repeat(pos[:1], 2, axis=0), pos, np.repeat(pos[-1:], 2, axis=0)])
    vel = (p[3:-1] - p[1:-3]) / (2 * dt)
    acc = (p[3:-1] - 2 * p[2:-2] + p[1:-3]) / dt**2
    jerk = (p[4:] - 3 * p[3:-1] + 3 * p[2:-2] - p[1:-3]) / dt**3
    return vel, acc, jerk


def _plan_blocks(blocks, path: Path, limits: AxisLimits, seg_feed: np.ndarray,
                 seg_time: np.ndarray, tol_m: float, dt: float, progress):
    """Each block planned from rest to rest, joined: positions (N, 3) m, source lines (N,),
    rapid flags (N,), the first sample on ``path.start``; ``progress`` by ``seg_time``."""
    budget = int(min(MAX_SAMPLES, MAX_MOTION_S / dt))
    done, whole = 0.0, float(np.sum(seg_time))
    report = progress if progress is not None else (lambda fraction: None)
    pos, line, rapid = [path.start[None, :]], [np.zeros(1, np.int64)], [np.zeros(1, bool)]
    used = 1
    for blk in blocks:
        share = float(np.sum(seg_time[blk.segments]))
        if _one_line(blk, seg_feed):  # ruckig's profile along the line
            p, ln = _straight_run(blk, path, limits, dt, budget - used, seg_feed)
        else:
            p, ln = _plan_feed(blk, path, limits, seg_feed, tol_m, dt, budget - used,
                               lambda f: report(min((done + f * share) / whole, 1.0)))
        pos.append(p[1:])  # p[0] is where the previous block ended, at rest
        line.append(ln[1:])
        rapid.append(np.full(len(p) - 1, blk.rapid))
        used += len(p) - 1
        done += share
        report(min(done / whole, 1.0))
    if blocks:  # the first sample belongs to the first move
        line[0][0], rapid[0][0] = line[1][0], rapid[1][0]
    return np.concatenate(pos), np.concatenate(line), np.concatenate(rapid)


def plan(
    path: Path,
    limits: AxisLimits,
    *,
    feed_m_s: float | None = None,
    tol_m: float = TOL_M,
    dt: float = DT_S,
    progress: Callable[[float], None] | None = None,
) -> Setpoints:
    """Plan jerk-limited setpoints along a path.

    Parameters
    ----------
    path : Path
        Programmed moves, metres.
    limits : AxisLimits
        Per-axis velocity, acceleration and jerk limits (SI).
    feed_m_s : float, optional
        Path speed (m/s) for every feed move, overriding the programmed feeds.
    tol_m : float
        Largest distance of a feed setpoint to the programmed geometry, metres
        (within :data:`~oga.defaults.TOL_RANGE_M`), where the program sets no ``G64 P``
        (see :func:`program_tolerance_m`; a warning says when P changes it).
    dt : float
        Sample period, seconds (within :data:`~oga.defaults.DT_RANGE_S`).
    progress : callable, optional
        Called as ``progress(fraction)``, ``fraction`` in [0, 1] (by the moves' least
        motion time planned so far), after every block and every variant tried in it.

    Returns
    -------
    Setpoints
        Starting at rest on ``path.start`` and ending at rest (last three samples
        equal) on the end of the last move. Finite differences of ``pos`` meet every
        axis limit, the path speed stays within 1.005 x the feed, every feed sample
        lies within ``tol_m`` of the programmed lines and arcs. ``vel`` and ``acc`` are
        centred differences of ``pos`` at each sample, ``jerk`` the third difference
        centred half a sample later (each within the limits like ``pos``'s backward
        differences). A feed above what the axes allow along a move is planned at what
        they allow, and ``warnings`` says so.

    Raises
    ------
    OptionError
        Bad ``feed_m_s``/``tol_m``/``dt``, or a feed move without feed and no override.
    ToolpathError
        No motion; the path moves an axis whose limits are 0; the motion would take
        more than :data:`~oga.defaults.MAX_MOTION_S` or
        :data:`~oga.defaults.MAX_SAMPLES` samples (estimated before planning, enforced
        while planning).
    PlanError
        No plan meets the limits.
    """
    _validate(path, limits, feed_m_s, tol_m, dt)
    seg_feed, allowed, warnings = _feeds(path, limits, feed_m_s)
    seg_time = _estimate(path, seg_feed, allowed, dt)
    given, tol_m = tol_m, program_tolerance_m(path, tol_m)
    if tol_m != given:
        warnings.append(f"the program's G64 P sets the tolerance to {tol_m * 1e3:.6g} mm "
                        f"(instead of {given * 1e3:.6g} mm)")
    blocks = blocks_of(path, tol_m * FIT_TOL_FRACTION, Blending(tol_m * BLEND_TOL_FRACTION,
                                                               limits, seg_feed))
    pos, line, rapid = _plan_blocks(blocks, path, limits, seg_feed, seg_time, tol_m, dt, progress)
    vel, acc, jerk = derivatives(pos, dt)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    return Setpoints(
        dt=dt,
        s=s,
        pos=pos,
        vel=vel,
        acc=acc,
        jerk=jerk,
        block=line,
        rapid=rapid,
        plane=plane_of(pos, rapid, path.plane),
        source=path.source,
        warnings=tuple(warnings),
    )
