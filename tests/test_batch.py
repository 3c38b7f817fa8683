"""``oga batch``: tables and summaries per program, failures reported, resume after interruption."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from oga.export import table_c_header, table_csv, table_json
from oga.machine import load_machine
from oga.options import options_from_dict
from oga.pipeline import run_job

SHORT = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X8\nG2 X13 Z5 I0 K5\nG1 X25 Z5\nM2\n"
OTHER = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X10\nG3 X15 Z5 I0 K5\nG1 X15 Z12\nM2\n"
BAD = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X10 Q\nM2\n"
OPTS: list[str] = []  # the defaults of oga optimize


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def batch(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "oga", "batch", *args], capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def reference():
    job = run_job(SHORT, "gcode", load_machine("ucp710"), options_from_dict({}),
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
    assert f"bad.ngc: bad.ngc:3:{bad_line.index('Q') + 1}:" in r.stderr  # reason, line, column
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
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_an_interrupted_batch_leaves_no_partial_output_and_resumes(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    names = ["p1", "p2", "p3"]
    for name, program in zip(names, (SHORT, OTHER, SHORT.replace("X25", "X22"))):
        (src / f"{name}.ngc").write_text(program)
    out.mkdir()
    (out / ".p3.csv.abc123.part").write_text("half a table")  # left by a killed earlier run
    # SIGINT with its default disposition in the batch, as on a terminal: a run started in
    # the background by a non-interactive shell (`cmd &`) inherits SIGINT ignored, and
    # Python then raises no KeyboardInterrupt
    proc = subprocess.Popen([sys.executable, "-m", "oga", "batch", str(src), "--out", str(out),
                             "--jobs", "1", *OPTS], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=_default_sigint)
    t_end = time.monotonic() + 240
    while not (out / "p1.summary.json").exists() and time.monotonic() < t_end:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the whole process group
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "run the same command again to resume" in err
    files = sorted(p.name for p in out.iterdir())
    assert not [f for f in files if f.endswith(".part")]
    done = {f.split(".")[0] for f in files if f.endswith(".summary.json")}
    assert "p1" in done and done != set(names)
    for name in done:  # every summary has its table
        assert (out / f"{name}.csv").exists()

    r = batch(str(src), "--out", str(out), "--jobs", "2", *OPTS)
    assert r.returncode == 0, r.stderr
    for name in names:
        assert (out / f"{name}.csv").exists() and (out / f"{name}.summary.json").exists()
        state = "skipped " if name in done else "ok      "
        assert f"{state} {name}.ngc" in r.stdout
