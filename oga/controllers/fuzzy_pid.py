"""``fuzzy-pid``: Mamdani fuzzy self-tuning PID position control per axis.

After Wang, Chen & Chen (2013), "A fuzzy self-tuning controlled feeding servo system
of machine tool" (``fuzzy_self_tuning_pid.txt``). Per contouring axis and sample k,
with the position error ``e_k = pd_k - p_k`` (m) and its rate
``ec_k = (e_k - e_{k-1}) / Te`` (m/s; 0 at k = 0):

- normalised inputs ``x_e = 6 e / e_range``, ``x_ec = 6 ec / ec_range`` (saturated to
  [-6, 6]);
- gains ``K = K' + (dK_max / 6) * mamdani(table, x_e, x_ec)`` for Kp, Ki, Kd with the
  classic tables of :mod:`oga.controllers.fuzzy` (paper eqs. 2-4);
- velocity command ``u_k = Kp e_k + Ki Te sum_{j<=k} e_j + Kd ec_k + kf vd_k``
  (paper eq. 5 in positional form, gains in SI: Kp 1/s, Ki 1/s^2, Kd dimensionless),
  plus the velocity feed-forward ``kf vd`` (the paper, a step test, has none; on a
  contour a fair comparison needs it: ``kf = 0`` gives the paper's law).

The paper's figures (Ke = 0.2, Kec = 0.1, k1 = 0.5, k2 = k3 = 0.01, K'p = 16.4,
K'i = 0.3, K'd = 0.5) are for its own normalised plant; we keep their proportions:
the largest increment is ``dK_max = ratio * K'`` with the paper's ratios
``6 k / K'`` (0.18, 0.2, 0.12). The initial PID is the baseline's: K'p the best fixed
Kp, K'i = K'p^2 / 10 (the PI zero a decade below the crossover, about K'p rad/s),
K'd = 0.05 (the PD zero at 20 K'p, above the crossover), kf the best fixed Kf.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from feedplan.setpoints import Setpoints
from oga import defaults
from oga.model.contour import plane_axes
from oga.controllers.base import (
    ControllerRun, check_parameters, given_or_baseline_si, grid_tune, load_array)
from oga.controllers.fuzzy import RULES, UNIVERSE, mamdani
from oga.errors import OptionError
from oga.model.machine import Machine
from oga.model.simulate import drive
from oga.model.response import axis_arrays

__all__ = ["NAME", "NEEDS_FIRMWARE", "PARAMETERS", "run", "law_inputs"]

NAME = "fuzzy-pid"
NEEDS_FIRMWARE = True
PARAMETERS = (
    "kp_1_s",
    "ki_1_s2",
    "kd",
    "kf",
    "e_range_m",
    "ec_range_m_s",
    "dkp_ratio",
    "dki_ratio",
    "dkd_ratio",
)

#: Largest increments as fractions of the initial gains: the paper's 6 k1 / K'p,
#: 6 k2 / K'i, 6 k3 / K'd.
PAPER_RATIOS = {
    "dkp_ratio": 6 * 0.5 / 16.4,
    "dki_ratio": 6 * 0.01 / 0.3,
    "dkd_ratio": 6 * 0.01 / 0.5,
}
#: Design defaults and tuning grid (:mod:`oga.defaults`, where their reasons are given).
KI_PER_KP2 = defaults.FUZZY_PID_KI_PER_KP2
KD_DEFAULT = defaults.FUZZY_PID_KD
E_RANGE_M = defaults.FUZZY_PID_E_RANGE_M
EC_RANGE_M_S = defaults.FUZZY_PID_EC_RANGE_M_S
TUNE_GRID = defaults.FUZZY_PID_TUNE_GRID
#: The parameters each grid axis sets (a grid axis is dropped when all of them are given).
_TUNES = {
    "kp_factor": ("kp_1_s",),
    "ki_per_kp2": ("ki_1_s2",),
    "range_factor": ("e_range_m", "ec_range_m_s"),
}


def law_inputs(setpoints: Setpoints, load_n) -> tuple[np.ndarray, ...]:
    """Contiguous arrays for a compiled multi-axis loop.

    Returns
    -------
    pd, vd, ad : ndarray, shape (N, 3)
        Setpoint position (m), velocity (m/s), acceleration (m/s^2).
    rapid : ndarray of bool, shape (N,)
    plane : ndarray of bool, shape (3,)
        Which of x, y, z are the contour-plane axes (x, y for a non-planar path).
    load : ndarray, shape (N, 3)
        External load force, N (zeros if ``load_n`` is None).
    """
    load = load_array(load_n, len(setpoints))
    e1, e2, _ = plane_axes(setpoints.plane)
    plane = np.zeros(3, dtype=np.bool_)
    plane[[e1, e2]] = True
    return (
        np.ascontiguousarray(setpoints.pos, dtype=np.float64),
        np.ascontiguousarray(setpoints.vel, dtype=np.float64),
        np.ascontiguousarray(setpoints.acc, dtype=np.float64),
        np.ascontiguousarray(setpoints.rapid),
        plane,
        load,
    )


#: The loop's inputs packed for :func:`_simulate`: ``present``, ``law`` (3,) bool, ``pd``,
#: ``vd`` (N, 3) setpoints (m, m/s), ``rapid`` (N,) bool, ``load`` (N, 3) force (N), and the
#: baseline ``kp_b`` (1/s), ``kf_b`` (3,) of the other axes and the rapids.
Inputs = namedtuple("Inputs", ["present", "law", "pd", "vd", "rapid", "load", "kp_b", "kf_b"])


@njit(cache=True)
def _simulate(params, states, inputs, gains, te, pos, u):
    """The fuzzy PID on the ``law`` axes, P + FFW elsewhere and on rapids.

    ``inputs`` an :data:`Inputs`; ``gains`` (9,): K'p, K'i, K'd, kf, 6/e_range,
    6/ec_range, dKp_max/6, dKi_max/6, dKd_max/6. Fills ``pos`` and ``u`` (N, 3).
    """
    present, pd, vd, rapid, law, load = (inputs.present, inputs.pd, inputs.vd, inputs.rapid,
                                         inputs.law, inputs.load)
    kp_b, kf_b = inputs.kp_b, inputs.kf_b
    n = pd.shape[0]
    e_prev = np.zeros(3)
    integ = np.zeros(3)
    for k in range(n):
        for a in range(3):
            if not present[a]:
                pos[k, a] = pd[k, a]
                continue
            p = states[a, 0]
            pos[k, a] = p
            e = pd[k, a] - p
            ec = 0.0 if k == 0 else (e - e_prev[a]) / te
            e_prev[a] = e
            if law[a] and not rapid[k]:
                xe, xec = e * gains[4], ec * gains[5]
                kp = gains[0] + gains[6] * mamdani(RULES[0], xe, xec)
                ki = gains[1] + gains[7] * mamdani(RULES[1], xe, xec)
                kd = gains[2] + gains[8] * mamdani(RULES[2], xe, xec)
                integ[a] += te * e
                cmd = kp * e + ki * integ[a] + kd * ec + gains[3] * vd[k, a]
            else:
                cmd = kp_b[a] * e + kf_b[a] * vd[k, a]
            u[k, a] = cmd
            drive(states[a], params[a], cmd, load[k, a])


def _values(given: dict, kp_b: np.ndarray, kf_b: np.ndarray) -> dict:
    """Every parameter: the given ones over the design defaults."""
    kp = given.get("kp_1_s", float(kp_b[0]))
    out = {
        "kp_1_s": kp,
        "ki_1_s2": KI_PER_KP2 * kp * kp,
        "kd": KD_DEFAULT,
        "kf": float(kf_b[0]),
        "e_range_m": E_RANGE_M,
        "ec_range_m_s": EC_RANGE_M_S,
        **PAPER_RATIOS,
    }
    out.update(given)
    for name in ("e_range_m", "ec_range_m_s"):
        if not out[name] > 0.0:
            raise OptionError(f"{NAME}: {name} must be positive, got {out[name]}")
    return out


_NOTES = (
    "Velocity feed-forward kf vd added to the paper's PID (kf = 0 gives the paper's law).",
    "Gains in SI: u = Kp e + Ki Te sum(e) + Kd de/dt; increments dK = ratio K' mamdani/6 "
    "with the paper's ratios 6 k / K'.",
    "Initial PID: K'p best fixed Kp, K'i = K'p^2/10, K'd = 0.05; other axes and rapids: "
    "P + FFW at the baseline gains.",
)


def _gain_array(values: dict) -> np.ndarray:
    """The ``gains`` (9,) of :func:`_simulate` from the parameter values."""
    return np.array(
        [
            values["kp_1_s"],
            values["ki_1_s2"],
            values["kd"],
            values["kf"],
            UNIVERSE / values["e_range_m"],
            UNIVERSE / values["ec_range_m_s"],
            values["dkp_ratio"] * values["kp_1_s"] / UNIVERSE,
            values["dki_ratio"] * values["ki_1_s2"] / UNIVERSE,
            values["dkd_ratio"] * values["kd"] / UNIVERSE,
        ]
    )


def _grid_values(values: dict, given: dict, choice: dict) -> dict:
    """The values at a point ``choice`` of the tuning grid (factors on ``values``; the
    ranges ``given`` are kept)."""
    v = dict(values)
    v["kp_1_s"] = values["kp_1_s"] * choice.get("kp_factor", 1.0)
    if "ki_per_kp2" in choice:
        v["ki_1_s2"] = choice["ki_per_kp2"] * v["kp_1_s"] ** 2
    for name in _TUNES["range_factor"]:
        if name not in given:
            v[name] = values[name] * choice.get("range_factor", 1.0)
    return v


def _tune(simulate, setpoints: Setpoints, machine: Machine, values: dict, given: dict,
          notes: list) -> dict:
    """The values tuned on :data:`TUNE_GRID` (the grid's parameters not ``given``); a note
    appended to ``notes``."""
    grid = {k: list(v) for k, v in TUNE_GRID.items() if not set(_TUNES[k]) <= set(given)}
    if not grid:
        return values
    choice, _, n_ok = grid_tune(
        lambda c: simulate(_grid_values(values, given, c)), setpoints, machine, grid
    )
    notes.append(f"Tuned on this toolpath: {n_ok} feasible grid points, chose {choice}.")
    return _grid_values(values, given, choice)


def run(
    setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True, **parameters
) -> ControllerRun:
    """Simulate the fuzzy self-tuning PID on ``setpoints``.

    Parameters
    ----------
    setpoints : Setpoints
        The toolpath (N samples at the machine's Te).
    machine : Machine
        The plant.
    load_n : array_like, shape (N, 3), optional
        External load force per sample and axis, N.
    tune : bool
        Tune K'p, K'i and the input ranges on this toolpath (:data:`TUNE_GRID`, paper
        eq. 2 feasibility); parameters given are kept fixed.
    **parameters
        Any of :data:`PARAMETERS`; ``kp_1_s`` and ``kf`` also set the P + FFW of the
        other axes and the rapids (default: the best fixed gains).

    Returns
    -------
    ControllerRun

    Raises
    ------
    OptionError
        Unknown parameter, bad value, or no tuned combination meets the limits.
    """
    check_parameters(NAME, parameters, PARAMETERS)
    kp_b, kf_b = given_or_baseline_si(setpoints, machine, parameters, "kp_1_s", "kf")
    pd, vd, _, rapid, law, load = law_inputs(setpoints, load_n)
    params, states0, present = axis_arrays(machine, pd[0] if len(pd) else np.zeros(3))
    inputs = Inputs(present, law, pd, vd, rapid, load, kp_b, kf_b)

    def simulate(values: dict) -> tuple[np.ndarray, np.ndarray]:
        pos = np.empty_like(pd)
        u = np.zeros_like(pd)
        _simulate(params, states0.copy(), inputs, _gain_array(values), machine.te, pos, u)
        return pos, u

    notes = list(_NOTES)
    values = _values(parameters, kp_b, kf_b)
    if tune:
        values = _tune(simulate, setpoints, machine, values, parameters, notes)
    pos, u = simulate(values)
    values["kp_base_1_s"] = float(kp_b[0])
    values["kf_base"] = float(kf_b[0])
    return ControllerRun(
        name=NAME,
        pos=pos,
        u=u,
        needs_firmware=NEEDS_FIRMWARE,
        parameters=values,
        notes=tuple(notes),
    )
