"""One program of ``oga batch``: the task an executor runs, its run, its outcome.

An executor (:class:`Executor`: :class:`oga.cli.batch_local.LocalExecutor`, this
machine's processes, or :class:`oga.cli.batch_dask.DaskExecutor`, a Dask cluster)
runs :func:`run_task` on each :class:`BatchTask` and hands every outcome to the
batch, which writes the outputs here; ``oga batch`` picks the executor
(:func:`oga.cli.batch.open_executor`).

An outcome is a dict: ``{"status": "ok", "summary", "tables": {name: text}, "time_s"}``
or ``{"status": "failed", "reason", "time_s"[, "summary"]}`` (the reason names the file
first).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path as FilePath
from typing import Callable, Protocol

from oga.cli._common import flag_message, toolpath_message
from oga.cli._progress import ProgressBar

__all__ = ["BatchTask", "Executor", "run_task", "failed_outcome", "output_names"]


@dataclass(frozen=True)
class BatchTask:
    """One program to optimise (sent to a worker process or a cluster's worker)."""

    index: int
    file: str
    stem: str
    formats: tuple[str, ...]
    machine: dict
    options: dict
    #: The program's text and format, read by the batch (a cluster's worker may not see the
    #: file); None: the worker reads ``file``.
    text: str | None = None
    fmt: str | None = None


class Executor(Protocol):
    """Where the programs of a batch run."""

    def label(self, n: int) -> str:
        """What runs ``n`` programs, for the progress bar (``4 processes``, ``Dask cluster
        tcp://...``)."""

    def execute(self, todo: list[BatchTask], finish: Callable[[BatchTask, dict], None],
                bar: ProgressBar) -> None:
        """Run every task of ``todo``; ``finish(task, outcome)`` as each one ends (in this
        thread); ``bar`` updated. Whatever ends it (the last program, a signal, an error),
        the work still running is ended before it returns."""

    def close(self) -> None:
        """Release the executor (a cluster's client)."""


def output_names(stem: str, formats) -> tuple[list[str], str]:
    """The table files of a program (one per format) and its summary file."""
    from oga.export.table import TABLE_FORMATS

    return [stem + TABLE_FORMATS[f][0] for f in formats], f"{stem}.summary.json"


def _c_name(stem: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", stem)
    return f"oga_{name}"[:63]


def run_task(task: BatchTask, progress) -> dict:
    """In a worker: optimise one program; returns its outputs or its failure (the reason
    names the file first)."""
    from feedplan.read import read_file
    from oga.export.table import table_c_header, table_csv, table_json
    from oga.model.machine import machine_from_dict
    from oga.options import options_from_dict
    from oga.pipeline import run_job

    t0 = time.perf_counter()
    try:
        text, fmt = read_file(task.file) if task.text is None else (task.text, task.fmt)
        # one thread per program unless --threads says otherwise: programs run side by side
        options = options_from_dict(task.options, threads=task.options.get("threads") or 1)
        job = run_job(text, fmt, machine_from_dict(task.machine), options,
                      source=FilePath(task.file).name, progress=progress)
        res = job.result
        summary = job.summary()
        if res.status != "ok":
            return {"status": "failed", "summary": summary, "time_s": time.perf_counter() - t0,
                    "reason": f"{task.file}: verification failed: "
                              + "; ".join(res.optimized.violations)}
        render = {
            "csv": lambda: table_csv(res),
            "json": lambda: table_json(res, toolpath_sha256=job.toolpath_sha256),
            "c": lambda: table_c_header(res, _c_name(task.stem),
                                        toolpath_sha256=job.toolpath_sha256),
        }
        tables = dict(zip(output_names(task.stem, task.formats)[0],
                          (render[f]() for f in task.formats)))
        return {"status": "ok", "summary": summary, "tables": tables,
                "time_s": time.perf_counter() - t0}
    except Exception as err:  # a bug must not stop the other programs
        return failed_outcome(task, err, time.perf_counter() - t0)


def failed_outcome(task: BatchTask, err: Exception, time_s: float = 0.0) -> dict:
    """The outcome of a program that failed with ``err`` (the reason names the file first)."""
    from oga.errors import GcodeError, OgaError, OptionError, ToolpathError

    if isinstance(err, (GcodeError, ToolpathError)):
        reason = str(toolpath_message(err, task.file))
    elif isinstance(err, OptionError):
        reason = f"{task.file}: {flag_message(err)}"
    elif isinstance(err, OgaError):
        reason = f"{task.file}: {err}"
    else:
        reason = f"{task.file}: internal error: {type(err).__name__}: {err}"
    return {"status": "failed", "reason": reason, "time_s": time_s}
