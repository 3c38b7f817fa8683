"""Worker processes that run the stored jobs, and the supervisor that keeps them going.

Each worker is a separate process (``spawn``): it claims the next queued job
from the store, runs :func:`oga.pipeline.run_job`, reports progress into the
store and writes the result in one transaction. The server's event loop never
runs an optimisation.

Limits: each attempt of a job runs under a CPU-time cap (``RLIMIT_CPU`` of its
worker, counted from the job's start: the kernel ends the worker with SIGXCPU)
and a memory cap (the supervisor reads each worker's resident size every
:data:`WATCH_S` and ends a worker above it). Either way the supervisor fails the
job ("job exceeded its CPU-time limit of 1800 s", "... its memory limit of
4096 MiB"); it is not requeued, and another worker starts. (``RLIMIT_AS`` is not
used: OpenBLAS spins instead of failing when it cannot allocate.)

Cancelling: ``DELETE`` of a running job kills its worker (SIGKILL, through
:meth:`WorkerPool.kill`); the supervisor wakes on the death and starts another.

Recovery: a job whose worker is gone goes back to the queue.

- at start, and every :data:`HEARTBEAT_S`, the supervisor requeues running jobs
  whose server is dead (same host: its pid is gone, or it is this pid under an
  older instance, as after a container restart; other hosts: no heartbeat for
  :data:`LEASE_S`);
- a worker that dies while the server lives (killed, out of memory) is replaced
  and its job requeued;
- a job that has been started :data:`MAX_ATTEMPTS` times and whose worker or
  server died again fails instead ("WorkerLost"): no job loops forever.

Stalls: the supervisor notes when each running job's progress last moved;
:meth:`WorkerPool.stalled` lists the jobs that have not moved for ``stall_s``
(``/healthz`` reports them).

Workers die with the server (``PR_SET_PDEATHSIG`` on Linux, and a parent check
between jobs and at each progress report); the attempt number fences every
write, so a straggler can never overwrite a newer state.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import math
import multiprocessing as mp
import os
import resource
import signal
import socket
import threading
import time
import traceback
import uuid
from dataclasses import dataclass
from multiprocessing.connection import wait as wait_ready

from api.schemas import error_body, json_safe
from api.storage import JobRow, Owner, Store, is_identification, open_store
from oga import defaults

__all__ = ["MAX_ATTEMPTS", "HEARTBEAT_S", "LEASE_S", "JobLimits", "WorkerPool", "run_claimed"]

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
#: Shortest interval between two progress writes of a worker, s.
PROGRESS_EVERY_S = 0.25
#: Niceness added to worker processes: the server's answers come before the jobs' CPU time.
WORKER_NICE = 10


@dataclass(frozen=True)
class JobLimits:
    """What one attempt of a job may use.

    Attributes
    ----------
    cpu_s : float
        CPU time, s (rounded up to whole seconds).
    memory_bytes : int
        Resident memory of the worker running the job, bytes.
    """

    cpu_s: float = defaults.API_JOB_CPU_S
    memory_bytes: int = defaults.API_JOB_MEMORY_BYTES

    def cpu_message(self) -> str:
        return f"job exceeded its CPU-time limit of {self.cpu_s:g} s (the server's --job-cpu-s)"

    def memory_message(self) -> str:
        return (f"job exceeded its memory limit of {self.memory_bytes / 2**20:g} MiB "
                "(the server's --job-memory-mb)")


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


def run_claimed(store: Store, job: JobRow) -> str:
    """Run a job this process has claimed, and store its outcome.

    An identification stores its summary and the identified machine's TOML (a fit that
    does not explain the trace too: its status, ``poor``, is in the summary). A verified
    schedule stores the summary and the table; a schedule that
    fails verification fails the job with its violations (and keeps the
    summary); a bad input fails it with the error naming line/field; a
    ``MemoryError`` fails it.

    Returns
    -------
    {"succeeded", "failed", "abandoned", "memory"}
        What happened ("memory": failed for want of memory; the caller should
        end this process, whose heap may be fragmented).
    """
    from oga.errors import OgaError
    from oga.export.table import table_npz
    from oga.model.machine import machine_from_dict
    from oga.pipeline import run_job, stored_options

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
        if is_identification(job):
            from api.identify import run_identification

            ident = run_identification(job.toolpath, job.toolpath_format, machine, job.options,
                                       job.source, progress=progress)
            store.succeed(job.id, job.attempts, json_safe(ident.summary()),
                          ident.toml.encode("utf-8"))
            return "succeeded"
        from api.law import is_law

        if is_law(job):
            from api.law import run_law

            summary, files = run_law(job.toolpath, machine, job.options, progress=progress)
            store.succeed(job.id, job.attempts, json_safe(summary), files)
            return "succeeded"
        # one thread per job unless its options say otherwise: jobs run side by side
        options, read = stored_options(job.options, threads=job.options.get("threads") or 1)
        done = run_job(job.toolpath, job.toolpath_format, machine, options, source=job.source,
                       progress=progress, setpoints_options=read)
        result = done.result
        summary = json_safe(done.summary())
        if result.status != "ok":
            error = {"message": "the schedule failed verification: "
                     + "; ".join(result.optimized.violations),
                     "type": "VerificationFailed",
                     "violations": list(result.optimized.violations)}
            store.fail(job.id, job.attempts, error, summary)
            return "failed"
        store.succeed(job.id, job.attempts, summary,
                      table_npz(result, toolpath_sha256=done.toolpath_sha256,
                                setpoints_source=None if done.recorded is None
                                else done.recorded.source))
        return "succeeded"
    except _Abandoned:
        log.info("job %s: abandoned (cancelled or requeued)", job.id)
        return "abandoned"
    except OgaError as err:
        store.fail(job.id, job.attempts, error_body(err))
        return "failed"
    except MemoryError:
        pass  # reported below, once this frame's references to the job's arrays are gone
    except Exception as err:  # a bug: the job fails with the reason, the worker lives on
        log.error("job %s: internal error\n%s", job.id, traceback.format_exc())
        store.fail(job.id, job.attempts, {"message": f"internal error: {type(err).__name__}: "
                                                     f"{err}", "type": "InternalError"})
        return "failed"
    gc.collect()
    store.fail(job.id, job.attempts, {"message": "job ran out of memory (an allocation failed)",
                                      "type": "MemoryLimit"})
    return "memory"


_PAGE = os.sysconf("SC_PAGE_SIZE")


def _resident_bytes(pid: int) -> int:
    """Resident memory of process ``pid`` (Linux ``/proc``), bytes; 0 where unknown."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return 0


def _cap_cpu(cpu_s: float) -> tuple[int, int]:
    """Cap this process's CPU time at ``cpu_s`` from now; returns the limit to restore."""
    saved = resource.getrlimit(resource.RLIMIT_CPU)
    use = resource.getrusage(resource.RUSAGE_SELF)
    soft = math.ceil(use.ru_utime + use.ru_stime + cpu_s)
    if saved[1] != resource.RLIM_INFINITY:
        soft = min(soft, saved[1])
    resource.setrlimit(resource.RLIMIT_CPU, (soft, saved[1]))
    return saved


def _die_with_parent(parent: int) -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before prctl
        os._exit(0)


def _worker_main(db_path: str, server_pid: int, instance: str, limits: JobLimits) -> None:
    """Body of a worker process: claim and run jobs as long as the server lives.

    Ends after a job that ran out of memory (the supervisor starts another worker).
    """
    _die_with_parent(server_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when workers stop
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a job killed at its CPU cap: no core file
    os.nice(WORKER_NICE)
    import oga.pipeline  # noqa: F401  (load the engine before the first job)

    store = open_store(db_path)
    owner = Owner(socket.gethostname(), server_pid, instance, os.getpid())
    while os.getppid() == server_pid:
        job = store.claim(owner)
        if job is None:
            time.sleep(POLL_S)
            continue
        saved = _cap_cpu(limits.cpu_s)
        try:
            outcome = run_claimed(store, job)
        finally:
            resource.setrlimit(resource.RLIMIT_CPU, saved)
        if outcome == "memory":
            return


class WorkerPool:
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
        self.db_path = str(db_path)
        self.n = n
        self.limits = limits
        self.stall_s = stall_s
        self.instance = uuid.uuid4().hex
        self.host = socket.gethostname()
        self._ctx = mp.get_context("spawn")
        self._halt = threading.Event()
        self._procs: list = []
        self._killed: set[int] = set()
        self._moved: dict[tuple[str, int], tuple[float, float, int]] = {}
        self._lock = threading.Lock()
        self._store = open_store(db_path)
        self._thread = threading.Thread(target=self._supervise, name="oga-supervisor", daemon=True)

    def start(self) -> None:
        """Recover jobs of a dead server, start the workers and the supervisor."""
        self.recover()
        self._thread.start()

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

    def _beat(self) -> None:
        """Heartbeat of this server's jobs, recovery of dead servers' jobs, stalls noted."""
        self._store.heartbeat(self.instance)
        self.recover()
        self._watch()

    def _check_memory(self) -> None:
        """Fail the job of a worker above the memory limit, and end that worker."""
        with self._lock:
            over = [p.pid for p in self._procs if p.pid not in self._killed
                    and _resident_bytes(p.pid) > self.limits.memory_bytes]
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
