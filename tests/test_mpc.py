"""The full-mode QP solver, checked by the KKT conditions (an independent optimality test)."""

from __future__ import annotations

import numpy as np
import pytest

from oga.search.window import _qp_active_set


def random_qp(seed, nv=12, m=60):
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(40, nv)) * np.concatenate([np.full(nv // 2, 1e-2), np.full(nv - nv // 2, 1.0)])
    p = s.T @ s + 1e-3 * np.eye(nv)
    q = rng.normal(size=nv) * 5
    a = rng.normal(size=(m, nv))
    return p, q, a, -np.abs(rng.normal(size=m)), np.abs(rng.normal(size=m))


def _dense(a):
    """Every row may use every column."""
    return np.zeros(a.shape[0], dtype=np.int64), np.full(a.shape[0], a.shape[1], dtype=np.int64)


def kkt_ok(p, q, a, lo, hi, x):
    ax = a @ x
    if not (np.all(ax >= lo - 1e-8) and np.all(ax <= hi + 1e-8)):
        return False
    at_lo, at_hi = np.isclose(ax, lo, atol=1e-8), np.isclose(ax, hi, atol=1e-8)
    act = at_lo | at_hi
    grad = -(p @ x + q)
    mu, *_ = np.linalg.lstsq(a[act].T, grad, rcond=None)
    stationary = np.allclose(a[act].T @ mu, grad, atol=1e-6 * (1 + np.abs(grad).max()))
    return stationary and bool(np.all(mu * np.where(at_hi[act], 1.0, -1.0) >= -1e-6))


def test_reported_optimum_meets_the_kkt_conditions():
    solved = 0
    for seed in range(100):
        p, q, a, lo, hi = random_qp(seed)
        x = np.empty(p.shape[0])
        if _qp_active_set(p, q, a, lo, hi, a.shape[0], *_dense(a), x):
            solved += 1
            assert kkt_ok(p, q, a, lo, hi, x), seed
    assert solved == 100  # hard random problems, many active rows


def test_few_active_rows_always_solved():
    for seed in range(50):
        p, q, a, lo, hi = random_qp(seed)
        lo, hi = lo - 3.0, hi + 3.0  # a few rows bind at most, as in the MPC's problems
        x = np.empty(p.shape[0])
        assert _qp_active_set(p, q, a, lo, hi, a.shape[0], *_dense(a), x)
        assert kkt_ok(p, q, a, lo, hi, x)


def test_rows_confined_to_column_ranges_solved_as_dense():
    # rows of one axis touch only that axis's variables (as the eq. 2 rows do): the solver
    # reads only those columns (whatever the array holds elsewhere), and must reach the
    # dense solver's KKT point of the matrix with zeros there
    rng = np.random.default_rng(7)
    for seed in range(30):
        p, q, a, lo, hi = random_qp(seed)
        c0 = np.where(np.arange(a.shape[0]) % 2 == 0, 0, 6).astype(np.int64)
        c1 = c0 + 6
        garbage = a.copy()
        for r in range(a.shape[0]):
            a[r, :c0[r]] = 0.0
            a[r, c1[r]:] = 0.0
            garbage[r, :c0[r]] = rng.normal(size=c0[r]) * 1e3
            garbage[r, c1[r]:] = rng.normal(size=a.shape[1] - c1[r]) * 1e3
        x = np.empty(p.shape[0])
        x_dense = np.empty(p.shape[0])
        ok = _qp_active_set(p, q, garbage, lo, hi, a.shape[0], c0, c1, x)
        assert ok == _qp_active_set(p, q, a, lo, hi, a.shape[0], *_dense(a), x_dense)
        if ok:
            assert kkt_ok(p, q, a, lo, hi, x)
            np.testing.assert_allclose(x, x_dense, rtol=1e-9, atol=1e-12)


def test_plan_is_the_quadratic_b_spline_of_its_control_points():
    # the planned gain against scipy's B-spline with the same control points: points
    # c_-1, c_0, c_1, ... sit at uniform knots kspace samples apart, and the last repeats
    from scipy.interpolate import BSpline

    from oga.search.window import _plan_at

    kspace, n_pts = 10, 9
    rng = np.random.default_rng(7)
    points = rng.uniform(1.0, 3.0, size=(3, 2, n_pts))
    ext = np.concatenate([points[1, 0], np.full(3, points[1, 0, -1])])  # rest beyond the last
    knots = kspace * (np.arange(len(ext) + 3) - 2.0)  # c_j's support starts at (j - 1) kspace
    spline = BSpline(knots, ext, 2)
    for tau in range(0, 100):
        assert _plan_at(points, 1, 0, tau, kspace) == pytest.approx(float(spline(tau)), rel=1e-12)
    # value and slope at tau = 0 depend on the two fixed points only (continuity with the past)
    assert _plan_at(points, 1, 0, 0, kspace) == pytest.approx(
        0.5 * (points[1, 0, 0] + points[1, 0, 1]))


def test_window_cost_counts_only_the_metrics_samples():
    # the search's exact window cost is the replay's squared contour error (um^2) summed
    # over the feed samples of the window: rapids and the padding past the end count 0
    from oga.model.contour import contour_error, path_index
    from oga.search.window import _window_cost

    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, 400)
    pd = np.stack([0.05 * np.cos(3 * t), 0.05 * np.sin(3 * t), 0.01 * t], axis=1)
    pa = pd + rng.normal(scale=5e-6, size=pd.shape)
    window = 150
    tree, lo, hi = path_index(pd, window)
    ce = contour_error(pd, pa, None, window=window)
    k, w = 300, 150  # the window runs 50 samples past the end
    feed = np.ones(k + w, dtype=bool)
    feed[320:340] = False  # a rapid
    feed[400:] = False  # padding
    trial = np.ascontiguousarray(
        np.vstack([pa[k:], np.repeat(pa[-1:], w - (400 - k), axis=0)]).T)
    got = _window_cost(pd, tree, lo, hi, k, w, trial, feed)
    keep = feed[k:400]
    assert got == pytest.approx(np.sum(ce[k:][keep] ** 2) * 1e12, rel=1e-12)
