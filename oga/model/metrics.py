"""Accuracy figures of a run: contour-error statistics and per-axis tracking error."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from feedplan.setpoints import AXES
from oga.errors import InputError

__all__ = ["ContourMetrics", "contour_metrics", "nan_max", "track_max"]

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
        Contour error, m (e.g. from :func:`oga.model.contour.contour_error`).
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
    a, mse, max_abs, track_max, track_rms = _figures(ce, pd, pa, keep)
    p50, p95, p99 = (float(v) for v in _percentiles(a, _QUANTILES))
    return ContourMetrics(
        n=int(a.size),
        mse_m2=mse,
        rms_m=float(np.sqrt(mse)),
        max_abs_m=max_abs,
        p50_m=p50,
        p95_m=p95,
        p99_m=p99,
        track_max_m=tuple(float(v) for v in track_max),
        track_rms_m=tuple(float(v) for v in track_rms),
    )


@njit(cache=True, nogil=True)
def _figures(ce, pd, pa, keep):
    """The figures of :func:`contour_metrics` but the percentiles, in one pass; the numbers of
    numpy's ``a = |ce[keep]|``, ``mean(a * a)``, ``a.max()``, ``|pd - pa|.max(axis=0)`` and
    ``sqrt(mean(|pd - pa|[keep] ** 2, axis=0))`` to the last bit: the same sums in the same
    order (:func:`_pairwise_sum`; a column sum of a C-ordered array adds row after row), the
    maxima NaN-propagating.

    Returns
    -------
    a : ndarray, shape (M,)
        |CE| of the counted samples, m.
    mse, max_abs : float
        m^2, m.
    track_max, track_rms : ndarray, shape (3,)
        m.
    """
    n = ce.shape[0]
    m = 0
    for k in range(n):
        m += keep[k]
    a = np.empty(m)
    a2 = np.empty(m)
    track_max = np.empty(3)
    track_sum = np.zeros(3)
    j = 0
    for k in range(n):
        for c in range(3):
            e = abs(pd[k, c] - pa[k, c])
            if k == 0:
                track_max[c] = e
            else:
                track_max[c] = nan_max(track_max[c], e)
            if keep[k]:
                track_sum[c] += e * e
        if keep[k]:
            a[j] = abs(ce[k])
            a2[j] = a[j] * a[j]
            j += 1
    max_abs = a[0]
    for j in range(1, m):
        max_abs = nan_max(max_abs, a[j])
    return a, _pairwise_sum(a2, 0, m) / m, max_abs, track_max, np.sqrt(track_sum / m)


#: The percentiles of :class:`ContourMetrics`, as fractions (numpy's ``q / 100``).
_QUANTILES = np.true_divide([50, 95, 99], 100)


def _percentiles(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``np.percentile(a, 100 * q)`` (linear interpolation) of ``a`` (M,), ``q`` in [0, 1], to
    the last bit, without numpy's per-call overhead (a fifth of a replay's checks on short
    programs): numpy's own steps of ``np.quantile`` for this case, in its order (the virtual
    index ``(M - 1) q`` and its neighbours, the last value at or above ``M - 1``; one
    ``np.partition`` at those ranks and the ends; the interpolation ``a + (b - a) t``, from
    ``b`` where ``t >= 0.5``; the last value where ``a`` holds a NaN)."""
    virtual = (a.size - 1) * q
    prev = np.floor(virtual)
    nxt = prev + 1
    above = virtual >= a.size - 1
    prev[above] = -1
    nxt[above] = -1
    prev, nxt = prev.astype(np.intp), nxt.astype(np.intp)
    part = np.partition(a, np.unique(np.concatenate(([0, -1], prev, nxt))))
    if np.isnan(part[-1]):  # a NaN sorts last
        return np.full(q.shape, part[-1])
    x0, x1 = part[prev], part[nxt]
    gamma = virtual - prev
    diff = x1 - x0
    out = x0 + diff * gamma
    np.subtract(x1, diff * (1 - gamma), out=out, where=gamma >= 0.5)
    return out


@njit(cache=True, inline="always")
def nan_max(x, y):
    """``max(x, y)`` as numpy's maximum: NaN once either is NaN."""
    return y if y > x or y != y else x


@njit(cache=True, nogil=True)
def _pairwise_sum(x, lo, n):
    """``x[lo:lo + n].sum()`` as numpy adds a contiguous float64 array: its pairwise summation
    (:func:`_block_sum` on blocks of up to 128, halves above, cut at multiples of 8), the
    recursion unrolled on a stack (n halves per level: 64 levels hold any size)."""
    los = np.empty(64, dtype=np.int64)
    ns = np.empty(64, dtype=np.int64)
    stage = np.zeros(64, dtype=np.int64)  # 0: sum the left half next, 1: the right, 2: add
    left = np.empty(64)
    top = 0
    los[0], ns[0] = lo, n
    total = 0.0
    while top >= 0:
        m = ns[top]
        if m <= 128:
            total = _block_sum(x, los[top], m)
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage[top] == 2:
            total = left[top] + total
            top -= 1
            continue
        if stage[top] == 1:
            left[top] = total
        stage[top] += 1
        los[top + 1] = los[top] + (half if stage[top] == 2 else 0)
        ns[top + 1] = m - half if stage[top] == 2 else half
        stage[top + 1] = 0
        top += 1
    return total


@njit(cache=True, inline="always")
def _block_sum(x, lo, n):
    """numpy's sum of a block of ``n <= 128``: in order below 8, else 8 running sums."""
    if n < 8:
        s = 0.0
        for i in range(lo, lo + n):
            s += x[i]
        return s
    r0, r1, r2, r3 = x[lo], x[lo + 1], x[lo + 2], x[lo + 3]
    r4, r5, r6, r7 = x[lo + 4], x[lo + 5], x[lo + 6], x[lo + 7]
    i = lo + 8
    end = lo + n - n % 8
    while i < end:
        r0 += x[i]
        r1 += x[i + 1]
        r2 += x[i + 2]
        r3 += x[i + 3]
        r4 += x[i + 4]
        r5 += x[i + 5]
        r6 += x[i + 6]
        r7 += x[i + 7]
        i += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < lo + n:
        s += x[i]
        i += 1
    return s


@njit(cache=True, nogil=True)
def track_max(pd, pa):
    """``np.abs(pd - pa).max(axis=0)``, the largest tracking error per axis (NaN-propagating,
    the same floats) in one compiled pass, without the temporaries; 0 for no sample.
    ``pd, pa``: shape (N, 3), m."""
    track = np.zeros(3)
    for k in range(pd.shape[0]):
        for c in range(3):
            track[c] = nan_max(track[c], abs(pd[k, c] - pa[k, c]))
    return track
