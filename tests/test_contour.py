"""Contour error and metrics against exact geometry and a brute-force reference."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from feedplan.path import PLANES, Arc
from oga.model.contour import (
    ce2_at,
    ce_at,
    ce_point,
    ce_series,
    contour_error,
    contour_error_of,
    moving_count,
    nearest_segment,
    path_index,
    window_bounds,
)
from oga.errors import InputError, OptionError
from oga.model.metrics import contour_metrics

UM = 1e-6


def _xyz(e1_vals, e2_vals, plane, normal_val=0.0):
    """(N, 3) points from in-plane coordinates of ``plane``."""
    i, j, n = PLANES[plane]
    out = np.empty((len(e1_vals), 3))
    out[:, i] = e1_vals
    out[:, j] = e2_vals
    out[:, n] = normal_val
    return out


def _lagged(pd, lag):
    """Index k-lag clipped at 0: where a lagging axis would be."""
    return pd[np.maximum(np.arange(len(pd)) - lag, 0)]


# ---------------------------------------------------------------- straight line


@pytest.mark.parametrize("side", [+1.0, -1.0])
def test_line_offset_is_perpendicular_distance_signed_by_side(side):
    # XY, travel along +X: left is +Y
    x = np.linspace(0.0, 0.01, 1001)
    pd = np.column_stack([x, np.zeros_like(x), np.full_like(x, 0.2)])
    pa = _lagged(pd, 20) + np.array([0.0, side * 7 * UM, 0.0])
    ce = contour_error(pd, pa, "xy")
    np.testing.assert_allclose(ce, side * 7 * UM, rtol=0, atol=1e-15)


def test_line_along_its_own_direction_has_zero_error():
    t = np.linspace(0.0, 1.0, 500)
    pd = np.column_stack([0.01 * t, 0.02 * t, np.zeros_like(t)])
    ce = contour_error(pd, _lagged(pd, 30), "xy")
    np.testing.assert_allclose(ce, 0.0, atol=1e-17)


def test_diagonal_line_offset_along_left_normal():
    # travel direction u = (3, 4)/5 in XY; left normal (-4, 3)/5
    t = np.linspace(0.0, 1.0, 800)[:, None]
    pd = np.hstack([0.003 * t, 0.004 * t, np.zeros_like(t)])
    d = 5 * UM
    pa = _lagged(pd, 10) + d * np.array([-0.8, 0.6, 0.0])
    np.testing.assert_allclose(contour_error(pd, pa, "xy"), d, rtol=1e-9)
    pa = _lagged(pd, 10) - d * np.array([-0.8, 0.6, 0.0])
    np.testing.assert_allclose(contour_error(pd, pa, "xy"), -d, rtol=1e-9)


# ---------------------------------------------------------------------- circles

R = 0.05
N_CIRCLE = 20000


def _sagitta(n):
    return R * (1 - np.cos(np.pi / n))


@pytest.mark.parametrize(
    "sense, radial, expected_sign",
    [
        (+1, +1, -1),  # CCW, outside: right of travel
        (+1, -1, +1),  # CCW, inside: left
        (-1, +1, +1),  # CW, outside: left
        (-1, -1, -1),  # CW, inside: right
    ],
)
def test_circle_radial_offset(sense, radial, expected_sign):
    th = sense * np.linspace(0.0, 2 * np.pi, N_CIRCLE + 1)
    pd = _xyz(R * np.cos(th), R * np.sin(th), "xy", 0.1)
    d = 4 * UM
    lag = 40
    th_a = th[np.maximum(np.arange(len(th)) - lag, 0)]
    pa = _xyz((R + radial * d) * np.cos(th_a), (R + radial * d) * np.sin(th_a), "xy", 0.1)
    ce = contour_error(pd, pa, "xy")
    # actual points sit on vertex rays: exact distance d (chords only reach further)
    np.testing.assert_allclose(ce, expected_sign * d, rtol=0, atol=_sagitta(N_CIRCLE) + 1e-15)


def test_circle_between_vertices_within_sagitta():
    th = np.linspace(0.0, 2 * np.pi, 4001)
    pd = _xyz(R * np.cos(th), R * np.sin(th), "xy")
    th_a = th - 25.5 * (th[1] - th[0])  # half way between vertices
    d = 2 * UM
    pa = _xyz((R + d) * np.cos(th_a), (R + d) * np.sin(th_a), "xy")
    ce = contour_error(pd, pa, "xy")[40:]
    # the chord lies inside the circle by at most the sagitta
    assert np.all(ce <= -d + 1e-15)
    assert np.all(ce >= -d - _sagitta(4000) - 1e-15)


# --------------------------------------------------------------- plane orientation


def test_zx_plane_sign_by_hand():
    # G18: e1 = Z, e2 = X, normal = Y. Travel along +X (= +e2, "up" when drawn
    # with Z to the right and X up); left of an upward arrow is -e1 = -Z.
    x = np.linspace(0.0, 0.02, 2001)
    pd = np.column_stack([x, np.zeros_like(x), np.full_like(x, 0.01)])
    below = _lagged(pd, 15) + np.array([0.0, 0.0, -3 * UM])
    above = _lagged(pd, 15) + np.array([0.0, 0.0, +3 * UM])
    np.testing.assert_allclose(contour_error(pd, below, "zx"), 3 * UM, atol=1e-15)
    np.testing.assert_allclose(contour_error(pd, above, "zx"), -3 * UM, atol=1e-15)
    # the same motion read in XY (travel +X, left +Y) is unaffected by Z: sign from
    # the in-plane components only, so a pure Z offset has no side there
    np.testing.assert_allclose(np.abs(contour_error(pd, below, "xy")), 3 * UM, atol=1e-15)


@pytest.mark.parametrize("sweep, expected_sign", [(-np.pi, +1), (+np.pi, -1)])
def test_zx_arc_outside(sweep, expected_sign):
    # G2 in G18 (sweep < 0) is clockwise seen from +Y in the (Z, X) frame: outside is left
    arc = Arc(
        start=(0.03, 0.0, 0.0), end=(0.01, 0.0, 0.0), center=(0.02, 0.0, 0.0),
        plane="zx", sweep_rad=sweep, feed_m_s=0.05,
    )
    u = np.linspace(0.0, 1.0, 5001)
    pd = arc.point(u)
    d = 6 * UM
    pa = arc.point(np.maximum(u - 30 * (u[1] - u[0]), 0.0))
    radial = pa - arc.center
    pa = pa + d * radial / np.linalg.norm(radial, axis=1)[:, None]
    ce = contour_error(pd, pa, "zx")
    sag = arc.radius * (1 - np.cos(np.pi / 5000))
    np.testing.assert_allclose(ce, expected_sign * d, atol=sag + 1e-15)


# ------------------------------------------------------------------ corners


def _dense(vertices, step):
    """A polyline through ``vertices`` (in XY) resampled every ``step`` metres."""
    pts = [np.asarray(vertices[0], float)]
    for a, b in zip(vertices[:-1], vertices[1:]):
        a, b = np.asarray(a, float), np.asarray(b, float)
        m = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        pts.extend(a + (b - a) * (np.arange(1, m + 1) / m)[:, None])
    xy = np.array(pts)
    return np.column_stack([xy, np.zeros(len(xy))])


def _one_point(pd, point, plane="xy", window=None):
    """CE of a single actual point placed at every sample (so every window sees it)."""
    pa = np.tile(np.asarray(point, float), (len(pd), 1))
    w = len(pd) if window is None else window
    return contour_error(pd, pa, plane, window=w)


def test_corner_outside_uses_vertex_distance_and_right_side():
    # left (CCW) turn at (1, 0) mm: outside of the turn is the right side
    pd = _dense([(0, 0), (1e-3, 0), (1e-3, 1e-3)], 1e-5)
    p = (1e-3 + 3 * UM, -4 * UM, 0.0)
    np.testing.assert_allclose(_one_point(pd, p), -5 * UM, rtol=1e-9)


def test_corner_inside_uses_nearest_leg():
    pd = _dense([(0, 0), (1e-3, 0), (1e-3, 1e-3)], 1e-5)
    p = (1e-3 - 6 * UM, 2 * UM, 0.0)
    np.testing.assert_allclose(_one_point(pd, p), 2 * UM, rtol=1e-9)


def test_hairpin_tip_is_outside_of_the_turn():
    # +X then a sharp left turn back at 170 degrees: beyond the tip lies outside (right);
    # the incoming leg alone would wrongly say "left" (the point is slightly above it)
    a = np.deg2rad(170.0)
    tip = np.array([1e-3, 0.0])
    pd = _dense([(0, 0), tip, tip + 1e-3 * np.array([np.cos(a), np.sin(a)])], 1e-5)
    p = (1e-3 + 5 * UM, 0.3 * UM, 0.0)
    ce = _one_point(pd, p)
    np.testing.assert_allclose(ce, -np.hypot(5 * UM, 0.3 * UM), rtol=1e-9)


# --------------------------------------------------------------- standing still


def test_standing_still_at_start_and_end():
    x = np.linspace(0.0, 0.005, 400)
    pd = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    pd = np.vstack([np.repeat(pd[:1], 300, axis=0), pd, np.repeat(pd[-1:], 300, axis=0)])
    # on the path while standing, moving and standing again: zero everywhere
    np.testing.assert_array_equal(contour_error(pd, pd, "xy", window=50), 0.0)
    # offset to the left (+Y) or right: the dwell samples take the side of the moving
    # segments next to them, though the dwells are longer than the window
    d = 2 * UM
    for side in (+1, -1):
        ce = contour_error(pd, pd + np.array([0.0, side * d, 0.0]), "xy", window=50)
        np.testing.assert_allclose(ce, side * d, atol=1e-15)


def test_lag_persisting_while_the_setpoints_wait():
    # the setpoints stop (300 samples of standstill, more than the window) while the
    # actual point is still 30 moving samples behind, 2 um to the left
    x = np.linspace(0.0, 0.005, 400)
    pd = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    pd = np.vstack([pd, np.repeat(pd[-1:], 300, axis=0)])
    pa = pd + np.array([0.0, 2 * UM, 0.0])
    pa[400:] = pd[369] + np.array([0.0, 2 * UM, 0.0])
    np.testing.assert_allclose(contour_error(pd, pa, "xy", window=50), 2 * UM, atol=1e-15)


def test_path_standing_still_throughout_gives_the_distance():
    pd = np.zeros((20, 3))
    pa = np.tile([3e-6, -4e-6, 0.0], (20, 1))
    np.testing.assert_allclose(contour_error(pd, pa, "xy", window=5), 5e-6, rtol=1e-12)


def test_window_ignores_the_return_pass():
    # out along y = 0, back along y = 10 um: a point 8 um left of the outward pass
    # is 2 um from the return pass, which lies far outside the window
    x = np.linspace(0.0, 0.01, 1000)
    out = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    back = np.column_stack([x[::-1], np.full_like(x, 10 * UM), np.zeros_like(x)])
    pd = np.vstack([out, back])
    pa = pd.copy()
    pa[:1000, 1] += 8 * UM
    ce = contour_error(pd, pa, "xy", window=100)
    np.testing.assert_allclose(ce[:900], 8 * UM, atol=1e-15)
    ce_all = contour_error(pd, pa, "xy", window=len(pd))
    np.testing.assert_allclose(np.abs(ce_all[300:700]), 2 * UM, atol=1e-15)


# ------------------------------------------------------------------ non-planar


def test_helix_unsigned():
    r, pitch = 0.02, 0.004
    th = np.linspace(0.0, 6 * np.pi, 30001)
    pd = np.column_stack([r * np.cos(th), r * np.sin(th), pitch * th / (2 * np.pi)])
    for radial in (+1.0, -1.0):
        d = 3 * UM
        tha = th[np.maximum(np.arange(len(th)) - 20, 0)]
        ra = r + radial * d
        pa = np.column_stack([ra * np.cos(tha), ra * np.sin(tha), pitch * tha / (2 * np.pi)])
        ce = contour_error(pd, pa, None)
        assert np.all(ce >= 0.0)
        np.testing.assert_allclose(ce, d, atol=1e-10)  # chord sagitta ~ 1e-11 m


# -------------------------------------------------------------- brute force


def _reference(pd, pa, plane):
    """All segments, no window, numpy; vertex side from the sum of adjacent directions."""
    keep = np.r_[True, np.any(np.diff(pd, axis=0) != 0, axis=1)]
    v = pd[keep]
    seg = np.diff(v, axis=0)
    l2 = np.sum(seg * seg, axis=1)
    u = seg / np.sqrt(l2)[:, None]
    out = np.empty(len(pa))
    for k, p in enumerate(pa):
        w = p - v[:-1]
        t = np.clip(np.sum(w * seg, axis=1) / l2, 0.0, 1.0)
        r = w - t[:, None] * seg
        d2 = np.sum(r * r, axis=1)
        i = int(np.argmin(d2))
        dist = np.sqrt(d2[i])
        if plane is None:
            out[k] = dist
            continue
        if 0.0 < t[i] < 1.0:
            tan = seg[i]
            q = v[i] + t[i] * seg[i]
        else:
            j = i + (t[i] == 1.0)
            tan = (u[j - 1] if j > 0 else 0) + (u[j] if j < len(u) else 0)
            q = v[j]
        e1, e2, _ = PLANES[plane]
        side = tan[e1] * (p - q)[e2] - tan[e2] * (p - q)[e1]
        out[k] = -dist if side < 0 else dist
    return out


@pytest.mark.parametrize("plane", ["xy", "zx", "yz", None])
def test_kernel_matches_brute_force_on_random_paths(plane):
    rng = np.random.default_rng(7)
    n = 1500
    # a wandering but forward-moving path (never comes back near itself), with dwells
    # and sharp direction changes; the actual point lags and strays by up to ~30 um
    heading = np.cumsum(rng.normal(0.0, 0.25, n))
    step = rng.uniform(0.0, 20e-6, n)
    step[rng.random(n) < 0.05] = 0.0
    e = np.cumsum(np.column_stack([step * np.cos(heading), step * np.sin(heading)]), axis=0)
    e[:, 0] += np.arange(n) * 15e-6  # forward drift
    if plane is None:
        pd = np.column_stack([e, np.cumsum(rng.uniform(0, 5e-6, n))])
    else:
        pd = _xyz(e[:, 0], e[:, 1], plane, 0.05)
    pa = _lagged(pd, 12) + rng.normal(0.0, 10e-6, (n, 3))
    ce = contour_error(pd, pa, plane, window=60)
    ref = _reference(pd, pa, plane)
    np.testing.assert_allclose(ce, ref, rtol=1e-9, atol=1e-16)
    if plane is not None:
        assert (ce > 0).any() and (ce < 0).any()


# ------------------------------------------------------- compiled building blocks


def test_nearest_segment_and_ce_point_from_compiled_code():
    from numba import njit

    @njit
    def both(pd, lo, hi, x, y):
        i, t, d2 = nearest_segment(pd, lo, hi, x, y, 0.0)
        return i, t, d2, ce_point(pd, lo, hi, x, y, 0.0, 0, 1, True)

    # (0,0) -> (1,0) -> (1,0) (standing) -> (1,1) mm
    pd = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1, 0]], float) * 1e-3
    i, t, d2, ce = both(pd, 0, 3, 0.25e-3, -0.1e-3)
    assert (i, t) == (0, pytest.approx(0.25)) and d2 == pytest.approx(1e-8)
    assert ce == pytest.approx(-0.1e-3)  # right of +X travel
    i, t, d2, ce = both(pd, 0, 3, 0.9e-3, 0.6e-3)
    assert (i, t) == (2, pytest.approx(0.6)) and ce == pytest.approx(0.1e-3)  # left of +Y
    i, t, d2, ce = both(pd, 1, 2, 1.0e-3, 0.5e-3)  # only the zero-length segment in the window
    assert i == -1 and d2 == np.inf and ce == pytest.approx(0.5e-3)


# ------------------------------------------------- hinted search against the plain one


def _wandering_path(rng, n):
    """A path with runs of standstill, steps from 0.1 to 100 um, turns, hairpins and small
    loops (it comes back near itself within a window, so the search's shortcuts often
    fail)."""
    turn = rng.normal(0.0, 0.3, n) + np.pi * (rng.random(n) < 0.03)
    step = 10.0 ** rng.uniform(-7, -4, n) * (rng.random(n) > 0.1)
    for start in rng.integers(0, n, 1 + n // 30):  # nearly closed loops of 3 to 10 segments
        m = int(rng.integers(3, 11))
        turn[start:start + m] = 2.0 * np.pi / m + rng.normal(0.0, 0.02)
        step[start:start + m] = step[start]
    heading = np.cumsum(turn)
    step[rng.integers(0, n):][: rng.integers(0, 80)] = 0.0  # a long dwell somewhere
    d = np.column_stack([step * np.cos(heading), step * np.sin(heading),
                         step * rng.normal(0.0, 0.3, n)])
    return np.cumsum(d, axis=0)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 700), st.integers(1, 120))
def test_hinted_search_is_the_plain_search(seed, n, window):
    # ce_at / ce2_at (index with block and leaf spheres and clearances, hinted) against
    # the plain scan of nearest_segment / ce_point over the window, whatever the hint:
    # the same segment, the same bits
    rng = np.random.default_rng(seed)
    pd = _wandering_path(rng, n)
    tree, lo, hi = path_index(pd, window)
    count = moving_count(pd)
    for k in range(n):
        assert (lo[k], hi[k]) == window_bounds(count, k, window)
    e1, e2, signed = 0, 1, bool(rng.random() < 0.7)
    for _ in range(30):
        # a point near a segment, from a sample whose window holds it, and hints all around
        seg = int(rng.integers(0, n - 1))
        k = int(np.clip(seg + rng.integers(-window, window + 1), 0, n - 1))
        x, y, z = pd[seg] + rng.random() * (pd[seg + 1] - pd[seg]) + rng.normal(
            0.0, 10.0 ** rng.uniform(-9, -3), 3)
        i, _t, d2 = nearest_segment(pd, lo[k], hi[k], x, y, z)
        ref = ce_point(pd, lo[k], hi[k], x, y, z, e1, e2, signed)
        for hint in [-1, int(rng.integers(0, n)), n + 3, *range(seg - 10, seg + 11)]:
            ce, j = ce_at(pd, tree, lo[k], hi[k], k, x, y, z, (e1, e2, signed), hint)
            ce2, j2 = ce2_at(pd, tree, lo[k], hi[k], k, x, y, z, hint)
            assert j == j2 == i
            assert ce == ref
            assert ce2 == pytest.approx(ce * ce, rel=5e-16, abs=0.0)
            if i >= 0:
                assert ce2 == d2
    pa = pd[np.maximum(np.arange(n) - int(rng.integers(0, 30)), 0)] + rng.normal(
        0.0, 10.0 ** rng.uniform(-8, -4), (n, 3))
    plain = [ce_point(pd, *window_bounds(count, k, window), *pa[k], e1, e2, signed)
             for k in range(n)]
    np.testing.assert_array_equal(ce_series(pd, pa, window, e1, e2, signed), plain)


@pytest.mark.parametrize("sides", range(3, 11))
def test_hinted_search_where_a_loop_closes_on_the_path(sides):
    # a straight run, a closed polygon loop whose last side nearly overlaps the side
    # before the loop (the two lie `sides` segments apart), then straight on: the
    # nearest of the two depends on the side of the point, whatever the hint
    step = 10 * UM
    for lead in range(4):  # the loop at every phase of the index's leaves
        turn = np.zeros(lead + 8 + sides + 10)
        s0 = lead + 8
        turn[s0:s0 + sides] = 2.0 * np.pi / sides
        turn[s0 + sides - 1] += 0.01
        heading = np.cumsum(turn)
        d = step * np.column_stack([np.cos(heading), np.sin(heading), np.zeros_like(heading)])
        pd = np.vstack([np.zeros(3), np.cumsum(d, axis=0)])
        tree, lo, hi = path_index(pd, 50)
        for seg in (s0 - 1, s0 + sides - 1):
            for f in np.linspace(0.05, 0.95, 7):
                for off in (-0.02, 0.005, 0.02):
                    x, y, z = pd[seg] + f * (pd[seg + 1] - pd[seg]) + [0.0, off * step, 0.0]
                    i, _t, d2 = nearest_segment(pd, lo[seg], hi[seg], x, y, z)
                    ref = ce_point(pd, lo[seg], hi[seg], x, y, z, 0, 1, True)
                    for hint in range(seg - 10, seg + 11):
                        ce, j = ce_at(pd, tree, lo[seg], hi[seg], seg, x, y, z, (0, 1, True),
                                      hint)
                        assert (j, ce) == (i, ref)
                        assert ce2_at(pd, tree, lo[seg], hi[seg], seg, x, y, z, hint) == (d2, i)


# ----------------------------------------------------------------- inputs


def test_bad_inputs_are_named():
    pd = np.zeros((10, 3))
    with pytest.raises(OptionError, match="plane"):
        contour_error(pd, pd, "xz")
    with pytest.raises(OptionError, match="window"):
        contour_error(pd, pd, "xy", window=0)
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        contour_error(pd, pd[:, :2], "xy")
    bad = pd.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="finite"):
        contour_error(pd, bad, "xy")


def test_contour_error_of_uses_the_setpoints_plane():
    from feedplan.setpoints import Setpoints

    x = np.linspace(0.0, 0.01, 200)
    pos = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    z = np.zeros_like(pos)
    sp = Setpoints(dt=1e-3, s=x, pos=pos, vel=z, acc=z, jerk=z, block=np.ones(200, int),
                   rapid=np.zeros(200, bool), plane="zx")
    pa = pos + np.array([0.0, 0.0, -1 * UM])
    np.testing.assert_allclose(contour_error_of(sp, pa), 1 * UM, atol=1e-15)


# ------------------------------------------------------------------ metrics


def test_metrics_by_hand_and_rapids_masked():
    ce = np.array([3.0, -4.0, 100.0]) * UM
    pd = np.zeros((3, 3))
    pa = np.array([[1.0, -2.0, 0.0], [-3.0, 0.0, 0.0], [50.0, 50.0, 50.0]]) * UM
    m = contour_metrics(ce, pd, pa, mask=np.array([True, True, False]))  # 3rd: a rapid
    d = m.to_dict()
    assert d["n"] == 2
    assert d["mse_ce_um2"] == pytest.approx(12.5)
    assert d["rms_ce_um"] == pytest.approx(np.sqrt(12.5))
    assert d["max_ce_um"] == pytest.approx(4.0)
    assert d["p50_ce_um"] == pytest.approx(3.5)
    # the largest following error counts every sample, the rapid included (a controller's
    # following-error limit applies there too); its RMS counts the masked samples only
    assert d["track_max_um"] == pytest.approx({"x": 50.0, "y": 50.0, "z": 50.0})
    assert d["track_rms_um"]["x"] == pytest.approx(np.sqrt(5.0))
    assert m.mse_m2 == pytest.approx(12.5e-12)


def test_metrics_percentiles_by_hand():
    ce = -np.arange(1.0, 102.0) * UM  # |CE| = 1..101 um
    z = np.zeros((101, 3))
    d = contour_metrics(ce, z, z).to_dict()
    assert (d["p50_ce_um"], d["p95_ce_um"], d["p99_ce_um"]) == pytest.approx((51, 96, 100))


def test_metrics_refuse_empty_and_bad_shapes():
    z = np.zeros((3, 3))
    with pytest.raises(InputError, match="no sample"):
        contour_metrics(np.zeros(3), z, z, mask=np.zeros(3, bool))
    with pytest.raises(InputError, match="shapes"):
        contour_metrics(np.zeros(4), z, z)
