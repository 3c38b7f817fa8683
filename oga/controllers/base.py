"""What every comparison controller shares: its result, the path frame, scoring and tuning.

A comparison controller is an alternative position/contour control law simulated on
the same setpoints and the same plant as the fixed gains and the OGA schedule: it
computes a velocity command per axis and sample and drives the plant through
:func:`oga.model.simulate.drive` (same dead time, inner loops, friction and limits).

Each controller module in :mod:`oga.controllers` exposes ``NAME``,
``NEEDS_FIRMWARE``, ``PARAMETERS`` (the names ``run`` accepts), and
``run(setpoints, machine, *, load_n=None, tune=True, **parameters) -> ControllerRun``.
"""

from __future__ import annotations

import itertools
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga.model.contour import contour_error_of, plane_axes
from oga.errors import OptionError, TuneError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.verify.replay import command_ratios

__all__ = [
    "ControllerRun",
    "Score",
    "path_frame",
    "score",
    "grid_tune",
    "check_parameters",
    "best_fixed",
    "baseline_si",
    "given_or_baseline_si",
    "load_array",
]

#: Slack on the command-limit check (float64 rounding only).
_SLACK = 1e-9
#: Best fixed gains of the last few (setpoints, machine) pairs: every controller of a
#: comparison starts from them, and the grid behind them is the costly part.
_BEST: OrderedDict = OrderedDict()
_BEST_KEPT = 4


@dataclass(frozen=True, eq=False)
class ControllerRun:
    """One controller simulated on one toolpath.

    Attributes
    ----------
    name : str
        Controller name (``"ccc"``, ...).
    pos : ndarray, shape (N, 3)
        Measured positions ``p_k`` of x, y, z, m.
    u : ndarray, shape (N, 3)
        Velocity commands ``u_k`` issued to the velocity loops, m/s.
    needs_firmware : bool
        Whether the law needs access to the drive firmware (anything but a gain table).
    parameters : dict
        Every parameter the run used (chosen, tuned or from the paper), names with units.
    notes : tuple of str
        Assumptions and choices a reader must know (one sentence each).
    """

    name: str
    pos: np.ndarray
    u: np.ndarray
    needs_firmware: bool
    parameters: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Score:
    """Contour error and command limits of a run (the quantities tuning compares).

    Attributes
    ----------
    mse_ce_m2 : float
        Mean squared contour error over the samples, m^2.
    command_ratios : ndarray, shape (3, 3)
        ``[axis, (v, a, j)]`` peak velocity-command ratios to the axis limits (paper eq. 2).
    limits_ok : bool
        Every ratio <= 1 (and the contour error finite).
    """

    mse_ce_m2: float
    command_ratios: np.ndarray
    limits_ok: bool


def score(setpoints: Setpoints, machine: Machine, pos: np.ndarray, u: np.ndarray) -> Score:
    """Score positions ``pos`` (N, 3) and commands ``u`` (N, 3) of a run on ``setpoints``.

    A diverged run (positions or commands not finite) scores ``inf`` and fails the limits.
    """
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(u))):
        return Score(mse_ce_m2=np.inf, command_ratios=np.full((3, 3), np.inf), limits_ok=False)
    ce = contour_error_of(setpoints, pos)
    mse = float(np.mean(ce * ce))
    ratios = command_ratios(u, setpoints, machine)
    ok = bool(np.isfinite(mse) and np.all(ratios <= 1.0 + _SLACK))
    return Score(mse_ce_m2=mse, command_ratios=ratios, limits_ok=ok)


def path_frame(setpoints: Setpoints) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """The reference path's local frame in its contour plane, per sample.

    From the setpoints' velocity and acceleration (no G-code geometry needed), as an
    online interpolator would have them.

    Returns
    -------
    tangent : ndarray, shape (N, 2)
        Unit tangent ``(cos theta, sin theta)`` in the plane axes ``(e1, e2)``; where
        the setpoint speed is zero, the last defined tangent (the next one at the start).
    normal : ndarray, shape (N, 2)
        Unit normal: the tangent turned +90 deg (to the left of travel).
    curvature_1_m : ndarray, shape (N,)
        Signed curvature ``(v x a) / |v|^3`` in the plane, 1/m (positive turning left);
        0 where the speed is zero.
    e1, e2 : int
        Column indices (into x, y, z) of the plane axes (x, y for a non-planar path).
    """
    e1, e2, _ = plane_axes(setpoints.plane)
    v = setpoints.vel[:, [e1, e2]]
    a = setpoints.acc[:, [e1, e2]]
    speed = np.hypot(v[:, 0], v[:, 1])
    moving = speed > 1e-9
    n = len(speed)
    tangent = np.zeros((n, 2))
    tangent[moving] = v[moving] / speed[moving, None]
    idx = np.where(moving, np.arange(n), -1)
    idx = np.maximum.accumulate(idx)  # last moving sample at or before k
    first = int(np.argmax(moving)) if moving.any() else 0
    idx[idx < 0] = first
    tangent = tangent[idx] if moving.any() else np.tile([1.0, 0.0], (n, 1))
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    cross = v[:, 0] * a[:, 1] - v[:, 1] * a[:, 0]
    curvature = np.zeros(n)
    curvature[moving] = cross[moving] / speed[moving] ** 3
    return tangent, normal, curvature, e1, e2


def check_parameters(name: str, given: dict, accepted) -> None:
    """OptionError naming the controller and the unknown parameter names, if any."""
    bad = sorted(set(given) - set(accepted))
    if bad:
        raise OptionError(
            f"{name}: unknown parameter(s) {bad}; accepted: {', '.join(sorted(accepted))}"
        )


def grid_tune(
    simulate_fn: Callable[[dict], tuple[np.ndarray, np.ndarray]],
    setpoints: Setpoints,
    machine: Machine,
    grid: dict[str, list],
) -> tuple[dict, Score, int]:
    """Least-MSE(CE) combination of a parameter grid whose commands meet the limits.

    The same effort as the fixed-gain baseline: a grid on the toolpath itself,
    feasibility by paper eq. 2 on the velocity command.

    Parameters
    ----------
    simulate_fn : callable
        ``simulate_fn(params) -> (pos, u)``, both (N, 3).
    setpoints, machine
        The toolpath and the plant.
    grid : dict of str to list
        Values per parameter; every combination is simulated.

    Returns
    -------
    best : dict
        The chosen parameters.
    best_score : Score
        Its score.
    n_feasible : int
        How many combinations met the limits.

    Raises
    ------
    TuneError
        No combination meets the limits (names the grid).
    """
    names = list(grid)
    best, best_score, feasible = None, None, 0
    for values in itertools.product(*(grid[k] for k in names)):
        params = dict(zip(names, values))
        s = score(setpoints, machine, *simulate_fn(params))
        if not s.limits_ok:
            continue
        feasible += 1
        if best_score is None or s.mse_ce_m2 < best_score.mse_ce_m2:
            best, best_score = params, s
    if best is None:
        raise TuneError(f"no parameter combination meets the axis limits; grid {grid}")
    return best, best_score, feasible


def best_fixed(setpoints: Setpoints, machine: Machine):
    """The best equal fixed gains on this toolpath (:func:`oga.search.ranges.best_fixed_gains`), memoised.

    Returns
    -------
    oga.search.ranges.BestFixed

    Raises
    ------
    OptionError
        No equal fixed gains meet the axis limits on this toolpath.
    """
    key = (setpoints, machine.digest())  # Setpoints hash by identity
    if key not in _BEST:
        from oga.search.ranges import best_fixed_gains

        _BEST[key] = best_fixed_gains(setpoints, machine)
        if len(_BEST) > _BEST_KEPT:
            _BEST.popitem(last=False)
    best = _BEST[key]
    if best is None:
        raise OptionError(
            f"{setpoints.source or 'toolpath'}: no equal fixed gains meet the axis limits "
            "(paper eq. 2); give the baseline gains"
        )
    return best


def baseline_si(setpoints: Setpoints, machine: Machine) -> tuple[np.ndarray, np.ndarray]:
    """The best fixed gains per axis x, y, z: ``(kp (3,), kf (3,))`` in 1/s and factor.

    Axes that do not move get the same (common) values. OptionError as :func:`best_fixed`.
    """
    best = best_fixed(setpoints, machine)
    kp0, kf0 = next(iter(best.kp.values())), next(iter(best.kf.values()))
    kp = np.array([best.kp.get(a, kp0) for a in AXES]) * KP_SI_PER_M_MIN_PER_MM
    kf = np.array([best.kf.get(a, kf0) for a in AXES])
    return kp, kf


def given_or_baseline_si(setpoints: Setpoints, machine: Machine, parameters: dict,
                         kp_name: str, kf_name: str) -> tuple[np.ndarray, np.ndarray]:
    """The baseline gains ``(kp (3,) 1/s, kf (3,))``: those named ``kp_name``, ``kf_name`` in
    ``parameters`` on every axis when both are given, else :func:`baseline_si`."""
    if kp_name in parameters and kf_name in parameters:
        return (np.full(3, float(parameters[kp_name])), np.full(3, float(parameters[kf_name])))
    return baseline_si(setpoints, machine)


def load_array(load_n, n: int) -> np.ndarray:
    """External load force per sample and axis as a new (n, 3) float64 array, N (zeros if None).

    Raises
    ------
    OptionError
        Not finite, or not of shape (n, 3).
    """
    if load_n is None:
        return np.zeros((n, 3))
    try:
        load = np.array(load_n, dtype=np.float64)
    except (TypeError, ValueError):
        raise OptionError(f"load_n: expected numbers of shape ({n}, 3)") from None
    if load.shape != (n, 3) or not np.all(np.isfinite(load)):
        raise OptionError(f"load_n: expected finite values of shape ({n}, 3), got {load.shape}")
    return load
