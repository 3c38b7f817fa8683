"""Gain ranges on a toolpath: kinematic feasibility of fixed gains and the best fixed gains.

For every fixed configuration (Kp, Kf) of a grid, each contouring (moving)
axis is simulated on the setpoints with the nonlinear cascade
(:mod:`oga.model.simulate`), and the configuration is kinematically feasible for that
axis when its velocity command ``u`` meets paper eq. 2 at every sample::

    |u_k| <= Vmax,   |u_k - u_{k-1}| / Te <= Amax,   |u_k - 2 u_{k-1} + u_{k-2}| / Te^2 <= Jmax

with the axis at rest before the first sample (``u_{-1} = u_{-2} = 0``): rapids,
dwells, the start and the end included (the machine runs the table through them; a
command that breaks a limit there is as wrong as on a cut).
Where the machine sets a following-error limit (``ferror_max_m``), a feasible
configuration also keeps ``|pd - p|`` within it at every sample.

The best fixed gains (paper case C1, the honest baseline) are the
configuration with EQUAL Kp and EQUAL Kf on every contouring axis (industrial
controllers require equal Kv on interpolating axes) that is feasible on all of
them, with the least MSE of the contour error over the feed samples.

Grids: Kp over each axis's stable range (the grid values of
:func:`oga.model.stability.stable_range` inside it, ``kp_step_m_min_per_mm`` apart); Kf
over ``machine.gains.kf_range`` in ``kf_step`` steps; values are exact decimals
(``1.1``, not ``1.1000000000000001``).
Every axis configuration is simulated once; the equal-gain contour error combines
the axes' runs of the same configuration.

:func:`best_fixed_gains` finds the same best fixed gains without the tables, in one
compiled pass over the equal-gain grid: a configuration's simulation stops at its first
violation of eq. 2 or of the machine's following-error limit, and its contour error is
summed only until the partial sum of squares proves that it cannot beat the best so far
(exact pruning, see :func:`_equal_gain_search`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga.model.contour import ce2_at, ce_series, contour_error_of, path_index, plane_axes
from oga.defaults import CE_WINDOW_SAMPLES
from oga.errors import InputError, OptionError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.model.metrics import ContourMetrics, contour_metrics
from oga.model.plant import Plant, plant_of
from oga.model.simulate import rest_state, run, run_axes, simulate_axis
from oga.model.response import simulate
from oga.model.kinematics import command_peaks
from oga.model.stability import decimal_grid

__all__ = [
    "KinematicRange",
    "BestFixed",
    "Ranges",
    "kinematic_range",
    "gain_ranges",
    "best_fixed_gains",
    "EqualGainMemo",
    "stability_to_dict",
]

#: um^2 per m^2 (the JSON's unit of squared errors).
_UM2 = 1e12
#: Relative margin on sums of squared contour errors compared in different summation
#: orders, from terms that may differ by 2 ulp (:func:`_equal_gain_search`): the rounding
#: of a sum of n >= 0 terms is below n * 1.1e-16 relative, the terms' 2 ulp add 4.4e-16,
#: so 1e-6 keeps every comparison sound up to 10^9 samples (and costs nothing in pruning).
_SUM_SLACK = 1e-6
#: Samples simulated between two eq. 2 checks in :func:`_equal_gain_search` (speed only:
#: a pruned configuration wastes the rest of its last chunk, a short chunk costs calls).
_CHUNK = 64
#: Parts of the equal-gain grid between two progress reports of :func:`best_fixed_gains`.
_PROGRESS_PARTS = 16
#: What :func:`_equal_gain_search` learnt of a configuration: not visited, broke a limit,
#: abandoned by the pruning, or simulated to the end (its sum and peaks known).
_UNSEEN, _INFEASIBLE, _PRUNED, _COMPLETE = 0, 1, 2, 3


@dataclass(frozen=True, eq=False)
class KinematicRange:
    """Kinematic feasibility of fixed gains for one axis on one toolpath (paper sec. 3.5).

    Attributes
    ----------
    axis : str
        Axis name.
    kp_grid : ndarray, shape (P,)
        Kp values, (m/min)/mm.
    kf_grid : ndarray, shape (F,)
        Kf values (factor).
    feasible : ndarray of bool, shape (P, F)
        True where eq. 2 holds at every sample, and the machine's following-error
        limit where it sets one.
    vel_peak_m_s, acc_peak_m_s2, jerk_peak_m_s3 : ndarray, shape (P, F)
        Largest ``|u|``, ``|du|/Te``, ``|d2u|/Te^2`` over every sample.
    mse_track_m2 : ndarray, shape (P, F)
        Mean squared tracking error ``(pd - p)^2`` of the axis over the feed samples, m^2.
    track_max_m : ndarray, shape (P, F)
        Largest following error ``|pd - p|`` of the axis over every sample, m.
    """

    axis: str
    kp_grid: np.ndarray
    kf_grid: np.ndarray
    feasible: np.ndarray
    vel_peak_m_s: np.ndarray
    acc_peak_m_s2: np.ndarray
    jerk_peak_m_s3: np.ndarray
    mse_track_m2: np.ndarray
    track_max_m: np.ndarray

    @property
    def count(self) -> int:
        """Number of feasible configurations."""
        return int(self.feasible.sum())

    def pairs(self) -> list[tuple[float, float]]:
        """Feasible ``(kp, kf)`` pairs, Kp-major order."""
        return [
            (float(self.kp_grid[i]), float(self.kf_grid[j])) for i, j in np.argwhere(self.feasible)
        ]


@dataclass(frozen=True)
class BestFixed:
    """The best equal fixed gains (paper case C1).

    Attributes
    ----------
    kp : dict of str to float
        Kp per contouring axis, (m/min)/mm (all equal).
    kf : dict of str to float
        Kf per contouring axis (all equal).
    mse_ce_m2 : float
        MSE of the contour error over the feed samples, m^2.
    metrics : ContourMetrics
        Full contour-error figures of that configuration.
    """

    kp: dict[str, float]
    kf: dict[str, float]
    mse_ce_m2: float
    metrics: ContourMetrics


@dataclass(frozen=True, eq=False)
class Ranges:
    """Stability and kinematic ranges of every contouring axis, and the best fixed gains.

    Attributes
    ----------
    machine : str
        Machine name.
    axes : tuple of str
        Contouring (moving) axes.
    stability : dict of str to StabilityRange
        Stable Kp range per contouring axis (:func:`oga.model.stability.stable_range`).
    kinematic : dict of str to KinematicRange
        Per contouring axis, over its own stable Kp grid.
    kp_grid : ndarray, shape (P,)
        Kp values stable on every contouring axis, (m/min)/mm (the equal-gain grid).
    kf_grid : ndarray, shape (F,)
        Kf values.
    mse_ce_m2 : ndarray, shape (P, F)
        MSE(CE) over the feed samples with that (Kp, Kf) on every contouring axis, m^2.
    feasible : ndarray of bool, shape (P, F)
        The equal-gain configuration is feasible on every contouring axis.
    best_fixed : BestFixed or None
        Least MSE(CE) among the feasible equal-gain configurations; None when
        none is feasible (then ``feasible`` is all False).
    """

    machine: str
    axes: tuple[str, ...]
    stability: dict
    kinematic: dict[str, KinematicRange]
    kp_grid: np.ndarray
    kf_grid: np.ndarray
    mse_ce_m2: np.ndarray
    feasible: np.ndarray
    best_fixed: BestFixed | None

    def to_dict(self) -> dict:
        """JSON-able summary in users' units (the ``oga ranges`` JSON).

        ``{"machine", "axes": {a: {"stability": .., "kinematic": {"feasible": [[kp, kf], ..],
        "count", "grid_size"}}}, "equal_gains": {"kp", "kf", "mse_ce_um2", "feasible"},
        "best_fixed": {"found", "kp": {a: v}, "kf": {a: v}, "mse_ce_um2", "metrics"}}``.
        """
        axes = {
            a: {
                "stability": stability_to_dict(self.stability[a]),
                "kinematic": {
                    "feasible": [list(p) for p in self.kinematic[a].pairs()],
                    "count": self.kinematic[a].count,
                    "grid_size": int(self.kinematic[a].feasible.size),
                },
            }
            for a in self.axes
        }
        best = self.best_fixed
        if best is None and self.kp_grid.size == 0:  # the margins rule every Kp out
            best_d = {"found": False, "message": "no Kp of the grid meets the stability "
                      f"criteria on every contouring axis ({', '.join(self.axes)}): "
                      + "; ".join(self.stability[a].message for a in self.axes)}
        elif best is None:
            best_d = {"found": False, "message": "no equal-gain configuration is kinematically "
                      f"feasible on every contouring axis ({', '.join(self.axes)}): eq. 2, and "
                      "the following-error limits where the machine sets them, at every sample"}
        else:
            best_d = {"found": True, "kp": best.kp, "kf": best.kf,
                      "mse_ce_um2": best.mse_ce_m2 * _UM2, "metrics": best.metrics.to_dict()}
        return {
            "machine": self.machine,
            "axes": axes,
            "equal_gains": {
                "kp": self.kp_grid.tolist(),
                "kf": self.kf_grid.tolist(),
                "mse_ce_um2": (self.mse_ce_m2 * _UM2).tolist(),
                "feasible": self.feasible.tolist(),
            },
            "best_fixed": best_d,
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def stability_to_dict(rng) -> dict:
    """JSON-able StabilityRange: ``{"kp_min", "kp_max", "status", "message", "pm_min_deg",
    "gm_min_db", "table": [{"kp", "pm_deg", "gm_db"}]}`` (non-finite values as null)."""
    return {
        "kp_min": _finite_or_none(rng.kp_min),
        "kp_max": _finite_or_none(rng.kp_max),
        "status": rng.status,
        "message": rng.message,
        "pm_min_deg": rng.pm_min_deg,
        "gm_min_db": rng.gm_min_db,
        "table": [
            {"kp": kp, "pm_deg": _finite_or_none(pm), "gm_db": _finite_or_none(gm)}
            for kp, pm, gm in rng.table
        ],
    }


def _feed_mask(setpoints: Setpoints, machine: Machine) -> np.ndarray:
    """Samples where the contour error counts (feed samples); refuses an unusable toolpath."""
    if not math.isclose(setpoints.dt, machine.te, rel_tol=1e-9):
        raise OptionError(
            f"setpoints period {setpoints.dt} s differs from the machine's Te {machine.te} s"
        )
    feed = setpoints.counted
    if not feed.any():
        raise InputError(f"{setpoints.source or 'toolpath'}: no feed move (only rapids)")
    return feed


def _sweep(setpoints, plant, axis_grids, kf_grid, common):
    """Simulate every (axis, Kp, Kf) once; per-axis peaks and tracking MSE, equal-gain MSE(CE).

    ``axis_grids`` maps each axis to its Kp grid; ``common`` is the Kp grid shared by
    all of them (empty: no contour error computed). Returns ``(per_axis, mse_ce)`` with
    ``per_axis[a]`` a (5, P_a, F) array (vel, acc, jerk peaks, tracking MSE, largest
    tracking error) and ``mse_ce`` of shape (len(common), F).
    """
    feed = _feed_mask(setpoints, plant.machine)
    every = np.ones(len(setpoints), dtype=bool)  # eq. 2 and the following error: all samples
    te = plant.machine.te
    cols = {a: AXES.index(a) for a in axis_grids}
    params = {a: np.array(plant.axis_params(a)) for a in axis_grids}
    per_axis = {a: np.empty((5, len(g), len(kf_grid))) for a, g in axis_grids.items()}
    mse_ce = np.empty((len(common), len(kf_grid)))
    e1, e2, signed = plane_axes(setpoints.plane)
    pa = np.array(setpoints.pos, dtype=np.float64)  # axes not simulated hold their setpoints
    pos = {a: np.ascontiguousarray(setpoints.pos[:, c]) for a, c in cols.items()}
    vel = {a: np.ascontiguousarray(setpoints.vel[:, c]) for a, c in cols.items()}
    row = {a: {float(kp): i for i, kp in enumerate(g)} for a, g in axis_grids.items()}
    every_kp = np.unique(np.concatenate(list(axis_grids.values())))
    common_row = {float(kp): i for i, kp in enumerate(common)}
    for kp in every_kp:
        kp = float(kp)
        for j, kf in enumerate(kf_grid):
            for a, c in cols.items():
                i = row[a].get(kp)
                if i is None:
                    continue
                p_act, u = simulate_axis(
                    params[a], pos[a][0], pos[a], vel[a], kp * KP_SI_PER_M_MIN_PER_MM, float(kf)
                )
                err = pos[a] - p_act
                per_axis[a][:3, i, j] = command_peaks(u, every, te)
                per_axis[a][3, i, j] = np.mean(err[feed] ** 2)
                per_axis[a][4, i, j] = np.abs(err).max()
                pa[:, c] = p_act
            if kp in common_row:
                ce = ce_series(setpoints.pos, pa, CE_WINDOW_SAMPLES, e1, e2, signed)[feed]
                mse_ce[common_row[kp], j] = np.mean(ce * ce)
    return per_axis, mse_ce


def _kinematic(axis, machine, kp_grid, kf_grid, table) -> KinematicRange:
    lim = machine.axis(axis).limits
    vel, acc, jerk, mse, track = table
    feasible = (vel <= lim.vmax_m_s) & (acc <= lim.amax_m_s2) & (jerk <= lim.jmax_m_s3)
    if lim.ferror_max_m is not None:
        feasible &= track <= lim.ferror_max_m
    return KinematicRange(axis, kp_grid, kf_grid, feasible, vel, acc, jerk, mse, track)


def _stable_grid(rng) -> np.ndarray:
    """The Kp grid values of a StabilityRange inside its range (empty if none is stable)."""
    return rng.kp[(rng.kp >= rng.kp_min) & (rng.kp <= rng.kp_max)]


def _kf_grid(machine: Machine) -> np.ndarray:
    lo, hi = machine.gains.kf_range
    return decimal_grid(lo, hi, machine.gains.kf_step)


def kinematic_range(
    setpoints: Setpoints,
    machine: Machine | Plant,
    axis: str,
    kp_grid: np.ndarray | None = None,
    kf_grid: np.ndarray | None = None,
) -> KinematicRange:
    """Kinematically feasible fixed (Kp, Kf) of one axis on a toolpath (paper eq. 2).

    Parameters
    ----------
    setpoints : Setpoints
        Planned motion; its period must be the machine's Te.
    machine : Machine
        Machine description (limits, cascade, gain settings).
    axis : {"x", "y", "z"}
        The axis (MachineError if the machine lacks it).
    kp_grid : array_like, shape (P,), optional
        Kp values, (m/min)/mm, positive; default the axis's stable range in
        ``kp_step_m_min_per_mm`` steps.
    kf_grid : array_like, shape (F,), optional
        Kf values; default ``kf_range`` in ``kf_step`` steps.

    Returns
    -------
    KinematicRange

    Raises
    ------
    OptionError
        Empty or non-positive Kp grid, empty Kf grid, or period differs from Te.
    InputError
        The toolpath has no feed move.
    """
    plant = plant_of(machine)
    machine = plant.machine
    machine.axis(axis)
    if kp_grid is None:
        from oga.model.stability import stable_range

        kp_grid = _stable_grid(stable_range(machine, axis))
    kp_grid = np.asarray(kp_grid, dtype=np.float64).reshape(-1)
    kf_grid = _kf_grid(machine) if kf_grid is None else np.asarray(kf_grid, np.float64).reshape(-1)
    if kp_grid.size == 0 or kf_grid.size == 0 or not np.all(kp_grid > 0):
        raise OptionError("kp_grid, kf_grid: need non-empty grids with positive Kp")
    per_axis, _ = _sweep(setpoints, plant, {axis: kp_grid}, kf_grid, np.empty(0))
    return _kinematic(axis, machine, kp_grid, kf_grid, per_axis[axis])


def _equal_grid(setpoints: Setpoints, machine: Machine):
    """Contouring axes, their stable ranges and Kp grids, the common Kp grid and the Kf grid.

    Returns ``(axes, stability, grids, common, kf_grid)``; InputError when no axis
    moves, MachineError when the machine lacks a moving axis.
    """
    from oga.model.stability import stable_range

    axes = tuple(AXES[c] for c in setpoints.moving_axes)
    if not axes:
        raise InputError(f"{setpoints.source or 'toolpath'}: no axis moves")
    for a in axes:
        machine.axis(a)
    stability = {a: stable_range(machine, a) for a in axes}
    grids = {a: _stable_grid(s) for a, s in stability.items()}
    common = grids[axes[0]]
    for a in axes[1:]:
        common = np.intersect1d(common, grids[a])
    return axes, stability, grids, common, _kf_grid(machine)


def _best_fixed(setpoints, machine, axes, kp: float, kf: float, mse_ce_m2: float) -> BestFixed:
    """The BestFixed of the equal gains ``(kp, kf)``, its contour-error figures simulated."""
    sim = simulate(setpoints, machine, kp, kf)
    metrics = contour_metrics(
        contour_error_of(setpoints, sim.pos), setpoints.pos, sim.pos, setpoints.counted
    )
    return BestFixed(
        kp={a: kp for a in axes}, kf={a: kf for a in axes}, mse_ce_m2=mse_ce_m2, metrics=metrics
    )


def gain_ranges(setpoints: Setpoints, machine: Machine | Plant) -> Ranges:
    """Stability and kinematic ranges of the contouring axes, and the best fixed gains.

    Parameters
    ----------
    setpoints : Setpoints
        Planned motion; its period must be the machine's Te.
    machine : Machine
        Machine description.

    Returns
    -------
    Ranges

    Raises
    ------
    InputError
        No axis moves, or no feed move.
    MachineError
        The toolpath moves an axis the machine lacks.
    """
    plant = plant_of(machine)
    machine = plant.machine
    axes, stability, grids, common, kf_grid = _equal_grid(setpoints, machine)
    per_axis, mse_ce = _sweep(setpoints, plant, grids, kf_grid, common)
    kinematic = {a: _kinematic(a, machine, grids[a], kf_grid, per_axis[a]) for a in axes}
    feasible = np.ones(mse_ce.shape, dtype=bool)
    for a in axes:
        rows = np.searchsorted(grids[a], common)
        feasible &= kinematic[a].feasible[rows]
    best = None
    if feasible.any():
        i, j = np.unravel_index(np.argmin(np.where(feasible, mse_ce, np.inf)), mse_ce.shape)
        best = _best_fixed(
            setpoints, machine, axes, float(common[i]), float(kf_grid[j]), float(mse_ce[i, j])
        )
    return Ranges(
        machine=machine.name,
        axes=axes,
        stability=stability,
        kinematic=kinematic,
        kp_grid=common,
        kf_grid=kf_grid,
        mse_ce_m2=mse_ce,
        feasible=feasible,
        best_fixed=best,
    )


def best_fixed_gains(setpoints: Setpoints, machine: Machine | Plant, *,
                     progress: Callable[[float], None] | None = None,
                     memo: EqualGainMemo | None = None) -> BestFixed | None:
    """The best equal fixed gains (paper case C1) without the full tables of :func:`gain_ranges`.

    Returns exactly ``gain_ranges(setpoints, machine).best_fixed`` (same gains, same
    MSE to the last bit, same choice among equal MSEs: the first in Kp-major grid
    order), several times faster: one compiled pass (:func:`_equal_gain_search`)
    simulates each equal-gain configuration until its first violation of eq. 2 or of
    the following-error limit and sums its squared contour error only while it can
    still beat the best so far. The few configurations left within rounding of the
    least sum are then evaluated exactly as :func:`gain_ranges` does.

    Parameters
    ----------
    setpoints : Setpoints
        Planned motion; its period must be the machine's Te.
    machine : Machine
        Machine description.
    progress : callable, optional
        Called with the fraction of the grid visited (0..1), :data:`_PROGRESS_PARTS` times
        (the same result: the pruning bound is carried from part to part).
    memo : EqualGainMemo, optional
        Shared by calls on the same setpoints and dynamics whose limits only shrink
        (the same result, fewer simulations).

    Returns
    -------
    BestFixed or None
        None when no equal-gain configuration is feasible on every contouring axis
        (as ``Ranges.best_fixed``).

    Raises
    ------
    InputError
        No axis moves, or no feed move.
    MachineError
        The toolpath moves an axis the machine lacks.
    OptionError
        Sample period different from Te.
    """
    plant = plant_of(machine)
    machine = plant.machine
    axes, _stability, _grids, common, kf_grid = _equal_grid(setpoints, machine)
    feed = _feed_mask(setpoints, machine)
    cols = np.array([AXES.index(a) for a in axes], dtype=np.int64)
    lim = plant.limits
    limits = np.column_stack([lim[:, 0], lim[:, 1], lim[:, 2], machine.ferror_limits()])[cols]
    params = plant.params[cols]  # ferror inf above: none set
    memo = EqualGainMemo() if memo is None else memo
    sse = memo.start(setpoints, params, common, kf_grid, limits)
    visit = _visit_order(memo, len(common), len(kf_grid))
    by_col = np.zeros((3, params.shape[1]))
    by_col[cols] = params
    fused = np.array([AXES.index(a) for a in axes if machine.axis(a).kind == "cascade"],
                     dtype=np.int64)
    tree, lo, hi = memo.index
    packed = ((by_col, fused, cols, limits, machine.te),
              (np.ascontiguousarray(setpoints.pos, dtype=np.float64),
               np.ascontiguousarray(setpoints.vel, dtype=np.float64), feed, tree, lo, hi),
              (common * KP_SI_PER_M_MIN_PER_MM, kf_grid))
    parts = [visit] if progress is None else np.array_split(visit, _PROGRESS_PARTS)
    for k, part in enumerate(parts):
        found = _equal_gain_search(*packed, part, _SUM_SLACK, sse.min(),
                                   (memo.status, memo.peaks, memo.lower, memo.resume))
        memo.sse = np.where(memo.status == _COMPLETE, np.minimum(memo.sse, found), memo.sse)
        sse = np.minimum(sse, found)
        if progress is not None:
            progress((k + 1) / len(parts))
    if not np.isfinite(sse).any():
        return None
    return _least_of_near(setpoints, plant, axes, (common, kf_grid), sse, feed)


def _visit_order(memo, n_kp: int, n_kf: int) -> np.ndarray:
    """The configurations ``(i, j)`` of the grid still to visit, shape (M, 2): a heuristic
    order (speed only, the result does not depend on it: stiff loops and strong
    feed-forward first, as the least contour error usually lies at the top of the stable
    range, at the largest feasible Kf), then the lowest known bounds first (those never
    visited keep it): the least sum is found early, and fewer abandoned configurations are
    simulated again."""
    visit = np.array(
        [(i, j) for i in range(n_kp - 1, -1, -1) for j in range(n_kf - 1, -1, -1)], np.int64
    ).reshape(-1, 2)
    status = memo.status[visit[:, 0], visit[:, 1]]
    visit = visit[(status == _UNSEEN) | (status == _PRUNED)]  # the others are known
    return visit[np.argsort(memo.lower[visit[:, 0], visit[:, 1]], kind="stable")]


def _least_of_near(setpoints, plant, axes, grid, sse, feed) -> BestFixed:
    """Among every configuration that may hold the least MSE(CE) (within rounding of the
    least sum ``sse``), the least, evaluated exactly, Kp-major like gain_ranges' argmin."""
    common, kf_grid = grid
    near = np.argwhere(sse <= sse.min() * (1.0 + _SUM_SLACK))
    mse = [_mse_ce(setpoints, plant, axes, float(common[i]), float(kf_grid[j]), feed)
           for i, j in near]
    k = int(np.argmin(mse))
    i, j = near[k]
    return _best_fixed(setpoints, plant.machine, axes, float(common[i]), float(kf_grid[j]),
                       mse[k])


class EqualGainMemo:
    """What :func:`best_fixed_gains` learnt of each equal-gain configuration, for a next call
    on the same setpoints, dynamics and grids whose limits are nowhere larger (the robust
    baseline's design machines, their limits cut reserve after reserve).

    A configuration that broke a limit breaks the smaller ones too; one simulated to the end
    keeps its sum of squared contour errors, and its peaks (eq. 2 and the following error)
    decide whether it holds the new limits, with the comparisons of the compiled search; one
    the pruning abandoned is simulated again only if its running sum there does not prove
    it worse than the best so far (visited in the order of that sum, least first), and
    resumes where it was abandoned: from the start of that chunk (:data:`_CHUNK`), with the
    state, commands, running sum and peaks it had there (the same operations on the same
    numbers as a simulation from the start: the same bits). The best
    fixed gains found are those of a call without the memo (the result does not depend on
    the visiting order or on which sums are known: :func:`_equal_gain_search`;
    tests/test_ranges_memo.py compares them). Any other call starts the memo afresh.

    Attributes
    ----------
    status : ndarray of int8, shape (P, F)
        :data:`_UNSEEN`, :data:`_INFEASIBLE`, :data:`_PRUNED` or :data:`_COMPLETE`.
    peaks : ndarray, shape (P, F, A, 4)
        Largest ``|u|``, ``|du|/Te``, ``|d2u|/Te^2`` and ``|pd - p|`` per moving axis.
    sse : ndarray, shape (P, F)
        Sum of squared contour errors of the complete configurations (``inf`` elsewhere).
    lower : ndarray, shape (P, F)
        A lower bound of each configuration's sum: the running sum where the pruning
        abandoned it (0: none known).
    resume : tuple
        Where each abandoned configuration resumes (:func:`_equal_gain_search`): ``(at,
        total, state, u)``, shapes (P, F), (P, F), (P, F, 3, Z), (P, F, 2, 3): the first
        sample of the chunk it was abandoned in (-1: none), the running sum, the axes'
        states and the two commands before that sample.
    index : tuple
        The path's index (:func:`oga.model.contour.path_index`, window
        :data:`oga.defaults.CE_WINDOW_SAMPLES`), built once per setpoints.
    """

    def __init__(self):
        self._key, self._limits = None, None
        self.status = self.peaks = self.sse = self.lower = self.resume = self.index = None

    def start(self, setpoints, params, common, kf_grid, limits) -> np.ndarray:
        """Prepare a call with ``limits`` (shape (A, 4)); returns the sums already known of
        the configurations that hold them (``inf`` elsewhere), shape (P, F)."""
        key = (setpoints, params.tobytes(), common.tobytes(), kf_grid.tobytes())
        same = (self._key is not None and self._key[0] is setpoints and self._key[1:] == key[1:]
                and bool(np.all(limits <= self._limits)))
        self._limits = limits.copy()
        if not same:
            if self._key is None or self._key[0] is not setpoints:
                self.index = path_index(np.ascontiguousarray(setpoints.pos, dtype=np.float64),
                                        CE_WINDOW_SAMPLES)
            self._key = key
            grid = (len(common), len(kf_grid))
            self.status = np.zeros(grid, dtype=np.int8)
            self.peaks = np.zeros(grid + (len(params), 4))
            self.sse = np.full(grid, np.inf)
            self.lower = np.zeros(grid)
            self.resume = (np.full(grid, -1, dtype=np.int64), np.zeros(grid),
                           np.zeros(grid + (3, rest_state(params[0], 0.0).size)),
                           np.zeros(grid + (2, 3)))
            return self.sse.copy()
        for i, j in np.argwhere(self.status == _COMPLETE):
            if not all(_holds(*self.peaks[i, j, a], limits[a]) for a in range(len(params))):
                self.status[i, j] = _INFEASIBLE
                self.sse[i, j] = np.inf
        return self.sse.copy()


def _mse_ce(setpoints, plant, axes, kp: float, kf: float, feed) -> float:
    """MSE(CE) over the feed samples of equal gains ``(kp, kf)``, evaluated as :func:`_sweep`
    does (same simulations, same contour error, same numpy mean: the same bits)."""
    pa = np.array(setpoints.pos, dtype=np.float64)
    for a in axes:
        c = AXES.index(a)
        pd = np.ascontiguousarray(setpoints.pos[:, c])
        pa[:, c], _ = simulate_axis(
            np.array(plant.params[c]), pd[0], pd, np.ascontiguousarray(setpoints.vel[:, c]),
            kp * KP_SI_PER_M_MIN_PER_MM, kf,
        )
    ce = ce_series(setpoints.pos, pa, CE_WINDOW_SAMPLES, *plane_axes(setpoints.plane))[feed]
    return float(np.mean(ce * ce))


@njit(cache=True)
def _checked(pd, p_act, u, te, lim, k0, k1, check, pk) -> bool:
    """Check eq. 2 and the following-error limit over samples ``k0 .. k1 - 1`` of one
    simulated axis.

    :func:`oga.model.kinematics.command_peaks` checks the new samples with the same arithmetic
    as :func:`_sweep`, the two commands before ``k0`` taken as history (they were checked
    with the previous samples).

    Parameters
    ----------
    pd, p_act, u : ndarray, shape (N,)
        Setpoint and measured positions (m) and commands (m/s) (read over ``k0 - 2 .. k1 - 1``).
    te : float
        Sample period, s.
    lim : ndarray, shape (4,)
        Vmax (m/s), Amax (m/s^2), Jmax (m/s^3), following-error limit (m, inf: none).
    k0, k1 : int
        Sample range.
    check : ndarray of bool, shape (>= k1 - k0 + 2,)
        Scratch.
    pk : ndarray, shape (4,)
        Largest ``|u|``, ``|du|/Te``, ``|d2u|/Te^2`` and ``|pd - p|`` so far: raised to
        this range's (``nan`` stays), whether or not it holds.

    Returns
    -------
    bool
        Whether eq. 2 and the following-error limit hold at every sample of the
        range (the latter as :func:`_kinematic` checks it: ``|pd - p| <= limit``).
    """
    h = max(k0 - 2, 0)
    mask = check[: k1 - h]
    mask[:] = True
    mask[: k0 - h] = False  # the history, checked with the previous samples
    v_pk, a_pk, j_pk = command_peaks(u[h:k1], mask, te)
    e_pk = 0.0
    for k in range(k0, k1):
        e = abs(pd[k] - p_act[k])
        if not e <= e_pk:
            e_pk = e
    _raise(pk, 0, v_pk)
    _raise(pk, 1, a_pk)
    _raise(pk, 2, j_pk)
    _raise(pk, 3, e_pk)
    return _holds(v_pk, a_pk, j_pk, e_pk, lim)


@njit(cache=True)
def _raise(pk, i, x):
    if not x <= pk[i]:
        pk[i] = x


@njit(cache=True)
def _holds(v_pk, a_pk, j_pk, e_pk, lim) -> bool:
    """Eq. 2 and the following-error limit (where one is set: ``lim[3]`` not inf) hold for
    these peaks, as :func:`_kinematic` checks them."""
    return (v_pk <= lim[0] and a_pk <= lim[1] and j_pk <= lim[2]
            and (lim[3] == np.inf or e_pk <= lim[3]))


@njit(cache=True)
def _keep(resume, i, j, k, s, states, u):
    """Keep in ``resume`` where configuration ``(i, j)`` goes on: at sample ``k`` (a chunk's
    start), the running sum ``s`` of the samples before it, the axes' ``states`` there and
    the two commands before it."""
    at, total, kept_state, kept_u = resume
    at[i, j] = k
    total[i, j] = s
    kept_state[i, j] = states
    if k >= 2:
        kept_u[i, j] = u[k - 2:k]


@njit(cache=True)
def _equal_gain_search(plant, path, grid, visit, slack, best, memo):
    """Sum of squared contour errors of the equal-gain configurations, pruned exactly.

    Best first: the configuration of ``visit`` with the least lower bound (``lower``: its
    running sum so far, 0 when never simulated; the first in the order ``visit`` among
    equal ones) is simulated until its running sum, at the end of a chunk, passes the
    next least bound (and its own bound on entry), then paused (kept in ``resume``, as an
    abandoned one below) for the one of least bound then. A configuration is simulated
    to the end only while no other can be proved to have a smaller sum, so a feasible one
    of larger sum is simulated only until its running sum passes the least sum (times ``1
    + slack``, to within a chunk), whichever order the grid would be visited in. The
    moving axes are simulated together, ``_CHUNK`` samples at a time (the cascade ones side by side:
    :func:`oga.model.simulate.run_axes`, the same bits as :func:`oga.model.simulate.run` axis by axis),
    and checked axis after axis (:func:`_checked`); a configuration is dropped at its
    first violation of eq. 2 or of the following-error limit (at any sample, rapids
    included). After each chunk the squared contour error of its feed samples is added to
    a running sum, in time order (:func:`oga.model.contour.ce2_at`, each sample's search hinted
    with the previous sample's nearest segment).

    Pruning and resuming: :func:`_run_config`.

    Parameters
    ----------
    plant : tuple ``(params, fused, cols, limits, te)``
        ``params`` (3, P): row ``c`` the packed parameters (:func:`oga.model.simulate.axis_params`)
        of the axis of column ``c``, for the moving ones; ``fused``: the columns of the
        moving cascade axes (run side by side, the others one by one); ``cols`` (A,): the
        columns of the A moving axes, in checking order; ``limits`` (A, 4): Vmax (m/s),
        Amax (m/s^2), Jmax (m/s^3), following-error limit (m, inf: none) of each; ``te``: s.
    path : tuple ``(pos, vel, feed, tree, lo, hi)``
        Setpoint positions (N, 3) (m; axes not simulated hold them) and velocities (m/s);
        the feed samples (N,) (the MSE counts them; eq. 2 applies at every sample); the
        path's index (:func:`oga.model.contour.path_index` of ``pos``, window of
        :func:`oga.model.contour.ce_series`).
    grid : tuple ``(kp_si, kf)``
        Kp grid (P,), 1/s, and Kf grid (F,).
    visit : ndarray of int, shape (M, 2)
        Grid indices ``(i, j)``, in the order that breaks ties of ``lower`` (speed only).
    slack : float
        Relative margin of the pruning test.
    best : float
        Least complete sum of configurations visited before (``inf``: none).
    memo : tuple ``(status, peaks, lower, resume)``
        Of :class:`EqualGainMemo`, for each configuration: ``status`` (P, F) int8 receives
        :data:`_INFEASIBLE`, :data:`_PRUNED` or :data:`_COMPLETE`; ``peaks`` (P, F, A, 4)
        its largest ``|u|``, ``|du|/Te``, ``|d2u|/Te^2``, ``|pd - p|`` per axis over the
        samples simulated; ``lower`` (P, F) a lower bound of its sum (0: none known; one
        above the pruning bound is not simulated, stays pruned), receives the running sum
        where pruned or completed; ``resume`` ``(at, total, state, u)`` (``at`` -1: from
        the first sample), read when visited, written when pruned.

    Returns
    -------
    ndarray, shape (P, F)
        Sum of the squared contour errors over the feed samples, m^2, of the
        feasible configurations not pruned; ``inf`` elsewhere (all ``inf``: none is
        feasible).
    """
    kp_si, kf = grid
    status, _peaks, lower, _resume = memo
    sse = np.full((kp_si.size, kf.size), np.inf)
    work = _search_work(plant, path[0])
    todo = np.ones(visit.shape[0], dtype=np.bool_)
    while True:
        bound = best * (1.0 + slack)
        m, least, other = _least_bound(visit, todo, lower, status, bound)
        if m < 0:
            break
        todo[m] = False
        i, j = visit[m, 0], visit[m, 1]
        s, end = _run_config(plant, path, grid, memo, work, (i, j), bound, max(other, least))
        if end == _PAUSED:
            todo[m] = True
        elif end == _DONE:
            sse[i, j] = s
            lower[i, j] = s
            status[i, j] = _COMPLETE
            best = min(best, s)
    return sse


#: How :func:`_run_config` left a configuration: dropped (infeasible or pruned), paused
#: (to be taken up again), or simulated to the end.
_DROPPED, _PAUSED, _DONE = 0, 1, 2


@njit(cache=True)
def _search_work(plant, pos):
    """Scratch of :func:`_equal_gain_search`: ``(p_act, u, kp_k, kf_k, check, alone, states,
    start)``: the path with the moving axes' columns overwritten chunk by chunk, the commands
    (each chunk's check reads the previous two), the gains per sample, the check's scratch,
    the moving axes not run side by side, the axes' states and those at the chunk's start."""
    params, fused, cols = plant[0], plant[1], plant[2]
    n = pos.shape[0]
    alone = np.ones(3, dtype=np.bool_)  # moving axes not in ``fused``: :func:`run` each
    alone[fused] = False
    states = np.zeros((3, rest_state(params[cols[0]], 0.0).size))
    return (pos.copy(), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)),
            np.empty(_CHUNK + 2, dtype=np.bool_), alone, states, np.empty_like(states))


@njit(cache=True)
def _least_bound(visit, todo, lower, status, bound):
    """The configuration of ``visit`` still to do with the least lower bound (the first in
    visiting order among equal ones), ``(q, its bound, the next least)``; ``q`` -1: none.
    Those whose bound passed ``bound`` are marked pruned and done."""
    m, least, other = -1, np.inf, np.inf
    for q in range(visit.shape[0]):
        if not todo[q]:
            continue
        lq = lower[visit[q, 0], visit[q, 1]]
        if lq > bound:  # pruned before, and still: its sum is at least that
            status[visit[q, 0], visit[q, 1]] = _PRUNED
            todo[q] = False
        elif lq < least:
            m, least, other = q, lq, least
        elif lq < other:
            other = lq
    return m, least, other


@njit(cache=True)
def _take_up(plant, pos, memo, work, ij):
    """Start configuration ``ij`` from rest, or resume it where it was left; returns
    ``(first sample, running sum)``, first -1 when the peaks kept break a limit."""
    params, _fused, cols, limits, _te = plant
    _status, peaks, _lower, resume = memo
    u, states = work[1], work[6]
    i, j = ij
    at, total, kept_state, kept_u = resume
    pk = peaks[i, j]
    first = at[i, j]
    if first < 0:
        for a in range(cols.size):
            states[cols[a]] = rest_state(params[cols[a]], pos[0, cols[a]])
        pk[:] = 0.0
        return 0, 0.0
    alive = True  # abandoned or paused before: on from that chunk
    for a in range(cols.size):
        if not _holds(pk[a, 0], pk[a, 1], pk[a, 2], pk[a, 3], limits[a]):
            alive = False
    if not alive:
        return -1, 0.0
    states[:] = kept_state[i, j]
    if first >= 2:
        u[first - 2:first] = kept_u[i, j]
    s = total[i, j]
    at[i, j] = -1
    return first, s


@njit(cache=True)
def _run_config(plant, path, grid, memo, work, ij, bound, pause):
    """Simulate configuration ``ij`` chunk by chunk from where :func:`_take_up` puts it,
    until it breaks a limit, its sum passes ``bound`` (pruned) or ``pause`` (paused), or
    it ends; returns ``(running sum, _DROPPED | _PAUSED | _DONE)``.

    Pruning: a sum of non-negative terms only grows, so once the running sum exceeds
    the best complete sum (times ``1 + slack``, covering the rounding of both sums and
    the 2 ulp by which each term may differ from the square of
    :func:`oga.model.contour.ce_series`) the configuration's MSE is provably larger than that
    of a feasible configuration; it cannot be the least, feasible or not, and is
    abandoned there (checked after every term), its simulation too.

    Resuming: an abandoned or paused configuration keeps, in ``resume``, the state of its
    axes, the two commands and the running sum at the start of the chunk it was abandoned
    in (or the next one, paused). It is taken up again (in this call or a later one) while
    its ``lower`` is within the bound (so a simulation from the start would reach that
    chunk unpruned): the peaks kept (those of every sample simulated) are checked against
    ``limits`` (broken: infeasible, as such a simulation would find), and it is simulated
    on from that chunk: the same operations on the same numbers from there, the same sum
    to the last bit. A paused configuration taken up again pauses only past its own
    bound, so the configurations are taken in the same order, and the memo holds the
    same, whether it resumes or starts again from the first sample.
    """
    status, peaks, lower, resume = memo
    p_act, u, states, start = work[0], work[1], work[6], work[7]
    i, j = ij
    n = p_act.shape[0]
    status[i, j] = _INFEASIBLE
    first, s = _take_up(plant, path[0], memo, work, ij)
    if first < 0:
        return s, _DROPPED
    near = -1  # nearest segment of the previous sample: the hint of the next
    for k0 in range(first, n, _CHUNK):
        k1 = min(k0 + _CHUNK, n)
        start[:] = states
        s0 = s
        if not _chunk_feasible(plant, path, grid, work, ij, k0, k1, peaks[i, j]):
            return s, _DROPPED
        s, near, over = _chunk_sum(path, p_act, (k0, k1), s, bound, near)
        if over:
            status[i, j] = _PRUNED
            lower[i, j] = s
            _keep(resume, i, j, k0, s0, start, u)
            return s, _DROPPED
        if s > pause and k1 < n:  # another configuration's sum is now the least
            status[i, j] = _PRUNED
            lower[i, j] = s
            _keep(resume, i, j, k1, s, states, u)
            return s, _PAUSED
    return s, _DONE


@njit(cache=True)
def _chunk_feasible(plant, path, grid, work, ij, k0, k1, pk):
    """Simulate samples ``k0 .. k1 - 1`` of configuration ``ij`` on the moving axes and
    check them (:func:`_checked`, raising the peaks ``pk``); False at the first violation."""
    params, fused, cols, limits, te = plant
    pos, vel = path[0], path[1]
    p_act, u, kp_k, kf_k, check, alone, states, _start = work
    i, j = ij
    kp_k[k0:k1] = grid[0][i]
    kf_k[k0:k1] = grid[1][j]
    run_axes(states, params, fused, pos[k0:k1], vel[k0:k1], kp_k[k0:k1], kf_k[k0:k1],
             p_act[k0:k1], u[k0:k1])
    for a in range(cols.size):
        c = cols[a]
        if alone[c]:
            run(states[c], params[c], pos[k0:k1, c], vel[k0:k1, c], kp_k[k0:k1, c],
                kf_k[k0:k1, c], p_act[k0:k1, c], u[k0:k1, c])
        if not _checked(pos[:, c], p_act[:, c], u[:, c], te, limits[a], k0, k1, check, pk[a]):
            return False
    return True


@njit(cache=True)
def _chunk_sum(path, p_act, span, s, bound, near):
    """Add the squared contour errors of the feed samples of ``span = (k0, k1)`` to the
    running sum ``s``, in time order, stopping where it passes ``bound``; returns ``(s,
    nearest segment hint, passed)``."""
    pos, _vel, feed, tree, lo, hi = path
    for k in range(span[0], span[1]):
        if feed[k]:
            ce2, near = ce2_at(pos, tree, lo[k], hi[k], k, p_act[k, 0], p_act[k, 1],
                               p_act[k, 2], near)
            s += ce2
            if s > bound:
                return s, near, True
    return s, near, False
