"""Programmed geometry: straight lines and circular/helical arcs in metres.

A :class:`Path` is what a toolpath reader returns and what the feed planner
consumes. Coordinates are machine axes ``(x, y, z)`` in metres.

Planes and arc sense
--------------------
Each plane has its own orientation ``(e1, e2, normal)`` with ``e1 x e2 = normal``:

======  ======  ======  ======
plane   e1      e2      normal
======  ======  ======  ======
``xy``  X       Y       Z      (G17)
``zx``  Z       X       Y      (G18)
``yz``  Y       Z       X      (G19)
======  ======  ======  ======

An arc's ``sweep_rad`` is signed about the plane normal: positive is
counter-clockwise seen from +normal (G3), negative is clockwise (G2). For G18
that makes G2 counter-clockwise when drawn with X to the right and Z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal, Union

import numpy as np

__all__ = ["PLANES", "Plane", "Line", "Arc", "Segment", "Path"]

Plane = Literal["xy", "zx", "yz"]

#: Axis indices (e1, e2, normal) of each plane, in its own orientation.
PLANES: dict[str, tuple[int, int, int]] = {"xy": (0, 1, 2), "zx": (2, 0, 1), "yz": (1, 2, 0)}


def _vec(a) -> np.ndarray:
    v = np.asarray(a, dtype=np.float64).reshape(3).copy()
    v.flags.writeable = False
    return v


@dataclass(frozen=True)
class Line:
    """A straight move from ``start`` to ``end``.

    Attributes
    ----------
    start, end : ndarray, shape (3,)
        End points in metres.
    feed_m_s : float
        Programmed feed (path speed) in m/s; ``inf`` for rapids (planned at the axis limits).
    rapid : bool
        True for G0 moves (not part of the contour).
    line : int
        1-based source line (block) of the move; 0 when not from a text source.
    blend_tol_m : float or None
        Path control at the end of the move: None blends the corner within the plan's
        tolerance (G64), 0 stops exactly (G61), > 0 blends within that (G64 P), metres.
    """

    start: np.ndarray
    end: np.ndarray
    feed_m_s: float
    rapid: bool = False
    line: int = 0
    blend_tol_m: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vec(self.start))
        object.__setattr__(self, "end", _vec(self.end))

    @cached_property  # start/end are read-only: computed once, read often (planning)
    def length(self) -> float:
        """Length in metres."""
        return float(np.linalg.norm(self.end - self.start))

    def point(self, u: np.ndarray | float) -> np.ndarray:
        """Points at fractions ``u`` in [0, 1] of the length; shape (..., 3)."""
        u = np.asarray(u, dtype=np.float64)[..., None]
        return self.start + u * (self.end - self.start)


@dataclass(frozen=True)
class Arc:
    """A circular arc in one plane, optionally helical along the plane normal.

    Attributes
    ----------
    start, end : ndarray, shape (3,)
        End points in metres (exact as programmed; ``end`` lies on the circle
        within the reader's tolerance).
    center : ndarray, shape (3,)
        Centre in metres; its normal coordinate equals ``start``'s.
    plane : {"xy", "zx", "yz"}
        Plane of the circle (G17, G18, G19).
    sweep_rad : float
        Signed sweep about the plane normal (G3 positive, G2 negative); a full
        circle is +-2 pi.
    feed_m_s : float
        Programmed feed (path speed) in m/s.
    line : int
        1-based source line of the move.
    blend_tol_m : float or None
        Path control at the end of the move, as :attr:`Line.blend_tol_m`.
    """

    start: np.ndarray
    end: np.ndarray
    center: np.ndarray
    plane: Plane
    sweep_rad: float
    feed_m_s: float
    line: int = 0
    blend_tol_m: float | None = None
    rapid: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vec(self.start))
        object.__setattr__(self, "end", _vec(self.end))
        object.__setattr__(self, "center", _vec(self.center))

    @cached_property
    def radius(self) -> float:
        """Radius in metres (distance of ``start`` from the centre in the plane)."""
        i, j, _ = PLANES[self.plane]
        d = self.start - self.center
        return float(np.hypot(d[i], d[j]))

    @cached_property
    def start_angle(self) -> float:
        """Angle of ``start`` about the centre in the plane's (e1, e2) frame, rad."""
        i, j, _ = PLANES[self.plane]
        d = self.start - self.center
        return float(np.arctan2(d[j], d[i]))

    @cached_property
    def rise(self) -> float:
        """Helical rise along the plane normal from start to end, metres."""
        return float(self.end[PLANES[self.plane][2]] - self.start[PLANES[self.plane][2]])

    @cached_property
    def length(self) -> float:
        """Length in metres (helical length when ``rise`` is non-zero)."""
        return float(np.hypot(self.radius * abs(self.sweep_rad), self.rise))

    def point(self, u: np.ndarray | float) -> np.ndarray:
        """Points at fractions ``u`` in [0, 1] of the sweep (and rise); shape (..., 3).

        The in-plane part lies exactly on the circle; ``u = 1`` returns the
        circle point nearest the programmed end.
        """
        u = np.asarray(u, dtype=np.float64)
        i, j, n = PLANES[self.plane]
        th = self.start_angle + u * self.sweep_rad
        r = self.radius
        out = np.empty(u.shape + (3,))
        out[..., i] = self.center[i] + r * np.cos(th)
        out[..., j] = self.center[j] + r * np.sin(th)
        out[..., n] = self.start[n] + u * self.rise
        return out


Segment = Union[Line, Arc]


@dataclass(frozen=True)
class Path:
    """A toolpath: the start point and the moves that follow it.

    Attributes
    ----------
    start : ndarray, shape (3,)
        Where the tool is at rest before the first segment, metres.
    segments : tuple of Line or Arc
        Moves in program order; each ``segments[k].start`` equals the previous end.
    plane : {"xy", "zx", "yz"}
        The plane selected when the last feed move was programmed (G17/G18/G19).
    source : str
        Name of the program, for messages.
    warnings : tuple of str
        Non-fatal remarks of the reader (e.g. a G28 that ended the program).
    """

    start: np.ndarray
    segments: tuple[Segment, ...]
    plane: Plane = "xy"
    source: str = ""
    warnings: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vec(self.start))
        object.__setattr__(self, "segments", tuple(self.segments))
        object.__setattr__(self, "warnings", tuple(self.warnings))

    @property
    def length(self) -> float:
        """Total programmed length in metres, rapids included."""
        return float(sum(s.length for s in self.segments))

    @property
    def feed_length(self) -> float:
        """Length of the feed (non-rapid) moves in metres."""
        return float(sum(s.length for s in self.segments if not s.rapid))
