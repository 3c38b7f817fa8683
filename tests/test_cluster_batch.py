"""``oga batch --scheduler`` on a real Dask cluster on loopback (``dask scheduler`` and two
``dask worker`` processes): the same bytes as a local run, resume, a worker killed mid-batch
costs a retry of its program only, SIGINT cancels the batch's tasks on the cluster, and an
unreachable scheduler is a one-line error (exit 2)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from dask_cluster import DaskCluster
from distributed import Client

DATA = Path(__file__).parent / "data"
#: One 1 m move at F600: about 10 s of work, long enough to kill its worker in the middle.
LONG = "G21 G90\nG1 X0 Y0 F600\nG1 X1000\nM2\n"
FORMATS = "csv,json,c"


def batch(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "oga", "batch", *args, "--format", FORMATS,
                           "--nominal"],
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def programs(tmp_path_factory) -> list[str]:
    """Six programs: five of tests/data and one long move."""
    folder = tmp_path_factory.mktemp("programs")
    (folder / "long_move.ngc").write_text(LONG)
    names = ["short_xz", "circle_r50_f3000", "reference_xz", "helix_r20", "corner_steps"]
    return [str(DATA / f"{n}.ngc") for n in names] + [str(folder / "long_move.ngc")]


@pytest.fixture(scope="module")
def local_run(programs, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local") / "out"
    r = batch(*programs, "--out", str(out), "--jobs", "2")
    assert r.returncode == 0, r.stdout + r.stderr
    return out


@pytest.fixture
def cluster(tmp_path):
    c = DaskCluster(tmp_path, workers=2)
    try:
        yield c
    finally:
        c.stop()


def _same_as(out: Path, reference: Path) -> None:
    """Every file byte for byte as the local run's (the summaries but their timing)."""
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in reference.iterdir())
    for ref in reference.iterdir():
        mine = out / ref.name
        if ref.name.endswith(".summary.json"):
            a, b = json.loads(mine.read_text()), json.loads(ref.read_text())
            a.pop("optimize_time_s"), b.pop("optimize_time_s")
            assert a == b, ref.name
        else:
            assert mine.read_bytes() == ref.read_bytes(), ref.name


def test_cluster_batch_is_byte_identical_to_local_and_resumes(cluster, programs, local_run,
                                                              tmp_path):
    out = tmp_path / "out"
    r = batch(*programs, "--out", str(out), "--scheduler", cluster.address)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.count("\nok ") + r.stdout.startswith("ok ") == 6
    assert "6 program(s): 6 optimised, 0 skipped, 0 failed" in r.stdout
    _same_as(out, local_run)
    with Client(cluster.address, set_as_default=False) as client:  # both workers took programs
        ran = client.run(lambda dask_worker: len(dask_worker.state.log) > 0)
    assert all(ran.values()) and len(ran) == 2

    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    r = batch(*programs, "--out", str(out), "--scheduler", cluster.address)
    assert r.returncode == 0 and r.stdout.count("(up to date)") == 6, r.stdout
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def _processing(client: Client) -> dict[str, list[str]]:
    return {w: [str(k) for k in keys] for w, keys in client.processing().items()}


def test_a_worker_killed_mid_batch_costs_a_retry_only(cluster, programs, local_run, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "oga", "batch", *programs, "--out", str(out),
                             "--scheduler", cluster.address, "--format", FORMATS, "--nominal"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with Client(cluster.address, set_as_default=False) as client:
        workers = {info["name"]: addr
                   for addr, info in client.scheduler_info()["workers"].items()}
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end:  # the long program started: kill its worker
            holder = [w for w, keys in _processing(client).items()
                      if any(k.endswith("-long_move") for k in keys)]
            executing = holder and client.run(
                lambda dask_worker: [str(ts.key) for ts in dask_worker.state.executing],
                workers=holder)[holder[0]]
            if executing and any(k.endswith("-long_move") for k in executing):
                break
            time.sleep(0.05)
        else:
            raise AssertionError("the long program never started")
        victim = next(n for n, a in workers.items() if a == holder[0])
        cluster.kill_worker(int(victim[1:]))
        stdout, stderr = proc.communicate(timeout=600)
        # the long program was retried on the surviving worker
        survivor = next(a for a in workers.values() if a != holder[0])
        log = client.run(lambda dask_worker: [str(entry) for entry in dask_worker.state.log],
                         workers=[survivor])[survivor]
        assert any("long_move" in entry and "executing" in entry for entry in log)
    assert proc.returncode == 0, stdout + stderr
    assert "6 program(s): 6 optimised, 0 skipped, 0 failed" in stdout
    _same_as(out, local_run)


def test_sigint_cancels_the_batch_tasks_on_the_cluster(cluster, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for k in range(4):
        (src / f"long{k}.ngc").write_text(LONG.replace("X1000", f"X{1000 + k}"))
    proc = subprocess.Popen([sys.executable, "-m", "oga", "batch", str(src), "--out",
                             str(tmp_path / "out"), "--scheduler", cluster.address, "--nominal"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with Client(cluster.address, set_as_default=False) as client:
        t_end = time.monotonic() + 120
        while not any(_processing(client).values()):
            assert time.monotonic() < t_end, "the batch never reached the cluster"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)  # a hang guard (it took > 30 s under load 8)
        assert proc.returncode == 130, stdout + stderr
        assert "stopped by SIGINT: 0 of 4 program(s) finished" in stderr
        t_end = time.monotonic() + 10
        while client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)):
            assert time.monotonic() < t_end, "the batch's tasks stayed on the cluster"
            time.sleep(0.1)


def test_an_unreachable_scheduler_is_a_one_line_error(tmp_path):
    r = batch(str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "out"), "--scheduler",
              "tcp://127.0.0.1:1", timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("oga batch: error: --scheduler tcp://127.0.0.1:1: cannot reach "
                               "the Dask scheduler")
    assert r.stderr.count("\n") == 1
    r = batch(str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "out"), "--scheduler",
              "tcp://127.0.0.1:1", "--jobs", "2")
    assert r.returncode == 2 and "--jobs is for a local run" in r.stderr
    for bad in ("foo", ""):
        r = batch(str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "out"), "--scheduler", bad,
                  timeout=60)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert f"--scheduler {bad!r}: expected tcp://HOST:PORT" in r.stderr
