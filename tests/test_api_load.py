"""Load on a real ``oga serve`` (loopback): 20 concurrent jobs, hostile and normal mixed.

Every normal job finishes with its table; every hostile one is refused at submission (4xx
naming the problem) or ends with a clear error (or, for a feed far above the axes' speed,
with a table planned at what the axes allow); the long ones are cancelled; ``/healthz``
answers throughout, 200 each time. Its latency is a figure, not an assertion (a shared host's
load decides the tail): ``bench/bench_api_load.py`` prints it idle and under such a burst.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx

from test_api_server import FINISHED, LONG, SHORT, Server

#: Limits of the server under test: a job that spins is failed after 5 s of CPU time.
FLAGS = ("--job-cpu-s", "5", "--job-memory-mb", "1024")
#: The test ends within this, s: a guard against a hang, not a speed bound (10 jobs take
#: 20-70 s on two shared cores).
DEADLINE_S = 400.0
HEALTH_EVERY_S = 0.05  # the jobs now plan in seconds: poll often enough to see the load


def _gcode(content: str, name: str) -> dict:
    return {"toolpath": {"format": "gcode", "content": content, "name": name},
            "options": {"nominal": True}}


NORMAL = [_gcode(SHORT.replace("F3000", f"F{feed}"), f"short_f{feed}.ngc")
          for feed in (1500, 2000, 2500, 3000, 3500, 4000, 4500, 5000)]
#: Refused at submission: (body, status, words of the message).
REFUSED = [
    (_gcode("G21 G90\nG1 X0 Y0 F0.001\nG1 X1 Y0\nM2\n", "tiny_feed.ngc"), (413, 422), "line 3"),
    (_gcode("G21 G90\nG1 X0 Y0 F0.0001\nG1 X0 Y2\nM2\n", "tinier_feed.ngc"), (413, 422), "line 3"),
    (_gcode("G21 G90\nG1 X0 Y0 F3000\nG1 X100000000\nM2\n", "100km.ngc"), (413, 422), "100km.ngc:3:4"),
    (_gcode("G21 G90\nG1 X0 Y0 F1000\nG1 X" + "9" * 320 + " Y5\nM2\n", "nines.ngc"), (422,),
     "nines.ngc:3:4"),
    (_gcode("G21 G90\nG1 X0 Y0 F1000\nG1 Y" + "9" * 400 + "\nM2\n", "more_nines.ngc"), (422,),
     "more_nines.ngc:3:4"),
    (_gcode("G21 G90\nG1 X0 Y0 F1000\nG1 X10 Q\nM2\n", "bad_word.ngc"), (422,), "3:"),
    (_gcode("", "empty.ngc"), (422,), "toolpath.content"),
]
#: Accepted, then either failed with a clear error or (the axes' speed) succeeded.
HUGE_FEED = [_gcode(f"G21 G90\nG1 X0 Y0 F{feed}\nG1 X10 Y5\nM2\n", f"huge_feed_{feed}.ngc")
             for feed in ("10000000000", "100000000000000")]
#: Accepted, then cancelled.
LONG_JOBS = [_gcode(LONG.replace("X1000", f"X{x}"), f"long_{x}.ngc") for x in (900, 1000, 1100)]
#: Clear errors a hostile job may end with.
CLEAR_ERRORS = {"CpuTimeLimit", "MemoryLimit", "GcodeError", "ToolpathError", "PlanError",
                "OptionError", "InputError"}


def test_twenty_concurrent_jobs_hostile_and_normal(tmp_path):
    server = Server(tmp_path / "oga.db", 2, tmp_path / "serve.log", *FLAGS)
    t_end = time.monotonic() + DEADLINE_S
    latencies: list[float] = []
    health_codes: set[int] = set()
    stop = threading.Event()

    def watch_health() -> None:
        with httpx.Client(base_url=server.url, timeout=5.0) as http:
            while not stop.is_set() and time.monotonic() < t_end:
                t0 = time.perf_counter()
                try:  # a loop held by a job would show here, as no answer within 5 s
                    health_codes.add(http.get("/healthz").status_code)
                except httpx.TransportError as e:
                    health_codes.add(type(e).__name__)
                latencies.append(time.perf_counter() - t0)
                stop.wait(HEALTH_EVERY_S)

    watcher = threading.Thread(target=watch_health)
    watcher.start()
    try:
        bodies = NORMAL + [b for b, _, _ in REFUSED] + HUGE_FEED + LONG_JOBS
        assert len(bodies) == 20
        with ThreadPoolExecutor(max_workers=20) as pool:
            answers = list(pool.map(lambda b: server.http.post("/v1/jobs", json=b), bodies))
        n = len(NORMAL)
        normal = answers[:n]
        refused = answers[n:n + len(REFUSED)]
        huge = answers[n + len(REFUSED):n + len(REFUSED) + len(HUGE_FEED)]
        long = answers[-len(LONG_JOBS):]
        for r, (_, statuses, words) in zip(refused, REFUSED):
            assert r.status_code in statuses and words in r.json()["message"], r.text
            assert "inf" not in r.json()["message"]
        for r in normal + huge + long:
            assert r.status_code == 202, r.text

        for r in long:  # cancelled queued or running: either way at once
            job = server.http.delete(f"/v1/jobs/{r.json()['id']}").json()
            assert job["status"] == "cancelled", job

        pending = {r.json()["id"]: r for r in normal + huge}
        done: dict[str, dict] = {}
        while pending and time.monotonic() < t_end:
            for job_id in list(pending):
                job = server.http.get(f"/v1/jobs/{job_id}").json()
                if job["status"] in FINISHED:
                    done[job_id] = job
                    del pending[job_id]
            time.sleep(0.2)
        assert not pending, f"jobs not finished in {DEADLINE_S} s: {list(pending)}"

        for r, body in zip(normal, NORMAL):
            job = done[r.json()["id"]]
            assert job["status"] == "succeeded", job
            table = server.http.get(f"/v1/jobs/{job['id']}/table")
            assert table.status_code == 200 and len(table.text.splitlines()) > 100
            assert job["source"] == body["toolpath"]["name"]
        for r in huge:
            job = done[r.json()["id"]]
            assert job["status"] in ("succeeded", "failed"), job
            if job["status"] == "failed":
                assert job["error"]["type"] in CLEAR_ERRORS and job["attempts"] == 1, job
        for r in long:
            assert server.http.get(f"/v1/jobs/{r.json()['id']}").json()["status"] == "cancelled"
        health = server.http.get("/healthz").json()
        assert health["workers_alive"] == 2 and health["jobs"]["running"] == 0
    finally:
        stop.set()
        watcher.join()
        server.stop()
    assert len(latencies) >= 20 and health_codes == {200}
    print(f"\n/healthz: {len(latencies)} answers, max {max(latencies) * 1e3:.1f} ms, "
          f"median {sorted(latencies)[len(latencies) // 2] * 1e3:.1f} ms")
