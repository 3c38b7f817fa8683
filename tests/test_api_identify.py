"""``POST /v1/identify``: a short synthetic trace identified by a job, the machine file it
returns, and the answers to bad traces (422 naming the column and the row)."""

from __future__ import annotations

import html
import socket
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api import Settings, create_app
from api.storage import Owner
from api.workers import run_claimed
from feedplan.read import read_toolpath
from oga.identify.excite import excite_program
from oga.identify.sim import synthetic_trace
from oga.identify.trace import trace_csv
from oga.model.machine import load_machine
from oga.pipeline import plan_toolpath

OWNER = Owner(socket.gethostname(), 12345, "t", 12345)


@pytest.fixture(scope="module")
def trace():
    """A 20 mm identification program of axis x run on ucp710 with Kv +20 % and Tn -30 %,
    recorded at Kp 3, Kf 0.8 with 0.1 um noise and quantum: (CSV text, true machine)."""
    base = load_machine("ucp710")
    cas = base.axis("x").cascade
    true = base.model_copy(update={"axes": {**base.axes, "x": base.axis("x").model_copy(update={
        "cascade": cas.model_copy(update={"kv_n_s_m": cas.kv_n_s_m * 1.2, "tn_s": cas.tn_s * 0.7})})}})
    program = excite_program(base, ["x"], travel_mm=20.0)
    sp = plan_toolpath(read_toolpath(program, "gcode"), base, feed_m_s=None, tol_m=2e-5)
    ch = synthetic_trace(sp, true, ["x"], 3.0, 0.8, noise_m=1e-7, quantum_m=1e-7, seed=5)
    t = ch.pop("t_s")
    return trace_csv(t, ch), true


@pytest.fixture
def client(tmp_path):
    """An app without workers: the test runs the jobs (``run_claimed``)."""
    app = create_app(Settings(db_path=str(tmp_path / "i.db"), workers=0))
    with TestClient(app) as c:
        yield c


@pytest.fixture(params=["sqlite", "postgresql"])
def any_client(request, tmp_path):
    """:func:`client` on each store backend (PostgreSQL: a throwaway cluster)."""
    if request.param == "sqlite":
        yield request.getfixturevalue("client")
        return
    from pg_cluster import PgCluster

    pg = PgCluster()
    try:
        with TestClient(create_app(Settings(db_path=pg.url, workers=0))) as c:
            yield c
    finally:
        pg.stop()


def request(content: str, fmt: str = "csv", **extra) -> dict:
    return {"trace": {"format": fmt, "content": content, "name": "trace.csv"},
            "machine": "ucp710", "kp": {"x": 3.0}, "kf": 0.8, **extra}


def test_identify_job_returns_a_machine_file_that_loads(any_client, trace, tmp_path):
    client = any_client
    text, true = trace
    r = client.post("/v1/identify", json=request(text))
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert r.headers["location"] == f"/v1/jobs/{job_id}"
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "queued" and job["toolpath_format"] == "trace-csv"
    assert job["links"]["machine"] == f"/v1/jobs/{job_id}/machine" and "table" not in job["links"]
    for route in ("machine", "report"):  # not run yet
        r = client.get(f"/v1/jobs/{job_id}/{route}")
        assert r.status_code == 409 and "is queued" in r.json()["message"], route

    app = client.app
    assert run_claimed(app.state.store, app.state.store.claim(OWNER)) == "succeeded"
    assert client.get(f"/v1/jobs/{job_id}").json()["status"] == "succeeded"
    r = client.get(f"/v1/jobs/{job_id}/machine")
    r_machine = r.text
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/toml")
    assert r.headers["x-oga-job-id"] == job_id and "trace-identified.toml" in r.headers[
        "content-disposition"]
    path = tmp_path / "mine.toml"
    path.write_bytes(r.content)
    mine = load_machine(path)  # loads like any machine file
    assert mine.name == "ucp710-identified"
    assert mine.timing.dead_time_samples == true.timing.dead_time_samples
    cas, ref = mine.axis("x").cascade, true.axis("x").cascade
    assert cas.kv_n_s_m == pytest.approx(ref.kv_n_s_m, rel=0.05)
    assert cas.tn_s == pytest.approx(ref.tn_s, rel=0.05)
    assert "# 95 % CI [" in r.text and "position residual RMS" in r.text
    assert mine.axis("x").uncertainty is not None

    summary = client.get(f"/v1/jobs/{job_id}/summary").json()
    x = summary["axes"]["x"]
    assert summary["status"] == x["status"] == "ok"
    assert x["values"]["kv_n_s_m"] == pytest.approx(cas.kv_n_s_m)
    assert x["ci_low"]["kv_n_s_m"] < cas.kv_n_s_m < x["ci_high"]["kv_n_s_m"]
    assert 0 < x["residual_rms_m"] < 1e-6
    # an identification has no gain table
    r = client.get(f"/v1/jobs/{job_id}/table")
    assert r.status_code == 409 and "/machine" in r.json()["message"]
    # its report is the fit report, rebuilt from what the job stored (as oga identify --report)
    r = client.get(f"/v1/jobs/{job_id}/report")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert r.headers["x-oga-job-id"] == job_id
    page = r.text
    assert "<h1>oga identify: ucp710-identified</h1>" in page and "<h2>Axis x</h2>" in page
    assert "Trace trace.csv: " in page and page.count("<svg") == 2  # fit and friction curve
    assert f"<th>kv_n_s_m</th><td>{x['values']['kv_n_s_m']:.6g}</td>" in page
    assert f"Residual RMS {x['residual_rms_m'] * 1e6:.4g} um" in page
    assert f"<pre>{html.escape(r_machine)}</pre>" in page  # the machine file the job returned


def _rows(text: str, row: int, edit) -> str:
    """``text`` with its line ``row`` (0-based; the header is line 0) edited: the messages
    call it row ``row + 1``, the file's line number."""
    lines = text.splitlines()
    lines[row] = edit(lines[row])
    return "\n".join(lines) + "\n"


def _cell(col: int, value: str):
    return lambda line: ",".join(value if j == col else c for j, c in enumerate(line.split(",")))


@pytest.mark.parametrize("edit, extra, message", [
    (lambda s: _rows(s, 5, _cell(1, "nan")), {}, "column 'x_cmd_m', row 6: nan is not a finite"),
    (lambda s: _rows(s, 40, _cell(0, repr(float(s.splitlines()[40].split(",")[0]) + 4e-4))), {},
     "column 't_s', row 41: non-uniform sampling"),
    (lambda s: _rows(s, 40, lambda ln: s.splitlines()[39]), {},
     "column 't_s', row 41: duplicated row"),
    (lambda s: s.replace("x_act_m", "x_actual_m", 1), {}, "column 3: unknown name 'x_actual_m'"),
    (lambda s: s, {"units": "mm", "kp": 3.0}, None),  # mm: speeds / 1000, accepted
    (lambda s: "\n".join(",".join(repr(float(c) * 1e3) if j else c for j, c in
                                  enumerate(ln.split(","))) if k else ln
                         for k, ln in enumerate(s.splitlines())), {},
     "column 'x_cmd_m', row "),  # a trace in mm read as metres: absurd speed
    (lambda s: s, {"kp": None}, "no x_kp_m_min_per_mm column and no --kp"),
    (lambda s: s, {"axes": ["z"]}, "axis z: not in the trace"),
    (lambda s: s, {"machine": "nosuch"}, "unknown preset 'nosuch'"),
])
def test_bad_traces_are_422_naming_column_and_row(client, trace, edit, extra, message):
    text, _ = trace
    r = client.post("/v1/identify", json=request(edit(text), **extra))
    if message is None:
        assert r.status_code == 202, r.text
        return
    assert r.status_code == 422, r.text
    assert message in r.json()["message"], r.json()
    assert client.get("/v1/jobs").json()["total"] == 0  # nothing queued


@pytest.mark.parametrize("bad", [
    {"tolerance": 1},  # unknown key
    {"trace": {"format": "csv", "content": "x", "colour": "red"}},  # unknown key in the trace
    {"trace": {"format": "excel", "content": "x"}},
    {"units": "inch"},
    {"holdout": 0.95},
    {"kp": {"q": 3.0}},
])
def test_unknown_keys_and_bad_options_are_422(client, trace, bad):
    body = {**request(trace[0]), **bad}
    r = client.post("/v1/identify", json=body)
    assert r.status_code == 422, r.text
    key = next(iter(bad))
    assert key in r.json()["message"] or key in str(r.json().get("loc", "")), r.json()


def test_halsampler_trace_with_named_columns(client, trace):
    """The same trace as halsampler prints it (no header, whitespace, a sample number)."""
    text, _ = trace
    names = text.splitlines()[0].split(",")
    data = np.array([[float(c) for c in ln.split(",")] for ln in text.splitlines()[1:]])
    rows = "\n".join(f"{k} " + " ".join(repr(float(v)) for v in row[1:]) for k, row in enumerate(data))
    body = request(rows + "\n", "halsampler", columns=["sample", *names[1:]])
    r = client.post("/v1/identify", json=body)
    assert r.status_code == 202, r.text
    job = client.get(f"/v1/jobs/{r.json()['id']}").json()
    assert job["toolpath_format"] == "trace-halsampler"
    assert job["options"]["columns"] == ["sample", *names[1:]]
    body["columns"] = names[1:]  # one channel name fewer than the columns
    r = client.post("/v1/identify", json=body)
    assert r.status_code == 422 and "column" in r.json()["message"], r.text


def test_machine_of_an_optimisation_job_is_409_and_identify_jobs_cancel(client, trace):
    program = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X8\nM2\n"
    opt = client.post("/v1/jobs", json={"toolpath": {"format": "gcode", "content": program},
                                        "options": {"nominal": True}})
    r = client.get(f"/v1/jobs/{opt.json()['id']}/machine")
    assert r.status_code == 409 and "optimises a toolpath" in r.json()["message"]
    assert client.get("/v1/jobs/nope/machine").status_code == 404
    job_id = client.post("/v1/identify", json=request(trace[0])).json()["id"]
    assert client.delete(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"


def test_a_fit_job_reports_rising_progress(tmp_path):
    """A real ``oga serve``: an identification with a held-out refit (two fits of a 13.9 s
    trace) reports a rising fraction while it runs (its work between two reports is bounded
    in CPU time in ``test_identify.py``; whether ``/healthz`` calls a job stalled depends on
    the CPU its niced worker gets, so it is not asserted here)."""
    from test_api_server import Server, wait_for

    base = load_machine("ucp710")
    program = excite_program(base, ["x"], travel_mm=10.0, pass_s=0.5,
                             sweep_hz=(4.0, 7.0, 10.0, 15.0, 20.0))
    sp = plan_toolpath(read_toolpath(program, "gcode"), base, feed_m_s=None, tol_m=2e-5)
    ch = synthetic_trace(sp, base, ["x"], 3.0, 0.8, noise_m=1e-7, quantum_m=1e-7, seed=5)
    t = ch.pop("t_s")
    server = Server(tmp_path / "oga.db", 1, tmp_path / "serve.log")
    try:
        r = server.http.post("/v1/identify", json=request(trace_csv(t, ch), holdout=0.25))
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        wait_for(server, job_id, ("running", "succeeded", "failed"))
        seen, t_end = [], time.monotonic() + 900
        while time.monotonic() < t_end:
            job = server.http.get(f"/v1/jobs/{job_id}").json()
            if job["status"] != "running":
                break
            seen.append(job["progress"])
            time.sleep(0.1)
        assert job["status"] == "succeeded", job
        assert seen == sorted(seen) and len({f for f in seen if 0 < f < 1}) >= 3, seen
        assert server.http.get(f"/v1/jobs/{job_id}/report").status_code == 200
    finally:
        server.stop()
