"""The kernel's opt-in linear friction map (``timing.friction_linear_below_m_s``) against
independent references: the sub-steps with the friction's tangent at rest (scipy's
discretisation, the PI in Python), the lifted linear map without friction, the exact kernel
within a stated bound, and every kernel entry point giving the same bits."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import cont2discrete

from feedplan.read import load_toolpath
from feedplan.setpoints import Setpoints
from oga.model.contour import contour_error_of
from oga.defaults import ROBUST_FRICTION_LINEAR_BELOW_M_S
from oga.errors import MachineError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.model.metrics import contour_metrics
from oga.pipeline import plan_toolpath
from oga.search.robust.plants import scenario_set
from oga.model.simulate import (
    _LA,
    _NA,
    _VLIN,
    _linear,
    _linear_guard,
    axis_params,
    drive,
    rest_state,
    run,
    simulate_axis,
    step,
    window,
)
from oga.model.response import simulate
from oga.model.tangent import run_tangent
from oga.verify.replay import command_ratios
from references import ucp710_values, value_differences

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")
V = ROBUST_FRICTION_LINEAR_BELOW_M_S
SCEN = scenario_set(UCP)
#: Low and high corners of every group, and a Monte Carlo plant (all carry the setting).
PLANTS = (SCEN.plants[64], SCEN.plants[-1], SCEN.plants[0])


def _setting(machine, v):
    """``machine`` with ``timing.friction_linear_below_m_s = v`` (None: unset)."""
    timing = machine.timing.model_copy(update={"friction_linear_below_m_s": v})
    return machine.model_copy(update={"timing": timing})


def _reference_substeps(machine, axis, z, u, load):
    """One Te of sub-steps with ``F_n,j = (Fs / eps) v_j`` held over each, from ``z = (p, v, F,
    I)``: the state after, and the velocities and force commands at the sub-step starts."""
    cas = machine.axes[axis].cascade
    n_sub = machine.timing.substeps
    h = machine.timing.te_s / n_sub
    m, tau = cas.mass_kg, cas.force_lag_s
    a = np.array([[0, 1, 0], [0, -cas.viscous_n_s_m / m, 1 / m], [0, 0, -1 / tau]])
    b = np.array([[0, 0], [0, -1 / m], [1 / tau, 0]])
    ad, bd, *_ = cont2discrete((a, b, np.eye(3), np.zeros((3, 2))), h, "zoh")
    c = cas.static_n / cas.friction_smoothing_m_s
    x = np.array(z[:3], dtype=float)
    i = z[3]
    vs, fcs = [], []
    for _ in range(n_sub):
        v = x[1]
        f_cmd = cas.kv_n_s_m * (u - v + i / cas.tn_s)
        vs.append(v)
        fcs.append(f_cmd)
        i += h * (u - v)
        x = ad @ x + bd @ np.array([f_cmd, c * v + load])
    return (x[0], x[1], x[2], i), np.array(vs), np.array(fcs)


@pytest.mark.parametrize("plant", PLANTS[:2], ids=["corner-lo", "corner-hi"])
@pytest.mark.parametrize("axis", ["x", "z"])
def test_the_map_is_the_substeps_with_the_tangent_friction_and_its_guard_holds(plant, axis):
    prm = axis_params(plant, axis)
    flim = plant.axes[axis].cascade.force_limit_n
    rng = np.random.default_rng(5)
    taken = 0
    for k in range(400):
        scale = 10.0 ** rng.uniform(-3, 1)  # around the guard's edge, on both sides
        v, u = rng.normal(0, 3e-7, 2) * scale
        f = rng.normal(0, 0.5) * scale
        i = rng.normal(0, 5e-8) * scale
        load = rng.normal(0, 0.3) * scale if k % 2 else 0.0
        p = 0.1
        ref, vs, fcs = _reference_substeps(plant, axis, (p, v, f, i), u, load)
        got = _linear(prm, p, v, f, i, u, load)
        # to rounding (scipy's and oga's discretisations differ by some 1e-16 relative)
        size = (abs(v) + abs(u) + abs(f) / 1e5 + abs(i) * 100 + abs(load) / 1e5)
        assert abs(got[0] - ref[0]) <= 1e-12 * size * 1e-3 + 1e-16
        assert got[1] == pytest.approx(ref[1], rel=1e-9, abs=1e-12 * size)
        assert got[2] == pytest.approx(ref[2], rel=1e-9, abs=1e-9 * size * 1e5)
        assert got[3] == pytest.approx(ref[3], rel=1e-9, abs=1e-12 * size * 1e-2)
        if _linear_guard(prm, v, f, i, u, load):
            taken += 1
            assert np.max(np.abs(vs)) < V and np.max(np.abs(fcs)) < flim
    assert 50 < taken < 350  # both sides exercised


def test_without_coulomb_and_static_friction_the_map_is_the_lifted_linear_map():
    data = UCP.model_dump(mode="json", exclude_none=True)
    for ax in data["axes"].values():
        ax["cascade"].update(coulomb_n=0.0, static_n=0.0)
    data["timing"]["friction_linear_below_m_s"] = V
    m = machine_from_dict(data)
    for a in "xyz":
        prm = axis_params(m, a)
        # [u, load] columns = the lifted map's [u, F_n] (a load enters where F_n does)
        assert np.array_equal(prm[_NA:_NA + 24], prm[_LA:_LA + 24])


def test_unset_it_changes_nothing_and_its_range_is_checked():
    # ucp710's values as stored before the setting existed (an unset setting leaves them, and
    # so every table's digest, as they were)
    assert value_differences(UCP.model_dump(mode="json", exclude_none=True), ucp710_values()) == []
    assert UCP.digest() == machine_from_dict(ucp710_values()).digest()
    assert "friction_linear_below_m_s" not in UCP.model_dump(exclude_none=True)["timing"]
    assert not np.any(axis_params(UCP, "x")[_VLIN:])
    assert axis_params(PLANTS[0], "x")[_VLIN] == V
    data = UCP.model_dump(mode="json", exclude_none=True)
    data["timing"]["friction_linear_below_m_s"] = 0.0
    with pytest.raises(MachineError, match="friction_linear_below_m_s"):
        machine_from_dict(data)


def test_only_where_the_friction_is_linear():
    """Far above the smoothing velocity the tangent is not the friction (tanh saturates): a
    machine file may not ask for it, and the scenario plants of an axis with little smoothing
    take the share of it where it holds."""
    data = UCP.model_dump(mode="json", exclude_none=True)
    data["timing"]["friction_linear_below_m_s"] = 2e-6  # above 0.01 of x's 1e-4 m/s
    with pytest.raises(MachineError, match=r"axes\.x\.cascade\.friction_smoothing_m_s"):
        machine_from_dict(data)
    data["timing"]["friction_linear_below_m_s"] = 1e-6  # 0.01 of it: within
    assert machine_from_dict(data).timing.friction_linear_below_m_s == 1e-6
    sharp = UCP.model_dump(mode="json", exclude_none=True)
    sharp["axes"]["z"]["cascade"]["friction_smoothing_m_s"] = 1e-6
    plants = scenario_set(machine_from_dict(sharp), n=2, corners=False).plants
    assert all(p.timing.friction_linear_below_m_s == pytest.approx(1e-8, rel=1e-12)
               for p in plants)
    assert {p.timing.friction_linear_below_m_s for p in PLANTS} == {V}
    slow = UCP.model_dump(mode="json", exclude_none=True)
    slow["axes"]["x"]["cascade"]["stribeck_m_s"] = 5e-5
    slow["timing"]["friction_linear_below_m_s"] = 1e-6
    with pytest.raises(MachineError, match=r"axes\.x\.cascade\.stribeck_m_s"):
        machine_from_dict(slow)
    del slow["timing"]["friction_linear_below_m_s"]
    plant = scenario_set(machine_from_dict(slow), n=1, corners=False).plants[0]
    least = min(min(ax.cascade.friction_smoothing_m_s, ax.cascade.stribeck_m_s)
                for ax in plant.axes.values())  # the plant's own (drawn) Stribeck velocities
    assert least < 1e-4 and plant.timing.friction_linear_below_m_s == 0.01 * least


def _dwell_case(n_move=400, n_dwell=3000):
    """A move, a dwell (the axis creeps to a stop: the map's periods), a move back."""
    te = UCP.te
    t = np.arange(n_move) * te
    dur = n_move * te * 0.6
    ph = np.clip(t / dur, 0.0, 1.0) * math.pi
    pd1 = 0.002 * 0.5 * (1.0 - np.cos(ph))
    vd1 = np.where(t < dur, 0.002 * 0.5 * math.pi / dur * np.sin(ph), 0.0)
    pd = np.concatenate([pd1, np.full(n_dwell, pd1[-1]), pd1[-1] - pd1])
    vd = np.concatenate([vd1, np.zeros(n_dwell), -vd1])
    return pd, vd


@pytest.mark.parametrize("axis", ["x", "z"])
def test_every_entry_point_takes_it_with_the_same_bits(axis):
    plant = PLANTS[0]
    prm = axis_params(plant, axis)
    pd, vd = _dwell_case()
    n = pd.size
    kp = np.linspace(2.0, 3.0, n) * KP_SI_PER_M_MIN_PER_MM
    kf = np.full(n, 0.8)
    # step by step (drive -> _advance), counting the periods the map takes
    state = rest_state(prm, pd[0])
    ref_p, ref_u, taken = np.empty(n), np.empty(n), np.zeros(n, dtype=bool)
    for k in range(n):
        ref_p[k] = state[0]
        ud = state[4 + int(prm[1]) - 1]  # the command applied during this period
        taken[k] = _linear_guard(prm, state[1], state[2], state[3], ud, 0.0)
        ref_u[k] = step(state, prm, pd[k], vd[k], kp[k], kf[k])
    assert taken[400:3400].mean() > 0.5 and not taken[100:240].any()  # not while moving
    exact = simulate_axis(axis_params(_setting(plant, None), axis), pd[0], pd, vd, kp, kf)
    assert not np.array_equal(exact[0], ref_p)  # the map was taken: not the exact kernel's bits
    # run
    p, u = np.empty(n), np.empty(n)
    run(rest_state(prm, pd[0]), prm, pd, vd, kp, kf, p, u)
    assert np.array_equal(p, ref_p) and np.array_equal(u, ref_u)
    # run_axes (simulate), this axis alone moving
    c = "xyz".index(axis)
    pos = np.zeros((n, 3))
    vel = np.zeros((n, 3))
    pos[:, c], vel[:, c] = pd, vd
    sp = Setpoints(dt=UCP.te, s=np.arange(n) * 1e-6, pos=pos, vel=vel, acc=np.zeros((n, 3)),
                   jerk=np.zeros((n, 3)), block=np.ones(n, int), rapid=np.zeros(n, bool))
    kp_t = np.full((n, 3), 2.0)
    kp_t[:, c] = kp / KP_SI_PER_M_MIN_PER_MM
    sim = simulate(sp, plant, kp_t, np.full((n, 3), 0.8))
    assert np.array_equal(sim.pos[:, c], ref_p) and np.array_equal(sim.u[:, c], ref_u)
    # window from inside the dwell, constant gains
    k0, nw = 1000, 1500
    kc = np.full(n, kp[k0])
    p_c, u_c = np.empty(n), np.empty(n)
    s0 = rest_state(prm, pd[0])
    run(s0, prm, pd[:k0], vd[:k0], kc[:k0], kf[:k0], p_c[:k0], u_c[:k0])
    out = np.empty(nw)
    window(s0, prm, pd, vd, k0, nw, kp[k0], 0.8, out)
    run(s0, prm, pd[k0:], vd[k0:], kc[k0:], kf[k0:], p_c[k0:], u_c[k0:])
    assert np.array_equal(out, p_c[k0 + 1:k0 + 1 + nw])
    # run_tangent (the full-mode search's sensitivities)
    start = np.zeros(1, dtype=np.int64)
    sp_t, su_t = np.empty((n, 1)), np.empty((n, 1))
    p_t, u_t = np.empty(n), np.empty(n)
    run_tangent(rest_state(prm, pd[0]), prm, (pd, vd, kp, kf,
                np.full((n, 1), KP_SI_PER_M_MIN_PER_MM), np.zeros((n, 1))), start,
                (p_t, u_t, sp_t, su_t))
    assert np.array_equal(p_t, ref_p) and np.array_equal(u_t, ref_u)
    # and its derivative is the central difference of run (the map is linear)
    h = 1e-4
    pp, pm, uu = np.empty(n), np.empty(n), np.empty(n)
    run(rest_state(prm, pd[0]), prm, pd, vd, kp + h * KP_SI_PER_M_MIN_PER_MM, kf, pp, uu)
    run(rest_state(prm, pd[0]), prm, pd, vd, kp - h * KP_SI_PER_M_MIN_PER_MM, kf, pm, uu)
    fd = (pp - pm) / (2 * h)
    assert np.max(np.abs(sp_t[:, 0] - fd)) <= 1e-3 * np.max(np.abs(fd))


def test_a_load_takes_it_as_the_substeps_would():
    plant = PLANTS[1]
    prm = axis_params(plant, "x")
    state = rest_state(prm, 0.0)
    state[1], state[2], state[3] = 2e-8, 0.5, 1e-9
    ud = state[4 + int(prm[1]) - 1]
    assert _linear_guard(prm, state[1], state[2], state[3], ud, 0.2)
    ref, _, _ = _reference_substeps(plant, "x", tuple(state[:4]), ud, 0.2)
    drive(state, prm, 0.0, 0.2)
    np.testing.assert_allclose(state[:4], ref, rtol=1e-9, atol=1e-15)


#: Stated bound of the approximation against the exact kernel, on ucp710's scenario plants
#: (measured over all 96 plants, three fixed gain pairs, reference_xz and cncjs_toolpath:
#: |dp| 8.5e-13 m, |du| 2.8e-11 m/s, MSE(CE) 7.9e-10, eq. 2 ratios 3.3e-10, following error
#: 2.0e-10 relative; the friction itself is within 7e-5 N of its tangent there).
BOUND = {"dp_m": 1e-11, "du_m_s": 1e-9, "rel": 1e-8}


@pytest.mark.parametrize("program", ["reference_xz.ngc", "cncjs_toolpath.nc"])
def test_within_the_stated_bound_of_the_exact_kernel(program):
    sp = plan_toolpath(load_toolpath(DATA / program), UCP, feed_m_s=None, tol_m=2e-5)
    n = len(sp)
    moving = list(sp.moving_axes)
    for plant, (kp, kf) in zip(PLANTS, ((2.0, 0.7), (4.0, 1.0), (1.0, 0.0))):
        kp_t, kf_t = np.full((n, 3), kp), np.full((n, 3), kf)
        runs = []
        for m in (plant, _setting(plant, None)):
            sim = simulate(sp, m, kp_t, kf_t)
            met = contour_metrics(contour_error_of(sp, sim.pos), sp.pos, sim.pos, ~sp.rapid)
            runs.append((sim, met, command_ratios(sim.u, sp, m)[moving]))
        (fast, mf, cf), (exact, me, ce) = runs
        assert not np.array_equal(fast.pos, exact.pos)  # the map is taken
        assert np.max(np.abs(fast.pos - exact.pos)) <= BOUND["dp_m"]
        assert np.max(np.abs(fast.u - exact.u)) <= BOUND["du_m_s"]
        assert mf.mse_m2 == pytest.approx(me.mse_m2, rel=BOUND["rel"])
        np.testing.assert_allclose(cf, ce, rtol=BOUND["rel"])
        np.testing.assert_allclose(np.array(mf.track_max_m)[moving],
                                   np.array(me.track_max_m)[moving], rtol=BOUND["rel"])
