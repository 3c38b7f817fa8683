"""``afsmc``: adaptive fuzzy sliding-mode control with velocity-scheduled dynamic compensation.

From "Adaptive Fuzzy Sliding Controller with Dynamic Compensation for Multi-Axis
Machining" (afsmc_dynamic_compensation.txt; the GJ-310 CNC). The law replaces the
position controller of each contour-plane axis; its output is the velocity command
(the paper's DAC output to an analog velocity drive), so the machine's velocity
loop stays. Per sample k, with the tracking error ``e = pd - p`` (eq. 1) of the
plane axes:

- dead zone (eq. 2): ``e_max = v_prog Te``, the distance travelled in one
  interpolation cycle at the programmed feed;
- dynamic compensation (eqs. 3, 4, 6): ``le = |e|`` (eq. 4) and, only when
  ``le > e_max``, ``comp = (v_k / v_prog) (le - e_max)`` with ``v_k`` the setpoint
  path speed, applied along the error vector: ``u_c = kp comp e / le``;
- sliding surface (eq. 9) for the reference model ``dp/dt = u`` (the velocity
  command drives the position: order n = 1, so ``s = e``); the ideal law (eq. 10)
  ``u* = dpd/dt + k sat(s / phi)``: its equivalent control is the feed-forward
  ``kf vd`` and its switching term is realised by a fuzzy system
  ``u_fz(e, de/dt | theta)`` with the 7x7 rules of the paper's Table 2 (inputs e and
  its change rate, labels LN..LP), uniform triangular memberships, product
  inference and centre-average defuzzification: on a uniform grid this is the
  bilinear interpolation of the rule singletons ``theta``;
- adaptation (eq. 14, n = 1, the scalar P folded into gamma):
  ``d theta / dt = gamma s_D xi(e, de/dt)`` with the dead-zone error
  ``s_D = e (1 - e_max / le)`` when ``le > e_max``, else 0: inside the dead zone
  the rules do not adapt (no drift);
- total (eq. 5): ``u = kf vd + u_fz + u_c``.

Axes outside the contour plane and rapids use P + feed-forward at the baseline
gains (the best fixed gains of :func:`oga.search.ranges.gain_ranges`); adaptation and
compensation are off during rapids.
"""

from __future__ import annotations

from collections import namedtuple

from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.controllers.base import (
    ControllerRun,
    baseline_si,
    check_parameters,
    grid_tune,
    load_array,
    path_frame,
    score,
)
from oga.errors import OptionError, TuneError
from oga.model.machine import Machine
from oga.model.simulate import drive
from oga.model.response import axis_arrays

__all__ = ["NAME", "NEEDS_FIRMWARE", "PARAMETERS", "RULES", "AfsmcTrace", "simulate_afsmc", "run"]

NAME = "afsmc"
NEEDS_FIRMWARE = True
PARAMETERS = (
    "kp_1_s",
    "kf",
    "error_scale_m",
    "rate_scale_m_s",
    "output_scale_m_s",
    "gamma_1_s2",
    "dead_zone_m",
    "prog_feed_m_s",
)

#: Paper Table 2: rows the tracking error e from LP down to LN, columns its change
#: rate from LN to LP; entries the output label.
_TABLE2 = (
    "LP LP LP LP LP LP LP",  # e = LP
    "SP SP SP MP MP LP LP",  # MP
    "ZZ SP SP SP MP MP LP",  # SP
    "ZZ ZZ ZZ ZZ ZZ ZZ ZZ",  # ZZ
    "LN MN MN SN SN SN ZZ",  # SN
    "LN LN MN MN SN SN SN",  # MN
    "LN LN LN LN LN LN LN",  # LN
)
_LABEL = {"LN": -3, "MN": -2, "SN": -1, "ZZ": 0, "SP": 1, "MP": 2, "LP": 3}
#: Table 2 as label values in [-3, 3], indexed ``[i_e, j_rate]`` from LN (0) to LP (6).
RULES = np.array([[_LABEL[w] for w in row.split()] for row in reversed(_TABLE2)], float)

#: Design defaults and tuning grid (:mod:`oga.defaults`, where their reasons are given).
ERROR_SCALE_PER_LAG = defaults.AFSMC_ERROR_SCALE_PER_LAG
RATE_PER_OUTPUT_SCALE = defaults.AFSMC_RATE_PER_OUTPUT_SCALE
GAMMA_PER_KP_1_S = defaults.AFSMC_GAMMA_PER_KP_1_S
TUNE_GAMMA_PER_KP_1_S = defaults.AFSMC_TUNE_GAMMA_PER_KP_1_S
TUNE_KP_COMP_PER_KP = defaults.AFSMC_TUNE_KP_COMP_PER_KP


@dataclass(frozen=True, eq=False)
class AfsmcTrace:
    """One afsmc simulation with its internal signals.

    Attributes
    ----------
    pos, u : ndarray, shape (N, 3)
        Measured positions (m) and velocity commands (m/s).
    theta0, theta : ndarray, shape (3, 7, 7)
        Rule singletons per axis ``[axis, i_e, j_rate]`` (m/s) at the start and at the end.
    compensated : ndarray of bool, shape (N,)
        Samples where the dynamic compensation acted (``le > e_max`` while moving).
    adapted : ndarray of bool, shape (N,)
        Samples where the rules adapted (``le > e_max``, gamma > 0, feed samples).
    parameters : dict
        The values used (names with units).
    """

    pos: np.ndarray
    u: np.ndarray
    theta0: np.ndarray
    theta: np.ndarray
    compensated: np.ndarray
    adapted: np.ndarray
    parameters: dict


#: The loop's inputs packed for :func:`_loop`: ``pd``, ``vd``, ``load`` (N, 3) (m, m/s, N),
#: ``speed`` (N,) the setpoint path speed (m/s), ``feed`` (N,) bool, ``present``, ``ctrl``
#: (3,) bool (axis exists, axis in the contour plane), ``kp_base`` (1/s), ``kf_base`` (3,).
Inputs = namedtuple("Inputs", ["pd", "vd", "load", "speed", "feed", "present", "ctrl",
                               "kp_base", "kf_base"])

#: Offsets in the law array of :func:`_loop`: kf, Kp_c (1/s), 1/error scale (1/m),
#: 1/rate scale (s/m), gamma (1/s^2), dead zone (m), 1/programmed feed (s/m), Te (s).
KF, KP_C, INV_ES, INV_RS, GAMMA, DEAD_ZONE, INV_VPROG, TE = range(8)


@njit(cache=True)
def _loop(params, states, inputs, law, theta, out_p, out_u, out_comp, out_adapt):
    """The per-sample loop over all axes (see the module docstring for the law).

    ``params, states`` from :func:`oga.model.response.axis_arrays` (advanced in place);
    ``inputs`` an :data:`Inputs`; ``law`` the constants at :data:`KF` ... :data:`TE`;
    ``theta`` (3, 7, 7) rule singletons (m/s), adapted in place; ``out_p, out_u`` (N, 3)
    (m, m/s), ``out_comp, out_adapt`` (N,) bool.
    """
    pd, vd, speed, feed, load = inputs.pd, inputs.vd, inputs.speed, inputs.feed, inputs.load
    present, ctrl, kp_base, kf_base = inputs.present, inputs.ctrl, inputs.kp_base, inputs.kf_base
    kf, kp_c, inv_es, inv_rs = law[KF], law[KP_C], law[INV_ES], law[INV_RS]
    gamma, dead_zone, inv_vprog, te = law[GAMMA], law[DEAD_ZONE], law[INV_VPROG], law[TE]
    n = pd.shape[0]
    e = np.zeros(3)
    e_prev = np.zeros(3)
    for k in range(n):
        for a in range(3):
            out_p[k, a] = states[a, 0] if present[a] else pd[k, a]
            e[a] = pd[k, a] - out_p[k, a]
        le2 = 0.0
        for a in range(3):
            if ctrl[a]:
                le2 += e[a] * e[a]
        le = np.sqrt(le2)
        outside = feed[k] and le > dead_zone
        for a in range(3):
            if not present[a]:
                out_u[k, a] = 0.0
                continue
            if not (feed[k] and ctrl[a]):
                out_u[k, a] = kp_base[a] * e[a] + kf_base[a] * vd[k, a]
                continue
            # fuzzy inputs on the label axis [-3, 3]; the grid cell and bilinear weights
            x1 = min(3.0, max(-3.0, 3.0 * e[a] * inv_es)) + 3.0
            x2 = min(3.0, max(-3.0, 3.0 * (e[a] - e_prev[a]) / te * inv_rs)) + 3.0
            i = min(5, int(x1))
            j = min(5, int(x2))
            w1 = x1 - i
            w2 = x2 - j
            xi00 = (1.0 - w1) * (1.0 - w2)
            xi01 = (1.0 - w1) * w2
            xi10 = w1 * (1.0 - w2)
            xi11 = w1 * w2
            u_fz = (xi00 * theta[a, i, j] + xi01 * theta[a, i, j + 1]
                    + xi10 * theta[a, i + 1, j] + xi11 * theta[a, i + 1, j + 1])
            u = kf * vd[k, a] + u_fz
            if outside:
                u += kp_c * speed[k] * inv_vprog * (le - dead_zone) * e[a] / le
                if gamma > 0.0:
                    g = gamma * te * e[a] * (1.0 - dead_zone / le)
                    theta[a, i, j] += g * xi00
                    theta[a, i, j + 1] += g * xi01
                    theta[a, i + 1, j] += g * xi10
                    theta[a, i + 1, j + 1] += g * xi11
            out_u[k, a] = u
        out_comp[k] = outside and speed[k] > 0.0
        out_adapt[k] = outside and gamma > 0.0
        for a in range(3):
            e_prev[a] = e[a]
            if present[a]:
                drive(states[a], params[a], out_u[k, a], load[k, a])


def _defaults(setpoints: Setpoints, kp_si: float, kf: float) -> dict:
    """Design defaults of every parameter from the baseline gains and the toolpath."""
    feed = ~setpoints.rapid
    speed = np.linalg.norm(setpoints.vel, axis=1)
    v_prog = float(speed[feed].max()) if feed.any() else 0.0
    if not v_prog > 0.0:
        raise OptionError("afsmc: the toolpath has no feed motion (no programmed velocity)")
    es = ERROR_SCALE_PER_LAG * v_prog / kp_si
    return {
        "kp_1_s": kp_si,
        "kf": kf,
        "error_scale_m": es,
        "rate_scale_m_s": RATE_PER_OUTPUT_SCALE * kp_si * es,
        "output_scale_m_s": kp_si * es,
        "gamma_1_s2": GAMMA_PER_KP_1_S * kp_si,
        "dead_zone_m": v_prog * setpoints.dt,
        "prog_feed_m_s": v_prog,
    }


def _simulate(setpoints, machine, base_kp, base_kf, p: dict, load) -> AfsmcTrace:
    for name in ("error_scale_m", "rate_scale_m_s", "prog_feed_m_s"):
        if not p[name] > 0.0:
            raise OptionError(f"afsmc: {name} must be positive, got {p[name]}")
    for name in ("kp_1_s", "gamma_1_s2", "dead_zone_m", "output_scale_m_s"):
        if not p[name] >= 0.0:
            raise OptionError(f"afsmc: {name} must be >= 0, got {p[name]}")
    _t, _nrm, _c, e1, e2 = path_frame(setpoints)
    n = len(setpoints)
    params, states, present = axis_arrays(machine, setpoints.pos[0])
    ctrl = np.zeros(3, dtype=np.bool_)
    ctrl[[e1, e2]] = True
    ctrl &= present
    theta0 = np.tile(RULES / 3.0 * p["output_scale_m_s"], (3, 1, 1))
    theta = theta0.copy()
    pos, u = np.empty((n, 3)), np.empty((n, 3))
    comp, adapt = np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
    inputs = Inputs(np.ascontiguousarray(setpoints.pos), np.ascontiguousarray(setpoints.vel),
                    load, np.linalg.norm(setpoints.vel, axis=1),
                    np.ascontiguousarray(~setpoints.rapid), present, ctrl, base_kp, base_kf)
    law = np.array([p["kf"], p["kp_1_s"], 1.0 / p["error_scale_m"], 1.0 / p["rate_scale_m_s"],
                    p["gamma_1_s2"], p["dead_zone_m"], 1.0 / p["prog_feed_m_s"], setpoints.dt],
                   dtype=np.float64)
    _loop(params, states, inputs, law, theta, pos, u, comp, adapt)
    return AfsmcTrace(pos=pos, u=u, theta0=theta0, theta=theta, compensated=comp, adapted=adapt,
                      parameters=dict(p))


def simulate_afsmc(setpoints: Setpoints, machine: Machine, *, load_n=None, baseline=None,
                   **parameters) -> AfsmcTrace:
    """Simulate afsmc with given parameters (no tuning), keeping the internal signals.

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples, period Te).
    machine : Machine
        The plant.
    load_n : array_like, shape (N, 3), optional
        External load force per sample and axis, N.
    baseline : tuple of ndarray, optional
        ``(kp_1_s, kf)`` per axis from :func:`baseline_gains` (computed when omitted).
    **parameters
        Any of :data:`PARAMETERS`; the others take the design defaults (from the
        best fixed gains Kp (1/s), Kf on this toolpath):

        - ``kp_1_s`` = Kp (compensation gain, eq. 6: the CNC's proportional gain);
        - ``kf`` = Kf (equivalent control);
        - ``error_scale_m`` = :data:`ERROR_SCALE_PER_LAG` * prog_feed_m_s / Kp;
        - ``output_scale_m_s`` = Kp * error_scale_m (the initial fuzzy surface has
          slope Kp in e, as the baseline);
        - ``rate_scale_m_s`` = :data:`RATE_PER_OUTPUT_SCALE` * output_scale_m_s;
        - ``gamma_1_s2`` = :data:`GAMMA_PER_KP_1_S` * Kp;
        - ``dead_zone_m`` = prog_feed_m_s * Te (eq. 2);
        - ``prog_feed_m_s`` = the largest setpoint path speed on the feed samples.

    Returns
    -------
    AfsmcTrace

    Raises
    ------
    OptionError
        Unknown or out-of-range parameter, malformed load, or no feasible baseline.
    """
    check_parameters(NAME, parameters, PARAMETERS)
    base_kp, base_kf = baseline_si(setpoints, machine) if baseline is None else baseline
    p = _defaults(setpoints, float(base_kp[0]), float(base_kf[0]))
    p.update(parameters)
    return _simulate(setpoints, machine, base_kp, base_kf, p, load_array(load_n, len(setpoints)))


def run(setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True,
        **parameters) -> ControllerRun:
    """Simulate afsmc on ``setpoints`` (see :func:`simulate_afsmc` for the parameters).

    ``tune=True`` grids the adaptation rate (:data:`TUNE_GAMMA_PER_KP_1_S` times the
    baseline Kp) and the compensation gain (:data:`TUNE_KP_COMP_PER_KP` times Kp) for
    the least MSE(CE) whose command meets the limits (paper eq. 2); parameters given
    are kept out of the grid.

    Returns
    -------
    ControllerRun
    """
    check_parameters(NAME, parameters, PARAMETERS)
    load = load_array(load_n, len(setpoints))
    base_kp, base_kf = baseline_si(setpoints, machine)
    kp_si = float(base_kp[0])
    p = _defaults(setpoints, kp_si, float(base_kf[0]))
    notes = [
        "reference model dp/dt = u (velocity command to position), sliding surface s = e (n = 1)",
        "equivalent control = feed-forward kf vd; switching term = the adaptive fuzzy system",
        "fuzzy: Table 2 rules, 7 uniform triangles per input on [-scale, scale], saturated "
        "beyond, product inference, centre average (bilinear interpolation of the singletons)",
        "initial singletons = Table 2 labels / 3 * output_scale_m_s (Figure 5's ranges are "
        "lost: scales are design choices relative to the baseline Kp)",
        "adaptation d theta/dt = gamma s_D xi with the vector dead zone of eq. 2 (P of eq. 14 "
        "folded into gamma); no adaptation or compensation during rapids",
        "dynamic compensation applied along the tracking-error vector of the plane axes",
        "axes outside the contour plane: P + feed-forward at the best fixed gains",
        "prog_feed_m_s (v of eqs. 2, 3) = the largest setpoint path speed",
    ]
    p.update(parameters)
    if tune:
        grid = {}
        if "gamma_1_s2" not in parameters:
            grid["gamma_1_s2"] = [g * kp_si for g in TUNE_GAMMA_PER_KP_1_S]
        if "kp_1_s" not in parameters:
            grid["kp_1_s"] = [c * kp_si for c in TUNE_KP_COMP_PER_KP]
        if grid:

            def sim(trial):
                tr = _simulate(setpoints, machine, base_kp, base_kf, dict(p, **trial), load)
                return tr.pos, tr.u

            try:
                best, _score, n_ok = grid_tune(sim, setpoints, machine, grid)
            except TuneError as err:
                mildest = score(setpoints, machine, *sim({k: min(v) for k, v in grid.items()}))
                raise TuneError(
                    f"afsmc: {err}; worst (v, a, j) command ratios at the mildest point: "
                    f"{np.round(mildest.command_ratios.max(axis=0), 3).tolist()}") from None
            p.update(best)
            notes.append(f"tuned {sorted(grid)} on this toolpath: {n_ok} of "
                         f"{int(np.prod([len(v) for v in grid.values()]))} grid points feasible")
    tr = _simulate(setpoints, machine, base_kp, base_kf, p, load)
    params = dict(p)
    params["baseline_kp_1_s"] = {a: float(base_kp[i]) for i, a in enumerate(AXES)}
    params["baseline_kf"] = {a: float(base_kf[i]) for i, a in enumerate(AXES)}
    notes.append(f"dynamic compensation active on {100.0 * tr.compensated.mean():.1f} % of the "
                 "samples")
    return ControllerRun(name=NAME, pos=tr.pos, u=tr.u, needs_firmware=NEEDS_FIRMWARE,
                         parameters=params, notes=tuple(notes))
