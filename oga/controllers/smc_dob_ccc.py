"""``smc-dob-ccc``: sliding-mode axis control with a disturbance observer and an
adaptive fuzzy PID cross-coupled controller on the Yeh-Hsu contour-error estimate.

After ``smc_dob_fuzzy_pid_ccc.txt`` (its equations and tables were lost; the standard
forms it cites are used). Our plant input is the velocity command ``u`` into the
machine's velocity loop, so every law is designed on the position plant seen from
``u``: the model ``x'' = (u(t - d Te) - x') / T - dist`` (m/s^2), i.e. the velocity
loop as a first-order lag ``T`` behind the known dead time of ``d`` samples. ``T`` is
identified from the linearised lifted velocity loop (:func:`oga.model.linear.lifted_axis`)
as its 63.2 % step rise time (:func:`velocity_lag_s`).

Per contouring axis and sample k (measured position ``p_k``, velocity estimate
``v_k = (p_k - p_{k-1}) / Te``, tracking error ``e = pd - p``, ``e' = vd - v``):

- sliding surface ``s = e' + c e`` (m/s);
- reaching law ``s' = -eta s - k sat(s / phi)`` (switching gain ``k`` in m/s^2, boundary
  layer ``phi`` in m/s), so with the model
  ``u = v + T (ad + c e' + eta s + k sat(s / phi) + dist_hat)``;
- disturbance observer (nonlinear DOB of Chen et al. 2000, the form the paper uses):
  ``dist_hat = z - L v``, ``z' = L ((u(t - d Te) - v) / T - dist_hat)`` (forward Euler),
  a first-order estimate of ``dist`` with bandwidth ``L`` (1/s);
- cross-coupling (Yeh & Hsu 2002): tracking-error vector ``e`` in the contour plane,
  unit tangent ``t``, normal ``n``, curvature ``kappa`` from :func:`path_frame`; the
  contour-error estimate ``eps = e.n + (kappa / 2) (e.t)^2`` (the tangent-line estimate
  ``e - (e.t) t`` plus the osculating-circle second-order term) along ``n``; a PID on
  ``eps`` gives ``u_c`` (m/s), added to the plane axes as ``u_c n``;
- the PID gains are adaptive fuzzy systems (singleton fuzzifier, product inference,
  center-average defuzzifier over the 7 x 7 labels of :mod:`oga.controllers.fuzzy`
  on ``6 eps / eps_range`` and ``6 eps' / eps_rate_range``):
  ``K_g = theta_g . xi``, ``theta_g`` initialised from the classic self-tuning tables
  (``K0_g (1 + ratio_g label / 6)``, the paper ratios of :mod:`oga.controllers.fuzzy_pid`)
  and adapted by the gradient of ``eps^2 / 2`` with sigma-leakage:
  ``theta_g' = gamma K0_g xi (eps q_g) / (eps_range r_g) - sigma (theta_g - theta_g(0))``,
  ``q = (eps, integral eps, eps')``, ``r = (eps_range, eps_range * 0.1 s, eps_rate_range)``.

Other axes and rapids: P + FFW at the baseline gains (the observer keeps running).

Design defaults (:data:`DEFAULTS`, for ucp710's scale; ``tune`` searches the main gains):
``c`` = 40 1/s, the surface pole near the baseline loop's crossover (Kp about 40 1/s)
and well below the velocity loop's ``1/T`` (about 190 1/s); ``eta`` = 100 1/s, reaching
faster than the surface, still below ``1/T``; ``k`` = 0.05 m/s^2 with ``phi`` = 1 mm/s,
a small switching part for the observer's residual, the boundary layer keeping the
command continuous; ``L`` = 100 1/s, below ``1/T`` and the dead time's ``1/(2 d Te)``;
CCC ``Kc_p`` = 20 1/s (half the axis stiffness), ``Kc_i = Kc_d = 0`` (the paper's
values are lost; a pure gain first), ``eps_range`` = 10 um (the order of the
baseline's contour-error peak on the test paths), ``eps_rate_range`` = 1 mm/s,
``gamma = sigma`` = 1 1/s (adaptation over about a second; the leakage bounds the
gains near twice their initial values while ``|eps|`` is about ``eps_range``).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from feedplan.setpoints import Setpoints
from oga import defaults
from oga.controllers.base import (
    ControllerRun, check_parameters, given_or_baseline_si, grid_tune, path_frame)
from oga.controllers.fuzzy import RULES, UNIVERSE, memberships
from oga.controllers.fuzzy_pid import PAPER_RATIOS, law_inputs
from oga.errors import MachineError, OptionError, TuneError
from oga.model.linear import lifted_axis
from oga.model.machine import Machine
from oga.model.simulate import drive
from oga.model.response import axis_arrays

__all__ = [
    "NAME", "NEEDS_FIRMWARE", "PARAMETERS", "run", "velocity_lag_s", "contour_error_estimate",
]

NAME = "smc-dob-ccc"
NEEDS_FIRMWARE = True
PARAMETERS = (
    "c_1_s",
    "eta_1_s",
    "k_switch_m_s2",
    "phi_m_s",
    "dob",
    "l_dob_1_s",
    "ccc",
    "kcp_1_s",
    "kci_1_s2",
    "kcd",
    "eps_range_m",
    "eps_rate_range_m_s",
    "gamma_1_s",
    "sigma_1_s",
    "kp_base_1_s",
    "kf_base",
)

#: Design defaults and tuning grid (:mod:`oga.defaults`; the reasons are in this docstring).
DEFAULTS = defaults.SMC_DOB_CCC_DEFAULTS
TUNE_GRID = defaults.SMC_DOB_CCC_TUNE_GRID
#: Normalising time of the contour-error integral in the adaptation law, s.
_I_TIME_S = 0.1


def velocity_lag_s(machine: Machine, axis: str, horizon_s: float = 0.2) -> float:
    """First-order lag ``T`` (s) of an axis velocity loop: its 63.2 % rise time.

    One-point identification on the unit step response of the linearised axis
    (:func:`oga.model.linear.lifted_axis`, dead time excluded; any axis model): the mean
    velocity over period k, ``(p_{k+1} - p_k) / Te``, is taken at ``(k + 1/2) Te`` and
    interpolated up to its first crossing of 63.2 %. (The method of moments does not
    suit a PI velocity loop: its zero makes the first moment almost zero although the
    loop rises in about 5 ms.)

    Raises
    ------
    MachineError
        The step response does not reach 63.2 % within ``horizon_s``.
    """
    a, b, c, _ = lifted_axis(machine, axis)
    n = int(round(horizon_s / machine.te))
    p = np.empty(n + 1)
    x = np.zeros(a.shape[0])
    for k in range(n + 1):
        p[k] = c[0] @ x
        x = a @ x + b[:, 0]
    v = np.diff(p) / machine.te
    level = 1.0 - np.exp(-1.0)
    if not v.max() > level:
        raise MachineError(f"axis {axis}: velocity step response below 63 % after {horizon_s} s")
    k = int(np.argmax(v > level))
    frac = 0.0 if k == 0 else (level - v[k - 1]) / (v[k] - v[k - 1])
    return float(machine.te * (k - 0.5 + frac))


@njit(cache=True)
def contour_error_estimate(e_a: float, e_b: float, t_a: float, t_b: float, kappa: float) -> float:
    """Signed contour-error estimate along the normal (Yeh & Hsu, second order), m.

    Parameters
    ----------
    e_a, e_b : float
        Tracking error ``pd - p`` along the plane axes, m.
    t_a, t_b : float
        Unit tangent of the path at ``pd``.
    kappa : float
        Signed curvature there, 1/m (positive turning left).

    Returns
    -------
    float
        ``e.n + (kappa / 2) (e.t)^2`` with ``n`` the tangent turned +90 deg: the path
        lies this far from the actual position along ``n`` (the tangent-line estimate
        ``e - (e.t) t`` plus the osculating circle's term).
    """
    et = e_a * t_a + e_b * t_b
    return -e_a * t_b + e_b * t_a + 0.5 * kappa * et * et


@njit(cache=True)
def _fuzzy_gain(theta, ie, te, ic, tc):
    """Center-average output of a rule base ``theta`` (7, 7) at the fired labels."""
    return (
        (1.0 - te) * (1.0 - tc) * theta[ie, ic]
        + te * (1.0 - tc) * theta[ie + 1, ic]
        + (1.0 - te) * tc * theta[ie, ic + 1]
        + te * tc * theta[ie + 1, ic + 1]
    )


#: The path the law follows, packed for :func:`_simulate`: ``present``, ``law`` (3,) bool,
#: ``pd``, ``vd``, ``ad`` (N, 3) setpoints (m, m/s, m/s^2), ``rapid`` (N,) bool, ``load``
#: (N, 3) force (N), ``tangent``, ``normal`` (N, 2), ``kappa`` (N,) 1/m, ``e1``, ``e2`` plane
#: axis columns.
Path = namedtuple("Path", ["present", "law", "pd", "vd", "ad", "rapid", "load", "tangent",
                           "normal", "kappa", "e1", "e2"])

#: Per-axis constants packed for :func:`_simulate`: velocity-loop ``lag`` (s), ``dead`` time
#: (whole samples, int), baseline ``kp_b`` (1/s) and ``kf_b`` (all shape (3,)).
AxisConstants = namedtuple("AxisConstants", ["lag", "dead", "kp_b", "kf_b"])


@njit(cache=True)
def _simulate(params, states, path, axc, g, theta0, te_s, pos, u):
    """Sliding mode + DOB on the ``law`` axes, adaptive fuzzy PID CCC on the plane.

    ``path`` a :data:`Path`, ``axc`` an :data:`AxisConstants`. ``g``: c, eta, k, phi,
    dob (0/1), L, ccc (0/1), 6/eps_range, 6/eps_rate_range, gamma, sigma, then the
    adaptation normalisers 1/(eps_range r_g) for p, i, d and the initial gains K0_p, K0_i,
    K0_d. ``theta0`` (3, 7, 7): initial rule consequents. Fills ``pos`` and ``u`` (N, 3).
    """
    present, pd, vd, ad, rapid, law, load = (path.present, path.pd, path.vd, path.ad,
                                             path.rapid, path.law, path.load)
    tangent, normal, kappa, e1, e2 = path.tangent, path.normal, path.kappa, path.e1, path.e2
    lag, dead, kp_b, kf_b = axc.lag, axc.dead, axc.kp_b, axc.kf_b
    n = pd.shape[0]
    c, eta, ksw, inv_phi = g[0], g[1], g[2], 1.0 / g[3]
    use_dob, ell, use_ccc = g[4] != 0.0, g[5], g[6] != 0.0
    theta = theta0.copy()
    p_prev = np.zeros(3)
    z = np.zeros(3)
    eps_prev = 0.0
    eps_int = 0.0
    for k in range(n):
        # contour error estimate and the adaptive fuzzy PID correction (along n)
        uc = 0.0
        if use_ccc and not rapid[k]:
            eps = contour_error_estimate(
                pd[k, e1] - states[e1, 0], pd[k, e2] - states[e2, 0],
                tangent[k, 0], tangent[k, 1], kappa[k],
            )
            deps = 0.0 if k == 0 else (eps - eps_prev) / te_s
            eps_int += te_s * eps
            ie, tfe = memberships(eps * g[7])
            ic, tfc = memberships(deps * g[8])
            kcp = _fuzzy_gain(theta[0], ie, tfe, ic, tfc)
            kci = _fuzzy_gain(theta[1], ie, tfe, ic, tfc)
            kcd = _fuzzy_gain(theta[2], ie, tfe, ic, tfc)
            uc = kcp * eps + kci * eps_int + kcd * deps
            grads = (eps * eps * g[11], eps * eps_int * g[12], eps * deps * g[13])
            for q in range(3):
                rate = g[9] * g[14 + q] * grads[q]
                for i in range(7):
                    for j in range(7):
                        xi = 0.0
                        if ie <= i <= ie + 1 and ic <= j <= ic + 1:
                            xi = (tfe if i > ie else 1.0 - tfe) * (tfc if j > ic else 1.0 - tfc)
                        leak = g[10] * (theta[q, i, j] - theta0[q, i, j])
                        theta[q, i, j] += te_s * (rate * xi - leak)
                        if theta[q, i, j] < 0.0:
                            theta[q, i, j] = 0.0  # projection: gains stay non-negative
            eps_prev = eps
        for a in range(3):
            if not present[a]:
                pos[k, a] = pd[k, a]
                continue
            p = states[a, 0]
            pos[k, a] = p
            v = 0.0 if k == 0 else (p - p_prev[a]) / te_s
            p_prev[a] = p
            e = pd[k, a] - p
            dh = 0.0
            if law[a] and use_dob:
                u_del = u[k - dead[a], a] if k >= dead[a] else 0.0
                dh = z[a] - ell * v
                z[a] += te_s * ell * ((u_del - v) / lag[a] - dh)
            if law[a] and not rapid[k]:
                de = vd[k, a] - v
                s = de + c * e
                sat = min(max(s * inv_phi, -1.0), 1.0)
                cmd = v + lag[a] * (ad[k, a] + c * de + eta * s + ksw * sat + dh)
                if a == e1:
                    cmd += uc * normal[k, 0]
                elif a == e2:
                    cmd += uc * normal[k, 1]
            else:
                cmd = kp_b[a] * e + kf_b[a] * vd[k, a]
            u[k, a] = cmd
            drive(states[a], params[a], cmd, load[k, a])


_NOTES = (
    "Plant seen from the velocity command: x'' = (u(t - d Te) - x') / T - dist, T the "
    "63 % rise time of the lifted velocity loop; the SMC law ignores the dead time, "
    "the observer uses the delayed command.",
    "Velocity measured by the backward difference of the position samples.",
    "Contour error: Yeh-Hsu tangent estimate plus the curvature (osculating-circle) term.",
    "The paper's CCC rule base and adaptation law were lost: classic self-tuning tables "
    "as initial consequents, gradient adaptation of eps^2/2 with sigma-leakage.",
    "Other axes and rapids: P + FFW at the baseline gains.",
)


def _values(setpoints: Setpoints, machine: Machine, parameters: dict):
    """The run's parameter values (defaults, baseline gains, given) and the baseline gains
    per axis ``(values, kp_b, kf_b)``; refuses a non-positive scale."""
    check_parameters(NAME, parameters, PARAMETERS)
    kp_b, kf_b = given_or_baseline_si(setpoints, machine, parameters, "kp_base_1_s", "kf_base")
    values = {**DEFAULTS, "kp_base_1_s": float(kp_b[0]), "kf_base": float(kf_b[0])}
    values.update(parameters)
    for name in ("phi_m_s", "eps_range_m", "eps_rate_range_m_s", "c_1_s"):
        if not float(values[name]) > 0.0:
            raise OptionError(f"{NAME}: {name} must be positive, got {values[name]}")
    return values, kp_b, kf_b


def _prepare(setpoints: Setpoints, machine: Machine, load_n, kp_b, kf_b):
    """``(params, states0, path, axis_constants)`` of :func:`_simulate`."""
    pd, vd, ad, rapid, law, load = law_inputs(setpoints, load_n)
    tangent, normal, kappa, e1, e2 = path_frame(setpoints)
    params, states0, present = axis_arrays(machine, pd[0] if len(pd) else np.zeros(3))
    law &= present
    lag = np.array([velocity_lag_s(machine, a) if law[c] else 1.0
                    for c, a in enumerate(("x", "y", "z"))])
    # each axis's dead time, whole samples (a fractional one rounded: the law's own model)
    dead = np.array([round(machine.dead_time_samples_of(a)) if a in machine.axes else 0
                     for a in ("x", "y", "z")], dtype=np.int64)
    path = Path(present, law, pd, vd, ad, rapid, load, tangent, normal, kappa, e1, e2)
    return params, states0, path, AxisConstants(lag, dead, kp_b, kf_b)


def _law_arrays(v: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(g, theta0)`` of :func:`_simulate` from the parameter values ``v``."""
    k0 = np.array([v["kcp_1_s"], v["kci_1_s2"], v["kcd"]], dtype=np.float64)
    ratios = np.array([PAPER_RATIOS[r] for r in ("dkp_ratio", "dki_ratio", "dkd_ratio")])
    theta0 = k0[:, None, None] * (1.0 + ratios[:, None, None] * 2.0 * RULES / UNIVERSE)
    er, rr = float(v["eps_range_m"]), float(v["eps_rate_range_m_s"])
    g = np.array([
        v["c_1_s"], v["eta_1_s"], v["k_switch_m_s2"], v["phi_m_s"], float(bool(v["dob"])),
        v["l_dob_1_s"], float(bool(v["ccc"])), UNIVERSE / er, UNIVERSE / rr,
        v["gamma_1_s"], v["sigma_1_s"],
        1.0 / (er * er), 1.0 / (er * er * _I_TIME_S), 1.0 / (er * rr),
        *k0,
    ], dtype=np.float64)
    return g, theta0


def _tune(simulate, setpoints: Setpoints, machine: Machine, values: dict, parameters: dict,
          notes: list) -> None:
    """Tune the grid's parameters not given on this toolpath: ``values`` and ``notes``
    updated in place."""
    grid = {k: vals for k, vals in TUNE_GRID.items() if k not in parameters}
    if not grid:
        return
    try:
        choice, _, n_ok = grid_tune(lambda c: simulate({**values, **c}), setpoints, machine, grid)
    except TuneError as err:
        raise TuneError(
            f"{NAME}: {err}. The law's model-based feed-forward T * (setpoint "
            "acceleration) alone breaks the jerk limit of paper eq. 2 when the plan "
            "runs at that limit (its velocity command needs the setpoint snap); run "
            "with tune=False to see the command ratios"
        ) from None
    values.update(choice)
    notes.append(f"Tuned on this toolpath: {n_ok} feasible grid points, chose {choice}.")


def run(
    setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True, **parameters
) -> ControllerRun:
    """Simulate sliding mode + DOB per axis with the adaptive fuzzy PID CCC.

    Parameters
    ----------
    setpoints : Setpoints
        The toolpath (N samples at the machine's Te).
    machine : Machine
        The plant.
    load_n : array_like, shape (N, 3), optional
        External load force per sample and axis, N.
    tune : bool
        Tune ``c_1_s``, ``eta_1_s``, ``kcp_1_s`` on :data:`TUNE_GRID` (paper eq. 2
        feasibility); parameters given are kept fixed.
    **parameters
        Any of :data:`PARAMETERS` (defaults :data:`DEFAULTS`; ``kp_base_1_s`` and
        ``kf_base`` default to the best fixed gains). ``dob`` and ``ccc`` switch the
        observer and the cross-coupling.

    Returns
    -------
    ControllerRun
        ``parameters`` also holds the identified lag ``lag_s`` per axis.

    Raises
    ------
    OptionError
        Unknown parameter, bad value, or no tuned combination meets the limits.
    """
    values, kp_b, kf_b = _values(setpoints, machine, parameters)
    params, states0, path, axc = _prepare(setpoints, machine, load_n, kp_b, kf_b)
    n = len(path.pd)

    def simulate(v: dict) -> tuple[np.ndarray, np.ndarray]:
        g, theta0 = _law_arrays(v)
        pos = np.empty((n, 3))
        u = np.zeros((n, 3))
        _simulate(params, states0.copy(), path, axc, g, theta0, machine.te, pos, u)
        return pos, u

    notes = list(_NOTES)
    if tune:
        _tune(simulate, setpoints, machine, values, parameters, notes)
    pos, u = simulate(values)
    values["lag_s"] = {a: float(axc.lag[c]) for c, a in enumerate(("x", "y", "z"))
                       if path.law[c]}
    return ControllerRun(
        name=NAME,
        pos=pos,
        u=u,
        needs_firmware=NEEDS_FIRMWARE,
        parameters=values,
        notes=tuple(notes),
    )
