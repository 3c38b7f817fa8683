"""``oga batch``: tables and summaries per program, failures reported, resume after interruption."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from oga.export.table import table_c_header, table_csv, table_json
from oga.model.machine import load_machine
from oga.options import options_from_dict
from oga.pipeline import run_job

SHORT = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X8\nG2 X13 Z5 I0 K5\nG1 X25 Z5\nM2\n"
OTHER = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X10\nG3 X15 Z5 I0 K5\nG1 X15 Z12\nM2\n"
BAD = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X10 Q\nM2\n"
OPTS: list[str] = []  # the defaults of oga optimize


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def batch(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "oga", "batch", *args, "--nominal"],
                          capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def reference():
    job = run_job(SHORT, "gcode", load_machine("ucp710"), options_from_dict({"nominal": True}),
                  source="short.ngc")
    assert job.result.status == "ok", job.result.optimized.violations
    return job


def _snapshot(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}


def test_batch_writes_tables_reports_failures_and_resumes(tmp_path, reference):
    src = tmp_path / "in"
    src.mkdir()
    (src / "short.ngc").write_text(SHORT)
    (src / "bad.ngc").write_text(BAD)
    out = tmp_path / "out"
    r = batch(str(src), "--out", str(out), "--jobs", "2", "--format", "csv,json,c", *OPTS)
    assert r.returncode == 1, r.stderr
    bad_line = BAD.splitlines()[2]
    # the file named once, first, with the line and column
    assert f"\n  {src / 'bad.ngc'}:3:{bad_line.index('Q') + 1}: Q word" in r.stderr
    assert f"FAILED   {src / 'bad.ngc'}:3:{bad_line.index('Q') + 1}: Q word" in r.stdout
    assert "1 optimised, 0 skipped, 1 failed" in r.stdout
    assert sorted(p.name for p in out.iterdir()) == [
        "short.csv", "short.h", "short.json", "short.summary.json"]
    res, digest = reference.result, reference.toolpath_sha256
    assert (out / "short.csv").read_text() == table_csv(res)
    assert (out / "short.json").read_text() == table_json(res, toolpath_sha256=digest)
    assert (out / "short.h").read_text() == table_c_header(res, "oga_short", toolpath_sha256=digest)
    summary = json.loads((out / "short.summary.json").read_text())
    assert summary["status"] == "ok" and summary["toolpath_sha256"] == digest

    # resume: the finished program is skipped and its files are left alone
    (src / "bad.ngc").unlink()
    before = _snapshot(out)
    r = batch(str(src), "--out", str(out), "--format", "csv,json,c", *OPTS)
    assert r.returncode == 0, r.stderr
    assert "skipped  short.ngc (up to date)" in r.stdout
    assert _snapshot(out) == before

    # other options: the program is redone
    r = batch(str(src), "--out", str(out), "--format", "csv", "--lam", "0.02")
    assert r.returncode == 0 and "ok       short.ngc" in r.stdout, r.stdout + r.stderr
    assert json.loads((out / "short.summary.json").read_text())["options"]["lam"] == 0.02


def test_bad_arguments_exit_2_before_any_work(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for d in ("a", "b"):
        (tmp_path / d / "part.ngc").write_text(SHORT)
    r = batch(str(tmp_path / "a" / "part.ngc"), str(tmp_path / "b" / "part.ngc"),
              "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "same outputs" in r.stderr
    r = batch(str(tmp_path / "a"), "--out", str(tmp_path / "out"), "--format", "csv,xlsx")
    assert r.returncode == 2 and "--format" in r.stderr
    r = batch(str(tmp_path / "a"), "--out", str(tmp_path / "out"), "--np", "0")
    assert r.returncode == 2 and "np" in r.stderr
    limit = 4 * (os.cpu_count() or 1)  # defaults.BATCH_MAX_JOBS_PER_CPU per CPU
    r = batch(str(tmp_path / "a"), "--out", str(tmp_path / "out"), "--jobs", str(limit + 1))
    assert r.returncode == 2 and f"--jobs must be in 1..{limit}" in r.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def _zigzag(lines: int) -> str:
    """A program of ``lines`` 30 mm moves: tens of seconds to optimise."""
    moves = "".join(f"G1 X{30 * (i % 2)} Z{i * 0.5:.1f}\n" for i in range(1, lines + 1))
    return f"G21 G90 G18\nG1 X0 Z0 F3000\n{moves}M2\n"


def _start_batch(src: Path, out: Path, *args: str) -> subprocess.Popen:
    """``oga batch`` in a process group of its own, SIGINT at its default disposition.

    A run started in the background by a non-interactive shell (``cmd &``) inherits SIGINT
    ignored, and a batch then (rightly) ignores it too: the test must not depend on how
    pytest itself was started.
    """
    return subprocess.Popen([sys.executable, "-m", "oga", "batch", str(src), "--out", str(out),
                             "--nominal", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=_default_sigint)


def _children(pid: int) -> set[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    found = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.add(int(entry.name))
    return found


def _running(pid: int) -> bool:
    """Whether ``pid`` exists and is not a zombie."""
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _started(proc: subprocess.Popen, workers: int = 2) -> set[int]:
    """The child processes of ``proc`` (its workers, multiprocessing's resource tracker) once
    its ``workers`` workers have started."""

    def spawned(pids: set[int]) -> int:
        return sum(b"spawn_main" in _cmdline(p) for p in pids)

    t_end = time.monotonic() + 60
    while spawned(_children(proc.pid)) < workers and time.monotonic() < t_end:
        time.sleep(0.05)
    children = _children(proc.pid)
    assert spawned(children) >= workers
    return children


def _cmdline(pid: int) -> bytes:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes()
    except OSError:
        return b""


def _assert_ended(pids: set[int]) -> None:
    """Assert that none of ``pids`` runs any more (waiting up to 10 s for the kernel)."""
    t_end = time.monotonic() + 10
    while any(_running(p) for p in pids) and time.monotonic() < t_end:
        time.sleep(0.05)
    assert not [p for p in pids if _running(p)]


def _lines(stream) -> "queue.Queue[str]":
    """The lines of ``stream`` as they come (read by a thread)."""
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in stream], daemon=True).start()
    return lines


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_ctrl_c_ends_the_batch_and_its_workers_keeping_finished_outputs(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    (src / "p1.ngc").write_text(SHORT)
    (src / "p2.ngc").write_text(_zigzag(400))
    (src / "p3.ngc").write_text(_zigzag(401))
    out.mkdir()
    (out / ".p3.csv.abc123.part").write_text("half a table")  # left by a killed earlier run
    proc = _start_batch(src, out, "--jobs", "2")
    stdout = _lines(proc.stdout)
    # stdout is a pipe, not a terminal: each finished program's line comes as it finishes
    line = stdout.get(timeout=240)
    assert line.startswith("ok       p1.ngc: MSE ratio"), line
    assert proc.poll() is None  # printed while p2 and p3 are still being optimised
    workers = _started(proc)
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, or timeout -s INT: the whole process group
    # the zigzags need tens of seconds more each: the batch does not wait for them
    # (how fast it stops is measured by bench/bench_batch_signal.py)
    assert proc.wait(timeout=30) == 130
    err = proc.stderr.read()
    assert err.splitlines() == [
        "oga batch: stopped by SIGINT: 1 of 3 program(s) finished (p1.ngc), 2 not (p2.ngc, "
        "p3.ngc); outputs written so far are complete: run the same command again to resume"]
    _assert_ended(workers)
    assert sorted(p.name for p in out.iterdir()) == ["p1.csv", "p1.summary.json"]

    # resume: p1 is up to date, the others are done
    (src / "p2.ngc").write_text(OTHER)
    (src / "p3.ngc").write_text(SHORT.replace("X25", "X22"))
    r = batch(str(src), "--out", str(out), "--jobs", "2", *OPTS)
    assert r.returncode == 0, r.stderr
    assert "skipped  p1.ngc (up to date)" in r.stdout
    for name in ("p2", "p3"):
        assert f"ok       {name}.ngc" in r.stdout
        assert (out / f"{name}.csv").exists() and (out / f"{name}.summary.json").exists()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_sigterm_to_the_batch_alone_ends_its_workers(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    (src / "a.ngc").write_text(_zigzag(400))
    (src / "b.ngc").write_text(_zigzag(401))
    proc = _start_batch(src, out, "--jobs", "2")
    workers = _started(proc)
    time.sleep(1.0)  # the workers are computing
    proc.send_signal(signal.SIGTERM)  # to the batch process only (kill PID)
    assert proc.wait(timeout=30) == 143
    err = proc.stderr.read()
    assert err.splitlines() == [
        "oga batch: stopped by SIGTERM: 0 of 2 program(s) finished (none), 2 not (a.ngc, "
        "b.ngc); outputs written so far are complete: run the same command again to resume"]
    _assert_ended(workers)
    assert list(out.iterdir()) == []


def test_a_closed_stdout_stops_the_batch_quietly(tmp_path):
    """``oga batch ... | head -1``: the reader has gone; no traceback, no worker left."""
    src = tmp_path / "in"
    src.mkdir()
    (src / "p1.ngc").write_text(SHORT)
    (src / "p2.ngc").write_text(_zigzag(400))
    proc = _start_batch(src, tmp_path / "out", "--jobs", "2")
    proc.stdout.close()
    workers = _started(proc)
    assert proc.wait(timeout=240) == 128 + signal.SIGPIPE  # at p1's line, long before p2 ends
    assert proc.stderr.read() == ""
    _assert_ended(workers)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_batch_leaves_no_worker_behind(tmp_path):
    """SIGKILL (or a crash) gives the batch no chance to end its workers: the kernel does."""
    src = tmp_path / "in"
    src.mkdir()
    (src / "a.ngc").write_text(_zigzag(400))
    (src / "b.ngc").write_text(_zigzag(401))
    proc = _start_batch(src, tmp_path / "out", "--jobs", "2")
    workers = _started(proc)
    proc.kill()
    assert proc.wait(timeout=30) == -signal.SIGKILL
    _assert_ended(workers)
