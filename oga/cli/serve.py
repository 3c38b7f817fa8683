"""``oga serve``: the REST API (FastAPI on uvicorn) with its worker processes."""

from __future__ import annotations

import argparse
import os

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    from api.storage import default_db_path
    from oga import defaults

    p = sub.add_parser(
        "serve",
        help="run the REST API (durable optimisation jobs)",
        description="Serve the REST API: POST /v1/jobs, GET /v1/jobs/{id}/table, ... "
        "(OpenAPI docs at /docs). Jobs and results live in an SQLite database (or a "
        "PostgreSQL one shared by several servers) and survive a restart.",
    )
    p.add_argument("--host", default=defaults.API_HOST,
                   help=f"interface to bind (default {defaults.API_HOST}, loopback only; "
                   "0.0.0.0 for all)")
    p.add_argument("--port", type=int, default=defaults.API_PORT,
                   help=f"TCP port (default {defaults.API_PORT})")
    p.add_argument("--db", default=None, metavar="PATH|URL",
                   help="jobs and results: an SQLite file (default "
                   f"{default_db_path()}), or a PostgreSQL database postgresql://USER@HOST/DB "
                   "that several servers share")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes, jobs optimised at once (default: one per CPU)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the jobs on the Dask cluster of this scheduler (tcp://HOST:8786) "
                   "instead of local worker processes; its workers must reach --db (PostgreSQL, "
                   "or an SQLite file on this host)")
    p.add_argument("--api-key", default=None, metavar="KEY",
                   help="require this key (header X-API-Key) on every route but /healthz and the web "
                   "page; "
                   "default the environment variable OGA_API_KEY, else none")
    p.add_argument("--max-upload-mb", type=float, default=defaults.API_MAX_UPLOAD_BYTES / 2**20,
                   metavar="MB",
                   help="largest request body in MiB (default "
                   f"{defaults.API_MAX_UPLOAD_BYTES / 2**20:g}; 413 beyond)")
    p.add_argument("--job-cpu-s", type=float, default=defaults.API_JOB_CPU_S, metavar="S",
                   help="CPU time one job may use, s (default "
                   f"{defaults.API_JOB_CPU_S:g}); the job fails beyond it")
    p.add_argument("--job-memory-mb", type=float, default=defaults.API_JOB_MEMORY_BYTES / 2**20,
                   metavar="MB", help="resident memory of the worker running a job, MiB (default "
                   f"{defaults.API_JOB_MEMORY_BYTES / 2**20:g}); the job fails beyond it")
    p.add_argument("--job-max-motion-s", type=float, default=defaults.API_JOB_MAX_MOTION_S,
                   metavar="S", help="longest toolpath of POST /v1/jobs, s of motion at the "
                   f"programmed feeds (default {defaults.API_JOB_MAX_MOTION_S:g}; 413 beyond)")
    p.add_argument("--stall-s", type=float, default=defaults.API_STALL_S, metavar="S",
                   help="/healthz says degraded while a running job's progress has not moved "
                   f"for this long, s (default {defaults.API_STALL_S:g})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from api.app import Settings, create_app, default_workers
    from api.storage import StoreError, default_db_path, open_store, without_password
    from oga import defaults
    from oga.errors import InputError

    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be in 0..65535, got {args.port}")
    workers = default_workers() if args.workers is None else args.workers
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    if args.scheduler is not None and args.workers is not None:
        raise InputError("--workers is for local worker processes: with --scheduler the "
                         "cluster's workers run the jobs")
    for flag in ("max_upload_mb", "job_cpu_s", "job_memory_mb", "job_max_motion_s", "stall_s"):
        value = getattr(args, flag)
        if not 0 < value < float("inf"):
            raise InputError(f"--{flag.replace('_', '-')} must be a positive number, got {value}")
    if args.job_max_motion_s > defaults.MAX_MOTION_S:  # the planner refuses longer ones
        raise InputError(f"--job-max-motion-s must be at most {defaults.MAX_MOTION_S:g} s (the "
                         f"planner's MAX_MOTION_S), got {args.job_max_motion_s:g}")
    api_key = args.api_key or os.environ.get("OGA_API_KEY") or None
    db = args.db or str(default_db_path())
    try:  # create or open it now: a bad path or URL is the user's error, said once
        open_store(db).close()
    except StoreError as err:
        raise InputError(f"--db {err}") from None
    if args.scheduler is not None:  # reachable now: an unreachable one is the user's error
        from oga.cli.batch_dask import connect

        connect(args.scheduler).close()
    settings = Settings(db_path=db, workers=workers, api_key=api_key,
                        max_upload_bytes=int(args.max_upload_mb * 2**20),
                        job_max_motion_s=args.job_max_motion_s, job_cpu_s=args.job_cpu_s,
                        job_memory_bytes=int(args.job_memory_mb * 2**20), stall_s=args.stall_s,
                        scheduler=args.scheduler)
    runs = (f"jobs on the Dask cluster {args.scheduler}" if args.scheduler
            else f"{workers} worker(s)")
    print(f"oga serve: http://{args.host}:{args.port} (docs /docs), database "
          f"{without_password(db)}, {runs}{', API key required' if api_key else ''}", flush=True)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="info")
    return 0
