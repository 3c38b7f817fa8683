"""Worker processes that run the stored jobs, and the supervisor that keeps them going.

Each worker is a separate process (``spawn``): it claims the next queued job
from the store, runs :func:`oga.pipeline.run_job`, reports progress into the
store and writes the result in one transaction. The server's event loop never
runs an optimisation.

Recovery: a job whose worker is gone goes back to the queue.

- at start, and every :data:`HEARTBEAT_S`, the supervisor requeues running jobs
  whose server is dead (same host: its pid is gone, or it is this pid under an
  older instance, as after a container restart; other hosts: no heartbeat for
  :data:`LEASE_S`);
- a worker that dies while the server lives (killed, out of memory) is replaced
  and its job requeued; after :data:`MAX_ATTEMPTS` such deaths the job fails.

Workers die with the server (``PR_SET_PDEATHSIG`` on Linux, and a parent check
between jobs and at each progress report); the attempt number fences every
write, so a straggler can never overwrite a newer state.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import signal
import socket
import threading
import time
import traceback
import uuid

from api.schemas import error_body, json_safe
from api.storage import JobRow, Owner, Store

__all__ = ["MAX_ATTEMPTS", "HEARTBEAT_S", "LEASE_S", "WorkerPool", "run_claimed"]

log = logging.getLogger("oga.api")

#: Worker deaths a job may cause before it is failed.
MAX_ATTEMPTS = 3
#: Idle worker's polling period of the queue, s.
POLL_S = 0.2
#: Supervisor period (heartbeat, recovery, respawn), s.
HEARTBEAT_S = 2.0
#: A job of another host's server is requeued after this long without a heartbeat, s.
LEASE_S = 60.0
#: Shortest interval between two progress writes of a worker, s.
PROGRESS_EVERY_S = 0.25


class _Abandoned(Exception):
    """The job was cancelled or handed to another worker: stop it, write nothing."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def run_claimed(store: Store, job: JobRow) -> None:
    """Run a job this process has claimed, and store its outcome.

    A verified schedule stores the summary and the table; a schedule that
    fails verification fails the job with its violations (and keeps the
    summary); a bad input fails it with the error naming line/field.
    """
    from oga.errors import OgaError
    from oga.export import table_npz
    from oga.machine import machine_from_dict
    from oga.options import options_from_dict
    from oga.pipeline import run_job

    parent = os.getppid()
    last = time.monotonic()

    def progress(fraction: float) -> None:
        nonlocal last
        if os.getppid() != parent:
            raise _Abandoned
        now = time.monotonic()
        if now - last >= PROGRESS_EVERY_S:
            last = now
            if not store.progress(job.id, job.attempts, min(float(fraction), 0.99)):
                raise _Abandoned

    try:
        machine = machine_from_dict(job.machine)
        options = options_from_dict(job.options)
        done = run_job(job.toolpath, job.toolpath_format, machine, options, source=job.source,
                       progress=progress)
        result = done.result
        summary = json_safe(done.summary())
        if result.status != "ok":
            error = {"message": "the schedule failed verification: "
                     + "; ".join(result.optimized.violations),
                     "type": "VerificationFailed",
                     "violations": list(result.optimized.violations)}
            store.fail(job.id, job.attempts, error, summary)
        else:
            store.succeed(job.id, job.attempts, summary,
                          table_npz(result, toolpath_sha256=done.toolpath_sha256))
    except _Abandoned:
        log.info("job %s: abandoned (cancelled or requeued)", job.id)
    except OgaError as err:
        store.fail(job.id, job.attempts, error_body(err))
    except Exception as err:  # a bug: the job fails with the reason, the worker lives on
        log.error("job %s: internal error\n%s", job.id, traceback.format_exc())
        store.fail(job.id, job.attempts, {"message": f"internal error: {type(err).__name__}: "
                                                     f"{err}", "type": "InternalError"})


def _die_with_parent(parent: int) -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before prctl
        os._exit(0)


def _worker_main(db_path: str, server_pid: int, instance: str) -> None:
    """Body of a worker process: claim and run jobs as long as the server lives."""
    _die_with_parent(server_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when workers stop
    import oga.pipeline  # noqa: F401  (load the engine before the first job)

    store = Store(db_path)
    owner = Owner(socket.gethostname(), server_pid, instance, os.getpid())
    while os.getppid() == server_pid:
        job = store.claim(owner)
        if job is None:
            time.sleep(POLL_S)
        else:
            run_claimed(store, job)


class WorkerPool:
    """``n`` worker processes on the store at ``db_path``, supervised by a thread.

    Parameters
    ----------
    db_path : path-like
        The job database.
    n : int
        Number of worker processes (jobs run at once).
    """

    def __init__(self, db_path, n: int) -> None:
        if n < 1:
            raise ValueError("a worker pool needs at least one worker")
        self.db_path = str(db_path)
        self.n = n
        self.instance = uuid.uuid4().hex
        self.host = socket.gethostname()
        self._ctx = mp.get_context("spawn")
        self._halt = threading.Event()
        self._procs: list = []
        self._lock = threading.Lock()
        self._store = Store(db_path)
        self._thread = threading.Thread(target=self._supervise, name="oga-supervisor", daemon=True)

    def start(self) -> None:
        """Recover jobs of a dead server, start the workers and the supervisor."""
        self.recover()
        self._thread.start()

    def alive(self) -> int:
        """Number of live worker processes."""
        with self._lock:
            return sum(p.is_alive() for p in self._procs)

    def _spawn(self):
        p = self._ctx.Process(target=_worker_main, name="oga-worker", daemon=True,
                              args=(self.db_path, os.getpid(), self.instance))
        p.start()
        return p

    def _supervise(self) -> None:
        # workers are started from this thread, which lives as long as the pool
        # (PR_SET_PDEATHSIG follows the thread that started the child)
        with self._lock:
            self._procs = [self._spawn() for _ in range(self.n)]
        while not self._halt.wait(HEARTBEAT_S):
            try:
                self._store.heartbeat(self.instance)
                with self._lock:
                    dead = [p for p in self._procs if not p.is_alive()]
                self.recover({p.pid for p in dead})
                with self._lock:
                    for p in dead:
                        log.warning("worker %s died (exit code %s); starting another",
                                    p.pid, p.exitcode)
                        self._procs[self._procs.index(p)] = self._spawn()
            except Exception:  # keep supervising whatever happens
                log.error("supervisor: %s", traceback.format_exc())

    def recover(self, dead_workers: set[int] = frozenset()) -> list[str]:
        """Requeue running jobs whose worker or server is gone; returns their ids."""
        me, now, done = os.getpid(), time.time(), []
        for job in self._store.running():
            o = job.owner
            if o is None:
                continue
            if o.instance == self.instance:
                if o.worker_pid in dead_workers:
                    if self._store.requeue(job.id, job.attempts, MAX_ATTEMPTS):
                        done.append(job.id)
                continue
            if o.host == self.host:
                gone = o.pid == me or not _pid_alive(o.pid)
            else:
                gone = job.heartbeat is None or now - job.heartbeat > LEASE_S
            if gone and self._store.requeue(job.id, job.attempts):
                done.append(job.id)
        if done:
            log.warning("requeued %d job(s) whose worker was gone: %s", len(done), ", ".join(done))
        return done

    def stop(self) -> None:
        """Stop the workers (SIGTERM) and requeue the jobs they were running.

        A worker stopped inside a write leaves nothing: SQLite rolls the transaction back.
        """
        self._halt.set()
        if self._thread.is_alive():
            self._thread.join()
        with self._lock:
            procs = list(self._procs)
        for p in procs:
            p.terminate()
        for p in procs:
            p.join()
        for job in self._store.running():
            if job.owner is not None and job.owner.instance == self.instance:
                self._store.requeue(job.id, job.attempts)
        self._store.close()
