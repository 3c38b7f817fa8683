"""What a gain search returns: the schedule (:class:`GainSchedule`) and the result of
:func:`oga.optimize.optimize` with the replays that judge it (:class:`OptimizeResult`).

Both the nominal path (:mod:`oga.optimize`) and the robust search
(:mod:`oga.search.robust.search`) build these; they live here so neither imports the other.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga.model.machine import Machine
from oga.options import OptimizeOptions
from oga.verify.replay import Verification

if TYPE_CHECKING:
    from oga.verify.certificate import Certificate

__all__ = ["GainSchedule", "OptimizeResult", "hold_baseline", "setpoints_digest"]


@dataclass(frozen=True, eq=False)
class GainSchedule:
    """Gains per sample and axis (columns x, y, z).

    Attributes
    ----------
    kp_m_min_per_mm : ndarray, shape (N, 3)
        Position-loop gain, (m/min)/mm.
    kf : ndarray, shape (N, 3)
        Velocity feed-forward factor.
    """

    kp_m_min_per_mm: np.ndarray
    kf: np.ndarray


@dataclass(frozen=True, eq=False)
class OptimizeResult:
    """What :func:`optimize` found, and the replays that judge it.

    Attributes
    ----------
    status : {"ok", "failed"}
        ``"ok"`` when the schedule passed every check of its replay; a failed
        schedule must never be exported as valid.
    setpoints : Setpoints
        The setpoints the schedule belongs to.
    machine : Machine
        The machine it was computed for.
    options : OptimizeOptions
        The options used.
    schedule : GainSchedule
        The gains to export: the searched schedule when it passed verification and
        beat the baseline, else the baseline's fixed gains (``kept_baseline``).
    baseline_kp, baseline_kf : dict
        The fixed gains per machine axis it starts from and is compared with.
    baseline, optimized : Verification
        Replays of the fixed baseline and of ``schedule``.
    searched_schedule : GainSchedule
        What the search found (equal to ``schedule`` unless ``kept_baseline``).
    searched : Verification
        Its replay.
    kept_baseline : bool
        True when the searched schedule failed verification or did not lower
        MSE(CE): then the table holds the fixed baseline gains, never worse gains.
    adjusted : tuple of str
        Axes whose gains the search moved.
    kp_bounds : dict
        Allowed Kp range per contouring axis, (m/min)/mm.
    optimize_time_s : float
        Wall time of the search and its verification, s.
    fallbacks : int
        Paper mode: samples where no candidate met eq. 2 and the least violating was
        taken; full mode: iterations where even the current plan broke eq. 2 over the
        window (the replay still checks every committed sample).
    windows : int
        Prediction windows simulated.
    certificate : Certificate or None
        Robust search: the candidate schedule against the fixed baseline on every plant
        of the machine's uncertainty set (:mod:`oga.verify.certificate`); None when the
        search was nominal (``nominal`` option, or a machine without a set).
    refusal : tuple of str
        Robust search: why its schedule was refused (the certificate's reasons), empty
        when it was not.
    """

    status: str
    setpoints: Setpoints
    machine: Machine
    options: OptimizeOptions
    schedule: GainSchedule
    baseline_kp: dict[str, float]
    baseline_kf: dict[str, float]
    baseline: Verification
    optimized: Verification
    searched_schedule: GainSchedule
    searched: Verification
    kept_baseline: bool
    adjusted: tuple[str, ...]
    kp_bounds: dict[str, tuple[float, float]]
    optimize_time_s: float
    fallbacks: int
    windows: int
    certificate: Certificate | None = None
    refusal: tuple[str, ...] = ()

    @property
    def robust(self) -> bool:
        """True when the robust search ran (the result carries a certificate)."""
        return self.certificate is not None

    @property
    def kept_baseline_reason(self) -> str:
        """Why the table holds the baseline's fixed gains ("" when it holds the schedule)."""
        if not self.kept_baseline:
            return ""
        if self.refusal:
            return "robustness certificate failed: " + "; ".join(self.refusal)
        if not self.searched.ok:
            return "failed verification: " + "; ".join(self.searched.violations)
        return f"MSE ratio {self.search_ratio_mse:.3f} >= 1"

    def search_kind(self) -> str:
        """How the schedule was searched, in words (for the summary and the CLI)."""
        if self.robust:
            return "robust"
        from oga.search.robust.plants import uncertain_axes

        if uncertain_axes(self.machine):
            return "nominal (requested: nominal option)"
        return "nominal (the machine has no uncertainty set)"

    @property
    def ratio_mse(self) -> float:
        """MSE(CE) of the exported schedule over MSE(CE) of the baseline."""
        return self.optimized.metrics.mse_m2 / self.baseline.metrics.mse_m2

    @property
    def search_ratio_mse(self) -> float:
        """MSE(CE) of the searched schedule over MSE(CE) of the baseline."""
        return self.searched.metrics.mse_m2 / self.baseline.metrics.mse_m2

    def summary(self, toolpath: str = "", toolpath_sha256: str | None = None) -> dict:
        """The summary JSON (users' units), as written by ``oga optimize --summary``."""
        from oga.identify.coverage import model_coverage

        def metrics(v: Verification) -> dict:
            m = v.metrics.to_dict()
            return {k: m[k] for k in ("mse_ce_um2", "rms_ce_um", "max_ce_um", "p95_ce_um",
                                      "track_max_um")}

        moving = [AXES[i] for i in self.setpoints.moving_axes]

        def command_ratio(v: Verification) -> dict:  # over every sample, rapids included
            return {a: dict(zip(("v", "a", "j"), v.command_ratio[i].tolist()))
                    for i, a in enumerate(AXES) if a in moving}

        return {
            "toolpath": toolpath or self.setpoints.source,
            "toolpath_sha256": toolpath_sha256,
            "setpoints_sha256": setpoints_digest(self.setpoints),
            "machine": self.machine.name,
            "machine_sha256": self.machine.digest(),
            "status": self.status,
            "samples": len(self.setpoints),
            "duration_s": self.setpoints.duration,
            "contouring_axes": moving,
            "adjusted": list(self.adjusted),
            "gains": list(self.options.gains),
            "kp_bounds_m_min_per_mm": {a: list(b) for a, b in self.kp_bounds.items()},
            "baseline": {"kp": self.baseline_kp, "kf": self.baseline_kf,
                         **metrics(self.baseline), "violations": list(self.baseline.violations),
                         "command_ratio_to_limits": command_ratio(self.baseline)},
            "optimized": metrics(self.optimized),
            "ratio_mse": self.ratio_mse,
            "kept_baseline": self.kept_baseline,
            "kept_baseline_reason": self.kept_baseline_reason,
            "search": {"kind": self.search_kind(), "status": self.searched.status,
                       "ratio_mse": self.search_ratio_mse,
                       "violations": list(self.searched.violations)},
            "certificate": (self.certificate.summary() if self.robust
                            else {"status": "none", "reasons": [self.search_kind()]}),
            "model": model_coverage(self.machine, moving),
            "limits_ok": self.optimized.limits_ok,
            "stability_ok": self.optimized.stability_ok,
            "violations": list(self.optimized.violations),
            "command_ratio_to_limits": command_ratio(self.optimized),
            "ferror_ratio_to_limit": {
                a: (float(r) if np.isfinite(r) else None)
                for a, r in zip(AXES, self.optimized.ferror_ratio) if a in moving
            },
            "max_dkp_per_sample": {a: float(self.optimized.max_dkp_per_sample[i])
                                   for i, a in enumerate(AXES) if a in moving},
            "max_dkf_per_sample": {a: float(self.optimized.max_dkf_per_sample[i])
                                   for i, a in enumerate(AXES) if a in moving},
            "fallback_samples": self.fallbacks,
            "optimize_time_s": self.optimize_time_s,
            "options": self.options.as_dict(),
        }


def setpoints_digest(sp: Setpoints) -> str:
    """SHA-256 of the setpoint positions and period (identifies the motion a table belongs to)."""
    h = hashlib.sha256()
    h.update(np.float64(sp.dt).tobytes())
    h.update(np.ascontiguousarray(sp.pos).tobytes())
    return h.hexdigest()


def hold_baseline(setpoints: Setpoints, kp: np.ndarray, kf: np.ndarray, kp_base: np.ndarray,
                  kf_base: np.ndarray) -> None:
    """Give a searched schedule the baseline's gains where the controller holds them
    (``setpoints.held``), in place, so that what is verified is what runs.

    Parameters
    ----------
    kp, kf : ndarray, shape (N, 3)
        The schedule, Kp in (m/min)/mm.
    kp_base, kf_base : ndarray, shape (3,)
        The baseline's gains per axis x, y, z.
    """
    if setpoints.held is not None:
        kp[setpoints.held] = kp_base
        kf[setpoints.held] = kf_base
