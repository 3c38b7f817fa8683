"""Optimising on setpoints another interpolator produced (``oga optimize --setpoints``, the
API's ``setpoints``), and the LinuxCNC production files of a table computed on a LinuxCNC
recording (``oga export --recording``), without LinuxCNC running (tests/test_lcnc_production.py
runs them in LinuxCNC).

Independent references: oga's own plan written out as recorded setpoints must read back
exactly and optimise to the same schedule as planning the program (two code paths); a
LinuxCNC recording must read back as pid's law says, sample by sample.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from feedplan.read import read_file
from feedplan.setpoints import AXES
from oga.cli import main
from oga.export.table import gain_table, table_csv
from oga.export.linuxcnc import FEEDER, MOTION_TCL, STREAM, UNIT_M
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.options import options_from_dict
from oga.pipeline import SETPOINTS_PREFIX, run_job
from oga.recorded import HEADER, SetpointsError, read_setpoints

DATA = Path(__file__).parent / "data"
MACHINE = DATA / "lcnc_sim.toml"
OPTIONS = {"nominal": True, "baseline": [3.0, 0.9]}


@pytest.fixture(scope="module")
def machine():
    return load_machine(MACHINE)


@pytest.fixture(scope="module")
def planned(machine):
    """short_xz planned by oga and optimised (the reference path)."""
    text, fmt = read_file(DATA / "short_xz.ngc")
    return run_job(text, fmt, machine, options_from_dict(OPTIONS), source="short_xz.ngc")


def _csv(sp, *, ff_vel=True, line=True) -> str:
    cols = {"t_s": sp.t}
    for k, a in enumerate(AXES):
        cols[f"{a}_cmd_m"] = sp.pos[:, k]
        if ff_vel:
            cols[f"{a}_ff_vel_m_s"] = sp.vel[:, k]
    if line:
        cols["line"], cols["rapid"] = sp.block, sp.rapid.astype(int)
    body = "\n".join(",".join(repr(float(c[i])) if n not in ("line", "rapid") else str(int(c[i]))
                              for n, c in cols.items()) for i in range(len(sp)))
    return ",".join(cols) + "\n" + body + "\n"


def _lcnc_recording(sp, *, rest=5, ept=1, drop=(), part=None) -> str:
    """oga's plan as an ``oga lcnc-record`` file: each plan position as the motor-pos-cmd of a
    servo period (mm), ``rest`` periods at rest before and after, and the motion columns
    (``part``: a part column, one value per period)."""
    c = np.vstack([np.repeat(sp.pos[:1], rest, 0), sp.pos, np.repeat(sp.pos[-1:], rest, 0)])
    n = len(c)
    line = np.concatenate([np.zeros(rest), sp.block, np.full(rest, sp.block[-1])])
    speed = np.concatenate([[0.0], np.linalg.norm(np.diff(c, axis=0), axis=1) / sp.dt])
    cols = {"sample": np.arange(n)}
    for k, a in enumerate(AXES):
        cols[f"{a}_cmd_m"] = c[:, k] * 1e3
        cols[f"{a}_act_m"] = c[:, k] * 1e3
    cols.update(line=line, motion_type=np.where(speed > 0, 2, 0), current_vel_m_s=speed * 1e3)
    if part is not None:
        cols["part"] = np.asarray(part)
    cols = {k: v for k, v in cols.items() if k not in drop}
    head = [HEADER[2:] + ": test", "servo-period-ns: 1000000", "units: mm",
            "joints: x=0 y=1 z=2", f"error-previous-target: x={ept} y={ept} z={ept}",
            "columns: " + " ".join(cols)]
    ints = ("sample", "line", "motion_type", "part")
    rows = [" ".join(str(int(v[i])) if k in ints else repr(float(v[i])) for k, v in cols.items())
            for i in range(n)]
    return "\n".join([f"# {h}" for h in head] + rows) + "\n"


# --- reading: two code paths ------------------------------------------------------------


def test_csv_of_oga_plan_reads_back_exactly_and_optimises_the_same(planned, machine, tmp_path):
    """oga's plan written as a setpoints CSV: the same setpoints, bit for bit, and the same
    schedule as planning the program; the summary names the file and its SHA-256."""
    sp = planned.setpoints
    text = _csv(sp)
    rec = read_setpoints(text, machine, source="plan.csv")
    for name in ("pos", "vel", "block", "rapid"):
        assert np.array_equal(getattr(rec.setpoints, name), getattr(sp, name)), name
    assert rec.setpoints.plane == sp.plane == "zx"
    job = run_job(text, SETPOINTS_PREFIX + "csv", machine, options_from_dict(OPTIONS),
                  source="plan.csv")
    assert np.array_equal(job.result.schedule.kp_m_min_per_mm,
                          planned.result.schedule.kp_m_min_per_mm)
    assert np.array_equal(job.result.schedule.kf, planned.result.schedule.kf)
    summary = job.summary()
    src = summary["setpoints_source"]
    assert src["sha256"] == hashlib.sha256(text.encode()).hexdigest() == job.toolpath_sha256
    assert (src["file"], src["format"], src["law"], src["samples"]) == \
        ("plan.csv", "csv", "given", len(sp))
    assert summary["setpoints_sha256"] == planned.summary()["setpoints_sha256"]
    meta = gain_table(job.result, toolpath_sha256=job.toolpath_sha256,
                      setpoints_source=job.recorded.source).meta
    assert meta["setpoints_source"]["sha256"] == src["sha256"]


def test_csv_without_ff_velocity_takes_the_centred_difference(planned, machine):
    """No <a>_ff_vel_m_s: the velocity is the centred difference of the positions, as the
    planner's (which is one)."""
    rec = read_setpoints(_csv(planned.setpoints, ff_vel=False, line=False), machine)
    assert np.array_equal(rec.setpoints.vel, planned.setpoints.vel)
    assert not rec.setpoints.block.any() and not rec.setpoints.rapid.any()


def test_twincat_export_reads_back(planned, machine):
    """A TwinCAT Scope View export (tab separated, decimal comma, a time column per channel):
    the positions to the printed precision."""
    sp = planned.setpoints
    head = ["Name\tx_cmd\tz_cmd", "SampleTime[ms]\t1\t1", ""]
    rows = ["\t".join(f"{v:.12g}".replace(".", ",") for v in
                      (t * 1e3, sp.pos[i, 0], t * 1e3, sp.pos[i, 2]))
            for i, t in enumerate(sp.t)]
    text = "\n".join(head + rows) + "\n"
    rec = read_setpoints(text, machine, "twincat", columns=["x_cmd_m", "z_cmd_m"])
    assert np.abs(rec.setpoints.pos - sp.pos).max() <= 1e-12
    assert rec.source["format"] == "twincat"


@pytest.mark.parametrize("ept", [1, 0])
def test_lcnc_recording_reads_with_pids_law(planned, machine, ept):
    """A LinuxCNC recording: sample 0 is the first period the command moves, pd_k = c_{k-1}
    (c_k without error-previous-target), vd_k = (c_k - c_{k-1}) / T, and the last sample is
    the first period at rest; the recorded line, speed and commands ride along."""
    sp = planned.setpoints
    text = _lcnc_recording(sp, ept=ept)
    rec = read_setpoints(text, machine, source="rec.txt")
    c = sp.pos  # the recording's motor-pos-cmd, in m (written in mm)
    moved = np.flatnonzero(np.any(np.diff(c, axis=0) != 0, axis=1)) + 1
    first, last = moved[0], moved[-1] + 1  # periods of c (the plan's index)
    got = rec.setpoints
    assert len(got) == last - first + 1
    cm = np.vstack([c, c[-1:]])[first:last + 1]
    prev = c[first - 1:last]
    assert np.allclose(got.pos, prev if ept else cm, rtol=0, atol=1e-15)
    assert np.allclose(got.vel, (cm - prev) / sp.dt, rtol=1e-12, atol=1e-12)
    lc = rec.linuxcnc
    assert lc.error_previous_target == {a: bool(ept) for a in AXES}
    assert np.allclose(lc.cmd_m, cm, rtol=0, atol=1e-15)
    assert lc.joints == {"x": 0, "y": 1, "z": 2} and lc.units == "mm"
    assert rec.source["law"] == "linuxcnc-pid" and rec.source["first_row"] == 7 + 5 + first
    # the same file without its header, its columns and setting given
    body = "\n".join(ln for ln in text.splitlines() if not ln.startswith("#")) + "\n"
    columns = text.splitlines()[5].removeprefix("# columns: ").split()
    plain = read_setpoints(body, machine, "halsampler", columns=columns, units="mm",
                           error_previous_target=bool(ept))
    assert np.array_equal(plain.setpoints.pos, got.pos)


def test_lcnc_recording_parts_ride_along_and_bad_ones_are_refused(planned, machine):
    """The part column of oga lcnc-record (-1 in a stop, 0, 1, ... in order) rides along per
    sample and its header line reaches the summary's source; a part number
    without a stop before it is refused naming the column and the row."""
    sp = planned.setpoints
    n = len(sp) + 10
    part = np.full(n, -1)
    part[5:n - 4] = 0  # the first moving period .. the first period at rest
    text = _lcnc_recording(sp, part=part).replace("# columns:", "# parts: 1 (test)\n# columns:")
    rec = read_setpoints(text, machine, source="rec.txt")
    assert np.array_equal(rec.linuxcnc.part, np.zeros(len(rec.setpoints), dtype=np.int64))
    assert rec.source["parts"] == "1 (test)"
    bad = part.copy()
    bad[40:] = 1  # a second part with no stop before it
    with pytest.raises(SetpointsError, match=r"column 'part', row 47: expected -1 .* got 1"):
        read_setpoints(_lcnc_recording(sp, part=bad), machine)


def test_motion_parts_split_at_long_standstills_and_runs_compare_per_part():
    """lcnc-record's parts: a standstill of stop_min_periods or more between two motions
    splits them, a shorter one does not; two runs whose stops last differently repeat the
    motion when each part does, period for period, and not when one differs by 2 um."""
    from oga.export.linuxcnc.record import _same_motion, motion_parts, part_column
    from oga.export.linuxcnc.session import LinuxcncError

    ramp = np.linspace(0.0, 1.0, 50)

    def run(stop: int) -> np.ndarray:  # x moves, stands still 3 periods, moves, stops, moves
        x = np.concatenate([[0.0] * 4, ramp, [1.0] * 3, 1 + ramp, [2.0] * stop, 2 + ramp,
                            [3.0] * 5])
        cols = np.zeros((len(x), 5))  # x cmd, x act, line, type, speed
        cols[:, 0] = cols[:, 1] = x
        cols[1:, 4] = np.abs(np.diff(x)) * 1e3
        return cols

    a, b = run(30), run(45)
    parts = motion_parts(a[:, :1], 20)
    assert parts.tolist() == [[5, 107], [138, 187]]
    assert motion_parts(a[:, :1], 32).tolist() == [[5, 187]]  # 31 periods at rest
    col = part_column(len(a), parts)
    assert (col[5:108] == 0).all() and (col[108:138] == -1).all() and (col[138:188] == 1).all()
    assert (col[:5] == -1).all() and (col[188:] == -1).all()
    _same_motion("p", a, b, 1, 1e-3, 20)  # the stop lasts 15 periods longer: the same motion
    c = b.copy()
    c[160:170, 0] += 2e-3  # b's part 1 starts at 153
    with pytest.raises(LinuxcncError, match="part 1 of 2 differs from servo period 7 "):
        _same_motion("p", a, c, 1, 1e-3, 20)
    with pytest.raises(LinuxcncError, match="made 1 parts"):
        _same_motion("p", a, run(10), 1, 1e-3, 20)


# --- bad input: refused naming the column and the row ------------------------------------


def _bad_cases(sp):
    good = _csv(sp, ff_vel=False, line=True).splitlines()
    header = good[0]
    rows = good[1:]

    def with_row(i, cells):
        out = list(rows)
        out[i] = cells
        return "\n".join([header] + out) + "\n"

    cell = rows[4].split(",")
    not_number = with_row(4, ",".join([cell[0], "abc", *cell[2:]]))
    t = [r.split(",") for r in rows]
    t[9][0] = repr(float(t[9][0]) + 0.0003)
    uneven = "\n".join([header] + [",".join(r) for r in t]) + "\n"
    slow = "\n".join([header] + [",".join([repr(float(r[0]) * 2), *r[1:]])
                                 for r in (x.split(",") for x in rows)]) + "\n"
    fast = "\n".join([header] + [",".join([r[0], repr(float(r[1]) * 1e3), *r[2:]])
                                 for r in (x.split(",") for x in rows)]) + "\n"
    scaled = "\n".join([header] + [",".join([r[0], repr(float(r[1]) * 6), *r[2:]])
                                   for r in (x.split(",") for x in rows)]) + "\n"
    line = with_row(20, ",".join([*rows[20].split(",")[:-2], "4.5", "0"]))
    return [
        (not_number, "csv", {}, "column 'x_cmd_m', row 6: 'abc' is not a number"),
        (uneven, "csv", {}, "column 't_s', row 11: non-uniform sampling"),
        (slow, "csv", {}, "column 't_s': the setpoints are 0.002 s apart"),
        (fast, "csv", {}, "column 'x_cmd_m', row"),
        (scaled, "csv", {}, "setpoint velocity"),
        (line, "csv", {}, "column 'line', row 22: 4.5 is not an integer"),
        ("t_s,x_act_m\n0,0\n0.001,0\n", "csv", {}, "no position setpoint column"),
        ("0 0\n1 0\n", "halsampler", {}, "--setpoints-columns"),
    ]


def test_bad_setpoints_are_refused_naming_column_and_row(planned, machine):
    for text, fmt, kw, what in _bad_cases(planned.setpoints):
        with pytest.raises(SetpointsError) as err:
            read_setpoints(text, machine, fmt, **kw)
        assert what in str(err.value), (what, str(err.value))
    with pytest.raises(SetpointsError, match=r"column 'x_cmd_m', row \d+: speed .* absurd "
                                             r"\(a trace in mm\? give --units mm\)"):
        read_setpoints(_lcnc_recording(planned.setpoints).replace("# units: mm\n", ""),
                       machine, units="m")


def test_cli_refuses_bad_setpoints_with_exit_2(planned, tmp_path, capsys):
    out = str(tmp_path / "t.csv")
    for i, (text, fmt, _, what) in enumerate(_bad_cases(planned.setpoints)):
        f = tmp_path / f"bad{i}.csv"
        f.write_text(text)
        argv = ["optimize", "--setpoints", str(f), "--machine", str(MACHINE), "--nominal",
                "--out", out]
        if fmt != "csv":
            argv += ["--setpoints-format", fmt]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"bad{i}.csv: " in err and what in err and len(err.strip().splitlines()) == 1, err
    good = tmp_path / "good.csv"
    good.write_text(_csv(planned.setpoints))
    for argv, what in (
            (["optimize", str(DATA / "short_xz.ngc"), "--setpoints", str(good)], "one of them"),
            (["optimize", "--setpoints", str(good), "--feed", "1000"], "--feed"),
            (["optimize", "--setpoints", str(good), "--tolerance", "0.01"], "--tolerance"),
            (["optimize", str(DATA / "short_xz.ngc"), "--setpoints-units", "mm"],
             "--setpoints-units: applies to --setpoints only")):
        assert main([*argv, "--machine", str(MACHINE), "--nominal", "--out", out]) == 2
        assert what in capsys.readouterr().err
    assert not Path(out).exists()


def test_cli_optimises_a_csv_and_names_it(planned, tmp_path, capsys):
    f = tmp_path / "plan.csv"
    f.write_text(_csv(planned.setpoints))
    argv = ["optimize", "--setpoints", str(f), "--machine", str(MACHINE), "--nominal",
            "--baseline", "3.0,0.9", "--out", str(tmp_path / "t.csv"), "--summary",
            str(tmp_path / "s.json")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"setpoints: plan.csv (csv, given), {len(planned.setpoints)} samples from row 2" in out
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["setpoints_source"]["sha256"] == hashlib.sha256(f.read_bytes()).hexdigest()
    # the same table but for s_m (a recording's path length is its chords')
    table = np.loadtxt(tmp_path / "t.csv", delimiter=",", skiprows=1)
    want = np.loadtxt(io.StringIO(table_csv(planned.result)), delimiter=",", skiprows=1)
    assert np.array_equal(np.delete(table, 1, axis=1), np.delete(want, 1, axis=1))


# --- the production export of a table on a LinuxCNC recording -----------------------------


@pytest.fixture(scope="module")
def recorded_job(planned, machine, tmp_path_factory):
    """short_xz as a LinuxCNC recording, optimised on, its table and summary written."""
    tmp = tmp_path_factory.mktemp("rec")
    text = _lcnc_recording(planned.setpoints)
    (tmp / "rec.txt").write_text(text)
    job = run_job(text, SETPOINTS_PREFIX + "halsampler", machine, options_from_dict(OPTIONS),
                  source="rec.txt")
    assert job.result.status == "ok" and not job.result.kept_baseline
    (tmp / "t.csv").write_text(table_csv(job.result))
    (tmp / "s.json").write_text(json.dumps(job.summary()))
    return tmp, job


def test_export_recording_writes_the_motion_files(recorded_job, capsys):
    """The stream holds, per servo period from the first motion, the recorded commands (mm),
    the table's Pgain (1/s) and FF1, the recorded speed and line; the HALFILE checks the loop,
    inserts its functions after motion-controller and drives only Pgain and FF1."""
    tmp, job = recorded_job
    assert main(["export", str(tmp / "t.csv"), "--summary", str(tmp / "s.json"),
                 "--recording", str(tmp / "rec.txt"), "--out", str(tmp / "lc")]) == 0
    assert "linuxcnc (motion): " in capsys.readouterr().out
    files = {p.name: p.read_text() for p in (tmp / "lc").iterdir()}
    assert set(files) == {STREAM, MOTION_TCL, FEEDER}
    data = np.loadtxt(io.StringIO(files[STREAM]), comments="#", ndmin=2)
    res, lc = job.result, job.recorded.linuxcnc
    n = len(res.setpoints)
    assert data.shape == (n, 3 * 2 + 3)  # x, z: cmd, kp, kf; speed, line, end of part
    assert not data[:, 8].any()  # one part: no stop
    for i, a in enumerate(("x", "z")):
        k = AXES.index(a)
        assert np.array_equal(data[:, 3 * i], lc.cmd_m[:, k] / UNIT_M["mm"])
        assert np.array_equal(data[:, 3 * i + 1],
                              res.schedule.kp_m_min_per_mm[:, k] * KP_SI_PER_M_MIN_PER_MM)
        assert np.array_equal(data[:, 3 * i + 2], res.schedule.kf[:, k])
    assert np.array_equal(data[:, 6], lc.current_vel_m_s / UNIT_M["mm"])
    assert np.array_equal(data[:, 7], lc.line)
    tcl = files[MOTION_TCL]
    assert "set oga_thread [thread_info ::OGA]" in tcl and "oga_addf $oga_thread" in tcl
    assert f"hal loadrt streamer depth={n + 1} cfg={'f' * 8}b" in tcl
    assert "hal net oga-kp-x oga-kp-x.out $oga_pid(x).Pgain" in tcl
    assert "hal net oga-kf-z oga-kf-z.out $oga_pid(z).FF1" in tcl
    assert ".command" not in "".join(ln for ln in tcl.splitlines() if ln.startswith("hal net"))
    assert f"hal setp oga-kp-x.in0 {3.0 * KP_SI_PER_M_MIN_PER_MM!r}" in tcl
    assert "oga_check_pid $oga_pid(x) 1 " in tcl


def test_export_recording_refuses_another_recording(recorded_job, planned, capsys):
    tmp, _ = recorded_job
    other = tmp / "other.txt"
    lines = _lcnc_recording(planned.setpoints).splitlines()  # one command moved by 1 nm
    cells = lines[20].split()
    cells[1] = repr(float(cells[1]) + 1e-6)
    lines[20] = " ".join(cells)
    other.write_text("\n".join(lines) + "\n")
    no_speed = tmp / "nospeed.txt"
    no_speed.write_text(_lcnc_recording(planned.setpoints, drop=("current_vel_m_s",)))
    for rec, what in ((other, "not computed on this recording"),
                      (no_speed, "no current_vel_m_s column")):
        assert main(["export", str(tmp / "t.csv"), "--summary", str(tmp / "s.json"),
                     "--recording", str(rec), "--out", str(tmp / "x")]) == 2
        err = capsys.readouterr().err
        assert what in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp / "x").exists()


# --- the API -----------------------------------------------------------------------------


def test_api_optimises_setpoints_and_refuses_bad_ones(planned, tmp_path):
    """POST /v1/jobs with setpoints: 422 naming the column and the row for a bad file; a good
    one (a LinuxCNC recording) runs, its summary and table name the file, and its
    table?format=linuxcnc is the production zip of oga export --recording."""
    from fastapi.testclient import TestClient

    from api import Settings, create_app
    from api.workers import run_claimed
    from tests.test_api import _owner

    machine = json.loads(json.dumps(load_machine(MACHINE).model_dump(mode="json",
                                                                      exclude_none=True)))
    app = create_app(Settings(db_path=str(tmp_path / "q.db"), workers=0))
    text = _lcnc_recording(planned.setpoints)
    with TestClient(app) as client:
        bad_text = _bad_cases(planned.setpoints)[0][0]
        r = client.post("/v1/jobs", json={"setpoints": {"format": "csv", "content": bad_text,
                                                        "name": "bad.csv"},
                                          "machine": machine, "options": OPTIONS})
        assert r.status_code == 422 and "column 'x_cmd_m', row 6" in r.json()["message"]
        r = client.post("/v1/jobs", json={"machine": machine, "options": OPTIONS})
        assert r.status_code == 422
        r = client.post("/v1/jobs", json={
            "setpoints": {"format": "halsampler", "content": text, "name": "rec.txt"},
            "machine": machine, "options": OPTIONS})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        store = app.state.store
        assert run_claimed(store, store.claim(_owner(4242))) == "succeeded"
        summary = client.get(f"/v1/jobs/{job_id}/summary").json()
        assert summary["setpoints_source"]["sha256"] == hashlib.sha256(text.encode()).hexdigest()
        npz = client.get(f"/v1/jobs/{job_id}/table", params={"format": "npz"})
        with np.load(io.BytesIO(npz.content)) as z:
            assert json.loads(str(z["meta"]))["setpoints_source"]["file"] == "rec.txt"
        r = client.get(f"/v1/jobs/{job_id}/table", params={"format": "linuxcnc"})
        assert r.status_code == 200
        with zipfile.ZipFile(io.BytesIO(r.content)) as z:
            names = {n.split("/")[-1] for n in z.namelist()}
        assert names == {STREAM, MOTION_TCL, FEEDER}
        assert client.get(f"/v1/jobs/{job_id}/report").status_code == 200
