"""End to end: identify a perturbed ucp710 from a synthetic trace, optimise reference_xz with
the identified machine, and replay that table on the TRUE perturbed plant.

The plant is the last row of issue 16's table (mass -20 %, Coulomb and static friction -50 %,
viscous -50 %, Kv +20 %, Tn -30 %), on which the nominal ucp710 schedule is worse than the
fixed gains. The table made with the identified file must beat the fixed baseline on the true
plant (ratio < 1) and come within 1.5x of the ratio of the table made with the true
parameters. Four traces, one test file each so that xdist's ``--dist loadfile`` spreads them
over the workers (each fits two axes on a minute and a half of trace: about 1-2 min of CPU):
clean (0.1 um noise and quantum, tests/test_identify_e2e.py), a feed-forward velocity recorded
as the backward difference of the commands (``_backward_ff``), actual positions logged one
sample late (``_late_act``), and commands from another interpolator (trapezoidal velocity,
unlimited jerk, not our planner: ``_other_interpolator``). This module is the cases' shared
code (not collected: its name does not start with ``test_``); the plans and the optimisation
with the true parameters are computed once per process.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from feedplan.read import load_toolpath, read_toolpath
from feedplan.setpoints import Setpoints
from oga.identify.excite import excite_program
from oga.identify.sim import synthetic_trace
from oga.identify.trace import read_trace, trace_csv
from oga.identify.workflow import identify
from oga.model.machine import load_machine
from oga.optimize import optimize
from oga.pipeline import plan_toolpath
from oga.verify.replay import verify

DATA = "tests/data/reference_xz.ngc"
CASES = ("clean", "backward_ff", "late_act", "other_interpolator")


def perturbed(m):
    axes = {}
    for a, ax in m.axes.items():
        c = ax.cascade
        axes[a] = ax.model_copy(update={"cascade": c.model_copy(update=dict(
            mass_kg=c.mass_kg * 0.8, coulomb_n=c.coulomb_n * 0.5, static_n=c.static_n * 0.5,
            viscous_n_s_m=c.viscous_n_s_m * 0.5, kv_n_s_m=c.kv_n_s_m * 1.2, tn_s=c.tn_s * 0.7))})
    return m.model_copy(update={"axes": axes})


@cache
def machines():
    """``(base, true)``: ucp710 and its perturbed plant."""
    base = load_machine("ucp710")
    return base, perturbed(base)


@cache
def excitation_setpoints() -> Setpoints:
    """The identification program for x and z, planned by our planner."""
    base, _ = machines()
    program = excite_program(base, ["x", "z"], travel_mm=50.0)
    return plan_toolpath(read_toolpath(program, "gcode"), base, feed_m_s=None, tol_m=2e-5)


@cache
def reference():
    """``(ref, with_truth)``: reference_xz planned, and optimised with the true parameters."""
    base, true = machines()
    ref = plan_toolpath(load_toolpath(DATA), base, feed_m_s=None, tol_m=2e-5)
    return ref, optimize(ref, true, {"nominal": True})


def trapezoid_setpoints(base, dt=1e-3) -> Setpoints:
    """Another interpolator: point-to-point moves with a trapezoidal velocity (each axis at its
    acceleration limit, jerk unlimited), at rest between moves; x then z, then both."""
    moves = []
    for c in (0, 2):
        for feed_mm_s, dist_mm in ((0.5, 1.0), (2.0, 4.0), (10.0, 30.0), (50.0, 50.0),
                                   (150.0, 50.0), (300.0, 50.0)):
            for sign in (1, -1):
                moves.append((c, sign * dist_mm * 1e-3, feed_mm_s * 1e-3))
        for amp_mm, feed_mm_s in ((5.0, 100.0), (1.0, 60.0), (0.3, 30.0)):
            for _ in range(4):
                moves += [(c, amp_mm * 1e-3, feed_mm_s * 1e-3),
                          (c, -amp_mm * 1e-3, feed_mm_s * 1e-3)]
    pos = [np.zeros(3)]
    for c, dist, v in moves:
        amax = 0.8 * base.axis("xyz"[c]).limits.amax_m_s2
        t_acc = v / amax
        if amax * t_acc ** 2 > abs(dist):  # triangle
            t_acc = np.sqrt(abs(dist) / amax)
            v = amax * t_acc
        t_tot = 2 * t_acc + (abs(dist) - amax * t_acc ** 2) / v
        t = np.arange(1, int(np.ceil(t_tot / dt)) + 1) * dt
        t = np.minimum(t, t_tot)
        s = np.where(t < t_acc, 0.5 * amax * t ** 2,
                     np.where(t < t_tot - t_acc, 0.5 * amax * t_acc ** 2 + v * (t - t_acc),
                              abs(dist) - 0.5 * amax * (t_tot - t) ** 2))
        start = pos[-1][-1] if pos[-1].ndim == 2 else pos[-1]
        seg = np.tile(start, (t.size + 100, 1))
        seg[: t.size, c] += np.sign(dist) * s
        seg[t.size:, c] += dist
        pos.append(seg)
    p = np.vstack([pos[0][None, :]] + pos[1:])
    vel = np.gradient(p, dt, axis=0)
    acc = np.gradient(vel, dt, axis=0)
    n = len(p)
    return Setpoints(dt=dt, s=np.zeros(n), pos=p, vel=vel, acc=acc,
                     jerk=np.gradient(acc, dt, axis=0), block=np.ones(n, np.int64),
                     rapid=np.zeros(n, bool))


def check_case(case: str) -> None:
    """Identify from the case's trace, optimise with the identified machine, replay on the true
    plant: the table holds there (see the module's docstring)."""
    if case not in CASES:
        raise ValueError(f"unknown case {case!r}: one of {CASES}")
    base, true = machines()
    ref, with_truth = reference()
    kw = dict(noise_m=1e-7, quantum_m=1e-7, seed=7)
    if case == "backward_ff":
        kw["ff"] = "backward"
    if case == "late_act":
        kw["act_delay"] = 1
    sp = trapezoid_setpoints(base) if case == "other_interpolator" else excitation_setpoints()
    ch = synthetic_trace(sp, true, ["x", "z"], 3.0, 0.8, **kw)
    t = ch.pop("t_s")
    trace = read_trace(trace_csv(t, ch), kp=3.0, kf=0.8)
    ident = identify(trace, base)
    assert ident.status == "ok"
    if case == "late_act":
        assert all(f.lag_samples == 1 for f in ident.fits.values())
    assert ident.machine.timing.dead_time_samples == true.timing.dead_time_samples
    table = optimize(ref, ident.machine, {"nominal": True}).schedule
    replay = verify(ref, true, table.kp_m_min_per_mm, table.kf, with_truth.kp_bounds)
    ratio = replay.metrics.mse_m2 / with_truth.baseline.metrics.mse_m2
    assert replay.ok, replay.violations
    assert ratio < 1.0
    assert ratio <= 1.5 * with_truth.ratio_mse, (ratio, with_truth.ratio_mse)
