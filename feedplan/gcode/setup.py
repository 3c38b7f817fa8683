"""What a program's meaning depends on beyond its text: home positions, work offsets, tools.

LinuxCNC keeps these in its parameter file (G28/G30 positions, G54-G59.3 offsets) and its
tool table. :class:`Setup` holds them for both
readers, in machine coordinates and metres; the default is LinuxCNC's own without those files:
every position and offset at machine zero, no tool table.

Tool table: LinuxCNC's format, one tool a line, words ``T`` (tool number), ``P`` (pocket),
``X Y Z`` (offsets), ``D`` (diameter), ``A B C U V W I J Q`` (read, not used), ``;`` to the end
of the line a comment (:func:`parse_tool_table`). Lengths are millimetres (the machine units of
a metric LinuxCNC machine).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from oga.errors import GcodeError

__all__ = ["Setup", "Tool", "WORK_SYSTEMS", "parse_tool_table", "load_tool_table"]

#: G codes of the work coordinate systems, in LinuxCNC's order (P1..P9 of G10 L2).
WORK_SYSTEMS: tuple[str, ...] = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2",
                                 "G59.3")
#: Largest tool number read (LinuxCNC's tool numbers are ints; pockets stop at 1000).
_MAX_TOOL = 99_999_999
_MAX_TOOLS = 1000
_TOOL_LETTERS = set("TPXYZABCUVWDIJQ")


@dataclass(frozen=True)
class Tool:
    """One tool of the table: number, offsets (x, y, z) m, diameter m, source line."""

    number: int
    offset_m: tuple[float, float, float]
    diameter_m: float = 0.0
    line: int = 0


def _xyz(v) -> np.ndarray:
    a = np.array(v, dtype=np.float64).reshape(3)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Setup:
    """Home positions, work offsets and tool table, in machine coordinates (metres).

    Attributes
    ----------
    g28_m, g30_m : ndarray, shape (3,)
        Where G28 and G30 go (LinuxCNC's parameters 5161-5163 and 5181-5183).
    work_offsets_m : ndarray, shape (9, 3)
        Offsets of G54 .. G59.3 (parameters 5221.. in steps of 20).
    tools : tuple of Tool or None
        The tool table (:func:`parse_tool_table`); None when none was given (then a G43
        applies length 0, with a warning).
    """

    g28_m: np.ndarray = field(default_factory=lambda: _xyz((0.0, 0.0, 0.0)))
    g30_m: np.ndarray = field(default_factory=lambda: _xyz((0.0, 0.0, 0.0)))
    work_offsets_m: np.ndarray = field(default_factory=lambda: np.zeros((9, 3)))
    tools: tuple[Tool, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "g28_m", _xyz(self.g28_m))
        object.__setattr__(self, "g30_m", _xyz(self.g30_m))
        w = np.array(self.work_offsets_m, dtype=np.float64).reshape(9, 3)
        w.flags.writeable = False
        object.__setattr__(self, "work_offsets_m", w)
        if self.tools is not None:
            object.__setattr__(self, "tools", tuple(self.tools))
        for name, v in (("g28_m", self.g28_m), ("g30_m", self.g30_m), ("work_offsets_m", w)):
            if not np.all(np.isfinite(v)):
                raise ValueError(f"Setup.{name} must be finite")

    def tool(self, number: int) -> Tool | None:
        """The tool ``number`` of the table (the first line giving it), None if absent."""
        for t in self.tools or ():
            if t.number == number:
                return t
        return None


def parse_tool_table(text: str, source: str = "") -> tuple[Tool, ...]:
    """Read a LinuxCNC tool table (lengths in millimetres).

    Raises
    ------
    GcodeError
        A word that does not parse, an unknown letter, a line without T, a tool number out
        of range or given twice, more than 1000 tools (line and column named).
    """
    tools: list[Tool] = []
    seen: dict[int, int] = {}
    for n, raw in enumerate(text.split("\n"), start=1):
        body = raw.rstrip("\r").split(";", 1)[0]
        words: dict[str, float] = {}
        column = 1
        for token in body.split():
            column = body.index(token, column - 1) + 1
            letter, number = token[0].upper(), token[1:]
            if letter not in _TOOL_LETTERS:
                raise GcodeError(f"tool table: unknown word {token!r}", n, column, source)
            try:
                value = float(number)
            except ValueError:
                raise GcodeError(f"tool table: {letter} word {number!r} is not a number",
                                 n, column, source) from None
            if not math.isfinite(value) or abs(value) > 1e6:
                raise GcodeError(f"tool table: {letter} word {number} is out of range",
                                 n, column, source)
            if letter in words:
                raise GcodeError(f"tool table: {letter} word appears twice", n, column, source)
            if letter in "TPQ" and value != int(value):
                raise GcodeError(f"tool table: {letter} must be an integer", n, column, source)
            words[letter] = value
            column += len(token)
        if not words:
            continue
        if "T" not in words:
            raise GcodeError("tool table: a line without a T word (tool number)", n, 1, source)
        number = int(words["T"])
        if not 0 < number <= _MAX_TOOL:
            raise GcodeError(f"tool table: tool number T{number} out of range (1..{_MAX_TOOL})",
                             n, 1, source)
        if number in seen:
            raise GcodeError(f"tool table: tool T{number} given twice (first on line "
                             f"{seen[number]})", n, 1, source)
        if len(tools) >= _MAX_TOOLS:
            raise GcodeError(f"tool table: more than {_MAX_TOOLS} tools", n, 1, source)
        seen[number] = n
        tools.append(Tool(number, tuple(words.get(a, 0.0) * 1e-3 for a in "XYZ"),
                          abs(words.get("D", 0.0)) * 1e-3, n))
    return tuple(tools)


def load_tool_table(path: str | os.PathLike) -> tuple[Tool, ...]:
    """Read a tool table file (:func:`parse_tool_table`), UTF-8 text of at most 1 MB.

    Raises
    ------
    GcodeError, ToolpathError
        Unreadable, too large or invalid (line and column named).
    """
    from oga.errors import ToolpathError
    from oga.files import read_limited

    name = os.fspath(path)
    data = read_limited(name, 1 << 20, ToolpathError, "tool table")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ToolpathError("tool table: not UTF-8 text", source=name) from None
    return parse_tool_table(text, source=name)
