"""Compiled fuzzy inference on two normalised inputs (error e, error rate ec).

Seven labels NB, NM, NS, ZO, PS, PM, PB with triangular memberships of half-width
2 peaking at -6, -4, ..., 6 on the universe [-6, 6] (inputs are saturated to it, so
the end labels are shoulders there); they form a partition of unity. Two inference
schemes over a 7 x 7 rule base (rows: label of e, columns: label of ec):

- :func:`mamdani`: min for AND, min implication, max aggregation and centroid
  defuzzification over the output universe [-6, 6] with the same seven triangles
  (MATLAB's ``mamfis`` defaults). The centroid is computed exactly: the aggregated
  membership is piecewise linear, with known breakpoints.
- :func:`memberships` gives the product-inference weights of the four rules that fire
  (singleton fuzzifier); with a center-average defuzzifier a rule base of consequents
  ``theta`` then yields the bilinear interpolation ``sum w theta`` (the weights sum to 1).

The classic self-tuning PID rule tables (Wang, Chen & Chen 2013, Tables 1-3; the
standard tables of the fuzzy-PID literature) are :data:`DKP`, :data:`DKI`, :data:`DKD`,
as label indices ``-3 .. 3`` (NB .. PB), i.e. consequent centres ``2 * index``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["LABELS", "UNIVERSE", "DKP", "DKI", "DKD", "RULES", "memberships", "mamdani"]

#: Label names, index 0..6 (centre ``2 * index - 6``).
LABELS = ("NB", "NM", "NS", "ZO", "PS", "PM", "PB")
#: Half-range of the normalised universe.
UNIVERSE = 6.0

_NB, _NM, _NS, _ZO, _PS, _PM, _PB = -3, -2, -1, 0, 1, 2, 3

#: Rule table of the Kp increment: rows e = NB..PB, columns ec = NB..PB (label -3..3).
DKP = np.array(
    [
        [_PB, _PB, _PM, _PM, _PS, _ZO, _ZO],
        [_PB, _PB, _PM, _PS, _PS, _ZO, _NS],
        [_PM, _PM, _PM, _PS, _ZO, _NS, _NS],
        [_PM, _PM, _PS, _ZO, _NS, _NM, _NM],
        [_PS, _PS, _ZO, _NS, _NS, _NM, _NM],
        [_PS, _ZO, _NS, _NM, _NM, _NM, _NB],
        [_ZO, _ZO, _NM, _NM, _NM, _NB, _NB],
    ],
    dtype=np.int64,
)
#: Rule table of the Ki increment (same layout).
DKI = np.array(
    [
        [_NB, _NB, _NM, _NM, _NS, _ZO, _ZO],
        [_NB, _NB, _NM, _NS, _NS, _ZO, _ZO],
        [_NB, _NM, _NS, _NS, _ZO, _PS, _PS],
        [_NM, _NM, _NS, _ZO, _PS, _PM, _PM],
        [_NM, _NS, _ZO, _PS, _PS, _PM, _PB],
        [_ZO, _ZO, _PS, _PS, _PM, _PB, _PB],
        [_ZO, _ZO, _PS, _PM, _PM, _PB, _PB],
    ],
    dtype=np.int64,
)
#: Rule table of the Kd increment (same layout).
DKD = np.array(
    [
        [_PS, _NS, _NB, _NB, _NB, _NM, _PS],
        [_PS, _NS, _NB, _NM, _NM, _NS, _ZO],
        [_ZO, _NS, _NM, _NM, _NS, _NS, _ZO],
        [_ZO, _NS, _NS, _NS, _NS, _NS, _ZO],
        [_ZO, _ZO, _ZO, _ZO, _ZO, _ZO, _ZO],
        [_PB, _NS, _PS, _PS, _PS, _PS, _PB],
        [_PB, _PM, _PM, _PM, _PS, _PS, _PB],
    ],
    dtype=np.int64,
)
#: The three tables stacked, shape (3, 7, 7): Kp, Ki, Kd.
RULES = np.stack([DKP, DKI, DKD])


@njit(cache=True)
def memberships(x: float) -> tuple[int, float]:
    """The two labels a normalised input fires: ``(i, t)``.

    ``x`` is saturated to [-6, 6]; label ``i`` (0..5) has membership ``1 - t`` and
    label ``i + 1`` has ``t`` (all others 0).
    """
    x = min(max(x, -UNIVERSE), UNIVERSE)
    i = min(int((x + UNIVERSE) // 2.0), 5)
    return i, 0.5 * (x - (2.0 * i - UNIVERSE))


@njit(cache=True)
def mamdani(table: np.ndarray, x_e: float, x_ec: float) -> float:
    """Mamdani min-max inference with centroid defuzzification.

    Parameters
    ----------
    table : ndarray of int, shape (7, 7)
        Consequent label index (-3..3) per rule, rows e, columns ec.
    x_e, x_ec : float
        Normalised inputs (saturated to [-6, 6]).

    Returns
    -------
    float
        Centroid of the aggregated output membership, in [-6, 6].
    """
    ie, te = memberships(x_e)
    ic, tc = memberships(x_ec)
    w = np.zeros(7)  # firing strength per output label (max over its rules)
    for di in range(2):
        me = te if di else 1.0 - te
        for dj in range(2):
            mc = tc if dj else 1.0 - tc
            s = min(me, mc)
            lab = table[ie + di, ic + dj] + 3
            if s > w[lab]:
                w[lab] = s
    area = 0.0
    moment = 0.0
    cut = np.empty(7)
    for j in range(6):  # between the peaks of labels j and j + 1: t in [0, 1]
        a, b = w[j], w[j + 1]
        if a == 0.0 and b == 0.0:
            continue
        # mu(t) = max(min(a, 1 - t), min(b, t)) is linear between these breakpoints
        cut[0], cut[1], cut[2], cut[3] = 0.0, 1.0, 0.5, a
        cut[4], cut[5], cut[6] = 1.0 - a, b, 1.0 - b
        for m in range(1, 7):  # insertion sort
            v = cut[m]
            q = m - 1
            while q >= 0 and cut[q] > v:
                cut[q + 1] = cut[q]
                q -= 1
            cut[q + 1] = v
        y0 = 2.0 * j - UNIVERSE
        for m in range(6):
            t0, t1 = cut[m], cut[m + 1]
            if t1 <= t0:
                continue
            f0 = max(min(a, 1.0 - t0), min(b, t0))
            f1 = max(min(a, 1.0 - t1), min(b, t1))
            h = 2.0 * (t1 - t0)  # the output variable y = y0 + 2 t
            ya, yb = y0 + 2.0 * t0, y0 + 2.0 * t1
            area += 0.5 * h * (f0 + f1)
            moment += h * (2.0 * ya * f0 + ya * f1 + yb * f0 + 2.0 * yb * f1) / 6.0
    if area == 0.0:
        return 0.0
    return moment / area
