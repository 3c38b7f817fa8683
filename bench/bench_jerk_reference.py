"""Benchmark: the best jerk-limited time along the planner's own blocks, at the planner's shares
and at the full axis limits.

Run: ``python bench/bench_jerk_reference.py [--only NAME,...] [--threshold R] [--top N]
[--joints free|sampled] [--spacing-mm D] [--max-nodes N] [--max-iter N] [--time-limit S]
[--refine N] [--shared DIR]`` from the repository root (CasADi and toppra are dev dependencies:
``pip install -e '.[dev]'``). A benchmark, not a test: it prints figures and asserts nothing.
``bench/bench_plan.py`` uses the same functions for its ``jerk`` columns.

For a program (default: short_segments, plasmatest, 51MeanderAve, line-contouring-xz; any of
``bench_plan``'s by ``--only``; the GPL programs of ``shared/toolpaths/external`` are read
there, never copied here) it plans with :func:`feedplan.plan.plan` at ucp710's planning limits
(its ``[planner]`` shares of the axis acceleration and jerk: the position loop's reserve),
captures the blocks the planner moved along (``blocks_of``, as ``bench_plan._Stages`` does) and
the planned time of each block, and per block, from rest to rest as the planner stops there,
twice: at those shares (what the planner may use: planned / this is the planner's own loss)
and at the full axis limits (planned / this adds what the reserve costs; the quotient of the
two references is the reserve's price):

- ``toppra``: toppra's time along the block, per-axis v and a, path speed at most
  ``F (1 + SPEED_MARGIN)``, no jerk (:func:`bench_plan.toppra_bound_s`): a lower bound;
- ``jerk``: a time-optimal parameterisation with the per-axis jerk limits as well (the whole
  jerk of the limit set, not the planner's internal shares of it). A block the planner plans
  as one line (a rapid, a lone feed line, a straight run of micro-segments) is exact: ruckig's
  1-D rest-to-rest optimum with the limits projected on the line. A curved block is solved by
  IPOPT (CasADi) when the planner runs it more than ``1 + --threshold`` times its toppra time
  at the shares (elsewhere toppra's time stands in: a lower bound of the optimum, so the
  program's planned / jerk is then an upper bound of the planner's loss; marked ``*``):
  multiple shooting pinned to a grid of the curve parameter ``u``: nodes ``u_k`` (every piece
  boundary, every knot of a fitted spline, a spacing of ``--spacing-mm``, at least 8 per
  piece), states ``udot_k``, ``uddot_k``, a constant ``udddot`` and a free duration ``h_k``
  per interval; the interval's motion is integrated exactly (a cubic in time reaching
  ``u_{k+1}``), so the rest-to-rest ends are exact. At every node, on both sides, per axis
  ``v = r' udot``, ``a = r'' udot^2 + r' uddot``, ``j = r''' udot^3 + 3 r'' udot uddot + r'
  udddot`` (with the jerk of the interval before and after) within the limits, and
  ``|r'| udot <= F (1 + SPEED_MARGIN)``. Minimise ``sum h_k``. Joints, piece boundaries
  where ``r'`` or ``r''`` jumps (a kink, a curvature step: an infinite jerk at any speed
  along the exact curve), are ``--joints free`` (default: nothing asked there, as toppra
  asks nothing at them; the planner's filter rounds them within the tolerance) or
  ``sampled`` (the step must look, at the 1 ms sample period, like a jerk within the
  limits: ``|dr''| udot^2 <= J dt``, ``|dr'| udot <= min(A dt, J dt^2)``).

A block of more than ``--max-nodes`` nodes is split into consecutive windows of at most that
many nodes, each solved with the speed and acceleration at its boundaries free (at rest only at
the block's real start and end): a relaxation, whose optimum is a lower bound of the block's
(planned / jerk leans conservative), though IPOPT's local optimum of each window is again an
upper estimate (micro_2k's one block: whole 2.367 s, in 4 windows 2.366 s at the shares); each
window's 1 ms re-check covers its own samples, not the motion across a window's end.

IPOPT returns a local optimum: a feasible time, i.e. an UPPER estimate of the jerk-limited
optimum along the same curves and stops (the true optimum lies between ``toppra`` and
``jerk``). It is an optimum along the exact curve: the planner may leave the curve by the
tolerance (its filter rounds a short corner blend, lowering ``r'''``), so on blocks of tight
blends the planner can be faster than ``jerk``. Each solution is re-checked independently:
sampled at 1 ms (``u(t)`` from the cubics, ``r(u)`` from the curve), backward differences of
the positions; the worst ratios of v, a, j to the limits and of the speed to the feed where
no difference spans a joint, and the worst jerk ratio of the differences that span one
(``recheck v/a/j/F/j@joints``). While a ratio away from the joints exceeds 1.01 the block
is solved again with every interval halved (``--refine`` times at most; a failed re-solve
keeps the last solved grid). Solves are bounded by ``--max-iter`` and ``--time-limit``
(IPOPT CPU seconds) per solve; a block that does not solve is reported with IPOPT's status,
and toppra's time then stands in for it.

The second table lists, per program, the blocks where planned / jerk (at the shares) is
largest: their planned, toppra and jerk times.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path as FilePath

import numpy as np

sys.path.insert(0, str(FilePath(__file__).resolve().parent))
from bench_plan import (MACHINE, ROOT, _PerBlock, _projected, _Stages,  # noqa: E402
                        programs, rest_to_rest_s, toppra_bound_s)

from feedplan.check import SPEED_MARGIN  # noqa: E402
from feedplan.gcode import parse_gcode  # noqa: E402
from feedplan.limits import AxisLimits  # noqa: E402
from feedplan.path import Line  # noqa: E402
from feedplan.plan import plan  # noqa: E402

#: Programs benchmarked by default (``--only`` names any of bench_plan's): those where the jerk
#: limit binds most.
PROGRAMS = ("short_segments_0.001", "plasmatest", "51MeanderAve", "line-contouring-xz")
DT = 1e-3  # sample period of the re-check and of the joints' jerk, s
BIG = 1e6  # no limit (a rapid's speed)


# --------------------------------------------------------------------------- capture


# --------------------------------------------------------------------------- one block


@dataclass
class JerkResult:
    """Jerk-limited time of one block: ``time_s`` (nan if not solved), ``status`` (IPOPT's,
    or "ruckig"), ``recheck`` (worst v, a, j, speed ratios at 1 ms), ``nodes``, ``cpu_s``,
    ``joints`` (boundaries where r' or r'' jumps)."""

    time_s: float
    status: str
    recheck: tuple = (math.nan,) * 5
    nodes: int = 0
    cpu_s: float = 0.0
    joints: int = 0


def _grid(curve, spacing_m: float, per_piece: int, max_nodes: int) -> np.ndarray:
    """Nodes along ``curve``: every piece boundary and every knot of a fitted spline (where
    its third derivative jumps), at most ``spacing_m`` apart, at least ``per_piece``
    intervals per piece (a short corner blend is resolved), at most about ``max_nodes``
    (then a coarser spacing)."""
    u0 = curve.u0
    lens = np.diff(u0)
    knots = [u0[p] + np.unique(curve.splines[int(curve.org[p, 0])].t)
             for p in np.flatnonzero(curve.kind == 2)]
    while True:
        n = np.maximum(per_piece, np.ceil(lens / spacing_m)).astype(int)
        u = np.concatenate([np.linspace(a, b, k, endpoint=False) for a, b, k in
                            zip(u0[:-1], u0[1:], n)] + [u0[-1:]] + knots)
        u = np.unique(np.clip(u, 0.0, u0[-1]))
        u = u[np.concatenate([[True], np.diff(u) > 1e-9])]  # no interval shorter than 1 nm
        # the piece boundaries exactly (a knot rounded next to one is dropped)
        near = np.abs(u - u0[np.clip(np.searchsorted(u0, u), 1, len(u0) - 1) - 1]) < 1e-9
        near |= np.abs(u - u0[np.clip(np.searchsorted(u0, u), 0, len(u0) - 1)]) < 1e-9
        u = np.union1d(u[~near], u0)
        if u.size <= max_nodes or spacing_m > curve.length:
            return u
        spacing_m *= 1.5


def _feed_at(blk, segs, u: np.ndarray) -> np.ndarray:
    """Programmed feed (times 1 + SPEED_MARGIN) of the move at each ``u``, m/s."""
    feed = np.array([segs[i].feed_m_s for i in blk.segments])
    feed = np.where(np.isfinite(feed), feed * (1.0 + SPEED_MARGIN), BIG)
    k = np.clip(np.searchsorted(blk.seg_u0, u, side="right") - 1, 0, len(feed) - 1)
    return feed[k]


def _initial(du, ceil, acc):
    """A slow, rest-to-rest guess: forward-backward passes under ``ceil`` with ``acc``."""
    v = np.minimum(ceil, np.sqrt(2 * acc * np.concatenate([[0], np.cumsum(du)])))
    v = np.minimum(v, np.sqrt(2 * acc * np.concatenate([np.cumsum(du[::-1])[::-1], [0]])))
    for _ in range(2):
        for k in range(1, len(v)):
            v[k] = min(v[k], math.sqrt(v[k - 1] ** 2 + 2 * acc * du[k - 1]))
        for k in range(len(v) - 2, -1, -1):
            v[k] = min(v[k], math.sqrt(v[k + 1] ** 2 + 2 * acc * du[k]))
    v[0] = v[-1] = 0.0
    h = 2 * du / np.maximum(v[:-1] + v[1:], 1e-9)
    return v, h


def solve_block(blk, segs, limits: AxisLimits, spacing_m: float, max_nodes: int,
                max_iter: int, time_limit_s: float, joints: str = "free",
                refine: int = 3) -> JerkResult:
    """Time-optimal jerk-limited rest-to-rest time along ``blk.curve`` (module docstring;
    ``joints``: "free" or "sampled"). A grid of more than ``max_nodes`` nodes is split into
    consecutive windows of at most ``max_nodes`` nodes, each solved with its boundary speed
    and acceleration free (at rest only at the block's ends): a relaxation (module docstring);
    the re-check and status are the worst over the windows, each window's re-check covering
    its own samples only."""
    c0 = time.process_time()
    u = _grid(blk.curve, spacing_m, 8, 1 << 40)
    if u.size <= max_nodes:
        res = _solve_refined(blk, segs, limits, u, max_nodes, max_iter, time_limit_s, joints,
                             refine, (True, True))
    else:
        cuts = np.linspace(0, u.size - 1, -(-(u.size - 1) // (max_nodes - 1)) + 1).astype(int)
        parts = [_solve_refined(blk, segs, limits, u[a:b + 1], max_nodes, max_iter,
                                time_limit_s, joints, refine, (a == 0, b == u.size - 1))
                 for a, b in zip(cuts[:-1], cuts[1:])]
        bad = [r.status for r in parts if not math.isfinite(r.time_s)]
        res = JerkResult(float(sum(r.time_s for r in parts)),
                         f"{len(parts)} windows" + (f", {bad[0]}" if bad else ""),
                         tuple(np.fmax.reduce(np.array([r.recheck for r in parts]), axis=0)),
                         sum(r.nodes for r in parts) - len(parts) + 1, 0.0,
                         sum(r.joints for r in parts))
    res.cpu_s = time.process_time() - c0
    return res


def _solve_refined(blk, segs, limits, u, max_nodes, max_iter, time_limit_s, joints, refine,
                   rest) -> JerkResult:
    """:func:`_solve_on_grid` on ``u``, again with every interval halved (``refine`` times at
    most, while the grid stays within ``max_nodes``) while the 1 ms re-check away from the
    joints exceeds a limit by more than 1 % (the last solved solution, or the last failure)."""
    res = None
    for _ in range(refine + 1):
        new = _solve_on_grid(blk, segs, limits, u, max_iter, time_limit_s, joints, rest=rest)
        if not math.isfinite(new.time_s):  # IPOPT failed: once more from a slower guess
            new = _solve_on_grid(blk, segs, limits, u, max_iter, time_limit_s, joints, 0.2,
                                 rest)
        if res is None or math.isfinite(new.time_s) or not math.isfinite(res.time_s):
            res = new
        if max(new.recheck[:4]) <= 1.01 or 2 * u.size > max_nodes:
            break
        u = np.sort(np.concatenate([u, (u[1:] + u[:-1]) / 2]))
    return res


def _joints(curve, u: np.ndarray, ax: np.ndarray) -> np.ndarray:
    """Which nodes ``u`` are piece boundaries where r' (above 1e-6) or r'' (above 1e-3 1/m)
    jumps on an axis of ``ax``: a kink or a curvature step."""
    at = np.isin(u, curve.u0[1:-1])
    _, r1r, r2r = curve.evaluate(u[at], left=False, order=2)
    _, r1l, r2l = curve.evaluate(u[at], left=True, order=2)
    out = np.zeros(u.size, bool)
    out[at] = ((np.abs(r1r - r1l)[:, ax].max(axis=1) > 1e-6)
               | (np.abs(r2r - r2l)[:, ax].max(axis=1) > 1e-3))
    return out


def _solve_on_grid(blk, segs, limits: AxisLimits, u: np.ndarray, max_iter: int,
                   time_limit_s: float, joints: str, guess: float = 0.7,
                   rest: tuple = (True, True)) -> JerkResult:
    """:func:`solve_block` on the nodes ``u``, IPOPT started from a profile at ``guess``
    times the nodes' speed ceilings; at rest at the first / last node where ``rest`` says
    so (elsewhere the speed and acceleration there are free)."""
    import casadi as ca

    curve = blk.curve
    n = len(u) - 1  # intervals
    du = np.diff(u)
    # each side of a node (0.1 nm off it: inside a spline, d3r/du3 jumps at its knots)
    _, r1r, r2r, r3r = curve.evaluate(np.minimum(u + 1e-10, curve.length), left=False)
    _, r1l, r2l, r3l = curve.evaluate(np.maximum(u - 1e-10, 0.0), left=True)
    feed = np.minimum(_feed_at(blk, segs, u), _feed_at(blk, segs, u - 1e-12))
    ax = np.flatnonzero(limits.present)
    vmax, amax, jmax = limits.vmax_m_s, limits.amax_m_s2, limits.jmax_m_s3
    joint = _joints(curve, u, ax)
    jump2 = joint & (np.abs(r2r - r2l)[:, ax].max(axis=1) > 0.0)

    # a speed ceiling per node (for the guess and the scaling only)
    sp = np.linalg.norm(r1r, axis=1)
    ceil = feed / np.maximum(sp, 1e-12)
    for r, lim, p in ((r1r, vmax, 1), (r2r, amax, 2), (r3r, jmax, 3)):
        for i in ax:
            with np.errstate(divide="ignore"):
                ceil = np.minimum(ceil, (lim[i] / np.abs(r[:, i])) ** (1 / p))
    for i in ax:
        with np.errstate(divide="ignore"):
            ceil = np.minimum(ceil, np.where(jump2, np.sqrt(jmax[i] * DT / np.abs(
                r2r[:, i] - r2l[:, i])), np.inf))
    acc_ref = float(np.min(amax[ax]))
    v0, h0 = _initial(du, guess * ceil, 0.3 * guess * acc_ref)
    vs = max(float(np.max(v0)), 1e-6)
    as_, js = acc_ref, float(np.min(jmax[ax]))

    V = ca.SX.sym("v", n + 1)
    A = ca.SX.sym("a", n + 1)
    Jk = ca.SX.sym("j", n)
    E = ca.SX.sym("e", n)  # h_k / h0_k
    v, a, j, h = vs * V, as_ * A, js * Jk, ca.DM(h0) * E
    g, lbg, ubg = [], [], []

    def add(expr, lo, hi):
        g.append(expr)
        size = expr.shape[0]
        lbg.append(np.broadcast_to(lo, size))
        ubg.append(np.broadcast_to(hi, size))

    vl, vr, al, ar = v[:-1], v[1:], a[:-1], a[1:]
    add((vl * h + al * h**2 / 2 + j * h**3 / 6) / ca.DM(du), 1.0, 1.0)
    add((vr - vl - al * h - j * h**2 / 2) / vs, 0.0, 0.0)
    add((ar - al - j * h) / as_, 0.0, 0.0)
    # right side of nodes 0..n-1 (with the jerk after), left side of nodes 1..n (before)
    both = np.flatnonzero(joint)
    sides = ((np.arange(n), r1r, r2r, r3r, j), (np.arange(1, n + 1), r1l, r2l, r3l, j))
    for s, (idx, r1, r2, r3, jj) in enumerate(sides):
        # v, a, speed: every node once (right side) and the left side of joints and the end
        va = idx if s == 0 else np.union1d(both, [n])
        vv, aa = v[va.tolist()], a[va.tolist()]
        for i in ax:
            add(ca.DM(r1[va, i]) * vv / vmax[i], -1.0, 1.0)
            add((ca.DM(r2[va, i]) * vv**2 + ca.DM(r1[va, i]) * aa) / amax[i], -1.0, 1.0)
            vj, aj = v[idx.tolist()], a[idx.tolist()]
            add((ca.DM(r3[idx, i]) * vj**3 + 3 * ca.DM(r2[idx, i]) * vj * aj
                 + ca.DM(r1[idx, i]) * jj) / jmax[i], -1.0, 1.0)
        fin = feed[va] < BIG
        if fin.any():
            add(ca.DM(np.linalg.norm(r1[va], axis=1)[fin] / feed[va][fin]) * v[va[fin].tolist()],
                -np.inf, 1.0)
    for i in ax:  # steps at joints, as seen at the sample period
        if both.size and joints == "sampled":
            vb = v[both.tolist()]
            d1, d2 = np.abs(r1r - r1l)[both, i], np.abs(r2r - r2l)[both, i]
            if d1.max() > 1e-6:
                add(ca.DM(d1) * vb / min(amax[i] * DT, jmax[i] * DT**2), -np.inf, 1.0)
            if d2.max() > 1e-3:
                add(ca.DM(d2) * vb**2 / (jmax[i] * DT), -np.inf, 1.0)

    x = ca.vertcat(V, A, Jk, E)
    lbx = np.concatenate([np.zeros(n + 1), np.full(n + 1, -np.inf), np.full(n, -np.inf),
                          np.full(n, 1e-4)])
    ubx = np.concatenate([np.full(n + 1, np.inf), np.full(n + 1, np.inf), np.full(n, np.inf),
                          np.full(n, 1e4)])
    for k in [k for k, r in zip((0, n), rest) if r]:  # at rest at the ends asked
        ubx[k] = lbx[k] = 0.0
        ubx[n + 1 + k] = lbx[n + 1 + k] = 0.0
    a0 = np.concatenate([np.diff(v0) / h0, [0.0]])
    a0[0] = 0.0
    x0 = np.concatenate([v0 / vs, a0 / as_, np.zeros(n), np.ones(n)])
    t0 = float(np.sum(h0))
    nlp = dict(x=x, f=ca.sum1(ca.DM(h0) * E) / t0, g=ca.vertcat(*g))
    opts = {"print_time": False, "ipopt": {"print_level": 0, "max_iter": max_iter,
                                           "max_cpu_time": time_limit_s, "tol": 1e-7,
                                           "mu_strategy": "adaptive", "sb": "yes"}}
    solver = ca.nlpsol("jerk", "ipopt", nlp, opts)
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=np.concatenate(lbg), ubg=np.concatenate(ubg))
    status = solver.stats()["return_status"]
    xs = np.asarray(sol["x"]).ravel()
    vk, ak = xs[:n + 1] * vs, xs[n + 1:2 * n + 2] * as_
    jk, hk = xs[2 * n + 2:3 * n + 2] * js, xs[3 * n + 2:] * h0
    chk = recheck(curve, u, vk, ak, jk, hk, limits, lambda uu: _feed_at(blk, segs, uu),
                  u[joint], rest)
    ok = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    return JerkResult(float(np.sum(hk)) if ok else math.nan, status, chk, n + 1, 0.0,
                      int(joint.sum()))


def recheck(curve, u, v, a, j, h, limits: AxisLimits, feed_of, u_joints,
            rest: tuple = (True, True)) -> tuple:
    """Worst v, a, j and speed ratios of the solution sampled at ``DT`` (finite differences
    of the positions ``r(u(t))``, at rest before and after where ``rest`` says so, else
    only the samples within ``u[0]..u[-1]``) where no difference spans one of
    the joints ``u_joints``, and the worst jerk ratio of the differences that do (nan if
    none)."""
    tk = np.concatenate([[0.0], np.cumsum(h)])
    t = np.arange(0.0, tk[-1] + DT * rest[1], DT)  # a free end: no sample held past it
    k = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(h) - 1)
    tau = np.minimum(t - tk[k], h[k])
    us = np.clip(u[k] + v[k] * tau + a[k] * tau**2 / 2 + j[k] * tau**3 / 6, u[0], u[-1])
    us = np.concatenate([[u[0]] * (3 * rest[0]), us, [u[-1]] * (3 * rest[1])])
    p = curve.evaluate(us, order=2)[0]
    ax = limits.present
    # samples before each joint: a difference over samples i..i+m spans it if they differ
    before = np.searchsorted(np.asarray(u_joints), us, side="left")
    out, at_joints = [], math.nan
    for m, lim in ((1, limits.vmax_m_s), (2, limits.amax_m_s2), (3, limits.jmax_m_s3)):
        ratio = np.max(np.abs(np.diff(p, m, axis=0)[:, ax]) / DT**m / lim[ax], axis=1)
        spans = before[m:] != before[:-m]
        out.append(float(np.max(ratio[~spans], initial=0.0)))
        if m == 3 and spans.any():
            at_joints = float(np.max(ratio[spans]))
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) / DT
    feed = np.minimum(feed_of(us[1:]), feed_of(us[:-1]))
    out.append(float(np.max((speed / feed)[before[1:] == before[:-1]], initial=0.0)))
    return (*out, at_joints)


def straight_block(seg: Line, limits: AxisLimits) -> JerkResult:
    """ruckig's exact rest-to-rest time along a line (limits projected, speed <= F)."""
    d = (seg.end - seg.start) / seg.length
    v = _projected(d, limits.vmax_m_s)
    if not seg.rapid:
        v = min(v, seg.feed_m_s * (1.0 + SPEED_MARGIN))
    return JerkResult(rest_to_rest_s(seg.length, v, _projected(d, limits.amax_m_s2),
                                     _projected(d, limits.jmax_m_s3)), "ruckig")


# --------------------------------------------------------------------------- program


def straight_of(blk, segs) -> Line | None:
    """The line a block runs along when the planner plans it as one line (ruckig): a rapid, a
    lone feed line or a straight run of micro-segments at one feed (``bench_plan``'s rule), else
    None."""
    if not blk.curve.is_line or len({segs[i].feed_m_s for i in blk.segments}) > 1:
        return None
    first, last = segs[blk.segments[0]], segs[blk.segments[-1]]
    return Line(first.start, last.end, first.feed_m_s, rapid=first.rapid, line=first.line)


def capture(path, limits: AxisLimits):
    """Plan ``path`` at ``limits``: the setpoints, the blocks the planner moved along and the
    planned time of each (s)."""
    with _Stages() as st, _PerBlock() as pb:
        sp = plan(path, limits)
    if len(pb.times) != len(st.blocks):  # the planner's block functions changed
        raise RuntimeError(f"{len(pb.times)} planned blocks for {len(st.blocks)} blocks")
    return sp, st.blocks, pb.times


def chosen_blocks(blocks, segs, planned, toppra, threshold: float, top: int) -> set[int]:
    """The curved blocks IPOPT solves: those the planner runs more than ``1 + threshold`` times
    their toppra time (elsewhere toppra's time stands in, a lower bound of the jerk-limited
    optimum: the program's ratio is then an upper bound of the planner's loss), the ``top`` of
    them where the planner loses most (0: all)."""
    curved = [b for b, blk in enumerate(blocks)
              if straight_of(blk, segs) is None and planned[b] > (1.0 + threshold) * toppra[b]]
    curved.sort(key=lambda b: -(planned[b] - toppra[b]))
    return set(curved[:top] if top else curved)


def block_references(path, blocks, planned, limits: AxisLimits, chosen: set[int], args,
                     log=None, toppra=None) -> list[dict]:
    """Per block at ``limits``: its toppra time (``toppra``, or computed) and its jerk-limited
    reference (ruckig for a straight block, IPOPT for the ``chosen`` curved ones, else toppra's
    time, status "toppra"); ``log(text)`` gets a line per IPOPT solve."""
    segs = path.segments
    rows = []
    for b, blk in enumerate(blocks):
        tp, note = (toppra[b], "") if toppra is not None else toppra_bound_s(path, limits, [blk])
        line = straight_of(blk, segs)
        first = segs[blk.segments[0]]
        r = dict(i=b, line=first.line, planned=planned[b], toppra=tp, note=note,
                 straight=line is not None, pieces=len(blk.curve.kind), length=blk.curve.length)
        if line is not None:
            r["jerk"] = straight_block(line, limits)
        elif b in chosen:
            j = solve_block(blk, segs, limits, args.spacing_mm * 1e-3, args.max_nodes,
                            args.max_iter, args.time_limit, args.joints, args.refine)
            if not math.isfinite(j.time_s):  # not solved: toppra's time stands in
                j = JerkResult(tp, f"toppra ({j.status})", j.recheck, j.nodes, j.cpu_s, j.joints)
            r["jerk"] = j
            if log is not None:
                log(f"    block {b:3d} (line {r['line']}, {r['pieces']} pieces, "
                    f"{r['length'] * 1e3:.1f} mm, {j.nodes} nodes, {j.joints} joints): "
                    f"planned {r['planned']:.3f} toppra {tp:.3f} jerk {j.time_s:.3f} s; "
                    f"{j.status}; recheck v/a/j/F/j@joints "
                    f"{'/'.join(f'{x:.3f}' for x in j.recheck)}; {j.cpu_s:.1f} cpu s")
        else:
            r["jerk"] = JerkResult(tp, "toppra")
        rows.append(r)
    return rows


def totals(rows) -> dict:
    """A program's sums over its blocks: planned, toppra, jerk (s), and whether toppra stands in
    for a curved block (``mixed``)."""
    return dict(planned=sum(r["planned"] for r in rows), toppra=sum(r["toppra"] for r in rows),
                jerk=sum(r["jerk"].time_s for r in rows),
                mixed=any(r["jerk"].status.startswith("toppra") for r in rows))


def measure(name: str, text: str, machine, args) -> dict:
    """Plan one program at ``machine``'s planning limits (its ``[planner]`` shares); per block
    its planned time and, at those shares and at the full axis limits, its toppra and
    jerk-limited times."""
    path = parse_gcode(text, source=name)
    shares, full = machine.planning_limits(), machine.axis_limits()
    sp, blocks, planned = capture(path, shares)
    tp = [toppra_bound_s(path, shares, [blk])[0] for blk in blocks]
    chosen = chosen_blocks(blocks, path.segments, planned, tp, args.threshold, args.top)
    out = dict(name=name, plan_s=sp.duration)
    for label, limits, known in (("shares", shares, tp), ("full", full, None)):
        print(f"  {name} at the {label} limits:", flush=True)
        out[label] = block_references(path, blocks, planned, limits, chosen, args,
                                      lambda t: print(t, flush=True), known)
    return out


def add_reference_args(ap) -> None:
    """The options of the IPOPT reference (shared with bench_plan)."""
    ap.add_argument("--threshold", type=float, default=0.02,
                    help="IPOPT solves the curved blocks planned above 1 + this times their "
                         "toppra time (elsewhere toppra's time stands in)")
    ap.add_argument("--top", type=int, default=0,
                    help="of those, only the N where the planner loses most (0: all)")
    ap.add_argument("--spacing-mm", type=float, default=0.2, help="grid spacing along u, mm")
    ap.add_argument("--max-nodes", type=int, default=6000, help="most nodes of one block")
    ap.add_argument("--max-iter", type=int, default=3000, help="IPOPT iterations per block")
    ap.add_argument("--time-limit", type=float, default=300.0, help="IPOPT CPU s per block")
    ap.add_argument("--refine", type=int, default=3,
                    help="most re-solves on a grid twice as fine while the re-check fails")
    ap.add_argument("--joints", choices=("free", "sampled"), default="free",
                    help="steps of r' and r'' at piece boundaries: free, or as seen at 1 ms")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="comma-separated program names (as bench_plan names them)")
    add_reference_args(ap)
    ap.add_argument("--shared", type=FilePath, default=ROOT.parent / "shared",
                    help="the shared folder holding toolpaths/external (default ../shared)")
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else set(PROGRAMS)
    print(f"{MACHINE.name}: planned at its [planner] shares (acceleration "
          f"{MACHINE.planner.accel_fraction:g}, jerk {MACHINE.planner.jerk_fraction:g}); "
          f"dt {DT * 1e3:g} ms, joints {args.joints}, grid {args.spacing_mm:g} mm; load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    results = []
    for name, text in programs(args.shared, only):
        c0, w0 = time.process_time(), time.perf_counter()
        print(f"{name}:", flush=True)
        res = measure(name, text, MACHINE, args)
        res["cpu"], res["wall"] = time.process_time() - c0, time.perf_counter() - w0
        results.append(res)
    print()
    head = (f"{'program':20s} {'limits':>6s} {'blocks':>6s} {'ipopt':>5s} {'plan_s':>8s} "
            f"{'toppra_s':>8s} {'jerk_s':>9s} {'plan/jerk':>9s} {'jerk/toppra':>11s} "
            f"{'recheck v/a/j/F/j@joints':>29s} {'>1.01':>5s} {'faster':>6s} {'cpu_s':>7s}")
    print(head)
    print("-" * len(head))
    for res in results:
        for label in ("shares", "full"):
            rows = res[label]
            tot = totals(rows)
            ipopt = [r["jerk"] for r in rows if r["jerk"].status not in ("ruckig", "toppra")]
            checks = [j.recheck for j in ipopt if math.isfinite(j.time_s)]
            worst = np.fmax.reduce(np.array(checks or [(math.nan,) * 5]), axis=0)  # nan: none
            over = sum(max(c[:4]) > 1.01 for c in checks)
            faster = sum(r["planned"] < r["jerk"].time_s for r in rows)
            print(f"{res['name']:20s} {label:>6s} {len(rows):6d} {len(ipopt):5d} "
                  f"{res['plan_s']:8.3f} {tot['toppra']:8.3f} {tot['jerk']:8.3f}"
                  f"{'*' if tot['mixed'] else ' '} {res['plan_s'] / tot['jerk']:9.3f} "
                  f"{tot['jerk'] / tot['toppra']:11.3f} "
                  f"{'/'.join(f'{x:.3f}' for x in worst):>29s} {over:5d} {faster:6d} "
                  f"{res['cpu']:7.1f}")
    print("(* toppra's time stands in for curved blocks planned within 1 + threshold of it, or "
          "not solved: a lower bound there; recheck: worst over the IPOPT blocks; >1.01: IPOPT "
          "blocks whose re-check away from the joints exceeds 1.01; faster: blocks the planner "
          "runs faster than the reference)")
    print()
    print("blocks where planned / jerk (at the shares) is largest:")
    for res in results:
        rows = sorted(res["shares"], key=lambda r: -r["planned"] / r["jerk"].time_s)
        for r in rows[:5]:
            kind = "line" if r["straight"] else f"{r['pieces']} pieces"
            print(f"  {res['name']:20s} block {r['i']:3d} line {r['line']:5d} ({kind}, "
                  f"{r['length'] * 1e3:7.2f} mm): planned {r['planned']:7.3f} toppra "
                  f"{r['toppra']:7.3f} jerk {r['jerk'].time_s:7.3f} ({r['jerk'].status}) "
                  f"planned/jerk {r['planned'] / r['jerk'].time_s:5.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
