"""Experiment: a speed profile along the exact curve by sequential linear programming.

Run: ``python bench/bench_lp_profile.py PROGRAM BLOCK [--grid-mm H] [--rest-mm R]
[--iterations N] [--margin M] [--shared DIR]`` from the repository root (PROGRAM: a name of
``bench_plan``'s programs; BLOCK: the index of a block the planner moved along, as
``bench_jerk_reference`` lists them). A benchmark, not a test: it prints figures and asserts
nothing. It is not the planner: it measures a candidate method for the curved blocks where the
planner's filtered profile loses most to the jerk-limited reference (docs/benchmarks/cycle-time.md).

Method. Nodes ``u_k`` along the block's curve (spacing ``--grid-mm``, halving towards both ends
down to ``--rest-mm``); unknowns ``x_k = udot^2`` and its slope ``g_k = dx/du``; ``x(u)`` is the
cubic Hermite of them on each cell, so ``udot = sqrt(x)``, ``uddot = g / 2`` and ``x''`` is
linear in the unknowns on each cell. Per axis at every node ``|r' udot| <= V`` and the path
speed ``<= F`` (bounds), ``|r'' x + r' g / 2| <= A`` (rows), and at both ends of every cell the
jerk ``sqrt(x) (r''' x + 1.5 r'' g + 0.5 r' x'') <= J``, whose ``1 / sqrt(x)`` is replaced by its
tangent at the previous iterate, taken at the faster end of the cell (the tangent lies below
the convex ``J / sqrt(x)``: every iterate keeps the true constraint; a node slowed on purpose
does not loosen its neighbours'). The first and last cells are pure-jerk cells from rest
(``x ~ u^(4/3)``, the rest-to-rest ends of a jerk-limited motion): ``g = 4 x / (3 h)`` at their
inner node and ``x`` bounded by the tangential jerk there. The objective is the time, linearised
at the previous iterate; HiGHS (scipy) solves each linear program. The motion is then sampled
every 1 ms by quintic Hermite pieces in time through ``(u_k, udot_k, uddot_k)``, each cell's
duration from the trapezoid rule with its end correction (exact for a cubic ``u(t)``), and
checked as the planner checks (finite differences of the positions, per axis).

Printed: the planner's time of the block, the profile's time per iteration with its CPU time,
and the sampled profile's duration and worst v, a, j ratios to the planning limits.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path as FilePath

import numpy as np
from scipy import sparse
from scipy.optimize import linprog

sys.path.insert(0, str(FilePath(__file__).resolve().parent))
from bench_plan import MACHINE, ROOT, programs  # noqa: E402
from bench_jerk_reference import capture  # noqa: E402

from feedplan.gcode import parse_gcode  # noqa: E402


def nodes(length: float, h: float, h_rest: float) -> np.ndarray:
    """Nodes (m) about ``h`` apart, halving towards both ends down to ``h_rest``."""
    steps, w = [], h_rest
    while w < h and sum(steps) + w < length / 3:
        steps.append(w)
        w *= 2
    left = np.cumsum([0.0, *steps])
    mid = left[-1] + np.linspace(0.0, length - 2 * left[-1],
                                 max(2, math.ceil((length - 2 * left[-1]) / h)) + 1)
    return np.unique(np.concatenate([left, mid, length - left[::-1]]))


def _rows(blocks, n_var):
    """A sparse matrix and right-hand side from (columns (m, c), values (m, c), rhs (m,))."""
    rows, cols, vals, rhs, r = [], [], [], [], 0
    for c, v, b in blocks:
        rows.append(np.repeat(np.arange(r, r + c.shape[0]), c.shape[1]))
        cols.append(c.ravel())
        vals.append(v.ravel())
        rhs.append(b)
        r += c.shape[0]
    m = sparse.csr_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(r, n_var))
    return m, np.concatenate(rhs)


def cell_times(u, x, g):
    """Duration of each cell (s): trapezoid rule with its end correction in ``udot``, ``uddot``
    (exact for a cubic ``u(t)``); the first and last pure jerk from rest."""
    h, v, a = np.diff(u), np.sqrt(np.maximum(x, 0.0)), g / 2
    qa, qb = (a[:-1] - a[1:]) / 12, (v[:-1] + v[1:]) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        root = (-qb + np.sqrt(np.maximum(qb * qb + 4 * qa * h, 0.0))) / (2 * qa)
        tau = np.where(np.abs(qa * h) > 1e-12 * np.maximum(qb * qb, 1e-300), root,
                       h / np.maximum(qb, 1e-300))
    tau[0], tau[-1] = 3 * h[0] / v[1], 3 * h[-1] / v[-2]
    return tau


def solve(curve, limits, feed: float, h: float, h_rest: float, iterations: int, margin: float,
          log=print):
    """The profile (nodes, x, g) after ``iterations`` linear programs at most."""
    u = nodes(curve.length, h, h_rest)
    n = len(u) - 1
    hk = np.diff(u)
    right, left = curve.evaluate(u), curve.evaluate(u, left=True)
    ax = np.flatnonzero(limits.present)
    vmax, amax, jmax = limits.vmax_m_s, limits.amax_m_s2, limits.jmax_m_s3
    with np.errstate(divide="ignore", over="ignore"):
        ub = np.minimum((feed / np.linalg.norm(right[1], axis=1)) ** 2,
                        np.min((vmax[ax] / np.abs(right[1][:, ax])) ** 2, axis=1))
    for k0, k1 in ((0, 1), (n, n - 1)):  # pure-jerk rest cells: the tangential jerk over them
        t1 = curve.evaluate(np.linspace(u[min(k0, k1)], u[max(k0, k1)], 9))[1]
        jt = np.min(jmax[ax] / np.max(np.abs(t1[:, ax]), axis=0).clip(1e-12))
        ub[k1] = min(ub[k1], margin ** (2 / 3) * jt ** (2 / 3) * (6 * hk[min(k0, k1)]) ** (4 / 3) / 4)
    ub[0] = ub[n] = 0.0
    lo = np.concatenate([np.zeros(n + 1), np.full(n + 1, -np.inf)])
    hi = np.concatenate([ub, np.full(n + 1, np.inf)])
    lo[n + 1] = hi[n + 1] = lo[2 * n + 1] = hi[2 * n + 1] = 0.0
    eq = sparse.csr_array(([1.0, -4 / (3 * hk[0]), 1.0, 4 / (3 * hk[-1])],
                           ([0, 0, 1, 1], [n + 2, 1, 2 * n, n - 1])), shape=(2, 2 * n + 2))
    gc = n + 1  # column of g_0

    def constraints(xhat):
        blocks = []
        k = np.arange(1, n)
        for i in ax:
            for d1, d2 in ((right[1], right[2]), (left[1], left[2])):
                for sg in (1, -1):
                    blocks.append((np.c_[k, gc + k], sg * np.c_[d2[k, i], d1[k, i] / 2],
                                   np.full(k.size, margin * amax[i])))
        c0 = np.arange(1, n - 1)
        c1, H = c0 + 1, hk[1:n - 1]
        q = np.where(xhat[c0] >= xhat[c1], c0, c1)  # the faster end of each cell
        xq = np.maximum(xhat[q], 1e-8)
        for end, (_, d1, d2, d3) in ((0, right), (1, left)):
            kn = c0 if end == 0 else c1
            coef = ((-6 / H**2, 6 / H**2, -4 / H, -2 / H) if end == 0   # x'' at the cell's start
                    else (6 / H**2, -6 / H**2, 2 / H, 4 / H))          # and at its end
            for i in ax:
                e = [0.5 * d1[kn, i] * c for c in coef]
                e[end] = e[end] + d3[kn, i]
                e[2 + end] = e[2 + end] + 1.5 * d2[kn, i]
                tangent = 0.5 * margin * jmax[i] / xq**1.5
                rhs = 1.5 * margin * jmax[i] / np.sqrt(xq)
                for sg in (1, -1):
                    blocks.append((np.c_[c0, c1, gc + c0, gc + c1, q],
                                   np.c_[sg * e[0], sg * e[1], sg * e[2], sg * e[3], tangent], rhs))
        for kn, hh, sgn, (_, d1, d2, d3) in ((1, hk[0], 1, left), (n - 1, hk[-1], -1, right)):
            xk = max(xhat[kn], 1e-8)
            for i in ax:  # the rest cells' inner ends: g = +-4x/(3h), x'' = 4x/(9h^2)
                e = d3[kn, i] + 2 * d2[kn, i] * sgn / hh + 2 * d1[kn, i] / (9 * hh**2)
                for sg in (1, -1):
                    blocks.append((np.array([[kn]]),
                                   np.array([[sg * e + 0.5 * margin * jmax[i] / xk**1.5]]),
                                   np.array([1.5 * margin * jmax[i] / math.sqrt(xk)])))
        return _rows(blocks, 2 * n + 2)

    x, g = np.minimum(ub, 1e-4), np.zeros(n + 1)
    x[0] = x[n] = 0.0
    xs = float(np.max(ub[np.isfinite(ub)]))
    hl = np.minimum(np.r_[hk, hk[-1]], np.r_[hk[0], hk])
    scale = np.concatenate([np.full(n + 1, xs), xs / hl])  # unknowns of order 1
    c0 = time.process_time()
    for it in range(iterations):
        m, b = constraints(x)
        v = np.sqrt(np.maximum(x, 1e-10))
        w = np.zeros(2 * n + 2)  # -d(time)/dx at the iterate (capped where nearly at rest)
        cell = hk / (v[:-1] + v[1:]) ** 2
        w[:n] += cell / v[:-1]
        w[1:n + 1] += cell / v[1:]
        w[:n + 1] = np.minimum(w[:n + 1], np.percentile(w[1:n], 95))
        w[0] = w[n] = 0.0
        ms = m @ sparse.diags_array(scale)
        row = 1.0 / np.maximum(abs(ms).max(axis=1).toarray().ravel(), 1e-300)
        res = linprog(-w * scale / np.max(np.abs(w * scale)), A_ub=sparse.diags_array(row) @ ms,
                      b_ub=b * row, A_eq=eq @ sparse.diags_array(scale), b_eq=np.zeros(2),
                      bounds=np.c_[lo / scale, hi / scale], method="highs")
        if res.status != 0:
            log(f"  iteration {it}: {res.message}")
            break
        new = np.maximum(res.x[:n + 1] * xs, 0.0)
        g = res.x[n + 1:] * scale[n + 1:]
        moved = np.max(np.abs(np.sqrt(new) - np.sqrt(x)))
        x = new
        log(f"  iteration {it}: {np.sum(cell_times(u, x, g)):.4f} s, {m.shape[0]} rows, "
            f"{time.process_time() - c0:.2f} cpu s")
        if moved < 1e-4 * math.sqrt(xs):
            break
    return u, x, g


def sample(u, x, g, dt: float) -> np.ndarray:
    """The curve parameter every ``dt`` through quintic Hermite pieces in time."""
    v, a = np.sqrt(np.maximum(x, 0.0)), g / 2
    a[0] = a[-1] = 0.0
    tau = cell_times(u, x, g)
    tk = np.concatenate([[0.0], np.cumsum(tau)])
    t = np.minimum(np.arange(math.ceil(tk[-1] / dt) + 1) * dt, tk[-1])
    c = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tau) - 1)
    T = tau[c]
    z = (t - tk[c]) / T
    basis = (1 - 10 * z**3 + 15 * z**4 - 6 * z**5, z - 6 * z**3 + 8 * z**4 - 3 * z**5,
             0.5 * z**2 - 1.5 * z**3 + 1.5 * z**4 - 0.5 * z**5, 10 * z**3 - 15 * z**4 + 6 * z**5,
             -4 * z**3 + 7 * z**4 - 3 * z**5, 0.5 * z**3 - z**4 + 0.5 * z**5)
    terms = (u[c], v[c] * T, a[c] * T * T, u[c + 1], v[c + 1] * T, a[c + 1] * T * T)
    out = sum(b * q for b, q in zip(basis, terms))
    out[-1] = u[-1]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("program")
    ap.add_argument("block", type=int)
    ap.add_argument("--grid-mm", type=float, default=0.1)
    ap.add_argument("--rest-mm", type=float, default=0.02)
    ap.add_argument("--iterations", type=int, default=12)
    ap.add_argument("--margin", type=float, default=0.99, help="share of the limits planned to")
    ap.add_argument("--shared", type=FilePath, default=ROOT.parent / "shared")
    args = ap.parse_args(argv)
    text = dict(programs(args.shared, {args.program}))[args.program]
    path = parse_gcode(text, source=args.program)
    limits = MACHINE.planning_limits()
    _, blocks, planned = capture(path, limits)
    blk = blocks[args.block]
    feed = min(path.segments[i].feed_m_s for i in blk.segments)
    print(f"{args.program} block {args.block}: {blk.curve.length * 1e3:.1f} mm, planned "
          f"{planned[args.block]:.3f} s")
    c0 = time.process_time()
    u, x, g = solve(blk.curve, limits, feed, args.grid_mm * 1e-3, args.rest_mm * 1e-3,
                    args.iterations, args.margin)
    cpu = time.process_time() - c0
    s = sample(u, x, g, MACHINE.te)
    p = blk.curve.evaluate(np.clip(s, 0.0, blk.curve.length), order=2)[0]
    p = np.concatenate([np.repeat(p[:1], 3, axis=0), p, np.repeat(p[-1:], 3, axis=0)])
    ax = limits.present
    ratios = [np.max(np.abs(np.diff(p, o, axis=0)[:, ax]) / MACHINE.te**o / lim[ax])
              for o, lim in ((1, limits.vmax_m_s), (2, limits.amax_m_s2), (3, limits.jmax_m_s3))]
    print(f"LP profile: {len(u)} nodes, {(len(s) - 1) * MACHINE.te:.3f} s sampled, worst v/a/j "
          f"{'/'.join(f'{r:.3f}' for r in ratios)} of the planning limits, {cpu:.2f} cpu s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
