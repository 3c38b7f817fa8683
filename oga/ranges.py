"""Gain ranges on a toolpath: kinematic feasibility of fixed gains and the best fixed gains.

For every fixed configuration (Kp, Kf) of a grid, each contouring (moving)
axis is simulated on the setpoints with the nonlinear cascade
(:mod:`oga.simulate`), and the configuration is kinematically feasible for that
axis when its velocity command ``u`` meets paper eq. 2 at every feed sample::

    |u_k| <= Vmax,   |u_k - u_{k-1}| / Te <= Amax,   |u_k - 2 u_{k-1} + u_{k-2}| / Te^2 <= Jmax

with the axis at rest before the first sample (``u_{-1} = u_{-2} = 0``). Samples
of rapid (G0) moves are not checked: the gains concern contouring, and a rapid
planned at the axis limits leaves no room for any position-loop correction.

The best fixed gains (paper case C1, the honest baseline) are the
configuration with EQUAL Kp and EQUAL Kf on every contouring axis (industrial
controllers require equal Kv on interpolating axes) that is feasible on all of
them, with the least MSE of the contour error over the feed samples.

Grids: Kp over each axis's stable range (the grid values of
:func:`oga.stability.stable_range` inside it, ``kp_step_m_min_per_mm`` apart); Kf
over ``machine.gains.kf_range`` in ``kf_step`` steps; values are exact decimals
(``1.1``, not ``1.1000000000000001``).
Every axis configuration is simulated once; the equal-gain contour error combines
the axes' runs of the same configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga.contour import ce_series, contour_error_of, plane_axes
from oga.defaults import CE_WINDOW_SAMPLES
from oga.errors import InputError, OptionError
from oga.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.metrics import ContourMetrics, contour_metrics
from oga.simulate import axis_params, simulate, simulate_axis
from oga.kinematics import command_peaks
from oga.stability import decimal_grid

__all__ = [
    "KinematicRange",
    "BestFixed",
    "Ranges",
    "kinematic_range",
    "gain_ranges",
    "stability_to_dict",
]

#: Decimals kept on grid values (removes float noise of lo + i * step).
_UM2 = 1e12


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
        True where eq. 2 holds at every feed sample.
    vel_peak_m_s, acc_peak_m_s2, jerk_peak_m_s3 : ndarray, shape (P, F)
        Largest ``|u|``, ``|du|/Te``, ``|d2u|/Te^2`` over the feed samples.
    mse_track_m2 : ndarray, shape (P, F)
        Mean squared tracking error ``(pd - p)^2`` of the axis over the feed samples, m^2.
    """

    axis: str
    kp_grid: np.ndarray
    kf_grid: np.ndarray
    feasible: np.ndarray
    vel_peak_m_s: np.ndarray
    acc_peak_m_s2: np.ndarray
    jerk_peak_m_s3: np.ndarray
    mse_track_m2: np.ndarray

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
        Stable Kp range per contouring axis (:func:`oga.stability.stable_range`).
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
        if best is None:
            best_d = {"found": False, "message": "no equal-gain configuration is kinematically "
                      f"feasible on every contouring axis ({', '.join(self.axes)})"}
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
    """Samples where eq. 2 applies (feed samples); refuses an unusable toolpath."""
    if not math.isclose(setpoints.dt, machine.te, rel_tol=1e-9):
        raise OptionError(
            f"setpoints period {setpoints.dt} s differs from the machine's Te {machine.te} s"
        )
    feed = ~setpoints.rapid
    if not feed.any():
        raise InputError(f"{setpoints.source or 'toolpath'}: no feed move (only rapids)")
    return feed


def _sweep(setpoints, machine, axis_grids, kf_grid, common):
    """Simulate every (axis, Kp, Kf) once; per-axis peaks and tracking MSE, equal-gain MSE(CE).

    ``axis_grids`` maps each axis to its Kp grid; ``common`` is the Kp grid shared by
    all of them (empty: no contour error computed). Returns ``(per_axis, mse_ce)`` with
    ``per_axis[a]`` a (4, P_a, F) array (vel, acc, jerk peaks, tracking MSE) and
    ``mse_ce`` of shape (len(common), F).
    """
    feed = _feed_mask(setpoints, machine)
    te = machine.te
    cols = {a: AXES.index(a) for a in axis_grids}
    params = {a: axis_params(machine, a) for a in axis_grids}
    per_axis = {a: np.empty((4, len(g), len(kf_grid))) for a, g in axis_grids.items()}
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
                err = (pos[a] - p_act)[feed]
                per_axis[a][:3, i, j] = command_peaks(u, feed, te)
                per_axis[a][3, i, j] = np.mean(err * err)
                pa[:, c] = p_act
            if kp in common_row:
                ce = ce_series(setpoints.pos, pa, CE_WINDOW_SAMPLES, e1, e2, signed)[feed]
                mse_ce[common_row[kp], j] = np.mean(ce * ce)
    return per_axis, mse_ce


def _kinematic(axis, machine, kp_grid, kf_grid, table) -> KinematicRange:
    lim = machine.axis(axis).limits
    vel, acc, jerk, mse = table
    feasible = (vel <= lim.vmax_m_s) & (acc <= lim.amax_m_s2) & (jerk <= lim.jmax_m_s3)
    return KinematicRange(axis, kp_grid, kf_grid, feasible, vel, acc, jerk, mse)


def _stable_grid(rng) -> np.ndarray:
    """The Kp grid values of a StabilityRange inside its range (empty if none is stable)."""
    return rng.kp[(rng.kp >= rng.kp_min) & (rng.kp <= rng.kp_max)]


def _kf_grid(machine: Machine) -> np.ndarray:
    lo, hi = machine.gains.kf_range
    return decimal_grid(lo, hi, machine.gains.kf_step)


def kinematic_range(
    setpoints: Setpoints,
    machine: Machine,
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
    machine.axis(axis)
    if kp_grid is None:
        from oga.stability import stable_range

        kp_grid = _stable_grid(stable_range(machine, axis))
    kp_grid = np.asarray(kp_grid, dtype=np.float64).reshape(-1)
    kf_grid = _kf_grid(machine) if kf_grid is None else np.asarray(kf_grid, np.float64).reshape(-1)
    if kp_grid.size == 0 or kf_grid.size == 0 or not np.all(kp_grid > 0):
        raise OptionError("kp_grid, kf_grid: need non-empty grids with positive Kp")
    per_axis, _ = _sweep(setpoints, machine, {axis: kp_grid}, kf_grid, np.empty(0))
    return _kinematic(axis, machine, kp_grid, kf_grid, per_axis[axis])


def gain_ranges(setpoints: Setpoints, machine: Machine) -> Ranges:
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
    from oga.stability import stable_range

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
    kf_grid = _kf_grid(machine)
    per_axis, mse_ce = _sweep(setpoints, machine, grids, kf_grid, common)
    kinematic = {a: _kinematic(a, machine, grids[a], kf_grid, per_axis[a]) for a in axes}
    feasible = np.ones(mse_ce.shape, dtype=bool)
    for a in axes:
        rows = np.searchsorted(grids[a], common)
        feasible &= kinematic[a].feasible[rows]
    best = None
    if feasible.any():
        i, j = np.unravel_index(np.argmin(np.where(feasible, mse_ce, np.inf)), mse_ce.shape)
        kp, kf = float(common[i]), float(kf_grid[j])
        sim = simulate(setpoints, machine, kp, kf)
        metrics = contour_metrics(
            contour_error_of(setpoints, sim.pos), setpoints.pos, sim.pos, ~setpoints.rapid
        )
        best = BestFixed(
            kp={a: kp for a in axes},
            kf={a: kf for a in axes},
            mse_ce_m2=float(mse_ce[i, j]),
            metrics=metrics,
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
