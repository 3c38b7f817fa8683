"""Wire shapes of the REST API: request and response bodies, and the error body."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from api.store import JobRow, is_identification
from oga.options import OptimizeOptions

__all__ = [
    "ToolpathIn",
    "SetpointsIn",
    "JobRequest",
    "TraceIn",
    "IdentifyRequest",
    "ErrorBody",
    "JobAccepted",
    "JobOut",
    "JobPage",
    "MachineInfo",
    "MachineList",
    "Health",
    "Stalled",
    "TableFormat",
    "error_body",
    "job_out",
    "json_safe",
]

#: Formats of ``GET /v1/jobs/{id}/table`` (``oga.export.TABLE_FORMATS``, and ``linuxcnc``).
TableFormat = Literal["csv", "json", "npz", "c", "linuxcnc"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ToolpathIn(_Strict):
    """The program to optimise, as text."""

    format: Literal["gcode", "csv", "json"] = Field(
        description="gcode (RS274/LinuxCNC), csv or json polyline")
    content: str = Field(min_length=1, description="the program text (UTF-8)")
    name: str = Field("", max_length=255, description="program name, for messages and the summary")


class SetpointsIn(_Strict):
    """Setpoints another interpolator produced, to optimise on instead of a planned toolpath
    (``oga optimize --setpoints``: :mod:`oga.recorded`)."""

    format: Literal["csv", "halsampler", "twincat"] = Field(
        description="csv (t_s, <a>_cmd_m, optional <a>_ff_vel_m_s, line, rapid), halsampler "
        "(LinuxCNC's joint.N.motor-pos-cmd per servo period, read with pid's law: an oga "
        "lcnc-record recording, or columns named by `columns`) or twincat (Scope View export)")
    content: str = Field(min_length=1, description="the file's text (UTF-8)")
    name: str = Field("", max_length=255, description="file name, for messages and the summary")
    columns: list[Annotated[str, Field(max_length=64)]] | None = Field(
        None, max_length=64, description="halsampler/twincat: column names in order")
    units: Literal["m", "mm", "inch"] | None = Field(
        None, description="length unit of the file (default: an lcnc-record header's, else m)")
    error_previous_target: bool | None = Field(
        None, description="halsampler without header: pid.N.error-previous-target (default "
        "true)")

    def read_options(self) -> dict:
        """The reading options of :func:`oga.recorded.read_setpoints`."""
        return {"columns": self.columns, "units": self.units,
                "error_previous_target": self.error_previous_target}


class JobRequest(_Strict):
    """Body of ``POST /v1/jobs`` and ``POST /v1/gain-table``: a ``toolpath`` to plan, or
    ``setpoints`` recorded from another interpolator (exactly one)."""

    toolpath: ToolpathIn | None = Field(None, description="the program to plan and optimise")
    setpoints: SetpointsIn | None = Field(
        None, description="instead of a toolpath: setpoints to optimise on as they are")
    machine: str | dict[str, Any] = Field(
        "ucp710", description="a preset name (GET /v1/machines) or a machine object "
        "(the fields of GET /v1/machines/{name})")
    options: OptimizeOptions = Field(
        default_factory=OptimizeOptions,
        description="the options of `oga optimize` (np, knot, lam, anchor, adjust, gains, baseline, "
        "kp_range, nominal, certify, threads, feed in mm/min, tolerance in mm; reader: auto, "
        "builtin or linuxcnc, the G-code reader; tool_table: the text of a LinuxCNC tool table, "
        "mm), same defaults but threads (one per job unless given): a machine with an "
        'uncertainty set (ucp710) gets the robust search and its certificate unless "nominal": '
        "true")

    @model_validator(mode="after")
    def _one_input(self):
        if (self.toolpath is None) == (self.setpoints is None):
            raise ValueError("give a toolpath or setpoints, one of them")
        return self


class TraceIn(_Strict):
    """A recorded trace of the position loop, as text (``oga identify``'s formats)."""

    format: Literal["csv", "halsampler", "twincat"] = Field(
        "csv", description="csv (header t_s, <a>_cmd_m, <a>_act_m, ...), halsampler "
        "(whitespace columns named by `columns`) or twincat (Scope View CSV export)")
    content: str = Field(min_length=1, description="the trace text (UTF-8)")
    name: str = Field("", max_length=255, description="trace name, for messages and the summary")


#: Gains active while recording: one value for every axis, or per axis.
_Gain = float | dict[Literal["x", "y", "z"], float] | None


class IdentifyRequest(_Strict):
    """Body of ``POST /v1/identify``: the options of ``oga identify``."""

    trace: TraceIn
    machine: str | dict[str, Any] = Field(
        "ucp710", description="the base machine (starting values, limits, gain settings): a "
        "preset name or a machine object")
    kp: _Gain = Field(None, description="Kp while recording, (m/min)/mm, where the trace has "
                      "no <a>_kp_m_min_per_mm column")
    kf: _Gain = Field(None, description="Kf while recording, where the trace has no <a>_kf column")
    units: Literal["m", "mm"] = Field("m", description="lengths in the trace")
    columns: list[Annotated[str, Field(max_length=64)]] | None = Field(
        None, max_length=64, description="halsampler/twincat: channel names in order, e.g. "
        "[sample, x_cmd_m, x_act_m]")
    axes: list[Literal["x", "y", "z"]] | None = Field(
        None, min_length=1, max_length=3, description="axes to fit (default every axis moved)")
    name: str | None = Field(None, max_length=255, description="name of the identified machine")
    holdout: float = Field(0.0, ge=0.0, lt=0.9, description="held-out check: refit without the "
                           "trace's last fraction and predict it (costs a second fit)")


class ErrorBody(BaseModel):
    """Every 4xx/5xx answer, and the ``error`` of a failed job."""

    message: str
    type: str | None = Field(None, description="error class, e.g. GcodeError, OptionError")
    line: int | None = Field(None, description="1-based line of the toolpath, when known")
    column: int | None = Field(None, description="1-based column of the toolpath, when known")
    violations: list[str] | None = Field(None, description="failed checks of a verification")


class JobAccepted(BaseModel):
    id: str
    status: str


class JobOut(BaseModel):
    """A job as the API shows it."""

    id: str
    status: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float = Field(description="fraction of the job done (planning, the best fixed "
                            "gains, the search), 0..1")
    error: dict[str, Any] | None = Field(description="null, or an ErrorBody")
    created_at: str
    started_at: str | None
    finished_at: str | None
    source: str = Field(description="program name")
    toolpath_format: str = Field(description="gcode, csv or json for an optimisation "
                                 "(setpoints-csv, setpoints-halsampler or setpoints-twincat on "
                                 "recorded setpoints); trace-csv, trace-halsampler or "
                                 "trace-twincat for an identification")
    machine: str = Field(description="machine name")
    options: dict[str, Any]
    attempts: int = Field(description="times a worker started this job")
    links: dict[str, str]


class JobPage(BaseModel):
    items: list[JobOut]
    total: int
    limit: int
    offset: int
    next_offset: int | None = Field(description="offset of the next page, null on the last")


class MachineInfo(BaseModel):
    name: str
    source: str
    axes: list[str]
    sha256: str


class MachineList(BaseModel):
    items: list[MachineInfo]


class Stalled(BaseModel):
    job: str = Field(description="id of the running job")
    worker_pid: int
    seconds: float = Field(description="time since its progress last moved, s")


class Health(BaseModel):
    status: Literal["ok", "degraded"] = Field(
        description="degraded: a running job has made no progress for the server's stall time")
    version: str
    workers_alive: int
    jobs: dict[str, int]
    stalled: list[Stalled] = Field(description="jobs without progress for the stall time")


def error_body(err: BaseException) -> dict:
    """The error body of a project exception (line/column when the error has them)."""
    body: dict[str, Any] = {"message": str(err), "type": type(err).__name__}
    for key in ("line", "column"):
        value = getattr(err, key, 0)
        if value:
            body[key] = int(value)
    return body


def job_out(row: JobRow) -> dict:
    """The API view of a stored job."""
    base = f"/v1/jobs/{row.id}"
    return {
        "id": row.id,
        "status": row.status,
        "progress": row.progress,
        "error": row.error,
        "created_at": row.created_at,
        "started_at": row.started_at,
        "finished_at": row.finished_at,
        "source": row.source,
        "toolpath_format": row.toolpath_format,
        "machine": row.machine.get("name", ""),
        "options": row.options,
        "attempts": row.attempts,
        "links": {"self": base, "summary": f"{base}/summary",
                  **({"machine": f"{base}/machine"} if is_identification(row)
                     else {"table": f"{base}/table"})},
    }


def json_safe(value):
    """``value`` with every non-finite float replaced by None (JSON has no inf/nan)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


class LawRequest(_Strict):
    """Body of ``POST /v1/law``: the options of ``oga law``."""

    programs: list[ToolpathIn] = Field(min_length=1, max_length=32,
                                       description="the programs the machine runs")
    machine: str | dict[str, Any] = Field(
        "ucp710", description="a preset name or a machine object, with an uncertainty set")
    kind: Literal["mac", "pl", "lincurve", "lincurve-sa"] = Field(
        "lincurve", description="mac: Heidenhain (Kp, Kf over |v| and |a|); pl: TwinCAT CNC "
        "dynamic Kv (Kp over |v|, Kf constant); lincurve: LinuxCNC (Kp, Kf over |v|); "
        "lincurve-sa: LinuxCNC (Kp over |v|, Kf over a sign(v))")
    points: int | None = Field(None, description="support points per input (default mac 3, "
                               "pl 2, lincurve 4, lincurve-sa 8)")
    overrides: list[float] = Field([0.5, 0.8, 1.0, 1.2], min_length=1, max_length=8,
                                   description="feed overrides (shares), 1 among them")
    tolerance: float | None = Field(None, description="interpolation tolerance, mm")
    units: Literal["mm", "inch"] = Field("mm", description="LinuxCNC machine units")
