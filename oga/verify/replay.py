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
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.model.plant import Plant, plant_of
from oga.model.metrics import ContourMetrics, nan_max, contour_metrics
from oga.model.kinematics import command_peaks
from oga.model.response import gain_tables, simulate_si

__all__ = ["Verification", "ReplayGains", "command_ratios", "ferror_ratios", "verify",
           "verify_prepared"]

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
    pos : ndarray, shape (N, 3), or None
        Actual positions of the replay, m; None in a replay kept without its series
        (:func:`verify_prepared`'s ``series=False``: a certificate's plants but its worst).
    u : ndarray, shape (N, 3), or None
        Velocity commands of the replay, m/s (None as ``pos``).
    ce : ndarray, shape (N,), or None
        Contour error of the replay, m (None as ``pos``).
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
    pos: np.ndarray | None
    u: np.ndarray | None
    ce: np.ndarray | None
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


@dataclass(frozen=True, eq=False)
class ReplayGains:
    """A gain table as :func:`verify_prepared` replays it, with what its checks need that does
    not depend on the plant: prepared once for a table replayed on many plants (a
    certificate), the same :class:`Verification` as :func:`verify`'s.

    Attributes
    ----------
    kp, kf : ndarray, shape (N, 3)
        The gains, (m/min)/mm and factor (private copies: never written).
    kp_si : ndarray, shape (N, 3)
        ``kp * KP_SI_PER_M_MIN_PER_MM``, 1/s.
    kp_range, kf_range : ndarray, shape (3, 2)
        Least and largest Kp and Kf per axis.
    max_dkp_per_sample, max_dkf_per_sample : ndarray, shape (3,)
        Largest gain change between consecutive samples per axis.
    """

    kp: np.ndarray
    kf: np.ndarray
    kp_si: np.ndarray
    kp_range: np.ndarray
    kf_range: np.ndarray
    max_dkp_per_sample: np.ndarray
    max_dkf_per_sample: np.ndarray

    @classmethod
    def of(cls, setpoints: Setpoints, kp_m_min_per_mm, kf) -> "ReplayGains":
        """The table ``kp_m_min_per_mm``, ``kf`` (N, 3) prepared for ``setpoints``.

        Raises
        ------
        OptionError
            Gains malformed, not finite or Kp not positive (as :func:`simulate`).
        """
        n = len(setpoints)
        kp, kf_t = gain_tables(kp_m_min_per_mm, kf, n)

        def ranges(t):
            return np.column_stack([t.min(axis=0), t.max(axis=0)]) if n else np.zeros((3, 2))
        shared = (ranges(kp), ranges(kf_t), _largest_steps(kp), _largest_steps(kf_t))
        for arr in shared:  # in every Verification of the table
            arr.flags.writeable = False
        return cls(kp, kf_t, kp * KP_SI_PER_M_MIN_PER_MM, *shared)


def verify(
    setpoints: Setpoints,
    machine: Machine,
    kp_m_min_per_mm: np.ndarray,
    kf: np.ndarray,
    kp_bounds: dict[str, tuple[float, float]],
    series: bool = True,
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
    series : bool
        False: the checks and figures without the series (:func:`verify_prepared`).

    Returns
    -------
    Verification
    """
    return verify_prepared(setpoints, machine, ReplayGains.of(setpoints, kp_m_min_per_mm, kf),
                           kp_bounds, series)


def verify_prepared(setpoints: Setpoints, machine: Machine, gains: ReplayGains,
                    kp_bounds: dict[str, tuple[float, float]], series: bool = True
                    ) -> Verification:
    """:func:`verify` of a table prepared once (:class:`ReplayGains`) for many plants;
    ``series=False`` keeps the checks and figures but not the series ``pos``, ``u``, ``ce``
    (7 doubles a sample: lathe_pawn's robust search, 331 621 samples, peaked at 9.9 GB with
    every certificate's plants keeping theirs, 0.72 GB without)."""
    plant = plant_of(machine)
    machine = plant.machine
    pos, u = simulate_si(setpoints, plant, gains.kp_si, gains.kf)
    ce = contour_error_of(setpoints, pos)
    metrics = contour_metrics(ce, setpoints.pos, pos, setpoints.counted)
    ratio = command_ratios(u, setpoints, plant)
    limit_v = [
        f"axis {a}: velocity command {what} reaches {ratio[k, j]:.3f}x its limit "
        + _where(setpoints, _peak_sample(u[:, k], j))
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
        + _where(setpoints, int(np.argmax(np.abs(setpoints.pos[:, k] - pos[:, k]))))
        for k, a in enumerate(AXES)
        if ferror_ratio[k] > 1.0 + _SLACK
    ]
    gain_v = []
    for a, (lo, hi) in kp_bounds.items():
        k_lo, k_hi = gains.kp_range[AXES.index(a)]
        if k_lo < lo - 1e-12 or k_hi > hi + 1e-12:
            gain_v.append(f"axis {a}: Kp leaves [{lo}, {hi}] (m/min)/mm: {k_lo:.4f}..{k_hi:.4f}")
    kf_lo, kf_hi = machine.gains.kf_range
    f_lo, f_hi = gains.kf_range[:, 0].min(), gains.kf_range[:, 1].max()
    if f_lo < kf_lo - 1e-12 or f_hi > kf_hi + 1e-12:
        gain_v.append(f"Kf leaves [{kf_lo}, {kf_hi}]: {f_lo:.4f}..{f_hi:.4f}")
    limits_ok, stability_ok = not limit_v, not gain_v
    return Verification(
        ok=limits_ok and stability_ok,
        limits_ok=limits_ok,
        stability_ok=stability_ok,
        pos=pos if series else None,
        u=u if series else None,
        ce=ce if series else None,
        metrics=metrics,
        command_ratio=ratio,
        ferror_ratio=ferror_ratio,
        max_dkp_per_sample=gains.max_dkp_per_sample,
        max_dkf_per_sample=gains.max_dkf_per_sample,
        violations=tuple(limit_v + gain_v),
    )
