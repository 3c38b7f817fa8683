"""Local repair of a robust table: the baseline's gains faded back in around the samples where
the table alone breaks a limit, the rest of the table kept.

The shrink (:func:`oga.search.robust.search._shrink`) scales the table's whole departure from the
baseline by one share; where a few samples break a limit on a few plants, it gives up most of
the table for them. The repair fades the table to the baseline (which keeps every limit on
every plant) over the samples where a failing plant's command or following error breaks its
limit, ``K = Kb + w (Ks - Kb)`` with ``w`` 0 within :data:`oga.defaults.ROBUST_REPAIR_HOLD_S`
of them and a raised-cosine ramp of :data:`oga.defaults.ROBUST_REPAIR_RAMP_S` either side (a
gain stepped at speed is a command step), and certifies again; breaks that remain inside a
faded stretch double both widths (at most :data:`oga.defaults.ROBUST_REPAIR_STEPS` times).

Why: on 51MeanderAve (ucp710, anchor 3000, the planner's profile with the mean cap) round 2's
table had median 0.329, p90 0.463, worst 0.628, and broke the jerk limit on 12 plants at five
samples; the rounds after it collapsed and the shrink kept median 0.455, worst 0.685.
"""

from __future__ import annotations

import numpy as np

from feedplan.setpoints import Setpoints
from oga import defaults
from oga.model.kinematics import command_rates
from oga.model.machine import Machine
from oga.model.plant import plant_of
from oga.verify.certificate import Certificate, certify
from oga.verify.replay import verify

__all__ = ["break_samples", "fade", "repaired"]


def break_samples(setpoints: Setpoints, machine: Machine, u: np.ndarray, pos: np.ndarray
                  ) -> np.ndarray:
    """The samples where a replay breaks a limit of ``machine``: eq. 2 of its velocity command
    ``u`` (N, 3), m/s (at rest before sample 0), or the following-error limit by its
    positions ``pos`` (N, 3), m. Returns a bool array (N,)."""
    limits = plant_of(machine).limits  # (3, 3): axis, (v, a, j)
    out = np.zeros(len(u), dtype=bool)
    for order, rate in enumerate((np.abs(u),) + command_rates(u, setpoints.dt)):
        out |= (rate > limits[:, order] * (1.0 + 1e-9)).any(axis=1)
    ferror = machine.ferror_limits()
    out |= (np.abs(setpoints.pos - pos) > ferror * (1.0 + 1e-9)).any(axis=1)
    return out


def fade(marked: np.ndarray, hold: int, ramp: int) -> np.ndarray:
    """Weights (N,) in [0, 1]: 0 within ``hold`` samples of a ``marked`` one (bool, (N,)),
    rising to 1 along a raised cosine over the next ``ramp`` samples either side."""
    n = marked.size
    idx = np.flatnonzero(marked)
    if idx.size == 0:
        return np.ones(n)
    k = np.arange(n)
    # distance of every sample to the nearest marked one
    pos = np.searchsorted(idx, k)
    left = np.where(pos > 0, k - idx[np.maximum(pos - 1, 0)], n)
    right = np.where(pos < idx.size, idx[np.minimum(pos, idx.size - 1)] - k, n)
    x = np.clip((np.minimum(left, right) - hold) / max(ramp, 1), 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def repaired(setpoints: Setpoints, machine: Machine, table, base, scenarios, bounds,
             cert: Certificate, base_replays, threads: int = 1):
    """The table ``(kp, kf)`` (N, 3) repaired against the baseline ``base`` ``(kp, kf)`` (N, 3)
    (module doc), where its certificate ``cert`` on ``scenarios`` fails by schedule-only
    breaks alone, on plants where the table is no worse than the baseline. Returns ``(kp, kf,
    certificate)`` once the certificate passes (at once where ``cert`` does), else None (a
    plant worse than the baseline, a break with no sample to fade, or the steps spent)."""
    kp, kf = table
    bkp, bkf = base
    kp_r, kf_r = kp, kf
    marked = np.zeros(len(setpoints), dtype=bool)
    w = np.ones(len(setpoints))
    hold = int(round(defaults.ROBUST_REPAIR_HOLD_S / setpoints.dt))
    ramp = int(round(defaults.ROBUST_REPAIR_RAMP_S / setpoints.dt))
    for _ in range(defaults.ROBUST_REPAIR_STEPS):
        if cert.status == "ok":
            return kp_r, kf_r, cert
        failing = np.flatnonzero(cert.failures())
        if any(not cert.plants[i].schedule_only_break or cert.plants[i].ratio > 1.0
               for i in failing):  # worse than the baseline: not a local fault
            return None
        new = np.zeros_like(marked)
        for i in failing:
            rep = verify(setpoints, scenarios.plants[i], kp_r, kf_r, bounds[i])
            new |= break_samples(setpoints, scenarios.plants[i], rep.u, rep.pos)
        if not new.any():  # a stability break: no sample to fade
            return None
        if (w[new] < 1.0).all():  # the breaks stayed where it faded: fade wider
            hold, ramp = 2 * hold, 2 * ramp
        marked |= new
        w = fade(marked, hold, ramp)
        kp_r, kf_r = bkp + w[:, None] * (kp - bkp), bkf + w[:, None] * (kf - bkf)
        cert = certify(setpoints, machine, kp_r, kf_r, bkp, bkf, scenarios, bounds, base_replays,
                       threads=threads)
    return (kp_r, kf_r, cert) if cert.status == "ok" else None
