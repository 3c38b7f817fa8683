"""``oga serve --scheduler``: the service's jobs on a real Dask cluster on loopback (``dask
scheduler`` and two ``dask worker`` processes): the same stored tables and summaries as local
workers (jobs in PostgreSQL), progress in the store, DELETE kills a running job's process (the
Dask worker takes the next job) and drops a job waiting on the cluster, a CPU-capped job fails
once, and a Dask worker killed mid-job costs one more attempt of its job only."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil
import pytest
from dask_cluster import DaskCluster
from distributed import Client
from pg_cluster import PgCluster
from test_api_server import (
    FINISHED,
    HOG,
    LONG,
    REFERENCE,
    SHORT,
    Server,
    _freeze,
    _gone,
    submit,
    wait_for,
)

from api.storage import open_store

PROGRAMS = {"short.ngc": SHORT, "reference_xz.ngc": REFERENCE, "long.ngc": LONG}


class DaskServer(Server):
    """``oga serve --scheduler ADDRESS`` in a subprocess on a free loopback port."""

    def __init__(self, db: str, scheduler: str, log: Path, *flags: str) -> None:
        super().__init__(db, None, log, "--scheduler", scheduler, *flags)
        self.store = open_store(db)

    def worker_of(self, job_id: str) -> int | None:
        owner = self.store.get(job_id).owner
        return None if owner is None else owner.worker_pid

    def child_of(self, job_id: str, timeout_s: float = 120) -> int:
        """Pid of the process running the job, once its Dask task has started it."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            pid = self.worker_of(job_id)
            if pid:
                return pid
            time.sleep(0.02)
        raise AssertionError(f"job {job_id} never started")



def _results(server: Server, job_id: str) -> tuple[bytes, dict]:
    """The stored table (npz bytes) and summary (without its timing) of a job."""
    summary = server.http.get(f"/v1/jobs/{job_id}/summary").json()
    summary.pop("optimize_time_s")
    return server.http.get(f"/v1/jobs/{job_id}/table", params={"format": "npz"}).content, summary


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = DaskCluster(tmp_path_factory.mktemp("dask"), workers=2)
    try:
        yield c
    finally:
        c.stop()


@pytest.fixture(scope="module")
def local_results(tmp_path_factory) -> dict:
    """The programs run by a server with one local worker: table and summary of each."""
    folder = tmp_path_factory.mktemp("local")
    server = Server(folder / "oga.db", 1, folder / "serve.log")
    try:
        ids = {name: submit(server, text, name) for name, text in PROGRAMS.items()}
        for job_id in ids.values():
            assert wait_for(server, job_id, FINISHED)[0]["status"] == "succeeded"
        return {name: _results(server, job_id) for name, job_id in ids.items()}
    finally:
        server.stop()


def _ran_jobs(cluster: DaskCluster) -> dict[str, int]:
    """Per Dask worker (by name): how many job tasks it started."""
    with Client(cluster.address, set_as_default=False) as client:
        counts = client.run(lambda dask_worker: (dask_worker.name, len(
            {str(e[0]) for e in dask_worker.state.log
             if str(e[0]).startswith("oga-job-") and "executing" in e})))
    return dict(counts.values())


def test_jobs_on_the_cluster_store_what_local_workers_store(cluster, local_results, tmp_path):
    pg = PgCluster()
    server = DaskServer(pg.url, cluster.address, tmp_path / "serve.log")
    try:
        ids = {name: submit(server, text, name) for name, text in PROGRAMS.items()}
        progress, t_end = set(), time.monotonic() + 240
        while time.monotonic() < t_end:  # the long job's progress reaches the store
            job = server.http.get(f"/v1/jobs/{ids['long.ngc']}").json()
            if job["status"] in FINISHED:
                break
            progress.add(job["progress"])
            time.sleep(0.05)
        assert any(0 < p < 1 for p in progress), progress
        for name, job_id in ids.items():
            job, _ = wait_for(server, job_id, FINISHED)
            assert (job["status"], job["attempts"]) == ("succeeded", 1), job
            assert _results(server, job_id) == local_results[name], name
        assert sorted(_ran_jobs(cluster).values()) >= [1, 1]  # both workers took jobs
    finally:
        server.stop()
        pg.stop()


def test_delete_kills_the_job_process_and_the_worker_takes_the_next(cluster, tmp_path):
    db = tmp_path / "oga.db"
    server = DaskServer(db, cluster.address, tmp_path / "serve.log", "--stall-s", "1")
    try:
        long_id = submit(server, LONG, "long.ngc")
        pid = server.child_of(long_id)
        holder = next(k for k, w in enumerate(cluster.workers)
                      if w.pid == psutil.Process(pid).ppid())
        before = _ran_jobs(cluster)[f"w{holder}"]
        _freeze(pid, db)  # a job that makes no progress: only a kill ends it
        t_end, health = time.monotonic() + 15, {}
        while time.monotonic() < t_end and health.get("status") != "degraded":
            health = server.http.get("/healthz").json()
            time.sleep(0.2)
        assert [(s["job"], s["worker_pid"]) for s in health["stalled"]] == [(long_id, pid)]

        # both threads busy: a third job is claimed and waits on the cluster; DELETE drops it
        other = submit(server, LONG.replace("X1000", "X1001"), "other.ngc")
        other_pid = server.child_of(other)
        _freeze(other_pid, db)
        waiting = submit(server, LONG.replace("X1000", "X1002"), "waiting.ngc")
        wait_for(server, waiting, ("running",))
        assert server.http.delete(f"/v1/jobs/{waiting}").json()["status"] == "cancelled"
        with Client(cluster.address, set_as_default=False) as client:
            t_end = time.monotonic() + 10
            while any(waiting in str(key) for key in client.run_on_scheduler(
                    lambda dask_scheduler: list(dask_scheduler.tasks))):
                assert time.monotonic() < t_end, "the cancelled job's task stayed on the cluster"
                time.sleep(0.05)
        assert server.worker_of(waiting) is None  # it never started
        for job_id, job_pid in ((other, other_pid), (long_id, pid)):
            t0 = time.monotonic()
            assert server.http.delete(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"
            while not _gone(job_pid) and time.monotonic() - t0 < 1.0:
                time.sleep(0.005)
            ended_s = time.monotonic() - t0
            assert _gone(job_pid), "the process of a cancelled job still runs after 1 s"
            print(f"\nDELETE -> job process {job_pid} gone in {ended_s * 1e3:.0f} ms")
        assert all(w.poll() is None for w in cluster.workers)  # the Dask workers live on
        ids = [submit(server, SHORT, f"next{k}.ngc") for k in range(2)]
        for job_id in ids:
            assert wait_for(server, job_id, FINISHED)[0]["status"] == "succeeded"
        assert _ran_jobs(cluster)[f"w{holder}"] > before  # the same worker took a next job
        assert server.http.get(f"/v1/jobs/{long_id}").json()["status"] == "cancelled"
        assert server.http.get("/healthz").json()["stalled"] == []
    finally:
        server.stop()


def test_a_job_over_its_cpu_cap_fails_once_and_the_next_runs(cluster, tmp_path):
    server = DaskServer(tmp_path / "oga.db", cluster.address, tmp_path / "serve.log",
                        "--job-cpu-s", "2")
    try:
        hog = submit(server, HOG, "hog.ngc")
        job, _ = wait_for(server, hog, FINISHED, timeout_s=120)
        assert (job["status"], job["attempts"]) == ("failed", 1), job
        assert job["error"] == {"message": "job exceeded its CPU-time limit of 2 s (the "
                                "server's --job-cpu-s)", "type": "CpuTimeLimit"}
        assert not psutil.pid_exists(server.worker_of(hog))
        short = submit(server, SHORT, "short.ngc")
        assert wait_for(server, short, FINISHED)[0]["status"] == "succeeded"
        again = server.http.get(f"/v1/jobs/{hog}").json()  # failed for good: never requeued
        assert (again["status"], again["attempts"]) == ("failed", 1)
        assert all(w.poll() is None for w in cluster.workers)
    finally:
        server.stop()


def test_a_dask_worker_killed_mid_job_costs_one_more_attempt(cluster, local_results, tmp_path):
    """Last: it leaves the cluster one worker short."""
    server = DaskServer(tmp_path / "oga.db", cluster.address, tmp_path / "serve.log")
    try:
        job_id = submit(server, LONG, "long.ngc")
        child = psutil.Process(server.child_of(job_id))
        holder = next(k for k, w in enumerate(cluster.workers) if w.pid == child.ppid())
        cluster.kill_worker(holder)
        child.wait(timeout=30)  # it dies with its Dask worker
        job, _ = wait_for(server, job_id, FINISHED)
        assert (job["status"], job["attempts"]) == ("succeeded", 2), job
        assert _results(server, job_id) == local_results["long.ngc"]
    finally:
        server.stop()


def test_serve_refuses_workers_with_a_scheduler(tmp_path):
    r = subprocess.run([sys.executable, "-m", "oga", "serve", "--db", str(tmp_path / "oga.db"),
                        "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "--workers is for local worker processes" in r.stderr
