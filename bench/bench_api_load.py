"""The service under load: ``/healthz`` latency while a real ``oga serve`` runs a burst of jobs.

Run:  python bench/bench_api_load.py [--jobs 20] [--workers 2] [--every-ms 50]

Starts ``oga serve`` on a free loopback port (SQLite in a temporary folder), submits ``--jobs``
nominal jobs at once (short XZ programs at feeds 1500-5000 mm/min, as in
tests/test_api_load.py), polls ``/healthz`` every ``--every-ms`` until every job has finished,
and prints the latency's median, p90, p99 and max, the same while idle, and the jobs' wall
time. The event loop must not wait on a job (jobs run in worker processes), so the latency
under load should stay near the idle one. A benchmark prints figures; it asserts nothing. On a
shared host the tail is only as good as the load.
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

SHORT = "G21 G90 G18\nG1 X0 Z0 F{feed}\nG1 X8\nG2 X13 Z5 I0 K5\nG1 X25 Z5\nM2\n"
FEEDS = (1500, 2000, 2500, 3000, 3500, 4000, 4500, 5000)
FINISHED = ("succeeded", "failed", "cancelled")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _poll(url: str, every_s: float, stop: threading.Event) -> list[float]:
    latencies: list[float] = []
    with httpx.Client(base_url=url, timeout=30.0) as http:
        while not stop.is_set():
            t0 = time.perf_counter()
            http.get("/healthz").raise_for_status()
            latencies.append(time.perf_counter() - t0)
            stop.wait(every_s)
    return latencies


def _measure(url: str, every_s: float, during) -> tuple[np.ndarray, float]:
    """Latencies (s) polled while ``during()`` runs, and its wall time (s)."""
    stop, out = threading.Event(), []
    poller = threading.Thread(target=lambda: out.extend(_poll(url, every_s, stop)))
    poller.start()
    t0 = time.perf_counter()
    try:
        during()
    finally:
        wall = time.perf_counter() - t0
        stop.set()
        poller.join()
    return np.array(out), wall


def _line(name: str, lat: np.ndarray) -> str:
    ms = lat * 1e3
    return (f"{name:<10} {len(ms):>6} {np.median(ms):>8.1f} {np.percentile(ms, 90):>8.1f} "
            f"{np.percentile(ms, 99):>8.1f} {ms.max():>8.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--every-ms", type=float, default=50.0)
    args = ap.parse_args()
    every_s = args.every_ms / 1e3
    with tempfile.TemporaryDirectory() as tmp:
        port = _free_port()
        url = f"http://127.0.0.1:{port}"
        log = open(Path(tmp) / "serve.log", "wb")
        proc = subprocess.Popen([sys.executable, "-m", "oga", "serve", "--port", str(port),
                                 "--db", str(Path(tmp) / "oga.db"), "--workers",
                                 str(args.workers)], stdout=log, stderr=subprocess.STDOUT)
        try:
            http = httpx.Client(base_url=url, timeout=30.0)
            t_end = time.monotonic() + 90
            while time.monotonic() < t_end:
                try:
                    if http.get("/healthz").json()["workers_alive"] == args.workers:
                        break
                except httpx.TransportError:
                    time.sleep(0.2)
            else:
                sys.exit("oga serve did not come up")
            idle, _ = _measure(url, every_s, lambda: time.sleep(3.0))

            def burst() -> None:
                bodies = [{"toolpath": {"format": "gcode", "name": f"short_{i}.ngc",
                                        "content": SHORT.format(feed=FEEDS[i % len(FEEDS)])},
                           "options": {"nominal": True}} for i in range(args.jobs)]
                ids = [http.post("/v1/jobs", json=b).json()["id"] for b in bodies]
                while ids:
                    ids = [i for i in ids if http.get(f"/v1/jobs/{i}").json()["status"]
                           not in FINISHED]
                    time.sleep(0.2)

            busy, wall = _measure(url, every_s, burst)
        finally:
            proc.terminate()
            proc.wait(30)
            log.close()
    print(f"/healthz latency, ms ({args.workers} workers, polled every {args.every_ms:g} ms)")
    print(f"{'':<10} {'n':>6} {'median':>8} {'p90':>8} {'p99':>8} {'max':>8}")
    print(_line("idle", idle))
    print(_line(f"{args.jobs} jobs", busy))
    print(f"{args.jobs} jobs finished in {wall:.1f} s wall")


if __name__ == "__main__":
    main()
