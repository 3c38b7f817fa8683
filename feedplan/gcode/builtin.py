"""The built-in G-code reader: the RS274/LinuxCNC dialect as CAM post-processors write it.

:func:`read_builtin` turns program text into a :class:`~feedplan.path.Path` of lines and
arcs in machine coordinates and metres, feeds in m/s, every segment tagged with its 1-based
source line. It executes each block in LinuxCNC's order (feed, tool, dwell, plane, units,
tool length, work system, path control, distance modes, home and offsets, motion, stop) and
emits LinuxCNC's canonical moves into :class:`~feedplan.gcode.moves.PathBuilder`, so that it
means what LinuxCNC means: the readers' paths are compared move by move in the tests.

Read
----
- Motion G0 G1 G2 G3 (modal over coordinate-only lines; G80 cancels it, ``G0 G80`` in one
  block is G0 as in LinuxCNC); G90 / G91 (absolute / incremental distance); arcs with I/J/K
  (incremental from the start under G91.1, the default, absolute under G90.1) or R (R > 0 the
  arc of at most 180 deg, R < 0 the longer one), P full turns, helical arcs, full circles;
  LinuxCNC's arc checks (the end on the circle within 0.0283 mm or 0.1 %, R reaching the end
  within 0.00127 mm), and oga's own: the end within 0.05 mm (0.002 in) of the circle.
- G17 / G18 / G19 with the arc sense of :mod:`feedplan.path`; G20 / G21 anywhere (mm and a
  warning when a move comes before either); F in program units per minute (G94), read with
  the units in effect before the block's G20/G21 (LinuxCNC's order), its speed kept across a
  later unit change.
- Canned cycles G73 G74 G81-G87 G89 with G98 / G99, R, Q, P, L, also in G91 and in the G18 /
  G19 planes (:mod:`feedplan.gcode.cycles`); they run in exact-path mode (no blending).
- G28 / G30 (through the given point to the home position of the named axes, of all without
  any: the ``G28 G91 Z0`` idiom), G28.1 / G30.1 (store the position), G53 (G0/G1 in machine
  coordinates), G54-G59.3 work offsets, G92 / G92.1 / G92.2 / G92.3; home positions and work
  offsets from the :class:`~feedplan.gcode.setup.Setup` (default: machine zero, no offset).
- Tools: T (select; with a tool table the tool must be in it), M6 (change: the motion stops;
  no move, as LinuxCNC without ``[EMCIO]TOOL_CHANGE_POSITION``: a tool change is a pause of
  unknown length, which no gain table spans in time anyway); G43 (the tool in
  the spindle) / G43 H / G43.2 H (add) / G43.1 (given) / G49 tool length offsets, lengths from
  the tool table (without one: length 0 and a warning: a constant Z shift changes no gain).
- Dwell G4 P (the motion stops there); path control G61 / G61.1 (stop at every corner), G64
  (blend within the plan's tolerance), G64 P (within P); Q read, not used.
- No-motion words: S, M0 M1 M60 (program stops: the plan does not wait), M2 / M30 (end),
  M3 M4 M5 (spindle), M7 M8 M9 (coolant), M48-M53 (overrides), M62-M65 P (outputs), G40,
  G94, G97, G8, G17; ``%`` lines (a second one ends the program), O program numbers
  (``O1234``), N words, ``/`` block delete (LinuxCNC's switch is off: the block runs),
  comments, blanks anywhere; grbl ``$`` lines are skipped with a warning.

Not read here (a :class:`~oga.errors.GcodeError` with ``unsupported`` set: ``--reader auto``
passes the program to LinuxCNC's interpreter): cutter compensation G41/G42, ``#`` parameters,
``[ ]`` expressions, O-word control flow, G10, G52, G88, splines, lathe cycles, G33, probing,
G93/G95, G96, M19, M61, M66-M73, user M codes. Anything else that is wrong names the line, the
column of the offending word and the feature.
"""

from __future__ import annotations

import math

import numpy as np

from feedplan.gcode.cycles import CYCLES, CycleMemory, cycle_moves
from feedplan.gcode.lexer import Word, unsupported, words
from feedplan.gcode.moves import PathBuilder
from feedplan.gcode.setup import Setup
from feedplan.path import PLANES, Path
from oga.defaults import MAX_COORD_M
from oga.errors import GcodeError

__all__ = ["read_builtin", "MM_M", "INCH_M", "ARC_END_TOL_MM", "ARC_END_TOL_IN"]

#: Metres per program unit under G21 and G20.
MM_M = 1e-3
INCH_M = 0.0254
#: Largest |radius to end - radius to start| of an arc oga plans, program units.
ARC_END_TOL_MM = 0.05
ARC_END_TOL_IN = 0.002
#: LinuxCNC's arc checks (interp_internal.hh): centre-format radius difference (absolute, and
#: relative above it), R-format reach, zero radius; program units.
_LCNC_ARC_ABS = {MM_M: 2 * 0.01 * math.sqrt(2), INCH_M: 2 * 0.001 * math.sqrt(2)}
_LCNC_ARC_REL = 0.001
_LCNC_RADIUS_TOL = {MM_M: 0.00005 * 25.4, INCH_M: 0.00005}


#: The warning for a program without M2, M30 or a closing % (LinuxCNC refuses to run it).
NO_END = ("the program has no end (M2, M30 or a closing %): LinuxCNC's interpreter refuses to "
          "run it as it is")


def _g_name(code: int) -> str:
    """``G61.1`` from the key 611 (G codes are keyed by ten times their number)."""
    return f"G{code // 10}" + (f".{code % 10}" if code % 10 else "")


_GROUP = {
    **dict.fromkeys((0, 10, 20, 30, 800, *CYCLES), "motion"),
    **dict.fromkeys((170, 180, 190), "plane"),
    **dict.fromkeys((200, 210), "units"),
    **dict.fromkeys((610, 611, 640), "path control"),
    **dict.fromkeys((40, 280, 281, 300, 301, 530, 920, 921, 922, 923), "non-modal"),
    **dict.fromkeys((900, 910), "distance"),
    **dict.fromkeys((901, 911), "arc distance"),
    **dict.fromkeys((430, 431, 432, 490), "tool length"),
    **dict.fromkeys((540, 550, 560, 570, 580, 590, 591, 592, 593), "work system"),
    **dict.fromkeys((980, 990), "retract"),
    940: "feed mode", 400: "cutter compensation", 80: "lathe mode", 970: "spindle mode",
}
_WORK = {k: n for n, k in enumerate((540, 550, 560, 570, 580, 590, 591, 592, 593))}
_PLANE = {170: "xy", 180: "zx", 190: "yz"}
_PLANE_G = {"xy": "G17", "zx": "G18", "yz": "G19"}
_UNIT_M = {200: INCH_M, 210: MM_M}
#: G codes LinuxCNC reads and this reader does not.
_LINUXCNC_G = {
    50: "G5 (cubic spline)", 51: "G5.1 (quadratic spline)", 52: "G5.2 (NURBS)",
    53: "G5.3 (NURBS end)", 70: "G7 (lathe diameter mode)", 100: "G10 (setting offsets and "
    "tool data)", 171: "G17.1 (UV plane)", 181: "G18.1 (UW plane)", 191: "G19.1 (VW plane)",
    330: "G33 (spindle-synchronised motion)", 331: "G33.1 (rigid tapping)",
    382: "G38.2 (probing)", 383: "G38.3 (probing)", 384: "G38.4 (probing)",
    385: "G38.5 (probing)", 410: "G41 (cutter radius compensation)",
    411: "G41.1 (cutter radius compensation)", 420: "G42 (cutter radius compensation)",
    421: "G42.1 (cutter radius compensation)", 520: "G52 (local coordinate offset)",
    700: "G70 (lathe finishing cycle)", 710: "G71 (lathe roughing cycle)",
    711: "G71.1 (lathe roughing cycle)", 712: "G71.2 (lathe roughing cycle)",
    720: "G72 (lathe facing cycle)", 721: "G72.1 (lathe facing cycle)",
    722: "G72.2 (lathe facing cycle)", 760: "G76 (threading cycle)",
    880: "G88 (boring cycle with manual retract)", 930: "G93 (inverse time feed mode)",
    950: "G95 (feed per revolution)", 960: "G96 (constant surface speed)",
}
_M_GROUP = {**dict.fromkeys((0, 1, 2, 30, 60), "stopping"), 6: "tool",
            **dict.fromkeys((3, 4, 5), "spindle"), **dict.fromkeys((7, 8, 9), "coolant"),
            **dict.fromkeys(range(48, 54), "override"), **dict.fromkeys(range(62, 66), "output")}
_LINUXCNC_M = {19: "M19 (spindle orientation)", 61: "M61 (set the tool number)",
               66: "M66 (wait on input)",
               67: "M67 (analog output)", 68: "M68 (analog output)", 70: "M70 (save modal "
               "state)", 71: "M71 (invalidate saved state)", 72: "M72 (restore modal state)",
               73: "M73 (save and restore modal state)", 98: "M98 (subprogram call)",
               99: "M99 (subprogram return)"}
_AXES = "XYZ"
_FOREIGN_AXES = "ABCUVW"
_ARGS = set("XYZIJKRFSTPQLH")


def _plane_roles(plane: str) -> tuple[str, str, str]:
    """The axis letters of the plane's (first, second, normal) roles."""
    return tuple(_AXES[k] for k in PLANES[plane])


class _Reader:
    """Modal state while reading one program; :meth:`block` per line, :meth:`path` at the end."""

    def __init__(self, source: str, axes: str, setup: Setup) -> None:
        self.source = source
        self.axes = axes
        self.absent_axes = _FOREIGN_AXES + "".join(a for a in _AXES if a.lower() not in axes)
        self.setup = setup
        self.out = PathBuilder(source, setup.work_offsets_m[0])
        self.unit_m: float | None = None  # None until G20/G21
        self.motion: int | None = None  # 0, 10, 20, 30, a cycle, or None (G80)
        self.incremental = False
        self.arc_absolute = False
        self.retract_r = True  # G99, LinuxCNC's default
        self.blend_tol_m: float | None = None
        self.work = 0
        self.g92 = np.zeros(3)
        self.g92_saved = np.zeros(3)
        self.tlo = np.zeros(3)
        self.g28 = setup.g28_m.copy()
        self.g30 = setup.g30_m.copy()
        self.selected = 0  # T0: no tool
        self.spindle_tool: int | None = None
        self.spindle = 0  # 1 clockwise, -1 counter-clockwise
        self.cycle = CycleMemory()
        self.percent = 0
        self.ended = False
        # the interpreter's position in program units (LinuxCNC's current_x/y/z): the moves
        # are computed there, as LinuxCNC does, and go to the path in machine coordinates
        self.cur = np.zeros(3)

    def error(self, message: str, line: int, column: int) -> GcodeError:
        return GcodeError(message, line, column, self.source)

    @property
    def offsets(self) -> np.ndarray:
        """Machine minus program coordinates: work offset, G92 and tool length, m."""
        return self.setup.work_offsets_m[self.work] + self.g92 + self.tlo

    @property
    def unit(self) -> float:
        """Metres per program unit (mm until G20/G21, LinuxCNC's start-up units)."""
        return MM_M if self.unit_m is None else self.unit_m

    def machine(self, p) -> np.ndarray:
        """Machine coordinates (m) of the program point ``p`` (program units)."""
        return np.asarray(p, dtype=np.float64) * self.unit + self.offsets

    def _offsets_changed(self, old: np.ndarray) -> None:
        """The offsets changed (from ``old``, m): the tool stays, its program position moves."""
        self.cur = self.cur + (old - self.offsets) / self.unit

    # -- one block ---------------------------------------------------------------------------
    def block(self, text: str, n: int) -> bool:
        """Apply one program line; True when the program ends there."""
        stripped = text.strip()
        if stripped == "%":
            self.percent += 1
            self.ended = self.percent >= 2
            return self.ended
        if stripped.startswith("$"):
            self.out.warn(f"line {n}: grbl command {stripped[:20]!r} skipped")
            return False
        notes: list[str] = []
        ws = words(text, n, self.source, notes)
        if notes:
            self.out.warn_once("nested comment", f"line {n}: nested comment (Estlcam's tool "
                               "names), read as one comment: LinuxCNC refuses it")
        if not ws:
            return False
        gcodes = self._gcodes(ws, n)
        mcodes = self._mcodes(ws, n)
        args = self._args(ws, n)
        motion = self._motion_to_be(gcodes, args, n)
        self._check_args(gcodes, mcodes, args, motion, n)
        # LinuxCNC's order of execution
        if "F" in args:
            f = args["F"]
            if not f.value > 0:
                raise self.error(f"F {f.value:g}: the feed must be positive", n, f.column)
            self.out.feed_m_s = f.value * self._unit(n) / 60.0
        self._tools(gcodes, mcodes, args, n)
        special = gcodes.get("non-modal", (None, None))
        if special[0] == 40:
            self.out.stop()
        self._modes(gcodes, args, n)
        self.out.blend_tol_m = self.blend_tol_m
        if special[0] in (280, 300):
            self._home(special, args, n)
        elif special[0] in (281, 301):
            home = self.machine(self.cur)
            if special[0] == 281:
                self.g28 = home
            else:
                self.g30 = home
        elif special[0] in (920, 921, 922, 923):
            self._g92(special[0], args, n)
        if motion is not None:
            self._motion(motion, gcodes, args, n)
        self.ended = bool({w.value for w in mcodes.values()} & {2.0, 30.0})
        return self.ended

    def _gcodes(self, ws: list[Word], n: int) -> dict[str, tuple[int, Word]]:
        """The G codes of the block by modal group; refuses the others."""
        out: dict[str, tuple[int, Word]] = {}
        for w in ws:
            if w.letter != "G":
                continue
            code = round(w.value * 10)
            if abs(w.value * 10 - code) > 1e-3 or code < 0 or code > 999:
                raise self.error(f"G{w.value:g} is not a G-code", n, w.column)
            if code in _LINUXCNC_G:
                raise unsupported(_LINUXCNC_G[code], n, w.column, self.source)
            if code not in _GROUP:
                raise self.error(f"{_g_name(code)} is not a G-code LinuxCNC knows", n, w.column)
            group = _GROUP[code]
            if group in out:
                if group == "motion" and 800 in (code, out[group][0]):  # G0 G80: G0
                    if code == 800:
                        continue
                else:
                    raise self.error(f"{_g_name(out[group][0])} and {_g_name(code)} are in "
                                     f"the same modal group ({group}) in one block",
                                     n, w.column)
            out[group] = (code, w)
        return out

    def _mcodes(self, ws: list[Word], n: int) -> dict[str, Word]:
        """The M codes of the block by modal group; refuses the others."""
        out: dict[str, Word] = {}
        for w in ws:
            if w.letter != "M":
                continue
            code = int(w.value)
            if code != w.value or code < 0:
                raise self.error(f"M{w.value:g} is not an M-code", n, w.column)
            if code in _LINUXCNC_M or 100 <= code <= 199:
                what = _LINUXCNC_M.get(code, f"M{code} (user M-code)")
                raise unsupported(what, n, w.column, self.source)
            if code not in _M_GROUP:
                raise self.error(f"M{code} is not an M-code LinuxCNC knows", n, w.column)
            group = _M_GROUP[code]
            if group in out and not {code, int(out[group].value)} == {7, 8}:
                raise self.error(f"M{out[group].value:g} and M{code} are in the same modal "
                                 f"group ({group}) in one block", n, w.column)
            out[group if group not in out else "coolant2"] = w
        if len(out) > 5:
            raise self.error("more than 5 M-codes in one block", n, list(out.values())[5].column)
        return out

    def _args(self, ws: list[Word], n: int) -> dict[str, Word]:
        """The non-G/M words of the block by letter; refuses foreign letters and repeats."""
        out: dict[str, Word] = {}
        for w in ws:
            letter = w.letter
            if letter in "GM":
                continue
            if letter in self.absent_axes:
                raise self.error(f"axis {letter} is not on this machine (axes "
                                 f"{self.axes.upper()})", n, w.column)
            if letter not in _ARGS:
                if letter in "DE":
                    raise unsupported(f"{letter} words", n, w.column, self.source)
                raise self.error(f"{letter} words are not G-code words LinuxCNC knows",
                                 n, w.column)
            if letter in out:
                raise self.error(f"{letter} word appears twice in one block", n, w.column)
            out[letter] = w
        return out

    def _motion_to_be(self, gcodes: dict, args: dict, n: int) -> int | None:
        """The motion the block makes (LinuxCNC's ``enhance_block``), None for none."""
        axis = [args[a] for a in _AXES if a in args]
        special = gcodes.get("non-modal", (None, None))[0]
        covets = special in (280, 300, 920)
        motion = gcodes.get("motion")
        if motion is not None:
            code, word = motion
            if code == 800:
                if axis and not covets:
                    raise self.error("axis words with G80 (cancel the motion mode)",
                                     n, axis[0].column)
                return 800
            if covets:
                raise self.error(f"{_g_name(code)} and {_g_name(special)} both use the axis "
                                 "words of the block", n, word.column)
            if not axis and code not in (0, 10, 20, 30):
                raise self.error(f"{_g_name(code)} without axis words", n, word.column)
            return code
        if covets:
            if not axis and special == 920:
                raise self.error("G92 needs axis words", n, gcodes["non-modal"][1].column)
            return None
        tool_length = gcodes.get("tool length", (None,))[0]
        if axis:
            if tool_length == 431:
                return None  # G43.1 takes the axis words
            if tool_length == 432:
                raise unsupported("G43.2 with axis words", n, axis[0].column, self.source)
            if self.motion is None:
                raise self.error(f"{axis[0].letter} word without a motion mode (G0, G1, G2, G3, "
                                 "a canned cycle) in effect", n, axis[0].column)
            return self.motion
        if any(a in args for a in "IJK") and self.motion in (20, 30):
            return self.motion
        return None

    def _check_args(self, gcodes: dict, mcodes: dict, args: dict, motion, n: int) -> None:
        """Each word has a code that uses it (LinuxCNC's ``check_other_codes``)."""
        special = gcodes.get("non-modal", (None,))[0]
        tool_length = gcodes.get("tool length", (None,))[0]
        control = gcodes.get("path control", (None,))[0]
        m = {int(w.value) for w in mcodes.values()}
        cycle = motion in CYCLES
        arc = motion in (20, 30)
        uses = {
            "H": tool_length in (430, 432), "I": arc or motion == 870,
            "J": arc or motion == 870, "K": arc or motion == 870, "L": cycle,
            "P": special == 40 or control == 640 or arc or motion in (740, 820, 840, 860, 890)
            or bool(m & {50, 51, 52, 53, 62, 63, 64, 65}),
            "Q": motion in (730, 830) or control == 640,
            "R": arc or cycle,
        }
        for letter, used in uses.items():
            if letter in args and not used:
                raise self.error(f"{letter} word without a code that uses it", n,
                                 args[letter].column)
        if special == 40 and "P" not in args:
            raise self.error("G4 (dwell) needs a P word", n, gcodes["non-modal"][1].column)
        if special == 40 and arc:
            raise self.error("G4 (dwell) and an arc both use P", n, gcodes["non-modal"][1].column)
        if arc and "P" in args:
            p = args["P"]
            if abs(p.value - round(p.value)) > 0.001 or round(p.value) < 1:
                raise self.error(f"P {p.value:g}: the turns of an arc must be a whole number "
                                 ">= 1", n, p.column)
        if special == 530:
            if motion not in (0, 10):
                raise self.error("G53 (machine coordinates) needs G0 or G1", n,
                                 gcodes["non-modal"][1].column)
            distance = gcodes.get("distance", (None,))[0]
            if distance == 910 or (distance is None and self.incremental):
                raise self.error("G53 (machine coordinates) in incremental distance mode (G91)",
                                 n, gcodes["non-modal"][1].column)

    def _unit(self, n: int) -> float:
        if self.unit_m is None:
            self.unit_m = MM_M
            self.out.warn(f"line {n}: no G20/G21 before the first move or feed; millimetres "
                          "assumed")
        return self.unit_m

    def _in_range(self, w: Word, n: int) -> float:
        """The word's value in metres; refuses one beyond :data:`MAX_COORD_M`."""
        unit = self._unit(n)
        if abs(w.value) * unit > MAX_COORD_M:
            name = "in" if unit == INCH_M else "mm"
            raise self.error(f"{w.letter} {w.value:.6g}: coordinate out of range (|{w.letter}| "
                             f"<= {MAX_COORD_M / unit:.6g} {name})", n, w.column)
        return w.value * unit

    # -- settings ------------------------------------------------------------------------------
    def _tools(self, gcodes: dict, mcodes: dict, args: dict, n: int) -> None:
        """T (select), M6 (change), spindle M3/M4/M5."""
        if "T" in args:
            t = args["T"]
            if t.value != int(t.value) or t.value < 0:
                raise self.error(f"T {t.value:g}: a tool number is a whole number >= 0",
                                 n, t.column)
            self._known_tool(int(t.value), n, t.column)
            self.selected = int(t.value)
        tool = mcodes.get("tool")
        if tool is not None:  # M6 (without a T before: tool 0, no tool, as LinuxCNC)
            self.out.stop()
            self.spindle_tool = self.selected
        spindle = mcodes.get("spindle")
        if spindle is not None:
            self.spindle = {3: 1, 4: -1, 5: 0}[int(spindle.value)]

    def _known_tool(self, number: int, n: int, column: int) -> None:
        if self.setup.tools is not None and number and self.setup.tool(number) is None:
            raise self.error(f"tool T{number} is not in the tool table", n, column)

    def _modes(self, gcodes: dict, args: dict, n: int) -> None:
        """Plane, units, tool length, work system, path control, distance, retract."""
        if "plane" in gcodes:
            self.out.plane = _PLANE[gcodes["plane"][0]]
        if "units" in gcodes:
            new = _UNIT_M[gcodes["units"][0]]
            if new != self.unit:  # LinuxCNC converts its position (feed: a speed, kept)
                self.cur = self.cur * 25.4 if new == MM_M else self.cur / 25.4
            self.unit_m = new
        if "tool length" in gcodes:
            old = self.offsets
            self._tool_length(*gcodes["tool length"], args, n)
            self._offsets_changed(old)
        if "work system" in gcodes:
            old = self.offsets
            self.work = _WORK[gcodes["work system"][0]]
            self._offsets_changed(old)
        control = gcodes.get("path control", (None,))[0]
        if control in (610, 611):
            self.blend_tol_m = 0.0
        elif control == 640:
            p = args.get("P")
            if p is not None and not p.value >= 0:
                raise self.error(f"P {p.value:g}: the blending tolerance of G64 must not be "
                                 "negative", n, p.column)
            self.blend_tol_m = p.value * self._unit(n) if p is not None and p.value > 0 else None
        if "distance" in gcodes:
            self.incremental = gcodes["distance"][0] == 910
        if "arc distance" in gcodes:
            self.arc_absolute = gcodes["arc distance"][0] == 901
        if "retract" in gcodes:
            self.retract_r = gcodes["retract"][0] == 990

    def _tool_length(self, code: int, word: Word, args: dict, n: int) -> None:
        """G43 (H), G43.1, G43.2 H, G49: the tool length offset."""
        if code == 490:
            self.tlo = np.zeros(3)
            return
        if code == 431:
            for k, a in enumerate(_AXES):
                if a in args:
                    self.tlo[k] = self._in_range(args[a], n)
            return
        h = args.get("H")
        if code == 432 and h is None:
            raise unsupported("G43.2 without H", n, word.column, self.source)
        if h is not None and (h.value != int(h.value) or h.value <= 0):
            if h.value == 0:
                raise unsupported("H0 (the tool in the spindle)", n, h.column, self.source)
            raise self.error(f"H {h.value:g}: a tool number is a whole number > 0", n, h.column)
        number = int(h.value) if h is not None else self.spindle_tool
        offset = np.zeros(3)
        if self.setup.tools is None:
            self.out.warn_once("without a tool table", f"line {n}: G43 without a tool table "
                               "(--tool-table): tool length 0 (a constant Z shift changes no "
                               "gain)")
        elif number:
            self._known_tool(number, n, (h or word).column)
            offset = np.array(self.setup.tool(number).offset_m)
        self.tlo = self.tlo + offset if code == 432 else offset

    # -- home, offsets -------------------------------------------------------------------------
    def _target(self, args: dict, n: int) -> np.ndarray:
        """The end point (program units) of the block's axis words (G90/G91); the axes not
        named keep their values."""
        end = self.cur.copy()
        for k, a in enumerate(_AXES):
            if a in args:
                self._in_range(args[a], n)
                end[k] = end[k] + args[a].value if self.incremental else args[a].value
        return end

    def _home(self, special: tuple[int, Word], args: dict, n: int) -> None:
        """G28/G30: traverse through the given point to the home of the named axes (all
        when none is named; LinuxCNC's ``convert_home``)."""
        code, word = special
        self.cur = self._target(args, n)
        self.out.traverse(self.machine(self.cur), n, word.column)
        home = (self.g28 if code == 280 else self.g30) - self.offsets
        for k in [k for k, a in enumerate(_AXES) if a in args] or range(3):
            self.cur[k] = home[k] / self.unit
        self.out.traverse(self.machine(self.cur), n, word.column)

    def _g92(self, code: int, args: dict, n: int) -> None:
        """G92 (the current point gets the given coordinates), G92.1 / G92.2 / G92.3."""
        old = self.offsets
        if code == 920:
            for k, a in enumerate(_AXES):
                if a in args:
                    self.g92[k] += (self.cur[k] - args[a].value) * self.unit
                    self._in_range(args[a], n)
            self.g92_saved = self.g92.copy()
        elif code == 921:
            self.g92 = np.zeros(3)
            self.g92_saved = np.zeros(3)
        elif code == 922:
            self.g92 = np.zeros(3)
        else:
            self.g92 = self.g92_saved.copy()
        self._offsets_changed(old)

    # -- motion --------------------------------------------------------------------------------
    def _motion(self, code: int, gcodes: dict, args: dict, n: int) -> None:
        word = gcodes.get("motion", (None, None))[1]
        first = min(args.values(), key=lambda w: w.column) if args else None
        column = word.column if word is not None else (first.column if first else 1)
        previous, self.motion = self.motion, None if code == 800 else code
        if code not in CYCLES:
            self.cycle.il = None
        if code == 800:
            return
        self._unit(n)
        if code in CYCLES:
            self._cycle(code, previous, args, n, column)
            return
        if gcodes.get("non-modal", (None,))[0] == 530:  # machine coordinates
            end = self.cur.copy()
            offsets = self.offsets
            for k, a in enumerate(_AXES):
                if a in args:
                    end[k] = (self._in_range(args[a], n) - offsets[k]) / self.unit
        else:
            end = self._target(args, n)
        if code == 0:
            self.out.traverse(self.machine(end), n, column)
        elif code == 10:
            self.out.feed(self.machine(end), n, column)
        else:
            self._arc(code, end, args, n, column)
        self.cur = end

    def _arc(self, code: int, end: np.ndarray, args: dict, n: int, column: int) -> None:
        """G2/G3 to ``end`` (program units): LinuxCNC's checks and centre (``arc_data_ijk``,
        ``arc_data_r``), in program units as LinuxCNC computes them."""
        plane = self.out.plane
        i, j, normal = PLANES[plane]
        first, second, third = _plane_roles(plane)
        g = f"{_PLANE_G[plane]} ({plane.upper()} plane)"
        unit = self.unit
        offsets = {L: args[L] for L in "IJK" if L in args}
        if "IJK"[normal] in offsets:
            w = offsets.pop("IJK"[normal])
            if w.value != 0:
                raise self.error(f"{w.letter} word in an arc in {g}", n, w.column)
            self.out.warn_once(f"{w.letter}0 on", f"line {n}: {w.letter}0 on an arc in {g} "
                               "(FreeCAD's posts write it) ignored: LinuxCNC refuses it")
        if "R" in args and offsets:
            w = max([args["R"], *offsets.values()], key=lambda w: w.column)
            raise self.error("arc with both R and I/J/K", n, w.column)
        if "R" not in args and not offsets:
            raise self.error(f"arc needs {'IJK'[i]}/{'IJK'[j]} centre offsets or R", n, column)
        if "R" in args and first not in args and second not in args:
            raise self.error(f"arc in {g} needs {first} or {second}", n, column)
        for w in offsets.values():
            self._in_range(w, n)
        a, b = self.cur[[i, j]], end[[i, j]]
        if "R" in args:
            w = args["R"]
            self._in_range(w, n)
            r = w.value
            if a[0] == b[0] and a[1] == b[1]:
                raise self.error("an R-form arc needs an end point different from its start "
                                 "(use I/J/K for a full circle)", n, w.column)
            mid = (b + a) / 2.0
            half = float(np.hypot(mid[0] - b[0], mid[1] - b[1]))
            if half - abs(r) > _LCNC_RADIUS_TOL[unit]:
                raise self.error(f"R {abs(r):g} is too small to reach the end point "
                                 f"{2 * half:g} away", n, w.column)
            if half / abs(r) > 1 - 1e-12:
                half = abs(r)
            turn_left = (code == 20 and r > 0) or (code == 30 and r < 0)
            theta = math.atan2(b[1] - a[1], b[0] - a[0]) + (-math.pi / 2 if turn_left
                                                              else math.pi / 2)
            offset = abs(r) * math.cos(math.asin(half / abs(r)))
            c = np.array([mid[0] + offset * math.cos(theta), mid[1] + offset * math.sin(theta)])
        else:
            w = min(offsets.values(), key=lambda w: w.column)
            if self.arc_absolute:
                for L in ("IJK"[i], "IJK"[j]):
                    if L not in offsets:
                        raise self.error(f"{L} word missing in an absolute-centre arc (G90.1)",
                                         n, w.column)
            off = np.array([offsets[L].value if L in offsets else 0.0
                            for L in ("IJK"[i], "IJK"[j])])
            c = off if self.arc_absolute else a + off
            r0, r1 = float(np.hypot(*(c - a))), float(np.hypot(*(c - b)))
            if min(r0, r1) < _LCNC_RADIUS_TOL[unit]:
                raise self.error(f"arc radius is zero (radius to start {r0:g}, to end {r1:g})",
                                 n, w.column)
            err = abs(r1 - r0)
            tol = _LCNC_ARC_ABS[unit]
            if err > 100 * tol or (err / max(r0, r1) > _LCNC_ARC_REL and err > tol):
                raise self.error(f"arc end point is off the circle: radius to start {r0:g}, "
                                 f"to end {r1:g} (LinuxCNC refuses it)", n, w.column)
        turns = int(round(args["P"].value)) if "P" in args else 1
        center = self.cur.copy()
        center[[i, j]] = c
        self.out.arc(self.machine(end), self.machine(center), turns if code == 30 else -turns,
                     n, column, unit_m=unit,
                     end_tol_m=(ARC_END_TOL_IN if unit == INCH_M else ARC_END_TOL_MM) * unit)

    def _cycle(self, code: int, previous: int | None, args: dict, n: int, column: int) -> None:
        """A canned cycle block: its moves (:func:`~feedplan.gcode.cycles.cycle_moves`)."""
        roles = PLANES[self.out.plane]
        letters = _plane_roles(self.out.plane)
        words_ = {role: args[L].value for role, L in zip("abc", letters) if L in args}
        words_.update({L: args[L].value for L in "RPQLIJK" if L in args})
        for L in (*letters, "R", "I", "J", "K"):
            if L in args:
                self._in_range(args[L], n)

        def error(message: str, letter: str) -> GcodeError:
            w = args.get(letter)
            return self.error(message, n, w.column if w is not None else column)

        ijk = "".join("IJK"[k] for k in roles)
        moves, _ = cycle_moves(code, previous, tuple(self.cur[list(roles)]), words_,
                               self.incremental, self.retract_r, self.unit == INCH_M,
                               self.spindle, self.cycle, error, ijk)
        self.out.blend_tol_m = 0.0  # LinuxCNC runs cycles in exact-path mode
        for kind, value in moves:
            if kind == "D":
                self.out.stop()
                continue
            self.cur = self.cur.copy()
            self.cur[list(roles)] = value
            if kind == "T":
                self.out.traverse(self.machine(self.cur), n, column)
            else:
                self.out.feed(self.machine(self.cur), n, column)
        self.out.blend_tol_m = self.blend_tol_m

    def path(self) -> Path:
        if not self.ended:
            self.out.warn(NO_END)
        return self.out.path()


def read_builtin(text: str, source: str = "", axes: str = "xyz",
                 setup: Setup | None = None) -> Path:
    """Read a G-code program with the built-in reader (see the module notes).

    Parameters
    ----------
    text : str
        The program.
    source : str, optional
        Its name (file name) for messages and ``Path.source``.
    axes : str, optional
        The machine's linear axes among ``"xyz"``; a word for any other axis is refused.
    setup : Setup, optional
        Home positions, work offsets, tool table (default: LinuxCNC's without files).

    Returns
    -------
    Path
        Lines and arcs in machine coordinates and metres, feeds in m/s (rapids ``inf``), each
        segment with its 1-based source line; ``warnings`` holds non-fatal remarks.

    Raises
    ------
    GcodeError
        The program is outside the dialect (``unsupported`` set where LinuxCNC's interpreter
        reads it) or inconsistent (line, column, feature).
    """
    reader = _Reader(source, axes, setup or Setup())
    for n, line in enumerate(text.split("\n"), start=1):
        if reader.block(line.rstrip("\r"), n):
            break
    return reader.path()
