"""The job store's interface: jobs, owners, the schema and every query of both backends.

Every change of a job is one transaction. A worker claims a queued job by
incrementing its ``attempts``; that number is the worker's fencing token: every
later write of the worker (progress, result) names it and changes nothing once
the job was cancelled or handed to another worker, so a stale worker can never
overwrite a newer state. A result (status, summary and table) is written in a
single transaction, so a job is either succeeded with its table or not at all.

:class:`Store` holds the queries (written with ``?`` parameters); a backend gives
its connections, its transaction, its schema's spellings and its claim lock:
:class:`api.storage_sqlite.SqliteStore` (one file, one host; the default) and
:class:`api.storage_pg.PgStore` (PostgreSQL: several servers on several hosts
share one queue; a claim takes its row ``FOR UPDATE SKIP LOCKED``).
:func:`api.storage.open_store` picks one from the ``--db`` value.

Owners: a running job records the server that runs it (host, pid, instance id)
and the worker's pid; :meth:`Store.running` lets the server find jobs whose
owner is gone and requeue them (see :mod:`api.workers`).
"""

from __future__ import annotations

import json
import time
import uuid
from abc import ABC, abstractmethod
from dataclasses import dataclass
from datetime import datetime, timezone

from oga.errors import OgaError

__all__ = ["STATUSES", "FINISHED", "TRACE_PREFIX", "SCHEMA", "Owner", "JobRow", "Store",
           "StoreError", "is_identification"]

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


class StoreError(OgaError, RuntimeError):
    """The job database cannot be opened (the backend's reason in one line)."""


class Store(ABC):
    """The job database; safe to share between threads.

    The queries of both backends live here (written with ``?`` parameters); a backend gives
    its connections (:meth:`_db`, :meth:`_tx`, :meth:`close`), its schema's spellings
    (:attr:`_SEQ`) and its claim lock (:attr:`_CLAIM_LOCK`). Open one with
    :func:`api.storage.open_store`.

    Attributes
    ----------
    url : str
        Where the store is, as another process (a worker) opens it: an SQLite file's
        absolute path, or the PostgreSQL URL.
    """

    #: The column that orders jobs created in the same millisecond (insertion order).
    _SEQ = "rowid"
    #: Appended to the claim's choice of a queued job (PostgreSQL: ``FOR UPDATE SKIP LOCKED``).
    _CLAIM_LOCK = ""
    #: Exceptions of the backend (an unusable ``--db`` raises one of them).
    errors: tuple[type[BaseException], ...] = ()
    url: str

    @abstractmethod
    def _db(self):
        """A connection for one read (``execute(sql, args)`` taking ``?``; rows by name)."""

    @abstractmethod
    def _tx(self):
        """A context manager: a write transaction (a connection as :meth:`_db`'s), committed
        at its end, rolled back on any exception."""

    @abstractmethod
    def close(self) -> None:
        """Close this store's connections (of this thread, or of the pool)."""

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
