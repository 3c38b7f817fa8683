"""The REST API in-process (FastAPI TestClient): jobs, tables, bad input, durability rules."""

from __future__ import annotations

import dataclasses
import json
import socket
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, Phase, settings

from api import Settings, create_app
from api.schemas import TableFormat
from api.storage import Owner, SqliteStore, StoreError, open_store
from api.workers import MAX_ATTEMPTS, WorkerPool, run_claimed
from oga.export.table import TABLE_FORMATS, table_csv, table_from_npz, table_columns
from oga.model.machine import load_machine, machine_from_dict
from oga.options import options_from_dict
from oga.pipeline import run_job

DATA = __import__("pathlib").Path(__file__).parent / "data"

#: A short XZ contour (line, arc, line; about 1 s of motion at F3000).
PROGRAM = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X8\nG2 X13 Z5 I0 K5\nG1 X25 Z5\nM2\n"
OPTIONS: dict = {"nominal": True}  # the nominal search (robust runs: test_robust_cli.py)


def body(content: str = PROGRAM, fmt: str = "gcode", **extra) -> dict:
    return {"toolpath": {"format": fmt, "content": content, "name": "short.ngc"},
            "options": OPTIONS, **extra}


def wait_job(client, job_id: str, timeout_s: float = 180.0) -> tuple[dict, list[str]]:
    """Poll a job until it finishes; returns it and the statuses seen."""
    seen, t_end = [], time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if not seen or seen[-1] != job["status"]:
            seen.append(job["status"])
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job, seen
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s (seen {seen})")


@pytest.fixture(scope="module")
def reference():
    """The same job run by the library in this process."""
    job = run_job(PROGRAM, "gcode", load_machine("ucp710"), options_from_dict(OPTIONS),
                  source="short.ngc")
    assert job.result.status == "ok", job.result.optimized.violations
    return job


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    """An app with one worker process."""
    db = tmp_path_factory.mktemp("api") / "jobs.db"
    with TestClient(create_app(Settings(db_path=str(db), workers=1))) as c:
        yield c


@pytest.fixture
def queue_only(tmp_path):
    """An app without workers: jobs stay queued unless a test runs them."""
    app = create_app(Settings(db_path=str(tmp_path / "q.db"), workers=0, sync_timeout_s=0.3,
                              max_upload_bytes=4096))
    with TestClient(app) as c:
        yield c


# -- the happy path ------------------------------------------------------------------------------

def test_job_runs_in_a_worker_to_the_library_table(client, reference):
    r = client.post("/v1/jobs", json=body())
    assert r.status_code == 202
    assert r.json()["status"] == "queued"
    job_id = r.json()["id"]
    assert r.headers["location"] == f"/v1/jobs/{job_id}"
    job, seen = wait_job(client, job_id)
    assert job["status"] == "succeeded" and seen[-1] == "succeeded", job
    assert set(seen) <= {"queued", "running", "succeeded"}
    assert job["progress"] == 1.0 and job["error"] is None and job["attempts"] == 1
    assert job["created_at"] <= job["started_at"] <= job["finished_at"]
    assert job["options"] == options_from_dict(OPTIONS).as_dict()

    csv = client.get(f"/v1/jobs/{job_id}/table")
    assert csv.status_code == 200 and csv.headers["content-type"].startswith("text/csv")
    assert csv.text == table_csv(reference.result)  # byte-identical to oga optimize --out

    summary = client.get(f"/v1/jobs/{job_id}/summary").json()
    expected = json.loads(json.dumps(reference.summary()))
    for key in ("optimize_time_s",):  # wall time differs between runs
        summary.pop(key), expected.pop(key)
    # a job runs on one thread unless its options say (the result is the same bits on any)
    assert summary["options"].pop("threads") == 1 and expected["options"].pop("threads") is None
    assert summary == expected

    header, cols = table_columns(reference.result)
    npz = client.get(f"/v1/jobs/{job_id}/table", params={"format": "npz"})
    table = table_from_npz(npz.content)
    assert table.header == tuple(header) and np.array_equal(table.data, np.column_stack(cols))
    assert table.meta["toolpath_sha256"] == reference.toolpath_sha256
    for fmt in ("json", "c"):
        r = client.get(f"/v1/jobs/{job_id}/table", params={"format": fmt, "name": "part_1"})
        assert r.status_code == 200
        assert r.headers["content-type"].split(";")[0] == TABLE_FORMATS[fmt][1].split(";")[0]
    assert "static const double part_1_kp_m_min_per_mm" in r.text
    assert client.get(f"/v1/jobs/{job_id}/table", params={"format": "xlsx"}).status_code == 422
    assert client.get(f"/v1/jobs/{job_id}/table",
                      params={"format": "c", "name": "1x"}).status_code == 422


def test_synchronous_gain_table_matches_the_job_table(client, reference):
    r = client.post("/v1/gain-table", json=body())
    assert r.status_code == 200, r.text
    assert r.text == table_csv(reference.result)
    job = client.get(f"/v1/jobs/{r.headers['x-oga-job-id']}").json()
    assert job["status"] == "succeeded"


def test_a_machine_object_with_a_following_error_limit(client):
    machine = load_machine("ucp710").model_dump(mode="json")
    for a in ("x", "z"):
        machine["axes"][a]["limits"]["ferror_max_m"] = 1.5e-4
    r = client.post("/v1/gain-table", json=body(machine=machine))
    assert r.status_code == 200, r.text
    summary = client.get(f"/v1/jobs/{r.headers['x-oga-job-id']}/summary").json()
    assert summary["limits_ok"] and summary["machine_sha256"] == machine_from_dict(machine).digest()
    for a in ("x", "z"):
        assert 0.0 < summary["ferror_ratio_to_limit"][a] <= 1.0
        assert summary["optimized"]["track_max_um"][a] <= 150.0
    # a limit no fixed gains keep: 422 naming it, the job and its error kept
    machine["axes"]["x"]["limits"]["ferror_max_m"] = 1e-6
    r = client.post("/v1/gain-table", json=body(machine=machine))
    assert r.status_code == 422 and "following-error" in r.json()["message"], r.text
    job = client.get(f"/v1/jobs/{r.headers['x-oga-job-id']}").json()
    assert job["status"] == "failed" and "following-error" in job["error"]["message"]


def test_synchronous_gain_table_refuses_long_toolpaths_with_a_hint(client):
    before = client.get("/v1/jobs").json()["total"]
    long = "G21 G90\nG1 X0 Y0 F3000\nG1 X1000\nM2\n"  # 20 s at 3 m/min
    r = client.post("/v1/gain-table", json=body(long))
    assert r.status_code == 413
    assert "POST /v1/jobs" in r.json()["message"] and "20.0 s" in r.json()["message"]
    assert client.get("/v1/jobs").json()["total"] == before


def test_machines_and_health(client):
    preset = load_machine("ucp710")
    items = client.get("/v1/machines").json()["items"]
    assert {"name": "ucp710", "source": preset.source, "axes": ["x", "y", "z"],
            "sha256": preset.digest()} in items
    r = client.get("/v1/machines/ucp710")
    assert machine_from_dict(r.json()) == preset
    assert r.headers["x-oga-machine-sha256"] == preset.digest()
    assert client.get("/v1/machines/nope").status_code == 404
    health = client.get("/healthz").json()
    assert health["status"] == "ok" and health["workers_alive"] == 1


def test_the_arx_preset_is_listed_and_served(client):
    preset = load_machine("mcv-op")
    items = {m["name"]: m for m in client.get("/v1/machines").json()["items"]}
    assert items["mcv-op"]["axes"] == ["x", "y"] and items["mcv-op"]["sha256"] == preset.digest()
    got = client.get("/v1/machines/mcv-op").json()
    assert "cascade" not in got["axes"]["x"] and got["axes"]["x"]["arx"]["den"][0] == 1.0
    assert machine_from_dict(got) == preset
    xy = "G21 G90 G17\nG1 X0 Y0 F3000\nG1 X8\nG3 X13 Y5 I0 J5\nG1 Y15\nM2\n"
    r = client.post("/v1/gain-table", json=body(xy, machine="mcv-op"))
    assert r.status_code == 200, r.text
    head = r.text.splitlines()
    assert head[0].startswith("t_s,s_m,x_pos_m") and len(head) > 500


# -- bad input: 4xx, never 5xx -------------------------------------------------------------------

def _bad_machine():
    m = load_machine("ucp710").model_dump(mode="json")
    m["axes"]["x"]["limits"]["vmax_m_s"] = -1.0
    return m


BAD_GCODE = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X10 Q\nM2\n"

BAD = {
    "unknown machine": (body(machine="nope"), 422, "unknown preset 'nope'"),
    "machine file path": (body(machine="/etc/passwd.json"), 422, "unknown preset"),
    "invalid machine field": (body(machine=_bad_machine()), 422, "axes.x.limits.vmax_m_s"),
    "option out of range": ({**body(), "options": {"np": 0}}, 422, "options.np"),
    "unknown option": ({**body(), "options": {"bogus": 1}}, 422, "options.bogus: unknown field"),
    "inconsistent baseline": ({**body(), "options": {"baseline": [2.0, 7.0]}}, 422, "Kf"),
    "unknown toolpath format": (body(fmt="dxf"), 422, "toolpath.format"),
    "missing content": ({"toolpath": {"format": "gcode"}}, 422, "toolpath.content"),
    "not an object": ([1, 2], 422, "body"),
    "empty toolpath": (body("G21\nM2\n"), 422, "no moves"),
    "nan in a csv polyline": (body("x,y,z\n0,0,0\nnan,1,0\n", fmt="csv"), 422, ""),
    "empty content": (body(""), 422, "toolpath.content: String should have at least 1 character"),
    "a coordinate beyond floating point": (
        body("G21 G90\nG1 X0 Y0 F1000\nG1 X" + "9" * 320 + " Y5\nM2\n"), 422, "short.ngc:3:4: X word: number out of range"),
    "a csv coordinate beyond floating point": (
        body("x,y,z\n0,0,0\n1e308,0,0\n-1e308,0,0\n", fmt="csv"), 422,
        ":3: point 2: coordinate out of range"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_answers_4xx_naming_what_is_wrong(queue_only, case):
    payload, status, words = BAD[case]
    r = queue_only.post("/v1/jobs", json=payload)
    assert r.status_code == status, r.text
    assert words in r.json()["message"] and r.json()["message"]


def test_motion_time_beyond_the_limit_is_413_at_submission(queue_only):
    """Tiny feeds and huge moves are refused before anything is planned, naming the move.

    (A reader that bounds feeds or coordinates itself may refuse them first: 422 naming
    the same line.)"""
    for payload, seconds in [
        (body("G21 G90\nG1 X0 Y0 F0.001\nG1 X1 Y0\nM2\n"), "60000.0 s"),  # 1 mm, 0.001 mm/min
        (body("G21 G90\nG1 X0 Y0 F3000\nG1 X100000000\nM2\n"), "2000000.0 s"),  # 100 km
        (body("x,y,z,feed\n0,0,0,1\n1e150,0,0,1\n", fmt="csv"), "6e+151 s"),
    ]:
        r = queue_only.post("/v1/jobs", json=payload)
        message = r.json()["message"]
        assert "inf" not in message and ("line 3" in message or ":3:" in message), message
        if r.status_code != 422:
            assert r.status_code == 413, r.text
            assert f"line 3, {seconds}" in message and "limit is 3600 s" in message, message
            assert "--job-max-motion-s" in message
    nines = body("G21 G90\nG1 X0 Y0 F1000\nG1 X" + "9" * 320 + " Y5\nM2\n")
    r = queue_only.post("/v1/gain-table", json=nines)  # was 413 "about inf s"
    assert r.status_code == 422 and ":3:4: X word" in r.json()["message"], r.text
    assert queue_only.get("/v1/jobs").json()["total"] == 0


def test_malformed_gcode_names_line_and_column(queue_only):
    r = queue_only.post("/v1/jobs", json=body(BAD_GCODE))
    assert r.status_code == 422
    err = r.json()
    line = BAD_GCODE.splitlines()[2]
    assert (err["line"], err["column"], err["type"]) == (3, line.index("Q") + 1, "GcodeError")


@pytest.mark.parametrize("raw", [
    b'{"toolpath": {"format": "gcode", "content": "G1 X1"}, "options": {"lam": NaN}}',
    b'{"toolpath": {"format": "gcode", "content": "G1 X1"}, "options": {"feed": Infinity}}',
    b'{"toolpath": {"format": "gcode", "content": "G1 X1"}, "options": {"kp_range": [1, 1e999]}}',
])
def test_non_finite_numbers_are_refused(queue_only, raw):
    r = queue_only.post("/v1/jobs", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422 and "options." in r.json()["message"]


def test_broken_json_is_400(queue_only):
    r = queue_only.post("/v1/jobs", content=b'{"toolpath": {', headers={"content-type": "application/json"})
    assert r.status_code == 400 and "malformed JSON" in r.json()["message"]


def test_oversized_uploads_are_413_with_or_without_length(queue_only):
    big = "G1 X1\n" * 1000  # 6000 bytes > the 4096 of this app
    assert queue_only.post("/v1/jobs", json=body(big)).status_code == 413

    def chunks():
        yield b'{"toolpath": {"format": "gcode", "content": "'
        for _ in range(100):
            yield b"G1 X1 " * 10
        yield b'"}}'

    r = queue_only.post("/v1/jobs", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and "4096" in r.json()["message"]
    assert queue_only.post("/v1/jobs", json=body()).status_code == 202


def test_unknown_jobs_and_routes_are_404(queue_only):
    for path in ("/v1/jobs/nope", "/v1/jobs/nope/table", "/v1/jobs/nope/summary", "/v2"):
        r = queue_only.get(path)
        assert r.status_code == 404 and r.json()["message"]
    assert queue_only.delete("/v1/jobs/nope").status_code == 404


# -- job life: cancel, pages, failed verification, recovery --------------------------------------

def test_cancel_a_queued_job(queue_only):
    job_id = queue_only.post("/v1/jobs", json=body()).json()["id"]
    assert queue_only.get(f"/v1/jobs/{job_id}/table").status_code == 409
    r = queue_only.delete(f"/v1/jobs/{job_id}")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert queue_only.delete(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"
    assert queue_only.get(f"/v1/jobs/{job_id}/table").status_code == 409
    assert queue_only.get(f"/v1/jobs/{job_id}/summary").status_code == 409


def test_jobs_are_listed_newest_first_in_pages(queue_only):
    ids = [queue_only.post("/v1/jobs", json=body()).json()["id"] for _ in range(3)]
    queue_only.delete(f"/v1/jobs/{ids[0]}")
    page = queue_only.get("/v1/jobs", params={"limit": 2}).json()
    assert [j["id"] for j in page["items"]] == ids[::-1][:2]
    assert (page["total"], page["next_offset"]) == (3, 2)
    last = queue_only.get("/v1/jobs", params={"limit": 2, "offset": 2}).json()
    assert [j["id"] for j in last["items"]] == [ids[0]] and last["next_offset"] is None
    queued = queue_only.get("/v1/jobs", params={"status": "queued"}).json()
    assert {j["id"] for j in queued["items"]} == set(ids[1:])
    assert queue_only.get("/v1/jobs", params={"limit": 0}).status_code == 422
    assert queue_only.get("/v1/jobs", params={"status": "done"}).status_code == 422


def _owner(pid: int, instance: str = "test", host: str | None = None) -> Owner:
    return Owner(host or socket.gethostname(), pid, instance, pid)


def test_a_schedule_failing_verification_fails_the_job_without_a_table(queue_only, reference,
                                                                        monkeypatch):
    store = queue_only.app.state.store
    job_id = queue_only.post("/v1/jobs", json=body()).json()["id"]
    violation = "axis x: velocity command jerk reaches 1.500x its limit"
    result = dataclasses.replace(
        reference.result, status="failed",
        optimized=dataclasses.replace(reference.result.optimized, violations=(violation,)))
    monkeypatch.setattr("oga.pipeline.run_job",
                        lambda *a, **k: dataclasses.replace(reference, result=result))
    run_claimed(store, store.claim(_owner(12345)))
    job = queue_only.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "failed"
    assert job["error"]["violations"] == [violation] and violation in job["error"]["message"]
    assert queue_only.get(f"/v1/jobs/{job_id}/table").status_code == 409
    assert queue_only.get(f"/v1/jobs/{job_id}/summary").json()["status"] == "failed"


def test_a_job_cancelled_while_running_stores_no_result(queue_only):
    store = queue_only.app.state.store
    job_id = queue_only.post("/v1/jobs", json=body()).json()["id"]
    claimed = store.claim(_owner(12345))
    assert queue_only.delete(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"
    run_claimed(store, claimed)  # the real engine; its writes are fenced off
    assert queue_only.get(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"
    assert store.table(job_id) is None


def _dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


def test_jobs_of_a_dead_server_or_worker_are_requeued(queue_only):
    store = queue_only.app.state.store
    pool = WorkerPool(store.path, 1)
    dead = _dead_pid()
    ids = [queue_only.post("/v1/jobs", json=body()).json()["id"] for _ in range(3)]
    # server on this host gone; server elsewhere silent for an hour; server elsewhere alive
    store.claim(_owner(dead, "old"))
    store.claim(_owner(4242, "far", host="elsewhere"))
    store.claim(_owner(4243, "near", host="elsewhere"))
    with sqlite3.connect(store.path) as db:
        db.execute("UPDATE jobs SET heartbeat = heartbeat - 3600 WHERE owner_instance = 'far'")
    assert sorted(pool.recover()) == sorted(ids[:2])
    statuses = [queue_only.get(f"/v1/jobs/{i}").json()["status"] for i in ids]
    assert statuses == ["queued", "queued", "running"]


def test_a_job_that_keeps_killing_its_worker_fails(queue_only):
    store = queue_only.app.state.store
    pool = WorkerPool(store.path, 1)
    dead = _dead_pid()
    job_id = queue_only.post("/v1/jobs", json=body()).json()["id"]
    for attempt in range(1, MAX_ATTEMPTS + 1):
        assert store.claim(_owner(dead, pool.instance)).attempts == attempt
        assert pool.recover({dead}) == [job_id]
    job = queue_only.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "failed" and job["error"]["type"] == "WorkerLost"


def test_a_submission_does_not_wait_behind_a_report_being_rendered(queue_only, monkeypatch):
    """CPU-bound request work runs one at a time per kind (api.app.CPU_WORK): while a report
    renders (held here until the submission is answered), a submission, which is reading,
    is answered; behind one limiter for both it would wait for the report."""
    import threading

    import api.routes as routes

    entered, release, held_out = threading.Event(), threading.Event(), []
    real = routes._report

    def held(request, job_id):
        entered.set()
        held_out.append(not release.wait(20))  # True: the submission waited behind it
        return real(request, job_id)

    monkeypatch.setattr(routes, "_report", held)
    job_id = queue_only.post("/v1/jobs", json=body()).json()["id"]
    answers = []
    report = threading.Thread(
        target=lambda: answers.append(queue_only.get(f"/v1/jobs/{job_id}/report")))
    report.start()
    try:
        assert entered.wait(20)
        r = queue_only.post("/v1/jobs", json=body())
        assert r.status_code == 202, r.text
    finally:
        release.set()
        report.join(30)
    assert held_out == [False]
    assert answers[0].status_code == 409  # the job is queued: no report yet


# -- the store's backend, chosen by the --db value ----------------------------------------------

def test_a_database_url_of_an_unknown_scheme_is_refused_naming_it(tmp_path, monkeypatch):
    """``mysql://...`` is no SQLite path (it would have made a folder ``mysql:``): refused,
    naming the scheme, the password hidden, nothing created; ``oga serve`` exits 2 on it. A
    path without a scheme is an SQLite file, which workers open by its absolute path."""
    monkeypatch.chdir(tmp_path)
    url = "mysql://oga:s3cret@localhost/jobs"
    with pytest.raises(StoreError) as err:
        open_store(url)
    assert "'mysql'" in str(err.value) and "s3cret" not in str(err.value)
    assert list(tmp_path.iterdir()) == []
    r = subprocess.run([sys.executable, "-m", "oga", "serve", "--db", url, "--port", "0"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "--db mysql://oga:***@localhost/jobs: unknown database scheme 'mysql'" in r.stderr
    store = open_store("jobs.db")
    assert isinstance(store, SqliteStore) and store.url == str(tmp_path / "jobs.db")
    store.close()


# -- API key --------------------------------------------------------------------------------------

def test_api_key_guards_every_route_but_healthz(tmp_path):
    app = create_app(Settings(db_path=str(tmp_path / "k.db"), workers=0, api_key="s3cret"))
    with TestClient(app) as c:
        assert c.get("/healthz").status_code == 200
        for path in ("/v1/machines", "/v1/jobs", "/docs", "/openapi.json", "/v1/jobs/x"):
            assert c.get(path).status_code == 401, path
        assert c.get("/v1/machines", headers={"X-API-Key": "wrong"}).status_code == 401
        assert c.post("/v1/jobs", json=body()).status_code == 401
        assert c.get("/v1/machines", headers={"X-API-Key": "s3cret"}).status_code == 200
        assert c.get("/v1/machines", headers={"Authorization": "Bearer s3cret"}).status_code == 200


# -- the OpenAPI schema, fuzzed --------------------------------------------------------------------

def test_table_formats_of_the_api_are_the_export_formats():
    assert set(TableFormat.__args__) == set(TABLE_FORMATS) | {"linuxcnc"}


def test_openapi_operations_never_answer_5xx_and_answer_as_documented(tmp_path):
    """schemathesis generates requests from the OpenAPI schema (a few per operation): no 5xx;
    status codes, media types and bodies as documented; schema-invalid requests refused."""
    import schemathesis
    from hypothesis import given
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import (
        content_type_conformance,
        negative_data_rejection,
        response_schema_conformance,
        status_code_conformance,
    )

    app = create_app(Settings(db_path=str(tmp_path / "f.db"), workers=0, sync_timeout_s=0.2))
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [r.ok() for r in schema.get_all_operations()]
    assert len(operations) >= 9

    for op in operations:
        @given(case=op.as_strategy())
        @settings(max_examples=8, deadline=None, derandomize=True, database=None,
                  phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
        def check(case):
            case.call_and_validate(checks=[not_a_server_error, status_code_conformance,
                                           content_type_conformance, response_schema_conformance,
                                           negative_data_rejection])

        check()


# -- HTTP conformance: media types, methods, the schema ---------------------------------------------

@pytest.mark.parametrize("headers, content, words", [
    ({"content-type": "text/plain"}, PROGRAM.encode(), "Content-Type text/plain"),
    ({"content-type": "multipart/form-data; boundary=x"},
     b'--x\r\nContent-Disposition: form-data; name="f"\r\n\r\nG1 X1\r\n--x--\r\n',
     "Content-Type multipart/form-data"),
    ({"content-type": "application/x-www-form-urlencoded"}, b"a=1", "application/x-www-form"),
    ({"content-type": "application/json", "content-encoding": "br"}, b"x", "Content-Encoding br"),
    ({"content-type": "application/json", "content-encoding": "gzip"},
     __import__("gzip").compress(json.dumps(body()).encode()), "Content-Encoding gzip"),
], ids=["text", "multipart", "form", "brotli", "gzip"])
def test_bodies_that_are_not_json_are_415(queue_only, headers, content, words):
    for path in ("/v1/jobs", "/v1/gain-table"):
        r = queue_only.post(path, content=content, headers=headers)
        assert r.status_code == 415, r.text
        assert words in r.json()["message"] and r.json()["type"] == "UnsupportedMediaType"


def test_json_bodies_need_a_json_content_type(queue_only):
    raw = json.dumps(body()).encode()
    for headers in ({"content-type": "application/json; charset=utf-8"},
                    {"content-type": "application/vnd.oga+json"},
                    {"content-type": "application/json", "content-encoding": "identity"}):
        assert queue_only.post("/v1/jobs", content=raw, headers=headers).status_code == 202
    r = queue_only.post("/v1/jobs", content=raw)
    assert r.status_code == 415 and r.json()["message"].startswith("no Content-Type")


def test_405_allows_every_method_of_the_path(queue_only):
    for method, path, allow in [("PUT", "/v1/jobs/x", "DELETE, GET"),
                                ("DELETE", "/v1/jobs", "GET, POST"),
                                ("GET", "/v1/gain-table", "POST"),
                                ("POST", "/healthz", "GET")]:
        r = queue_only.request(method, path)
        assert r.status_code == 405 and r.headers["allow"] == allow, (method, path, r.headers)
        for other in allow.split(", "):  # each one listed is served
            assert queue_only.request(other, path, json=body()).status_code != 405


def test_the_schema_says_what_the_server_answers(queue_only):
    schema = queue_only.get("/openapi.json").json()
    content = schema["components"]["schemas"]["ToolpathIn"]["properties"]["content"]
    assert content["minLength"] == 1
    report = schema["paths"]["/v1/jobs/{job_id}/report"]["get"]["responses"]
    assert list(report["200"]["content"]) == ["text/html"]
    for code in ("404", "409"):
        assert list(report[code]["content"]) == ["application/json"]
    job_id = queue_only.post("/v1/jobs", json=body()).json()["id"]
    r = queue_only.get(f"/v1/jobs/{job_id}/report")
    assert r.status_code == 409 and r.headers["content-type"] == "application/json"
    health = schema["components"]["schemas"]["Health"]["properties"]
    assert set(health["status"]["enum"]) == {"ok", "degraded"} and "stalled" in health


# -- progress ------------------------------------------------------------------------------------

def test_progress_moves_through_planning_the_baseline_and_the_search():
    """A program of many blocks: the fraction rises through planning (to PLAN_SHARE), the
    best-fixed-gains grid and the search, and never falls; the grid in parts finds the same
    best fixed gains as in one pass."""
    from feedplan.read import read_toolpath
    from oga.pipeline import PLAN_SHARE, plan_toolpath
    from oga.search.ranges import best_fixed_gains

    text = (DATA / "reference_xz.ngc").read_text()
    machine, seen = load_machine("ucp710"), []
    job = run_job(text, "gcode", machine, options_from_dict({"nominal": True}),
                  progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == 1.0
    planning = [f for f in seen if f <= PLAN_SHARE]
    grid = [f for f in seen if PLAN_SHARE < f <= PLAN_SHARE + (1 - PLAN_SHARE) / 2]
    assert len(set(planning)) >= 5 and planning[-1] == PLAN_SHARE
    assert len(set(grid)) >= 10
    assert len(set(seen)) - len(set(planning)) - len(set(grid)) >= 1  # the search's chunks

    sp = plan_toolpath(read_toolpath(text, "gcode"), machine, feed_m_s=None,
                       tol_m=options_from_dict({}).tol_m)
    parts: list[float] = []
    split, whole = best_fixed_gains(sp, machine, progress=parts.append), best_fixed_gains(sp, machine)
    assert (split.kp, split.kf, split.mse_ce_m2) == (whole.kp, whole.kf, whole.mse_ce_m2)
    assert parts == sorted(parts) and len(parts) >= 10 and parts[-1] == 1.0
    assert job.result.baseline_kp["x"] == whole.kp["x"]
