"""Corner blending (G64) against exact stops (G61): limits, tolerance, speed at the corner.

Independent references: finite differences of the planned positions (every sample, v/a/j
per axis), the exact distance of every feed sample to the programmed polyline (point to
segment, written here), and the same program planned with exact stops.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from feedplan.blend import Blend, quintic
from feedplan import fit
from feedplan.fit import BLEND_MAX_TURN_RAD, Blending, blocks_of, fit_polyline
from feedplan.gcode import parse_gcode
from feedplan.limits import AxisLimits
from feedplan.path import Line, Path
from feedplan.plan import plan, program_tolerance_m
from oga.defaults import TOL_M

UCP = AxisLimits(np.full(3, 0.5), np.array([2.5, 2.5, 2.1]), np.array([10.0, 10.0, 100.0]))
MM = 1e-3


def fd(pos: np.ndarray, dt: float):
    """Backward differences, at rest before and after (every sample)."""
    p = np.concatenate([np.repeat(pos[:1], 3, axis=0), pos, np.repeat(pos[-1:], 3, axis=0)])
    v = np.diff(p, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    return v, a, np.diff(a, axis=0) / dt


def polyline_distance(pts: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact distance of each point (N, 3) to the nearest segment a[k]..b[k] (S, 3)."""
    d = b - a
    w = pts[:, None, :] - a[None, :, :]
    t = np.clip(np.sum(w * d, axis=2) / np.sum(d * d, axis=1), 0.0, 1.0)
    return np.min(np.linalg.norm(w - t[..., None] * d, axis=2), axis=1)


def assert_within(sp, path: Path, limits: AxisLimits, tol: float) -> float:
    """Every sample within every axis limit and every feed sample within ``tol`` of the
    programmed feed lines; returns the largest deviation, m."""
    for x, lim in zip(fd(sp.pos, sp.dt), (limits.vmax_m_s, limits.amax_m_s2, limits.jmax_m_s3)):
        assert np.all(np.abs(x) <= lim), (np.abs(x).max(axis=0), lim)
    feed = [s for s in path.segments if not s.rapid]
    a, b = np.array([s.start for s in feed]), np.array([s.end for s in feed])
    dev = polyline_distance(sp.pos[~sp.rapid], a, b)
    assert dev.max() <= tol, dev.max()
    return float(dev.max())


def kink(turn_deg: float, mode: str, feed: float = 3000, extra: str = "") -> str:
    """20 mm along X, then 20 mm turned by ``turn_deg`` in XY, under ``mode``."""
    t = math.radians(turn_deg)
    return (f"G21 G90 G17 {mode}\nG0 X0 Y0\nG1 X20 F{feed:g}\n"
            f"X{20 + 20 * math.cos(t):.6f} Y{20 * math.sin(t):.6f}\n{extra}M2\n")


def speed_at(sp, point: np.ndarray) -> float:
    """Path speed of the sample nearest ``point``, m/s."""
    v = fd(sp.pos, sp.dt)[0][2 : 2 + len(sp.pos)]
    dist = np.linalg.norm(sp.pos - point, axis=1)
    nearest = dist <= dist.min() + 1e-12  # all the samples held there, if at rest
    return float(np.min(np.linalg.norm(v[nearest], axis=1)))


CORNER = np.array([20 * MM, 0.0, 0.0])


@pytest.mark.parametrize("turn_deg, tol", [(3, TOL_M), (11, TOL_M), (30, 0.1 * MM),
                                           (60, 0.5 * MM), (90, 0.5 * MM), (135, 2 * MM)])
def test_blended_kink_keeps_limits_and_tolerance(turn_deg, tol):
    path = parse_gcode(kink(turn_deg, "G64"))
    sp = plan(path, UCP, tol_m=tol)
    dev = assert_within(sp, path, UCP, tol)
    assert speed_at(sp, CORNER) > 0.0  # not a stop
    assert dev > 0.2 * tol  # the corner is cut (within the tolerance)


@pytest.mark.parametrize("turn_deg", [45, 90, 135])
def test_slow_blend_is_left_an_exact_stop(turn_deg):
    # within 20 um these corners pass at < 0.15 F (BLEND_MIN_SPEED_SHARE): a stop is as fast
    blend = plan(parse_gcode(kink(turn_deg, "G64")), UCP)
    stop = plan(parse_gcode(kink(turn_deg, "G61")), UCP)
    assert np.array_equal(blend.pos, stop.pos)
    assert speed_at(blend, CORNER) == 0.0


@pytest.mark.parametrize("turn_deg, tol, gain", [(3, TOL_M, 0.9), (11, TOL_M, 0.95),
                                                 (30, 0.1 * MM, 0.95)])
def test_blend_is_faster_than_the_exact_stop(turn_deg, tol, gain):
    blend = plan(parse_gcode(kink(turn_deg, "G64")), UCP, tol_m=tol)
    stop = plan(parse_gcode(kink(turn_deg, "G61")), UCP, tol_m=tol)
    assert blend.duration < gain * stop.duration, (blend.duration, stop.duration)


@pytest.mark.parametrize("mode", ["G61", "G61.1"])
def test_g61_stops_exactly_at_the_corner(mode):
    path = parse_gcode(kink(30, mode))
    sp = plan(path, UCP)
    assert_within(sp, path, UCP, 1e-9)  # on the programmed lines
    at = np.flatnonzero(np.all(np.abs(sp.pos - CORNER) < 1e-12, axis=1))
    assert at.size >= 3 and np.all(np.diff(at) == 1)  # at rest there: v = a = 0


def test_g64_p_sets_the_tolerance_of_the_plan():
    for p_mm in (0.005, 0.5):  # tighter and looser than tol_m (0.02 mm)
        path = parse_gcode(kink(8, f"G64 P{p_mm}"))
        assert program_tolerance_m(path, TOL_M) == pytest.approx(p_mm * MM)
        sp = plan(path, UCP)
        dev = assert_within(sp, path, UCP, p_mm * MM)
        assert dev > 0.2 * p_mm * MM
        assert speed_at(sp, CORNER) > 0.0
        assert any("G64 P sets the tolerance" in w for w in sp.warnings)
    # a move without P keeps tol_m: the least of the moves' tolerances holds
    mixed = parse_gcode("G21 G90 G17\nG0 X0 Y0\nG1 X20 F3000\nG64 P0.5 X40 Y3\nX60\nM2\n")
    assert program_tolerance_m(mixed, TOL_M) == TOL_M
    assert not plan(mixed, UCP).warnings
    tight = plan(parse_gcode(kink(8, "G64 P0.002")), UCP)
    loose = plan(parse_gcode(kink(8, "G64")), UCP)
    assert tight.duration > loose.duration  # a tighter blend is slower


def test_modes_switch_per_move():
    # 10 deg kinks: at P1 under G64, at P2 under G61 (the mode in effect for the move that
    # ends at the corner), at P3 under G64 again
    text = ("G21 G90 G17\nG0 X0 Y0\nG1 X20 F3000\nG61 X39.696 Y3.473\nG64 X59.696\n"
            "X79.392 Y6.946\nM2\n")
    path = parse_gcode(text)
    assert [s.blend_tol_m for s in path.segments] == [None, 0.0, None, None]
    sp = plan(path, UCP)
    assert_within(sp, path, UCP, TOL_M)
    for corner, stops in (((20, 0), False), ((39.696, 3.473), True), ((59.696, 3.473), False)):
        at = np.array([corner[0] * MM, corner[1] * MM, 0.0])
        exact = np.all(np.abs(sp.pos - at) < 1e-12, axis=1).sum() >= 3
        assert exact == stops, corner
        assert (speed_at(sp, at) == 0.0) == stops


def test_rapids_next_to_feeds_stop_and_keep_limits():
    # rapid in, a feed zigzag of several angles, rapid out: the feed corners are blended,
    # the rapid/feed transitions are exact stops (rapids are not blended)
    text = ("G21 G90 G17\nG0 X0 Y0 Z5\nG0 Z0\nG1 X10 F2000\nX20 Y2\nX30 Y-1\nX35 Y8\n"
            "X36 Y20\nG0 Z5\nG0 X0 Y0\nM2\n")
    path = parse_gcode(text)
    sp = plan(path, UCP, tol_m=0.2 * MM)
    assert_within(sp, path, UCP, 0.2 * MM)
    for k, seg in enumerate(path.segments[:-1]):
        if seg.rapid != path.segments[k + 1].rapid:
            assert np.all(np.abs(sp.pos - seg.end) < 1e-12, axis=1).sum() >= 3, k
    feed = [s for s in path.segments if not s.rapid]
    for s in feed[:-1]:  # every feed corner passed in motion
        assert speed_at(sp, s.end) > 0.0, s.line


def test_reversal_is_an_exact_stop():
    path = parse_gcode("G21 G90 G17\nG0 X0 Y0\nG1 X20 F3000\nX0.5 Y0.01\nM2\n")
    (blk_a, blk_b) = [b for b in blocks_of(path, 1e-5, Blending(1e-5))]
    assert len(blk_a.segments) == len(blk_b.segments) == 1
    assert math.pi - 0.01 > BLEND_MAX_TURN_RAD
    assert_within(plan(path, UCP), path, UCP, TOL_M)


def test_blend_is_curvature_continuous():
    """Position, tangent and curvature vector continuous where a blend meets the lines
    (finite differences of the curve, independent of the blend's own formulas)."""
    path = parse_gcode(kink(40, "G64"))
    (blk,) = [b for b in blocks_of(path, 0.5 * TOL_M, Blending(0.5 * TOL_M)) if not b.rapid]
    curve = blk.curve
    assert list(curve.kind) == [0, 3, 0]  # line, blend, line
    h = 1e-7
    for u in curve.u0[1:-1]:
        p = curve.evaluate(np.array([u - 2 * h, u - h, u, u + h, u + 2 * h]))[0]
        left_d1 = (p[2] - p[1]) / h
        right_d1 = (p[3] - p[2]) / h
        assert np.allclose(left_d1, right_d1, atol=1e-6)
        assert abs(np.linalg.norm(right_d1) - 1.0) < 1e-6
        left_d2 = (p[2] - 2 * p[1] + p[0]) / h**2  # at u - h
        right_d2 = (p[4] - 2 * p[3] + p[2]) / h**2  # at u + h: 2 h d3r/du3 from left_d2
        k = np.max(np.linalg.norm(curve.evaluate(np.linspace(curve.u0[1], curve.u0[2], 50))[2],
                                  axis=1))
        assert np.linalg.norm(left_d2 - right_d2) < 1e-2 * k  # no curvature jump


def test_quintic_matches_its_end_conditions():
    rng = np.random.default_rng(5)
    p0, d0, k0, p1, d1, k1 = rng.normal(size=(6, 3))
    blend = Blend(quintic(p0, d0, k0, p1, d1, k1, 2.0), 2.0, 0.0, 0.0)
    got = blend.evaluate(np.array([0.0, 2.0]))
    for end, want in enumerate(((p0, d0, k0), (p1, d1, k1))):
        for nu, w in enumerate(want):
            assert np.allclose(got[nu][end], w, atol=1e-12)
    # its derivatives are those of its positions (finite differences)
    u = np.linspace(0.3, 1.7, 8)
    h = 1e-4
    p, d1, d2, d3 = blend.evaluate(u)
    pm, pp = blend.evaluate(u - h)[0], blend.evaluate(u + h)[0]
    assert np.allclose((pp - pm) / (2 * h), d1, atol=1e-6)
    assert np.allclose((pp - 2 * p + pm) / h**2, d2, atol=1e-5)
    d2m, d2p = blend.evaluate(u - h)[2], blend.evaluate(u + h)[2]
    assert np.allclose((d2p - d2m) / (2 * h), d3, atol=1e-5)


def test_blend_shorter_than_half_of_a_short_line():
    # a 0.1 mm line between two corners: both blends fit in it, without overlapping
    text = "G21 G90 G17\nG0 X0 Y0\nG1 X10 F3000\nX10.1 Y0.02\nX20 Y0.5\nM2\n"
    path = parse_gcode(text)
    (blk,) = [b for b in blocks_of(path, 0.5 * TOL_M, Blending(0.5 * TOL_M)) if not b.rapid]
    assert list(blk.curve.kind) == [0, 3, 0, 3, 0]
    assert np.all(np.diff(blk.curve.u0) > 0) and np.all(np.diff(blk.seg_u0) > 0)
    sp = plan(path, UCP)
    assert_within(sp, path, UCP, TOL_M)


def test_hand_built_path_blends_by_default_and_stops_under_g61():
    l1 = Line([0, 0, 0], [10 * MM, 0, 0], 0.05, line=1)
    l2 = Line(l1.end, [20 * MM, 3 * MM, 0], 0.05, line=2)
    for tol, stops in ((None, False), (0.0, True)):
        a = Line(l1.start, l1.end, 0.05, line=1, blend_tol_m=tol)
        path = Path(a.start, (a, l2), "xy")
        sp = plan(path, UCP)
        assert_within(sp, path, UCP, TOL_M)
        assert (speed_at(sp, l1.end) == 0.0) == stops


def test_corner_between_long_micro_segment_runs_is_blended():
    # 300 moves of 0.05 mm, then 300 turned by 60 deg: the blend replaces far more than
    # the deviation's search window of moves; measured against the moves within its cut
    # only, it is found (it was refused, an exact stop, when measured from the first move)
    t = math.radians(60)
    lines = ["G21 G90 G17 G64", "G0 X0 Y0", "G1 F3000"]
    lines += [f"X{0.05 * k:.4f}" for k in range(1, 301)]
    lines += [f"X{15 + 0.05 * k * math.cos(t):.6f} Y{0.05 * k * math.sin(t):.6f}"
              for k in range(1, 301)]
    path = parse_gcode("\n".join(lines + ["M2"]) + "\n")
    tol = 0.2 * MM
    assert len(blocks_of(path, 0.5 * tol, Blending(0.5 * tol, UCP))) == 1
    sp = plan(path, UCP, tol_m=tol)
    dev = assert_within(sp, path, UCP, tol)
    assert speed_at(sp, np.array([15 * MM, 0.0, 0.0])) > 0.2 * 0.05  # not a stop
    assert dev > 0.1 * tol


def chords(n: int = 60, step_rad: float = 0.075, radius_mm: float = 20.0) -> str:
    """G1 chords of a circle: ``n`` chords turning by ``step_rad`` each (1.5 mm at R20)."""
    pts = [(radius_mm * math.sin(k * step_rad), radius_mm * (1.0 - math.cos(k * step_rad)))
           for k in range(1, n + 1)]
    lines = ["G21 G90 G17 G64", "G0 X0 Y0", "G1 F6000"] + [f"X{x:.6f} Y{y:.6f}" for x, y in pts]
    return "\n".join(lines + ["M2"]) + "\n"


def test_chords_of_a_curve_are_fitted_and_faster_than_blended(monkeypatch):
    # 1.5 mm chords of R20 (sagitta 14 um) within 0.05 mm: one spline, no blend; with the
    # rule off (no line is a chord) every vertex is blended and the plan is slower
    path = parse_gcode(chords())
    tol = 0.05 * MM
    (blk,) = blocks_of(path, 0.5 * tol, Blending(0.5 * tol, UCP))
    assert list(blk.curve.kind) == [2]  # one fitted spline
    fitted = plan(path, UCP, tol_m=tol)
    assert_within(fitted, path, UCP, tol)
    monkeypatch.setattr(fit, "CHORD_SEGMENT_M", 0.0)
    (blk,) = blocks_of(path, 0.5 * tol, Blending(0.5 * tol, UCP))
    assert np.count_nonzero(blk.curve.kind == 3) == 59  # a blend at every vertex
    blended = plan(path, UCP, tol_m=tol)
    assert_within(blended, path, UCP, tol)
    assert fitted.duration < 0.9 * blended.duration


def test_chords_turning_more_than_the_corner_angle_are_blended():
    # the same chords turning 0.25 rad each are corners, not a curve: blended one by one
    path = parse_gcode(chords(n=8, step_rad=0.25))
    (blk,) = blocks_of(path, 0.5 * TOL_M, Blending(0.5 * TOL_M, UCP))
    assert np.count_nonzero(blk.curve.kind == 3) == 7 and not np.any(blk.curve.kind == 2)


def test_vertex_where_a_fit_splits_is_blended():
    # micro-segments of 0.9 mm kinked by 0.19 rad: no spline keeps within 2.5 um of both
    # sides, the fit splits there; the split is blended (it was an exact stop)
    t = 0.19
    lines = ["G21 G90 G17 G64", "G0 X0 Y0", "G1 F3000"] + [f"X{0.9 * k:.4f}" for k in range(1, 11)]
    lines += [f"X{9 + 0.9 * k * math.cos(t):.6f} Y{0.9 * k * math.sin(t):.6f}"
              for k in range(1, 11)]
    path = parse_gcode("\n".join(lines + ["M2"]) + "\n")
    tol = 5e-6
    verts = np.vstack([path.segments[0].start] + [s.end for s in path.segments])
    assert len(fit_polyline(verts, 0.5 * tol)) == 2
    (blk,) = blocks_of(path, 0.5 * tol, Blending(0.5 * tol, UCP))
    assert list(blk.curve.kind) == [2, 3, 2]
    sp = plan(path, UCP, tol_m=tol)
    assert_within(sp, path, UCP, tol)
    assert speed_at(sp, np.array([9 * MM, 0.0, 0.0])) > 0.0  # not a stop


def jittered(jitter_mm: float, n: int = 400) -> Path:
    """``n`` micro-segments of 15 um along X, every other vertex ``jitter_mm`` off in Y."""
    lines = ["G21 G90 G17 G64", "G0 X0 Y0", "G1 F3000"]
    lines += [f"X{0.015 * k:.4f} Y{jitter_mm if k % 2 else 0.0:.4f}" for k in range(1, n + 1)]
    return parse_gcode("\n".join(lines + ["M2"]) + "\n")


def test_jitter_of_micro_segments_is_fitted_not_blended():
    # a 4 um jitter turns the 15 um moves by 30 deg at every vertex: within the fit's
    # tolerance of the chord of its neighbours, it is no corner; one spline, planned nearly
    # as fast as the same moves without the jitter (it was 399 blends, 14x slower; those
    # are one line, ruckig's profile: 0.302 s against 0.280 s measured)
    path, straight = jittered(0.004), jittered(0.0)
    assert _turns(path).min() > 0.5
    (blk,) = blocks_of(path, 0.5 * TOL_M, Blending(0.5 * TOL_M, UCP))
    assert list(blk.curve.kind) == [2]
    sp = plan(path, UCP)
    assert_within(sp, path, UCP, TOL_M)
    assert sp.duration <= 1.1 * plan(straight, UCP).duration


def test_jitter_beyond_the_fit_tolerance_is_a_corner():
    # 12 um off the chord of its neighbours (more than the fit's 10 um): every vertex a
    # corner (blended), no fit over them
    path = jittered(0.012, n=40)
    (blk,) = blocks_of(path, 0.5 * TOL_M, Blending(0.5 * TOL_M, UCP))
    assert np.count_nonzero(blk.curve.kind == 3) == 39 and not np.any(blk.curve.kind == 2)


def _turns(path: Path) -> np.ndarray:
    d = np.array([(s.end - s.start) / s.length for s in path.segments])
    return np.arccos(np.clip(np.sum(d[:-1] * d[1:], axis=1), -1.0, 1.0))
