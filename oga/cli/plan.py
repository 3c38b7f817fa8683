"""``oga plan``: toolpath in, jerk-limited setpoints CSV (and a summary JSON) out."""

from __future__ import annotations

import argparse
import time

from oga.cli._common import add_toolpath_args, check_files, load_inputs, write_json, write_text

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        help="plan jerk-limited setpoints of a toolpath",
        description="Plan jerk-limited position setpoints (one row per sample) of a toolpath.",
    )
    add_toolpath_args(p)
    p.add_argument("--dt", type=float, default=None, metavar="S",
                   help="sample period in seconds (default: the machine's Te)")
    p.add_argument("--out", required=True, metavar="SETPOINTS.csv", help="setpoints CSV to write")
    p.add_argument("--summary", metavar="SUMMARY.json", help="summary JSON to write")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from oga.errors import OptionError

    if args.dt is not None and not 0 < args.dt < float("inf"):
        raise OptionError(f"--dt: must be a positive number of seconds (got {args.dt})")
    check_files(args, "out", "summary")  # before the compiled kernels load

    from feedplan.check import check_setpoints
    from feedplan.plan import program_tolerance_m
    from oga.export.table import setpoints_csv
    from oga.pipeline import plan_toolpath

    path, machine, feed_m_s, tol_m = load_inputs(args)
    dt = machine.te if args.dt is None else args.dt
    limits = machine.axis_limits()
    t0 = time.perf_counter()
    sp = plan_toolpath(path, machine, feed_m_s=feed_m_s, tol_m=tol_m, dt=dt)
    planning_time = time.perf_counter() - t0
    check = check_setpoints(sp, path, limits, feed_m_s=feed_m_s,
                            tol_m=program_tolerance_m(path, tol_m))  # G64 P where given
    write_text(args.out, setpoints_csv(sp))
    if args.summary:
        write_json(args.summary, {
            "toolpath": path.source,
            "machine": machine.name,
            "samples": len(sp),
            "duration_s": sp.duration,
            "length_m": path.length,
            "max_deviation_m": check.max_deviation_m,
            "axes": check.axes_dict(),
            "limits_ok": check.ok,
            "violations": list(check.violations),
            "planning_time_s": planning_time,
            "warnings": [*path.warnings, *sp.warnings],
        })
    for w in (*path.warnings, *sp.warnings):
        print(f"warning: {w}")
    print(f"{len(sp)} samples, {sp.duration:.3f} s, max deviation "
          f"{check.max_deviation_m * 1e6:.2f} um, limits {'ok' if check.ok else 'VIOLATED'}, "
          f"planned in {planning_time:.2f} s -> {args.out}")
    return 0 if check.ok else 1
