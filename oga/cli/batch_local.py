"""``oga batch``'s programs in worker processes of its own (the default executor).

The workers are spawned, one pipe each for the task, its progress and its
outcome; they ignore SIGINT and SIGTERM (a Ctrl-C or ``timeout`` reaches the whole
process group): the batch kills them when it stops, and on Linux they die with it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as _wait

from oga.cli._signals import STOP_SIGNALS, signals_deferred
from oga.cli.batch_task import BatchTask, run_task

__all__ = ["LocalExecutor"]


def _worker(conn, parent_pid: int) -> None:
    """A worker process: optimise the tasks the parent sends, until it closes the pipe.

    Signals are the parent's business: a worker ignores SIGINT and SIGTERM (a Ctrl-C or
    ``timeout`` reaches the whole process group) and is killed by the parent when the batch
    stops; on Linux it is also killed if the parent dies.
    """
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)  # blocked by the parent at start
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before prctl
        return
    last = 0.0

    def progress(fraction: float) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last >= 0.2 or fraction >= 1.0:
            last = now
            conn.send(("progress", fraction))

    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        conn.send(("done", run_task(task, progress)))


@dataclass
class _Slot:
    """A worker process, its end of the pipe and the task it computes (None: idle)."""

    process: mp.process.BaseProcess
    conn: Connection
    task: BatchTask | None = None


def _start_worker(ctx) -> _Slot:
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_worker, args=(child, os.getpid()), daemon=True,
                          name="oga-batch-worker")
    with signals_deferred():  # the worker starts with them blocked, then ignores them
        process.start()
    child.close()
    return _Slot(process, parent)


def _receive(conn: Connection) -> tuple[list, bool]:
    """The messages a worker has sent, and False if its end of the pipe is closed (it died)."""
    messages = []
    try:
        while conn.poll():
            messages.append(conn.recv())
    except (EOFError, OSError):
        return messages, False
    return messages, True


def _end_worker(slot: _Slot, *, kill: bool) -> None:
    """End a worker: killed at once, or told to stop (pipe closed) and killed if it lingers."""
    slot.conn.close()
    if kill:
        slot.process.kill()
    slot.process.join(timeout=None if kill else 1.0)
    if slot.process.exitcode is None:
        slot.process.kill()
        slot.process.join()


class LocalExecutor:
    """The programs in at most ``jobs`` worker processes of this machine.

    Parameters
    ----------
    jobs : int
        Programs optimised at once (fewer processes when there are fewer programs).
    """

    def __init__(self, jobs: int) -> None:
        self.jobs = jobs

    def label(self, n: int) -> str:
        workers = min(self.jobs, n)
        return f"{workers} process" + ("es" if workers > 1 else "")

    def close(self) -> None:
        pass

    def execute(self, todo: list[BatchTask], finish, bar) -> None:
        """Optimise ``todo``; ``finish(task, outcome)`` as each program ends.

        Whatever ends this function (the last program, a signal, an error), every worker
        is ended before it returns.
        """
        ctx = mp.get_context("spawn")
        workers = min(self.jobs, len(todo))
        pending = list(reversed(todo))  # pop() takes them in input order
        slots: list[_Slot] = []
        partial = {t.index: 0.0 for t in todo}
        finished: set[int] = set()

        def done(task: BatchTask, outcome: dict) -> None:
            finish(task, outcome)
            finished.add(task.index)
            partial[task.index] = 1.0

        try:
            while len(finished) < len(todo):
                while pending and len(slots) < workers:
                    slots.append(_start_worker(ctx))
                _hand_out(slots, pending)
                _wait([s.conn for s in slots] + [s.process.sentinel for s in slots], 0.2)
                for slot in list(slots):
                    _collect(slot, slots, pending, partial, done)
                bar.update(sum(partial.values()) / len(todo))
        finally:
            with signals_deferred():  # a second Ctrl-C must not leave a worker behind
                for slot in slots:
                    _end_worker(slot, kill=True)


def _hand_out(slots: list[_Slot], pending: list[BatchTask]) -> None:
    """Send the next pending task to each idle worker."""
    for slot in slots:
        if slot.task is None and pending:
            slot.task = pending.pop()
            try:
                slot.conn.send(slot.task)
            except OSError:  # the worker died: found by _collect
                pass


def _collect(slot: _Slot, slots: list[_Slot], pending: list, partial: dict, done) -> None:
    """A worker's progress and outcomes; a worker idle for good or dead is ended (its task,
    if it died computing one, failed)."""
    messages, alive = _receive(slot.conn)
    for kind, value in messages:
        if kind == "progress":
            partial[slot.task.index] = value
        else:
            task, slot.task = slot.task, None
            done(task, value)
    if alive and slot.process.is_alive() and (slot.task or pending):
        return
    slots.remove(slot)
    _end_worker(slot, kill=False)
    if slot.task is not None:  # killed (out of memory?) while computing
        code = slot.process.exitcode
        done(slot.task, {"status": "failed", "time_s": 0.0,
                         "reason": f"{slot.task.file}: its worker process "
                         f"died (exit code {code}: out of memory?)"})
