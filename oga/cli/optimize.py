"""``oga optimize``: toolpath (or recorded setpoints) in, verified gain table (and summary
JSON) out."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path as FilePath

from oga.cli._common import (
    add_search_args,
    add_toolpath_args,
    check_files,
    flag_message,
    options_from_args,
    toolpath_message,
    write_json,
    write_text,
)
from oga.cli._progress import ProgressBar

__all__ = ["register", "run", "certificate_lines", "add_setpoints_args", "setpoints_options"]


def add_setpoints_args(p: argparse.ArgumentParser) -> None:
    """``--setpoints FILE`` and how to read it (:func:`oga.recorded.read_setpoints`)."""
    from oga.recorded import SETPOINT_FORMATS, UNITS

    g = p.add_argument_group("recorded setpoints (instead of TOOLPATH)")
    g.add_argument("--setpoints", metavar="FILE",
                   help="optimise on these setpoints instead of planning TOOLPATH: an oga "
                        "lcnc-record recording, a halsampler recording of joint.N.motor-pos-cmd, "
                        "or the CSV/TwinCAT formats of oga identify (<a>_cmd_m per axis)")
    g.add_argument("--setpoints-format", choices=SETPOINT_FORMATS, default=None,
                   help="default: halsampler for an oga lcnc-record file or with "
                        "--setpoints-columns (not .csv), else csv")
    g.add_argument("--setpoints-columns", metavar="A,B,...",
                   help="halsampler/twincat: column names in order, e.g. "
                        "sample,x_cmd_m,z_cmd_m,line")
    g.add_argument("--setpoints-units", choices=tuple(UNITS), default=None,
                   help="length unit of the file (default: an oga lcnc-record header's, else m)")
    g.add_argument("--error-previous-target", choices=("true", "false"), default=None,
                   help="halsampler without header: pid.N.error-previous-target (default true)")


def setpoints_options(args: argparse.Namespace) -> dict:
    """The reading options of ``--setpoints`` (InputError if given without it)."""
    from oga.errors import InputError

    given = {"--setpoints-format": args.setpoints_format,
             "--setpoints-columns": args.setpoints_columns,
             "--setpoints-units": args.setpoints_units,
             "--error-previous-target": args.error_previous_target}
    if args.setpoints is None:
        extra = [flag for flag, v in given.items() if v is not None]
        if extra:
            raise InputError(f"{extra[0]}: applies to --setpoints only")
        return {}
    return {"columns": None if args.setpoints_columns is None
            else args.setpoints_columns.split(","),
            "units": args.setpoints_units,
            "error_previous_target": None if args.error_previous_target is None
            else args.error_previous_target == "true"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "optimize",
        help="compute a verified gain schedule for a toolpath",
        description="Plan the toolpath, search the gain schedule (receding-horizon OGA), "
        "verify it by replay and write the gain table. With --setpoints, optimise on the "
        "setpoints another interpolator produced (e.g. LinuxCNC's, oga lcnc-record) instead.",
    )
    add_toolpath_args(p, toolpath_required=False)
    add_search_args(p)
    add_setpoints_args(p)
    p.add_argument("--out", required=True, metavar="TABLE.csv", help="gain table CSV to write")
    p.add_argument("--summary", metavar="SUMMARY.json", help="summary JSON to write")
    p.add_argument("--report", metavar="REPORT.html",
                   help="optimisation report to write (one self-contained HTML file)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from oga.errors import InputError

    options = options_from_args(args)
    if (args.toolpath is None) == (args.setpoints is None):
        raise InputError("give a TOOLPATH to plan or --setpoints FILE, one of them")
    read_options = setpoints_options(args)
    if args.setpoints is not None and args.tolerance is not None:
        raise InputError("--tolerance: recorded setpoints are optimised as recorded (their "
                         "interpolator applied its tolerance)")
    check_files(args, "out", "summary", "report")  # before the compiled kernels load

    from oga.export.table import table_csv
    from oga.model.machine import load_machine

    machine = load_machine(args.machine)
    job = _run_job(args, machine, options, read_options)
    res = job.result
    summary = job.summary()
    if args.summary:
        write_json(args.summary, summary)
    if args.report:
        from oga.report.optimize import render_report

        write_text(args.report, render_report(job))
    _print_result(job, summary, machine, options)
    if res.status != "ok":
        print("verification FAILED, no table written: " + "; ".join(res.optimized.violations),
              file=sys.stderr)
        return 1
    write_text(args.out, table_csv(res))
    print(f"limits ok, stability ok -> {args.out}")
    return 0


def _run_job(args: argparse.Namespace, machine, options, read_options: dict):
    """The job of the toolpath or of the recorded setpoints, with a progress bar; a reader's
    or an option's error as the CLI names it."""
    from feedplan.read import read_file
    from oga.errors import GcodeError, OptionError, ToolpathError
    from oga.identify.trace import TraceError
    from oga.pipeline import run_job

    try:
        if args.setpoints is not None:
            from oga.pipeline import SETPOINTS_PREFIX
            from oga.recorded import read_setpoints_file

            text, fmt = read_setpoints_file(args.setpoints, args.setpoints_format,
                                            read_options["columns"])
            with ProgressBar("optimize", enabled=sys.stderr.isatty()) as bar:
                return run_job(text, SETPOINTS_PREFIX + fmt, machine, options,
                               source=FilePath(args.setpoints).name, progress=bar.update,
                               setpoints_options=read_options)
        text, fmt = read_file(args.toolpath)
        with ProgressBar("optimize", enabled=sys.stderr.isatty()) as bar:
            return run_job(text, fmt, machine, options, source=FilePath(args.toolpath).name,
                           progress=bar.update)
    except (GcodeError, ToolpathError) as err:
        raise toolpath_message(err, args.toolpath) from None
    except TraceError as err:  # SetpointsError too
        raise toolpath_message(err, args.setpoints) from None
    except OptionError as err:
        raise flag_message(err) from None


def _print_result(job, summary: dict, machine, requested) -> None:
    """What ``oga optimize`` prints: the setpoints read, warnings, baseline and optimised
    contour errors, following errors, the certificate or search (and the anchor, where the
    robust search raised it from the ``requested`` options' default), the model's note."""
    from feedplan.setpoints import AXES
    from oga import defaults

    res = job.result
    if job.recorded is not None:
        src = job.recorded.source
        print(f"setpoints: {src['file']} ({src['format']}, {src['law']}), {src['samples']} "
              f"samples from row {src['first_row']}, SHA-256 {src['sha256'][:12]}...")
    for w in job.warnings:
        print(f"warning: {w}")
    b, o = summary["baseline"], summary["optimized"]
    kp_b = {a: v for a, v in b["kp"].items() if a in machine.axes}
    kf_b = {a: v for a, v in b["kf"].items() if a in machine.axes}
    print(f"baseline  Kp {kp_b} Kf {kf_b}: CE rms {b['rms_ce_um']:.3f} um, "
          f"max {b['max_ce_um']:.3f} um")
    print(f"optimized ({','.join(res.adjusted)}; {','.join(res.options.gains)}): "
          f"CE rms {o['rms_ce_um']:.3f} um, max {o['max_ce_um']:.3f} um, "
          f"MSE ratio {res.ratio_mse:.3f}, {res.optimize_time_s:.1f} s")
    lag_b, lag_o = b["track_max_um"], o["track_max_um"]
    limit_um = dict(zip(AXES, (v * 1e6 for v in machine.ferror_limits())))
    print("following error max (um): " + ", ".join(
        f"{a} {lag_b[a]:.1f} -> {lag_o[a]:.1f}"
        + (f" (limit {limit_um[a]:.1f})" if math.isfinite(limit_um[a]) else "")
        for a in res.adjusted))
    if b["violations"]:  # fixed gains given by the user (the best fixed gains keep the limits)
        print("warning: the baseline's fixed gains break: " + "; ".join(b["violations"]))
    if res.robust:
        for line in certificate_lines(summary["certificate"]):
            print(line)
        if requested.anchor is None and res.options.anchor is not None:
            print(f"anchor: {res.options.anchor:g} (at the default "
                  f"{defaults.ANCHOR[res.options.mode]:g} no share of any round's table "
                  "passed its certificate)")
    else:
        print(f"search: {res.search_kind()}")
    if summary["model"]["note"]:
        print(("warning: " if not summary["model"]["covers"] else "model: ")
              + summary["model"]["note"])
    if res.kept_baseline:
        print(f"warning: the searched schedule was not kept ({res.kept_baseline_reason}); "
              "the table holds the baseline's fixed gains")


def certificate_lines(cert: dict) -> list[str]:
    """The certificate of a summary (``summary["certificate"]``) as the lines printed."""
    from oga.verify.certificate import confidence_text

    br = cert["breaks"]
    s, b = cert["schedule"], cert["baseline"]
    axes = [a for a in s["track_max_um"] if s["track_max_um"][a] or b["track_max_um"][a]]
    return [
        f"certificate {cert['status']}: {cert['plants']} plants of the uncertainty set "
        f"({cert['monte_carlo']} Monte Carlo, seed {cert['seed']}; {cert['corners']} corners)",
        f"  MSE ratio to the fixed baseline: median {cert['ratio_median']:.3f}, "
        f"p90 {cert['ratio_p90']:.3f}, worst {cert['ratio_worst']:.3f} ({cert['worst_plant']})",
        f"  plants where a limit breaks: schedule {len(br['schedule'])}, baseline "
        f"{len(br['baseline'])}, schedule only {len(br['schedule-only'])}",
        f"  {confidence_text(cert)}",
        f"  largest CE (um): schedule {s['max_ce_um']:.3f}, baseline {b['max_ce_um']:.3f}; "
        "largest following error (um): " + ", ".join(
            f"{a} {s['track_max_um'][a]:.1f} (baseline {b['track_max_um'][a]:.1f})" for a in axes),
    ]
