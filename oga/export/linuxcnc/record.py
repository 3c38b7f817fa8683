"""``oga lcnc-record``: a program run through the user's own LinuxCNC configuration, its
setpoints recorded per servo period.

LinuxCNC's trajectory planner (its blending, ``G64 P``, its 2.9 planner, the configuration's
limits) produces the commands; a ``sampler`` added right after ``motion-controller`` records,
per servo period from just before the program starts to just after it ends, per axis
``joint.N.motor-pos-cmd`` and ``motor-pos-fb``, and ``motion.program-line``,
``motion.motion-type`` and ``motion.current-vel``, and the part of the program each period
belongs to. The recording (:data:`HEADER` format,
:mod:`oga.recorded.lcnc`) also names the units, the servo period, the joints and each
loop's ``pid.N.error-previous-target``, so that ``oga optimize --setpoints`` reads it alone.

Parts: LinuxCNC's task, not its planner, times what a program does between two motions (a
tool change M6, a pause M0/M1, the spindle M3-M5, a dwell G4): the motion stops, the task
runs the command and queues the next motion when it is done, so no two runs repeat such a
stop to the servo period. A standstill of ``LINUXCNC_RECORD["stop_min_periods"]`` periods
or more between two motions splits the program into parts (the planner's own standstills
last a period or two); each part, from its first moving period to the first period at rest
after its last move, is what the runs must repeat period for period (:func:`motion_parts`),
and what a table steps through; the stops between them take as long as they take.

Run it on a simulation of the machine (its configuration with the drives simulated: the
planner does not depend on them), or on the machine itself as a dry run.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from feedplan.setpoints import AXES
from oga.defaults import LINUXCNC_MOTION, LINUXCNC_RECORD
from oga.errors import InputError, OptionError
from oga.export.linuxcnc.export import UNIT_M
from oga.export.linuxcnc.halfile import HalCommands, printable
from oga.export.linuxcnc.session import LinuxcncError, run_session
from oga.recorded.lcnc import HEADER

__all__ = ["Recording", "ini_value", "ini_axes", "motion_parts", "part_column", "record_program",
           "recorder_tcl"]

#: ``motion.*`` pins recorded after the joints' (name in the file, pin, sampler type).
_MOTION = (("line", "motion.program-line", "s"), ("motion_type", "motion.motion-type", "s"),
           ("current_vel_m_s", "motion.current-vel", "f"))
#: File the recorder writes: per joint its pid loop and error-previous-target.
_PIDS = "pids.txt"


def ini_value(text: str, section: str, key: str) -> str | None:
    """The first value of ``key`` in ``[section]`` of a LinuxCNC INI text, or None."""
    current = None
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("[") and s.endswith("]"):
            current = s[1:-1].strip()
        elif current == section and "=" in s and s[0] not in "#;":
            k, v = s.split("=", 1)
            if k.strip() == key:
                return v.split("#")[0].strip()
    return None


def ini_axes(text: str) -> dict[str, int]:
    """Joint per axis x, y, z of a configuration with trivial kinematics (``trivkins``: the
    joints in the order of its ``coordinates=`` letters, the first joint of an axis).

    Raises
    ------
    OptionError
        Other kinematics (give the joints), or no linear axis.
    """
    kins = ini_value(text, "KINS", "KINEMATICS") or ""
    words = kins.split()
    if not words or words[0] != "trivkins":
        raise OptionError(f"joints: [KINS] KINEMATICS is {kins!r}, not trivkins: give the joint "
                          "of each axis (--joints x=0,z=2)")
    letters = next((w.split("=", 1)[1] for w in words[1:] if w.startswith("coordinates=")),
                   None) or (ini_value(text, "TRAJ", "COORDINATES") or "XYZ").replace(" ", "")
    out = {}
    for j, letter in enumerate(letters.lower()):
        if letter in AXES and letter not in out:
            out[letter] = j
    if not out:
        raise OptionError(f"joints: no x, y or z among the coordinates {letters!r}")
    return out


def _units(text: str) -> str:
    u = (ini_value(text, "TRAJ", "LINEAR_UNITS") or "mm").lower()
    if u in ("mm", "metric"):
        return "mm"
    if u in ("in", "inch", "imperial"):
        return "inch"
    raise InputError(f"[TRAJ] LINEAR_UNITS = {u!r}: expected mm or inch")


def recorder_tcl(joints: dict[str, int], channel: int = 0,
                 depth: int = LINUXCNC_RECORD["fifo_rows"]) -> str:
    """The recorder's HALFILE: a ``sampler`` right after ``motion-controller`` (LinuxCNC's
    ``hal_procs_lib.tcl`` finds the signals and the thread), and :data:`_PIDS`."""
    h = HalCommands()
    h.comment("oga lcnc-record: the setpoints of LinuxCNC's motion controller, per servo period")
    h.raw("source [file join $::env(HALLIB_DIR) hal_procs_lib.tcl]")
    h.raw("proc oga_signal {pin} {\n"
          "  if {[is_connected $pin sig] == \"not_connected\"} {\n"
          "    set sig oga-$pin\n    hal net $sig $pin\n  }\n  return $sig\n}")
    h.raw("set oga_thread [thread_info ::OGA]")
    types = "ff" * len(joints) + "".join(t for _, _, t in _MOTION)
    h.raw("if {[lsearch -exact [hal list comp] sampler] >= 0} {return -code error \"oga "
          "lcnc-record: the configuration loads sampler already (a component loads once): "
          "record on a copy without it\"}")
    h.loadrt("sampler", depth=depth, cfg=types)
    h.raw("hal addf sampler.0 $oga_thread [expr {$::OGA($oga_thread,motion-controller) + 1}]")
    k = 0
    for a, j in joints.items():
        for pin in (f"joint.{j}.motor-pos-cmd", f"joint.{j}.motor-pos-fb"):
            h.raw(f"hal net [oga_signal {pin}] sampler.{channel}.pin.{k}")
            k += 1
    for _, pin, _ in _MOTION:
        h.raw(f"hal net [oga_signal {pin}] sampler.{channel}.pin.{k}")
        k += 1
    h.raw(f"set f [open [file join [file dirname [file normalize [info script]]] {_PIDS}] w]")
    for a, j in joints.items():
        h.raw(f"set sig [oga_signal joint.{j}.motor-pos-cmd]\n"
              "get_netlist inpins outpin iopins $sig\n"
              f"set ept {{}}\n"
              "foreach p $inpins {\n"
              "  if {[string match *.command $p]} {\n"
              "    set pid [string range $p 0 end-8]\n"
              "    if {[pin_exists $pid.error-previous-target]} {\n"
              "      lappend ept $pid [string is true [hal getp $pid.error-previous-target]]\n"
              "    }\n  }\n}\n"
              f"puts $f \"{a} {j} $ept\"")
    h.raw("close $f")
    return h.tcl()


@dataclass(frozen=True, eq=False)
class Recording:
    """A program recorded in LinuxCNC.

    Attributes
    ----------
    text : str
        The recording file (:mod:`oga.recorded.lcnc`'s format).
    rows : int
        Servo periods recorded.
    first_motion_row, last_motion_row : int
        Rows (0-based) of the first and the last period whose command moved.
    parts : ndarray of int, shape (P, 2)
        First and last row of each part (:func:`motion_parts`).
    units : str
        Machine units.
    period_ns : int
        Servo period, ns.
    joints : dict of str to int
        Joint per recorded axis.
    error_previous_target : dict of str to bool
        ``pid.N.error-previous-target`` per axis.
    errors : list
        Messages of LinuxCNC's error channel during the run.
    seconds : float
        Wall time of the LinuxCNC session, s.
    """

    text: str
    rows: int
    first_motion_row: int
    last_motion_row: int
    units: str
    period_ns: int
    joints: dict
    error_previous_target: dict
    errors: list
    seconds: float
    parts: np.ndarray


def record_program(program: str | os.PathLike, ini: str | os.PathLike, *,
                   joints: dict[str, int] | None = None, home: bool = True,
                   timeout_s: float | None = None, repeats: int | None = None) -> Recording:
    """Run ``program`` on the configuration ``ini`` headless and record its setpoints.

    Parameters
    ----------
    program : path
        The G-code program.
    ini : path
        The configuration's INI file.
    joints : dict of str to int, optional
        Joint per axis (default from ``trivkins``' coordinates).
    home : bool
        Home the machine first if it is not homed.
    timeout_s : float, optional
        Longest run of the program (default ``LINUXCNC_RECORD["run_timeout_s"]``).
    repeats : int, optional
        Runs of the program (each from the first one's start position, moved back to with
        ``G53 G0``) whose commands must agree within the production tolerances (default
        ``LINUXCNC_RECORD["repeats"]``); the first one is the recording.

    Raises
    ------
    InputError
        A file is missing or the INI file lacks what is needed.
    LinuxcncError
        LinuxCNC did not start or the program failed (its messages).
    """
    program, ini = Path(program).absolute(), Path(ini).absolute()
    for path, what in ((program, "PROGRAM"), (ini, "--ini")):
        if not path.is_file():
            raise InputError(f"{what} {path}: no such file")
    text = ini.read_text(errors="replace")
    joints = ini_axes(text) if joints is None else dict(joints)
    units = _units(text)
    period = ini_value(text, "EMCMOT", "SERVO_PERIOD")
    try:
        period_ns = int(float(period))
    except (TypeError, ValueError):
        raise InputError(f"{ini.name}: [EMCMOT] SERVO_PERIOD = {period!r} is not a number of "
                         "ns") from None
    run_timeout = LINUXCNC_RECORD["run_timeout_s"] if timeout_s is None else float(timeout_s)
    repeats = LINUXCNC_RECORD["repeats"] if repeats is None else int(repeats)
    if not 1 <= repeats <= 10:
        raise OptionError(f"repeats: 1..10, got {repeats}")
    res = run_session(ini, _record_job(program, joints, home, run_timeout, repeats),
                      halfiles={"oga_record.tcl": recorder_tcl(joints)},
                      timeout_s=LINUXCNC_RECORD["start_timeout_s"]
                      + repeats * (run_timeout + 10.0) + 60.0)
    errors = res.status.get("errors", [])
    if errors:
        raise LinuxcncError(f"{program.name}: LinuxCNC reported "
                            + "; ".join(str(m[1]) for m in errors))
    ept = _pids(res.status["files"][_PIDS], joints)
    rows = res.runs[0]
    n_axes = len(joints)
    min_stop = LINUXCNC_RECORD["stop_min_periods"]
    parts = motion_parts(rows[:, 0:2 * n_axes:2], min_stop)
    if len(parts) == 0:
        raise LinuxcncError(f"{program.name}: no joint moved while the program ran")
    for again in res.runs[1:]:
        _same_motion(program.name, rows, again, n_axes, UNIT_M.get(units, 1.0), min_stop)
    header = [
        f"program: {printable(program.name)} (SHA-256 "
        f"{hashlib.sha256(program.read_bytes()).hexdigest()})",
        f"configuration: {printable(str(ini))}",
        f"linuxcnc: {printable(str(res.status.get('version', '')))}",
        f"servo-period-ns: {period_ns}",
        f"units: {units}",
        "program-pauses: " + _pauses(res.status),
        _parts_line(parts, min_stop),
    ]
    return Recording(text=_recording_text(header, joints, ept, rows, parts), rows=len(rows),
                     first_motion_row=int(parts[0, 0]), last_motion_row=int(parts[-1, 1]) - 1,
                     units=units, period_ns=period_ns, joints=joints,
                     error_previous_target=ept, errors=errors, seconds=res.seconds,
                     parts=parts)


def _record_job(program: Path, joints: dict[str, int], home: bool, run_timeout: float,
                repeats: int) -> dict:
    """The display's job: sample the joints' commands and the motion columns through
    ``repeats`` runs of ``program``, each after the first back to its start."""
    types = "ff" * len(joints) + "".join(t for _, _, t in _MOTION)
    back = {"back_to_start": {a.upper(): 2 * i for i, a in enumerate(joints)}}
    runs = [{"timeout_s": run_timeout, "tail_s": 0.1}] + [
        {"prepare": [{"tool_of_run": 0}, back, {"sleep": 0.2}], "timeout_s": run_timeout,
         "tail_s": 0.1}
        for _ in range(repeats - 1)]
    return {"program": str(program), "home": home,
            "sampler": {"channel": 0, "types": types}, "read_files": [_PIDS], "runs": runs}


def _parts_line(parts: np.ndarray, min_stop: int) -> str:
    """The header's ``parts`` line: how many, and the rows of each."""
    return (f"parts: {len(parts)} (split at standstills of {min_stop} servo periods or more "
            "between two motions: LinuxCNC's task timed them; rows"
            + ",".join(f" {a}-{b}" for a, b in parts) + ")")


def _recording_text(about: list[str], joints: dict[str, int], ept: dict[str, bool],
                    rows: np.ndarray, parts: np.ndarray) -> str:
    """The recording file: its header (``about`` lines, then joints, error-previous-target,
    columns) and a row per servo period, its part last (-1 outside every part)."""
    n_axes = len(joints)
    names = ["sample"] + [f"{a}_{c}_m" for a in joints for c in ("cmd", "act")] \
        + [name for name, _, _ in _MOTION] + ["part"]
    header = [
        HEADER[2:] + ": LinuxCNC's setpoints, one row per servo period (oga optimize "
        "--setpoints)",
        *about,
        "joints: " + " ".join(f"{a}={j}" for a, j in joints.items()),
        "error-previous-target: " + " ".join(f"{a}={int(ept[a])}" for a in joints),
        "columns: " + " ".join(names),
    ]
    body = np.column_stack([np.arange(len(rows)), rows, part_column(len(rows), parts)])
    fmt = ["%d"] + ["%.17g"] * (2 * n_axes) + ["%d", "%d", "%.17g", "%d"]
    lines = [" ".join(f % v for f, v in zip(fmt, row)) for row in body]
    return "\n".join([f"# {h}" for h in header] + lines) + "\n"


def _pauses(status: dict) -> str:
    """The program's own pauses (M0, M1) in the recorded run, which oga's display resumed at
    once (its ``auto_resume``): how many, and their lines."""
    p = status["runs"][0].get("pauses", [])
    return f"{len(p)} (M0/M1, auto_resume)" + "".join(f" at={q['at_s']:.3f}s" for q in p)


def _pids(text: str, joints: dict[str, int]) -> dict[str, bool]:
    """error-previous-target per axis from the recorder's file (one pid loop per joint)."""
    out = {}
    for line in text.splitlines():
        words = line.split()
        if len(words) < 2 or words[0] not in joints:
            continue
        pairs = words[2:]
        if len(pairs) != 2:
            raise LinuxcncError(f"joint {words[1]} (axis {words[0]}): its motor-pos-cmd feeds "
                                f"{len(pairs) // 2} pid loops; the table needs exactly one")
        out[words[0]] = pairs[1] == "1"
    missing = [a for a in joints if a not in out]
    if missing:
        raise LinuxcncError(f"axis {', '.join(missing)}: no pid loop found on its joint's "
                            "motor-pos-cmd")
    return out


def motion_parts(cmd: np.ndarray, min_stop: int) -> np.ndarray:
    """The parts of a run: the motions between the standstills of at least ``min_stop``
    periods (the stops LinuxCNC's task times: module docstring).

    Parameters
    ----------
    cmd : ndarray, shape (R, J)
        The joints' commands per servo period.
    min_stop : int
        Shortest standstill between two moving periods that splits them, periods (>= 2).

    Returns
    -------
    ndarray of int, shape (P, 2)
        Per part its first row (the first period whose command moved) and its last (the
        first period at rest after its last move); none when the command never moves.
    """
    moved = np.flatnonzero(np.any(np.diff(cmd, axis=0) != 0, axis=1)) + 1
    if moved.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    cut = np.flatnonzero(np.diff(moved) - 1 >= min_stop)
    firsts = np.concatenate([moved[:1], moved[cut + 1]])
    lasts = np.minimum(np.concatenate([moved[cut], moved[-1:]]) + 1, len(cmd) - 1)
    return np.column_stack([firsts, lasts]).astype(np.int64)


def part_column(rows: int, parts: np.ndarray) -> np.ndarray:
    """Part of each row (R,): its index in ``parts``, -1 outside every part."""
    out = np.full(rows, -1, dtype=np.int64)
    for i, (a, b) in enumerate(parts):
        out[a:b + 1] = i
    return out


def _same_motion(name: str, first: np.ndarray, again: np.ndarray, n_axes: int,
                 unit: float, min_stop: int) -> None:
    """LinuxcncError unless a repeated run commanded what the first one did: the same parts,
    each period for period from its first motion (the stops between them may last longer or
    shorter), within the production tolerances (:data:`oga.defaults.LINUXCNC_MOTION`)."""
    cols = list(range(0, 2 * n_axes, 2))
    pa, pb = motion_parts(first[:, cols], min_stop), motion_parts(again[:, cols], min_stop)
    if len(pa) != len(pb):
        raise LinuxcncError(
            f"{name}: LinuxCNC did not repeat the motion (run again from the same start, it "
            f"made {len(pb)} parts between stops of {min_stop} servo periods or more, the first "
            f"run {len(pa)}); record again")
    pos_tol, vel_tol = LINUXCNC_MOTION["pos_tol_m"] / unit, LINUXCNC_MOTION["vel_tol_m_s"] / unit
    for i, ((a0, a1), (b0, b1)) in enumerate(zip(pa, pb)):
        a, b = first[a0:a1 + 1], again[b0:b1 + 1]
        m = min(len(a), len(b))
        bad = np.any(np.abs(a[:m, cols] - b[:m, cols]) > pos_tol, axis=1)
        bad |= np.abs(a[:m, -1] - b[:m, -1]) > vel_tol
        if bad.any() or len(a) != len(b):
            k = int(np.flatnonzero(bad)[0]) if bad.any() else m
            line = int(a[min(k, len(a) - 1), 2 * n_axes])
            raise LinuxcncError(
                f"{name}: LinuxCNC did not repeat the motion (run again from the same start, "
                f"part {i} of {len(pa)} differs from servo period {k} of its motion on, program "
                f"line {line}); its planner starts differently when its task queues the next "
                "moves late (a loaded PC): a table follows one motion only. Record again, on a "
                "less loaded PC if it recurs")
