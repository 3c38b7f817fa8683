"""Planning speed work changes no output: setpoints against the stored reference arrays.

``tests/data/reference/plan.npz`` holds, per program of :data:`plan_reference.PROGRAMS`, the
sample count, source lines and rapid flags (compared exactly) and every
:data:`plan_reference.STRIDE`-th position (within :data:`references.TOL`, measured across CPU
configurations: ``tests/references.py``); regenerate it with ``PYTHONPATH=. python
tests/references.py regen plan`` when the planner's output is meant to change. A generated
micro-segment program is also checked here against the limits (finite differences) and the
tolerance (exact distance to its programmed polyline).
"""

from __future__ import annotations

import numpy as np
import pytest

import plan_reference as ref
import references
from feedplan.read import read_toolpath
from oga.defaults import TOL_M
from oga.model.machine import load_machine


@pytest.mark.portable
@pytest.mark.parametrize("name", ref.PROGRAMS)
def test_setpoints_as_stored(name):
    got = references.cases("plan")[name]()
    assert references.compare("plan", name, got) == []


def test_comparison_sees_a_change_above_the_tolerance():
    """A position moved by ten times the tolerance, a block number changed: both named."""
    name = "short_xz.ngc"
    got = references.stored("plan", name)
    assert references.compare("plan", name, got) == []
    tol = references.TOL["plan"]["pos"][0]
    moved = {**got, "pos": got["pos"].copy(), "block": got["block"].copy()}
    moved["pos"][len(moved["pos"]) // 2, 0] += 10 * tol
    moved["block"][-1] += 1
    bad = references.compare("plan", name, moved)
    assert len(bad) == 2 and "pos: largest difference" in bad[1] and "block" in bad[0]


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of each point p (N, 3) to the nearest of the segments a[i]-b[i] (M, 3)."""
    ab = b - a
    best = np.full(len(p), np.inf)
    for k in range(0, len(a), 256):
        aa, bb = a[k:k + 256], ab[k:k + 256]
        w = p[:, None, :] - aa[None]
        f = np.clip(np.sum(w * bb[None], axis=2) / np.sum(bb * bb, axis=1)[None], 0.0, 1.0)
        d = np.linalg.norm(w - f[..., None] * bb[None], axis=2)
        best = np.minimum(best, d.min(axis=1))
    return best


def test_micro_segments_within_limits_and_tolerance():
    n = 2000
    text = ref.micro_program(n)
    path = read_toolpath(text, "gcode", source="micro")
    assert len(path.segments) == n
    _assert_within(ref.plan_program(f"micro_{n}"), path)


def test_a_long_fitted_block_is_planned_along_its_curve(monkeypatch):
    """A fitted block of more grid nodes than the old limit (4 000) gets the exact-curve
    profile: within the limits and the tolerance, and faster than the filter's plan of the
    same block (that limit put back, in the same process)."""
    import importlib

    from feedplan import profile

    planner = importlib.import_module("feedplan.plan")
    path = read_toolpath(ref.micro_program(15000), "gcode", source="micro")
    lim = load_machine("ucp710").planning_limits()
    grids = []
    grid = profile.grid
    monkeypatch.setattr(profile, "grid", lambda curve, **kw: grids.append(grid(curve, **kw)) or grids[-1])
    exact = planner.plan(path, lim)
    assert 4000 < max(g.size for g in grids) <= planner._PROFILE_NODES  # the fitted block
    _assert_within(exact, path)
    monkeypatch.setattr(planner, "_PROFILE_NODES", 4000)
    filtered = planner.plan(path, lim)
    _assert_within(filtered, path)
    assert exact.duration < 0.95 * filtered.duration


def _assert_within(sp, path):
    """Every sample within the planning limits (finite differences, from rest to rest), the
    feed and the tolerance of the programmed polyline ``path``."""
    lim = load_machine("ucp710").planning_limits()
    p = np.concatenate([np.repeat(sp.pos[:1], 3, axis=0), sp.pos, np.repeat(sp.pos[-1:], 3, axis=0)])
    v = np.diff(p, axis=0) / sp.dt
    a = np.diff(v, axis=0) / sp.dt
    j = np.diff(a, axis=0) / sp.dt
    for x, bound in ((v, lim.vmax_m_s), (a, lim.amax_m_s2), (j, lim.jmax_m_s3)):
        assert np.all(np.abs(x).max(axis=0) <= bound * (1 + 1e-9))
    speed = np.linalg.norm(v[2:-3], axis=1)  # row k + 2 ends at pos[k]
    assert speed.max() <= path.segments[0].feed_m_s * 1.005
    a_pts = np.array([s.start for s in path.segments])
    b_pts = np.array([s.end for s in path.segments])
    assert np.all(_distance_within(sp.pos, a_pts, b_pts, TOL_M))
    assert np.array_equal(sp.pos[0], path.start) and np.array_equal(sp.pos[-1], b_pts[-1])


def _distance_within(p, a, b, tol):
    """Whether each point p (N, 3) is within ``tol`` of one of the segments a[i]-b[i]: exact
    distances (:func:`_segment_distance`) to the short segments whose middle is within ``tol``
    plus their largest half-length (a k-d tree finds them) and to every long one."""
    from scipy.spatial import cKDTree

    length = np.linalg.norm(b - a, axis=1)
    short = length <= 1e-3
    near = cKDTree(0.5 * (a[short] + b[short])).query_ball_point(
        p, tol + 0.5 * length[short].max())
    best = _segment_distance(p, a[~short], b[~short])
    sa, sb = a[short], b[short]
    for i, cand in enumerate(near):
        if cand:
            best[i] = min(best[i], _segment_distance(p[i:i + 1], sa[cand], sb[cand])[0])
    return best <= tol


@pytest.mark.parametrize("n, step", [(4, 1), (60, 1), (60, 7), (3000, 1), (3000, 10), (20000, 10)])
def test_lsq_coefficients_as_scipy(n, step):
    """The linear-time QR gives make_lsq_spline's coefficients bit for bit."""
    from scipy.interpolate import make_lsq_spline

    from feedplan.fit import _lsq_coefficients

    rng = np.random.default_rng(n + step)
    u = np.concatenate([[0.0], np.cumsum(rng.uniform(10e-6, 50e-6, n))])
    x = np.sort(np.concatenate([u, 0.5 * (u[:-1] + u[1:])]))
    y = np.column_stack([np.sin(x / 3e-3), np.cos(x / 7e-3), x]) * 1e-3
    y += 1e-7 * rng.standard_normal(y.shape)
    t = np.concatenate([[u[0]] * 4, u[np.arange(step, n, step)], [u[-1]] * 4])
    assert np.array_equal(_lsq_coefficients(x, y, t), make_lsq_spline(x, y, t, k=3).c)


def test_spline_values_as_scipy():
    """The compiled cubic evaluation gives scipy's BSpline values and derivatives bit for bit."""
    from scipy.interpolate import make_lsq_spline

    from feedplan.fit import _spline_values, _spline_values_d2

    rng = np.random.default_rng(5)
    u = np.concatenate([[0.0], np.cumsum(rng.uniform(10e-6, 50e-6, 400))])
    y = np.column_stack([np.sin(u / 2e-3), np.cos(u / 5e-3), u]) * 1e-3
    t = np.concatenate([[0.0] * 4, u[3:-3:3], [u[-1]] * 4])
    spl = make_lsq_spline(u, y, t, k=3)
    x = np.concatenate([np.sort(rng.uniform(0, u[-1], 5000)), u, rng.uniform(-1e-4, u[-1] + 1e-4, 99)])
    got = _spline_values(spl.t, spl.c, x, 3)
    for nu in range(4):
        assert np.array_equal(got[nu], spl(x, nu)), nu
    # the planner's unrolled order-2 kernel: the same bits, also beside repeated knots
    assert np.array_equal(_spline_values_d2(spl.t, spl.c, x), got[:3])
    t2 = np.array([0, 0, 0, 0, 0.2, 0.5, 0.5, 0.5, 0.8, 1, 1, 1, 1.0])
    c2 = rng.standard_normal((t2.size - 4, 3))
    x2 = np.concatenate([np.linspace(0, 1, 501), t2, rng.uniform(-0.1, 1.1, 99)])
    assert np.array_equal(_spline_values_d2(t2, c2, x2), _spline_values(t2, c2, x2, 2),
                          equal_nan=True)


def _track_reference(pos, segs, window=64):
    """The tracking rule of feedplan.check.deviation_m without any pruning: every move of
    the window measured (lines only)."""
    a = np.array([s.start for s in segs])
    b = np.array([s.end for s in segs])

    def dist(p, s):
        ab, ap = b[s] - a[s], p - a[s]
        den = ab @ ab
        f = min(1.0, max(0.0, (ap @ ab) / den)) if den > 0 else 0.0
        return float(np.linalg.norm(ap - f * ab))

    cur, out, near = 0, [], []
    for p in pos:
        best = dist(p, cur)
        held, arg = best, cur
        for s in [*range(cur + 1, cur + window + 1), *range(cur - 1, cur - window - 1, -1)]:
            if 0 <= s < len(segs):
                d = dist(p, s)
                best = min(best, d)
                if d < held - 1e-9:
                    held, arg = d, s
        out.append(best)
        near.append(arg)
        cur = arg
    return np.array(out), np.array(near)


def test_deviation_tracker_as_without_pruning():
    """The pruned tracker (balls of groups and windows) finds the same distances and moves."""
    from feedplan.check import deviation_m, segment_table

    sp = ref.plan_program("micro_2000")
    path = read_toolpath(ref.micro_program(2000), "gcode", source="micro")
    segs = [s for s in path.segments if not s.rapid]
    rng = np.random.default_rng(11)
    feed = sp.pos[sp.pos[:, 0] > 0][::7]  # past the rapid to the start
    pos = feed + rng.normal(0.0, 20e-6, feed.shape)
    dist, near = deviation_m(pos, segment_table(segs))
    want_d, want_n = _track_reference(pos, segs)
    assert np.array_equal(near, want_n)
    assert np.allclose(dist, want_d, rtol=0, atol=1e-15)
