"""Read a toolpath of any supported format: G-code, CSV or JSON polyline -> Path."""

from __future__ import annotations

import os
from pathlib import Path as FilePath

from feedplan.gcode import Setup, parse_gcode
from feedplan.path import Path
from feedplan.polyline import parse_csv, parse_json
from oga.defaults import MAX_TOOLPATH_BYTES, MAX_TOOLPATH_LINES
from oga.files import read_limited
from oga.errors import OptionError, ToolpathError

__all__ = ["FORMATS", "SUFFIXES", "read_toolpath", "read_file", "load_toolpath"]

#: Reader of each format name.
FORMATS = {"gcode": parse_gcode, "csv": parse_csv, "json": parse_json}

#: Format of each file name extension (lower case).
SUFFIXES = {**dict.fromkeys((".ngc", ".nc", ".gcode", ".gc", ".tap", ".cnc"), "gcode"),
            ".csv": "csv", ".json": "json"}


def read_toolpath(text: str, fmt: str, source: str = "", *, reader: str = "auto",
                  setup: Setup | None = None) -> Path:
    """Parse toolpath text of a given format.

    Parameters
    ----------
    text : str
        The program or polyline.
    fmt : {"gcode", "csv", "json"}
        Its format.
    source : str, optional
        Its name, for messages and ``Path.source``.
    reader : {"auto", "builtin", "linuxcnc"}, optional
        G-code only: the reader (:func:`feedplan.gcode.parse_gcode`).
    setup : Setup, optional
        G-code only: home positions, work offsets, tool table.

    Returns
    -------
    Path
        Lines and arcs in metres, feeds in m/s.

    Raises
    ------
    OptionError
        ``fmt`` is not a known format.
    GcodeError, ToolpathError
        The text is invalid (line/column or field named), or has more lines (JSON: arrays)
        than :data:`~oga.defaults.MAX_TOOLPATH_LINES`.
    """
    if fmt not in FORMATS:
        raise OptionError(f"unknown toolpath format {fmt!r} (expected one of "
                          f"{', '.join(FORMATS)})")
    # bounded before the readers split or decode it (a line list or a JSON tree of the whole
    # text costs far more memory than the text): lines, or JSON's arrays (one per point)
    unit, count = ("arrays", text.count("[")) if fmt == "json" else ("lines", text.count("\n"))
    if count > MAX_TOOLPATH_LINES:
        raise ToolpathError(f"{source or 'toolpath'}: {count} {unit}, more than the "
                            f"{MAX_TOOLPATH_LINES} a toolpath may have")
    if fmt == "gcode":
        return parse_gcode(text, source=source, reader=reader, setup=setup)
    return FORMATS[fmt](text, source=source)


def read_file(path: str | os.PathLike) -> tuple[str, str]:
    """The text of a toolpath file and its format, chosen by the extension.

    G-code: ``.ngc .nc .gcode .gc .tap .cnc``; polylines: ``.csv``, ``.json``
    (any case). The file must be UTF-8 text (a byte-order mark is allowed).

    Returns
    -------
    text : str
    fmt : {"gcode", "csv", "json"}

    Raises
    ------
    ToolpathError
        Unknown extension, unreadable or too large file (:data:`~oga.defaults.MAX_TOOLPATH_BYTES`),
        or not UTF-8 text.
    """
    name = os.fspath(path)
    suffix = FilePath(name).suffix.lower()
    if suffix not in SUFFIXES:
        raise ToolpathError(f"{name}: unknown toolpath extension {suffix or '(none)'!r} "
                            f"(expected one of {' '.join(SUFFIXES)})")
    data = read_limited(name, MAX_TOOLPATH_BYTES, ToolpathError)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        column = err.start - (data.rfind(b"\n", 0, err.start) + 1) + 1
        raise ToolpathError(f"not UTF-8 text (byte 0x{data[err.start]:02x})",
                            line, column, source=name) from None
    return text, SUFFIXES[suffix]


def load_toolpath(path: str | os.PathLike, *, reader: str = "auto",
                  setup: Setup | None = None) -> Path:
    """Read and parse a toolpath file (:func:`read_file`, then :func:`read_toolpath`).

    The file name as given becomes ``Path.source``; ``reader`` and ``setup`` are those of
    :func:`read_toolpath`.

    Raises
    ------
    ToolpathError, GcodeError
        Unreadable file or invalid content (line/column or field named).
    """
    text, fmt = read_file(path)
    return read_toolpath(text, fmt, source=os.fspath(path), reader=reader, setup=setup)
