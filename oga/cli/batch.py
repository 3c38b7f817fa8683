"""``oga batch``: optimise many programs in parallel processes, resumably.

Per program ``<stem>`` it writes ``<stem>.<suffix>`` for each table format and
``<stem>.summary.json``, every file atomically. The summary is written last and
removed first when a program is redone, so a summary always belongs to the
tables beside it; a program is up to date (skipped) when its summary says
``ok`` for the same toolpath text, machine and options and its tables exist.

Programs run in worker processes of the batch's own (spawned; one pipe each for
the task, its progress and its outcome), which ignore SIGINT and SIGTERM: on
either signal the batch kills them and returns 128 + the signal's number. A
program's files are written with the signals deferred, so they are all there or
all absent.

With ``--scheduler tcp://HOST:8786`` the programs run on an existing Dask
cluster instead (:mod:`oga.cli.batch_dask`): the batch reads each program and
sends its text, a worker returns the rendered tables, and the batch writes them
here exactly as a local run does.
"""

from __future__ import annotations

import argparse
import glob
import json
import multiprocessing as mp
import os
import re
import signal
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as _wait
from pathlib import Path as FilePath

from oga.cli._common import (
    add_plan_args,
    add_search_args,
    check_files,
    flag_message,
    options_from_args,
    output_folder,
    toolpath_message,
    write_json,
    write_text,
)
from oga.cli._progress import ProgressBar

__all__ = ["register", "run"]

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


@dataclass(frozen=True)
class _Task:
    """One program to optimise (sent to a worker process)."""

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


def _outputs(stem: str, formats) -> tuple[list[str], str]:
    from oga.export.table import TABLE_FORMATS

    return [stem + TABLE_FORMATS[f][0] for f in formats], f"{stem}.summary.json"


def _all_outputs(stem: str, formats) -> list[str]:
    tables, summary_name = _outputs(stem, formats)
    return [*tables, summary_name]


def _c_name(stem: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", stem)
    return f"oga_{name}"[:63]


def _run_one(task: _Task, progress) -> dict:
    """In a worker process: optimise one program; returns its outputs or its failure (the
    reason names the file first)."""
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
        tables = dict(zip(_outputs(task.stem, task.formats)[0],
                          (render[f]() for f in task.formats)))
        return {"status": "ok", "summary": summary, "tables": tables,
                "time_s": time.perf_counter() - t0}
    except Exception as err:  # a bug must not stop the other programs
        return _failed(task, err, time.perf_counter() - t0)


def _failed(task: _Task, err: Exception, time_s: float = 0.0) -> dict:
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


def _worker(conn, parent_pid: int) -> None:
    """A worker process: optimise the tasks the parent sends, until it closes the pipe.

    Signals are the parent's business: a worker ignores SIGINT and SIGTERM (a Ctrl-C or
    ``timeout`` reaches the whole process group) and is killed by the parent when the batch
    stops; on Linux it is also killed if the parent dies.
    """
    for sig in _STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)  # blocked by the parent at start
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
        conn.send(("done", _run_one(task, progress)))


def _up_to_date(out: FilePath, task: _Task, machine_sha256: str) -> bool:
    from feedplan.read import read_file
    from oga.pipeline import toolpath_sha256

    tables, summary_name = _outputs(task.stem, task.formats)
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


def _store(out: FilePath, task: _Task, outcome: dict) -> None:
    """Write a program's outputs: old summary removed first, tables, then the summary."""
    tables, summary_name = _outputs(task.stem, task.formats)
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
    from oga.defaults import BATCH_MAX_JOBS_PER_CPU
    from oga.errors import InputError
    from oga.model.machine import load_machine

    formats = tuple(f.strip() for f in args.format.split(",") if f.strip())
    bad = [f for f in formats if f not in BATCH_TABLE_FORMATS]
    if bad or not formats or len(set(formats)) != len(formats):
        raise InputError(f"--format: expected names from {','.join(BATCH_TABLE_FORMATS)}, "
                         f"each once; got {args.format!r}")
    cpus = os.cpu_count() or 1
    cluster = args.scheduler != "local"
    if cluster and args.jobs is not None:
        raise InputError("--jobs is for a local run: a Dask cluster runs as many programs at "
                         "once as its workers have threads")
    jobs = cpus if args.jobs is None else args.jobs
    if not 1 <= jobs <= BATCH_MAX_JOBS_PER_CPU * cpus:
        raise InputError(f"--jobs must be in 1..{BATCH_MAX_JOBS_PER_CPU * cpus} "
                         f"({BATCH_MAX_JOBS_PER_CPU} per CPU), got {jobs}")
    check_files(args)
    machine = load_machine(args.machine)
    options = options_from_args(args).as_dict()
    files = _expand(args.inputs)
    stems: dict[str, FilePath] = {}
    for f in files:
        if f.stem in stems:
            raise InputError(f"{f} and {stems[f.stem]} would write the same outputs "
                             f"({f.stem}.*): rename one")
        stems[f.stem] = f
    inputs = {os.path.realpath(f) for f in files}
    for stem in stems:
        for name in _all_outputs(stem, formats):
            if os.path.realpath(os.path.join(args.out, name)) in inputs:
                raise InputError(f"--out {args.out}: its {name} would overwrite an input")
    out = output_folder("--out", args.out)
    tasks = [_Task(i, str(f), f.stem, formats, machine.model_dump(mode="json"), options)
             for i, f in enumerate(files)]
    for task in tasks:  # temporary files of a run killed by SIGKILL or a crash
        for name in _all_outputs(task.stem, formats):
            for part in out.glob(f".{glob.escape(name)}.*.part"):
                part.unlink(missing_ok=True)

    digest = machine.digest()
    skipped = {t.index for t in tasks if _up_to_date(out, t, digest)}
    for t in tasks:
        if t.index in skipped:
            print(f"skipped  {FilePath(t.file).name} (up to date)", flush=True)
    todo = [t for t in tasks if t.index not in skipped]
    outcomes: dict[int, dict] = {}
    t0 = time.perf_counter()
    client = None
    if cluster and todo:
        from oga.cli.batch_dask import connect

        client = connect(args.scheduler)
    try:
        with _stop_on_signals():
            if client is not None:
                from oga.cli.batch_dask import execute_on

                execute_on(client, out, todo, outcomes, finish=_finish)
            elif todo:
                _execute(out, todo, min(jobs, len(todo)), outcomes)
    except _Stopped as stop:
        undone = [FilePath(t.file).name for t in todo if t.index not in outcomes]
        done = [FilePath(t.file).name for t in todo if t.index in outcomes]
        print(f"oga batch: stopped by {signal.Signals(stop.signum).name}: {len(done)} of "
              f"{len(todo)} program(s) finished ({_names(done)}), {len(undone)} not "
              f"({_names(undone)}); outputs written so far are complete: run the same command "
              "again to resume", file=sys.stderr, flush=True)
        return 128 + stop.signum
    finally:
        if client is not None:
            client.close()
    _report(tasks, skipped, outcomes, out, time.perf_counter() - t0)
    return 1 if any(o["status"] != "ok" for o in outcomes.values()) else 0


def _names(names: list[str], most: int = 5) -> str:
    if not names:
        return "none"
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


#: Signals that stop a batch: the workers are killed, finished outputs kept.
_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


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
    previous = {sig: signal.getsignal(sig) for sig in _STOP_SIGNALS}
    for sig, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(sig, _raise_stopped)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def _signals_deferred():
    """SIGINT and SIGTERM held back (delivered at the end of the block)."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@dataclass
class _Slot:
    """A worker process, its end of the pipe and the task it computes (None: idle)."""

    process: mp.process.BaseProcess
    conn: Connection
    task: _Task | None = None


def _start_worker(ctx) -> _Slot:
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_worker, args=(child, os.getpid()), daemon=True,
                          name="oga-batch-worker")
    with _signals_deferred():  # the worker starts with them blocked, then ignores them
        process.start()
    child.close()
    return _Slot(process, parent)


def _execute(out: FilePath, todo: list[_Task], workers: int, outcomes: dict[int, dict]) -> None:
    """Optimise ``todo`` in ``workers`` processes; fills ``outcomes`` as programs finish.

    Each finished program's files are written at once (signals deferred meanwhile, so a
    program's outputs are all there or all absent) and its line printed. Whatever ends
    this function (the last program, a signal, an error), every worker is ended before it
    returns.
    """
    ctx = mp.get_context("spawn")
    pending = list(reversed(todo))  # pop() takes them in input order
    slots: list[_Slot] = []
    partial = {t.index: 0.0 for t in todo}
    label = f"batch ({len(todo)} program{'s' * (len(todo) > 1)}, {workers} process"
    label += "es)" if workers > 1 else ")"
    bar = ProgressBar(label, enabled=sys.stderr.isatty())

    def finish(task: _Task, outcome: dict) -> None:
        _finish(out, task, outcome, outcomes, bar)
        partial[task.index] = 1.0

    try:
        with bar:
            while len(outcomes) < len(todo):
                while pending and len(slots) < workers:
                    slots.append(_start_worker(ctx))
                for slot in slots:
                    if slot.task is None and pending:
                        slot.task = pending.pop()
                        try:
                            slot.conn.send(slot.task)
                        except OSError:  # the worker died: found below
                            pass
                _wait([s.conn for s in slots] + [s.process.sentinel for s in slots], 0.2)
                for slot in list(slots):
                    messages, alive = _receive(slot.conn)
                    for kind, value in messages:
                        if kind == "progress":
                            partial[slot.task.index] = value
                        else:
                            task, slot.task = slot.task, None
                            finish(task, value)
                    if alive and slot.process.is_alive() and (slot.task or pending):
                        continue
                    slots.remove(slot)
                    _end_worker(slot, kill=False)
                    if slot.task is not None:  # killed (out of memory?) while computing
                        code = slot.process.exitcode
                        finish(slot.task, {"status": "failed", "time_s": 0.0,
                                           "reason": f"{slot.task.file}: its worker process "
                                           f"died (exit code {code}: out of memory?)"})
                bar.update(sum(partial.values()) / len(todo))
    finally:
        with _signals_deferred():  # a second Ctrl-C must not leave a worker behind
            for slot in slots:
                _end_worker(slot, kill=True)


def _finish(out: FilePath, task: _Task, outcome: dict, outcomes: dict[int, dict],
            bar: ProgressBar) -> None:
    """A program is finished: its outputs written (signals deferred, so all or none), its
    outcome noted and its line printed."""
    with _signals_deferred():
        outcomes[task.index] = outcome
        _store(out, task, outcome)
    bar.clear()
    print(_line(task, outcome), flush=True)


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


def _line(task: _Task, outcome: dict) -> str:
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
