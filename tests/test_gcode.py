"""The G-code reader against hand-computed geometry, exact unit conversion and LinuxCNC's rules."""

from __future__ import annotations

import math
from pathlib import Path as FilePath

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from feedplan.gcode import parse_gcode
from feedplan.gcode.builtin import NO_END
from feedplan.path import Arc, Line
from oga.errors import GcodeError, OptionError

DATA = FilePath(__file__).parent / "data"
MM = 1e-3
IN = 0.0254


def parse(text: str, **kw):
    return parse_gcode(text, source="t.ngc", reader="builtin", **kw)


def feed_moves(path):
    return [s for s in path.segments if not s.rapid]


def direction(seg, at_end: bool) -> np.ndarray:
    """Unit tangent by a finite difference of the segment's own points."""
    eps = 1e-7
    a, b = (seg.point(1 - eps), seg.point(1.0)) if at_end else (seg.point(0.0), seg.point(eps))
    d = b - a
    return d / np.linalg.norm(d)


def mm(*xyz):
    return np.array(xyz, dtype=float) * MM


# --- arc sense and geometry --------------------------------------------------------------------

def test_reference_xz_is_tangent_continuous():
    path = parse_gcode((DATA / "reference_xz.ngc").read_text(), "reference_xz.ngc")
    moves = feed_moves(path)
    assert [type(s).__name__ for s in moves].count("Arc") == 6
    assert path.plane == "zx"
    for prev, nxt in zip(moves, moves[1:]):
        assert np.array_equal(prev.end, nxt.start)
        # Coordinates have 4 decimals on radii of 5-10 mm: angle error ~1e-5 rad.
        cos = float(direction(prev, True) @ direction(nxt, False))
        assert cos > math.cos(1e-3), (prev.line, nxt.line)


def test_g18_g2_is_counter_clockwise_with_x_right_z_up():
    # First arc of reference_xz: G2 from (20, 0) to (28.6603, 5) about (20, 10) in (X, Z).
    arc = parse("G21 G18 G1 X20 Z0 F100\nG2 X28.6603 Z5 I0 K10\n").segments[0]
    assert isinstance(arc, Arc) and arc.plane == "zx"
    np.testing.assert_allclose(arc.center, mm(20, 0, 10), atol=1e-12)
    # In the (Z, X) frame the start is at 180 deg, the end at 120 deg: clockwise by 60 deg.
    assert arc.sweep_rad == pytest.approx(-math.pi / 3, abs=1e-5)
    # Drawn with X right and Z up it goes from the bottom of the circle to the right:
    # the middle point lies at -60 deg, i.e. (20 + 10 sin 30, 10 - 10 cos 30).
    np.testing.assert_allclose(arc.point(0.5), mm(25, 0, 10 - 10 * math.cos(math.pi / 6)),
                               atol=1e-8)
    g3 = parse("G21 G18 G1 X20 Z0 F100\nG3 X28.6603 Z5 I0 K10\n").segments[0]
    assert g3.sweep_rad == pytest.approx(2 * math.pi - math.pi / 3, abs=1e-5)


@pytest.mark.parametrize("g, sweep, mid", [
    ("G2", -math.pi / 2, (10 / math.sqrt(2), -10 / math.sqrt(2))),
    ("G3", 3 * math.pi / 2, (-10 / math.sqrt(2), 10 / math.sqrt(2))),
])
def test_g17_sense(g, sweep, mid):
    # From (10, 0) to (0, -10) about the origin: clockwise a quarter, counter-clockwise 3/4.
    arc = parse(f"G21 G17 G1 X10 Y0 F100\n{g} X0 Y-10 I-10 J0\n").segments[0]
    assert arc.plane == "xy"
    np.testing.assert_allclose(arc.center, 0, atol=1e-15)
    assert arc.sweep_rad == pytest.approx(sweep, rel=1e-12)
    assert arc.length == pytest.approx(10 * MM * abs(sweep), rel=1e-12)
    np.testing.assert_allclose(arc.point(0.5), mm(*mid, 0), atol=1e-12)


@pytest.mark.parametrize("g, sweep, mid", [
    ("G3", math.pi / 2, (10 / math.sqrt(2), 10 / math.sqrt(2))),
    ("G2", -3 * math.pi / 2, (-10 / math.sqrt(2), -10 / math.sqrt(2))),
])
def test_g19_sense(g, sweep, mid):
    # G19: (e1, e2) = (Y, Z), seen from +X with Y right and Z up. From (Y10, Z0) to (Y0, Z10).
    arc = parse(f"G21 G19 G1 Y10 Z0 F100\n{g} Y0 Z10 J-10 K0\n").segments[0]
    assert arc.plane == "yz"
    assert arc.sweep_rad == pytest.approx(sweep, rel=1e-12)
    np.testing.assert_allclose(arc.point(0.5), mm(0, *mid), atol=1e-12)


def test_full_circle_ijk():
    path = parse_gcode((DATA / "circle_r50_f3000.ngc").read_text())
    (arc,) = path.segments
    assert arc.sweep_rad == 2 * math.pi
    assert arc.length == pytest.approx(2 * math.pi * 50 * MM, rel=1e-15)
    np.testing.assert_array_equal(arc.end, arc.start)
    assert arc.feed_m_s == pytest.approx(3000 * MM / 60, rel=1e-15)
    cw = parse("G21 G0 X40 Y30\nG2 X40 Y30 I10 J0 F600\n").segments[0]
    assert cw.sweep_rad == -2 * math.pi
    np.testing.assert_allclose(cw.center, mm(50, 30, 0), atol=1e-15)
    np.testing.assert_allclose(cw.point(0.25), mm(50, 40, 0), atol=1e-12)  # clockwise: via +Y


def test_helix():
    # G17 G3 half turn of radius 20 rising 5 mm along Z.
    arc = parse("G21 G0 X20 Y0 Z0\nG3 X-20 Y0 Z5 I-20 J0 F600\n").segments[0]
    assert arc.rise == pytest.approx(5 * MM, rel=1e-15)
    assert arc.center[2] == 0.0
    assert arc.length == pytest.approx(math.hypot(math.pi * 20, 5) * MM, rel=1e-14)
    np.testing.assert_allclose(arc.point(0.5), mm(0, 20, 2.5), atol=1e-12)


@pytest.mark.parametrize("g, r, center, sweep", [
    # From (0, 0) to (10, 0) with |R| = sqrt(50): centre (5, +-5), quarter or 3/4 circle.
    ("G3", "", (5, 5), math.pi / 2),
    ("G3", "-", (5, -5), 3 * math.pi / 2),
    ("G2", "", (5, -5), -math.pi / 2),
    ("G2", "-", (5, 5), -3 * math.pi / 2),
])
def test_r_form_both_signs(g, r, center, sweep):
    arc = parse(f"G21 G0 X0 Y0\n{g} X10 Y0 R{r}{math.sqrt(50)!r} F100\n").segments[0]
    np.testing.assert_allclose(arc.center, mm(*center, 0), atol=1e-15)
    assert arc.sweep_rad == pytest.approx(sweep, rel=1e-12)
    assert arc.radius == pytest.approx(math.sqrt(50) * MM, rel=1e-14)


def test_r_form_half_circle_and_small_excess():
    exact = parse("G21 G0 X0 Y0\nG3 X10 Y0 R5 F100\n").segments[0]
    np.testing.assert_allclose(exact.center, mm(5, 0, 0), atol=1e-15)
    assert exact.sweep_rad == pytest.approx(math.pi, rel=1e-14)
    # A radius 0.001 mm short of the half chord is within LinuxCNC's tolerance (0.00005 in,
    # 0.00127 mm): the half circle; 0.002 mm short is refused.
    short = parse("G21 G0 X0 Y0\nG2 X10 Y0 R4.999 F100\n").segments[0]
    np.testing.assert_allclose(short.center, mm(5, 0, 0), atol=1e-15)
    assert short.sweep_rad == pytest.approx(-math.pi, rel=1e-14)
    with pytest.raises(GcodeError, match="R 4.998 is too small"):
        parse("G21 G0 X0 Y0\nG2 X10 Y0 R4.998 F100\n")


@pytest.mark.parametrize("r_mm", [1598.76735, -1598.76735, 576.15163])
def test_large_radius_r_arc(r_mm):
    # Almost straight G18 arc: chord ~50 mm, sagitta ~0.2 mm.
    z0, x0, z1, x1 = 0.49686, 55.10202, 3.80337, 104.66452
    arc = parse(f"G21 G18 G1 X{x0} Z{z0} F3500\nG2 X{x1} Z{z1} R{r_mm}\n").segments[0]
    r = abs(r_mm) * MM
    p0, p1 = mm(x0, 0, z0), mm(x1, 0, z1)
    # The centre is at distance R of both end points, to float precision of metres.
    assert np.linalg.norm(arc.center - p0) == pytest.approx(r, rel=1e-13)
    assert np.linalg.norm(arc.center - p1) == pytest.approx(r, rel=1e-13)
    h = np.linalg.norm(p1 - p0) / 2
    small = 2 * math.asin(h / r)
    expected = -small if r_mm > 0 else -(2 * math.pi - small)
    assert arc.sweep_rad == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(arc.point(1.0), p1, atol=1e-12)
    if r_mm > 0:
        # Middle point: sagitta h^2 / (R + sqrt(R^2 - h^2)) off the chord midpoint.
        sag = h * h / (r + math.sqrt(r * r - h * h))
        assert np.linalg.norm(arc.point(0.5) - (p0 + p1) / 2) == pytest.approx(sag, rel=1e-9)


def test_end_point_off_circle_tolerance_mm_and_inch():
    # Radius to start 100, to end 100.04: accepted, programmed end and centre kept exactly.
    arc = parse("G21 G0 X100 Y0\nG3 X0 Y100.04 I-100 J0 F100\n").segments[0]
    np.testing.assert_array_equal(arc.end, mm(0, 100.04, 0))
    np.testing.assert_array_equal(arc.center, mm(0, 0, 0))
    # 0.06: LinuxCNC runs it as a spiral (0.1 % of the radius), oga plans circles (0.05 mm)
    with pytest.raises(GcodeError) as err:
        parse("G21 G0 X100 Y0\nG3 X0 Y100.06 I-100 J0 F100\n")
    assert (err.value.line, err.value.column) == (2, 1)
    assert "off the circle" in err.value.message and "not spirals" in err.value.message
    # 0.2 mm (0.2 %) and 0.04 mm on a radius of 10 (0.4 %): LinuxCNC's own rule refuses them
    for text in ("G21 G0 X100 Y0\nG3 X0 Y100.2 I-100 J0 F100\n",
                 "G21 G0 X10 Y0\nG3 X0 Y10.04 I-10 J0 F100\n"):
        with pytest.raises(GcodeError, match="LinuxCNC refuses it") as err:
            parse(text)
        assert (err.value.line, err.value.column) == (2, 14)  # the I word
    parse("G20 G0 X10 Y0\nG3 X0 Y10.0019 I-10 J0 F10\n")
    with pytest.raises(GcodeError, match="off the circle"):
        parse("G20 G0 X10 Y0\nG3 X0 Y10.0021 I-10 J0 F10\n")


# --- units, feed, start point -------------------------------------------------------------------

def test_inch_program_converts_exactly():
    inch = parse("G20 G90 G17\nG0 X1 Y2 Z0.5\nG1 X1.5 Y-0.25 F10\nG2 X2 Y0.25 I0.5 J0\nM2\n")
    metric = parse("G21 G90 G17\nG0 X25.4 Y50.8 Z12.7\nG1 X38.1 Y-6.35 F254\n"
                   "G2 X50.8 Y6.35 I12.7 J0\nM2\n")
    np.testing.assert_allclose(inch.start, metric.start, rtol=0, atol=1e-17)
    for a, b in zip(inch.segments, metric.segments, strict=True):
        np.testing.assert_allclose(a.end, b.end, rtol=0, atol=1e-17)
        assert a.feed_m_s == pytest.approx(10 * 0.0254 / 60, rel=1e-15)
        assert a.feed_m_s == pytest.approx(b.feed_m_s, rel=1e-15)
    assert inch.segments[1].sweep_rad == pytest.approx(metric.segments[1].sweep_rad, rel=1e-14)
    np.testing.assert_allclose(inch.segments[1].center, mm(50.8, -6.35, 12.7), atol=1e-17)
    assert inch.warnings == ()


def test_feed_keeps_its_speed_across_a_unit_change():
    path = parse("G21 G0 X0\nG1 X10 F600\nG20\nX1\n")
    assert [s.feed_m_s for s in path.segments] == pytest.approx([0.01, 0.01], rel=1e-15)
    np.testing.assert_allclose(path.segments[1].end, [0.0254, 0, 0], atol=1e-18)


def test_start_point_rapids_and_zero_length_moves():
    path = parse("G21\nG0 Z5\nG0 X10 Y10\nG0 X10\nG1 Z-1 F200\nG1 Z-1\n")
    np.testing.assert_array_equal(path.start, mm(0, 0, 5))
    rapid, cut = path.segments  # the G0 X10 and G1 Z-1 repeats are zero-length
    assert rapid.rapid and rapid.feed_m_s == math.inf and rapid.line == 3
    np.testing.assert_array_equal(rapid.start, mm(0, 0, 5))
    np.testing.assert_array_equal(cut.end, mm(10, 10, -1))
    assert not cut.rapid and cut.feed_m_s == pytest.approx(200 * MM / 60) and cut.line == 5


def test_feed_is_modal_and_required():
    path = parse("G21 G0 X0\nG1 X1 F120\nX2\nG0 X3\nG1 X4\n")
    assert [s.feed_m_s for s in path.segments] == pytest.approx([0.002, 0.002, math.inf, 0.002])
    with pytest.raises(GcodeError, match="before any F") as err:
        parse("G21 G0 X0\nG1 X1\n")
    assert (err.value.line, err.value.column) == (2, 1)


def test_missing_units_warns_millimetres():
    path = parse("G0 X0\nG1 X1 F60\nM2\n")
    assert path.segments[0].end[0] == pytest.approx(1e-3, rel=1e-15)
    assert len(path.warnings) == 1 and "millimetres assumed" in path.warnings[0]


def test_plane_is_that_of_the_last_feed_move():
    path = parse("G21 G0 X0\nG18 G1 X1 F60\nG17\nG0 X5\n")
    assert path.plane == "zx"
    assert parse("G21 G19 G0 X0\n").plane == "yz"  # no feed move: the plane in effect


def test_cncjs_file():
    path = parse_gcode((DATA / "cncjs_toolpath.nc").read_text(), "cncjs_toolpath.nc")
    lines = [s for s in path.segments if isinstance(s, Line) and not s.rapid]
    arcs = [s for s in path.segments if isinstance(s, Arc)]
    rapids = [s for s in path.segments if s.rapid]
    # Counted by hand in the file: 9 G1 moves, 4 arcs, 10 G0 of which the first positions.
    assert (len(lines), len(arcs), len(rapids)) == (9, 4, 9)
    np.testing.assert_array_equal(path.start, mm(0, 0, 5))
    full, ccw, cw, xz = arcs
    assert full.sweep_rad == -2 * math.pi and full.radius == pytest.approx(10 * MM)
    # (20,20) -> (30,30) about (30,20): from 180 deg counter-clockwise to 90 deg is 3/4 turn
    # (the file's comment says "quarter arcs", but G3 takes the long way here).
    assert ccw.sweep_rad == pytest.approx(3 * math.pi / 2)
    assert cw.sweep_rad == pytest.approx(-math.pi / 2)  # (30,30) -> (40,40) about (40,30)
    # G18 G2 from X20 to X40 about X30 at Z-1: half circle dipping to Z-11 in the middle.
    assert xz.plane == "zx" and xz.sweep_rad == pytest.approx(-math.pi)
    np.testing.assert_allclose(xz.point(0.5), mm(30, 45, -11), atol=1e-12)
    assert path.plane == "zx" and path.warnings == (NO_END,)  # it has no M2
    for a, b in zip(path.segments, path.segments[1:]):
        np.testing.assert_array_equal(a.end, b.start)


# --- dialect --------------------------------------------------------------------------------------

REFERENCE = "G21 G90 G17\nG0 X0 Y0 Z1\nG1 Z-0.1 F24\nG1 X-0.992 Y25\nG2 X24.008 Y50 I25 J0\n"


@pytest.mark.parametrize("text", [
    # comments whole-line, after code, between words; ';' comments; blank lines
    "(header)\nG21 G90 G17 (units)\n\nG0 X0 Y0 Z1 ; go\nG1 (plunge) Z-0.1 F24\n"
    "G1 X-0.992 Y25;x\nG2 X24.008 Y50 I25 J0 (arc)\n",
    # a blank after a comment (the lexer once refused "(c) "), a comment between two words
    "(header) \nG21 G90 G17 (units)  \nG0 X0 Y0 Z1 \t\nG1 Z-0.1 (plunge) F24 \n"
    "G1 X-0.992 Y25 ( ) \nG2 X24.008 Y50 I25 J0\t(arc)\t\n",
    # N words, lower case, no spaces
    "N0010 g21g90g17\nn20 g0x0y0z1\nN30g1z-.1f24\nN0040 g1x-.992y25\nN50 g2x24.008y50i25j0\n",
    # spaces and TABs inside words, leading and trailing dots
    "G21 G90 G17\nG 0 X0. Y0. Z1.\nG1\tZ - .1 F 24.\nG1 X- .992 Y\t25\nG2 X2 4.008 Y5 0 I25. J0.\n",
    # % lines, modal motion on coordinate-only lines, G00 alone on a line
    "%\nG21 G90 G17\nG00 X0 Y0 Z1\nG00\nG01 F24\nZ-0.1\nX-0.992 Y25\nG02 X24.008 Y50 I25 J0\n%\n",
    # skipped words: S T M G4 P G40 G49 G54 G8 G94; path control (G61 G61.1 G64 P Q) is read
    "G21 G90 G17 G40 G49 G54 G94 G61 G8\nG61.1\nG64 P0.01 q00.01\nM06 T1 S1000 M3 M8\n"
    "G0 X0 Y0 Z1\nM01\nG04 P0.6\nG1 Z-0.1 F24 M7\nG1 X-0.992 Y25 S100\nG2 X24.008 Y50 I25 J0\n"
    "M9 M5 M0\nG64\nM4\n",
    # M2 / M30 end the program: what follows is ignored
    REFERENCE + "M30\nG91 #1=2 [junk]\n",
    REFERENCE + "M2\nG0 X100\n",
])
def test_dialect_variants_give_the_same_path(text):
    ref = parse(REFERENCE)
    path = parse(text)
    assert len(path.segments) == len(ref.segments) == 3
    np.testing.assert_array_equal(path.start, ref.start)
    for a, b in zip(path.segments, ref.segments):
        assert type(a) is type(b)
        np.testing.assert_array_equal(a.end, b.end)
        assert a.feed_m_s == b.feed_m_s
    assert isinstance(path.segments[2], Arc)
    np.testing.assert_allclose(path.segments[1].end, mm(-0.992, 25, -0.1), atol=1e-18)


def test_windows_line_endings_and_second_percent_ends():
    path = parse("%\r\nG21\r\nG0 X0\r\nG1 X1 F60\r\n%\r\nG1 X5 #1\r\n")
    assert len(path.segments) == 1


def test_modal_arc_continuation_with_new_centres_and_r():
    path = parse("G21 G17 G0 X0 Y0\nG2 X10 Y10 I10 J0 F100\nX20 Y0 I0 J-10\nX30 Y10 R10\n")
    arcs = path.segments
    assert all(isinstance(a, Arc) for a in arcs)
    np.testing.assert_allclose([a.center for a in arcs], [mm(10, 0, 0), mm(10, 0, 0),
                                                          mm(30, 0, 0)], atol=1e-15)
    assert [a.sweep_rad for a in arcs] == pytest.approx([-math.pi / 2] * 3)
    assert [a.line for a in arcs] == [2, 3, 4]


def test_source_line_of_each_segment():
    path = parse("(c)\nG21 G0 X0\n\nG1 X1 F60\nX2\n\nG0 X0\n")
    assert [s.line for s in path.segments] == [4, 5, 7]


# --- refusals ---------------------------------------------------------------------------------

@pytest.mark.parametrize("text, line, column, words", [
    ("G21 G0 X0\nG1 X#1 F60\n", 2, 5, "# parameters"),
    ("G21 G0 X0\nG1 X[1+2] F60\n", 2, 5, "[ ] expressions"),
    ("G21\nO100 sub\n", 2, 1, "O-words"),
    ("G21\n o100 call\n", 2, 2, "O-words"),
    ("G21 G0 X0\nG41 D1 G1 X5 F60\n", 2, 1, "G41 (cutter radius compensation)"),
    ("G21 G0 X0\ng42 G1 X5 F60\n", 2, 1, "G42 (cutter radius compensation)"),
    ("G21 G0 X0\nG5 X1 Y1 I0 J1 P1 Q0\n", 2, 1, "G5 (cubic spline)"),
    ("G21 G0 X0\nG5.1 X1 I1 J1\n", 2, 1, "G5.1 (quadratic spline)"),
    ("G21 G0 X0\nG5.2 X1 Y1 P1 L3\n", 2, 1, "G5.2 (NURBS)"),
    ("G21 G18 G7\n", 1, 9, "G7 (lathe diameter mode)"),
    ("G21 G93\n", 1, 5, "G93 (inverse time feed mode)"),
    ("G21 G95\n", 1, 5, "G95 (feed per revolution)"),
    ("G21 G0 X0 Z5\nG76 P1 Z-1\n", 2, 1, "G76 (threading cycle)"),
    ("G21 G0 X0 Z5\nG88 Z-1 R1 P1 F60\n", 2, 1, "G88 (boring cycle with manual retract)"),
    ("G21 G0 X0\nG1 X1 D1 F60\n", 2, 7, "D words (not in the built-in reader"),
    ("G21 M66 P1 L0\n", 1, 5, "M66 (wait on input)"),
    ("G21 M101\n", 1, 5, "M101 (user M-code)"),
    ("G21 G0 X@1\n", 1, 9, "polar coordinates (@)"),
    ("G21 G0 X0\nG1 X1 K1 F60\n", 2, 7, "K word without a code that uses it"),
    ("G21 G0 X0\nG1 X1 L2 F60\n", 2, 7, "L word without a code that uses it"),
    ("G21 G0 X0\nG1 X1 H1 F60\n", 2, 7, "H word without a code that uses it"),
    ("G21 G0 X0\nG80 X5\n", 2, 5, "axis words with G80"),
    ("G21 G0 X0\nG1 G28 X5\n", 2, 1, "G1 and G28 both use the axis words"),
    ("G21 G92\n", 1, 5, "G92 needs axis words"),
    ("G21 G91 G0 X0\nG53 G0 X5\n", 2, 1, "G53 (machine coordinates) in incremental"),
    ("G21 G53 G2 X5 Y0 I1 F60\n", 1, 5, "G53 (machine coordinates) needs G0 or G1"),
    ("G21 G0 X0 Z5\nG81 X1 Z-1 F60\n", 2, 1, "G81: R (clearance plane) is missing"),
    ("G21 G0 X0 Z5\nG81 X1 R1 F60\n", 2, 1, "G81: the depth"),
    ("G21 G0 X0 Z5\nG81 X1 Z2 R1 F60\n", 2, 11, "G81: R 1 is below the depth 2"),
    ("G21 G0 X0 Z5\nG83 X1 Z-2 R1 F60\n", 2, 1, "G83: Q (peck depth) is missing"),
    ("G21 G0 X0 Z5\nG83 X1 Z-2 R1 Q-1 F60\n", 2, 15, "Q (peck depth) must be positive"),
    ("G21 G0 X0 Z5\nG82 X1 Z-2 R1 F60\n", 2, 1, "G82: P (dwell, seconds) is missing"),
    ("G21 G0 X0 Z5\nG81 X1 Z-2 R1 L0 F60\n", 2, 15, "L0 (no repeat)"),
    ("G21 G0 X0 Z5\nG86 X1 Z-2 R1 P1 F60\n", 2, 1, "G86: the spindle is not turning"),
    ("G21 G0 X0 Z5\nM4\nG84 X1 Z-2 R1 F60\n", 3, 1, "G84: the spindle must turn clockwise"),
    ("G21 G90.1 G0 X0 Y0\nG2 X2 Y0 I1 F60\n", 2, 10, "J word missing in an absolute-centre arc"),
    ("G21 G0 X0\nG2 X2 Y0 I1 P1.5 F60\n", 2, 13, "the turns of an arc"),
    ("G21 T1.5\n", 1, 5, "a tool number is a whole number"),
    ("G21 M3 M4\n", 1, 8, "M3 and M4 are in the same modal group"),
    ("G21 M31\n", 1, 5, "M31 is not an M-code LinuxCNC knows"),
    ("G21 G0 X0\nG1 X1 ) F60\n", 2, 7, "')' without a '('"),
    ("G21 G0 X0\nG1 X1 (a (b (c)) F60\n", 2, 7, "comment is not closed"),
    ("G21 G0 X0 Z5\nG33 Z-1 K1\n", 2, 1, "G33 (spindle-synchronised motion)"),
    ("G21 G0 X0\nG1 X1 A10 F60\n", 2, 7, "axis A is not on this machine"),
    ("G21 G0 X0\nG1 X1 b10 F60\n", 2, 7, "axis B is not on this machine"),
    ("G21 G0 X0\nG1 C1\n", 2, 4, "axis C"),
    ("G21 G0 X0\nG1 U1\n", 2, 4, "axis U"),
    ("G21 G12\n", 1, 5, "G12 is not a G-code LinuxCNC knows"),
    ("G21 G1.5\n", 1, 5, "G1.5 is not a G-code LinuxCNC knows"),
    ("G21 G1.05\n", 1, 5, "G1.05 is not a G-code"),
    ("G21 G0 X0 $1\n", 1, 11, "unexpected character '$'"),
    ("G21 G0 X0\nG1 X1.2.3 F60\n", 2, 4, "number '1.2.3' does not parse"),
    ("G21 G0 X0\nG1 X F60\n", 2, 4, "X word: has no number"),
    ("G21 G0 X0\nG1 X1 (open comment\n", 2, 7, "comment is not closed"),
    ("G21 G0 X0\nG1 X1 X2 F60\n", 2, 7, "X word appears twice"),
    ("G21 G0 X0\nG1 G2 X1 F60\n", 2, 4, "G1 and G2 are in the same modal group"),
    ("G21 G17 G18\n", 1, 9, "G17 and G18 are in the same modal group"),
    ("G21\nX5\n", 2, 1, "without a motion mode"),
    ("G21 G0 X0\nG80\nX5\n", 3, 1, "without a motion mode"),
    ("G21 G0 X0 P1\n", 1, 11, "P word without a code that uses it"),
    ("G21 G4 Q1 P1\n", 1, 8, "Q word without a code that uses it"),
    ("G21 G4\n", 1, 5, "G4 (dwell) needs a P word"),
    ("G21 G0 X0\nG1 X1 F0\n", 2, 7, "the feed must be positive"),
    ("G21\nG2 X10 Y0 I5 J0 F60\n", 2, 1, "the first move is an arc"),
    ("G21 G0 X0\nG1 X1 I1 F60\n", 2, 7, "I word without a code that uses it"),
    ("G21 G0 X0\nG2 X10 Y0 K5 F60\n", 2, 11, "K word in an arc in G17"),
    ("G21 G18 G0 X0\nG2 X10 Z0 J5 F60\n", 2, 11, "J word in an arc in G18"),
    ("G21 G19 G0 Y0\nG2 Y10 Z0 I5 F60\n", 2, 11, "I word in an arc in G19"),
    ("G21 G0 X0 Y0\nG2 X10 F60\n", 2, 1, "arc needs I/J centre offsets or R"),
    ("G21 G0 X0 Y0\nG2 X10 I5 R5 F60\n", 2, 11, "both R and I/J/K"),
    ("G21 G0 X0 Y0\nG2 X0 Y0 R5 F60\n", 2, 10, "R-form arc needs an end point different"),
    ("G21 G0 X0 Y0\nG2 X10 Y0 R4.9 F60\n", 2, 11, "R 4.9 is too small"),
    ("G21 G0 X0 Y0\nG2 X10 Y0 I0 J0 F60\n", 2, 11, "arc radius is zero"),
    # numbers beyond float64 and coordinates beyond MAX_COORD_M (issue 18 rows 5 and 12)
    ("G21 G0 X0\nG1 X" + "9" * 320 + " F60\n", 2, 4, "X word: number out of range"),
    ("G21 G0 X0\nG1 X1 F" + "9" * 400 + "\n", 2, 7, "F word: number out of range"),
    ("G21 G" + "9" * 330 + "\n", 1, 5, "G word: number out of range"),
    ("G21 G0 X0\nG1 X1e308 F60\n", 2, 4, "1E308 has an exponent"),
    ("G21 G0 X0\nG1 Y2.5E-3 F60\n", 2, 4, "(coordinate out of range?"),
    ("G21 G0 X0\nG1 X" + "9" * 300 + " F60\n", 2, 4, "coordinate out of range (|X| <= 1e+06 mm)"),
    ("G21 G0 X0\nG1 Z-1000001 F60\n", 2, 4, "Z -1e+06: coordinate out of range"),
    ("G20 G0 X0\nG1 Y40000 F60\n", 2, 4, "coordinate out of range (|Y| <= 39370.1 in)"),
    ("G21 G0 X0 Y0\nG2 X1 Y0 I2000000 J0 F60\n", 2, 10, "I 2e+06: coordinate out of range"),
    ("G21 G0 X0 Y0\nG2 X1 Y0 R-2e9 F60\n", 2, 10, "R word: -2E9 has an exponent"),
])
def test_refusals_name_line_column_and_feature(text, line, column, words):
    with pytest.raises(GcodeError) as err:
        parse(text)
    e = err.value
    assert words in e.message
    assert (e.line, e.column) == (line, column)
    assert str(e) == f"t.ngc:{line}:{column}: {e.message}"
    assert isinstance(e, ValueError)


def test_axes_of_the_machine():
    path = parse("G21 G18 G0 X0 Z0\nG1 X1 Z1 F60\n", axes="xz")
    assert len(path.segments) == 1
    with pytest.raises(GcodeError, match="axis Y is not on this machine") as err:
        parse("G21 G0 X0\nG1 X1 Y1 F60\n", axes="xz")
    assert (err.value.line, err.value.column) == (2, 7)
    for bad in ("xa", "", "xx"):
        with pytest.raises(OptionError):
            parse("G21\n", axes=bad)


# --- properties -------------------------------------------------------------------------------

coord = st.floats(-500, 500, allow_nan=False).map(lambda v: round(v, 4))


@settings(max_examples=150, deadline=None)
@given(coord, coord, st.floats(0.5, 800), st.floats(-math.pi, math.pi),
       st.one_of(st.floats(0.05, math.pi - 0.3), st.floats(math.pi + 0.3, 2 * math.pi - 0.05)),
       st.booleans(), st.sampled_from(["G17", "G18", "G19"]))
def test_arc_written_as_ijk_and_as_r_gives_the_generating_geometry(cx, cy, r, theta0, span,
                                                                   ccw, plane_g):
    """A random arc (centre, radius, start angle, sweep) written both ways reads back exactly."""
    plane = {"G17": "xy", "G18": "zx", "G19": "yz"}[plane_g]
    e1, e2 = {"xy": "XY", "zx": "ZX", "yz": "YZ"}[plane]
    o1, o2 = {"xy": "IJ", "zx": "KI", "yz": "JK"}[plane]
    sweep = span if ccw else -span
    a1, a2 = cx + r * math.cos(theta0), cy + r * math.sin(theta0)
    b1, b2 = cx + r * math.cos(theta0 + sweep), cy + r * math.sin(theta0 + sweep)
    g = "G3" if ccw else "G2"
    f = "{:.10f}".format  # 1e-13 m resolution, no exponent
    head = f"G21 {plane_g} G0 {e1}{f(a1)} {e2}{f(a2)}\n{g} {e1}{f(b1)} {e2}{f(b2)} F100 "
    ijk = parse(head + f"{o1}{f(cx - a1)} {o2}{f(cy - a2)}\n").segments[0]
    rr = parse(head + f"R{f(r if span < math.pi else -r)}\n").segments[0]
    axes = {"X": 0, "Y": 1, "Z": 2}
    expect_c = np.zeros(3)
    expect_c[axes[e1]], expect_c[axes[e2]] = cx * MM, cy * MM
    for arc in (ijk, rr):
        assert arc.plane == plane
        np.testing.assert_allclose(arc.center, expect_c, rtol=0, atol=1e-10)
        assert arc.sweep_rad == pytest.approx(sweep, abs=1e-8)
        assert arc.radius == pytest.approx(r * MM, rel=1e-8)


def _styled(value: float, style: int) -> str:
    """``value`` (6 decimals) written as CAM posts and hand-typed programs do."""
    text = f"{value:.6f}"
    if style == 1:  # shortest: trailing dot ("25."), leading dot ("-.25")
        text = text.rstrip("0").replace("0.", ".", 1) if 0 < abs(value) < 1 else text.rstrip("0")
    if style == 2:
        text = text[0] + " \t" + text[1:]  # blanks inside the word
    if style == 3 and not text.startswith("-"):
        text = "+" + text
    return text


@settings(max_examples=200, deadline=None)
@given(st.floats(-1e4, 1e4, allow_nan=False).map(lambda v: round(v, 6)),
       st.integers(0, 3), st.booleans())
def test_number_formats_round_trip(value, style, lower):
    word = f"X{_styled(value, style)}"
    text = f"G21 G0 X{value + 1:.6f}\nG1 {word.lower() if lower else word} F60\n"
    (seg,) = parse(text).segments
    assert seg.end[0] == pytest.approx(value / 1000, rel=1e-15, abs=1e-21)


def test_coordinates_at_the_range_limit_are_read():
    """1e6 mm (MAX_COORD_M) is the last coordinate accepted; the next digit is refused."""
    path = parse("G21 G0 X0\nG1 X1000000 F60\nG1 X-1000000\n")
    assert path.segments[-1].end[0] == -1e3


def test_segment_count_is_bounded(monkeypatch):
    """More moves than MAX_SEGMENTS: refused at the first move beyond it (line, column)."""
    import feedplan.gcode.moves as moves

    monkeypatch.setattr(moves, "MAX_SEGMENTS", 3)
    parse("G21 G0 X0\nG1 X1 F60\nX2\nX3\n")
    with pytest.raises(GcodeError) as err:
        parse("G21 G0 X0\nG1 X1 F60\nX2\nX3\nX4\n")
    assert (err.value.line, err.value.column) == (5, 1)
    assert "more than 3 moves" in err.value.message


def test_path_control_modes_apply_to_the_moves_programmed_under_them():
    path = parse("G21 G90 G17\nG0 X0 Y0\nG1 X1 F600\nG61 X2\nG64 P0.05 X3\nG61.1\nX4\n"
                 "G64 P0 X5\nG20 G64 P0.001 X0.3\nG21 G64 X6\nG64 Q0.03 X7\n")
    got = [s.blend_tol_m for s in path.segments]
    assert got[:4] == [None, 0.0, pytest.approx(0.05e-3), 0.0]
    assert got[4] is None  # P0: G64 without P, as in LinuxCNC
    assert got[5] == pytest.approx(0.001 * 0.0254)  # P in the program's units (inch)
    assert got[6:] == [None, None]  # Q alone: the plan's tolerance
    arc = parse("G21 G17 G61 G0 X0 Y0\nG2 X10 Y10 I10 J0 F100\n").segments[0]
    assert arc.blend_tol_m == 0.0


def test_negative_g64_p_is_refused_at_its_column():
    with pytest.raises(GcodeError, match="must not be negative") as err:
        parse("G21 G0 X0\nG64 P-0.1\n")
    assert (err.value.line, err.value.column) == (2, 5)
