"""``oga law``: programs in, one certified gain law out, in its controller's own terms."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path as FilePath

from oga import defaults
from oga.cli._common import (
    check_files,
    output_file,
    output_folder,
    toolpath_message,
    write_json,
    write_text,
)
from oga.cli._progress import ProgressBar
from oga.errors import InputError, OptionError

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "law",
        help="a certified gain law (Heidenhain MAC, TwinCAT dynamic Kv, LinuxCNC lincurve)",
        description="Search one gain law (Kp and Kf as functions of the commanded |v| and "
        "|a| per axis) for the programs at the feed overrides, robust over the machine's "
        "uncertainty set, certify it, and write it for its controller.",
    )
    p.add_argument("programs", nargs="+", metavar="PROGRAM",
                   help="G-code, CSV or JSON toolpaths the machine runs")
    p.add_argument("--machine", default="ucp710", metavar="NAME|FILE",
                   help="machine preset or file with an uncertainty set; default ucp710")
    p.add_argument("--kind", default="lincurve", metavar="mac|pl|lincurve|lincurve-sa",
                   help="mac: Heidenhain (Kp, Kf over |v| and |a|); pl: TwinCAT CNC dynamic "
                        "Kv (Kp over |v|, Kf constant); lincurve: LinuxCNC (Kp, Kf over |v|); "
                        "lincurve-sa: LinuxCNC (Kp over |v|, Kf over a sign(v))")
    p.add_argument("--points", type=int, default=None, metavar="N",
                   help="support points per input (default mac 3, pl 2, lincurve 4, lincurve-sa 8)")
    p.add_argument("--overrides", default=",".join(f"{o:g}" for o in defaults.LAW_OVERRIDES),
                   metavar="O,...", help="feed overrides (shares, 1 among them); "
                   "default 0.5,0.8,1,1.2")
    p.add_argument("--tolerance", type=float, default=None, metavar="MM",
                   help=f"interpolation tolerance in mm (default {defaults.TOL_M * 1e3:g})")
    p.add_argument("--units", default="mm", metavar="mm|inch",
                   help="LinuxCNC machine units of the HAL file (default mm)")
    p.add_argument("--joints", default=None, metavar="A=N,...",
                   help="LinuxCNC pid loop per axis (default 0, 1, ... in x, y, z order)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the controller files")
    p.add_argument("--summary", metavar="SUMMARY.json", help="summary JSON to write")
    p.set_defaults(func=run)


def _overrides(text: str) -> tuple[float, ...]:
    from oga.law.override import check_overrides

    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise OptionError(f"--overrides: shares of the feed expected, e.g. 0.5,1,1.2, got "
                          f"{text!r}") from None
    return check_overrides(values)


def _joints(text: str | None) -> dict[str, int] | None:
    if text is None:
        return None
    try:
        out = {a.strip(): int(n) for a, n in (x.split("=") for x in text.split(","))}
    except ValueError:
        raise OptionError(f"--joints: expected e.g. x=0,z=1, got {text!r}") from None
    if any(a not in "xyz" or not a or n < 0 for a, n in out.items()):
        raise OptionError(f"--joints: axes x, y, z and loops >= 0, got {text!r}")
    return out


def run(args: argparse.Namespace) -> int:
    from oga.law.law import check_kind

    check_kind(args.kind, args.points)  # before any work: bad options name their flag
    overrides = _overrides(args.overrides)
    joints = _joints(args.joints)
    if args.units not in ("mm", "inch"):
        raise OptionError(f"--units: mm or inch, got {args.units!r}")
    tol_m = defaults.TOL_M if args.tolerance is None else args.tolerance * 1e-3
    lo, hi = defaults.TOL_RANGE_M
    if not lo <= tol_m <= hi:
        raise OptionError(f"--tolerance: must lie within {lo * 1e3:g}..{hi * 1e3:g} mm, got "
                          f"{args.tolerance!r}")
    for prog in args.programs:
        args.toolpath = prog
        check_files(args, "summary")
    if args.summary:
        output_file("--summary", args.summary)
    out = output_folder("--out", args.out)

    from feedplan.read import load_toolpath
    from oga.law.export import law_files
    from oga.law.run import law_optimize
    from oga.model.machine import load_machine

    machine = load_machine(args.machine)
    paths = []
    for prog in args.programs:
        try:
            paths.append((FilePath(prog).name, load_toolpath(prog)))
        except InputError as err:
            raise toolpath_message(err, prog) from None
    with ProgressBar("law", enabled=sys.stderr.isatty()) as bar:
        res = law_optimize(paths, machine, args.kind, args.points, overrides=overrides,
                           tol_m=tol_m, progress=bar.update)
    from oga.search.robust.plants import scenario_set

    files = law_files(res, machine.name, len(scenario_set(machine)), units=args.units,
                      joints=joints)
    for name, text in files.items():
        write_text(out / name, text)
    if args.summary:
        write_json(args.summary, {"programs": [p for p, _ in paths], "machine": machine.name,
                                  "overrides": list(overrides), "files": sorted(files),
                                  **res.summary()})
    b = next(iter(res.baselines.values()))
    print(f"baseline: Kp {b.kp:.4g} (m/min)/mm, Kf {b.kf:.4g}" + (
        " (joint: the one fixed setting that keeps every plant's limits on all the programs)"
        if len(res.baselines) > 1 else ""))
    for (prog, o), c in res.certificate.cases.items():
        print(f"{prog} at {o * 100:g} % feed: MSE ratio to the baseline median {c.median:.3f}, "
              f"p90 {c.p90:.3f}, worst {c.worst:.3f}; law-only breaks "
              f"{len(c.breaks('schedule-only'))}; nominal plant {res.nominal_ratio[(prog, o)]:.3f}")
    if res.status != "ok":
        print(f"warning: no law certified, the baseline is kept ({res.reason})", file=sys.stderr)
    print(f"law {res.law.kind} {res.status}: {', '.join(sorted(files))} -> {out}")
    return 0
