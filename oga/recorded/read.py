"""Setpoints another interpolator produced, read from a recording and checked.

Formats (the readers of ``oga identify``, :mod:`oga.identify.trace`):

- ``csv``: ``t_s`` and per axis ``<a>_cmd_m``, the position setpoint into the position loop;
  optional ``<a>_ff_vel_m_s``, the velocity the loop multiplies by Kf (else the centred
  difference of the positions, as oga's planner gives), ``line`` (program line) and
  ``rapid`` (1 in a rapid); other channels of a trace (``<a>_act_m``, ...) are ignored.
- ``twincat``: a Scope View export of the same channels (``columns`` names them).
- ``halsampler``: LinuxCNC's ``joint.N.motor-pos-cmd`` per servo period, read with ``pid``'s
  law (:mod:`oga.recorded.lcnc`): a recording of ``oga lcnc-record`` (its header names the
  columns, units and ``pid`` setting) or a plain ``halsampler`` file (``columns``, ``units``
  and ``error_previous_target`` given). Optional ``line`` (``motion.program-line``),
  ``motion_type`` (``motion.motion-type``, 1 in a rapid) and ``current_vel_m_s``
  (``motion.current-vel``), ``part`` (``oga lcnc-record``: the part of the program between
  two stops LinuxCNC's task timed, -1 in a stop).

Refused, naming the column and the row: what the trace readers refuse (a cell that is not a
finite number, non-uniform sampling, an absurd speed), a period other than the machine's Te,
setpoints whose finite differences break the machine's axis velocity, acceleration or jerk
limits, a program line or flag that is not an integer.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import numpy as np

from feedplan.plan import derivatives, plane_of
from feedplan.setpoints import AXES, Setpoints
from oga.defaults import LINUXCNC, TRACE_MAX_BYTES
from oga.files import read_limited
from oga.identify.trace import TraceError, check_speed, read_table
from oga.model.machine import Machine
from oga.recorded.check import SetpointsError, check_limits, check_period
from oga.recorded.lcnc import LinuxcncPeriods, parse_header, pid_law

__all__ = ["SETPOINT_FORMATS", "UNITS", "RecordedSetpoints", "read_setpoints", "load_setpoints",
           "read_setpoints_file"]

#: Formats of recorded setpoints.
SETPOINT_FORMATS = ("csv", "halsampler", "twincat")
#: Length units of a file: metres per unit.
UNITS = {"m": 1.0, "mm": 1e-3, "inch": 0.0254}
#: Columns besides the trace channels.
_EXTRA = ("line", "rapid", "motion_type", "current_vel_m_s", "part")
#: ``motion.motion-type`` of a rapid (LinuxCNC's EMC_MOTION_TYPE_TRAVERSE).
_TRAVERSE = 1


@dataclass(frozen=True, eq=False)
class RecordedSetpoints:
    """Setpoints read from a recording, and where they came from.

    Attributes
    ----------
    setpoints : Setpoints
        The setpoints (the machine's Te apart).
    source : dict
        ``file``, ``format``, ``sha256`` (of the file's text), ``law`` (``given`` or
        ``linuxcnc-pid``), ``samples``, ``first_row`` (file line of sample 0); JSON-able.
    linuxcnc : LinuxcncPeriods or None
        The recorded servo periods (``halsampler`` files), for the LinuxCNC export.
    """

    setpoints: Setpoints
    source: dict
    linuxcnc: LinuxcncPeriods | None = None


def _integers(x: np.ndarray, name: str, rows: np.ndarray) -> np.ndarray:
    bad = np.flatnonzero(x != np.round(x))
    if bad.size:
        k = int(bad[0])
        raise SetpointsError(f"column {name!r}, row {int(rows[k])}: {float(x[k])!r} is not an "
                             "integer")
    return np.round(x).astype(np.int64)


def read_setpoints(text: str, machine: Machine | None, fmt: str | None = None, *,
                   columns: list[str] | None = None, units: str | None = None,
                   error_previous_target: bool | None = None, source: str = "",
                   te_s: float | None = None) -> RecordedSetpoints:
    """Read and check recorded setpoints (module docstring for the formats).

    Parameters
    ----------
    text : str
        The file's content.
    machine : Machine or None
        The machine they are optimised for (its Te and axis limits); None: read them again
        (for an export), the period ``te_s`` given, no limit checked.
    fmt : {"csv", "halsampler", "twincat"}, optional
        Default: ``halsampler`` for an ``oga lcnc-record`` file, else ``csv``.
    columns : list of str, optional
        Channel names in order (``halsampler`` without header, ``twincat``).
    units : {"m", "mm", "inch"}, optional
        Length unit of the file (default: the header's, else m).
    error_previous_target : bool, optional
        ``halsampler`` without header: ``pid.N.error-previous-target`` (default TRUE).
    source : str
        The file's name, for messages and the summary.
    te_s : float, optional
        The period, s, without a machine.

    Raises
    ------
    SetpointsError
        Naming the column and the row (TraceError, an InputError).
    """
    header = parse_header(text)
    te = machine.te if machine is not None else te_s
    if te is None:
        raise ValueError("read_setpoints: give the machine or the period")
    fmt, columns, units = _format(header, fmt, columns, units, te, source)
    try:
        table = read_table(text, fmt, columns=columns, te_s=te, extra=_EXTRA)
    except SetpointsError:
        raise
    except TraceError as err:  # the trace readers' message, as this reader's error
        raise SetpointsError(str(err)) from None
    col, data, rows = table.columns, table.data, table.rows
    check_period(table.dt_s, te, "t_s" if "t_s" in col else "sample")
    axes, raw = _commands(table, units)
    line, rapid = _line_and_rapid(table)
    periods, lcnc = np.arange(len(data)), None
    if fmt == "halsampler":
        ept = _error_previous_target(header, axes, error_previous_target)
        periods, pos, vel = pid_law(raw, te, ept, axes)
        cv = (data[periods, col["current_vel_m_s"]] * UNITS[units]
              if "current_vel_m_s" in col else None)
        lcnc = LinuxcncPeriods(
            cmd_m=raw[periods], axes=axes, line=None if line is None else line[periods],
            current_vel_m_s=cv, part=_parts(table, periods),
            error_previous_target={a: ept[a] for a in axes}, units=units,
            joints=None if header is None else header.joints, first_row=int(rows[periods[0]]))
        _, acc, jerk = derivatives(pos, te)
    else:
        pos = raw
        vel, acc, jerk = derivatives(pos, te)
        for k, a in enumerate(AXES):
            if f"{a}_ff_vel_m_s" in col:
                vel[:, k] = data[:, col[f"{a}_ff_vel_m_s"]] * UNITS[units]
    sample_rows = rows[periods]
    if machine is not None:
        check_limits(pos, te, machine, {a: f"{a}_cmd_m" for a in AXES}, sample_rows)
    sp = _setpoints(te, (pos, vel, acc, jerk), None if line is None else line[periods],
                    rapid[periods], source, None if lcnc is None else lcnc.part)
    info = {"file": source, "format": fmt,
            "sha256": hashlib.sha256(text.encode("utf-8")).hexdigest(),
            "law": "linuxcnc-pid" if fmt == "halsampler" else "given", "units": units,
            "samples": len(sp), "first_row": int(sample_rows[0])}
    if lcnc is not None:
        info["error_previous_target"] = lcnc.error_previous_target
    meta = {} if header is None else header.meta  # lcnc-record: resumed M0/M1, the parts
    info.update({k.replace("-", "_"): meta[k] for k in ("program-pauses", "parts") if k in meta})
    return RecordedSetpoints(setpoints=sp, source=info, linuxcnc=lcnc)


def _format(header, fmt: str | None, columns, units: str | None, te: float, source: str):
    """The format, column names and units: given, or the ``oga lcnc-record`` header's
    (whose servo period must be ``te``); SetpointsError where they do not fit."""
    if fmt is None:
        fmt = "halsampler" if header is not None else "csv"
    if fmt not in SETPOINT_FORMATS:
        raise SetpointsError(f"unknown setpoints format {fmt!r}; use one of "
                             f"{', '.join(SETPOINT_FORMATS)}")
    if header is not None and fmt != "halsampler":
        raise SetpointsError(f"{source or 'the file'} is an oga lcnc-record recording: read it "
                             "as halsampler")
    if header is not None:
        columns = columns or header.columns
        units = units or header.units
        if header.period_ns is not None:
            check_period(header.period_ns * 1e-9, te, "servo-period-ns")
    if fmt == "halsampler" and not columns:
        raise SetpointsError("a halsampler recording without an oga lcnc-record header needs "
                             "its column names in order (--setpoints-columns, e.g. "
                             "sample,x_cmd_m,z_cmd_m)")
    units = units or "m"
    if units not in UNITS:
        raise SetpointsError(f"units: expected one of {', '.join(UNITS)}, got {units!r}")
    return fmt, columns, units


def _commands(table, units: str) -> tuple[tuple[str, ...], np.ndarray]:
    """The axes with a position setpoint column and the setpoints (rows, 3) m, each axis's
    speed checked (zeros on the others)."""
    col, data, rows = table.columns, table.data, table.rows
    scale = UNITS[units]
    axes = tuple(a for a in AXES if f"{a}_cmd_m" in col)
    if not axes:
        raise SetpointsError("no position setpoint column (<a>_cmd_m, a = x, y, z)")
    raw = np.zeros((len(data), 3))
    for k, a in enumerate(AXES):
        if a in axes:
            raw[:, k] = data[:, col[f"{a}_cmd_m"]] * scale
            try:
                check_speed(raw[:, k], table.dt_s, f"{a}_cmd_m", rows, units)
            except TraceError as err:
                raise SetpointsError(str(err)) from None
    return axes, raw


def _line_and_rapid(table) -> tuple[np.ndarray | None, np.ndarray]:
    """The program line per row (None without the column) and the rapid flags (from
    ``rapid``, else ``motion_type``, else none)."""
    col, data, rows = table.columns, table.data, table.rows
    line = _integers(data[:, col["line"]], "line", rows) if "line" in col else None
    if "rapid" in col:
        rapid = _integers(data[:, col["rapid"]], "rapid", rows)
        if np.any((rapid != 0) & (rapid != 1)):
            k = int(np.flatnonzero((rapid != 0) & (rapid != 1))[0])
            raise SetpointsError(f"column 'rapid', row {int(rows[k])}: expected 0 or 1")
        rapid = rapid.astype(bool)
    elif "motion_type" in col:
        rapid = _integers(data[:, col["motion_type"]], "motion_type", rows) == _TRAVERSE
    else:
        rapid = np.zeros(len(data), dtype=bool)
    return line, rapid


def _setpoints(te, kinematics, line, rapid, source, part) -> Setpoints:
    """The :class:`Setpoints` of the samples: ``kinematics`` (pos, vel, acc, jerk) (N, 3) each,
    ``line`` (N,) or None, ``rapid`` (N,), ``part`` (N,) or None (-1 in a stop: held)."""
    pos = kinematics[0]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    return Setpoints(dt=te, s=s, pos=pos, vel=kinematics[1], acc=kinematics[2],
                     jerk=kinematics[3],
                     block=np.zeros(len(pos), dtype=np.int64) if line is None else line,
                     rapid=rapid, plane=plane_of(pos, rapid, "xy"), source=source,
                     held=None if part is None else part < 0)


def _parts(table, periods: np.ndarray) -> np.ndarray | None:
    """The part of each sample (N,) from the ``part`` column (None without it): -1 in a stop,
    else 0, 1, ... in order, each part's samples contiguous, the first and the last sample in
    a part; SetpointsError naming the row otherwise."""
    if "part" not in table.columns:
        return None
    rows = table.rows[periods]
    part = _integers(table.data[periods, table.columns["part"]], "part", rows)
    starts = np.r_[0, np.flatnonzero(np.diff(part)) + 1]  # runs of one value: 0, -1, 1, ...
    want = np.full(len(starts) + (len(starts) + 1) % 2, -1)
    want[::2] = np.arange((len(want) + 1) // 2)
    bad = np.flatnonzero(part[starts] != want[:len(starts)])
    if bad.size or len(starts) % 2 == 0:
        k = int(starts[bad[0]]) if bad.size else int(starts[-1])
        raise SetpointsError(f"column 'part', row {int(rows[k])}: expected -1 (a stop) or the "
                             "part's number (0, 1, ... in order, the first and the last sample "
                             f"in a part), got {int(part[k])}")
    return part


def _error_previous_target(header, axes, error_previous_target: bool | None) -> dict:
    """``pid.N.error-previous-target`` per axis: the header's, else given, else LinuxCNC's."""
    if header is not None and header.error_previous_target is not None:
        ept = header.error_previous_target
        missing = [a for a in axes if a not in ept]
        if missing:
            raise SetpointsError(f"header 'error-previous-target': no value for axis "
                                 f"{', '.join(missing)}")
        return ept
    flag = LINUXCNC["error_previous_target"] if error_previous_target is None \
        else bool(error_previous_target)
    return dict.fromkeys(axes, flag)


def read_setpoints_file(path: str | os.PathLike, fmt: str | None = None,
                        columns: list[str] | None = None) -> tuple[str, str]:
    """The text of a setpoints file (its size checked first) and its format: ``fmt``, or
    ``halsampler`` for an ``oga lcnc-record`` file or when ``columns`` are given to a file
    not named ``.csv``, else ``csv``."""
    try:
        text = read_limited(path, TRACE_MAX_BYTES, SetpointsError, "setpoints").decode("utf-8")
    except UnicodeDecodeError:
        raise SetpointsError(f"{path}: not a UTF-8 text file") from None
    if fmt is None:
        fmt = "halsampler" if parse_header(text) is not None or (
            columns and not str(path).endswith(".csv")) else "csv"
    return text, fmt


def load_setpoints(path: str | os.PathLike, machine: Machine, fmt: str | None = None,
                   **kw) -> RecordedSetpoints:
    """Read a setpoints file (:func:`read_setpoints`; format as :func:`read_setpoints_file`)."""
    text, fmt = read_setpoints_file(path, fmt, kw.get("columns"))
    return read_setpoints(text, machine, fmt, source=os.path.basename(str(path)), **kw)
