"""Canned cycles G73, G74, G81-G87, G89 expanded into the moves LinuxCNC makes.

Transcribed from LinuxCNC 2.9's ``interp_cycles.cc`` (``convert_cycle_xy/yz/zx``, the
``CYCLE_MACRO`` loop and ``convert_cycle_g73`` .. ``g89``), in program units (the arithmetic
LinuxCNC does, so that a peck count or a retract height comes out the same). The plane's axes
are (first, second, normal): XY (X, Y, Z), ZX (Z, X, Y), YZ (Y, Z, X); "Z" below is the normal.

Per cycle, after positioning (traverse in the plane at the clearance, then down to R):
G81 feed to Z, traverse out; G82 feed, dwell P, traverse out; G73 pecks of Q (feed, retract
0.010 in) then traverse out; G83 pecks of Q (feed, traverse to R, traverse back to 0.010 in
above the last depth); G85 feed in, feed out to R, traverse out; G86 feed, dwell, traverse out
(spindle turning); G89 feed, dwell, feed out; G74/G84 (tapping) feed, dwell, feed out (spindle
counter-clockwise / clockwise); G87 back boring (I, J offset, K top of the bore). The retract
height is R under G99 and the initial level (the normal coordinate when the cycles began, or
R if higher) under G98. In G91, X/Y are increments repeated L times, R is from the initial
level and Z from R. G88 (manual retract) is not expanded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

__all__ = ["CYCLES", "CycleMemory", "cycle_moves"]

#: Canned cycle G codes (keys are ten times the G number) and their names.
CYCLES = {730: "G73", 740: "G74", 810: "G81", 820: "G82", 830: "G83", 840: "G84", 850: "G85",
          860: "G86", 870: "G87", 890: "G89"}
_DWELL_P = {820: "G82", 860: "G86", 890: "G89"}
_PECK_Q = {730: "G73", 830: "G83"}
#: G83/G73 retract above the last depth, inches (LinuxCNC's G83_RAPID_DELTA).
_RAPID_DELTA_IN = 0.010


@dataclass
class CycleMemory:
    """What LinuxCNC remembers between cycle blocks (raw word values, program units)."""

    r: float = 0.0  # cycle_r
    cc: float = 0.0  # cycle_cc: the last Z (normal) word
    p: float = 0.0  # cycle_p: dwell
    q: float = 0.0  # cycle_q: peck
    i: float = 0.0
    j: float = 0.0
    k: float = 0.0
    il: float | None = None  # cycle_il: initial level, None when not set (cycle_il_flag)


def cycle_moves(
    code: int, previous: int | None, current: tuple[float, float, float],
    words: dict[str, float], incremental: bool, retract_r: bool, inch: bool, spindle: int,
    memory: CycleMemory, error: Callable[[str, str], Exception], ijk: str = "IJK",
) -> tuple[list[tuple], tuple[float, float, float]]:
    """The moves of one cycle block, in program units of the plane's axes.

    Parameters
    ----------
    code : int
        The cycle (ten times its G number, a key of :data:`CYCLES`).
    previous : int or None
        The motion mode before this block (the same cycle continues without R, Z, P, Q).
    current : (aa, bb, cc)
        Current program position in the plane's (first, second, normal) axes.
    words : dict
        The block's words by plane role: ``"a" "b" "c"`` (first, second, normal axis words),
        ``"R" "P" "Q" "L" "I" "J" "K"``, raw values in program units.
    incremental : bool
        G91 in effect.
    retract_r : bool
        G99 (retract to R) rather than G98 (to the initial level).
    inch : bool
        Program units are inches (the G73/G83 retract is 0.010 in, 0.254 mm).
    spindle : int
        1 clockwise, -1 counter-clockwise, 0 stopped.
    memory : CycleMemory
        Updated in place.
    error : callable
        ``error(message, letter)``: the exception to raise, at the word ``letter`` (or the
        cycle's G word for ``""``).
    ijk : str
        The G87 offset letters of the plane's (first, second, normal) roles: ``"IJK"`` in
        G17, ``"KIJ"`` in G18, ``"JKI"`` in G19.

    Returns
    -------
    moves : list of tuple
        ``("T", (aa, bb, cc))`` traverse, ``("F", (aa, bb, cc))`` feed, ``("D", seconds)``.
    end : (aa, bb, cc)
        The position after the block.
    """
    repeats, c_word = _repeats_and_depth(code, previous, words, memory, error)
    cur_a, cur_b, current_cc = current
    if memory.il is None:
        memory.il = current_cc
    old_cc = memory.il
    inc_a = inc_b = 0.0
    if incremental:
        inc_a, inc_b = words.get("a", 0.0), words.get("b", 0.0)
        r = words["R"] + old_cc
        cc = r + c_word
        aa, bb = cur_a, cur_b
    else:
        r, cc = words["R"], c_word
        aa, bb = words.get("a", cur_a), words.get("b", cur_b)
    if r < cc:
        raise error(f"{CYCLES[code]}: R {r:g} is below the depth {cc:g}", "R")
    moves: list[tuple] = []
    if old_cc < r:
        moves.append(("T", (cur_a, cur_b, r)))
        old_cc = current_cc = r
    hole = _hole(code, previous, words, spindle, memory, error, ijk, incremental,
                 r=r, cc=cc, clear=r if retract_r else old_cc,
                 delta=_RAPID_DELTA_IN * (1.0 if inch else 25.4))
    for n in range(repeats, 0, -1):
        aa, bb = aa + inc_a, bb + inc_b
        if n == repeats and current_cc > r:
            moves += [("T", (aa, bb, current_cc)), ("T", (aa, bb, r))]
        else:
            moves.append(("T", (aa, bb, hole.clear)))
            if hole.clear > r:
                moves.append(("T", (aa, bb, r)))
        moves += _FAMILIES[code](aa, bb, hole)
    _remember(code, memory, hole, c_word, words["R"])
    return moves, (aa, bb, hole.clear)


def _remember(code: int, memory: CycleMemory, hole: "_Hole", c_word: float, r_word: float):
    """What LinuxCNC keeps of the block for the next one of the cycle."""
    if code in _DWELL_P or code in (740, 840):
        memory.p = hole.p
    if code in _PECK_Q:
        memory.q = hole.q
    memory.cc = c_word
    memory.r = r_word


def _repeats_and_depth(code: int, previous: int | None, words: dict[str, float],
                       memory: CycleMemory, error) -> tuple[int, float]:
    """L (repeats) and the depth word of the block, R taken from the memory when the cycle
    continues without it; the errors of a missing R or depth, or a bad L."""
    name = CYCLES[code]
    if "R" not in words:
        if previous != code:
            raise error(f"{name}: R (clearance plane) is missing in the first block of the cycle",
                        "")
        words["R"] = memory.r
    repeats = words.get("L", 1.0)
    if repeats != int(repeats) or repeats < 0:
        raise error(f"{name}: L (repeats) must be a whole number, got {repeats:g}", "L")
    if repeats == 0:
        raise error(f"{name}: L0 (no repeat) is not allowed", "L")
    if previous != code and "c" not in words:
        raise error(f"{name}: the depth (the axis word normal to the plane) is missing in the "
                    "first block of the cycle", "")
    return int(repeats), words.get("c", memory.cc)


@dataclass(frozen=True)
class _Hole:
    """One cycle's levels along the normal (program units) and its words, for every hole."""

    r: float  # clearance plane R
    cc: float  # depth
    clear: float  # retract height
    delta: float  # G73/G83 retract above the last depth
    p: float  # dwell, seconds
    q: float  # peck depth
    off_a: float = 0.0  # G87: offset of the bore's axis, top of the bore
    off_b: float = 0.0
    middle: float = 0.0


def _hole(code, previous, words, spindle, memory, error, ijk, incremental, **levels) -> _Hole:
    """The cycle's dwell, peck and G87 words (or the memory's), checked; the spindle's
    direction checked for the cycles that need it."""
    name = CYCLES[code]
    if code in _DWELL_P and previous != code and "P" not in words:
        raise error(f"{name}: P (dwell, seconds) is missing", "")
    if code in _PECK_Q and previous != code and "Q" not in words:
        raise error(f"{name}: Q (peck depth) is missing", "")
    if code in (860, 870) and spindle == 0:
        raise error(f"{name}: the spindle is not turning (M3 or M4 first)", "")
    if code == 840 and spindle != 1:
        raise error(f"G84: the spindle must turn clockwise (M3), it is "
                    f"{'stopped' if spindle == 0 else 'turning counter-clockwise'}", "")
    if code == 740 and spindle != -1:
        raise error(f"G74: the spindle must turn counter-clockwise (M4), it is "
                    f"{'stopped' if spindle == 0 else 'turning clockwise'}", "")
    p = words.get("P", memory.p)
    q = words.get("Q", memory.q)
    if code in _PECK_Q and q <= 0:
        raise error(f"{name}: Q (peck depth) must be positive, got {q:g}", "Q")
    if code != 870:
        return _Hole(p=p, q=q, **levels)
    if previous != code:
        for letter in "IJK":
            if letter not in words:
                raise error(f"G87: {letter} is missing", "")
    memory.i, memory.j, memory.k = (words.get(x, getattr(memory, x.lower())) for x in "IJK")
    off_a, off_b, top = (getattr(memory, x.lower()) for x in ijk)
    middle = levels["cc"] + top if incremental else top
    return _Hole(p=p, q=q, off_a=off_a, off_b=off_b, middle=middle, **levels)


def _drill(aa: float, bb: float, h: _Hole) -> list[tuple]:
    """G81: feed to the depth, traverse out."""
    return [("F", (aa, bb, h.cc)), ("T", (aa, bb, h.clear))]


def _dwell_drill(aa: float, bb: float, h: _Hole) -> list[tuple]:
    """G82, G86: feed to the depth, dwell, traverse out."""
    return [("F", (aa, bb, h.cc)), ("D", h.p), ("T", (aa, bb, h.clear))]


def _peck(aa: float, bb: float, h: _Hole, to_r: bool) -> list[tuple]:
    """G73 (``to_r`` False: retract by delta) and G83 (traverse to R and back to delta above
    the last depth): pecks of Q, then the last feed to the depth and out."""
    moves = []
    depth = h.r - h.q
    while depth > h.cc:
        moves.append(("F", (aa, bb, depth)))
        if to_r:
            moves.append(("T", (aa, bb, h.r)))
        moves.append(("T", (aa, bb, depth + h.delta)))
        depth = depth - h.q
    return moves + [("F", (aa, bb, h.cc)), ("T", (aa, bb, h.clear))]


def _bore(aa: float, bb: float, h: _Hole) -> list[tuple]:
    """G85: feed in, feed out to R, traverse out."""
    return [("F", (aa, bb, h.cc)), ("F", (aa, bb, h.r)), ("T", (aa, bb, h.clear))]


def _tap(aa: float, bb: float, h: _Hole) -> list[tuple]:
    """G74, G84, G89: feed in, dwell, feed out."""
    return [("F", (aa, bb, h.cc)), ("D", h.p), ("F", (aa, bb, h.clear))]


def _back_bore(aa: float, bb: float, h: _Hole) -> list[tuple]:
    """G87: down beside the bore at the offset, in under it, feed up to the top and back,
    out beside it again."""
    oa, ob, cc, clear = aa + h.off_a, bb + h.off_b, h.cc, h.clear
    return [("T", (oa, ob, h.r)), ("T", (oa, ob, cc)), ("T", (aa, bb, cc)),
            ("F", (aa, bb, h.middle)), ("F", (aa, bb, cc)), ("T", (oa, ob, cc)),
            ("T", (oa, ob, clear)), ("T", (aa, bb, clear))]


#: The moves of one hole, per cycle.
_FAMILIES = {810: _drill, 820: _dwell_drill, 860: _dwell_drill,
             730: lambda aa, bb, h: _peck(aa, bb, h, False),
             830: lambda aa, bb, h: _peck(aa, bb, h, True),
             850: _bore, 740: _tap, 840: _tap, 890: _tap, 870: _back_bore}
