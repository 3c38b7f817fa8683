"""The CAM corpus through the whole product: read, planned within every limit and feed,
optimised and verified on every sample; through the library, the CLI and the API.

The planner's feed check pairs each sample with the move it belongs to: a finishing pass
going back over a roughing pass at another feed (``fusion_mach3.tap``, 400 and 762 mm/min:
the old check reported "1.9049 x the programmed feed") and back-and-forth passes beyond the
tracker's window (``oga excite``'s programs: "path speed 6x, deviation 100000 um") plan clean,
while a plan that runs a move faster than its feed still fails.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path as FilePath

import numpy as np
import pytest
from fastapi.testclient import TestClient

from feedplan.check import check_setpoints
from feedplan.gcode import parse_gcode
from feedplan.path import Path
from feedplan.plan import move_times_s, program_tolerance_m
from oga.cli import main
from oga.defaults import TOL_M
from oga.model.machine import load_machine
from oga.optimize import optimize
from oga.options import options_from_dict
from oga.pipeline import plan_toolpath

CAM = FilePath(__file__).parent / "data" / "cam"
PROGRAMS = sorted(p.name for p in CAM.iterdir() if p.suffix in (".ngc", ".nc", ".gcode", ".tap"))
#: Programs planned whole here (the others, minutes of motion each, are planned whole by
#: bench/check_cam.py; here a stretch of them).
WHOLE = {"fusion_linuxcnc.ngc", "fusion_haas.nc", "fusion_mach3.tap", "fusion_mpcnc.gcode",
         "inkscape_laser.gcode", "pcb2gcode_drill.ngc", "pcbgcode_eagle.nc"}


@pytest.fixture(scope="module")
def machine():
    return load_machine("ucp710")


def window(path: Path, machine, seconds: float) -> Path:
    """The moves from the first feed move on, about ``seconds`` of motion at least."""
    segs = path.segments
    i0 = next(k for k, s in enumerate(segs) if not s.rapid)
    times = move_times_s(path, machine.planning_limits(), None)
    k = i0
    while k < len(segs) and (np.sum(times[i0:k]) < seconds or k == i0):
        k += 1
    return dataclasses.replace(path, start=segs[i0].start, segments=segs[i0:k])


def plan_checked(path: Path, machine):
    sp = plan_toolpath(path, machine, feed_m_s=None, tol_m=TOL_M)
    check = check_setpoints(sp, path, machine.axis_limits(),
                            tol_m=program_tolerance_m(path, TOL_M))
    return sp, check


@pytest.mark.parametrize("name", PROGRAMS)
def test_corpus_program_plans_within_limits_tolerance_and_feeds(name, machine):
    path = parse_gcode((CAM / name).read_text(), name)
    if name not in WHOLE:
        path = window(path, machine, 4.0)
    sp, check = plan_checked(path, machine)
    assert check.ok, check.violations
    assert check.speed_ratio <= 1.005 and check.max_deviation_m <= TOL_M
    assert len(sp) > 1000


@pytest.mark.parametrize("name", PROGRAMS)
def test_corpus_program_optimises_verified_on_every_sample(name, machine):
    """The nominal search on a stretch of each program; the table verified by replay."""
    path = window(parse_gcode((CAM / name).read_text(), name), machine, 1.0)
    sp = plan_toolpath(path, machine, feed_m_s=None, tol_m=TOL_M)
    res = optimize(sp, machine, options_from_dict({"nominal": True}))
    assert res.status == "ok", res.optimized.violations
    assert res.optimized.ok and res.ratio_mse <= 1.0 + 1e-9


def test_feed_check_pairs_each_sample_with_its_own_move(machine):
    """A finishing pass back over the roughing one at 762 mm/min: clean; the same samples
    against the program with that pass at 400 fail at 762/400 of the feed."""
    text = (CAM / "fusion_mach3.tap").read_text()
    contour = text[:text.index("(CIRCULAR1)")].count("\n")  # its lines
    path = parse_gcode(text, "fusion_mach3.tap")
    cut = dataclasses.replace(path, segments=[s for s in path.segments if s.line < contour])
    sp, check = plan_checked(cut, machine)
    assert check.ok, check.violations
    slow = dataclasses.replace(cut, segments=tuple(
        dataclasses.replace(s, feed_m_s=400 / 60e3) if not s.rapid and s.feed_m_s > 0.01
        else s for s in cut.segments))
    bad = check_setpoints(sp, slow, machine.axis_limits())
    assert not bad.ok and bad.speed_ratio == pytest.approx(762 / 400, rel=0.005)


def test_back_and_forth_beyond_the_tracker_window(machine):
    lines = ["G21 G90 G94 G17", "G1 X0 Y0 Z0 F600"]
    lines += [f"G1 X{1 - k % 2} F{600 if k % 4 < 2 else 1200}" for k in range(70)]
    path = parse_gcode("\n".join([*lines, "G1 Z2 F600", "G1 X1", "M2"]), "bf.ngc")
    sp, check = plan_checked(path, machine)
    assert check.ok, check.violations
    # every pass at 600: the 1200 passes (over 1 mm, reaching about 715 mm/min) now break it
    slow = dataclasses.replace(path, segments=tuple(
        dataclasses.replace(s, feed_m_s=0.01) for s in path.segments))
    bad = check_setpoints(sp, slow, machine.axis_limits())
    assert bad.violations == (f"path speed reaches {bad.speed_ratio:.4f} x the programmed feed",)
    assert 1.1 < bad.speed_ratio < 2.0


def test_the_program_of_oga_excite_plans_through_oga_plan(tmp_path, capsys):
    """Its back-and-forth X section failed the old check ("path speed 6x", exit 1)."""
    program, out = str(tmp_path / "excite.ngc"), str(tmp_path / "excite.csv")
    assert main(["excite", "--machine", "ucp710", "--axes", "x", "--travel-mm", "20", "--out",
                 program]) == 0
    assert main(["plan", program, "--machine", "ucp710", "--out", out]) == 0
    assert "limits ok" in capsys.readouterr().out


def test_cli_reads_plans_and_refuses_with_line_and_column(tmp_path, capsys):
    src = str(CAM / "fusion_mpcnc.gcode")
    tools = tmp_path / "tools.tbl"
    tools.write_text("T1 P1 Z30 D3.175 ;flat\n")
    out = tmp_path / "sp.csv"
    assert main(["plan", src, "--reader", "linuxcnc", "--tool-table", str(tools), "--out",
                 str(out)]) == 0
    assert "limits ok" in capsys.readouterr().out and out.stat().st_size > 0
    bad = tmp_path / "haas_m31.nc"
    bad.write_text((CAM / "fusion_haas.nc").read_text().replace("N25 G90\n", "N25 G90\nM31\n"))
    assert main(["plan", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:10:1: M31 is not an M-code LinuxCNC knows" in err, err
    assert main(["plan", str(bad), "--reader", "linuxcnc", "--out", str(out)]) == 2
    assert f"{bad}:10:1: LinuxCNC: Unknown m code used: M31" in capsys.readouterr().err
    tools.write_text("T1 P1 Z30\nT2 P2 Y\n")
    assert main(["plan", src, "--tool-table", str(tools), "--out", str(out)]) == 2
    assert f"{tools}:2:7: tool table: Y word '' is not a number" in capsys.readouterr().err


def test_cli_robust_optimize_of_a_real_program(tmp_path, capsys):
    """One robust run (its certificate over the uncertainty set) on an excerpt of pcb2gcode's
    real output: its header, the infeed with its G04 P0 stop, the first corner of the first
    isolation pass (lines 34-42; a rapid to its start instead of the 53 mm line before it)."""
    text = (CAM / "pcb2gcode_isolation_back.ngc").read_text().split("\n")
    cut = tmp_path / "pcb2gcode_cut.ngc"
    cut.write_text("\n".join([*text[:10], "G00 X71.77052 Y55.53050 ( rapid move to begin. )",
                              *text[26:31], *text[33:42], "M2", ""]))
    table, summary = tmp_path / "t.csv", tmp_path / "s.json"
    assert main(["optimize", str(cut), "--out", str(table), "--summary", str(summary)]) == 0
    out = capsys.readouterr().out
    assert "certificate" in out and "limits ok" in out
    s = json.loads(summary.read_text())
    assert s["options"]["reader"] == "auto" and s["certificate"]["plants"] > 1


def test_api_reader_option_and_422_naming_line_and_column(tmp_path):
    from api import Settings, create_app

    app = create_app(Settings(db_path=str(tmp_path / "q.db"), workers=0))
    comp = ("G21 G17 G90\nG0 X-10 Y-10 Z5\nG1 Z-1 F300\nG41 D1 G1 X0 Y0\nG1 X20\nG40 G1 X30 "
            "Y10\nM2\n")
    with TestClient(app) as c:
        def post(content, **options):
            return c.post("/v1/jobs", json={"toolpath": {"format": "gcode", "content": content,
                                                          "name": "p.ngc"},
                                            "options": {"nominal": True, **options}})
        assert post(comp, tool_table="T1 P1 Z0 D4\n").status_code == 202
        r = post(comp, reader="builtin")
        assert r.status_code == 422 and (r.json()["line"], r.json()["column"]) == (4, 1)
        assert "G41 (cutter radius compensation)" in r.json()["message"]
        r = post("G21 G0 X0\nG1 X1 F100\nM31\nM2\n")
        assert r.status_code == 422 and (r.json()["line"], r.json()["column"]) == (3, 1)
        assert "M31 is not an M-code LinuxCNC knows" in r.json()["message"]
        r = post(comp, tool_table="T1 P1 Z0 Q\n")
        assert r.status_code == 422 and "options.tool_table" in r.json()["message"]
        assert post(comp, reader="rs274").status_code == 422
        for name in PROGRAMS:  # read at submission: every corpus program is accepted
            assert post((CAM / name).read_text()).status_code == 202, name
