"""Geometry of the planner: exact lines and arcs, spline fits of micro-segments, blocks.

References are independent: central finite differences for derivatives, the circle
equation for arcs, and k-d trees over densely sampled polylines/curves for the
two-way deviation of fits.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from feedplan.fit import CORNER_ANGLE_RAD, blocks_of, fit_polyline
from feedplan.path import Arc, Line, Path

MM = 1e-3
F = 0.05


def polyline(verts: np.ndarray, step: float = 0.2e-6) -> np.ndarray:
    out = [verts[:1]]
    for a, b in zip(verts[:-1], verts[1:]):
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / step)) + 1)
        out.append(a + np.linspace(0, 1, n)[1:, None] * (b - a))
    return np.vstack(out)


def two_way(curve_pts: np.ndarray, verts: np.ndarray, step: float = 0.2e-6) -> float:
    """Largest distance curve -> polyline and vertices -> curve (overestimates by < step^2 / d)."""
    to_poly = cKDTree(polyline(verts, step)).query(curve_pts)[0].max()
    to_curve = cKDTree(curve_pts).query(verts)[0].max()
    return max(to_poly, to_curve)


def noisy_sine(n=300, seed=1, noise=0.5e-6):
    rng = np.random.default_rng(seed)
    x = np.arange(n + 1) * 0.05 * MM
    z = 2 * MM * np.sin(2 * np.pi * x / (10 * MM)) + rng.uniform(-noise, noise, x.size)
    return np.round(np.column_stack([x, np.zeros_like(x), z]), 6)


def test_derivatives_of_lines_arcs_and_splines_match_finite_differences():
    l1 = Line([0, 0, 0], [5 * MM, 0, 0], F)
    c = np.array([5 * MM, 4 * MM, 0])
    end = c + 4 * MM * np.array([math.cos(0.0), math.sin(0.0), 0]) + [0, 0, 1 * MM]
    arc = Arc(l1.end, end, c, "xy", math.pi / 2, F)  # helical quarter turn
    verts = noisy_sine(40)
    verts = verts + arc.end - verts[0]
    micro = tuple(Line(a, b, F) for a, b in zip(verts[:-1], verts[1:]))
    blocks = [b for b in blocks_of(Path(l1.start, (l1, arc) + micro), 10e-6) if not b.rapid]
    h = 1e-6
    for blk in blocks:
        cv = blk.curve
        for k in range(len(cv.kind)):
            u = np.linspace(cv.u0[k] + 10 * h, cv.u0[k + 1] - 10 * h, 7)
            p, d1, d2, d3 = cv.evaluate(u)
            pp, dp1, dp2, _ = cv.evaluate(u + h)
            pm, dm1, dm2, _ = cv.evaluate(u - h)
            assert np.allclose((pp - pm) / (2 * h), d1, rtol=0, atol=1e-6)
            assert np.allclose((dp1 - dm1) / (2 * h), d2, rtol=1e-4, atol=1e-3)
            assert np.allclose((dp2 - dm2) / (2 * h), d3, rtol=1e-4, atol=1.0)
            assert np.all(np.abs(np.linalg.norm(d1, axis=1) - 1) < 5e-3)  # ~ arc-length parameter


def test_arc_pieces_lie_on_the_circle_and_end_on_the_programmed_point():
    c = np.array([0.0, 0.0, 10 * MM])
    start = c + [0, 0, -10 * MM]
    arc = Arc(start, c + [10 * MM * math.sin(1.0), 0, -10 * MM * math.cos(1.0)], c, "zx", -1.0, F)
    (blk,) = blocks_of(Path(start, (arc,), "zx"), 10e-6)
    u = np.linspace(0, blk.curve.length, 101)
    p, *_ = blk.curve.evaluate(u)
    r = np.hypot(p[:, 0] - c[0], p[:, 2] - c[2])
    assert np.abs(r - 10 * MM).max() < 1e-12
    assert np.abs(p[-1] - arc.end).max() < 1e-15
    assert np.abs(p[0] - start).max() < 1e-15
    assert math.isclose(blk.curve.length, 10 * MM * 1.0, rel_tol=1e-12)


def test_fit_of_noisy_micro_lines_is_within_tolerance_both_ways():
    verts = noisy_sine(300)
    tol = 5e-6
    parts = fit_polyline(verts, tol)
    assert parts[0][0] == 0 and parts[-1][1] == len(verts) - 1
    for first, last, spl, dev in parts:
        u = np.linspace(0, spl.t[-1], 100000)
        pts = spl(u)
        assert np.array_equal(pts[0], verts[first])
        assert np.allclose(pts[-1], verts[last], rtol=0, atol=1e-15)
        measured = two_way(pts, verts[first : last + 1])
        assert measured <= tol
        assert abs(measured - dev) < 0.1e-6  # the fit reports what it achieved
    # and it smooths: far fewer knots than vertices
    assert len(parts[0][2].t) < len(verts) / 3


def test_kink_below_the_corner_angle_is_fitted_within_tolerance():
    # two straight micro-line runs meeting at a kink just under the corner angle
    turn = 0.9 * CORNER_ANGLE_RAD
    n = 60
    step = 0.05 * MM
    a = np.column_stack([np.arange(n + 1) * step, np.zeros(n + 1), np.zeros(n + 1)])
    d = np.array([math.cos(turn), 0, math.sin(turn)])
    b = a[-1] + np.arange(1, n + 1)[:, None] * step * d
    verts = np.vstack([a, b])
    tol = 10e-6
    parts = fit_polyline(verts, tol)
    for first, last, spl, _ in parts:
        pts = spl(np.linspace(0, spl.t[-1], 20000))
        assert two_way(pts, verts[first : last + 1]) <= tol


def test_an_unfittable_run_is_split_into_exactly_joined_stretches():
    k = np.arange(13)
    verts = np.column_stack([k * 0.05 * MM, np.zeros(13), np.where(k % 2, 10e-6, -10e-6)])  # zigzag
    tol = 1e-6
    parts = fit_polyline(verts, tol)
    assert len(parts) > 1
    assert parts[0][0] == 0 and parts[-1][1] == len(verts) - 1
    for (f0, l0, s0, _), (f1, _, s1, _) in zip(parts[:-1], parts[1:]):
        assert l0 == f1
        assert np.allclose(s0(s0.t[-1]), s1(0.0), rtol=0, atol=1e-15)
    for first, last, spl, _ in parts:
        pts = spl(np.linspace(0, spl.t[-1], 20000))
        assert two_way(pts, verts[first : last + 1], step=0.02e-6) <= tol


def test_blocks_split_at_rapids_and_corners_only():
    r = Line([0, 0, 0], [0, 0, 5 * MM], math.inf, rapid=True)
    l1 = Line(r.end, r.end + [10 * MM, 0, 0], F)
    c = l1.end + [0, 5 * MM, 0]
    arc = Arc(l1.end, c + [5 * MM, 0, 0], c, "xy", math.pi / 2, F)  # tangent to l1
    l2 = Line(arc.end, arc.end + [0, 10 * MM, 0], F)  # tangent to the arc
    l3 = Line(l2.end, l2.end + [-10 * MM, 0, 0], F)  # 90 degree corner
    path = Path(r.start, (r, l1, arc, l2, l3))
    blocks = blocks_of(path, 10e-6)
    assert [b.rapid for b in blocks] == [True, False, False]
    assert [b.segments.tolist() for b in blocks] == [[0], [1, 2, 3], [4]]
    expect = np.concatenate([[0], np.cumsum([l1.length, arc.length, l2.length])])
    assert np.allclose(blocks[1].seg_u0, expect, rtol=0, atol=1e-15)
    assert math.isclose(blocks[1].curve.length, expect[-1], rel_tol=1e-12)


def test_short_runs_stay_lines_and_long_runs_become_one_spline():
    verts = noisy_sine(50)
    segs = tuple(Line(a, b, F) for a, b in zip(verts[:-1], verts[1:]))
    (blk,) = blocks_of(Path(verts[0], segs), 10e-6)
    assert blk.curve.kind.tolist() == [2]
    assert len(blk.segments) == 50 and blk.fit_deviation_m <= 10e-6
    (blk,) = blocks_of(Path(verts[0], segs[:3]), 10e-6)
    assert blk.curve.kind.tolist() == [0, 0, 0]


def test_chords_of_an_arc_fit_a_curve_of_the_arc_curvature():
    # a CAM's chords of a 16 mm arc, 0.1 - 1.4 mm long in an irregular order (as
    # line-contouring-xz's contour): the chords' sagitta (up to 15 um) exceeds the fit's
    # tolerance, so the fit must run between vertices and chords; a least-squares fit does
    # so by rippling at the chord length (curvature 62 +- 60 1/m there), the smoothing fit
    # keeps the circle's curvature within 30 % (a least-squares fit: 0.0004 to 21 times it).
    radius, tol = 16 * MM, 10e-6
    rng = np.random.default_rng(3)
    steps = rng.choice([0.1, 0.2, 0.5, 1.0, 1.35, 1.4], size=40) * MM
    theta = np.concatenate([[0.0], np.cumsum(steps / radius)])
    verts = np.column_stack([radius * np.sin(theta), np.zeros(theta.size),
                             radius * np.cos(theta)])
    parts = fit_polyline(verts, tol)
    assert len(parts) == 1
    _, _, spl, dev = parts[0]
    u = np.linspace(0.0, spl.t[-1], 20001)
    pts = spl(u)
    assert two_way(pts, verts) <= tol + 1e-9
    d1, d2 = spl(u, 1), spl(u, 2)
    kappa = np.linalg.norm(np.cross(d1, d2), axis=1) / np.linalg.norm(d1, axis=1) ** 3
    inner = (u > 2 * MM) & (u < spl.t[-1] - 2 * MM)  # away from the clamped ends
    assert np.abs(kappa[inner] * radius - 1.0).max() < 0.3
    assert abs(np.linalg.norm(d1, axis=1) - 1.0).max() < 5e-3  # ~ arc-length parameter
