"""``oga batch``: optimise many programs in parallel processes, resumably.

Per program ``<stem>`` it writes ``<stem>.<suffix>`` for each table format and
``<stem>.summary.json``, every file atomically. The summary is written last and
removed first when a program is redone, so a summary always belongs to the
tables beside it; a program is up to date (skipped) when its summary says
``ok`` for the same toolpath text, machine and options and its tables exist.
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import multiprocessing as mp
import os
import re
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path as FilePath
from queue import Empty

from oga.cli._common import add_search_args, options_from_args, write_json, write_text
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
        "are skipped, so an interrupted batch resumes where it stopped.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="toolpath files (.ngc .nc .gcode .tap .csv .json ...) or folders of them")
    p.add_argument("--machine", default="ucp710", metavar="NAME|FILE",
                   help="machine preset name or machine file (.toml/.json); default ucp710")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the outputs")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="programs optimised at once (default: one per CPU)")
    p.add_argument("--format", default=",".join(BATCH_FORMATS), metavar="LIST",
                   help=f"table formats, comma-separated from {','.join(BATCH_TABLE_FORMATS)} "
                   f"(default {','.join(BATCH_FORMATS)})")
    p.add_argument("--feed", type=float, metavar="MM_PER_MIN",
                   help="feed override in mm/min (default: each program's F)")
    p.add_argument("--tolerance", type=float, default=None, metavar="MM",
                   help="interpolation tolerance in mm (default 0.02)")
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


def _expand(inputs: list[str]) -> list[FilePath]:
    from feedplan.read import SUFFIXES
    from oga.errors import InputError

    files = []
    for name in inputs:
        p = FilePath(name)
        if p.is_dir():
            files += sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in SUFFIXES)
        elif p.exists():
            files.append(p)
        else:
            raise InputError(f"{name}: no such file or folder")
    if not files:
        raise InputError("no toolpath among the inputs")
    return files


def _outputs(stem: str, formats) -> tuple[list[str], str]:
    from oga.export import TABLE_FORMATS

    return [stem + TABLE_FORMATS[f][0] for f in formats], f"{stem}.summary.json"


def _c_name(stem: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", stem)
    return f"oga_{name}"[:63]


_progress_queue = None


def _init_worker(queue) -> None:
    global _progress_queue
    _progress_queue = queue


def _run_one(task: _Task) -> dict:
    """In a worker process: optimise one program; returns its outputs or its failure."""
    from feedplan.read import read_file
    from oga.errors import OgaError
    from oga.export import table_c_header, table_csv, table_json
    from oga.machine import machine_from_dict
    from oga.options import options_from_dict
    from oga.pipeline import run_job

    last = 0.0

    def progress(fraction: float) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last >= 0.2 or fraction >= 1.0:
            last = now
            _progress_queue.put((task.index, fraction))

    t0 = time.perf_counter()
    try:
        text, fmt = read_file(task.file)
        job = run_job(text, fmt, machine_from_dict(task.machine), options_from_dict(task.options),
                      source=FilePath(task.file).name, progress=progress)
        res = job.result
        summary = job.summary()
        if res.status != "ok":
            return {"status": "failed", "summary": summary, "time_s": time.perf_counter() - t0,
                    "reason": "verification failed: " + "; ".join(res.optimized.violations)}
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
    except OgaError as err:
        return {"status": "failed", "reason": str(err), "time_s": time.perf_counter() - t0}
    except Exception as err:  # a bug must not stop the other programs
        return {"status": "failed", "reason": f"internal error: {type(err).__name__}: {err}",
                "time_s": time.perf_counter() - t0}


def _up_to_date(out: FilePath, task: _Task, machine_sha256: str) -> bool:
    tables, summary_name = _outputs(task.stem, task.formats)
    try:
        summary = json.loads((out / summary_name).read_text(encoding="utf-8"))
        text = FilePath(task.file).read_bytes().decode("utf-8-sig")
    except (OSError, ValueError):
        return False
    return (summary.get("status") == "ok"
            and summary.get("toolpath_sha256") == hashlib.sha256(text.encode()).hexdigest()
            and summary.get("machine_sha256") == machine_sha256
            and summary.get("options") == task.options
            and all((out / t).is_file() for t in tables))


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
    from oga.errors import InputError
    from oga.machine import load_machine

    formats = tuple(f.strip() for f in args.format.split(",") if f.strip())
    bad = [f for f in formats if f not in BATCH_TABLE_FORMATS]
    if bad or not formats or len(set(formats)) != len(formats):
        raise InputError(f"--format: expected names from {','.join(BATCH_TABLE_FORMATS)}, "
                         f"each once; got {args.format!r}")
    jobs = (os.cpu_count() or 1) if args.jobs is None else args.jobs
    if jobs < 1:
        raise InputError(f"--jobs must be at least 1, got {jobs}")
    machine = load_machine(args.machine)
    options = options_from_args(args).as_dict()
    files = _expand(args.inputs)
    stems: dict[str, FilePath] = {}
    for f in files:
        if f.stem in stems:
            raise InputError(f"{f} and {stems[f.stem]} would write the same outputs "
                             f"({f.stem}.*): rename one")
        stems[f.stem] = f
    out = FilePath(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [_Task(i, str(f), f.stem, formats, machine.model_dump(mode="json"), options)
             for i, f in enumerate(files)]
    for task in tasks:  # temporary files of an interrupted earlier run
        for name in [*_outputs(task.stem, formats)[0], _outputs(task.stem, formats)[1]]:
            for part in out.glob(f".{glob.escape(name)}.*.part"):
                part.unlink(missing_ok=True)

    digest = machine.digest()
    skipped = {t.index for t in tasks if _up_to_date(out, t, digest)}
    todo = [t for t in tasks if t.index not in skipped]
    outcomes: dict[int, dict] = {}
    t0 = time.perf_counter()
    if todo:
        outcomes = _execute(out, todo, min(jobs, len(todo)))
    _report(tasks, skipped, outcomes, out, time.perf_counter() - t0)
    return 1 if any(o["status"] != "ok" for o in outcomes.values()) else 0


def _execute(out: FilePath, todo: list[_Task], workers: int) -> dict[int, dict]:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    partial = {t.index: 0.0 for t in todo}
    outcomes: dict[int, dict] = {}
    by_index = {t.index: t for t in todo}
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                               initargs=(queue,))
    label = f"batch ({len(todo)} program{'s' * (len(todo) > 1)}, {workers} process"
    label += "es)" if workers > 1 else ")"
    try:
        with ProgressBar(label, enabled=sys.stderr.isatty()) as bar:
            futures = {pool.submit(_run_one, t): t.index for t in todo}
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = futures[fut]
                    try:
                        outcomes[i] = fut.result()
                    except BrokenProcessPool:
                        outcomes[i] = {"status": "failed", "time_s": 0.0,
                                       "reason": "a worker process died (out of memory?)"}
                    _store(out, by_index[i], outcomes[i])
                    partial[i] = 1.0
                try:
                    while True:
                        i, fraction = queue.get_nowait()
                        if i not in outcomes:
                            partial[i] = fraction
                except Empty:
                    pass
                bar.update(sum(partial.values()) / len(todo))
    except KeyboardInterrupt:
        done = len(outcomes)
        print(f"\ninterrupted after {done} of {len(todo)} program(s); outputs written so far "
              "are complete: run the same command again to resume", file=sys.stderr)
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return outcomes


def _report(tasks, skipped, outcomes: dict[int, dict], out: FilePath, wall_s: float) -> None:
    failed = []
    for t in tasks:
        name = FilePath(t.file).name
        if t.index in skipped:
            print(f"skipped  {name} (up to date)")
            continue
        o = outcomes[t.index]
        if o["status"] == "ok":
            s = o["summary"]
            print(f"ok       {name}: MSE ratio {s['ratio_mse']:.3f}, CE rms "
                  f"{s['optimized']['rms_ce_um']:.3f} um ({o['time_s']:.1f} s)")
        else:
            print(f"FAILED   {name}: {o['reason']}")
            failed.append((name, o["reason"]))
    n_ok = sum(o["status"] == "ok" for o in outcomes.values())
    print(f"{len(tasks)} program(s): {n_ok} optimised, {len(skipped)} skipped, "
          f"{len(failed)} failed in {wall_s:.1f} s -> {out}")
    if failed:
        print(f"oga batch: {len(failed)} program(s) failed:", file=sys.stderr)
        for name, reason in failed:
            print(f"  {name}: {reason}", file=sys.stderr)
