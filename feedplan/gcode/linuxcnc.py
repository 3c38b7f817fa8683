"""LinuxCNC's own interpreter as a G-code reader (``--reader linuxcnc``).

Why the ``gcode`` Python module and not the ``rs274`` program: both run LinuxCNC's interpreter
(``librs274``), but ``rs274`` prints its canonical calls with four decimals (0.1 um in mm
programs, 2.5 um in inch ones) and without the source line of a move, while ``gcode.parse``
(what LinuxCNC's own AXIS preview uses, ``rs274/glcanon.py``) hands every call to Python with
full double precision and the line (``next_line``) of each. It runs in a child process
(:mod:`feedplan.gcode._worker`), never in ours: bounded in time (an endless O-word loop, an
M66 wait end there), memory and output, on a temporary copy of the program in a temporary
folder that also holds the tool table and the parameter file written from the
:class:`~feedplan.gcode.setup.Setup` (G28/G30 positions #5161-5163 and #5181-5183, work
offsets #5221...), with no INI file (units: mm; LinuxCNC's defaults otherwise; G64 first).
LinuxCNC 2.9 reads its tool data through a memory-mapped file that the process creating it
owns: the worker creates it (``tool_mmap_creator``, as the ``rs274`` program does) and loads
the table into it (``tooldata_load``).

The canonical calls map onto the path as LinuxCNC's motion controller sees them: machine
position = XY rotation of (program position + G92 offset) + work offset + tool length offset
(LinuxCNC's ``find_relative``); arcs keep their end, centre, plane, rotation sense and turns.
One difference from a machine remains: where the interpreter re-reads the position from the
controller (after M6), the module gives back the last move's end in the program units it
had then (a program switching G20/G21 and then changing tools: the built-in reader keeps the
converted position, as LinuxCNC's controller does). What the module does not report is taken
from the source line: path control (G61/G64 P; a
move of a block that names none gets the mode in effect, its P the last G64 line's) and
whether a block is a canned cycle (cycles run in exact-path mode). Without a tool table, every
tool the program names (T, H words) gets length 0 (a warning), as the built-in reader does.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tempfile
from functools import lru_cache
from pathlib import Path as FilePath

import numpy as np

from feedplan.gcode.builtin import ARC_END_TOL_IN, ARC_END_TOL_MM, INCH_M, MM_M, NO_END
from feedplan.gcode.cycles import CYCLES
from feedplan.gcode.lexer import words as line_words
from feedplan.gcode.moves import PathBuilder
from feedplan.gcode.setup import Setup
from feedplan.path import PLANES, Path
from oga.defaults import (LINUXCNC_PYTHON_PATH, LINUXCNC_READ_MEMORY_BYTES,
                          LINUXCNC_READ_TIMEOUT_S, MAX_SEGMENTS)
from oga.errors import GcodeError, OgaError

__all__ = ["read_linuxcnc", "linuxcnc_available", "linuxcnc_python"]

_WORKER = FilePath(__file__).with_name("_worker.py")
_PLANES = {1: "xy", 2: "yz", 3: "zx"}
#: LinuxCNC's message for a program that does not end with M2, M30 or a closing %.
_NO_END = "File ended with no percent sign or program end"
_TOOL_WORD = re.compile(r"[TtHh][ \t]*(\d+)")
_COMMENT = re.compile(r"\([^)]*\)|;.*")
_CODE = re.compile(r"([A-Za-z])[ \t]*([-+]?[ \t]*(?:\d[\d \t]*\.?[\d \t]*|\.[\d \t]+))")


@lru_cache(maxsize=1)
def linuxcnc_python() -> str | None:
    """A Python that imports LinuxCNC's ``gcode`` module (ours, else Debian's), or None."""
    folder = FilePath(LINUXCNC_PYTHON_PATH)
    if not any(folder.glob("gcode.*.so")):
        return None
    probe = ("import sys, ctypes; sys.path.append(sys.argv[1]); import gcode; "
             "ctypes.CDLL('libtooldata.so.0')")
    for python in dict.fromkeys((sys.executable, "/usr/bin/python3")):
        try:
            done = subprocess.run([python, "-c", probe, str(folder)], capture_output=True,
                                  timeout=60, env=_env(tempfile.gettempdir()))
        except (OSError, subprocess.TimeoutExpired):
            continue
        if done.returncode == 0:
            return python
    return None


def linuxcnc_available() -> bool:
    """LinuxCNC's interpreter can read programs here (package linuxcnc-uspace)."""
    return linuxcnc_python() is not None


def _env(home: str) -> dict[str, str]:
    """A minimal environment: no INI file, the C locale, HOME for the tool data's mmap."""
    return {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": home, "LC_ALL": "C"}


def _column(text: str, message: str) -> int:
    """Column of the word ``message`` names in the line ``text`` (first non-blank if none)."""
    for letter, number in re.findall(r"\b([A-Za-z])\s*(-?\d+(?:\.\d+)?)\b", message):
        for m in _CODE.finditer(text):
            try:
                value = float(m.group(2).replace(" ", "").replace("\t", ""))
            except ValueError:
                continue
            if m.group(1).upper() == letter.upper() and value == float(number):
                return m.start() + 1
    for letter in re.findall(r"\b([A-Za-z]) word", message):
        m = re.search(letter, _COMMENT.sub(lambda c: " " * len(c.group()), text), re.I)
        if m:
            return m.start() + 1
    return len(text) - len(text.lstrip()) + 1


def _scan(lines: list[str], source: str) -> tuple[list[str], dict, set[int], set[int],
                                                  list[str]]:
    """The program as LinuxCNC gets it and what its lines say: (lines, {line: (path control,
    G64 P)}, lines naming a cycle, lines naming a motion, warnings)."""
    out, control, cycle, warnings = [], {}, set(), []
    motion_words: set[int] = set()
    for n, text in enumerate(lines, start=1):
        stripped = text.strip()
        if stripped.startswith("$"):  # grbl's system commands, as the built-in reader
            warnings.append(f"line {n}: grbl command {stripped[:20]!r} skipped")
            out.append("")
            continue
        upper = text.upper()
        if "PROBEOPEN" in upper or "LOGOPEN" in upper or "LOGAPPEND" in upper:
            raise GcodeError("a comment that writes a file (PROBEOPEN, LOGOPEN) is not run",
                             n, upper.find("OPEN") + 1 if "OPEN" in upper else 1, source)
        out.append(text)
        try:
            ws = line_words(text, n, source)
        except GcodeError:
            continue
        for w in ws:
            if w.letter != "G":
                continue
            code = round(w.value * 10)
            if code in (610, 611):
                control[n] = (0.0, None)
            elif code == 640:
                p = [x.value for x in ws if x.letter == "P"]
                control[n] = (None, p[0] if p and p[0] > 0 else None)
            if code in CYCLES or code == 880:
                cycle.add(n)
            if code in (0, 10, 20, 30, 800, 330, 331, 382, 383, 384, 385, 760, *CYCLES, 880):
                motion_words.add(n)
    return out, control, cycle, motion_words, warnings


def _tool_table(setup: Setup, text: str) -> str:
    """The tool table LinuxCNC gets (P = index, lengths in mm): the setup's, or every tool the
    program names with length 0."""
    if setup.tools is not None:
        rows = [(t.number, *(float(v) * 1e3 for v in t.offset_m), float(t.diameter_m) * 1e3)
                for t in setup.tools]
    else:
        numbers = sorted({int(x) for x in _TOOL_WORD.findall(_COMMENT.sub("", text))
                          if 0 < int(x) < 100_000_000})[:1000]
        rows = [(t, 0.0, 0.0, 0.0, 0.0) for t in numbers]
    return "".join(f"T{t} P{k} X{x!r} Y{y!r} Z{z!r} D{d!r}\n"
                   for k, (t, x, y, z, d) in enumerate(rows, start=1))


def _parameters(setup: Setup) -> str:
    """LinuxCNC's parameter file (mm): G28 and G30 positions, G54 selected, work offsets."""
    rows = {5220: 1.0}
    for base, xyz in ((5161, setup.g28_m), (5181, setup.g30_m)):
        rows.update({base + k: v * 1e3 for k, v in enumerate(xyz)})
    for w, xyz in enumerate(setup.work_offsets_m):
        rows.update({5221 + 20 * w + k: v * 1e3 for k, v in enumerate(xyz)})
    return "".join(f"{k}\t{float(v)!r}\n" for k, v in sorted(rows.items()))


def _run(program: str, tools: str, params: str, axes: str, timeout_s: float) -> list[str]:
    """The worker's records for ``program`` (text), with the given tool table and parameters."""
    python = linuxcnc_python()
    if python is None:
        raise OgaError("LinuxCNC's interpreter is not installed here (Debian package "
                       "linuxcnc-uspace): --reader linuxcnc cannot run")
    with tempfile.TemporaryDirectory(prefix="oga-lcnc-") as tmp:
        files = {"program.ngc": program, "tools.tbl": tools, "params.var": params}
        for name, content in files.items():
            with open(os.path.join(tmp, name), "w", encoding="utf-8") as f:
                f.write(content)
        mask = sum(1 << "xyz".index(a) for a in axes)
        cmd = [python, str(_WORKER), "program.ngc", "tools.tbl", "params.var",
               str(4 * MAX_SEGMENTS + 1000), repr(timeout_s), LINUXCNC_PYTHON_PATH, str(mask),
               str(LINUXCNC_READ_MEMORY_BYTES)]
        try:
            done = subprocess.run(cmd, cwd=tmp, env=_env(tmp), capture_output=True,
                                  timeout=timeout_s + 10)
        except subprocess.TimeoutExpired:
            return [f"E -2 0 not finished within {timeout_s:g} s (an endless loop?)"]
    out = done.stdout.decode("utf-8", "replace").splitlines()
    if done.returncode != 0 or not out or not out[-1].startswith("E "):
        err = done.stderr.decode("utf-8", "replace").strip().splitlines()
        why = err[-1] if err else f"exit status {done.returncode}"
        return out + [f"E -4 0 LinuxCNC's interpreter failed: {why[:300]}"]
    return out


def read_linuxcnc(text: str, source: str = "", axes: str = "xyz", setup: Setup | None = None,
                  *, timeout_s: float = LINUXCNC_READ_TIMEOUT_S) -> Path:
    """Read a G-code program through LinuxCNC's interpreter (see the module notes).

    Parameters
    ----------
    text : str
        The program.
    source : str, optional
        Its name, for messages and ``Path.source``.
    axes : str, optional
        The machine's linear axes among ``"xyz"`` (the interpreter refuses words of others).
    setup : Setup, optional
        Home positions, work offsets, tool table.
    timeout_s : float, optional
        Longest run of the interpreter, seconds.

    Returns
    -------
    Path
        As :func:`feedplan.gcode.builtin.read_builtin` gives it.

    Raises
    ------
    GcodeError
        LinuxCNC refuses the program (its message, the line, the column of the word it names),
        or it does not finish in time, or it makes more moves than a path may hold.
    OgaError
        LinuxCNC's interpreter is not installed.
    """
    setup = setup or Setup()
    lines = text.split("\n")
    program, control, cycle_lines, motion_lines, warnings = _scan(
        [t.rstrip("\r") for t in lines], source)
    records = _run("\n".join(program) + "\n", _tool_table(setup, text), _parameters(setup),
                   axes, timeout_s)
    canon = _Canon(lines, source, axes, setup, control, cycle_lines, motion_lines)
    for w in warnings:
        canon.out.warn(w)
    for rec in records:
        if not canon.take(rec):
            break
    return canon.out.path()


class _Canon:
    """The worker's records (canon calls, line reports, the end) made into a Path.

    Positions come in inches in the program's coordinates with no offsets (as LinuxCNC's
    canon calls them); the offsets (G5x, G92, tool length) and the XY rotation reported
    beside them are applied here.
    """

    def __init__(self, lines: list[str], source: str, axes: str, setup: Setup, control: dict,
                 cycle_lines: set, motion_lines: set) -> None:
        self.lines, self.source, self.axes, self.setup = lines, source, axes, setup
        self.control, self.cycle_lines, self.motion_lines = control, cycle_lines, motion_lines
        self.out = PathBuilder(source, setup.work_offsets_m[0])
        self.g5x = np.zeros(3)
        self.g92 = np.zeros(3)
        self.tlo = np.zeros(3)
        self.rot = 0.0
        self.line, self.state = 0, None
        self.last_g64_p: float | None = None
        self.last_seen = 0
        self.unit_m = MM_M

    def machine(self, p) -> np.ndarray:
        """Machine position (m) of a program position (inches)."""
        v = np.asarray(p, dtype=np.float64) * INCH_M + self.g92
        if self.rot:
            c, s = math.cos(math.radians(self.rot)), math.sin(math.radians(self.rot))
            v = np.array([v[0] * c - v[1] * s, v[0] * s + v[1] * c, v[2]])
        return v + self.g5x + self.tlo

    def blend(self, n: int) -> float | None:
        """The blend tolerance (m) of a move of line ``n`` (0: exact stop; None: default)."""
        state = self.state
        if n in self.cycle_lines or (state is not None and state[0] in CYCLES
                                     and n not in self.motion_lines):
            return 0.0
        if n in self.control:
            mode, p = self.control[n]
            return mode if p is None else p * self.unit_m
        if state is not None and state[10] in (610, 611):
            return 0.0
        return None if self.last_g64_p is None else self.last_g64_p * self.unit_m

    def check_axes(self, values: list[float], n: int) -> None:
        """A rotary or UVW axis that moves: not on this machine."""
        for letter, v in zip("ABCUVW", values):
            if v != 0.0:
                raise GcodeError(f"axis {letter} moves: not on this machine (axes "
                                 f"{self.axes.upper()})", n, 1, self.source)

    def take(self, rec: str) -> bool:
        """Take one record; False at the end of the records."""
        kind, _, rest = rec.partition(" ")
        if kind == "N":
            self.at_line(rest)
        elif kind == "E":
            self.end(rest)
            return False
        else:
            self.canon(kind, [float(x) for x in rest.split()], self.line)
        return True

    def at_line(self, rest: str) -> None:
        """A line report: its number and the interpreter's modal state."""
        fields = [int(x) for x in rest.split()]
        self.line, self.state = fields[0], fields[1:]
        self.unit_m = INCH_M if self.state[4] == 200 else MM_M
        if self.last_seen < self.line:  # lines run since the last report (a linear program)
            for k in range(self.last_seen + 1, self.line + 1):
                if k in self.control and self.control[k][0] is None:
                    self.last_g64_p = self.control[k][1]
            self.last_seen = self.line

    def end(self, rest: str) -> None:
        """The last record: the program ended, or LinuxCNC's error (a GcodeError at the line
        and the column of the word it names)."""
        parts = rest.split(" ", 2)
        code, err_line, message = int(parts[0]), int(parts[1]), (parts[2:] or [""])[0]
        if not (code > 3 or code < 0):
            return
        if message.strip() == _NO_END:
            self.out.warn(NO_END)
            return
        lines = self.lines
        where = max(self.line or int(err_line), 1)
        src = lines[where - 1] if 0 < where <= len(lines) else ""
        # the interpreter reads the program from a copy: name the user's file
        message = message.strip().replace("file:program.ngc",
                                          f"file:{self.source or 'the program'}")
        raise GcodeError(f"LinuxCNC: {message}", where, _column(src, message), self.source)

    def canon(self, kind: str, v: list[float], n: int) -> None:
        """A canon call of line ``n``: a move, or a change of plane, feed, offsets."""
        out = self.out
        if kind in ("T", "F"):
            self.check_axes(v[3:], n)
            out.blend_tol_m = self.blend(n)
            (out.traverse if kind == "T" else out.feed)(self.machine(v[:3]), n)
        elif kind == "A":
            self.arc(v, n)
        elif kind == "P":
            out.plane = _PLANES.get(int(v[0]), out.plane)
        elif kind == "R":
            out.feed_m_s = v[0] * INCH_M / 60.0 if v[0] > 0 else None
        elif kind in ("D", "C"):
            out.stop()
        elif kind == "O":
            self.g5x = np.array(v[1:4]) * INCH_M
        elif kind == "G":
            self.g92 = np.array(v[:3]) * INCH_M
        elif kind == "X":
            self.rot = v[0]
        elif kind == "L":
            self.tool_length(v, n)

    def arc(self, v: list[float], n: int) -> None:
        """An arc: end and centre in the plane's axes, turns, the normal axis's end."""
        out = self.out
        self.check_axes(v[6:], n)
        i, j, k = PLANES[out.plane]
        if self.rot and out.plane != "xy":
            raise GcodeError("an arc outside G17 with an XY rotation (G10 L2 R) cannot be "
                             "planned", n, 1, self.source)
        prog_end = np.zeros(3)
        prog_end[[i, j, k]] = v[0], v[1], v[5]
        prog_centre = prog_end.copy()
        prog_centre[[i, j]] = v[2], v[3]
        out.blend_tol_m = self.blend(n)
        unit_m = self.unit_m
        end_tol = (ARC_END_TOL_IN if unit_m == INCH_M else ARC_END_TOL_MM) * unit_m
        out.arc(self.machine(prog_end), self.machine(prog_centre), int(v[4]), n,
                end_tol_m=end_tol, unit_m=unit_m)

    def tool_length(self, v: list[float], n: int) -> None:
        """The tool length offset; a warning for G43 without a tool table."""
        self.tlo = np.array(v[:3]) * INCH_M
        lines = self.lines
        src = _COMMENT.sub("", lines[n - 1]) if 0 < n <= len(lines) else ""
        if self.setup.tools is None and re.search(r"G\s*4\s*3(?![\s\d]*\.\s*1)", src, re.I):
            self.out.warn_once("without a tool table", f"line {n}: G43 without a tool table "
                               "(--tool-table): tool length 0 (a constant Z shift changes no "
                               "gain)")
