"""Every sample is checked: rapids, dwells, the start and the end, not only the cuts.

A program with long rapids between two cuts (tests/data/rapids_xy.ngc): its rapids
run the axes at their speed and acceleration, where the position loop's velocity
command is hardest to keep within paper eq. 2. The references are independent of
oga's checks: a fresh simulation of the exported gains (:func:`oga.model.response.simulate`,
not :func:`oga.verify.verify`'s replay) and plain numpy differences of its velocity
command over every sample, the axes at rest before the start.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from feedplan.plan import plan
from feedplan.read import load_toolpath
from oga.errors import MachineError
from oga.model.machine import load_machine, machine_from_dict
from oga.optimize import optimize
from oga.search.ranges import best_fixed_gains
from oga.model.response import simulate
from oga.verify.replay import verify

DATA = Path(__file__).parent / "data"
#: float64 rounding of the limit checks (as oga.verify.replay's slack)
SLACK = 1e-9


def ratios(u, te, machine):
    """Per-sample |v|, |a|, |j| of the commands ``u`` (N, 3) over the axis limits, (N, 3, 3)."""
    lim = machine.axis_limits()
    up = np.vstack([np.zeros((2, 3)), u])
    v = np.abs(up[2:])
    a = np.abs(up[2:] - up[1:-1]) / te
    j = np.abs(up[2:] - 2 * up[1:-1] + up[:-2]) / te**2
    limits = (lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3)
    return np.stack([q / np.where(m > 0, m, np.inf) for q, m in zip((v, a, j), limits)], axis=2)


def with_ferror(machine, limit_m):
    data = machine.model_dump(mode="json")
    for axis in data["axes"].values():
        axis["limits"]["ferror_max_m"] = limit_m
    return machine_from_dict(data)


@pytest.fixture(scope="module")
def ucp():
    return load_machine("ucp710")


@pytest.fixture(scope="module")
def rapids(ucp):
    sp = plan(load_toolpath(DATA / "rapids_xy.ngc"), ucp.planning_limits())
    assert sp.rapid.sum() > 0.25 * len(sp) and (~sp.rapid).sum() > 0.25 * len(sp)
    return sp


#: Following-error limit (m): between the lags of the feed moves and of the rapids with the
#: best fixed gains of ucp710 (0.94 mm): it rules those gains out, by the rapids alone.
FERROR_M = 0.7e-3


@pytest.mark.parametrize("ferror", [None, FERROR_M])
def test_exported_schedule_and_baseline_keep_every_limit_at_every_sample(ucp, rapids, ferror):
    machine = ucp if ferror is None else with_ferror(ucp, ferror)
    r = optimize(rapids, machine, {"nominal": True})
    assert r.status == "ok" and not r.kept_baseline and r.ratio_mse < 0.5
    kp = r.schedule.kp_m_min_per_mm
    if ferror is None:  # the search did act during the rapids
        assert np.ptp(kp[rapids.rapid][:, 0]) > 0.1
    cols = list(rapids.moving_axes)
    for name, kp_s, kf_s in (("schedule", kp, r.schedule.kf),
                             ("baseline", r.baseline_kp, r.baseline_kf)):
        sim = simulate(rapids, machine, kp_s, kf_s)
        q = ratios(sim.u, rapids.dt, machine)
        assert q.max() <= 1.0 + SLACK, (name, q.max(axis=0))
        # a tight test: the jerk limit is nearly reached, and in the rapids
        assert q[:, cols, 2].max() > 0.8, name
        assert q[rapids.rapid][:, cols, 2].max() > 0.8, name
        lag = np.abs(rapids.pos - sim.pos)
        if ferror is not None:
            assert lag.max() <= ferror * (1 + SLACK), name
        # oga's own figures agree with the fresh simulation
        v = r.optimized if name == "schedule" else r.baseline
        np.testing.assert_allclose(v.command_ratio, q.max(axis=0), rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(v.metrics.track_max_m, lag.max(axis=0), rtol=1e-12)
    if ferror is not None:  # the limit, broken only in the rapids, changed the fixed gains
        free = best_fixed_gains(rapids, ucp)
        assert (free.kp["x"], free.kf["x"]) != (r.baseline_kp["x"], r.baseline_kf["x"])
        lag = np.abs(rapids.pos - simulate(rapids, ucp, free.kp["x"], free.kf["x"]).pos)
        assert lag[rapids.rapid].max() > ferror > lag[~rapids.rapid].max()


def test_verify_rejects_a_jerk_spike_inside_a_rapid(ucp, rapids):
    best = best_fixed_gains(rapids, ucp)
    kp0, kf0 = best.kp["x"], best.kf["x"]
    n = len(rapids)
    kp, kf = np.full((n, 3), kp0), np.full((n, 3), kf0)
    bounds = {"x": (1.0, 3.0), "y": (1.0, 3.0)}
    assert verify(rapids, ucp, kp, kf, bounds).ok
    # the middle of the longest rapid, where X lags most: a small Kp step there
    lag = np.abs(rapids.pos - simulate(rapids, ucp, kp0, kf0).pos)[:, 0]
    k = int(np.argmax(np.where(rapids.rapid, lag, 0.0)))
    assert rapids.rapid[k - 5:k + 5].all()
    kp[k:, 0] = kp0 - 0.05
    sim = simulate(rapids, ucp, kp, kf)
    q = ratios(sim.u, rapids.dt, ucp)
    # independent check that only the jerk breaks, only in the rapid
    assert q[..., :2].max() <= 1.0 and q[~rapids.rapid].max() <= 1.0
    assert q[k, 0, 2] > 2.0 and np.argmax(q[:, 0, 2]) == k
    v = verify(rapids, ucp, kp, kf, bounds)
    assert not v.ok and not v.limits_ok and v.stability_ok
    assert len(v.violations) == 1
    msg = v.violations[0]
    assert msg.startswith("axis x: velocity command jerk reaches")
    assert re.search(rf"at sample {k} \(t = {k * rapids.dt:.3f} s, line {rapids.block[k]}, "
                     r"in a rapid\)", msg), msg
    assert f"{q[k, 0, 2]:.3f}x" in msg


def test_verify_names_a_following_error_in_a_rapid(ucp, rapids):
    kp0, kf0 = 1.7, 0.9
    n = len(rapids)
    lag = np.abs(rapids.pos - simulate(rapids, ucp, kp0, kf0).pos)
    k = int(np.argmax(lag[:, 1]))
    assert rapids.rapid[k] and lag[~rapids.rapid].max() < 0.5 * lag[k, 1]
    limit = 0.5 * (lag[k, 1] + lag[~rapids.rapid, 1].max())  # breaks only in the rapids
    m = with_ferror(ucp, limit)
    v = verify(rapids, m, np.full((n, 3), kp0), np.full((n, 3), kf0),
               {"x": (1.0, 3.0), "y": (1.0, 3.0)})
    assert not v.limits_ok
    msg = [s for s in v.violations if s.startswith("axis y: following error")]
    assert len(msg) == 1 and f"at sample {k} " in msg[0] and "in a rapid" in msg[0]


def test_an_impossible_stability_margin_is_named(ucp, tmp_path, capsys):
    from oga.cli import main

    data = ucp.model_dump(mode="json")
    data["gains"]["pm_min_deg"] = 89.0  # ucp710's best phase margin is 88.7 deg (Kp 0.5)
    with pytest.raises(MachineError, match=r"no Kp of the grid meets PM >= 89.0 deg, GM >= 10"):
        optimize(plan(load_toolpath(DATA / "short_xz.ngc"), ucp.planning_limits()),
                 machine_from_dict(data), {"nominal": True})
    path = tmp_path / "pm89.json"
    path.write_text(machine_from_dict(data).model_dump_json())
    out = tmp_path / "t.csv"
    assert main(["optimize", str(DATA / "short_xz.ngc"), "--machine", str(path),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "PM >= 89.0 deg" in err and "kinematic" not in err
    assert not out.exists()


def test_report_shades_the_rapids_on_the_command_and_following_error_figures(ucp, rapids):
    from oga.report.optimize import render_report

    r = optimize(rapids, ucp, {"nominal": True})
    edges = np.flatnonzero(np.diff(np.r_[0, rapids.rapid.astype(int), 0]))
    runs = len(edges) // 2
    assert runs == 2  # the two G0 moves of the program
    page = render_report(r)
    figures = page.split("<figure")[1:]
    shade = 'fill="#888888" fill-opacity="0.2"'
    panels = len(rapids.moving_axes)
    assert figures[3].count(shade) == 3 * panels * runs  # velocity, acceleration, jerk
    assert figures[4].count(shade) == panels * runs  # following error
    assert ">rapid</text>" in figures[3]


def test_ranges_name_the_stability_margins_when_no_kp_is_stable(ucp):
    from oga.search.ranges import gain_ranges

    data = ucp.model_dump(mode="json")
    data["gains"]["pm_min_deg"] = 89.0
    sp = plan(load_toolpath(DATA / "short_xz.ngc"), ucp.planning_limits())
    best = gain_ranges(sp, machine_from_dict(data)).to_dict()["best_fixed"]
    assert not best["found"] and "PM >= 89.0 deg" in best["message"]
    assert "kinematically" not in best["message"]
