"""``compare`` and ``oga compare``: rows recomputed independently, failures, JSON and report."""

from __future__ import annotations

import dataclasses
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

import oga.cli as cli
from feedplan.read import load_toolpath
from oga.controllers.compare import compare
from oga.controllers.base import score
from oga.model.contour import contour_error_of
from oga.controllers import CONTROLLERS, load_controller
from oga.controllers.afsmc import run as afsmc_run
from oga.defaults import TOL_M
from oga.errors import OptionError
from oga.model.machine import load_machine, machine_from_dict
from oga.pipeline import plan_toolpath
from oga.search.ranges import gain_ranges
from oga.model.response import simulate

DATA = Path(__file__).parent / "data"
MACHINE = load_machine("ucp710")
SHORT = DATA / "short_xz.ngc"


@pytest.fixture(scope="module")
def setpoints():
    return plan_toolpath(load_toolpath(SHORT), MACHINE, feed_m_s=None, tol_m=TOL_M)


def _ratios(u, dt, feed):
    """Peak |u|, |du|/Te, |d2u|/Te^2 per axis over the feed samples, at rest before sample 0."""
    u0 = np.vstack([np.zeros((2, 3)), u])
    d1 = np.diff(u0, axis=0)
    a = d1[1:] / dt
    j = np.diff(d1, axis=0) / dt**2
    return np.abs(u[feed]).max(axis=0), np.abs(a[feed]).max(axis=0), np.abs(j[feed]).max(axis=0)


def test_registry_order_and_errors(monkeypatch):
    assert CONTROLLERS == ("fixed", "oga", "fuzzy-pid", "ccc", "zpetc-ccc-ddob", "smc-dob-ccc",
                           "afsmc")
    with pytest.raises(OptionError, match="'nope'.*fixed, oga"):
        load_controller("nope")
    monkeypatch.setitem(sys.modules, "oga.controllers.ccc", None)  # a module not installed
    with pytest.raises(OptionError, match="'ccc' is not available.*known: fixed"):
        load_controller("ccc")
    assert load_controller("fixed").needs_firmware is False
    assert load_controller("oga").needs_firmware is False
    assert load_controller("afsmc").needs_firmware is True


def test_rows_equal_an_independent_recomputation(setpoints):
    sp = setpoints
    cmp = compare(sp, MACHINE, ["fixed", "afsmc"])
    fixed, af = cmp.rows
    assert (fixed.name, fixed.status, af.name, af.status) == ("fixed", "ok", "afsmc", "ok")
    feed = ~sp.rapid
    best = gain_ranges(sp, MACHINE).best_fixed
    ref = simulate(sp, MACHINE, best.kp["x"], best.kf["x"])
    again = afsmc_run(sp, MACHINE)  # deterministic: the same run
    lim = MACHINE.axis_limits()
    for row, pos, u in ((fixed, ref.pos, ref.u), (af, again.pos, again.u)):
        ce = contour_error_of(sp, pos)[feed]
        assert row.mse_ce_um2 == pytest.approx(np.mean(ce**2) * 1e12, rel=1e-12)
        assert row.rms_ce_um == pytest.approx(np.sqrt(np.mean(ce**2)) * 1e6, rel=1e-12)
        assert row.max_ce_um == pytest.approx(np.abs(ce).max() * 1e6, rel=1e-12)
        track = np.abs(sp.pos[feed] - pos[feed]).max(axis=0) * 1e6
        np.testing.assert_allclose(list(row.track_max_um.values()), track, rtol=1e-12)
        v, a, j = _ratios(u, sp.dt, feed)
        cols = [0, 2]  # x and z (ucp710 also has y, at rest here)
        assert row.velocity_ratio == pytest.approx((v / lim.vmax_m_s)[cols].max(), rel=1e-9)
        assert row.accel_ratio == pytest.approx((a / lim.amax_m_s2)[cols].max(), rel=1e-9)
        assert row.jerk_ratio == pytest.approx((j / lim.jmax_m_s3)[cols].max(), rel=1e-9)
        assert row.limits_ok == bool(max(row.velocity_ratio, row.accel_ratio,
                                         row.jerk_ratio) <= 1.0 + 1e-9)
    # the fixed row is the ranges' own best fixed configuration
    assert fixed.mse_ce_um2 == pytest.approx(best.mse_ce_m2 * 1e12, rel=1e-9)
    assert fixed.needs_firmware is False and af.needs_firmware is True


def test_limits_ok_includes_the_following_error_limit(setpoints):
    gains = {"fixed": {"kp_m_min_per_mm": 3.0, "kf": 0.8}}
    (free,) = compare(setpoints, MACHINE, ["fixed"], parameters=gains).rows
    lag_um = free.track_max_um["x"]
    assert free.limits_ok and lag_um > 0
    data = MACHINE.model_dump(mode="json")
    for factor, ok in ((1.001, True), (0.999, False)):
        data["axes"]["x"]["limits"]["ferror_max_m"] = factor * lag_um * 1e-6
        (row,) = compare(setpoints, machine_from_dict(data), ["fixed"], parameters=gains).rows
        assert row.track_max_um["x"] == lag_um and row.limits_ok is ok


def test_a_failing_controller_gives_a_failed_row(setpoints):
    cmp = compare(setpoints, MACHINE, ["fixed", "afsmc"], parameters={"afsmc": {"bogus": 1}})
    ok, failed = cmp.rows
    assert ok.status == "ok" and np.isfinite(ok.mse_ce_um2)
    assert failed.status == "failed" and "bogus" in failed.message
    assert np.isnan(failed.mse_ce_um2) and failed.limits_ok is False and failed.ce_m.size == 0
    assert failed.to_dict()["mse_ce_um2"] is None


def test_unknown_controller_names(setpoints):
    with pytest.raises(OptionError, match="'nope'"):
        compare(setpoints, MACHINE, ["fixed", "nope"])
    with pytest.raises(OptionError, match="more than once"):
        compare(setpoints, MACHINE, "fixed,fixed")


def test_cli_unknown_controller_exits_2_naming_it(capsys):
    code = cli.main(["compare", str(SHORT), "--controllers", "fixed,pid3000"])
    err = capsys.readouterr().err
    assert code == 2 and "pid3000" in err and len(err.strip().splitlines()) == 1


def test_cli_table_json_and_report(tmp_path, capsys):
    js, rep = tmp_path / "c.json", tmp_path / "c.html"
    code = cli.main(["compare", str(SHORT), "--machine", "ucp710", "--controllers",
                              "fixed,oga,afsmc", "--json", str(js), "--report", str(rep)])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.splitlines()
    for name in ("fixed", "oga", "afsmc"):
        assert sum(line.startswith(name + " ") for line in lines) == 1
    d = json.loads(js.read_text())
    assert {"toolpath", "machine", "samples", "te_s", "controllers"} <= set(d)
    assert [c["name"] for c in d["controllers"]] == ["fixed", "oga", "afsmc"]
    for c in d["controllers"]:
        assert {"name", "status", "message", "needs_firmware", "mse_ce_um2", "rms_ce_um",
                "max_ce_um", "track_max_um", "velocity_ratio", "accel_ratio", "jerk_ratio",
                "limits_ok", "time_s", "parameters", "notes"} <= set(c)
        assert set(c["track_max_um"]) == {"x", "y", "z"}
        assert c["needs_firmware"] is (c["name"] == "afsmc")
    rows = {c["name"]: c for c in d["controllers"]}
    # the OGA table is never worse than the fixed gains it starts from
    assert rows["oga"]["mse_ce_um2"] <= rows["fixed"]["mse_ce_um2"] * (1 + 1e-12)
    page = rep.read_text()
    assert page.startswith("<!DOCTYPE html>") and "http" not in page.split("</style>")[1]
    assert page.count("<svg") == 1
    for name in ("fixed", "oga", "afsmc"):
        group = re.search(rf'<g class="controller" data-controller="{name}">(.*?)</g>', page)
        assert group and group.group(1).count("<path d=\"M") >= 1
        assert f'<tr data-controller="{name}" class="status-ok">' in page


def test_a_law_no_tuning_can_keep_in_the_limits_shows_its_untuned_figures(setpoints):
    # zpetc-ccc-ddob breaks eq. 2 at every grid point (its command inverts the loop)
    (row,) = compare(setpoints, MACHINE, ["zpetc-ccc-ddob"]).rows
    assert row.status == "untuned" and "eq. 2" in row.message
    assert np.isfinite(row.mse_ce_um2) and row.limits_ok is False and row.jerk_ratio > 1.0
    assert row.ce_m.shape == (len(setpoints),)


def test_a_diverged_run_scores_as_infeasible_and_fails_its_row(setpoints, monkeypatch):
    sim = simulate(setpoints, MACHINE, 3.0, 0.8)
    pos = sim.pos.copy()
    pos[len(pos) // 2, 0] = np.nan
    s = score(setpoints, MACHINE, pos, sim.u)
    assert s.mse_ce_m2 == np.inf and s.limits_ok is False
    ok = score(setpoints, MACHINE, sim.pos, sim.u)
    assert np.isfinite(ok.mse_ce_m2) and ok.limits_ok
    # a law whose loop diverges gets a failed row naming it, not a crash
    fixed = load_controller("fixed")

    def diverging(sp, machine, **kw):
        run = fixed.run(sp, machine, **kw)
        return type(run)(name=run.name, pos=pos, u=run.u, needs_firmware=False)

    broken = dataclasses.replace(fixed, run=diverging)
    monkeypatch.setattr("oga.controllers.compare.load_controller", lambda name: broken)
    (row,) = compare(setpoints, MACHINE, ["fixed"]).rows
    assert row.status == "failed" and "diverged" in row.message
