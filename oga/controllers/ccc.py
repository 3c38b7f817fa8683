"""Koren's variable-gain cross-coupled control (CCC) on top of P + feed-forward.

Paper: zpetc_ccc_ddob_friction.txt, section 2.2 (after Koren and Lo). Per sample k, in
the contour plane ``(e1, e2)`` of the setpoints:

- axis errors ``E1 = pd1 - p1``, ``E2 = pd2 - p2`` (m);
- variable cross-coupling gains from the path frame (:func:`oga.controllers.base.path_frame`:
  unit tangent ``(cos theta, sin theta)``, signed curvature ``kappa``; paper eqs. 7-10
  with ``1 / R`` -> ``kappa``, so lines are ``kappa = 0`` and clockwise arcs ``kappa < 0``):
  ``Cx = sin theta - kappa E1 / 2``, ``Cy = cos theta + kappa E2 / 2``;
- contour-error estimate ``eps = -Cx E1 + Cy E2`` (m, positive right of travel):
  ``n . E + kappa |E|^2 / 2`` with ``n`` the left normal;
- compensator ``C(z) = Kc + Ki Te / (1 - z^-1)`` (a PI on ``eps``; the paper's constant
  ``C = 1.3`` is the special case ``Ki = 0`` on its own plant's units):
  ``W_k = Kc eps_k + Ki Te sum_{j<=k} eps_j`` (m/s);
- the correction distributed to the axes: ``u1 = Kp E1 + Kf vd1 - Cx W``,
  ``u2 = Kp E2 + Kf vd2 + Cy W``.

Axes outside the plane and rapid samples: P + feed-forward only (the integral restarts
after a rapid). With ``Kc = Ki = 0`` the run is the uncoupled P + FFW of
:func:`oga.model.response.simulate`.

The shared pieces of the cross-coupled laws (:func:`baseline_gains`,
:func:`cc_correction`, :func:`prepare`) are used by :mod:`oga.controllers.zpetc_ccc_ddob`.
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.controllers.base import (
    ControllerRun,
    best_fixed,
    check_parameters,
    grid_tune,
    load_array,
    path_frame,
)
from oga.errors import OptionError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.model.simulate import drive
from oga.model.response import axis_arrays

__all__ = [
    "NAME",
    "NEEDS_FIRMWARE",
    "PARAMETERS",
    "DEFAULTS",
    "TUNE_GRID",
    "Prepared",
    "Track",
    "baseline_gains",
    "add_coupling",
    "prepare",
    "cc_correction",
    "run",
]

NAME = "ccc"
NEEDS_FIRMWARE = True
PARAMETERS = ("kp_m_min_per_mm", "kf", "cc_gain_1_s", "cc_integral_1_s2")

#: Design defaults and tuning grid (:mod:`oga.defaults`, where their reasons are given).
DEFAULTS = defaults.CCC_DEFAULTS
TUNE_GRID = defaults.CCC_TUNE_GRID

#: The path a cross-coupled loop follows, packed for compiled code: ``present`` (3,) bool,
#: ``pd``, ``vd`` (N, 3) setpoint positions (m) and velocities (m/s), ``rapid`` (N,) bool,
#: ``tangent`` (N, 2), ``kappa`` (N,) signed curvature (1/m), ``load`` (N, 3) force (N),
#: ``e1``, ``e2`` the plane axis columns (see :class:`Prepared`).
Track = namedtuple("Track", ["present", "pd", "vd", "rapid", "tangent", "kappa", "load",
                             "e1", "e2"])

#: Offsets in the gain array of a cross-coupled loop: Kp (1/s), Kf, Kc (1/s), Ki Te (1/s).
KP, KF, KC, KI_TE = 0, 1, 2, 3


def baseline_gains(setpoints: Setpoints, machine: Machine, given: dict) -> tuple[float, float]:
    """``(kp_m_min_per_mm, kf)``: those in ``given``, else the best fixed gains.

    The best equal fixed gains of :func:`oga.search.ranges.gain_ranges` (computed only when
    ``given`` lacks one of them).

    Raises
    ------
    OptionError
        A gain is needed and no fixed-gain configuration meets the limits on this toolpath.
    """
    if "kp_m_min_per_mm" in given and "kf" in given:
        return float(given["kp_m_min_per_mm"]), float(given["kf"])
    best = best_fixed(setpoints, machine)
    axis = next(iter(best.kp))
    kp = float(given.get("kp_m_min_per_mm", best.kp[axis]))
    return kp, float(given.get("kf", best.kf[axis]))


@dataclass(frozen=True, eq=False)
class Prepared:
    """What every cross-coupled loop needs, as plain arrays for compiled code.

    Attributes
    ----------
    params, states : ndarray, shape (3, P), (3, S)
        :func:`oga.model.response.axis_arrays` of the machine, states at the first setpoint.
    present : ndarray of bool, shape (3,)
    pd, vd : ndarray, shape (N, 3)
        Setpoint positions (m) and velocities (m/s).
    rapid : ndarray of bool, shape (N,)
    tangent : ndarray, shape (N, 2)
        Unit tangent in the plane axes.
    curvature_1_m : ndarray, shape (N,)
        Signed curvature, 1/m.
    e1, e2 : int
        Plane axis columns.
    load_n : ndarray, shape (N, 3)
        External load force per sample and axis, N.
    kp_si : float
        Baseline position gain, 1/s.
    kf : float
        Baseline velocity feed-forward factor.
    """

    params: np.ndarray
    states: np.ndarray
    present: np.ndarray
    pd: np.ndarray
    vd: np.ndarray
    rapid: np.ndarray
    tangent: np.ndarray
    curvature_1_m: np.ndarray
    e1: int
    e2: int
    load_n: np.ndarray
    kp_si: float
    kf: float

    @property
    def track(self) -> Track:
        """The path arrays as one :data:`Track` for a compiled loop."""
        return Track(self.present, self.pd, self.vd, self.rapid, self.tangent,
                     self.curvature_1_m, self.load_n, self.e1, self.e2)

    def gains(self, te: float, cc_gain_1_s: float, cc_integral_1_s2: float, *extra) -> np.ndarray:
        """The gain array (offsets :data:`KP`, :data:`KF`, :data:`KC`, :data:`KI_TE`, then
        ``extra``) of a compiled loop."""
        return np.array([self.kp_si, self.kf, float(cc_gain_1_s),
                         float(cc_integral_1_s2) * te, *extra], dtype=np.float64)


def prepare(
    setpoints: Setpoints, machine: Machine, load_n, kp_m_min_per_mm: float, kf: float
) -> Prepared:
    """Check the inputs and pack them for a compiled cross-coupled loop.

    Raises
    ------
    OptionError
        Sample period different from Te, or gains not positive/finite.
    InputError
        ``load_n`` not finite of shape (N, 3), or the toolpath moves an axis the
        machine lacks.
    """
    n = len(setpoints)
    if not math.isclose(setpoints.dt, machine.te, rel_tol=1e-9):
        raise OptionError(
            f"setpoints period {setpoints.dt} s differs from the machine's Te {machine.te} s"
        )
    if not (math.isfinite(kp_m_min_per_mm) and kp_m_min_per_mm > 0.0):
        raise OptionError(f"kp_m_min_per_mm: must be positive and finite, got {kp_m_min_per_mm}")
    if not math.isfinite(kf):
        raise OptionError(f"kf: must be finite, got {kf}")
    for c in setpoints.moving_axes:
        machine.axis(AXES[c])  # MachineError (an InputError) names a missing axis
    load = load_array(load_n, n)
    pd = np.ascontiguousarray(setpoints.pos, dtype=np.float64)
    params, states, present = axis_arrays(machine, pd[0] if n else np.zeros(3))
    tangent, _, curvature, e1, e2 = path_frame(setpoints)
    return Prepared(
        params=params,
        states=states,
        present=present,
        pd=pd,
        vd=np.ascontiguousarray(setpoints.vel, dtype=np.float64),
        rapid=np.ascontiguousarray(setpoints.rapid, dtype=np.bool_),
        tangent=np.ascontiguousarray(tangent),
        curvature_1_m=np.ascontiguousarray(curvature),
        e1=e1,
        e2=e2,
        load_n=load,
        kp_si=kp_m_min_per_mm * KP_SI_PER_M_MIN_PER_MM,
        kf=float(kf),
    )


@njit(cache=True)
def cc_correction(err1, err2, cos_t, sin_t, kappa, kc, ki_te, integ):
    """Koren's contour-error estimate and the compensator output, for one sample.

    Parameters
    ----------
    err1, err2 : float
        Axis errors ``pd - p`` in the plane axes, m.
    cos_t, sin_t : float
        Unit tangent of the reference path.
    kappa : float
        Signed curvature, 1/m (0 on lines).
    kc : float
        Proportional gain of C, 1/s.
    ki_te : float
        Integral gain of C times Te, 1/s.
    integ : float
        Integral state: sum of the past estimates, m.

    Returns
    -------
    d1, d2 : float
        Velocity-command corrections of the plane axes, m/s (``-Cx W``, ``+Cy W``).
    eps : float
        Contour-error estimate, m (positive right of travel).
    integ : float
        Updated integral state, m.
    """
    cx = sin_t - 0.5 * kappa * err1
    cy = cos_t + 0.5 * kappa * err2
    eps = -cx * err1 + cy * err2
    integ += eps
    w = kc * eps + ki_te * integ
    return -cx * w, cy * w, eps, integ


@njit(cache=True)
def add_coupling(u, k, track, out_p, gains, integ):
    """Add the cross-coupled correction of sample ``k`` to the commands ``u`` (3,), in place.

    :func:`cc_correction` on the plane axes' errors ``pd[k] - out_p[k]`` of the
    :data:`Track` ``track``, with ``gains[KC]`` and ``gains[KI_TE]``; during a rapid there is
    none and the compensator's integral restarts. Returns the integral state.
    """
    if track.rapid[k]:
        return 0.0
    e1, e2, pd = track.e1, track.e2, track.pd
    d1, d2, _, integ = cc_correction(
        pd[k, e1] - out_p[k, e1], pd[k, e2] - out_p[k, e2],
        track.tangent[k, 0], track.tangent[k, 1], track.kappa[k], gains[KC], gains[KI_TE],
        integ,
    )
    if track.present[e1]:
        u[e1] += d1
    if track.present[e2]:
        u[e2] += d2
    return integ


@njit(cache=True)
def _loop(params, states, track, gains, out_p, out_u):
    """Simulate all axes jointly with P + FFW and the cross-coupled correction."""
    present, pd, vd, load = track.present, track.pd, track.vd, track.load
    kp, kf = gains[KP], gains[KF]
    n = pd.shape[0]
    u = np.zeros(3)
    integ = 0.0
    for k in range(n):
        for a in range(3):
            out_p[k, a] = states[a, 0] if present[a] else pd[k, a]
            u[a] = kp * (pd[k, a] - out_p[k, a]) + kf * vd[k, a] if present[a] else 0.0
        integ = add_coupling(u, k, track, out_p, gains, integ)
        for a in range(3):
            if present[a]:
                drive(states[a], params[a], u[a], load[k, a])
            out_u[k, a] = u[a]


def _simulate(prep: Prepared, te: float, cc_gain_1_s: float, cc_integral_1_s2: float):
    n = prep.pd.shape[0]
    pos = np.empty((n, 3))
    u = np.empty((n, 3))
    _loop(prep.params, prep.states.copy(), prep.track,
          prep.gains(te, cc_gain_1_s, cc_integral_1_s2), pos, u)
    return pos, u


def run(
    setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True, **parameters
) -> ControllerRun:
    """Simulate Koren's cross-coupled control on ``setpoints`` (see the module docstring).

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples, period Te).
    machine : Machine
        The plant.
    load_n : array_like, shape (N, 3), optional
        External load force per sample and axis, N.
    tune : bool
        True: choose ``cc_gain_1_s`` and ``cc_integral_1_s2`` on :data:`TUNE_GRID` with
        :func:`oga.controllers.base.grid_tune` (those given are held); False: :data:`DEFAULTS`.
    **parameters
        Any of :data:`PARAMETERS`: ``kp_m_min_per_mm`` and ``kf`` (default: the best fixed
        gains), ``cc_gain_1_s`` (Kc, 1/s), ``cc_integral_1_s2`` (Ki, 1/s^2).

    Returns
    -------
    ControllerRun

    Raises
    ------
    OptionError
        Unknown parameter, no feasible tuning, or no feasible baseline.
    """
    check_parameters(NAME, parameters, PARAMETERS)
    notes = [
        "Kp and Kf are the best equal fixed gains of oga.search.ranges unless given.",
        "Contour-error estimate and gains Cx, Cy of Koren and Lo (paper eqs. 7-10) with the "
        "signed curvature of the setpoints for 1/R (0 on lines).",
        "Compensator C = Kc + Ki Te/(1 - z^-1) acting on the estimate, in m/s per m.",
        "Rapids and axes outside the contour plane: P + feed-forward only; the integral "
        "restarts after a rapid.",
    ]
    kp, kf = baseline_gains(setpoints, machine, parameters)
    prep = prepare(setpoints, machine, load_n, kp, kf)
    chosen = {k: parameters[k] for k in DEFAULTS if k in parameters}
    free = {k: v for k, v in TUNE_GRID.items() if k not in chosen}
    if tune and free:
        best, _, feasible = grid_tune(
            lambda p: _simulate(prep, machine.te, **{**chosen, **p}), setpoints, machine,
            {**{k: [v] for k, v in chosen.items()}, **free},
        )
        chosen = best
        notes.append(f"Tuned {sorted(free)} on this toolpath: {feasible} feasible combinations.")
    values = {**DEFAULTS, **chosen}
    pos, u = _simulate(prep, machine.te, **values)
    used = {"kp_m_min_per_mm": kp, "kf": kf, **{k: float(v) for k, v in values.items()}}
    return ControllerRun(
        name=NAME, pos=pos, u=u, needs_firmware=NEEDS_FIRMWARE, parameters=used,
        notes=tuple(notes),
    )
