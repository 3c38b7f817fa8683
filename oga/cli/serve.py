"""``oga serve``: the REST API (FastAPI on uvicorn) with its worker processes."""

from __future__ import annotations

import argparse
import os
import sqlite3

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    from api.storage import default_db_path
    from oga.defaults import API_HOST, API_MAX_UPLOAD_BYTES, API_PORT

    p = sub.add_parser(
        "serve",
        help="run the REST API (durable optimisation jobs)",
        description="Serve the REST API: POST /v1/jobs, GET /v1/jobs/{id}/table, ... "
        "(OpenAPI docs at /docs). Jobs and results live in an SQLite database and "
        "survive a restart.",
    )
    p.add_argument("--host", default=API_HOST,
                   help=f"interface to bind (default {API_HOST}, loopback only; "
                   "0.0.0.0 for all)")
    p.add_argument("--port", type=int, default=API_PORT, help=f"TCP port (default {API_PORT})")
    p.add_argument("--db", default=None, metavar="PATH",
                   help=f"SQLite database of jobs and results (default {default_db_path()})")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes, jobs optimised at once (default: one per CPU)")
    p.add_argument("--api-key", default=None, metavar="KEY",
                   help="require this key (header X-API-Key) on every route but /healthz and the web "
                   "page; "
                   "default the environment variable OGA_API_KEY, else none")
    p.add_argument("--max-upload-mb", type=float, default=API_MAX_UPLOAD_BYTES / 2**20,
                   metavar="MB",
                   help=f"largest request body in MiB (default {API_MAX_UPLOAD_BYTES / 2**20:g}; "
                   "413 beyond)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from api.app import Settings, create_app, default_workers
    from api.storage import Store, default_db_path
    from oga.errors import InputError

    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be in 0..65535, got {args.port}")
    workers = default_workers() if args.workers is None else args.workers
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    if not 0 < args.max_upload_mb < float("inf"):
        raise InputError(f"--max-upload-mb must be a positive number, got {args.max_upload_mb}")
    api_key = args.api_key or os.environ.get("OGA_API_KEY") or None
    db = args.db or str(default_db_path())
    try:
        Store(db).close()  # create or open it now: a bad path is the user's error, said once
    except (OSError, sqlite3.Error) as err:
        raise InputError(f"--db {db}: cannot open the database: {err}") from None
    settings = Settings(db_path=db, workers=workers, api_key=api_key,
                        max_upload_bytes=int(args.max_upload_mb * 2**20))
    print(f"oga serve: http://{args.host}:{args.port} (docs /docs), database {db}, "
          f"{workers} worker(s){', API key required' if api_key else ''}", flush=True)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="info")
    return 0
