"""A plant of another structure than oga's model, simulated independently of oga (numpy, scipy).

Each axis is a two-mass drive: the motor (``m1``) and the table (``m2``) joined by the ball
screw's stiffness ``k`` and damping ``c`` (the mode ``f0 = sqrt(k (m1 + m2) / (m1 m2)) / 2 pi``,
40-80 Hz here), the velocity PI closed on the motor's velocity (``Kv``, ``Tn``) every
sub-step ``h = Te / substeps``, the force command limited and reaching the motor through a
first-order lag ``tau``, friction on the guideways (Coulomb, smoothed by ``tanh``, and viscous
on the table) and in the bearings (viscous on the motor). The position loop runs every
``Te``: ``u_k = Kp (pd_k - p_k) + Kf vd_k`` reaches the velocity loop ``dead`` samples later;
``p`` is the motor's position (``semi``-closed loop: an encoder on the motor) or the table's
(``full``-closed: a linear scale). The tool is on the table: the contour error is the table's.

Per sub-step the linear part ``z = [x1, v1, x2, v2, F]`` is advanced exactly (zero-order hold
of the force command and the friction forces over the sub-step, ``scipy.linalg.expm``), the
friction evaluated at the sub-step's start. Several axes and gain tables run side by side as
one batch (arrays of shape (B, ...)): nothing here is oga's code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

__all__ = ["TwoMassAxis", "simulate_batch", "TE", "SUBSTEPS"]

TE = 1e-3
SUBSTEPS = 8


@dataclass(frozen=True)
class TwoMassAxis:
    """One two-mass axis (SI). ``loop``: ``"semi"`` (motor encoder) or ``"full"`` (scale)."""

    m1_kg: float
    m2_kg: float
    mode_hz: float
    damping_ratio: float
    kv_n_s_m: float
    tn_s: float
    force_lag_s: float
    coulomb_n: float
    viscous_table_n_s_m: float
    viscous_motor_n_s_m: float
    dead_samples: int
    loop: str
    force_limit_n: float = 12000.0
    smoothing_m_s: float = 1e-4

    @property
    def stiffness_n_m(self) -> float:
        mu = self.m1_kg * self.m2_kg / (self.m1_kg + self.m2_kg)
        return mu * (2 * math.pi * self.mode_hz) ** 2

    def matrices(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact zero-order-hold step over ``h`` of ``z' = A z + B [F_cmd, Ffr_motor, Ffr_table]``."""
        m1, m2, k = self.m1_kg, self.m2_kg, self.stiffness_n_m
        mu = m1 * m2 / (m1 + m2)
        c = 2 * self.damping_ratio * math.sqrt(k * mu)
        b1, b2 = self.viscous_motor_n_s_m, self.viscous_table_n_s_m
        a = np.zeros((5, 5))
        a[0, 1] = 1.0
        a[1] = [-k / m1, -(c + b1) / m1, k / m1, c / m1, 1.0 / m1]
        a[2, 3] = 1.0
        a[3] = [k / m2, c / m2, -k / m2, -(c + b2) / m2, 0.0]
        a[4, 4] = -1.0 / self.force_lag_s
        b = np.zeros((5, 3))
        b[4, 0] = 1.0 / self.force_lag_s
        b[1, 1] = -1.0 / m1
        b[3, 2] = -1.0 / m2
        big = np.zeros((8, 8))
        big[:5, :5], big[:5, 5:] = a * h, b * h
        e = expm(big)
        return e[:5, :5], e[:5, 5:]


def simulate_batch(axes: list[TwoMassAxis], pd: np.ndarray, vd: np.ndarray, kp_si: np.ndarray,
                   kf: np.ndarray, te: float = TE, substeps: int = SUBSTEPS):
    """Run B axes (each its own plant, setpoints and gains) from rest at their first setpoint.

    Parameters
    ----------
    axes : list of TwoMassAxis, length B
    pd, vd : ndarray, shape (N, B)
        Position (m) and velocity (m/s) setpoints.
    kp_si, kf : ndarray, shape (N, B)
        Position gain (1/s) and feed-forward factor per sample.

    Returns
    -------
    measured, table, force : ndarray, shape (N, B)
        The position the loop measures at each sample (motor or table), the table's
        position (m), and the motor force (N).
    """
    n, nb = pd.shape
    h = te / substeps
    mats = [ax.matrices(h) for ax in axes]
    ad = np.stack([m[0] for m in mats])  # (B, 5, 5)
    bd = np.stack([m[1] for m in mats])  # (B, 5, 3)
    kv = np.array([ax.kv_n_s_m for ax in axes])
    inv_tn = np.array([1.0 / ax.tn_s for ax in axes])
    flim = np.array([ax.force_limit_n for ax in axes])
    fc = np.array([ax.coulomb_n for ax in axes])
    inv_eps = np.array([1.0 / ax.smoothing_m_s for ax in axes])
    full = np.array([ax.loop == "full" for ax in axes])
    dead = np.array([ax.dead_samples for ax in axes])
    z = np.zeros((nb, 5))
    z[:, 0] = z[:, 2] = pd[0]
    integ = np.zeros(nb)
    u_hist = np.zeros((n, nb))
    measured, table, force = np.empty((n, nb)), np.empty((n, nb)), np.empty((n, nb))
    rows = np.arange(nb)
    inputs = np.zeros((nb, 3))
    for k in range(n):
        p = np.where(full, z[:, 2], z[:, 0])
        measured[k], table[k], force[k] = p, z[:, 2], z[:, 4]
        u_hist[k] = kp_si[k] * (pd[k] - p) + kf[k] * vd[k]
        src = k - dead
        ud = np.where(src >= 0, u_hist[np.maximum(src, 0), rows], 0.0)
        for _ in range(substeps):
            e = ud - z[:, 1]
            f_cmd = kv * (e + integ * inv_tn)
            limited = np.abs(f_cmd) >= flim
            f_cmd = np.clip(f_cmd, -flim, flim)
            integ = np.where(limited & (np.sign(e) == np.sign(f_cmd)), integ, integ + h * e)
            inputs[:, 0] = f_cmd
            inputs[:, 1] = 0.0
            inputs[:, 2] = fc * np.tanh(z[:, 3] * inv_eps)
            z = np.einsum("bij,bj->bi", ad, z) + np.einsum("bij,bj->bi", bd, inputs)
    return measured, table, force
