"""LinuxCNC recordings: ``joint.N.motor-pos-cmd`` per servo period, read with ``pid``'s law.

LinuxCNC's ``pid`` (velocity mode, ``command-deriv`` unconnected) outputs in servo period k

    ``Pgain (c_{k-1} - p_k) + FF1 (c_k - c_{k-1}) / T``   (``error-previous-target`` TRUE)
    ``Pgain (c_k - p_k) + FF1 (c_k - c_{k-1}) / T``       (FALSE)

with ``c_k`` the motion controller's ``joint.N.motor-pos-cmd`` of that period. That is oga's
law ``u_k = Kp (pd_k - p_k) + Kf vd_k`` with ``pd_k = c_{k-1}`` (or ``c_k``) and
``vd_k = (c_k - c_{k-1}) / T``. Sample 0 is the first period whose command moved (the
program's first motion); the last is the first period at rest after the last move.

A file written by ``oga lcnc-record`` starts with :data:`HEADER` and ``# key: value`` lines
(``columns``, ``units``, ``servo-period-ns``, ``error-previous-target``, ``joints``, the
program and the configuration); a plain ``halsampler`` recording has no header, its columns,
units and setting are given by the reader's options.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES
from oga.recorded.check import SetpointsError

__all__ = ["HEADER", "RecordingHeader", "LinuxcncPeriods", "parse_header", "pid_law"]

#: First line of a recording written by ``oga lcnc-record``.
HEADER = "# oga lcnc-record"


@dataclass(frozen=True)
class RecordingHeader:
    """The ``# key: value`` lines of an ``oga lcnc-record`` file.

    Attributes
    ----------
    meta : dict of str to str
        Every key and value, as written.
    columns : list of str or None
        Column names in order.
    units : str or None
        Machine units of lengths (``mm`` or ``inch``).
    period_ns : int or None
        Servo period, ns.
    error_previous_target : dict of str to bool or None
        ``pid.N.error-previous-target`` per axis.
    joints : dict of str to int or None
        Joint (and ``pid`` loop) per axis.
    """

    meta: dict
    columns: list | None
    units: str | None
    period_ns: int | None
    error_previous_target: dict | None
    joints: dict | None


def _pairs(text: str, key: str, cast) -> dict:
    out = {}
    for item in text.split():
        a, sep, v = item.partition("=")
        if not sep or a not in AXES:
            raise SetpointsError(f"header {key!r}: expected a=value per axis, got {item!r}")
        try:
            out[a] = cast(v)
        except ValueError:
            raise SetpointsError(f"header {key!r}: {v!r} is not a valid value") from None
    return out


def parse_header(text: str) -> RecordingHeader | None:
    """The header of an ``oga lcnc-record`` file, or None when ``text`` is not one."""
    if not text.startswith(HEADER):
        return None
    meta = {}
    for line in text.splitlines()[1:200]:
        if not line.startswith("#"):
            break
        key, sep, value = line[1:].partition(":")
        if sep:
            meta[key.strip()] = value.strip()
    try:
        period = int(meta["servo-period-ns"]) if "servo-period-ns" in meta else None
    except ValueError:
        raise SetpointsError(f"header 'servo-period-ns': {meta['servo-period-ns']!r} is not "
                             "an integer") from None
    ept = meta.get("error-previous-target")
    joints = meta.get("joints")
    return RecordingHeader(
        meta=meta, columns=meta["columns"].split() if "columns" in meta else None,
        units=meta.get("units"), period_ns=period,
        error_previous_target=None if ept is None else _pairs(
            ept, "error-previous-target", lambda v: {"1": True, "0": False}[v]),
        joints=None if joints is None else _pairs(joints, "joints", int))


@dataclass(frozen=True, eq=False)
class LinuxcncPeriods:
    """The recorded servo periods behind setpoints read with ``pid``'s law, one per sample.

    Attributes
    ----------
    cmd_m : ndarray, shape (N, 3)
        ``joint.N.motor-pos-cmd`` of each sample's period, m (axes not recorded: 0).
    axes : tuple of str
        Recorded axes.
    line : ndarray of int, shape (N,), or None
        ``motion.program-line`` of each period, where recorded.
    current_vel_m_s : ndarray, shape (N,), or None
        ``motion.current-vel`` of each period (the trajectory's speed), m/s, where recorded.
    error_previous_target : dict of str to bool
        The ``pid`` setting per recorded axis the setpoints were read with.
    units : str
        Machine units of the file (``m``, ``mm`` or ``inch``).
    joints : dict of str to int or None
        Joint per axis, where the file names them.
    first_row : int
        File line of sample 0's period.
    part : ndarray of int, shape (N,), or None
        Part of the program of each sample (``oga lcnc-record``'s ``part`` column: 0, 1, ...
        between the stops LinuxCNC's task timed, -1 in a stop), where recorded.
    """

    cmd_m: np.ndarray
    axes: tuple
    line: np.ndarray | None
    current_vel_m_s: np.ndarray | None
    error_previous_target: dict
    units: str
    joints: dict | None
    first_row: int
    part: np.ndarray | None = None


def pid_law(c_m: np.ndarray, dt_s: float, ept: dict[str, bool],
            axes: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples, position setpoints and velocities of ``pid``'s law (module docstring).

    Parameters
    ----------
    c_m : ndarray, shape (R, 3)
        ``motor-pos-cmd`` per recorded period, m.
    dt_s : float
        Servo period, s.
    ept : dict of str to bool
        ``error-previous-target`` per recorded axis.
    axes : tuple of str
        Recorded axes.

    Returns
    -------
    periods : ndarray of int, shape (N,)
        The recorded period of each sample (first motion .. first rest after the last).
    pd, vd : ndarray, shape (N, 3)
        Position setpoints (m) and the velocities ``pid`` multiplies by FF1 (m/s).

    Raises
    ------
    SetpointsError
        The command never moves.
    """
    moved = np.flatnonzero(np.any(np.diff(c_m, axis=0) != 0.0, axis=1)) + 1
    if moved.size == 0:
        raise SetpointsError("the recorded joint commands never move: no program ran while "
                             "recording")
    periods = np.arange(moved[0], min(moved[-1] + 1, len(c_m) - 1) + 1)
    prev = c_m[periods - 1]
    pd = prev.copy()
    for k, a in enumerate(AXES):
        if a in axes and not ept[a]:
            pd[:, k] = c_m[periods, k]
    vd = (c_m[periods] - prev) / dt_s
    return periods, pd, vd
