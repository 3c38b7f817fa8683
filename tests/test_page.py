"""The web page of ``oga serve`` in a real browser: headless Chromium (Debian's ``chromium``)
driven by Playwright, against a real ``oga serve`` on 127.0.0.1.

Never skipped silently in CI: without the browser (or Playwright) the tests fail when
``CI`` is set (``true``) and skip with the reason elsewhere. Screenshots go to the folder named by
``OGA_SCREENSHOTS`` (else the test's tmp_path); their paths are printed.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import Settings, create_app
from oga.defaults import NP
from test_api_server import Server, wait_for

DATA = Path(__file__).parent / "data"
CHROMIUM = os.environ.get("OGA_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
JOB_TIMEOUT_MS = 240_000  # as tests/test_api_server.py: room for a cold numba cache
REPORT_TIMEOUT_MS = 60_000
KEY = "page-test-key"


def _missing() -> str | None:
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the Python package playwright is not installed (pip install -e '.[dev]')"
    if not os.access(CHROMIUM, os.X_OK):
        return f"no Chromium at {CHROMIUM} (apt-get install -y chromium, or set OGA_CHROMIUM)"
    return None


@pytest.fixture(scope="module")
def browser():
    reason = _missing()
    if reason is not None:
        if os.environ.get("CI", "").lower() not in ("", "0", "false"):
            pytest.fail(f"the browser test cannot run in CI: {reason}", pytrace=False)
        pytest.skip(reason)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture
def shots(tmp_path) -> Path:
    folder = Path(os.environ.get("OGA_SCREENSHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


class Console:
    """Errors the pages of a browser context print (console errors, uncaught exceptions)."""

    def __init__(self, context) -> None:
        self.errors: list[str] = []
        self.http_errors: list[str] = []  # which request a "Failed to load resource" was
        context.on("page", self.watch)

    def watch(self, page) -> None:
        page.on("console", lambda m: self.errors.append(f"{page.url}: {m.text}")
                if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"{page.url}: uncaught {e}"))
        page.on("response", lambda r: self.http_errors.append(
            f"{r.request.method} {r.url}: {r.status}") if r.status >= 400 else None)


def _screenshot(page, path: Path) -> None:
    page.screenshot(path=str(path), full_page=True)
    print(f"\nscreenshot: {path}")


def _run_job(page, server: Server, running_shot: Path | None = None) -> dict:
    """Submit the form, wait for the page to show the job finished; the job as the API has it
    (its summary as ``job["summary"]``). ``running_shot``: a screenshot once the progress bar
    moves (or the job has finished, on a machine faster than the page's polling)."""
    finished = ("['succeeded', 'failed', 'cancelled']"
                ".includes(document.getElementById('job-status').textContent)")
    page.check("#nominal")  # the nominal search: the robust one is tested in test_robust_cli.py
    page.click("#submit")
    if running_shot is not None:
        page.wait_for_function(f"document.getElementById('job-progress').value > 0 || {finished}",
                               timeout=JOB_TIMEOUT_MS)
        _screenshot(page, running_shot)
    page.wait_for_function(finished, timeout=JOB_TIMEOUT_MS)
    job_id = page.text_content("#job-id")
    job, _ = wait_for(server, job_id, ("succeeded", "failed", "cancelled"), timeout_s=1)
    assert page.text_content("#job-status") == job["status"] == "succeeded", job
    assert page.eval_on_selector("#job-progress", "p => p.value") == 1.0
    job["summary"] = server.http.get(f"/v1/jobs/{job_id}/summary").json()
    page.wait_for_function("document.getElementById('outcome').textContent !== ''")
    outcome = page.text_content("#outcome")
    for key in ("rms_ce_um", "max_ce_um"):
        assert (f"{job['summary']['baseline'][key]:.2f} \u2192 "
                f"{job['summary']['optimized'][key]:.2f} \u00b5m") in outcome, outcome
    for a in job["summary"]["contouring_axes"]:
        assert (f"{a} {job['summary']['baseline']['track_max_um'][a] / 1000:.3f} \u2192 "
                f"{job['summary']['optimized']['track_max_um'][a] / 1000:.3f} mm") in outcome, outcome
    assert "limits ok, stability ok" in outcome, outcome
    return job


def _open_report(page) -> object:
    """Open the report from the page; the report's tab once every figure is in it."""
    with page.expect_popup() as popup:
        page.click("#open-report")
    report = popup.value
    report.wait_for_function("document.querySelectorAll('svg').length >= 5",
                             timeout=REPORT_TIMEOUT_MS)
    report.wait_for_load_state()
    return report


def _figures(report) -> list[int]:
    """Per <svg> of the report, how many of its <path> elements draw something."""
    return report.eval_on_selector_all(
        "svg", "svgs => svgs.map(s => [...s.querySelectorAll('path')]"
               ".filter(p => (p.getAttribute('d') || '').trim().length > 2"
               " && p.getBBox().width + p.getBBox().height > 0).length)")


def test_page_and_its_files_are_served_without_the_key_and_need_no_network(tmp_path):
    app = create_app(Settings(db_path=str(tmp_path / "k.db"), workers=0, api_key=KEY))
    with TestClient(app) as client:
        page = client.get("/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        refs = re.findall(r'(?:src|href)="([^"]*)"', page.text)
        assert {"/static/app.js", "/static/style.css"} <= set(refs), refs
        for ref in refs:
            assert ref.startswith(("/static/", "data:")), f"{ref}: not served by the app"
            if ref.startswith("/static/"):
                assert client.get(ref).status_code == 200, ref
        assert client.get("/v1/machines").status_code == 401
        assert client.get("/v1/machines", headers={"X-API-Key": KEY}).status_code == 200


def test_page_takes_the_reference_program_to_a_report(browser, tmp_path, shots):
    server = Server(tmp_path / "oga.db", workers=1, log=tmp_path / "serve.log")
    context = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
    console = Console(context)
    try:
        page = context.new_page()
        page.goto(server.url + "/")
        page.wait_for_selector("#machine option[value=ucp710]", state="attached")
        assert page.input_value("#machine") == "ucp710"
        # the horizon's default per mode, from /openapi.json
        assert page.get_attribute("#np", "placeholder") == f"default {NP['full']}"
        page.select_option("#mode", "paper")
        assert page.get_attribute("#np", "placeholder") == f"default {NP['paper']}"
        page.select_option("#mode", "full")

        # a malformed program: the API's 422 in words, with line and column
        page.fill("#program", "G21 G18\nG1 X1 Y\n")
        page.click("#submit")
        page.wait_for_selector("#message.error")
        message = page.text_content("#message")
        assert "Line 2, column 7" in message and "G1 X1 Y" in message, message
        assert page.evaluate("document.getElementById('program').selectionStart") == len("G21 G18\n")
        _screenshot(page, shots / "page_bad_gcode.png")
        bad = [e for e in console.errors if "status of 422" not in e]
        assert bad == [], bad  # the browser logs the 422 answer itself; nothing else
        console.errors.clear()
        console.http_errors.clear()

        # the reference program, uploaded as a file
        page.set_input_files("#file", str(DATA / "reference_xz.ngc"))
        page.wait_for_function("document.getElementById('name').value === 'reference_xz.ngc'")
        assert page.input_value("#program") == (DATA / "reference_xz.ngc").read_text()
        job = _run_job(page, server, running_shot=shots / "page_running.png")
        assert job["source"] == "reference_xz.ngc" and job["machine"] == "ucp710"
        page.wait_for_selector("#jobs td:text-is('reference_xz.ngc')")
        _screenshot(page, shots / "page_succeeded.png")

        with page.expect_download() as download:
            page.click("#results button[data-path='table?format=csv']")
        assert download.value.suggested_filename == "reference_xz.csv"
        csv = Path(download.value.path()).read_text()
        assert csv == server.http.get(f"/v1/jobs/{job['id']}/table").text

        report = _open_report(page)
        figures = _figures(report)
        assert len(figures) == 6 and all(n > 0 for n in figures), figures
        assert "reference_xz.ngc" in report.text_content("body")
        _screenshot(report, shots / "report.png")
        assert console.errors == [], console.http_errors
    finally:
        context.close()
        server.stop()


def test_page_works_with_the_api_key(browser, tmp_path, shots, monkeypatch):
    monkeypatch.setenv("OGA_API_KEY", KEY)  # `oga serve` reads it
    server = Server(tmp_path / "oga.db", workers=1, log=tmp_path / "serve.log")
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    console = Console(context)
    try:
        assert server.http.get("/v1/machines").status_code == 401
        server.http.headers["X-API-Key"] = KEY
        page = context.new_page()
        page.goto(server.url + "/")  # the page itself needs no key
        page.wait_for_selector("#message.error")
        assert "needs an API key" in page.text_content("#message")
        # every keyless request answered (on a loaded machine some 401s come after the first
        # error shows, and must not be counted after the clear below)
        page.wait_for_load_state("networkidle")
        bad = [e for e in console.errors if "status of 401" not in e]
        assert bad == [], bad  # the browser logs the 401 answers itself; nothing else
        console.errors.clear()
        console.http_errors.clear()

        page.fill("#api-key", KEY)
        page.press("#api-key", "Tab")
        page.wait_for_selector("#machine option[value=ucp710]", state="attached")
        assert page.is_hidden("#message")
        assert page.evaluate("sessionStorage.getItem('oga.apiKey')") == KEY
        page.fill("#program", (DATA / "short_xz.ngc").read_text())
        page.fill("#name", "short_xz.ngc")
        _run_job(page, server)
        report = _open_report(page)
        figures = _figures(report)
        assert len(figures) == 6 and all(n > 0 for n in figures), figures
        _screenshot(page, shots / "page_with_key.png")

        page.reload()  # the key outlives a reload of the tab
        page.wait_for_selector("#jobs td:text-is('short_xz.ngc')")
        assert page.input_value("#api-key") == KEY
        assert console.errors == [], console.http_errors
    finally:
        context.close()
        server.stop()
