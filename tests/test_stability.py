"""Stability margins and the stable Kp range, against python-control and first principles."""

import math
import warnings

import control
import numpy as np
import pytest

from oga.errors import MachineError, OptionError
from oga.model.linear import lifted_axis, position_open_loop
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.model.stability import margins, stable_range

UCP = load_machine("ucp710")


def _with_gains(**gains):
    data = UCP.model_dump()
    data["gains"].update(gains)
    return machine_from_dict(data)


def _control_margins(machine, axis, kp):
    a, b, c, d = position_open_loop(machine, axis, kp * KP_SI_PER_M_MIN_PER_MM)
    sys = control.ss(a, b, c, d, machine.te)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # python-control's own numerical-method notices
        gm, pm, wpc, wgc = control.margin(sys)
    return sys, 20 * math.log10(gm), pm, wpc, wgc


@pytest.mark.parametrize("axis", ["x", "z"])
@pytest.mark.parametrize("kp", [1.0, 2.0, 3.0, 3.1, 5.0, 10.0, 20.0])
def test_margins_agree_with_python_control(axis, kp):
    sys, gm_db, pm, wpc, wgc = _control_margins(UCP, axis, kp)
    m = margins(UCP, axis, kp)
    assert m.pm_deg == pytest.approx(pm, abs=0.5)
    assert m.gm_db == pytest.approx(gm_db, abs=0.2)
    assert m.w_gain_crossover_rad_s == pytest.approx(wgc, rel=1e-3)
    assert m.w_phase_crossover_rad_s == pytest.approx(wpc, rel=1e-3)
    closed = control.feedback(sys, 1)
    assert m.stable == bool(np.max(np.abs(closed.poles())) < 1.0)


def test_margins_fall_with_kp_and_instability_is_reported():
    low, high, unstable = (margins(UCP, "x", k) for k in (1.0, 5.0, 20.0))
    assert low.pm_deg > high.pm_deg > 0 > unstable.pm_deg
    assert low.gm_db > high.gm_db > 0 > unstable.gm_db
    assert low.stable and high.stable and not unstable.stable


def test_lifted_axis_is_an_integrator_with_unity_velocity_gain():
    # The velocity PI makes the axis velocity equal the held command at DC, viscous
    # friction notwithstanding, so G(z) = C (zI - A)^-1 B ~ Te / (z - 1) near z = 1.
    a, b, c, _ = lifted_axis(UCP, "z")
    z = 1.0 + 1e-7
    g = (c @ np.linalg.solve(z * np.eye(4) - a, b))[0, 0]
    assert (z - 1.0) * g == pytest.approx(UCP.te, rel=1e-4)


def test_dead_time_adds_its_phase_lag():
    # z^-d at the gain crossover lags by d * w * Te: with the same gain crossover,
    # each extra sample of dead time costs exactly w_gc * Te rad of phase margin.
    data = UCP.model_dump()
    data["timing"]["dead_time_samples"] = 3
    m3 = margins(machine_from_dict(data), "x", 2.0)
    m2 = margins(UCP, "x", 2.0)
    assert m3.w_gain_crossover_rad_s == pytest.approx(m2.w_gain_crossover_rad_s, rel=1e-9)
    lag = math.degrees(m2.w_gain_crossover_rad_s * UCP.te)
    assert m2.pm_deg - m3.pm_deg == pytest.approx(lag, rel=1e-6)


@pytest.mark.parametrize("axis", ["x", "z"])
def test_ucp710_stable_range_is_1_to_3(axis):
    r = stable_range(UCP, axis)
    assert r.status == "ok" and r.ok
    assert r.kp_min == 1.0
    assert r.kp_max in (2.9, 3.0, 3.1)
    # the grid holds exact decimals over the span [0.5, 5] in steps of 0.1
    assert r.kp.shape == (46,)
    assert [k for k, _, _ in r.table] == [round(0.5 + 0.1 * i, 1) for i in range(46)]
    # every value inside the range meets the criteria, its neighbour above does not
    inside = (r.kp >= r.kp_min) & (r.kp <= r.kp_max)
    assert np.all(r.pm_deg[inside] >= 70.0) and np.all(r.gm_db[inside] >= 10.0)
    above = np.flatnonzero(r.kp > r.kp_max)[0]
    assert r.pm_deg[above] < 70.0 or r.gm_db[above] < 10.0
    # the lower end is the configured bound, not a margin: 0.9 meets the criteria
    below = np.flatnonzero(r.kp < 1.0)[-1]
    assert r.pm_deg[below] >= 70.0 and r.gm_db[below] >= 10.0


def test_stable_range_follows_the_axis_model_not_its_name():
    # X and Y of ucp710 have the same model: the same margins, each under its own name
    x, y = stable_range(UCP, "x"), stable_range(UCP, "y")
    assert np.array_equal(x.pm_deg, y.pm_deg) and np.array_equal(x.gm_db, y.gm_db)
    assert (x.axis, y.axis) == ("x", "y")
    assert y.message == x.message.replace("axis x:", "axis y:")
    # a Y with half the velocity-loop gain is another loop: its own margins (python-control
    # agrees), a shorter range, and X is unchanged
    data = UCP.model_dump()
    data["axes"]["y"]["cascade"]["kv_n_s_m"] /= 2
    soft = machine_from_dict(data)
    soft_y = stable_range(soft, "y")
    i = int(np.flatnonzero(soft_y.kp == 3.0)[0])
    _, gm_db, pm, _, _ = _control_margins(soft, "y", 3.0)
    assert soft_y.pm_deg[i] == pytest.approx(pm, abs=0.5)  # 39.8 deg against 70.3 for X
    assert soft_y.gm_db[i] == pytest.approx(gm_db, abs=0.2)
    assert soft_y.kp_max < x.kp_max
    assert np.array_equal(stable_range(soft, "x").pm_deg, x.pm_deg)


def test_stable_range_respects_bounds_and_reports_empty():
    r = stable_range(_with_gains(kp_bounds_m_min_per_mm=(2.0, 2.5)), "x")
    assert (r.status, r.kp_min, r.kp_max) == ("ok", 2.0, 2.5)
    empty = stable_range(_with_gains(pm_min_deg=89.9), "x")
    assert empty.status == "empty" and not empty.ok
    assert math.isnan(empty.kp_min) and math.isnan(empty.kp_max)
    assert "no Kp" in empty.message


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf, "fast", None])
def test_margins_refuse_bad_kp(bad):
    with pytest.raises(OptionError, match="kp_m_min_per_mm"):
        margins(UCP, "x", bad)


def test_unknown_axis_is_refused():
    with pytest.raises(MachineError, match="'w'"):
        margins(UCP, "w", 2.0)
    data = UCP.model_dump()
    del data["axes"]["y"]
    with pytest.raises(MachineError, match="'y'"):
        stable_range(machine_from_dict(data), "y")
    with pytest.raises(ValueError):  # InputError is a ValueError for foreign callers
        stable_range(UCP, "a")
