"""The compiled axis kernel against independent references (linear model, analytic motion)."""

import math

import numpy as np
import pytest
from scipy.signal import cont2discrete

from feedplan.setpoints import Setpoints
from oga.errors import MachineError, OptionError
from oga.model.linear import lifted_axis
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.model.response import simulate
from oga.model.simulate import (
    _lifted_guard,
    axis_params,
    friction_nonlinear,
    rest_state,
    run,
    simulate_axis,
    state_size,
    step,
    window,
)
from oga.model.response import simulate

UCP = load_machine("ucp710")
MCV = load_machine("mcv-op")  # ARX axes (tests/test_arx.py has their own references)
TE = UCP.te
#: One axis of each kind, for the properties every axis has.
BOTH_KINDS = pytest.mark.parametrize("machine, axis", [(UCP, "z"), (MCV, "x")],
                                     ids=["cascade", "arx"])


def _machine(axis_updates=None, **timing):
    """ucp710 with some cascade fields changed on every axis."""
    data = UCP.model_dump()
    for ax in data["axes"].values():
        ax["cascade"].update(axis_updates or {})
    data["timing"].update(timing)
    return machine_from_dict(data)


LINEAR = _machine({"coulomb_n": 0.0, "static_n": 0.0, "force_limit_n": 1e12})


def _smooth_move(n, dist, p0=0.0):
    """A 1 - cos position move over n samples and its exact velocity."""
    t = np.arange(n) * TE
    dur = n * TE * 0.6
    ph = np.clip(t / dur, 0.0, 1.0) * math.pi
    pd = p0 + dist * 0.5 * (1.0 - np.cos(ph))
    vd = np.where(t < dur, dist * 0.5 * math.pi / dur * np.sin(ph), 0.0)
    return pd, vd


def _reference_lifted(machine, axis):
    """The linear cascade lifted over Te, built independently of oga.model.linear."""
    cas = machine.axes[axis].cascade
    n_sub = machine.timing.substeps
    h = machine.timing.te_s / n_sub
    m, b, tau, kv, tn = cas.mass_kg, cas.viscous_n_s_m, cas.force_lag_s, cas.kv_n_s_m, cas.tn_s
    # state [p, v, F, I]; the force command is held over h (ZOH), the PI integral is
    # forward Euler: with input u, F_cmd = kv (u - v + I / tn), I+ = I + h (u - v)
    ac = np.array([[0, 1, 0], [0, -b / m, 1 / m], [0, 0, -1 / tau]], dtype=float)
    bc = np.array([[0.0], [0.0], [1 / tau]])
    ad, bd, *_ = cont2discrete((ac, bc, np.eye(3), np.zeros((3, 1))), h, method="zoh")
    k_row = kv * np.array([[0.0, -1.0, 0.0, 1.0 / tn]])  # F_cmd = k_row @ z + kv u
    a_sub = np.block([[ad, np.zeros((3, 1))], [np.array([[0.0, -h, 0.0, 1.0]])]])
    a_sub[:3] += bd @ k_row
    b_sub = np.vstack([bd * kv, [[h]]])
    a_te = np.linalg.matrix_power(a_sub, n_sub)
    b_te = sum(np.linalg.matrix_power(a_sub, j) @ b_sub for j in range(n_sub))
    return a_te, b_te


def _reference_run(a_te, b_te, dead, p0, pd, vd, kp_si, kf):
    """Sample-by-sample closed position loop of the lifted linear model."""
    z = np.array([p0, 0.0, 0.0, 0.0])
    line = [0.0] * dead
    p_out, u_out = [], []
    for k in range(pd.size):
        p_out.append(z[0])
        u = kp_si[k] * (pd[k] - z[0]) + kf[k] * vd[k]
        u_out.append(u)
        line.insert(0, u)
        z = a_te @ z + b_te[:, 0] * line.pop()
    return np.array(p_out), np.array(u_out)


@pytest.mark.parametrize("lifted", [True, False])
@pytest.mark.parametrize("axis", ["x", "z"])
def test_linear_case_equals_the_lifted_linear_model(axis, lifted):
    n = 2000
    pd, vd = _smooth_move(n, 0.02, p0=0.1)
    kp_si = np.where(np.arange(n) < n // 2, 2.0, 3.0) * KP_SI_PER_M_MIN_PER_MM
    kf = np.where(np.arange(n) < n // 3, 0.9, 0.5)
    a_te, b_te = _reference_lifted(LINEAR, axis)
    p_ref, u_ref = _reference_run(a_te, b_te, 2, 0.1, pd, vd, kp_si, kf)
    p_act, u = simulate_axis(axis_params(LINEAR, axis, lifted), 0.1, pd, vd, kp_si, kf)
    # relative to the motion (0.02 m) and to the commands
    assert np.max(np.abs(p_act - p_ref)) <= 1e-9 * 0.02
    assert np.max(np.abs(u - u_ref)) <= 1e-9 * np.max(np.abs(u_ref))
    # oga.model.linear builds the same lifted model
    a, b, _, _ = lifted_axis(LINEAR, axis)
    np.testing.assert_allclose(a, a_te, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b, b_te, rtol=1e-9, atol=1e-15)


def test_linear_case_without_dead_time():
    machine = _machine({"coulomb_n": 0.0, "static_n": 0.0, "force_limit_n": 1e12},
                       dead_time_samples=0)
    n = 800
    pd, vd = _smooth_move(n, -0.01)
    kp_si = np.full(n, 2.5 * KP_SI_PER_M_MIN_PER_MM)
    kf = np.full(n, 0.7)
    a_te, b_te = _reference_lifted(machine, "x")
    p_ref, _ = _reference_run(a_te, b_te, 0, 0.0, pd, vd, kp_si, kf)
    for lifted in (True, False):
        p_act, _ = simulate_axis(axis_params(machine, "x", lifted), 0.0, pd, vd, kp_si, kf)
        assert np.max(np.abs(p_act - p_ref)) <= 1e-9 * 0.01


@pytest.mark.parametrize("axis", ["x", "z"])
def test_lifted_steps_equal_the_substeps_on_the_nonlinear_model(axis):
    # reversals (friction), then a 20 mm jump of the setpoint (force limit)
    n = 4000
    t = np.arange(n) * TE
    pd = 0.01 * np.sin(2 * math.pi * t) + np.where(t > 3.0, 0.02, 0.0)
    vd = 0.02 * math.pi * np.cos(2 * math.pi * t)
    kp, kf = 2.5 * KP_SI_PER_M_MIN_PER_MM, 0.8
    fast = simulate_axis(axis_params(UCP, axis, True), pd[0], pd, vd, kp, kf)
    ref = simulate_axis(axis_params(UCP, axis, False), pd[0], pd, vd, kp, kf)
    assert np.max(np.abs(fast[0] - ref[0])) <= 1e-12 * 0.03
    assert np.max(np.abs(fast[1] - ref[1])) <= 1e-12 * np.max(np.abs(ref[1]))
    # the lifted step is taken at speed, never near a reversal nor at the limit
    params = axis_params(UCP, axis)
    state = rest_state(params, pd[0])
    taken, speed, force = [], [], []
    for k in range(n):
        ud = state[5]  # u_{k-2}, the command applied during this period
        fn = friction_nonlinear(params, state[1])
        taken.append(_lifted_guard(params, state[1], state[2], state[3], ud, fn))
        speed.append(abs(state[1]))
        step(state, params, pd[k], vd[k], kp, kf)
        force.append(abs(state[2]))
    taken, speed, force = np.array(taken), np.array(speed), np.array(force)
    assert 0.6 < taken[:3000].mean() < 0.99
    assert not np.any(taken & (speed < 2e-3))
    saturated = np.flatnonzero(force > 0.99 * UCP.axes[axis].cascade.force_limit_n)
    assert saturated.size > 0 and not np.any(taken[saturated])


@pytest.mark.parametrize("axis", ["x", "z"])
@pytest.mark.parametrize("v", [0.05, -0.2])
def test_steady_lag_is_one_minus_kf_v_over_kp_despite_friction(axis, v):
    kp, kf = 2.0 * KP_SI_PER_M_MIN_PER_MM, 0.6
    n = 3000
    pd = 0.3 + v * np.arange(n) * TE
    vd = np.full(n, v)
    params = axis_params(UCP, axis)
    state = rest_state(params, 0.3)
    p_act, u = np.empty(n), np.empty(n)
    run(state, params, pd, vd, np.full(n, kp), np.full(n, kf), p_act, u)
    lag = (1.0 - kf) * v / kp
    np.testing.assert_allclose(pd[-500:] - p_act[-500:], lag, rtol=1e-7)
    # the velocity PI's integral removes friction from the steady velocity: the axis
    # moves at the commanded velocity and its force balances Coulomb + viscous friction
    cas = UCP.axes[axis].cascade
    assert state[1] == pytest.approx(v, rel=1e-9)
    np.testing.assert_allclose(u[-500:], v, rtol=1e-9)
    assert state[2] == pytest.approx(math.copysign(cas.coulomb_n, v) + cas.viscous_n_s_m * v,
                                     rel=1e-7)


@pytest.mark.parametrize("axis", ["x", "z"])
def test_friction_opposes_motion(axis):
    params = axis_params(UCP, axis)
    b = UCP.axes[axis].cascade.viscous_n_s_m
    for v in np.concatenate([np.geomspace(1e-7, 1.0, 60), -np.geomspace(1e-7, 1.0, 60)]):
        ffr = friction_nonlinear(params, v) + b * v
        assert math.copysign(1.0, ffr) == math.copysign(1.0, v) and ffr != 0.0
    assert friction_nonlinear(params, 0.0) == 0.0
    # oga.model.machine.Cascade's friction formula, with numpy's tanh and exp
    cas = UCP.axes[axis].cascade
    for v in np.linspace(-0.02, 0.02, 4001):
        s = np.tanh(v / cas.friction_smoothing_m_s)
        design = (cas.coulomb_n + (cas.static_n - cas.coulomb_n)
                  * np.exp(-(v / cas.stribeck_m_s) ** 2)) * s
        assert friction_nonlinear(params, v) == pytest.approx(design, rel=1e-14, abs=1e-13)
    # Stribeck: near zero velocity the friction peaks above Coulomb
    peak = max(friction_nonlinear(params, v) for v in np.geomspace(1e-5, 1e-2, 200))
    assert cas.coulomb_n < peak <= cas.static_n


@pytest.mark.parametrize("v0", [0.05, -0.05])
def test_coasting_axis_decelerates_as_coulomb_plus_viscous_predicts(v0):
    # no drive force (negligible velocity-loop gain): m dv/dt = -Fc sign(v) - B v
    machine = _machine({"kv_n_s_m": 1e-9})
    cas = machine.axes["x"].cascade
    m, fc, b = cas.mass_kg, cas.coulomb_n, cas.viscous_n_s_m
    params = axis_params(machine, "x")
    state = rest_state(params, 0.0)
    state[1] = v0
    vel = []
    for _ in range(1000):
        step(state, params, 0.0, 0.0, 0.0, 0.0)
        vel.append(state[1])
    vel = np.array(vel)
    t = np.arange(1, 1001) * TE
    s = math.copysign(1.0, v0)
    analytic = s * ((abs(v0) + fc / b) * np.exp(-b * t / m) - fc / b)
    fast = s * analytic > 0.01  # still moving, Stribeck and smoothing exactly absent
    assert fast.sum() > 200
    np.testing.assert_allclose(vel[fast], analytic[fast], rtol=1e-8)
    # it slows down monotonically, stops, and friction does not push it back
    moving = np.abs(vel) > 1e-6
    assert np.all(np.diff(np.abs(vel[moving])) < 0)
    assert np.all(np.abs(vel[-300:]) < 1e-6)


def _step_response(params, target, n):
    """Positions and forces at every sample after a position step from rest at 0."""
    state = rest_state(params, 0.0)
    pos, force = np.empty(n), np.empty(n)
    for k in range(n):
        step(state, params, target, 0.0, 3.0 * KP_SI_PER_M_MIN_PER_MM, 0.0)
        pos[k], force[k] = state[0], state[2]
    return pos, force


def test_force_limit_saturates_and_the_axis_still_settles():
    cas = UCP.axes["x"].cascade
    flim = cas.force_limit_n
    target = 0.02  # a 20 mm step: the command asks far more than the limit
    wide = axis_params(_machine({"force_limit_n": 1e9}), "x")
    _, force_wide = _step_response(wide, target, 1500)
    pos, force = _step_response(axis_params(UCP, "x"), target, 1500)
    assert np.max(np.abs(force_wide)) > 3 * flim  # without the limit, far beyond it
    assert flim * 0.99 < np.max(np.abs(force)) <= flim  # with it, up to the limit only
    # |m a| <= limit + friction (Stribeck peak + viscous at under 1 m/s)
    assert np.max(np.abs(np.diff(pos))) / TE < 0.9
    acc = np.diff(pos, 2) / TE**2
    assert np.max(np.abs(acc)) <= (flim + cas.static_n + cas.viscous_n_s_m) / cas.mass_kg
    # anti-windup: the axis settles on the target without a runaway overshoot
    assert np.max(pos) < target * 1.2
    assert pos[-1] == pytest.approx(target, abs=1e-7)


@BOTH_KINDS
def test_window_continues_a_run_exactly_and_leaves_the_state(machine, axis):
    params = axis_params(machine, axis)
    n = 1500
    t = np.arange(n) * TE
    pd = 0.01 * np.sin(2 * math.pi * 2.0 * t)  # reverses: friction at work
    vd = 0.01 * 2 * math.pi * 2.0 * np.cos(2 * math.pi * 2.0 * t)
    kp = np.linspace(1.5, 2.7, n) * KP_SI_PER_M_MIN_PER_MM
    kf = np.linspace(0.9, 0.6, n)
    k0, nw = 240, 50  # near a reversal (t = 0.25 s)
    state = rest_state(params, pd[0])
    p, u = np.empty(k0), np.empty(k0)
    run(state, params, pd[:k0], vd[:k0], kp[:k0], kf[:k0], p, u)
    saved = state.copy()
    out = np.full(nw + 5, np.nan)
    window(state, params, pd, vd, k0, nw, 2.2 * KP_SI_PER_M_MIN_PER_MM, 0.8, out)
    assert np.array_equal(state, saved)
    assert np.all(np.isnan(out[nw:]))
    tail_p, tail_u = np.empty(nw + 1), np.empty(nw + 1)
    run(state, params, pd[k0:k0 + nw + 1], vd[k0:k0 + nw + 1],
        np.full(nw + 1, 2.2 * KP_SI_PER_M_MIN_PER_MM), np.full(nw + 1, 0.8), tail_p, tail_u)
    assert np.array_equal(out[:nw], tail_p[1:])


@BOTH_KINDS
def test_run_in_pieces_equals_one_run(machine, axis):
    # the state (dead-time line / ARX histories included) carries over between runs,
    # also runs shorter than the dead time
    params = axis_params(machine, axis)
    n = 400
    pd, vd = _smooth_move(n, 0.01)
    kp = np.full(n, 2.0 * KP_SI_PER_M_MIN_PER_MM)
    kf = np.full(n, 0.9)
    whole_p, whole_u = np.empty(n), np.empty(n)
    whole_state = rest_state(params, 0.0)
    run(whole_state, params, pd, vd, kp, kf, whole_p, whole_u)
    state = rest_state(params, 0.0)
    p, u = np.empty(n), np.empty(n)
    for a, b in [(0, 1), (1, 2), (2, 5), (5, 150), (150, 151), (151, n)]:
        run(state, params, pd[a:b], vd[a:b], kp[a:b], kf[a:b], p[a:b], u[a:b])
    assert np.array_equal(p, whole_p) and np.array_equal(u, whole_u)
    assert np.array_equal(state, whole_state)
    if machine is UCP:
        assert np.array_equal(state[4:], whole_u[[-1, -2]])
    # and sample by sample with step
    state = rest_state(params, 0.0)
    for k in range(n):
        assert state[0] == whole_p[k]
        assert step(state, params, pd[k], vd[k], kp[k], kf[k]) == whole_u[k]
    assert np.array_equal(state, whole_state)



@pytest.mark.parametrize("axis", ["x", "z"])
def test_standstill_shortcut_gives_the_bits_of_step_by_step(axis):
    # a move, a long dwell (the friction-held axis creeps onto the target and after some
    # 13 s reaches a floating-point fixed point, which run and window skip while the
    # command is unchanged), then a move back
    params = axis_params(UCP, axis)
    n_move, n_dwell = 300, 20000
    pd1, vd1 = _smooth_move(n_move, 0.002)
    pd2, vd2 = _smooth_move(n_move, -0.002, p0=pd1[-1])
    pd = np.concatenate([pd1, np.full(n_dwell, pd1[-1]), pd2])
    vd = np.concatenate([vd1, np.zeros(n_dwell), vd2])
    n = pd.size
    kp, kf = 2.5 * KP_SI_PER_M_MIN_PER_MM, 0.7
    ref_p, ref_u = np.empty(n), np.empty(n)
    state = rest_state(params, 0.0)
    states = [state.copy()]
    for k in range(n):
        ref_p[k] = state[0]
        ref_u[k] = step(state, params, pd[k], vd[k], kp, kf)
        states.append(state.copy())
    unchanged = sum(np.array_equal(a, b) for a, b in zip(states[:-1], states[1:]))
    assert unchanged > 3000  # the shortcut is exercised
    p, u = np.empty(n), np.empty(n)
    end = rest_state(params, 0.0)
    run(end, params, pd, vd, np.full(n, kp), np.full(n, kf), p, u)
    assert np.array_equal(p, ref_p) and np.array_equal(u, ref_u)
    assert np.array_equal(end, states[-1])
    out = np.empty(n - 1)
    window(rest_state(params, 0.0), params, pd, vd, 0, n - 1, kp, kf, out)
    assert np.array_equal(out, ref_p[1:])


@BOTH_KINDS
def test_window_past_the_end_holds_the_last_setpoint(machine, axis):
    params = axis_params(machine, axis)
    n = 300
    pd, vd = _smooth_move(n, 0.004)
    vd[-1] = 0.01  # a nonzero last velocity must not be extrapolated
    k0, nw = n - 20, 60
    state = rest_state(params, pd[0])
    p, u = np.empty(k0), np.empty(k0)
    run(state, params, pd[:k0], vd[:k0], np.full(k0, 40.0), np.full(k0, 0.9), p, u)
    out = np.empty(nw)
    window(state, params, pd, vd, k0, nw, 40.0, 0.9, out)
    ext_pd = np.concatenate([pd[k0:], np.full(nw, pd[-1])])
    ext_vd = np.concatenate([vd[k0:], np.zeros(nw)])
    tail_p, tail_u = np.empty(nw + 1), np.empty(nw + 1)
    run(state, params, ext_pd[:nw + 1], ext_vd[:nw + 1], np.full(nw + 1, 40.0),
        np.full(nw + 1, 0.9), tail_p, tail_u)
    assert np.array_equal(out, tail_p[1:])


def _setpoints(pos, vel):
    n = pos.shape[0]
    return Setpoints(dt=TE, s=np.arange(n) * 1e-6, pos=pos, vel=vel, acc=np.zeros((n, 3)),
                     jerk=np.zeros((n, 3)), block=np.ones(n, int), rapid=np.zeros(n, bool))


def test_simulate_wrapper_axes_and_gain_forms():
    n = 600
    px, vx = _smooth_move(n, 0.01, p0=0.05)
    pz, vz = _smooth_move(n, -0.006, p0=-0.02)
    pos = np.column_stack([px, np.full(n, 0.1), pz])
    vel = np.column_stack([vx, np.zeros(n), vz])
    sp = _setpoints(pos, vel)
    by_dict = simulate(sp, UCP, {"x": 2.0, "y": 2.0, "z": 3.0}, {"x": 0.9, "y": 0.9, "z": 0.5})
    table_kp = np.tile([2.0, 2.0, 3.0], (n, 1))
    table_kf = np.tile([0.9, 0.9, 0.5], (n, 1))
    by_table = simulate(sp, UCP, table_kp, table_kf)
    assert np.array_equal(by_dict.pos, by_table.pos) and np.array_equal(by_dict.u, by_table.u)
    assert by_dict.pos.shape == by_dict.u.shape == by_dict.kf.shape == (n, 3)
    np.testing.assert_array_equal(by_dict.kp_m_min_per_mm, table_kp)
    p_z, u_z = simulate_axis(axis_params(UCP, "z"), pz[0], pz, vz,
                             3.0 * KP_SI_PER_M_MIN_PER_MM, 0.5)
    assert np.array_equal(by_dict.pos[:, 2], p_z) and np.array_equal(by_dict.u[:, 2], u_z)
    # the axis that does not move holds exactly
    assert np.all(by_dict.pos[:, 1] == 0.1) and np.all(by_dict.u[:, 1] == 0.0)
    scalar = simulate(sp, UCP, 2.0, 0.9)
    assert np.array_equal(scalar.pos[:, 0], by_dict.pos[:, 0])
    assert not scalar.pos.flags.writeable
    # a machine without Y: the Y column holds the setpoint
    data = UCP.model_dump()
    del data["axes"]["y"]
    xz = machine_from_dict(data)
    sim = simulate(sp, xz, 2.0, 0.9)
    assert np.all(sim.pos[:, 1] == 0.1) and np.array_equal(sim.pos[:, 0], scalar.pos[:, 0])
    pos_y = pos.copy()
    pos_y[:, 1] = px
    with pytest.raises(MachineError, match="'y'"):
        simulate(_setpoints(pos_y, vel), xz, 2.0, 0.9)


@pytest.mark.parametrize(
    "kp, kf, match",
    [
        ({"x": 2.0, "z": 2.0}, 0.9, "kp_m_min_per_mm: no value"),
        ({"x": 2.0, "y": 2.0, "z": 2.0, "a": 1.0}, 0.9, "kp_m_min_per_mm: unknown axis"),
        (np.ones((5, 3)), 0.9, r"kp_m_min_per_mm: expected shape \(10, 3\)"),
        (0.0, 0.9, "must be positive"),
        (2.0, math.nan, "kf: values must be finite"),
        ("fast", 0.9, "kp_m_min_per_mm: expected a number"),
    ],
)
def test_simulate_refuses_bad_gains(kp, kf, match):
    sp = _setpoints(np.zeros((10, 3)), np.zeros((10, 3)))
    with pytest.raises(OptionError, match=match):
        simulate(sp, UCP, kp, kf)


@pytest.mark.parametrize("machine, size", [(UCP, 4 + 2), (MCV, 1 + 7 + 6)])
def test_state_layout(machine, size):
    # cascade [p, v, F, I, u_k-1, u_k-2]; mcv-op X (the longer axis): p, 7 velocities
    # (den has 8 coefficients), 6 inputs (num has 7)
    assert state_size(machine) == size
    for axis in machine.axes:
        params = axis_params(machine, axis)
        s = rest_state(params, 0.25)
        assert s.shape == (size,) and s[0] == 0.25 and not np.any(s[1:])
