"""The optimisation report: one self-contained HTML page whose figures and tables hold the job."""

from __future__ import annotations

import math
import socket
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from oga.cli import main
from oga.model.kinematics import command_peaks
from oga.model.machine import load_machine, machine_from_dict
from oga.options import options_from_dict
from oga.pipeline import plan_toolpath, run_job
from oga.report.optimize import _command_derivatives, curvature, decimate, render_report

DATA = Path(__file__).parent / "data"
PAPER = {"mode": "paper", "baseline": "1.6,0.9", "adjust": "z", "gains": "kp",
         "kp_range": "1.0,2.7", "nominal": True}  # the exact-model search
#: The figures: path, gains/curvature, contour error, velocity command, following error,
#: stability.
FIGURES = 6


def _job(options: dict):
    text = (DATA / "short_xz.ngc").read_text()
    return run_job(text, "gcode", load_machine("ucp710"),
                   options_from_dict({"nominal": True, **options}),
                   source="short_xz.ngc")


@pytest.fixture(scope="module")
def paper_job():
    return _job(PAPER)


@pytest.fixture(scope="module")
def full_job():
    return _job({})


class Page(HTMLParser):
    """What a browser would see: figures, their SVG paths, table rows, every attribute."""

    def __init__(self, text: str):
        super().__init__()
        self.tags: list[str] = []
        self.attrs: list[tuple[str, str]] = []
        self.figures: list[dict] = []  # per <figure>: svg count, path d lengths
        self.rows: dict[str, list[str]] = {}  # data-key -> <td> texts (first table wins)
        self._row = self._cell = None
        self.feed(text)
        self.close()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        self.attrs += [(k, v or "") for k, v in attrs]
        if tag == "figure":
            self.figures.append({"svg": 0, "paths": []})
        elif tag == "svg" and self.figures:
            self.figures[-1]["svg"] += 1
        elif tag == "path" and self.figures:
            self.figures[-1]["paths"].append(len(a.get("d", "")))
        elif tag == "tr" and "data-key" in a:
            self._row = a["data-key"]
            self.rows.setdefault(self._row, [])
        elif tag == "td" and self._row is not None:
            self._cell = ""

    def handle_endtag(self, tag):
        if tag == "td" and self._cell is not None:
            if len(self.rows[self._row]) < 2:
                self.rows[self._row].append(self._cell)
            self._cell = None
        elif tag == "tr":
            self._row = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data


def _leaves(d: dict, prefix: str = ""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def _check_page(text: str, summary: dict) -> Page:
    page = Page(text)
    assert page.tags[0] == "html" and "body" in page.tags
    assert len(page.figures) == FIGURES
    for fig in page.figures:
        assert fig["svg"] == 1 and fig["paths"] and min(fig["paths"]) > 0, fig
    # self-contained: no external reference of any kind
    assert "http://" not in text and "https://" not in text
    assert not {"script", "link", "img", "iframe"} & set(page.tags)
    assert not [v for k, v in page.attrs if k in ("src", "href") or "url(" in v and "#" not in v]
    # the metrics table and the summary table hold the summary's numbers
    for key in ("mse_ce_um2", "rms_ce_um", "max_ce_um", "p95_ce_um"):
        base, opt = page.rows[key]
        assert float(base) == pytest.approx(summary["baseline"][key], rel=1e-6)
        assert float(opt) == pytest.approx(summary["optimized"][key], rel=1e-6)
    for a in summary["contouring_axes"]:
        base, opt = page.rows[f"track_max_um.{a}"]
        assert float(base) == pytest.approx(summary["baseline"]["track_max_um"][a], rel=1e-6)
        assert float(opt) == pytest.approx(summary["optimized"]["track_max_um"][a], rel=1e-6)
    numeric = 0
    for key, value in _leaves(summary):
        if isinstance(value, float) and math.isfinite(value):
            cell = page.rows[key][0] if key in page.rows else None
            assert cell is not None, key
            assert float(cell) == pytest.approx(value, rel=1e-6, abs=1e-12), key
            numeric += 1
    assert numeric > 20
    for key in ("toolpath_sha256", "setpoints_sha256", "machine_sha256", "options.mode"):
        assert page.rows[key][0] == str(_lookup(summary, key))
    for name in ("oga", "numpy", "numba", "python"):
        assert page.rows[name][0]
    return page


def _lookup(d: dict, key: str):
    for part in key.split("."):
        d = d[part]
    return d


def test_paper_mode_report_parses_and_holds_the_summary(paper_job):
    text = render_report(paper_job)
    _check_page(text, paper_job.summary())
    # an OptimizeResult gives the same page as its job, but for the toolpath hash it lacks
    assert render_report(paper_job.result).count("<svg") == FIGURES


def test_full_mode_report_draws_every_adjusted_axis(full_job):
    summary = full_job.summary()
    assert summary["adjusted"] == ["x", "z"] and summary["gains"] == ["kp", "kf"]
    text = render_report(full_job)
    _check_page(text, summary)
    for label in ("Kp x", "Kp z", "Kf x", "Kf z"):
        assert f">{label}</text>" in text


def test_following_error_figure_draws_the_limit_where_set(full_job):
    def figure(text, n):  # the SVG of figure n (1-based)
        return text.split("<figure")[n].split("</figure>")[0]

    free = figure(render_report(full_job), 5)
    assert "following error" in free and ">limit</text>" not in free
    data = load_machine("ucp710").model_dump(mode="json")
    for a in ("x", "z"):
        data["axes"][a]["limits"]["ferror_max_m"] = 1.5e-4
    text = (DATA / "short_xz.ngc").read_text()
    job = run_job(text, "gcode", machine_from_dict(data), options_from_dict({"nominal": True}),
                  source="short_xz.ngc")
    limited = figure(render_report(job), 5)
    assert limited.count(">limit</text>") == 2  # one panel per contouring axis
    assert limited.count("<path") == free.count("<path") + 4  # +-limit on each


def test_decimation_keeps_every_bucket_extreme():
    rng = np.random.default_rng(3)
    n, target = 100_003, 2000
    y = np.cumsum(rng.normal(size=n))
    y[[17, 5000, 77_777]] = [1e4, -1e4, 5e3]  # isolated spikes
    y[123] = np.nan
    idx = decimate(y, target)
    assert np.all(np.diff(idx) > 0) and idx[0] == 0 and idx[-1] == n - 1
    assert len(idx) <= 3 * target // 2 + 2
    assert {17, 5000, 77_777} <= set(idx.tolist())
    # every sample has a kept sample at least as high (and one as low) less than a bucket away
    size = math.ceil(2 * n / target)
    kept = np.full(n, np.nan)
    kept[idx] = y[idx]
    finite = ~np.isnan(y)
    for i in range(0, n, 997):
        if finite[i]:
            win = kept[max(0, i - size + 1): i + size]
            assert np.nanmax(win) >= y[i] and np.nanmin(win) <= y[i]
    short = np.arange(50.0)
    assert np.array_equal(decimate(short, target), np.arange(50))


def test_curvature_of_a_circle_is_one_over_its_radius():
    machine = load_machine("ucp710")
    from feedplan.read import load_toolpath

    sp = plan_toolpath(load_toolpath(DATA / "circle_r50_f3000.ngc"), machine, feed_m_s=None,
                       tol_m=20e-6)
    kappa = curvature(sp)
    speed = np.linalg.norm(sp.vel, axis=1)
    tangential = np.abs(np.sum(sp.vel * sp.acc, axis=1)) / np.maximum(speed, 1e-300)
    # at constant feed, m/s^2 (the exact-curve profile's speed wobbles by ~1e-6 relative on
    # the arc: tangential acceleration up to ~1e-3 on 93 % of the samples, measured)
    steady = ~sp.rapid & (speed > 1e-3 * speed.max()) & (tangential < 1e-3)  # kappa defined
    assert steady.sum() > 0.9 * len(sp)
    # exact geometry: 1/R (the setpoints lie within the 20 um chord tolerance of R 50 mm)
    assert np.allclose(kappa[steady], 1 / 0.05, rtol=1e-3)
    assert np.isnan(kappa[speed <= 1e-3 * speed.max()]).all() and (speed == 0).any()


def test_drawn_command_derivatives_are_the_eq2_peaks(paper_job):
    res = paper_job.result
    sp, lim = res.setpoints, res.machine.axis_limits()
    acc, jerk = _command_derivatives(res.optimized.u, sp.dt)
    feed = ~sp.rapid
    for k in sp.moving_axes:
        u = np.ascontiguousarray(res.optimized.u[:, k])
        v_pk, a_pk, j_pk = command_peaks(u, np.ascontiguousarray(feed), sp.dt)
        assert np.abs(acc[feed, k]).max() == pytest.approx(a_pk, rel=1e-12)
        assert np.abs(jerk[feed, k]).max() == pytest.approx(j_pk, rel=1e-12)
        assert j_pk / lim.jmax_m_s3[k] == pytest.approx(res.optimized.command_ratio[k, 2])
    # independent: second difference of u with two zero commands before the start
    u0 = np.concatenate([[0.0, 0.0], res.optimized.u[:, 2]])
    assert np.allclose(jerk[:, 2], (u0[2:] - 2 * u0[1:-1] + u0[:-2]) / sp.dt**2)


def test_cli_optimize_writes_the_report(tmp_path):
    out, report = tmp_path / "t.csv", tmp_path / "sub" / "r.html"
    report.parent.mkdir()  # oga creates no folder for an output file
    code = main(["optimize", str(DATA / "short_xz.ngc"), "--baseline", "1.6,0.9", "--adjust", "z",
                 "--gains", "kp", "--kp-range", "1.0,2.7", "--mode", "paper", "--nominal",
                 "--out", str(out), "--report", str(report)])
    assert code == 0 and out.exists()
    page = Page(report.read_text(encoding="utf-8"))
    assert len(page.figures) == FIGURES and page.rows["options.mode"] == ["paper"]


def test_engine_does_not_import_the_report():
    code = ("import sys, oga.optimize, oga.pipeline, oga.cli; "
            "assert 'oga.report.optimize' not in sys.modules, 'report imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_api_report_is_rebuilt_from_the_stored_job(tmp_path, monkeypatch):
    from api import Settings, create_app
    from api.storage import Owner
    from api.workers import run_claimed

    program = (DATA / "short_xz.ngc").read_text()
    req = {"toolpath": {"format": "gcode", "content": program, "name": "short_xz.ngc"},
           "options": PAPER}
    app = create_app(Settings(db_path=str(tmp_path / "r.db"), workers=0))
    with TestClient(app) as client:
        store = app.state.store
        job_id = client.post("/v1/jobs", json=req).json()["id"]
        assert client.get(f"/v1/jobs/{job_id}/report").status_code == 409  # queued
        assert client.get("/v1/jobs/nope/report").status_code == 404
        run_claimed(store, store.claim(Owner(socket.gethostname(), 12345, "t", 12345)))
        assert client.get(f"/v1/jobs/{job_id}").json()["status"] == "succeeded"
        # the request replays the stored table; it never searches
        # (the module by sys.modules: the attribute oga.optimize is the function)
        for module, name in (("oga.optimize", "optimize"), ("oga.pipeline", "optimize"),
                             ("oga.pipeline", "run_job")):
            monkeypatch.setattr(sys.modules[module], name, lambda *a, **k: pytest.fail("searched"))
        r = client.get(f"/v1/jobs/{job_id}/report")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert r.headers["x-oga-job-id"] == job_id
        summary = client.get(f"/v1/jobs/{job_id}/summary").json()
        _check_page(r.text, summary)
