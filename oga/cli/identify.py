"""``oga identify``: a recorded trace and a base machine in, the identified machine file out."""

from __future__ import annotations

import argparse

from oga.cli._common import add_base_machine_arg, check_files, write_json, write_text

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "identify", help="fit the axis model of a machine to a recorded trace",
        description="Fit every cascade parameter (mass, friction, velocity PI, force lag, dead "
                    "time) of the traced axes through the optimizer's simulator; write the "
                    "machine file with confidence intervals and an uncertainty section.")
    p.add_argument("trace", metavar="TRACE", help="recorded trace (CSV, halsampler, TwinCAT)")
    add_base_machine_arg(p, "starting values, limits, gain settings")
    p.add_argument("--out", required=True, metavar="MINE.toml", help="machine file to write")
    p.add_argument("--format", default=None, choices=("csv", "halsampler", "twincat"),
                   help="trace format (default csv; halsampler when --columns is given and the "
                        "file is not .csv)")
    p.add_argument("--columns", default=None, metavar="NAMES",
                   help="halsampler/TwinCAT: channel names in order, e.g. x_cmd_m,x_act_m")
    p.add_argument("--units", default="m", choices=("m", "mm"), help="lengths in the trace")
    p.add_argument("--kp", default=None, metavar="KP|a=KP,..",
                   help="Kp while recording, (m/min)/mm, one or per axis (x=2.0,z=2.5)")
    p.add_argument("--kf", default=None, metavar="KF|a=KF,..", help="Kf while recording")
    p.add_argument("--axes", default=None, metavar="AXES", help="axes to fit (default all traced)")
    p.add_argument("--name", default=None, help="name of the identified machine")
    p.add_argument("--report", metavar="FIT.html", help="HTML report of the fit")
    p.add_argument("--summary", metavar="FIT.json", help="summary JSON of the fit")
    p.add_argument("--holdout", type=float, default=None, metavar="FRACTION",
                   help="held-out check: refit without the trace's last FRACTION and predict it "
                        "(default 0.25 with --report, else none)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from oga.identify.trace import load_trace
    from oga.identify.workflow import identify
    from oga.model.machine import load_machine

    check_files(args, "out", "summary", "report")  # before any work: a fit takes minutes
    machine = load_machine(args.machine)
    columns = None if args.columns is None else args.columns.split(",")
    trace = load_trace(args.trace, args.format, columns=columns, units=args.units, kp=args.kp,
                       kf=args.kf, te_s=machine.te)
    axes = None if args.axes is None else [a.strip() for a in args.axes.split(",")]
    holdout = args.holdout if args.holdout is not None else (0.25 if args.report else 0.0)
    ident = identify(trace, machine, axes=axes, name=args.name, holdout_fraction=holdout)
    write_text(args.out, ident.toml)
    if args.summary:
        write_json(args.summary, ident.summary())
    if args.report:
        from oga.identify.report import identify_report

        write_text(args.report, identify_report(ident))
    for a, f in ident.fits.items():
        v = f.values
        print(f"{a}: mass {v['mass_kg']:.1f} kg{'' if f.mass_identified else ' (base)'}, "
              f"Kv {v['kv_n_s_m']:.4g} N s/m, Tn {v['tn_s'] * 1e3:.2f} ms, "
              f"lag {v['force_lag_s'] * 1e3:.3f} ms, Coulomb {v['coulomb_n']:.1f} N, "
              f"static {v['static_n']:.1f} N, Stribeck {v['stribeck_m_s'] * 1e3:.3g} mm/s, "
              f"viscous {v['viscous_n_s_m']:.0f} N s/m, dead time {f.dead_time_samples:.4g}"
              f"{f' (+{f.lag_samples} logging lag)' if f.lag_samples else ''}: residual "
              f"{f.residual_rms_m * 1e6:.3f} um RMS (noise {f.noise_rms_m * 1e6:.3f} um), "
              f"{f.status}")
        if f.status != "ok":
            print(f"{a}: model error: residual {f.noise_ratio:.3g} times the noise, correlated "
                  f"over {f.correlation_samples:.3g} samples, {f.model_error_share:.3g} of the "
                  "velocity loop's imprint unexplained"
                  + (f", on a physical bound: {', '.join(f.at_bounds)}" if f.at_bounds else ""))
        if a in ident.holdout:
            h = ident.holdout[a]
            print(f"{a}: held out last {h['fraction']:.0%}: predicted {h['rms_heldout_m'] * 1e6:.3f} um"
                  f" RMS (fitted part {h['rms_fit_m'] * 1e6:.3f} um)")
    print(f"{ident.status}, {ident.time_s:.1f} s -> {args.out}")
    if ident.status == "model-error":
        print("warning: the model explains the trace only in part: the uncertainty section is "
              "widened by the evidence (robust tables hold on the wider set)")
    elif ident.status != "ok":
        print("warning: the model does not cover the plant (residual far above the noise): a "
              "table certified on this file promises nothing on the machine")
    return 1 if ident.status == "poor" else 0
