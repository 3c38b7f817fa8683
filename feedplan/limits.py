"""Per-axis kinematic limits handed to the feed planner."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES

__all__ = ["AxisLimits"]


@dataclass(frozen=True, eq=False)
class AxisLimits:
    """Velocity, acceleration and jerk limits of the machine axes (x, y, z).

    A limit of 0 marks an axis that must not move (e.g. one the machine lacks):
    a path that moves it cannot be planned.

    Attributes
    ----------
    vmax_m_s, amax_m_s2, jmax_m_s3 : ndarray, shape (3,)
        Largest |velocity| (m/s), |acceleration| (m/s^2) and |jerk| (m/s^3) of
        each axis, in the order of :data:`feedplan.setpoints.AXES`.
    """

    vmax_m_s: np.ndarray
    amax_m_s2: np.ndarray
    jmax_m_s3: np.ndarray

    def __post_init__(self) -> None:
        for name in ("vmax_m_s", "amax_m_s2", "jmax_m_s3"):
            a = np.array(getattr(self, name), dtype=np.float64)
            if a.shape != (3,):
                raise ValueError(f"AxisLimits.{name} must have shape (3,), got {a.shape}")
            if not np.all(np.isfinite(a)) or np.any(a < 0):
                raise ValueError(f"AxisLimits.{name} must be finite and >= 0, got {a.tolist()}")
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        if not np.any(self.present):
            raise ValueError("AxisLimits: no axis may move (every axis has a 0 limit)")

    @property
    def present(self) -> np.ndarray:
        """Boolean mask, shape (3,), of the axes that may move (all three limits > 0)."""
        return (self.vmax_m_s > 0) & (self.amax_m_s2 > 0) & (self.jmax_m_s3 > 0)

    @property
    def absent_names(self) -> tuple[str, ...]:
        """Names of the axes that must not move."""
        return tuple(a for a, p in zip(AXES, self.present) if not p)
