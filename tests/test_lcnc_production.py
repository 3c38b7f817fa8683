"""A table in production on LinuxCNC 2.9: its own motion controller runs the program.

Per program (reference_xz, and a real CAM program with rapids and stops: an excerpt of
pcb2gcode's drill program, ``tests/data/pcb2gcode_drill_parts.ngc``: a retract, a tool change
with M5, G4, M6, M0, M3, a descent, a 1 s dwell, G81 over 8 holes: three parts between the
stops LinuxCNC's task times, each compared at every sample): ``oga lcnc-record`` runs
it headless in the servo simulation of ``tests/lcnc_sim.py`` (``linuxcnc`` with ``milltask``,
``motmod``, ``halui`` and oga's display; POSIX non-realtime) on the fixed gains, twice (the
two runs must command the same motion), ``oga optimize --setpoints`` computes its table on
that recording, ``oga export --recording`` writes the HAL files, and one more LinuxCNC
session with them installed runs the program several times:

- on the fixed gains (the recording's own run, its feedback recorded): the contour error
  measured in LinuxCNC is oga's prediction for them;
- with the table: ``pid.N.output`` is oga's predicted velocity command at every sample of the
  table (the table's replay on the machine file, which describes the simulated drive
  exactly), the contour error measured in LinuxCNC is oga's prediction, and the table beats
  the fixed gains by the predicted ratio;
- with a 90 % feed override, a feed hold, and an abort (or E-stop) mid-program: the gains
  are the baseline from the very servo period the motion leaves the recorded one, and stay so.

LinuxCNC's planner starts a program a little differently when its task queues the next moves
late (on this loaded host about one start in 15): a run whose table fell back in its first
rows for that reason is run again (at most three times), and a recording LinuxCNC did not
repeat is made again.

FERROR is active throughout (the configuration's following-error limits, sampled) and no run
trips it. These tests need ``linuxcnc-uspace`` (``.ci/run`` installs it): without LinuxCNC
they fail, never skip.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import os
import pwd
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from feedplan.setpoints import AXES
from oga.cli import main
from oga.cli.export import read_table
from oga.model.contour import contour_error_of
from oga.defaults import LINUXCNC_RECORD
from oga.export.linuxcnc import run_session
from oga.export.linuxcnc.record import motion_parts
from oga.export.linuxcnc.session import LinuxcncError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.recorded import read_setpoints
from oga.model.response import simulate
from tests.lcnc_sim import write_config
from tests.test_linuxcnc import _LOCK

DATA = Path(__file__).parent / "data"
MACHINE = DATA / "lcnc_sim.toml"
#: The configuration's fixed gains (pid Pgain = 50 1/s, FF1 = 0.9), the table's baseline.
BASE_KP, BASE_KF = 3.0, 0.9
#: Sampled per table axis: pid output, Pgain, FF1, command, feedback, f-error (a HAL stream
#: holds at most 21 values).
PER_AXIS = 6
#: After them: oga-valid, motion.current-vel, motion.program-line.
VALID, CVEL, LINE = 0, 1, 2
OFF, ON = {"setp": {"oga-go.in-01": 0}}, {"setp": {"oga-go.in-01": 1}}  # table off, on
READY = {"wait_pin": "oga-feeder.ready"}


def _owner() -> int | None:
    """LinuxCNC runs unprivileged: as root, the configurations are given to ``nobody``."""
    if os.geteuid() != 0:
        return None
    try:
        return pwd.getpwnam("nobody").pw_uid
    except KeyError:
        return 65534


def _run_cli(argv) -> tuple[int, str, str]:
    """Run the CLI: exit code, standard output and error."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def _cli(argv) -> str:
    """Run the CLI; its standard output (exit code 0 required)."""
    code, out, err = _run_cli(argv)
    assert code == 0, err
    return out


def _test_hal(axes, joints) -> tuple[str, str]:
    """HAL file sampling what the checks need (after the servo thread's functions), and the
    sampler's types."""
    lines = [f"loadrt sampler depth=200000 cfg={'f' * PER_AXIS * len(axes)}bfs",
             "addf sampler.0 servo-thread"]
    k = 0
    for a in axes:
        j = joints[a]
        for sig in (f"{a}-out", f"oga-kp-{a}", f"oga-kf-{a}", f"{a}-pos-cmd", f"{a}-pos-fb"):
            lines.append(f"net {sig} => sampler.0.pin.{k}")
            k += 1
        lines.append(f"net oga-test-{a}-ferror joint.{j}.f-error => sampler.0.pin.{k}")
        k += 1
    lines += [f"net oga-valid => sampler.0.pin.{k}",
              f"net oga-motion.current-vel => sampler.0.pin.{k + 1}",
              f"net oga-motion.program-line => sampler.0.pin.{k + 2}"]
    return "\n".join(lines) + "\n", f"{'f' * PER_AXIS * len(axes)}bfs"


def _production(name: str, tmp: Path, stops, home_mm: dict | None = None) -> dict:
    """Record, optimise, export and run ``name`` in LinuxCNC (module docstring); ``stops``:
    the actions of the runs after the table's and the fixed gains' (one run each), or a
    function of the recorded setpoints giving them; ``home_mm``: where homing leaves the
    axes (the program starts there)."""
    program = DATA / name
    tmp.mkdir()
    owner = _owner()
    rec_ini = write_config(tmp / "rec", BASE_KP * KP_SI_PER_M_MIN_PER_MM, BASE_KF, owner=owner,
                           home_mm=home_mm)
    rec_file = tmp / "rec.txt"
    for attempt in range(4):  # LinuxCNC did not repeat the motion: record again
        code, record_out, err = _run_cli(["lcnc-record", str(program), "--ini", str(rec_ini),
                                          "--out", str(rec_file)])
        if code == 0 or "did not repeat the motion" not in err or attempt == 3:
            break
    assert code == 0, err
    table_csv, summary_json = tmp / "table.csv", tmp / "summary.json"
    optimize_out = _cli(["optimize", "--setpoints", str(rec_file), "--machine", str(MACHINE),
                         "--baseline", f"{BASE_KP},{BASE_KF}", "--out", str(table_csv),
                         "--summary", str(summary_json)])
    prod = tmp / "prod"
    export_out = _cli(["export", str(table_csv), "--summary", str(summary_json), "--recording",
                       str(rec_file), "--out", str(prod)])
    machine = load_machine(MACHINE)
    recorded = read_setpoints(rec_file.read_text(), machine, source=rec_file.name)
    table = read_table(table_csv)
    summary = json.loads(summary_json.read_text())
    axes = tuple(a for a in AXES if a in summary["adjusted"])
    joints = {a: AXES.index(a) for a in axes}  # trivkins XYZ
    hal, types = _test_hal(axes, joints)
    (prod / "test.hal").write_text(hal)
    ini = write_config(prod, BASE_KP * KP_SI_PER_M_MIN_PER_MM, BASE_KF,
                       extra_halfiles=("oga_table.tcl", "test.hal"), owner=owner,
                       home_mm=home_mm)
    retry = {"column": PER_AXIS * len(axes) + VALID, "min_rows": 100, "attempts": 3}
    home = {"x": 0.0, "y": 0.0, "z": 0.0, **(home_mm or {})}
    back = [OFF, {"mdi": "G0 " + " ".join(f"{a.upper()}{v!r}" for a, v in home.items())},
            {"tool_of_run": 0}, {"sleep": 0.5}, ON, READY]  # a first run: no move, as recorded
    if callable(stops):
        stops = stops(recorded)
    runs = [{"prepare": back, "tail_s": 0.3, "retry": retry}]
    runs += [{"prepare": back, "actions": acts, "tail_s": 0.3, "retry": retry}
             for acts in stops]
    job = {"program": str(program), "home": True, "runs": runs,
           "sampler": {"channel": 0, "types": types}, "read": ["oga-feeder.loads"]}
    session = run_session(ini, job, timeout_s=300)
    return {"recorded": recorded, "table": table, "summary": summary, "axes": axes,
            "session": session, "machine": machine, "outputs": (record_out, optimize_out,
                                                                export_out),
            "recording": np.loadtxt(rec_file, comments="#", ndmin=2)}


@pytest.fixture(scope="module")
def workdir():
    """A folder LinuxCNC's unprivileged user can reach (pytest's are private to root), and the
    lock of tests/test_linuxcnc.py's HAL sessions (HAL's shared memory keys are fixed: without
    private namespaces two sessions at once would share one HAL)."""
    root = Path(tempfile.mkdtemp(prefix="oga-lcnc-test-"))
    root.chmod(0o755)
    with open(_LOCK, "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield root
        finally:
            shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def reference(workdir):
    """reference_xz: fallbacks on a 90 % feed override, a feed hold, an E-stop."""
    return _production("reference_xz.ngc", workdir / "ref", [
        [{"after_s": 1.0, "do": "feed_override", "value": 0.9}],
        [{"after_s": 1.2, "do": "setp", "name": "motion.feed-hold", "value": 1},
         {"after_s": 1.5, "do": "setp", "name": "motion.feed-hold", "value": 0}],
        [{"after_s": 0.8, "do": "estop"}]])


def _mid_feed(sp, after_s: float, start: int = 0) -> float:
    """The middle (s from sample ``start``, the first motion of a part) of the first feed move
    (the speed above 5 mm/s, not a rapid) starting after ``after_s``: a feed override acts on
    the motion there, in the servo period it is applied, wherever the display's timing puts
    it within the move."""
    te = sp.dt
    moving = ~sp.rapid & (np.linalg.norm(sp.vel, axis=1) > 5e-3)
    edges = np.flatnonzero(np.diff(moving.astype(np.int8)))
    starts, ends = edges[moving[edges + 1]] + 1, edges[~moving[edges + 1]] + 1
    for a in starts[(starts - start) * te > after_s]:
        b = ends[ends > a][0]
        return float(((a + b) / 2 - start) * te)
    raise AssertionError(f"no feed move after {after_s} s")


@pytest.fixture(scope="module")
def cam(workdir):
    """A real CAM program with rapids and stops LinuxCNC's task times (pcb2gcode's drilling,
    started at Z0: its retract to Z40; the spindle stop, a 1 s dwell, the tool change M6, the
    pause M0 and the spindle start; the descent to Z0.5; a 1 s dwell; the holes): three parts.
    Fallbacks on a feed override and a feed hold in the middle of a hole's feed in the third
    part, an abort in a later one (times from that part's first motion: the stops before it
    last as long as the task takes)."""
    def stops(recorded):
        sp, start = recorded.setpoints, int(np.flatnonzero(recorded.linuxcnc.part == 2)[0])
        t1, t2, t3 = (_mid_feed(sp, t, start) for t in (0.3, 0.9, 1.6))
        return [[{"part": 2, "after_s": t1, "do": "feed_override", "value": 0.9}],
                [{"part": 2, "after_s": t2, "do": "setp", "name": "motion.feed-hold",
                  "value": 1},
                 {"part": 2, "after_s": t2 + 0.3, "do": "setp", "name": "motion.feed-hold",
                  "value": 0}],
                [{"part": 2, "after_s": t3, "do": "abort"}]]
    return _production("pcb2gcode_drill_parts.ngc", workdir / "cam", stops)


@pytest.fixture(params=["reference", "cam"])
def prod(request):
    return request.getfixturevalue(request.param)


def _row_of_sample(rows: np.ndarray, axes, part: np.ndarray) -> np.ndarray:
    """The sampled row of each sample of the table's parts in a run (N,): part i of the
    recording starts at the run's part i (its first moving period, split as lcnc-record
    splits), one row per period from there; -1 in a stop, or where the run made no such part
    (after a fallback the run's parts need not be the recording's)."""
    cmd = rows[:, [PER_AXIS * i + 3 for i in range(len(axes))]]
    runs = motion_parts(cmd, LINUXCNC_RECORD["stop_min_periods"])
    out = np.full(len(part), -1)
    for i in range(int(part.max()) + 1):
        idx = np.flatnonzero(part == i)
        if i < len(runs):
            out[idx] = runs[i, 0] + np.arange(len(idx))
    return out


def _tail(rows: np.ndarray, axes) -> np.ndarray:
    return rows[:, PER_AXIS * len(axes):]


def _prediction(p) -> dict:
    """oga's prediction: the table's and the fixed gains' replays on the machine file (what
    oga optimize verified, the stops included), on the recorded setpoints."""
    sp, machine, t = p["recorded"].setpoints, p["machine"], p["table"]
    col = {c: t.data[:, i] for i, c in enumerate(t.header)}
    kp = np.column_stack([col[f"{a}_kp_m_min_per_mm"] for a in AXES])
    kf = np.column_stack([col[f"{a}_kf"] for a in AXES])
    n = len(sp)
    part = p["recorded"].linuxcnc.part
    # the stops run on the baseline, and oga optimize gave them the baseline's gains
    assert np.all(kp[part < 0] == BASE_KP) and np.all(kf[part < 0] == BASE_KF)
    table = simulate(sp, machine, kp, kf)
    base = simulate(sp, machine, np.full((n, 3), BASE_KP), np.full((n, 3), BASE_KF))
    return {"sp": sp, "kp_si": kp * KP_SI_PER_M_MIN_PER_MM, "kf": kf, "table": table,
            "base": base, "n": n, "part": part, "ins": np.flatnonzero(part >= 0)}


def _measured_positions(rows, r, axes, fill) -> np.ndarray:
    """Actual positions p_k (m) of the samples of the parts (rows ``r``, -1 in a stop: there
    ``fill``'s): the sampler runs last in the period, so row k holds p_{k+1}."""
    pos = fill.copy()
    at = r >= 0
    for i, a in enumerate(axes):
        pos[at, AXES.index(a)] = rows[r[at] - 1, PER_AXIS * i + 4] * 1e-3
    return pos


def _mse(ce, sp, part) -> float:
    """MSE of the contour error over the feed samples of the parts (rapids and the stops,
    whose length the task sets, left out): as oga's metrics count them (``Setpoints.counted``)."""
    return float(np.mean(ce[~sp.rapid & (part >= 0)] ** 2))


def test_session_ran_headless_with_the_exported_files(prod):
    """lcnc-record, optimize --setpoints and export --recording said what they did; the
    session ran every run on LinuxCNC 2.9 without a LinuxCNC error; the recording's parts
    are named in the summary (the program's M0 resumed once in the recording of the CAM
    program)."""
    record_out, optimize_out, export_out = prod["outputs"]
    assert "servo periods of 1000000 ns" in record_out and "units mm" in record_out
    assert "error-previous-target x=TRUE" in record_out
    assert "(halsampler, linuxcnc-pid)" in optimize_out and "limits ok" in optimize_out
    assert "HALFILE = oga_table.tcl" in export_out
    st = prod["session"].status
    assert st["version"].startswith("2.9"), st["version"]
    assert st["errors"] == [], st["errors"]
    assert [r["overruns"] for r in st["runs"]] == [0] * len(st["runs"])
    src = prod["summary"]["setpoints_source"]
    assert src["law"] == "linuxcnc-pid" and src["format"] == "halsampler"
    assert src["samples"] == len(prod["recorded"].setpoints) == prod["table"].data.shape[0]
    n_parts = int(prod["recorded"].linuxcnc.part.max()) + 1
    assert src["parts"].startswith(f"{n_parts} (") and f"in {n_parts} part" in record_out
    pauses = 1 if n_parts > 1 else 0  # the CAM program's M0, between its first two parts
    assert src["program_pauses"].startswith(f"{pauses} (M0/M1, auto_resume)")


def test_table_run_is_oga_prediction_sample_for_sample(prod):
    """The table ran each part from its first motion to its end, one row per servo period,
    and held through the stops between them: Pgain and FF1 are the table's in the parts and
    the baseline everywhere else, pid.N.output is oga's velocity command and the actual
    positions are oga's at every sample of every part (oga's prediction: the table's replay
    on the machine file, the baseline in the stops as recorded; relative error <= 1e-9 of the
    loop's terms: HAL's lowpass and integ round differently from oga's ARX by about 1e-16 per
    step, measured at most 1e-10, and 1e-13 m/s absolute where the terms vanish: measured at
    most 1.3e-14 m/s)."""
    axes, rows = prod["axes"], prod["session"].runs[0]
    pr = _prediction(prod)
    ins, part = pr["ins"], pr["part"]
    r = _row_of_sample(rows, axes, part)[ins]
    cmd = rows[:, [PER_AXIS * i + 3 for i in range(len(axes))]]
    assert len(motion_parts(cmd, LINUXCNC_RECORD["stop_min_periods"])) == part.max() + 1
    assert (r >= 0).all()
    valid = _tail(rows, axes)[:, VALID]
    other = np.ones(len(rows), dtype=bool)
    other[r] = False
    assert valid[r].all() and not valid[other].any()
    sp, table = pr["sp"], pr["table"]
    worst = np.zeros(int(part.max()) + 1)
    for i, a in enumerate(axes):
        k, c = AXES.index(a), PER_AXIS * i
        assert np.array_equal(rows[r, c + 1], pr["kp_si"][ins, k])
        assert np.array_equal(rows[r, c + 2], pr["kf"][ins, k])
        assert np.all(rows[other, c + 1] == BASE_KP * KP_SI_PER_M_MIN_PER_MM)
        assert np.all(rows[other, c + 2] == BASE_KF)
        u = rows[r, c] * 1e-3
        terms = np.abs(pr["kp_si"][ins, k] * (sp.pos[ins, k] - table.pos[ins, k])) \
            + np.abs(pr["kf"][ins, k] * sp.vel[ins, k])
        err = np.abs(u - table.u[ins, k])
        assert (err <= 1e-9 * terms + 1e-13).all(), (a, float(err.max()))
        np.maximum.at(worst, part[ins], err)
    pos = _measured_positions(rows, _row_of_sample(rows, axes, part), axes, table.pos)
    assert np.abs(pos - table.pos).max() <= 1e-12
    sizes = np.bincount(part[ins])
    print(f"{prod['recorded'].source['file']}: {len(ins)} rows in {len(sizes)} parts "
          f"({', '.join(str(int(q)) for q in sizes)} rows; stops {len(part) - len(ins)} periods "
          f"recorded, {len(rows) - int(r[0]) - len(ins)} in this run); pid.N.output vs oga's "
          "command: at most " + ", ".join(f"{w:.2g}" for w in worst) + " m/s off per part; "
          f"positions {np.abs(pos - table.pos).max():.2g} m")


def test_contour_error_is_the_prediction_and_beats_the_fixed_gains(prod):
    """The contour error measured in LinuxCNC on the fixed gains (the recording's run) and with
    the table is oga's prediction for each over the parts' feed samples (MSE within 1e-9
    relative, measured about 1e-13), and the table beats the fixed gains by the predicted
    ratio, the summary's (oga counts the parts' feed samples, not the stops, whose length
    the task sets)."""
    axes, pr = prod["axes"], _prediction(prod)
    sp, n, part = pr["sp"], pr["n"], pr["part"]
    rec = prod["recording"]  # sample, per axis (x, y, z) cmd and act, line, type, speed, part
    f = int(np.flatnonzero(np.any(np.diff(rec[:, [1, 3, 5]], axis=0) != 0, axis=1))[0]) + 1
    # the recorder samples right after motion-controller: row k holds the feedback p_k
    base = np.column_stack([rec[f:f + n, 2 + 2 * k] * 1e-3 for k in range(3)])
    rows = prod["session"].runs[0]
    measured = {"base": contour_error_of(sp, base),
                "table": contour_error_of(sp, _measured_positions(
                    rows, _row_of_sample(rows, axes, part), axes, pr["table"].pos))}
    for name, ce in measured.items():
        predicted = contour_error_of(sp, pr[name].pos)
        assert abs(_mse(ce, sp, part) / _mse(predicted, sp, part) - 1) <= 1e-9, name
    ratio = _mse(measured["table"], sp, part) / _mse(measured["base"], sp, part)
    predicted_ratio = _mse(contour_error_of(sp, pr["table"].pos), sp, part) / _mse(
        contour_error_of(sp, pr["base"].pos), sp, part)
    assert abs(ratio / predicted_ratio - 1) <= 1e-9
    summary_ratio = prod["summary"]["ratio_mse"]  # counts the parts' feed samples too
    assert abs(predicted_ratio - summary_ratio) <= 1e-9 * predicted_ratio
    assert ratio < 0.5
    rms = {k: float(np.sqrt(_mse(v, sp, part))) * 1e6 for k, v in measured.items()}
    print(f"{prod['recorded'].source['file']}: CE rms in LinuxCNC over the parts: table "
          f"{rms['table']:.4f} um, fixed gains {rms['base']:.4f} um, MSE ratio {ratio:.6f} "
          f"(predicted {predicted_ratio:.6f}, the summary's {summary_ratio:.6f})")


def _deviation(rows, r, axes, rec, ins) -> int:
    """First sample of the parts (index into ``ins``) where the motion is no longer the
    recorded one: a joint's command further than the position tolerance from the row (an
    E-stop sets it to the feedback), the trajectory speed further than the velocity
    tolerance, another program line, the run made no such part, or the end of the table."""
    from oga.defaults import LINUXCNC_MOTION

    vel_tol, pos_tol = LINUXCNC_MOTION["vel_tol_m_s"] * 1e3, LINUXCNC_MOTION["pos_tol_m"] * 1e3
    at = r[ins]
    bad = (at < 0) | (at >= len(rows))
    ok = ~bad
    tail = _tail(rows, axes)[at[ok]]
    worse = np.abs(tail[:, CVEL] - rec.current_vel_m_s[ins[ok]] * 1e3) > vel_tol
    worse |= tail[:, LINE] != rec.line[ins[ok]]
    for i, a in enumerate(axes):
        worse |= np.abs(rows[at[ok], PER_AXIS * i + 3]
                        - rec.cmd_m[ins[ok], AXES.index(a)] * 1e3) > pos_tol
    bad[ok] = worse
    return int(np.flatnonzero(bad)[0]) if bad.any() else len(ins)


def test_fallbacks_in_the_same_servo_period(prod):
    """A 90 % feed override, a feed hold, an E-stop or an abort mid-program: the gains are the
    table's up to the period before the motion leaves the recorded one and the fixed baseline
    from that very period on, latched to the end of the run. The position command is the
    motion controller's throughout (no jump): from the switch on, pid.N.output is the
    baseline law on it, Pgain (c_{k-1} - p_k) + FF1 (c_k - c_{k-1}) / T, at every period
    (relative error <= 1e-12 of its terms; after an E-stop the drive is off, the output 0)."""
    axes, rec, te = prod["axes"], prod["recorded"].linuxcnc, prod["machine"].te
    pr = _prediction(prod)
    ins, base_kp = pr["ins"], BASE_KP * KP_SI_PER_M_MIN_PER_MM
    for run in range(1, len(prod["session"].runs)):
        rows = prod["session"].runs[run]
        r = _row_of_sample(rows, axes, pr["part"])
        k = _deviation(rows, r, axes, rec, ins)
        assert 0 < k < len(ins) - 100, (run, k)  # mid-program
        valid = _tail(rows, axes)[:, VALID]
        table_rows = r[ins[:k]]
        first_off = int(table_rows[np.flatnonzero(valid[table_rows] == 0)[0]]) \
            if not valid[table_rows].all() else None
        assert valid[table_rows].all() and valid.sum() == k, (
            run, k, first_off, None if first_off is None else (
                _tail(rows, axes)[first_off - 2:first_off + 2].tolist(),
                rows[first_off - 2:first_off + 2, [PER_AXIS * i + 3 for i in range(len(axes))]
                     ].tolist(), np.flatnonzero(table_rows == first_off).tolist()))
        switch = int(r[ins[k]])  # the first period off the recording: baseline from it on
        assert switch > table_rows[-1]
        action = prod["session"].status["runs"][run]["actions"][0]["do"]
        steps = []
        for i, a in enumerate(axes):
            c = PER_AXIS * i
            assert np.array_equal(rows[table_rows, c + 1], pr["kp_si"][ins[:k], AXES.index(a)])
            assert np.all(rows[switch:, c + 1] == base_kp) and np.all(rows[switch:, c + 2] == BASE_KF)
            cmd, fb, u = rows[:, c + 3], rows[:, c + 4], rows[:, c]
            on = np.arange(switch, len(rows))
            err = cmd[on - 1] - fb[on - 1]  # pid's error-previous-target: c_{k-1} - p_k
            vel = (cmd[on] - cmd[on - 1]) / te
            want = base_kp * err + BASE_KF * vel
            terms = np.abs(base_kp * err) + np.abs(BASE_KF * vel) + 1e-12
            law = np.abs(u[on] - want) <= 1e-12 * terms
            if action == "estop":  # once motion disables the drive, pid's output is 0
                law |= u[on] == 0.0
                assert u[-1] == 0.0
            assert law.all(), (run, a)
            steps.append(abs(u[switch] - u[switch - 1]) * 1e-3)
        print(f"{prod['recorded'].source['file']} run {run} ({action}): the table ran {k} of "
              f"{len(ins)} rows (to part {pr['part'][ins[k]]}), the baseline from the period "
              f"the motion left the recording; velocity command step there "
              f"{max(steps) * 1e3:.3f} mm/s")


def test_following_error_checked_and_never_tripped(prod):
    """FERROR is active: LinuxCNC's following error (motion's own, joint.N.f-error) stays below
    the configuration's least limit MIN_FERROR in every run (its limit is FERROR scaled by the
    speed, never below MIN_FERROR: no trip, and no error was reported), the table's run using
    a good part of it."""
    from tests.lcnc_sim import MIN_FERROR_MM

    axes = prod["axes"]
    peaks = [(run, float(np.abs(rows[:, [PER_AXIS * i + 5 for i in range(len(axes))]]).max()))
             for run, rows in enumerate(prod["session"].runs)]
    assert all(p < MIN_FERROR_MM for _, p in peaks), peaks
    assert peaks[0][1] > 0.2 * MIN_FERROR_MM
    print(f"{prod['recorded'].source['file']}: largest following error per run (mm): "
          + ", ".join(f"{p:.4f}" for _, p in peaks) + f" (MIN_FERROR {MIN_FERROR_MM} mm)")


def test_program_pause_resumed_in_a_headless_run(workdir):
    """A real CAM program's M0 (pcb2gcode's drill program up to its first hole: a tool change
    M6 with an operator message, M0, dwells) in oga's headless display: the pause is resumed
    at once and listed in the run's status (auto_resume, on by default), after the 1 s dwell
    before it; the message is the program's, no error; with auto_resume off the session ends
    at the pause with an error, within a bounded time (a headless run never waits for cycle
    start)."""
    program = DATA / "pcb2gcode_drill_start.ngc"
    tmp = workdir / "pause"
    ini = write_config(tmp, BASE_KP * KP_SI_PER_M_MIN_PER_MM, BASE_KF, owner=_owner(),
                       home_mm={"z": 40.0})
    job = {"program": str(program), "home": True, "runs": [{"timeout_s": 60}]}
    st = run_session(ini, job, timeout_s=120).status
    assert st["ok"] and st["auto_resume"], st.get("exception")
    assert st["errors"] == []
    assert any("Change tool bit" in m for _, m in st["messages"]), st["messages"]
    (pause,) = st["runs"][0]["pauses"]
    assert 1.0 < pause["at_s"] < st["runs"][0]["duration_s"] - 1.0, pause  # between the dwells
    assert 0 <= pause["lasted_s"] < 1.0, pause
    assert st["runs"][0]["tool"] == 0
    with pytest.raises(LinuxcncError, match=r"paused \(M0 or M1\) .* auto_resume is off"):
        run_session(ini, {**job, "auto_resume": False}, timeout_s=120)
    print(f"{program.name}: M0 at {pause['at_s']:.3f} s resumed after "
          f"{pause['lasted_s'] * 1e3:.1f} ms; "
          f"the run took {st['runs'][0]['duration_s']:.2f} s")
