"""Phase and gain margins of the position loop, and the stable Kp range of an axis.

The open loop ``L(z) = Kp z^-d G(z)`` of :func:`oga.linear.position_open_loop`
(either axis kind; friction -> its viscous part, no force limit) is evaluated on the unit circle
``z = exp(j w Te)`` over a dense logarithmic grid from ``1e-6 / Te`` rad/s to the
Nyquist frequency ``pi / Te``; every crossing of ``|L| = 1`` (gain crossover) and
of the phase ``-180 deg (mod 360)`` (phase crossover, ``Im L = 0`` with ``Re L < 0``)
found between grid points is refined with Brent's method. The phase margin is the
least ``180 + arg L`` over the gain crossovers, the gain margin the least
``-20 log10 |L|`` over the phase crossovers (the Nyquist frequency included, where
``L`` is real).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from oga.errors import OptionError
from oga.linear import position_open_loop
from oga.machine import KP_SI_PER_M_MIN_PER_MM, Machine

__all__ = ["Margins", "StabilityRange", "decimal_grid", "margins", "stable_range"]

#: Points of the logarithmic frequency grid.
_GRID_POINTS = 4000
#: Lowest grid frequency times Te.
_W_LOW_TE = 1e-6
#: Kp grid values are rounded to this many decimals (3.0, not 2.9999999).
_KP_DECIMALS = 10


@dataclass(frozen=True)
class Margins:
    """Stability margins of one axis's position loop at one Kp.

    Attributes
    ----------
    kp_m_min_per_mm : float
        The position gain, (m/min)/mm.
    pm_deg : float
        Phase margin, degrees (``inf`` if ``|L|`` never crosses 1).
    gm_db : float
        Gain margin, dB (``inf`` if the phase never crosses -180 deg).
    w_gain_crossover_rad_s : float
        Frequency where the phase margin is read, rad/s (``nan`` if none).
    w_phase_crossover_rad_s : float
        Frequency where the gain margin is read, rad/s (``nan`` if none).
    stable : bool
        Whether the closed position loop is asymptotically stable (every
        closed-loop eigenvalue inside the unit circle).
    """

    kp_m_min_per_mm: float
    pm_deg: float
    gm_db: float
    w_gain_crossover_rad_s: float
    w_phase_crossover_rad_s: float
    stable: bool


@dataclass(frozen=True, eq=False)
class StabilityRange:
    """The stable Kp range of one axis.

    Attributes
    ----------
    axis : str
        Axis name.
    status : {"ok", "disjoint", "empty"}
        ``"ok"``: one contiguous run of grid values meets both margins inside the
        bounds; ``"disjoint"``: several runs do, the lowest is reported; ``"empty"``:
        none does (``kp_min`` and ``kp_max`` are ``nan``).
    message : str
        One line explaining the status.
    kp_min, kp_max : float
        Ends of the stable range, (m/min)/mm.
    kp : ndarray, shape (M,)
        The Kp grid, (m/min)/mm (exact decimal values).
    pm_deg, gm_db : ndarray, shape (M,)
        Phase margin (deg) and gain margin (dB) at each grid value.
    stable : ndarray of bool, shape (M,)
        Closed-loop stability at each grid value.
    pm_min_deg, gm_min_db : float
        The criteria used.
    kp_bounds_m_min_per_mm : tuple of float
        The configured bounds the range was intersected with.
    """

    axis: str
    status: str
    message: str
    kp_min: float
    kp_max: float
    kp: np.ndarray
    pm_deg: np.ndarray
    gm_db: np.ndarray
    stable: np.ndarray
    pm_min_deg: float
    gm_min_db: float
    kp_bounds_m_min_per_mm: tuple[float, float]

    @property
    def ok(self) -> bool:
        """True when a range was found (status ``"ok"`` or ``"disjoint"``)."""
        return self.status != "empty"

    @property
    def table(self) -> tuple[tuple[float, float, float], ...]:
        """Rows ``(kp, pm_deg, gm_db)`` of the grid."""
        return tuple(
            (float(k), float(p), float(g)) for k, p, g in zip(self.kp, self.pm_deg, self.gm_db)
        )


def _response(a, b, c, w, te):
    """``L(exp(j w Te))`` for every frequency of ``w`` (shape (n,)), complex (n,)."""
    z = np.exp(1j * np.asarray(w, dtype=np.float64) * te)
    n = a.shape[0]
    mats = z[:, None, None] * np.eye(n) - a
    x = np.linalg.solve(mats, np.broadcast_to(b.astype(complex), (z.size, n, 1)))
    return (c @ x)[:, 0, 0]


def _root(f, lo: float, hi: float, f_lo: float, f_hi: float) -> float:
    """The root of ``f`` in ``[lo, hi]`` (Brent), where ``f_lo``, ``f_hi`` bracket it."""
    if f_lo == 0.0:
        return lo
    if f_hi == 0.0:
        return hi
    return brentq(f, lo, hi, xtol=1e-12, rtol=1e-14)


def margins(machine: Machine, axis: str, kp_m_min_per_mm: float) -> Margins:
    """Phase and gain margins of the linearised position loop of one axis.

    Parameters
    ----------
    machine : Machine
        Machine description.
    axis : str
        Axis name; MachineError if the machine lacks it.
    kp_m_min_per_mm : float
        Position gain, (m/min)/mm; positive and finite.

    Returns
    -------
    Margins

    Raises
    ------
    OptionError
        ``kp_m_min_per_mm`` not a positive finite number.
    """
    try:
        kp = float(kp_m_min_per_mm)
    except (TypeError, ValueError):
        raise OptionError(f"kp_m_min_per_mm: expected a number, got {kp_m_min_per_mm!r}") from None
    if not (math.isfinite(kp) and kp > 0.0):
        raise OptionError(f"kp_m_min_per_mm: must be positive and finite, got {kp}")
    a, b, c, _ = position_open_loop(machine, axis, kp * KP_SI_PER_M_MIN_PER_MM)
    te = machine.te

    def resp(w):
        return _response(a, b, c, np.atleast_1d(w), te)[0]

    def log_mag(w):
        return math.log(abs(resp(w)))

    def imag(w):
        return resp(w).imag

    w = np.geomspace(_W_LOW_TE / te, math.pi / te, _GRID_POINTS)
    lw = _response(a, b, c, w, te)
    mag = np.log(np.abs(lw))
    phase = np.unwrap(np.angle(lw))

    pm, w_gc = math.inf, math.nan
    for i in np.flatnonzero(np.sign(mag[:-1]) != np.sign(mag[1:])):
        wc = _root(log_mag, w[i], w[i + 1], mag[i], mag[i + 1])
        # the unwrapped phase at wc: the grid phase plus the (small) change from w[i]
        ph = phase[i] + np.angle(resp(wc) / lw[i])
        pm_i = (math.degrees(ph) + 360.0) % 360.0 - 180.0
        if pm_i < pm:
            pm, w_gc = pm_i, wc

    turns = np.floor((phase + math.pi) / (2.0 * math.pi))  # changes where the phase passes -180
    crossings = [
        _root(imag, w[i], w[i + 1], lw[i].imag, lw[i + 1].imag)
        for i in np.flatnonzero(turns[:-1] != turns[1:])
    ]
    if lw[-1].real < 0.0:  # at Nyquist L is real: a phase crossover if negative
        crossings.append(w[-1])
    gm, w_pc = math.inf, math.nan
    for wc in crossings:
        gm_i = -20.0 * math.log10(abs(resp(wc)))
        if gm_i < gm:
            gm, w_pc = gm_i, wc

    stable = bool(np.max(np.abs(np.linalg.eigvals(a - b @ c))) < 1.0)
    return Margins(
        kp_m_min_per_mm=kp,
        pm_deg=float(pm),
        gm_db=float(gm),
        w_gain_crossover_rad_s=float(w_gc),
        w_phase_crossover_rad_s=float(w_pc),
        stable=stable,
    )


def decimal_grid(lo: float, hi: float, step: float) -> np.ndarray:
    """``lo, lo + step, ... <= hi`` rounded to exact decimals (``1.1``, not ``1.1000000000000001``).

    Raises
    ------
    OptionError
        ``step <= 0`` or ``hi < lo``.
    """
    if not step > 0 or not hi >= lo:
        raise OptionError(f"grid: need step > 0 and lo <= hi, got lo={lo}, hi={hi}, step={step}")
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    return np.round(lo + np.arange(n) * step, _KP_DECIMALS)


#: stable_range results by (machine digest, axis): the margins take about a second per axis.
_RANGES: dict[tuple[str, str], "StabilityRange"] = {}


def stable_range(machine: Machine, axis: str) -> StabilityRange:
    """The stable Kp range of one axis over the machine's Kp grid.

    The grid spans ``machine.gains.kp_span_m_min_per_mm`` in steps of
    ``kp_step_m_min_per_mm``; a value qualifies when the closed loop is stable,
    ``PM >= pm_min_deg`` and ``GM >= gm_min_db``, and it lies inside
    ``kp_bounds_m_min_per_mm``. The range is the contiguous run of qualifying
    grid values (the lowest run if there are several, with status ``"disjoint"``).

    Parameters
    ----------
    machine : Machine
        Machine description.
    axis : str
        Axis name; MachineError if the machine lacks it.

    Returns
    -------
    StabilityRange
    """
    machine.axis(axis)
    key = (machine.digest(), axis)
    if key not in _RANGES:
        _RANGES[key] = _stable_range(machine, axis)
    return _RANGES[key]


def _stable_range(machine: Machine, axis: str) -> StabilityRange:
    g = machine.gains
    kp = decimal_grid(*g.kp_span_m_min_per_mm, g.kp_step_m_min_per_mm)
    found = [margins(machine, axis, k) for k in kp]
    pm = np.array([m.pm_deg for m in found])
    gm = np.array([m.gm_db for m in found])
    stable = np.array([m.stable for m in found])
    lo_b, hi_b = g.kp_bounds_m_min_per_mm
    inside = (kp >= lo_b - 1e-9) & (kp <= hi_b + 1e-9)
    good = stable & (pm >= g.pm_min_deg) & (gm >= g.gm_min_db) & inside
    idx = np.flatnonzero(good)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
    criteria = f"PM >= {g.pm_min_deg} deg, GM >= {g.gm_min_db} dB, Kp in [{lo_b}, {hi_b}]"
    if not runs:
        status, kp_min, kp_max = "empty", math.nan, math.nan
        message = f"axis {axis}: no Kp of the grid meets {criteria}"
    else:
        kp_min, kp_max = float(kp[runs[0][0]]), float(kp[runs[0][-1]])
        if len(runs) == 1:
            status = "ok"
            message = f"axis {axis}: Kp in [{kp_min}, {kp_max}] (m/min)/mm meets {criteria}"
        else:
            status = "disjoint"
            others = ", ".join(f"[{kp[r[0]]}, {kp[r[-1]]}]" for r in runs[1:])
            message = (
                f"axis {axis}: several runs meet {criteria}; the lowest "
                f"[{kp_min}, {kp_max}] is used, not {others}"
            )
    for arr in (kp, pm, gm, stable):
        arr.flags.writeable = False
    return StabilityRange(
        axis=axis,
        status=status,
        message=message,
        kp_min=kp_min,
        kp_max=kp_max,
        kp=kp,
        pm_deg=pm,
        gm_db=gm,
        stable=stable,
        pm_min_deg=g.pm_min_deg,
        gm_min_db=g.gm_min_db,
        kp_bounds_m_min_per_mm=(lo_b, hi_b),
    )
