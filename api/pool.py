"""The executors' interface: a pool runs the store's queued jobs and keeps them going.

:class:`JobPool` is what the app drives (``start``, ``kill``, ``alive``, ``stalled``,
``stop``) and what both executors share: the heartbeat of this server's jobs, the
recovery of jobs whose worker or server is gone, the notes on stalled jobs, and
the requeue of this server's jobs at stop. An executor gives its workers:
:class:`api.workers.WorkerPool` (local processes) and
:class:`api.workers_dask.DaskPool` (a Dask cluster); the app picks one
(:func:`api.app.open_pool`).

Recovery: a job whose worker is gone goes back to the queue.

- at start, and every :data:`HEARTBEAT_S`, the supervisor requeues running jobs
  whose server is dead (same host: its pid is gone, or it is this pid under an
  older instance, as after a container restart; other hosts: no heartbeat for
  :data:`LEASE_S`);
- a job that has been started :data:`MAX_ATTEMPTS` times and whose worker or
  server died again fails instead ("WorkerLost"): no job loops forever.

Stalls: the supervisor notes when each running job's progress last moved;
:meth:`JobPool.stalled` lists the jobs that have not moved for ``stall_s``
(``/healthz`` reports them).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from abc import ABC, abstractmethod

from api.job_process import JobLimits
from api.store import JobRow
from api.storage import open_store
from oga import defaults

__all__ = ["MAX_ATTEMPTS", "POLL_S", "HEARTBEAT_S", "WATCH_S", "LEASE_S", "JobPool"]

log = logging.getLogger("oga.api")

#: Times a job may be started before a death of its worker or server fails it.
MAX_ATTEMPTS = 3
#: Idle worker's polling period of the queue, s.
POLL_S = 0.2
#: Supervisor period (heartbeat, recovery, stalls), s; it also wakes at once when a worker dies.
HEARTBEAT_S = 2.0
#: Period of the supervisor's check of the workers' resident memory, s.
WATCH_S = 0.1
#: A job of another host's server is requeued after this long without a heartbeat, s.
LEASE_S = 60.0


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class JobPool(ABC):
    """The jobs of the store at ``db_path``, run by an executor's workers.

    Parameters
    ----------
    db_path : path-like
        The job database (an SQLite file or a PostgreSQL URL).
    limits : JobLimits
        CPU time and memory of one attempt of a job.
    stall_s : float
        A running job whose progress has not moved for this long is reported by
        :meth:`stalled`, s.
    """

    def __init__(self, db_path, limits: JobLimits = JobLimits(),
                 stall_s: float = defaults.API_STALL_S) -> None:
        self._store = open_store(db_path)
        #: The database as the workers open it (an SQLite file by its absolute path).
        self.db_path = self._store.url
        self.limits = limits
        self.stall_s = stall_s
        self.instance = uuid.uuid4().hex
        self.host = socket.gethostname()
        self._halt = threading.Event()
        self._moved: dict[tuple[str, int], tuple[float, float, int]] = {}
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._supervise, name="oga-supervisor", daemon=True)

    # -- what an executor gives -------------------------------------------------------------

    @abstractmethod
    def _supervise(self) -> None:
        """The supervisor thread's body: run the jobs, call :meth:`_beat` every
        :data:`HEARTBEAT_S`, until :attr:`_halt` is set."""

    @abstractmethod
    def alive(self) -> int:
        """Number of live workers."""

    @abstractmethod
    def kill(self, job: JobRow) -> bool:
        """End the run of ``job`` (just cancelled in the store); whether one was ended."""

    @abstractmethod
    def _stop_workers(self) -> None:
        """End every worker (the supervisor has stopped)."""

    # -- shared -------------------------------------------------------------------------------

    def start(self) -> None:
        """Recover jobs of a dead server, start the workers and the supervisor."""
        self.recover()
        self._thread.start()

    def stalled(self) -> list[dict]:
        """Running jobs of this pool whose progress has not moved for ``stall_s``:
        ``{"job", "worker_pid", "seconds"}`` each (seconds since it last moved)."""
        now = time.monotonic()
        with self._lock:
            moved = dict(self._moved)
        running = {(job.id, job.attempts) for job in self._store.running()}  # still running now
        return [{"job": key[0], "worker_pid": pid, "seconds": round(now - since, 1)}
                for key, (_, since, pid) in moved.items()
                if key in running and now - since > self.stall_s]

    def _beat(self) -> None:
        """Heartbeat of this server's jobs, recovery of dead servers' jobs, stalls noted."""
        self._store.heartbeat(self.instance)
        self.recover()
        self._watch()

    def _fail_jobs_of(self, worker_pid: int, message: str, kind: str) -> bool:
        """Fail the job that worker ``worker_pid`` runs; False if it runs none."""
        failed = False
        for job in self._store.running():
            o = job.owner
            if o is not None and o.instance == self.instance and o.worker_pid == worker_pid:
                log.warning("job %s: %s", job.id, message)
                failed |= self._store.fail(job.id, job.attempts, {"message": message,
                                                                  "type": kind})
        return failed

    def _watch(self) -> None:
        """Note when each running job's progress last moved."""
        now, moved = time.monotonic(), {}
        for job in self._store.running():
            o = job.owner
            if o is None or o.instance != self.instance:
                continue
            key = (job.id, job.attempts)
            before = self._moved.get(key)
            moved[key] = (before if before is not None
                          and before[::2] == (job.progress, o.worker_pid)
                          else (job.progress, now, o.worker_pid))
        with self._lock:
            self._moved = moved

    def recover(self, dead_workers: set[int] = frozenset()) -> list[str]:
        """Requeue running jobs whose worker or server is gone; returns their ids.

        A job started :data:`MAX_ATTEMPTS` times fails instead.
        """
        me, now, done = os.getpid(), time.time(), []
        for job in self._store.running():
            o = job.owner
            if o is None:
                continue
            if o.instance == self.instance:
                gone = o.worker_pid in dead_workers
            elif o.host == self.host:
                gone = o.pid == me or not _pid_alive(o.pid)
            else:
                gone = job.heartbeat is None or now - job.heartbeat > LEASE_S
            if gone and self._store.requeue(job.id, job.attempts, MAX_ATTEMPTS):
                done.append(job.id)
        if done:
            log.warning("requeued or failed %d job(s) whose worker was gone: %s", len(done),
                        ", ".join(done))
        return done

    def stop(self) -> None:
        """Stop the supervisor and the workers, and requeue the jobs they were running.

        A worker stopped inside a write leaves nothing: the transaction is rolled back.
        """
        self._halt.set()
        if self._thread.is_alive():
            self._thread.join()
        self._stop_workers()
        for job in self._store.running():
            if job.owner is not None and job.owner.instance == self.instance:
                self._store.requeue(job.id, job.attempts)
        self._store.close()
