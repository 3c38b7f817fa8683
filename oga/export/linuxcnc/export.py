"""A verified gain table as files LinuxCNC runs: a ``streamer`` data file and HAL files.

LinuxCNC's position loop is the ``pid`` HAL component; in a velocity-mode loop its output is

    ``output = Pgain * error + FF1 * commandD``  (machine units per second)

with ``commandD`` the ``command-deriv`` pin when it is connected. oga's law is
``u_k = Kp_k (pd_k - p_k) + Kf_k vd_k`` (:mod:`oga.model.simulate`), so per servo period k the
stream holds, per axis: the position command (machine units), the setpoint velocity for
``command-deriv`` (units/s), ``Pgain = Kp`` in 1/s (``Kp`` in (m/min)/mm times 1000/60: the
same number in mm and inch machines) and ``FF1 = Kf``. With ``error-previous-target`` TRUE
(LinuxCNC 2.9's default) ``pid`` takes the error against the *previous* period's command,
so the stream's position column is one sample ahead (``pd_{k+1}``; the last position is
repeated), and the output is the same.

The HAL file (:data:`TABLE_HAL`) wires ``streamer.0`` through one ``mux2`` per pin: while the
stream is valid (``oga-run`` is TRUE and a row was read this period) the streamed values
pass, otherwise the gains are the fixed baseline, ``command-deriv`` is 0 and the position
command is held (before the start: the table's first position; after the end or an abort
the streamer's last row, which it keeps). Its functions run first in the servo thread, before
``pid``.
"""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES
from oga.defaults import LINUXCNC
from oga.errors import InputError, MachineError, OptionError
from oga.export.linuxcnc.halfile import printable
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM

__all__ = [
    "UNIT_M",
    "STREAM",
    "TABLE_HAL",
    "BENCH_HAL",
    "LinuxcncExport",
    "linuxcnc_export",
    "export_table",
    "replay_feedback",
    "baseline_gains",
]

#: Machine units: metres per unit.
UNIT_M: dict[str, float] = {"mm": 1e-3, "inch": 0.0254}
#: File names of an export.
STREAM, TABLE_HAL, BENCH_HAL = "oga_table.stream", "oga_table.hal", "oga_bench.hal"
#: ``pid`` loads at most this many loops.
_MAX_PID = 16
#: Stream columns per axis: name, unit (``u`` = machine unit), what it drives.
_COLUMNS = (("cmd", "u", "pid.N.command"), ("vel", "u/s", "pid.N.command-deriv"),
            ("kp", "1/s", "pid.N.Pgain"), ("kf", "1", "pid.N.FF1"))
_FEEDBACK = ("fb", "u", "oga-<axis>-fb-sim (bench feedback)")


@dataclass(frozen=True, eq=False)
class LinuxcncExport:
    """The files of a LinuxCNC export and what they assume.

    Attributes
    ----------
    files : dict of str to str
        File name -> text: :data:`STREAM`, :data:`TABLE_HAL`, :data:`BENCH_HAL`.
    axes : tuple of str
        Exported axes, in stream order.
    joints : dict of str to int
        ``pid`` loop index per axis.
    rows : int
        Stream rows (one per servo period, the table's samples).
    units : {"mm", "inch"}
        Machine units.
    error_previous_target : bool
        The ``pid.N.error-previous-target`` setting the stream is made for.
    period_ns : int
        Servo period the table needs, ns (the table's Te).
    columns : tuple of str
        Stream columns, ``<axis>_<cmd|vel|kp|kf|fb>``.
    """

    files: dict
    axes: tuple
    joints: dict
    rows: int
    units: str
    error_previous_target: bool
    period_ns: int
    columns: tuple

    def zip_bytes(self) -> bytes:
        """The files as one zip archive (fixed timestamps: same table, same bytes)."""
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            for name, text in self.files.items():
                info = zipfile.ZipInfo(f"oga_linuxcnc/{name}", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                z.writestr(info, text)
        return buf.getvalue()


def _column(table, name: str) -> np.ndarray:
    try:
        return table.data[:, table.header.index(name)]
    except ValueError:
        raise InputError(f"table: no column {name!r}") from None


def _period_ns(table) -> int:
    te = table.meta.get("sample_period_s")
    if not isinstance(te, (int, float)) or not (0 < te < 1):
        raise InputError(f"table: sample period {te!r} s is not a servo period")
    ns = round(te * 1e9)
    if ns < 1 or abs(te * 1e9 - ns) > 1e-6 * ns:
        raise InputError(f"table: sample period {te!r} s is not a whole number of ns")
    return ns


def _axes(table, axes) -> tuple[str, ...]:
    if axes is None:  # the axes the table moves (by more than 1 nm, as Setpoints.moving_axes)
        axes = tuple(a for a in AXES if np.ptp(_column(table, f"{a}_pos_m")) > 1e-9)
        if not axes:
            raise InputError("table: no axis moves; name the axes to export")
        return axes
    axes = tuple(axes)
    bad = [a for a in axes if a not in AXES]
    if bad or not axes or len(set(axes)) != len(axes):
        raise OptionError(f"axes: expected distinct names among x, y, z, got {list(axes)}")
    return tuple(a for a in AXES if a in axes)


def _joints(axes, joints) -> dict[str, int]:
    if joints is None:
        return {a: i for i, a in enumerate(axes)}
    joints = dict(joints)
    if set(joints) != set(axes):
        raise OptionError(f"joints: give one pid loop for each exported axis {list(axes)}, "
                          f"got {sorted(joints)}")
    values = list(joints.values())
    if any(not isinstance(j, int) or not 0 <= j < _MAX_PID for j in values) \
            or len(set(values)) != len(values):
        raise OptionError(f"joints: pid loops must be distinct integers 0..{_MAX_PID - 1}, "
                          f"got {joints}")
    return {a: joints[a] for a in axes}


def _baseline(baseline_kp, baseline_kf, axes) -> dict[str, tuple[float, float]]:
    out = {}
    for a in axes:
        try:
            kp, kf = float(baseline_kp[a]), float(baseline_kf[a])
        except (KeyError, TypeError, ValueError):
            raise OptionError(f"baseline: no fixed Kp and Kf for axis {a!r}") from None
        if not (math.isfinite(kp) and kp > 0 and math.isfinite(kf)):
            raise OptionError(f"baseline: axis {a}: Kp {kp} must be positive, Kf {kf} finite")
        out[a] = (kp, kf)
    return out


def replay_feedback(table, machine, axes=None) -> dict[str, np.ndarray]:
    """The simulated actual positions of a table's axes (m): its replay on ``machine``.

    The same replay as the verification of ``oga optimize`` (each axis from rest at its
    first setpoint, the table's gains per sample), so ``p_k`` is what the table was
    verified with.

    Parameters
    ----------
    table : GainTable
        The table (:func:`oga.export.gain_table` or read back).
    machine : Machine
        The machine it was computed for.
    axes : sequence of str, optional
        Axes to replay (default the moving axes).

    Returns
    -------
    dict of str to ndarray, shape (N,)

    Raises
    ------
    MachineError
        The table names another machine (by its SHA-256) or the machine lacks an axis.
    InputError
        The table's period is not the machine's Te.
    """
    from oga.model.simulate import axis_params, simulate_axis

    digest = table.meta.get("machine_sha256")
    if digest and digest != machine.digest():
        raise MachineError(f"machine: the table was computed for machine "
                           f"{table.meta.get('machine')!r} (SHA-256 {digest[:12]}...), not for "
                           f"{machine.name!r} ({machine.digest()[:12]}...)")
    if round(machine.te * 1e9) != _period_ns(table):
        raise InputError(f"table: sample period {table.meta['sample_period_s']} s differs from "
                         f"machine {machine.name!r}'s Te {machine.te} s")
    out = {}
    for a in _axes(table, axes):
        pd = np.ascontiguousarray(_column(table, f"{a}_pos_m"))
        p_act, _ = simulate_axis(
            axis_params(machine, a), pd[0], pd, _column(table, f"{a}_vel_m_s"),
            _column(table, f"{a}_kp_m_min_per_mm") * KP_SI_PER_M_MIN_PER_MM,
            _column(table, f"{a}_kf"))
        out[a] = p_act
    return out


def _stream_text(head: list[str], data: np.ndarray) -> str:
    buf = io.StringIO()
    for line in head:
        buf.write(f"# {line}\n")
    np.savetxt(buf, data, fmt="%.17g", delimiter=" ")  # round-trips float64 through strtod
    return buf.getvalue()


def _settings(units: str | None, error_previous_target: bool | None,
              thread: str | None) -> tuple[str, bool, str]:
    """Units, error-previous-target and thread: given (checked) or :data:`LINUXCNC`'s."""
    units = LINUXCNC["units"] if units is None else units
    if units not in UNIT_M:
        raise OptionError(f"units: expected one of {', '.join(UNIT_M)}, got {units!r}")
    ept = LINUXCNC["error_previous_target"] if error_previous_target is None \
        else bool(error_previous_target)
    thread = LINUXCNC["thread"] if thread is None else thread
    if not thread or not all(c.isalnum() or c in "-_." for c in thread):
        raise OptionError(f"thread: {thread!r} is not a HAL thread name")
    return units, ept, thread


def _export_columns(table, axes, ept: bool, unit: float,
                    feedback_m: dict | None) -> tuple[np.ndarray, list[str]]:
    """The stream's rows (N, 4 or 5 per axis) in machine units: per axis the command (the
    next period's where error-previous-target), velocity, Kp (1/s), Kf [, simulated
    feedback]; and the columns' names."""
    cols, names = [], []
    for a in axes:
        pd = _column(table, f"{a}_pos_m")
        cmd = np.append(pd[1:], pd[-1]) if ept else pd  # pid takes the error vs prev command
        cols += [cmd / unit, _column(table, f"{a}_vel_m_s") / unit,
                 _column(table, f"{a}_kp_m_min_per_mm") * KP_SI_PER_M_MIN_PER_MM,
                 _column(table, f"{a}_kf")]
        names += [f"{a}_{c}" for c, _, _ in _COLUMNS]
        if feedback_m is not None:
            cols.append(np.asarray(feedback_m[a], dtype=np.float64) / unit)
            names.append(f"{a}_fb")
    data = np.column_stack(cols)
    if not np.isfinite(data).all():
        raise InputError("table: non-finite values; not exported")
    return data, names


def linuxcnc_export(table, baseline_kp: dict, baseline_kf: dict, *, units: str | None = None,
                    error_previous_target: bool | None = None, axes=None, joints=None,
                    thread: str | None = None, feedback_m: dict | None = None) -> LinuxcncExport:
    """The LinuxCNC files of a verified gain table.

    Parameters
    ----------
    table : GainTable
        The table: columns ``<axis>_pos_m``, ``_vel_m_s``, ``_kp_m_min_per_mm``, ``_kf`` and
        ``meta["sample_period_s"]``.
    baseline_kp, baseline_kf : dict of str to float
        The fixed gains per axis ((m/min)/mm, factor) the loops fall back to before the
        start, at the end and on an abort (the summary's ``baseline``).
    units : {"mm", "inch"}, optional
        Machine units (default :data:`oga.defaults.LINUXCNC`).
    error_previous_target : bool, optional
        The ``pid.N.error-previous-target`` setting (default TRUE, LinuxCNC's).
    axes : sequence of str, optional
        Axes to export (default the axes the table moves).
    joints : dict of str to int, optional
        ``pid`` loop per axis (default 0, 1, ... in x, y, z order).
    thread : str, optional
        HAL thread (default ``servo-thread``).
    feedback_m : dict of str to ndarray, shape (N,), optional
        Simulated actual positions per axis (:func:`replay_feedback`): streamed as
        ``oga-<axis>-fb-sim``, which the bench file connects to ``pid.N.feedback``.

    Raises
    ------
    OptionError
        Bad units, axes, joints, thread, baseline or feedback.
    InputError
        A column is missing, a value is not finite, the period is not whole ns, or the
        table is longer than ``LINUXCNC["max_rows"]``.
    """
    units, ept, thread = _settings(units, error_previous_target, thread)
    axes = _axes(table, axes)
    joints = _joints(axes, joints)
    base = _baseline(baseline_kp, baseline_kf, axes)
    period_ns = _period_ns(table)
    n = table.data.shape[0]
    if not 1 <= n <= LINUXCNC["max_rows"]:
        raise InputError(f"table: {n} samples; LinuxCNC export takes 1..{LINUXCNC['max_rows']}")
    if feedback_m is not None and (set(feedback_m) != set(axes) or any(
            np.shape(feedback_m[a]) != (n,) for a in axes)):
        raise OptionError(f"feedback: expected {n} positions for each of {list(axes)}")
    unit = UNIT_M[units]
    data, names = _export_columns(table, axes, ept, unit, feedback_m)
    m = {k: printable(v) for k, v in table.meta.items() if isinstance(v, str)}
    per_axis = list(_COLUMNS) + ([_FEEDBACK] if feedback_m is not None else [])
    about = [
        f"oga gain table for LinuxCNC: {m.get('toolpath', '')}, machine {m.get('machine', '')}",
        f"setpoints SHA-256 {m.get('setpoints_sha256', '')}",
        f"machine SHA-256 {m.get('machine_sha256', '')}",
        f"{n} rows, one per servo period of {period_ns} ns; machine units {units}; "
        f"pid.N.error-previous-target {'TRUE' if ept else 'FALSE'}",
    ]
    head = about + [
        "columns, per axis " + " ".join(f"{a} (pid.{joints[a]})" for a in axes) + ": "
        + ", ".join(f"{c} [{u.replace('u', units)}] -> {pin}" for c, u, pin in per_axis),
        "cmd is the setpoint of the " + ("NEXT period (error-previous-target TRUE)"
                                         if ept else "same period"),
    ]
    start = {a: float(_column(table, f"{a}_pos_m")[0] / unit) for a in axes}
    hal = _table_hal(about, axes, joints, base, start, data, per_axis, n, ept, thread, units)
    bench = _bench_hal(about, axes, joints, period_ns, thread, feedback_m is not None)
    files = {STREAM: _stream_text(head, data), TABLE_HAL: hal, BENCH_HAL: bench}
    return LinuxcncExport(files=files, axes=axes, joints=joints, rows=n, units=units,
                          error_previous_target=ept, period_ns=period_ns, columns=tuple(names))


def _table_hal(about, axes, joints, base, start, data, per_axis, n, ept, thread, units) -> str:
    width = len(per_axis)
    muxes = [f"oga-{a}-{c}" for a in axes for c, _, _ in per_axis]
    lines = [f"# {line}" for line in about] + [
        "#",
        f"# Include after the pid loops {', '.join(f'pid.{joints[a]}' for a in axes)} are loaded",
        f"# and added to {thread}; this file drives their command, command-deriv, Pgain and",
        "# FF1 (do not connect or set them elsewhere) and runs its functions first in the thread.",
        "# Start: 'sets oga-run 1' once the stream is loaded into the FIFO",
        f"# ('loadusr -w halstreamer -c 0 {STREAM}'); 'sets oga-run 0' aborts.",
        "# While oga-valid is FALSE (before the start, after the last row, after an abort)",
        "# Pgain/FF1 are the fixed baseline, command-deriv is 0 and the command is held.",
        "",
        f"loadrt streamer depth={n + 1} cfg={'f' * data.shape[1]}",  # holds depth - 1 rows
        "loadrt and2 names=oga-run-now,oga-valid",
        "loadrt not names=oga-not-empty",
        "loadrt flipflop names=oga-started",
        f"loadrt mux2 names={','.join(muxes)}",
    ]
    order = ["oga-run-now", "streamer.0", "oga-not-empty", "oga-valid", "oga-started"] + muxes
    lines += [f"addf {f} {thread} {i}" for i, f in enumerate(order, start=1)]
    lines += [
        "",
        "# oga-run is sampled once per period, so the streamer and oga-valid see the same value",
        "net oga-run => oga-run-now.in0",
        "setp oga-run-now.in1 1",
        "net oga-run-now oga-run-now.out => streamer.0.enable oga-valid.in0",
        "net oga-empty streamer.0.empty => oga-not-empty.in",
        "net oga-not-empty oga-not-empty.out => oga-valid.in1",
        # gains and velocity: streamed while valid; positions: from the first valid row on
        "net oga-valid oga-valid.out => oga-started.set "
        + " ".join(f"{m}.sel" for m in muxes if not m.endswith(("-cmd", "-fb"))),
        "net oga-started oga-started.out => "
        + " ".join(f"{m}.sel" for m in muxes if m.endswith(("-cmd", "-fb"))),
    ]
    for i, a in enumerate(axes):
        j, (kp, kf) = joints[a], base[a]
        lines += ["", f"# axis {a} -> pid.{j} ({units}; Pgain in 1/s = Kp in (m/min)/mm x 1000/60)"]
        for k, (c, _, _) in enumerate(per_axis):
            pin = f"streamer.0.pin.{i * width + k}"
            lines.append(f"net oga-{a}-{c}-stream {pin} => oga-{a}-{c}.in1")
        lines += [
            f"setp oga-{a}-cmd.in0 {start[a]!r}",
            f"setp oga-{a}-vel.in0 0",
            f"setp oga-{a}-kp.in0 {kp * KP_SI_PER_M_MIN_PER_MM!r}",
            f"setp oga-{a}-kf.in0 {kf!r}",
            f"net oga-{a}-cmd oga-{a}-cmd.out => pid.{j}.command",
            f"net oga-{a}-vel oga-{a}-vel.out => pid.{j}.command-deriv",
            f"net oga-{a}-kp oga-{a}-kp.out => pid.{j}.Pgain",
            f"net oga-{a}-kf oga-{a}-kf.out => pid.{j}.FF1",
            f"setp pid.{j}.error-previous-target {1 if ept else 0}",
            "# oga's law has no other term",
            *(f"setp pid.{j}.{p} 0" for p in ("Igain", "Dgain", "FF0", "FF2", "FF3", "bias",
                                              "deadband")),
        ]
        if width > len(_COLUMNS):  # bench feedback: the simulated position, held likewise
            lines += [f"setp oga-{a}-fb.in0 {start[a]!r}",
                      f"net oga-{a}-fb-sim oga-{a}-fb.out"]
    return "\n".join(lines) + "\n"


def _bench_hal(about, axes, joints, period_ns, thread, feedback) -> str:
    loops = sorted(joints.values())
    lines = [f"# {line}" for line in about] + [
        "#",
        "# Bench run without a machine: halrun -I -f " + BENCH_HAL + " , then 'sets oga-run 1'.",
        "# pid.N.output is the velocity command (units/s)"
        + ("; pid.N.feedback is oga's simulated position." if feedback
           else "; connect pid.N.feedback to your feedback."),
        "",
        f"loadrt threads name1={thread} period1={period_ns} fp1=1",
        f"loadrt pid num_chan={loops[-1] + 1}",
        *(f"addf pid.{j}.do-pid-calcs {thread}" for j in loops),
        f"source {TABLE_HAL}",
        *(f"setp pid.{j}.enable 1" for j in loops),
    ]
    if feedback:
        lines += [f"net oga-{a}-fb-sim => pid.{joints[a]}.feedback" for a in axes]
    lines += [f"loadusr -w halstreamer -c 0 {STREAM}", "start"]
    return "\n".join(lines) + "\n"


def baseline_gains(table, summary: dict | None = None, baseline=None) -> tuple[dict, dict]:
    """The fixed gains per axis a table falls back to: ``baseline`` (Kp, Kf for every axis),
    else the summary's, whose hashes must be the table's.

    Raises
    ------
    InputError
        The summary belongs to another table, or no baseline is given.
    """
    if summary is not None:
        for key in ("setpoints_sha256", "machine_sha256"):
            ours, theirs = table.meta.get(key), summary.get(key)
            if ours and theirs and ours != theirs:
                raise InputError(f"summary: {key} {theirs[:12]}... is not the table's "
                                 f"({ours[:12]}...): not the same "
                                 + ("program" if key.startswith("setpoints") else "machine"))
    if baseline is not None:
        kp, kf = baseline
        return dict.fromkeys(AXES, kp), dict.fromkeys(AXES, kf)
    if summary is not None and isinstance(summary.get("baseline"), dict):
        base_kp, base_kf = summary["baseline"].get("kp"), summary["baseline"].get("kf")
        if not isinstance(base_kp, dict) or not isinstance(base_kf, dict):
            raise InputError("summary: baseline has no kp and kf per axis")
        return base_kp, base_kf
    raise InputError("the fixed baseline gains are needed (the loops fall back to them): "
                     "give the summary or Kp,Kf")


def export_table(table, *, summary: dict | None = None, baseline=None, machine=None,
                 with_feedback: bool = False, **options) -> LinuxcncExport:
    """:func:`linuxcnc_export` of a stored table, its summary and its machine.

    Parameters
    ----------
    table : GainTable
        The table (its metadata may hold the setpoints' and machine's SHA-256).
    summary : dict, optional
        Its summary (``oga optimize --summary``): the baseline gains, and the hashes, which
        must be the table's.
    baseline : (float, float), optional
        Fixed Kp ((m/min)/mm) and Kf for every axis, instead of the summary's.
    machine : Machine, optional
        Needed with ``with_feedback`` (the table's replay).
    with_feedback : bool
        Stream the simulated actual positions (:func:`replay_feedback`).
    **options
        ``units``, ``error_previous_target``, ``axes``, ``joints``, ``thread``.

    Raises
    ------
    InputError
        The summary belongs to another table, or no baseline is given.
    """
    base_kp, base_kf = baseline_gains(table, summary, baseline)
    feedback = None
    if with_feedback:
        if machine is None:
            raise OptionError("with_feedback: the machine is needed to replay the table")
        feedback = replay_feedback(table, machine, options.get("axes"))
    return linuxcnc_export(table, base_kp, base_kf, feedback_m=feedback, **options)
