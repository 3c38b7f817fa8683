"""The robust baseline: the equal fixed gains best over an uncertainty set.

Among the equal fixed gains (one Kp and one Kf on every moving axis, constant in time)
that keep every plant's limits (eq. 2 and the following-error limit, at every sample) and
stable range (Kp inside the range common to every plant and the nominal one, Kf inside the
machine's range), the one of least **geometric mean of MSE(CE) over the objective
plants**: the first :data:`oga.defaults.ROBUST_BASELINE_PLANTS` Monte Carlo plants of the
set, a sample of its distribution (the corners are its extremes, not a sample: they are
constraints only). The constraints hold on the plants themselves: the nominal plant and
every plant of the set, each replayed by :func:`oga.verify.verify`.

Why the geometric mean (the mean of log MSE): the certificate judges a table by its ratio
to the baseline plant by plant, and the geometric mean weighs every plant's relative change
alike. The arithmetic mean is ruled by the few plants of largest error: on reference_xz its
optimum (Kp 1.93, Kf 0.872 over 64 plants) was worse than Kp 1.95 / Kf 0.86 on 75 % of the
plants (median ratio 0.976 for that pair). Kp and Kf are continuous; the search stops where
the aggregate's model promises under :data:`oga.defaults.ROBUST_BASELINE_GAIN` per plant
(0.05 %) or its step is under :data:`oga.defaults.ROBUST_BASELINE_TOL` of a grid step.

Search (:func:`robust_baseline`), exact evaluations throughout (every figure is a replay of
the nonlinear model on a plant):

1. **Grid** (start): Kp and Kf on twice the machine's grid steps (``kp_step_m_min_per_mm``,
   ``kf_step``) inside the ranges, stiff loops and strong feed-forward first, ranked by the
   sum of squared contour errors over a screen of the objective plants (the first
   :data:`oga.defaults.ROBUST_BASELINE_GRID_PLANTS`): a candidate's sum is abandoned
   where it exceeds the best so far (exact: a sum of non-negative terms only grows), and
   one that breaks a limit on a screened or *critical* plant is refused.
2. **Refinement**: a trust-region SQP from there. At each point every modelled plant is
   replayed once with the derivatives of its positions and commands along Kp and Kf
   (:func:`oga.model.tangent.run_tangent`): each plant's sum of squared contour errors gets its
   Gauss-Newton model, each limit ratio (eq. 2, following error, at its peak sample) its
   slope; the 2-D QP of the aggregate's model under the linearised limits (kept
   :data:`oga.defaults.ROBUST_BASELINE_MARGIN` clear) and the trust region gives the
   step, taken if the replays there keep every limit and lower the aggregate (a point
   that breaks one is first moved to one that breaks it less). First on the screen, then
   on every objective plant.
3. **Confirmation** on every plant (the nominal one and the whole set) by
   :func:`oga.verify.verify`: the plants where the result breaks a check become critical
   (modelled at every point from then on) and the refinement goes on from there, until the
   result keeps them all. The corners at :data:`oga.defaults.ROBUST_BASELINE_SEED` of a
   limit or more at the grid's best are critical from the start. The confirmation's replays are
   returned: every certificate reuses them.

**Several programs** (:func:`joint_baseline`, the one fixed setting of a machine that runs
them all: what one gain law for several programs is judged against): the same search over
every pair of plant and program, the aggregate the geometric mean over every program's
objective plants, the constraints every program's on every plant (on short_xz and
circle_r50_f3000, 16 Monte Carlo plants: Kp 1.378 / Kf 0.913, between circle's own 1.369 /
0.917, which its jerk limit holds down, and short_xz's 1.944 / 0.866).

The replays of one step are independent and run on ``threads`` threads; the choices depend
only on their figures, combined in a fixed order, so the result is the same bits for any
thread count.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numba import njit

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.model.contour import _point_d2, ce2_at, nearest_at, path_index
from oga.errors import OptionError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, Machine
from oga.parallel import resolve_threads, thread_map
from oga.search.ranges import _checked, _holds
from oga.search.robust.plants import ScenarioSet, perturbed_machine
from oga.model.simulate import axis_params, rest_state, run, run_axes
from oga.model.tangent import run_tangent
from oga.model.stability import decimal_grid
from oga.verify.replay import ReplayGains, Verification, verify_prepared

__all__ = ["BaselineResult", "robust_baseline", "joint_baseline", "common_kp_range"]

#: Samples simulated between two limit checks of a candidate (speed only: a refused or
#: abandoned candidate wastes the rest of its last chunk).
_CHUNK = 256
#: Replay outcomes of :func:`_replay`.
_HELD, _BROKE, _ABANDONED = 0, 1, 2
#: Decimals candidates are rounded to (exact decimals in the summary, one key per value).
_DECIMALS = 10
#: Linearised limits in a refinement step's QP at most: those that may come nearest to their
#: limit within the trust region (a limit left out that a step breaks refuses that step).
_ROWS = 16


@dataclass(frozen=True, eq=False)
class BaselineResult:
    """What :func:`robust_baseline` found.

    Attributes
    ----------
    status : {"ok", "none"}
        ``"none"``: no equal fixed gains keep every plant's checks (``message`` says why).
    kp : float
        Kp on every moving axis, (m/min)/mm (``nan`` when none).
    kf : float
        Kf on every moving axis (``nan`` when none).
    mse_m2 : float
        The aggregate minimised: the geometric mean of MSE(CE) over the objective plants, m^2.
    objective_plants : tuple of int
        Their indices in the set.
    replays : tuple of Verification
        The gains replayed on every plant of the set (the set's order; their checks and
        figures, not their series: :func:`oga.verify.replay.verify_prepared`); empty when none.
    nominal : Verification or None
        The gains replayed on the nominal plant.
    critical : tuple of int
        The plants (indices in the set; -1 the nominal one) the search learnt to check
        every candidate on: where an earlier best broke a check.
    candidates : int
        Distinct gains evaluated.
    confirmations : int
        Confirmations on every plant (one more than the times the critical plants grew).
    message : str
        Why none was found (empty when ok).
    """

    status: str
    kp: float
    kf: float
    mse_m2: float
    objective_plants: tuple[int, ...]
    replays: tuple[Verification, ...] = ()
    nominal: Verification | None = None
    critical: tuple[int, ...] = ()
    candidates: int = 0
    confirmations: int = 0
    message: str = ""

    @property
    def ok(self) -> bool:
        """Gains were found."""
        return self.status == "ok"


@dataclass
class _Candidate:
    """What is known of one grid candidate (Kp, Kf): its per-plant sums of squared contour
    errors over the screen (complete ones), the plants where it breaks a limit or holds them
    (by index in the packed list), and its least known total (lower bound when abandoned)."""

    kp: float
    kf: float
    sse: dict = field(default_factory=dict)
    broke: set = field(default_factory=set)
    held: set = field(default_factory=set)
    lower: float = 0.0
    total: float | None = None  # the sum over the screen, once complete


class _Path(NamedTuple):
    """The setpoints as the compiled replays take them (N samples, A moving axes)."""

    cols: np.ndarray  # int64 (A,): the moving axes' columns
    pos: np.ndarray  # (N, 3) setpoints, m
    vel: np.ndarray  # (N, 3) velocity setpoints, m/s
    pos_t: np.ndarray  # (3, N) the same by axis (contiguous rows)
    vel_t: np.ndarray  # (3, N)
    feed: np.ndarray  # bool (N,): feed samples
    te: float  # sample period, s
    tree: tuple  # the path's index (oga.model.contour.path_index)
    lo: np.ndarray
    hi: np.ndarray


class _Plant(NamedTuple):
    """One plant as the compiled replays take it."""

    params: np.ndarray  # (3, P) packed parameters of the moving axes (their columns)
    fused: np.ndarray  # int64: the moving cascade axes' columns (simulated side by side)
    limits: np.ndarray  # (A, 4) vmax, amax, jmax, following-error limit


class _Packed:
    """The setpoints and plants as the compiled replays take them: one entry per plant and
    program, plant-major (entry ``q * G + g``: plant ``q``, program ``g`` of ``G``)."""

    def __init__(self, setpoints: tuple[Setpoints, ...], plants: tuple[Machine, ...],
                 threads: int = 1):
        self.n_programs = len(setpoints)
        self.paths = []
        for sp in setpoints:
            pos = np.ascontiguousarray(sp.pos, dtype=np.float64)
            vel = np.ascontiguousarray(sp.vel, dtype=np.float64)
            self.paths.append(_Path(np.array(sp.moving_axes, dtype=np.int64), pos, vel,
                                    np.ascontiguousarray(pos.T), np.ascontiguousarray(vel.T),
                                    np.ascontiguousarray(sp.counted), float(sp.dt),
                                    *path_index(pos, defaults.CE_WINDOW_SAMPLES)))
        # the limits' rows of every entry over the axes any program moves (zero elsewhere)
        self.axes = np.array(sorted({int(c) for path in self.paths for c in path.cols}),
                             dtype=np.int64)

        def pack(entry):
            plant = plants[entry // self.n_programs]
            cols = self.paths[entry % self.n_programs].cols
            moving = [AXES[c] for c in cols]
            prm = np.zeros((3, axis_params(plant, moving[0]).size))
            for c, a in zip(cols, moving):
                prm[c] = axis_params(plant, a)
            lim = plant.axis_limits()
            return _Plant(prm, np.array([c for c, a in zip(cols, moving)
                                         if plant.axis(a).kind == "cascade"], dtype=np.int64),
                          np.ascontiguousarray(np.column_stack(
                              [lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3,
                               plant.ferror_limits()])[cols]))

        self.plants = thread_map(pack, range(len(plants) * self.n_programs), threads)
        self._tangents: dict[tuple[int, float, float], tuple] = {}

    def entries(self, plants) -> tuple[int, ...]:
        """The entries of ``plants`` (indices in the plant list), every program of each."""
        g = self.n_programs
        return tuple(q * g + k for q in plants for k in range(g))

    def replay(self, q: int, kp: float, kf: float, bound: float, with_ce: bool):
        """:func:`_replay` of entry ``q``: ``(outcome, sum)``."""
        path = self.paths[q % self.n_programs]
        peaks = np.zeros((path.cols.size, 4))
        return _replay(self.plants[q], path, kp * KP_SI_PER_M_MIN_PER_MM, kf, bound,
                       with_ce, peaks)

    def tangent(self, q: int, kp: float, kf: float, with_ce: bool):
        """:func:`_tangent_replay` of entry ``q``: ``(holds, ratios (A, 4), slopes (A, 4, 2),
        model (6,) or None without ``with_ce``)``, the ratios and slopes over the limits (0
        where none is set), A the axes any program moves.

        Memoised by ``(q, kp, kf)``: the search asks again for points it has replayed (the
        refinement's last point on the objective plants, a point whose critical plants grew),
        and a replay with ``with_ce`` serves one without (the same peaks and slopes; the
        arrays returned are shared: read-only by convention)."""
        key = (q, kp, kf)
        known = self._tangents.get(key)
        if known is not None and (known[3] is not None or not with_ce):
            return known if with_ce or known[3] is None else (*known[:3], None)
        out = self._tangent(q, kp, kf, with_ce)
        self._tangents[key] = out
        return out

    def _tangent(self, q: int, kp: float, kf: float, with_ce: bool):
        path = self.paths[q % self.n_programs]
        n_a = path.cols.size
        peaks, slopes, model = np.zeros((n_a, 4)), np.zeros((n_a, 4, 2)), np.zeros(6)
        _tangent_replay(self.plants[q].params, path, kp * KP_SI_PER_M_MIN_PER_MM, kf,
                        with_ce, peaks, slopes, model)
        lim = self.plants[q].limits
        holds = all(_holds(*peaks[a], lim[a]) for a in range(n_a))
        finite = np.isfinite(lim)
        scale = np.where(finite, 1.0 / np.where(finite, lim, 1.0), 0.0)
        ratios, slopes = peaks * scale, slopes * scale[:, :, None]
        if n_a < self.axes.size:  # another program moves more axes: rows of zeros there
            rows = np.searchsorted(self.axes, path.cols)
            ratios = _padded(ratios, rows, self.axes.size)
            slopes = _padded(slopes, rows, self.axes.size)
        return holds, ratios, slopes, model if with_ce else None


def _padded(x: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """``x`` (A, ...) placed at ``rows`` of an array of ``n`` rows of zeros."""
    out = np.zeros((n,) + x.shape[1:])
    out[rows] = x
    return out


@njit(cache=True, nogil=True)
def _replay(plant, path, kp_si, kf, bound, with_ce, peaks):
    """Replay equal fixed gains on one plant from rest, checking eq. 2 and the following-error
    limit chunk by chunk and (``with_ce``) summing the squared contour error of the feed
    samples in time order.

    The simulation is :func:`oga.model.simulate.run_axes` (the moving cascade axes side by side;
    others :func:`oga.model.simulate.run`), the checks :func:`oga.search.ranges._checked`, the contour
    error :func:`oga.model.contour.ce2_at`: the figures of :func:`oga.verify.verify` (its
    squared contour error to 2 ulp per sample).

    Parameters
    ----------
    plant : _Plant
    path : _Path
    kp_si, kf : float
        The gains (1/s, factor).
    bound : float
        Abandon where the sum exceeds it, m^2.
    with_ce : bool
    peaks : ndarray, shape (A, 4)
        Receives the peaks the checks saw (:func:`oga.search.ranges._checked`).

    Returns
    -------
    outcome : int
        :data:`_HELD` (every sample simulated, every limit kept), :data:`_BROKE` (a limit
        broken: stopped at the end of that chunk), :data:`_ABANDONED` (the sum exceeded
        ``bound``: stopped there).
    sum : float
        The sum of squared contour errors so far, m^2 (0 without ``with_ce``).
    """
    params, fused, limits = plant.params, plant.fused, plant.limits
    cols, pos, vel = path.cols, path.pos, path.vel
    n_ax, n = cols.size, pos.shape[0]
    p_act = pos.copy()  # the axes not simulated hold their setpoints
    u = np.empty((n, 3))
    kp_k = np.full((_CHUNK, 3), kp_si)
    kf_k = np.full((_CHUNK, 3), kf)
    check = np.empty(_CHUNK + 2, dtype=np.bool_)
    alone = np.zeros(3, dtype=np.bool_)
    alone[cols] = True
    alone[fused] = False
    states = np.zeros((3, rest_state(params[cols[0]], 0.0).size))
    for a in range(n_ax):
        states[cols[a]] = rest_state(params[cols[a]], pos[0, cols[a]])
    s = 0.0
    near = -1
    for k0 in range(0, n, _CHUNK):
        k1 = min(k0 + _CHUNK, n)
        m = k1 - k0
        run_axes(states, params, fused, pos[k0:k1], vel[k0:k1], kp_k[:m], kf_k[:m],
                 p_act[k0:k1], u[k0:k1])
        for a in range(n_ax):
            c = cols[a]
            if alone[c]:
                run(states[c], params[c], pos[k0:k1, c], vel[k0:k1, c], kp_k[:m, c],
                    kf_k[:m, c], p_act[k0:k1, c], u[k0:k1, c])
            if not _checked(pos[:, c], p_act[:, c], u[:, c], path.te, limits[a], k0, k1, check,
                            peaks[a]):
                return _BROKE, s
        if with_ce:
            for k in range(k0, k1):
                if path.feed[k]:
                    ce2, near = ce2_at(pos, path.tree, path.lo[k], path.hi[k], k, p_act[k, 0],
                                       p_act[k, 1], p_act[k, 2], near)
                    s += ce2
            if s > bound:
                return _ABANDONED, s
    return _HELD, s


@njit(cache=True, nogil=True)
def _tangent_replay(params, path, kp_si, kf, with_ce, peaks, slopes, model):
    """Replay equal fixed gains on one plant from rest with the derivatives of every position
    and command along Kp ((m/min)/mm) and Kf (:func:`oga.model.tangent.run_tangent`: the same
    positions and commands as :func:`oga.model.simulate.run`, to the last bit).

    Parameters
    ----------
    params : ndarray, shape (3, P)
        Packed parameters of the moving axes (their columns).
    path : _Path
    kp_si, kf : float
        The gains (1/s, factor).
    with_ce : bool
        Sum the contour error's model (else ``model`` is zero).
    peaks : ndarray, shape (A, 4)
        Receives per axis the largest ``|u|``, ``|du|/Te``, ``|d2u|/Te^2`` (over every
        sample, the axis at rest before: :func:`oga.model.kinematics.command_peaks`' numbers) and
        ``|pd - p|``.
    slopes : ndarray, shape (A, 4, 2)
        Receives their derivatives along Kp and Kf (at the sample of the peak).
    model : ndarray, shape (6,)
        Receives :func:`_ce_model` (zero without ``with_ce``).
    """
    cols, pos, pos_t, vel_t = path.cols, path.pos, path.pos_t, path.vel_t
    n = pos.shape[0]
    p_act = pos.copy()
    sp = np.zeros((n, 3, 2))
    kp_k = np.full(n, kp_si)
    kf_k = np.full(n, kf)
    dkp = np.zeros((n, 2))
    dkf = np.zeros((n, 2))
    dkp[:, 0] = KP_SI_PER_M_MIN_PER_MM
    dkf[:, 1] = 1.0
    start = np.zeros(2, dtype=np.int64)
    pa, ua = np.empty(n), np.empty(n)
    spa, sua = np.empty((n, 2)), np.empty((n, 2))
    for a in range(cols.size):
        c = cols[a]
        state = rest_state(params[c], pos_t[c, 0])
        run_tangent(state, params[c], (pos_t[c], vel_t[c], kp_k, kf_k, dkp, dkf), start,
                    (pa, ua, spa, sua))
        if with_ce:  # the contour error's model reads them
            for k in range(n):
                p_act[k, c] = pa[k]
                sp[k, c, 0] = spa[k, 0]
                sp[k, c, 1] = spa[k, 1]
        _peak_slopes(ua, sua, pa, spa, pos_t[c], path.te, peaks[a], slopes[a])
    model[:] = 0.0
    if with_ce:
        _ce_model(path, p_act, sp, model)


@njit(cache=True, nogil=True)
def _ce_model(path, p_act, sp, model):
    """Add to ``model`` (6,) the sum of squared contour errors over the feed samples (the
    numbers of :func:`_replay`) and its Gauss-Newton model: ``g`` (2) and ``H`` (2x2, ``h00,
    h01, h11``) with ``sum(d) ~ sum + 2 g.d + d'H d``: the residual is the vector from the
    nearest path point to the actual one ``p_act`` (N, 3), its derivative the positions'
    ``sp`` (N, 3, 2) with the path's direction there taken out (the nearest point slides
    along the path)."""
    pos, tree, lo, hi = path.pos, path.tree, path.lo, path.hi
    near = -1
    j = np.empty((3, 2))  # the residual's derivative at one sample
    for k in range(pos.shape[0]):
        if not path.feed[k]:
            continue
        x, y, z = p_act[k, 0], p_act[k, 1], p_act[k, 2]
        bi, bt, d2 = nearest_at(pos, tree, lo[k], hi[k], k, x, y, z, near)
        near = bi
        tx, ty, tz = 0.0, 0.0, 0.0
        if bi < 0:  # standing still over the window (as :func:`oga.model.contour.ce2_at`)
            d2 = _point_d2(pos, lo[k], x, y, z)
            qx, qy, qz = pos[lo[k], 0], pos[lo[k], 1], pos[lo[k], 2]
        else:
            sx = pos[bi + 1, 0] - pos[bi, 0]
            sy = pos[bi + 1, 1] - pos[bi, 1]
            sz = pos[bi + 1, 2] - pos[bi, 2]
            qx, qy, qz = pos[bi, 0] + bt * sx, pos[bi, 1] + bt * sy, pos[bi, 2] + bt * sz
            length = np.sqrt(sx * sx + sy * sy + sz * sz)
            if 0.0 < bt < 1.0 and length > 0.0:  # inside the segment: it slides along it
                tx, ty, tz = sx / length, sy / length, sz / length
        rx, ry, rz = x - qx, y - qy, z - qz
        model[0] += d2
        for d in range(2):
            along = tx * sp[k, 0, d] + ty * sp[k, 1, d] + tz * sp[k, 2, d]
            j[0, d] = sp[k, 0, d] - along * tx
            j[1, d] = sp[k, 1, d] - along * ty
            j[2, d] = sp[k, 2, d] - along * tz
        for d in range(2):
            model[1 + d] += rx * j[0, d] + ry * j[1, d] + rz * j[2, d]
        model[3] += j[0, 0] * j[0, 0] + j[1, 0] * j[1, 0] + j[2, 0] * j[2, 0]
        model[4] += j[0, 0] * j[0, 1] + j[1, 0] * j[1, 1] + j[2, 0] * j[2, 1]
        model[5] += j[0, 1] * j[0, 1] + j[1, 1] * j[1, 1] + j[2, 1] * j[2, 1]


@njit(cache=True, nogil=True)
def _peak_slopes(u, su, p, sp, pd, te, peaks, slopes):
    """The peaks of one axis's command (as :func:`oga.model.kinematics.command_peaks`, every
    sample checked) and following error, and their derivatives at the sample of each peak
    (the first of the largest)."""
    v_pk, da_pk, dj_pk, e_pk = 0.0, 0.0, 0.0, 0.0
    u1, u2 = 0.0, 0.0
    s1, s2 = np.zeros(2), np.zeros(2)
    slopes[:] = 0.0
    for k in range(u.shape[0]):
        uk = u[k]
        x = abs(uk)
        if x > v_pk:
            v_pk = x
            for d in range(2):
                slopes[0, d] = np.sign(uk) * su[k, d]
        x = abs(uk - u1)
        if x > da_pk:
            da_pk = x
            for d in range(2):
                slopes[1, d] = np.sign(uk - u1) * (su[k, d] - s1[d]) / te
        x = abs(uk - 2.0 * u1 + u2)
        if x > dj_pk:
            dj_pk = x
            for d in range(2):
                slopes[2, d] = np.sign(uk - 2.0 * u1 + u2) * (su[k, d] - 2.0 * s1[d] + s2[d]) / (
                    te * te)
        x = abs(pd[k] - p[k])
        if x > e_pk:
            e_pk = x
            for d in range(2):
                slopes[3, d] = -np.sign(pd[k] - p[k]) * sp[k, d]
        u2, u1 = u1, uk
        for d in range(2):
            s2[d] = s1[d]
            s1[d] = su[k, d]
    peaks[0], peaks[1], peaks[2], peaks[3] = v_pk, da_pk / te, dj_pk / (te * te), e_pk


class _Cuts:
    """The limits a refused step broke, linearised where it broke them (ratio and slope at
    that point's own peak sample), as rows of the next steps' QPs.

    Why: a limit's model at the current point is its peak sample's; along the boundary of
    the feasible gains the peak moves to another sample, the model promises room that is not
    there, and the region shrank until the refinement stopped (circle_r50_f3000: stopped at
    Kp 1.4257 / Kf 0.8966 on a limit, where Kp 1.41 / Kf 0.90 keeps every plant's checks
    and its aggregate is 5.8 % lower)."""

    def __init__(self):
        self.at, self.ratios, self.slopes = [], [], []

    def add(self, kp: float, kf: float, ratios: np.ndarray, slopes: np.ndarray) -> None:
        """The broken limits (ratio > 1) of one plant at ``(kp, kf)``: ratios (A, 4), slopes
        (A, 4, 2) per unit of Kp and Kf."""
        broken = ratios.ravel() > 1.0
        self.at += [(kp, kf)] * int(broken.sum())
        self.ratios += list(ratios.ravel()[broken])
        self.slopes += list(slopes.reshape(-1, 2)[broken])

    def rows(self, centre: np.ndarray, scale: np.ndarray, cap: float):
        """Rows and right-hand sides in grid steps ``scale`` from ``centre``: each cut's
        ratio, extended linearly from where it broke, at most ``cap``."""
        if not self.at:
            return np.zeros((0, 2)), np.zeros(0)
        at, s = np.array(self.at), np.array(self.slopes)
        return s * scale, cap - np.array(self.ratios) - ((centre - at) * s).sum(axis=1)


@dataclass
class _Point:
    """One point of the refinement: its figures over the objective plants (the sum of squared
    contour errors and its model), whether it holds on them and the critical plants, and
    the constraints' linear models there (ratio to the limit and its slope, per plant,
    axis and limit)."""

    kp: float
    kf: float
    holds: bool
    total: float
    g: np.ndarray
    h: np.ndarray
    ratios: np.ndarray
    slopes: np.ndarray


def _qp(g, h, rows, rhs, radius):
    """The least ``2 g.x + x'Hx`` over ``rows @ x <= rhs`` and ``|x_i| <= radius`` (2-D: the
    constraints' active sets enumerated). Where no point meets the rows, the point of the
    trust region that exceeds them least. Returns ``x``."""
    a = np.vstack([rows, np.eye(2), -np.eye(2)])
    b = np.concatenate([rhs, np.full(4, radius)])
    h = h + 1e-12 * max(np.trace(h), 1e-300) * np.eye(2)
    points = [np.zeros((1, 2))]
    try:
        points.append(np.linalg.solve(h, -g)[None, :])
    except np.linalg.LinAlgError:
        pass
    n2 = np.einsum("ij,ij->i", a, a)
    ok = n2 > 0.0
    base = a[ok] * (b[ok] / n2[ok])[:, None]  # each row's line: base + t d
    d = np.column_stack([-a[ok, 1], a[ok, 0]])
    curv = np.einsum("ij,jk,ik->i", d, h, d)
    t = -(d @ g + np.einsum("ij,jk,ik->i", d, h, base)) / np.where(curv > 0.0, curv, 1.0)
    points.append((base + d * t[:, None])[curv > 0.0])  # the least on each row's line
    i, j = np.triu_indices(len(a), 1)  # each pair of rows' corner
    det = a[i, 0] * a[j, 1] - a[i, 1] * a[j, 0]
    keep = np.abs(det) > 1e-14 * (n2[i] + n2[j])
    i, j, det = i[keep], j[keep], det[keep]
    points.append(np.column_stack([(b[i] * a[j, 1] - b[j] * a[i, 1]) / det,
                                   (a[i, 0] * b[j] - a[j, 0] * b[i]) / det]))
    points = np.vstack(points)
    tol = 1e-12 * (1.0 + np.abs(b[:-4]))
    inside = np.all(np.abs(points) <= radius * (1.0 + 1e-12), axis=1)
    excess = np.max(points @ a[:-4].T - b[:-4] - tol, axis=1, initial=0.0)
    value = 2.0 * points @ g + np.einsum("ij,jk,ik->i", points, h, points)
    if np.any(inside & (excess <= 0.0)):
        value = np.where(inside & (excess <= 0.0), value, np.inf)
    else:  # none meets the rows: the least excess, then the least value
        value = np.where(inside & (excess <= excess[inside].min()), value, np.inf)
    return points[int(np.argmin(value))]


class _Search:
    """The state of one :func:`robust_baseline` search (module doc)."""

    def __init__(self, packed, screen, objective, kp_box, kf_box, threads):
        self.packed, self.screen, self.objective = packed, screen, objective
        self.kp_box, self.kf_box, self.threads = kp_box, kf_box, threads
        self.known: dict[tuple[float, float], _Candidate] = {}
        self.critical: list[int] = []  # packed indices
        self.breakers: list[int] = []  # the plants that refused a step, the latest first

    def candidate(self, kp: float, kf: float) -> _Candidate:
        key = (round(kp, _DECIMALS), round(kf, _DECIMALS))
        if key not in self.known:
            self.known[key] = _Candidate(*key)
        return self.known[key]

    def _evaluate(self, c: _Candidate, bound: float) -> None:
        """Learn ``c``'s total over the screen unless it exceeds ``bound``, then,
        where it is below ``bound``, whether it holds on the critical plants (writes ``c``
        only)."""
        if c.broke & set(self.critical):
            return
        if c.total is None and c.lower <= bound:
            s = 0.0
            for q in self.screen:
                if q in c.sse:
                    s += c.sse[q]
                    continue
                outcome, part = self.packed.replay(q, c.kp, c.kf, bound - s, True)
                if outcome == _BROKE:
                    c.broke.add(q)
                    return
                if outcome == _ABANDONED:
                    c.lower = max(c.lower, s + part)
                    return
                c.sse[q] = part
                c.held.add(q)
                s += part
            c.total = c.lower = s
        if c.total is None or c.total >= bound or c.broke & set(self.screen):
            return
        for q in self.critical:  # the limits only, up to the first break
            if q not in c.held:
                outcome, _ = self.packed.replay(q, c.kp, c.kf, math.inf, False)
                (c.broke if outcome == _BROKE else c.held).add(q)
                if outcome == _BROKE:
                    return

    def feasible_total(self, c: _Candidate) -> float:
        """``c``'s total if it is known to hold on the critical and screen plants, else inf."""
        if c.total is None or any(q in c.broke or q not in c.held
                                  for q in self.critical + list(self.screen)):
            return math.inf
        return c.total

    def evaluate(self, cands: list[_Candidate], bound: float) -> None:
        thread_map(lambda c: self._evaluate(c, bound), cands, self.threads)

    def best_of(self, cands, best: _Candidate | None) -> _Candidate | None:
        """The candidate of least feasible total among ``best`` and ``cands`` (the first
        among equal ones, ``best`` first)."""
        for c in cands:
            t = self.feasible_total(c)
            if t < (math.inf if best is None else self.feasible_total(best)):
                best = c
        return best

    def point(self, kp: float, kf: float, modelled: tuple[int, ...]) -> _Point:
        """The :class:`_Point` of ``(kp, kf)``: tangent replays on the ``modelled`` plants (the
        aggregate's) and the critical ones."""
        plants = list(modelled) + [q for q in self.critical if q not in modelled]
        out = thread_map(lambda q: self.packed.tangent(q, kp, kf, q in modelled), plants,
                         self.threads)
        models = np.array([m for _h, _r, _s, m in out[:len(modelled)]])
        sse = np.maximum(models[:, 0], np.finfo(float).tiny)
        total = 0.0  # the aggregate: the sum of the logs, in the plants' order
        for v in np.log(sse):
            total += v
        g = (models[:, 1:3] / sse[:, None]).sum(axis=0)
        h00, h01, h11 = (models[:, 3:6] / sse[:, None]).sum(axis=0)
        return _Point(kp, kf, all(o[0] for o in out), total, g, np.array([[h00, h01], [h01, h11]]),
                      np.concatenate([o[1].ravel() for o in out]),
                      np.concatenate([o[2].reshape(-1, 2) for o in out]))

    def breaks(self, kp: float, kf: float, modelled: tuple[int, ...], near: _Point) -> bool:
        """Whether ``(kp, kf)`` breaks a limit on a plant :meth:`point` replays, found by
        replaying ``threads`` at a time, stopping at the first break: first the plants that
        broke a refused step (the latest first), then the others by their largest limit ratio
        at the point ``near`` (the refinement's current one), the nearest to a limit first.
        The answer does not depend on the order, only its cost: a refused step of the
        refinement is usually refused by the plant that refused the last one. The replays
        are memoised: :meth:`point` there reuses them."""
        plants = list(modelled) + [q for q in self.critical if q not in modelled]
        ratio = near.ratios.reshape(len(plants), -1).max(axis=1)  # :meth:`point`'s order
        order = sorted(range(len(plants)), key=lambda j: -ratio[j])  # stable: ties keep order
        rest = [plants[j] for j in order if plants[j] not in self.breakers]
        plants = [q for q in self.breakers if q in plants] + rest
        for k in range(0, len(plants), self.threads):
            batch = plants[k:k + self.threads]
            out = thread_map(lambda q: self.packed.tangent(q, kp, kf, q in modelled), batch,
                             self.threads)
            broke = [q for q, o in zip(batch, out) if not o[0]]
            if broke:
                self.breakers = broke + [q for q in self.breakers if q not in broke]
                return True
        return False

    def refine(self, x: _Point, steps: tuple[float, float], modelled: tuple[int, ...]) -> _Point:
        """Step 2: the trust-region refinement from ``x`` of the aggregate over the
        ``modelled`` plants (module doc); a start that breaks a limit on the plants modelled
        is first moved to one that does not."""
        scale = np.array(steps, dtype=float)
        lo = np.array([self.kp_box[0], self.kf_box[0]])
        hi = np.array([self.kp_box[1], self.kf_box[1]])
        box = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
        margin = defaults.ROBUST_BASELINE_MARGIN
        radius = 2.0  # in grid steps
        cuts = _Cuts()
        for _ in range(defaults.ROBUST_BASELINE_ITERATIONS):
            slopes = x.slopes * scale
            reach = x.ratios + np.abs(slopes).sum(axis=1) * radius  # the most within the region
            near = reach >= max(1.0 - margin, np.sort(reach)[-min(_ROWS, reach.size)])
            # a limit kept stays kept (x = 0 meets the rows); a broken one is to be restored
            rhs = (np.maximum(1.0 - margin, x.ratios[near]) if x.holds
                   else np.full(near.sum(), 1.0 - margin)) - x.ratios[near]
            centre = np.array([x.kp, x.kf])
            box_rhs = np.maximum(np.concatenate([(hi - centre) / scale, (centre - lo) / scale]),
                                 0.0)
            cut_rows, cut_rhs = cuts.rows(centre, scale, 1.0 - margin)
            step = _qp(x.g * scale, x.h * np.outer(scale, scale),
                       np.vstack([slopes[near], cut_rows, box]),
                       np.concatenate([rhs, cut_rhs, box_rhs]), radius)
            size = float(np.max(np.abs(step)))
            gain = -(2.0 * x.g @ (step * scale) + (step * scale) @ x.h @ (step * scale))
            if size < defaults.ROBUST_BASELINE_TOL or (
                    x.holds and gain < defaults.ROBUST_BASELINE_GAIN * len(modelled)):
                break
            kp, kf = (round(float(v), 6) for v in np.clip(centre + step * scale, lo, hi))
            if x.holds and self.breaks(kp, kf, modelled, x):  # refused, whatever its total
                q = self.breakers[0]
                cuts.add(kp, kf, *self.packed.tangent(q, kp, kf, q in modelled)[1:3])
                radius = size / 4.0
                continue
            y = self.point(kp, kf, modelled)
            if (y.total < x.total and y.holds) if x.holds else _excess_of(y) < _excess_of(x):
                x = y
                radius = max(radius, 2.0 * size)
            else:
                radius = size / 4.0
        return x

    def seed(self, c: _Candidate, plants) -> None:
        """The ``plants`` where ``c`` reaches :data:`oga.defaults.ROBUST_BASELINE_SEED` of a
        limit or more become critical."""
        plants = [q for q in plants if q not in self.critical]
        out = thread_map(lambda q: self.packed.tangent(q, c.kp, c.kf, False), plants,
                         self.threads)
        self.critical += [q for q, (_h, r, _s, _m) in zip(plants, out)
                          if r.max(initial=0.0) >= defaults.ROBUST_BASELINE_SEED]

    def grid(self, kp_grid, kf_grid) -> _Candidate | None:
        """Step 1: the grid's best feasible candidate (on the critical plants)."""
        order = [self.candidate(float(kp), float(kf)) for kp in kp_grid[::-1]
                 for kf in kf_grid[::-1]]
        best = None
        for k in range(0, len(order), self.threads):
            batch = order[k:k + self.threads]
            self.evaluate(batch, math.inf if best is None else self.feasible_total(best))
            best = self.best_of(batch, best)
        return best


def robust_baseline(
    setpoints: Setpoints,
    machine: Machine,
    plants: ScenarioSet,
    bounds: tuple[dict[str, tuple[float, float]], ...] | None = None,
    kp_range: tuple[float, float] | None = None,
    *,
    threads: int | None = None,
    progress: Callable[[float], None] | None = None,
) -> BaselineResult:
    """The equal fixed gains of least geometric-mean MSE(CE) over the objective plants among
    those that keep every plant's checks (module doc).

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples).
    machine : Machine
        The nominal machine (its Kp and Kf grids and Kf range; its nominal plant is a
        constraint too).
    plants : ScenarioSet
        The plants (:func:`oga.search.robust.plants.scenario_set`).
    bounds : tuple of dict, optional
        Each plant's stable Kp range per moving axis
        (:func:`oga.verify.certificate.plant_bounds`; computed when omitted).
    kp_range : (float, float), optional
        The Kp range stable on every plant and the nominal one, (m/min)/mm (computed from
        ``bounds`` and the nominal plant's when omitted).
    threads : int, optional
        Threads for independent candidates and replays (default: the available cores);
        the result does not depend on it.
    progress : callable, optional
        Called with the fraction done (0..1) after each step.

    Returns
    -------
    BaselineResult
        ``status "none"`` with a message naming the gains tried last, the plants they
        break and a remedy, when none keep every plant's checks.
    """
    return joint_baseline({"": setpoints}, machine, plants, bounds, kp_range, threads=threads,
                          progress=progress)[0]


def joint_baseline(
    programs: dict[str, Setpoints],
    machine: Machine,
    plants: ScenarioSet,
    bounds: tuple[dict[str, tuple[float, float]], ...] | None = None,
    kp_range: tuple[float, float] | None = None,
    *,
    threads: int | None = None,
    progress: Callable[[float], None] | None = None,
) -> tuple[BaselineResult, ...]:
    """The robust baseline of several programs together: the equal fixed gains of least
    geometric-mean MSE(CE) over every program's objective plants among those that keep every
    plant's checks on every program (the one fixed setting of a machine that runs them all).

    Parameters
    ----------
    programs : dict of str to Setpoints
        Each program's planned motion by name (the same sample period).
    machine, plants, bounds, kp_range, threads, progress
        As :func:`robust_baseline` (``bounds`` over every axis any program moves).

    Returns
    -------
    tuple of BaselineResult
        One per program, in ``programs``' order: the same gains, each with its program's
        replays and aggregate (``status "none"`` on every one when none keep the checks).
    """
    if not programs:
        raise OptionError("programs: a joint baseline needs at least one program")
    if len({sp.dt for sp in programs.values()}) > 1:
        raise OptionError("programs: every program needs the same sample period")
    threads = resolve_threads(threads)
    report = progress or (lambda f: None)
    setpoints = tuple(programs.values())
    search, all_plants, bounds_of = _prepare(programs, machine, plants, bounds, kp_range,
                                             threads)
    g = machine.gains
    kp_lo, kp_hi = search.kp_box
    grids = (decimal_grid(kp_lo, kp_hi, 2 * g.kp_step_m_min_per_mm),
             decimal_grid(*g.kf_range, 2 * g.kf_step))
    steps = (g.kp_step_m_min_per_mm, g.kf_step)
    n_g = len(setpoints)

    def confirm(x: _Point) -> list[Verification]:
        gains = [ReplayGains.of(sp, np.full((len(sp), 3), x.kp), np.full((len(sp), 3), x.kf))
                 for sp in setpoints]
        return thread_map(lambda e: verify_prepared(setpoints[e % n_g], all_plants[e // n_g],
                                                    gains[e % n_g], bounds_of[e], series=False),
                          range(len(all_plants) * n_g), threads)

    confirmations, x = 0, None
    while True:
        report(min(0.9, 0.3 * confirmations + 0.05))
        if x is None or not x.holds:  # (again) from the grid's best
            x = _from_grid(search, grids, steps, plants, confirmations == 0)
            if isinstance(x, tuple):  # none on the grid: the closest, named
                return _none(plants, tuple(programs), (x[0], confirm(x[0])), search, *x[1:])
        x = search.refine(x, steps, search.objective)
        if not x.holds:
            continue
        replays = confirm(x)
        confirmations += 1
        broke = [i for i, v in enumerate(replays) if not v.ok]
        if not broke:
            break
        if confirmations == defaults.ROBUST_BASELINE_CONFIRMATIONS:
            return _none(plants, tuple(programs), (x, replays), search,
                         f"no equal fixed gains found keep the limits on every plant of the "
                         f"uncertainty set in {confirmations} tries", "the last tried")
        search.critical += [i for i in broke if i not in search.critical]
        x = search.point(x.kp, x.kf, search.objective)  # it breaks a limit there: restored next
    report(1.0)
    return _found(plants, search, x, replays, confirmations)


def _prepare(programs, machine, plants, bounds, kp_range, threads):
    """The :class:`_Search` of :func:`joint_baseline` (its Kp box the range stable on every
    plant and the nominal one), the plants replayed (the set's, then the nominal one) and
    each entry's stable ranges (its program's moving axes)."""
    from oga.verify.certificate import plant_bounds

    moving_of = {name: tuple(AXES[i] for i in sp.moving_axes) for name, sp in programs.items()}
    for name, moving in moving_of.items():
        if not moving:
            raise OptionError(f"{name + ': ' if name else ''}toolpath: no axis moves; "
                              "nothing to optimise")
    moving = tuple(a for a in AXES if any(a in m for m in moving_of.values()))
    nominal = perturbed_machine(machine, {}, 0, machine.name)
    if bounds is None:
        bounds = plant_bounds(plants, moving, threads=threads)
    nominal_bounds = plant_bounds(_alone(machine, nominal), moving)[0]
    if kp_range is None:
        kp_range = common_kp_range(machine, bounds, moving, nominal_bounds)
    all_plants = tuple(plants.plants) + (nominal,)  # plant index len(set): the nominal one
    packed = _Packed(tuple(programs.values()), all_plants, threads)
    objective = packed.entries(range(min(defaults.ROBUST_BASELINE_PLANTS, plants.n_monte_carlo)
                                     or len(plants)))
    screen = objective[:defaults.ROBUST_BASELINE_GRID_PLANTS * len(programs)]
    kp_lo, kp_hi = kp_range
    search = _Search(packed, screen, objective, (kp_lo, kp_hi), tuple(machine.gains.kf_range),
                     threads)
    if not kp_lo <= kp_hi:
        raise OptionError(f"baseline: no Kp is stable on every plant of the uncertainty set "
                          f"(common range {kp_lo}..{kp_hi} (m/min)/mm): narrow its "
                          "[axes.*.uncertainty], or search the nominal model only (--nominal)")
    bounds_of = [{a: b[a] for a in m} for b in bounds + (nominal_bounds,)
                 for m in moving_of.values()]  # entry order: plant-major
    return search, all_plants, bounds_of


def _from_grid(search, grids, steps, plants, first):
    """Steps 1 and 2 from the grid's best: the screen's optimum (cheap), then the point of the
    objective plants there; on the ``first`` pass the corners near a limit at the grid's best
    become critical. Where no grid point holds: ``(closest point, why, which)``, the gains
    that come closest to keeping the limits on the screen."""
    best = search.grid(*grids)
    screen = search.screen
    if best is None:
        (kp_lo, kp_hi), kf_range = search.kp_box, search.kf_box
        mid = ((kp_lo + kp_hi) / 2, sum(kf_range) / 2)
        x = min((search.point(kp, kf, screen) for kp in (kp_lo, mid[0], kp_hi)
                 for kf in (kf_range[0], mid[1], kf_range[1])), key=_excess_of)
        return (search.refine(x, steps, screen), "no equal fixed gains keep the limits on every "
                "plant of the uncertainty set", "the closest to keeping them")
    if first:  # the corners near a limit there: critical from the start
        search.seed(best, search.packed.entries(range(plants.n_monte_carlo, len(plants) + 1)))
    x = search.refine(search.point(best.kp, best.kf, screen), steps, screen)
    return search.point(x.kp, x.kf, search.objective)


def _found(plants, search, x, replays, confirmations) -> tuple[BaselineResult, ...]:
    """The results of a search whose point ``x`` was confirmed by ``replays`` (every entry:
    the set's plants, then the nominal one, every program of each), one per program."""
    n_g, n = search.packed.n_programs, len(plants)
    objective = tuple(e // n_g for e in search.objective[::n_g])
    out = []
    for k in range(n_g):
        mine = replays[k::n_g]
        mse = np.array([mine[i].metrics.mse_m2 for i in objective])
        out.append(BaselineResult(
            status="ok", kp=x.kp, kf=x.kf, mse_m2=float(np.exp(np.mean(np.log(mse)))),
            objective_plants=objective, replays=tuple(mine[:n]), nominal=mine[n],
            critical=tuple(-1 if e // n_g == n else e // n_g for e in search.critical
                           if e % n_g == k),
            candidates=len(search.known), confirmations=confirmations))
    return tuple(out)


def common_kp_range(machine: Machine, bounds, moving, nominal_bounds=None
                    ) -> tuple[float, float]:
    """The Kp range (lo, hi), (m/min)/mm, stable on every plant (their ``bounds``:
    :func:`oga.verify.certificate.plant_bounds` over the axes ``moving``) and on the nominal
    one (``nominal_bounds``, computed when not given)."""
    if nominal_bounds is None:
        from oga.verify.certificate import plant_bounds

        nominal = perturbed_machine(machine, {}, 0, machine.name)
        nominal_bounds = plant_bounds(_alone(machine, nominal), moving)[0]
    every = tuple(bounds) + (nominal_bounds,)
    return (max(b[a][0] for b in every for a in moving),
            min(b[a][1] for b in every for a in moving))


def _alone(machine: Machine, plant: Machine) -> ScenarioSet:
    """A set of the one ``plant``."""
    return ScenarioSet(status="nominal-only", nominal=machine, plants=(plant,),
                       labels=("nominal",), draws=(({}, 0),), seed=0, n_monte_carlo=0,
                       n_corners=0)


def _none(plants, names, last, search, why, which) -> tuple[BaselineResult, ...]:
    """The results (one per program of ``names``) when no gains keep every plant's checks,
    the message naming the gains ``last`` (a point and its replays on every entry; ``which``
    says what they are), on how many plants they break a check, the worst break, and the
    remedies."""
    x, replays = last
    n_g = len(names)
    labels = [lab + (f" ({name})" if n_g > 1 else "")
              for lab in tuple(plants.labels) + ("nominal",) for name in names]
    broke = [i for i, v in enumerate(replays) if not v.ok] or list(range(len(replays)))
    worst = max(broke, key=lambda i: _excess(replays[i]))
    v = replays[worst]
    what = v.violations[0] if v.violations else "no check broken"
    runs = "plants" if n_g == 1 else f"runs ({len(replays) // n_g} plants x {n_g} programs)"
    why += (f" ({which}, Kp {x.kp:.4g} Kf {x.kf:.4g}, break them on "
            f"{sum(not v.ok for v in replays)} of {len(replays)} {runs}; on "
            f"{labels[worst]!r}: {what})")
    why += (". The motion leaves the loop too little room on these plants: plan it with "
            "smaller [planner] accel_fraction and jerk_fraction in the machine file, narrow its "
            "[axes.*.uncertainty], or search the nominal model only (--nominal, no certificate)")
    return (BaselineResult(status="none", kp=math.nan, kf=math.nan, mse_m2=math.nan,
                           objective_plants=tuple(e // n_g for e in search.objective[::n_g]),
                           candidates=len(search.known), message="baseline: " + why),) * n_g


def _excess_of(x: _Point) -> float:
    """The largest limit ratio a point's replays reach (over the plants modelled)."""
    return float(np.max(x.ratios, initial=0.0))


def _excess(v: Verification) -> float:
    """Largest limit ratio of a replay (eq. 2 and following error)."""
    return max(float(np.max(v.command_ratio)), float(np.nanmax(np.append(v.ferror_ratio, 0.0))))
