"""G-code reader: the RS274/LinuxCNC dialect as CAM post-processors write it.

:func:`parse_gcode` turns program text into a :class:`feedplan.path.Path` of
lines and arcs in metres, feeds in m/s, every segment tagged with its 1-based
source line.

Supported
---------
- G0 / G1 / G2 / G3, modal over coordinate-only lines (``G00`` alone on a line,
  coordinates on the next); G80 cancels the motion mode.
- Arcs with incremental I/J/K centre offsets (from the start point) or the R
  form (R > 0 the arc of at most 180 deg, R < 0 the longer one); full circles
  with I/J/K when the end equals the start; helical arcs (move along the
  plane normal). The end point must lie on the circle within 0.05 mm (mm
  programs) or 0.002 in (inch programs), LinuxCNC's rule; the programmed end
  and centre are kept as given.
- G17 / G18 / G19 planes with the arc sense of :mod:`feedplan.path`; G20 / G21
  (inch / mm; mm and a warning when a move comes before either); G90; G94 with
  F in program units per minute (modal; a feed move before any F is an error).
  F is converted with the units in effect when it is read, so its physical
  speed survives a later G20/G21 (as in LinuxCNC); in a block holding both,
  G20/G21 applies first.
- ``( )`` comments (anywhere) and ``;`` to end of line, N words, any letter
  case, spaces and TABs inside words (``X- .992`` is X-0.992), leading- and
  trailing-dot numbers, ``%`` lines (a second one ends the program), M2 / M30
  (what follows is ignored).
- Path control, modal, as LinuxCNC means it, on the end of every move programmed
  while it is in effect (``blend_tol_m`` of :class:`~feedplan.path.Line` and
  :class:`~feedplan.path.Arc`): G61 and G61.1 stop exactly at every corner (0); G64
  blends corners within the plan's tolerance (None; also before any G61/G64); G64 P
  blends within P program units (P0 is G64 without P, as in LinuxCNC). Q (LinuxCNC's
  naive-CAM tolerance) is read and not used: runs of short lines are always fitted
  within a share of the tolerance (:mod:`feedplan.fit`).
- Skipped (no motion): S, T, M0 M1 M3-M9, G4 P (dwell), G8 (lathe radius
  mode), G40, G49, G54.
- G28 / G30 / G53 (moves to machine positions) after the last feed move end
  the program with a warning; before it they are refused.

Everything else (``#`` parameters, ``[ ]`` expressions, O-words, G91, G91.1,
G90.1, cutter compensation, splines, G7, G93/G95, canned cycles, G33, other
work systems, axes the machine lacks, unknown G/M codes or letters, numbers
that do not parse) raises :class:`oga.errors.GcodeError` naming the line, the
column of the offending word and the feature.

Start point: the tool starts at rest where the first motion block puts it
(axes not named yet are 0); that positioning move is not a segment. Zero-length
moves are dropped; G0 moves are ``Line(rapid=True, feed_m_s=inf)``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from feedplan.path import PLANES, Arc, Line, Path
from oga.defaults import MAX_COORD_M, MAX_SEGMENTS
from oga.errors import GcodeError, OptionError

__all__ = ["parse_gcode", "MM_M", "INCH_M", "ARC_END_TOL_MM", "ARC_END_TOL_IN"]

#: Metres per program unit under G21 and G20.
MM_M = 1e-3
INCH_M = 0.0254
#: Largest |radius to end - radius to start| of an arc (LinuxCNC's rule), program units.
ARC_END_TOL_MM = 0.05
ARC_END_TOL_IN = 0.002

_TOKEN = re.compile(
    r"[ \t]*(?:(?P<comment>\([^)]*\))"
    r"|(?P<rest>;.*)"
    r"|(?P<letter>[A-Za-z])(?P<number>[-+0-9. \t]*)"
    r"|(?P<bad>.))"
)
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
_BAD_CHAR = {
    "#": "# parameters are not supported",
    "[": "[ ] expressions are not supported",
    "(": "comment is not closed: ')' is missing",
    "/": "block delete '/' is not supported",
}


def _g_name(code: int) -> str:
    """``G61.1`` from the key 611 (G codes are keyed by ten times their number)."""
    return f"G{code // 10}" + (f".{code % 10}" if code % 10 else "")


_GROUP = {
    **dict.fromkeys((0, 10, 20, 30, 800), "motion"),
    **dict.fromkeys((170, 180, 190), "plane"),
    **dict.fromkeys((200, 210), "units"),
    **dict.fromkeys((610, 611, 640), "path control"),
    **dict.fromkeys((40, 280, 300, 530), "non-modal"),
    900: "distance", 940: "feed mode", 400: "cutter compensation",
    490: "tool length", 540: "work system", 80: "lathe mode",
}
_PLANE = {170: "xy", 180: "zx", 190: "yz"}
_PLANE_G = {"xy": "G17", "zx": "G18", "yz": "G19"}
_UNIT_M = {200: INCH_M, 210: MM_M}
_MACHINE_MOVE = {
    280: "G28 (move to the machine's home position)",
    300: "G30 (move to the machine's second home position)",
    530: "G53 (move in machine coordinates)",
}
_REFUSED_G = {
    50: "G5 (cubic spline)", 51: "G5.1 (quadratic spline)", 52: "G5.2 (NURBS)",
    70: "G7 (lathe diameter mode)", 100: "G10 (setting offsets and tool data)",
    330: "G33 (spindle-synchronised motion)", 331: "G33.1 (rigid tapping)",
    410: "G41 (cutter radius compensation)", 411: "G41.1 (cutter radius compensation)",
    420: "G42 (cutter radius compensation)", 421: "G42.1 (cutter radius compensation)",
    430: "G43 (tool length offset)", 431: "G43.1 (tool length offset)",
    432: "G43.2 (tool length offset)",
    **{k: f"{_g_name(k)} (work coordinate system other than G54)"
       for k in (550, 560, 570, 580, 590, 591, 592, 593)},
    **{k: f"{_g_name(k)} (canned cycle)"
       for k in (730, 760, 810, 820, 830, 840, 850, 860, 870, 880, 890)},
    901: "G90.1 (absolute arc centre mode)",
    910: "G91 (incremental distance mode)",
    911: "G91.1 (arc centre distance mode; incremental I/J/K is the default, omit it)",
    920: "G92 (coordinate system offset)", 930: "G93 (inverse time feed mode)",
    950: "G95 (feed per revolution)",
}
_SKIPPED_M = {0, 1, 3, 4, 5, 6, 7, 8, 9}
_END_M = {2, 30}
_AXIS_LETTERS = "XYZ"
_FOREIGN_AXES = "ABCUVW"
_ARGS = set("XYZIJKRFSTPQ")


@dataclass(frozen=True)
class _Word:
    letter: str
    value: float
    column: int


def _words(text: str, line: int, source: str) -> list[_Word]:
    """The words of one program line (comments and N words dropped), upper-case letters."""
    raw = []
    for m in _TOKEN.finditer(text):
        letter, number, bad = m.group("letter", "number", "bad")
        if letter is not None:
            column = m.start("letter") + 1
            if letter in "Oo":
                raise GcodeError("O-words (subroutines, loops, conditions) are not supported",
                                 line, column, source)
            raw.append((letter.upper(), number, column))
        elif bad is not None:
            raise GcodeError(_BAD_CHAR.get(bad, f"unexpected character {bad!r}"),
                             line, m.start("bad") + 1, source)
        elif m.group("rest") is not None:
            break
    words = []
    for k, (letter, number, column) in enumerate(raw):
        digits = number.replace(" ", "").replace("\t", "")
        if not _NUMBER.fullmatch(digits):
            what = f"number {digits!r} does not parse" if digits else "has no number"
            raise GcodeError(f"{letter} word: {what}", line, column, source)
        after = raw[k + 1] if k + 1 < len(raw) else None
        if after and after[0] == "E" and number and after[2] == column + 1 + len(number):
            raise GcodeError(f"{letter} word: {digits}E{after[1].strip()} has an exponent, which "
                             "G-code numbers do not have (coordinate out of range? write plain "
                             "digits)", line, column, source)
        value = float(digits)
        if not math.isfinite(value):
            raise GcodeError(f"{letter} word: number out of range ({len(digits)} digits)",
                             line, column, source)
        if letter != "N":
            words.append(_Word(letter, value, column))
    return words


def _arc_sweep(a: np.ndarray, b: np.ndarray, c: np.ndarray, ccw: bool) -> float:
    """Signed sweep (rad) from in-plane point ``a`` to ``b`` about centre ``c``.

    Positive (counter-clockwise) in (0, 2 pi] for G3, negative in [-2 pi, 0)
    for G2; ``a == b`` is a full circle.
    """
    if np.array_equal(a, b):
        return 2 * math.pi if ccw else -2 * math.pi
    u, v = a - c, b - c
    angle = math.atan2(u[0] * v[1] - u[1] * v[0], u[0] * v[0] + u[1] * v[1])
    if ccw:
        return angle if angle > 0 else angle + 2 * math.pi
    return angle if angle < 0 else angle - 2 * math.pi


def _r_center(a: np.ndarray, b: np.ndarray, r: float, ccw: bool) -> np.ndarray:
    """Centre of the R-form arc from in-plane point ``a`` to ``b != a``.

    R > 0 selects the arc of at most 180 deg, R < 0 the longer one; a chord
    longer than the diameter gives the half circle (the caller bounds the excess).
    """
    chord = b - a
    d = float(np.hypot(chord[0], chord[1]))
    h, rr = d / 2, abs(r)
    offset = math.sqrt(max((rr - h) * (rr + h), 0.0))  # stable for R >> chord
    left = (ccw and r > 0) or (not ccw and r < 0)
    normal = np.array([-chord[1], chord[0]]) / d
    return (a + b) / 2 + (offset if left else -offset) * normal


class _Reader:
    """Modal state while reading one program; :meth:`block` per line, :meth:`path` at the end."""

    def __init__(self, source: str, axes: str) -> None:
        self.source = source
        self.axes = axes
        self.absent_axes = _FOREIGN_AXES + "".join(a for a in _AXIS_LETTERS
                                                   if a.lower() not in axes)
        self.plane = "xy"
        self.feed_plane: str | None = None  # plane at the last feed move
        self.unit_m: float | None = None  # None until G20/G21
        self.motion: int | None = None  # 0, 10, 20, 30 (G0..G3) or None
        self.feed_m_s: float | None = None
        self.blend_tol_m: float | None = None  # path control: None G64, 0 G61, > 0 G64 P
        self.pos: np.ndarray | None = None  # None until the first motion block
        self.start: np.ndarray | None = None
        self.segments: list[Line | Arc] = []
        self.warnings: list[str] = []
        self.machine_move: tuple[int, int, str] | None = None  # line, column, what
        self.percent = 0

    def error(self, message: str, line: int, column: int) -> GcodeError:
        return GcodeError(message, line, column, self.source)

    # -- one block ---------------------------------------------------------------------------
    def block(self, text: str, n: int) -> bool:
        """Apply one program line; True when the program ends there."""
        if text.strip() == "%":
            self.percent += 1
            return self.percent >= 2
        words = _words(text, n, self.source)
        gcodes = self._gcodes(words, n)
        args = self._args(words, n)
        ends = self._mcodes(words, n)
        self._settings(gcodes, args, n)
        if "motion" in gcodes:
            code = gcodes["motion"][0]
            self.motion = None if code == 800 else code
        axis = {a: args[a] for a in _AXIS_LETTERS if a in args}
        arc = {a: args[a] for a in "IJKR" if a in args}
        special = gcodes.get("non-modal")
        if special and special[0] in _MACHINE_MOVE:
            self._machine_move(special, axis, arc, n)
        elif axis or arc:
            self._move(axis, arc, gcodes.get("motion"), n)
        return ends

    def _gcodes(self, words: list[_Word], n: int) -> dict[str, tuple[int, _Word]]:
        """Supported G codes of the block by modal group; refuses the others."""
        out: dict[str, tuple[int, _Word]] = {}
        for w in words:
            if w.letter != "G":
                continue
            code = round(w.value * 10)
            if abs(w.value * 10 - code) > 1e-6:
                raise self.error(f"G{w.value:g} is not a G-code", n, w.column)
            if code in _REFUSED_G:
                raise self.error(f"{_REFUSED_G[code]} is not supported", n, w.column)
            if code not in _GROUP:
                raise self.error(f"{_g_name(code)} is not a supported G-code", n, w.column)
            group = _GROUP[code]
            if group in out:
                raise self.error(f"{_g_name(out[group][0])} and {_g_name(code)} are in the same "
                                 f"modal group ({group}) in one block", n, w.column)
            out[group] = (code, w)
        return out

    def _mcodes(self, words: list[_Word], n: int) -> bool:
        """Checks the M codes of the block; True if one ends the program (M2, M30)."""
        ends = False
        for w in words:
            if w.letter != "M":
                continue
            if w.value not in _SKIPPED_M and w.value not in _END_M:
                raise self.error(f"M{w.value:g} is not a supported M-code", n, w.column)
            ends = ends or w.value in _END_M
        return ends

    def _args(self, words: list[_Word], n: int) -> dict[str, _Word]:
        """The non-G/M words of the block by letter; refuses foreign letters and repeats."""
        out: dict[str, _Word] = {}
        for w in words:
            letter = w.letter
            if letter in "GM":
                continue
            if letter in self.absent_axes:
                raise self.error(f"axis {letter} is not on this machine (axes "
                                 f"{self.axes.upper()})", n, w.column)
            if letter not in _ARGS:
                raise self.error(f"{letter} words are not supported", n, w.column)
            if letter in out:
                raise self.error(f"{letter} word appears twice in one block", n, w.column)
            out[letter] = w
        return out

    def _settings(self, gcodes: dict, args: dict[str, _Word], n: int) -> None:
        """Plane, units, feed; checks that P and Q words have a G code that uses them."""
        if "plane" in gcodes:
            self.plane = _PLANE[gcodes["plane"][0]]
        if "units" in gcodes:
            self.unit_m = _UNIT_M[gcodes["units"][0]]
        if "F" in args:
            f = args["F"]
            if not f.value > 0:
                raise self.error(f"F {f.value:g}: the feed must be positive", n, f.column)
            self.feed_m_s = f.value * self._unit(n) / 60.0
        dwell = gcodes.get("non-modal", (None,))[0] == 40
        control = gcodes.get("path control", (None,))[0]
        blend = control == 640
        if control in (610, 611):
            self.blend_tol_m = 0.0
        elif blend:
            p = args.get("P")
            if p is not None and not p.value >= 0:
                raise self.error(f"P {p.value:g}: the blending tolerance of G64 must not be "
                                 "negative", n, p.column)
            self.blend_tol_m = p.value * self._unit(n) if p is not None and p.value > 0 else None
        if dwell and "P" not in args:
            raise self.error("G4 (dwell) needs a P word", n, gcodes["non-modal"][1].column)
        for letter, used in (("P", dwell or blend), ("Q", blend)):
            if letter in args and not used:
                raise self.error(f"{letter} word without a G-code that uses it (G4, G64)",
                                 n, args[letter].column)

    def _unit(self, n: int) -> float:
        if self.unit_m is None:
            self.unit_m = MM_M
            self.warnings.append(f"line {n}: no G20/G21 before the first move or feed; "
                                 "millimetres assumed")
        return self.unit_m

    # -- motion ------------------------------------------------------------------------------
    def _machine_move(self, special, axis: dict, arc: dict, n: int) -> None:
        """G28/G30/G53: ends the program if no feed move follows (checked in :meth:`_move`)."""
        code, word = special
        if arc:
            w = min(arc.values(), key=lambda w: w.column)
            raise self.error(f"{w.letter} word in a block with {_g_name(code)}", n, w.column)
        if self.machine_move is None:
            self.machine_move = (n, word.column, _MACHINE_MOVE[code])
        if code == 530 and axis and self.motion != 0:
            raise self.error("G53 (move in machine coordinates) is supported only with G0 at "
                             "the end of the program", n, word.column)

    def _move(self, axis: dict[str, _Word], arc: dict[str, _Word], motion_word, n: int) -> None:
        """One motion block with axis and/or arc words."""
        first = min([*axis.values(), *arc.values()], key=lambda w: w.column)
        column = motion_word[1].column if motion_word else first.column
        if self.motion is None:
            raise self.error(f"{first.letter} word without a motion mode (G0, G1, G2, G3) in "
                             "effect", n, first.column)
        is_arc = self.motion in (20, 30)
        if arc and not is_arc:
            w = min(arc.values(), key=lambda w: w.column)
            raise self.error(f"{w.letter} word outside a G2/G3 arc", n, w.column)
        if self.motion != 0:
            if self.machine_move is not None:
                line, col, what = self.machine_move
                raise self.error(f"{what} before the last feed move (line {n}) cannot be "
                                 "planned without the machine's home position", line, col)
            if self.feed_m_s is None:
                raise self.error("feed move before any F word (feed rate)", n, column)
        unit = self._unit(n)
        for w in (*axis.values(), *arc.values()):
            self._in_range(w, n)
        end = np.zeros(3) if self.pos is None else self.pos.copy()
        for w in axis.values():
            end["XYZ".index(w.letter)] = w.value * unit
        if self.pos is None:
            if is_arc:
                raise self.error("the first move is an arc: its start point is unknown",
                                 n, column)
            self.pos = self.start = end
            return
        if self.machine_move is not None:  # rapids after G28/G30/G53 are not planned
            return
        start, self.pos = self.pos, end
        if len(self.segments) >= MAX_SEGMENTS:
            raise self.error(f"more than {MAX_SEGMENTS} moves (the limit of one program)",
                             n, column)
        if is_arc:
            self.segments.append(self._arc(start, end, axis, arc, n, column))
        elif start[0] != end[0] or start[1] != end[1] or start[2] != end[2]:  # no numpy call
            rapid = self.motion == 0
            self.segments.append(Line(start, end, math.inf if rapid else self.feed_m_s,
                                      rapid=rapid, line=n, blend_tol_m=self.blend_tol_m))
        if self.motion != 0:
            self.feed_plane = self.plane

    def _in_range(self, w: _Word, n: int) -> None:
        """Refuses a coordinate, arc offset or radius beyond :data:`MAX_COORD_M`."""
        if abs(w.value) * self.unit_m > MAX_COORD_M:
            unit = "in" if self.unit_m == INCH_M else "mm"
            raise self.error(f"{w.letter} {w.value:.6g}: coordinate out of range (|{w.letter}| "
                             f"<= {MAX_COORD_M / self.unit_m:.6g} {unit})", n, w.column)

    def _arc(self, start, end, axis, arc, n: int, column: int) -> Arc:
        """The G2/G3 arc from ``start`` to ``end`` (metres) of one block."""
        i, j, normal = PLANES[self.plane]
        letters = "XYZ"
        g = f"{_PLANE_G[self.plane]} ({self.plane.upper()} plane)"
        if letters[i] not in axis and letters[j] not in axis:
            raise self.error(f"arc in {g} needs {letters[i]} or {letters[j]}", n, column)
        tol = (ARC_END_TOL_IN if self.unit_m == INCH_M else ARC_END_TOL_MM) * self.unit_m
        ccw = self.motion == 30
        a, b = start[[i, j]], end[[i, j]]
        offsets = {w.letter: w for w in arc.values() if w.letter != "R"}
        if "IJK"[normal] in offsets:
            w = offsets["IJK"[normal]]
            raise self.error(f"{w.letter} word in an arc in {g}", n, w.column)
        if "R" in arc and offsets:
            w = max(arc.values(), key=lambda w: w.column)
            raise self.error("arc with both R and I/J/K", n, w.column)
        u = self.unit_m
        if "R" in arc:
            w = arc["R"]
            chord = float(np.hypot(*(b - a)))
            if chord == 0.0:
                raise self.error("an R-form arc needs an end point different from its start "
                                 "(use I/J/K for a full circle)", n, w.column)
            if chord / 2 - abs(w.value) * u > tol:
                raise self.error(f"R {abs(w.value):g} is too small to reach the end point "
                                 f"{chord / u:g} away", n, w.column)
            c = _r_center(a, b, w.value * u, ccw)
        elif offsets:
            w = min(offsets.values(), key=lambda w: w.column)
            off = [offsets[k].value * u if k in offsets else 0.0
                   for k in ("IJK"[i], "IJK"[j])]
            c = a + np.array(off)
            r0, r1 = float(np.hypot(*(a - c))), float(np.hypot(*(b - c)))
            if r0 == 0.0:
                raise self.error("arc radius is zero (I/J/K offsets are 0)", n, w.column)
            if abs(r1 - r0) > tol:
                raise self.error(f"arc end point is off the circle: radius to start "
                                 f"{r0 / u:g}, to end {r1 / u:g} (difference above "
                                 f"{tol / u:g})", n, w.column)
        else:
            offs = "IJK"[i] + "/" + "IJK"[j]
            raise self.error(f"arc needs {offs} centre offsets or R", n, column)
        center = start.copy()
        center[[i, j]] = c
        return Arc(start, end, center, self.plane, _arc_sweep(a, b, c, ccw),
                   self.feed_m_s, line=n, blend_tol_m=self.blend_tol_m)

    def path(self) -> Path:
        if self.machine_move is not None:
            line, _, what = self.machine_move
            self.warnings.append(f"line {line}: {what} ends the program (moves to machine "
                                 "positions are not planned)")
        return Path(start=np.zeros(3) if self.start is None else self.start,
                    segments=tuple(self.segments), plane=self.feed_plane or self.plane,
                    source=self.source, warnings=tuple(self.warnings))


def parse_gcode(text: str, source: str = "", axes: str = "xyz") -> Path:
    """Read a G-code program (RS274/LinuxCNC dialect, see the module notes).

    Parameters
    ----------
    text : str
        The program.
    source : str, optional
        Its name (file name) for messages and ``Path.source``.
    axes : str, optional
        The machine's linear axes among ``"xyz"``; a word for any other axis is refused.

    Returns
    -------
    Path
        Lines and arcs in metres, feeds in m/s (rapids ``inf``), each segment with
        its 1-based source line; ``warnings`` holds non-fatal remarks.

    Raises
    ------
    GcodeError
        The program is outside the supported dialect or inconsistent (line, column, feature).
    OptionError
        ``axes`` is not a set of letters among x, y, z.
    """
    axes_l = axes.lower()
    if not axes_l or set(axes_l) - set("xyz") or len(set(axes_l)) != len(axes_l):
        raise OptionError(f"axes must be distinct letters among x, y, z, got {axes!r}")
    reader = _Reader(source, axes_l)
    for n, line in enumerate(text.split("\n"), start=1):
        if reader.block(line.rstrip("\r"), n):
            break
    return reader.path()
