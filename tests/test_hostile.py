"""Hostile programs and machine files at ``plan`` and ``oga.optimize``, each case bounded.

Every case runs in a worker process whose address space is capped (``RLIMIT_AS``) and
whose answer is awaited for a bounded wall time; the worker is ended and replaced when
a case overruns. A case must either plan within the axis limits (checked here by finite
differences of the positions, independently of ``feedplan.check``) -- and then optimise
to a result with a status -- or raise an :class:`oga.errors.OgaError` with a one-line
message. Any other exception, a memory error, a crash or an overrun fails the test.
"""

from __future__ import annotations

import json
import math
import os
import select
import subprocess
import sys
import textwrap
import time
import tomllib
from pathlib import Path as FilePath

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

PRESET = FilePath(__file__).parents[1] / "oga" / "presets" / "ucp710.toml"
#: Address space of the worker, bytes (imports and compiled kernels take about 0.8 GB).
MEMORY_BYTES = 3 * 1024**3
#: Wall time of one case, seconds (about 100 times a normal case: the host may be busy).
CASE_S = 30.0
#: Wall time of the worker's start (imports, and kernels compiled on a cold cache).
START_S = 600.0
#: The workers' plan limits (oga.defaults.MAX_MOTION_S, MAX_SAMPLES: 3600 s, 4e6 samples):
#: the same checks at a size whose planning fits the per-case time on a busy host.
MOTION_S, SAMPLES = 200.0, 200_000

WORKER = textwrap.dedent(
    """
    import json, resource, sys, traceback
    limit = int(sys.argv[1])
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    import numpy as np
    import oga
    from feedplan.gcode import parse_gcode
    from feedplan.plan import plan
    from feedplan.read import read_toolpath
    from oga.errors import OgaError
    from oga.model.machine import load_machine, machine_from_dict

    # smaller plans than a service allows (the same checks, at a size the per-case time fits)
    planner = sys.modules["feedplan.plan"]
    planner.MAX_MOTION_S, planner.MAX_SAMPLES = float(sys.argv[2]), int(sys.argv[3])

    def fd_ratio(pos, dt, lim):
        p = np.concatenate([np.repeat(pos[:1], 3, axis=0), pos, np.repeat(pos[-1:], 3, axis=0)])
        out = []
        for limit in (lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3):
            p = np.diff(p, axis=0) / dt
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(limit > 0, np.abs(p) / np.where(limit > 0, limit, 1.0),
                             np.where(np.abs(p) > 0, np.inf, 0.0))
            out.append(float(np.max(r)))
        return out

    def run(case):
        machine = (load_machine("ucp710") if case["machine"] is None
                   else machine_from_dict(case["machine"], where="hostile.json"))
        path = read_toolpath(case["text"], case["fmt"], source="hostile")
        lim = machine.planning_limits()
        sp = plan(path, lim, feed_m_s=case["feed_m_s"], tol_m=case["tol_m"], dt=machine.te)
        out = {"outcome": "planned", "samples": len(sp), "finite": bool(np.isfinite(sp.pos).all()),
               "ratios": fd_ratio(sp.pos, sp.dt, lim),
               "end_m": float(np.max(np.abs(sp.pos[-1] - path.segments[-1].end)))}
        if case["optimize"] and len(sp) <= 3000:
            out["status"] = oga.optimize(sp, machine, {"nominal": True, "np": 40}).status
        return out

    # warm up (kernels compiled on a cold cache) before the cases are timed
    m = load_machine("ucp710")
    oga.optimize(plan(parse_gcode("G21 G0 X0\\nG1 X2 Y1 F3000\\n"), m.planning_limits()), m,
                 {"nominal": True, "np": 40})
    print(json.dumps({"ready": True}), flush=True)
    for raw in sys.stdin:
        case = json.loads(raw)
        try:
            out = run(case)
        except OgaError as err:
            out = {"outcome": "refused", "type": type(err).__name__, "message": str(err)}
        except MemoryError:
            out = {"outcome": "memory"}
        except BaseException as err:
            out = {"outcome": "crash", "type": type(err).__name__,
                   "trace": traceback.format_exc()}
        print(json.dumps(out), flush=True)
    """
)


class Worker:
    """A worker process answering one JSON case per line, restarted after an overrun."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None

    def _start(self) -> None:
        env = {**os.environ, "PYTHONPATH": str(FilePath(__file__).parents[1])}
        self.proc = subprocess.Popen(
            [sys.executable, "-c", WORKER, str(MEMORY_BYTES), str(MOTION_S), str(SAMPLES)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
        assert self._read(START_S) == {"ready": True}

    def _read(self, timeout: float):
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            ready, _, _ = select.select([self.proc.stdout], [], [], max(left, 0.0))
            if ready:
                line = self.proc.stdout.readline()
                return json.loads(line) if line else {"outcome": "died",
                                                      "code": self.proc.wait(5)}
            if left <= 0:
                self.stop()
                return {"outcome": "overrun"}

    def ask(self, case: dict) -> dict:
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        self.proc.stdin.write(json.dumps(case) + "\n")
        self.proc.stdin.flush()
        return self._read(CASE_S)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self.proc = None


@pytest.fixture(scope="module")
def worker():
    w = Worker()
    yield w
    w.stop()


# ----------------------------------------------------------------------------- strategies

HOSTILE_NUMBERS = ["9" * 320, "9" * 300, "-" + "9" * 40, "0.0000001", "-0", ".", "1e308",
                   "1E-300", "nan", "inf", "-inf", "1.2.3", "", "+-1", "0", "1000000",
                   "-1000000.0001", "0.5"]
sane = st.one_of(st.integers(-200, 200).map(str),
                 st.floats(-50, 50, allow_nan=False).map(lambda x: f"{x:.4f}"))
number = st.one_of(st.sampled_from(HOSTILE_NUMBERS), sane, sane, sane, sane, sane)
feed = st.one_of(st.sampled_from(["0.001", "1", "10000000000", "9" * 60, "0.0000000001",
                                  "3000", "30000", "-5", "0", "nan"]),
                 st.integers(100, 100000).map(str), st.integers(100, 100000).map(str))
motion = st.sampled_from(["G0", "G1", "G1", "G2", "G3", "", "G17", "G18 G2", "G19 G3",
                          "G20 G1", "G64 P0.01 G1", "G61 G1", "G4 P1", "G91", "M3 S1e9"])
arc_words = st.one_of(st.just(""), number.map(lambda r: f"R{r}"),
                      st.tuples(number, number).map(lambda ij: f"I{ij[0]} J{ij[1]}"))
words_line = st.tuples(motion, number, number, number, arc_words, st.one_of(st.just(""), feed)).map(
    lambda w: f"{w[0]} X{w[1]} Y{w[2]} Z{w[3]} {w[4]} " + (f"F{w[5]}" if w[5] else ""))
junk_line = st.text(alphabet="GXYZIJKRFMNOPQE#[]();%0123456789.-+ \t\u00e9", max_size=30)
gcode_program = st.lists(st.one_of(words_line, words_line, words_line, junk_line),
                         min_size=1, max_size=10).map(
    lambda lines: "G21 G90\nG0 X0 Y0 Z0\n" + "\n".join(lines) + "\n")


@st.composite
def micro_program(draw):
    """Many tiny moves: a zigzag or a wavy line of 100-1500 segments of 0.1 um-10 um."""
    n = draw(st.integers(100, 1500))
    step_mm = draw(st.sampled_from([1e-4, 1e-3, 1e-2]))
    f = draw(st.sampled_from([100, 3000, 30000, 10**9]))
    zig = draw(st.booleans())
    lines = ["G21 G90", "G0 X0 Y0", f"G1 F{f}"]
    for k in range(1, n + 1):
        y = (k % 2) * step_mm if zig else (k * k % 7) * step_mm / 7
        lines.append(f"X{k * step_mm:.7f} Y{y:.7f}")
    return "\n".join(lines) + "\n"


@st.composite
def valid_program(draw):
    """Lines and arcs that read (ends on their circles), at hostile and normal feeds."""
    f = draw(st.sampled_from(["0.5", "10", "3000", "30000", "10000000000", "9" * 40]))
    lines = ["G21 G90 G17", "G0 X0 Y0 Z0", f"G1 F{f}"]
    x = y = z = 0.0
    for _ in range(draw(st.integers(1, 6))):
        if draw(st.booleans()):
            x, y = float(draw(sane)), float(draw(sane))
            z += draw(st.sampled_from([0.0, 1.0]))
            lines.append(f"G1 X{x:.4f} Y{y:.4f} Z{z:.4f}")
            continue
        r = draw(st.floats(0.01, 40.0))
        th0, sweep = draw(st.floats(0.0, 6.28)), draw(st.floats(0.01, 6.0))
        cx, cy = x - r * math.cos(th0), y - r * math.sin(th0)
        g = draw(st.sampled_from(["G2", "G3"]))
        th1 = th0 + (sweep if g == "G3" else -sweep)
        i, j = cx - x, cy - y
        x, y = cx + r * math.cos(th1), cy + r * math.sin(th1)
        lines.append(f"{g} X{x:.4f} Y{y:.4f} I{i:.4f} J{j:.4f}")
    return "\n".join(lines) + "\n"


polyline_csv = st.lists(st.tuples(number, number, number, st.one_of(st.just(""), feed)),
                        min_size=0, max_size=8).map(
    lambda rows: "x,y,z,feed\n" + "\n".join(",".join(r) for r in rows) + "\n")
polyline_json = st.lists(st.tuples(number, number, number), max_size=6).map(
    lambda pts: "[" + ",".join("[" + ",".join(p or "0" for p in pt) + "]" for pt in pts) + "]")

toolpath = st.one_of(
    gcode_program.map(lambda t: ("gcode", t)),
    valid_program().map(lambda t: ("gcode", t)),
    valid_program().map(lambda t: ("gcode", t)),
    micro_program().map(lambda t: ("gcode", t)),
    polyline_csv.map(lambda t: ("csv", t)),
    polyline_json.map(lambda t: ("json", t)),
)

MACHINE_FIELDS = [
    ("axes", "x", "limits", "vmax_m_s"), ("axes", "x", "limits", "jmax_m_s3"),
    ("axes", "y", "limits", "amax_m_s2"), ("axes", "z", "limits", "jmax_m_s3"),
    ("axes", "x", "cascade", "mass_kg"), ("axes", "z", "cascade", "kv_n_s_m"),
    ("axes", "x", "cascade", "force_lag_s"), ("timing", "te_s"), ("timing", "substeps"),
    ("gains", "kp_step_m_min_per_mm"), ("gains", "kp_span_m_min_per_mm"),
    ("gains", "kf_step"), ("planner", "jerk_fraction"), ("axes", "x", "limits"),
]
machine_value = st.sampled_from([1e308, -1e308, 1e-300, -1.0, 0.0, float("nan"), float("inf"),
                                 "abc", [1, 2], None, 1e6, 1e-3, 20.0, 0.01, [0.01, 50.0], {}])


@st.composite
def machine(draw):
    """None (the preset) or the preset's dict with up to two fields made hostile."""
    if draw(st.integers(0, 9)) < 6:
        return None
    data = tomllib.loads(PRESET.read_text())
    for path in draw(st.lists(st.sampled_from(MACHINE_FIELDS), max_size=2)):
        node = data
        for key in path[:-1]:
            node = node[key] if isinstance(node, dict) else None
        if isinstance(node, dict):  # (not under a table already made hostile)
            node[path[-1]] = draw(machine_value)
    return data


override = st.integers(0, 9).flatmap(lambda k: st.none() if k < 8 else st.sampled_from(
    [1e14 / 60e3, 1e-10, -1.0, float("nan"), 0.05, 100.0]))
tolerance = st.integers(0, 9).flatmap(lambda k: st.just(20e-6) if k < 8 else st.sampled_from(
    [0.0, 1e-12, 1e-7, 1e-3, 1.0, float("inf")]))


# ----------------------------------------------------------------------------- the test


def judge(case: dict, answer: dict) -> None:
    where = json.dumps(case)[:2000]
    outcome = answer["outcome"]
    assert outcome in ("planned", "refused"), (answer, where)
    if outcome == "refused":
        msg = answer["message"]
        assert msg and "\n" not in msg and "Traceback" not in msg, (answer, where)
        return
    assert answer["finite"], where
    assert all(r <= 1.0 + 1e-9 for r in answer["ratios"]), (answer, where)
    assert answer["end_m"] <= 1e-9, (answer, where)
    if "status" in answer:
        assert answer["status"] in ("ok", "baseline", "failed"), (answer, where)


@settings(max_examples=40, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                 HealthCheck.function_scoped_fixture])
@given(tp=toolpath, mach=machine(), feed_m_s=override, tol_m=tolerance,
       optimize=st.integers(0, 9).map(lambda k: k == 0))
def test_hostile_inputs_are_planned_within_the_limits_or_refused(worker, tp, mach, feed_m_s,
                                                                  tol_m, optimize):
    fmt, text = tp
    case = {"fmt": fmt, "text": text, "machine": mach, "feed_m_s": feed_m_s, "tol_m": tol_m,
            "optimize": optimize}
    answer = worker.ask(case)
    event(f"{answer['outcome']} {answer.get('type', '')} {answer.get('status', '')}")
    judge(case, answer)


@pytest.mark.parametrize("text, message", [
    ("G21 G90\nG1 X0 Y0 F10000000000\nG1 X10 Y5\nM2\n", None),  # row 1: capped, planned
    ("G21 G90\nG1 X0 Y0 F0.001\nG1 X1 Y0\n", "program would take 6e+04 s"),  # row 2
    ("G21 G90\nG1 X0 Y0 F10\nG2 X-60 Y0 I-30 J0\n", "(limits 200 s, 200000 samples)"),
    ("G21 G90\nG1 X0 Y0 F100\nG1 X100000000\n", "coordinate out of range"),
    ("G21\nG1 X" + "9" * 320 + " F100\n", "number out of range"),  # row 5
    ("(nothing)\n", "no motion in hostile"),  # row 9
])
def test_issue_rows_within_the_budget(worker, text, message):
    case = {"fmt": "gcode", "text": text, "machine": None, "feed_m_s": None, "tol_m": 20e-6,
            "optimize": True}
    answer = worker.ask(case)
    judge(case, answer)
    if message is None:
        assert answer["outcome"] == "planned" and answer["status"] == "ok"
    else:
        assert message in answer["message"]


def test_a_case_beyond_its_time_is_stopped(worker):
    """The time bound is real: a case that overruns is not waited for, its worker is ended."""
    saved = CASE_S
    try:
        case = {"fmt": "gcode", "text": "G21\nG0 X0\nG1 X1 F1\n", "machine": None,
                "feed_m_s": None, "tol_m": 20e-6, "optimize": False}
        globals()["CASE_S"] = 1e-3  # a budget no case meets
        assert worker.ask(case) == {"outcome": "overrun"} and worker.proc is None
    finally:
        globals()["CASE_S"] = saved


def test_the_memory_bound_is_real():
    """Under the workers' RLIMIT_AS an allocation beyond it fails at once (MemoryError)."""
    code = (f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({MEMORY_BYTES}, "
            f"{MEMORY_BYTES})); import numpy as np\ntry:\n    np.ones({MEMORY_BYTES} // 8 + 1)\n"
            "except MemoryError:\n    print('bounded')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "bounded"
