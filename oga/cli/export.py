"""``oga export``: a gain table written by ``oga optimize`` (or the API) as controller files.

``--format linuxcnc`` writes a ``streamer`` data file and HAL files (:mod:`oga.export.linuxcnc`):
with ``--recording`` (the LinuxCNC recording the table was computed on) the production files
for LinuxCNC's motion controller (:mod:`oga.export.linuxcnc.motion`), else the bench stream.
The table is a ``.csv`` (``oga optimize --out``), ``.json`` or ``.npz`` (the API's formats,
with their metadata); the summary JSON (``--summary``) gives the fixed baseline gains the
loops fall back to and must hash to the same program and machine.
"""

from __future__ import annotations

import argparse
import io
import json
import types
from pathlib import Path as FilePath

import numpy as np

from oga.cli._common import output_folder, write_text
from oga.defaults import TABLE_MAX_BYTES
from oga.errors import InputError
from oga.files import read_limited

__all__ = ["register", "run", "read_table", "parse_joints"]


def register(sub: argparse._SubParsersAction) -> None:
    from oga.defaults import LINUXCNC, LINUXCNC_MOTION

    p = sub.add_parser(
        "export",
        help="write a gain table as controller files (LinuxCNC streamer + HAL)",
        description="Write a verified gain table as the files a controller runs. "
        "linuxcnc: a streamer data file (per axis position command, command-deriv, Pgain, "
        "FF1, one line per servo period) and HAL files wiring it to pid.N.",
    )
    p.add_argument("table", metavar="TABLE", help="gain table: .csv (oga optimize --out), "
                   ".json or .npz (GET /v1/jobs/ID/table)")
    p.add_argument("--format", default="linuxcnc", choices=("linuxcnc",),
                   help="controller (default linuxcnc)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write the files to")
    p.add_argument("--summary", metavar="SUMMARY.json",
                   help="the table's summary (oga optimize --summary): baseline gains, hashes")
    p.add_argument("--baseline", metavar="KP,KF",
                   help="fixed gains to fall back to, (m/min)/mm and factor (default: the "
                        "summary's)")
    p.add_argument("--machine", metavar="NAME|FILE",
                   help="machine for --with-feedback (default: the one the table names)")
    p.add_argument("--with-feedback", action="store_true",
                   help="also stream the simulated actual positions (bench check)")
    p.add_argument("--units", default=LINUXCNC["units"], choices=("mm", "inch"),
                   help=f"machine units (default {LINUXCNC['units']})")
    p.add_argument("--error-previous-target", default=None, choices=("true", "false"),
                   help="pid.N.error-previous-target (default true, LinuxCNC's)")
    p.add_argument("--axes", metavar="AXES", help="axes to export, e.g. x,z (default: the "
                   "axes the table moves)")
    p.add_argument("--joints", metavar="A=N,...",
                   help="pid loop per axis, e.g. x=0,z=1 (default 0, 1, ... in x, y, z order)")
    p.add_argument("--thread", default=LINUXCNC["thread"], metavar="NAME",
                   help=f"HAL thread (default {LINUXCNC['thread']})")
    g = p.add_argument_group("production on LinuxCNC's motion controller")
    g.add_argument("--recording", metavar="REC",
                   help="the LinuxCNC recording the table was computed on (oga lcnc-record; "
                        "oga optimize --setpoints REC): write oga_table.tcl, its stream and "
                        "feeder, which drive only Pgain and FF1 while the motion is the "
                        "recorded one")
    g.add_argument("--pos-tol-um", type=float, default=None, metavar="UM",
                   help=f"fall back once a joint's command leaves the row by more (default "
                        f"{LINUXCNC_MOTION['pos_tol_m'] * 1e6:g})")
    g.add_argument("--vel-tol-um-s", type=float, default=None, metavar="UM_S",
                   help=f"fall back once motion.current-vel leaves the row's by more (default "
                        f"{LINUXCNC_MOTION['vel_tol_m_s'] * 1e6:g})")
    p.set_defaults(func=run)


def _csv_table(path: FilePath, blob: bytes):
    from oga.export.table import GainTable
    from oga.search.result import setpoints_digest

    text = blob.decode("utf-8", errors="replace")
    header = tuple(text.split("\n", 1)[0].strip().split(","))
    if header[:1] != ("t_s",):
        raise InputError(f"{path.name}:1: not a gain table (its header must start with t_s)")
    try:
        data = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, ndmin=2)
    except ValueError as err:
        raise InputError(f"{path.name}: {err}") from None
    if data.shape[1] != len(header) or len(data) < 2:
        raise InputError(f"{path.name}: expected at least 2 rows of {len(header)} columns, "
                         f"got {data.shape[0]} of {data.shape[1]}")
    t = data[:, 0]
    meta = {"sample_period_s": float(t[1] - t[0])}
    try:
        pos = np.column_stack([data[:, header.index(f"{a}_pos_m")] for a in "xyz"])
    except ValueError:
        pass  # the exporter names the missing column
    else:
        meta["setpoints_sha256"] = setpoints_digest(
            types.SimpleNamespace(dt=meta["sample_period_s"], pos=pos))
    return GainTable(header=header, data=data, meta=meta)


def read_table(path) -> "GainTable":  # noqa: F821
    """A gain table file (``.csv``, ``.json`` or ``.npz``) as a GainTable (InputError if bad)."""
    from oga.export.table import GainTable, table_from_npz

    path = FilePath(path)
    blob = read_limited(path, TABLE_MAX_BYTES, InputError, "table")
    suffix = path.suffix.lower()
    try:
        if suffix == ".csv":
            return _csv_table(path, blob)
        if suffix == ".npz":
            return table_from_npz(blob)
        if suffix == ".json":
            doc = json.loads(blob)
            meta = doc["meta"]
            header = tuple(meta["columns"])
            data = np.column_stack([np.asarray(doc["columns"][c], dtype=np.float64)
                                    for c in header])
            return GainTable(header=header, data=data, meta=meta)
    except InputError:
        raise
    except (ValueError, KeyError, TypeError, OSError) as err:
        raise InputError(f"{path.name}: not a gain table: {err}") from None
    raise InputError(f"{path.name}: unknown table type {suffix!r} (expected .csv, .json, .npz)")


def _pair(text: str, flag: str) -> tuple[float, float]:
    try:
        kp, kf = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"{flag}: expected KP,KF, got {text!r}") from None
    return kp, kf


def parse_joints(text: str) -> dict[str, int]:
    """``--joints x=0,z=1`` as a dict (InputError if malformed)."""
    try:
        return {a.strip(): int(j) for a, j in (item.split("=") for item in text.split(","))}
    except ValueError:
        raise InputError(f"--joints: expected e.g. x=0,z=1, got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    from oga.export.linuxcnc import export_table
    from oga.model.machine import load_machine

    if not (args.summary or args.baseline):
        raise InputError("the loops fall back to the fixed baseline gains: give --summary "
                         "SUMMARY.json (oga optimize --summary) or --baseline KP,KF")
    table = read_table(args.table)
    summary = None
    if args.summary:
        try:
            summary = json.loads(read_limited(args.summary, TABLE_MAX_BYTES, InputError, "summary"))
        except ValueError as err:
            raise InputError(f"{args.summary}: not JSON: {err}") from None
        if not isinstance(summary, dict):
            raise InputError(f"{args.summary}: not a summary (expected an object)")
        for key in ("toolpath", "machine", "machine_sha256"):  # a CSV table has no metadata
            if summary.get(key):
                table.meta.setdefault(key, summary[key])
    table.meta.setdefault("toolpath", FilePath(args.table).name)
    if args.recording:
        return _run_motion(args, table, summary)
    for flag in ("pos_tol_um", "vel_tol_um_s"):
        if getattr(args, flag) is not None:
            raise InputError(f"--{flag.replace('_', '-')}: applies with --recording only")
    machine = None
    if args.with_feedback:
        name = args.machine or table.meta.get("machine")
        if not name:
            raise InputError("--with-feedback: name the machine (--machine), or give --summary")
        machine = load_machine(name)
    export = export_table(
        table, summary=summary, machine=machine, with_feedback=args.with_feedback,
        baseline=_pair(args.baseline, "--baseline") if args.baseline else None,
        units=args.units, thread=args.thread,
        error_previous_target=None if args.error_previous_target is None
        else args.error_previous_target == "true",
        axes=args.axes.split(",") if args.axes else None,
        joints=parse_joints(args.joints) if args.joints else None)
    out = output_folder("--out", args.out)  # DIR is created (not its parents) once all is read
    for name, text in export.files.items():
        write_text(out / name, text)
    loops = ", ".join(f"{a} -> pid.{export.joints[a]}" for a in export.axes)
    print(f"linuxcnc: {export.rows} rows ({loops}), {export.units}, error-previous-target "
          f"{'TRUE' if export.error_previous_target else 'FALSE'}, servo period "
          f"{export.period_ns} ns" + (", simulated feedback" if args.with_feedback else "")
          + f" -> {out}/")
    return 0


def _run_motion(args: argparse.Namespace, table, summary) -> int:
    """``oga export --recording``: the production files (:func:`oga.export.linuxcnc.motion_export`)."""
    from oga.identify.trace import TraceError
    from oga.export.linuxcnc.export import baseline_gains
    from oga.export.linuxcnc.motion import motion_export
    from oga.recorded import read_setpoints, read_setpoints_file

    for flag, given in (("--with-feedback", args.with_feedback),
                        ("--error-previous-target", args.error_previous_target is not None),
                        ("--axes", args.axes is not None)):
        if given:
            raise InputError(f"{flag}: not with --recording (the recording sets it)")
    te = table.meta.get("sample_period_s")
    try:
        text, fmt = read_setpoints_file(args.recording)
        recorded = read_setpoints(text, None, fmt, source=FilePath(args.recording).name,
                                  te_s=te)
    except TraceError as err:
        raise InputError(f"--recording {args.recording}: {err}") from None
    base_kp, base_kf = baseline_gains(
        table, summary, _pair(args.baseline, "--baseline") if args.baseline else None)
    export = motion_export(
        table, base_kp, base_kf, recorded,
        joints=parse_joints(args.joints) if args.joints else None,
        pos_tol_m=None if args.pos_tol_um is None else args.pos_tol_um * 1e-6,
        vel_tol_m_s=None if args.vel_tol_um_s is None else args.vel_tol_um_s * 1e-6)
    out = output_folder("--out", args.out)
    for name, text in export.files.items():
        write_text(out / name, text)
    joints = ", ".join(f"{a} -> joint {export.joints[a]}" for a in export.axes)
    print(f"linuxcnc (motion): {export.rows} rows ({joints}), {export.units}, servo period "
          f"{export.period_ns} ns -> {out}/ (HALFILE = oga_table.tcl)")
    return 0
