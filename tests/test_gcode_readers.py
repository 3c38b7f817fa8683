"""The two G-code readers against each other: the built-in one means what LinuxCNC means.

LinuxCNC's own interpreter (``--reader linuxcnc``, package linuxcnc-uspace, which CI installs)
is the reference: for every program of the CAM corpus it accepts, and for programs written to
exercise canned cycles, G28/G30, G53, work offsets, G92 and tool lengths with a setup of
non-zero home positions, offsets and a tool table, the built-in reader's path must equal it
move by move: each end point within 1e-9 m, arcs the same arcs (centre, radius, plane,
direction and turns), the same source line, rapid flag, feed and path control. What LinuxCNC
refuses is refused naming the line, the column and the construct.
"""

from __future__ import annotations

import math
from pathlib import Path as FilePath

import numpy as np
import pytest

import feedplan.gcode.linuxcnc as lcnc
from feedplan.gcode import Setup, linuxcnc_available, parse_gcode, parse_tool_table
from feedplan.gcode.linuxcnc import read_linuxcnc
from feedplan.path import Arc
from oga.errors import GcodeError, MachineError, OptionError

CAM = FilePath(__file__).parent / "data" / "cam"
#: Corpus programs LinuxCNC refuses, the line:column it names and what (the built-in reader
#: reads them, with a warning naming what LinuxCNC refuses).
REFUSED = {"estlcam_spool.nc": (11, 28, "Nested comment", "nested comment"),
           "freecad_grbl.gcode": (28, 43, "K word given for arc in xy plane", "K0 on an arc")}
ACCEPTED = sorted(p.name for p in CAM.iterdir()
                  if p.suffix in (".ngc", ".nc", ".gcode", ".tap") and p.name not in REFUSED)
TOL_M = 1e-9

#: A setup of non-zero home positions, work offsets and tools (a tool with an X offset too).
SETUP = Setup(g28_m=(0.01, 0.02, 0.05), g30_m=(-0.1, 0.2, 0.03),
              work_offsets_m=np.arange(27).reshape(9, 3) * 1e-3 + 0.0123,
              tools=parse_tool_table("T1 P3 Z25.4 X0.5 ;long\nT2 P1 Z-10 D6\n"))

FEATURES = {
    "home_offsets": """(G28/G30, G53, work offsets, the G92 family)
G21 G17 G90
G28
G0 X10 Y10 Z5
G55 G0 X0 Y0
G1 Z-1 F300
G1 X20 Y5
G56
G0 X1 Y1
G59.3 G1 X2 Y2 F600
G54
G92 X0 Y0
G1 X5 Y5
G92.2
G1 X5 Y5
G92.3
G1 X1 Y1
G92.1
G1 X3 Y3
G30 X20
G28.1
G0 X40 Y40
G28 Z30
G53 G0 Z0
G53 G1 X-10 Y-5 F900
G28 G91 Z0.
G90
G30
M2
""",
    "tools": """(tool lengths: G43 H, G43 with the spindle's tool, G43.1, G43.2, G49, inch)
G20 G17 G90
T1 M6
G43 H1
G0 X1 Y1 Z1
G1 Z-0.1 F20
G43 H2
G1 X2
T2 M6
G43
G1 Y2
G43.1 Z0.5
G1 X3
G43.2 H1
G1 Y3
G49
G1 X1
T1 M6
G43
G21
G1 X10 Y10
M2
""",
    "arcs_units": """(G91, G90.1, arcs with P turns, helices, the three planes, units)
G21 G17 G90
G0 X0 Y0 Z0
G91 G1 X10 F500
Y5
G3 X-5 Y5 I0 J5
G2 X5 Y5 Z-2 R5 P2
G90
G90.1
G2 X20 Y15 I15 J15
G91.1
G18 G2 X30 Z-2 I5 K0
G19 G3 Y25 Z-2 J5 K0
G17
G20 G1 X1.5 F10
G21 F300 G1 X2
G20 G91
G3 X0.5 Y0.5 R0.5
G90 G21
G0 X0 Y0 Z0
G3 I5 J0 F600
M2
""",
    "cycles": """(canned cycles in every plane, G98/G99, G91 with L, pecks, dwells)
G21 G17 G90
G0 X0 Y0 Z10
M3 S1000
G99 G81 X5 Y5 Z-3 R2 F200
X10
G98 G82 X15 Z-3 R2 P0.5
G83 X20 Z-7 R2 Q2.5
G73 X25 Z-7 R1 Q1.5
G85 X30 Z-4 R1
G86 X35 Z-4 R1 P0.2
G89 X40 Z-4 R1 P0.2
G84 X45 Z-6 R2 P0.1
G87 X50 Y5 Z-8 R1 I2 J0 K-4
G80
G0 Z20
G91 G98 G81 X5 Z-6 R-8 L3 F150
G90 G80
M4
G74 X5 Y20 Z-3 R2 F150
G80
M3
G18 G0 Y10
G81 X10 Z0 Y-5 R5 F100
Z10
G80
G19 G0 X10
G83 Y10 Z20 X-5 R5 Q2 F100
G80
G17 G61 G0 X0 Y0
G64 P0.02 G1 X5 F300
G64 X10
M2
""",
}

@pytest.fixture(scope="module", autouse=True)
def _linuxcnc_installed():
    assert linuxcnc_available(), ("LinuxCNC's interpreter is missing: install the Debian "
                                  "package linuxcnc-uspace (.ci/run does)")


def assert_same_path(a, b):
    """The paths of the two readers: move by move, the same."""
    np.testing.assert_allclose(a.start, b.start, rtol=0, atol=TOL_M)
    assert len(a.segments) == len(b.segments)
    for s, t in zip(a.segments, b.segments):
        where = f"line {s.line}"
        assert (type(s), s.line, s.rapid) == (type(t), t.line, t.rapid), where
        np.testing.assert_allclose(s.start, t.start, rtol=0, atol=TOL_M, err_msg=where)
        np.testing.assert_allclose(s.end, t.end, rtol=0, atol=TOL_M, err_msg=where)
        assert s.feed_m_s == pytest.approx(t.feed_m_s, rel=1e-12), where
        assert (s.blend_tol_m is None) == (t.blend_tol_m is None), where
        if s.blend_tol_m is not None:
            assert s.blend_tol_m == pytest.approx(t.blend_tol_m, rel=1e-12), where
        if isinstance(s, Arc):
            assert s.plane == t.plane, where
            np.testing.assert_allclose(s.center, t.center, rtol=0, atol=TOL_M, err_msg=where)
            assert abs(s.radius - t.radius) <= TOL_M, where
            # the signed sweep holds the direction and the full turns of the P word
            assert abs(s.sweep_rad - t.sweep_rad) * s.radius <= TOL_M, where
    assert a.plane == b.plane


@pytest.mark.parametrize("name", ACCEPTED)
def test_corpus_program_reads_the_same_through_both_readers(name):
    text = (CAM / name).read_text()
    builtin = parse_gcode(text, name, reader="builtin")
    assert_same_path(builtin, parse_gcode(text, name, reader="linuxcnc"))
    assert len(builtin.segments) > 10


@pytest.mark.parametrize("name", FEATURES)
def test_dialect_features_mean_what_linuxcnc_means(name):
    text = FEATURES[name]
    builtin = parse_gcode(text, name, reader="builtin", setup=SETUP)
    assert_same_path(builtin, parse_gcode(text, name, reader="linuxcnc", setup=SETUP))
    # and the same with LinuxCNC's defaults (machine zero, no offsets, no tool table)
    default = parse_gcode(text, name, reader="builtin")
    assert_same_path(default, parse_gcode(text, name, reader="linuxcnc"))


def test_features_against_hand_computed_positions():
    """Independent of LinuxCNC: G28 goes to the setup's home, G55 adds its offset, G53 is
    machine coordinates, G92 shifts, G43 H1 moves the tool's program zero by its length."""
    path = parse_gcode(FEATURES["home_offsets"], "h", reader="builtin", setup=SETUP)
    ends = {s.line: s.end for s in path.segments}
    g54, g55 = SETUP.work_offsets_m[0], SETUP.work_offsets_m[1]
    np.testing.assert_allclose(path.start, g54, atol=1e-15)  # at G54's zero: G28 goes home
    np.testing.assert_allclose(path.segments[0].end, SETUP.g28_m, atol=1e-15)
    np.testing.assert_allclose(ends[4], g54 + [0.010, 0.010, 0.005], atol=1e-15)
    # G55 X0 Y0: X and Y at G55's zero, Z (not named) stays where the machine is
    np.testing.assert_allclose(ends[5], [g55[0], g55[1], ends[4][2]], atol=1e-15)
    np.testing.assert_allclose(ends[25], [-0.010, -0.005, 0.0], atol=1e-15)  # G53
    np.testing.assert_allclose(ends[13], ends[10] + [0.005, 0.005, 0], atol=1e-15)  # G92 X0 Y0
    tools = parse_gcode(FEATURES["tools"], "t", reader="builtin", setup=SETUP)
    # T1 (X 0.5, Z 25.4 mm), G43 H1, then G0 X1 Y1 Z1 (inch): the first move, the start
    np.testing.assert_allclose(tools.start, g54 + [0.0254 + 0.0005, 0.0254, 0.0254 + 0.0254],
                               atol=1e-15)
    arcs = parse_gcode(FEATURES["arcs_units"], "a", reader="builtin")
    helix = next(s for s in arcs.segments if s.line == 7)  # G2 ... R5 P2
    assert helix.sweep_rad == pytest.approx(-2.5 * math.pi, rel=1e-12)  # 90 deg + one turn
    assert helix.rise == pytest.approx(-0.002, rel=1e-12)


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_corpus_programs_linuxcnc_refuses(name):
    line, column, what, warning = REFUSED[name]
    text = (CAM / name).read_text()
    with pytest.raises(GcodeError) as err:
        parse_gcode(text, name, reader="linuxcnc")
    assert err.value.line == line and what in err.value.message
    path = parse_gcode(text, name)  # auto: the built-in reader reads it, and says so
    assert any(warning in w for w in path.warnings) and path.segments


# --- auto: the built-in reader first, LinuxCNC's for the rest ---------------------------------

CUTTER_COMP = """G21 G17 G90
G0 X-10 Y-10 Z5
G1 Z-1 F300
G41 D1 G1 X0 Y0
G1 X20
G3 X30 Y10 R10
G1 Y20
G40 G1 X40 Y30
#1 = 3
o100 while [#1 GT 0]
  G1 X[40 + #1] Y30
  #1 = [#1 - 1]
o100 endwhile
M2
"""


def test_auto_reads_what_the_builtin_reader_does_not_through_linuxcnc():
    with pytest.raises(GcodeError) as err:
        parse_gcode(CUTTER_COMP, "comp.ngc", reader="builtin")
    assert (err.value.line, err.value.column) == (4, 1) and err.value.unsupported
    assert "G41 (cutter radius compensation)" in err.value.message
    tools = parse_tool_table("T1 P1 Z0 D4\n")  # the 2 mm radius of cutter compensation
    path = parse_gcode(CUTTER_COMP, "comp.ngc", setup=Setup(tools=tools))
    assert path.warnings[0].startswith("line 4:1: G41 (cutter radius compensation)")
    assert "read by LinuxCNC's interpreter" in path.warnings[0]
    # compensated: the tool runs 2 mm left of the programmed X0-X20 line, at Y2
    line = next(s for s in path.segments if s.line == 5)
    assert line.end[1] == pytest.approx(2e-3, abs=1e-12)
    assert [s.line for s in path.segments][-3:] == [11, 11, 11]  # the loop's three moves


@pytest.mark.parametrize("text, line, column, what", [
    ("G21 G0 X0\nG1 X1 F100\nM31\nM2\n", 3, 1, "Unknown m code used: M31"),
    ("G21 G0 X0 Y0\nG2 X2 Y0 I1 K1 F100\nM2\n", 2, 13, "K word given for arc in xy plane"),
    ("G21 G0 X0\nG1 X1 F100\n% vfd on\nM2\n", 3, 1, "Bad character '%' used"),
    ("G21 G0 X0\n#1 = [1 / 0]\nM2\n", 2, 1, "Attempt to divide by zero"),
    ("G21 G0 X0\no100 call\nM2\n", 2, 1, "EOF in file:bad.ngc seeking o-word: o<100>"),
])
def test_a_program_linuxcnc_refuses_is_refused_at_line_and_column(text, line, column, what):
    with pytest.raises(GcodeError) as err:
        parse_gcode(text, "bad.ngc", reader="linuxcnc")
    assert (err.value.line, err.value.column) == (line, column), err.value
    assert err.value.message.startswith("LinuxCNC: ") and what in err.value.message
    with pytest.raises(GcodeError) as err:  # auto: where both refuse, at the same place
        parse_gcode(text, "bad.ngc")
    assert (err.value.line, err.value.column) == (line, column), err.value


def test_endless_loop_probeopen_and_too_many_moves_are_bounded(monkeypatch):
    with pytest.raises(GcodeError, match="not finished within 2 s"):
        read_linuxcnc("G21\no1 while [1]\no1 endwhile\nM2\n", "loop.ngc", timeout_s=2.0)
    with pytest.raises(GcodeError, match="writes a file") as err:
        read_linuxcnc("G21\n(PROBEOPEN /tmp/x.txt)\nM2\n", "probe.ngc")
    assert err.value.line == 2
    import feedplan.gcode.moves as moves

    monkeypatch.setattr(moves, "MAX_SEGMENTS", 50)
    looped = ("G21 G0 X0\n#1=0\no1 while [#1 LT 100]\nG1 X[#1 MOD 2] F600\n#1=[#1+1]\n"
              "o1 endwhile\nM2\n")
    with pytest.raises(GcodeError, match="more than 50 moves") as err:
        read_linuxcnc(looped, "many.ngc")
    assert err.value.line == 4


def test_without_linuxcnc_the_refusal_says_where_it_would_read(monkeypatch):
    monkeypatch.setattr(lcnc, "linuxcnc_python", lambda: None)
    monkeypatch.setattr("feedplan.gcode.linuxcnc_available", lambda: False)
    with pytest.raises(GcodeError) as err:
        parse_gcode(CUTTER_COMP, "comp.ngc")
    assert (err.value.line, err.value.column) == (4, 1)
    assert "--reader linuxcnc, package linuxcnc-uspace, not installed here" in err.value.message
    with pytest.raises(OptionError, match="not installed"):
        parse_gcode(CUTTER_COMP, "comp.ngc", reader="linuxcnc")


def test_reader_and_tool_table_errors_name_what_and_where():
    with pytest.raises(OptionError, match="unknown G-code reader 'rs274'"):
        parse_gcode("G21\n", reader="rs274")
    for table, line, column, what in [("T1 P1 Z1\nT1 P2 Z2\n", 2, 1, "given twice"),
                                      ("T1 P1 Z1e\n", 1, 7, "Z word '1e' is not a number"),
                                      ("T1 P1 Z1 K3\n", 1, 10, "unknown word 'K3'"),
                                      ("P1 Z1\n", 1, 1, "without a T word")]:
        with pytest.raises(GcodeError, match=what) as err:
            parse_tool_table(table, "tools.tbl")
        assert (err.value.line, err.value.column) == (line, column)
    with pytest.raises(GcodeError, match="tool T3 is not in the tool table") as err:
        parse_gcode("G21\nT3 M6\nM2\n", reader="builtin", setup=SETUP)
    assert (err.value.line, err.value.column) == (2, 1)
    with pytest.raises(GcodeError, match="Requested tool 3 not found"):
        parse_gcode("G21\nT3 M6\nM2\n", reader="linuxcnc", setup=SETUP)


def test_machine_file_home_section():
    from oga.model.machine import load_machine, machine_from_dict

    base = load_machine("ucp710").model_dump(mode="json", exclude_none=True)
    home = {"g28_mm": [1, 2, 3], "work_offsets_mm": {"g55": [10, 20, -30], "g59_3": [1, 1, 1]}}
    machine = machine_from_dict({**base, "home": home})
    setup = machine.gcode_setup("T7 P1 Z12\n")
    np.testing.assert_allclose(setup.g28_m, [1e-3, 2e-3, 3e-3])
    np.testing.assert_allclose(setup.work_offsets_m[[0, 1, 8]],
                               [[0, 0, 0], [0.01, 0.02, -0.03], [1e-3, 1e-3, 1e-3]])
    assert setup.tool(7).offset_m == (0.0, 0.0, 0.012)
    # a machine without the section keeps its digest (the field is left out when unset)
    assert machine_from_dict(base).digest() == load_machine("ucp710").digest()
    for bad, field in [({"g28_mm": [1, 2]}, "home.g28_mm"),
                       ({"work_offsets_mm": {"g60": [0, 0, 0]}}, "home.work_offsets_mm.g60"),
                       ({"g30_mm": [0, 0, 1e9]}, "home.g30_mm.2")]:
        with pytest.raises(MachineError, match=field.replace(".", r"\.")):
            machine_from_dict({**base, "home": bad})
