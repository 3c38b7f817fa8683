"""Gain-law jobs (``oga law`` as a job): their stored form, their check and their run.

A law job stores its programs as one JSON text in the job's toolpath field, with the format
``law`` (:data:`LAW_FORMAT`), and its options; its result is the summary and a zip of the
controller files (:func:`oga.law.export.law_files`).
"""

from __future__ import annotations

import io
import json
import zipfile

from oga import defaults
from oga.errors import OptionError
from oga.model.machine import Machine

__all__ = ["LAW_FORMAT", "is_law", "law_job", "check_law", "run_law"]

#: The stored toolpath format of a law job.
LAW_FORMAT = "law"


def is_law(row) -> bool:
    """Whether a stored job searches a gain law."""
    return row.toolpath_format == LAW_FORMAT


def law_job(body) -> tuple[str, dict]:
    """The stored programs (JSON text) and options of an :class:`api.schemas.LawRequest`."""
    programs = [{"name": p.name or f"program{i + 1}", "format": p.format, "content": p.content}
                for i, p in enumerate(body.programs)]
    options = body.model_dump(mode="json", exclude={"programs", "machine"})
    return json.dumps(programs), options


def check_law(text: str, machine: Machine, options: dict):
    """The job's programs read (``[(name, Path)]``) and its options checked.

    Raises
    ------
    InputError
        A program that cannot be read (named, with line and column), or an option out of
        range (named as the field).
    """
    from feedplan.read import read_toolpath
    from oga.law.law import check_kind
    from oga.law.override import check_overrides

    try:
        check_kind(options["kind"], options["points"])
        check_overrides(options["overrides"])
    except OptionError as err:
        raise OptionError(str(err).removeprefix("--")) from None
    tol = options["tolerance"]
    lo, hi = defaults.TOL_RANGE_M
    if tol is not None and not lo <= tol * 1e-3 <= hi:
        raise OptionError(f"tolerance: must lie within {lo * 1e3:g}..{hi * 1e3:g} mm, got {tol!r}")
    if not any(ax.uncertainty is not None for ax in machine.axes.values()):
        raise OptionError(f"machine: {machine.name!r} has no uncertainty set; a law is "
                          "certified on one")
    programs = json.loads(text)
    names = [p["name"] for p in programs]
    if len(set(names)) != len(names):
        raise OptionError(f"programs: names must differ, got {names}")
    return [(p["name"], read_toolpath(p["content"], p["format"], source=p["name"]))
            for p in programs]


def run_law(text: str, machine: Machine, options: dict, progress=None) -> tuple[dict, bytes]:
    """Search and certify the job's law; returns its summary and the zip of its files."""
    from oga.law.export import law_files
    from oga.law.run import law_optimize
    from oga.search.robust.plants import scenario_set

    paths = check_law(text, machine, options)
    tol_m = defaults.TOL_M if options["tolerance"] is None else options["tolerance"] * 1e-3
    res = law_optimize(paths, machine, options["kind"], options["points"],
                       overrides=options["overrides"], tol_m=tol_m, progress=progress,
                       threads=1)  # one thread per job: jobs run side by side
    files = law_files(res, machine.name, len(scenario_set(machine)), units=options["units"])
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, body in sorted(files.items()):
            z.writestr(name, body)
    summary = {"programs": [n for n, _ in paths], "machine": machine.name,
               "overrides": list(options["overrides"]), "files": sorted(files), **res.summary()}
    return summary, buf.getvalue()
