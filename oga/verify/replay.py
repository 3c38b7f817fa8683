"""Verification of a gain schedule: replay it from scratch and check every constraint.

Every metric a user sees comes from this replay on the nonlinear model, never
from the search's predictions. The checks:

- the velocity command ``u`` of every axis meets paper eq. 2 at every sample, rapids,
  dwells, the start and the end included (the machine runs the table through all of
  them): ``|u| <= Vmax``, ``|u_k - u_{k-1}| / Te <= Amax``,
  ``|u_k - 2 u_{k-1} + u_{k-2}| / Te^2 <= Jmax`` (commands before the start are 0:
  the axis starts at rest);
- where the machine sets a following-error limit (``ferror_max_m``), the following
  error ``|pd - p|`` of the axis stays within it at every sample;
- every Kp lies inside its axis's allowed range (within the stable range);
- Kf lies in the machine's Kf range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga.model.contour import contour_error_of
from oga.model.machine import Machine
from oga.model.plant import Plant, plant_of
from oga.model.metrics import ContourMetrics, nan_max, contour_metrics
from oga.model.kinematics import command_peaks
from oga.model.response import simulate

__all__ = ["Verification", "command_ratios", "ferror_ratios", "verify"]

#: Relative slack on the limit checks, for float64 rounding only.
_SLACK = 1e-9


def command_ratios(u: np.ndarray, setpoints: Setpoints, machine: Machine | Plant) -> np.ndarray:
    """Largest ratio of the velocity command's |v|, |a|, |j| to the axis limits (paper eq. 2).

    Checked over every sample, rapids included, as the kinematic range is (:mod:`oga.search.ranges`).

    Parameters
    ----------
    u : ndarray, shape (N, 3)
        Velocity commands, m/s (axes x, y, z); the axes are at rest before sample 0.
    setpoints : Setpoints
        The setpoints (sample period).
    machine : Machine or Plant
        Supplies the limits; an axis the machine lacks must have u == 0.

    Returns
    -------
    ndarray, shape (3, 3)
        ``[axis, (v, a, j)]`` ratios; <= 1 means within the limit.
    """
    limits = plant_of(machine).limits
    u = np.asarray(u, dtype=np.float64)
    check = np.ones(len(u), dtype=bool)
    out = np.zeros((3, 3))
    for k in range(3):
        peaks = command_peaks(u[:, k], check, setpoints.dt)  # a column read in place
        for j in range(3):
            if limits[k, j] > 0:
                out[k, j] = peaks[j] / limits[k, j]
            elif peaks[j] > 0:
                out[k, j] = np.inf
    return out


@njit(cache=True, nogil=True)
def _largest_steps(x):
    """``np.abs(np.diff(x, axis=0)).max(axis=0, initial=0.0)`` of ``x`` (N, 3) in one pass,
    the same numbers (NaN once a step is NaN, as numpy's maximum)."""
    out = np.zeros(3)
    for k in range(1, x.shape[0]):
        for c in range(3):
            out[c] = nan_max(out[c], abs(x[k, c] - x[k - 1, c]))
    return out


def _peak_sample(u: np.ndarray, order: int) -> int:
    """Index of the sample where ``|u|`` (order 0), ``|du|`` (1) or ``|d2u|`` (2) of the
    commands ``u`` (N,) peaks, the axis at rest before sample 0."""
    return int(np.argmax(np.abs(np.diff(np.concatenate([np.zeros(2), u]), order)[2 - order:])))


def _where(setpoints: Setpoints, k: int) -> str:
    """Sample ``k`` in words: index, time, program line, rapid or feed."""
    kind = "in a rapid" if setpoints.rapid[k] else "in a feed move"
    return f"at sample {k} (t = {k * setpoints.dt:.3f} s, line {setpoints.block[k]}, {kind})"


def ferror_ratios(track_max_m, machine: Machine) -> np.ndarray:
    """Largest following error per axis (x, y, z) over the machine's limit (``ferror_max_m``).

    ``track_max_m`` (3,), m: the largest following error of each axis over every sample,
    rapids included (``ContourMetrics.track_max_m``, :func:`oga.model.metrics.contour_metrics`).

    Returns
    -------
    ndarray, shape (3,)
        ``track_max_m / ferror_max_m``; <= 1 means within the limit; NaN where the
        machine sets none.
    """
    limit = machine.ferror_limits()
    return np.where(np.isfinite(limit), np.asarray(track_max_m) / limit, np.nan)


@dataclass(frozen=True, eq=False)
class Verification:
    """The replay of a schedule and its checks.

    Attributes
    ----------
    ok : bool
        Every check passed (``limits_ok and stability_ok``).
    limits_ok : bool
        Eq. 2 holds for every axis at every sample, and so does the machine's
        following-error limit where it sets one.
    stability_ok : bool
        Every Kp inside its allowed range and Kf inside the machine's Kf range.
    pos : ndarray, shape (N, 3)
        Actual positions of the replay, m.
    u : ndarray, shape (N, 3)
        Velocity commands of the replay, m/s.
    ce : ndarray, shape (N,)
        Contour error of the replay, m.
    metrics : ContourMetrics
        Contour-error statistics over the feed samples, the largest following error over
        every sample.
    command_ratio : ndarray, shape (3, 3)
        Largest |v|, |a|, |j| of the command per axis as a ratio to the limit.
    ferror_ratio : ndarray, shape (3,)
        Largest following error per axis as a ratio to the machine's limit; NaN where
        the machine sets none.
    max_dkp_per_sample, max_dkf_per_sample : ndarray, shape (3,)
        Largest gain change between consecutive samples per axis ((m/min)/mm, 1).
    violations : tuple of str
        What failed, in words (a limit: with the sample where it is worst, its time, program
        line, and whether it lies in a rapid or a feed move).
    """

    ok: bool
    limits_ok: bool
    stability_ok: bool
    pos: np.ndarray
    u: np.ndarray
    ce: np.ndarray
    metrics: ContourMetrics
    command_ratio: np.ndarray
    ferror_ratio: np.ndarray
    max_dkp_per_sample: np.ndarray
    max_dkf_per_sample: np.ndarray
    violations: tuple[str, ...]

    @property
    def status(self) -> str:
        """``"ok"`` or ``"failed"``."""
        return "ok" if self.ok else "failed"


def verify(
    setpoints: Setpoints,
    machine: Machine,
    kp_m_min_per_mm: np.ndarray,
    kf: np.ndarray,
    kp_bounds: dict[str, tuple[float, float]],
) -> Verification:
    """Replay gains on the model from rest and check them.

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples).
    machine : Machine or Plant
        The machine (or its plant, packed once).
    kp_m_min_per_mm, kf : ndarray, shape (N, 3)
        The gains per sample and axis.
    kp_bounds : dict
        Allowed (lo, hi) Kp in (m/min)/mm per checked axis (the moving axes).

    Returns
    -------
    Verification
    """
    plant = plant_of(machine)
    machine = plant.machine
    kp = np.asarray(kp_m_min_per_mm, dtype=np.float64)
    kf = np.asarray(kf, dtype=np.float64)
    sim = simulate(setpoints, plant, kp, kf)
    ce = contour_error_of(setpoints, sim.pos)
    metrics = contour_metrics(ce, setpoints.pos, sim.pos, setpoints.counted)
    ratio = command_ratios(sim.u, setpoints, plant)
    limit_v = [
        f"axis {a}: velocity command {what} reaches {ratio[k, j]:.3f}x its limit "
        + _where(setpoints, _peak_sample(sim.u[:, k], j))
        for k, a in enumerate(AXES)
        for j, what in enumerate(("velocity", "acceleration", "jerk"))
        if ratio[k, j] > 1.0 + _SLACK
    ]
    ferror_max = machine.ferror_limits()
    track_max = np.array(metrics.track_max_m)
    ferror_ratio = ferror_ratios(metrics.track_max_m, machine)
    limit_v += [
        f"axis {a}: following error reaches {track_max[k] * 1e3:.4f} mm, "
        f"{ferror_ratio[k]:.3f}x its limit ferror_max_m = {ferror_max[k] * 1e3:.4f} mm "
        + _where(setpoints, int(np.argmax(np.abs(setpoints.pos[:, k] - sim.pos[:, k]))))
        for k, a in enumerate(AXES)
        if ferror_ratio[k] > 1.0 + _SLACK
    ]
    gain_v = []
    for a, (lo, hi) in kp_bounds.items():
        col = kp[:, AXES.index(a)]
        if col.min() < lo - 1e-12 or col.max() > hi + 1e-12:
            gain_v.append(
                f"axis {a}: Kp leaves [{lo}, {hi}] (m/min)/mm: {col.min():.4f}..{col.max():.4f}"
            )
    kf_lo, kf_hi = machine.gains.kf_range
    if kf.min() < kf_lo - 1e-12 or kf.max() > kf_hi + 1e-12:
        gain_v.append(f"Kf leaves [{kf_lo}, {kf_hi}]: {kf.min():.4f}..{kf.max():.4f}")
    limits_ok, stability_ok = not limit_v, not gain_v
    dkp, dkf = _largest_steps(kp), _largest_steps(kf)
    return Verification(
        ok=limits_ok and stability_ok,
        limits_ok=limits_ok,
        stability_ok=stability_ok,
        pos=sim.pos,
        u=sim.u,
        ce=ce,
        metrics=metrics,
        command_ratio=ratio,
        ferror_ratio=ferror_ratio,
        max_dkp_per_sample=dkp,
        max_dkf_per_sample=dkf,
        violations=tuple(limit_v + gain_v),
    )
