"""The grey-box fit of one cascade axis to a recorded trace, through the optimizer's simulator.

The model is exactly :mod:`oga.model.simulate`'s cascade (velocity PI ``Kv``/``Tn``, force lag,
mass, Coulomb/static/Stribeck/viscous friction, dead time ``d`` samples), closed by the
recorded position loop: ``u_k = Kp_k (cmd_k - p_k) + Kf_k ff_k`` with the recorded gains
and setpoints. The simulated positions, shifted by ``l`` samples of measurement lag (a
recorder that logs the position ``l`` periods late), are fitted to the measured ones by
:func:`scipy.optimize.least_squares` (trust-region reflective, bounds; the Jacobian from
forward-mode derivatives through the simulation, :mod:`oga.identify.sensitivity`: one pass
instead of a simulation per parameter) over

    x = [log Kv, log Tn, log force lag, Fc, Fs - Fc, log vs, B]

with the mass held at the base machine's. Positions alone cannot tell the mass: scaling
mass, ``Kv``, every friction force and the force limit by one factor leaves every
position unchanged (divide the equation of motion by the mass), so they determine
``Kv/m``, ``Fc/m``, ...; a fit at the base mass is then the same plant as far as any
table can tell. Where the trace records the drive force, the force is linear in that
factor: the force joins the residual (weighted by its noise, at least
``IDENT_FORCE_NOISE_SHARE`` of its RMS) with the factor as an eighth entry of ``x``, the mass
is the factor's least-squares solution at the optimum and every force-like parameter is
rescaled with it. Positions alone leave the fit in a low-friction minimum on high friction and
a slow loop (bench draws 30, 48: Kv and Coulomb 15-60 % low at a residual a few times the
noise); the force pins the friction, and its regressions (:func:`friction_from_force`,
:func:`velocity_loop_from_force`) give the second start.

The logging lag ``l`` comes from the steady following error at constant speed
(:func:`logging_lag`: there the loop's error does not depend on the plant). The dead time
``d`` is searched by the nonlinear fit itself (a linear ARX fit of the velocity, tried
first, picks the wrong delay under encoder quantisation): upwards from 0, each fit from the
base values and from the fit one sample shorter with that sample moved out of its force lag
(the two trade against each other), until the residual clearly rises (with a force channel:
every ``d``); the least residual wins. Multi-start over the Stribeck velocity (the fit is not
convex in it). Confidence intervals from the Jacobian at the optimum,
``cov = (J'J)^-1 s^2`` with ``s^2`` the residual variance.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from oga.defaults import (
    IDENT_BOUNDS,
    IDENT_CONFIDENCE,
    IDENT_CORRELATION_LAGS,
    IDENT_FRACTION_MIN_GAIN,
    IDENT_FORCE_NOISE_SHARE,
    IDENT_FORCE_REGRESSION_V_M_S,
    IDENT_MAX_DEAD_SAMPLES,
    IDENT_MODEL_ERROR_MAX_SHARE,
    IDENT_MODEL_ERROR_NOISE_RATIO,
    IDENT_POOR_FORCE_SHARE,
    IDENT_POOR_NOISE_RATIO,
    IDENT_PROGRESS_EVERY_S,
    IDENT_STARTS,
)
from oga.errors import InputError, OgaError
from oga.identify.trace import AxisTrace, TraceError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Cascade, Machine, Timing

__all__ = ["AxisFit", "fit_axis", "check_fit_input", "axis_inputs", "PARAMETERS"]

#: Fitted cascade parameters, in the order of the result's tables.
PARAMETERS = ("mass_kg", "coulomb_n", "static_n", "stribeck_m_s", "viscous_n_s_m", "kv_n_s_m",
              "tn_s", "force_lag_s")
#: Most measurement lag searched, samples.
_MAX_LAG = 2
#: Function evaluations of the solver per dead-time candidate, and for the final fits.
_SEARCH_NFEV = 15
_FINAL_NFEV = 40
#: Second starting point of the dead-time search: the base's friction forces times this.
_FRICTION_START = 4.0
#: Relative step of the central differences of the packed parameters in ``x`` (the Jacobian).
_PACK_STEP = 1e-6
#: Entries of ``x`` clamped at 0 by the model (Fc, Fs - Fc, B): one-sided steps there.
_CLAMPED = (3, 4, 6)
#: A fractional dead time's fraction stays inside these (its whole ends are the whole fits).
_FRAC_BOUNDS = (1e-3, 1.0 - 1e-3)


class IdentifyError(OgaError, RuntimeError):
    """The fit failed (the solver's message wrapped)."""


@dataclass(frozen=True, eq=False)
class AxisFit:
    """The fit of one axis.

    Attributes
    ----------
    status : {"ok", "model-error", "poor"}
        ``model-error``: the model explains the trace only in part: its position residual
        exceeds ``IDENT_MODEL_ERROR_NOISE_RATIO`` times the trace's noise, or a parameter
        ended on its physical bound (``at_bounds``); the identified uncertainty set is widened
        by the evidence (:func:`oga.identify.write.uncertainty_of`). ``poor``: the model does
        not cover the plant: the residual RMS exceeds ``IDENT_POOR_NOISE_RATIO`` times the
        noise, the model-error share ``IDENT_MODEL_ERROR_MAX_SHARE``, or the force residual
        ``IDENT_POOR_FORCE_SHARE`` of the recorded force's RMS (the values are then the best
        the model gives). On high friction the position residual of a wrong fit can sit as
        close to the noise as a right one's (bench draw 48: 3.3 times, both); the force tells
        them apart.
    cascade : Cascade
        The fitted cascade (force limit and friction smoothing from the base).
    dead_time_samples : int or float
        Fitted dead time, samples: a whole number, or a fraction where that fits measurably
        better (``IDENT_FRACTION_MIN_GAIN``).
    lag_samples : int
        Fitted measurement lag.
    values, ci_low, ci_high : dict[str, float]
        Each fitted parameter (:data:`PARAMETERS`) with its confidence interval
        (``IDENT_CONFIDENCE``). Without a force channel the mass is the base's and its
        interval that value (``mass_identified`` False).
    mass_identified : bool
        True when a force channel fixed the mass.
    residual_rms_m : float
        RMS of the position residual, m.
    noise_rms_m : float
        Estimate of the measurement noise (RMS of the second difference of the measured
        positions over sqrt(6), where the axis stands still), m.
    force_residual_rms_n : float or None
    candidates : list of (d, l, residual RMS m)
        Every dead time and lag tried (fractional ones included).
    fit_time_s : float
    n_samples : int
    correlation_samples : float
        Correlation time of the position residual, samples (``1 + 2 sum rho_k`` over its
        positive autocorrelations, at most ``IDENT_CORRELATION_LAGS`` lags): 1 for white
        noise, large where the residual is what the model leaves out. The intervals are
        widened by its square root (the independent samples are fewer by that factor).
    model_error_share : float
        The part of the position residual above the noise, relative to the velocity loop's
        imprint on the positions (RMS of the measured positions minus those of the recorded
        position loop around an ideal velocity loop with the fitted dead time,
        :func:`oga.identify.sim.ideal_loop_positions`): how much of what the model is there
        to predict it does not.
    at_bounds : tuple of str
        Parameters that ended on a physical bound (``IDENT_BOUNDS``).
    model_error_changes : dict[str, float]
        Per cascade parameter (the uncertainty section's names) the relative change, and for
        ``dead_time_samples`` the samples, that alone moves the simulated positions by the
        unexplained residual (its RMS above the noise, through the Jacobian at the optimum):
        the model error expressed as parameter error, each parameter's own scale.
    """

    status: str
    cascade: Cascade
    dead_time_samples: int
    lag_samples: int
    values: dict
    ci_low: dict
    ci_high: dict
    mass_identified: bool
    residual_rms_m: float
    noise_rms_m: float
    force_residual_rms_n: float | None
    candidates: list = field(default_factory=list)
    fit_time_s: float = 0.0
    n_samples: int = 0
    correlation_samples: float = 1.0
    model_error_share: float = 0.0
    at_bounds: tuple = ()
    model_error_changes: dict = field(default_factory=dict)

    @property
    def noise_ratio(self) -> float:
        """Position residual RMS over the noise estimate."""
        return self.residual_rms_m / max(self.noise_rms_m, 1e-12)


def axis_inputs(tr: AxisTrace, dt: float):
    """(cmd, ff velocity, Kp in 1/s, Kf) of an axis trace as float64 arrays; the feed-forward
    velocity is the centred difference of the commands (our planner's) where not recorded."""
    cmd = np.ascontiguousarray(tr.cmd_m, dtype=np.float64)
    if tr.ff_vel_m_s is not None:
        ff = np.ascontiguousarray(tr.ff_vel_m_s, dtype=np.float64)
    else:
        ff = np.gradient(cmd, dt) if cmd.size > 1 else np.zeros_like(cmd)
    kp = np.ascontiguousarray(tr.kp_m_min_per_mm * KP_SI_PER_M_MIN_PER_MM, dtype=np.float64)
    kf = np.ascontiguousarray(tr.kf, dtype=np.float64)
    return cmd, ff, kp, kf


def _machine(base: Machine, axis: str, cas: Cascade, dead: float) -> Machine:
    """``base`` with only ``axis``, its cascade replaced, and dead time ``dead`` (samples,
    whole or fractional)."""
    whole = float(dead).is_integer()
    ax = base.axis(axis).model_copy(update={"cascade": cas, "uncertainty": None,
                                             "dead_time_samples": None if whole else float(dead)})
    timing = Timing(te_s=base.te, substeps=base.timing.substeps,
                    dead_time_samples=int(dead) if whole else 0)
    return base.model_copy(update={"axes": {axis: ax}, "timing": timing})


class _Model:
    """Simulation of one axis for a parameter vector ``x`` (module docstring)."""

    def __init__(self, base: Machine, axis: str, tr: AxisTrace, dt: float, mass: float,
                 use_force: bool = False):
        self.base, self.axis, self.mass = base, axis, mass
        self.cas0 = base.axis(axis).cascade
        self.cmd, self.ff, self.kp, self.kf = axis_inputs(tr, dt)
        self.meas = np.ascontiguousarray(tr.act_m, dtype=np.float64)
        self.p0 = start_position(self.cmd, self.meas)
        # the recorded force as a second channel (x[7] = log of its scale: mass / base mass),
        # weighted to um per N by the two channels' noise (the force's at least a share of it)
        self.force = None
        if use_force and tr.force_n is not None:
            self.force = np.ascontiguousarray(tr.force_n, dtype=np.float64)
            f_noise = max(_noise_rms(self.meas, self.force),
                          IDENT_FORCE_NOISE_SHARE * float(np.sqrt(np.mean(self.force ** 2))), 1e-9)
            self.force_weight = max(_noise_rms(self.meas), 1e-9) * 1e6 / f_noise

    def cascade(self, x) -> Cascade:
        fc, dfs, b = max(x[3], 0.0), max(x[4], 0.0), max(x[6], 0.0)
        return self.cas0.model_copy(update={
            "mass_kg": self.mass, "kv_n_s_m": math.exp(x[0]), "tn_s": math.exp(x[1]),
            "force_lag_s": math.exp(x[2]), "coulomb_n": fc, "static_n": fc + dfs,
            "stribeck_m_s": math.exp(x[5]), "viscous_n_s_m": b,
        })

    def params(self, x, dead: int, frac: bool = False) -> np.ndarray:
        """Packed parameters; ``frac``: the dead time is ``dead + x[-1]`` (its fraction last
        in ``x``, inside (0, 1))."""
        from oga.model.simulate import _pack

        total = dead + float(x[-1]) if frac else dead
        return _pack(_machine(self.base, self.axis, self.cascade(x), total), self.axis, True)

    def simulate(self, x, dead: int, frac: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(positions, forces) simulated, shape (N,) each."""
        from oga.identify.sim import simulate_forces

        return simulate_forces(self.params(x, dead, frac), self.p0, self.cmd, self.ff, self.kp,
                               self.kf)

    def jacobian(self, x, dead: int, lag: int, frac: bool = False) -> np.ndarray:
        """d :meth:`residual` / dx, um per unit of ``x``, shape (N - lag, x.size): forward-mode
        derivatives through the simulation (:mod:`oga.identify.sensitivity`) in one pass, the
        packed parameters' derivatives in ``x`` by central differences (a few small matrix
        exponentials each; one-sided where a clamped entry sits at 0); a fractional dead
        time's is its own packed entry."""
        from oga.identify.sensitivity import forces_and_sensitivities
        from oga.model.simulate import _FRAC

        params = self.params(x, dead, frac)
        npl = 7  # plant entries of x (then x[7]: the force's scale; last: the fraction)
        dpar = np.zeros((npl + frac, params.size))
        for j in range(npl):
            h = _PACK_STEP * max(1.0, abs(x[j]))
            up, down = x.copy(), x.copy()
            up[j] += h
            down[j] -= h
            if j in _CLAMPED and down[j] < 0.0:
                dpar[j] = (self.params(up, dead, frac) - params) / h
            else:
                dpar[j] = (self.params(up, dead, frac) - self.params(down, dead, frac)) / (2 * h)
        if frac:
            dpar[npl, _FRAC] = 1.0
        _, dp, f, df = forces_and_sensitivities(params, dpar, self.p0, self.cmd, self.ff, self.kp,
                                                self.kf)
        jac = dp[: dp.shape[0] - lag] * 1e6
        if self.force is not None:
            m = f.size - lag
            scale = math.exp(x[7]) * self.force_weight
            jac = np.block([[jac[:, :npl], np.zeros((m, 1)), jac[:, npl:]],
                            [df[:m, :npl] * scale, (f[:m] * scale)[:, None],
                             df[:m, npl:] * scale]])
        if np.all(np.isfinite(jac)):
            return jac
        # a tangent that overflowed (a trial plant at the edge of stability): forward differences
        f0 = self.residual(x, dead, lag, frac)
        for j in range(x.size):
            h = _PACK_STEP * max(1.0, abs(x[j]))
            step = x.copy()
            step[j] += h
            jac[:, j] = (self.residual(step, dead, lag, frac) - f0) / h
        return jac

    def residual(self, x, dead: int, lag: int, frac: bool = False) -> np.ndarray:
        """Simulated minus measured positions, um (the simulation ``lag`` samples earlier),
        shape (N - lag,); with the force channel followed by the weighted force residual."""
        from oga.model.simulate import simulate_axis

        if self.force is None:
            p, _ = simulate_axis(self.params(x, dead, frac), self.p0, self.cmd, self.ff,
                                 self.kp, self.kf)
            return (p[: p.size - lag] - self.meas[lag:]) * 1e6
        p, f = self.simulate(x, dead, frac)
        m = p.size - lag
        return np.concatenate([(p[:m] - self.meas[lag:]) * 1e6,
                               (math.exp(x[7]) * f[:m] - self.force[lag:]) * self.force_weight])


def _x0(cas: Cascade, vs_factor: float = 1.0) -> np.ndarray:
    return np.array([math.log(cas.kv_n_s_m), math.log(cas.tn_s), math.log(cas.force_lag_s),
                     cas.coulomb_n, cas.static_n - cas.coulomb_n,
                     math.log(cas.stribeck_m_s * vs_factor), cas.viscous_n_s_m])


#: The entries of ``x`` (module doc) and the physical bound of each (``IDENT_BOUNDS``).
_X_NAMES = ("kv_n_s_m", "tn_s", "force_lag_s", "coulomb_n", "static_n", "stribeck_m_s",
            "viscous_n_s_m")


def _bounds(cas: Cascade, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """The physical bounds of ``x`` (:data:`oga.defaults.IDENT_BOUNDS`) at ``mass`` (kg)."""
    b = IDENT_BOUNDS
    flim = cas.force_limit_n
    two_pi_m = 2 * math.pi * mass
    lo = [math.log(two_pi_m * b["velocity_loop_hz"][0]), math.log(b["tn_s"][0]),
          math.log(b["force_lag_s"][0]), mass * b["coulomb_n_per_kg"][0],
          mass * b["stribeck_rise_n_per_kg"][0], math.log(b["stribeck_m_s"][0]),
          mass * b["viscous_1_s"][0]]
    hi = [math.log(two_pi_m * b["velocity_loop_hz"][1]), math.log(b["tn_s"][1]),
          math.log(b["force_lag_s"][1]), min(flim / 2, mass * b["coulomb_n_per_kg"][1]),
          min(flim / 2, mass * b["stribeck_rise_n_per_kg"][1]), math.log(b["stribeck_m_s"][1]),
          mass * b["viscous_1_s"][1]]
    return np.array(lo), np.array(hi)


def _at_bounds(x, lo, hi) -> tuple[str, ...]:
    """The plant entries of ``x`` (and the force's scale, ``mass_kg``) that ended on a
    physical bound; a friction force of zero is physical (no friction), not a bound."""
    names = (*_X_NAMES, "mass_kg")
    out = []
    for i in range(min(len(names), x.size)):
        span = hi[i] - lo[i]
        low = x[i] <= lo[i] + 1e-6 * span and names[i] not in ("coulomb_n", "static_n",
                                                              "viscous_n_s_m")
        if low or x[i] >= hi[i] - 1e-6 * span:
            out.append(names[i])
    return tuple(out)


#: The uncertainty section's fields and the entry of ``x`` each moves (the mass moves the
#: loop as Kv does: positions depend on Kv / m).
_X_OF_FIELD = {"kv_n_s_m": 0, "mass_kg": 0, "tn_s": 1, "force_lag_s": 2, "coulomb_n": 3,
               "static_n": 4, "stribeck_m_s": 5, "viscous_n_s_m": 6}


def _equivalent_changes(model, r, n: int, unexplained_m: float, dead, lag: int,
                        frac: bool) -> dict[str, float]:
    """:attr:`AxisFit.model_error_changes`: ``unexplained_m`` (m) over the RMS of each
    parameter's column of the Jacobian (the positions' rows), per relative change of the
    parameter (log entries as they are, force entries times their value; a force of zero has
    no relative change: 0); the dead time's column by a difference of half a sample."""
    jac = r.jac[:n]
    col_rms = np.sqrt(np.mean(np.asarray(jac) ** 2, axis=0)) * 1e-6  # m per unit of x
    x = r.x
    scale = {3: x[3], 4: x[3] + x[4], 6: x[6]}  # relative change of Fc, Fs (Fc held), B
    out = {}
    for name, i in _X_OF_FIELD.items():
        s = col_rms[i] * abs(scale.get(i, 1.0))
        out[name] = float(unexplained_m / s) if s > 0 else 0.0
    if unexplained_m > 0:
        d0 = math.floor(dead)
        base = model.residual(x, dead if not frac else d0, lag, frac)[:n]
        xs = x.copy() if frac else np.append(x, 0.5)
        if frac:
            xs[-1] = min(xs[-1] + 0.5, 1.0 - 1e-3) if xs[-1] < 0.5 else xs[-1] - 0.5
        step = abs(float(xs[-1]) - (float(x[-1]) if frac else 0.0))
        moved = model.residual(xs, d0, lag, True)[:n]
        s = float(np.sqrt(np.mean((moved - base) ** 2))) * 1e-6 / step
        out["dead_time_samples"] = float(unexplained_m / s) if s > 0 else 0.0
    else:
        out["dead_time_samples"] = 0.0
    return out


def correlation_samples(res: np.ndarray, lags: int = IDENT_CORRELATION_LAGS) -> float:
    """Correlation time of a residual, samples: ``1 + 2 sum_k rho_k`` over its
    autocorrelations ``rho_k`` from lag 1 on, up to the first that is not positive or
    ``lags`` (Geyer's initial positive sequence): 1 for white noise, about
    ``(1 + rho) / (1 - rho)`` for a first-order colour ``rho``."""
    r = np.asarray(res, dtype=np.float64) - float(np.mean(res))
    n = r.size
    var = float(r @ r)
    if n < 3 or var == 0.0:
        return 1.0
    size = 1 << int(math.ceil(math.log2(2 * n)))
    spec = np.fft.rfft(r, size)
    acf = np.fft.irfft(spec * np.conj(spec), size)[: min(lags, n - 1) + 1] / var
    total = 1.0
    for k in range(1, acf.size):
        if acf[k] <= 0.0:
            break
        total += 2.0 * float(acf[k])
    return total


def logging_lag(cmd, ff, kp_si, kf, meas, dt: float) -> int:
    """Samples by which the log's measured position lags the loop's, from the steady
    following error: at a constant speed ``v`` the velocity PI has no error, so the loop's
    ``pd - p = (v - Kf ff) / Kp`` whatever the plant, and a log ``l`` samples late adds
    ``l v Te``. Median over the samples whose commanded speed (above 1 mm/s) has not changed
    for 300 samples; 0 if there are none. Clipped to 0 .. :data:`_MAX_LAG`."""
    v = np.gradient(cmd, dt)
    changed = np.abs(np.diff(v, prepend=v[0])) > 1e-9
    window = 300
    recent = np.convolve(changed.astype(np.float64), np.ones(window))[: v.size]
    steady = (recent == 0) & (np.abs(v) > 1e-3)
    steady[:window] = False
    if steady.sum() < 10:
        return 0
    extra = (cmd - meas - (v - kf * ff) / kp_si)[steady] / (v[steady] * dt)
    return int(np.clip(np.round(np.median(extra)), 0, _MAX_LAG))


def _smooth_rate(x: np.ndarray, dt: float) -> np.ndarray:
    """Centred difference of ``x`` per second, averaged over 5 samples (against the encoder's
    noise), shape of ``x``."""
    return np.convolve(np.gradient(x, dt), np.ones(5) / 5, mode="same")


def friction_from_force(meas, force, dt: float, v_min: float = IDENT_FORCE_REGRESSION_V_M_S):
    """Mass, Coulomb and viscous friction from a recorded drive force: least squares of
    ``F = m a + Fc sign(v) + B v`` over the samples moving faster than ``v_min`` (m/s; well
    above the Stribeck band, where the static and Stribeck terms have died out), with ``v``
    and ``a`` the centred differences of the measured positions (smoothed over 5 samples
    against the encoder's noise).

    Parameters
    ----------
    meas, force : ndarray, shape (N,)
        Measured positions (m) and drive forces (N).
    dt : float
        Period, s.
    v_min : float

    Returns
    -------
    (mass_kg, coulomb_n, viscous_n_s_m) or None
        None where fewer than 100 samples move that fast, the columns are degenerate or the
        result is not physical (mass <= 0).
    """
    v = _smooth_rate(meas, dt)
    a = _smooth_rate(v, dt)
    use = np.abs(v) > v_min
    use[:5] = use[-5:] = False
    if use.sum() < 100:
        return None
    cols = np.column_stack([a[use], np.sign(v[use]), v[use]])
    sol, _, rank, _ = np.linalg.lstsq(cols, np.asarray(force, dtype=np.float64)[use], rcond=None)
    if rank < 3 or not np.all(np.isfinite(sol)) or sol[0] <= 0:
        return None
    return float(sol[0]), max(float(sol[1]), 0.0), max(float(sol[2]), 0.0)


def velocity_loop_from_force(u, meas, force, dt: float, max_dead: int):
    """``Kv`` and ``Tn`` from a recorded drive force: the velocity PI gives
    ``F = Kv e + (Kv / Tn) sum(e) dt`` with ``e`` the position loop's output ``u`` (known: the
    recorded gains on the recorded setpoints and positions) ``d`` samples late minus the
    velocity; least squares (with an offset) for each dead time ``d`` in 0 .. ``max_dead``,
    the least residual wins. Force lag and the velocity's smoothing bias it at high bandwidth:
    a starting point, not a result.

    Parameters
    ----------
    u, meas, force : ndarray, shape (N,)
        Velocity command of the position loop (m/s), measured positions (m), forces (N).
    dt : float
    max_dead : int

    Returns
    -------
    (kv_n_s_m, tn_s, dead_time_samples) or None
        None where no dead time gives a positive Kv and Tn.
    """
    n = meas.size
    v = _smooth_rate(meas, dt)
    force = np.asarray(force, dtype=np.float64)
    best = None
    for d in range(min(max_dead, n - 1) + 1):
        e = np.concatenate([np.zeros(d), u[: n - d]]) - v
        cols = np.column_stack([e, np.cumsum(e) * dt, np.ones(n)])
        sol, _, rank, _ = np.linalg.lstsq(cols, force, rcond=None)
        if rank < 3 or not (sol[0] > 0 and sol[1] > 0 and np.all(np.isfinite(sol))):
            continue
        rss = float(np.sum((cols @ sol - force) ** 2))
        if best is None or rss < best[0]:
            best = (rss, float(sol[0]), float(sol[0] / sol[1]), d)
    return None if best is None else best[1:]


def start_position(cmd: np.ndarray, meas: np.ndarray) -> float:
    """Where the axis stands when the trace starts (m): the simulation's ``p0``.

    The median of the positions ``meas`` (N,) before the command ``cmd`` (N,) first moves;
    the command itself where they do not tell the two apart (within three standard errors
    of a median of the noise, or half the positions' resolution): a standing error below the
    noise is not measurable, and a simulation started off its command by one noisy sample is
    driven by that error while the axis stands, stuck in its friction and never at a fixed
    point, so it runs every period's sub-steps (the standing Z of the e2e test's trace with
    its first sample 0.2 um off: each fit evaluation took twice as long).
    """
    moved = np.flatnonzero(cmd != cmd[0])
    rest = meas[: moved[0] if moved.size else meas.size]
    p = float(np.median(rest))
    steps = np.abs(np.diff(rest))
    resolution = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
    tol = max(3.0 * 1.253 * _noise_rms(meas) / math.sqrt(rest.size), 0.5 * resolution)
    return float(cmd[0]) if abs(p - cmd[0]) <= tol else p


def _noise_rms(meas: np.ndarray, signal: np.ndarray | None = None) -> float:
    """Noise RMS of ``signal`` (default: the positions ``meas``) from its second differences
    where the axis stands (white noise: their variance is 6 sigma^2); all of them if the axis
    never stands."""
    d2 = np.diff(meas if signal is None else signal, 2)
    still = np.abs(np.diff(meas)[1:]) < 1e-6
    if still.sum() < 20:
        return float(np.sqrt(np.mean(d2 ** 2) / 6))
    return float(np.sqrt(np.mean(d2[still] ** 2) / 6))


def check_fit_input(base: Machine, axis: str, tr: AxisTrace, dt: float) -> None:
    """What :func:`fit_axis` needs, checked: the trace's period is the machine's Te, the
    axis is a cascade, the trace moves it (>= 10 um) over >= 200 samples.

    Raises
    ------
    InputError
        TraceError for the trace, MachineError for an axis the machine lacks.
    """
    if not math.isclose(dt, base.te, rel_tol=1e-6):
        raise TraceError(f"the trace's period {dt:g} s differs from the machine's Te {base.te:g} s")
    if base.axis(axis).cascade is None:
        raise InputError(f"axis {axis} of {base.name} is not a cascade axis")
    if tr.cmd_m.size < 200 or np.ptp(tr.cmd_m) < 1e-5:
        raise TraceError(f"axis {axis}: the trace must move the axis (>= 10 um) over >= 200 samples")


class _Progress:
    """The fraction of a fit done, reported to ``report`` (at most every
    ``IDENT_PROGRESS_EVERY_S``): each of ``planned`` solves an equal share, inside a solve its
    evaluations (residuals and Jacobians) against its budget. Never falls; 1 only at the end."""

    def __init__(self, report, planned: int):
        self.report, self.planned = report, planned
        self.solves, self.calls, self.budget = 0, 0, 1
        self.last = -math.inf

    def start(self, budget: int) -> None:
        self.calls, self.budget = 0, max(budget, 1)

    def tick(self) -> None:
        """One evaluation (a residual or a Jacobian)."""
        self.calls += 1
        now = time.monotonic()
        if self.report is not None and now - self.last >= IDENT_PROGRESS_EVERY_S:
            self.last = now
            inside = min(self.calls / self.budget, 0.99)
            self.report(min((self.solves + inside) / self.planned, 0.99))

    def solved(self) -> None:
        self.solves = min(self.solves + 1, self.planned - 1)


def fit_axis(base: Machine, axis: str, tr: AxisTrace, dt: float, *,
             max_dead: int = IDENT_MAX_DEAD_SAMPLES, starts: int = IDENT_STARTS,
             progress=None) -> AxisFit:
    """Fit the cascade of ``axis`` of ``base`` to the trace ``tr`` (period ``dt``).

    Parameters
    ----------
    base : Machine
        The base machine: its cascade of the axis starts the fit and gives the force limit,
        friction smoothing, Te and sub-steps; its mass is kept where no force is recorded.
    axis : str
    tr : AxisTrace
    dt : float
        Trace period, s; must equal the machine's Te.
    max_dead : int
        Largest dead time searched, samples.
    starts : int
        Starting points of the Stribeck velocity (multi-start).
    progress : callable, optional
        Called with the fraction done (0..1, never falling) at least every
        ``IDENT_PROGRESS_EVERY_S`` of work while the solver runs, and with 1 at the end; an
        exception it raises ends the fit (a cancelled job).

    Returns
    -------
    AxisFit

    Raises
    ------
    InputError
        Period differs from Te, axis not a cascade, trace too short or not moving.
    IdentifyError
        The solver failed.
    """
    t_start = time.process_time()
    # tiny matrices (the sub-step exponentials of every trial plant) and a tall Jacobian: a
    # BLAS thread pool costs far more than it gives here (16 ms instead of 0.14 ms a packing)
    with threadpool_limits(limits=1, user_api="blas"):
        fit = _fit_axis(base, axis, tr, dt, max_dead, starts, t_start, progress)
    if progress is not None:
        progress(1.0)
    return fit


class _Solver:
    """Bounded least-squares solves of one axis's :class:`_Model` (each counted in the
    progress ``done``)."""

    def __init__(self, model, axis: str, lo, hi, done: _Progress):
        self.model, self.axis, self.lo, self.hi, self.done = model, axis, lo, hi, done

    def _residual(self, x, dead, lag, frac):
        self.done.tick()
        return self.model.residual(x, dead, lag, frac)

    def _jacobian(self, x, dead, lag, frac):
        self.done.tick()
        return self.model.jacobian(x, dead, lag, frac)

    def solve(self, x0, dead, lag, nfev, frac=False):
        """The solve from ``x0`` at a dead time and lag (``frac``: its fraction appended to x)."""
        from scipy.optimize import least_squares

        self.done.start(2 * nfev)  # each evaluation and its Jacobian
        lo, hi = self.lo, self.hi
        lo_f, hi_f = (np.append(lo, _FRAC_BOUNDS[0]), np.append(hi, _FRAC_BOUNDS[1])) if frac \
            else (lo, hi)
        try:
            r = least_squares(self._residual, np.clip(x0, lo_f + 1e-9, hi_f - 1e-9),
                              jac=self._jacobian, args=(dead, lag, frac), bounds=(lo_f, hi_f),
                              x_scale="jac", method="trf", max_nfev=nfev)
        except (ValueError, np.linalg.LinAlgError) as err:
            raise IdentifyError(f"axis {self.axis}: the fit failed: {err}") from None
        self.done.solved()
        return r


def _start_bounds(model, cas0, mass0, reg):
    """``(lo, hi, x_base)``: the bounds and the base's start, with the force's scale (the
    mass over the base's, x[7]) where a force is recorded."""
    lo, hi = _bounds(cas0, mass0)
    x_base = _x0(cas0)
    if model.force is not None:
        lo = np.append(lo, math.log(IDENT_BOUNDS["mass_ratio"][0]))
        hi = np.append(hi, math.log(IDENT_BOUNDS["mass_ratio"][1]))
        x_base = np.append(x_base, math.log(reg[0] / mass0) if reg is not None else 0.0)
    return lo, hi, np.clip(x_base, lo, hi)


def _high_start(model, cas0, mass0, reg, x_base, lo, hi, force_n, dt, max_dead):
    """The second start of each dead time: 4 times the base's friction, or, where the force
    is recorded, the friction's level and the velocity loop from it.

    Two starts per dead time: the fit is not convex in the friction level, and a real axis
    may have much more than its base. From the force (regressions:
    :func:`friction_from_force`, :func:`velocity_loop_from_force`) in the fit's units (scaled
    to the base mass): on high friction and a slow loop the base's and 4x its friction both
    stop in a low-friction minimum (bench draws 30, 48).
    """
    x_high = x_base.copy()
    x_high[[3, 4, 6]] *= _FRICTION_START
    if reg is not None:
        m_reg, fc_reg, b_reg = reg
        x_high[3], x_high[6] = fc_reg * mass0 / m_reg, b_reg * mass0 / m_reg
        x_high[4] = x_high[3] * (cas0.static_n / cas0.coulomb_n - 1.0) if cas0.coulomb_n > 0 else 0.0
        u = model.kp * (model.cmd - model.meas) + model.kf * model.ff
        loop = velocity_loop_from_force(u, model.meas, force_n, dt, max_dead)
        if loop is not None:
            x_high[0], x_high[1] = math.log(loop[0] * mass0 / m_reg), math.log(loop[1])
    return np.clip(x_high, lo, hi)


def _shifted_start(x, dt: float, lo) -> np.ndarray | None:
    """The fit ``x`` at dead time ``d`` as a start at ``d + 1``: its force lag one sample
    shorter, or None where that leaves less than the lag's lower bound ``lo[2]``.

    The force lag and the dead time trade against each other: a first-order lag ``T`` delays
    the slow part of the motion as ``T`` of dead time does (``exp(-sT) = 1/(1 + sT)`` to first
    order), so a fit one sample short of the true dead time takes that sample into its force
    lag (random plant 3: d = 2 with a lag of 1.15 ms for the true 3 and 0.33 ms). Started at
    the truth with the base's lag instead, the solver can drive the lag onto its bound and stop
    there (3 with a residual 17 times the noise while 2 was 1.8): which of the two happens
    depended on the excitation's length (0.3 % shorter: the dead time flipped, issue 29).
    """
    tau = math.exp(x[2]) - dt
    if not tau > math.exp(lo[2]):
        return None
    out = x.copy()
    out[2] = math.log(tau)
    return out


def _search_dead_times(solver: _Solver, starts_x, lag, max_dead, dt) -> dict:
    """Short fits per dead time upwards from 0, each from the starts ``starts_x`` and from the
    best fit one sample shorter with that sample taken out of its force lag
    (:func:`_shifted_start`), until the residual clearly rises twice (without a force channel).
    Returns ``{(dead, lag): result}``."""
    tried = {}
    for dead in range(max_dead + 1):
        chained = _shifted_start(tried[(dead - 1, lag)].x, dt, solver.lo) if dead else None
        starts = (*starts_x, chained) if chained is not None else starts_x
        tried[(dead, lag)] = min((solver.solve(x0, dead, lag, _SEARCH_NFEV) for x0 in starts),
                                 key=lambda r: r.cost)
        (d_best, _), r_best = min(tried.items(), key=lambda kv: kv[1].cost)
        # with a force channel every dead time is tried: its residual is not monotone in the
        # dead time (bench draw 0 of the recovery test: d = 0 < 1 < 2 > 3, the truth)
        if (solver.model.force is None and dead > d_best + 1
                and tried[(dead, lag)].cost > 1.5 * r_best.cost):
            break
    return tried


def _refine(solver: _Solver, tried: dict, starts: int):
    """``(result, dead, lag)``: the two best pairs of ``tried`` fitted to convergence (a short
    search fit may stop early; ``tried`` updated), then the multi-start over the Stribeck
    velocity."""
    best = None
    for (dead, lag), r in sorted(tried.items(), key=lambda kv: kv[1].cost)[:2]:
        r_f = solver.solve(r.x, dead, lag, _FINAL_NFEV)
        tried[(dead, lag)] = r_f
        if best is None or r_f.cost < best[0].cost:
            best = (r_f, dead, lag)
    r, dead, lag = best
    for k in range(1, max(1, starts)):
        x0 = r.x.copy()
        x0[5] += math.log(3.0) * (1 if k % 2 else -1) * ((k + 1) // 2)
        r_k = solver.solve(x0, dead, lag, _FINAL_NFEV)
        if r_k.cost < best[0].cost:
            best = (r_k, dead, lag)
    return best


def _fractional(solver: _Solver, tried: dict, r, dead, lag, max_dead, noise, pos_rms):
    """``(result, frac, dead)``: a fractional dead time, in the sample towards the better of
    the whole neighbours, started next to the whole one: kept where its position residual's
    mean square is measurably below the whole one's (not tried where the whole one is at the
    noise already: nothing could be measurably better). ``tried`` updated."""

    def cost_of(d):
        return tried[(d, lag)].cost if (d, lag) in tried else math.inf

    d0, f0 = ((dead, 0.1) if dead == 0 or cost_of(dead + 1) <= cost_of(dead - 1)
              else (dead - 1, 0.9))
    if d0 + 1 <= max_dead and (1.0 - IDENT_FRACTION_MIN_GAIN) * pos_rms(r) ** 2 > noise ** 2:
        r_f = solver.solve(np.append(r.x, f0), d0, lag, _FINAL_NFEV, frac=True)
        tried[(d0 + float(r_f.x[-1]), lag)] = r_f
        if pos_rms(r_f) ** 2 < (1.0 - IDENT_FRACTION_MIN_GAIN) * pos_rms(r) ** 2:
            return r_f, True, d0 + float(r_f.x[-1])
    return r, False, dead


def _covariance(r, n):
    """``(cov, tau)``: the parameters' covariance (x per um^2) and the residual's correlation
    time, samples. A residual that is not white holds fewer independent samples than its
    length: the variance widened by its correlation time."""
    dof = max(r.fun.size - r.x.size, 1)
    s2 = 2 * r.cost / dof
    tau = correlation_samples(r.fun[:n])
    try:
        cov = np.linalg.pinv(r.jac.T @ r.jac) * s2 * tau  # x per um^2: s2 in um^2
    except np.linalg.LinAlgError:
        cov = np.full((r.x.size, r.x.size), np.inf)
    return cov, tau


def _force_scale(model, x, dead, lag, n, force_n, mass0, axis):
    """``(mass, mass_sd, f_rms, ratio, f_meas)``: the mass from the force channel (the force
    is linear in the common scale factor); the base's mass without one."""
    mass, mass_sd, f_rms, ratio, f_meas = mass0, 0.0, None, 1.0, None
    if force_n is None:
        return mass, mass_sd, f_rms, ratio, f_meas
    _, f_unit = model.simulate(x, dead)
    f_unit = f_unit[: n]
    f_meas = np.asarray(force_n, dtype=np.float64)[lag:]
    den = float(f_unit @ f_unit)
    if den > 0:
        ratio = float(f_unit @ f_meas) / den
        if not ratio > 0:  # a force recorded with the opposite sign, or unrelated
            raise TraceError(f"column {axis}_force_n: the recorded force opposes the force "
                             f"the fit needs (scale {ratio:.3g}); record it with the sign "
                             f"of the axis's motion")
        res = f_meas - ratio * f_unit
        f_rms = float(np.sqrt(np.mean(res ** 2)))
        ratio_sd = math.sqrt(float(res @ res) / max(n - 1, 1) / den)
        mass, mass_sd = mass0 * ratio, mass0 * ratio_sd
    return mass, mass_sd, f_rms, ratio, f_meas


def _intervals(x, cov, mass, mass_sd, ratio, force: bool):
    """``(values, low, high)`` of every parameter at the confidence ``IDENT_CONFIDENCE``.

    With a force channel the mass's scale is ``x[7]``, fitted jointly with the rest: its
    variance (and covariances) from the joint ``cov``, at least the scale regression's
    ``mass_sd``. The regression alone takes the force's shape as exact; its interval was
    ten times too narrow (mass 4e-5 relative, moved by 8e-4 by an excitation 1 % shorter; the
    joint one 3.6e-4, random plant 1).
    """
    from scipy.stats import norm

    z = float(norm.ppf(0.5 + IDENT_CONFIDENCE / 2))
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    rel_m = mass_sd / mass if mass > 0 else 0.0
    var_s = max(float(cov[7, 7]), rel_m ** 2) if force else 0.0  # of log(mass / base mass)

    def with_scale(i):  # covariance of x[i] (or the sum of entries i) with the scale
        return float(np.sum(cov[i, 7])) if force else 0.0

    vals, los, his = {}, {}, {}

    def log_param(name, i, scaled):
        v = math.exp(x[i]) * (ratio if scaled else 1.0)
        var = sd[i] ** 2 + ((var_s + 2 * with_scale(i)) if scaled else 0.0)
        w = min(z * math.sqrt(max(var, 0.0)), 700.0)  # unidentifiable: an interval of (0, inf)
        vals[name], los[name], his[name] = v, v * math.exp(-w), v * math.exp(w)

    def lin_param(name, entries, var):
        v = float(np.sum(x[entries])) * ratio
        var_v = var * ratio ** 2 + v ** 2 * var_s + 2 * ratio * v * with_scale(entries)
        half = z * math.sqrt(max(var_v, 0.0))
        vals[name], los[name], his[name] = v, max(v - half, 0.0), v + half

    half_m = z * mass * math.sqrt(var_s)
    vals["mass_kg"], los["mass_kg"], his["mass_kg"] = mass, mass - half_m, mass + half_m
    lin_param("coulomb_n", [3], cov[3, 3])
    lin_param("static_n", [3, 4], cov[3, 3] + cov[4, 4] + 2 * cov[3, 4])
    log_param("stribeck_m_s", 5, False)
    lin_param("viscous_n_s_m", [6], cov[6, 6])
    log_param("kv_n_s_m", 0, True)
    log_param("tn_s", 1, False)
    log_param("force_lag_s", 2, False)
    return vals, los, his


def _status(rms, noise, share, f_rms, f_meas, ends) -> str:
    """``poor``, ``model-error`` or ``ok`` (see :class:`AxisFit`)."""
    f_level = float(np.sqrt(np.mean(f_meas ** 2))) if f_rms is not None else 0.0
    if (rms > IDENT_POOR_NOISE_RATIO * max(noise, 1e-9) or share > IDENT_MODEL_ERROR_MAX_SHARE
            or (f_rms is not None and f_rms > IDENT_POOR_FORCE_SHARE * f_level)):
        return "poor"
    if rms > IDENT_MODEL_ERROR_NOISE_RATIO * max(noise, 1e-9) or ends:
        return "model-error"
    return "ok"


def _fit_axis(base, axis, tr, dt, max_dead, starts, t_start, progress) -> AxisFit:
    """:func:`fit_axis` inside one BLAS thread."""
    check_fit_input(base, axis, tr, dt)
    cas0 = base.axis(axis).cascade
    mass0 = cas0.mass_kg
    model = _Model(base, axis, tr, dt, mass0, use_force=True)
    reg = friction_from_force(model.meas, model.force, dt) if model.force is not None else None
    lo, hi, x_base = _start_bounds(model, cas0, mass0, reg)
    # solves: up to three per dead time searched, the two best refined, the further starts,
    # the fractional dead time
    done = _Progress(progress, 3 * (max_dead + 1) + 2 + max(starts - 1, 0) + 1)
    solver = _Solver(model, axis, lo, hi, done)
    # the logging lag from the steady following error; the dead time upwards from 0; then
    # multi-start over the Stribeck velocity
    lag = logging_lag(model.cmd, model.ff, model.kp, model.kf, model.meas, dt)
    x_high = _high_start(model, cas0, mass0, reg, x_base, lo, hi, tr.force_n, dt, max_dead)
    tried = _search_dead_times(solver, (x_base, x_high), lag, max_dead, dt)
    r, dead, lag = _refine(solver, tried, starts)
    n = model.meas.size - lag  # the position residual leads r.fun (the force's follows)

    def pos_rms(t):  # every fit tried has the one logging lag
        return float(np.sqrt(np.mean(t.fun[:n] ** 2))) * 1e-6

    noise = _noise_rms(model.meas)
    r, frac, dead = _fractional(solver, tried, r, dead, lag, max_dead, noise, pos_rms)
    candidates = [(d, lg, pos_rms(t)) for (d, lg), t in sorted(tried.items())]
    cov, tau = _covariance(r, n)
    x = r.x
    mass, mass_sd, f_rms, ratio, f_meas = _force_scale(model, x, dead, lag, n, tr.force_n,
                                                       mass0, axis)
    vals, los, his = _intervals(x, cov, mass, mass_sd, ratio, tr.force_n is not None)
    cas = model.cascade(x).model_copy(update={
        "mass_kg": mass, "kv_n_s_m": vals["kv_n_s_m"], "coulomb_n": vals["coulomb_n"],
        "static_n": max(vals["static_n"], vals["coulomb_n"]), "viscous_n_s_m": vals["viscous_n_s_m"],
        "force_limit_n": cas0.force_limit_n * ratio,
    })
    rms = pos_rms(r)
    # the evidence of model error: the residual above the noise, relative to the velocity
    # loop's imprint on the positions (what the model is there to predict); a parameter
    # pushed to a physical bound
    from oga.identify.sim import ideal_loop_positions

    ideal = ideal_loop_positions(model.p0, model.cmd, model.ff, model.kp, model.kf, dt, dead)
    imprint = float(np.sqrt(np.mean((ideal[: ideal.size - lag] - model.meas[lag:]) ** 2)))
    share = math.sqrt(max(rms ** 2 - noise ** 2, 0.0)) / max(imprint, noise, 1e-12)
    ends = _at_bounds(r.x[: r.x.size - frac], lo, hi)
    equivalent = _equivalent_changes(model, r, n, math.sqrt(max(rms ** 2 - noise ** 2, 0.0)),
                                     dead, lag, frac)
    return AxisFit(status=_status(rms, noise, share, f_rms, f_meas, ends), cascade=cas,
                   dead_time_samples=dead, lag_samples=lag,
                   values=vals, ci_low=los, ci_high=his, mass_identified=tr.force_n is not None,
                   residual_rms_m=rms, noise_rms_m=noise, force_residual_rms_n=f_rms,
                   candidates=candidates, fit_time_s=time.process_time() - t_start, n_samples=n,
                   correlation_samples=tau, model_error_share=share, at_bounds=ends,
                   model_error_changes=equivalent)
