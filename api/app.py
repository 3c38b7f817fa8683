"""The FastAPI application: settings, lifespan (store and executor), guards, error bodies.

Every error answer is an :class:`api.schemas.ErrorBody` (``{"message", ...}``):
bad input is 4xx (422 naming field, line and column; 400 for malformed JSON;
413 for an oversized body or a toolpath beyond the motion-time limit; 415 for a
body that is not ``application/json``; 405 with every allowed method), never 5xx.
The API key, when set, is required (header ``X-API-Key`` or ``Authorization:
Bearer``) by every route but ``/healthz`` and the web page (``/`` and
``/static/``: they hold no data; the page sends the key its user types).
"""

from __future__ import annotations

import hmac
import json
import logging
import os
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path

import anyio
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.routing import Match, Route

from api import routes
from api.schemas import Health, error_body
from api.job_process import JobLimits
from api.pool import JobPool
from api.storage import open_store
from api.workers import WorkerPool
from oga import __version__, defaults
from oga.errors import InputError

__all__ = ["Settings", "create_app", "default_workers", "open_pool"]

log = logging.getLogger("oga.api")

#: The kinds of CPU-bound request work, each run one at a time: reading a submitted toolpath
#: or trace (milliseconds), and rendering a report or a table (up to seconds: a submission
#: does not wait behind one). More threads only contend for the GIL and delay ``/healthz``
#: (20 submissions at once: /healthz up to 60-130 ms with a thread each, 13-39 ms this way).
CPU_WORK = ("read", "render")

#: The web page: ``index.html`` served at ``/``, its script and style under ``/static/``.
STATIC_DIR = Path(__file__).parent / "static"


def _public(path: str) -> bool:
    """Routes open without the API key: liveness and the web page."""
    return path in ("/healthz", "/") or path.startswith("/static/")


def default_workers() -> int:
    """One worker per CPU available to this process."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
               else os.cpu_count() or 1)


@dataclass(frozen=True)
class Settings:
    """How a server runs.

    Attributes
    ----------
    db_path : str
        The jobs and results: an SQLite file, or a PostgreSQL URL (``postgresql://...``).
    workers : int
        Worker processes (jobs optimised at once); 0 starts none (the API only queues).
    api_key : str or None
        Required by every route but ``/healthz`` and the web page when set.
    max_upload_bytes : int
        Largest request body, bytes.
    sync_max_motion_s, sync_timeout_s : float
        Limits of ``POST /v1/gain-table`` (motion time of the toolpath, wait), s.
    job_max_motion_s : float
        Longest toolpath of ``POST /v1/jobs``, s of motion (413 beyond).
    job_cpu_s : float
        CPU time of one attempt of a job, s (the job fails beyond).
    job_memory_bytes : int
        Resident memory of the worker running a job, bytes (the job fails beyond).
    stall_s : float
        ``/healthz`` says "degraded" while a running job's progress has not moved for this
        long, s.
    scheduler : str or None
        A Dask scheduler (``tcp://HOST:PORT``): the jobs run on its cluster
        (:mod:`api.workers_dask`) instead of ``workers`` local processes.
    """

    db_path: str
    workers: int = field(default_factory=default_workers)
    api_key: str | None = None
    max_upload_bytes: int = defaults.API_MAX_UPLOAD_BYTES
    sync_max_motion_s: float = defaults.API_SYNC_MAX_MOTION_S
    sync_timeout_s: float = defaults.API_SYNC_TIMEOUT_S
    job_max_motion_s: float = defaults.API_JOB_MAX_MOTION_S
    job_cpu_s: float = defaults.API_JOB_CPU_S
    job_memory_bytes: int = defaults.API_JOB_MEMORY_BYTES
    stall_s: float = defaults.API_STALL_S
    scheduler: str | None = None


def _message_of(err: dict) -> str:
    loc = ".".join(str(x) for x in err.get("loc", ()) if x != "body") or "body"
    msg = "unknown field" if err.get("type") == "extra_forbidden" else err.get("msg", "invalid")
    return f"{loc}: {msg}"


async def _send_json(send, status: int, body: dict, headers: tuple = ()) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(data)).encode()), *headers]})
    await send({"type": "http.response.body", "body": data})


def _unsupported_body(headers: dict) -> str | None:
    """Why a request body cannot be read as JSON (415), or None.

    ``application/json`` and ``application/*+json`` are JSON (FastAPI reads no other
    body, and none without a Content-Type); any Content-Encoding but identity is refused.
    """
    encoding = headers.get(b"content-encoding", b"").decode("latin-1").strip().lower()
    if encoding not in ("", "identity"):
        return f"Content-Encoding {encoding} is not supported: send the JSON body uncompressed"
    media = headers.get(b"content-type", b"").decode("latin-1").split(";")[0].strip().lower()
    if media == "application/json" or (media.startswith("application/")
                                       and media.endswith("+json")):
        return None
    return (f"Content-Type {media} is not supported" if media else "no Content-Type"
            ) + ": the body must be application/json"


def _http_routes(app: FastAPI) -> list[Route]:
    """The routes of the app and of the ``/v1`` router."""
    return [*routes.router.routes, *(r for r in app.router.routes if isinstance(r, Route))]


def _allowed_methods(app: FastAPI, scope) -> str:
    """Every method of every route at the request's path (a 405's Allow header)."""
    methods: set[str] = set()
    for route in _http_routes(app):
        if route.matches(scope)[0] != Match.NONE:
            methods |= route.methods or set()
    return ", ".join(sorted(methods))


class _Guard:
    """ASGI middleware: the API key, the body's media type (415 on the routes that read JSON,
    ``json_paths``), then the body-size limit (read before the app sees it)."""

    def __init__(self, app, api_key: str | None, max_bytes: int,
                 json_paths: frozenset[str] = frozenset()) -> None:
        self.app = app
        self.api_key = api_key.encode() if api_key else None
        self.max_bytes = max_bytes
        self.json_paths = json_paths

    def _authorised(self, scope) -> bool:
        if self.api_key is None or _public(scope["path"]):
            return True
        headers = dict(scope["headers"])
        given = headers.get(b"x-api-key")
        auth = headers.get(b"authorization", b"")
        if given is None and auth[:7].lower() == b"bearer ":
            given = auth[7:].strip()
        return given is not None and hmac.compare_digest(given, self.api_key)

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        if not self._authorised(scope):
            return await _send_json(send, 401, {"message": "missing or wrong API key "
                                                "(header X-API-Key)", "type": "Unauthorized"},
                                    ((b"www-authenticate", b'ApiKey header="X-API-Key"'),))
        if scope["method"] in ("POST", "PUT", "PATCH") and scope["path"] in self.json_paths:
            problem = _unsupported_body(dict(scope["headers"]))
            if problem:
                return await _send_json(send, 415, {"message": problem,
                                                    "type": "UnsupportedMediaType"})
        too_big = {"message": f"request body larger than {self.max_bytes} bytes "
                              "(the server's --max-upload-mb)", "type": "TooLarge"}
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_bytes):
            return await _send_json(send, 413, too_big)
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                return await _send_json(send, 413, too_big)
            chunks.append(chunk)
            more = message.get("more_body", False)
        body, replayed = b"".join(chunks), False

        async def replay():
            nonlocal replayed
            if replayed:
                return await receive()
            replayed = True
            return {"type": "http.request", "body": body, "more_body": False}

        await self.app(scope, replay, send)


def open_pool(settings: Settings) -> JobPool | None:
    """The executor of the jobs: the Dask cluster of ``settings.scheduler``, else
    ``settings.workers`` local processes, else none (the API only queues)."""
    limits = JobLimits(settings.job_cpu_s, settings.job_memory_bytes)
    if settings.scheduler:
        from api.workers_dask import DaskPool

        return DaskPool(settings.db_path, settings.scheduler, limits, settings.stall_s)
    if settings.workers:
        return WorkerPool(settings.db_path, settings.workers, limits, settings.stall_s)
    return None


def _lifespan(settings: Settings):
    """The app's lifespan: the executor started with the app and stopped with it."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        pool = open_pool(settings)
        app.state.pool = pool
        app.state.cpu_limiters = {kind: anyio.CapacityLimiter(1) for kind in CPU_WORK}
        if pool is not None:
            await run_in_threadpool(pool.start)
        try:
            yield
        finally:
            if pool is not None:
                await run_in_threadpool(pool.stop)

    return lifespan


def _description(settings: Settings) -> str:
    """The OpenAPI description: what the service does and this server's limits."""
    return ("POST a toolpath, get a verified table of position-loop gains (Kp in (m/min)/mm "
            "and Kf per axis, per sample). Jobs are durable (SQLite, WAL): they survive a "
            "restart of the server. Limits of this server: request body "
            f"{settings.max_upload_bytes} bytes (413 beyond); `POST /v1/gain-table` up to "
            f"{settings.sync_max_motion_s:g} s of motion (413 beyond: use jobs). "
            + ("Every route but /healthz and the web page needs the header `X-API-Key`."
               if settings.api_key else ""))


def _add_guard(app: FastAPI, settings: Settings) -> None:
    """The API key, media-type and body-size middleware (:class:`_Guard`)."""
    json_paths = frozenset(r.path for r in routes.router.routes
                           if isinstance(r, APIRoute) and r.body_field is not None)
    app.add_middleware(_Guard, api_key=settings.api_key, max_bytes=settings.max_upload_bytes,
                       json_paths=json_paths)


def _add_error_handlers(app: FastAPI) -> None:
    """Every error answer an :class:`api.schemas.ErrorBody`: 4xx for bad input, 500 for a bug."""

    @app.exception_handler(InputError)
    async def _input_error(request: Request, err: InputError):
        return JSONResponse(error_body(err), status_code=422)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, err: RequestValidationError):
        errors = err.errors()
        bad_json = [e for e in errors if e.get("type") == "json_invalid"]
        if bad_json:
            ctx = bad_json[0].get("ctx", {})
            return JSONResponse({"message": f"malformed JSON body: {ctx.get('error', 'invalid')}"
                                 f" at character {bad_json[0]['loc'][-1]}",
                                 "type": "MalformedJSON"}, status_code=400)
        return JSONResponse({"message": "; ".join(_message_of(e) for e in errors),
                             "type": "ValidationError"}, status_code=422)

    @app.exception_handler(HTTPException)
    async def _http(request: Request, err: HTTPException):
        headers = getattr(err, "headers", None)
        if err.status_code == 405:
            headers = {**(headers or {}), "Allow": _allowed_methods(app, request.scope)}
        return JSONResponse({"message": str(err.detail)}, status_code=err.status_code,
                            headers=headers)

    @app.exception_handler(Exception)
    async def _bug(request: Request, err: Exception):
        log.exception("internal error on %s %s", request.method, request.url.path)
        return JSONResponse({"message": "internal error", "type": "InternalError"},
                            status_code=500)


def _add_health_and_page(app: FastAPI) -> None:
    """``/healthz`` and the web page (``/`` and ``/static/``), open without the API key."""

    @app.get("/healthz", response_model=Health, summary="Liveness (no API key needed)")
    def healthz(request: Request) -> dict:
        """Always 200 while the server answers. ``status`` is ``"degraded"`` while a running
        job's progress has not moved for the server's stall time (``stalled`` names the job,
        its worker and for how long), else ``"ok"``: the server still takes, serves and
        cancels jobs, so a probe that restarts it on 503 would gain nothing."""
        pool = request.app.state.pool
        stalled = pool.stalled() if pool else []
        return {"status": "degraded" if stalled else "ok", "version": __version__,
                "workers_alive": pool.alive() if pool else 0,
                "jobs": request.app.state.store.counts(), "stalled": stalled}

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", response_class=FileResponse, include_in_schema=False)
    def page() -> FileResponse:
        """The web page: submit a program, watch the job, open the report, download tables."""
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html")


def create_app(settings: Settings) -> FastAPI:
    """The API on ``settings.db_path``; the executor starts with the app's lifespan."""
    app = FastAPI(title="oga", version=__version__,
                  summary="Offline gain schedules for CNC machine tools",
                  description=_description(settings), lifespan=_lifespan(settings))
    app.state.settings = settings
    app.state.store = open_store(settings.db_path)
    app.state.pool = None
    app.include_router(routes.router)
    _add_guard(app, settings)
    _add_error_handlers(app)
    _add_health_and_page(app)
    return app
