"""Phase and gain margins of the position loop, and the stable Kp range of an axis.

The open loop ``L(z) = Kp z^-d G(z)`` of :func:`oga.model.linear.position_open_loop`
(either axis kind; friction -> its viscous part, no force limit) is evaluated on the unit circle
``z = exp(j w Te)`` over a dense logarithmic grid from ``1e-6 / Te`` rad/s to the
Nyquist frequency ``pi / Te``; every crossing of ``|L| = 1`` (gain crossover) and
of the phase ``-180 deg (mod 360)`` (phase crossover, ``Im L = 0`` with ``Re L < 0``)
found between grid points is refined with Brent's method. The phase margin is the
least ``180 + arg L`` over the gain crossovers, the gain margin the least
``-20 log10 |L|`` over the phase crossovers (the Nyquist frequency included, where
``L`` is real).

``L = Kp H`` with ``H`` the loop at ``Kp = 1 1/s``: the lifted inner loops, ``H`` on the
grid and the phase crossovers (a positive Kp moves neither ``arg L`` nor the zeros of
``Im L``) are computed once per axis model and timing; each Kp adds its gain crossovers
and a closed-loop eigenvalue problem. Both are memoised (a few dozen entries) by what
they depend on, not by axis name.

``H`` is evaluated in modal form, ``z^-d sum_i r_i / (z - p_i)`` over the poles of the
balanced axis (:func:`_modal`; the exact solve of ``C (zI - A)^-1 B`` where the poles are
near-defective): the same values to 1e-13 relative (7e-14 at most over the 96 plants of
ucp710's default set), several times cheaper. Where only the ends of the stable
range are wanted (the robust search's ~100 plants), :func:`stable_ends` walks the grid
upwards and stops where the lowest run ends, compiled (:func:`_walk_modal`: the same
figures as :func:`_margins`, tests/test_stability_walk.py). A loop costs about 0.6 ms
(ucp710's plants: the response on the grid from a table of ``z`` shared by the loops of one
period, the phase crossovers compiled, then the walk: blocks of the grid where ``|L|`` cannot
cross 1 skipped, the closed-loop eigenvalues by LAPACK's real ``geev`` away from the unit
circle; tests/test_fixed_costs.py).
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numba import njit, types
from numba.np.linalg import _LAPACK, ensure_lapack
from scipy.linalg import matrix_balance
from scipy.optimize import brentq

from oga.errors import OptionError
from oga.model.linear import dead_line, position_open_loop
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, GainSettings, Machine, json_digest

if TYPE_CHECKING:  # a Plant is taken for its machine only: the plant imports this module
    from oga.model.plant import Plant

ensure_lapack()  # scipy's LAPACK for :data:`_DGEEV`

__all__ = ["Margins", "StabilityRange", "decimal_grid", "margins", "stable_ends", "stable_range"]

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
    """``C (zI - A)^-1 B`` at ``z = exp(j w Te)`` for every frequency of ``w`` (one batched solve).

    Parameters
    ----------
    a, b, c : ndarray, shapes (n, n), (n, 1), (1, n)
        Discrete state space of period ``te``.
    w : array_like, shape (G,)
        Frequencies, rad/s.
    te : float
        Period, s.

    Returns
    -------
    ndarray of complex, shape (G,)
    """
    z = np.exp(1j * np.asarray(w, dtype=np.float64) * te)
    n = a.shape[0]
    mats = np.empty((z.size, n, n), dtype=complex)  # zI - A, stacked
    mats[:] = -a
    diag = np.arange(n)
    mats[:, diag, diag] += z[:, None]
    x = np.linalg.solve(mats, np.broadcast_to(b.astype(complex), (z.size, n, 1)))
    return (c @ x)[:, 0, 0]


def _root(f, lo: float, hi: float, f_lo: float, f_hi: float) -> float:
    """The root of ``f`` in ``[lo, hi]`` (Brent), where ``f_lo``, ``f_hi`` bracket it.

    ``f_lo`` and ``f_hi`` (the grid's values) stand for ``f`` at the ends, where Brent's
    method starts: two evaluations fewer, and the signs are the ones the bracket was
    chosen by.
    """
    if f_lo == 0.0:
        return lo
    if f_hi == 0.0:
        return hi
    if (f_lo > 0.0) == (f_hi > 0.0):  # the crossing is an end, within rounding (e.g. Nyquist)
        return lo if abs(f_lo) < abs(f_hi) else hi
    ends = {lo: f_lo, hi: f_hi}

    def g(w):
        return ends[w] if w in ends else f(w)

    return brentq(g, lo, hi, xtol=1e-12, rtol=1e-14)


class _Loop:
    """The part of one axis's position loop that does not depend on Kp.

    The open loop is ``L = Kp H`` with ``H`` the open loop of
    :func:`oga.model.linear.position_open_loop` at ``Kp = 1 1/s`` (the lifted inner loops and the
    dead time). ``H`` on the frequency grid, its unwrapped phase and the phase crossovers
    (``Im H = 0`` with ``Re H < 0``: a positive Kp moves none of them) are computed here once;
    a Kp then costs its gain crossovers and one eigenvalue problem (:func:`_margins`).

    Attributes
    ----------
    a, b, c : ndarray, shapes (n, n), (n, 1), (1, n)
        State space of ``H`` (period Te): input the velocity command (m/s), output the
        position (m) times ``Kp = 1 1/s``, so ``H`` is in s.
    te : float
        Period, s.
    w : ndarray, shape (G,)
        The logarithmic frequency grid, rad/s.
    h : ndarray of complex, shape (G,)
        ``H(exp(j w Te))`` on the grid, s.
    log_mag : ndarray, shape (G,)
        ``ln |H|`` on the grid (``H`` in s).
    phase : ndarray, shape (G,)
        Unwrapped ``arg H`` on the grid, rad (``arg L`` for every Kp > 0).
    gm_db : float
        ``min -20 log10 |H|`` over the phase crossovers, dB (``inf`` if none): the gain
        margin at Kp (1/s) is ``gm_db - 20 log10 Kp``.
    w_phase_crossover_rad_s : float
        Where ``gm_db`` is read, rad/s (``nan`` if no phase crossover).
    """

    def __init__(self, machine: Machine, axis: str):
        self.a, self.b, self.c, _ = position_open_loop(machine, axis, 1.0)
        self.te = machine.te
        dead, frac = dead_line(machine, axis)
        # a fractional dead time is no shift register's z^-d: the exact solves take it
        self.modal = _modal(self.a, self.b, self.c, dead) if frac == 0.0 else None
        self.w = _frequency_grid(self.te)
        self.h = self.responses(self.w)
        self.log_mag = np.log(np.abs(self.h))
        self.phase = _unwrap(np.angle(self.h))
        for arr in (self.a, self.b, self.c, self.h, self.log_mag, self.phase):
            arr.flags.writeable = False

        if self.modal is not None:
            lam, res, dead = self.modal
            gm, wc = _gain_margin_modal(lam, res, dead, self.te, self.w, self.h, self.phase)
            self.gm_db, self.w_phase_crossover_rad_s = float(gm), float(wc)
            return

        def imag(w):
            return self.response(w).imag

        w, h = self.w, self.h
        turns = np.floor((self.phase + math.pi) / (2.0 * math.pi))  # changes where it passes -180
        crossings = [
            _root(imag, w[i], w[i + 1], h[i].imag, h[i + 1].imag)
            for i in np.flatnonzero(turns[:-1] != turns[1:])
        ]
        if h[-1].real < 0.0:  # at Nyquist H is real: a phase crossover if negative
            crossings.append(w[-1])
        self.gm_db, self.w_phase_crossover_rad_s = math.inf, math.nan
        for wc in crossings:
            gm_i = -20.0 * math.log10(abs(self.response(wc)))
            if gm_i < self.gm_db:
                self.gm_db, self.w_phase_crossover_rad_s = gm_i, float(wc)

    def responses(self, w) -> np.ndarray:
        """``H(exp(j w Te))`` at the frequencies ``w`` (rad/s, shape (G,)), s, shape (G,):
        from the modal form (:func:`_modal`, compiled :func:`_h_modal`) when there is one,
        else one batched solve."""
        if self.modal is None:
            return _response(self.a, self.b, self.c, w, self.te)
        lam, res, dead = self.modal
        w = np.asarray(w, dtype=np.float64)
        if w is self.w:
            return _h_modal_table(lam, res, *_unit_circle(self.te, dead))
        return _h_modal_grid(lam, res, dead, self.te, w)

    def response(self, w: float) -> complex:
        """``H(exp(j w Te))`` at one frequency ``w`` (rad/s), s."""
        if self.modal is None:
            return _response(self.a, self.b, self.c, np.atleast_1d(w), self.te)[0]
        lam, res, dead = self.modal
        return _h_modal(lam, res, dead, self.te, float(w))


@functools.lru_cache(maxsize=8)
def _unit_circle(te: float, dead: int) -> tuple[np.ndarray, np.ndarray]:
    """``z = exp(j w Te)`` and ``z^-d`` (as :func:`_h_modal` computes them) on the grid of
    :func:`_frequency_grid`, read-only: what every loop of that period and dead time shares."""
    z, inv = _unit_circle_of(_frequency_grid(te), te, dead)
    for arr in (z, inv):
        arr.flags.writeable = False
    return z, inv


@functools.lru_cache(maxsize=8)
def _frequency_grid(te: float) -> np.ndarray:
    """The logarithmic frequency grid of the loops of period ``te`` (s), rad/s, shape (G,),
    read-only (one array shared by every loop of that period)."""
    w = np.geomspace(_W_LOW_TE / te, math.pi / te, _GRID_POINTS)
    w.flags.writeable = False
    return w


@njit(cache=True, nogil=True)
def _unwrap(p):
    """``np.unwrap(p)`` (period 2 pi, discontinuity pi) of shape (G,), compiled: numpy's
    arithmetic in numpy's order (``mod(dd + pi, 2 pi) - pi``, the ambiguous ``-pi`` made
    ``pi`` where ``dd > 0``, no correction where ``|dd| < pi``, the corrections summed
    sequentially as ``cumsum`` does), the same floats."""
    period = 2.0 * math.pi
    up = p.copy()
    total = 0.0
    for k in range(1, p.size):
        dd = p[k] - p[k - 1]
        correct = 0.0
        if not abs(dd) < math.pi:  # numpy computes the rest everywhere, uses it only here
            ddmod = (dd - -math.pi) % period + -math.pi
            if ddmod == -math.pi and dd > 0:
                ddmod = math.pi
            correct = ddmod - dd
        total = total + correct if k > 1 else correct
        up[k] = p[k] + total
    return up


#: Largest condition number of the eigenvector matrix for which :func:`_modal` is used:
#: its relative error is about ``cond * 1e-16``, 1e-10 here, far below what moves a margin
#: across its threshold; beyond it (near-defective poles) the exact solve is used.
_MODAL_COND_MAX = 1e6


def _modal(a, b, c, dead: int):
    """The loop ``H(z) = z^-d G(z)`` in modal form ``G(z) = sum_i r_i / (z - p_i)``.

    ``a, b, c`` are :func:`oga.model.linear.position_open_loop`'s (balanced here): the axis's
    ``m`` states first, then the dead-time line of ``d`` samples (a shift register: its
    poles are a defective ``d``-fold zero, so it is taken out as ``z^-d``). ``G`` is the axis alone
    (its input the oldest command of the line).

    Returns
    -------
    (poles, residues, d) : (ndarray of complex, shape (m,), same, int), or None
        None when the eigenvectors of ``G`` are ill-conditioned (:data:`_MODAL_COND_MAX`).
    """
    m = a.shape[0] - dead
    # balanced (a similarity by powers of 2: exact): the states' units differ by 1e5
    a_g, t = matrix_balance(a[:m, :m], permute=False)
    b_g = (a[:m, -1:] if dead else b[:m]) / np.diag(t)[:, None]
    c_g = c[:, :m] * np.diag(t)[None, :]
    lam, vec = np.linalg.eig(a_g)
    if not np.all(np.isfinite(lam)) or np.linalg.cond(vec) > _MODAL_COND_MAX:
        return None
    res = (c_g @ vec)[0] * np.linalg.solve(vec, b_g.astype(complex))[:, 0]
    for arr in (lam, res):
        arr.flags.writeable = False
    return lam, res, dead


def _margins(loop: _Loop, kp: float) -> Margins:
    """The :class:`Margins` of ``L = Kp H`` at ``kp`` ((m/min)/mm, positive and finite)."""
    kp_si = kp * KP_SI_PER_M_MIN_PER_MM
    log_kp = math.log(kp_si)
    w, h, phase = loop.w, loop.h, loop.phase

    def log_mag(w):
        return math.log(abs(loop.response(w))) + log_kp

    mag = loop.log_mag + log_kp  # ln |L| on the grid
    pm, w_gc = math.inf, math.nan
    for i in np.flatnonzero(np.sign(mag[:-1]) != np.sign(mag[1:])):
        wc = _root(log_mag, w[i], w[i + 1], mag[i], mag[i + 1])
        # the unwrapped phase at wc: the grid phase plus the (small) change from w[i]
        ph = phase[i] + np.angle(loop.response(wc) / h[i])
        pm_i = (math.degrees(ph) + 360.0) % 360.0 - 180.0
        if pm_i < pm:
            pm, w_gc = pm_i, wc

    stable = bool(np.max(np.abs(np.linalg.eigvals(loop.a - loop.b @ (kp_si * loop.c)))) < 1.0)
    return Margins(
        kp_m_min_per_mm=kp,
        pm_deg=float(pm),
        gm_db=float(loop.gm_db - 20.0 * math.log10(kp_si)),
        w_gain_crossover_rad_s=float(w_gc),
        w_phase_crossover_rad_s=loop.w_phase_crossover_rad_s,
        stable=stable,
    )


#: The Kp-independent loops (:class:`_Loop`, about 160 kB each) of the last few axis models,
#: by :func:`_loop_key`: the lifted inner loops and the frequency grid are most of the cost.
_LOOPS: OrderedDict[str, _Loop] = OrderedDict()
_LOOPS_KEPT = 16
#: Margins over the Kp grid, ``(kp, pm_deg, gm_db, stable)``, by (loop key, Kp span, Kp step).
_TABLES: OrderedDict[tuple, tuple[np.ndarray, ...]] = OrderedDict()
_TABLES_KEPT = 64


#: :func:`stable_ends` by (loop key, gain settings): a corner moves X and Y alike (one
#: computation for both), and a server sees the same uncertainty set again and again.
_ENDS: OrderedDict[tuple, tuple[float, float]] = OrderedDict()
_ENDS_KEPT = 1024


def _memo(store: OrderedDict, key, kept: int, compute):
    """``store[key]``, computed by ``compute()`` if missing; keeps the ``kept`` latest used."""
    try:
        store.move_to_end(key)
        return store[key]
    except KeyError:
        value = store[key] = compute()
        while len(store) > kept:
            store.popitem(last=False)
        return value


def _loop_key(machine: Machine, axis: str) -> str:
    """What the position loop of ``axis`` depends on: its model (not its limits) and the timing.

    Axes with the same model (X and Y of ucp710) share the key, whatever their names.
    MachineError if the machine lacks the axis.
    """
    model = machine.axis(axis).model_dump(mode="json", exclude_none=True, exclude={"limits"})
    return json_digest({"model": model, "timing": machine.timing.model_dump(mode="json")})


def _loop(machine: Machine, axis: str, key: str | None = None) -> _Loop:
    """The memoised :class:`_Loop` of ``axis`` (``key``: its :func:`_loop_key`, if known)."""
    key = _loop_key(machine, axis) if key is None else key
    return _memo(_LOOPS, key, _LOOPS_KEPT, lambda: _Loop(machine, axis))


def margins(machine: Machine | Plant, axis: str, kp_m_min_per_mm: float) -> Margins:
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
    machine = getattr(machine, "machine", machine)  # a Plant: its machine
    try:
        kp = float(kp_m_min_per_mm)
    except (TypeError, ValueError):
        raise OptionError(f"kp_m_min_per_mm: expected a number, got {kp_m_min_per_mm!r}") from None
    if not (math.isfinite(kp) and kp > 0.0):
        raise OptionError(f"kp_m_min_per_mm: must be positive and finite, got {kp}")
    return _margins(_loop(machine, axis), kp)


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


def stable_range(machine: Machine | Plant, axis: str) -> StabilityRange:
    """The stable Kp range of one axis over the machine's Kp grid.

    The grid spans ``machine.gains.kp_span_m_min_per_mm`` in steps of
    ``kp_step_m_min_per_mm``; a value qualifies when the closed loop is stable,
    ``PM >= pm_min_deg`` and ``GM >= gm_min_db``, and it lies inside
    ``kp_bounds_m_min_per_mm``. The range is the contiguous run of qualifying
    grid values (the lowest run if there are several, with status ``"disjoint"``).

    The margins over the grid are memoised by what they depend on (the axis model,
    the timing and the grid), so axes with the same model are computed once.

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
    machine = getattr(machine, "machine", machine)  # a Plant: its machine
    g = machine.gains
    loop_key = _loop_key(machine, axis)
    kp, pm, gm, stable = _memo(
        _TABLES,
        (loop_key, g.kp_span_m_min_per_mm, g.kp_step_m_min_per_mm),
        _TABLES_KEPT,
        lambda: _margin_table(_loop(machine, axis, loop_key), g),
    )
    return _summarise(axis, g, kp, pm, gm, stable)


def stable_ends(machine: Machine | Plant, axis: str) -> tuple[float, float]:
    """``(kp_min, kp_max)`` of :func:`stable_range` (``nan`` both when empty), computing
    only what decides them.

    The grid is walked upwards and stops where the lowest qualifying run ends. A value
    outside the bounds or below the gain margin (``gm = gm(1) - 20 log10 Kp``: no
    crossover search) needs neither the phase margin nor the eigenvalues. The margins that
    are computed are :func:`stable_range`'s (same :func:`_margins`), so the ends are its
    (tests/test_robust_speed.py compares them over a set of plants). A table
    :func:`stable_range` already holds is used as is; the ends are memoised by what they
    depend on (the loop and the gain settings).
    """
    machine = getattr(machine, "machine", machine)  # a Plant: its machine
    g = machine.gains
    loop_key = _loop_key(machine, axis)
    return _memo(_ENDS, (loop_key, g.model_dump_json()), _ENDS_KEPT,
                 lambda: _ends(machine, axis, loop_key))


def _ends(machine: Machine, axis: str, loop_key: str) -> tuple[float, float]:
    """:func:`stable_ends`, computed."""
    g = machine.gains
    table = _TABLES.get((loop_key, g.kp_span_m_min_per_mm, g.kp_step_m_min_per_mm))
    if table is not None:
        r = _summarise(axis, g, *table)
        return r.kp_min, r.kp_max
    loop = _loop(machine, axis, loop_key)
    if loop.modal is not None:
        return _walk_compiled(loop, g)
    return _walk(loop, g)


def _walk(loop: _Loop, g: GainSettings) -> tuple[float, float]:
    """The grid of ``g`` walked upwards to the end of the lowest qualifying run, each value's
    margins by :func:`_margins` (any loop)."""
    lo_b, hi_b = g.kp_bounds_m_min_per_mm
    run: list[float] = []
    for k in decimal_grid(*g.kp_span_m_min_per_mm, g.kp_step_m_min_per_mm):
        k = float(k)
        ok = (lo_b - 1e-9 <= k <= hi_b + 1e-9
              and loop.gm_db - 20.0 * math.log10(k * KP_SI_PER_M_MIN_PER_MM) >= g.gm_min_db)
        if ok:
            m = _margins(loop, k)
            ok = m.stable and m.pm_deg >= g.pm_min_deg and m.gm_db >= g.gm_min_db
        if ok:
            run.append(k)
        elif run:
            break
    return (run[0], run[-1]) if run else (math.nan, math.nan)


def _walk_compiled(loop: _Loop, g: GainSettings) -> tuple[float, float]:
    """:func:`_walk` of a loop in modal form, compiled (:func:`_walk_modal`)."""
    lam, res, dead = loop.modal
    lo_b, hi_b = (float(b) for b in g.kp_bounds_m_min_per_mm)
    ends = _walk_modal((lam, res, dead, loop.te), (loop.w, loop.h, loop.log_mag, loop.phase),
                       (loop.a, loop.b, loop.c), loop.gm_db,
                       decimal_grid(*g.kp_span_m_min_per_mm, g.kp_step_m_min_per_mm),
                       (lo_b, hi_b, float(g.pm_min_deg), float(g.gm_min_db),
                        KP_SI_PER_M_MIN_PER_MM))
    return float(ends[0]), float(ends[1])


def _margin_table(loop: _Loop, g: GainSettings) -> tuple[np.ndarray, ...]:
    """``(kp, pm_deg, gm_db, stable)`` over the Kp grid of ``g``, read-only arrays of shape (M,)."""
    kp = decimal_grid(*g.kp_span_m_min_per_mm, g.kp_step_m_min_per_mm)
    found = [_margins(loop, float(k)) for k in kp]
    pm = np.array([m.pm_deg for m in found])
    gm = np.array([m.gm_db for m in found])
    stable = np.array([m.stable for m in found])
    for arr in (kp, pm, gm, stable):
        arr.flags.writeable = False
    return kp, pm, gm, stable


def _summarise(axis: str, g: GainSettings, kp, pm, gm, stable) -> StabilityRange:
    """The :class:`StabilityRange` of ``axis`` from its margins over the Kp grid."""
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


# compiled walk of the stable range (the robust search's ~200 plant-axes) ------------------------
#
# The same arithmetic as :func:`_ends` over :func:`_margins` (modal form only): the loop's
# response, the gain crossovers refined by Brent's method (the algorithm of scipy's
# ``brentq``, C source scipy/optimize/Zeros/brentq.c, BSD; same iterates, same tolerances),
# the phase margin read as :func:`_margins` reads it, and the closed-loop eigenvalues
# (:func:`_closed_loop_stable`: LAPACK's complex ``geev`` on the real matrix, the same moduli
# to rounding, decides within 1e-6 of the unit circle; the real ``geev`` elsewhere).


@njit(cache=True, nogil=True)
def _h_modal(lam, res, dead, te, w):
    """``H(exp(j w Te))`` of the modal form (:meth:`_Loop.response`), s."""
    z = complex(math.cos(w * te), math.sin(w * te))
    s = 0j
    for i in range(lam.size):
        s += res[i] / (z - lam[i])
    p = 1.0 + 0j
    for _ in range(dead):
        p *= z
    return s * (1.0 / p)


@njit(cache=True, nogil=True)
def _h_modal_grid(lam, res, dead, te, w):
    """:func:`_h_modal` at every frequency of ``w`` (shape (G,)), s."""
    out = np.empty(w.size, dtype=np.complex128)
    for k in range(w.size):
        out[k] = _h_modal(lam, res, dead, te, w[k])
    return out


@njit(cache=True, nogil=True)
def _unit_circle_of(w, te, dead):
    """``z`` and ``1 / z^d`` at each frequency of ``w`` (shape (G,)): :func:`_h_modal`'s."""
    z = np.empty(w.size, dtype=np.complex128)
    inv = np.empty(w.size, dtype=np.complex128)
    for k in range(w.size):
        zk = complex(math.cos(w[k] * te), math.sin(w[k] * te))
        p = 1.0 + 0j
        for _ in range(dead):
            p *= zk
        z[k] = zk
        inv[k] = 1.0 / p
    return z, inv


@njit(cache=True, nogil=True)
def _h_modal_table(lam, res, z, inv):
    """:func:`_h_modal_grid` from the table of :func:`_unit_circle` (the same operations, the
    same bits; the sines and cosines once per period), s."""
    out = np.empty(z.size, dtype=np.complex128)
    for k in range(z.size):
        s = 0j
        for i in range(lam.size):
            s += res[i] / (z[k] - lam[i])
        out[k] = s * inv[k]
    return out


@njit(cache=True, nogil=True)
def _f_modal(kind, offset, lam, res, dead, te, w):
    """What a crossover zeroes: ``ln |H| + offset`` (kind 0, gain) or ``Im H`` (kind 1, phase)."""
    h = _h_modal(lam, res, dead, te, w)
    if kind == 0:
        return math.log(abs(h)) + offset
    return h.imag


@njit(cache=True, nogil=True)
def _root_modal(kind, offset, lam, res, dead, te, lo, hi, f_lo, f_hi):
    """:func:`_root` of :func:`_f_modal` (Brent's method as scipy's ``brentq``, xtol 1e-12,
    rtol 1e-14, 100 iterations; ``f_lo``, ``f_hi`` stand for the ends' values)."""
    if f_lo == 0.0:
        return lo
    if f_hi == 0.0:
        return hi
    if (f_lo > 0.0) == (f_hi > 0.0):
        return lo if abs(f_lo) < abs(f_hi) else hi
    xtol, rtol = 1e-12, 1e-14
    xpre, xcur, fpre, fcur = lo, hi, f_lo, f_hi
    xblk, fblk, spre, scur = 0.0, 0.0, 0.0, 0.0
    for _ in range(100):
        if fpre * fcur < 0:
            xblk, fblk = xpre, fpre
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2
        sbis = (xblk - xcur) / 2
        if fcur == 0 or abs(sbis) < delta:
            return xcur
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:  # interpolate
                stry = -fcur * (xcur - xpre) / (fcur - fpre)
            else:  # extrapolate
                dpre = (fpre - fcur) / (xpre - xcur)
                dblk = (fblk - fcur) / (xblk - xcur)
                stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
            if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - delta):
                spre, scur = scur, stry
            else:
                spre = scur = sbis
        else:
            spre = scur = sbis
        xpre, fpre = xcur, fcur
        if abs(scur) > delta:
            xcur += scur
        else:
            xcur += delta if sbis > 0 else -delta
        fcur = (f_lo if xcur == lo else f_hi if xcur == hi
                else _f_modal(kind, offset, lam, res, dead, te, xcur))
    return xcur


@njit(cache=True, nogil=True)
def _gain_margin_modal(lam, res, dead, te, w, h, phase):
    """``(gm_db, w_phase_crossover_rad_s)`` of :class:`_Loop` (modal form), compiled: the
    phase crossovers where the unwrapped ``phase`` passes -180 deg refined by Brent's method
    on ``Im H`` (:func:`_root_modal`), the Nyquist frequency if ``H`` is negative there, the
    least ``-20 log10 |H|`` over them (``inf``, ``nan`` if none): the same operations as the
    Python path, the same bits."""
    gm, w_pc = np.inf, np.nan
    n = w.size
    turn_was = math.floor((phase[0] + math.pi) / (2.0 * math.pi))
    for i in range(n):
        wc = np.nan
        if i < n - 1:
            turn = math.floor((phase[i + 1] + math.pi) / (2.0 * math.pi))
            if turn_was != turn:
                wc = _root_modal(1, 0.0, lam, res, dead, te, w[i], w[i + 1], h[i].imag,
                                 h[i + 1].imag)
            turn_was = turn
        elif h[n - 1].real < 0.0:  # at Nyquist H is real: a phase crossover if negative
            wc = w[n - 1]
        if not np.isnan(wc):
            gm_i = -20.0 * math.log10(abs(_h_modal(lam, res, dead, te, wc)))
            if gm_i < gm:
                gm, w_pc = gm_i, wc
    return gm, w_pc


@njit(cache=True, nogil=True)
def _sign(x):
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else (0.0 if x == 0.0 else x))


#: Pairs of grid points per block of :func:`_walk_modal`'s scan for gain crossovers.
_BLOCK = 64

#: LAPACK's real ``geev`` (eigenvalues only) as numba's ``np.linalg.eigvals`` calls it.
_DGEEV = _LAPACK().numba_ez_rgeev(types.float64)
#: :func:`_closed_loop_stable` trusts the real ``geev``'s spectral radius where it is farther
#: than this from 1: both ``geev`` are backward stable on the same matrix, their moduli differ
#: by rounding (1e-15 over ucp710's set, tests/test_fixed_costs.py), far below it.
_RADIUS_GUARD = 1e-6


@njit(cache=True, nogil=True)
def _closed_loop_stable(a, b, c, kp_si, acl, acl_f, wr, wi):
    """Whether every eigenvalue of ``A - B (Kp C)`` lies inside the unit circle, decided as
    the complex ``geev`` of numba's ``np.linalg.eigvals`` on it (the walk's reference) decides.

    The real ``geev`` (three times cheaper) decides where its spectral radius is farther than
    :data:`_RADIUS_GUARD` from 1; nearer, or if it fails or the matrix is not finite, the
    complex one does. ``acl`` (complex), ``acl_f`` (real, filled column-major), ``wr``, ``wi``:
    work arrays of the matrix's shape and size.
    """
    n = a.shape[0]
    finite = True
    for j in range(n):
        for i in range(n):
            x = a[i, j] - b[i, 0] * (kp_si * c[0, j])
            acl[i, j] = x
            acl_f[j, i] = x  # acl_f's memory read column-major: acl
            finite = finite and math.isfinite(x)
    if finite:
        info = _DGEEV(ord("d"), ord("N"), ord("N"), n, acl_f.ctypes, n, wr.ctypes, wi.ctypes,
                      wr.ctypes, 1, wr.ctypes, 1)  # no eigenvectors: vl, vr not referenced
        if info == 0:
            rho = 0.0
            for i in range(n):
                rho = max(rho, abs(complex(wr[i], wi[i])))
            if rho < 1.0 - _RADIUS_GUARD:
                return True
            if rho > 1.0 + _RADIUS_GUARD:
                return False
    return np.max(np.abs(np.linalg.eigvals(acl))) < 1.0


@njit(cache=True, nogil=True)
def _walk_modal(modal, curve, abc, gm_db, grid, rule):
    """:func:`_ends`'s walk over ``grid`` with :func:`_margins`' figures, compiled.

    ``modal = (lam, res, dead, te)`` (:attr:`_Loop.modal` and the period), ``curve = (w, h,
    log_mag, phase)`` (the loop's frequency grid and response there), ``abc = (a, b, c)``
    (the lifted loop), ``gm_db`` its gain margin at Kp = 1/s, ``rule = (lo_b, hi_b, pm_min,
    gm_min, kp_si_per)``: the configured Kp bounds, the margins asked for and the unit of
    ``grid``. Returns ``(kp_min, kp_max)`` (``nan`` both when no grid value qualifies).
    """
    lam, res, dead, te = modal
    w, h, log_mag, phase = curve
    a, b, c = abc
    lo_b, hi_b, pm_min, gm_min, kp_si_per = rule
    first, last = np.nan, np.nan
    acl = np.empty(a.shape, dtype=np.complex128)
    acl_f = np.empty(a.shape)  # the real matrix, column-major (:func:`_closed_loop_stable`)
    wr, wi = np.empty(a.shape[0]), np.empty(a.shape[0])
    # the grid's pairs (i, i + 1) in blocks, with the least and largest ln |H| each touches:
    # ln |H| + ln Kp has the sign of the exact sum (rounding keeps it), so where the block's
    # least value exceeds -ln Kp, or its largest falls short of it, no pair changes sign
    n_pairs = w.size - 1
    n_blocks = (n_pairs + _BLOCK - 1) // _BLOCK
    b_min, b_max = np.empty(n_blocks), np.empty(n_blocks)
    for j in range(n_blocks):
        lo_v, hi_v = np.inf, -np.inf
        for i in range(j * _BLOCK, min((j + 1) * _BLOCK, n_pairs) + 1):
            x = log_mag[i]
            if x != x:  # NaN: the block is scanned
                lo_v, hi_v = -np.inf, np.inf
                break
            lo_v, hi_v = min(lo_v, x), max(hi_v, x)
        b_min[j], b_max[j] = lo_v, hi_v
    for k in grid:
        kp_si = k * kp_si_per
        gm = gm_db - 20.0 * math.log10(kp_si)
        ok = lo_b - 1e-9 <= k <= hi_b + 1e-9 and gm >= gm_min
        if ok:
            log_kp = math.log(kp_si)
            pm = np.inf
            for j in range(n_blocks):
                if b_min[j] > -log_kp or b_max[j] < -log_kp:
                    continue  # no sign change in this block (the comment above)
                for i in range(j * _BLOCK, min((j + 1) * _BLOCK, n_pairs)):
                    m0, m1 = log_mag[i] + log_kp, log_mag[i + 1] + log_kp
                    if _sign(m0) != _sign(m1):
                        wc = _root_modal(0, log_kp, lam, res, dead, te, w[i], w[i + 1], m0, m1)
                        r = _h_modal(lam, res, dead, te, wc) / h[i]
                        ph = phase[i] + math.atan2(r.imag, r.real)
                        pm_i = (math.degrees(ph) + 360.0) % 360.0 - 180.0
                        if pm_i < pm:
                            pm = pm_i
            ok = pm >= pm_min and gm >= gm_min
            if ok:
                ok = _closed_loop_stable(a, b, c, kp_si, acl, acl_f, wr, wi)
        if ok:
            if np.isnan(first):
                first = k
            last = k
        elif not np.isnan(first):
            break
    return first, last
