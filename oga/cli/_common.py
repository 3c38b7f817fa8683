"""Helpers shared by the sub-commands: common flags, reading inputs, writing outputs."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path as FilePath

from oga.defaults import NP
from oga.errors import InputError

__all__ = [
    "add_base_machine_arg",
    "add_search_args",
    "add_toolpath_args",
    "load_inputs",
    "options_from_args",
    "write_json",
    "write_text",
]


def add_toolpath_args(p: argparse.ArgumentParser, *, toolpath_required: bool = True) -> None:
    """Flags every toolpath command shares: TOOLPATH, --machine, --feed, --tolerance."""
    p.add_argument("toolpath", nargs=None if toolpath_required else "?", metavar="TOOLPATH",
                   help="G-code (.ngc/.nc/.gcode/.tap), CSV or JSON polyline")
    p.add_argument("--machine", default="ucp710", metavar="NAME|FILE",
                   help="machine preset name or machine file (.toml/.json); default ucp710")
    p.add_argument("--feed", type=float, metavar="MM_PER_MIN",
                   help="feed override in mm/min (default: the program's F)")
    p.add_argument("--tolerance", type=float, default=None, metavar="MM",
                   help="interpolation tolerance in mm (default 0.02)")


def add_base_machine_arg(p: argparse.ArgumentParser, what: str) -> None:
    """``--machine``, the base machine of ``oga excite``/``oga identify`` (``what`` it gives)."""
    p.add_argument("--machine", default="ucp710", metavar="NAME|FILE",
                   help=f"base machine preset or file ({what}); default ucp710")


def add_search_args(p: argparse.ArgumentParser) -> None:
    """The search flags of ``oga optimize`` (names and meaning of the API's options)."""
    p.add_argument("--mode", default=None, choices=("full", "paper"),
                   help="full (default): gain trajectories planned over a receding window; "
                        "paper: the published five-candidate search")
    p.add_argument("--baseline", default=None, metavar="best|KP,KF",
                   help="fixed gains to start from and compare with (default best)")
    p.add_argument("--adjust", default=None, metavar="AXES",
                   help="axes to adjust, e.g. x,z (default every contouring axis)")
    p.add_argument("--gains", default=None, metavar="kp|kp,kf", help="gains to adjust (default kp,kf)")
    p.add_argument("--kp-range", default=None, metavar="LO,HI",
                   help="Kp bounds in (m/min)/mm for adjusted axes (default the stable range)")
    p.add_argument("--np", type=int, default=None, metavar="N",
                   help=f"prediction horizon, samples (default {NP['paper']} in paper mode, "
                        f"the {NP['full']}-sample window in full mode)")
    p.add_argument("--knot", type=int, default=None, metavar="N",
                   help="full mode: samples between the gain spline's control points "
                        "(default np/10, at least 10)")
    p.add_argument("--lam", type=float, default=None, metavar="L", help="increment weight")
    p.add_argument("--anchor", type=float, default=None, metavar="MU",
                   help="weight pulling the gains back to the baseline (0: the paper's cost)")


def options_from_args(args: argparse.Namespace):
    """OptimizeOptions from the search flags and --feed/--tolerance (OptionError if bad)."""
    from oga.options import options_from_dict

    return options_from_dict(
        None, mode=args.mode, baseline=args.baseline, adjust=args.adjust, gains=args.gains,
        kp_range=args.kp_range, np=args.np, knot=args.knot, lam=args.lam, anchor=args.anchor,
        feed=args.feed, tolerance=args.tolerance,
    )


def load_inputs(args: argparse.Namespace):
    """(path, machine, feed_m_s or None, tol_m) from the common flags; InputError if bad."""
    from feedplan.read import load_toolpath
    from oga.defaults import TOL_M
    from oga.machine import load_machine

    if args.feed is not None and not (0 < args.feed < float("inf")):
        raise InputError(f"--feed must be a positive number of mm/min, got {args.feed}")
    if args.tolerance is not None and not (0 < args.tolerance <= 10):
        raise InputError(f"--tolerance must be in (0, 10] mm, got {args.tolerance}")
    machine = load_machine(args.machine)
    path = load_toolpath(args.toolpath)
    feed_m_s = None if args.feed is None else args.feed / 60e3
    tol_m = TOL_M if args.tolerance is None else args.tolerance * 1e-3
    return path, machine, feed_m_s, tol_m


def write_text(target: str | os.PathLike, text: str) -> None:
    """Write ``text`` atomically (temporary file in the same folder, then rename)."""
    target = FilePath(target)
    if target.parent and not target.parent.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual file mode
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_json(target: str | os.PathLike, data: dict) -> None:
    """Write ``data`` as indented JSON, atomically."""
    write_text(target, json.dumps(data, indent=2, sort_keys=False) + "\n")
