"""Accuracy figures of a run: contour-error statistics and per-axis tracking error."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES
from oga.errors import InputError

__all__ = ["ContourMetrics", "contour_metrics"]

_UM = 1e6


@dataclass(frozen=True)
class ContourMetrics:
    """Contour-error and tracking-error statistics.

    Attributes
    ----------
    n : int
        Number of samples counted (feed samples; rapids excluded).
    mse_m2 : float
        Mean of CE^2, m^2.
    rms_m, max_abs_m : float
        Root mean square and largest |CE|, m.
    p50_m, p95_m, p99_m : float
        Percentiles of |CE|, m (linear interpolation).
    track_max_m : tuple of 3 float
        Per axis (x, y, z): largest |pd - pa| over EVERY sample (rapids included: a
        controller's following-error limit applies there too), m.
    track_rms_m : tuple of 3 float
        Per axis: RMS of |pd - pa| over the samples counted, m.
    """

    n: int
    mse_m2: float
    rms_m: float
    max_abs_m: float
    p50_m: float
    p95_m: float
    p99_m: float
    track_max_m: tuple[float, float, float]
    track_rms_m: tuple[float, float, float]

    def to_dict(self) -> dict:
        """The figures in users' units (um, um^2), keys naming the unit."""
        return {
            "n": self.n,
            "mse_ce_um2": self.mse_m2 * _UM**2,
            "rms_ce_um": self.rms_m * _UM,
            "max_ce_um": self.max_abs_m * _UM,
            "p50_ce_um": self.p50_m * _UM,
            "p95_ce_um": self.p95_m * _UM,
            "p99_ce_um": self.p99_m * _UM,
            "track_max_um": {a: v * _UM for a, v in zip(AXES, self.track_max_m)},
            "track_rms_um": {a: v * _UM for a, v in zip(AXES, self.track_rms_m)},
        }


def contour_metrics(
    ce: np.ndarray, pd: np.ndarray, pa: np.ndarray, mask: np.ndarray | None = None
) -> ContourMetrics:
    """Statistics of the contour error ``ce`` and of the tracking error ``pd - pa``.

    Parameters
    ----------
    ce : array_like, shape (N,)
        Contour error, m (e.g. from :func:`oga.contour.contour_error`).
    pd, pa : array_like, shape (N, 3)
        Desired and actual positions, m.
    mask : array_like of bool, shape (N,), optional
        Samples to count (typically ``~setpoints.rapid``); default all. The largest
        tracking error is taken over every sample regardless.

    Returns
    -------
    ContourMetrics

    Raises
    ------
    InputError
        Shapes disagree, or no sample is counted.
    """
    ce = np.asarray(ce, dtype=np.float64)
    pd = np.asarray(pd, dtype=np.float64)
    pa = np.asarray(pa, dtype=np.float64)
    n = ce.shape[0] if ce.ndim == 1 else -1
    if n < 0 or pd.shape != (n, 3) or pa.shape != (n, 3):
        raise InputError(
            f"contour_metrics: ce {ce.shape}, pd {pd.shape}, pa {pa.shape} "
            "must have shapes (N,), (N, 3), (N, 3)"
        )
    keep = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if keep.shape != (n,):
        raise InputError(f"contour_metrics: mask {keep.shape} must have shape ({n},)")
    if not keep.any():
        raise InputError("contour_metrics: no sample to count (all masked, e.g. only rapids)")
    a = np.abs(ce[keep])
    err_all = np.abs(pd - pa)
    err = err_all[keep]
    mse = float(np.mean(a * a))
    p50, p95, p99 = (float(v) for v in np.percentile(a, [50, 95, 99]))
    return ContourMetrics(
        n=int(a.size),
        mse_m2=mse,
        rms_m=float(np.sqrt(mse)),
        max_abs_m=float(a.max()),
        p50_m=p50,
        p95_m=p95,
        p99_m=p99,
        track_max_m=tuple(float(v) for v in err_all.max(axis=0)),
        track_rms_m=tuple(float(v) for v in np.sqrt(np.mean(err * err, axis=0))),
    )
