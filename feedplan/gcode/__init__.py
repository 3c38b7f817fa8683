"""G-code readers: program text -> :class:`~feedplan.path.Path` (machine coordinates, metres).

Two readers give the same path for the same program (the tests compare them move by move):

- ``builtin`` (:mod:`feedplan.gcode.builtin`): the dialect CAM post-processors write, in
  pure Python, fast, with a ``line:column`` for every refusal;
- ``linuxcnc`` (:mod:`feedplan.gcode.linuxcnc`): LinuxCNC's own interpreter (package
  linuxcnc-uspace) for everything it runs: cutter compensation, O-word subroutines and
  loops, parameters and expressions;
- ``auto`` (the default): the built-in reader, and LinuxCNC's where the built-in one meets a
  construct it does not read (``unsupported``) and LinuxCNC is installed (a warning names the
  construct); an error of the program itself (which the built-in reader sees as LinuxCNC's
  interpreter does) is the built-in reader's refusal, at its exact column, and costs no run
  of the interpreter.

Both take a :class:`Setup` (home positions, work offsets, tool table). Modules: ``lexer``
(the words of a line), ``builtin`` (modal state, home, offsets, tools), ``cycles`` (canned
cycles), ``setup`` (the setup, tool tables), ``moves`` (canonical moves -> Path, shared),
``linuxcnc`` (the interpreter in a child process).
"""

from __future__ import annotations

from feedplan.gcode.builtin import (ARC_END_TOL_IN, ARC_END_TOL_MM, INCH_M, MM_M,
                                    read_builtin)
from feedplan.gcode.linuxcnc import linuxcnc_available, read_linuxcnc
from feedplan.gcode.setup import Setup, Tool, load_tool_table, parse_tool_table
from feedplan.path import Path
from oga.defaults import GCODE_READER, GCODE_READERS
from oga.errors import GcodeError, OptionError

__all__ = ["parse_gcode", "Setup", "Tool", "load_tool_table", "parse_tool_table",
           "linuxcnc_available", "READERS", "MM_M", "INCH_M", "ARC_END_TOL_MM",
           "ARC_END_TOL_IN"]

#: The readers (``reader=``).
READERS = GCODE_READERS


def parse_gcode(text: str, source: str = "", axes: str = "xyz", *, reader: str = GCODE_READER,
                setup: Setup | None = None) -> Path:
    """Read a G-code program.

    Parameters
    ----------
    text : str
        The program.
    source : str, optional
        Its name (file name) for messages and ``Path.source``.
    axes : str, optional
        The machine's linear axes among ``"xyz"``; a word for any other axis is refused.
    reader : {"auto", "builtin", "linuxcnc"}, optional
        Which reader (module notes); default ``auto``.
    setup : Setup, optional
        Home positions, work offsets and tool table (default: machine zero, no offsets,
        no tool table).

    Returns
    -------
    Path
        Lines and arcs in machine coordinates and metres, feeds in m/s (rapids ``inf``),
        each segment with its 1-based source line; ``warnings`` holds non-fatal remarks.

    Raises
    ------
    GcodeError
        The program is refused (line, column, what): by the built-in reader, or by
        LinuxCNC's interpreter when it reads it.
    OptionError
        ``axes`` is not a set of letters among x, y, z, or ``reader`` is unknown, or
        ``linuxcnc`` is asked for where LinuxCNC is not installed.
    """
    axes_l = axes.lower()
    if not axes_l or set(axes_l) - set("xyz") or len(set(axes_l)) != len(axes_l):
        raise OptionError(f"axes must be distinct letters among x, y, z, got {axes!r}")
    if reader not in READERS:
        raise OptionError(f"reader: unknown G-code reader {reader!r} (expected one of "
                          f"{', '.join(READERS)})")
    if reader == "linuxcnc":
        if not linuxcnc_available():
            raise OptionError("reader linuxcnc: LinuxCNC's interpreter is not installed here "
                              "(Debian package linuxcnc-uspace)")
        return read_linuxcnc(text, source, axes_l, setup)
    try:
        return read_builtin(text, source, axes_l, setup)
    except GcodeError as builtin_err:
        err = builtin_err
        if reader == "builtin" or not getattr(err, "unsupported", False):
            raise  # an error LinuxCNC's interpreter has too (the built-in reader mirrors it)
        if not linuxcnc_available():
            raise GcodeError(err.message.replace(
                "--reader linuxcnc reads it", "LinuxCNC's interpreter (--reader linuxcnc, "
                "package linuxcnc-uspace, not installed here) reads it"),
                err.line, err.column, err.source) from None
        path = read_linuxcnc(text, source, axes_l, setup)
    note = (f"line {err.line}:{err.column}: {err.message.split(' (not in the built-in')[0]}: "
            "read by LinuxCNC's interpreter")
    return Path(start=path.start, segments=path.segments, plane=path.plane, source=path.source,
                warnings=(note, *path.warnings))
