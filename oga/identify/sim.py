"""The simulator's cascade with its drive force recorded, and synthetic traces from it.

:func:`simulate_forces` is :func:`oga.model.simulate.simulate_axis` (the same :func:`oga.model.simulate.drive`
per sample, so the same positions) that also records the force-lag output, the force a
drive reports. :func:`synthetic_trace` makes the trace a machine would record on planned
setpoints: for tests, the benchmark, and trying the workflow without a machine.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.model.simulate import _same, axis_params, drive, rest_state

__all__ = ["simulate_forces", "ideal_loop_positions", "synthetic_trace", "random_cascade"]

_P, _F = 0, 2  # position and force in the cascade state (oga.model.simulate's layout)


@njit(cache=True)
def _run_forces(state, params, pd, vd, kp_si, kf, out_p, out_f):
    # a period that left the whole state (its dead-time line too) as it was, to the bit, does
    # so again under the same command: skipped (an axis stuck in its friction, standing)
    before = np.empty_like(state)
    still, u_still = False, 0.0
    for k in range(pd.shape[0]):
        out_p[k] = state[_P]
        out_f[k] = state[_F]
        u = kp_si[k] * (pd[k] - state[_P]) + kf[k] * vd[k]
        if still and _same(u, u_still):
            continue
        before[:] = state
        drive(state, params, u, 0.0)
        still, u_still = True, u
        for j in range(state.shape[0]):
            if not _same(state[j], before[j]):
                still = False
                break


@njit(cache=True)
def _ideal_loop(p0, pd, vd, kp_si, kf, te, line, frac, out_p):
    u = np.zeros(pd.shape[0])
    p = p0
    for k in range(pd.shape[0]):
        out_p[k] = p
        u[k] = kp_si[k] * (pd[k] - p) + kf[k] * vd[k]
        m = k - line
        ud = u[m] if m >= 0 else 0.0
        if frac != 0.0:
            ud = frac * ud + (1.0 - frac) * (u[m + 1] if m + 1 >= 0 else 0.0)
        p += te * ud


def ideal_loop_positions(p0: float, pd, vd, kp_si, kf, te: float, dead_time_samples: float):
    """The positions of the recorded position loop around an ideal velocity loop (the axis
    moves at the command it receives, ``dead_time_samples`` late; a fraction interpolated as
    :mod:`oga.model.simulate` does): what the positions would be without the velocity loop's
    dynamics. Their difference to the measured ones is the velocity loop's imprint, which an
    axis model has to predict.

    Parameters
    ----------
    p0 : float
    pd, vd, kp_si, kf : ndarray, shape (N,)
        Setpoints (m, m/s) and gains (1/s, factor), float64.
    te : float
        Period, s.
    dead_time_samples : float

    Returns
    -------
    ndarray, shape (N,)
        Positions, m.
    """
    d = float(dead_time_samples)
    whole = int(np.floor(d))
    line, frac = (whole, 0.0) if d == whole else (whole + 1, d - whole)
    out = np.empty(np.shape(pd)[0])
    _ideal_loop(float(p0), *(np.ascontiguousarray(a, dtype=np.float64) for a in (pd, vd, kp_si, kf)),
                float(te), line, frac, out)
    return out


def simulate_forces(params: np.ndarray, p0: float, pd, vd, kp_si, kf):
    """Simulate a cascade axis from rest at ``p0`` (m) with per-sample gains.

    Parameters
    ----------
    params : ndarray
        :func:`oga.model.simulate.axis_params` of a cascade axis.
    p0 : float
    pd, vd, kp_si, kf : ndarray, shape (N,), float64, contiguous
        Setpoints (m, m/s) and gains (1/s, factor).

    Returns
    -------
    p, force : ndarray, shape (N,)
        Measured positions (m) and drive forces (N) at each sample.
    """
    n = pd.shape[0]
    out_p, out_f = np.empty(n), np.empty(n)
    _run_forces(rest_state(params, float(p0)), params, pd, vd, kp_si, kf, out_p, out_f)
    return out_p, out_f


def synthetic_trace(sp: Setpoints, machine: Machine, axes, kp_m_min_per_mm: float, kf: float, *,
                    noise_m: float = 0.0, quantum_m: float = 0.0, seed: int = 0,
                    force_noise_n: float | None = None, act_delay: int = 0,
                    ff: str = "centred") -> dict[str, np.ndarray]:
    """The channels a recorder would log while ``machine`` runs ``sp`` at fixed gains.

    Parameters
    ----------
    sp : Setpoints
    machine : Machine
        The (true) machine.
    axes : iterable of str
    kp_m_min_per_mm, kf : float
        Gains while recording.
    noise_m, quantum_m : float
        RMS of white measurement noise and the encoder's quantum on the positions, m.
    seed : int
    force_noise_n : float, optional
        Record ``<a>_force_n`` with this noise RMS (N); None: no force channel.
    act_delay : int
        Samples the recorder logs the measured position late (the first value repeated).
    ff : {"centred", "backward"}
        The feed-forward velocity: the planner's centred difference, or a backward difference
        of the commands (recorded as ``<a>_ff_vel_m_s``).

    Returns
    -------
    dict
        ``t_s`` and per axis ``<a>_cmd_m``, ``<a>_act_m`` (and ``<a>_ff_vel_m_s`` for a
        backward difference, ``<a>_force_n``), ready for :func:`oga.identify.trace.trace_csv`.
    """
    rng = np.random.default_rng(seed)
    n = len(sp)
    out = {"t_s": np.arange(n) * sp.dt}
    for a in axes:
        c = AXES.index(a)
        pd = np.ascontiguousarray(sp.pos[:, c])
        vd = np.ascontiguousarray(sp.vel[:, c]) if ff == "centred" else np.diff(pd, prepend=pd[0]) / sp.dt
        p, f = simulate_forces(axis_params(machine, a), pd[0], pd, vd,
                               np.full(n, kp_m_min_per_mm * KP_SI_PER_M_MIN_PER_MM), np.full(n, kf))
        meas = p + rng.normal(0.0, noise_m, n) if noise_m > 0 else p.copy()
        if quantum_m > 0:
            meas = np.round(meas / quantum_m) * quantum_m
        if act_delay:
            meas = np.concatenate([np.full(act_delay, meas[0]), meas[:-act_delay]])
        out[f"{a}_cmd_m"] = pd
        out[f"{a}_act_m"] = meas
        if ff != "centred":
            out[f"{a}_ff_vel_m_s"] = vd
        if force_noise_n is not None:
            out[f"{a}_force_n"] = f + rng.normal(0.0, force_noise_n, n) if force_noise_n else f
    return out


def random_cascade(base: Machine, axis: str, rng: np.random.Generator) -> tuple[Machine, float]:
    """``base`` with the cascade of ``axis`` drawn over wide ranges, and a Kp to record with.

    Mass 100-2000 kg, Coulomb friction 0-500 N (static 1-1.5 times it), Stribeck velocity
    0.5-3 mm/s, viscous 0-2000 N s/m, velocity-loop bandwidth 10-80 Hz (``Kv = m 2 pi f``),
    Tn 5-30 ms, force lag 0.2-1 ms (uniform; the Stribeck velocity log-uniform), dead time
    0-4 samples. The Kp, (m/min)/mm, is a quarter of the velocity loop's bandwidth in 1/s,
    within 0.5-3 (inside the plant's stable range).

    Returns
    -------
    machine : Machine
    kp_m_min_per_mm : float
    """
    mass = rng.uniform(100.0, 2000.0)
    bw = rng.uniform(10.0, 80.0)
    fc = rng.uniform(0.0, 500.0)
    cas = base.axis(axis).cascade.model_copy(update={
        "mass_kg": mass, "kv_n_s_m": mass * 2 * np.pi * bw, "tn_s": rng.uniform(5e-3, 30e-3),
        "coulomb_n": fc, "static_n": fc * rng.uniform(1.0, 1.5),
        "stribeck_m_s": float(np.exp(rng.uniform(np.log(5e-4), np.log(3e-3)))),
        "viscous_n_s_m": rng.uniform(0.0, 2000.0), "force_lag_s": rng.uniform(2e-4, 1e-3),
    })
    axis_model = base.axis(axis).model_copy(update={"cascade": cas})
    timing = base.timing.model_copy(update={"dead_time_samples": int(rng.integers(0, 5))})
    machine = base.model_copy(update={"axes": {**base.axes, axis: axis_model}, "timing": timing})
    kp = float(np.clip(2 * np.pi * bw / 4 / KP_SI_PER_M_MIN_PER_MM, 0.5, 3.0))
    return machine, kp
