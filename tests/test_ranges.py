"""Kinematic range, best fixed gains and ``oga ranges``, against independent evaluations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from feedplan.path import Arc, Line
from feedplan.setpoints import AXES, Setpoints
from oga.model.contour import contour_error_of
from oga.errors import InputError, OptionError
from oga.model.machine import load_machine, machine_from_dict
from oga.search.ranges import best_fixed_gains, gain_ranges, kinematic_range
from oga.model.stability import decimal_grid, stable_range
from oga.model.response import simulate

UCP = load_machine("ucp710")


def _synthetic(v=0.05, dt=1e-3, rapid_lead_m=0.0):
    """An XZ (G18) contour: line +X, quarter arc, line +Z; smooth speed profile at 1 ms.

    Tangent-continuous, with curvature jumps at the arc ends (so high Kf breaks
    X's 10 m/s^3 jerk limit). ``rapid_lead_m`` prepends a rapid approach along X.
    """
    segs = []
    if rapid_lead_m:
        segs.append(Line((-rapid_lead_m, 0, 0), (0, 0, 0), np.inf, rapid=True))
    segs += [
        Line((0, 0, 0), (0.02, 0, 0), v),
        Arc(start=(0.02, 0, 0), end=(0.03, 0, 0.01), center=(0.02, 0, 0.01), plane="zx",
            sweep_rad=-np.pi / 2, feed_m_s=v),
        Line((0.03, 0, 0.01), (0.03, 0, 0.03), v),
    ]
    lens = np.array([s.length for s in segs])
    cum = np.r_[0.0, np.cumsum(lens)]
    ramp_s = 0.15
    total_s = cum[-1] / v + ramp_s

    def speed(t):
        a = np.clip(t / ramp_s, 0, 1)
        b = np.clip((total_s - t) / ramp_s, 0, 1)
        smooth = lambda x: x**3 * (10 - 15 * x + 6 * x * x)  # noqa: E731
        return v * np.minimum(smooth(a), smooth(b))

    fine = np.arange(0.0, total_s + 0.1, dt / 20)
    s_fine = np.r_[0.0, np.cumsum((speed(fine[1:]) + speed(fine[:-1])) / 2 * dt / 20)]
    t = np.arange(0.0, total_s + 0.1, dt)
    s = np.minimum(np.interp(t, fine, s_fine), cum[-1])
    seg = np.minimum(np.searchsorted(cum, s, side="right") - 1, len(segs) - 1)
    pos = np.array([segs[i].point((sk - cum[i]) / lens[i]) for sk, i in zip(s, seg)])
    zero = np.zeros_like(pos)
    return Setpoints(
        dt=dt, s=s, pos=pos, vel=np.gradient(pos, dt, axis=0), acc=zero, jerk=zero,
        block=seg + 1, rapid=np.array([segs[i].rapid for i in seg]), plane="zx",
    )


def _eq2_peaks(u, mask, te):
    """Independent numpy evaluation of paper eq. 2 (axis at rest before sample 0)."""
    du = np.diff(u, prepend=0.0) / te
    d2u = np.diff(u, n=2, prepend=[0.0, 0.0]) / te**2
    return np.abs(u[mask]).max(), np.abs(du[mask]).max(), np.abs(d2u[mask]).max()


SP = _synthetic(rapid_lead_m=0.004)


def test_grids_are_exact_decimals():
    kp = decimal_grid(1.0, 3.0, 0.1)
    assert len(kp) == 21
    assert [float(v) for v in kp] == [float(f"{1.0 + i / 10:.1f}") for i in range(21)]
    kf = decimal_grid(0.0, 1.0, 0.1)
    assert len(kf) == 11 and kf[3] == 0.3 and kf[-1] == 1.0
    with pytest.raises(OptionError):
        decimal_grid(1.0, 0.5, 0.1)


@pytest.mark.parametrize("axis", ["x", "z"])
def test_feasibility_matches_independent_eq2(axis):
    kp_grid = [1.0, 2.0, 3.0]
    kf_grid = [0.0, 0.5, 0.9, 1.0]
    kr = kinematic_range(SP, UCP, axis, kp_grid, kf_grid)
    lim = UCP.axis(axis).limits
    col = AXES.index(axis)
    feed = ~SP.rapid
    every = np.ones_like(feed)
    assert SP.rapid.any() and feed.any()
    rapid_counts = False
    for i, kp in enumerate(kp_grid):
        for j, kf in enumerate(kf_grid):
            u = simulate(SP, UCP, kp, kf).u[:, col]
            v, a, jk = _eq2_peaks(u, every, UCP.te)
            np.testing.assert_allclose(
                [kr.vel_peak_m_s[i, j], kr.acc_peak_m_s2[i, j], kr.jerk_peak_m_s3[i, j]],
                [v, a, jk], rtol=1e-9,
            )
            expected = v <= lim.vmax_m_s and a <= lim.amax_m_s2 and jk <= lim.jmax_m_s3
            assert kr.feasible[i, j] == expected
            rapid_counts |= _eq2_peaks(u, feed, UCP.te)[2] < jk
    # the test discriminates: both outcomes occur, and (on X, which the rapid moves) the
    # largest jerk lies in the rapid in some configuration: the rapid samples count
    assert kr.feasible.any() and not kr.feasible.all()
    assert rapid_counts == (axis == "x")
    assert kr.count == len(kr.pairs()) == int(kr.feasible.sum())
    assert all(kr.feasible[kp_grid.index(p), kf_grid.index(f)] for p, f in kr.pairs())


def test_default_ce_window_covers_the_largest_lag():
    # slowest loop of the stable range (Kp 1.0, Kf 0): the default window finds the
    # same nearest points as a search over the whole path (which never comes back)
    sim = simulate(SP, UCP, 1.0, 0.0)
    lag_samples = np.abs(SP.pos[:, 0] - sim.pos[:, 0]).max() / np.abs(SP.vel[:, 0]).max() / SP.dt
    assert lag_samples > 50  # a real test of the window
    np.testing.assert_array_equal(
        contour_error_of(SP, sim.pos), contour_error_of(SP, sim.pos, window=len(SP))
    )


def test_tracking_mse_is_steady_lag_on_a_constant_velocity_line():
    # one axis at constant speed: steady lag (1 - Kf) v / Kp dominates the tracking MSE
    n, v, dt = 3000, 0.02, 1e-3
    x = v * dt * np.arange(n)
    pos = np.column_stack([x, np.zeros(n), np.zeros(n)])
    vel = np.column_stack([np.full(n, v), np.zeros(n), np.zeros(n)])
    z = np.zeros_like(pos)
    rapid = np.zeros(n, bool)
    sp = Setpoints(dt=dt, s=x, pos=pos, vel=vel, acc=z, jerk=z, block=np.ones(n, int),
                   rapid=rapid, plane="xy")
    kr = kinematic_range(sp, UCP, "x", [2.0], [0.5])
    lag = (1 - 0.5) * v / (2.0 * 1000 / 60)
    # the start transient (~0.3 s) is a small part of the 3 s run
    assert kr.mse_track_m2[0, 0] == pytest.approx(lag**2, rel=0.1)


def test_bad_inputs_are_refused():
    with pytest.raises(OptionError, match="kp_grid"):
        kinematic_range(SP, UCP, "x", [], [0.5])
    with pytest.raises(OptionError, match="kp_grid"):
        kinematic_range(SP, UCP, "x", [-1.0], [0.5])
    sp2 = Setpoints(dt=2e-3, s=SP.s, pos=SP.pos, vel=SP.vel, acc=SP.acc, jerk=SP.jerk,
                    block=SP.block, rapid=SP.rapid, plane=SP.plane)
    with pytest.raises(OptionError, match="Te"):
        kinematic_range(sp2, UCP, "x", [1.0], [0.5])
    only_rapid = Setpoints(dt=SP.dt, s=SP.s, pos=SP.pos, vel=SP.vel, acc=SP.acc, jerk=SP.jerk,
                           block=SP.block, rapid=np.ones(len(SP), bool), plane=SP.plane)
    with pytest.raises(InputError, match="no feed"):
        kinematic_range(only_rapid, UCP, "x", [1.0], [0.5])


def _small_grid_machine():
    data = UCP.model_dump(mode="json")
    data["gains"].update(
        kp_span_m_min_per_mm=[1.8, 2.5], kp_bounds_m_min_per_mm=[2.0, 2.3],
        kf_range=[0.0, 1.0], kf_step=0.25,
    )
    return machine_from_dict(data)


def test_best_fixed_is_the_brute_force_minimum_over_feasible_equal_gains():
    m = _small_grid_machine()
    r = gain_ranges(SP, m)
    assert r.axes == ("x", "z")
    kp_grid, kf_grid = [2.0, 2.1, 2.2, 2.3], [0.0, 0.25, 0.5, 0.75, 1.0]
    assert r.kp_grid.tolist() == kp_grid and r.kf_grid.tolist() == kf_grid
    feed = ~SP.rapid
    mse = np.empty((4, 5))
    feasible = np.empty((4, 5), bool)
    for i, kp in enumerate(kp_grid):
        for j, kf in enumerate(kf_grid):
            sim = simulate(SP, m, kp, kf)
            ce = contour_error_of(SP, sim.pos)[feed]
            mse[i, j] = np.mean(ce**2)
            ok = True
            for a in ("x", "z"):
                lim = m.axis(a).limits
                v, acc, jk = _eq2_peaks(sim.u[:, AXES.index(a)], np.ones_like(feed), m.te)
                ok &= v <= lim.vmax_m_s and acc <= lim.amax_m_s2 and jk <= lim.jmax_m_s3
            feasible[i, j] = ok
    np.testing.assert_allclose(r.mse_ce_m2, mse, rtol=1e-12)
    np.testing.assert_array_equal(r.feasible, feasible)
    # discriminating grid: the unconstrained minimum is infeasible, some configurations are feasible
    assert feasible.any() and not feasible[np.unravel_index(np.argmin(mse), mse.shape)]
    i, j = np.unravel_index(np.argmin(np.where(feasible, mse, np.inf)), mse.shape)
    best = r.best_fixed
    assert best.kp == {"x": kp_grid[i], "z": kp_grid[i]}
    assert best.kf == {"x": kf_grid[j], "z": kf_grid[j]}
    assert best.mse_ce_m2 == pytest.approx(mse[i, j], rel=1e-12)
    assert best.metrics.mse_m2 == pytest.approx(mse[i, j], rel=1e-12)
    d = r.to_dict()
    assert d["best_fixed"]["found"]
    assert d["best_fixed"]["mse_ce_um2"] == pytest.approx(mse[i, j] * 1e12)
    assert d["axes"]["x"]["kinematic"]["count"] == r.kinematic["x"].count
    assert set(d["axes"]) == {"x", "z"}


def test_no_feasible_equal_gains_gives_no_best_fixed():
    # X jerk limit far below anything the loop can meet on this contour
    data = _small_grid_machine().model_dump(mode="json")
    data["axes"]["x"]["limits"]["jmax_m_s3"] = 0.1
    r = gain_ranges(SP, machine_from_dict(data))
    assert r.kinematic["x"].count == 0 and not r.feasible.any()
    assert r.best_fixed is None
    assert r.to_dict()["best_fixed"]["found"] is False


# ------------------------------------------------------- best_fixed_gains (fast path)

DATA = Path(__file__).parent / "data"
MCV = load_machine("mcv-op")


def _planned(name, machine):
    from feedplan.plan import plan
    from feedplan.read import load_toolpath
    from oga.defaults import TOL_M

    return plan(load_toolpath(DATA / name), machine.axis_limits(), tol_m=TOL_M, dt=machine.te)


@pytest.mark.parametrize("machine, name", [
    (UCP, "reference_xz.ngc"), (UCP, "circle_r50_f3000.ngc"), (UCP, "helix_r20.ngc"),
    (UCP, "freeform_xz.ngc"), (MCV, "circle_r50_f3000.ngc"),
])
def test_best_fixed_gains_equals_the_full_tables(machine, name):
    sp = _planned(name, machine)
    full = gain_ranges(sp, machine)
    fast = best_fixed_gains(sp, machine)
    ref = full.best_fixed
    assert ref is not None and fast is not None
    assert fast.kp == ref.kp and fast.kf == ref.kf
    assert fast.mse_ce_m2 == ref.mse_ce_m2  # the same bits
    assert fast.metrics == ref.metrics
    # the grid discriminates: feasible and infeasible configurations, a spread of MSEs
    assert full.feasible.any() and not full.feasible.all()
    assert np.ptp(full.mse_ce_m2[full.feasible]) > 0.5 * ref.mse_ce_m2


def test_best_fixed_gains_equals_the_tables_when_the_free_minimum_is_infeasible():
    m = _small_grid_machine()
    r = gain_ranges(SP, m)
    assert not r.feasible[np.unravel_index(np.argmin(r.mse_ce_m2), r.mse_ce_m2.shape)]
    fast = best_fixed_gains(SP, m)
    assert (fast.kp, fast.kf, fast.mse_ce_m2) == (r.best_fixed.kp, r.best_fixed.kf,
                                                  r.best_fixed.mse_ce_m2)


@pytest.mark.parametrize("machine, name", [(UCP, "short_xz.ngc"), (MCV, "circle_r50_f3000.ngc")])
def test_best_fixed_gains_is_the_brute_force_minimum(machine, name):
    # every equal-gain pair of the grid (stable Kp on every moving axis x Kf range)
    # simulated, contour error and eq. 2 evaluated independently of oga.search.ranges
    sp = _planned(name, machine)
    axes = [AXES[c] for c in sp.moving_axes]
    kp_grid = None
    for a in axes:
        st = stable_range(machine, a)
        g = {float(k) for k in st.kp if st.kp_min <= k <= st.kp_max}
        kp_grid = g if kp_grid is None else kp_grid & g
    lo, hi = machine.gains.kf_range
    kf_grid = decimal_grid(lo, hi, machine.gains.kf_step)
    feed = ~sp.rapid
    best = best_fixed_gains(sp, machine)
    kp0, kf0 = best.kp[axes[0]], best.kf[axes[0]]
    assert all(best.kp[a] == kp0 and best.kf[a] == kf0 for a in axes)
    seen_best, n_feasible, n_infeasible = False, 0, 0
    for kp in sorted(kp_grid):
        for kf in kf_grid:
            sim = simulate(sp, machine, kp, float(kf))
            ok = True
            for a in axes:
                lim = machine.axis(a).limits
                v, acc, jk = _eq2_peaks(sim.u[:, AXES.index(a)], np.ones_like(feed), machine.te)
                ok &= v <= lim.vmax_m_s and acc <= lim.amax_m_s2 and jk <= lim.jmax_m_s3
            if not ok:
                n_infeasible += 1
                continue
            n_feasible += 1
            mse = np.mean(contour_error_of(sp, sim.pos)[feed] ** 2)
            if (kp, float(kf)) == (kp0, kf0):
                seen_best = True
                assert mse == pytest.approx(best.mse_ce_m2, rel=1e-12)
            else:
                assert mse >= best.mse_ce_m2 * (1 - 1e-12)
    assert seen_best and n_feasible > 1 and n_infeasible > 0


def _with_ferror(machine, limit_m):
    data = machine.model_dump(mode="json")
    for axis in data["axes"].values():
        axis["limits"]["ferror_max_m"] = limit_m
    return machine_from_dict(data)


def test_best_fixed_gains_keep_the_following_error_limit():
    sp = _planned("short_xz.ngc", UCP)
    axes = [AXES[c] for c in sp.moving_axes]
    cols = [AXES.index(a) for a in axes]

    def lag(machine, kp, kf):  # largest |pd - p| per moving axis over every sample
        sim = simulate(sp, machine, kp, kf)
        return np.abs(sp.pos - sim.pos)[:, cols].max(axis=0)

    free = best_fixed_gains(sp, UCP)
    a0 = axes[0]
    limit = 0.75 * lag(UCP, free.kp[a0], free.kf[a0]).max()  # the free best breaks it
    m = _with_ferror(UCP, limit)
    full = gain_ranges(sp, m)
    fast = best_fixed_gains(sp, m)
    ref = full.best_fixed
    assert (fast.kp, fast.kf, fast.mse_ce_m2) == (ref.kp, ref.kf, ref.mse_ce_m2)
    assert (fast.kp[a0], fast.kf[a0]) != (free.kp[a0], free.kf[a0])
    assert fast.mse_ce_m2 > free.mse_ce_m2
    assert lag(m, fast.kp[a0], fast.kf[a0]).max() <= limit
    # the limit removes exactly the cells whose following error exceeds it, and some
    free_full = gain_ranges(sp, UCP)
    for a, c in zip(axes, cols):
        k, k0 = full.kinematic[a], free_full.kinematic[a]
        np.testing.assert_array_equal(k.feasible, k0.feasible & (k.track_max_m <= limit))
        assert (k0.feasible & ~k.feasible).any() and k.feasible.any()
        for i, j in [(0, 0), (-1, -1), (len(k.kp_grid) // 2, 5)]:  # brute force
            sim = simulate(sp, m, float(k.kp_grid[i]), float(k.kf_grid[j]))
            assert k.track_max_m[i, j] == pytest.approx(
                np.abs(sp.pos - sim.pos)[:, c].max(), rel=1e-12)


def test_best_fixed_gains_none_when_nothing_is_feasible():
    data = _small_grid_machine().model_dump(mode="json")
    data["axes"]["x"]["limits"]["jmax_m_s3"] = 0.1
    assert best_fixed_gains(SP, machine_from_dict(data)) is None


# ------------------------------------------------------------------------ CLI


def _machine_file(tmp_path):
    path = tmp_path / "small.json"
    path.write_text(json.dumps(_small_grid_machine().model_dump(mode="json")))
    return str(path)


def test_cli_bad_machine_exits_2_with_one_line(capsys):
    from oga.cli import main

    assert main(["ranges", "--machine", "no_such_machine"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no_such_machine" in err


def test_cli_stability_only(tmp_path, capsys):
    from oga.cli import main

    out = tmp_path / "r.json"
    assert main(["ranges", "--machine", _machine_file(tmp_path), "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["machine"] == "ucp710" and set(data["axes"]) == {"x", "y", "z"}
    for a in "xyz":
        st = data["axes"][a]["stability"]
        assert (st["kp_min"], st["kp_max"]) == (2.0, 2.3)  # bounds inside the stable span
        assert [row["kp"] for row in st["table"]] == [1.8, 1.9, 2.0, 2.1, 2.2, 2.3, 2.4, 2.5]
        assert all(row["pm_deg"] >= 70 and row["gm_db"] >= 10 for row in st["table"])
        assert "kinematic" not in data["axes"][a]
    assert "best_fixed" not in data
    assert "x PM deg" in capsys.readouterr().out


def test_cli_with_a_toolpath_writes_the_documented_json(tmp_path, capsys):
    from oga.cli import main

    prog = tmp_path / "part.ngc"
    prog.write_text(
        "G21 G90 G18 G94\nG1 X0 Z0 F3000\nG1 X10 Z0\nG2 X15 Z5 I0 K5\nG1 X15 Z12\nM2\n"
    )
    out = tmp_path / "r.json"
    rc = main(["ranges", "--machine", _machine_file(tmp_path), str(prog), "--feed", "1500",
               "--tolerance", "0.01", "--json", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert set(data["axes"]) == {"x", "z"}  # the contouring axes only
    grid = {(kp, kf) for kp in (2.0, 2.1, 2.2, 2.3) for kf in (0.0, 0.25, 0.5, 0.75, 1.0)}
    for a in ("x", "z"):
        kin = data["axes"][a]["kinematic"]
        assert kin["count"] == len(kin["feasible"]) and kin["grid_size"] == 20
        assert {tuple(p) for p in kin["feasible"]} <= grid
        assert data["axes"][a]["stability"]["kp_max"] == 2.3
    best = data["best_fixed"]
    if best["found"]:
        assert best["kp"]["x"] == best["kp"]["z"] and best["kf"]["x"] == best["kf"]["z"]
        assert [best["kp"]["x"], best["kf"]["x"]] in data["axes"]["x"]["kinematic"]["feasible"]
        assert [best["kp"]["z"], best["kf"]["z"]] in data["axes"]["z"]["kinematic"]["feasible"]
        assert best["mse_ce_um2"] > 0
    eq = data["equal_gains"]
    assert len(eq["mse_ce_um2"]) == 4 and len(eq["mse_ce_um2"][0]) == 5
    assert "best fixed gains" in capsys.readouterr().out
