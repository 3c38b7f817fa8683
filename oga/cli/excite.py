"""``oga excite``: the identification program of a machine's axes (and its setpoints)."""

from __future__ import annotations

import argparse

from oga.cli._common import add_base_machine_arg, check_files, write_text
from oga.defaults import EXCITE_TRAVEL_MM

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "excite", help="write the identification program of a machine's axes",
        description="Write a G-code program whose moves make every cascade parameter of the "
                    "given axes visible (friction passes, velocity steps, swept frequency, "
                    "circles); run it on the machine and record a trace for oga identify.")
    add_base_machine_arg(p, "limits and Stribeck band")
    p.add_argument("--axes", required=True, metavar="AXES", help="axes to identify, e.g. x,z")
    p.add_argument("--travel-mm", type=float, default=EXCITE_TRAVEL_MM, metavar="MM",
                   help=f"free travel per axis from the start point, + direction (default "
                        f"{EXCITE_TRAVEL_MM:g})")
    p.add_argument("--out", required=True, metavar="EXCITE.ngc", help="program to write")
    p.add_argument("--setpoints", metavar="S.csv", help="also write its planned setpoints")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from feedplan.read import read_toolpath
    from oga.identify.excite import excite_program
    from oga.model.machine import load_machine

    check_files(args, "out", "setpoints")  # before any work
    machine = load_machine(args.machine)
    axes = [a.strip() for a in args.axes.split(",") if a.strip()]
    text = excite_program(machine, axes, args.travel_mm)
    path = read_toolpath(text, "gcode", source=args.out)
    write_text(args.out, text)
    msg = f"{args.out}: {len(text.splitlines())} lines, path {path.length * 1e3:.0f} mm"
    if args.setpoints:
        from oga.defaults import TOL_M
        from oga.export.table import setpoints_csv
        from oga.pipeline import plan_toolpath

        sp = plan_toolpath(path, machine, feed_m_s=None, tol_m=TOL_M)
        write_text(args.setpoints, setpoints_csv(sp))
        msg += f"; {sp.duration:.1f} s of motion planned -> {args.setpoints}"
    print(msg)
    return 0
