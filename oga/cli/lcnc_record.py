"""``oga lcnc-record``: a program run through a LinuxCNC configuration headless, its setpoints
recorded per servo period (:mod:`oga.export.linuxcnc.record`) for ``oga optimize --setpoints``."""

from __future__ import annotations

import argparse
from pathlib import Path as FilePath

from oga.cli._common import check_files, write_text

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "lcnc-record",
        help="run a program in your LinuxCNC configuration headless and record its setpoints",
        description="Start LinuxCNC on your configuration without a GUI (as an unprivileged "
        "user; LinuxCNC must not be running), home it, run PROGRAM and record per servo "
        "period each axis's joint.N.motor-pos-cmd (and feedback), the program line, the motion "
        "type and the trajectory speed. The recording is what LinuxCNC's own trajectory "
        "planner commands: optimise on it with oga optimize --setpoints REC, then install the "
        "table with oga export --recording REC. Use a simulation of your machine's "
        "configuration, or run the machine itself as a dry run.",
    )
    p.add_argument("program", metavar="PROGRAM", help="G-code program (.ngc)")
    p.add_argument("--ini", required=True, metavar="MACHINE.ini",
                   help="the LinuxCNC configuration's INI file")
    p.add_argument("--out", required=True, metavar="REC.txt", help="recording to write")
    p.add_argument("--joints", metavar="A=N,...",
                   help="joint per axis, e.g. x=0,z=2 (default: trivkins' coordinates)")
    p.add_argument("--no-home", action="store_true",
                   help="do not home the machine first (it must be homed, or need no homing)")
    p.add_argument("--timeout", type=float, default=None, metavar="S",
                   help="longest run of the program, s (default 3600)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from oga.cli.export import parse_joints
    from oga.errors import InputError
    from oga.export.linuxcnc.record import record_program

    check_files(args, "out")
    if args.timeout is not None and not 0 < args.timeout <= 86400:
        raise InputError(f"--timeout: expected 0 < S <= 86400, got {args.timeout:g}")
    rec = record_program(args.program, args.ini,
                         joints=parse_joints(args.joints) if args.joints else None,
                         home=not args.no_home, timeout_s=args.timeout)
    write_text(args.out, rec.text)
    moving = rec.last_motion_row - rec.first_motion_row + 1
    print(f"recorded {FilePath(args.program).name} on {FilePath(args.ini).name}: {rec.rows} "
          f"servo periods of {rec.period_ns} ns, motion in rows {rec.first_motion_row}.."
          f"{rec.last_motion_row} ({moving * rec.period_ns * 1e-9:.3f} s) in {len(rec.parts)} "
          f"part{'s' if len(rec.parts) != 1 else ''} (rows "
          + ", ".join(f"{a}-{b}" for a, b in rec.parts) + f"), units {rec.units}, "
          "joints "
          + ", ".join(f"{a}={j}" for a, j in rec.joints.items()) + ", error-previous-target "
          + ", ".join(f"{a}={'TRUE' if v else 'FALSE'}"
                      for a, v in rec.error_previous_target.items())
          + f"; LinuxCNC session {rec.seconds:.1f} s -> {args.out}")
    return 0
