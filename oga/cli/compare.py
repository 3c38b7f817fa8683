"""``oga compare``: the controllers of the literature, the fixed gains and OGA side by side."""

from __future__ import annotations

import argparse

from oga.cli._common import add_toolpath_args, check_files, load_inputs, write_json, write_text

__all__ = ["register", "run", "format_table"]


def register(sub: argparse._SubParsersAction) -> None:
    from oga.controllers import CONTROLLERS

    p = sub.add_parser(
        "compare",
        help="compare the fixed gains, OGA and online contouring controllers on a toolpath",
        description="Plan the toolpath and simulate each controller on the same setpoints and "
        "plant; print one row per controller (contour and tracking errors, command ratios to "
        "the limits of paper eq. 2, whether it needs drive-firmware access).",
    )
    add_toolpath_args(p)
    p.add_argument("--controllers", default=",".join(CONTROLLERS), metavar="NAMES",
                   help=f"comma-separated controllers (default all: {','.join(CONTROLLERS)})")
    p.add_argument("--no-tune", action="store_true",
                   help="run every law with its paper/design parameters instead of tuning them "
                        "on the toolpath (fixed and oga are unaffected)")
    p.add_argument("--json", metavar="OUT.json", help="comparison JSON to write")
    p.add_argument("--report", metavar="OUT.html",
                   help="comparison report to write (one self-contained HTML file)")
    p.set_defaults(func=run)


def format_table(cmp) -> str:
    """The comparison as a fixed-width text table (one row per controller, reasons below).

    An untuned row (no tuning met the limits) is marked ``*`` after its name.
    """
    head = (f"{'controller':<15} {'firmware':>8} {'MSE um^2':>10} {'RMS um':>8} {'max um':>8} "
            f"{'track max um (x/y/z)':>22} {'acc':>6} {'jerk':>6} {'limits':>6} {'time s':>7}")
    lines = [head, "-" * len(head)]
    failed = []
    for r in cmp.rows:
        fw = "-" if r.needs_firmware is None else ("yes" if r.needs_firmware else "no")
        if r.status == "failed":
            lines.append(f"{r.name:<15} {fw:>8} {'FAILED':>10}")
            failed.append(f"failed {r.name}: {r.message.removeprefix(r.name + ': ')}")
            continue
        if r.status == "untuned":
            failed.append(f"* {r.name}: {r.message.removeprefix(r.name + ': ')}")
        label = r.name + ("*" if r.status == "untuned" else "")
        track = "/".join(f"{v:.1f}" for v in r.track_max_um.values())
        lines.append(f"{label:<15} {fw:>8} {r.mse_ce_um2:>10.4g} {r.rms_ce_um:>8.3f} "
                     f"{r.max_ce_um:>8.3f} {track:>22} {r.accel_ratio:>6.3f} {r.jerk_ratio:>6.3f} "
                     f"{'ok' if r.limits_ok else 'NO':>6} {r.time_s:>7.1f}")
    return "\n".join(lines + failed)


def run(args: argparse.Namespace) -> int:
    check_files(args, "json", "report")  # before the compiled kernels load

    from oga.controllers.compare import compare, parse_controllers
    from oga.pipeline import plan_toolpath

    names = parse_controllers(args.controllers)
    path, machine, feed_m_s, tol_m = load_inputs(args)
    setpoints = plan_toolpath(path, machine, feed_m_s=feed_m_s, tol_m=tol_m)
    cmp = compare(setpoints, machine, names, tune=not args.no_tune)
    if args.json:
        write_json(args.json, cmp.to_dict())
    if args.report:
        from oga.report.compare import render_compare_report

        write_text(args.report, render_compare_report(cmp))
    for w in path.warnings:
        print(f"warning: {w}")
    print(f"{setpoints.source or args.toolpath} on {machine.name}: {len(setpoints)} samples")
    print(format_table(cmp))
    return 0
