"""The service's jobs in local worker processes (``oga serve --workers N``).

Each worker is a separate process (``spawn``): it claims the next queued job
from the store, runs :func:`api.job_process.run_claimed`, reports progress into the
store and writes the result in one transaction. The server's event loop never
runs an optimisation.

Limits: each attempt of a job runs under a CPU-time cap (``RLIMIT_CPU`` of its
worker, counted from the job's start: the kernel ends the worker with SIGXCPU)
and a memory cap (the supervisor reads each worker's resident size every
:data:`~api.pool.WATCH_S` and ends a worker above it). Either way the supervisor fails the
job ("job exceeded its CPU-time limit of 1800 s", "... its memory limit of
4096 MiB"); it is not requeued, and another worker starts. (``RLIMIT_AS`` is not
used: OpenBLAS spins instead of failing when it cannot allocate.)

Cancelling: ``DELETE`` of a running job kills its worker (SIGKILL, through
:meth:`WorkerPool.kill`); the supervisor wakes on the death and starts another.

Recovery (:class:`api.pool.JobPool`): a job whose worker is gone goes back to the
queue; a worker that dies while the server lives (killed, out of memory) is
replaced and its job requeued, failing after :data:`~api.pool.MAX_ATTEMPTS` starts.

Workers die with the server (``PR_SET_PDEATHSIG`` on Linux, and a parent check
between jobs and at each progress report); the attempt number fences every
write, so a straggler can never overwrite a newer state.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import socket
import time
import traceback
from multiprocessing.connection import wait as wait_ready

from api.job_process import JobLimits, become_job_process, resident_bytes, run_capped, run_claimed
from api.pool import HEARTBEAT_S, LEASE_S, MAX_ATTEMPTS, POLL_S, WATCH_S, JobPool
from api.store import JobRow, Owner
from api.storage import open_store
from oga import defaults

__all__ = ["MAX_ATTEMPTS", "HEARTBEAT_S", "LEASE_S", "JobLimits", "WorkerPool", "run_claimed"]

log = logging.getLogger("oga.api")


def _worker_main(db_path: str, server_pid: int, instance: str, limits: JobLimits) -> None:
    """Body of a worker process: claim and run jobs as long as the server lives.

    Ends after a job that ran out of memory (the supervisor starts another worker).
    """
    become_job_process(server_pid)
    store = open_store(db_path)
    owner = Owner(socket.gethostname(), server_pid, instance, os.getpid())
    while os.getppid() == server_pid:
        job = store.claim(owner)
        if job is None:
            time.sleep(POLL_S)
            continue
        if run_capped(store, job, limits.cpu_s) == "memory":
            return


class WorkerPool(JobPool):
    """``n`` worker processes on the store at ``db_path``, supervised by a thread.

    Parameters
    ----------
    db_path : path-like
        The job database.
    n : int
        Number of worker processes (jobs run at once).
    limits : JobLimits
        CPU time and memory of one attempt of a job.
    stall_s : float
        A running job whose progress has not moved for this long is reported by
        :meth:`stalled`, s.
    """

    def __init__(self, db_path, n: int, limits: JobLimits = JobLimits(),
                 stall_s: float = defaults.API_STALL_S) -> None:
        if n < 1:
            raise ValueError("a worker pool needs at least one worker")
        super().__init__(db_path, limits, stall_s)
        self.n = n
        self._ctx = mp.get_context("spawn")
        self._procs: list = []
        self._killed: set[int] = set()

    def alive(self) -> int:
        """Number of live worker processes."""
        with self._lock:
            return sum(p.is_alive() for p in self._procs)

    def kill(self, job: JobRow) -> bool:
        """End the worker that runs ``job`` (just cancelled) at once; another one starts.

        Only a worker of this pool is ended, and only while the job names it as its
        owner; returns whether one was. The job's writes were fenced off by the cancel.
        """
        o = job.owner
        if o is None or o.instance != self.instance:
            return False
        with self._lock:
            if o.worker_pid not in {p.pid for p in self._procs}:  # reaped (and replaced)
                return False  # only under this lock: the pid cannot have been reused
            self._killed.add(o.worker_pid)
            os.kill(o.worker_pid, signal.SIGKILL)
        log.info("job %s: cancelled; worker %s ended", job.id, o.worker_pid)
        return True

    def _spawn(self):
        p = self._ctx.Process(target=_worker_main, name="oga-worker", daemon=True,
                              args=(self.db_path, os.getpid(), self.instance, self.limits))
        p.start()
        return p

    def _supervise(self) -> None:
        # workers are started from this thread, which lives as long as the pool
        # (PR_SET_PDEATHSIG follows the thread that started the child)
        with self._lock:
            self._procs = [self._spawn() for _ in range(self.n)]
        beat = 0.0
        while not self._halt.is_set():
            with self._lock:
                sentinels = [p.sentinel for p in self._procs]
            wait_ready(sentinels, timeout=WATCH_S)  # wakes at once when a worker dies
            if self._halt.is_set():
                break
            try:
                self._check_memory()
                self._replace_dead()
                if time.monotonic() - beat >= HEARTBEAT_S:
                    beat = time.monotonic()
                    self._beat()
            except Exception:  # keep supervising whatever happens
                log.error("supervisor: %s", traceback.format_exc())

    def _check_memory(self) -> None:
        """Fail the job of a worker above the memory limit, and end that worker."""
        with self._lock:
            over = [p.pid for p in self._procs if p.pid not in self._killed
                    and resident_bytes(p.pid) > self.limits.memory_bytes]
        for pid in over:
            if self._fail_jobs_of(pid, self.limits.memory_message(), "MemoryLimit"):
                with self._lock:
                    self._killed.add(pid)
                    os.kill(pid, signal.SIGKILL)  # not reaped yet: the pid is still ours

    def _replace_dead(self) -> None:
        with self._lock:
            dead = [p for p in self._procs if not p.is_alive()]
        if not dead:
            return
        for p in dead:
            if p.exitcode == -signal.SIGXCPU:
                self._fail_jobs_of(p.pid, self.limits.cpu_message(), "CpuTimeLimit")
        self.recover({p.pid for p in dead})
        with self._lock:
            for p in dead:
                if p.pid in self._killed:
                    self._killed.discard(p.pid)
                elif p.exitcode != 0:
                    log.warning("worker %s died (exit code %s); starting another",
                                p.pid, p.exitcode)
                self._procs[self._procs.index(p)] = self._spawn()
        self._watch()

    def _stop_workers(self) -> None:
        """SIGTERM to every worker, and wait for them."""
        with self._lock:
            procs = list(self._procs)
        for p in procs:
            p.terminate()
        for p in procs:
            p.join()
