"""LinuxCNC export, proven in LinuxCNC's own HAL (``halrun``, POSIX non-realtime).

The exported files run in ``halrun`` with the simulated actual positions streamed as
``pid.N.feedback`` and a ``sampler`` on ``pid.N.output``; the output must be oga's velocity
command sample for sample. These tests need ``linuxcnc-uspace`` (``.ci/run`` installs it):
without ``halrun`` they fail, never skip.
"""

from __future__ import annotations

import fcntl
import io
import json
import os
import pwd
import shutil
import subprocess
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from feedplan.read import read_file
from feedplan.setpoints import AXES
from oga.cli import main
from oga.errors import MachineError, OptionError
from oga.export.table import gain_table, render_table, table_csv
from oga.export.linuxcnc import (BENCH_HAL, STREAM, TABLE_HAL, UNIT_M, export_table, linuxcnc_export,
                          replay_feedback)
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.options import options_from_dict
from oga.pipeline import run_job

DATA = Path(__file__).parent / "data"
#: pid.N.output is sampled times 2**40 (exact): halsampler prints "%f", 6 decimals.
SCALE = 2.0**40
#: Periods sampled after the table's end or an abort.
POST = 50


def _job(name):
    text, fmt = read_file(DATA / name)
    job = run_job(text, fmt, load_machine("ucp710"), options_from_dict({"nominal": True}),
                  source=name)
    assert job.result.status == "ok"
    return job


@pytest.fixture(scope="module")
def ref():
    """reference_xz (the paper's contour), optimised on ucp710."""
    return _job("reference_xz.ngc")


@pytest.fixture(scope="module")
def cncjs():
    """A real program (cncjs's, MIT): rapids, cuts and arcs in three planes."""
    return _job("cncjs_toolpath.nc")


def _export(job, **kw):
    res = job.result
    return export_table(gain_table(res), summary=res.summary(), machine=res.machine,
                        with_feedback=True, **kw)


# --- running halrun -------------------------------------------------------------------


def _halrun_env(root: Path) -> dict:
    """halrun's environment: its own rtapi socket; as root an unprivileged RTAPI_UID."""
    env = dict(os.environ, RTAPI_FIFO_PATH=str(root / "rtapi_fifo"))
    if os.geteuid() == 0:
        try:
            env["RTAPI_UID"] = str(pwd.getpwnam("nobody").pw_uid)
        except KeyError:
            env["RTAPI_UID"] = "65534"
    return env


def _isolated() -> list[str]:
    """A private SysV IPC namespace where the kernel allows it: HAL's shared memory keys are
    fixed, so two sessions at once (or a LinuxCNC running here) would share one HAL.
    Sessions of these tests also take :data:`_LOCK` (for hosts without namespaces)."""
    if shutil.which("unshare") and subprocess.run(
            ["unshare", "--ipc", "true"], capture_output=True).returncode == 0:
        return ["unshare", "--ipc"]
    return []


#: Lock file serialising the halrun sessions of concurrent test processes.
_LOCK = os.path.join(tempfile.gettempdir(), "oga-halrun.lock")


def _session(export, period_ns, lines, out_name, *, files=None, before_start=()) -> list:
    """Run the export in halrun: its bench set-up (the exported bench file if ``period_ns`` is
    None, else the same with a thread of that period: the outputs do not depend on it, no
    term of the loop differentiates numerically; ``before_start`` lines come before the
    thread starts), then ``lines``; the rows of ``out_name``."""
    assert shutil.which("halrun"), "halrun missing: install linuxcnc-uspace (.ci/run does)"
    root = Path(tempfile.mkdtemp(prefix="oga-hal-"))
    try:
        os.chmod(root, 0o777)  # RTAPI_UID's user writes its socket here
        for name, text in {**export.files, **(files or {})}.items():
            (root / name).write_text(text)
        joints = [export.joints[a] for a in export.axes]
        if period_ns is None:
            head = [f"source {BENCH_HAL}"]
        else:
            head = [f"loadrt threads name1=servo-thread period1={period_ns} fp1=1",
                    f"loadrt pid num_chan={max(joints) + 1}",
                    *(f"addf pid.{j}.do-pid-calcs servo-thread" for j in joints),
                    f"source {TABLE_HAL}",
                    *(f"setp pid.{j}.enable 1" for j in joints),
                    *(f"net oga-{a}-fb-sim => pid.{export.joints[a]}.feedback"
                      for a in export.axes),
                    *before_start,
                    f"loadusr -w timeout 60 halstreamer -c 0 {STREAM}",
                    "start"]
        (root / "test.hal").write_text("\n".join(head + lines) + "\n")
        (root / "wait.sh").write_text(  # in a file: halcmd would expand "$" itself
            'until [ "$(halcmd -s getp streamer.0.curr-depth)" -le "$1" ]; do sleep 0.005; done\n')
        with open(_LOCK, "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            proc = subprocess.run([*_isolated(), "halrun", "-f", "test.hal"], cwd=root,
                                  env=_halrun_env(root), capture_output=True, text=True,
                                  timeout=180)
        out = root / out_name
        assert proc.returncode == 0 and out.exists(), proc.stdout + proc.stderr
        rows = [line.split() for line in out.read_text().splitlines()]
        assert "overrun" not in {r[0] for r in rows if r}
        return rows
    finally:
        shutil.rmtree(root, ignore_errors=True)


def _run_hal(export, *, period_ns=None, abort_after=None) -> tuple[np.ndarray, np.ndarray]:
    """The sampled pid outputs (N_s, axes) and oga-valid (N_s,) of an export run in halrun,
    from its first row to POST periods past its end. ``abort_after``: ``sets oga-run 0``
    once at least that many rows were read."""
    samples = export.rows + POST
    names = [f"oga-test-{a}" for a in export.axes]
    lines = [f"loadrt scale names={','.join(names)}",
             f"loadrt sampler depth={samples + 10} cfg={'f' * len(names)}b"]
    for k, (a, s) in enumerate(zip(export.axes, names)):
        lines += [f"net oga-test-{a}-out pid.{export.joints[a]}.output => {s}.in",
                  f"setp {s}.gain {SCALE!r}",
                  f"net oga-test-{a}-scaled {s}.out => sampler.0.pin.{k}"]
    lines += [f"net oga-valid => sampler.0.pin.{len(names)}",
              "net oga-started => sampler.0.enable",  # from the first row on
              *(f"addf {s} servo-thread" for s in names),  # after the pid loops
              "addf sampler.0 servo-thread",
              "loadusr -w sleep 0.05",  # the loops run before the start
              "sets oga-run 1"]
    if abort_after is not None:
        lines += [f"loadusr -w timeout 60 sh wait.sh {export.rows - abort_after}",
                  "sets oga-run 0"]
    lines += [f"loadusr -w timeout 120 halsampler -c 0 -n {samples} out.txt"]
    data = np.array(_session(export, period_ns, lines, "out.txt"), dtype=np.float64)
    assert data.shape == (samples, len(names) + 1)
    return data[:, :-1] / SCALE, data[:, -1].astype(bool)


def _expected(job, export, read: int, total: int, offset: float) -> np.ndarray:
    """oga's velocity command (m/s) for the sampled periods: the verified replay for the
    ``read`` rows, then the baseline P term on the held command and feedback."""
    res = job.result
    cols = [AXES.index(a) for a in export.axes]
    u = res.optimized.u[:read, cols]
    pd, p = res.setpoints.pos[:, cols] + offset, res.optimized.pos[:, cols] + offset
    n = len(res.setpoints)
    held = pd[min(read, n - 1)] if export.error_previous_target else pd[read - 1]
    kp = np.array([res.baseline_kp[a] for a in export.axes]) * KP_SI_PER_M_MIN_PER_MM
    tail = kp * (held / UNIT_M[export.units] - p[read - 1] / UNIT_M[export.units])
    return np.vstack([u, np.tile(tail * UNIT_M[export.units], (total - read, 1))])


def _check(job, export, out, valid, read, offset=0.0):
    """Sample for sample: relative error <= 1e-9 of the loop's terms (after units), plus the
    rounding of the two positions to machine units (one unit in the last place each)."""
    assert valid[:read].all() and not valid[read:].any()
    want = _expected(job, export, read, len(out), offset)
    got = out * UNIT_M[export.units]
    res = job.result
    cols = [AXES.index(a) for a in export.axes]
    kp = res.schedule.kp_m_min_per_mm[:read, cols] * KP_SI_PER_M_MIN_PER_MM
    pd, p = res.setpoints.pos[:read, cols] + offset, res.optimized.pos[:read, cols] + offset
    terms = np.abs(want).copy()
    terms[:read] = np.abs(kp * (pd - p)) + np.abs(res.schedule.kf[:read, cols]
                                                  * res.setpoints.vel[:read, cols])
    floor = np.zeros_like(want)
    floor[:read] = kp * np.finfo(float).eps * (np.abs(pd) + np.abs(p))
    err = np.abs(got - want)
    excess = err - 1e-9 * terms - floor
    assert (excess <= 0).all(), f"{int((excess > 0).sum())} samples off, by up to " \
        f"{excess.max():.3g} m/s (first at {np.argwhere(excess > 0)[0].tolist()})"
    big = np.abs(want) >= 1e-6  # figures for the record: 1 um/s and more, and absolute
    return float(np.max(err[big] / np.abs(want[big]))), float(err.max())


# --- halrun: the exported files reproduce oga's command --------------------------------


def test_bench_file_mm_previous_target(ref):
    """The bench file as exported (1 ms servo period), mm, error-previous-target TRUE,
    to the table's end and past it (baseline gains, command held)."""
    export = _export(ref, units="mm", error_previous_target=True)
    out, valid = _run_hal(export)
    _check(ref, export, out, valid, export.rows)


@pytest.mark.parametrize("ept", [False, True])
def test_inch(ref, ept):
    """An inch machine, both error-previous-target settings, other pid loops."""
    export = _export(ref, units="inch", error_previous_target=ept, joints={"x": 2, "z": 0})
    out, valid = _run_hal(export, period_ns=20_000)
    _check(ref, export, out, valid, export.rows)


def test_real_program_with_rapids(cncjs):
    """A real program, rapids included (every axis; 50 s of motion at a 10 us thread)."""
    res = cncjs.result
    assert res.setpoints.rapid.any() and not res.setpoints.rapid.all()
    export = _export(cncjs)
    assert export.axes == ("x", "y", "z")
    out, valid = _run_hal(export, period_ns=10_000)
    _check(cncjs, export, out, valid, export.rows)


def test_table_away_from_zero_primes_the_previous_target(ref):
    """A table whose positions are far from 0 (every program here starts at 0): with
    error-previous-target TRUE the first row's error uses the command held before the
    start, which must be the table's first position."""
    res, offset = ref.result, 0.1234
    table = gain_table(res)
    for c, a in enumerate(AXES):
        table.data[:, table.header.index(f"{a}_pos_m")] += offset
    fb = {a: res.optimized.pos[:, AXES.index(a)] + offset for a in ("x", "z")}
    export = linuxcnc_export(table, res.baseline_kp, res.baseline_kf, feedback_m=fb,
                             error_previous_target=True)
    out, valid = _run_hal(export, period_ns=20_000)
    _check(ref, export, out, valid, export.rows, offset)


@pytest.mark.parametrize("ept", [True, False])
def test_abort_falls_back_to_baseline(ref, ept):
    """oga-run FALSE in the middle: from the next period on the gains are the baseline,
    command-deriv 0, the command held at the last row read."""
    export = _export(ref, units="mm", error_previous_target=ept)
    out, valid = _run_hal(export, period_ns=None if ept else 100_000, abort_after=300)
    read = int(valid.sum())
    assert 300 <= read < export.rows
    _check(ref, export, out, valid, read)


# --- the files, without halrun ----------------------------------------------------------


def _stream(export) -> np.ndarray:
    lines = [ln for ln in export.files[STREAM].splitlines() if not ln.startswith("#")]
    return np.array([ln.split() for ln in lines], dtype=np.float64)


def test_stream_columns_are_the_table_in_machine_units(ref):
    """Per axis: command (one sample ahead with error-previous-target), velocity, Pgain in
    1/s (the same in mm and inch), FF1; exact float64 round trip."""
    res = ref.result
    table = gain_table(res)
    x, z = AXES.index("x"), AXES.index("z")
    for units, ept in (("mm", True), ("inch", False)):
        export = linuxcnc_export(table, res.baseline_kp, res.baseline_kf, units=units,
                                 error_previous_target=ept)
        assert export.columns == ("x_cmd", "x_vel", "x_kp", "x_kf", "z_cmd", "z_vel", "z_kp",
                                  "z_kf")
        s, unit = _stream(export), UNIT_M[units]
        pd = res.setpoints.pos[:, z]
        cmd = np.append(pd[1:], pd[-1]) if ept else pd
        assert np.array_equal(s[:, 4], cmd / unit)
        assert np.array_equal(s[:, 1], res.setpoints.vel[:, x] / unit)
        assert np.allclose(s[:, 2], res.schedule.kp_m_min_per_mm[:, x] * 1000 / 60, rtol=1e-15)
        assert np.array_equal(s[:, 7], res.schedule.kf[:, z])
        hal = export.files[TABLE_HAL]
        assert f"setp pid.1.error-previous-target {int(ept)}" in hal
        assert f"loadrt streamer depth={len(pd) + 1} cfg=ffffffff" in hal
        assert f"setp oga-x-kp.in0 {res.baseline_kp['x'] * KP_SI_PER_M_MIN_PER_MM!r}" in hal
        assert f"setp oga-z-cmd.in0 {float(pd[0] / unit)!r}" in hal
    assert abs(UNIT_M["inch"] / UNIT_M["mm"] - 25.4) < 1e-12


def test_feedback_is_the_verified_replay(ref):
    res = ref.result
    fb = replay_feedback(gain_table(res), res.machine)
    for a, p in fb.items():
        assert np.array_equal(p, res.optimized.pos[:, AXES.index(a)])
    other = load_machine("mcv-op")
    with pytest.raises(MachineError, match="computed for machine 'ucp710'"):
        replay_feedback(gain_table(res), other)


def test_metadata_cannot_leave_the_comments(ref):
    """A program named with a newline stays inside the HAL comment line."""
    table = gain_table(ref.result)
    table.meta["toolpath"] = "part.ngc\nloadusr -w rm -rf /"
    export = linuxcnc_export(table, ref.result.baseline_kp, ref.result.baseline_kf)
    for text in export.files.values():
        assert not any(line.startswith("loadusr -w rm") for line in text.splitlines())
    assert "# oga gain table for LinuxCNC: part.ngc?loadusr -w rm -rf /," in export.files[TABLE_HAL]


def test_bad_options_are_refused(ref):
    res = ref.result
    table = gain_table(res)
    kp, kf = res.baseline_kp, res.baseline_kf
    with pytest.raises(OptionError, match="units"):
        linuxcnc_export(table, kp, kf, units="m")
    with pytest.raises(OptionError, match="joints"):
        linuxcnc_export(table, kp, kf, joints={"x": 0, "z": 0})
    with pytest.raises(OptionError, match="joints"):
        linuxcnc_export(table, kp, kf, joints={"x": 0, "z": 16})
    with pytest.raises(OptionError, match="axes"):
        linuxcnc_export(table, kp, kf, axes=["x", "q"])
    with pytest.raises(OptionError, match="baseline"):
        linuxcnc_export(table, {"x": 3.0}, kf)
    with pytest.raises(OptionError, match="thread"):
        linuxcnc_export(table, kp, kf, thread="servo thread")


def test_cli_csv_and_summary_give_the_library_files(ref, tmp_path, capsys):
    res = ref.result
    (tmp_path / "t.csv").write_text(table_csv(res))
    summary = res.summary()
    (tmp_path / "s.json").write_text(json.dumps(summary))
    args = ["export", str(tmp_path / "t.csv"), "--summary", str(tmp_path / "s.json"),
            "--out", str(tmp_path / "lc"), "--with-feedback", "--units", "inch",
            "--error-previous-target", "false", "--joints", "x=0,z=2"]
    assert main(args) == 0
    assert "linuxcnc: 2940 rows (x -> pid.0, z -> pid.2), inch" in capsys.readouterr().out
    want = _export(ref, units="inch", error_previous_target=False, joints={"x": 0, "z": 2})
    got = {p.name: p.read_text() for p in (tmp_path / "lc").iterdir()}
    assert got[STREAM] == want.files[STREAM] and got[TABLE_HAL] == want.files[TABLE_HAL]
    # the NPZ table (the API's) gives the same stream
    (tmp_path / "t.npz").write_bytes(render_table(gain_table(res), "npz"))
    assert main(["export", str(tmp_path / "t.npz"), "--out", str(tmp_path / "n"),
                 "--summary", str(tmp_path / "s.json"), "--machine", "ucp710",
                 "--with-feedback", "--units", "inch", "--error-previous-target", "false",
                 "--joints", "x=0,z=2"]) == 0
    assert (tmp_path / "n" / STREAM).read_text().splitlines()[4:] == \
        want.files[STREAM].splitlines()[4:]


def test_cli_refuses_bad_input(ref, tmp_path, capsys):
    res = ref.result
    (tmp_path / "t.csv").write_text(table_csv(res))
    other = dict(res.summary(), setpoints_sha256="0" * 64)
    (tmp_path / "s.json").write_text(json.dumps(other))
    (tmp_path / "bad.csv").write_text("t_s,s_m\n0,0\n0.001,x\n")
    out = str(tmp_path / "o")
    cases = [
        (["export", str(tmp_path / "t.csv"), "--out", out], "baseline"),
        (["export", str(tmp_path / "t.csv"), "--summary", str(tmp_path / "s.json"), "--out", out],
         "not the same program"),
        (["export", str(tmp_path / "bad.csv"), "--baseline", "3,0.8", "--out", out], "bad.csv"),
        (["export", str(tmp_path / "t.csv"), "--baseline", "3", "--out", out], "--baseline"),
        (["export", str(tmp_path / "t.csv"), "--baseline", "3,0.8", "--joints", "x:0",
          "--out", out], "--joints"),
        (["export", str(tmp_path / "t.csv"), "--baseline", "3,0.8", "--with-feedback",
          "--out", out], "--with-feedback"),
        (["export", str(tmp_path / "missing.npz"), "--baseline", "3,0.8", "--out", out],
         "cannot read"),
    ]
    for argv, what in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert what in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_api_table_format_linuxcnc_is_a_zip_of_the_files(ref, tmp_path):
    """GET /v1/jobs/ID/table?format=linuxcnc: the files of oga export (no simulated feedback:
    a replay, which no request handler runs)."""
    from fastapi.testclient import TestClient

    from api import Settings, create_app
    from api.workers import run_claimed
    from tests.test_api import _owner

    app = create_app(Settings(db_path=str(tmp_path / "q.db"), workers=0))
    text = (DATA / "reference_xz.ngc").read_text()
    with TestClient(app) as client:
        job_id = client.post("/v1/jobs", json={
            "toolpath": {"format": "gcode", "content": text, "name": "reference_xz.ngc"},
            "machine": "ucp710", "options": {"nominal": True}}).json()["id"]
        store = app.state.store
        run_claimed(store, store.claim(_owner(12345)))
        r = client.get(f"/v1/jobs/{job_id}/table", params={"format": "linuxcnc"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(r.content)) as z:
        files = {n.split("/")[-1]: z.read(n).decode() for n in z.namelist()}
    res = ref.result
    want = export_table(gain_table(res), summary=res.summary())
    assert set(files) == {STREAM, TABLE_HAL, BENCH_HAL}
    assert files[STREAM] != _export(ref).files[STREAM]  # the feedback column is not there
    assert files[STREAM].splitlines()[4:] == want.files[STREAM].splitlines()[4:]


def test_trace_example_records_command_and_feedback(ref):
    """examples/linuxcnc/record_trace.hal records what its comments say: sample number, then
    per axis x, y, z the command and the feedback in machine units (the bench's signals
    named as in pncconf configurations)."""
    export = _export(ref, axes=("x", "y", "z"), error_previous_target=False)
    example = (Path(__file__).parents[1] / "examples" / "linuxcnc" / "record_trace.hal")
    copies = [f"oga-copy-{a}-{w}" for a in export.axes for w in ("cmd", "fb")]
    lines = [f"loadrt scale names={','.join(copies)}"]
    for a in export.axes:  # the pncconf signal names, written by copies of the loop's pins
        lines += [f"net oga-{a}-cmd => oga-copy-{a}-cmd.in",
                  f"net oga-{a}-fb-sim => oga-copy-{a}-fb.in",
                  f"net {a}-pos-cmd oga-copy-{a}-cmd.out",
                  f"net {a}-pos-fb oga-copy-{a}-fb.out"]
    lines += [*(f"setp {c}.gain 1" for c in copies), *(f"addf {c} servo-thread" for c in copies),
              "source record_trace.hal",
              "net oga-started => sampler.0.enable"]
    run = ["sets oga-run 1",
           f"loadusr -w timeout 120 halsampler -t -c 0 -n {export.rows} trace.txt"]
    rows = _session(export, 20_000, run, "trace.txt", before_start=lines,
                    files={"record_trace.hal": example.read_text()})
    trace = np.array(rows, dtype=np.float64)
    assert trace.shape == (export.rows, 7)
    assert np.array_equal(np.diff(trace[:, 0]), np.ones(export.rows - 1))
    res = ref.result
    for c in range(3):
        assert np.abs(trace[:, 1 + 2 * c] - res.setpoints.pos[:, c] * 1e3).max() <= 5.1e-7
        assert np.abs(trace[:, 2 + 2 * c] - res.optimized.pos[:, c] * 1e3).max() <= 5.1e-7
