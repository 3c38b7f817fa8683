"""The job store: jobs and their results in one SQLite database (WAL).

Every change of a job is one transaction. A worker claims a queued job by
incrementing its ``attempts``; that number is the worker's fencing token: every
later write of the worker (progress, result) names it and changes nothing once
the job was cancelled or handed to another worker, so a stale worker can never
overwrite a newer state. A result (status, summary and table) is written in a
single transaction, so a job is either succeeded with its table or not at all.

Two backends share this logic and its SQL: :class:`SqliteStore` (one file, one
host; the default) and :class:`api.storage_pg.PgStore` (PostgreSQL: several
servers on several hosts share one queue; a claim takes its row ``FOR UPDATE
SKIP LOCKED``). :func:`open_store` picks one from the ``--db`` value.

Owners: a running job records the server that runs it (host, pid, instance id)
and the worker's pid; :meth:`Store.running` lets the server find jobs whose
owner is gone and requeue them (see :mod:`api.workers`).
"""

from __future__ import annotations

import json
import os
import re
import sqlite3
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path as FilePath

from oga.errors import OgaError

__all__ = ["STATUSES", "FINISHED", "TRACE_PREFIX", "Owner", "JobRow", "Store", "SqliteStore",
           "open_store", "is_identification", "is_postgres_url", "without_password",
           "default_db_path", "StoreError"]

#: Every job status.
STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")
#: Statuses a job never leaves.
FINISHED = ("succeeded", "failed", "cancelled")

#: ``toolpath_format`` of an identification job: this prefix and the trace's format
#: (``trace-csv``, ``trace-halsampler``, ``trace-twincat``); its ``toolpath`` is the trace,
#: its ``options`` those of ``oga identify``, its result (``results.table_npz``) the
#: identified machine's TOML, UTF-8.
TRACE_PREFIX = "trace-"

#: The tables; ``{seq}``, ``{real}`` and ``{blob}`` are the backend's spellings of an
#: insertion-order column, a double and a byte string.
SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,{seq}
    status TEXT NOT NULL CHECK (status IN ('queued','running','succeeded','failed','cancelled')),
    priority INTEGER NOT NULL DEFAULT 0,
    progress {real} NOT NULL DEFAULT 0,
    created_at TEXT NOT NULL,
    started_at TEXT,
    finished_at TEXT,
    source TEXT NOT NULL,
    toolpath_format TEXT NOT NULL,
    toolpath TEXT NOT NULL,
    machine TEXT NOT NULL,
    options TEXT NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    owner_host TEXT,
    owner_pid INTEGER,
    owner_instance TEXT,
    worker_pid INTEGER,
    heartbeat {real},
    error TEXT,
    summary TEXT
);
CREATE INDEX IF NOT EXISTS jobs_queue ON jobs (status, priority DESC, created_at);
CREATE TABLE IF NOT EXISTS results (
    job_id TEXT PRIMARY KEY REFERENCES jobs (id) ON DELETE CASCADE,
    table_npz {blob} NOT NULL
);
"""


def is_identification(row: "JobRow") -> bool:
    """Whether a stored job identifies a machine from a trace (else it optimises a toolpath)."""
    return row.toolpath_format.startswith(TRACE_PREFIX)


def default_db_path() -> FilePath:
    """``$XDG_DATA_HOME/oga/oga.db``, else ``~/.local/share/oga/oga.db``."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return FilePath(base) / "oga" / "oga.db"


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass(frozen=True)
class Owner:
    """Who runs a job: the server process (host, pid, instance id) and its worker's pid
    (None until a Dask task has started the job's process)."""

    host: str
    pid: int
    instance: str
    worker_pid: int | None


@dataclass(frozen=True)
class JobRow:
    """One job as stored (JSON columns decoded; the toolpath text left out of listings)."""

    id: str
    status: str
    priority: int
    progress: float
    created_at: str
    started_at: str | None
    finished_at: str | None
    source: str
    toolpath_format: str
    toolpath: str | None
    machine: dict
    options: dict
    attempts: int
    owner: Owner | None
    heartbeat: float | None
    error: dict | None
    summary: dict | None

    @classmethod
    def _from(cls, r) -> "JobRow":
        keys = r.keys()
        owner = None
        if r["owner_instance"] is not None:
            owner = Owner(r["owner_host"], r["owner_pid"], r["owner_instance"], r["worker_pid"])
        return cls(
            id=r["id"], status=r["status"], priority=r["priority"], progress=r["progress"],
            created_at=r["created_at"], started_at=r["started_at"], finished_at=r["finished_at"],
            source=r["source"], toolpath_format=r["toolpath_format"],
            toolpath=r["toolpath"] if "toolpath" in keys else None,
            machine=json.loads(r["machine"]), options=json.loads(r["options"]),
            attempts=r["attempts"], owner=owner, heartbeat=r["heartbeat"],
            error=None if r["error"] is None else json.loads(r["error"]),
            summary=None if r["summary"] is None else json.loads(r["summary"]),
        )


_LIST_COLUMNS = ("id, status, priority, progress, created_at, started_at, finished_at, source, "
                 "toolpath_format, machine, options, attempts, owner_host, owner_pid, "
                 "owner_instance, worker_pid, heartbeat, error, summary")


class Store:
    """The job database; safe to share between threads (one connection per thread).

    The queries of both backends live here (written with ``?`` parameters); a backend
    gives its connection, its transaction, its schema spellings and its claim lock.
    Open one with :func:`open_store`.
    """

    #: The column that orders jobs created in the same millisecond (insertion order).
    _SEQ = "rowid"
    #: Appended to the claim's choice of a queued job (PostgreSQL: ``FOR UPDATE SKIP LOCKED``).
    _CLAIM_LOCK = ""
    #: Exceptions of the backend (an unusable ``--db`` raises one of them).
    errors: tuple[type[BaseException], ...] = ()

    def __init__(self) -> None:
        self._local = threading.local()

    def _connect(self):
        """A new connection of this thread (with ``execute(sql, args)`` taking ``?``)."""
        raise NotImplementedError

    def _is_open(self, db) -> bool:
        return True

    def _db(self):
        db = getattr(self._local, "db", None)
        if db is None or not self._is_open(db):
            db = self._local.db = self._connect()
        return db

    @contextmanager
    def _tx(self):
        """A write transaction; rolled back on any exception."""
        raise NotImplementedError
        yield

    def close(self) -> None:
        """Close this thread's connection."""
        db = getattr(self._local, "db", None)
        if db is not None:
            db.close()
            self._local.db = None

    # -- submitting and reading -------------------------------------------------------------

    def submit(self, *, source: str, toolpath_format: str, toolpath: str, machine: dict,
               options: dict, priority: int = 0) -> JobRow:
        """Store a new queued job; returns it."""
        job_id = uuid.uuid4().hex
        with self._tx() as db:
            db.execute(
                "INSERT INTO jobs (id, status, priority, created_at, source, toolpath_format, "
                "toolpath, machine, options) VALUES (?, 'queued', ?, ?, ?, ?, ?, ?, ?)",
                (job_id, priority, _now(), source, toolpath_format, toolpath,
                 json.dumps(machine), json.dumps(options)),
            )
        return self.get(job_id)

    def get(self, job_id: str, *, with_toolpath: bool = False) -> JobRow | None:
        """The job, or None if there is no such job."""
        cols = "*" if with_toolpath else _LIST_COLUMNS
        r = self._db().execute(f"SELECT {cols} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if r is None else JobRow._from(r)

    def list(self, *, limit: int, offset: int, status: str | None = None) -> tuple[list[JobRow], int]:
        """A page of jobs, newest first, and the total count (of that status)."""
        where, args = ("WHERE status = ?", (status,)) if status else ("", ())
        db = self._db()
        total = db.execute(f"SELECT COUNT(*) AS n FROM jobs {where}", args).fetchone()["n"]
        rows = db.execute(
            f"SELECT {_LIST_COLUMNS} FROM jobs {where} "
            f"ORDER BY created_at DESC, {self._SEQ} DESC LIMIT ? OFFSET ?", (*args, limit, offset),
        ).fetchall()
        return [JobRow._from(r) for r in rows], total

    def counts(self) -> dict[str, int]:
        """Number of jobs per status."""
        rows = self._db().execute(
            "SELECT status, COUNT(*) AS n FROM jobs GROUP BY status").fetchall()
        return {s: 0 for s in STATUSES} | {r["status"]: r["n"] for r in rows}

    def table(self, job_id: str) -> bytes | None:
        """The stored table (``oga.export.table_npz`` bytes) of a succeeded job."""
        r = self._db().execute("SELECT table_npz FROM results WHERE job_id = ?", (job_id,)).fetchone()
        return None if r is None else bytes(r["table_npz"])

    def cancel(self, job_id: str) -> JobRow | None:
        """Cancel a queued or running job; returns it (with the owner that ran it, if it
        was running), or None if it had already finished (or is unknown)."""
        with self._tx() as db:
            r = db.execute(
                f"UPDATE jobs SET status = 'cancelled', finished_at = ? "
                f"WHERE id = ? AND status IN ('queued', 'running') RETURNING {_LIST_COLUMNS}",
                (_now(), job_id)).fetchone()
        return None if r is None else JobRow._from(r)

    # -- workers ----------------------------------------------------------------------------

    def claim(self, owner: Owner) -> JobRow | None:
        """Take the next queued job (highest priority, then oldest) for ``owner``, or None."""
        if self._db().execute("SELECT 1 FROM jobs WHERE status = 'queued' LIMIT 1").fetchone() is None:
            return None  # nothing to do: no write lock taken
        with self._tx() as db:
            r = db.execute(
                "UPDATE jobs SET status = 'running', attempts = attempts + 1, progress = 0, "
                "started_at = ?, owner_host = ?, owner_pid = ?, owner_instance = ?, "
                "worker_pid = ?, heartbeat = ? WHERE status = 'queued' AND id = (SELECT id "
                f"FROM jobs WHERE status = 'queued' ORDER BY priority DESC, created_at, "
                f"{self._SEQ} LIMIT 1{self._CLAIM_LOCK}) RETURNING *",
                (_now(), owner.host, owner.pid, owner.instance, owner.worker_pid, time.time()),
            ).fetchone()
        return None if r is None else JobRow._from(r)

    def mark_started(self, job_id: str, attempt: int, worker_pid: int) -> bool:
        """Record the process that runs this attempt, once: False when the attempt already
        named one (a Dask task run again after its worker died) or is no longer running."""
        with self._tx() as db:
            cur = db.execute(
                "UPDATE jobs SET worker_pid = ?, heartbeat = ? WHERE id = ? AND attempts = ? "
                "AND status = 'running' AND worker_pid IS NULL",
                (worker_pid, time.time(), job_id, attempt))
        return cur.rowcount == 1

    def progress(self, job_id: str, attempt: int, fraction: float) -> bool:
        """Record progress; False when the job is no longer this attempt's (cancelled, requeued)."""
        with self._tx() as db:
            cur = db.execute(
                "UPDATE jobs SET progress = ?, heartbeat = ? "
                "WHERE id = ? AND attempts = ? AND status = 'running'",
                (fraction, time.time(), job_id, attempt))
        return cur.rowcount == 1

    def succeed(self, job_id: str, attempt: int, summary: dict, table_npz: bytes) -> bool:
        """Store the result and mark the job succeeded, in one transaction."""
        with self._tx() as db:
            cur = db.execute(
                "UPDATE jobs SET status = 'succeeded', progress = 1, finished_at = ?, summary = ? "
                "WHERE id = ? AND attempts = ? AND status = 'running'",
                (_now(), json.dumps(summary), job_id, attempt))
            if cur.rowcount == 1:
                db.execute("INSERT INTO results (job_id, table_npz) VALUES (?, ?) ON CONFLICT "
                           "(job_id) DO UPDATE SET table_npz = excluded.table_npz",
                           (job_id, table_npz))
        return cur.rowcount == 1

    def fail(self, job_id: str, attempt: int, error: dict, summary: dict | None = None) -> bool:
        """Mark the job failed with ``error`` (and the summary of a failed verification)."""
        with self._tx() as db:
            cur = db.execute(
                "UPDATE jobs SET status = 'failed', finished_at = ?, error = ?, summary = ? "
                "WHERE id = ? AND attempts = ? AND status = 'running'",
                (_now(), json.dumps(error), None if summary is None else json.dumps(summary),
                 job_id, attempt))
        return cur.rowcount == 1

    # -- recovery ---------------------------------------------------------------------------

    def running(self) -> list[JobRow]:
        """Every running job (for the recovery of jobs whose worker or server is gone)."""
        rows = self._db().execute(
            f"SELECT {_LIST_COLUMNS} FROM jobs WHERE status = 'running'").fetchall()
        return [JobRow._from(r) for r in rows]

    def heartbeat(self, instance: str) -> None:
        """Mark every job running under server ``instance`` as alive now."""
        with self._tx() as db:
            db.execute("UPDATE jobs SET heartbeat = ? WHERE status = 'running' "
                       "AND owner_instance = ?", (time.time(), instance))

    def requeue(self, job_id: str, attempt: int, max_attempts: int | None = None) -> str | None:
        """Put a running job whose worker is gone back in the queue.

        With ``max_attempts``, a job that has been tried that often fails instead (a job
        that kills its worker must not loop forever). Returns the new status, or None if
        the job had moved on meanwhile.
        """
        with self._tx() as db:
            if max_attempts is not None and attempt >= max_attempts:
                error = {"message": f"the worker running this job died {attempt} times; "
                                    "giving up", "type": "WorkerLost"}
                cur = db.execute(
                    "UPDATE jobs SET status = 'failed', finished_at = ?, error = ? "
                    "WHERE id = ? AND attempts = ? AND status = 'running'",
                    (_now(), json.dumps(error), job_id, attempt))
                new = "failed"
            else:
                cur = db.execute(
                    "UPDATE jobs SET status = 'queued', progress = 0, owner_host = NULL, "
                    "owner_pid = NULL, owner_instance = NULL, worker_pid = NULL "
                    "WHERE id = ? AND attempts = ? AND status = 'running'", (job_id, attempt))
                new = "queued"
        return new if cur.rowcount == 1 else None


class SqliteStore(Store):
    """The jobs in one SQLite file (WAL): one host, zero setup.

    Parameters
    ----------
    path : path-like
        SQLite file; created with its folder if missing.
    """

    errors = (OSError, sqlite3.Error)

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__()
        self.path = FilePath(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db().executescript(SCHEMA.format(seq="", real="REAL", blob="BLOB"))

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.execute("PRAGMA foreign_keys=ON")
        return db

    @contextmanager
    def _tx(self):
        """BEGIN IMMEDIATE (the one writer), COMMIT, or ROLLBACK on any exception."""
        db = self._db()
        db.execute("BEGIN IMMEDIATE")
        try:
            yield db
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")


def without_password(db: str | os.PathLike) -> str:
    """``db`` as it may be printed: a URL's password replaced by ``***``."""
    text = re.sub(r"(://[^:/@]*):[^@]*@", r"\1:***@", str(db))
    return re.sub(r"(?i)(password=)[^&\s]*", r"\1***", text)  # libpq's ?password=...


def is_postgres_url(db: str) -> bool:
    """Whether ``--db`` names a PostgreSQL database (``postgresql://`` or ``postgres://``)."""
    return db.startswith(("postgresql://", "postgres://"))


class StoreError(OgaError, RuntimeError):
    """The job database cannot be opened (the backend's reason in one line)."""


def open_store(db: str | os.PathLike) -> Store:
    """The store at ``db``: a PostgreSQL URL, else an SQLite file.

    Raises
    ------
    StoreError
        When it cannot be opened or created (the URL's password is never in the message).
    """
    if is_postgres_url(str(db)):
        from api.storage_pg import PgStore

        kind = PgStore
    else:
        kind = SqliteStore
    try:
        return kind(db)
    except kind.errors as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise StoreError(f"{without_password(db)}: cannot open the database: {reason}") from None
