"""Helpers shared by the sub-commands: common flags, reading inputs, writing outputs."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path as FilePath

from oga.defaults import (ANCHOR, GCODE_READER, GCODE_READERS, NP, ROBUST_ANCHOR_RETRY,
                          ROBUST_MC_PLANTS, TOL_M)
from oga.errors import InputError, OgaError, OptionError

__all__ = [
    "add_base_machine_arg",
    "add_plan_args",
    "add_search_args",
    "add_toolpath_args",
    "check_files",
    "flag_message",
    "load_inputs",
    "options_from_args",
    "output_file",
    "output_folder",
    "toolpath_message",
    "write_json",
    "write_text",
]


def add_toolpath_args(p: argparse.ArgumentParser, *, toolpath_required: bool = True) -> None:
    """Flags every toolpath command shares: TOOLPATH, --machine, --feed, --tolerance."""
    p.add_argument("toolpath", nargs=None if toolpath_required else "?", metavar="TOOLPATH",
                   help="G-code (.ngc/.nc/.gcode/.tap), CSV or JSON polyline")
    add_plan_args(p, "the program's")


def add_plan_args(p: argparse.ArgumentParser, whose: str) -> None:
    """``--machine``, ``--feed`` (``whose`` F it overrides), ``--tolerance``, ``--reader``,
    ``--tool-table``: what a plan needs."""
    p.add_argument("--machine", default="ucp710", metavar="NAME|FILE",
                   help="machine preset name or machine file (.toml/.json); default ucp710")
    p.add_argument("--feed", type=float, metavar="MM_PER_MIN",
                   help=f"feed override in mm/min (default: {whose} F)")
    p.add_argument("--tolerance", type=float, default=None, metavar="MM",
                   help=f"interpolation tolerance in mm (default {TOL_M * 1e3:g})")
    p.add_argument("--reader", default=None, choices=GCODE_READERS,
                   help="G-code reader: builtin (the dialect of CAM posts), linuxcnc "
                        "(LinuxCNC's own interpreter: cutter compensation, O-words, "
                        f"parameters), auto (default {GCODE_READER}: builtin, and linuxcnc "
                        "for what it does not read)")
    p.add_argument("--tool-table", default=None, metavar="FILE",
                   help="LinuxCNC tool table (lengths in mm) for G43's tool lengths "
                        "(default none: length 0, with a warning)")


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
                   help="weight pulling the gains back to the baseline (0: the paper's cost; "
                        f"default {ANCHOR['full']:g}, and where the robust search certifies no "
                        f"table there, {', then '.join(f'{a:g}' for a in ROBUST_ANCHOR_RETRY)})")
    p.add_argument("--nominal", action="store_true", default=None,
                   help="search the machine's nominal model only (default: where the machine "
                        "has an uncertainty set, as ucp710 has, the robust search and its "
                        "certificate)")
    p.add_argument("--certify", type=int, default=None, metavar="N",
                   help=f"robust search: Monte Carlo plants of the certificate, the set's corners "
                        f"on top (default {ROBUST_MC_PLANTS}; more tighten its confidence bound)")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="threads for the robust search's independent replays (default: the "
                        "available cores; the result does not depend on it)")


def options_from_args(args: argparse.Namespace, fields: tuple[str, ...] = ()):
    """OptimizeOptions from the flags ``fields`` (default: the search flags and --feed,
    --tolerance); OptionError naming the flag and the value given if bad."""
    from oga.options import options_from_dict

    fields = fields or _SEARCH_FLAGS
    given = {name: getattr(args, name, None) for name in fields}
    if given.get("tool_table") is not None:
        given["tool_table"] = _tool_table_text(given["tool_table"])
    return options_from_dict(None, names={name: _flag(name) for name in fields}, **given)


def _tool_table_text(name: str) -> str:
    """The text of the ``--tool-table`` file, checked (InputError naming file:line:column)."""
    from feedplan.gcode import load_tool_table

    if os.path.exists(name) and not os.path.isfile(name):
        raise InputError(f"--tool-table {name}: not a regular file")
    load_tool_table(name)  # ToolpathError / GcodeError naming the file, line and column
    with open(name, encoding="utf-8-sig") as f:
        return f.read()


def _flag(field: str) -> str:
    return "--" + field.replace("_", "-")


def flag_message(err: OptionError) -> OptionError:
    """``err`` with a leading option field (``kp_range: ...``) as its flag (``--kp-range``)."""
    head, sep, rest = str(err).partition(": ")
    if sep and head in _SEARCH_FLAGS:
        return OptionError(f"{_flag(head)}: {rest}")
    return err


#: The flags of add_search_args and add_toolpath_args that are fields of OptimizeOptions.
_SEARCH_FLAGS = ("mode", "baseline", "adjust", "gains", "kp_range", "np", "knot", "lam",
                 "anchor", "nominal", "certify", "threads", "feed", "tolerance", "reader",
                 "tool_table")


def load_inputs(args: argparse.Namespace):
    """(path, machine, feed_m_s or None, tol_m) from the common flags; InputError if bad."""
    from feedplan.read import load_toolpath
    from oga.model.machine import load_machine

    options = options_from_args(args, ("feed", "tolerance", "reader", "tool_table"))
    machine = load_machine(args.machine)
    try:
        setup = machine.gcode_setup(options.tool_table)
        path = load_toolpath(args.toolpath, reader=options.reader, setup=setup)
    except InputError as err:
        raise toolpath_message(err, args.toolpath) from None
    return path, machine, options.feed_m_s, options.tol_m


def toolpath_message(err: InputError, path: str) -> InputError:
    """``err``, raised reading the toolpath file ``path``, as one message naming the file once,
    first: ``path:line:column: what`` (the readers name it after the line, or not at all)."""
    name = FilePath(path).name
    text = getattr(err, "message", str(err))  # GcodeError, ToolpathError: without the place
    for prefix in (f"{path}: ", f"{name}: "):
        text = text.removeprefix(prefix)
    if text.startswith((f"{path}:", f"{name}:")):  # named first already
        return InputError(text)
    line, column = getattr(err, "line", 0), getattr(err, "column", 0)
    where = (f":{line}" + (f":{column}" if column else "")) if line else ""
    return InputError(f"{path}{where}: {text}")


def output_file(option: str, target: str) -> FilePath:
    """Check, before any work, that the file ``target`` of ``option`` can be written.

    Its folder must exist (oga creates no folders for a file), the name must not be a
    folder or a special file, and the folder must accept the temporary file that
    :func:`write_text` writes first. InputError naming the option, the path and the
    problem otherwise.
    """
    if not target:
        raise InputError(f"{option}: empty file name")
    path = FilePath(target)
    if os.path.isdir(path):  # os.path's tests: False, never OSError, on a bad name
        raise InputError(f"{option} {target}: is a folder, give a file name")
    if os.path.lexists(path) and not os.path.isfile(path):
        raise InputError(f"{option} {target}: not a regular file")
    folder = path.parent
    if not os.path.isdir(folder):
        what = (f"{folder} is not a folder" if os.path.lexists(folder)
                else f"folder {folder} does not exist (oga creates none)")
        raise InputError(f"{option} {target}: {what}")
    _probe(option, target, folder, f".{path.name}.")
    return path


def output_folder(option: str, target: str) -> FilePath:
    """Check the output folder ``target`` of ``option``; create it (not its parents) if missing."""
    if not target:
        raise InputError(f"{option}: empty folder name")
    path = FilePath(target)
    if os.path.lexists(path) and not os.path.isdir(path):
        raise InputError(f"{option} {target}: not a folder")
    if not os.path.isdir(path):
        parent = path.absolute().parent
        if not os.path.isdir(parent):
            raise InputError(f"{option} {target}: its parent folder {parent} does not exist "
                             f"(oga creates {path.name} only)")
        try:
            path.mkdir()
        except OSError as err:
            raise InputError(f"{option} {target}: cannot create the folder ({err.strerror})"
                             ) from None
    _probe(option, target, path, ".oga-probe.")
    return path


def _probe(option: str, target: str, folder: FilePath, prefix: str) -> None:
    """InputError unless a file named ``prefix...`` can be created in ``folder`` (then removed)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=prefix, suffix=".part")
    except OSError as err:
        raise InputError(f"{option} {target}: cannot write in {folder} ({err.strerror})"
                         ) from None
    os.close(fd)
    os.unlink(tmp)


def check_files(args: argparse.Namespace, *names: str) -> None:
    """Before any work: the input files given (TOOLPATH, a --machine file) are regular files
    (a FIFO or a device would block or never end), and each output option given
    (``args.<name>``, flag ``--<name>``) can be written and names a file of its own,
    neither another output nor an input."""
    seen = {}
    for name, label in (("toolpath", "TOOLPATH"), ("setpoints", "--setpoints"),
                        ("machine", "--machine")):
        value = getattr(args, name, None)
        if value and os.path.exists(value):
            if not os.path.isfile(value):
                raise InputError(f"{label} {value}: not a regular file")
            seen[os.path.realpath(value)] = f"the {label} file"
    for name in names:
        value = getattr(args, name)
        if value is None:
            continue
        option = _flag(name)
        key = os.path.realpath(output_file(option, value))
        if key in seen:
            raise InputError(f"{option} {value}: the same file as {seen[key]}")
        seen[key] = option


def write_text(target: str | os.PathLike, text: str) -> None:
    """Write ``text`` atomically (temporary file in the same folder, then rename).

    The folder must exist (checked beforehand by :func:`output_file`); a failure to write
    (disk full, folder removed meanwhile) is an OgaError naming the file, and leaves no
    temporary file behind.
    """
    target = FilePath(target)
    try:
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".part")
    except OSError as err:
        raise OgaError(f"cannot write {target}: {err.strerror}") from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual file mode
        os.replace(tmp, target)
    except BaseException as err:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(err, OSError):
            raise OgaError(f"cannot write {target}: {err.strerror}") from None
        raise


def write_json(target: str | os.PathLike, data: dict) -> None:
    """Write ``data`` as indented JSON, atomically."""
    write_text(target, json.dumps(data, indent=2, sort_keys=False) + "\n")
