"""Identification that says how wrong its model is: the evidence (residual over noise, its
correlation, the model-error share), the uncertainty set grown with it, the physical bounds,
a fractional dead time where it fits measurably better, and what the file and a table's
summary say of it."""

from __future__ import annotations

import dataclasses
import math
import tomllib

import numpy as np
import pytest

from feedplan.read import read_toolpath
from oga.defaults import (
    IDENT_BOUNDS,
    IDENT_MODEL_ERROR_MAX_WIDTH,
    IDENT_MODEL_ERROR_WIDTHS,
    IDENT_UNCERTAINTY_FLOOR,
)
from oga.identify.coverage import model_coverage
from oga.identify.excite import excite_program
from oga.identify.fit import AxisFit, _at_bounds, _bounds, correlation_samples, fit_axis
from oga.identify.sim import synthetic_trace
from oga.identify.trace import AxisTrace
from oga.identify.write import identified_machine, machine_toml, uncertainty_of
from oga.model.machine import FACTOR_FIELDS, load_machine, machine_from_dict
from oga.pipeline import plan_toolpath

UCP = load_machine("ucp710")


def test_correlation_time_of_white_and_coloured_residuals():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(50_000)
    assert correlation_samples(white) == pytest.approx(1.0, abs=0.1)
    rho = 0.9  # first-order colour: (1 + rho) / (1 - rho) = 19 samples
    ar = np.empty_like(white)
    ar[0] = white[0]
    for k in range(1, ar.size):
        ar[k] = rho * ar[k - 1] + white[k]
    assert correlation_samples(ar) == pytest.approx(19.0, rel=0.15)
    assert correlation_samples(np.zeros(10)) == 1.0


def _fit(share=0.0, changes=None, status="ok", dead=2, **values):
    """An AxisFit of ucp710's X (some ``values`` replaced) with +-1 % intervals (no solver)."""
    cas = UCP.axes["x"].cascade.model_copy(update=values)
    values = {k: getattr(cas, k) for k in FACTOR_FIELDS}
    return AxisFit(status=status, cascade=cas, dead_time_samples=dead, lag_samples=0,
                   values=values, ci_low={k: 0.99 * v for k, v in values.items()},
                   ci_high={k: 1.01 * v for k, v in values.items()}, mass_identified=False,
                   residual_rms_m=1e-7, noise_rms_m=1e-7, force_residual_rms_n=None,
                   candidates=[(dead, 0, 1e-7), (dead + 1, 0, 5e-7)],
                   model_error_share=share, model_error_changes=changes or {})


def test_the_set_grows_continuously_with_the_evidence():
    """The floor (+-5 %) where the model explains the trace; beyond floor / widths of
    model-error share every range grows with it, without a step (a 1e-4 change of the share
    moves no factor by more than widths x 1e-4 plus the 4-digit rounding), up to +-50 %; a
    parameter whose own model-error change is larger gets that; the held-out ratio widens the
    intervals' share; never beyond x0.1-x10 nor the physical bounds."""
    w, cap = IDENT_MODEL_ERROR_WIDTHS, IDENT_MODEL_ERROR_MAX_WIDTH
    assert uncertainty_of(_fit()).kv_n_s_m == (1 - IDENT_UNCERTAINTY_FLOOR,
                                               1 + IDENT_UNCERTAINTY_FLOOR)
    last = None
    for share in np.arange(0.0, 0.08, 1e-4):
        u = uncertainty_of(_fit(float(share)))
        hi = u.kv_n_s_m[1]
        assert hi == pytest.approx(1 + max(IDENT_UNCERTAINTY_FLOOR, min(cap, w * share)),
                                   abs=1e-4)
        if last is not None:
            assert 0.0 <= hi - last <= w * 1e-4 + 1e-4 + 1e-12
        last = hi
    assert hi == 1 + cap
    u = uncertainty_of(_fit(0.002, {"coulomb_n": 0.03, "tn_s": 0.001}))
    assert u.coulomb_n == (round(1 - w * 0.03, 4), round(1 + w * 0.03, 4))
    assert u.tn_s == (1 - IDENT_UNCERTAINTY_FLOOR, 1 + IDENT_UNCERTAINTY_FLOOR)  # 10 x 0.002
    assert u.fit_status == "ok" and u.model_error_share == 0.002
    # the intervals' share: 2 half-widths (2 %), times the held-out ratio 4 -> 8 %
    assert uncertainty_of(_fit(), floor=0.0, heldout_ratio=4.0).tn_s == (0.92, 1.08)
    # wide intervals (a parameter the trace hardly sees) meet x0.1-x10 and the physical bounds
    wide = _fit(tn_s=0.5, force_lag_s=1e-3, kv_n_s_m=2 * math.pi * 600 * 10)
    wide = dataclasses.replace(wide, ci_low={k: v * 1e-3 for k, v in wide.values.items()},
                               ci_high={k: v * 1e3 for k, v in wide.values.items()})
    huge = uncertainty_of(wide)
    assert huge.mass_kg == (0.1, 10.0)
    assert huge.tn_s == (0.1, round(IDENT_BOUNDS["tn_s"][1] / 0.5, 4))
    assert huge.force_lag_s == (0.1, round(IDENT_BOUNDS["force_lag_s"][1] / 1e-3, 4))
    assert huge.kv_n_s_m == (round(IDENT_BOUNDS["velocity_loop_hz"][0] / 10, 4), 10.0)


def test_dead_time_doubt_in_the_set():
    assert uncertainty_of(_fit()).dead_time_extra_samples == (0, 0)
    assert uncertainty_of(_fit(status="model-error")).dead_time_extra_samples == (0, 1)
    more = _fit(0.01, {"dead_time_samples": 0.15})  # 10 x 0.15 samples, rounded
    assert uncertainty_of(more).dead_time_extra_samples == (0, 2)


def test_the_bounds_are_the_documented_physical_ones():
    cas = UCP.axes["x"].cascade
    lo, hi = _bounds(cas, 600.0)
    assert math.exp(lo[0]) == pytest.approx(2 * math.pi * 600 * IDENT_BOUNDS["velocity_loop_hz"][0])
    assert math.exp(hi[1]) == pytest.approx(IDENT_BOUNDS["tn_s"][1])
    assert math.exp(lo[2]) == pytest.approx(IDENT_BOUNDS["force_lag_s"][0])
    assert hi[6] == pytest.approx(600 * IDENT_BOUNDS["viscous_1_s"][1])
    x = (lo + hi) / 2
    assert _at_bounds(x, lo, hi) == ()
    x[2], x[6], x[3] = lo[2], hi[6], lo[3]  # force lag low, viscous high; no friction is physical
    assert _at_bounds(x, lo, hi) == ("force_lag_s", "viscous_n_s_m")


@pytest.fixture(scope="module")
def excite_short():
    text = excite_program(UCP, ["x"], travel_mm=5.0, pass_s=0.3, sweep_hz=(7.0, 15.0))
    return plan_toolpath(read_toolpath(text, "gcode"), UCP, feed_m_s=None, tol_m=2e-5)


def test_a_fractional_dead_time_only_where_it_fits_measurably_better(excite_short):
    """ucp710 with X's own dead time 2.4 samples (0.1 um noise and quantum): on oga's cascade a
    fraction of a sample trades against the force lag (0.4 -> 0.76 ms) and the viscous
    friction, so a whole dead time explains the trace to the noise, and no fractional one is
    tried (none could fit measurably better). The fit's Jacobian column of the fraction is
    the derivative of the residual. (The two-mass plants of tests/test_two_mass.py keep
    fractional dead times: there they fit measurably better.)"""
    from oga.identify.fit import _Model, _x0

    ax = UCP.axes["x"].model_copy(update={"dead_time_samples": 2.4})
    true = UCP.model_copy(update={"axes": {**UCP.axes, "x": ax}})
    sp = excite_short
    ch = synthetic_trace(sp, true, ["x"], 3.0, 0.8, noise_m=1e-7, quantum_m=1e-7, seed=2)
    n = len(sp)
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, 3.0),
                   kf=np.full(n, 0.8))
    fit = fit_axis(UCP, "x", tr, sp.dt)
    assert fit.status == "ok" and fit.noise_ratio < 1.5 and fit.correlation_samples < 1.5
    assert fit.dead_time_samples == 2 and fit.values["force_lag_s"] > 1.5 * 4e-4
    assert all(float(d).is_integer() for d, _, _ in fit.candidates)
    model = _Model(UCP, "x", tr, sp.dt, 600.0)
    x = np.append(_x0(UCP.axes["x"].cascade), 0.4)
    jac = model.jacobian(x, 2, 0, frac=True)
    h = 1e-5
    up, down = x.copy(), x.copy()
    up[-1] += h
    down[-1] -= h
    fd = (model.residual(up, 2, 0, True) - model.residual(down, 2, 0, True)) / (2 * h)
    assert np.linalg.norm(jac[:, -1] - fd) < 1e-4 * np.linalg.norm(fd)


def test_the_file_and_the_summary_say_what_was_identified():
    """x fitted 2.4 samples with model error, z 2 and ok, y not identified: the machine's dead
    time is 2, x carries its own; each fitted set says its fit's status; a table's summary
    names the axes and whether the model covers the plant."""
    fits = {"x": dataclasses.replace(_fit(0.05, status="model-error"), dead_time_samples=2.4),
            "z": _fit()}
    m = identified_machine(UCP, fits)
    assert m.timing.dead_time_samples == 2 and m.dead_time_samples_of("x") == 2.4
    assert m.axes["z"].dead_time_samples is None and m.dead_time_samples_of("y") == 2.0
    text = machine_toml(m, fits)
    assert "[axes.x]\ndead_time_samples = 2.4   # fitted" in text
    assert "the base machine's set (this axis was not identified)" in text
    back = machine_from_dict(tomllib.loads(text))
    assert back.digest() == m.digest()
    assert back.axes["x"].uncertainty.fit_status == "model-error"
    cov = model_coverage(back, ["x", "y", "z"])
    assert cov["covers"] and cov["axes"]["y"]["set"] == "assumed"
    assert cov["axes"]["x"] == {"set": "identified", "fit_status": "model-error",
                                "model_error_share": 0.05, "dead_time_samples": 2.4}
    assert "axis x: identified with model error" in cov["note"] and "axis y: an assumed" in cov["note"]
    poor = identified_machine(UCP, {"z": _fit(0.4, status="poor")})
    cov = model_coverage(poor, ["x", "z"])
    assert not cov["covers"] and "does not cover the plant on axis z" in cov["note"]
    assert model_coverage(UCP, ["x", "z"]) == {
        "covers": True, "note": "", "axes": {a: {"set": "assumed", "fit_status": None,
                                                 "model_error_share": None,
                                                 "dead_time_samples": 2.0} for a in "xz"}}
