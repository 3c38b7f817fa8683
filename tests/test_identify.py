"""Identification: trace reading and its refusals, the identification program, the
uncertainty section, and the fit's recovery of parameters drawn at random (synthetic traces
from the simulator, with measurement noise and encoder quantisation).

The recovery test runs 20 seeded draws on a short identification program (10 mm travel,
0.5 s slow passes, sweep 4-20 Hz: 13.9 s, every parameter still visible; 2-10 s a fit on a
loaded machine) with the force channel recorded (from positions alone mass, Kv and the
forces scale together), and one high-friction, slow-loop draw of the bench on the full 52 s
program (about 10 s of CPU); ``bench/bench_identify.py`` runs 100 on that program.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from feedplan.read import read_toolpath
from oga.identify.excite import excite_program
from oga.identify.fit import PARAMETERS, fit_axis, start_position
from oga.identify.sim import random_cascade, simulate_forces, synthetic_trace
from oga.identify.trace import AxisTrace, TraceError, read_trace, trace_csv
from oga.model.machine import load_machine, machine_from_dict
from oga.pipeline import plan_toolpath
from oga.model.simulate import axis_params, simulate_axis


@pytest.fixture(scope="module")
def ucp():
    return load_machine("ucp710")


def _csv(n=50, dt=1e-3, extra=""):
    t = np.arange(n) * dt
    cmd = 1e-3 * np.sin(t)
    return trace_csv(t, {"x_cmd_m": cmd, "x_act_m": cmd - 1e-6})


# --- trace reader ----------------------------------------------------------------------------

def test_csv_round_trip_and_gains():
    tr = read_trace(_csv(), kp="x=2.5", kf=0.7)
    assert tr.n == 50 and math.isclose(tr.dt_s, 1e-3)
    ax = tr.axes["x"]
    assert np.all(ax.kp_m_min_per_mm == 2.5) and np.all(ax.kf == 0.7)
    np.testing.assert_array_equal(ax.act_m, 1e-3 * np.sin(np.arange(50) * 1e-3) - 1e-6)


def test_units_mm_scale_lengths_not_gains():
    text = "t_s,x_cmd_m,x_act_m,x_kp_m_min_per_mm,x_kf,x_force_n\n" + "\n".join(
        f"{k * 1e-3},{k * 0.01},{k * 0.01 - 0.001},2.0,0.5,10" for k in range(10))
    ax = read_trace(text, units="mm").axes["x"]
    np.testing.assert_allclose(ax.cmd_m, np.arange(10) * 1e-5)
    assert np.all(ax.kp_m_min_per_mm == 2.0) and np.all(ax.force_n == 10.0)


@pytest.mark.parametrize("mutate, where", [
    (lambda ls: ls.__setitem__(5, ls[5].replace(ls[5].split(",")[2], "nan")), "column 'x_act_m', row 6"),
    (lambda ls: ls.__setitem__(5, ls[5].replace(ls[5].split(",")[1], "abc")), "column 'x_cmd_m', row 6"),
    (lambda ls: ls.insert(6, ls[5]), "row 7: duplicated row"),
    (lambda ls: ls.pop(6), "row 7: gap of 2 periods"),
])
def test_bad_rows_are_named(mutate, where):
    lines = _csv().splitlines()
    mutate(lines)
    with pytest.raises(TraceError, match=where):
        read_trace("\n".join(lines), kp=2.0, kf=0.5)


def test_non_uniform_sampling_refused():
    lines = _csv().splitlines()
    cells = lines[10].split(",")
    cells[0] = repr(float(cells[0]) + 3e-4)
    lines[10] = ",".join(cells)
    with pytest.raises(TraceError, match="row 11: non-uniform sampling"):
        read_trace("\n".join(lines), kp=2.0, kf=0.5)


def test_mm_read_as_metres_refused():
    t = np.arange(100) * 1e-3
    cmd = 50.0 * t  # 50 mm/s written in mm, read as metres: 50 m/s
    text = trace_csv(t, {"x_cmd_m": cmd, "x_act_m": cmd})
    with pytest.raises(TraceError, match=r"column 'x_cmd_m', row 3: speed 50 m/s is absurd.*--units mm"):
        read_trace(text, kp=2.0, kf=0.5)
    assert read_trace(text, units="mm", kp=2.0, kf=0.5).n == 100


def test_missing_gains_unknown_columns_and_row_limit(monkeypatch):
    with pytest.raises(TraceError, match="axis x: no x_kp_m_min_per_mm column and no --kp"):
        read_trace(_csv())
    with pytest.raises(TraceError, match="column 2: unknown name 'x_pos'"):
        read_trace("t_s,x_pos\n0,0\n0.001,0\n")
    with pytest.raises(TraceError, match="--kp: unknown axis 'q'"):
        read_trace(_csv(), kp="q=2", kf=0.5)
    import oga.identify.trace as trace_mod

    monkeypatch.setattr(trace_mod, "TRACE_MAX_ROWS", 20)
    with pytest.raises(TraceError, match="row 22: more than 20 rows"):
        read_trace(_csv(), kp=2.0, kf=0.5)
    # counted before the text is split: a trace of empty lines never becomes a line list
    with pytest.raises(TraceError, match="1021 lines, more than the 20 rows"):
        read_trace("\n" * 1021, kp=2.0, kf=0.5)


def test_halsampler_columns_and_sample_numbers():
    rows = "\n".join(f"{k} {k * 1e-6:.9f} {k * 1e-6 - 1e-7:.9f}" for k in range(100, 130))
    tr = read_trace(rows, "halsampler", columns=["sample", "x_cmd_m", "x_act_m"], te_s=1e-3,
                    kp=3.0, kf=0.8)
    assert tr.n == 30 and math.isclose(tr.dt_s, 1e-3)
    gap = rows.replace("\n115 ", "\n116 ", 1)  # an overrun: sample 115 missing, 116 twice
    with pytest.raises(TraceError, match="column 'sample', row 16"):
        read_trace(gap, "halsampler", columns=["sample", "x_cmd_m", "x_act_m"], te_s=1e-3,
                   kp=3.0, kf=0.8)
    with pytest.raises(TraceError, match="needs --columns"):
        read_trace(rows, "halsampler", te_s=1e-3, kp=3.0, kf=0.8)


def test_twincat_scope_export():
    # TwinCAT Scope View CSV export: header rows, channel rows, then (time ms, value) per channel
    head = ("Name\tScope01\nFile\t\nStartRecord\t133449148496160000\n\n"
            "Name\t\tMAIN.x_cmd\t\tMAIN.x_act\nSampleTime[ms]\t\t1\t\t1\n")
    body = "\n".join(f"{k}\t{k * 1e-3:.6f}\t{k}\t{k * 1e-3 - 1e-4:.6f}".replace(".", ",")
                     for k in range(40))
    tr = read_trace(head + body, "twincat", columns=["x_cmd_m", "x_act_m"], units="mm",
                    kp=3.0, kf=0.8)
    assert tr.n == 40 and math.isclose(tr.dt_s, 1e-3)
    np.testing.assert_allclose(tr.axes["x"].act_m, np.arange(40) * 1e-6 - 1e-7)
    with pytest.raises(TraceError, match="unknown name 'MAIN.x_cmd'"):
        read_trace(head + body, "twincat", kp=3.0, kf=0.8)


# --- identification program ------------------------------------------------------------------

def test_excite_program_plans_within_limits_and_travel(ucp):
    from feedplan.check import check_setpoints

    text = excite_program(ucp, ["x", "z"], travel_mm=50.0)
    path = read_toolpath(text, "gcode")
    sp = plan_toolpath(path, ucp, feed_m_s=None, tol_m=2e-5)
    check = check_setpoints(sp, path, ucp.axis_limits(), tol_m=2e-5)
    # the axis limits hold (the path-following part of the check loses its place on a program
    # that runs over the same lines many times; the planner keeps the geometry by construction)
    for ratio in (check.vel_ratio, check.acc_ratio, check.jerk_ratio):
        assert np.all(ratio <= 1.0)
    for c in (0, 2):
        assert sp.pos[:, c].min() >= -2e-5 and sp.pos[:, c].max() <= 50e-3 + 2e-5  # tolerance
        v = sp.vel[:, c]
        vs = ucp.axis("x" if c == 0 else "z").cascade.stribeck_m_s
        # constant speed inside and far above the Stribeck band, both directions
        assert np.any((np.abs(v) > 0.2 * vs) & (np.abs(v) < vs)) and np.max(np.abs(v)) > 50 * vs
        assert v.min() < 0 < v.max()
    assert "G18 G2" in text  # the circle in the plane x and z span
    with pytest.raises(ValueError, match="--axes: unknown axis 'q'"):
        excite_program(ucp, ["q"])


# --- uncertainty section ---------------------------------------------------------------------

def test_uncertainty_section_validated(ucp):
    data = ucp.model_dump(mode="json", exclude_none=True)
    data["axes"]["x"]["uncertainty"] = {"coulomb_n": [0.5, 1.5], "force_lag_s": [0.5, 2.0],
                                        "dead_time_extra_samples": [0, 1]}
    m = machine_from_dict(data)
    assert m.axes["x"].uncertainty.force_lag_s == (0.5, 2.0)
    assert m.axes["x"].uncertainty.mass_kg == (1.0, 1.0)
    assert ucp.digest() == load_machine("ucp710").digest()
    data["axes"]["x"]["uncertainty"] = {"coulmb_n": [0.5, 1.5]}
    with pytest.raises(ValueError, match="axes.x.uncertainty.coulmb_n: unknown field"):
        machine_from_dict(data)
    data["axes"]["x"]["uncertainty"] = {"tn_s": [1.2, 1.5]}
    with pytest.raises(ValueError, match="tn_s: factors .* low <= 1 <= high"):
        machine_from_dict(data)


# --- recovery ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def excite_x(ucp):
    text = excite_program(ucp, ["x"])
    return plan_toolpath(read_toolpath(text, "gcode"), ucp, feed_m_s=None, tol_m=2e-5)


@pytest.fixture(scope="module")
def excite_short(ucp):
    """A short identification program of axis x (13.9 s): friction passes at 0.3-3 Stribeck
    velocities for 0.5 s each way and up to 60 % of the speed limit, velocity steps, and a
    sweep at 4-20 Hz (loop dynamics and dead time)."""
    text = excite_program(ucp, ["x"], travel_mm=10.0, pass_s=0.5,
                          sweep_hz=(4.0, 7.0, 10.0, 15.0, 20.0))
    sp = plan_toolpath(read_toolpath(text, "gcode"), ucp, feed_m_s=None, tol_m=2e-5)
    assert 12.0 < len(sp) * sp.dt < 16.0
    return sp


def test_simulate_forces_matches_the_simulator(ucp, excite_x):
    params = axis_params(ucp, "x")
    pd = np.ascontiguousarray(excite_x.pos[:, 0])
    vd = np.ascontiguousarray(excite_x.vel[:, 0])
    n = pd.size
    kp, kf = np.full(n, 50.0), np.full(n, 0.8)
    p, f = simulate_forces(params, pd[0], pd, vd, kp, kf)
    p_ref, _ = simulate_axis(params, pd[0], pd, vd, kp, kf)
    np.testing.assert_array_equal(p, p_ref)
    # at constant speed v (10 mm/s: 10 Stribeck velocities, the Stribeck term gone) the drive
    # force balances friction alone: F = Fc sign(v) + B v
    cas = ucp.axis("x").cascade
    k = int(np.argmax(np.abs(vd) > 0.0099))
    sl = slice(k + 1000, k + 1500)
    assert np.all(np.abs(vd[sl] - 0.01) < 1e-12)
    np.testing.assert_allclose(f[sl], cas.coulomb_n + cas.viscous_n_s_m * 0.01, rtol=1e-6)


def test_the_start_position_is_the_command_unless_measurably_off():
    """The simulation starts where the axis stands: at its command where the positions before
    the first move cannot tell them apart (a first sample 3 sigma off included), at their
    median where the standing error is measurable (50 sigma)."""
    rng = np.random.default_rng(0)
    cmd = np.r_[np.full(2000, 0.01), 0.01 + np.linspace(0.0, 1e-3, 3000)]

    def measured(offset_m):  # 0.1 um noise and quantum
        return np.round((cmd + offset_m + rng.normal(0.0, 1e-7, cmd.size)) / 1e-7) * 1e-7

    meas = measured(0.0)
    meas[0] = cmd[0] + 3e-7
    assert start_position(cmd, meas) == cmd[0]
    assert start_position(cmd[2000:], meas[2000:]) == cmd[2000]  # moving from the first sample
    assert start_position(cmd, measured(5e-6)) == pytest.approx(cmd[0] + 5e-6, abs=1e-8)


@pytest.fixture(scope="module")
def recovered():
    """The recovery draws' fits on the short program, by seed (the continuity test reuses one)."""
    return {}


@pytest.mark.parametrize("seed", range(20))
def test_recovery_of_random_plants(ucp, excite_short, recovered, seed):
    recovered[seed] = _check_recovery(ucp, excite_short, seed)


@pytest.mark.parametrize("seed", [1048])
def test_recovery_of_high_friction_slow_loops(ucp, excite_x, seed):
    """Bench draw 48 on the full program (Coulomb 471 N on 1484 kg, an 18 Hz loop, dead time
    3): from positions alone the fit stopped in a low-friction minimum (Kv, Coulomb and mass
    55-59 % low) with status ``ok``."""
    _check_recovery(ucp, excite_x, seed)


def _random_trace(ucp, sp, seed, n=None):
    """``(true machine, trace of axis x)``: draw ``seed`` recorded on ``sp`` with noise,
    quantisation and the force channel; only its first ``n`` samples where given."""
    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(seed))
    ch = synthetic_trace(sp, true_machine, ["x"], kp, 0.8, noise_m=1e-7, quantum_m=1e-7,
                         seed=seed, force_noise_n=1.0)
    n = len(sp) if n is None else n
    return true_machine, AxisTrace(cmd_m=ch["x_cmd_m"][:n], act_m=ch["x_act_m"][:n],
                                   kp_m_min_per_mm=np.full(n, kp), kf=np.full(n, 0.8),
                                   force_n=ch["x_force_n"][:n])


def _check_recovery(ucp, sp, seed):
    true_machine, tr = _random_trace(ucp, sp, seed)
    fit = fit_axis(ucp, "x", tr, sp.dt)
    true = true_machine.axis("x").cascade
    assert fit.dead_time_samples == true_machine.timing.dead_time_samples and fit.lag_samples == 0
    for name in ("mass_kg", "kv_n_s_m", "tn_s"):
        assert fit.values[name] == pytest.approx(getattr(true, name), rel=0.05), name
    assert fit.values["coulomb_n"] == pytest.approx(true.coulomb_n, rel=0.10, abs=2.0)
    # draw 48 sticks at its reversals (Coulomb 471 N): even the right fit leaves a residual 3.3
    # times the noise, correlated over 18 samples (the stick-slip is not reproduced to the
    # noise): marked model-error, its set widened by that evidence
    assert fit.status == ("model-error" if seed == 1048 else "ok") and fit.mass_identified
    # the interval brackets the truth within a few widths (the fit is unbiased on its own model)
    for name in ("kv_n_s_m", "tn_s"):
        half = fit.ci_high[name] - fit.values[name]
        assert abs(fit.values[name] - getattr(true, name)) < 5 * half + 1e-3 * getattr(true, name)
    return fit


def test_identification_is_continuous_in_the_excitation(ucp, excite_short, recovered):
    """A result must change little when its input changes little (issue 29): on a replanned
    short program 0.3 % shorter, draw 3 (true dead time 3 samples, force lag 0.33 ms) came out
    2 samples with the missing sample in its force lag (1.15 ms), viscous friction 3 times the
    truth and status ``poor``: the solve at the true dead time had stuck with its force lag on
    its bound. The same recording with its last 3 % cut off (the end of the 20 Hz sweep) gives
    the same dead time and logging lag, and every parameter within two of its interval's
    half-widths."""
    seed = 3
    full = recovered.get(seed) or fit_axis(ucp, "x", _random_trace(ucp, excite_short, seed)[1],
                                           excite_short.dt)
    cut = fit_axis(ucp, "x", _random_trace(ucp, excite_short, seed,
                                           int(0.97 * len(excite_short)))[1], excite_short.dt)
    assert cut.status == full.status == "ok"
    assert (cut.dead_time_samples, cut.lag_samples) == (full.dead_time_samples, full.lag_samples)
    # every parameter moves by less than two of its interval's half-widths: measured over draws
    # 0-3 on this program against the last 3 % cut, against main's plan 0.3 % longer and a
    # replan with 3 % shorter slow passes, the largest move was 1.15 half-widths (draw 2's
    # viscous friction; the mass 0.74 since its interval is the joint fit's; draw 3 here: 0.08).
    # A wrong whole dead time moves the force lag and the viscous friction by far more (draw 3
    # at d = 2: lag 3.5 times, viscous 3 times the truth; their half-widths 1 % and 0.2 %)
    for name in PARAMETERS:
        half = max(full.ci_high[name] - full.values[name], full.values[name] - full.ci_low[name])
        assert abs(cut.values[name] - full.values[name]) <= 2.0 * half, name


def test_a_force_the_model_cannot_explain_is_poor(ucp, excite_short):
    """Positions of one plant, the force of another (Coulomb friction 500 N more): no fit
    explains both, and the force residual marks the fit poor."""
    from oga.defaults import IDENT_POOR_FORCE_SHARE, IDENT_POOR_NOISE_RATIO

    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(4))
    cas = true_machine.axis("x").cascade
    other = true_machine.model_copy(update={"axes": {**true_machine.axes, "x": true_machine.axis(
        "x").model_copy(update={"cascade": cas.model_copy(update={
            "coulomb_n": cas.coulomb_n + 500.0, "static_n": cas.static_n + 500.0})})}})
    ch = synthetic_trace(excite_short, true_machine, ["x"], kp, 0.8, noise_m=1e-7,
                         quantum_m=1e-7, seed=4)
    force = synthetic_trace(excite_short, other, ["x"], kp, 0.8, seed=4,
                            force_noise_n=1.0)["x_force_n"]
    n = len(excite_short)
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8), force_n=force)
    fit = fit_axis(ucp, "x", tr, excite_short.dt)
    assert fit.status == "poor"
    # the force decides: the positions alone pass (8.6 times the noise), the force residual is
    # 8 % of the force
    assert fit.residual_rms_m < IDENT_POOR_NOISE_RATIO * fit.noise_rms_m
    assert fit.force_residual_rms_n > IDENT_POOR_FORCE_SHARE * np.sqrt(np.mean(force ** 2))


@pytest.mark.parametrize("delay", [0, 1, 2])
def test_logging_lag_from_the_steady_following_error(ucp, excite_x, delay):
    from oga.identify.fit import axis_inputs, logging_lag

    # a plant unlike the base (the steady error does not depend on it), backward-difference
    # feed-forward recorded, the log `delay` samples late
    rng = np.random.default_rng(delay)
    true_machine, kp = random_cascade(ucp, "x", rng)
    ch = synthetic_trace(excite_x, true_machine, ["x"], kp, 0.8, noise_m=1e-7, quantum_m=1e-7,
                         act_delay=delay, ff="backward")
    n = len(excite_x)
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8), ff_vel_m_s=ch["x_ff_vel_m_s"])
    cmd, ff, kp_si, kf = axis_inputs(tr, excite_x.dt)
    assert logging_lag(cmd, ff, kp_si, kf, tr.act_m, excite_x.dt) == delay


def test_library_entry_is_the_callable_package(ucp):
    import oga

    trace = oga.identify.read_trace(_csv(n=300), kp=3.0, kf=0.8)
    with pytest.raises(oga.InputError, match="axis z: not in the trace"):
        oga.identify(trace, ucp, axes=["z"])
    idle = oga.identify.read_trace("t_s,x_cmd_m,x_act_m\n0,0,0\n0.001,0,0\n", kp=3.0, kf=0.8)
    with pytest.raises(oga.InputError, match="no axis moves in the trace"):
        oga.identify(idle, ucp)


def test_progress_rises_through_every_fit_to_one(ucp, excite_short, monkeypatch):
    """``oga.identify(..., progress=)``: each fit (the held-out refit too) an equal share, the
    fraction rising through the solver's evaluations, never falling, 1 at the end."""
    import oga
    import oga.identify.fit as fit_module
    from oga.identify.trace import Trace
    from oga.identify.workflow import identify

    monkeypatch.setattr(fit_module, "IDENT_PROGRESS_EVERY_S", 0.0)  # every evaluation
    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(3))
    ch = synthetic_trace(excite_short, true_machine, ["x"], kp, 0.8, noise_m=1e-7,
                         quantum_m=1e-7, seed=3)
    n = len(excite_short)
    trace = Trace(dt_s=excite_short.dt, n=n, axes={"x": AxisTrace(
        cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
        kf=np.full(n, 0.8))}, source="short")
    seen, cpu = [], [time.process_time()]

    def progress(f):
        seen.append(f)
        cpu.append(time.process_time())

    ident = identify(trace, ucp, holdout_fraction=0.25, progress=progress)
    assert ident.holdout["x"]["rms_heldout_m"] < 1e-6
    assert seen == sorted(seen) and seen[-1] == 1.0 and 0.0 < seen[0] < 0.1
    assert np.max(np.diff(cpu)) < 2.0  # a report at least every 2 s of work (0.4 s measured)
    first, second = [f for f in seen if f < 0.5], [f for f in seen if 0.5 < f < 1.0]
    assert len(set(first)) > 50 and len(set(second)) > 50  # both fits report as they go
    assert 0.5 in seen  # the first fit's end

    # the report of a stored job, rebuilt from its summary and machine file, is this report
    from oga.identify.report import identify_report
    from oga.identify.workflow import identification_from_summary

    summary = ident.summary()
    assert identify_report(identification_from_summary(summary, trace, ucp, ident.toml)) == \
        identify_report(ident)
    summary["axes"]["x"]["ci_high"]["stribeck_m_s"] = None  # inf stored as JSON null
    page = identify_report(identification_from_summary(summary, trace, ucp, ident.toml))
    assert "<th>stribeck_m_s</th>" in page and "</td><td>nan</td>" in page
    del summary["axes"]["x"]["values"]
    with pytest.raises(oga.InputError, match="stored identification is incomplete: KeyError"):
        identification_from_summary(summary, trace, ucp, ident.toml)


@pytest.mark.parametrize("seed, force", [(0, False), (3, False), (5, False), (0, True),
                                         (5, True)])
def test_jacobian_is_the_derivative_of_the_simulation(ucp, excite_short, seed, force):
    """The fit's Jacobian (forward mode through the simulation) against central differences
    of the residual, at the true plant of a draw; the positions of that pass are the
    simulator's to the bit. Draw 3 sticks at its reversals (Coulomb 400 N on 263 kg): there
    the simulation chatters about v = 0 and the derivative is the sticking axis's, so only
    finite and within 30 % (measured 20.9 % since the simulation starts on the command:
    ``start_position``, 25.5 % on the excitation as the profile plans it since its jerk share,
    2026-11-29); elsewhere within 1e-3. With the force channel the residual also
    holds the weighted force and ``x`` its scale (an eighth column)."""
    from oga.identify.fit import _Model, _x0
    from oga.identify.sensitivity import positions_and_sensitivities

    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(seed))
    ch = synthetic_trace(excite_short, true_machine, ["x"], kp, 0.8, noise_m=1e-7,
                         quantum_m=1e-7, seed=seed, force_noise_n=1.0 if force else None)
    n = len(excite_short)
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8), force_n=ch.get("x_force_n"))
    cas, dead = true_machine.axis("x").cascade, true_machine.timing.dead_time_samples
    model = _Model(ucp, "x", tr, excite_short.dt, cas.mass_kg, use_force=force)
    x = np.append(_x0(cas), [0.1] if force else [])
    params = model.params(x, dead)
    p, _ = positions_and_sensitivities(params, np.zeros((2, params.size)), model.p0, model.cmd,
                                       model.ff, model.kp, model.kf)
    p_ref, _ = simulate_axis(params, model.p0, model.cmd, model.ff, model.kp, model.kf)
    np.testing.assert_array_equal(p, p_ref)
    jac = model.jacobian(x, dead, 1)
    assert jac.shape == ((2 if force else 1) * (n - 1), x.size) and np.all(np.isfinite(jac))
    for j, err in enumerate(_central_difference_errors(model, jac, x, dead, 1)):
        assert err < (0.3 if seed == 3 else 1e-3), (j, err)


def test_friction_and_velocity_loop_from_the_force(ucp, excite_x):
    """The fit's starting point from a recorded force (regressions) against the true plant of
    a high-friction, slow-loop draw (bench draw 30: Coulomb 406 N, 11.8 Hz, dead time 1)."""
    from oga.identify.fit import axis_inputs, friction_from_force, velocity_loop_from_force

    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(1030))
    ch = synthetic_trace(excite_x, true_machine, ["x"], kp, 0.8, noise_m=1e-7, quantum_m=1e-7,
                         seed=1030, force_noise_n=1.0)
    n, dt = len(excite_x), excite_x.dt
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8), force_n=ch["x_force_n"])
    true = true_machine.axis("x").cascade
    mass, fc, b = friction_from_force(tr.act_m, tr.force_n, dt)
    assert mass == pytest.approx(true.mass_kg, rel=0.05)
    assert fc == pytest.approx(true.coulomb_n, rel=0.01)
    assert b == pytest.approx(true.viscous_n_s_m, rel=0.02)
    cmd, ff, kp_si, kf = axis_inputs(tr, dt)
    kv, tn, dead = velocity_loop_from_force(kp_si * (cmd - tr.act_m) + kf * ff, tr.act_m, tr.force_n,
                                      dt, 6)
    assert kv == pytest.approx(true.kv_n_s_m, rel=0.1) and tn == pytest.approx(true.tn_s, rel=0.1)
    assert dead == true_machine.timing.dead_time_samples
    # no fast samples: no answer
    assert friction_from_force(tr.act_m[:50], tr.force_n[:50], dt) is None


def test_jacobian_falls_back_to_differences_where_the_tangent_overflows(ucp, excite_short,
                                                                       monkeypatch):
    import oga.identify.sensitivity as sens
    from oga.identify.fit import _Model, _x0

    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(0))
    ch = synthetic_trace(excite_short, true_machine, ["x"], kp, 0.8, seed=0)
    n = len(excite_short)
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8))
    cas, dead = true_machine.axis("x").cascade, true_machine.timing.dead_time_samples
    model, x = _Model(ucp, "x", tr, excite_short.dt, cas.mass_kg), _x0(cas)
    exact = model.jacobian(x, dead, 0)
    real = sens.forces_and_sensitivities

    def overflowed(*a):
        p, dp, f, df = real(*a)
        return p, np.full_like(dp, np.inf), f, df

    monkeypatch.setattr(sens, "forces_and_sensitivities", overflowed)
    fallback = model.jacobian(x, dead, 0)
    assert np.all(np.isfinite(fallback))
    for j in range(7):
        assert np.linalg.norm(fallback[:, j] - exact[:, j]) < 1e-2 * np.linalg.norm(exact[:, j])


@pytest.mark.parametrize("seed", [0, 5])
def test_jacobian_holds_where_the_axis_stands_while_another_moves(ucp, seed):
    """Axis x on a two-axis program: it stands, stuck in its friction, while z moves, where the
    kernels skip a period that leaves state and tangents as they were (and read a stuck
    period's nominal sub-steps back). Positions and forces there are the simulator's to the
    bit, and the Jacobian matches central differences of the residual (1e-5 measured; 1e-3
    as for a moving axis)."""
    from oga.identify.fit import _Model, _x0
    from oga.identify.sensitivity import forces_and_sensitivities

    text = excite_program(ucp, ["x", "z"], travel_mm=10.0, pass_s=0.5, sweep_hz=(4.0, 10.0))
    sp = plan_toolpath(read_toolpath(text, "gcode"), ucp, feed_m_s=None, tol_m=2e-5)
    true_machine, kp = random_cascade(ucp, "x", np.random.default_rng(seed))
    ch = synthetic_trace(sp, true_machine, ["x"], kp, 0.8, noise_m=1e-7, quantum_m=1e-7,
                         seed=seed)
    n = len(sp)
    assert np.mean(np.diff(ch["x_cmd_m"]) == 0.0) > 0.3  # x stands for a third of it
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8))
    cas, dead = true_machine.axis("x").cascade, true_machine.timing.dead_time_samples
    model = _Model(ucp, "x", tr, sp.dt, cas.mass_kg)
    x = _x0(cas)
    params = model.params(x, dead)
    args = (model.p0, model.cmd, model.ff, model.kp, model.kf)
    p, _, f, _ = forces_and_sensitivities(params, np.zeros((2, params.size)), *args)
    np.testing.assert_array_equal(p, simulate_axis(params, *args)[0])
    np.testing.assert_array_equal(f, simulate_forces(params, *args)[1])
    jac = model.jacobian(x, dead, 0)
    for j, err in enumerate(_central_difference_errors(model, jac, x, dead, 0)):
        assert err < 1e-3, (j, err)


def _central_difference_errors(model, jac, x, dead, which):
    """Relative error of each Jacobian column against central differences of the residual."""
    for j in range(x.size):
        h = 1e-5 * max(1.0, abs(x[j]))
        up, down = x.copy(), x.copy()
        up[j] += h
        down[j] -= h
        fd = (model.residual(up, dead, which) - model.residual(down, dead, which)) / (2 * h)
        yield np.linalg.norm(jac[:, j] - fd) / np.linalg.norm(fd)
