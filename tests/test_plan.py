"""Feed planner: every plan checked here by finite differences and exact geometry.

The checks are written in this file (not feedplan.check): backward differences of
the float64 positions held at rest before and after, and distances to densely
sampled programmed geometry via a k-d tree (1 um spacing: the nearest-sample
distance overestimates the true distance by well under 0.1 um at 20 um).
"""

from __future__ import annotations

import importlib
import math
from pathlib import Path as FilePath

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from ruckig import InputParameter, Ruckig, Trajectory
from scipy.spatial import cKDTree

from feedplan.check import check_setpoints
from feedplan.gcode import parse_gcode
from feedplan.limits import AxisLimits
from feedplan.path import PLANES, Arc, Line, Path
from feedplan.setpoints import Setpoints
from feedplan.plan import _AT_SHARE, plan
from oga.errors import OptionError, ToolpathError

#: ucp710.toml: X and Y 30 m/min, 2.5 m/s^2, 10 m/s^3; Z 30 m/min, 2.1 m/s^2, 100 m/s^3
UCP = AxisLimits(np.full(3, 0.5), np.array([2.5, 2.5, 2.1]), np.array([10.0, 10.0, 100.0]))
F3000 = 0.05  # m/s
DATA = FilePath(__file__).with_name("data")
MM = 1e-3
TOL = 20e-6


# ----------------------------------------------------------------------------- helpers


def fd(pos: np.ndarray, dt: float):
    """Backward differences, at rest before and after; row k ends at pos[k] (N + 3 rows)."""
    p = np.concatenate([np.repeat(pos[:1], 3, axis=0), pos, np.repeat(pos[-1:], 3, axis=0)])
    v = np.diff(p, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    j = np.diff(a, axis=0) / dt
    return v[2:], a[1:], j


def dense(seg, step=1e-6) -> np.ndarray:
    n = max(2, int(math.ceil(seg.length / step)) + 1)
    return seg.point(np.linspace(0.0, 1.0, n))


def deviation(pos: np.ndarray, segs) -> np.ndarray:
    tree = cKDTree(np.vstack([dense(s) for s in segs]))
    return tree.query(pos)[0]


def arc_between(start, center, plane, sweep, feed, rise=0.0, line=0) -> Arc:
    start = np.asarray(start, float)
    center = np.asarray(center, float)
    i, j, n = PLANES[plane]
    d = start - center
    th = math.atan2(d[j], d[i]) + sweep
    r = math.hypot(d[i], d[j])
    end = center.copy()
    end[i] += r * math.cos(th)
    end[j] += r * math.sin(th)
    end[n] = start[n] + rise
    return Arc(start, end, center, plane, sweep, feed, line)


def assert_plan_ok(sp, path: Path, limits: AxisLimits, tol=TOL):
    v, a, j = fd(sp.pos, sp.dt)
    for x, lim in ((v, limits.vmax_m_s), (a, limits.amax_m_s2), (j, limits.jmax_m_s3)):
        assert np.all(np.abs(x) <= lim), (np.abs(x).max(axis=0), lim)
    feed_samples = ~sp.rapid
    speed = np.linalg.norm(v[: len(sp.pos)], axis=1)
    fmax = max(s.feed_m_s for s in path.segments if not s.rapid)
    assert speed[feed_samples].max() <= 1.005 * fmax
    feed_segs = [s for s in path.segments if not s.rapid]
    dev = deviation(sp.pos[feed_samples], feed_segs)
    assert dev.max() <= tol, dev.max()
    assert np.array_equal(sp.pos[0], path.start)
    assert np.allclose(sp.pos[-3:], path.segments[-1].end, rtol=0, atol=1e-12)
    assert np.all(sp.pos[-3:] == sp.pos[-1])  # at rest: v = a = 0 at the end


def rest_to_rest(length, v, a, j) -> float:
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [length]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v], [a], [j]
    traj = Trajectory(1)
    Ruckig(1).calculate(inp, traj)
    return traj.duration


# ----------------------------------------------------------------------------- cases


def test_line_near_ruckig_time_optimum():
    seg = Line([0, 0, 0], [20 * MM, 0, 0], F3000, line=1)
    path = Path(seg.start, (seg,), "xy")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    best = rest_to_rest(seg.length, F3000, 2.5, 10.0)
    assert best - 1e-9 <= sp.duration <= 1.03 * best + 3e-3
    assert np.all(sp.block == 1) and not sp.rapid.any()


def test_rapid_at_axis_limits_is_ruckig_optimal_and_straight():
    d = np.array([30, 40, 0]) * MM
    seg = Line([0, 0, 0], d, math.inf, rapid=True, line=2)
    path = Path(seg.start, (seg,), "xy")
    sp = plan(path, UCP)
    v, a, j = fd(sp.pos, sp.dt)
    for x, lim in ((v, UCP.vmax_m_s), (a, UCP.amax_m_s2), (j, UCP.jmax_m_s3)):
        assert np.all(np.abs(x) <= lim)
    u = d / np.linalg.norm(d)
    # the jerk: the share a feed line's tangential motion gets (the position loop's reserve)
    lims = (UCP.vmax_m_s, UCP.amax_m_s2, UCP.jmax_m_s3 * _AT_SHARE)
    best = rest_to_rest(0.05, *(float(np.min(x[:2] / u[:2])) for x in lims))
    assert best - 1e-9 <= sp.duration <= 1.002 * best + 3 * sp.dt
    # on the line: cross product with its direction vanishes
    assert np.abs(np.cross(sp.pos, u)).max() < 1e-12
    assert sp.rapid.all()


def test_full_circle_within_limits_and_fast():
    start = np.array([50 * MM, 0, 0])
    arc = arc_between(start, [0, 0, 0], "xy", 2 * math.pi, F3000, line=4)
    path = Path(start, (arc,), "xy")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    # start/stop along Y: half the extra of a 1-D rest-to-rest each
    extra = rest_to_rest(1.0, F3000, 2.5, 10.0) - 1.0 / F3000
    assert sp.duration <= 1.05 * (arc.length / F3000 + extra)
    assert sp.plane == "xy"


@pytest.mark.parametrize("name", ["reference_xz", "freeform_xz"])
def test_contour_within_limits_and_cycle_time_target(name):
    # reference_xz: lines and arcs, curvature jumps at their joints; freeform_xz: 3000 G1
    # micro-segments fitted to splines, no corner, where the jerk of the turning centripetal
    # acceleration binds (1.14 before the speed profile took it into account)
    path = parse_gcode((DATA / f"{name}.ngc").read_text(), source=name)
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    # bound: L/F plus half the extra of a 1-D rest-to-rest profile at each end (along X)
    extra = rest_to_rest(1.0, F3000, 2.5, 10.0) - 1.0 / F3000
    assert sp.duration <= 1.10 * (path.feed_length / F3000 + extra)


def test_speed_changes_on_arcs_keep_the_jerk_of_the_centripetal_acceleration():
    # R2 mm arcs at F6000 (centripetal 5 m/s^2 above the limit: the speed drops on the arcs
    # and rises on the lines between them, v^2 / R changing with it), reversing each time
    segs, p, sense = [], np.zeros(3), 1.0
    feed = 0.1
    for k in range(4):
        q = p + [30 * MM, 0, 0]
        segs.append(Line(p, q, feed, line=2 * k + 1))
        arc = arc_between(q, q + [0, 0, sense * 2 * MM], "zx", -sense * math.pi, feed,
                          line=2 * k + 2)
        segs.append(arc)
        p, sense = arc.end, -sense
    path = Path(np.zeros(3), tuple(segs), "zx")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    v, _, _ = fd(sp.pos, sp.dt)
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() > 0.9 * feed  # it does speed up between arcs


def test_line_arc_line_curvature_jumps_in_xz():
    # X line, G18 quarter arc R5 mm, Z line: curvature jumps of 200 1/m at both joints
    l1 = Line([0, 0, 0], [20 * MM, 0, 0], F3000, line=1)
    arc = arc_between(l1.end, [20 * MM, 0, 5 * MM], "zx", -math.pi / 2, F3000, line=2)  # G2 in G18
    assert np.allclose(arc.end, [25 * MM, 0, 5 * MM], atol=1e-12)
    l2 = Line(arc.end, arc.end + [0, 0, 15 * MM], F3000, line=3)
    path = Path(l1.start, (l1, arc, l2), "zx")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    assert sp.plane == "zx"
    assert set(np.unique(sp.block)) == {1, 2, 3}
    # no exact stop at tangent joints: the speed never drops near zero in mid-path
    v, _, _ = fd(sp.pos, sp.dt)
    speed = np.linalg.norm(v[: len(sp.pos)], axis=1)
    mid = (sp.s > 5 * MM) & (sp.s < path.length - 5 * MM)
    assert speed[mid].min() > 0.3 * F3000


def test_helix_three_axes():
    start = np.array([10 * MM, 0, 0])
    arc = arc_between(start, [0, 0, 0], "xy", 3 * math.pi, 2000 / 60000, rise=3 * MM, line=7)
    path = Path(start, (arc,), "xy")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    assert sp.plane is None  # Z moves with the feed
    assert sp.moving_axes == (0, 1, 2)


def test_sharp_corner_under_g61_is_an_exact_stop():
    l1 = Line([0, 0, 0], [10 * MM, 0, 0], F3000, line=1, blend_tol_m=0.0)  # G61
    l2 = Line(l1.end, [10 * MM, 10 * MM, 0], F3000, line=2)
    path = Path(l1.start, (l1, l2), "xy")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    at_corner = np.flatnonzero(np.all(sp.pos == l1.end, axis=1))
    assert at_corner.size >= 3 and np.all(np.diff(at_corner) == 1)  # at rest there (v = a = 0)


def test_noisy_micro_lines_are_fitted_within_tolerance():
    rng = np.random.default_rng(3)
    x = np.arange(0, 401) * 0.05 * MM
    z = 1.5 * MM * np.sin(2 * np.pi * x / (12 * MM)) + rng.uniform(-0.5e-6, 0.5e-6, x.size)
    pts = np.round(np.column_stack([x, np.zeros_like(x), z]), 6)  # 1 um grid
    segs = tuple(Line(pts[k], pts[k + 1], F3000, line=k + 10) for k in range(len(pts) - 1))
    path = Path(pts[0], segs, "zx")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    assert sp.block.min() == 10 and sp.block.max() == 409
    assert np.all(np.diff(sp.block) >= 0)


def test_feed_override_and_rapid_then_feed():
    r = Line([0, 0, 0], [0, 0, 10 * MM], math.inf, rapid=True, line=1)
    l1 = Line(r.end, r.end + [20 * MM, 0, 0], 0.2, line=2)
    path = Path(r.start, (r, l1), "xy")
    sp = plan(path, UCP, feed_m_s=F3000)
    v, _, _ = fd(sp.pos, sp.dt)
    speed = np.linalg.norm(v[: len(sp.pos)], axis=1)
    assert speed[~sp.rapid].max() <= 1.005 * F3000
    assert speed[~sp.rapid].max() >= 0.99 * F3000
    assert sp.rapid[: 10].all() and not sp.rapid[-10:].any()
    assert sp.plane == "xy"


def test_feed_change_and_reported_derivatives():
    l1 = Line([0, 0, 0], [20 * MM, 0, 0], F3000, line=1)
    l2 = Line(l1.end, [40 * MM, 0, 0], 1000 / 60000, line=2)
    l3 = Line(l2.end, [60 * MM, 0, 0], F3000, line=3)
    path = Path(l1.start, (l1, l2, l3), "xy")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    v, a, j = fd(sp.pos, sp.dt)
    speed = np.linalg.norm(v[: len(sp.pos)], axis=1)
    inside = (sp.pos[:, 0] > 20.001 * MM) & (sp.pos[:, 0] < 39.999 * MM)
    assert speed[inside].max() <= 1.005 * l2.feed_m_s
    assert speed[sp.pos[:, 0] < 19 * MM].max() >= 0.99 * F3000
    # vel/acc/jerk: the backward differences centred on the sample, within the limits too
    n = len(sp.pos)
    assert np.allclose(sp.vel, (v[:n] + v[1 : n + 1]) / 2, rtol=0, atol=1e-12)
    assert np.allclose(sp.acc, a[1 : n + 1], rtol=0, atol=1e-9)
    assert np.allclose(sp.jerk, j[2 : n + 2], rtol=0, atol=1e-6)
    for x, lim in ((sp.vel, UCP.vmax_m_s), (sp.acc, UCP.amax_m_s2), (sp.jerk, UCP.jmax_m_s3)):
        assert np.all(np.abs(x) <= lim)
    assert np.allclose(sp.s[-1], path.length, rtol=1e-9)


def test_no_feed_without_override_is_an_option_error():
    seg = Line([0, 0, 0], [1 * MM, 0, 0], math.nan, line=3)
    with pytest.raises(OptionError, match="line 3"):
        plan(Path(seg.start, (seg,)), UCP)


def test_machine_without_z_plans_in_xy():
    lim = AxisLimits(np.array([0.5, 0.5, 0]), np.array([2.5, 2.5, 0]), np.array([10.0, 10.0, 0]))
    start = np.array([10 * MM, 0, 0])
    arc = arc_between(start, [0, 0, 0], "xy", math.pi, F3000, line=1)
    line = Line(arc.end, arc.end + [0, -10 * MM, 0], F3000, line=2)
    path = Path(start, (arc, line), "xy")
    sp = plan(path, lim)
    assert_plan_ok(sp, path, lim)
    assert np.all(sp.pos[:, 2] == 0.0)


def test_moving_an_absent_axis_is_a_toolpath_error():
    lim = AxisLimits(np.array([0.5, 0.5, 0]), np.array([2.5, 2.5, 0]), np.array([10.0, 10.0, 0]))
    seg = Line([0, 0, 0], [1 * MM, 0, 1 * MM], F3000, line=4)
    with pytest.raises(ToolpathError, match="axis z, which the machine lacks"):
        plan(Path(seg.start, (seg,)), lim)


@pytest.mark.parametrize("kw", [{"tol_m": 0.0}, {"dt": -1e-3}, {"feed_m_s": math.inf}])
def test_bad_options(kw):
    seg = Line([0, 0, 0], [1 * MM, 0, 0], F3000)
    with pytest.raises(OptionError):
        plan(Path(seg.start, (seg,)), UCP, **kw)


# ----------------------------------------------------------------------------- feedplan.check


def line_arc_line() -> Path:
    l1 = Line([0, 0, 0], [20 * MM, 0, 0], F3000, line=1)
    arc = arc_between(l1.end, [20 * MM, 0, 5 * MM], "zx", -math.pi / 2, F3000, line=2)
    l2 = Line(arc.end, arc.end + [0, 0, 15 * MM], F3000, line=3)
    return Path(l1.start, (l1, arc, l2), "zx")


def test_check_agrees_with_independent_measurements():
    path = line_arc_line()
    sp = plan(path, UCP)
    chk = check_setpoints(sp, path, UCP)
    v, a, j = fd(sp.pos, sp.dt)
    assert chk.ok and chk.violations == ()
    assert np.allclose(chk.max_jerk_m_s3, np.abs(j).max(axis=0), rtol=1e-12)
    assert np.allclose(chk.acc_ratio, np.abs(a).max(axis=0) / UCP.amax_m_s2, rtol=1e-12)
    assert abs(chk.max_deviation_m - deviation(sp.pos, path.segments).max()) < 0.05e-6
    assert chk.ends_at_rest and chk.end_error_m == 0.0
    axes = chk.axes_dict()
    assert set(axes) == {"x", "y", "z"}
    assert axes["x"]["max_jerk_m_s3"] == np.abs(j[:, 0]).max() and axes["x"]["jmax_m_s3"] == 10.0


def test_check_flags_a_constant_feed_plan_and_measures_arcs_exactly():
    path = line_arc_line()
    s = np.arange(0.0, path.length, F3000 * 1e-3)
    bounds = np.cumsum([0.0] + [seg.length for seg in path.segments])
    k = np.clip(np.searchsorted(bounds, s, side="right") - 1, 0, 2)
    segs = path.segments
    pos = np.array([segs[i].point((x - bounds[i]) / segs[i].length) for i, x in zip(k, s)])
    zero = np.zeros((len(pos), 3))
    sp = Setpoints(1e-3, s, pos, zero, zero, zero, k + 1, np.zeros(len(pos), bool))
    chk = check_setpoints(sp, path, UCP)
    assert not chk.ok
    assert chk.max_deviation_m < 1e-12  # samples on the arc itself, not on chords
    text = " ".join(chk.violations)
    assert "axis x jerk" in text and "axis z jerk" in text  # speed step at start, curvature jumps
    assert "end at rest" in text and "programmed end" in text
    # a sample pushed 30 um off the line is measured as such
    bumped = pos.copy()
    bumped[100, 2] += 30e-6
    sp2 = Setpoints(1e-3, s, bumped, sp.vel, sp.acc, sp.jerk, sp.block, sp.rapid)
    assert abs(check_setpoints(sp2, path, UCP).max_deviation_m - 30e-6) < 1e-12


# ----------------------------------------------------------------------------- properties


@st.composite
def chains(draw):
    """Random chains of 1-3 lines and arcs in XY or ZX, a few mm long."""
    plane = draw(st.sampled_from(["xy", "zx"]))
    i, j, n = PLANES[plane]
    feed = draw(st.floats(500, 4000)) / 60000
    p = np.zeros(3)
    heading = draw(st.floats(-math.pi, math.pi))
    segs = []
    for k in range(draw(st.integers(1, 3))):
        if draw(st.booleans()):
            L = draw(st.floats(0.5, 6.0)) * MM
            q = p.copy()
            q[i] += L * math.cos(heading)
            q[j] += L * math.sin(heading)
            segs.append(Line(p, q, feed, line=k + 1))
        else:
            R = draw(st.floats(1.0, 20.0)) * MM
            sweep = draw(st.floats(0.3, 3.0)) * draw(st.sampled_from([-1.0, 1.0]))
            side = math.copysign(1.0, sweep)  # centre to the left for CCW
            c = p.copy()
            c[i] += R * math.cos(heading + side * math.pi / 2)
            c[j] += R * math.sin(heading + side * math.pi / 2)
            segs.append(arc_between(p, c, plane, sweep, feed, line=k + 1))
            heading += sweep
        p = segs[-1].end
        heading += draw(st.sampled_from([0.0, 0.0, 0.05, 1.0]))  # tangent, kink, corner
    return Path(np.zeros(3), tuple(segs), plane)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(chains())
def test_random_chains_plan_within_limits_and_tolerance(path):
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)


# ----------------------------------------------------------------------------- issue 18: bounded


def x_move(length_m, feed_m_s, line=2) -> Path:
    seg = Line([0, 0, 0], [length_m, 0, 0], feed_m_s, line=line)
    return Path(seg.start, (seg,), "xy")


def test_higher_programmed_feed_is_never_slower():
    """11 mm on X, F3000 .. F1e10 (vmax 30000 mm/min): durations non-increasing, all within
    the limits, a warning where F is above the axis speed; above it, the plan is F30000's."""
    feeds_mm_min = [3000, 10000, 30000, 30001, 1e6, 1e7, 1e8, 1e10]
    out = []
    for f in feeds_mm_min:
        path = x_move(11 * MM, f / 60e3)
        sp = plan(path, UCP)
        capped = Path(path.start, (Line(path.start, path.segments[0].end, min(f, 30000) / 60e3),))
        assert_plan_ok(sp, capped, UCP)
        assert bool(sp.warnings) == (f > 30000), sp.warnings
        out.append(sp)
    durations = [sp.duration for sp in out]
    assert all(b <= a + 1e-12 for a, b in zip(durations, durations[1:])), durations
    assert durations[-1] == durations[2]
    assert np.array_equal(out[-1].pos, out[2].pos)
    assert "feed 1e+10 mm/min is above what the axes allow (30000 mm/min)" in out[-1].warnings[0]


def test_feed_above_axis_speed_on_arcs_and_diagonals_is_capped_at_the_axes():
    """A diagonal's axis speed is vmax / max|direction|; an arc's is its largest along the sweep
    (vmax_x = vmax_y: sqrt(2) vmax at 45 deg) and the planned plan is F30000*sqrt(2)'s."""
    diag = Line([0, 0, 0], [10 * MM, 5 * MM, 0], 1e8 / 60e3, line=2)
    sp = plan(Path(diag.start, (diag,)), UCP)
    assert f"({0.5 / (10 / math.hypot(10, 5)) * 60e3:.6g} mm/min)" in sp.warnings[0]
    arc = arc_between([10 * MM, 0, 0], [0, 0, 0], "xy", math.pi / 2, 1e9, line=3)
    sp = plan(Path(arc.start, (arc,)), UCP)
    assert f"({0.5 * math.sqrt(2) * 60e3:.6g} mm/min)" in sp.warnings[0]
    capped = arc_between(arc.start, [0, 0, 0], "xy", math.pi / 2, 0.5 * math.sqrt(2), line=3)
    path = Path(arc.start, (capped,))
    assert_plan_ok(sp, path, UCP)
    assert sp.duration == plan(path, UCP).duration


@pytest.mark.parametrize("feed_mm_min", [10.0, 100.0])
@pytest.mark.parametrize("pieces", [1, 2])
def test_slow_feed_takes_the_time_of_its_ramps(feed_mm_min, pieces):
    """1 mm at F10 / F100, as one line (planned by ruckig) and as two collinear halves (a
    chain: profile and filter): within 2 % of ruckig's rest-to-rest optimum at the same
    v, a, j (no per-cell overhead of the speed profile's grid)."""
    f = feed_mm_min / 60e3
    ends = np.linspace(0.0, 1 * MM, pieces + 1)
    segs = tuple(Line([a, 0, 0], [b, 0, 0], f, line=k + 2)
                 for k, (a, b) in enumerate(zip(ends, ends[1:])))
    path = Path(segs[0].start, segs, "xy")
    sp = plan(path, UCP)
    assert_plan_ok(sp, path, UCP)
    best = rest_to_rest(1 * MM, f, 2.5, 10.0)
    assert best - 1e-9 <= sp.duration <= 1.02 * best, (sp.duration, best)


@pytest.mark.parametrize("axis, length_mm, feed_mm_min", [
    (0, 0.04, 100000), (0, 0.04, 3000), (0, 11, 30000), (2, 200, 30000), (1, 14.5, 50),
    (0, 1, 1000), (2, 3, 600)])
def test_straight_blocks_within_2_percent_of_ruckig(axis, length_mm, feed_mm_min):
    """Issue 21: a lone feed line is ruckig's time-optimal profile (limits projected on it,
    speed capped at the feed and at the axis), within 2 % (its 1e-3 margin) and the sample
    grid: the motion ends at the next whole sample and 2 samples at rest follow (+ 3 dt)."""
    end = np.zeros(3)
    end[axis] = length_mm * MM
    seg = Line([0, 0, 0], end, feed_mm_min / 60e3, line=2)
    path = Path(seg.start, (seg,), "xy")
    sp = plan(path, UCP)
    capped = Line(seg.start, seg.end, min(seg.feed_m_s, 0.5), line=2)
    assert_plan_ok(sp, Path(seg.start, (capped,)), UCP)
    # at the jerk share a feed line's tangential motion gets (_AT_SHARE), as rapids
    best = rest_to_rest(seg.length, capped.feed_m_s, UCP.amax_m_s2[axis],
                        UCP.jmax_m_s3[axis] * _AT_SHARE)
    assert best - 1e-9 <= sp.duration <= 1.02 * best + 3 * sp.dt, (sp.duration, best)


def test_absurd_feeds_end_quickly_at_the_axis_speed():
    """Issue 18 row 1: F1e10 (and an override of 1e14 mm/min) used to loop for ever."""
    text = "G21 G90\nG1 X0 Y0 F10000000000\nG1 X10 Y5\nM2\n"
    path = parse_gcode(text, source="f.ngc")
    a = plan(path, UCP)
    b = plan(path, UCP, feed_m_s=1e14 / 60e3)
    assert a.duration == b.duration < 0.5
    assert a.warnings[0].startswith("line 3: feed 1e+10 mm/min")
    assert b.warnings[0].startswith("line 3: feed 1e+14 mm/min")


def test_too_long_programs_are_refused_before_planning():
    """Issue 18 row 2: the least motion time is estimated first, naming the slowest move."""
    path = parse_gcode("G21 G90\nG1 X0 Y0 F0.001\nG1 X1 Y0\n", source="slow.ngc")
    with pytest.raises(ToolpathError) as err:
        plan(path, UCP)
    assert str(err.value) == (
        "slow.ngc: program would take 6e+04 s of motion, 6e+07 samples of 0.001 s (limits "
        "3600 s, 4000000 samples): line 3 moves 1 mm at F0.001 mm/min")
    path = parse_gcode("G21 G90\nG0 X0 Y0\nG0 X1000000\nG0 X-1000000\n", source="r.ngc")
    with pytest.raises(ToolpathError, match="program would take 6e\\+03 s .* line 4 moves a "
                       "rapid of 2e\\+06 mm"):
        plan(path, UCP)
    path = x_move(0.5, 0.01)  # 50 s: fine at 1 ms, too many samples at 10 us
    with pytest.raises(ToolpathError, match="5e\\+06 samples of 1e-05 s"):
        plan(path, UCP, dt=1e-5)


def test_least_motion_time_is_a_lower_bound_of_the_plan():
    """At the feeds (capped at the axes; the diagonal rapid at 0.5 / 0.8 m/s) without ramps:
    L / F exactly, below the plan."""
    from feedplan.plan import least_motion_s

    path = parse_gcode("G21 G90\nG0 X0 Y0\nG1 X30 F600\nG1 Y40 F1000000000\nG0 X0 Y0\n")
    t = least_motion_s(path, UCP)
    assert t == pytest.approx(30e-3 / 0.01 + 40e-3 / 0.5 + 50e-3 / 0.625, rel=1e-12)
    assert t < plan(path, UCP).duration
    assert least_motion_s(path, UCP, feed_m_s=0.02) == pytest.approx(
        30e-3 / 0.02 + 40e-3 / 0.02 + 50e-3 / 0.625, rel=1e-12)


def test_sample_limit_is_enforced_while_planning(monkeypatch):
    """Stops at corners cost more than the estimate (no ramps): the limit still holds."""
    planner = importlib.import_module("feedplan.plan")  # the module, not feedplan.plan()
    pts = [[k * 0.1 * MM, (k % 2) * 0.1 * MM, 0] for k in range(11)]
    segs = tuple(Line(a, b, F3000, line=k + 2) for k, (a, b) in enumerate(zip(pts, pts[1:])))
    path = Path(segs[0].start, segs)
    full = len(plan(path, UCP))
    monkeypatch.setattr(planner, "MAX_SAMPLES", full // 2)
    with pytest.raises(ToolpathError, match="the plan exceeds the limits of one plan"):
        plan(path, UCP)
    rapid = Path(np.zeros(3), (Line([0, 0, 0], [0.1, 0, 0], math.inf, rapid=True, line=1),))
    monkeypatch.setattr(planner, "MAX_SAMPLES", 300)  # 0.1 m at 0.5 m/s: 0.2 s + ramps
    with pytest.raises(ToolpathError, match="line 1: the plan exceeds"):
        plan(rapid, UCP)


def test_hand_built_paths_beyond_the_bounds_are_refused():
    """Paths not from a reader: non-finite or far points, arcs of endless turns."""
    far = Line([0, 0, 0], [2e3, 0, 0], F3000, line=4)
    nan = Line([0, 0, 0], [math.nan, 0, 0], F3000, line=5)
    for seg, what in ((far, "line 4: a point beyond 1000 m"), (nan, "line 5: a point beyond")):
        with pytest.raises(ToolpathError, match=what):
            plan(Path(seg.start, (seg,)), UCP)
    arc = Arc([1e-3, 0, 0], [1e-3, 0, 0], [0, 0, 0], "xy", 1e300, F3000, line=6)
    with pytest.raises(ToolpathError, match="line 6: arc sweep 1e\\+300 rad: more than 1000 turns"):
        plan(Path(arc.start, (arc,)), UCP)


def test_no_motion_is_a_toolpath_error():
    for text in ("", "(only a comment)\n", "G21 G0 X1 Y2\nM2\n"):
        with pytest.raises(ToolpathError, match="^no motion in p.ngc$"):
            plan(parse_gcode(text, source="p.ngc"), UCP)


@pytest.mark.parametrize("kw", [{"dt": 1e-9}, {"dt": 0.5}, {"tol_m": 1e-12}, {"tol_m": 0.5}])
def test_dt_and_tolerance_ranges(kw):
    with pytest.raises(OptionError, match=next(iter(kw)) + " must be in"):
        plan(x_move(1 * MM, F3000), UCP, **kw)


def test_progress_reaches_one_and_never_goes_back():
    seen = []
    path = parse_gcode((DATA / "reference_xz.ngc").read_text())
    plan(path, UCP, progress=seen.append)
    assert len(seen) > 10 and seen[-1] == 1.0
    assert all(0.0 <= a <= b <= 1.0 for a, b in zip(seen, seen[1:]))


def _micro_run(end_mm, n, feed, jitter_mm=0.0, backwards_at=None):
    """Lines 2.. of ``n`` micro-segments from the origin to ``end_mm`` (each vertex moved by
    ``jitter_mm`` across the run, alternating sides; one vertex moved back along it)."""
    end = np.asarray(end_mm, float) * MM
    side = np.cross(end, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) else np.array([1.0, 0, 0])
    pts = np.linspace(0.0, 1.0, n + 1)[:, None] * end
    pts[1:-1] += ((-1.0) ** np.arange(1, n))[:, None] * jitter_mm * MM * side
    if backwards_at is not None:
        pts[backwards_at] = pts[backwards_at - 2]
    segs = tuple(Line(a, b, feed, line=k + 2) for k, (a, b) in enumerate(zip(pts, pts[1:])))
    return Path(pts[0], segs, "xy")


def test_straight_run_of_micro_segments_is_planned_as_its_line():
    """Issue 21: a straight move the CAM cut into 0.5 mm pieces (lcnc_short_segments) is the
    line's ruckig profile, bit for bit; each sample's source line is the move it lies on."""
    path = _micro_run([12.0, 5.0, 0.0], 26, F3000)  # 13 mm in 26 moves of 0.5 mm
    sp = plan(path, UCP)
    whole = plan(Path(path.start, (Line(path.start, path.segments[-1].end, F3000, line=2),),
                      "xy"), UCP)
    assert np.array_equal(sp.pos, whole.pos)
    assert_plan_ok(sp, path, UCP)
    u = sp.pos @ (path.segments[0].end / path.segments[0].length)
    starts = np.array([s.start @ (path.segments[0].end / path.segments[0].length)
                       for s in path.segments] + [np.inf])
    expect = np.clip(np.searchsorted(starts, u, side="right") - 1, 0, 25) + 2
    assert np.array_equal(sp.block, expect)


def test_straight_run_with_rounded_vertices_is_a_line_and_a_zigzag_is_not():
    # vertices 0.5 um either side of the chord (a CAM's rounding): within COLLINEAR_TOL_SHARE
    # of the 10 um fit tolerance (half of 20 um), the chord itself
    near = _micro_run([10.0, 0.0, 0.0], 40, F3000, jitter_mm=0.0005)
    sp = plan(near, UCP, tol_m=TOL)
    assert np.abs(sp.pos[:, 1]).max() == 0.0
    assert_plan_ok(sp, near, UCP)
    for far in (_micro_run([10.0, 0.0, 0.0], 40, F3000, jitter_mm=0.005),  # 5 um: fitted
                _micro_run([10.0, 0.0, 0.0], 40, F3000, backwards_at=20)):  # one move back
        sp_far = plan(far, UCP, tol_m=TOL)
        assert not np.array_equal(sp_far.pos[:, 1:], sp.pos[:, 1:]) or len(sp_far) != len(sp)
        assert_plan_ok(sp_far, far, UCP)
