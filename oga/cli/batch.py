"""``oga batch``: optimise many programs in parallel processes, resumably.

Per program ``<stem>`` it writes ``<stem>.<suffix>`` for each table format and
``<stem>.summary.json``, every file atomically. The summary is written last and
removed first when a program is redone, so a summary always belongs to the
tables beside it; a program is up to date (skipped) when its summary says
``ok`` for the same toolpath text, machine and options and its tables exist.

Programs run on an executor (:class:`oga.cli.batch_task.Executor`) picked by
:func:`open_executor`: by default worker processes of the batch's own
(:mod:`oga.cli.batch_local`; spawned, one pipe each for the task, its progress and
its outcome), which ignore SIGINT and SIGTERM: on either signal the batch kills
them and returns 128 + the signal's number. A program's files are written with
the signals deferred, so they are all there or all absent.

With ``--scheduler tcp://HOST:8786`` the programs run on an existing Dask
cluster instead (:mod:`oga.cli.batch_dask`): the batch reads each program and
sends its text, a worker returns the rendered tables, and the batch writes them
here exactly as a local run does.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path as FilePath

from oga.cli._common import (
    add_plan_args,
    add_search_args,
    check_files,
    options_from_args,
    output_folder,
    write_json,
    write_text,
)
from oga.cli._progress import ProgressBar
from oga.cli._signals import STOP_SIGNALS, signals_deferred
from oga.cli.batch_local import LocalExecutor
from oga.cli.batch_task import BatchTask, Executor, output_names

__all__ = ["register", "run", "open_executor"]

#: Formats ``oga batch`` writes: the text formats of oga.export.TABLE_FORMATS.
BATCH_TABLE_FORMATS = ("csv", "json", "c")


def register(sub: argparse._SubParsersAction) -> None:
    from oga.defaults import BATCH_FORMATS

    p = sub.add_parser(
        "batch",
        help="optimise many toolpaths in parallel (resumable)",
        description="Optimise every program: one gain table per format and one summary JSON "
        "per program in DIR. Programs already done with the same text, machine and options "
        "are skipped, so an interrupted batch resumes where it stopped. A line per program is "
        "printed as it finishes; Ctrl-C or SIGTERM stops the batch and its workers at once "
        "(exit 130 / 143), keeping the finished programs' outputs.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="toolpath files (.ngc .nc .gcode .tap .csv .json ...) or folders of them")
    add_plan_args(p, "each program's")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="folder of the outputs (created if missing; its parent must exist)")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="programs optimised at once, each in a process of its own (default: "
                   "one per CPU; at most 4 per CPU)")
    p.add_argument("--scheduler", default="local", metavar="ADDRESS",
                   help="run the programs on the Dask cluster of this scheduler "
                   "(tcp://HOST:8786), the outputs still written here; default local "
                   "(this machine's processes, --jobs)")
    p.add_argument("--format", default=",".join(BATCH_FORMATS), metavar="LIST",
                   help=f"table formats, comma-separated from {','.join(BATCH_TABLE_FORMATS)} "
                   f"(default {','.join(BATCH_FORMATS)})")
    add_search_args(p)
    p.set_defaults(func=run)


def _expand(inputs: list[str]) -> list[FilePath]:
    from feedplan.read import SUFFIXES
    from oga.errors import InputError

    files = []
    for name in inputs:
        p = FilePath(name)
        if os.path.isdir(p):  # os.path's tests: False, never OSError, on a bad name
            files += sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in SUFFIXES)
        elif os.path.isfile(p):
            files.append(p)
        elif os.path.lexists(p):  # a FIFO or a device would block or never end
            raise InputError(f"{name}: not a regular file")
        else:
            raise InputError(f"{name}: no such file or folder")
    if not files:
        raise InputError("no toolpath among the inputs")
    return files


def _all_outputs(stem: str, formats) -> list[str]:
    tables, summary_name = output_names(stem, formats)
    return [*tables, summary_name]


def _up_to_date(out: FilePath, task: BatchTask, machine_sha256: str) -> bool:
    from feedplan.read import read_file
    from oga.pipeline import toolpath_sha256

    tables, summary_name = output_names(task.stem, task.formats)
    try:
        summary = json.loads((out / summary_name).read_text(encoding="utf-8"))
        text, _ = read_file(task.file)
    except (OSError, ValueError):  # ValueError: bad JSON, or the file's ToolpathError
        return False
    return (summary.get("status") == "ok"
            and summary.get("toolpath_sha256") == toolpath_sha256(text)
            and summary.get("machine_sha256") == machine_sha256
            and _result_options(summary.get("options")) == _result_options(task.options)
            and all((out / t).is_file() for t in tables))


def _result_options(options) -> dict | None:
    """The options that decide a program's result: all but ``threads`` (a program is run on one
    thread unless told, and the result is the same bits on any number)."""
    if not isinstance(options, dict):
        return None
    return {k: v for k, v in options.items() if k != "threads"}


def _store(out: FilePath, task: BatchTask, outcome: dict) -> None:
    """Write a program's outputs: old summary removed first, tables, then the summary."""
    tables, summary_name = output_names(task.stem, task.formats)
    (out / summary_name).unlink(missing_ok=True)
    if outcome["status"] == "ok":
        for name, text in outcome["tables"].items():
            write_text(out / name, text)
    else:  # a failed program keeps no table from an earlier run
        for name in tables:
            (out / name).unlink(missing_ok=True)
    if "summary" in outcome:
        write_json(out / summary_name, outcome["summary"])


def run(args: argparse.Namespace) -> int:
    from oga.model.machine import load_machine

    formats = _formats(args.format)
    jobs = _jobs(args)
    check_files(args)
    machine = load_machine(args.machine)
    options = options_from_args(args).as_dict()
    files = _expand(args.inputs)
    _check_stems(files, formats, args.out)
    out = output_folder("--out", args.out)
    tasks = [BatchTask(i, str(f), f.stem, formats, machine.model_dump(mode="json"), options)
             for i, f in enumerate(files)]
    _remove_parts(out, tasks)
    digest = machine.digest()
    skipped = {t.index for t in tasks if _up_to_date(out, t, digest)}
    for t in tasks:
        if t.index in skipped:
            print(f"skipped  {FilePath(t.file).name} (up to date)", flush=True)
    todo = [t for t in tasks if t.index not in skipped]
    outcomes: dict[int, dict] = {}
    t0 = time.perf_counter()
    if todo:
        stopped = _execute(open_executor(args.scheduler, jobs), out, todo, outcomes)
        if stopped:
            return stopped
    _report(tasks, skipped, outcomes, out, time.perf_counter() - t0)
    return 1 if any(o["status"] != "ok" for o in outcomes.values()) else 0


def _formats(text: str) -> tuple[str, ...]:
    """The ``--format`` list, checked."""
    from oga.errors import InputError

    formats = tuple(f.strip() for f in text.split(",") if f.strip())
    bad = [f for f in formats if f not in BATCH_TABLE_FORMATS]
    if bad or not formats or len(set(formats)) != len(formats):
        raise InputError(f"--format: expected names from {','.join(BATCH_TABLE_FORMATS)}, "
                         f"each once; got {text!r}")
    return formats


def _jobs(args: argparse.Namespace) -> int:
    """``--jobs``, checked (a local run's only: a cluster runs as many as it has threads)."""
    from oga.defaults import BATCH_MAX_JOBS_PER_CPU
    from oga.errors import InputError

    cpus = os.cpu_count() or 1
    if args.scheduler != "local" and args.jobs is not None:
        raise InputError("--jobs is for a local run: a Dask cluster runs as many programs at "
                         "once as its workers have threads")
    jobs = cpus if args.jobs is None else args.jobs
    if not 1 <= jobs <= BATCH_MAX_JOBS_PER_CPU * cpus:
        raise InputError(f"--jobs must be in 1..{BATCH_MAX_JOBS_PER_CPU * cpus} "
                         f"({BATCH_MAX_JOBS_PER_CPU} per CPU), got {jobs}")
    return jobs


def _check_stems(files: list[FilePath], formats, out: str) -> None:
    """No two programs write the same outputs, and no output overwrites an input."""
    from oga.errors import InputError

    stems: dict[str, FilePath] = {}
    for f in files:
        if f.stem in stems:
            raise InputError(f"{f} and {stems[f.stem]} would write the same outputs "
                             f"({f.stem}.*): rename one")
        stems[f.stem] = f
    inputs = {os.path.realpath(f) for f in files}
    for stem in stems:
        for name in _all_outputs(stem, formats):
            if os.path.realpath(os.path.join(out, name)) in inputs:
                raise InputError(f"--out {out}: its {name} would overwrite an input")


def _remove_parts(out: FilePath, tasks: list[BatchTask]) -> None:
    """Remove the temporary files of a run killed by SIGKILL or a crash."""
    for task in tasks:
        for name in _all_outputs(task.stem, task.formats):
            for part in out.glob(f".{glob.escape(name)}.*.part"):
                part.unlink(missing_ok=True)


def open_executor(scheduler: str, jobs: int) -> Executor:
    """Where the programs run: ``local`` (``jobs`` processes of this machine), else the Dask
    cluster of the scheduler at that address (an unreachable one is an InputError)."""
    if scheduler == "local":
        return LocalExecutor(jobs)
    from oga.cli.batch_dask import DaskExecutor

    return DaskExecutor(scheduler)


def _execute(executor: Executor, out: FilePath, todo: list[BatchTask],
             outcomes: dict[int, dict]) -> int:
    """Run ``todo`` on ``executor``, each program's outputs written as it finishes; 0, or
    128 + the signal's number when SIGINT or SIGTERM stopped the batch (said on stderr)."""
    bar = ProgressBar(f"batch ({len(todo)} program{'s' * (len(todo) > 1)}, "
                      f"{executor.label(len(todo))})", enabled=sys.stderr.isatty())
    try:
        with _stop_on_signals(), bar:
            executor.execute(todo, lambda task, outcome: _finish(out, task, outcome, outcomes,
                                                                 bar), bar)
    except _Stopped as stop:
        undone = [FilePath(t.file).name for t in todo if t.index not in outcomes]
        done = [FilePath(t.file).name for t in todo if t.index in outcomes]
        print(f"oga batch: stopped by {signal.Signals(stop.signum).name}: {len(done)} of "
              f"{len(todo)} program(s) finished ({_names(done)}), {len(undone)} not "
              f"({_names(undone)}); outputs written so far are complete: run the same command "
              "again to resume", file=sys.stderr, flush=True)
        return 128 + stop.signum
    finally:
        executor.close()
    return 0


def _names(names: list[str], most: int = 5) -> str:
    if not names:
        return "none"
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


class _Stopped(BaseException):
    """SIGINT or SIGTERM arrived in ``oga batch`` (``signum``)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum, frame) -> None:
    raise _Stopped(signum)


@contextmanager
def _stop_on_signals():
    """SIGTERM, and SIGINT unless it is ignored (``nohup``, ``cmd &``), raise :class:`_Stopped`."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(sig, _raise_stopped)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _finish(out: FilePath, task: BatchTask, outcome: dict, outcomes: dict[int, dict],
            bar: ProgressBar) -> None:
    """A program is finished: its outputs written (signals deferred, so all or none), its
    outcome noted and its line printed."""
    with signals_deferred():
        outcomes[task.index] = outcome
        _store(out, task, outcome)
    bar.clear()
    print(_line(task, outcome), flush=True)


def _line(task: BatchTask, outcome: dict) -> str:
    """The line printed when a program is finished."""
    if outcome["status"] != "ok":
        return f"FAILED   {outcome['reason']}"
    s = outcome["summary"]
    cert = s["certificate"]
    robust = (f", certificate {cert['status']} (median {cert['ratio_median']:.3f}, worst "
              f"{cert['ratio_worst']:.3f})" if "ratio_worst" in cert else "")
    kept = f"; baseline kept: {s['kept_baseline_reason']}" if s["kept_baseline"] else ""
    return (f"ok       {FilePath(task.file).name}: MSE ratio {s['ratio_mse']:.3f}, CE rms "
            f"{s['optimized']['rms_ce_um']:.3f} um{robust}{kept} ({outcome['time_s']:.1f} s)")


def _report(tasks, skipped, outcomes: dict[int, dict], out: FilePath, wall_s: float) -> None:
    """The batch's last line, and the failures again on stderr."""
    failed = [outcomes[t.index]["reason"] for t in tasks
              if t.index in outcomes and outcomes[t.index]["status"] != "ok"]
    n_ok = len(outcomes) - len(failed)
    print(f"{len(tasks)} program(s): {n_ok} optimised, {len(skipped)} skipped, "
          f"{len(failed)} failed in {wall_s:.1f} s -> {out}", flush=True)
    if failed:
        print(f"oga batch: {len(failed)} program(s) failed:", file=sys.stderr)
        for reason in failed:
            print(f"  {reason}", file=sys.stderr)
