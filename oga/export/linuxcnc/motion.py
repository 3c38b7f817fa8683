"""A gain table in production on LinuxCNC: the motion controller runs the program, the table
drives only ``pid.N.Pgain`` and ``FF1`` while the motion is the one it was computed for.

The table must have been computed on setpoints recorded from the same configuration
(``oga lcnc-record``, read with ``pid``'s law, :mod:`oga.recorded.lcnc`): row k belongs to
the k-th servo period from the program's first motion, and the recording says what the motion
controller commands in that period. The export writes three files:

- ``oga_table.stream``: one row per servo period of the program's parts (``oga
  lcnc-record``'s ``part`` column; the stops between them left out): per axis the recorded
  ``joint.N.motor-pos-cmd`` (machine units), ``Pgain`` (1/s) and ``FF1``, then the recorded
  ``motion.current-vel`` (units/s), ``motion.program-line``, and ``end_of_part`` (1 on the
  last row of a part a stop follows);
- ``oga_table.tcl``: a ``[HAL] HALFILE`` (run by ``haltcl``), which finds with LinuxCNC's
  ``hal_procs_lib.tcl`` the ``pid`` loop each joint's ``motor-pos-cmd`` feeds and the
  signals of the pins it reads, checks the loop is the one the table assumes (servo period,
  ``error-previous-target``, no I, D, FF0, FF2, FF3 or bias term, ``command-deriv`` left to
  ``pid``, ``Pgain``/``FF1`` not driven elsewhere), and inserts its functions right after
  ``motion-controller`` (as LinuxCNC's ``hookup_moveoff.tcl`` does), before the loops;
- ``oga_feeder.py``: a small userspace component (LinuxCNC's ``hal`` module; why, in its
  docstring) that refills the ``streamer`` FIFO from the first row for every run.

Per servo period, in LinuxCNC's own components (``ddt``, ``near``, ``logic``,
``flipflop``, ``conv_s32_float``, ``streamer`` and its ``enable``, ``mux2``; no component of
oga's in the realtime thread):

- start: the table is ready, enabled (``oga-go.in-01``, TRUE by default), the motion is
  coordinated (auto or MDI) and a joint command moves in this period (its ``ddt`` leaves 0):
  this is row 0, and one row is read per period from then on;
- a stop (a tool change, pause, spindle start or dwell between two motions, timed by
  LinuxCNC's task, so never the same length twice): from the period after a row with
  ``end_of_part`` (flipflop ``oga-held``) no row is read and the gains are the baseline (at
  standstill they change nothing; the command is motion's, no jump) while the command stands
  at the part's end and motion is enabled and coordinated; in the period a joint command
  moves again the hold ends and that period reads the next part's first row, exactly as
  recorded (its first moving period), and checks it as below;
- the row is valid while every joint's command is within ``pos_tol`` of the row's,
  ``motion.current-vel`` within ``vel_tol`` of the row's, ``motion.program-line`` is the
  row's, the feed and rapid overrides are 1 (``halui``), motion is enabled and coordinated,
  and a row was read (``streamer.0.empty`` FALSE: end of table);
- while valid, ``Pgain`` and ``FF1`` are the row's; in the first period that is not, and
  until the program has ended and the feeder has loaded the table again, they are the fixed
  baseline (the same period: the checks read this period's motion outputs before ``pid``
  runs). ``pid.N.command`` stays the motion controller's throughout: no jump in the command.

Which pin decides each fallback, and why none races the motion: every pin but the two
overrides is written by ``motion-controller`` (or ``streamer``) earlier in the same servo
thread, so the checks see this period's motion. A feed override, feed hold (``motion.feed-hold``)
or pause (task's, or M0) changes ``net_feed_scale`` and the trajectory planner's speed in the
period motion applies it: ``motion.current-vel`` leaves the row's by about ``a T`` (far above
``vel_tol``) in that very period. An abort stops the trajectory (speed, and then the line);
E-stop or machine off drops ``motion.motion-enabled`` (and the command jumps to the feedback);
a position off the row: ``motor-pos-cmd`` against the row; another line:
``motion.program-line``; end of table: ``streamer.0.empty``. ``halui``'s pins are written by
a userspace process that polls the task's status every 20 ms (``halui.cc``: ``esleep(0.02)``),
late by that and by the host's load, so none of them may decide a period: ``is-paused``
can still be TRUE when the task, a few ms after the display resumed a program's M0, starts
the next part's first motion, and latch a fallback there; ``is-running``/``is-paused`` are not used
at all (a pause is seen in the speed; an abort in a stop leaves the gains on the baseline,
where they are in a stop anyway, and the next motion is checked against the next part's first
row in its own period). The overrides stay as ``halui.feed-override.value`` and
``rapid-override.value`` (LinuxCNC 2.9's motion exports no pin of its feed scale): they can
only be late, the speed check falling back first; a value other than 1 is one the operator
set. The feeder's rearm reads ``halui.program.is-idle`` only once the fallback latched
(``oga-feeder.done``) and after having seen the program run or idle for a second.
"""

from __future__ import annotations

import math
from importlib import resources

import numpy as np

from feedplan.setpoints import AXES
from oga.defaults import LINUXCNC, LINUXCNC_MOTION
from oga.errors import InputError, OptionError
from oga.export.linuxcnc.export import (STREAM, UNIT_M, LinuxcncExport, _baseline, _column,
                                 _period_ns)
from oga.export.linuxcnc.halfile import HalCommands, hal_number, printable
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM

__all__ = ["MOTION_TCL", "FEEDER", "motion_export"]

#: File names of a production export (the stream is :data:`oga.export.linuxcnc.STREAM`).
MOTION_TCL, FEEDER = "oga_table.tcl", "oga_feeder.py"
#: ``ddt`` of a standing command is exactly 0; a moving one's first step is far above this
#: (units/s).
_STILL = 1e-12
#: Terms of ``pid`` oga's law does not have: each must be 0.
_ZERO_TERMS = ("Igain", "Dgain", "FF0", "FF2", "FF3", "bias")

_PROCS = r'''
source [file join $::env(HALLIB_DIR) hal_procs_lib.tcl]
set oga_dir [file dirname [file normalize [info script]]]

# The signal on PIN: the one it is connected to, or a new one for an unconnected pin.
proc oga_signal {pin} {
  if {![pin_exists $pin]} {return -code error "oga_table.tcl: no pin $pin"}
  if {[is_connected $pin sig] == "not_connected"} {
    set sig oga-$pin
    hal net $sig $pin
  }
  return $sig
}

# The pid loop (prefix of its pins) whose command is JOINT's motor-pos-cmd.
proc oga_pid {joint} {
  set sig [oga_signal joint.$joint.motor-pos-cmd]
  get_netlist inpins outpin iopins $sig
  set found {}
  foreach p $inpins {
    if {[string match *.command $p]} {
      set prefix [string range $p 0 end-8]
      if {[pin_exists $prefix.Pgain] && [pin_exists $prefix.FF1]} {lappend found $prefix}
    }
  }
  if {[llength $found] != 1} {
    return -code error "oga_table.tcl: joint.$joint.motor-pos-cmd (signal $sig) feeds\
      [llength $found] pid loops ($found); the table needs exactly one"
  }
  return [lindex $found 0]
}

# Errors unless the loop PID is the one the table was computed for.
proc oga_check_pid {pid ept base_kp base_kf} {
  foreach pin [list $pid.Pgain $pid.FF1] {
    if {[is_connected $pin sig] != "not_connected"} {
      return -code error "oga_table.tcl: $pin is driven by signal $sig; the table drives it:\
        remove that net (keep your value as the baseline of oga optimize)"
    }
  }
  if {[is_connected $pid.command-deriv sig] != "not_connected"} {
    return -code error "oga_table.tcl: $pid.command-deriv is connected (signal $sig); the\
      table assumes pid's own derivative of the command: remove that net"
  }
  foreach term {TERMS} {
    set v [hal getp $pid.$term]
    if {$v != 0} {
      return -code error "oga_table.tcl: $pid.$term is $v; oga's law is Pgain * error +\
        FF1 * command-deriv: set it to 0 (and record and optimise again)"
    }
  }
  set e [hal getp $pid.error-previous-target]
  if {[string is true $e] != $ept} {
    return -code error "oga_table.tcl: $pid.error-previous-target is $e, the table was\
      recorded with [expr {$ept ? "TRUE" : "FALSE"}]"
  }
  foreach {pin want} [list $pid.Pgain $base_kp $pid.FF1 $base_kf] {
    set v [hal getp $pin]
    if {abs($v - $want) > 1e-6 * abs($want) + 1e-12} {
      puts "oga_table.tcl: note: $pin was $v; the table falls back to the baseline $want"
    }
  }
}

# Errors unless COMP is not loaded yet (a component loads once: merge its names= instead).
proc oga_free_comp {comp} {
  if {[lsearch -exact [hal list comp] $comp] >= 0} {
    return -code error "oga_table.tcl: your configuration loads $comp already; add the\
      names= of this file's loadrt $comp line to yours and delete this one"
  }
}

# Insert FUNCS right after motion-controller in its thread, before the pid loops PIDS.
proc oga_addf {thread funcs pids} {
  set mc $::OGA($thread,motion-controller)
  foreach pid $pids {
    if {![info exists ::OGA($thread,$pid.do-pid-calcs)]
        || $::OGA($thread,$pid.do-pid-calcs) < $mc} {
      return -code error "oga_table.tcl: $pid.do-pid-calcs must run in $thread after\
        motion-controller"
    }
  }
  set at [expr {$mc + 1}]
  foreach f $funcs {
    hal addf $f $thread $at
    incr at
  }
}
'''


def _recorded_columns(recorded, axes):
    lc = recorded.linuxcnc
    if lc is None:
        raise InputError("recording: the table must be computed on a LinuxCNC recording "
                         "(oga lcnc-record, read with pid's law), not on a "
                         f"{recorded.source.get('format')} file")
    missing = [name for name, v in (("current_vel_m_s", lc.current_vel_m_s), ("line", lc.line))
               if v is None]
    if missing:
        raise InputError(f"recording: no {' and no '.join(missing)} column; record "
                         "motion.current-vel and motion.program-line (oga lcnc-record does)")
    absent = [a for a in axes if a not in lc.axes]
    if absent:
        raise InputError(f"recording: axis {', '.join(absent)} of the table is not recorded")
    return lc


def motion_export(table, baseline_kp: dict, baseline_kf: dict, recorded, *,
                  joints: dict | None = None, pos_tol_m: float | None = None,
                  vel_tol_m_s: float | None = None, override_tol: float | None = None,
                  fifo_rows: int | None = None) -> LinuxcncExport:
    """The production files of a table computed on a LinuxCNC recording.

    Parameters
    ----------
    table : GainTable
        The table (columns ``<axis>_pos_m``, ``_kp_m_min_per_mm``, ``_kf``).
    baseline_kp, baseline_kf : dict of str to float
        The fixed gains per axis ((m/min)/mm, factor) the loops fall back to.
    recorded : RecordedSetpoints
        The recording the table was computed on (its setpoints must hash as the table's).
    joints : dict of str to int, optional
        Joint per axis (default: the recording's header).
    pos_tol_m, vel_tol_m_s, override_tol : float, optional
        Fallback tolerances (default :data:`oga.defaults.LINUXCNC_MOTION`).
    fifo_rows : int, optional
        Rows the ``streamer`` FIFO holds (default the whole table, at most
        ``LINUXCNC["max_rows"]``); the feeder keeps it filled.

    Raises
    ------
    InputError
        The recording is not the table's, lacks a column, or the table is too long.
    OptionError
        Bad joints, tolerances or baseline.
    """
    from oga.search.result import setpoints_digest

    tols = _tolerances(pos_tol_m, vel_tol_m_s, override_tol)
    digest = table.meta.get("setpoints_sha256")
    if digest != setpoints_digest(recorded.setpoints):
        raise InputError("recording: the table was not computed on this recording (setpoints "
                         f"SHA-256 {str(digest)[:12]}... vs "
                         f"{setpoints_digest(recorded.setpoints)[:12]}...)")
    axes = tuple(a for a in AXES if np.ptp(_column(table, f"{a}_pos_m")) > 1e-9)
    lc = _recorded_columns(recorded, axes)
    joints = _motion_joints(lc, joints, axes)
    base = _baseline(baseline_kp, baseline_kf, axes)
    period_ns = _period_ns(table)
    n = table.data.shape[0]
    if not 1 <= n <= LINUXCNC["max_rows"]:
        raise InputError(f"table: {n} samples; LinuxCNC export takes 1..{LINUXCNC['max_rows']}")
    if lc.units not in UNIT_M:
        raise InputError(f"recording: units {lc.units!r}; LinuxCNC machines run in "
                         f"{' or '.join(UNIT_M)} (the recording's header names them)")
    units, unit = lc.units, UNIT_M[lc.units]
    data, names = _motion_columns(table, lc, axes, unit)
    rows, parts = len(data), int(data[:, -1].sum()) + 1
    depth = rows + 1 if fifo_rows is None else int(fifo_rows)
    if not 2 <= depth <= LINUXCNC["max_rows"] + 1:
        raise OptionError(f"fifo_rows: 2..{LINUXCNC['max_rows'] + 1}, got {fifo_rows}")
    m = {k: printable(v) for k, v in table.meta.items() if isinstance(v, str)}
    src = recorded.source
    about = [
        f"oga gain table for LinuxCNC's motion: {m.get('toolpath', '')}, machine "
        f"{m.get('machine', '')}",
        f"recording {printable(src.get('file', ''))} SHA-256 {src.get('sha256', '')}",
        f"setpoints SHA-256 {m.get('setpoints_sha256', '')}",
        f"machine SHA-256 {m.get('machine_sha256', '')}",
        f"{rows} rows, one per servo period of {period_ns} ns from the program's first motion, "
        f"in {parts} part{'s' if parts > 1 else ''} (the stops between them, {n - rows} "
        f"periods recorded, run on the baseline); machine units {units}",
    ]
    head = about + ["columns: " + " ".join(names) + f" (cmd [{units}] = joint.N.motor-pos-cmd, "
                    f"kp [1/s] -> pid Pgain, kf -> pid FF1, current_vel [{units}/s], line, "
                    "end_of_part: 1 on a part's last row)"]
    stream = "".join(f"# {line}\n" for line in head)
    body = np.char.mod("%.17g", data)
    stream += "\n".join(" ".join(row) for row in body) + "\n"
    tcl = _motion_tcl(about, axes, joints, base, lc.error_previous_target, period_ns, depth,
                      len(names), tols, unit)
    feeder = resources.files("oga.export.linuxcnc").joinpath("feeder.py").read_text()
    return LinuxcncExport(files={STREAM: stream, MOTION_TCL: tcl, FEEDER: feeder}, axes=axes,
                          joints=joints, rows=rows, units=units,
                          error_previous_target=all(lc.error_previous_target[a] for a in axes),
                          period_ns=period_ns, columns=tuple(names))


def _motion_joints(lc, joints: dict | None, axes) -> dict[str, int]:
    """The joint of each axis: given, or the recording header's."""
    joints = dict(lc.joints or {}) if joints is None else dict(joints)
    if set(joints) < set(axes) or any(not isinstance(joints[a], int) or joints[a] < 0
                                      for a in axes):
        raise OptionError(f"joints: give the joint of each axis {list(axes)} (the recording's "
                          f"header names none), got {joints}")
    return {a: joints[a] for a in axes}


def _tolerances(pos_tol_m, vel_tol_m_s, override_tol) -> dict[str, float]:
    """The fallback tolerances, each given or :data:`oga.defaults.LINUXCNC_MOTION`'s."""
    d = LINUXCNC_MOTION
    tols = {"pos_tol_m": d["pos_tol_m"] if pos_tol_m is None else pos_tol_m,
            "vel_tol_m_s": d["vel_tol_m_s"] if vel_tol_m_s is None else vel_tol_m_s,
            "override_tol": d["override_tol"] if override_tol is None else override_tol}
    for name, v in tols.items():
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise OptionError(f"{name}: must be a positive number, got {v!r}")
    return tols


def _motion_columns(table, lc, axes, unit: float) -> tuple[np.ndarray, list[str]]:
    """The stream's rows (M, 3 * axes + 3) in machine units, the samples of the program's
    parts in order (a recording without parts: one): per axis the recorded command, the
    table's Kp (1/s) and Kf; the recorded speed and line; 1 on the last row of a part that a
    stop follows, else 0; and the columns' names."""
    part = np.zeros(len(lc.cmd_m), dtype=np.int64) if lc.part is None else lc.part
    cols, names = [], []
    for a in axes:
        k = AXES.index(a)
        cols += [lc.cmd_m[:, k] / unit,
                 _column(table, f"{a}_kp_m_min_per_mm") * KP_SI_PER_M_MIN_PER_MM,
                 _column(table, f"{a}_kf")]
        names += [f"{a}_cmd", f"{a}_kp", f"{a}_kf"]
    moves = np.r_[False, np.any(np.diff(lc.cmd_m, axis=0) != 0, axis=1)]
    if np.any(moves & (part < 0)):
        k = int(np.flatnonzero(moves & (part < 0))[0])
        raise InputError(f"recording: sample {k} (file row {lc.first_row + k}) is in a stop "
                         "(part -1) but its command moves: not a recording of oga lcnc-record")
    end = np.r_[(part[:-1] >= 0) & (part[1:] < 0), False]
    cols += [lc.current_vel_m_s / unit, lc.line.astype(np.float64), end.astype(np.float64)]
    names += ["current_vel", "line", "end_of_part"]
    data = np.column_stack(cols)
    if not np.isfinite(data).all():
        raise InputError("table: non-finite values; not exported")
    return data[part >= 0], names


def _motion_tcl(about, axes, joints, base, ept, period_ns, depth, width, tols, unit) -> str:
    """The HALFILE: checks of the thread and the pid loops, the components, the start
    condition, the per-period checks against the row and the gains' multiplexers."""
    h = HalCommands()
    h.comment(*about)
    h.comment(
        "",
        "Install: copy oga_table.tcl, oga_table.stream and oga_feeder.py into the configuration",
        "folder; in the INI file, [HAL] HALFILE = oga_table.tcl after the HAL files that load",
        "motion and the pid loops, and [HAL] HALUI = halui. Run the program as usual, from the",
        "position it was recorded from. 'setp oga-go.in-01 0' disables the table.",
        "oga-valid is TRUE while the table drives Pgain and FF1; at any other time they are",
        "the fixed baseline. The fallback latches until the program has ended.")
    h.raw(_PROCS.replace("{TERMS}", "{" + " ".join(_ZERO_TERMS) + "}"))
    h.raw("set oga_thread [thread_info ::OGA]")
    h.raw('if {$oga_thread == ""} {return -code error "oga_table.tcl: motion-controller is in '
          'no thread: load this file after motion"}')
    h.raw(f"if {{$::OGA($oga_thread,period) != {period_ns}}} {{return -code error "
          f'"oga_table.tcl: $oga_thread runs every $::OGA($oga_thread,period) ns, the table '
          f'needs {period_ns} ns"}}')
    for a in axes:
        j = joints[a]
        kp, kf = base[a]
        h.raw(f"set oga_pid({a}) [oga_pid {j}]")
        h.raw(f"oga_check_pid $oga_pid({a}) {1 if ept[a] else 0} "
              f"{hal_number(kp * KP_SI_PER_M_MIN_PER_MM)} {hal_number(kf)}")
    muxes = _tcl_components(h, axes, depth, width)
    _tcl_start(h, axes, joints)
    _tcl_checks(h, axes, tols, unit, muxes)
    h.blank()
    h.comment("the gains: the row's while valid, else the fixed baseline")
    for i, a in enumerate(axes):
        kp, kf = base[a]
        h.setp(f"oga-kp-{a}.in0", kp * KP_SI_PER_M_MIN_PER_MM)
        h.setp(f"oga-kf-{a}.in0", kf)
        h.net(f"oga-row-{a}-kp", f"streamer.0.pin.{i * _PER_AXIS + 1}", "=>", f"oga-kp-{a}.in1")
        h.net(f"oga-row-{a}-kf", f"streamer.0.pin.{i * _PER_AXIS + 2}", "=>", f"oga-kf-{a}.in1")
        h.raw(f"hal net oga-kp-{a} oga-kp-{a}.out $oga_pid({a}).Pgain")
        h.raw(f"hal net oga-kf-{a} oga-kf-{a}.out $oga_pid({a}).FF1")
    return h.tcl()


#: Stream columns per axis (command, Kp, Kf).
_PER_AXIS = 3


def _tcl_components(h: HalCommands, axes, depth: int, width: int) -> list[str]:
    """Load the components (freed first where an earlier load left them), the feeder, and add
    their functions to the thread; the gains' multiplexers' names."""
    comps = ("streamer", "ddt", "near", "conv_s32_float", "logic", "flipflop", "mux2")
    h.raw("foreach c {" + " ".join(comps) + "} {oga_free_comp $c}")
    n_ok = len(axes) + 7
    still = [f"oga-still-{a}" for a in axes]
    pos = [f"oga-pos-{a}" for a in axes]
    muxes = [f"oga-{g}-{a}" for a in axes for g in ("kp", "kf")]
    h.blank()
    h.loadrt("streamer", depth=depth, cfg="f" * (width - 1) + "b")
    h.loadrt("ddt", names=",".join(f"oga-ddt-{a}" for a in axes))
    h.loadrt("near", names=",".join(still + pos + ["oga-vel", "oga-line", "oga-fo", "oga-ro"]))
    h.loadrt("conv_s32_float", names="oga-line-f")
    gates = {"oga-still": 0x800 | len(axes), "oga-go": 0x100 | 4, "oga-run": 0x100 | 3,
             "oga-step": 0x100 | 2, "oga-flowing": 0x1000 | 1, "oga-ok": 0x900 | n_ok,
             "oga-hold-ok": 0x900 | (len(axes) + 2),
             "oga-valid": 0x100 | 2, "oga-bad-step": 0x100 | 2, "oga-bad-hold": 0x100 | 3,
             "oga-bad": 0x200 | 2}
    h.loadrt("logic", names=",".join(gates),
             personality=",".join(f"{v:#x}" for v in gates.values()))
    h.loadrt("flipflop", names="oga-started,oga-held,oga-fallen")
    h.loadrt("mux2", names=",".join(muxes))
    h.raw(f"hal loadusr -Wn oga-feeder python3 [file join $oga_dir {FEEDER}] "
          f"[file join $oga_dir {STREAM}] 0 {LINUXCNC_MOTION['feeder_poll_s']!r}")
    funcs = [f"oga-ddt-{a}" for a in axes] + still + [
        "oga-still", "oga-go", "oga-started", "oga-run", "oga-held", "oga-step", "streamer.0",
        *pos, "oga-vel", "oga-line-f", "oga-line", "oga-fo", "oga-ro", "oga-flowing", "oga-ok",
        "oga-hold-ok", "oga-valid", "oga-bad-step", "oga-bad-hold", "oga-bad",
        "oga-fallen", *muxes]
    h.raw("oga_addf $oga_thread {" + " ".join(funcs) + "} [list "
          + " ".join(f"$oga_pid({a})" for a in axes) + "]")
    return muxes


def _tcl_start(h: HalCommands, axes, joints) -> None:
    """The start: the feeder ready, enabled, coordinated motion, and a joint command moves."""
    h.blank()
    h.comment("start: ready, enabled, coordinated motion, and a joint command moves")
    for i, a in enumerate(axes):
        h.raw(f"hal net [oga_signal joint.{joints[a]}.motor-pos-cmd] oga-ddt-{a}.in "
              f"oga-pos-{a}.in1")
        h.net(f"oga-ddt-{a}", f"oga-ddt-{a}.out", "=>", f"oga-still-{a}.in1")
        h.setp(f"oga-still-{a}.in2", 0.0)
        h.setp(f"oga-still-{a}.difference", _STILL)
        h.net(f"oga-still-{a}", f"oga-still-{a}.out", "=>", f"oga-still.in-{i:02d}")
    h.net("oga-ready", "oga-feeder.ready", "=>", "oga-go.in-00", "oga-run.in-00")
    h.setp("oga-go.in-01", 1)
    h.raw("hal net [oga_signal motion.coord-mode] oga-go.in-02 oga-ok.in-"
          f"{len(axes) + 6:02d}")
    h.net("oga-moving", "oga-still.nand", "=>", "oga-go.in-03")
    h.net("oga-go", "oga-go.and", "=>", "oga-started.set")
    h.net("oga-rearm", "oga-feeder.rearm", "=>", "oga-started.reset", "oga-fallen.reset")
    h.net("oga-started", "oga-started.out", "=>", "oga-run.in-01", "oga-feeder.used")
    h.net("oga-not-fallen", "oga-fallen.out-not", "=>", "oga-run.in-02")
    h.net("oga-run", "oga-run.and", "=>", "oga-step.in-00", "oga-bad-hold.in-00")
    h.raw("hal net [oga_signal halui.program.is-idle] oga-feeder.idle")
    h.comment("a stop between two parts: held from the period after a part's last row (its",
              "end_of_part) to the period a joint command moves again, which reads the next",
              "part's first row")
    h.net("oga-end-of-part", f"streamer.0.pin.{len(axes) * _PER_AXIS + 2}", "=>",
          "oga-held.set")
    h.net("oga-moving", "oga-held.reset")
    h.net("oga-held", "oga-held.out", "=>", "oga-bad-hold.in-01")
    h.net("oga-not-held", "oga-held.out-not", "=>", "oga-step.in-01")
    h.net("oga-step", "oga-step.and", "=>", "streamer.0.enable", "oga-valid.in-00",
          "oga-bad-step.in-00")


def _tcl_checks(h: HalCommands, axes, tols: dict, unit: float, muxes: list[str]) -> None:
    """This period's motion against the row: commands, speed, line, overrides, the stream
    flowing, motion enabled; valid while all hold, the fallback latched when one fails."""
    h.blank()
    h.comment("checks of this period's motion against the row")
    for i, a in enumerate(axes):
        h.net(f"oga-row-{a}-cmd", f"streamer.0.pin.{i * _PER_AXIS}", "=>", f"oga-pos-{a}.in2")
        h.setp(f"oga-pos-{a}.difference", tols["pos_tol_m"] / unit)
        h.net(f"oga-pos-{a}", f"oga-pos-{a}.out", "=>", f"oga-ok.in-{i:02d}")
    nv = len(axes) * _PER_AXIS
    h.raw("hal net [oga_signal motion.current-vel] oga-vel.in1")
    h.net("oga-row-current-vel", f"streamer.0.pin.{nv}", "=>", "oga-vel.in2")
    h.setp("oga-vel.difference", tols["vel_tol_m_s"] / unit)
    h.raw("hal net [oga_signal motion.program-line] oga-line-f.in")
    h.net("oga-line-f", "oga-line-f.out", "=>", "oga-line.in1")
    h.net("oga-row-line", f"streamer.0.pin.{nv + 1}", "=>", "oga-line.in2")
    h.setp("oga-line.difference", 0.5)
    for name, pin in (("oga-fo", "halui.feed-override.value"),
                      ("oga-ro", "halui.rapid-override.value")):
        h.raw(f"hal net [oga_signal {pin}] {name}.in1")
        h.setp(f"{name}.in2", 1.0)
        h.setp(f"{name}.difference", tols["override_tol"])
    h.net("oga-empty", "streamer.0.empty", "=>", "oga-flowing.in-00")
    k = len(axes)
    for name in ("oga-vel", "oga-line", "oga-fo", "oga-ro", "oga-flowing"):
        h.net(f"{name}-ok" if name != "oga-flowing" else "oga-flowing",
              f"{name}.out" if name != "oga-flowing" else "oga-flowing.nor", "=>",
              f"oga-ok.in-{k:02d}")
        k += 1
    h.raw(f"hal net [oga_signal motion.motion-enabled] oga-ok.in-{k:02d} "
          f"oga-hold-ok.in-{k - 5:02d}")
    h.net("oga-ok", "oga-ok.and", "=>", "oga-valid.in-01")
    h.net("oga-not-ok", "oga-ok.nand", "=>", "oga-bad-step.in-01")
    h.comment("in a stop: the command stands at the part's end, motion enabled and",
              "coordinated (an E-stop or machine off there falls back)")
    for i, a in enumerate(axes):
        h.net(f"oga-pos-{a}", f"oga-hold-ok.in-{i:02d}")
    h.raw(f"hal net [oga_signal motion.coord-mode] oga-hold-ok.in-{len(axes) + 1:02d}")
    h.net("oga-hold-bad", "oga-hold-ok.nand", "=>", "oga-bad-hold.in-02")
    h.net("oga-bad-step", "oga-bad-step.and", "=>", "oga-bad.in-00")
    h.net("oga-bad-hold", "oga-bad-hold.and", "=>", "oga-bad.in-01")
    h.net("oga-bad", "oga-bad.or", "=>", "oga-fallen.set")
    h.net("oga-fallen", "oga-fallen.out", "=>", "oga-feeder.done")
    h.net("oga-valid", "oga-valid.and", "=>", *(f"{m}.sel" for m in muxes))
