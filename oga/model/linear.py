"""The linear axis: exact discrete models of the axis under the position loop.

Used by the simulation kernel (its sub-step matrices and its lifted step) and by
the stability analysis (the linearised loop lifted over Te). An axis is either a
cascade (below) or an identified ARX velocity loop (:func:`arx_state_space`).

The continuous mechanics of one axis (:class:`oga.model.machine.Cascade`), with state ``x = [p, v, F]``
(position m, velocity m/s, actual force N) and inputs ``[F_cmd, F_n]`` (force
command N, nonlinear friction force N)::

    dp/dt = v
    dv/dt = (F - B v - F_n) / m
    dF/dt = (F_cmd - F) / tau

are discretised exactly over one sub-step ``h = Te / substeps`` with both inputs
held (zero-order hold): :func:`substep_matrices`. The simulation kernel
(:mod:`oga.model.simulate`) propagates exactly these matrices, so its linear part is exact.

The discrete velocity PI of every sub-step ``j`` (the same in the kernel) is::

    e_j     = u - v_j
    F_cmd,j = Kv * (e_j + I_j / Tn)       (limited to +-force_limit in the kernel)
    I_j+1   = I_j + h * e_j               (forward-Euler integral)

Without force limit and with ``F_n`` held, one sub-step is linear in
``z = [p, v, F, I]`` and the inputs ``[u, F_n]`` (the velocity command u held over
Te); composing ``substeps`` of them gives the axis over one Te
(:func:`substep_sequence`). Linearised (friction -> its viscous part B, which is
inside the matrices, so ``F_n = 0``) this is the lifted axis (:func:`lifted_axis`). The position loop adds the axis's dead time
(:func:`dead_line`: whole samples, or a fractional one as a linear interpolation between
two) and the gain Kp (:func:`position_open_loop`).

An ARX axis (:class:`oga.model.machine.Arx`) is already discrete over Te; its velocity
``v_k`` follows the difference equation of ``V(z)`` on the input
``u_k - viscous_ratio v_{k-1}`` (friction linearised: the Coulomb term is dropped)
and ``p_{k+1} = p_k + Te v_k`` (:func:`arx_state_space`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.linalg import expm

from oga.errors import MachineError
from oga.model.machine import Arx, Cascade, Machine

__all__ = [
    "substep_matrices",
    "substep_sequence",
    "substep_sequence_of",
    "arx_state_space",
    "lifted_axis",
    "dead_line",
    "position_open_loop",
]


def substep_matrices(cascade: Cascade, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of the linear mechanics over ``h``.

    Parameters
    ----------
    cascade : Cascade
        The axis model (mass, viscous friction B, force lag tau are used).
    h : float
        Sub-step length, s.

    Returns
    -------
    ad : ndarray, shape (3, 3)
        State transition of ``x = [p, v, F]`` (m, m/s, N) over ``h``.
    bd : ndarray, shape (3, 2)
        Input matrix of the held inputs ``[F_cmd, F_n]`` (N, N).
    """
    ad, bd = _matrices(_key(cascade.mass_kg, cascade.viscous_n_s_m, cascade.force_lag_s, h))
    return ad.copy(), bd.copy()


def _key(*values: float) -> bytes:
    """A memo key of floats: their bits (``0.0`` and ``-0.0`` differ, as their results may)."""
    return np.array(values, dtype=np.float64).tobytes()


@functools.lru_cache(maxsize=512)
def _matrices(key: bytes) -> tuple[np.ndarray, np.ndarray]:
    """:func:`substep_matrices` of ``key = _key(mass_kg, viscous_n_s_m, force_lag_s, h)``,
    memoised, read-only: a plant's axis asks for them from its packed parameters and from its
    stability loop alike (one matrix exponential, not one per caller)."""
    m, viscous, tau, h = np.frombuffer(key).tolist()
    a = np.array([[0.0, 1.0, 0.0], [0.0, -viscous / m, 1.0 / m], [0.0, 0.0, -1.0 / tau]])
    b = np.array([[0.0, 0.0], [0.0, -1.0 / m], [1.0 / tau, 0.0]])
    # exp([[A, B], [0, 0]] h) = [[Ad, Bd], [0, I]]
    aug = np.zeros((5, 5))
    aug[:3, :3] = a
    aug[:3, 3:] = b
    e = expm(aug * h)
    ad, bd = e[:3, :3].copy(), e[:3, 3:].copy()
    # exact by structure: p does not act on anything, v does not act on F, and the
    # friction force does not reach F (the kernel relies on these zeros)
    ad[:, 0] = (1.0, 0.0, 0.0)
    ad[2, 1] = 0.0
    bd[2, 1] = 0.0
    for arr in (ad, bd):
        arr.flags.writeable = False
    return ad, bd


def substep_sequence(machine: Machine, axis: str) -> tuple[np.ndarray, np.ndarray]:
    """The linear axis with its velocity PI after each of the sub-steps of one Te.

    Without force limit and with the friction force ``F_n`` held, the state after
    ``j`` sub-steps is ``z_j = A_j z_0 + B_j [u, F_n]`` with ``z = [p, v, F, I]``.

    Parameters
    ----------
    machine : Machine
        Machine description (timing and the axis cascade).
    axis : str
        Axis name ("x", "y" or "z"); MachineError if the machine lacks it.

    Returns
    -------
    a : ndarray, shape (S + 1, 4, 4)
        ``A_j`` for ``j = 0 .. S`` (``S = substeps``; ``A_0`` is the identity).
    b : ndarray, shape (S + 1, 4, 2)
        ``B_j``: columns for the velocity command u (m/s) and the friction force F_n (N).
    """
    a, b = substep_sequence_of(machine, axis)
    return a.copy(), b.copy()


def substep_sequence_of(machine: Machine, axis: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`substep_sequence`, memoised by what it depends on and read-only (not copied:
    callers must not write it), for the packed parameters and the stability loops of the
    same plants."""
    cas = machine.axis(axis).cascade
    if cas is None:
        raise MachineError(f"machine {machine.name!r}: axis {axis!r} is not a cascade")
    return _sequence(_key(cas.mass_kg, cas.viscous_n_s_m, cas.force_lag_s, cas.kv_n_s_m,
                          cas.tn_s, machine.timing.te_s), machine.timing.substeps)


@functools.lru_cache(maxsize=512)
def _sequence(key: bytes, n_sub: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`substep_sequence` of ``key = _key(mass_kg, viscous_n_s_m, force_lag_s, kv_n_s_m,
    tn_s, te_s)`` and ``n_sub`` sub-steps, computed (read-only)."""
    m, viscous, tau, kv, tn, te = np.frombuffer(key).tolist()
    h = te / n_sub
    ad, bd = _matrices(_key(m, viscous, tau, h))
    bf = bd[:, 0] * kv  # force command gain on (u - v + I/Tn)
    m_sub = np.zeros((4, 4))  # z_{j+1} = M z_j + N [u, F_n]
    m_sub[:3, :3] = ad
    m_sub[:3, 1] -= bf
    m_sub[:3, 3] = bf / tn
    m_sub[3, 1] = -h
    m_sub[3, 3] = 1.0
    n_sub_in = np.zeros((4, 2))
    n_sub_in[:3, 0] = bf
    n_sub_in[3, 0] = h
    n_sub_in[:3, 1] = bd[:, 1]
    a = np.empty((n_sub + 1, 4, 4))
    b = np.empty((n_sub + 1, 4, 2))
    a[0] = np.eye(4)
    b[0] = 0.0
    for j in range(n_sub):
        a[j + 1] = m_sub @ a[j]
        b[j + 1] = m_sub @ b[j] + n_sub_in
    for arr in (a, b):
        arr.flags.writeable = False
    return a, b


def arx_state_space(arx: Arx, te: float) -> tuple[np.ndarray, np.ndarray]:
    """The linearised ARX axis (velocity command -> position) over one Te.

    State ``z = [p, v_{k-1}, .., v_{k-nv}, w_{k-1}, .., w_{k-nw}]`` (m, then m/s) with
    ``w = u - viscous_ratio v`` the velocity loop's input, ``nv = max(1, len(den) - 1)``
    and ``nw = len(num) - 1``; this is the simulation kernel's state layout. One
    period: ``w_k = u_k - viscous_ratio v_{k-1}``,
    ``v_k = sum_i num[i] w_{k-i} - sum_{i>=1} den[i] v_{k-i}``, ``p_{k+1} = p_k + Te v_k``.

    Parameters
    ----------
    arx : Arx
        The axis model (``den[0] == 1``).
    te : float
        Period, s.

    Returns
    -------
    a : ndarray, shape (n, n)
        State transition, ``n = 1 + nv + nw``.
    b : ndarray, shape (n, 1)
        Input matrix of the velocity command ``u_k`` (m/s).
    """
    num, den = np.asarray(arx.num), np.asarray(arx.den)
    nv, nw = max(1, den.size - 1), num.size - 1
    n = 1 + nv + nw
    # w_k and v_k as rows over the state, plus their input gains
    w_row = np.zeros(n)
    w_row[1] = -arx.viscous_ratio
    v_row = np.zeros(n)
    v_row[1 : den.size] -= den[1:]
    v_row[1 + nv :] += num[1:]
    v_row += num[0] * w_row
    a = np.zeros((n, n))
    b = np.zeros((n, 1))
    a[0] = te * v_row
    a[0, 0] += 1.0
    b[0, 0] = te * num[0]
    a[1] = v_row
    b[1, 0] = num[0]
    for j in range(2, 1 + nv):
        a[j, j - 1] = 1.0
    if nw:
        a[1 + nv] = w_row
        b[1 + nv, 0] = 1.0
        for j in range(2 + nv, n):
            a[j, j - 1] = 1.0
    return a, b


def lifted_axis(
    machine: Machine, axis: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The linearised axis under the position loop over one period Te, dead time excluded.

    Parameters
    ----------
    machine : Machine
        Machine description (timing and the axis model).
    axis : str
        Axis name ("x", "y" or "z"); MachineError if the machine lacks it.

    Returns
    -------
    a : ndarray, shape (n, n)
        Discrete state transition over Te. Cascade: ``n = 4``, ``z = [p, v, F, I]``
        (m, m/s, N, m: I is the integral of the velocity error), the inner loops
        lifted over the sub-steps. ARX: the state of :func:`arx_state_space`.
    b : ndarray, shape (n, 1)
        Input matrix of the velocity command ``u`` (m/s) held over Te.
    c : ndarray, shape (1, n)
        Output: the position p (m, the first state), measured at the start of the period.
    d : ndarray, shape (1, 1)
        Zero feed-through.
    """
    model = machine.axis(axis)
    if model.arx is not None:
        a, b = arx_state_space(model.arx, machine.te)
    else:
        a_j, b_j = substep_sequence_of(machine, axis)
        a, b = a_j[-1].copy(), b_j[-1][:, :1].copy()
    c = np.zeros((1, a.shape[0]))
    c[0, 0] = 1.0
    return a, b, c, np.zeros((1, 1))


def dead_line(machine: Machine, axis: str) -> tuple[int, float]:
    """The dead time of ``axis`` (:meth:`oga.model.machine.Machine.dead_time_samples_of`) as a
    line of commands: ``(L, f)``, the line's length and the weight of its oldest command.

    A whole dead time ``d`` is ``(d, 0.0)``: the axis receives ``u_{k-d}``. A fractional one
    ``d`` is ``(floor(d) + 1, d - floor(d))``: the axis receives ``f u_{k-L} + (1 - f)
    u_{k-L+1}``, the linear-interpolation fractional delay (over the period, the mean of the
    command delayed by ``d Te``; continuous in ``d``, whole values included).
    """
    d = machine.dead_time_samples_of(axis)
    whole = math.floor(d)
    return (whole, 0.0) if d == whole else (whole + 1, d - whole)


def position_open_loop(
    machine: Machine, axis: str, kp_si: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The position open loop ``L(z) = Kp z^-d G(z)`` as a discrete state-space (period Te).

    ``G`` is :func:`lifted_axis` (velocity command -> position, ``n`` states) and
    ``z^-d`` the axis's dead time (:func:`dead_line`; a fractional one
    ``z^-L (f + (1 - f) z)``). The state is ``[z, w]`` with ``w = [u_k-1, ..., u_k-L]`` the
    dead-time line; negative unity feedback ``u = -y`` closes the position loop.

    Parameters
    ----------
    machine : Machine
        Machine description.
    axis : str
        Axis name.
    kp_si : float
        Position-loop gain Kp, 1/s.

    Returns
    -------
    a : ndarray, shape (n + L, n + L)
    b : ndarray, shape (n + L, 1)
    c : ndarray, shape (1, n + L)
        Output ``y = Kp p`` (m/s).
    d : ndarray, shape (1, 1)
        Zero feed-through.
    """
    a_g, b_g, c_g, _ = lifted_axis(machine, axis)
    dead, frac = dead_line(machine, axis)
    m = a_g.shape[0]
    n = m + dead
    a = np.zeros((n, n))
    b = np.zeros((n, 1))
    a[:m, :m] = a_g
    if dead == 0:
        b[:m] = b_g
    else:
        a[:m, n - 1 : n] = b_g  # the oldest command enters the axis
        b[m, 0] = 1.0  # the newest command enters the line
        for i in range(m + 1, n):
            a[i, i - 1] = 1.0
        if frac != 0.0:  # and the next oldest: f u_{k-L} + (1 - f) u_{k-L+1}
            a[:m, n - 1 : n] = frac * b_g
            if dead > 1:
                a[:m, n - 2 : n - 1] = (1.0 - frac) * b_g
            else:
                b[:m] = (1.0 - frac) * b_g
    c = np.zeros((1, n))
    c[0, :m] = kp_si * c_g[0]
    return a, b, c, np.zeros((1, 1))
