"""The plant's response to setpoints and gains: every axis of a machine simulated at once.

The compiled axis models and their packing live in :mod:`oga.model.simulate`; this module
runs them on a :class:`~oga.model.plant.Plant` (a machine packed once), so that the plant
depends on the kernels and the response on both, not the other way round.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga.errors import MachineError, OptionError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.model.plant import Plant, plant_of
from oga.model.simulate import _CASCADE, _KIND, _P, rest_state, run_axes, simulate_axis

__all__ = ["Simulation", "simulate", "simulate_si", "gain_tables", "axis_arrays"]


def axis_arrays(machine: Machine | Plant, p0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Packed parameters and rest states of the x, y, z axes, for compiled multi-axis loops.

    Rows are in ``AXES`` order (every axis of a machine has the same lengths), so a
    compiled loop can pass ``params[a]`` and ``states[a]`` (contiguous row views)
    to :func:`drive` for every present axis ``a``.

    Parameters
    ----------
    machine : Machine or Plant
        Machine description (or its plant).
    p0 : array_like, shape (3,)
        Initial positions of x, y, z, m (each present axis starts at rest there).

    Returns
    -------
    params : ndarray, shape (3, P)
        :func:`axis_params` of each present axis (zeros for an absent axis).
    states : ndarray, shape (3, S)
        :func:`rest_state` of each present axis (zeros for an absent axis).
    present : ndarray of bool, shape (3,)
        Whether the machine has the axis.
    """
    plant = plant_of(machine)
    params = np.array(plant.params)  # writeable: the compiled loops take the same types
    states = np.zeros((3, plant.state_size))
    for c, a in enumerate(AXES):
        if a in plant.axes:
            states[c] = rest_state(params[c], float(p0[c]))
    present = np.array([a in plant.axes for a in AXES])
    return params, states, present


@dataclass(frozen=True, eq=False)
class Simulation:
    """The simulated machine on a toolpath (columns in ``AXES`` order x, y, z).

    Attributes
    ----------
    pos : ndarray, shape (N, 3)
        Measured (actual) positions ``p_k``, m.
    u : ndarray, shape (N, 3)
        Velocity commands ``u_k``, m/s.
    kp_m_min_per_mm : ndarray, shape (N, 3)
        Position gains used, (m/min)/mm.
    kf : ndarray, shape (N, 3)
        Velocity feed-forward factors used.
    """

    pos: np.ndarray
    u: np.ndarray
    kp_m_min_per_mm: np.ndarray
    kf: np.ndarray


def _gain_table(value, name: str, n: int) -> np.ndarray:
    """A gain given as scalar, {axis: value} or (N, 3) array, as an (N, 3) float64 array."""
    if isinstance(value, dict):
        bad = sorted(set(value) - set(AXES))
        if bad:
            raise OptionError(f"{name}: unknown axis name(s) {bad}; use x, y, z")
        missing = [a for a in AXES if a not in value]
        if missing:
            raise OptionError(f"{name}: no value for axis/axes {missing}")
        row = [value[a] for a in AXES]
        try:
            table = np.tile(np.asarray(row, dtype=np.float64), (n, 1))
        except (TypeError, ValueError):
            raise OptionError(f"{name}: values must be numbers, got {row}") from None
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise OptionError(f"{name}: expected a number, a dict or an (N, 3) array") from None
        if arr.ndim == 0:
            table = np.full((n, 3), float(arr))
        elif arr.shape == (n, 3):
            table = arr.copy()
        else:
            raise OptionError(f"{name}: expected shape ({n}, 3), got {arr.shape}")
    if not np.all(np.isfinite(table)):
        raise OptionError(f"{name}: values must be finite")
    return table


def gain_tables(kp_m_min_per_mm, kf, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The gains of :func:`simulate` (each a scalar, {axis: value} or (N, 3) array) as new
    (N, 3) float64 arrays ``(kp, kf)``, checked.

    Raises
    ------
    OptionError
        Malformed, not finite, or a Kp not positive.
    """
    kp = _gain_table(kp_m_min_per_mm, "kp_m_min_per_mm", n)
    kf_t = _gain_table(kf, "kf", n)
    if np.any(kp <= 0.0):
        raise OptionError("kp_m_min_per_mm: gains must be positive")
    return kp, kf_t


def _at_rest(model, pd: np.ndarray, vd: np.ndarray) -> bool:
    """Whether a cascade axis started at rest at ``pd[0]`` stays there exactly, whatever the
    gains: its setpoint never moves (``pd == pd[0]``, ``vd == 0`` at every sample).

    Then every command is ``Kp (pd - p) + Kf vd = 0`` exactly, the dead-time line, the PI
    integral and the force stay 0, the friction of a zero velocity is 0 (``tanh(0)``), so the
    kernel would return ``p = pd[0]`` and ``u = 0`` at every sample: the replay is skipped
    (tests/test_robust_speed.py compares it with the kernel's, bit for bit). An ARX axis is
    always replayed. ``model``: the axis (:class:`oga.model.machine.Axis`).
    """
    return model.arx is None and _still(pd, vd)


@njit(cache=True, nogil=True)
def _still(pd, vd):
    """``np.all(pd == pd[0]) and not np.any(vd)`` of ``pd``, ``vd`` (N,), N >= 1, in one
    compiled pass (a NaN setpoint is not still, a NaN velocity is not zero)."""
    p0 = pd[0]
    for k in range(pd.size):
        if not pd[k] == p0 or vd[k] != 0.0:
            return False
    return True


def simulate(setpoints: Setpoints, machine: Machine | Plant, kp_m_min_per_mm, kf) -> Simulation:
    """Simulate every axis of ``machine`` on ``setpoints``, each from rest at its first setpoint.

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples); its period must be the machine's Te.
    machine : Machine or Plant
        Machine description, or its :class:`~oga.model.plant.Plant` (packed once).
    kp_m_min_per_mm : float, dict or array_like, shape (N, 3)
        Position gain in (m/min)/mm: one value, one per axis ``{"x": .., "y": .., "z": ..}``
        (every axis named), or per sample and axis. Must be positive.
    kf : float, dict or array_like, shape (N, 3)
        Velocity feed-forward factor, in the same forms.

    Returns
    -------
    Simulation
        An axis the machine lacks holds its setpoint (u = 0); it must not move.

    Raises
    ------
    OptionError
        Gains malformed or not positive, or sample period different from Te.
    MachineError
        A setpoint moves an axis the machine lacks.
    """
    plant = plant_of(machine)
    kp, kf_t = gain_tables(kp_m_min_per_mm, kf, len(setpoints))
    pos, u = simulate_si(setpoints, plant, kp * KP_SI_PER_M_MIN_PER_MM, kf_t)
    for arr in (kp, kf_t):
        arr.flags.writeable = False
    return Simulation(pos=pos, u=u, kp_m_min_per_mm=kp, kf=kf_t)


def _same_period(setpoints: Setpoints, plant: Plant) -> None:
    """Raise :class:`OptionError` unless the setpoints' period is the machine's Te."""
    te = plant.machine.te
    if not math.isclose(setpoints.dt, te, rel_tol=1e-9):
        raise OptionError(f"setpoints period {setpoints.dt} s differs from the machine's Te {te} s")


def simulate_si(setpoints: Setpoints, plant: Plant, kp_si: np.ndarray, kf: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`simulate` of gains already checked: the same positions and commands, for
    callers that replay one gain table on many plants (:func:`oga.verify.replay.verify_prepared`).

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples); its period must be the plant's Te.
    plant : Plant
        The packed machine.
    kp_si, kf : ndarray, shape (N, 3), float64
        Position gain in 1/s (``Kp * KP_SI_PER_M_MIN_PER_MM``, positive) and feed-forward
        factor per sample and axis, finite (not checked; read only).

    Returns
    -------
    pos, u : ndarray, shape (N, 3)
        As :class:`Simulation`'s, read-only.

    Raises
    ------
    OptionError
        Sample period different from Te.
    MachineError
        A setpoint moves an axis the machine lacks.
    """
    _same_period(setpoints, plant)
    n = len(setpoints)
    machine = plant.machine
    pos = np.empty((n, 3))
    u = np.zeros((n, 3))
    params, states = np.zeros(plant.params.shape), np.zeros((3, plant.state_size))
    fused = []  # the moving cascade axes: one :func:`run_axes`
    for c, a in enumerate(AXES):
        pd = setpoints.pos[:, c]
        if a not in machine.axes:
            if c in setpoints.moving_axes:
                raise MachineError(
                    f"machine {machine.name!r} has no axis {a!r}, but the toolpath moves it"
                )
            pos[:, c] = pd
            continue
        if not n:
            pos[:, c] = pd
            continue
        if _at_rest(machine.axes[a], pd, setpoints.vel[:, c]):
            pos[:, c] = pd  # exact rest: u stays 0 (:func:`_at_rest`), nothing to pack
            continue
        params[c] = plant.params[c]
        if params[c, _KIND] == _CASCADE:
            states[c, _P] = pd[0]  # :func:`rest_state`
            fused.append(c)
        else:
            pos[:, c], u[:, c] = simulate_axis(params[c], pd[0], np.ascontiguousarray(pd),
                                               setpoints.vel[:, c], kp_si[:, c], kf[:, c])
    if fused:
        run_axes(states, params, np.array(fused, dtype=np.int64), setpoints.pos, setpoints.vel,
                 kp_si, kf, pos, u)
    for arr in (pos, u):
        arr.flags.writeable = False
    return pos, u
