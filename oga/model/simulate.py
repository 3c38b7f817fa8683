"""The compiled nonlinear axis simulation, one axis at a time: cascade or ARX axes.

An axis is one of two kinds (:class:`oga.model.machine.Axis`), told apart by a kind code
in its packed parameters, so every compiled function below takes either.

**Cascade** (:class:`oga.model.machine.Cascade`). Per axis and position-loop sample k (period Te):

1. measure ``p_k``;
2. velocity command ``u_k = Kp_k (pd_k - p_k) + Kf_k vd_k`` (Kp in 1/s);
3. ``u_k`` enters a dead-time line of ``d`` samples (the axis's own,
   :meth:`oga.model.machine.Machine.dead_time_samples_of`): during ``[k Te, (k+1) Te)`` the
   velocity loop receives ``u_{k-d}`` (zero before the start); a fractional dead time
   ``d = L - 1 + f`` (``0 < f < 1``) gives it ``f u_{k-L} + (1 - f) u_{k-L+1}`` (the
   linear-interpolation fractional delay: over the period, the mean of the command
   delayed by ``d Te``), the line then ``L`` long;
4. ``substeps`` sub-steps of ``h = Te / substeps``, each:

   - discrete velocity PI: ``e = u_{k-d} - v``, ``F_cmd = Kv (e + I / Tn)``
     limited to ``+-force_limit``; forward-Euler integral ``I += h e``, with
     conditional anti-windup (the integral is frozen while the command is limited,
     unless the error drives it back out of the limit);
   - the nonlinear friction part ``F_n = (Fc + (Fs - Fc) exp(-(v/vs)^2)) tanh(v/eps)``
     evaluated at the sub-step start;
   - ``F_cmd`` and ``F_n`` held over ``h`` (zero-order hold) and the linear part
     (position, velocity, force lag with the viscous friction B) propagated exactly
     with its matrix exponential (:func:`oga.model.linear.substep_matrices`).

With ``Fc = Fs = 0`` and a force limit never reached this is exactly the linear
lifted model of :mod:`oga.model.linear`. ``F_n`` takes ``tanh`` and ``exp`` only where their
float64 result is not exactly ``+-1`` or changes it (the sub-steps take both and choose
after, without branches: the same bits, :func:`_friction_flat`).

Speed without approximation: wherever it provably gives the same result as the
sub-steps (the force command stays inside the limit and ``F_n`` stays exactly
``+-Fc`` at every sub-step, checked by a bound linear in the state), a whole Te is
advanced with the lifted linear map of :func:`oga.model.linear.substep_sequence` (the
same model; the two paths differ by floating-point rounding only, about 1e-15
relative). On a contour this covers all but the samples near axis reversals.
Where an axis stands still its state soon stops changing to the last bit (a
floating-point fixed point of the period); :func:`run` and :func:`window` then skip
the periods whose command is also unchanged, which gives the same bits.

One opt-in approximation, a setting of the machine (``timing.friction_linear_below_m_s``
= ``V``, unset by default; the robust search's scenario plants set it): where an axis
(nearly) stands still its state converges without reaching a fixed point, and every period
takes the sub-steps. There the friction force is taken as its tangent at rest,
``F_n,j = c v_j`` with ``c = Fs / eps`` (held over each sub-step as ``F_n`` is), which makes
the sub-steps one linear map over Te (:func:`_linear_friction_map`), taken where a bound
linear in the state proves ``|v_j| < V`` at every sub-step start and the force command
inside the limit (:func:`_linear_guard`). For ``|v| <= V``,
``|F_n(v) - c v| <= Fs x^3 / 3 + (Fs - Fc) (V / vs)^2 x`` with ``x = V / eps``
(``|tanh x - x| <= |x|^3 / 3``, ``0 <= 1 - exp(-r2) <= r2``): with the robust default
``V = 1e-6`` m/s and ucp710's plants, below 1e-4 N against the friction ``c V`` of about
1 N there.

**ARX** (:class:`oga.model.machine.Arx`): an identified velocity loop, already discrete
over Te. At sample k, with the command ``u_k`` issued:

1. the velocity loop's input ``w_k = u_k - f(v_{k-1}) - g_load F_load`` with the
   input-equivalent friction ``f`` of :func:`friction_command_m_s` at the velocity
   of the last period and the load gain ``g_load`` (m/s per N);
2. ``v_k = sum_i num[i] w_{k-i} - sum_{i>=1} den[i] v_{k-i}``;
3. ``p_{k+1} = p_k + Te v_k``.

The dead time is folded into the numerator (``d`` leading zeros; a fractional one as
``z^-(L-1) (1 - f + f z^-1)``); with the
friction off this is exactly the linear model of :func:`oga.model.linear.arx_state_space`.

The compiled functions (:func:`rest_state`, :func:`step`, :func:`drive`, :func:`window`,
:func:`run`) take the packed parameters of :func:`axis_params` and a state vector of
:func:`state_size` entries, whose first entries are always the position p (m) and
the velocity v (m/s):

- cascade: ``[p, v, F, I, u_{k-1}, ..., u_{k-L}]`` (m, m/s, N, m, then m/s; ``L`` the
  dead time rounded up);
- ARX: ``[p, v_{k-1}, .., v_{k-nv}, w_{k-1}, .., w_{k-nw}]`` (m, then m/s), the
  velocities of the last ``nv = max(1, len(den) - 1)`` periods and the last
  ``nw = len(num) - 1 + d`` velocity-loop inputs.

All axes of a machine share one parameter length and one state length (the
longest; shorter ones are zero-padded), so they stack into arrays.

They are meant to be called from other compiled code (the gain search, the
comparison controllers) as well as through :func:`simulate`, which runs a machine's
moving cascade axes side by side in one loop (:func:`run_axes`: the same bits as
:func:`run` axis by axis, sooner).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from oga.errors import OptionError
from oga.model.linear import dead_line, substep_matrices, substep_sequence_of
from oga.model.machine import Machine

__all__ = [
    "axis_params",
    "state_size",
    "rest_state",
    "step",
    "drive",
    "friction_command_m_s",
    "friction_and_slope",
    "window",
    "run",
    "run_axes",
    "simulate_axis",
]

# Layout of the packed parameters (float64 vector). Header, both kinds:
_KIND = 0  # _CASCADE or _ARX
_DEAD = 1  # length of the dead-time line, samples (the dead time rounded up)
_NSTATE = 2  # length of the state vector
_CASCADE, _ARX = 0.0, 1.0
# cascade:
_AD = 3  # 3x3 row-major: x = [p, v, F] over one sub-step
_BD = 12  # 3x2 row-major: held inputs [F_cmd, F_n]
_KV = 18  # velocity PI gain, N s/m
_INV_TN = 19  # 1 / Tn, 1/s
_H = 20  # sub-step, s
_FLIM = 21  # force limit, N
_FC = 22  # Coulomb friction, N
_DFS = 23  # Fs - Fc, N
_INV_VS = 24  # 1 / Stribeck velocity, s/m
_INV_EPS = 25  # 1 / friction smoothing velocity, s/m
_R2_CUT = 26  # (v/vs)^2 above which the Stribeck term leaves F_n unchanged
_NSUB = 27  # sub-steps per Te
_LIFTED = 28  # 1.0: take the lifted step over Te where it is exact; 0.0: never
_LA = 29  # 4x4 row-major: z = [p, v, F, I] over Te, unsaturated, F_n held
_LB = 45  # 4x2 row-major: inputs [u, F_n] over Te
_WV = 53  # 5: bound of |v_j - v_0| over the sub-steps, on |[v, e, F, I, F_n]|
_WR = 58  # 5: bound of |F_cmd,j - F_cmd,0| over the sub-steps, same coordinates
_VFAST = 63  # |v| above which F_n is exactly +-Fc (-inf if F_n is identically 0)
_B = 64  # viscous friction, N s/m
_VLIN = 65  # timing.friction_linear_below_m_s: |v| below which F_n may be linear (0: never)
_NA = 66  # 4x4 row-major: z = [p, v, F, I] over Te, unsaturated, F_n = c v_j (c = Fs / eps)
_NB = 82  # 4x2 row-major: inputs [u, load] over Te, same
_WL = 90  # 5: bound of |v_j| over the sub-steps of that map, on |[v, e, F, I, load]|
_WF = 95  # 5: bound of |F_cmd,j| over them, same coordinates
_FRAC = 100  # fractional dead time: weight of the line's oldest command (0: a whole dead time)
_N_PARAMS = 101
# ARX (then den[1:] padded to nv, then the numerator past its first entry, nw):
_A_TE = 3  # period, s
_A_NV = 4  # number of past velocities in the state (nv)
_A_NW = 5  # number of past velocity-loop inputs in the state (nw)
_A_B0 = 6  # num[0] (after the dead time's leading zeros)
_A_FC = 7  # input-equivalent Coulomb friction, m/s
_A_VISC = 8  # input-equivalent viscous friction, (m/s)/(m/s)
_A_INV_EPS = 9  # 1 / friction smoothing velocity, s/m
_A_LOAD = 10  # load gain, (m/s)/N
_A_COEF = 11

# Layout of the cascade state vector.
_P, _V, _F, _I, _LINE = 0, 1, 2, 3, 4

#: |v / eps| above which tanh(v / eps) is exactly +-1.0 in float64.
_TANH_CUT = 20.0
#: (v / vs)^2 above which exp(-(v / vs)^2) is exactly 0.0 in float64.
_EXP_CUT = 746.0


def axis_params(machine: Machine, axis: str, lifted: bool = True) -> np.ndarray:
    """Packed float64 parameters of one axis for the compiled kernel.

    Parameters
    ----------
    machine : Machine
        Machine description.
    axis : str
        Axis name; MachineError if the machine lacks it.
    lifted : bool, optional
        Cascade axes only (an ARX axis is discrete over Te already). If True
        (default), the kernel advances a whole Te with the lifted linear
        map wherever that provably equals the sub-steps (no force limit reached and
        the friction force exactly constant at every sub-step: see
        :func:`_lifted_guard`); results then differ from pure sub-stepping by
        rounding only. False: sub-steps everywhere (the reference).

    Returns
    -------
    ndarray, shape (P,)
        Kind code, dead time and state size (:func:`state_size`), then for a
        cascade the sub-step matrices, PI, force limit, friction constants,
        sub-steps, lifted map, the bounds of its guard, the viscous friction, and the
        linear friction map with its guard (all zero where the machine leaves
        ``timing.friction_linear_below_m_s`` unset), the dead time's fraction: 101 entries;
        for an ARX axis Te,
        history lengths, friction, load gain and the coefficients (``11 + nv + nw``). Zero-padded to the longest over the
        machine's axes, so every axis of a machine has the same P.
    """
    return _params_of(machine.digest(), machine, axis, lifted).copy()


def _params_of(digest: str, machine: Machine, axis: str, lifted: bool = True) -> np.ndarray:
    """The memoised packed parameters of :func:`axis_params`, not copied (callers must not
    write them), by the machine's ``digest`` (once per :func:`simulate`, not per axis)."""
    key = (digest, axis, lifted)
    value = _PARAMS.get(key)  # one lookup: another thread may clear the memo meanwhile
    if value is None:
        if len(_PARAMS) >= 1024:  # a server sees many machines: keep the memo small (a robust
            # certificate alone asks for 3 axes of ~100 plants; an entry is ~0.5 kB)
            _PARAMS.clear()
        value = _PARAMS[key] = _pack(machine, axis, lifted)
    return value


#: Packed parameters per (machine digest, axis, lifted): the sub-step matrices cost a
#: matrix exponential per axis, and every stage of a run asks for them again.
_PARAMS: dict[tuple[str, str, bool], np.ndarray] = {}


def _pack(machine: Machine, axis: str, lifted: bool) -> np.ndarray:
    """The packed parameters of :func:`axis_params`, computed."""
    model = machine.axis(axis)
    n_params, n_state = _sizes(machine)
    out = np.zeros(n_params)
    if model.arx is not None:
        _arx_params(model.arx, machine, axis, out)
    else:
        _cascade_params(machine, axis, lifted, out)
    out[_NSTATE] = n_state
    return out


def _cascade_params(machine: Machine, axis: str, lifted: bool, out: np.ndarray) -> None:
    """Fill ``out`` with the packed parameters of a cascade axis (layout above)."""
    cas = machine.axis(axis).cascade
    h = machine.timing.te_s / machine.timing.substeps
    ad, bd = substep_matrices(cas, h)
    dfs = cas.static_n - cas.coulomb_n
    if dfs == 0.0:
        r2_cut = 0.0  # no Stribeck term at all
    elif cas.coulomb_n == 0.0:
        r2_cut = _EXP_CUT
    else:
        # dfs * exp(-r2) < Fc * 2^-54 (half an ulp of Fc): Fc + that term == Fc exactly
        r2_cut = min(_EXP_CUT, math.log(dfs / cas.coulomb_n) + 54.0 * math.log(2.0) + 1.0)
    if cas.coulomb_n == 0.0 and dfs == 0.0:
        v_fast = -math.inf  # no Coulomb/Stribeck friction: F_n == 0 at every velocity
    else:
        # beyond both cuts (1 % margin against rounding in the kernel's tests)
        v_fast = 1.01 * max(
            _TANH_CUT * cas.friction_smoothing_m_s, math.sqrt(r2_cut) * cas.stribeck_m_s
        )
    out[_KIND] = _CASCADE
    out[_AD : _AD + 9] = ad.ravel()
    out[_BD : _BD + 6] = bd.ravel()
    out[_KV] = cas.kv_n_s_m
    out[_INV_TN] = 1.0 / cas.tn_s
    out[_H] = h
    out[_FLIM] = cas.force_limit_n
    out[_FC] = cas.coulomb_n
    out[_DFS] = dfs
    out[_INV_VS] = 1.0 / cas.stribeck_m_s
    out[_INV_EPS] = 1.0 / cas.friction_smoothing_m_s
    out[_R2_CUT] = r2_cut
    out[_NSUB] = machine.timing.substeps
    out[_DEAD], out[_FRAC] = dead_line(machine, axis)
    out[_LIFTED] = 1.0 if lifted else 0.0
    a_j, b_j = substep_sequence_of(machine, axis)
    out[_LA : _LA + 16] = a_j[-1].ravel()
    out[_LB : _LB + 8] = b_j[-1].ravel()
    out[_WV : _WV + 5], out[_WR : _WR + 5] = _guard_bounds(a_j[:-1], b_j[:-1], cas)
    out[_VFAST] = v_fast
    out[_B] = cas.viscous_n_s_m
    v_lin = machine.timing.friction_linear_below_m_s
    if v_lin is not None:  # else 0: the linear friction map is never taken
        out[_VLIN] = v_lin
        a_n, b_n, wl, wf = _linear_friction_map(a_j[1], b_j[1], cas, machine.timing.substeps)
        out[_NA : _NA + 16] = a_n.ravel()
        out[_NB : _NB + 8] = b_n.ravel()
        out[_WL : _WL + 5], out[_WF : _WF + 5] = wl, wf


def _arx_numerator(machine: Machine, axis: str) -> np.ndarray:
    """The ARX numerator with the axis's dead time folded in (module doc)."""
    num = np.asarray(machine.axis(axis).arx.num, dtype=np.float64)
    line, frac = dead_line(machine, axis)
    if frac == 0.0:
        return np.concatenate([np.zeros(line), num])
    return np.concatenate([np.zeros(line - 1), np.convolve([1.0 - frac, frac], num)])


def _arx_params(arx, machine: Machine, axis: str, out: np.ndarray) -> None:
    """Fill ``out`` with the packed parameters of an ARX axis (layout ``_A_*``), the dead
    time folded into ``num``."""
    num = _arx_numerator(machine, axis)
    dead = dead_line(machine, axis)[0]
    den = np.asarray(arx.den)
    nv, nw = max(1, den.size - 1), num.size - 1
    out[_KIND] = _ARX
    out[_DEAD] = dead
    out[_A_TE] = machine.te
    out[_A_NV] = nv
    out[_A_NW] = nw
    out[_A_B0] = num[0]
    out[_A_FC] = arx.coulomb_m_s
    out[_A_VISC] = arx.viscous_ratio
    out[_A_INV_EPS] = 1.0 / arx.friction_smoothing_m_s
    out[_A_LOAD] = arx.load_m_s_per_n
    out[_A_COEF : _A_COEF + den.size - 1] = den[1:]
    out[_A_COEF + nv : _A_COEF + nv + nw] = num[1:]


def _guard_bounds(a_j, b_j, cas) -> tuple[np.ndarray, np.ndarray]:
    """Worst-case sub-step deviations of v and of the force command, linear in the state.

    At the starts ``j = 0 .. S-1`` of the sub-steps, ``v_j - v_0`` and
    ``F_cmd,j - F_cmd,0`` are linear in ``w = [v_0, e_0, F_0, I_0, F_n]``
    (``e_0 = u - v_0``; the position does not enter). Returns ``(wv, wr)``, each of
    shape (5,), with ``|v_j - v_0| <= wv . |w|`` and ``|F_cmd,j - F_cmd,0| <= wr . |w|``
    for every j (while unsaturated and with F_n held).
    """
    w_rows = _w_rows(a_j, b_j)
    dv = w_rows[:, 1, :] - w_rows[0, 1, :]
    di = w_rows[:, 3, :] - w_rows[0, 3, :]
    dr = cas.kv_n_s_m * (-dv + di / cas.tn_s)  # F_cmd = kv (u - v + I / Tn), u held
    return np.max(np.abs(dv), axis=0), np.max(np.abs(dr), axis=0)


def _w_rows(a_j, b_j) -> np.ndarray:
    """``z_j = A_j z_0 + B_j [u, x]`` (``x``: the second held input) as rows over
    ``w = [v_0, e_0, F_0, I_0, x]`` (``e_0 = u - v_0``; the position does not enter):
    shape (S, 4, 5)."""
    # rows over [p, v, F, I, u, x] -> columns over [v, e, F, I, x] (u = e + v)
    phi = np.concatenate([a_j, b_j], axis=2)  # (S, 4, 6)
    to_w = np.zeros((6, 5))
    to_w[1, 0] = to_w[4, 0] = 1.0  # v_0 enters directly and through u
    to_w[4, 1] = 1.0
    to_w[2, 2] = to_w[3, 3] = to_w[5, 4] = 1.0
    return phi @ to_w


def _linear_friction_map(m_sub, n_sub, cas, n_steps: int):
    """The sub-steps of one Te with the friction force taken as its tangent at rest.

    One sub-step is ``z_{j+1} = M z_j + N [u, F_n,j + load]`` (:func:`oga.model.linear.substep_sequence`,
    ``M = A_1``, ``N = B_1``; PI unsaturated); with ``F_n,j = c v_j``, ``c = Fs / eps`` (the
    slope of ``F_n`` at ``v = 0``), held over the sub-step as the kernel holds ``F_n``, it is
    ``z_{j+1} = (M + c N[:, 1] e_v^T) z_j + N [u, load]``, and ``n_steps`` of them one map.

    Returns
    -------
    a : ndarray, shape (4, 4)
        Over Te, on ``z = [p, v, F, I]``.
    b : ndarray, shape (4, 2)
        Inputs ``[u, load]`` (m/s, N) over Te.
    wl, wf : ndarray, shape (5,)
        ``|v_j| <= wl . |w|`` and ``|F_cmd,j| <= wf . |w|`` at every sub-step start
        ``j = 0 .. n_steps - 1``, ``w = [v, u - v, F, I, load]`` at the period's start.
    """
    mc = m_sub.copy()
    mc[:, 1] += cas.static_n / cas.friction_smoothing_m_s * n_sub[:, 1]
    a = np.empty((n_steps + 1, 4, 4))
    b = np.empty((n_steps + 1, 4, 2))
    a[0] = np.eye(4)
    b[0] = 0.0
    for j in range(n_steps):  # as :func:`oga.model.linear.substep_sequence` composes them
        a[j + 1] = mc @ a[j]
        b[j + 1] = mc @ b[j] + n_sub
    w_rows = _w_rows(a[:-1], b[:-1])
    u_row = np.array([1.0, 1.0, 0.0, 0.0, 0.0])  # u = v_0 + e_0, held
    f_cmd = cas.kv_n_s_m * (u_row - w_rows[:, 1, :] + w_rows[:, 3, :] / cas.tn_s)
    return (a[-1], b[-1], np.max(np.abs(w_rows[:, 1, :]), axis=0),
            np.max(np.abs(f_cmd), axis=0))


def _sizes(machine: Machine) -> tuple[int, int]:
    """Common lengths (parameters, state) of the machine's axes: the longest of each.

    Every axis of a machine is packed to these lengths (unused entries zero), so
    the axes' parameters and states stack into arrays for compiled multi-axis loops.
    """
    sizes = []
    for name, model in machine.axes.items():
        if model.arx is None:
            sizes.append((_N_PARAMS, 4 + dead_line(machine, name)[0]))
        else:
            nv, nw = max(1, len(model.arx.den) - 1), _arx_numerator(machine, name).size - 1
            sizes.append((_A_COEF + nv + nw, 1 + nv + nw))
    return max(p for p, _ in sizes), max(n for _, n in sizes)


def state_size(machine: Machine) -> int:
    """Length of the machine's axis state vectors: the longest natural length over its
    axes (cascade ``4 + L``, ARX ``1 + nv + nw``); a shorter axis leaves its tail zero."""
    return _sizes(machine)[1]


@njit(cache=True, nogil=True)
def rest_state(params: np.ndarray, p0: float) -> np.ndarray:
    """An axis at rest at position ``p0`` (m): every other entry (velocities, force,
    integral, command histories) zero.

    Returns
    -------
    ndarray, shape (state size,)
    """
    state = np.zeros(int(params[_NSTATE]))
    state[_P] = p0
    return state


@njit(cache=True, inline="always")
def _smooth_sign(x: float) -> float:
    """``tanh(x)``, exactly +-1 beyond ``_TANH_CUT``."""
    if x > _TANH_CUT:
        return 1.0
    if x < -_TANH_CUT:
        return -1.0
    # tanh(x) from one exp: half the latency of libm's tanh, error < 3e-16
    t = math.exp(-2.0 * abs(x))
    return math.copysign((1.0 - t) / (1.0 + t), x)


@njit(cache=True, nogil=True)
def friction_command_m_s(params: np.ndarray, v: float) -> float:
    """The machine's friction at velocity ``v`` as an input-equivalent velocity command.

    The velocity command (m/s) an ideal friction compensator adds to cancel the
    axis friction; the kernel subtracts exactly this from an ARX axis's command.

    - ARX: ``coulomb_m_s tanh(v / eps) + viscous_ratio v``;
    - cascade: the whole friction force over the velocity PI's proportional gain,
      ``(F_n(v) + B v) / Kv`` (the velocity error that makes the PI's proportional
      part deliver it; the kernel applies the force itself).

    Parameters
    ----------
    params : ndarray
        From :func:`axis_params` (either kind).
    v : float
        Axis velocity, m/s.

    Returns
    -------
    float
        m/s, the sign of ``v``.
    """
    if params[_KIND] == _ARX:
        return params[_A_FC] * _smooth_sign(v * params[_A_INV_EPS]) + params[_A_VISC] * v
    return (friction_nonlinear(params, v) + params[_B] * v) / params[_KV]


@njit(cache=True, nogil=True)
def friction_nonlinear(params: np.ndarray, v: float) -> float:
    """Coulomb + Stribeck friction force (N) at velocity ``v`` (m/s) of a cascade axis,
    viscous part excluded."""
    return friction_and_slope(params, v)[0]


@njit(cache=True, inline="always")
def _smooth_sign_and_slope(x: float) -> tuple[float, float]:
    """:func:`_smooth_sign` at ``x`` and its derivative (zero where it is exactly +-1)."""
    s = _smooth_sign(x)
    if x > _TANH_CUT or x < -_TANH_CUT:
        return s, 0.0
    return s, 1.0 - s * s


@njit(cache=True, inline="always")
def friction_and_slope(params: np.ndarray, v: float) -> tuple[float, float]:
    """:func:`friction_nonlinear` (N) and its slope ``dF_n/dv`` (N s/m) at ``v`` (m/s), from
    one set of exponentials (where only the force is used, the slope's few operations are
    compiled away)."""
    inv_eps = params[_INV_EPS]
    s, ds = _smooth_sign_and_slope(v * inv_eps)
    ds *= inv_eps
    r = v * params[_INV_VS]
    r2 = r * r
    if r2 > params[_R2_CUT]:
        return params[_FC] * s, params[_FC] * ds
    ex = math.exp(-r2)
    g = params[_FC] + params[_DFS] * ex
    return g * s, g * ds - 2.0 * r * params[_INV_VS] * params[_DFS] * ex * s


@njit(cache=True, inline="always")
def _friction_flat(params: np.ndarray, v: float) -> float:
    """:func:`friction_nonlinear` to the last bit, without branches: both exponentials always
    taken (their arguments clamped where the value is then not used), the cut values chosen
    after. In a chain of sub-steps whose velocity crosses the cuts unpredictably, this keeps
    the processor from discarding the work of the other axes at each mispredicted branch.

    Where :func:`friction_nonlinear` takes an exponential it takes the same one here (the
    clamps leave the arguments it takes, NaN included); where it returns a cut value (tanh
    exactly +-1, no Stribeck term) the same value is chosen here. It costs the exponentials
    it skips: for the sub-steps only (the periods' first friction decides the path).
    """
    x = v * params[_INV_EPS]
    arg = -2.0 * abs(x)  # as :func:`_smooth_sign`
    t = math.exp(arg if not arg < -2.0 * _TANH_CUT - 8.0 else -2.0 * _TANH_CUT - 8.0)
    s = math.copysign((1.0 - t) / (1.0 + t), x)
    s = 1.0 if x > _TANH_CUT else (-1.0 if x < -_TANH_CUT else s)
    r = v * params[_INV_VS]
    r2 = r * r
    ex = math.exp(-r2 if not -r2 < -_EXP_CUT else -_EXP_CUT)
    g = params[_FC] + params[_DFS] * ex
    return params[_FC] * s if r2 > params[_R2_CUT] else g * s


@njit(cache=True, inline="always")
def _pi_coefs(params):
    """The velocity PI of a cascade axis: ``(Kv (N s/m), 1/Tn (1/s), sub-step (s), force
    limit (N))``."""
    return params[_KV], params[_INV_TN], params[_H], params[_FLIM]


@njit(cache=True, inline="always")
def _pi_substep(ud, v, i, pi):
    """One sub-step of the velocity PI with anti-windup (``pi`` from :func:`_pi_coefs`):
    ``(F_cmd, I after, linear, integrating)``.

    ``linear``: the force command is not limited; ``integrating``: the integral
    moved (it is frozen while the command is limited, unless the error drives it
    back out of the limit).
    """
    kv, inv_tn, h, flim = pi
    e = ud - v
    raw = kv * (e + i * inv_tn)
    if raw > flim:
        fc = flim
    elif raw < -flim:
        fc = -flim
    else:
        fc = raw
    integrating = fc == raw or e * raw < 0.0
    if integrating:
        i += h * e
    return fc, i, fc == raw, integrating


@njit(cache=True, nogil=True)
def _substeps(params, p, v, f, i, ud, load, fn):
    """The sub-steps of one Te from ``(p, v, F, I)`` with velocity command ``ud`` and load held;
    ``fn`` is ``F_n + load`` at ``v`` (the first sub-step's, already known to the caller)."""
    c = _substep_coefs(params)
    pi = _pi_coefs(params)
    for j in range(int(params[_NSUB])):
        if j > 0:
            fn = _friction_flat(params, v) + load
        fc, i, _lin, _integrating = _pi_substep(ud, v, i, pi)
        p, v, f = _mechanics(c, p, v, f, fc, fn)
    return p, v, f, i


@njit(cache=True, inline="always")
def _substep_coefs(params):
    """The nonzero entries of the sub-step matrices: ``(a01, a02, a11, a12, a22, b00, b01,
    b10, b11, b20)``. In x = [p, v, F] the position integrates, the force depends on
    neither p nor v, and the friction input does not reach F (structural zeros of
    :func:`oga.model.linear.substep_matrices`)."""
    return (params[_AD + 1], params[_AD + 2], params[_AD + 4], params[_AD + 5], params[_AD + 8],
            params[_BD], params[_BD + 1], params[_BD + 2], params[_BD + 3], params[_BD + 4])


@njit(cache=True, inline="always")
def _mechanics(c, p, v, f, fc, fn):
    """The linear mechanics over one sub-step, force command ``fc`` and friction ``fn`` held;
    ``c`` from :func:`_substep_coefs`. Linear: applied to derivatives it gives theirs."""
    return (
        p + c[0] * v + c[1] * f + c[5] * fc + c[6] * fn,
        c[2] * v + c[3] * f + c[7] * fc + c[8] * fn,
        c[4] * f + c[9] * fc,
    )


@njit(cache=True, nogil=True)
def _lifted_guard(params, v, f, i, ud, fn):
    """True when the lifted map over Te equals the sub-steps from this state.

    With ``w = [v, u - v, F, I, F_n]`` at the start of the period, every sub-step
    start satisfies ``|v_j| >= |v| - wv.|w|`` and ``|F_cmd,j| <= |F_cmd,0| + wr.|w|``
    (:func:`_guard_bounds`). If the first stays above the friction cuts (``v_j`` keeps
    its sign and ``F_n`` is exactly ``fn`` throughout) and the second below the force
    limit (the PI is linear throughout), the sub-steps are the linear map.
    """
    e = ud - v
    av, ae, af, ai, an = abs(v), abs(e), abs(f), abs(i), abs(fn)
    w = params[_WV : _WV + 5]
    if av - (w[0] * av + w[1] * ae + w[2] * af + w[3] * ai + w[4] * an) <= params[_VFAST]:
        return False
    w = params[_WR : _WR + 5]
    dr = w[0] * av + w[1] * ae + w[2] * af + w[3] * ai + w[4] * an
    return abs(params[_KV] * (e + i * params[_INV_TN])) + dr < params[_FLIM] * (1.0 - 1e-9)


@njit(cache=True, inline="always")
def _linear_guard(params, v, f, i, ud, load):
    """True when the linear friction map over Te (:func:`_linear`) may replace the sub-steps.

    Only where the axis sets ``timing.friction_linear_below_m_s`` (``V``, packed as
    ``_VLIN``): with ``w = [v, u - v, F, I, load]`` at the period's start, that map's
    sub-step starts satisfy ``|v_j| <= wl.|w|`` and ``|F_cmd,j| <= wf.|w|``
    (:func:`_linear_friction_map`). If the first stays below ``V`` (the friction is its
    tangent at rest within the bound of :class:`oga.model.machine.Timing` at every sub-step) and
    the second below the force limit (the PI is linear throughout), the map is the sub-steps
    with that friction.
    """
    if params[_VLIN] == 0.0:
        return False
    e = ud - v
    av, ae, af, ai, al = abs(v), abs(e), abs(f), abs(i), abs(load)
    w = params[_WL : _WL + 5]
    if not w[0] * av + w[1] * ae + w[2] * af + w[3] * ai + w[4] * al < params[_VLIN]:
        return False  # NaN included
    w = params[_WF : _WF + 5]
    dr = w[0] * av + w[1] * ae + w[2] * af + w[3] * ai + w[4] * al
    return dr < params[_FLIM] * (1.0 - 1e-9)


@njit(cache=True, inline="always")
def _linear(params, p, v, f, i, ud, load):
    """The linear friction map over one Te (valid where :func:`_linear_guard` holds): the
    sub-steps with ``F_n`` its tangent at rest. Linear: applied to derivatives (with that of
    ``load`` zero) it gives theirs."""
    return _affine(params, _NA, p, v, f, i, ud, load)


@njit(cache=True, nogil=True)
def _advance(params, p, v, f, i, ud, load):
    """One Te from ``(p, v, F, I)`` with velocity command ``ud`` held: ``(p, v, F, I)``.

    ``load`` (N) is an external force held over Te, opposing positive motion like
    friction (it enters where the friction force does).
    """
    if v == 0.0 and f == 0.0 and i == 0.0 and ud == 0.0 and load == 0.0:
        return p, v, f, i  # at rest and not driven: the sub-steps change nothing
    if _linear_guard(params, v, f, i, ud, load):
        return _linear(params, p, v, f, i, ud, load)
    fn = friction_nonlinear(params, v) + load
    if params[_LIFTED] != 0.0 and _lifted_guard(params, v, f, i, ud, fn):
        return _lifted(params, p, v, f, i, ud, fn)
    return _substeps(params, p, v, f, i, ud, load, fn)


@njit(cache=True, inline="always")
def _lifted(params, p, v, f, i, ud, fn):
    """The lifted linear map over one Te (valid where :func:`_lifted_guard` holds). Linear:
    applied to derivatives (with that of ``fn`` zero) it gives theirs."""
    return _affine(params, _LA, p, v, f, i, ud, fn)


@njit(cache=True, inline="always")
def _affine(params, at, p, v, f, i, ud, x):
    """``z' = A z + B [ud, x]`` over Te, ``A`` (4x4, its position column the identity's) at
    ``params[at:]`` and ``B`` (4x2) right after it (row-major both)."""
    a = params[at : at + 16]
    b = params[at + 16 : at + 24]
    return (
        p + a[1] * v + a[2] * f + a[3] * i + b[0] * ud + b[1] * x,
        a[5] * v + a[6] * f + a[7] * i + b[2] * ud + b[3] * x,
        a[9] * v + a[10] * f + a[11] * i + b[4] * ud + b[5] * x,
        a[13] * v + a[14] * f + a[15] * i + b[6] * ud + b[7] * x,
    )


@njit(cache=True, inline="always")
def _delayed(params, oldest, newer):
    """The command the velocity loop receives over a period: the dead-time line's
    ``oldest`` (``u_{k-L}``), or for a fractional dead time ``f oldest + (1 - f) newer``
    with ``newer`` = ``u_{k-L+1}`` (module doc)."""
    frac = params[_FRAC]
    if frac == 0.0:
        return oldest
    return frac * oldest + (1.0 - frac) * newer


@njit(cache=True, nogil=True)
def step(
    state: np.ndarray, params: np.ndarray, pd: float, vd: float, kp_si: float, kf: float
) -> float:
    """Advance one axis by one Te, in place, from sample k to k+1.

    Parameters
    ----------
    state : ndarray, shape (state size,)
        Axis state at sample k; overwritten with the state at k+1.
    params : ndarray
        From :func:`axis_params`.
    pd, vd : float
        Setpoint position (m) and velocity (m/s) of sample k.
    kp_si, kf : float
        Position gain (1/s) and velocity feed-forward factor of sample k.

    Returns
    -------
    float
        The velocity command ``u_k`` (m/s).
    """
    u = kp_si * (pd - state[_P]) + kf * vd
    drive(state, params, u, 0.0)
    return u


@njit(cache=True, nogil=True)
def drive(state: np.ndarray, params: np.ndarray, u: float, load_n: float) -> None:
    """Issue the velocity command ``u`` at sample k and advance the axis to k+1, in place.

    The command enters the dead-time line; the velocity loop receives the command
    issued ``d`` samples ago. Any position control law (not only ``Kp, Kf``) drives
    the plant through this function, so all laws see the same plant, dead time and
    inner loops.

    Parameters
    ----------
    state : ndarray, shape (state size,)
        Axis state at sample k (the measured position is ``state[0]``, m, the
        velocity ``state[1]``, m/s); overwritten with the state at k+1.
    params : ndarray
        From :func:`axis_params`.
    u : float
        Velocity command issued at sample k, m/s.
    load_n : float
        External load force held over the period, N (0 for none); it acts like
        friction: a positive load opposes positive motion. Cascade: a force on the
        mechanics; ARX: the input-equivalent velocity ``load_m_s_per_n * load_n``
        subtracted from the command.
    """
    if params[_KIND] == _ARX:
        _arx_drive(state, params, u, load_n)
        return
    dead = int(params[_DEAD])
    if dead == 0:
        ud = u
    else:
        ud = _delayed(params, state[_LINE + dead - 1], state[_LINE + dead - 2] if dead > 1 else u)
        for j in range(dead - 1, 0, -1):
            state[_LINE + j] = state[_LINE + j - 1]
        state[_LINE] = u
    p, v, f, i = _advance(params, state[_P], state[_V], state[_F], state[_I], ud, load_n)
    state[_P] = p
    state[_V] = v
    state[_F] = f
    state[_I] = i


@njit(cache=True, nogil=True)
def _arx_drive(state, params, u, load_n):
    """:func:`drive` for an ARX axis (state and parameter layouts in the module docstring)."""
    nv = int(params[_A_NV])
    nw = int(params[_A_NW])
    w = u - friction_command_m_s(params, state[1]) - params[_A_LOAD] * load_n
    v = params[_A_B0] * w
    for i in range(nv):
        v -= params[_A_COEF + i] * state[1 + i]
    for i in range(nw):
        v += params[_A_COEF + nv + i] * state[1 + nv + i]
    for j in range(nv - 1, 0, -1):
        state[1 + j] = state[j]
    state[1] = v
    if nw > 0:
        for j in range(nw - 1, 0, -1):
            state[1 + nv + j] = state[nv + j]
        state[1 + nv] = w
    state[0] += params[_A_TE] * v


@njit(cache=True, inline="always")
def _same(a: float, b: float) -> bool:
    """``a`` and ``b`` are the same float64 (signed zeros told apart, NaN never the same)."""
    return a == b and (a != 0.0 or math.copysign(1.0, a) == math.copysign(1.0, b))


@njit(cache=True, inline="always")
def _period(params, p, v, f, i, ud, still, ud_still):
    """:func:`_advance` (no load) of one period, skipped where it provably changes nothing.

    ``still`` says the last period left ``(p, v, F, I)`` exactly as it was (a
    floating-point fixed point of :func:`_advance`) under the command ``ud_still``: under
    the same command this period does too. Returns ``(p, v, F, I, still, ud_still)`` for
    the next period (start a run with ``still`` False).
    """
    if still and _same(ud, ud_still):
        return p, v, f, i, True, ud
    p1, v1, f1, i1 = _advance(params, p, v, f, i, ud, 0.0)
    still = _same(p1, p) and _same(v1, v) and _same(f1, f) and _same(i1, i)
    return p1, v1, f1, i1, still, ud


@njit(cache=True, inline="always")
def _command(pd, vd, k, p, kp_si, kf):
    """``Kp (pd_k - p) + Kf vd_k``; past the last sample its position is held, velocity 0."""
    last = pd.shape[0] - 1
    if k <= last:
        return kp_si * (pd[k] - p) + kf * vd[k]
    return kp_si * (pd[last] - p)


@njit(cache=True, nogil=True)
def window(
    state: np.ndarray,
    params: np.ndarray,
    pd: np.ndarray,
    vd: np.ndarray,
    k0: int,
    n: int,
    kp_si: float,
    kf: float,
    out_p: np.ndarray,
) -> None:
    """Predict ``n`` samples from a state with constant gains, leaving ``state`` untouched.

    Cascade: allocates nothing (the state is carried in local variables and the
    commands still in the dead-time line are recomputed from ``out_p``). ARX:
    works on one copy of the state.

    Parameters
    ----------
    state : ndarray, shape (state size,)
        Axis state at sample ``k0`` (not modified).
    params : ndarray
        From :func:`axis_params`.
    pd, vd : ndarray, shape (N,)
        Setpoint positions (m) and velocities (m/s) of the whole toolpath; past
        its end the last position is held with zero velocity.
    k0, n : int
        First sample and number of samples to simulate.
    kp_si, kf : float
        Candidate gains (1/s and factor), held over the window.
    out_p : ndarray, shape (>= n,)
        Receives the positions ``p_{k0+1} .. p_{k0+n}`` (m) in ``out_p[0:n]``.
    """
    if params[_KIND] == _ARX:
        s = state.copy()
        for j in range(n):
            _arx_drive(s, params, _command(pd, vd, k0 + j, s[_P], kp_si, kf), 0.0)
            out_p[j] = s[_P]
        return
    dead = int(params[_DEAD])
    p0 = state[_P]
    p, v, f, i = p0, state[_V], state[_F], state[_I]
    still, ud_still = False, 0.0  # see :func:`_period`
    for j in range(n):
        m = j - dead  # the command applied now is u_{k0+m}
        if m < 0:
            ud = state[_LINE + dead - 1 - j]
        else:
            ud = _command(pd, vd, k0 + m, p0 if m == 0 else out_p[m - 1], kp_si, kf)
        if params[_FRAC] != 0.0:  # and u_{k0+m+1} (m + 1 <= j: issued already)
            if m + 1 < 0:
                newer = state[_LINE + dead - 2 - j]
            else:
                newer = _command(pd, vd, k0 + m + 1, p0 if m + 1 == 0 else out_p[m], kp_si, kf)
            ud = _delayed(params, ud, newer)
        p, v, f, i, still, ud_still = _period(params, p, v, f, i, ud, still, ud_still)
        out_p[j] = p


@njit(cache=True, nogil=True)
def run(
    state: np.ndarray,
    params: np.ndarray,
    pd: np.ndarray,
    vd: np.ndarray,
    kp_si: np.ndarray,
    kf: np.ndarray,
    out_p: np.ndarray,
    out_u: np.ndarray,
) -> None:
    """Simulate N samples with per-sample gains, advancing ``state`` in place.

    Parameters
    ----------
    state : ndarray, shape (state size,)
        Axis state at sample 0; on return the state at sample N.
    params : ndarray
        From :func:`axis_params`.
    pd, vd, kp_si, kf : ndarray, shape (N,)
        Setpoints (m, m/s) and gains (1/s, factor) per sample.
    out_p, out_u : ndarray, shape (N,)
        Receive the measured positions ``p_k`` (m) and the commands ``u_k`` (m/s).
    """
    n = pd.shape[0]
    if params[_KIND] == _ARX:
        for k in range(n):
            out_p[k] = state[_P]
            out_u[k] = kp_si[k] * (pd[k] - state[_P]) + kf[k] * vd[k]
            _arx_drive(state, params, out_u[k], 0.0)
        return
    dead = int(params[_DEAD])
    p, v, f, i = state[_P], state[_V], state[_F], state[_I]
    still, ud_still = False, 0.0  # see :func:`_period`
    for k in range(n):
        out_p[k] = p
        u = kp_si[k] * (pd[k] - p) + kf[k] * vd[k]
        out_u[k] = u
        m = k - dead  # the command applied now is u_m
        ud = out_u[m] if m >= 0 else state[_LINE + dead - 1 - k]
        if params[_FRAC] != 0.0:
            ud = _delayed(params, ud, out_u[m + 1] if m + 1 >= 0 else state[_LINE + dead - 2 - k])
        p, v, f, i, still, ud_still = _period(params, p, v, f, i, ud, still, ud_still)
    _store_cascade(state, dead, out_u, n, p, v, f, i)


@njit(cache=True, nogil=True)
def run_axes(states, params, axes, pd, vd, kp_si, kf, out_p, out_u):
    """:func:`run` of several cascade axes at once: per axis the same operations in the same
    order (the same bits), the axes' sub-steps interleaved.

    An axis's sub-steps are one chain of dependent exponentials and divisions (each sub-step's
    friction needs the velocity the last one left); advancing the axes' chains side by side
    lets the processor overlap them, where one axis after the other waits on each in turn.

    Parameters
    ----------
    states : ndarray, shape (3, state size)
        Row ``a``: the state of axis ``a`` at sample 0; on return at sample N, for the axes
        run (the other rows untouched).
    params : ndarray, shape (3, P)
        Row ``a``: :func:`axis_params` of axis ``a``, a cascade axis for every ``a`` run.
    axes : ndarray of int64, shape (A,)
        The axes (columns) to run, at most 3, each once.
    pd, vd, kp_si, kf : ndarray, shape (N, 3)
        Setpoints (m, m/s) and gains (1/s, factor) per sample and axis.
    out_p, out_u : ndarray, shape (N, 3)
        Receive, in the columns of the axes run, the positions ``p_k`` (m) and the commands
        ``u_k`` (m/s).
    """
    n = pd.shape[0]
    na = axes.shape[0]
    if na == 0:
        return
    now, was = np.empty((4, 3)), np.empty((4, 3))  # rows p, v, F, I; column q: axis axes[q]
    now[:, :na] = states[axes, _P:_I + 1].T
    ud, fn, ud_still = np.empty(3), np.empty(3), np.zeros(3)
    still = np.zeros(3, dtype=np.bool_)  # see :func:`_period`
    sub = np.empty(3, dtype=np.int64)  # the axes taking the sub-steps this period
    nsub = int(params[axes[0], _NSUB])  # the machine's timing: every axis the same
    for k in range(n):
        ns = 0
        for q in range(na):  # :func:`run`'s sample k of axis a, up to :func:`_substeps`
            a = axes[q]
            prm = params[a]
            p, v, f, i = now[0, q], now[1, q], now[2, q], now[3, q]
            out_p[k, a] = p
            out_u[k, a] = kp_si[k, a] * (pd[k, a] - p) + kf[k, a] * vd[k, a]
            m = k - int(prm[_DEAD])  # the command applied now is u_m
            udq = out_u[m, a] if m >= 0 else states[a, _LINE - 1 - m]
            if prm[_FRAC] != 0.0:
                udq = _delayed(prm, udq, out_u[m + 1, a] if m + 1 >= 0
                               else states[a, _LINE - 2 - m])
            if still[q] and _same(udq, ud_still[q]):
                continue
            ud_still[q] = udq
            if v == 0.0 and f == 0.0 and i == 0.0 and udq == 0.0:  # at rest, not driven
                still[q] = _same(p, p)
                continue
            linear = _linear_guard(prm, v, f, i, udq, 0.0)  # as :func:`_advance`, load 0
            fnq = 0.0 if linear else friction_nonlinear(prm, v) + 0.0
            if linear or (prm[_LIFTED] != 0.0 and _lifted_guard(prm, v, f, i, udq, fnq)):
                p1, v1, f1, i1 = (_linear(prm, p, v, f, i, udq, 0.0) if linear
                                  else _lifted(prm, p, v, f, i, udq, fnq))
                still[q] = _same(p1, p) and _same(v1, v) and _same(f1, f) and _same(i1, i)
                now[0, q], now[1, q], now[2, q], now[3, q] = p1, v1, f1, i1
                continue
            was[0, q], was[1, q], was[2, q], was[3, q] = p, v, f, i
            ud[q], fn[q] = udq, fnq
            sub[ns] = q
            ns += 1
        for j in range(nsub if ns else 0):  # :func:`_substeps`, the axes side by side
            for r in range(ns):
                q = sub[r]
                prm = params[axes[q]]
                v = now[1, q]
                if j > 0:
                    fn[q] = _friction_flat(prm, v) + 0.0
                fc, now[3, q], _lin, _integrating = _pi_substep(ud[q], v, now[3, q],
                                                                _pi_coefs(prm))
                now[0, q], now[1, q], now[2, q] = _mechanics(_substep_coefs(prm), now[0, q], v,
                                                             now[2, q], fc, fn[q])
        for r in range(ns):
            q = sub[r]
            still[q] = (_same(now[0, q], was[0, q]) and _same(now[1, q], was[1, q])
                        and _same(now[2, q], was[2, q]) and _same(now[3, q], was[3, q]))
    _store_axes(states, params, axes, out_u, n, now)


@njit(cache=True, inline="always")
def _store_axes(states, params, axes, out_u, n, now):
    """:func:`_store_cascade` of the axes ``axes[q]``, their state ``now[:, q]`` (rows p,
    v, F, I), at the end of :func:`run_axes`."""
    for q in range(axes.shape[0]):
        a = axes[q]
        _store_cascade(states[a], int(params[a, _DEAD]), out_u[:, a], n, now[0, q], now[1, q],
                       now[2, q], now[3, q])


@njit(cache=True, inline="always")
def _store_cascade(state, dead, out_u, n, p, v, f, i):
    """Write a cascade axis's state after a run of ``n`` samples (commands ``out_u[:n]``) into
    ``state`` (which holds the state at its start): ``(p, v, F, I)`` and the dead-time line
    ``u_{n-1}, .., u_{n-d}`` (older entries from the line itself when ``n < d``)."""
    for j in range(dead - 1, -1, -1):  # downwards: an old entry is read before it is overwritten
        state[_LINE + j] = out_u[n - 1 - j] if n - 1 - j >= 0 else state[_LINE + j - n]
    state[_P], state[_V], state[_F], state[_I] = p, v, f, i


def simulate_axis(
    params: np.ndarray, p0: float, pd, vd, kp_si, kf
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate one axis from rest at ``p0`` (m).

    Parameters
    ----------
    params : ndarray
        From :func:`axis_params`.
    p0 : float
        Initial position, m.
    pd, vd : array_like, shape (N,)
        Setpoint positions (m) and velocities (m/s).
    kp_si, kf : float or array_like, shape (N,)
        Gains per sample (1/s, factor), or one value for all.

    Returns
    -------
    p_act, u : ndarray, shape (N,)
        Measured positions (m) and velocity commands (m/s).

    Raises
    ------
    OptionError
        An input neither one number nor N of them.
    """
    n = np.shape(pd)[0]
    # writeable C-contiguous float64 arrays: one compiled signature of run
    pd, vd = _vector(pd, "pd", n), _vector(vd, "vd", n)
    kp, kf_a = _vector(kp_si, "kp_si", n), _vector(kf, "kf", n)
    p_act = np.empty(n)
    u = np.empty(n)
    run(rest_state(params, float(p0)), params, pd, vd, kp, kf_a, p_act, u)
    return p_act, u


def _vector(x, name: str, n: int) -> np.ndarray:
    """``x`` (scalar or shape (n,)) as a writeable C-contiguous float64 array of shape (n,):
    ``x`` itself if it is one (the kernel reads it only), else a new one."""
    if (isinstance(x, np.ndarray) and x.dtype == np.float64 and x.shape == (n,)
            and x.flags.c_contiguous and x.flags.writeable):
        return x
    out = np.empty(n)
    try:
        out[:] = x
    except (TypeError, ValueError):
        raise OptionError(f"{name}: expected a number or numbers of shape ({n},)") from None
    return out
