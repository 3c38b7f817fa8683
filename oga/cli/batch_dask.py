"""``oga batch --scheduler tcp://HOST:8786``: the programs of a batch on a Dask cluster.

The batch reads every program itself and sends its text (a worker on another host
need not see the file); a worker optimises it with the same code as a local worker
process (:func:`oga.cli.batch_task.run_task`) and returns the rendered tables; the batch
writes them as a local run does. A worker lost mid-program costs a retry of that
program only (the scheduler hands it to another worker; after
``distributed.scheduler.allowed-failures`` deaths it fails, named). SIGINT or
SIGTERM cancels the batch's tasks on the cluster (a task already computing ends
when its program does; its result is dropped).
"""

from __future__ import annotations

import uuid
from dataclasses import replace

from oga.cli.batch_task import BatchTask, failed_outcome, run_task

__all__ = ["connect", "DaskExecutor"]


def connect(address: str):
    """A client of the scheduler at ``address``; an unreachable one is the user's error."""
    from distributed import Client
    from distributed.comm.addressing import parse_address, parse_host_port

    from oga.defaults import DASK_CONNECT_S
    from oga.errors import InputError

    try:  # a malformed address is refused before a Client exists (it would linger)
        scheme, where = parse_address(address)
        if scheme in ("tcp", "tls"):
            parse_host_port(where)
    except ValueError as err:
        raise InputError(f"--scheduler {address!r}: expected tcp://HOST:PORT ({err})") from None
    try:
        return Client(address, timeout=DASK_CONNECT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError, TypeError) as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise InputError(f"--scheduler {address}: cannot reach the Dask scheduler: "
                         f"{reason}") from None


def _run_remote(task: BatchTask) -> dict:
    """On a Dask worker: optimise one program (no progress reports)."""
    return run_task(task, lambda fraction: None)


class DaskExecutor:
    """The programs on the Dask cluster of the scheduler at ``address`` (connected at once:
    an unreachable scheduler is the user's error, :class:`~oga.errors.InputError`)."""

    def __init__(self, address: str) -> None:
        self.client = connect(address)

    def label(self, n: int) -> str:
        return f"Dask cluster {self.client.scheduler.address}"

    def close(self) -> None:
        self.client.close()

    def execute(self, todo: list[BatchTask], finish, bar) -> None:
        """Optimise ``todo`` on the cluster; ``finish(task, outcome)`` as each program ends.

        Whatever ends this function (the last program, a signal, an error), the batch's
        tasks still on the cluster are cancelled before it returns.
        """
        from distributed import as_completed

        futures: dict = {}
        try:
            self._submit(todo, finish, futures)
            for future in as_completed(list(futures), loop=self.client.loop):
                task = futures.pop(future)
                finish(task, _outcome(task, future))
                bar.update((len(todo) - len(futures)) / len(todo))
        finally:
            if futures:
                self.client.cancel(list(futures), force=True)

    def _submit(self, todo: list[BatchTask], finish, futures: dict) -> None:
        """Read each program here and submit it with its text (a program that cannot be
        read is finished at once, failed)."""
        from feedplan.read import read_file

        run = uuid.uuid4().hex[:8]
        for task in todo:
            try:
                text, fmt = read_file(task.file)
            except Exception as err:
                finish(task, failed_outcome(task, err))
                continue
            future = self.client.submit(_run_remote, replace(task, text=text, fmt=fmt),
                                        pure=False, key=f"oga-batch-{run}-{task.index}-{task.stem}")
            futures[future] = task


def _outcome(task: BatchTask, future) -> dict:
    """A finished task's outcome; a task the cluster failed is a failed program."""
    from distributed.scheduler import KilledWorker

    try:
        return future.result()
    except KilledWorker:
        return {"status": "failed", "time_s": 0.0,
                "reason": f"{task.file}: the Dask workers running it died "
                "too often (KilledWorker; out of memory?)"}
    except Exception as err:  # cancelled on the cluster, a worker without oga...
        return {"status": "failed", "time_s": 0.0,
                "reason": f"{task.file}: the Dask cluster failed it: "
                f"{type(err).__name__}: {err}"}
