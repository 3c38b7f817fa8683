"""A gain law: per axis, Kp and Kf as piecewise-linear functions of what the controller
measures, the axis's commanded velocity ``|v|`` and acceleration ``|a|``.

A table (:mod:`oga.optimize`) gives a gain per servo period of one program; a controller
with a native gain adaptation instead evaluates a function of its own commanded motion in
every period. Four kinds, each what one controller evaluates:

- ``"lincurve"`` (LinuxCNC): Kp and Kf each a ``lincurve`` of ``|v|`` (N <= 16 support
  points; below the first point its value, above the last the last value, no
  extrapolation; LinuxCNC ``src/hal/components/lincurve.comp``). The evaluation below uses
  the component's arithmetic, ``y_i + f (y_{i+1} - y_i)`` with
  ``f = (x - x_i) / (x_{i+1} - x_i)``, so HAL gives the same gains.
- ``"pl"`` (Beckhoff TwinCAT CNC dynamic Kv, axis parameters P-AXIS-00244..00248,
  ``getriebe[i].dyn_kv.*``): Kp linear in ``|v|`` between ``(v1, kv1)`` and ``(v2, kv2)``
  and held at the ends (the manual: below v1 and above v2 the gain stays within
  ``min/max(kv1, kv2)``); ``N`` points in general, exactly two for TwinCAT. Kf is one
  constant (the feedforward weighting ``vorsteuer.vs_v_faktor / vs_v_nenner``,
  P-AXIS-00228/00229).
- ``"lincurve-sa"`` (LinuxCNC): Kp a ``lincurve`` of ``|v|`` as ``"lincurve"``'s, Kf a
  ``lincurve`` of the signed acceleration ``s = a sign(v)`` (``sign(0) = +1``): ``s > 0``
  while the axis speeds up, ``s < 0`` while it brakes, so the feedforward can differ entering
  and leaving a reversal, which a function of ``|v|`` cannot. HAL evaluates it as two
  ``lincurve`` of the commanded acceleration (``Kf(a)`` and its mirror ``Kf(-a)``) and a
  ``mux2`` on ``abs``'s ``is-negative`` of the velocity. Neither
  TwinCAT's dynamic Kv (Kp only) nor MAC (``|a|``) can express it.
- ``"mac"`` (Heidenhain MAC, Motion Adaptive Control: controller parameters adapted to the
  axis's velocity and acceleration at support points, set up in TNCopt; iTNC 530 HSCI
  technical manual, software options 142 PAC / MAC): Kp and Kf bilinear on an ``N x N`` grid
  of ``|v|`` and ``|a|``, held beyond the grid's edges.

Each axis law holds its support points (``v_m_s``, ``a_m_s2``) and the values there
(``kp_m_min_per_mm``, ``kf``, shape ``(len(a_m_s2), len(v_m_s))``; one row for the
one-input kinds; ``pl``'s Kf one value; ``lincurve-sa``: ``a_m_s2`` Kf's support points in
``s``, Kf shape ``(1, len(a_m_s2))``). Values are convex combinations of support
values, so a law whose support values lie in a range gives gains in that range at every
sample. :func:`quantized` rounds a law to its controller's resolution (what is exported is
what is certified).

Pure functions on plain data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.errors import OptionError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM

__all__ = ["AxisLaw", "Law", "law_gains", "interp", "basis", "support_points", "quantized",
           "check_kind"]

#: Resolution of what each controller takes (SI; Kp in (m/min)/mm): TwinCAT's kv in
#: 0.01/s and v in um/s (UNS32), Kf as a ratio over 1000; Heidenhain's machine parameters
#: with three decimals ((m/min)/mm, the feedforward factor), velocity in mm/min, acceleration
#: in mm/s^2 (our choice of TNCopt's entry); LinuxCNC's float64 ``setp`` is exact.
_RESOLUTION = {
    "pl": {"kp": 0.01 / KP_SI_PER_M_MIN_PER_MM, "kf": 1e-3, "v": 1e-6, "a": None},
    "mac": {"kp": 1e-3, "kf": 1e-3, "v": 1e-3 / 60.0, "a": 1e-3},
    "lincurve": {"kp": None, "kf": None, "v": None, "a": None},
    "lincurve-sa": {"kp": None, "kf": None, "v": None, "a": None},
}


@dataclass(frozen=True, eq=False)
class AxisLaw:
    """One axis's law.

    Attributes
    ----------
    v_m_s : ndarray, shape (nv,)
        Support points in ``|v|``, strictly increasing, m/s.
    a_m_s2 : ndarray, shape (na,)
        Support points in ``|a|`` (``mac``), strictly increasing, m/s^2; ``[0.0]`` for the
        kinds that read velocity only.
    kp_m_min_per_mm : ndarray, shape (na, nv)
        Kp at the support points.
    kf : ndarray, shape (na, nv), or (1, 1) for ``pl``
        Kf at the support points.
    """

    v_m_s: np.ndarray
    a_m_s2: np.ndarray
    kp_m_min_per_mm: np.ndarray
    kf: np.ndarray


@dataclass(frozen=True, eq=False)
class Law:
    """A gain law for every axis.

    Attributes
    ----------
    kind : {"mac", "pl", "lincurve", "lincurve-sa"}
    axes : dict of str to AxisLaw
        The adapted axes.
    fixed_kp, fixed_kf : dict of str to float
        The gains of the other axes (the baseline's), Kp in (m/min)/mm.
    """

    kind: str
    axes: dict[str, AxisLaw]
    fixed_kp: dict[str, float] = field(default_factory=dict)
    fixed_kf: dict[str, float] = field(default_factory=dict)

    @property
    def n_params(self) -> int:
        """Support values of the law (Kp and Kf, every axis)."""
        return sum(a.kp_m_min_per_mm.size + a.kf.size for a in self.axes.values())

    def summary(self) -> dict:
        """The law in users' units (mm/s, mm/s^2, (m/min)/mm), for the summary JSON."""
        return {
            "kind": self.kind,
            "axes": {a: {"v_mm_s": (law.v_m_s * 1e3).tolist(),
                         "a_mm_s2": (law.a_m_s2 * 1e3).tolist(),
                         "kp_m_min_per_mm": law.kp_m_min_per_mm.tolist(),
                         "kf": law.kf.tolist()} for a, law in self.axes.items()},
            "fixed_kp_m_min_per_mm": dict(self.fixed_kp),
            "fixed_kf": dict(self.fixed_kf),
        }


def check_kind(kind: str, points: int | None) -> int:
    """The support points per input of ``kind`` (``points`` or the kind's default).

    Raises
    ------
    OptionError
        Unknown kind, or points out of the kind's range (naming ``--kind``/``--points``).
    """
    if kind not in defaults.LAW_KINDS:
        raise OptionError(f"--kind: unknown law kind {kind!r}; use one of "
                          f"{', '.join(defaults.LAW_KINDS)}")
    if points is None:
        return defaults.LAW_POINTS[kind]
    hi = defaults.LAW_POINTS_MAX[kind]
    if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or not 2 <= points <= hi:
        raise OptionError(f"--points: the {kind} law takes 2..{hi} support points per input, "
                          f"got {points!r}")
    return int(points)


def interp(xs: np.ndarray, ys: np.ndarray, x: np.ndarray) -> np.ndarray:
    """LinuxCNC ``lincurve``'s value at ``x``: ``ys[0]`` at or below ``xs[0]``, ``ys[-1]`` at
    or above ``xs[-1]``, else ``y_i + f (y_{i+1} - y_i)``, ``f = (x - x_i)/(x_{i+1} - x_i)``
    with ``x_i < x <= x_{i+1}`` (the component's arithmetic, so the same float64 values)."""
    x = np.asarray(x, dtype=np.float64)
    i = np.clip(np.searchsorted(xs, x, side="left") - 1, 0, len(xs) - 2)
    f = (x - xs[i]) / (xs[i + 1] - xs[i])
    y = ys[i] + f * (ys[i + 1] - ys[i])
    return np.where(x >= xs[-1], ys[-1], np.where(x <= xs[0], ys[0], y))


def _hat(xs: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Segment ``i`` and share ``f`` in [0, 1] of ``x`` between ``xs[i]`` and ``xs[i+1]``,
    held at the ends."""
    if len(xs) == 1:
        return np.zeros(len(x), dtype=np.int64), np.zeros(len(x))
    i = np.clip(np.searchsorted(xs, x, side="left") - 1, 0, len(xs) - 2)
    f = np.clip((x - xs[i]) / (xs[i + 1] - xs[i]), 0.0, 1.0)
    return i, f


def _bilinear(law: AxisLaw, table: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``table`` (na, nv) at ``(|v|, |a|)``: lincurve's rule along ``v`` on the two rows
    around ``a``, then along ``a``; held beyond the grid."""
    if table.shape == (1, 1):
        return np.full(len(v), table[0, 0])
    rows = np.stack([interp(law.v_m_s, row, v) for row in table])  # (na, N)
    if table.shape[0] == 1:
        return rows[0]
    cols = np.arange(len(v))
    j, g = _hat(law.a_m_s2, a)
    return rows[j, cols] + g * (rows[j + 1, cols] - rows[j, cols])


def signed_acc(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``a sign(v)`` with ``sign(0) = +1`` (what HAL's ``mux2`` selects on ``abs``'s
    ``is-negative``): > 0 speeding up, < 0 braking, m/s^2."""
    a = np.asarray(a, dtype=np.float64)
    return np.where(np.asarray(v) < 0.0, -a, a)


def law_gains(law: Law, setpoints: Setpoints) -> tuple[np.ndarray, np.ndarray]:
    """The gains the law gives at every sample of ``setpoints``.

    Returns
    -------
    kp_m_min_per_mm, kf : ndarray, shape (N, 3)
    """
    n = len(setpoints)
    kp, kf = np.empty((n, 3)), np.empty((n, 3))
    for i, a in enumerate(AXES):
        if a in law.axes:
            ax = law.axes[a]
            v, acc = np.abs(setpoints.vel[:, i]), np.abs(setpoints.acc[:, i])
            kp[:, i] = _bilinear(ax, ax.kp_m_min_per_mm, v, acc)
            if law.kind == "lincurve-sa":
                kf[:, i] = interp(ax.a_m_s2, ax.kf[0], signed_acc(setpoints.vel[:, i],
                                                                  setpoints.acc[:, i]))
            else:
                kf[:, i] = _bilinear(ax, ax.kf, v, acc)
        else:
            kp[:, i] = law.fixed_kp.get(a, 0.0)
            kf[:, i] = law.fixed_kf.get(a, 0.0)
    return kp, kf


def basis(law: AxisLaw, table_shape: tuple[int, int], v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Weights ``W`` (N, size) with ``gain = W @ table.ravel()`` for a table of
    ``table_shape`` of ``law``'s support points (rows sum to 1: a convex combination)."""
    n = len(v)
    if table_shape == (1, 1):
        return np.ones((n, 1))
    na, nv = table_shape
    i, f = _hat(law.v_m_s, np.abs(v))
    j, g = _hat(law.a_m_s2, np.abs(a)) if na > 1 else (np.zeros(n, dtype=np.int64), np.zeros(n))
    w = np.zeros((n, na * nv))
    rows = np.arange(n)
    for dj, wj in ((0, 1.0 - g), (1, g)):
        jj = np.minimum(j + dj, na - 1)
        for di, wi in ((0, 1.0 - f), (1, f)):
            ii = np.minimum(i + di, nv - 1)
            np.add.at(w, (rows, jj * nv + ii), wj * wi)
    return w


def curve_basis(xs: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Weights ``W`` (N, len(xs)) with ``interp(xs, ys, x) = W @ ys`` (held at the ends)."""
    n = len(x)
    i, f = _hat(xs, np.asarray(x, dtype=np.float64))
    w = np.zeros((n, len(xs)))
    rows = np.arange(n)
    np.add.at(w, (rows, i), 1.0 - f)
    np.add.at(w, (rows, np.minimum(i + 1, len(xs) - 1)), f)
    return w


def signed_support_points(samples: list[np.ndarray], n: int) -> np.ndarray:
    """``n`` support points of a signed input, symmetric about 0: the magnitudes of
    :func:`support_points` over ``|samples|`` (0 among them for odd ``n``) and their
    negatives, strictly increasing."""
    k = n // 2 + 1 if n % 2 else n // 2
    m = support_points(samples, k, positive=not n % 2)
    return np.concatenate([-m[::-1], m[1:] if n % 2 else m])


def support_points(samples: list[np.ndarray], n: int, positive: bool = False) -> np.ndarray:
    """``n`` support points over the magnitudes in ``samples`` (one array per program and
    override: an axis's ``|v|`` or ``|a|`` on its feed samples): from 0 (or, ``positive``, the
    10 % quantile) to the largest (or the 90 % quantile) at evenly spaced quantiles of the
    moving samples, strictly increasing."""
    x = np.concatenate([np.abs(s) for s in samples]) if samples else np.zeros(0)
    x = x[x > 1e-9]
    if x.size == 0:
        return np.arange(n, dtype=np.float64) * 1e-3
    qs = np.linspace(0.1, 0.9, n) if positive else np.linspace(0.0, 1.0, n)
    pts = np.quantile(x, qs)
    if not positive:
        pts[0] = 0.0
    for k in range(1, n):  # strictly increasing
        pts[k] = max(pts[k], pts[k - 1] + max(1e-6, 1e-6 * abs(pts[k - 1])))
    return pts


def _round(x: np.ndarray, step: float | None) -> np.ndarray:
    return np.asarray(x, dtype=np.float64) if step is None else np.round(np.asarray(x) / step) * step


def quantized(law: Law) -> Law:
    """``law`` rounded to its controller's resolution (module doc); support points kept
    strictly increasing."""
    res = _RESOLUTION[law.kind]
    axes = {}
    for a, ax in law.axes.items():
        v = _round(ax.v_m_s, res["v"])
        acc = _round(ax.a_m_s2, res["a"]) if len(ax.a_m_s2) > 1 else ax.a_m_s2
        for pts, step in ((v, res["v"]), (acc, res["a"])):
            for k in range(1, len(pts)):
                if pts[k] <= pts[k - 1]:
                    pts[k] = pts[k - 1] + (step or 1e-9)
        axes[a] = AxisLaw(v_m_s=v, a_m_s2=acc, kp_m_min_per_mm=_round(ax.kp_m_min_per_mm, res["kp"]),
                          kf=_round(ax.kf, res["kf"]))
    return Law(kind=law.kind, axes=axes, fixed_kp=dict(law.fixed_kp), fixed_kf=dict(law.fixed_kf))
