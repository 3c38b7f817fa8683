"""Identification jobs (``POST /v1/identify``): the trace of a job read and checked, and
the fit run, as ``oga identify`` does. Used by the route (checks at submission) and the
worker (the fit)."""

from __future__ import annotations

from api.store import TRACE_PREFIX
from oga.model.machine import Machine

__all__ = ["identify_options", "read_job_trace", "run_identification", "identification_report"]


def identify_options(body) -> dict:
    """The stored options of an :class:`api.schemas.IdentifyRequest`."""
    return body.model_dump(mode="json", exclude={"trace", "machine"})


def read_job_trace(text: str, toolpath_format: str, machine: Machine, options: dict,
                   source: str = ""):
    """The job's trace read and checked, and the axes to fit (``(Trace, list[str])``).

    Raises
    ------
    InputError
        TraceError naming the column and the row; an axis not traced or not a cascade.
    """
    from oga.identify.trace import read_trace
    from oga.identify.workflow import axes_to_fit

    trace = read_trace(text, toolpath_format.removeprefix(TRACE_PREFIX),
                       columns=options["columns"], units=options["units"], kp=options["kp"],
                       kf=options["kf"], te_s=machine.te, source=source)
    return trace, axes_to_fit(trace, machine, options["axes"])


def run_identification(text: str, toolpath_format: str, machine: Machine, options: dict,
                       source: str = "", progress=None):
    """Identify ``machine``'s traced axes from the job's trace
    (:class:`oga.identify.workflow.Identification`), reporting the fraction done to
    ``progress``."""
    from oga.identify.workflow import identify

    trace, axes = read_job_trace(text, toolpath_format, machine, options, source)
    return identify(trace, machine, axes=axes, name=options["name"],
                    holdout_fraction=options["holdout"], progress=progress)


def identification_report(text: str, toolpath_format: str, machine: Machine, options: dict,
                          source: str, summary: dict, toml: bytes) -> str:
    """The fit report (HTML, as ``oga identify --report``) of a succeeded job, rebuilt from
    what it stored: its trace read again, its summary and identified machine file; the
    fitted model is simulated on the trace again, nothing is fitted again."""
    from oga.identify.report import identify_report
    from oga.identify.workflow import identification_from_summary

    trace, _ = read_job_trace(text, toolpath_format, machine, options, source)
    return identify_report(identification_from_summary(summary, trace, machine,
                                                       toml.decode("utf-8")))
