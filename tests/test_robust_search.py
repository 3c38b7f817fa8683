"""The robust search prototype: its baseline and table hold on every plant of the set."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.machine import load_machine
from oga.pipeline import plan_toolpath
from oga.robust.certificate import certify
from oga.robust.plants import scenario_set
from oga.robust.search import design_machine, robust_optimize
from oga.stability import stable_range
from oga.verify import verify

DATA = Path(__file__).parent / "data"


def test_design_machine_scales_the_limits_and_cuts_the_kp_bounds_only():
    m = load_machine("ucp710-robust")
    d = design_machine(m, 0.8, (1.2, 2.3))
    for a in ("x", "y", "z"):
        lim, dl = m.axes[a].limits, d.axes[a].limits
        assert dl.vmax_m_s == lim.vmax_m_s and dl.amax_m_s2 == pytest.approx(0.8 * lim.amax_m_s2)
        assert dl.jmax_m_s3 == pytest.approx(0.8 * lim.jmax_m_s3)
        assert d.axes[a].cascade == m.axes[a].cascade and d.axes[a].uncertainty is None
    assert d.gains.kp_bounds_m_min_per_mm == (1.2, 2.3)
    assert stable_range(d, "x").kp_max == pytest.approx(2.3)


def test_robust_table_and_baseline_hold_on_every_plant():
    m = load_machine("ucp710-robust")
    sp = plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), m, feed_m_s=None, tol_m=2e-5)
    scen = scenario_set(m, n=8, seed=9)
    r = robust_optimize(sp, m, scenarios=scen)
    n = len(sp)
    kp0, kf0 = r.result.baseline_kp["x"], r.result.baseline_kf["x"]
    bkp, bkf = np.full((n, 3), kp0), np.full((n, 3), kf0)
    kp_top = min(stable_range(p, a).kp_max for p in scen.plants for a in ("x", "z"))
    assert r.kp_max == pytest.approx(kp_top) and kp0 <= kp_top + 1e-12
    sched = r.schedule
    for plant in scen.plants:
        bounds = {a: (stable_range(plant, a).kp_min, stable_range(plant, a).kp_max)
                  for a in ("x", "z")}
        assert verify(sp, plant, bkp, bkf, bounds).ok  # the baseline holds everywhere
        assert sched.kp_m_min_per_mm[:, [0, 2]].max() <= bounds["x"][1] + 1e-12
    # the exported table's certificate, recomputed
    cert = certify(sp, m, sched.kp_m_min_per_mm, sched.kf, bkp, bkf, scen)
    np.testing.assert_allclose(cert.ratio, r.certificate.ratio, rtol=1e-12)
    if r.status == "ok":
        assert cert.worst <= 1.0 and not cert.breaks("schedule-only")
        s = r.result.searched_schedule
        np.testing.assert_allclose(sched.kf, bkf + r.alpha[1] * (s.kf - bkf), atol=1e-15)
        np.testing.assert_allclose(sched.kp_m_min_per_mm,
                                   bkp + r.alpha[0] * (s.kp_m_min_per_mm - bkp), atol=1e-15)
        nominal = verify(sp, m, sched.kp_m_min_per_mm, sched.kf, r.result.kp_bounds)
        assert nominal.ok and nominal.metrics.mse_m2 < verify(
            sp, m, bkp, bkf, r.result.kp_bounds).metrics.mse_m2
    else:
        np.testing.assert_array_equal(sched.kp_m_min_per_mm, bkp)
        np.testing.assert_array_equal(sched.kf, bkf)
