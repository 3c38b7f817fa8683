"""ZPETC feed-forward, digital disturbance observer, CCC and friction compensation.

Paper: zpetc_ccc_ddob_friction.txt (integrated controller, Fig. 21). Per contour-plane
axis, designed offline on the linearised plant of :func:`oga.model.linear.position_open_loop`
(``G(z)``: velocity command -> measured position, dead time included):

- **ZPETC** (paper eqs. 1-6, Tomizuka) on the closed position loop
  ``T = Kp G / (1 + Kp G) = z^-d Ba(z^-1) Bu(z^-1) / A(z^-1)``: zeros inside the radius
  ``accept_radius`` are acceptable (``Ba``, monic), the others (outside it or on/near the
  unit circle) unacceptable (``Bu``, with the gain). The modified reference
  ``r = Bu(z) z^d A(z^-1) / (Bu(1)^2 Ba(z^-1)) pd`` needs ``d + deg Bu`` samples of
  preview, which an interpolator has (computed over the whole toolpath before the
  loop; past its end the last setpoint is held). The position law is ``u_c = Kp (r - p)``
  (no separate velocity feed-forward: the ZPETC is the feed-forward).
- **CCC** of :mod:`oga.controllers.ccc` on the true axis errors ``pd - p``.
- **DDOB** (paper eqs. 16-18, Fig. 4) with the nominal model ``Pn = Nn / Dn = G``:
  ``w = Dn p - Nn u``, disturbance estimate ``d = Q w`` with
  ``Q = LPF / (Nn^a(z^-1) [N^u_n]*(z^-1))`` (stable zeros cancelled, the others by the
  all-pass reversal; ``Nn Q`` = delay x all-pass x LPF, unity DC gain) and ``LPF`` a
  Butterworth low-pass (paper: 3rd order, 30 Hz at 1 ms); the command becomes
  ``u = u_c + u_f - d`` (``d`` in velocity-command units).
- **Friction compensation** from the machine's friction model, its nonlinear part only
  (the viscous part is in the linear model the ZPETC inverts), at the setpoint velocity
  ``d`` samples ahead (when the command reaches the velocity loop):
  cascade: the Coulomb/Stribeck force ``F_n(v)`` mapped to a velocity command through
  the inverse of the velocity PI ``Kv (1 + 1/(Tn s))``, ``u_f = F_n / Kv * Tn s / (1 + Tn s)``
  (backward Euler at Te; the PI's integral then carries the steady part, so ``u_f`` never
  biases the velocity); ARX: the input-equivalent Coulomb command itself (the model
  subtracts it from the command). Both from :func:`oga.model.simulate.friction_command_m_s`
  minus its viscous term.

Rapid samples and axes outside the plane: P + feed-forward at the baseline gains; the
observer and the friction compensation stay active on the plane axes throughout.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import signal

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.controllers.base import ControllerRun, check_parameters, grid_tune, score
from oga.controllers.ccc import KF, KP, Prepared, add_coupling, baseline_gains, prepare
from oga.errors import OptionError, TuneError
from oga.model.linear import position_open_loop
from oga.model.machine import Machine
from oga.model.simulate import drive, friction_command_m_s

__all__ = [
    "NAME",
    "NEEDS_FIRMWARE",
    "PARAMETERS",
    "DEFAULTS",
    "TUNE_GRID",
    "Zpetc",
    "Observer",
    "transfer_function",
    "zpetc_design",
    "zpetc_reference",
    "observer_design",
    "run",
]

NAME = "zpetc-ccc-ddob"
NEEDS_FIRMWARE = True
PARAMETERS = (
    "kp_m_min_per_mm",
    "kf",
    "cc_gain_1_s",
    "cc_integral_1_s2",
    "q_cutoff_hz",
    "q_order",
    "accept_radius",
    "zpetc",
    "dob",
    "friction",
)

#: Design defaults and tuning grid (:mod:`oga.defaults`, where their reasons are given).
DEFAULTS = defaults.ZPETC_CCC_DDOB_DEFAULTS
TUNE_GRID = defaults.ZPETC_CCC_DDOB_TUNE_GRID

#: Relative size below which a transfer-function coefficient is rounding noise.
_COEF_EPS = 1e-9


def transfer_function(a, b, c, d) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator in powers of ``z^-1`` of a discrete SISO state-space.

    Coefficients below ``1e-9`` of the largest are set to zero (rounding of
    :func:`scipy.signal.ss2tf`); trailing zeros are dropped.

    Returns
    -------
    num, den : ndarray
        ``num[0] + num[1] z^-1 + ...`` over ``den[0] + den[1] z^-1 + ...`` (``den[0] = 1``).
    """
    num, den = signal.ss2tf(a, b, c, d)
    num = np.where(np.abs(num[0]) < _COEF_EPS * np.abs(num[0]).max(), 0.0, num[0])
    den = np.where(np.abs(den) < _COEF_EPS * np.abs(den).max(), 0.0, den)
    return np.trim_zeros(num, "b"), np.trim_zeros(den, "b")


def _split(num: np.ndarray, accept_radius: float):
    """``num(z^-1) = z^-delay * acc(z^-1) * unacc(z^-1)``: ``(delay, acc, unacc)``.

    ``acc`` is monic with the zeros of modulus below ``accept_radius``; ``unacc`` holds
    the other zeros and the gain.
    """
    delay = int(np.argmax(num != 0.0))
    core = num[delay:]
    zeros = np.roots(core)
    good = np.abs(zeros) < accept_radius
    acc = np.atleast_1d(np.real(np.poly(zeros[good])))  # np.poly of no roots: 1.0
    unacc = core[0] * np.atleast_1d(np.real(np.poly(zeros[~good])))
    return delay, acc, unacc


@dataclass(frozen=True)
class Zpetc:
    """A ZPETC feed-forward ``r_k = (fir / ba)(pd_{k+lead})`` (paper eq. 6).

    Attributes
    ----------
    fir : ndarray
        Numerator in ``z^-1`` (``A(z^-1) Bu(z)`` reversed, over ``Bu(1)^2``).
    ba : ndarray
        Monic acceptable-zero polynomial ``Ba(z^-1)`` (the recursive part).
    lead : int
        Preview in samples: ``d + deg Bu``.
    unacceptable_zeros : ndarray
        Zeros of ``Bu`` (complex).
    """

    fir: np.ndarray
    ba: np.ndarray
    lead: int
    unacceptable_zeros: np.ndarray


def zpetc_design(num: np.ndarray, den: np.ndarray, accept_radius: float) -> Zpetc:
    """The ZPETC of a closed loop ``T = num / den`` (powers of ``z^-1``).

    ``Zp = Bu(z) z^d A(z^-1) / (Bu(1)^2 Ba(z^-1))`` with ``z^d Bu(z) = z^(d+p) Bu_rev(z^-1)``,
    ``p = deg Bu``; ``Zp T = Bu(z) Bu(z^-1) / Bu(1)^2``: zero phase, unity DC gain.
    """
    delay, acc, unacc = _split(num, accept_radius)
    fir = np.convolve(unacc[::-1], den) / np.sum(unacc) ** 2
    return Zpetc(
        fir=fir, ba=acc, lead=delay + len(unacc) - 1,
        unacceptable_zeros=np.roots(unacc) if len(unacc) > 1 else np.zeros(0),
    )


def zpetc_reference(z: Zpetc, pd: np.ndarray) -> np.ndarray:
    """The modified reference ``r`` (N,) of setpoints ``pd`` (N,), from rest at ``pd[0]``."""
    n = len(pd)
    ahead = np.concatenate([pd[z.lead :], np.full(min(z.lead, n), pd[-1])])[:n]
    return pd[0] + signal.lfilter(z.fir, z.ba, ahead - pd[0])


@dataclass(frozen=True)
class Observer:
    """A digital disturbance observer ``d = Q (Dn p - Nn u)`` (paper Fig. 4, eq. 17).

    Attributes
    ----------
    dn, nn : ndarray
        Nominal model ``Pn = Nn / Dn`` (velocity command -> position), powers of ``z^-1``
        (``nn[0] = 0``: at least one sample of delay).
    qb, qa : ndarray
        ``Q = qb / qa``, powers of ``z^-1``.
    """

    dn: np.ndarray
    nn: np.ndarray
    qb: np.ndarray
    qa: np.ndarray


def observer_design(
    machine: Machine, axis: str, cutoff_hz: float, order: int, accept_radius: float
) -> Observer:
    """The DDOB of one axis on its linearised plant (paper eqs. 16-18).

    ``Q = LPF / (Nn^a(z^-1) [N^u_n]*(z^-1))``, ``[N^u_n]*`` the coefficient reversal of the
    unacceptable part (zeros mirrored into the unit disc, delay dropped); LPF a Butterworth
    low-pass of ``order`` and ``cutoff_hz`` at Te.

    Raises
    ------
    OptionError
        Cut-off not below the Nyquist frequency, or order < 1.
    """
    nyquist = 0.5 / machine.te
    if not (0.0 < cutoff_hz < nyquist) or int(order) != order or order < 1:
        raise OptionError(
            f"q_cutoff_hz must lie in (0, {nyquist}) Hz and q_order be an integer >= 1; "
            f"got {cutoff_hz}, {order}"
        )
    nn, dn = transfer_function(*position_open_loop(machine, axis, 1.0))
    _, acc, unacc = _split(nn, accept_radius)
    lpf_b, lpf_a = signal.butter(int(order), cutoff_hz, fs=1.0 / machine.te)
    qa = np.convolve(np.convolve(lpf_a, acc), unacc[::-1])
    return Observer(dn=dn, nn=nn, qb=lpf_b, qa=qa)


@njit(cache=True)
def _filter_step(b, a, x_hist, y_hist, x):
    """One sample of ``y = (b / a) x`` with histories ``[x_k, x_k-1, ..]``; returns ``y_k``."""
    for j in range(x_hist.shape[0] - 1, 0, -1):
        x_hist[j] = x_hist[j - 1]
        y_hist[j] = y_hist[j - 1]
    x_hist[0] = x
    acc = 0.0
    for j in range(b.shape[0]):
        acc += b[j] * x_hist[j]
    for j in range(1, a.shape[0]):
        acc -= a[j] * y_hist[j]
    y = acc / a[0]
    y_hist[0] = y
    return y


#: Offset of the plane axes' feed-forward factor in the gain array, after the CCC gains.
KF_PLANE = 4

#: The plane axes' design packed for :func:`_loop`: ``ref`` (N, 3) ZPETC references (m),
#: observer rows ``dn``, ``nn``, ``qb``, ``qa`` (3, W), ``v_fric`` (N, 3) the velocity the
#: friction compensation sees (m/s), ``viscous``, ``beta`` (3,).
Plane = namedtuple("Plane", ["ref", "dn", "nn", "qb", "qa", "v_fric", "viscous", "beta"])


@njit(cache=True)
def _loop(params, states, track, gains, plane, dob, fric, out_p, out_u):
    """All axes jointly: ZPETC reference, CCC, observer and friction compensation.

    ``track`` a :data:`oga.controllers.ccc.Track`, ``gains`` the CCC gain array with the
    plane's feed-forward factor at :data:`KF_PLANE`, ``plane`` a :data:`Plane`.
    """
    present, pd, vd, rapid, load = track.present, track.pd, track.vd, track.rapid, track.load
    e1, e2 = track.e1, track.e2
    kp, kf, kf_plane = gains[KP], gains[KF], gains[KF_PLANE]
    ref, dn, nn, qb, qa = plane.ref, plane.dn, plane.nn, plane.qb, plane.qa
    v_fric, viscous, beta = plane.v_fric, plane.viscous, plane.beta
    n = pd.shape[0]
    width = dn.shape[1]
    p_hist = np.zeros((3, width))
    for a in range(3):
        p_hist[a, :] = states[a, 0]  # at rest there forever before: w = 0 (Dn(1) = 0)
    u_hist = np.zeros((3, width))
    w_hist = np.zeros((3, width))
    d_hist = np.zeros((3, width))
    x_prev = np.zeros(3)
    u_f = np.zeros(3)
    u = np.zeros(3)
    integ = 0.0
    for k in range(n):
        for a in range(3):
            out_p[k, a] = states[a, 0] if present[a] else pd[k, a]
            if not present[a]:
                u[a] = 0.0
            elif rapid[k] or (a != e1 and a != e2):
                u[a] = kp * (pd[k, a] - out_p[k, a]) + kf * vd[k, a]
            else:
                u[a] = kp * (ref[k, a] - out_p[k, a]) + kf_plane * vd[k, a]
        integ = add_coupling(u, k, track, out_p, gains, integ)
        for a in (e1, e2):
            if not present[a]:
                continue
            if dob:
                # w_k = Dn p_k - Nn u_k; nn[0] = 0, so u_k (not known yet) does not enter
                for j in range(width - 1, 0, -1):
                    p_hist[a, j] = p_hist[a, j - 1]
                    u_hist[a, j] = u_hist[a, j - 1]
                p_hist[a, 0] = out_p[k, a]
                u_hist[a, 0] = 0.0
                w = 0.0
                for j in range(width):
                    w += dn[a, j] * p_hist[a, j] - nn[a, j] * u_hist[a, j]
                u[a] -= _filter_step(qb[a], qa[a], w_hist[a], d_hist[a], w)
                u_hist[a, 0] = u[a]
            if fric:
                # inside the plant the observer sees (the paper compensates friction in the
                # velocity loop): the observer then estimates only what friction is left
                v = v_fric[k, a]
                x = friction_command_m_s(params[a], v) - viscous[a] * v
                u_f[a] = beta[a] * (u_f[a] + x - x_prev[a])
                x_prev[a] = x
                u[a] += u_f[a]
        for a in range(3):
            if present[a]:
                drive(states[a], params[a], u[a], load[k, a])
            out_u[k, a] = u[a]


@dataclass(frozen=True, eq=False)
class _Design:
    """The offline design of the plane axes: the arrays of :func:`_loop`, the plane's
    feed-forward factor and the ZPETC preview per axis (samples)."""

    plane: Plane
    kf_plane: float
    lead: dict


def _design(prep: Prepared, machine: Machine, values: dict) -> _Design:
    """ZPETC references, observers and friction constants of the plane axes."""
    te = machine.te
    ref = prep.pd.copy()
    lead = {}
    observers = [None, None, None]
    viscous = np.zeros(3)
    beta = np.zeros(3)
    plane = [c for c in (prep.e1, prep.e2) if prep.present[c]]
    for c in plane:
        axis = AXES[c]
        if values["zpetc"]:
            a, b, cc, d = position_open_loop(machine, axis, prep.kp_si)
            closed = transfer_function(a - b @ cc, prep.kp_si * b, cc / prep.kp_si, d)
            z = zpetc_design(*closed, values["accept_radius"])
            ref[:, c] = zpetc_reference(z, prep.pd[:, c])
            lead[axis] = z.lead
        observers[c] = observer_design(
            machine, axis, values["q_cutoff_hz"], values["q_order"], values["accept_radius"]
        )
        cas = machine.axis(axis).cascade
        if cas is not None:  # viscous part (in the linear model) and the PI inverse
            viscous[c] = cas.viscous_n_s_m / cas.kv_n_s_m
            beta[c] = cas.tn_s / (cas.tn_s + te)
        else:  # ARX: the friction is already an input-equivalent command
            viscous[c] = machine.axis(axis).arx.viscous_ratio
            beta[c] = 1.0
    width = max(len(p) for c in plane for p in vars(observers[c]).values())
    rows = {name: np.zeros((3, width)) for name in ("dn", "nn", "qb", "qa")}
    rows["qa"][:, 0] = 1.0  # rows of axes without an observer: never used, kept finite
    for c in plane:
        for name, row in rows.items():
            coefs = getattr(observers[c], name)
            row[c] = 0.0
            row[c, : len(coefs)] = coefs
    n = prep.vd.shape[0]
    v_fric = prep.vd.copy()  # per axis, the setpoint velocity its dead time (whole) ahead
    for c, a in enumerate(("x", "y", "z")):
        if a in machine.axes:
            dead = round(machine.dead_time_samples_of(a))
            v_fric[:, c] = prep.vd[np.minimum(np.arange(n) + dead, n - 1), c]
    return _Design(
        plane=Plane(ref=ref, **rows, v_fric=np.ascontiguousarray(v_fric), viscous=viscous,
                    beta=beta),
        kf_plane=0.0 if values["zpetc"] else prep.kf,
        lead=lead,
    )


def _simulate(prep: Prepared, machine: Machine, values: dict):
    des = _design(prep, machine, values)
    n = prep.pd.shape[0]
    pos = np.empty((n, 3))
    u = np.empty((n, 3))
    gains = prep.gains(machine.te, values["cc_gain_1_s"], values["cc_integral_1_s2"],
                       des.kf_plane)
    _loop(prep.params, prep.states.copy(), prep.track, gains, des.plane, bool(values["dob"]),
          bool(values["friction"]), pos, u)
    return pos, u, des


def run(
    setpoints: Setpoints, machine: Machine, *, load_n=None, tune: bool = True, **parameters
) -> ControllerRun:
    """Simulate the integrated ZPETC + CCC + DDOB + friction controller (module docstring).

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples, period Te).
    machine : Machine
        The plant (cascade or ARX axes).
    load_n : array_like, shape (N, 3), optional
        External load force per sample and axis, N.
    tune : bool
        True: choose ``cc_gain_1_s`` and ``q_cutoff_hz`` on :data:`TUNE_GRID` (those given
        are held) with :func:`oga.controllers.base.grid_tune`; False: :data:`DEFAULTS`.
    **parameters
        Any of :data:`PARAMETERS`: ``kp_m_min_per_mm`` (the loop the ZPETC is designed on)
        and ``kf`` (rapids, other axes, and the plane axes when ``zpetc=False``), default
        the best fixed gains; ``cc_gain_1_s``, ``cc_integral_1_s2`` (CCC); ``q_cutoff_hz``,
        ``q_order`` (the Q low-pass); ``accept_radius`` (zeros cancelled by ZPETC and Q);
        ``zpetc``, ``dob``, ``friction`` (bool: each part on or off).

    Returns
    -------
    ControllerRun

    Raises
    ------
    OptionError
        Unknown parameter, bad design value, no feasible tuning or baseline.
    """
    check_parameters(NAME, parameters, PARAMETERS)
    kp, kf = baseline_gains(setpoints, machine, parameters)
    prep = prepare(setpoints, machine, load_n, kp, kf)
    given = {k: parameters[k] for k in DEFAULTS if k in parameters}
    if not 0.0 < given.get("accept_radius", DEFAULTS["accept_radius"]) <= 1.0:
        raise OptionError(f"accept_radius: must lie in (0, 1], got {given['accept_radius']}")
    notes = [
        "Kp and Kf are the best equal fixed gains of oga.search.ranges unless given; the ZPETC is "
        "designed on the closed loop with that Kp and replaces Kf on the plane axes.",
        "ZPETC needs preview of the setpoints (d + unacceptable zeros samples), computed "
        "offline over the whole toolpath.",
        "Observer and ZPETC use the linearised plant of oga.model.linear (friction -> viscous).",
        "Friction compensation: the nonlinear friction at the setpoint velocity d samples "
        "ahead; on a cascade axis its force through the inverse velocity PI "
        "(Tn s/(1 + Tn s))/Kv, on an ARX axis its input-equivalent command.",
        "Rapids and axes outside the contour plane: P + feed-forward; observer and friction "
        "compensation act on the plane axes throughout.",
    ]
    free = {k: v for k, v in TUNE_GRID.items() if k not in given}
    chosen = dict(given)
    if tune and free:
        try:
            best, _, feasible = grid_tune(
                lambda p: _simulate(prep, machine, {**DEFAULTS, **given, **p})[:2],
                setpoints, machine, free,
            )
        except TuneError:
            pos, u, _ = _simulate(prep, machine, {**DEFAULTS, **given})
            worst = score(setpoints, machine, pos, u).command_ratios.max(axis=0)
            raise TuneError(
                f"{NAME}: no combination of {free} keeps the velocity command within the "
                "axis limits (paper eq. 2): the ZPETC inverts the closed loop (its command "
                "follows the setpoints' snap and starts before the motion) and the friction "
                "compensation steps the command at reversals; worst (v, a, j) ratios with "
                f"the defaults: {np.round(worst, 2).tolist()}; run with tune=False to see it"
            ) from None
        chosen.update(best)
        notes.append(f"Tuned {sorted(free)} on this toolpath: {feasible} feasible combinations.")
    values = {**DEFAULTS, **chosen}
    pos, u, des = _simulate(prep, machine, values)
    used = {"kp_m_min_per_mm": kp, "kf": kf, **values}
    used["zpetc_preview_samples"] = des.lead
    return ControllerRun(
        name=NAME, pos=pos, u=u, needs_firmware=NEEDS_FIRMWARE, parameters=used,
        notes=tuple(notes),
    )
