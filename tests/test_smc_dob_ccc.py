"""Sliding mode + disturbance observer + adaptive fuzzy PID CCC: the paper's claims on our plant.

References: the continuous velocity loop of python-control (for the identified lag),
exact circle geometry (for the contour-error estimate), and the uncoupled P + FFW loops
of :func:`oga.model.response.simulate` under the same load.
"""

from __future__ import annotations

from pathlib import Path

import control
import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.model.contour import contour_error_of
from oga.controllers import smc_dob_ccc
from oga.controllers.base import score
from oga.defaults import TOL_M
from oga.errors import OptionError, TuneError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.pipeline import plan_toolpath
from oga.search.ranges import gain_ranges
from oga.model.response import simulate
from oga.verify.replay import command_ratios

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")


def _plan(name):
    return plan_toolpath(load_toolpath(DATA / name), UCP, feed_m_s=None, tol_m=TOL_M)


def _base(best):
    """The baseline parameters (P + FFW of the other axes) from the best fixed gains."""
    return {"kp_base_1_s": best.kp["x"] * KP_SI_PER_M_MIN_PER_MM, "kf_base": best.kf["x"]}


@pytest.fixture(scope="module")
def circle():
    sp = _plan("circle_r50_f3000.ngc")
    return sp, gain_ranges(sp, UCP).best_fixed


@pytest.fixture(scope="module", params=["circle_r50_f3000.ngc", "reference_xz.ngc"])
def path(request):
    sp = _plan(request.param)
    return sp, gain_ranges(sp, UCP).best_fixed


def test_unknown_parameter_raises(circle):
    sp, best = circle
    with pytest.raises(OptionError, match="switching_gain"):
        smc_dob_ccc.run(sp, UCP, tune=False, switching_gain=1.0, **_base(best))


def test_velocity_lag_is_the_63_percent_rise_of_the_velocity_loop():
    cas = UCP.axis("x").cascade
    s = control.tf("s")
    pi = cas.kv_n_s_m * (1 + 1 / (cas.tn_s * s))
    loop = control.feedback(pi / (cas.force_lag_s * s + 1) / (cas.mass_kg * s + cas.viscous_n_s_m))
    t = np.linspace(0.0, 0.03, 30001)
    v = control.step_response(loop, T=t).outputs
    t63 = np.interp(1 - np.exp(-1), v[: np.argmax(v)], t[: np.argmax(v)])
    # the kernel's PI integrates by forward Euler over 125 us sub-steps: a few percent
    assert smc_dob_ccc.velocity_lag_s(UCP, "x") == pytest.approx(t63, rel=0.05)


def test_contour_error_estimate_against_exact_circle_geometry():
    """Second-order Yeh-Hsu estimate: error O(|e|^3 / R^2), far below the tangent estimate."""
    rng = np.random.default_rng(3)
    radius = 0.05
    worst_2, worst_1 = 0.0, 0.0
    for _ in range(200):
        phi = rng.uniform(0, 2 * np.pi)
        pd = radius * np.array([np.cos(phi), np.sin(phi)])
        tangent = np.array([-np.sin(phi), np.cos(phi)])  # counter-clockwise: kappa = 1/R
        e = rng.uniform(-50e-6, 50e-6, 2)
        p = pd - e
        exact = np.hypot(*p) - radius  # the path lies this far from p toward the centre (+n)
        est = smc_dob_ccc.contour_error_estimate(e[0], e[1], tangent[0], tangent[1], 1 / radius)
        first = smc_dob_ccc.contour_error_estimate(e[0], e[1], tangent[0], tangent[1], 0.0)
        worst_2 = max(worst_2, abs(est - exact))
        worst_1 = max(worst_1, abs(first - exact))
    assert worst_2 < 1e-10
    assert worst_1 > 100 * worst_2


def _load_figures(sp, run):
    """x tracking error RMS and max (m), total variation of x's command (m/s)."""
    e = sp.pos[:, 0] - run.pos[:, 0]
    tv = float(np.abs(np.diff(run.u[:, 0])).sum())
    return float(np.sqrt(np.mean(e * e))), float(np.abs(e).max()), tv


def test_claim_observer_needs_a_smaller_switching_gain(circle):
    """Paper: with the observer, a small switching gain gives the error a large one needs
    without it, with far less chattering. Load: 2000 N on x during the middle third."""
    sp, best = circle
    n = len(sp)
    load = np.zeros((n, 3))
    load[n // 3 : 2 * n // 3, 0] = 2000.0
    common = dict(tune=False, load_n=load, ccc=False, **_base(best))
    k1, k2 = 0.5, 5.0
    no_k1 = _load_figures(sp, smc_dob_ccc.run(sp, UCP, dob=False, k_switch_m_s2=k1, **common))
    no_k2 = _load_figures(sp, smc_dob_ccc.run(sp, UCP, dob=False, k_switch_m_s2=k2, **common))
    dob_k1 = _load_figures(sp, smc_dob_ccc.run(sp, UCP, dob=True, k_switch_m_s2=k1, **common))
    # for scale: the tracking error of P + FFW at the best fixed gains (unloaded: simulate
    # takes no load)
    ref = simulate(sp, UCP, best.kp["x"], best.kf["x"])
    ref_rms = float(np.sqrt(np.mean((sp.pos[:, 0] - ref.pos[:, 0]) ** 2)))
    print(f"\nx tracking error RMS / max (m), total variation of u (m/s): "
          f"no DOB k={k1}: {no_k1}; no DOB k={k2}: {no_k2}; DOB k={k1}: {dob_k1}; "
          f"P+FFW unloaded RMS {ref_rms:.3g}")
    assert dob_k1[0] < no_k2[0] < no_k1[0]  # RMS: DOB at k1 beats no DOB at k2 > k1
    assert dob_k1[2] < no_k2[2] / 10  # and chatters far less
    assert no_k2[2] > 50 * no_k1[2]  # the large gain is what chatters without DOB
    # the load step's peak is not removed as well: the observer needs time to converge
    assert no_k2[1] < dob_k1[1] < no_k1[1]
    assert dob_k1[0] < ref_rms / 5


def test_cross_coupling_lowers_the_contour_error(circle):
    sp, best = circle
    figures = {}
    for ccc in (False, True):
        run = smc_dob_ccc.run(sp, UCP, tune=False, ccc=ccc, **_base(best))
        figures[ccc] = score(sp, UCP, run.pos, run.u).mse_ce_m2
    print(f"\ncircle MSE(CE) m^2: SMC+DOB {figures[False]:.3g}, with CCC {figures[True]:.3g}, "
          f"best fixed {best.mse_ce_m2:.3g}")
    assert figures[True] < 0.7 * figures[False]
    # but it does not beat the best fixed P + FFW gains on our plant
    assert figures[True] > best.mse_ce_m2


def test_untuned_breaks_the_jerk_limit_and_tuning_says_why(path):
    sp, best = path
    run = smc_dob_ccc.run(sp, UCP, tune=False, **_base(best))
    s = score(sp, UCP, run.pos, run.u)
    assert set(smc_dob_ccc.PARAMETERS) <= set(run.parameters)
    ce = np.abs(contour_error_of(sp, run.pos))[~sp.rapid]
    print(f"\n{sp.source}: MSE {s.mse_ce_m2:.3g} m^2 = {s.mse_ce_m2 / best.mse_ce_m2:.2f} x best "
          f"fixed, RMS {np.sqrt(s.mse_ce_m2):.3g} m, max {ce.max():.3g} m, ratios "
          f"{np.round(s.command_ratios.max(axis=0), 2)}")
    assert not s.limits_ok and s.command_ratios[:, 2].max() > 2.0
    # independent cause: the model's acceleration feed-forward alone, vd + T ad
    lag = run.parameters["lag_s"]["x"]
    alone = command_ratios(np.asarray(sp.vel + lag * sp.acc), sp, UCP)
    assert alone[:, 2].max() > 2.0
    with pytest.raises(TuneError, match="jerk limit"):
        smc_dob_ccc.run(sp, UCP, tune=True, **_base(best))
