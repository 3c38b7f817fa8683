"""Canonical moves -> :class:`~feedplan.path.Path`: what both G-code readers hand over.

Both readers (the built-in one and LinuxCNC's interpreter) reduce a program to LinuxCNC's
canonical calls, in machine coordinates and metres: traverses, straight feeds, arc feeds
(end, centre, rotation), dwells, feed rates, planes. :class:`PathBuilder` turns that stream
into a Path, the same way for both, so that the two readers' paths can be compared move by
move.

- Before the program the tool is at the program zero of G54 (where LinuxCNC's interpreter
  assumes it: machine zero without a G54 offset); the first move positions the tool and is
  not a segment (the tool starts at rest at its end: where it was before is unknown). A block
  that moves without naming an axis (``G0`` alone) is a move to where the tool is: as the
  first move, it puts the start at that program zero; so do the axes the first move does not
  name.
- Zero-length moves are dropped; traverses are ``Line(rapid=True, feed_m_s=inf)``.
- An arc's sweep follows LinuxCNC's rotation: the sign is the sense about the plane normal
  (positive counter-clockwise, G3), ``|rotation| - 1`` extra full turns (the P word); an end
  equal to the start is a full circle. The end must lie on the circle within ``end_tol_m``
  (oga plans circular arcs; LinuxCNC would run a slightly larger difference as a spiral).
- A dwell or a tool change stops the motion exactly at the end of the move before it.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from feedplan.path import PLANES, Arc, Line, Path
from oga.defaults import MAX_COORD_M, MAX_SEGMENTS
from oga.errors import GcodeError

__all__ = ["PathBuilder", "arc_sweep"]


def arc_sweep(a: np.ndarray, b: np.ndarray, c: np.ndarray, rotation: int) -> float:
    """Signed sweep (rad) from in-plane point ``a`` to ``b`` about centre ``c``.

    ``rotation`` > 0 is counter-clockwise (G3): the first turn in (0, 2 pi]; < 0 clockwise
    (G2): in [-2 pi, 0); ``a == b`` is a full circle; ``|rotation| - 1`` more full turns.
    """
    ccw = rotation > 0
    if a[0] == b[0] and a[1] == b[1]:
        angle = 2 * math.pi if ccw else -2 * math.pi
    else:
        u0, u1, v0, v1 = a[0] - c[0], a[1] - c[1], b[0] - c[0], b[1] - c[1]
        angle = math.atan2(u0 * v1 - u1 * v0, u0 * v0 + u1 * v1)
        if ccw and angle <= 0:
            angle += 2 * math.pi
        elif not ccw and angle >= 0:
            angle -= 2 * math.pi
    extra = (abs(rotation) - 1) * 2 * math.pi
    return angle + (extra if ccw else -extra)


class PathBuilder:
    """Collects canonical moves (machine coordinates, metres) into a Path.

    Parameters
    ----------
    source : str
        Name of the program, for messages and ``Path.source``.
    before_m : array_like, shape (3,), optional
        Where the machine is before the program, m (default machine zero).
    """

    def __init__(self, source: str = "", before_m=(0.0, 0.0, 0.0)) -> None:
        self.source = source
        self.pos = np.array(before_m, dtype=np.float64).reshape(3)
        self.start: np.ndarray | None = None
        self.segments: list[Line | Arc] = []
        self.warnings: list[str] = []
        self.plane = "xy"
        self.feed_plane: str | None = None
        self.feed_m_s: float | None = None
        self.blend_tol_m: float | None = None  # path control of the moves to come

    def error(self, message: str, line: int, column: int) -> GcodeError:
        return GcodeError(message, line, column, self.source)

    def warn(self, message: str) -> None:
        if message not in self.warnings:
            self.warnings.append(message)

    def warn_once(self, key: str, message: str) -> None:
        """Warn ``message`` unless a warning holding ``key`` was given."""
        if not any(key in w for w in self.warnings):
            self.warnings.append(message)

    # -- moves ---------------------------------------------------------------------------------
    def _end(self, end, line: int, column: int) -> np.ndarray | None:
        """The end as an array; None for the first move (it positions the tool)."""
        end = np.array(end, dtype=np.float64).reshape(3)
        if not (abs(end[0]) <= MAX_COORD_M and abs(end[1]) <= MAX_COORD_M
                and abs(end[2]) <= MAX_COORD_M):  # nan too; no numpy call per move
            k = int(np.argmax(np.abs(end)))
            raise self.error(f"{'XYZ'[k]} {end[k] * 1e3:.6g} mm (machine coordinates, offsets "
                             f"included): out of range (|{'XYZ'[k]}| <= {MAX_COORD_M * 1e3:g} mm)",
                             line, column)
        if self.start is None:  # the first move positions the tool
            self.start = self.pos = end
            return None
        if len(self.segments) >= MAX_SEGMENTS:
            raise self.error(f"more than {MAX_SEGMENTS} moves (the limit of one program)",
                             line, column)
        return end

    def traverse(self, end, line: int, column: int = 1) -> None:
        """A G0 move to ``end`` (m)."""
        end = self._end(end, line, column)
        if end is None:
            return
        start, self.pos = self.pos, end
        if start[0] != end[0] or start[1] != end[1] or start[2] != end[2]:  # no numpy call
            self.segments.append(Line(start, end, math.inf, rapid=True, line=line,
                                      blend_tol_m=self.blend_tol_m))

    def feed(self, end, line: int, column: int = 1) -> None:
        """A straight feed move to ``end`` (m) at the feed set last."""
        if self.feed_m_s is None:
            raise self.error("feed move before any F word (feed rate)", line, column)
        end = self._end(end, line, column)
        if end is None:
            return
        start, self.pos = self.pos, end
        if start[0] != end[0] or start[1] != end[1] or start[2] != end[2]:
            self.segments.append(Line(start, end, self.feed_m_s, line=line,
                                      blend_tol_m=self.blend_tol_m))
        self.feed_plane = self.plane

    def arc(self, end, center, rotation: int, line: int, column: int = 1, *,
            end_tol_m: float, unit_m: float = 1e-3) -> None:
        """An arc feed in the current plane to ``end`` about ``center`` (m; only its in-plane
        coordinates are used), ``rotation`` as LinuxCNC's ARC_FEED.

        ``end_tol_m`` bounds |radius to end - radius to start|; ``unit_m`` (program unit, m)
        is for the messages only.
        """
        if self.feed_m_s is None:
            raise self.error("feed move before any F word (feed rate)", line, column)
        if self.start is None:
            raise self.error("the first move is an arc: its start point is unknown", line, column)
        end = self._end(end, line, column)
        i, j, n = PLANES[self.plane]
        start = self.pos
        c = np.array(center, dtype=np.float64).reshape(3).copy()
        c[n] = start[n]
        a, b, cc = start[[i, j]], end[[i, j]], c[[i, j]]
        r0, r1 = float(np.hypot(*(a - cc))), float(np.hypot(*(b - cc)))
        unit = "in" if unit_m == 0.0254 else "mm"
        if r0 == 0.0:
            raise self.error("arc radius is zero", line, column)
        if abs(r1 - r0) > end_tol_m:
            raise self.error(f"arc end point is off the circle: radius to start {r0 / unit_m:g}, "
                             f"to end {r1 / unit_m:g} {unit} (difference above "
                             f"{end_tol_m / unit_m:g} {unit}: oga plans circular arcs, not "
                             "spirals)", line, column)
        self.pos = end
        self.segments.append(Arc(start, end, c, self.plane, arc_sweep(a, b, cc, rotation),
                                 self.feed_m_s, line=line, blend_tol_m=self.blend_tol_m))
        self.feed_plane = self.plane

    def stop(self) -> None:
        """The motion stops exactly at the end of the last move (a dwell, a tool change)."""
        if self.segments and self.segments[-1].blend_tol_m != 0.0:
            self.segments[-1] = replace(self.segments[-1], blend_tol_m=0.0)

    def path(self) -> Path:
        """The Path of the moves so far."""
        return Path(start=self.pos if self.start is None else self.start,
                    segments=tuple(self.segments), plane=self.feed_plane or self.plane,
                    source=self.source, warnings=tuple(self.warnings))
