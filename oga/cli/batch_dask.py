"""``oga batch --scheduler tcp://HOST:8786``: the programs of a batch on a Dask cluster.

The batch reads every program itself and sends its text (a worker on another host
need not see the file); a worker optimises it with the same code as a local worker
process (:func:`oga.cli.batch._run_one`) and returns the rendered tables; the batch
writes them as a local run does. A worker lost mid-program costs a retry of that
program only (the scheduler hands it to another worker; after
``distributed.scheduler.allowed-failures`` deaths it fails, named). SIGINT or
SIGTERM cancels the batch's tasks on the cluster (a task already computing ends
when its program does; its result is dropped).
"""

from __future__ import annotations

import sys
import uuid
from dataclasses import replace
from pathlib import Path as FilePath

__all__ = ["connect", "execute_on"]


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


def _run_remote(task) -> dict:
    """On a Dask worker: optimise one program (no progress reports)."""
    from oga.cli.batch import _run_one

    return _run_one(task, lambda fraction: None)


def execute_on(client, out: FilePath, todo: list, outcomes: dict[int, dict], *, finish) -> None:
    """Optimise ``todo`` on the cluster of ``client``; ``finish(out, task, outcome, outcomes,
    bar)`` writes each program's outputs and prints its line as it finishes.

    Whatever ends this function (the last program, a signal, an error), the batch's tasks
    still on the cluster are cancelled before it returns.
    """
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    from feedplan.read import read_file
    from oga.cli._progress import ProgressBar
    from oga.cli.batch import _failed

    bar = ProgressBar(f"batch ({len(todo)} program{'s' * (len(todo) > 1)}, Dask cluster "
                      f"{client.scheduler.address})", enabled=sys.stderr.isatty())
    run = uuid.uuid4().hex[:8]
    futures = {}
    with bar:
        try:
            for task in todo:
                try:
                    text, fmt = read_file(task.file)
                except Exception as err:
                    finish(out, task, _failed(task, err), outcomes, bar)
                    continue
                future = client.submit(_run_remote, replace(task, text=text, fmt=fmt),
                                       pure=False, key=f"oga-batch-{run}-{task.index}-{task.stem}")
                futures[future] = task
            for future in as_completed(list(futures), loop=client.loop):
                task = futures.pop(future)
                try:
                    outcome = future.result()
                except KilledWorker:
                    outcome = {"status": "failed", "time_s": 0.0,
                               "reason": f"{task.file}: the Dask workers running it died "
                               "too often (KilledWorker; out of memory?)"}
                except Exception as err:  # cancelled on the cluster, a worker without oga...
                    outcome = {"status": "failed", "time_s": 0.0,
                               "reason": f"{task.file}: the Dask cluster failed it: "
                               f"{type(err).__name__}: {err}"}
                finish(out, task, outcome, outcomes, bar)
                bar.update(len(outcomes) / len(todo))
        finally:
            if futures:
                client.cancel(list(futures), force=True)
