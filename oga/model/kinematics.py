"""Paper eq. 2 on the velocity command: the kinematic limits a gain choice must keep.

With the velocity loop taken as ideal, an axis moves at its velocity command
``u``; so ``u`` must keep ``|u| <= Vmax``, ``|u_k - u_{k-1}| / Te <= Amax`` and
``|u_k - 2 u_{k-1} + u_{k-2}| / Te^2 <= Jmax``. These compiled helpers are the
one implementation used by the kinematic range, the searches and the verification.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["command_peaks", "command_rates", "eq2_excess"]


def command_rates(u: np.ndarray, te: float) -> tuple[np.ndarray, np.ndarray]:
    """The velocity command's ``|du|/Te`` and ``|d2u|/Te^2`` at every sample, the axes at
    rest before sample 0 (:func:`command_peaks`'s differences, not only their peaks).

    ``u`` (N, A), m/s; returns two arrays (N, A), m/s^2 and m/s^3."""
    du = np.diff(u, axis=0, prepend=np.zeros((1,) + u.shape[1:]))
    d2u = np.diff(du, axis=0, prepend=np.zeros((1,) + u.shape[1:]))
    return np.abs(du) / te, np.abs(d2u) / (te * te)


@njit(cache=True, nogil=True)
def command_peaks(u, check, te):
    """Largest ``|u|``, ``|du|/Te`` and ``|d2u|/Te^2`` over the samples to check.

    Parameters
    ----------
    u : ndarray, shape (N,)
        Velocity commands, m/s; the axis is at rest before sample 0.
    check : ndarray of bool, shape (N,)
        Samples to check (the differences still reach back to the others).
    te : float
        Sample period, s (> 0).

    Returns
    -------
    (float, float, float)
        Peaks in m/s, m/s^2, m/s^3 (zero when no sample is checked; a NaN command is
        passed over).

    Notes
    -----
    The largest difference is divided once, after the loop: rounded division by a positive
    number is monotonic, so that is the largest of the rounded quotients, to the last bit.
    """
    v_pk = 0.0
    da_pk = 0.0  # largest |u_k - u_{k-1}|
    dj_pk = 0.0  # largest |u_k - 2 u_{k-1} + u_{k-2}|
    u1 = 0.0  # u_{k-1}
    u2 = 0.0  # u_{k-2}
    for k in range(u.shape[0]):
        uk = u[k]
        if check[k]:
            v_pk = max(v_pk, abs(uk))
            da_pk = max(da_pk, abs(uk - u1))
            dj_pk = max(dj_pk, abs(uk - 2.0 * u1 + u2))
        u2 = u1
        u1 = uk
    return v_pk, da_pk / te, dj_pk / (te * te)


@njit(cache=True, nogil=True)
def eq2_excess(u, u1, u2, vmax, amax, jmax, te, n, check):
    """Largest excess over 1 of ``|u|/V``, ``|du|/(A Te)``, ``|d2u|/(J Te^2)`` over ``u[:n]``
    at the samples where ``check`` is True (every sample of the program: the callers
    leave out only the padding past its end, or history checked before).

    Parameters
    ----------
    u : ndarray, shape (>= n,)
        Velocity commands of consecutive samples, m/s.
    u1, u2 : float
        The two commands before ``u[0]`` (``u_{-1}``, ``u_{-2}``), m/s.
    vmax, amax, jmax : float
        The axis limits (m/s, m/s^2, m/s^3).
    te : float
        Sample period, s.
    n : int
        Samples to check.
    check : ndarray of bool, shape (>= n,)
        Samples to check (the differences still reach back to the others).

    Returns
    -------
    float
        0 when eq. 2 holds at every sample, else the largest relative excess.

    Notes
    -----
    The largest ``|u|``, difference and second difference are scaled once, after the loop:
    rounded division by a positive limit and the subtraction of 1 are monotonic, so that is
    the largest of the per-sample excesses, to the last bit (a NaN passed over as before).
    """
    v_pk = 0.0
    da_pk = 0.0
    dj_pk = 0.0
    for i in range(n):
        v = u[i]
        if check[i]:
            v_pk = max(v_pk, abs(v))
            da_pk = max(da_pk, abs(v - u1))
            dj_pk = max(dj_pk, abs(v - 2.0 * u1 + u2))
        u2 = u1
        u1 = v
    return max(0.0, v_pk / vmax - 1.0, da_pk / (amax * te) - 1.0,
               dj_pk / (jmax * te * te) - 1.0)
