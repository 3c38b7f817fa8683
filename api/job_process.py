"""One job in a job process: run a claimed job under its limits and store its outcome.

Shared by both executors of the service (:class:`api.workers.WorkerPool`'s local
worker processes and :class:`api.workers_dask.DaskPool`'s job processes on the
Dask workers): the same code writes the same bytes to the store.

Limits: each attempt of a job runs under a CPU-time cap (``RLIMIT_CPU`` of its
process, counted from the job's start: the kernel ends the process with SIGXCPU)
and a memory cap (read by the process's watcher from ``/proc``: above it the
watcher ends the process). Job processes die with their parent
(``PR_SET_PDEATHSIG`` on Linux, and a parent check at each progress report); the
attempt number fences every write, so a straggler can never overwrite a newer state.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import math
import os
import resource
import signal
import time
import traceback
from dataclasses import dataclass

from api.schemas import error_body, json_safe
from api.store import JobRow, Store, is_identification
from oga import defaults

__all__ = ["JobLimits", "run_claimed", "PROGRESS_EVERY_S", "WORKER_NICE"]

log = logging.getLogger("oga.api")

#: Shortest interval between two progress writes of a worker, s.
PROGRESS_EVERY_S = 0.25
#: Niceness added to job processes: the server's answers come before the jobs' CPU time.
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


def _progress_writer(store: Store, job: JobRow):
    """The job's progress callback: writes at most every :data:`PROGRESS_EVERY_S`; raises
    :class:`_Abandoned` once the job is no longer this attempt's or the parent is gone."""
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

    return progress


def _run_identification(store: Store, job: JobRow, machine, progress) -> str:
    """An identification: its summary and the identified machine's TOML."""
    from api.identify import run_identification

    ident = run_identification(job.toolpath, job.toolpath_format, machine, job.options,
                               job.source, progress=progress)
    store.succeed(job.id, job.attempts, json_safe(ident.summary()), ident.toml.encode("utf-8"))
    return "succeeded"


def _run_law(store: Store, job: JobRow, machine, progress) -> str:
    """A control-law search: its summary and its files."""
    from api.law import run_law

    summary, files = run_law(job.toolpath, machine, job.options, progress=progress)
    store.succeed(job.id, job.attempts, json_safe(summary), files)
    return "succeeded"


def _run_schedule(store: Store, job: JobRow, machine, progress) -> str:
    """An optimisation: the summary and the table, or the verification's violations."""
    from oga.export.table import table_npz
    from oga.pipeline import run_job, stored_options

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


def _run_kind(store: Store, job: JobRow, progress) -> str:
    """Run the job by its kind (identification, control law, schedule) and store its result."""
    from api.law import is_law
    from oga.model.machine import machine_from_dict

    machine = machine_from_dict(job.machine)
    if is_identification(job):
        return _run_identification(store, job, machine, progress)
    if is_law(job):
        return _run_law(store, job, machine, progress)
    return _run_schedule(store, job, machine, progress)


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

    try:
        return _run_kind(store, job, _progress_writer(store, job))
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


def resident_bytes(pid: int) -> int:
    """Resident memory of process ``pid`` (Linux ``/proc``), bytes; 0 where unknown."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return 0


def cap_cpu(cpu_s: float) -> tuple[int, int]:
    """Cap this process's CPU time at ``cpu_s`` from now; returns the limit to restore."""
    saved = resource.getrlimit(resource.RLIMIT_CPU)
    use = resource.getrusage(resource.RUSAGE_SELF)
    soft = math.ceil(use.ru_utime + use.ru_stime + cpu_s)
    if saved[1] != resource.RLIM_INFINITY:
        soft = min(soft, saved[1])
    resource.setrlimit(resource.RLIMIT_CPU, (soft, saved[1]))
    return saved


def run_capped(store: Store, job: JobRow, cpu_s: float) -> str:
    """:func:`run_claimed` under a CPU-time cap of ``cpu_s`` from now (restored after)."""
    saved = cap_cpu(cpu_s)
    try:
        return run_claimed(store, job)
    finally:
        resource.setrlimit(resource.RLIMIT_CPU, saved)


def become_job_process(parent: int) -> None:
    """Set up this process to run jobs: it dies with ``parent`` (Linux), ignores SIGINT (its
    parent decides when it stops), writes no core file (a job killed at its CPU cap) and is
    niced by :data:`WORKER_NICE`; then the engine is imported, before the first job."""
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    os.nice(WORKER_NICE)
    import oga.pipeline  # noqa: F401  (load the engine before the first job)


def _die_with_parent(parent: int) -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before prctl
        os._exit(0)
