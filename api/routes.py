"""The ``/v1`` routes: jobs, their tables and summaries, the synchronous gain table, machines.

Handlers are plain functions run in the thread pool (database and formatting
work). The CPU-bound ones run one at a time per kind (``api.app.CPU_WORK``: reading a
submitted toolpath or trace; rendering a report or a table): in more threads they would
only contend for the GIL, and ``/healthz`` and the light routes would wait behind a burst
of them. The synchronous gain table waits for its job without holding a thread. No
handler optimises: the worker processes do.
"""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import PurePath

import anyio
import numpy as np
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import HTMLResponse, JSONResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException

from api.schemas import (
    ErrorBody,
    IdentifyRequest,
    JobAccepted,
    JobOut,
    JobPage,
    JobRequest,
    LawRequest,
    MachineList,
    TableFormat,
    job_out,
)
from api.store import FINISHED, STATUSES, TRACE_PREFIX, JobRow, Store, is_identification
from feedplan.setpoints import AXES
from oga.errors import MachineError, ToolpathError
from oga.export.table import C_NAME, TABLE_FORMATS, render_table, table_from_npz
from oga.model.machine import PRESETS, Machine, load_machine, machine_from_dict

__all__ = ["router"]

router = APIRouter(prefix="/v1")

_ERRORS = {
    404: {"model": ErrorBody, "description": "no such job or machine"},
    409: {"model": ErrorBody, "description": "the job is not in a state that allows this"},
    413: {"model": ErrorBody, "description": "upload too large"},
    422: {"model": ErrorBody, "description": "invalid input (line and column for a toolpath)"},
}
#: Answers of the routes that read a JSON body.
_BODY_ERRORS = {
    **_ERRORS,
    413: {"model": ErrorBody, "description": "upload too large, or the toolpath's motion too long"},
    415: {"model": ErrorBody, "description": "the body is not application/json (or is compressed)"},
}


def _store(request: Request) -> Store:
    return request.app.state.store


async def _cpu(request: Request, kind: str, fn, *args):
    """``fn(*args)`` in a thread, one at a time with the other CPU work of its ``kind``."""
    return await anyio.to_thread.run_sync(
        fn, *args, limiter=request.app.state.cpu_limiters[kind])


def _result(request: Request, row, what: str) -> bytes:
    """A succeeded job's stored result; 409 naming ``what`` until the job has one."""
    blob = _store(request).table(row.id)
    if row.status != "succeeded" or blob is None:
        raise HTTPException(409, f"job {row.id} is {row.status}: no {what}")
    return blob


def _job(request: Request, job_id: str) -> JobRow:
    row = _store(request).get(job_id)
    if row is None:
        raise HTTPException(404, f"no job {job_id!r}")
    return row


def _machine(spec: str | dict) -> Machine:
    """A preset by name (never a server file) or a machine object."""
    if isinstance(spec, str):
        if spec not in PRESETS:
            raise MachineError(f"machine: unknown preset {spec!r} (presets: {', '.join(PRESETS)})")
        return load_machine(spec)
    return machine_from_dict(spec)


def _duration(seconds: float) -> str:
    return (f"{seconds:.1f} s" if seconds < 1e7 else f"{seconds:.2g} s" if math.isfinite(seconds)
            else "longer than any limit")


def _check_motion(path, machine, feed_m_s: float | None, limit_s: float, *, where: str = "",
                  advice: str = "") -> None:
    """Refuse a toolpath whose motion would take longer than ``limit_s`` (413), before
    anything is planned: the planner's own lower bound
    (:func:`feedplan.plan.move_times_s`). ``where`` and ``advice`` complete the message.
    """
    from feedplan.plan import move_times_s

    seconds = move_times_s(path, machine.planning_limits(), feed_m_s)
    total = float(np.sum(seconds))
    if total > limit_s:
        k = int(np.argmax(seconds))
        raise HTTPException(
            413, f"toolpath too long{where}: about {_duration(total)} of motion at the "
            f"programmed feeds (the longest move, line {path.segments[k].line}, "
            f"{_duration(float(seconds[k]))}); the limit is {limit_s:g} s{advice}")


def _accept(request: Request, body: JobRequest, sync: bool) -> JobRow:
    """Validate a request (toolpath read, machine checked, motion time bounded) and queue
    its job. A synchronous job has its own, shorter motion-time limit and goes ahead of the
    queue.
    """
    from oga.pipeline import read_program

    machine = _machine(body.machine)
    if body.setpoints is not None:
        return _accept_setpoints(request, body, machine, sync)
    tp = body.toolpath
    path = read_program(tp.content, tp.format, machine, body.options, source=tp.name)
    if not path.segments:
        raise ToolpathError("toolpath: the program has no moves")
    settings = request.app.state.settings
    if sync:
        _check_motion(path, machine, body.options.feed_m_s, settings.sync_max_motion_s,
                      where=" for the synchronous endpoint",
                      advice="; submit it with POST /v1/jobs instead")
    else:
        _check_motion(path, machine, body.options.feed_m_s, settings.job_max_motion_s,
                      advice=" (the server's --job-max-motion-s)")
    return _store(request).submit(
        source=tp.name, toolpath_format=tp.format, toolpath=tp.content,
        machine=machine.model_dump(mode="json", exclude_none=True), options=body.options.as_dict(),
        priority=1 if sync else 0)


def _accept_setpoints(request: Request, body: JobRequest, machine: Machine, sync: bool) -> JobRow:
    """:func:`_accept` of recorded setpoints: read and checked now (422 naming the column and
    the row), their duration bounded as a toolpath's motion."""
    from oga.errors import OptionError
    from oga.pipeline import SETPOINTS_PREFIX
    from oga.recorded import read_setpoints

    sp_in = body.setpoints
    if body.options.feed_m_s is not None:
        raise OptionError("feed: recorded setpoints are optimised as recorded (their "
                          "interpolator applied its feeds)")
    rec = read_setpoints(sp_in.content, machine, sp_in.format, source=sp_in.name,
                         **sp_in.read_options())
    settings = request.app.state.settings
    limit = settings.sync_max_motion_s if sync else settings.job_max_motion_s
    seconds = rec.setpoints.duration
    if seconds > limit:
        raise HTTPException(413, f"setpoints too long: {_duration(seconds)} of motion; the "
                            f"limit is {limit:g} s" + (
                                "; submit them with POST /v1/jobs instead" if sync else ""))
    return _store(request).submit(
        source=sp_in.name, toolpath_format=SETPOINTS_PREFIX + sp_in.format,
        toolpath=sp_in.content, machine=machine.model_dump(mode="json", exclude_none=True),
        options={**body.options.as_dict(), "setpoints": sp_in.read_options()},
        priority=1 if sync else 0)


def _no_table(row: JobRow) -> None:
    """409 for an identification or a law job at a route of optimisations."""
    from api.law import is_law

    if is_identification(row):
        raise HTTPException(409, f"job {row.id} identifies a machine: no table "
                            f"(GET /v1/jobs/{row.id}/machine)")
    if is_law(row):
        raise HTTPException(409, f"job {row.id} searches a gain law: no table "
                            f"(GET /v1/jobs/{row.id}/law)")


def _table_response(request: Request, row: JobRow, fmt: str, name: str) -> Response:
    _no_table(row)
    blob = _result(request, row, "table")
    if fmt == "linuxcnc" and row.toolpath_format == "setpoints-halsampler":
        # a table computed on a LinuxCNC recording: the production files (oga export
        # --recording), the recording read again from the job
        from oga.export.linuxcnc import baseline_gains, motion_export
        from oga.pipeline import stored_options
        from oga.recorded import read_setpoints

        table = table_from_npz(blob)
        _, read = stored_options(row.options)
        text = _store(request).get(row.id, with_toolpath=True).toolpath
        rec = read_setpoints(text, None, "halsampler", source=row.source,
                             te_s=table.meta["sample_period_s"], **(read or {}))
        data = motion_export(table, *baseline_gains(table, row.summary), rec).zip_bytes()
        suffix, media = ".zip", "application/zip"
    elif fmt == "linuxcnc":  # a zip of the LinuxCNC files (oga export --format linuxcnc)
        from oga.export.linuxcnc import export_table

        # no simulated feedback: that is a replay, which no handler runs (oga export
        # --with-feedback on the npz table gives it)
        data = export_table(table_from_npz(blob), summary=row.summary).zip_bytes()
        suffix, media = ".zip", "application/zip"
    else:
        data = render_table(table_from_npz(blob), fmt, name=name)
        suffix, media = TABLE_FORMATS[fmt]
    stem = PurePath(row.source).stem or row.id
    return Response(data, media_type=media, headers={
        "Content-Disposition": f'attachment; filename="{_ascii(stem)}{suffix}"',
        "X-Oga-Job-Id": row.id})


def _ascii(text: str) -> str:
    return "".join(c if c.isascii() and c.isprintable() and c not in '"\\' else "_" for c in text)


Name = Annotated[str, Query(max_length=63, pattern=r"^[A-Za-z_][A-Za-z0-9_]*$",
                            description="C identifier prefix (format c)")]


@router.post("/jobs", status_code=202, response_model=JobAccepted, responses=_BODY_ERRORS,
             summary="Submit a toolpath for optimisation")
async def submit_job(body: JobRequest, request: Request, response: Response) -> dict:
    """Queue a job. The toolpath is read at once (422 naming line and column if it is
    malformed); planning and the search run in a worker process. Poll ``GET /v1/jobs/{id}``."""
    row = await _cpu(request, "read", _accept, request, body, False)
    response.headers["Location"] = f"/v1/jobs/{row.id}"
    return {"id": row.id, "status": row.status}


@router.get("/jobs", response_model=JobPage, summary="List jobs, newest first")
def list_jobs(
    request: Request,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**62)] = 0,
    status: Literal[STATUSES] | None = None,  # type: ignore[valid-type]
) -> dict:
    rows, total = _store(request).list(limit=limit, offset=offset, status=status)
    nxt = offset + len(rows)
    return {"items": [job_out(r) for r in rows], "total": total, "limit": limit,
            "offset": offset, "next_offset": nxt if nxt < total else None}


@router.get("/jobs/{job_id}", response_model=JobOut, responses=_ERRORS, summary="A job")
def get_job(job_id: str, request: Request) -> dict:
    return job_out(_job(request, job_id))


@router.delete("/jobs/{job_id}", response_model=JobOut, responses=_ERRORS, summary="Cancel a job")
def cancel_job(job_id: str, request: Request) -> dict:
    """Cancel a queued or running job. A running job's worker process is ended at once
    (and another started); a job run by another server sharing the database stops at its
    next progress report. Cancelling a cancelled job is a no-op; a finished job answers 409."""
    _job(request, job_id)  # 404 for an unknown job
    cancelled = _store(request).cancel(job_id)
    if cancelled is None:
        row = _job(request, job_id)
        if row.status != "cancelled":
            raise HTTPException(409, f"job {job_id} has already {row.status}")
        return job_out(row)
    if request.app.state.pool is not None:
        request.app.state.pool.kill(cancelled)
    return job_out(cancelled)


@router.get("/jobs/{job_id}/table", responses={
    200: {"content": {m: {} for _, m in TABLE_FORMATS.values()},
          "description": "the gain table"}, **_ERRORS}, response_class=Response,
    summary="The gain table of a succeeded job")
async def get_table(job_id: str, request: Request, format: TableFormat = "csv",
                    name: Name = C_NAME) -> Response:
    """``csv`` is byte-identical to ``oga optimize --out``; ``json`` holds the columns and
    the metadata; ``npz`` one float64 array per column; ``c`` a C header for firmware;
    ``linuxcnc`` a zip of the streamer and HAL files (mm, error-previous-target TRUE, no
    simulated feedback; ``oga export`` on the npz table for other settings); for a job on a
    LinuxCNC recording (``setpoints`` in ``halsampler`` format) the production files of
    ``oga export --recording``."""
    row = await run_in_threadpool(_job, request, job_id)
    return await _cpu(request, "render", _table_response, request, row, format, name)


@router.get("/jobs/{job_id}/summary", responses=_ERRORS, summary="The summary of a job")
def get_summary(job_id: str, request: Request) -> dict:
    """As ``oga optimize --summary``; also for a job whose schedule failed verification."""
    row = _job(request, job_id)
    if row.summary is None:
        raise HTTPException(409, f"job {job_id} is {row.status}: no summary")
    return row.summary


@router.get("/jobs/{job_id}/report", responses={
    200: {"content": {"text/html": {}}, "description": "the report, one self-contained page"},
    **{code: {"description": _ERRORS[code]["description"], "content": {"application/json": {
        "schema": {"$ref": "#/components/schemas/ErrorBody"}}}} for code in (404, 409, 422)}},
    response_class=HTMLResponse, summary="The report of a succeeded job")
async def get_report(job_id: str, request: Request) -> Response:
    """As ``oga optimize --report``. Rebuilt from what the job stored: its toolpath is planned
    again (the setpoint hash must match the summary's) and the baseline gains and the stored
    table are replayed on the model; nothing is searched again. 409 until the job has
    succeeded (a failed job stores no schedule to replay). An identification job: its fit
    report (as ``oga identify --report``), the fitted model simulated on its trace again."""
    return await _cpu(request, "render", _report, request, job_id)


def _report(request: Request, job_id: str) -> Response:
    from oga.pipeline import SETPOINTS_PREFIX, plan_toolpath, read_program, stored_options
    from oga.report.optimize import render_report, replay_report_data

    store = _store(request)
    row = store.get(job_id, with_toolpath=True)
    if row is None:
        raise HTTPException(404, f"no job {job_id!r}")
    blob = store.table(row.id)
    if row.status != "succeeded" or blob is None or row.summary is None:
        raise HTTPException(409, f"job {row.id} is {row.status}: no report")
    if is_identification(row):  # the fit report (as oga identify --report)
        from api.identify import identification_report

        page = identification_report(row.toolpath, row.toolpath_format, machine_from_dict(
            row.machine), row.options, row.source, row.summary, blob)
        return HTMLResponse(page, headers={"X-Oga-Job-Id": row.id})
    _no_table(row)  # a law job has no report: its summary holds the certificates
    table = table_from_npz(blob)
    machine = machine_from_dict(row.machine)
    options, read = stored_options(row.options)
    if row.toolpath_format.startswith(SETPOINTS_PREFIX):
        from oga.recorded import read_setpoints

        sp = read_setpoints(row.toolpath, machine, row.toolpath_format.removeprefix(
            SETPOINTS_PREFIX), source=row.source, **(read or {})).setpoints
    else:
        path = read_program(row.toolpath, row.toolpath_format, machine, options,
                            source=row.source)
        sp = plan_toolpath(path, machine, feed_m_s=options.feed_m_s, tol_m=options.tol_m)
    column = {name: table.data[:, i] for i, name in enumerate(table.header)}
    kp = np.column_stack([column[f"{a}_kp_m_min_per_mm"] for a in AXES])
    kf = np.column_stack([column[f"{a}_kf"] for a in AXES])
    data = replay_report_data(sp, machine, kp, kf, row.summary)
    return HTMLResponse(render_report(data), headers={"X-Oga-Job-Id": row.id})


@router.post("/identify", status_code=202, response_model=JobAccepted, responses=_BODY_ERRORS,
             summary="Submit a recorded trace: identify the machine's axis model")
async def submit_identify(body: IdentifyRequest, request: Request, response: Response) -> dict:
    """Queue an identification (``oga identify``). The trace is read and checked at once
    (422 naming the column and the row if it is malformed; an axis not traced, or not a
    cascade of the base machine, 422 too); the fit runs in a worker. When the job has
    succeeded, ``GET /v1/jobs/{id}/machine`` is the identified machine file and
    ``/summary`` the fitted values, their intervals and the residuals per axis."""
    row = await _cpu(request, "read", _accept_trace, request, body)
    response.headers["Location"] = f"/v1/jobs/{row.id}"
    return {"id": row.id, "status": row.status}


def _accept_trace(request: Request, body: IdentifyRequest) -> JobRow:
    """Check a trace (read, its axes against the base machine) and queue its identification."""
    from api.identify import identify_options, read_job_trace

    machine = _machine(body.machine)
    fmt, options = TRACE_PREFIX + body.trace.format, identify_options(body)
    read_job_trace(body.trace.content, fmt, machine, options, body.trace.name)
    return _store(request).submit(
        source=body.trace.name, toolpath_format=fmt, toolpath=body.trace.content,
        machine=machine.model_dump(mode="json", exclude_none=True), options=options)


@router.get("/jobs/{job_id}/machine", responses={
    200: {"content": {"application/toml": {}}, "description": "the identified machine file"},
    **_ERRORS}, response_class=Response, summary="The machine file of a succeeded identification")
def get_identified_machine(job_id: str, request: Request) -> Response:
    """The identified machine as TOML (as ``oga identify --out``): it loads as any machine
    file (``oga optimize --machine MINE.toml``); each fitted value has its confidence
    interval and the fit's residual beside it. 409 until the job has succeeded, and for
    an optimisation job."""
    row = _job(request, job_id)
    if not is_identification(row):
        raise HTTPException(409, f"job {row.id} optimises a toolpath: no machine file")
    blob = _result(request, row, "machine file")
    stem = PurePath(row.source).stem or row.id
    return Response(blob, media_type="application/toml", headers={
        "Content-Disposition": f'attachment; filename="{_ascii(stem)}-identified.toml"',
        "X-Oga-Job-Id": row.id})


@router.post("/gain-table", responses={
    200: {"content": {m: {} for _, m in TABLE_FORMATS.values()}, "description": "the table"},
    202: {"model": JobAccepted, "description": "not done in time: poll the job"},
    **_BODY_ERRORS}, response_class=Response, summary="Optimise a short toolpath and return the table")
async def gain_table(body: JobRequest, request: Request, format: TableFormat = "csv",
                     name: Name = C_NAME) -> Response:
    """Synchronous: for toolpaths up to the server's motion-time limit (default 10 s of
    motion at the programmed feeds; 413 beyond it: use ``POST /v1/jobs``). The job runs in
    a worker ahead of queued jobs; if it is not done within the server's wait limit the
    answer is 202 with the job to poll. A schedule that fails verification answers 422
    with the violations."""
    row = await _cpu(request, "read", _accept, request, body, True)
    settings = request.app.state.settings
    deadline = time.monotonic() + settings.sync_timeout_s
    while row.status not in FINISHED and time.monotonic() < deadline:
        await asyncio.sleep(0.1)
        row = await run_in_threadpool(_job, request, row.id)
    headers = {"X-Oga-Job-Id": row.id, "Location": f"/v1/jobs/{row.id}"}
    if row.status == "succeeded":
        return await _cpu(request, "render", _table_response, request, row, format, name)
    if row.status == "failed":
        return JSONResponse(row.error, status_code=422, headers=headers)
    if row.status == "cancelled":
        raise HTTPException(409, f"job {row.id} was cancelled")
    return JSONResponse({"id": row.id, "status": row.status}, status_code=202, headers=headers)


@router.get("/machines", response_model=MachineList, summary="The machine presets")
def list_machines() -> dict:
    items = []
    for name in PRESETS:
        m = load_machine(name)
        items.append({"name": m.name, "source": m.source, "axes": sorted(m.axes),
                      "sha256": m.digest()})
    return {"items": items}


@router.get("/machines/{name}", responses=_ERRORS, summary="A machine preset, every field")
def get_machine(name: str, response: Response) -> dict:
    """The preset as a machine object, usable as the ``machine`` of a job (edited or not);
    its SHA-256 (as in the tables' metadata) in the header ``X-Oga-Machine-Sha256``."""
    if name not in PRESETS:
        raise HTTPException(404, f"no machine preset {name!r} (presets: {', '.join(PRESETS)})")
    m = load_machine(name)
    response.headers["X-Oga-Machine-Sha256"] = m.digest()
    return m.model_dump(mode="json", exclude_none=True)  # an axis has one model kind


@router.post("/law", status_code=202, response_model=JobAccepted, responses=_BODY_ERRORS,
             summary="Submit programs: a certified gain law for a controller that adapts its gains")
async def submit_law(body: LawRequest, request: Request, response: Response) -> dict:
    """Queue a gain-law search (``oga law``): the programs are read and the options checked
    at once (422 naming the program's line and column, or the field); the search and the
    certificate at every feed override run in a worker. When the job has succeeded,
    ``GET /v1/jobs/{id}/law`` is a zip of the controller files and ``/summary`` the law and
    its certificate per program and override."""
    row = await _cpu(request, "read", _accept_law, request, body)
    response.headers["Location"] = f"/v1/jobs/{row.id}"
    return {"id": row.id, "status": row.status}


def _accept_law(request: Request, body: LawRequest) -> JobRow:
    """Check a law request (programs read, options, machine with a set, motion bounded) and
    queue its job."""
    from api.law import LAW_FORMAT, check_law, law_job

    machine = _machine(body.machine)
    text, options = law_job(body)
    paths = check_law(text, machine, options)
    settings = request.app.state.settings
    for name, path in paths:  # every override plans it again: bounded at the slowest
        _check_motion(path, machine, None, settings.job_max_motion_s * min(options["overrides"]),
                      where=f" ({name})", advice=" (the server's --job-max-motion-s, at the "
                      "slowest override)")
    return _store(request).submit(
        source=",".join(n for n, _ in paths)[:255], toolpath_format=LAW_FORMAT, toolpath=text,
        machine=machine.model_dump(mode="json", exclude_none=True), options=options)


@router.get("/jobs/{job_id}/law", responses={
    200: {"content": {"application/zip": {}}, "description": "the controller files"},
    **_ERRORS}, summary="The controller files of a gain-law job")
def get_law(job_id: str, request: Request) -> Response:
    """The zip of a succeeded law job's files (``oga law --out``)."""
    from api.law import is_law

    row = _job(request, job_id)
    if not is_law(row):
        raise HTTPException(409, f"job {row.id} is not a gain-law job")
    blob = _result(request, row, "law")
    return Response(blob, media_type="application/zip", headers={
        "Content-Disposition": f'attachment; filename="oga_law_{row.id}.zip"',
        "X-Oga-Job-Id": row.id})
