"""Programs per minute of ``oga batch`` on a Dask cluster with 1 and 2 workers, and the overhead
the cluster adds per task (a benchmark, not a test).

Run: ``python bench/bench_scale.py [N]`` from the repository root (N programs, default 12:
the programs of tests/data, copied with a distinct comment each). For 1 and 2 workers
(``dask worker --nthreads 1`` each, on loopback, started here) it runs ``oga batch
--scheduler`` and prints the wall time and programs per minute. Overheads: the cluster's per
task is the wall time of 400 empty tasks through a client, / 400; the fixed cost of a batch is
the same command run again (every program skipped: start, connect, checks); "beyond
optimize" is ((wall - fixed) x workers - sum of the summaries' ``optimize_time_s``) / N, the
time of a program outside the gain search (planning, verification, rendering, transfer,
writing).

The service on the same cluster (``oga serve --scheduler``, jobs in SQLite): the N programs
POSTed at once (after one job per worker has started the workers' job processes), the wall
time until the last one finished, and per job ``wall x workers /
N - optimize`` beyond the search: planning, verification, the job's own process (start,
imports, kernels loaded from the cache) and the store's writes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from dask_cluster import DaskCluster  # noqa: E402

NAMES = ["short_xz", "circle_r50_f3000", "reference_xz", "helix_r20", "corner_steps",
         "sharp_corners_xy"]


def _programs(folder: Path, n: int) -> list[str]:
    files = []
    for k in range(n):
        name = NAMES[k % len(NAMES)]
        text = (ROOT / "tests" / "data" / f"{name}.ngc").read_text()
        path = folder / f"{name}_{k}.ngc"
        path.write_text(text + f"\n(copy {k})\n")
        files.append(str(path))
    return files


def _noop(x):
    return x


def _service(address: str, folder: Path, programs: list[str],
             workers: int) -> tuple[float, float]:
    """``oga serve --scheduler``: wall time of the programs as jobs, and their optimize time."""
    import httpx
    from test_api_server import _free_port

    port = _free_port()
    folder.mkdir()
    with open(folder / "serve.log", "ab") as log:
        server = subprocess.Popen([sys.executable, "-m", "oga", "serve", "--port", str(port),
                                   "--db", str(folder / "oga.db"), "--scheduler", address],
                                  stdout=log, stderr=subprocess.STDOUT)
    try:
        http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30)
        while True:
            try:
                http.get("/healthz")
                break
            except httpx.TransportError:
                assert server.poll() is None, f"oga serve exited: see {folder / 'serve.log'}"
                time.sleep(0.2)

        def run(paths: list[str]) -> list[str]:
            before = http.get("/healthz").json()["jobs"]["succeeded"]
            ids = [http.post("/v1/jobs", json={
                "toolpath": {"format": "gcode", "name": Path(p).name,
                             "content": Path(p).read_text()}, "machine": "ucp710"}).json()["id"]
                for p in paths]
            while True:
                jobs = http.get("/healthz").json()["jobs"]
                if jobs["succeeded"] + jobs["failed"] == before + len(ids):
                    break
                time.sleep(0.05)
            assert not jobs["failed"], f"{jobs['failed']} job(s) failed: see {folder}"
            return ids

        run(programs[:workers])  # every worker thread's job process started and warm
        t0 = time.perf_counter()
        ids = run(programs)
        wall = time.perf_counter() - t0
        compute = sum(http.get(f"/v1/jobs/{i}/summary").json()["optimize_time_s"] for i in ids)
        return wall, compute
    finally:
        server.terminate()
        server.wait(30)


def main(n: int) -> None:
    from distributed import Client

    print(f"load before (1/5/15 min): {' '.join(f'{x:.2f}' for x in os.getloadavg())} on "
          f"{os.cpu_count()} CPUs", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        programs = _programs(tmp, n)
        for workers in (1, 2):
            cluster = DaskCluster(tmp, workers)
            try:
                with Client(cluster.address, set_as_default=False) as client:
                    client.gather(client.map(_noop, range(400)))  # connections warm
                    t0 = time.perf_counter()
                    client.gather(client.map(_noop, range(400), pure=False))
                    empty_ms = (time.perf_counter() - t0) / 400 * 1e3
                    # warm the kernels' cache and the workers' imports on one program each
                    warm = tmp / f"warm{workers}"
                    subprocess.run([sys.executable, "-m", "oga", "batch", *programs[:workers],
                                    "--out", str(warm), "--scheduler", cluster.address],
                                   check=True, capture_output=True)
                out = tmp / f"out{workers}"
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "oga", "batch", *programs, "--out",
                                str(out), "--scheduler", cluster.address], check=True,
                               capture_output=True)
                wall = time.perf_counter() - t0
                t0 = time.perf_counter()  # again: every program skipped, the fixed cost
                subprocess.run([sys.executable, "-m", "oga", "batch", *programs, "--out",
                                str(out), "--scheduler", cluster.address], check=True,
                               capture_output=True)
                fixed = time.perf_counter() - t0
                service_wall, service_compute = _service(cluster.address, tmp / f"serve{workers}",
                                                         programs, workers)
            finally:
                cluster.stop()
            compute = sum(json.loads(p.read_text())["optimize_time_s"]
                          for p in out.glob("*.summary.json"))
            print(f"{workers} worker(s): {n} programs in {wall:.1f} s = "
                  f"{n / wall * 60:.1f} programs/min; optimize {compute:.1f} s in all; "
                  f"fixed cost {fixed:.1f} s; "
                  f"{((wall - fixed) * workers - compute) / n * 1e3:.0f} ms/program beyond "
                  f"optimize; empty task {empty_ms:.2f} ms",
                  flush=True)
            print(f"  oga serve --scheduler: {n} jobs in {service_wall:.1f} s = "
                  f"{n / service_wall * 60:.1f} jobs/min; "
                  f"{(service_wall * workers - service_compute) / n * 1e3:.0f} ms/job beyond "
                  f"optimize", flush=True)
    print(f"load after (1/5/15 min): {' '.join(f'{x:.2f}' for x in os.getloadavg())}",
          flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 12)
