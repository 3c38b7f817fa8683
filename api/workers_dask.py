"""The service's jobs on a Dask cluster (``oga serve --scheduler tcp://HOST:8786``).

:class:`DaskPool` takes the place of the local :class:`api.workers.WorkerPool`: its
dispatcher thread claims queued jobs from the store (for each worker thread of the
cluster, one to run and one to wait) and submits one Dask task per claimed attempt. The store keeps every rule of the local path: the claim's attempt number
fences every write, the server heartbeats its jobs, and the recovery of other
servers' jobs is :meth:`api.pool.JobPool.recover`'s.

Jobs run in a child process. Dask cannot interrupt a running task, so the task
(:func:`run_on_worker`) hands its job to a job process of its Dask worker thread
(``python -m api.workers_dask``: started on the thread's first job and kept warm
for the next, as a local worker process is; it runs :func:`api.job_process.run_claimed`
with the same niceness, no core file, ``PR_SET_PDEATHSIG``, and the CPU cap as
``RLIMIT_CPU`` counted from the job's start) and watches it every
:data:`~api.pool.WATCH_S`:

- CPU cap: the kernel ends the job process with SIGXCPU; the task fails the job
  with the local path's message; it is not requeued.
- Memory cap: the task reads the job process's resident size; above the cap it
  kills it and fails the job.
- Cancel: the task reads the job's row; once it is no longer this attempt's
  running job (``DELETE``, on this server or on any other one sharing the
  database, or a requeue by the lease rules) it kills the job process. The
  server also cancels the task's future, which drops a task still waiting on the
  cluster.
- Any other death of the job process: the job goes back to the queue, failing
  after :data:`~api.pool.MAX_ATTEMPTS` starts ("WorkerLost"), as locally.

A killed job process is replaced on the thread's next job; the Dask worker lives
on and takes the next task.

Progress and results: the job process writes them to the store itself, exactly
as a local worker (same code, same bytes), so the Dask workers must reach the
database: a PostgreSQL URL from any host, or an SQLite file on the same host. No
result travels through the scheduler, and a ``DELETE`` on another server reaches
the job through the row the task already polls; Dask's pub/sub would add a
second channel with neither property.

A Dask worker lost mid-job: its job process dies with it (``PR_SET_PDEATHSIG``) and
the scheduler runs the task again elsewhere. The first run recorded its job process in the
row (:meth:`~api.store.Store.mark_started`, once per attempt), so the rerun
starts nothing: it requeues the job, which is claimed again as a new attempt,
one more start counted against :data:`~api.pool.MAX_ATTEMPTS`. A stale run's
writes are fenced off by its attempt number, so no job completes twice.
"""

from __future__ import annotations

import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
import traceback

from api.job_process import JobLimits, become_job_process, resident_bytes, run_capped
from api.pool import HEARTBEAT_S, MAX_ATTEMPTS, POLL_S, WATCH_S, JobPool
from api.store import Owner, Store
from api.storage import open_store
from oga import defaults

__all__ = ["DaskPool", "run_on_worker"]

log = logging.getLogger("oga.api")

#: Claimed jobs a server keeps waiting on the cluster per worker thread, besides the running one.
WAITING_PER_THREAD = 1

_stores: dict[str, Store] = {}
_stores_lock = threading.Lock()


def _store_of(db: str) -> Store:
    """One store per database per process (Dask worker or job process), shared by its threads."""
    with _stores_lock:
        if db not in _stores:
            _stores[db] = open_store(db)
        return _stores[db]


def _ours(store: Store, job_id: str, attempt: int) -> bool:
    """Whether the job is still running as this attempt (not cancelled, requeued, finished)."""
    row = store.get(job_id)
    return row is not None and row.status == "running" and row.attempts == attempt


_children = threading.local()


def _child() -> subprocess.Popen:
    """The job process of this Dask worker thread: started on its first job, kept warm for
    the next ones (engine imported, kernels loaded) until it is killed or dies."""
    child = getattr(_children, "proc", None)
    if child is None or child.poll() is not None:
        child = subprocess.Popen([sys.executable, "-m", "api.workers_dask", str(os.getpid())],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        _children.proc = child
    return child


def _end(child: subprocess.Popen) -> None:
    """Kill the job process (a later job starts another one)."""
    child.kill()
    child.wait()
    _children.proc = None


def run_on_worker(db: str, job_id: str, attempt: int, limits: JobLimits) -> str:
    """The Dask task of one attempt of a job: run it in this thread's job process and watch.

    Returns
    -------
    {"succeeded", "failed", "abandoned", "memory", "cpu", "lost", "requeued"}
        How it ended ("lost": the job process died, the job requeued by the lease rules;
        "requeued": this task had run before, on a Dask worker that died).
    """
    store = _store_of(db)
    child = _child()
    if not store.mark_started(job_id, attempt, child.pid):
        if _ours(store, job_id, attempt):  # run again after its Dask worker died
            new = store.requeue(job_id, attempt, MAX_ATTEMPTS)
            log.warning("job %s: its Dask worker was lost; %s", job_id, new)
            return "requeued"
        return "abandoned"
    try:
        child.stdin.write(json.dumps({"db": db, "job": job_id, "attempt": attempt,
                                      "cpu_s": limits.cpu_s}).encode() + b"\n")
        child.stdin.flush()
    except OSError:  # it died meanwhile: told below by its exit code
        pass
    while True:
        if select.select([child.stdout], [], [], WATCH_S)[0]:
            outcome = child.stdout.readline().decode().strip()
            if not outcome:  # the job process died
                break
            if outcome == "memory":  # it ends itself (a fragmented heap)
                _end(child)
            return outcome
        if resident_bytes(child.pid) > limits.memory_bytes:
            _end(child)
            store.fail(job_id, attempt, {"message": limits.memory_message(),
                                         "type": "MemoryLimit"})
            return "memory"
        if not _ours(store, job_id, attempt):  # cancelled, or requeued by the lease rules
            _end(child)
            log.info("job %s: cancelled or requeued; its process %s ended", job_id, child.pid)
            return "abandoned"
    code = child.wait()
    _children.proc = None
    if code == -signal.SIGXCPU:
        store.fail(job_id, attempt, {"message": limits.cpu_message(), "type": "CpuTimeLimit"})
        return "cpu"
    log.warning("job %s: its process %s died (exit code %s)", job_id, child.pid, code)
    store.requeue(job_id, attempt, MAX_ATTEMPTS)
    return "lost"


def _child_main(parent: int) -> None:
    """``python -m api.workers_dask PID``: the job process of a Dask worker thread (``PID``
    the Dask worker's); runs the jobs named on stdin (JSON lines), answers each with its
    outcome; ends after a job that ran out of memory."""
    answers = os.fdopen(os.dup(1), "w")  # the outcomes; anything printed goes to stderr
    os.dup2(2, 1)
    become_job_process(parent)

    for line in sys.stdin:
        spec = json.loads(line)
        store = _store_of(spec["db"])
        job = store.get(spec["job"], with_toolpath=True)
        outcome = "abandoned"
        if job is not None and job.status == "running" and job.attempts == spec["attempt"]:
            outcome = run_capped(store, job, spec["cpu_s"])
        answers.write(outcome + "\n")
        answers.flush()
        if outcome == "memory":
            return


class DaskPool(JobPool):
    """The jobs of the store at ``db_path`` run on the Dask cluster at ``address``.

    The interface of :class:`~api.pool.JobPool` (``start``, ``kill``, ``alive``,
    ``stalled``, ``stop``); :meth:`alive` counts the cluster's workers.

    Parameters
    ----------
    db_path : str
        The job database (reachable from the Dask workers).
    address : str
        The scheduler, ``tcp://HOST:PORT``.
    limits : JobLimits
        CPU time and memory of one attempt of a job.
    stall_s : float
        As :class:`~api.pool.JobPool`'s.
    """

    def __init__(self, db_path, address: str, limits: JobLimits = JobLimits(),
                 stall_s: float = defaults.API_STALL_S) -> None:
        super().__init__(db_path, limits, stall_s)  # db_path: an SQLite file made absolute
        self.address = address
        self.client = None
        self._futures: dict[str, tuple[object, int]] = {}  # job id -> (future, attempt)
        self._threads, self._threads_at = 0, -HEARTBEAT_S

    def start(self) -> None:
        from oga.cli.batch_dask import connect

        self.client = connect(self.address)
        super().start()

    def alive(self) -> int:
        try:
            return len(self.client.nthreads())
        except Exception:  # the scheduler is unreachable: no worker to speak of
            return 0

    def kill(self, job) -> bool:
        """Cancel the task of ``job`` (just cancelled in the store): dropped if it waits on
        the cluster; if it runs, it kills its job process within :data:`~api.pool.WATCH_S`."""
        o = job.owner
        if o is None or o.instance != self.instance:
            return False
        with self._lock:
            entry = self._futures.get(job.id)
        if entry is None:
            return False
        entry[0].cancel()
        log.info("job %s: cancelled; its Dask task told", job.id)
        return True

    def stalled(self) -> list[dict]:
        """As :meth:`JobPool.stalled`, of the jobs whose task has started their process
        (a job waiting for a busy cluster is not stalled)."""
        return [s for s in super().stalled() if s["worker_pid"] is not None]

    def _supervise(self) -> None:
        beat = 0.0
        while not self._halt.wait(POLL_S):
            try:
                self._reap()
                self._dispatch()
                if time.monotonic() - beat >= HEARTBEAT_S:
                    beat = time.monotonic()
                    self._beat()
            except Exception:  # keep supervising whatever happens
                log.error("dispatcher: %s", traceback.format_exc())

    def _capacity(self) -> int:
        """Jobs this server keeps on the cluster: one running and :data:`WAITING_PER_THREAD`
        waiting per worker thread (threads asked at most every HEARTBEAT_S), so that no
        thread idles between two jobs."""
        if time.monotonic() - self._threads_at >= HEARTBEAT_S:
            self._threads = sum(self.client.nthreads().values())
            self._threads_at = time.monotonic()
        return self._threads * (1 + WAITING_PER_THREAD)

    def _dispatch(self) -> None:
        """Claim queued jobs up to :meth:`_capacity`; submit a task for each."""
        owner = Owner(self.host, os.getpid(), self.instance, None)
        while len(self._futures) < self._capacity() and not self._halt.is_set():
            job = self._store.claim(owner)
            if job is None:
                return
            try:
                future = self.client.submit(
                    run_on_worker, self.db_path, job.id, job.attempts, self.limits, pure=False,
                    key=f"oga-job-{job.id}-{job.attempts}")
            except Exception:
                self._store.requeue(job.id, job.attempts)
                raise
            with self._lock:
                self._futures[job.id] = (future, job.attempts)

    def _reap(self) -> None:
        """Forget finished tasks; requeue the job of a task the cluster lost or failed."""
        from distributed.scheduler import KilledWorker

        with self._lock:
            done = {k: v for k, v in self._futures.items() if v[0].done()}
            for k in done:
                del self._futures[k]
        for job_id, (future, attempt) in done.items():
            if future.status == "finished":
                continue
            err = future.exception() if future.status == "error" else None
            if err is None or isinstance(err, KilledWorker):  # cancelled (fenced) or lost
                self._store.requeue(job_id, attempt, MAX_ATTEMPTS)
            else:  # the task itself failed (oga missing on a worker, database unreachable)
                log.error("job %s: its Dask task failed: %s: %s", job_id, type(err).__name__, err)
                self._store.fail(job_id, attempt, {
                    "message": f"the Dask cluster failed the job: {type(err).__name__}: {err}",
                    "type": "ClusterError"})

    def _stop_workers(self) -> None:
        """Cancel this server's tasks (the tasks running them see the requeue that follows
        and kill their job processes) and close the client."""
        if self.client is not None:
            with self._lock:
                futures = [f for f, _ in self._futures.values()]
            if futures:
                self.client.cancel(futures, force=True)
            self.client.close()


if __name__ == "__main__":
    _child_main(int(sys.argv[1]))
