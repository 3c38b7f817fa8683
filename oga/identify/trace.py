"""Recorded traces of the position loop: reading and checking them.

Three formats, each to one :class:`Trace` (SI inside):

- ``csv``: a header row, comma separated: ``t_s``, and per recorded axis ``<a>_cmd_m``
  (position setpoint into the position loop) and ``<a>_act_m`` (measured position);
  optional ``<a>_ff_vel_m_s`` (velocity setpoint feeding Kf), ``<a>_vcmd_m_s`` (velocity
  command out of the position loop), ``<a>_act_vel_m_s``, ``<a>_force_n``, and the gains
  active while recording, ``<a>_kp_m_min_per_mm`` and ``<a>_kf``. With ``units="mm"``
  every length (positions, velocities) is in mm.
- ``halsampler``: LinuxCNC's ``halsampler`` output, whitespace-separated numbers, one
  row per servo period, no header; ``columns`` names them (the names above; ``sample``
  for the sample number of ``halsampler -t``, ``-`` for a column to skip). Times are
  the sample number (or the row) times the machine's period.
- ``twincat``: a TwinCAT Scope View CSV export (tab, ``;`` or ``,`` separated, decimal
  comma accepted where ``,`` is not the separator): header rows, then rows of numbers
  whose first column is the time in ms; further columns equal to it (one time line per
  channel) are dropped; the remaining channels are named by ``columns`` in order, or by
  the header row starting with ``Name``.

Refused, naming the column and the row: a cell that is not a number or not finite, a
time step that is zero (duplicated row), over 1.5 periods (gap) or otherwise off the
period (non-uniform sampling), a speed no machine reaches (a trace in mm read as
metres), more rows than :data:`oga.defaults.TRACE_MAX_ROWS`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES
from oga.defaults import (
    TRACE_DT_REL_TOL,
    TRACE_MAX_BYTES,
    TRACE_MAX_ROWS,
    TRACE_MAX_SPEED_M_S,
)
from oga.errors import InputError
from oga.files import read_limited

__all__ = ["AxisTrace", "Trace", "TraceError", "TraceTable", "FORMATS", "read_table",
           "read_trace", "load_trace", "parse_gains", "trace_csv", "check_speed"]

#: Trace formats read.
FORMATS = ("csv", "halsampler", "twincat")
#: Per-axis channels: suffix -> (AxisTrace field, is a length).
_CHANNELS = {
    "cmd_m": ("cmd_m", True),
    "act_m": ("act_m", True),
    "ff_vel_m_s": ("ff_vel_m_s", True),
    "vcmd_m_s": ("vcmd_m_s", True),
    "act_vel_m_s": ("act_vel_m_s", True),
    "force_n": ("force_n", False),
    "kp_m_min_per_mm": ("kp_m_min_per_mm", False),
    "kf": ("kf", False),
}
_NAME = re.compile(r"^([xyz])_(" + "|".join(_CHANNELS) + r")$")


class TraceError(InputError):
    """A trace cannot be read or is not fit to identify from (column and row named)."""


@dataclass(frozen=True, eq=False)
class AxisTrace:
    """The recorded channels of one axis, each of shape (N,) or None when not recorded.

    Attributes
    ----------
    cmd_m, act_m : ndarray
        Position setpoint and measured position, m.
    ff_vel_m_s, vcmd_m_s, act_vel_m_s : ndarray or None
        Velocity setpoint feeding Kf, velocity command, measured velocity, m/s.
    force_n : ndarray or None
        Drive force, N.
    kp_m_min_per_mm, kf : ndarray
        Gains active at each sample.
    """

    cmd_m: np.ndarray
    act_m: np.ndarray
    kp_m_min_per_mm: np.ndarray
    kf: np.ndarray
    ff_vel_m_s: np.ndarray | None = None
    vcmd_m_s: np.ndarray | None = None
    act_vel_m_s: np.ndarray | None = None
    force_n: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Trace:
    """A recorded trace: uniform period ``dt_s`` (s), ``n`` samples, the recorded axes."""

    dt_s: float
    n: int
    axes: dict[str, AxisTrace]
    source: str = ""


def parse_gains(text: str | float | dict | None, name: str) -> dict[str, float] | None:
    """``--kp``/``--kf`` values: one number for every axis (``2.0``, as ``{"*": 2.0}``) or per
    axis (``x=2.0,z=2.5``); None stays None. TraceError naming the option if malformed."""
    if text is None:
        return None
    if isinstance(text, dict):
        items = text.items()
    elif isinstance(text, (int, float)):
        items = [("*", text)]
    else:
        items = []
        for part in str(text).split(","):
            key, sep, val = part.partition("=")
            items.append((key.strip(), val) if sep else ("*", key))
    out = {}
    for key, val in items:
        if key not in ("*", *AXES):
            raise TraceError(f"--{name}: unknown axis {key!r}; use x, y, z")
        try:
            out[key] = float(val)
        except (TypeError, ValueError):
            raise TraceError(f"--{name}: {val!r} is not a number") from None
        if not math.isfinite(out[key]) or out[key] < 0 or (name == "kp" and out[key] == 0):
            raise TraceError(f"--{name}: {out[key]} is out of range")
    return out


def _float(cell: str, col: str, row: int, decimal_comma: bool = False) -> float:
    text = cell.strip()
    if decimal_comma:
        text = text.replace(",", ".")
    try:
        x = float(text)
    except ValueError:
        raise TraceError(f"column {col!r}, row {row}: {cell.strip()!r} is not a number") from None
    if not math.isfinite(x):
        raise TraceError(f"column {col!r}, row {row}: {cell.strip()} is not a finite number")
    return x


def _table(lines, names: list[str], first_row: int, split,
           decimal_comma=False) -> tuple[np.ndarray, np.ndarray]:
    """Rows of numbers into an (N, len(names)) array, and the 1-based file line of each row
    (``lines[0]`` is line ``first_row``; blank lines are skipped)."""
    rows, where = [], []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        if len(rows) >= TRACE_MAX_ROWS:
            raise TraceError(f"row {first_row + i}: more than {TRACE_MAX_ROWS} rows")
        cells = split(line)
        if len(cells) != len(names):
            raise TraceError(
                f"row {first_row + i}: {len(cells)} columns, the header names {len(names)}")
        rows.append([_float(c, n, first_row + i, decimal_comma) for c, n in zip(cells, names)])
        where.append(first_row + i)
    if len(rows) < 2:
        raise TraceError("the trace has fewer than 2 rows of data")
    return np.array(rows), np.array(where)


def _read_csv(text: str) -> tuple[list[str], np.ndarray, np.ndarray]:
    lines = text.splitlines()
    if not lines:
        raise TraceError("empty trace")
    names = [c.strip() for c in lines[0].split(",")]
    return (names, *_table(lines[1:], names, 2, lambda s: s.split(",")))


def _read_halsampler(text: str,
                     columns: list[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
    if not columns:
        raise TraceError("a halsampler trace needs --columns naming its columns in order")
    lines = ["" if ln.startswith("#") else ln for ln in text.splitlines()]  # comments
    return (columns, *_table(lines, columns, 1, str.split))


def _read_twincat(text: str,
                  columns: list[str] | None) -> tuple[list[str], np.ndarray, np.ndarray]:
    lines = text.splitlines()
    sep = "\t" if any("\t" in ln for ln in lines[:50]) else (
        ";" if any(";" in ln for ln in lines[:50]) else ",")
    dec = sep != ","
    split = (lambda s: s.split(sep))
    start = None
    header_names = None
    for i, line in enumerate(lines[:1000]):
        cells = [c.strip() for c in split(line)]
        if cells and cells[0].lower() == "name":
            header_names = cells
        try:
            if line.strip() and all(c for c in cells):
                [float(c.replace(",", ".") if dec else c) for c in cells]
                start = i
                break
        except ValueError:
            continue
    if start is None:
        raise TraceError("no rows of numbers found in the first 1000 lines of the TwinCAT export")
    width = len(split(lines[start]))
    raw, where = _table(lines[start:], [f"column {j + 1}" for j in range(width)], start + 1,
                        split, dec)
    keep = [j for j in range(1, width) if not np.array_equal(raw[:, j], raw[:, 0])]
    if columns:
        names = columns
    elif header_names is not None and len(header_names) - 1 == width:  # key, then one per column
        names = [header_names[1 + j] for j in keep]
    else:
        raise TraceError("name the TwinCAT channels with --columns (no Name row matches them)")
    if len(names) != len(keep):
        raise TraceError(
            f"--columns names {len(names)} channels; the export has {len(keep)} besides time")
    data = np.column_stack([raw[:, 0] * 1e-3] + [raw[:, j] for j in keep])
    return ["t_s", *names], data, where


@dataclass(frozen=True, eq=False)
class TraceTable:
    """The numbers of a trace file before they are given meaning: named columns over
    uniformly sampled rows (:func:`read_table`).

    Attributes
    ----------
    columns : dict of str to int
        Column name -> index into ``data`` (columns named ``-`` are left out).
    data : ndarray, shape (N, C)
        The rows of numbers (TwinCAT: the time in s first, its channels' time columns dropped).
    dt_s : float
        The uniform period, s.
    rows : ndarray of int, shape (N,)
        1-based line of the file holding each row (messages name file rows).
    """

    columns: dict
    data: np.ndarray
    dt_s: float
    rows: np.ndarray


def read_table(text: str, fmt: str = "csv", *, columns: list[str] | None = None,
               te_s: float | None = None, extra: tuple[str, ...] = ()) -> TraceTable:
    """A trace file's rows, named and checked for uniform sampling (:func:`read_trace`'s
    first steps, shared with readers of other recordings).

    Parameters
    ----------
    text, fmt, columns, te_s
        As :func:`read_trace`. A halsampler file's ``#`` lines are comments.
    extra : tuple of str
        Column names accepted besides ``t_s``, ``sample`` and ``<a>_<channel>``.

    Raises
    ------
    TraceError
        Naming the column and the row.
    """
    if fmt not in FORMATS:
        raise TraceError(f"unknown trace format {fmt!r}; use one of {', '.join(FORMATS)}")
    lines = text.count("\n")  # bounded before the text is split into lines
    if lines > TRACE_MAX_ROWS + 1000:  # the rows and a header (TwinCAT's is long)
        raise TraceError(f"{lines} lines, more than the {TRACE_MAX_ROWS} rows a trace may have")
    cols = None if columns is None else [c.strip() for c in columns]
    if fmt == "csv":
        names, data, rows = _read_csv(text)
    elif fmt == "halsampler":
        names, data, rows = _read_halsampler(text, cols)
    else:
        names, data, rows = _read_twincat(text, cols)
    col = _columns(names, extra)
    if "t_s" in col:
        t = data[:, col["t_s"]]
    elif "sample" in col:
        if te_s is None:
            raise TraceError("a trace with sample numbers needs the machine's period")
        t = data[:, col["sample"]] * te_s
    elif te_s is not None:
        t = np.arange(len(data)) * te_s
    else:
        raise TraceError("the trace has no t_s column")
    dt = _check_times(t, "t_s" if "t_s" in col else "sample", rows)
    return TraceTable(columns=col, data=data, dt_s=dt, rows=rows)


def read_trace(
    text: str,
    fmt: str = "csv",
    *,
    columns: list[str] | None = None,
    units: str = "m",
    kp=None,
    kf=None,
    te_s: float | None = None,
    source: str = "",
) -> Trace:
    """Read and check a trace (module docstring for the formats).

    Parameters
    ----------
    text : str
        The file's content.
    fmt : {"csv", "halsampler", "twincat"}
    columns : list of str, optional
        Channel names in order (halsampler, twincat).
    units : {"m", "mm"}
        Unit of the lengths in the file.
    kp, kf : str, float or dict, optional
        The gains active while recording (:func:`parse_gains`), where no column gives them.
    te_s : float, optional
        The position-loop period, s: the period of a trace without times (halsampler).
    source : str
        Name of the trace for messages.

    Returns
    -------
    Trace

    Raises
    ------
    TraceError
        Anything wrong, naming the column and the row.
    """
    if units not in ("m", "mm"):
        raise TraceError(f"--units must be m or mm, got {units!r}")
    table = read_table(text, fmt, columns=columns, te_s=te_s)
    col, data, dt, rows = table.columns, table.data, table.dt_s, table.rows
    scale = 1e-3 if units == "mm" else 1.0
    kp_opt, kf_opt = parse_gains(kp, "kp"), parse_gains(kf, "kf")
    axes = {}
    for a in AXES:
        chans = {}
        for suffix, (field, length) in _CHANNELS.items():
            j = col.get(f"{a}_{suffix}")
            if j is not None:
                chans[field] = data[:, j] * (scale if length else 1.0)
        if not chans:
            continue
        for need in ("cmd_m", "act_m"):
            if need not in chans:
                raise TraceError(f"axis {a}: the trace has {sorted(chans)} but no {a}_{need} column")
        for gain, opt in (("kp_m_min_per_mm", kp_opt), ("kf", kf_opt)):
            if gain in chans:
                continue
            value = None if opt is None else opt.get(a, opt.get("*"))
            if value is None:
                flag = "--kp" if gain.startswith("kp") else "--kf"
                raise TraceError(f"axis {a}: no {a}_{gain} column and no {flag} for it")
            chans[gain] = np.full(len(data), value)
        for name in ("cmd_m", "act_m"):
            check_speed(chans[name], dt, f"{a}_{name}", rows, units)
        if np.any(chans["kp_m_min_per_mm"] <= 0):
            k = int(np.argmax(chans["kp_m_min_per_mm"] <= 0))
            raise TraceError(f"column {a}_kp_m_min_per_mm, row {rows[k]}: Kp must be positive")
        axes[a] = AxisTrace(**chans)
    if not axes:
        raise TraceError("the trace has no axis columns (<a>_cmd_m and <a>_act_m, a = x, y, z)")
    return Trace(dt_s=dt, n=len(data), axes=axes, source=source)


def _columns(names: list[str], extra: tuple[str, ...] = ()) -> dict[str, int]:
    col = {}
    for j, name in enumerate(names):
        if name == "-":
            continue
        if name not in ("t_s", "sample", *extra) and not _NAME.match(name):
            raise TraceError(
                f"column {j + 1}: unknown name {name!r} (t_s, sample, or <a>_<channel> with "
                f"a in x, y, z and channel in {', '.join(_CHANNELS)})")
        if name in col:
            raise TraceError(f"column {j + 1}: {name!r} appears twice")
        col[name] = j
    return col


def _check_times(t: np.ndarray, name: str, rows: np.ndarray) -> float:
    """The trace's period (s); TraceError at the first duplicated, missing or off-period step."""
    steps = np.diff(t)
    dt = float(np.median(steps))
    if not dt > 0:
        raise TraceError(f"column {name!r}: times do not increase")
    for k in np.flatnonzero(np.abs(steps - dt) > TRACE_DT_REL_TOL * dt)[:1]:
        row = int(rows[k + 1])
        if steps[k] == 0:
            raise TraceError(f"column {name!r}, row {row}: duplicated row (same time as the row before)")
        if steps[k] > 1.5 * dt:
            raise TraceError(
                f"column {name!r}, row {row}: gap of {steps[k] / dt:.3g} periods ({dt:g} s) before it")
        raise TraceError(
            f"column {name!r}, row {row}: non-uniform sampling, step {steps[k]:g} s, period {dt:g} s")
    return dt


def check_speed(x: np.ndarray, dt: float, name: str, rows: np.ndarray, units: str) -> None:
    """TraceError naming the column and the row where ``x`` (m) moves faster than any
    machine axis does (:data:`oga.defaults.TRACE_MAX_SPEED_M_S`): a file in mm read as m."""
    v = np.abs(np.diff(x)) / dt
    over = np.flatnonzero(v > TRACE_MAX_SPEED_M_S)
    if over.size:
        k = int(over[0])
        hint = "" if units in ("mm", "inch") else " (a trace in mm? give --units mm)"
        raise TraceError(
            f"column {name!r}, row {int(rows[k + 1])}: speed {v[k]:.3g} m/s is absurd{hint}")


def load_trace(path: str | os.PathLike, fmt: str | None = None, **kw) -> Trace:
    """Read a trace file (:func:`read_trace`); ``fmt`` None: ``halsampler`` when ``columns`` is
    given and the file is not ``.csv``, else ``csv``; the file size is checked first."""
    try:
        text = read_limited(path, TRACE_MAX_BYTES, TraceError, "trace").decode("utf-8")
    except UnicodeDecodeError:
        raise TraceError(f"{path}: not a UTF-8 text file") from None
    if fmt is None:
        fmt = "halsampler" if kw.get("columns") and not str(path).endswith(".csv") else "csv"
    return read_trace(text, fmt, source=os.path.basename(str(path)), **kw)


def trace_csv(t_s: np.ndarray, channels: dict[str, np.ndarray]) -> str:
    """A trace as the CSV this module reads: ``t_s`` then the named channels (SI, full
    precision)."""
    names = ["t_s", *channels]
    cols = [np.asarray(t_s)] + [np.asarray(c) for c in channels.values()]
    body = "\n".join(",".join(repr(float(c[k])) for c in cols) for k in range(len(t_s)))
    return ",".join(names) + "\n" + body + "\n"
