"""The receding-horizon gain search (OGA, paper sec. 3.6), compiled.

At every sample ``k`` and for every axis ``a`` the search

1. bounds the gain increments: the stability bound (paper eq. 7) keeps the gain
   inside its range; the kinematic bound (eqs. 8-10) keeps the velocity command
   ``u_k = Kp E_k + Kf Vd_k`` inside the interval that eq. 2 allows given the
   two previous commands (``|u| <= Vmax``, ``|du|/Te <= Amax``,
   ``|d2u|/Te^2 <= Jmax``);
2. forms the paper's five candidates ``{a2 dKmin, a1 dKmin, 0, a1 dKmax,
   a2 dKmax}`` for Kp and, when Kf is adjusted too, the same five for Kf, each
   held inside the admissible interval (eq. 7 and eq. 10 intersected); every
   (dKp, dKf) pair whose command stays inside the eq. 2 interval is a candidate;
3. simulates every candidate of every axis over ``Np`` samples on the exact
   nonlinear axis model from the current true state (axes are independent,
   so each axis's windows are simulated once);
4. scores every combination of the axes' candidates with
   ``J = E'E + lam dK'dK`` (contour error E in mm, a CNC's unit, as the paper's
   tuning of lam implies, increments in (m/min)/mm and 1) and applies the least-cost one,
   advances the true state by one sample and recedes.

Reading of the candidate rule
-----------------------------
The paper: "dKp is tuned in [a2 dKmin, a1 dKmin, 0, a1 dKmax, a2 dKmax] ...;
dKmin and dKmax are calculated at each instant by (7) and (10)". Here ``dKmin``,
``dKmax`` are the ends of the stability interval (eq. 7, ``Kmin - K`` and
``Kmax - K``), and each of the five increments is then held inside the kinematic
bound (eq. 10), so that eq. 2 holds as the paper requires. The other reading,
the fractions of the intersection of eqs. 7 and 10, caps every gain change at
``a2`` of the jerk room, ``Jmax Te^2 / (|E_k| 1000/60)`` (m/min)/mm: a few
thousandths per sample on a curve, too slow to follow the curvature. On ucp710
and the reference contour that reading does worse than the fixed gains with the
published settings (MSE ratio 1.36 at Np 50; 0.52 at Np 100), while this one
gives 0.33 (bench/bench_paper.py).

Scoring combinations
--------------------
The predicted contour error of sample ``j`` is the distance of the predicted
point from the path. The candidates of one sample differ by fractions of a
micrometre, so the nearest segment of the path is found once per predicted
sample, for the prediction with no increment, and every combination is scored
with its exact distance to that segment's line: ``|P (p - q)|^2`` with
``P = I - t t'`` (``t`` the unit tangent, ``q`` the foot point). That squared
distance is a quadratic form in the axes' predicted positions, so it splits
into per-axis terms and pairwise cross terms: all combinations of two axes cost
one small matrix product, and three adjusted axes are searched by coordinate
descent over the axes. The verification (:mod:`oga.verify.replay`) replays the chosen
schedule and measures the true point-to-polyline contour error.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from oga import defaults
from oga.model.contour import nearest_segment
from oga.model.kinematics import eq2_excess
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM
from oga.model.simulate import step, window

__all__ = ["apply_gains", "paper_search", "paper_settings_of", "state_of", "Gains", "Axes",
           "PaperSettings", "State",
           "MAX_CANDIDATES", "STAT_FALLBACK", "STAT_WINDOWS"]

#: Largest number of candidates per axis and sample (5 Kp x 5 Kf).
MAX_CANDIDATES = 25
#: Index in ``stats``: samples where no candidate met eq. 2 and the least violating was taken.
STAT_FALLBACK = 0
#: Index in ``stats``: windows simulated.
STAT_WINDOWS = 1

_C = KP_SI_PER_M_MIN_PER_MM
#: E in mm: with E in um the paper's lam = 0.01 would weigh nothing against E'E (about
#: 50 um^2 over a horizon), while the paper finds lam = 0 lets gain peaks through and
#: 0.01 smooths them; in mm the two terms are of one order, and they behave so here.
_M2_TO_MM2 = 1e6
#: Largest number of full combinations enumerated before switching to coordinate descent.
_MAX_ENUM = 4096
#: Relative slack of the eq. 2 checks (float64 rounding).
_SLACK = 1e-9


@njit(cache=True)
def _fractions(slo, shi, lo, hi, a1, a2, out):
    """The paper's five increments; returns how many (deduplicated).

    Parameters
    ----------
    slo, shi : float
        Ends of the stability interval of the increment (eq. 7): ``dKmin``, ``dKmax``.
    lo, hi : float
        The admissible interval (eq. 7 and eq. 10), inside ``[slo, shi]``.
    a1, a2 : float
        Candidate fractions.
    out : ndarray, shape (>= 5,)
        Receives ``0, a1 dKmin, a1 dKmax, a2 dKmin, a2 dKmax``, each held inside
        ``[lo, hi]``, in that order (smallest first, so that among candidates of
        exactly equal cost the search keeps the smallest increment: with ``lam = 0``
        an axis at rest on its setpoint, whose gain the horizon cannot see, keeps
        its gain instead of drifting to a bound).
    """
    vals = (0.0, a1 * slo, a1 * shi, a2 * slo, a2 * shi)
    n = 0
    for v in vals:
        v = min(max(v, lo), hi)
        dup = False
        for i in range(n):
            if out[i] == v:
                dup = True
                break
        if not dup:
            out[n] = v
            n += 1
    return n


@njit(cache=True)
def _interval(lo, hi, num_lo, num_hi, den):
    """Intersect [lo, hi] with {x : num_lo <= den * x <= num_hi}; void when den ~ 0."""
    if abs(den) > 1e-12:
        a = num_lo / den
        b = num_hi / den
        if den < 0.0:
            a, b = b, a
        lo = max(lo, a)
        hi = min(hi, b)
    return lo, hi


@njit(cache=True)
def _candidates(e, vd, kp, kf, box, adjust, band, fractions, out_dkp, out_dkf):
    """Admissible (dKp, dKf) candidates of one axis; returns (count, fallback_used).

    ``e`` the following error (m), ``vd`` the planned velocity (m/s), ``kp``, ``kf`` the
    gains now; ``box`` ``(kp_lo, kp_hi, kf_lo, kf_hi)`` their bounds, ``adjust``
    ``(adj_kp, adj_kf)``, ``band`` ``(ulo, uhi)`` the command's eq. 2 interval, ``fractions``
    ``(a1, a2)``; the candidates into ``out_dkp``, ``out_dkf``.
    """
    kp_lo, kp_hi, kf_lo, kf_hi = box
    adj_kp, adj_kf = adjust
    ulo, uhi = band
    a1, a2 = fractions
    c = _C
    fr_p = np.empty(5)
    fr_f = np.empty(5)
    # Kp interval: stability, then kinematic through u = (kp + dkp) c e + kf vd
    if adj_kp:
        slo, shi = kp_lo - kp, kp_hi - kp
        lo, hi = _interval(slo, shi, ulo - kf * vd - kp * c * e, uhi - kf * vd - kp * c * e,
                           c * e)
        if lo > hi:  # kinematics and stability disagree: stay within stability only
            lo, hi = slo, shi
        n_p = _fractions(slo, shi, lo, hi, a1, a2, fr_p)
    else:
        fr_p[0] = 0.0
        n_p = 1
    if adj_kf:
        slo, shi = kf_lo - kf, kf_hi - kf
        lo, hi = _interval(slo, shi, ulo - kp * c * e - kf * vd, uhi - kp * c * e - kf * vd, vd)
        if lo > hi:
            lo, hi = slo, shi
        n_f = _fractions(slo, shi, lo, hi, a1, a2, fr_f)
    else:
        fr_f[0] = 0.0
        n_f = 1
    tol = 1e-12 * (1.0 + abs(ulo) + abs(uhi))
    n = 0
    best_v = np.inf
    best_i = 0
    best_j = 0
    for i in range(n_p):
        for j in range(n_f):
            u = (kp + fr_p[i]) * c * e + (kf + fr_f[j]) * vd
            viol = max(ulo - u, u - uhi, 0.0)
            if viol <= tol:
                out_dkp[n] = fr_p[i]
                out_dkf[n] = fr_f[j]
                n += 1
            elif viol < best_v:
                best_v = viol
                best_i = i
                best_j = j
    if n == 0:
        out_dkp[0] = fr_p[best_i]
        out_dkf[0] = fr_f[best_j]
        return 1, True
    return n, False


@njit(cache=True)
def _window_violation(p_now, pred, pd, vd, k, law, hist, lims, u, every):
    """Eq. 2 excess (:func:`oga.model.kinematics.eq2_excess`) of a candidate's predicted commands.

    The commands of the window's samples ``k .. k+n-1`` (``n`` the length of ``u``) are
    rebuilt into ``u`` from the predicted positions (``p_now`` at k, then ``pred[m-1]``)
    with the candidate gains ``law`` ``(kp_si, kf)`` held, after the commands ``hist``
    ``(u_{k-1}, u_{k-2})``. ``lims`` ``(vmax, amax, jmax, te, ferror_max)``: the excess of
    the following error ``|pd - p|`` over ``ferror_max`` (m, ``inf``: none) at the predicted
    samples of the program (rapids included) counts alike; ``every`` as in
    :func:`oga.model.kinematics.eq2_excess`.
    """
    kp_si, kf = law
    u1, u2 = hist
    vmax, amax, jmax, te, ferror_max = lims
    n = u.shape[0]
    last = pd.shape[0] - 1
    worst = 0.0
    for m in range(n):
        i = min(k + m, last)
        p = p_now if m == 0 else pred[m - 1]
        u[m] = kp_si * (pd[i] - p) + (kf * vd[i] if k + m <= last else 0.0)
        if m > 0 and k + m <= last and ferror_max < np.inf:
            worst = max(worst, abs(pd[i] - p) / ferror_max - 1.0)
    return max(worst, eq2_excess(u, u1, u2, vmax, amax, jmax, te, n, every))


@njit(cache=True)
def apply_gains(k, states, params, pdT, vdT, kp, kf, out, u_hist):
    """Apply the gains ``kp``, ``kf`` (3,) at sample ``k``: record them into ``out``
    ``(kp_out, kf_out, u_out)`` (N, 3), advance every axis's true state by one Te on the
    exact kernel, record the commands and shift their history."""
    kp_out, kf_out, u_out = out
    for a in range(3):
        kp_out[k, a] = kp[a]
        kf_out[k, a] = kf[a]
        u = step(states[a], params[a], pdT[a, k], vdT[a, k], kp[a] * _C, kf[a])
        u_out[k, a] = u
        u_hist[a, 1] = u_hist[a, 0]
        u_hist[a, 0] = u


class Gains(NamedTuple):
    """The gains searched, per axis (3,): ``adj_kp``, ``adj_kf`` (bool) which are adjusted,
    their bounds ``kp_lo .. kp_hi`` ((m/min)/mm) and ``kf_lo .. kf_hi``, and the baseline
    ``kp_base``, ``kf_base`` the anchor pulls to (both modes' searches)."""

    adj_kp: np.ndarray
    adj_kf: np.ndarray
    kp_lo: np.ndarray
    kp_hi: np.ndarray
    kf_lo: np.ndarray
    kf_hi: np.ndarray
    kp_base: np.ndarray
    kf_base: np.ndarray


class Axes(NamedTuple):
    """The plant's axes: ``params`` (3, P) packed (:func:`oga.model.simulate.axis_params`),
    ``vmax``, ``amax``, ``jmax``, ``ferror_max`` (3,) their limits."""

    params: np.ndarray
    vmax: np.ndarray
    amax: np.ndarray
    jmax: np.ndarray
    ferror_max: np.ndarray


class PaperSettings(NamedTuple):
    """Paper mode's scalars (see :func:`paper_search`, built by :func:`paper_settings_of`)."""

    te: float
    n_pred: int
    lam: float
    mu: float
    a1: float
    a2: float
    ce_window: int


class State(NamedTuple):
    """What the search changes in place: ``states`` (3, Z), ``kp``, ``kf`` (3,),
    ``u_hist`` (3, 2), ``kp_out``, ``kf_out``, ``u_out`` (N, 3), ``stats`` (2,) int64."""

    states: np.ndarray
    kp: np.ndarray
    kf: np.ndarray
    u_hist: np.ndarray
    kp_out: np.ndarray
    kf_out: np.ndarray
    u_out: np.ndarray
    stats: np.ndarray


class _Work(NamedTuple):
    """The buffers of one sample's choice (per axis, candidate, window sample)."""

    ncand: np.ndarray  # (3,) candidates per axis
    dkp: np.ndarray  # (3, MAX_CANDIDATES) increments
    dkf: np.ndarray
    pred: np.ndarray  # (3, MAX_CANDIDATES, n_pred) predicted positions
    ref: np.ndarray  # (n_pred, 3) the prediction nearest to "no change"
    q: np.ndarray  # (n_pred, 3) the path's nearest points to it
    tang: np.ndarray  # (n_pred, 3) and its tangents there
    d: np.ndarray  # (3, MAX_CANDIDATES, n_pred) offsets from q
    diag: np.ndarray  # (3, MAX_CANDIDATES) one axis's cost terms
    cross: np.ndarray  # (3, 3, MAX_CANDIDATES, MAX_CANDIDATES) two axes' cross terms
    choice: np.ndarray  # (3,) the candidate chosen
    viol: np.ndarray  # (3, MAX_CANDIDATES) eq. 2 excess
    u_scratch: np.ndarray  # (n_pred,)
    every: np.ndarray  # (n_pred,) eq. 2 on every window sample (rapids too)
    allowed: np.ndarray  # (3, MAX_CANDIDATES)


def paper_settings_of(options, te) -> PaperSettings:
    """Paper mode's scalars from its ``options`` (horizon, lam, anchor) and the period
    ``te`` (s), the candidate fractions and contour-error window from :mod:`oga.defaults`."""
    return PaperSettings(float(te), int(options.np_value), float(options.lam_value),
                         float(options.anchor_value), float(defaults.A1), float(defaults.A2),
                         int(defaults.CE_WINDOW_SAMPLES))


def state_of(states, kp, kf, n) -> State:
    """The search's :class:`State` at the program's start: the axes' ``states`` (3, Z)
    (changed in place), copies of the gains ``kp``, ``kf`` (3,), no command history,
    outputs for ``n`` samples, zero counters."""
    return State(states, kp.copy(), kf.copy(), np.zeros((3, 2)), np.empty((n, 3)),
                 np.empty((n, 3)), np.empty((n, 3)), np.zeros(4, dtype=np.int64))


@njit(cache=True)
def paper_search(k0, k1, pd, pdT, vdT, moving, axes, gains, cfg, st):
    """Run the receding-horizon search over samples ``k0 .. k1 - 1`` in place.

    Parameters
    ----------
    k0, k1 : int
        Sample range of this call (the caller loops over chunks for progress).
    pd : ndarray, shape (N, 3)
        Desired positions (the path), metres, C-contiguous.
    pdT, vdT : ndarray, shape (3, N)
        Desired positions (m) and velocities (m/s) per axis, contiguous rows.
    moving : ndarray of bool, shape (3,)
        Axes that take part in the contour error.
    axes : Axes
        The plant's packed parameters (3, P) (:func:`oga.model.simulate.axis_params`) and
        its limits (3,): ``vmax``, ``amax``, ``jmax`` (m/s, m/s^2, m/s^3) on the velocity
        command (eq. 2), ``ferror_max`` (m, ``inf``: none; a candidate's predicted excess
        over it counts as an eq. 2 excess does, at every sample, as in
        :mod:`oga.verify.replay`).
    gains : Gains
        Which gains of which axis the search may change, their bounds ((m/min)/mm, 1) and
        the baseline the anchor pulls to.
    cfg : PaperSettings
        ``te`` the period (s), ``n_pred`` the horizon Np (samples), ``lam`` the increment
        weight (mm^2 per unit^2 of increment; the anchor ``mu`` likewise), ``a1``, ``a2``
        the candidate fractions, ``ce_window`` the half-width of the index window searched
        for the nearest path point (:func:`paper_settings_of`).
    st : State
        Changed in place (:func:`state_of`): the true axis states at sample ``k0``, the
        current gains, the command history ``[u_{k-1}, u_{k-2}]`` per axis, the schedule
        and commands written for samples ``k0 .. k1 - 1``, the counters (``STAT_*``).
    """
    n_pred = cfg.n_pred
    work = _Work(np.ones(3, dtype=np.int64), np.zeros((3, MAX_CANDIDATES)),
                 np.zeros((3, MAX_CANDIDATES)), np.empty((3, MAX_CANDIDATES, n_pred)),
                 np.empty((n_pred, 3)), np.empty((n_pred, 3)), np.empty((n_pred, 3)),
                 np.empty((3, MAX_CANDIDATES, n_pred)), np.zeros((3, MAX_CANDIDATES)),
                 np.zeros((3, 3, MAX_CANDIDATES, MAX_CANDIDATES)), np.zeros(3, dtype=np.int64),
                 np.zeros((3, MAX_CANDIDATES)), np.empty(n_pred), np.ones(n_pred, dtype=np.bool_),
                 np.ones((3, MAX_CANDIDATES), dtype=np.bool_))
    # each step is handed only the arrays it reads (every array passed costs a copy of its
    # descriptor per call: the whole State and _Work were ~2 kB per step and sample)
    now = (st.states, st.kp, st.kf, st.u_hist, st.stats)
    cand = (work.ncand, work.dkp, work.dkf)
    check = (work.pred, work.viol, work.allowed, work.u_scratch, work.every)
    path = (work.ref, work.q, work.tang)
    cost = (work.pred, work.allowed, work.d, work.diag, work.cross)
    anchor = (st.kp, st.kf, gains.kp_base, gains.kf_base)
    bounds = (gains.adj_kp, gains.adj_kf, gains.kp_lo, gains.kp_hi, gains.kf_lo, gains.kf_hi)
    limits = (axes.vmax, axes.amax, axes.jmax)
    for k in range(k0, k1):
        _axis_candidates(k, pdT, vdT, moving, limits, bounds, cfg, now, cand)  # 1-2
        _predict_candidates(k, pdT, vdT, moving, axes, cfg, now, cand, check)  # 3
        _nearest_points(k, pd, moving, cfg, st.states, cand, work.pred, path)
        _quadratic_terms(moving, anchor, cfg, cand, path, cost)  # 4
        _choose(moving, work.ncand, work.diag, work.cross, work.choice)
        # apply, advance the true state, recede
        for a in range(3):
            st.kp[a] += work.dkp[a, work.choice[a]]
            st.kf[a] += work.dkf[a, work.choice[a]]
        apply_gains(k, st.states, axes.params, pdT, vdT, st.kp, st.kf,
                    (st.kp_out, st.kf_out, st.u_out), st.u_hist)


@njit(cache=True)
def _axis_candidates(k, pdT, vdT, moving, limits, bounds, cfg, now, cand):
    """Steps 1-2: every axis's admissible increments at sample ``k`` (one, zero, where the
    axis is not adjusted); ``limits`` ``(vmax, amax, jmax)`` (3,), ``bounds`` the first six
    fields of :class:`Gains`, ``now`` ``(states, kp, kf, u_hist, stats)`` of :class:`State`,
    ``cand`` ``(ncand, dkp, dkf)`` receives the candidates."""
    vmax, amax, jmax = limits
    adj_kp, adj_kf, kp_lo, kp_hi, kf_lo, kf_hi = bounds
    states, kp, kf, u_hist, stats = now
    ncand, dkp, dkf = cand
    te = cfg.te
    te2 = te * te
    for a in range(3):
        u1 = u_hist[a, 0]
        u2 = u_hist[a, 1]
        ulo = max(-vmax[a], u1 - amax[a] * te, 2.0 * u1 - u2 - jmax[a] * te2)
        uhi = min(vmax[a], u1 + amax[a] * te, 2.0 * u1 - u2 + jmax[a] * te2)
        if moving[a] and (adj_kp[a] or adj_kf[a]):
            e = pdT[a, k] - states[a, 0]
            n, fb = _candidates(
                e, vdT[a, k], kp[a], kf[a], (kp_lo[a], kp_hi[a], kf_lo[a], kf_hi[a]),
                (adj_kp[a], adj_kf[a]), (ulo, uhi), (cfg.a1, cfg.a2), dkp[a], dkf[a],
            )
            if fb:
                stats[STAT_FALLBACK] += 1
        else:
            dkp[a, 0] = 0.0
            dkf[a, 0] = 0.0
            n = 1
        ncand[a] = n


@njit(cache=True)
def _predict_candidates(k, pdT, vdT, moving, axes, cfg, now, cand, check):
    """Step 3: the predicted positions of every candidate's window (moving axes only) into
    ``pred`` and which candidates may be chosen into ``allowed``: those that keep eq. 2 (or
    least violate it); ``check`` ``(pred, viol, allowed, u_scratch, every)`` of ``_Work``."""
    states, kp, kf, u_hist, stats = now
    ncand, dkp, dkf = cand
    pred, viol, allowed, u_scratch, every = check
    n_pred = cfg.n_pred
    for a in range(3):
        if not moving[a]:
            continue
        least = np.inf
        lims = (axes.vmax[a], axes.amax[a], axes.jmax[a], cfg.te, axes.ferror_max[a])
        for c in range(ncand[a]):
            kp_si = (kp[a] + dkp[a, c]) * _C
            kf_c = kf[a] + dkf[a, c]
            window(states[a], axes.params[a], pdT[a], vdT[a], k, n_pred, kp_si, kf_c, pred[a, c])
            stats[STAT_WINDOWS] += 1
            viol[a, c] = _window_violation(
                states[a, 0], pred[a, c], pdT[a], vdT[a], k, (kp_si, kf_c),
                (u_hist[a, 0], u_hist[a, 1]), lims, u_scratch, every,
            )
            least = min(least, max(viol[a, c], _SLACK))
        for c in range(ncand[a]):
            allowed[a, c] = viol[a, c] <= least


@njit(cache=True)
def _nearest_points(k, pd, moving, cfg, states, cand, pred, path):
    """The path's nearest points ``q`` and tangents ``tang`` (``path`` ``(ref, q, tang)``)
    to the prediction nearest to "no change" (``ref``), walking along the window."""
    n_pred, ce_window = cfg.n_pred, cfg.ce_window
    ref, q, tang = path
    ncand, dkp, dkf = cand
    n_total = pd.shape[0]
    for a in range(3):
        best_c = 0
        best_m = np.inf
        for c in range(ncand[a]):
            m = abs(dkp[a, c]) + abs(dkf[a, c])
            if m < best_m:
                best_m = m
                best_c = c
        for j in range(n_pred):
            ref[j, a] = pred[a, best_c, j] if moving[a] else states[a, 0]
    idx = min(k + 1, n_total - 1)
    for j in range(n_pred):
        centre = min(k + 1 + j, n_total - 1)
        if j == 0:
            lo = max(centre - ce_window, 0)
            hi = min(centre + ce_window, n_total - 1)
        else:
            lo = max(idx - 3, 0)
            hi = min(max(idx + 4, centre + 1), n_total - 1)
            lo = min(lo, hi)
        i, t, _d2 = nearest_segment(pd, lo, hi, ref[j, 0], ref[j, 1], ref[j, 2])
        if i < 0:  # the path stands still over the window: distance to the point
            idx = lo
            for a in range(3):
                q[j, a] = pd[lo, a]
                tang[j, a] = 0.0
            continue
        idx = i
        inv = 0.0
        for a in range(3):
            inv += (pd[i + 1, a] - pd[i, a]) ** 2
        inv = 1.0 / np.sqrt(inv)
        for a in range(3):
            q[j, a] = pd[i, a] + t * (pd[i + 1, a] - pd[i, a])
            tang[j, a] = (pd[i + 1, a] - pd[i, a]) * inv


@njit(cache=True)
def _quadratic_terms(moving, anchor, cfg, cand, path, cost):
    """Step 4: the cost's terms with ``M = I - t t'``: per axis and candidate into ``diag``
    (``inf`` where not allowed) and per pair of axes and candidates into ``cross``;
    ``anchor`` ``(kp, kf, kp_base, kf_base)``, ``cost`` ``(pred, allowed, d, diag, cross)``."""
    n_pred, lam, mu = cfg.n_pred, cfg.lam, cfg.mu
    kp, kf, kp_base, kf_base = anchor
    ncand, dkp, dkf = cand
    _ref, q, tang = path
    pred, allowed, d, diag, cross = cost
    for a in range(3):
        if not moving[a]:
            continue
        for c in range(ncand[a]):
            s = 0.0
            for j in range(n_pred):
                dv = pred[a, c, j] - q[j, a]
                d[a, c, j] = dv
                s += (1.0 - tang[j, a] * tang[j, a]) * dv * dv
            if not allowed[a, c]:
                diag[a, c] = np.inf
                continue
            diag[a, c] = (s * _M2_TO_MM2 + lam * (dkp[a, c] ** 2 + dkf[a, c] ** 2)
                          + mu * ((kp[a] + dkp[a, c] - kp_base[a]) ** 2
                                  + (kf[a] + dkf[a, c] - kf_base[a]) ** 2))
    for a in range(3):
        for b in range(a + 1, 3):
            if not (moving[a] and moving[b]):
                continue
            for ca in range(ncand[a]):
                for cb in range(ncand[b]):
                    s = 0.0
                    for j in range(n_pred):
                        s -= tang[j, a] * tang[j, b] * d[a, ca, j] * d[b, cb, j]
                    cross[a, b, ca, cb] = 2.0 * s * _M2_TO_MM2


@njit(cache=True)
def _choose(moving, ncand, diag, cross, choice):
    """The least-cost combination of candidates into ``choice``: every one enumerated, or
    coordinate descent from each axis's own best where they are too many."""
    if ncand[0] * ncand[1] * ncand[2] > _MAX_ENUM:
        _descend(moving, ncand, diag, cross, choice)
        return
    best = np.inf
    for c0 in range(ncand[0]):
        for c1 in range(ncand[1]):
            for c2 in range(ncand[2]):
                j_ = diag[0, c0] * moving[0] + diag[1, c1] * moving[1] + diag[2, c2] * moving[2]
                if moving[0] and moving[1]:
                    j_ += cross[0, 1, c0, c1]
                if moving[0] and moving[2]:
                    j_ += cross[0, 2, c0, c2]
                if moving[1] and moving[2]:
                    j_ += cross[1, 2, c1, c2]
                if j_ < best:
                    best = j_
                    choice[0], choice[1], choice[2] = c0, c1, c2


@njit(cache=True)
def _descend(moving, ncand, diag, cross, choice):
    """Coordinate descent over the axes' candidates from each axis's own best."""
    for a in range(3):
        choice[a] = np.argmin(diag[a, : ncand[a]])
    for _sweep in range(4):
        changed = False
        for a in range(3):
            if not moving[a]:
                continue
            best = np.inf
            bc = choice[a]
            for c in range(ncand[a]):
                j_ = diag[a, c]
                for b in range(3):
                    if b == a or not moving[b]:
                        continue
                    if a < b:
                        j_ += cross[a, b, c, choice[b]]
                    else:
                        j_ += cross[b, a, choice[b], c]
                if j_ < best:
                    best = j_
                    bc = c
            if bc != choice[a]:
                choice[a] = bc
                changed = True
        if not changed:
            break
