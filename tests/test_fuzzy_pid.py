"""Fuzzy self-tuning PID: the paper's claim on our plant, against independent references.

References: the P + FFW loops of :func:`oga.model.response.simulate`, and the discrete PID
closed loop of python-control on :func:`oga.model.linear.position_open_loop`.
"""

from __future__ import annotations

from pathlib import Path

import control
import numpy as np
import pytest

from feedplan.read import load_toolpath
from feedplan.setpoints import Setpoints
from oga.model.contour import contour_error_of
from oga.controllers import fuzzy_pid
from oga.controllers.base import score
from oga.defaults import TOL_M
from oga.errors import OptionError, TuneError
from oga.model.linear import position_open_loop
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.pipeline import plan_toolpath
from oga.search.ranges import gain_ranges
from oga.model.response import simulate

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")
OFF = {"dkp_ratio": 0.0, "dki_ratio": 0.0, "dkd_ratio": 0.0}  # the initial PID alone


def _linear_machine():
    """ucp710 without Coulomb/Stribeck friction and force limit: the linear model exactly."""
    data = UCP.model_dump()
    for ax in data["axes"].values():
        ax["cascade"].update({"coulomb_n": 0.0, "static_n": 0.0, "force_limit_n": 1e12})
    return machine_from_dict(data)


def _step(height_m, n=1500):
    """A position step of x at sample 1 (the axes start at rest at sample 0's setpoint)."""
    pos = np.zeros((n, 3))
    pos[1:, 0] = height_m
    zero = np.zeros((n, 3))
    return Setpoints(dt=UCP.te, s=np.zeros(n), pos=pos, vel=zero, acc=zero, jerk=zero,
                     block=np.ones(n, dtype=int), rapid=np.zeros(n, dtype=bool), plane="xy")


@pytest.fixture(scope="module", params=["circle_r50_f3000.ngc", "reference_xz.ngc"])
def path(request):
    """A test toolpath and its best fixed gains (oga.search.ranges)."""
    sp = plan_toolpath(load_toolpath(DATA / request.param), UCP, feed_m_s=None, tol_m=TOL_M)
    return sp, gain_ranges(sp, UCP).best_fixed


def test_unknown_parameter_raises():
    with pytest.raises(OptionError, match="kp_m_min_per_mm"):
        fuzzy_pid.run(_step(1e-4), UCP, tune=False, kp_1_s=40.0, kf=0.0, kp_m_min_per_mm=2.0)


def test_without_fuzzy_integral_and_derivative_it_is_p_ffw(path):
    sp, best = path
    kp, kf = best.kp["x"], best.kf["x"]
    run = fuzzy_pid.run(sp, UCP, tune=False, kp_1_s=kp * KP_SI_PER_M_MIN_PER_MM, kf=kf,
                        ki_1_s2=0.0, kd=0.0, **OFF)
    ref = simulate(sp, UCP, kp, kf)
    np.testing.assert_allclose(run.pos, ref.pos, rtol=0, atol=1e-15)
    np.testing.assert_allclose(run.u, ref.u, rtol=0, atol=1e-15)


def test_initial_pid_matches_python_control():
    """Friction-free plant: the PID's step response is python-control's closed loop."""
    machine = _linear_machine()
    kp, ki, kd, h, n = 40.0, 160.0, 0.05, 1e-4, 400
    run = fuzzy_pid.run(_step(h, n), machine, tune=False, kp_1_s=kp, kf=0.0, ki_1_s2=ki,
                        kd=kd, **OFF)
    te = machine.te
    a, b, c, d = position_open_loop(machine, "x", 1.0)
    plant = control.ss(a, b, c, d, te)
    z = control.tf([1, 0], [1], te)
    pid = kp + ki * te * z / (z - 1) + kd * (z - 1) / (te * z)
    loop = control.feedback(pid * plant, 1)
    r = np.full(n, h)
    r[0] = 0.0
    resp = control.forced_response(loop, T=np.arange(n) * te, U=r)
    np.testing.assert_allclose(run.pos[:, 0], np.ravel(resp.outputs), rtol=0, atol=1e-9 * h)


def test_claim_less_overshoot_than_the_initial_pid():
    """Paper: the fuzzy self-tuning PID overshoots less than its initial PID on a step."""
    kp = 40.0  # about the best fixed Kp on these paths, 2.4 (m/min)/mm
    h = 1e-3
    common = dict(kp_1_s=kp, kf=0.0, ki_1_s2=0.1 * kp * kp, kd=0.05, e_range_m=h,
                  ec_range_m_s=kp * h)
    initial = fuzzy_pid.run(_step(h), UCP, tune=False, **common, **OFF)
    fuzzy = fuzzy_pid.run(_step(h), UCP, tune=False, **common)
    over = [(r.pos[:, 0].max() - h) / h for r in (initial, fuzzy)]
    print(f"\n1 mm step, overshoot: initial PID {over[0]:.2%}, fuzzy PID {over[1]:.2%}")
    assert over[0] > 0.03  # the integral makes the initial PID overshoot
    assert over[1] < over[0]  # the claim holds, barely: about 2 % of the overshoot
    assert over[1] > 0.9 * over[0]
    # a position step breaks the velocity command's acceleration and jerk limits (eq. 2)
    ratios = score(_step(h), UCP, fuzzy.pos, fuzzy.u).command_ratios[0]
    print(f"x command ratios (v, a, j): {np.round(ratios, 1)}")
    assert ratios[0] < 1.0 and ratios[1] > 1.0 and ratios[2] > 1.0


def test_tuned_and_untuned_on_the_test_paths(path):
    sp, best = path
    untuned = fuzzy_pid.run(sp, UCP, tune=False)
    s0 = score(sp, UCP, untuned.pos, untuned.u)
    # the design defaults swing the gains with the error: the command's jerk breaks eq. 2
    assert not s0.limits_ok and s0.command_ratios[:, 2].max() > 5.0
    assert s0.mse_ce_m2 > 50 * best.mse_ce_m2
    tuned = fuzzy_pid.run(sp, UCP, tune=True)
    s1 = score(sp, UCP, tuned.pos, tuned.u)
    ce = np.abs(contour_error_of(sp, tuned.pos))[~sp.rapid]
    print(f"\n{sp.source}: untuned MSE {s0.mse_ce_m2:.3g} m^2 (jerk ratio "
          f"{s0.command_ratios[:, 2].max():.1f}); tuned MSE {s1.mse_ce_m2:.3g} m^2 = "
          f"{s1.mse_ce_m2 / best.mse_ce_m2:.3f} x best fixed, RMS {np.sqrt(s1.mse_ce_m2):.3g} m, "
          f"max {ce.max():.3g} m; {tuned.parameters}")
    assert s1.limits_ok
    assert set(fuzzy_pid.PARAMETERS) <= set(tuned.parameters)
    # feasible only with wide input ranges (inputs near ZO, slowly varying gains): then
    # within a few percent of the best fixed gains
    assert tuned.parameters["e_range_m"] >= 10 * fuzzy_pid.E_RANGE_M
    assert 0.8 * best.mse_ce_m2 < s1.mse_ce_m2 < 1.1 * best.mse_ce_m2


def test_paper_law_without_feed_forward_cannot_meet_the_limits(path):
    sp, best = path
    kp = best.kp["x"] * KP_SI_PER_M_MIN_PER_MM
    with pytest.raises(TuneError, match="no parameter combination"):
        fuzzy_pid.run(sp, UCP, tune=True, kp_1_s=kp, kf=0.0)
