"""Sampled position setpoints: what a controller's interpolator hands to the axes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feedplan.path import Plane

__all__ = ["AXES", "Setpoints"]

#: Machine axis names in column order of every (N, 3) array.
AXES: tuple[str, str, str] = ("x", "y", "z")


def _frozen(a, dtype=np.float64) -> np.ndarray:
    a = np.array(a, dtype=dtype)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Setpoints:
    """Uniformly sampled setpoints of a planned toolpath.

    Attributes
    ----------
    dt : float
        Sample period Te in seconds.
    s : ndarray, shape (N,)
        Path length travelled at each sample, metres (rapids included).
    pos, vel, acc, jerk : ndarray, shape (N, 3)
        Per axis (x, y, z) position m, velocity m/s, acceleration m/s^2 and jerk
        m/s^3 of the planned motion; the planner gives centred finite differences of
        ``pos`` (consistent with the limit checks, which difference ``pos`` itself).
    block : ndarray of int, shape (N,)
        1-based source line of the segment each sample belongs to.
    rapid : ndarray of bool, shape (N,)
        True where the sample belongs to a rapid (G0) move.
    plane : {"xy", "zx", "yz"} or None
        The plane if every feed sample lies in one coordinate plane (its normal
        coordinate constant), else None (a non-planar path: contour error unsigned).
    source : str
        Name of the program.
    warnings : tuple of str
        Non-fatal remarks of the planner (e.g. a feed above what the axes allow).
    held : ndarray of bool, shape (N,), or None
        True where the controller runs its fixed baseline gains whatever the table says: the
        stops between the parts of a recorded program, which LinuxCNC's task times (a table
        holds there). The searches give those samples the baseline's gains; the figures do
        not count them (their length is the task's), the checks do. None: nowhere.
    """

    dt: float
    s: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    jerk: np.ndarray
    block: np.ndarray
    rapid: np.ndarray
    plane: Plane | None = None
    source: str = ""
    warnings: tuple[str, ...] = ()
    held: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("s", "pos", "vel", "acc", "jerk"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        object.__setattr__(self, "block", _frozen(self.block, np.int64))
        object.__setattr__(self, "rapid", _frozen(self.rapid, np.bool_))
        object.__setattr__(self, "warnings", tuple(self.warnings))
        n = self.s.shape[0]
        for name in ("pos", "vel", "acc", "jerk"):
            if getattr(self, name).shape != (n, 3):
                raise ValueError(f"Setpoints.{name} must have shape ({n}, 3)")
        if self.held is not None:
            object.__setattr__(self, "held", _frozen(self.held, np.bool_))
        if self.block.shape != (n,) or self.rapid.shape != (n,) or (
                self.held is not None and self.held.shape != (n,)):
            raise ValueError("Setpoints.block, .rapid and .held must have one entry per sample")
        if not self.dt > 0:
            raise ValueError("Setpoints.dt must be positive")

    def __len__(self) -> int:
        return int(self.s.shape[0])

    @property
    def t(self) -> np.ndarray:
        """Sample times in seconds, shape (N,)."""
        return np.arange(len(self)) * self.dt

    @property
    def counted(self) -> np.ndarray:
        """The samples the contour-error figures count, shape (N,) bool: the feed samples
        outside the held stops (rapids and stops are checked, not counted)."""
        return ~self.rapid if self.held is None else ~self.rapid & ~self.held

    @property
    def duration(self) -> float:
        """Time from the first to the last sample, seconds."""
        return (len(self) - 1) * self.dt

    @property
    def moving_axes(self) -> tuple[int, ...]:
        """Indices of the axes whose position changes (by more than 1 nm)."""
        span = self.pos.max(axis=0) - self.pos.min(axis=0) if len(self) else np.zeros(3)
        return tuple(int(i) for i in np.flatnonzero(span > 1e-9))
