"""Forward-mode derivatives of the simulation, checked by central finite differences of ``run``."""

from __future__ import annotations

import numpy as np
import pytest

from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.model.simulate import (
    axis_params,
    friction_command_m_s,
    friction_nonlinear,
    rest_state,
    run,
)
from oga.model.tangent import friction_slope, run_tangent

UCP = load_machine("ucp710")
MCV = load_machine("mcv-op")
TE = UCP.te
N = 400


def _own_dead_time(machine, axis, d):
    """``machine`` with ``axis``'s own dead time ``d`` (samples, fractional allowed)."""
    ax = machine.axes[axis].model_copy(update={"dead_time_samples": d})
    return machine.model_copy(update={"axes": {**machine.axes, axis: ax}})


AXES = pytest.mark.parametrize(
    "machine, axis", [(UCP, "x"), (UCP, "z"), (MCV, "x"), (_own_dead_time(UCP, "x", 2.4), "x"),
                      (_own_dead_time(UCP, "z", 0.7), "z"), (_own_dead_time(MCV, "x", 1.3), "x")],
    ids=["cascade-x", "cascade-z", "arx", "cascade-x-dead-2.4", "cascade-z-dead-0.7",
         "arx-dead-1.3"])


def _reversal_case():
    """Setpoints through a reversal (friction band, sub-steps) and time-varying gains."""
    t = np.arange(N) * TE
    pd = 2e-3 * np.sin(2 * np.pi * 1.5 * t)  # reverses at 167 ms
    vd = np.gradient(pd, TE)
    kp = (3.0 + 0.3 * np.sin(7 * t)) * KP_SI_PER_M_MIN_PER_MM
    kf = 0.8 + 0.1 * np.cos(5 * t)
    # six smooth bumps, Kp and Kf alternately, starting at 0, 50 and 200 samples
    start = np.array([0, 0, 50, 50, 200, 200])
    dkp = np.zeros((N, start.size))
    dkf = np.zeros((N, start.size))
    for d, s in enumerate(start):
        bump = np.exp(-(((t - (s + 40) * TE) / 0.02) ** 2)) * (t >= s * TE)
        if d % 2 == 0:
            dkp[:, d] = bump * KP_SI_PER_M_MIN_PER_MM
        else:
            dkf[:, d] = bump
    return pd, vd, kp, kf, dkp, dkf, start


@AXES
def test_nominal_is_run_to_the_last_bit(machine, axis):
    prm = axis_params(machine, axis)
    pd, vd, kp, kf, dkp, dkf, start = _reversal_case()
    s_run, s_tan = rest_state(prm, pd[0]), rest_state(prm, pd[0])
    p_run, u_run, p_tan, u_tan = (np.empty(N) for _ in range(4))
    run(s_run, prm, pd, vd, kp, kf, p_run, u_run)
    sp, su = np.empty((N, start.size)), np.empty((N, start.size))
    run_tangent(s_tan, prm, (pd, vd, kp, kf, dkp, dkf), start, (p_tan, u_tan, sp, su))
    assert np.array_equal(p_run, p_tan) and np.array_equal(u_run, u_tan)
    assert np.array_equal(s_run, s_tan)  # the state carried to the next call too


@AXES
def test_derivatives_equal_central_differences(machine, axis):
    prm = axis_params(machine, axis)
    pd, vd, kp, kf, dkp, dkf, start = _reversal_case()
    sp, su = np.empty((N, start.size)), np.empty((N, start.size))
    run_tangent(rest_state(prm, pd[0]), prm, (pd, vd, kp, kf, dkp, dkf), start,
                (np.empty(N), np.empty(N), sp, su))
    h = 1e-4
    for d in range(start.size):
        out = []
        for sign in (1.0, -1.0):
            p, u = np.empty(N), np.empty(N)
            run(rest_state(prm, pd[0]), prm, pd, vd, kp + sign * h * dkp[:, d],
                kf + sign * h * dkf[:, d], p, u)
            out.append((p, u))
        fd_p = (out[0][0] - out[1][0]) / (2 * h)
        fd_u = (out[0][1] - out[1][1]) / (2 * h)
        assert np.abs(fd_p).max() > 1e-6  # the direction moves the axis
        np.testing.assert_allclose(sp[:, d], fd_p, rtol=0, atol=1e-6 * np.abs(fd_p).max())
        np.testing.assert_allclose(su[:, d], fd_u, rtol=0, atol=1e-6 * np.abs(fd_u).max())
        assert not sp[: start[d] + 1, d].any()  # zero before the direction starts


def test_directions_superpose_and_scale():
    """The derivative along a combination of directions is that combination of derivatives."""
    prm = axis_params(UCP, "z")
    pd, vd, kp, kf, dkp, dkf, start = _reversal_case()
    sp, su = np.empty((N, start.size)), np.empty((N, start.size))
    run_tangent(rest_state(prm, pd[0]), prm, (pd, vd, kp, kf, dkp, dkf), start,
                (np.empty(N), np.empty(N), sp, su))
    w = np.array([0.5, -2.0, 1.0, 3.0, -1.0, 0.25])
    comb_p, comb_u = np.empty((N, 1)), np.empty((N, 1))
    run_tangent(rest_state(prm, pd[0]), prm, (pd, vd, kp, kf, (dkp @ w)[:, None],
                (dkf @ w)[:, None]), np.zeros(1, dtype=np.int64), (np.empty(N), np.empty(N),
                comb_p, comb_u))
    np.testing.assert_allclose(comb_p[:, 0], sp @ w, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(comb_u[:, 0], su @ w, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("machine, axis, fn", [(UCP, "z", friction_nonlinear),
                                                (MCV, "x", friction_command_m_s)],
                         ids=["cascade", "arx"])
def test_friction_slope_is_the_derivative(machine, axis, fn):
    prm = axis_params(machine, axis)
    for v in np.concatenate([np.linspace(-3e-3, 3e-3, 61), [0.0, 1e-6, -2e-5, 0.05]]):
        h = 1e-9
        fd = (fn(prm, v + h) - fn(prm, v - h)) / (2 * h)
        assert friction_slope(prm, v) == pytest.approx(fd, rel=1e-5, abs=1e-6 * abs(fd) + 1e-9)
