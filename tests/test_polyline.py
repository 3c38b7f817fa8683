"""CSV and JSON polyline readers, and format dispatch (read_toolpath, load_toolpath)."""

from __future__ import annotations

import json
import math
from pathlib import Path as FilePath

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from feedplan.gcode import parse_gcode
from feedplan.path import Line
from feedplan.polyline import parse_csv, parse_json
from feedplan.read import load_toolpath, read_toolpath
from oga.errors import GcodeError, OptionError, ToolpathError

DATA = FilePath(__file__).parent / "data"


def xyz_m(path) -> np.ndarray:
    return np.array([path.start] + [s.end for s in path.segments])


# --- CSV ---------------------------------------------------------------------------------------

def test_csv_points_and_modal_feed():
    text = "x,y,z,feed\n0,0,0,3000\n10,0,0,\n\n10,5,-1,1500\n0,5,-1\n"
    path = parse_csv(text, source="p.csv")
    np.testing.assert_allclose(xyz_m(path), [[0, 0, 0], [0.01, 0, 0], [0.01, 0.005, -0.001],
                                             [0, 0.005, -0.001]], rtol=0, atol=1e-18)
    assert all(isinstance(s, Line) and not s.rapid for s in path.segments)
    # 3000 mm/min = 0.05 m/s carried to the second point; 1500 from the third on.
    assert [s.feed_m_s for s in path.segments] == pytest.approx([0.05, 0.025, 0.025], rel=1e-15)
    assert [s.line for s in path.segments] == [3, 5, 6]
    assert path.source == "p.csv"
    assert path.length == pytest.approx((10 + math.hypot(5, 1) + 10) * 1e-3, rel=1e-15)


def test_csv_without_feed_gives_nan_and_unit_header():
    path = parse_csv("X_mm, y_mm ,Z_MM\r\n1,2,3\r\n4,6,3\r\n4,6,3\r\n")
    (seg,) = path.segments  # the repeated point is a zero-length move, dropped
    assert math.isnan(seg.feed_m_s)
    assert seg.length == pytest.approx(5e-3, rel=1e-15)
    parse_csv("x,y,z,feed_mm_per_min\n0,0,0,100\n1,0,0,\n")


@pytest.mark.parametrize("text, line, column, words", [
    ("", 0, 0, "empty CSV"),
    ("a,b,c\n0,0,0\n1,1,1\n", 1, 1, "CSV header must be"),
    ("x,y,z,feed,extra\n0,0,0,1,1\n", 1, 1, "CSV header must be"),
    ("x,y,z\n0,0,0\n1,1\n", 3, 1, "row has 2 fields"),
    ("x,y,z\n0,0,0\n1,abc,1\n", 3, 2, "field y: 'abc' is not a number"),
    ("x,y,z\n0,0,0\n1,1,nan\n", 3, 3, "must be finite"),
    ("x,y,z,feed\n0,0,0,100\n1,1,1,-5\n", 3, 4, "must be a positive number"),
    ("x,y,z,feed\n0,0,0\n1,0,0\n2,0,0,100\n", 3, 0, "point 2: the segment ending here has no feed"),
    ("x,y,z\n0,0,0\n", 0, 0, "at least 2 points"),
])
def test_csv_errors_name_row_and_field(text, line, column, words):
    with pytest.raises(ToolpathError) as err:
        parse_csv(text)
    assert words in err.value.message
    assert (err.value.line, err.value.column) == (line, column)


# --- JSON ---------------------------------------------------------------------------------------

def test_json_forms_agree_with_csv():
    csv_path = parse_csv("x,y,z,feed\n0,0,0,600\n3,4,0\n3,4,12,300\n")
    forms = [
        {"points": [[0, 0, 0], [3, 4, 0], [3, 4, 12, 300]], "feed_mm_per_min": 600},
        [[0, 0, 0, 600], [3, 4, 0], [3, 4, 12, 300]],
        [{"x": 0, "y": 0, "z": 0, "feed": 600}, {"x": 3, "y": 4, "z": 0},
         {"x_mm": 3, "y_mm": 4, "z_mm": 12, "feed_mm_per_min": 300}],
    ]
    for doc in forms:
        path = parse_json(json.dumps(doc))
        np.testing.assert_array_equal(xyz_m(path), xyz_m(csv_path))
        assert [s.feed_m_s for s in path.segments] == [s.feed_m_s for s in csv_path.segments]
        assert [s.line for s in path.segments] == [2, 3]  # point numbers
    assert csv_path.segments[0].feed_m_s == pytest.approx(0.01, rel=1e-15)
    assert math.isnan(parse_json('{"points": [[0,0,0],[1,0,0]]}').segments[0].feed_m_s)


@pytest.mark.parametrize("text, words", [
    ('{"points": [[0,0,0],', "invalid JSON"),
    ('{"pts": []}', "has the keys 'points'"),
    ('{"points": [[0,0,0],[1,1,1]], "feed": 5}', "has the keys 'points'"),
    ('"hello"', "a list of points"),
    ('[[0,0,0],[1,1]]', "points[1]: expected [x, y, z]"),
    ('[[0,0,0],[1,1,"a"]]', "points[1].z: 'a' is not a number"),
    ('[[0,0,0],[1,1,true]]', "points[1].z: True is not a number"),
    ('[[0,0,0],{"x":1,"y":1}]', "points[1]: missing z"),
    ('[[0,0,0],{"x":1,"y":1,"z":1,"w":2}]', "points[1]: unknown or repeated key 'w'"),
    ('[[0,0,0],{"x":1,"x_mm":1,"y":1,"z":1}]', "unknown or repeated key 'x_mm'"),
    ('[[0,0,0],[1,1,1,0]]', "points[1].feed: 0 must be a positive number"),
    ('{"points": [[0,0,0],[1,1,1]], "feed_mm_per_min": -1}', "feed_mm_per_min: -1 must be"),
    ('[[0,0,0],[1,0,0],[2,0,0,100]]', "points[1]: the segment ending here has no feed"),
    ('[[0,0,0], 5]', "points[1]: expected a list"),
    ('[[0,0,0]]', "at least 2 points"),
])
def test_json_errors_name_the_field(text, words):
    with pytest.raises(ToolpathError) as err:
        parse_json(text)
    assert words in err.value.message


def test_json_syntax_error_has_line_and_column():
    with pytest.raises(ToolpathError) as err:
        parse_json('{"points": [\n  [0, 0, 0],\n  [1, 1 1]\n]}')
    assert (err.value.line, err.value.column) == (3, 9)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-1e3, 1e3).map(lambda v: round(v, 6))] * 3), min_size=2,
                max_size=20),
       st.floats(1, 1e5))
def test_csv_and_json_polyline_length(points, feed):
    """Both formats give the same segments; lengths add up to the polyline's, feed in m/s."""
    csv_text = "x,y,z\n" + "\n".join(",".join(repr(v) for v in p) for p in points)
    a = parse_csv(csv_text)
    b = parse_json(json.dumps({"points": points, "feed_mm_per_min": feed}))
    expected = sum(math.dist(p, q) for p, q in zip(points, points[1:])) * 1e-3
    assert a.length == pytest.approx(expected, rel=1e-12, abs=1e-18)
    np.testing.assert_array_equal(xyz_m(a), xyz_m(b))
    assert all(s.feed_m_s == pytest.approx(feed / 60e3, rel=1e-15) for s in b.segments)
    assert all(s.length > 0 for s in a.segments)


# --- dispatch -----------------------------------------------------------------------------------

def test_read_toolpath_by_format():
    g = read_toolpath("G21 G0 X0\nG1 X1 F60\n", "gcode", source="s")
    assert g.source == "s" and g.segments[0].end[0] == pytest.approx(1e-3)
    assert len(read_toolpath("x,y,z\n0,0,0\n1,0,0\n", "csv").segments) == 1
    assert len(read_toolpath("[[0,0,0],[1,0,0]]", "json").segments) == 1
    with pytest.raises(OptionError, match="unknown toolpath format 'dxf'"):
        read_toolpath("", "dxf")


@pytest.mark.parametrize("name", ["p.ngc", "p.NC", "p.gcode", "p.gc", "p.tap", "p.cnc"])
def test_load_gcode_extensions(tmp_path, name):
    f = tmp_path / name
    f.write_bytes(b"\xef\xbb\xbfG21 G0 X0\r\nG1 X2 F60\r\n")  # UTF-8 with a byte-order mark
    path = load_toolpath(f)
    assert path.source == str(f)
    assert path.segments[0].end[0] == pytest.approx(2e-3)


def test_load_polylines_and_gcode_error_names_the_file(tmp_path):
    (tmp_path / "a.csv").write_text("x,y,z\n0,0,0\n0,0,1\n")
    (tmp_path / "b.JSON").write_text("[[0,0,0],[0,0,1]]")
    assert load_toolpath(tmp_path / "a.csv").length == pytest.approx(1e-3)
    assert load_toolpath(str(tmp_path / "b.JSON")).length == pytest.approx(1e-3)
    (tmp_path / "bad.ngc").write_text("G21\nG12\n")
    with pytest.raises(GcodeError) as err:
        load_toolpath(tmp_path / "bad.ngc")
    assert str(err.value).startswith(f"{tmp_path / 'bad.ngc'}:2:1: G12")


def test_load_errors(tmp_path):
    with pytest.raises(ToolpathError, match=r"unknown toolpath extension '\.dxf'"):
        load_toolpath(tmp_path / "x.dxf")
    with pytest.raises(ToolpathError, match="unknown toolpath extension '\\(none\\)'"):
        load_toolpath(tmp_path / "noext")
    with pytest.raises(ToolpathError, match="cannot read the file"):
        load_toolpath(tmp_path / "missing.ngc")
    (tmp_path / "dir.ngc").mkdir()
    with pytest.raises(ToolpathError, match="cannot read the file"):
        load_toolpath(tmp_path / "dir.ngc")
    (tmp_path / "latin.ngc").write_bytes("G21\n(caf\u00e9)\n".encode("latin-1"))
    with pytest.raises(ToolpathError, match="not UTF-8 text") as err:
        load_toolpath(tmp_path / "latin.ngc")
    assert (err.value.line, err.value.column) == (2, 5)
    assert str(err.value) == f"{tmp_path / 'latin.ngc'}:2:5: not UTF-8 text (byte 0xe9)"


def test_polyline_errors_name_the_file_first(tmp_path):
    (tmp_path / "p.csv").write_text("x,y,z\n0,0,0\n1,a,0\n")
    with pytest.raises(ToolpathError) as err:
        load_toolpath(tmp_path / "p.csv")
    assert str(err.value) == f"{tmp_path / 'p.csv'}:3:2: field y: 'a' is not a number"
    (tmp_path / "p.json").write_text('{"points": [[0, 0, 0], [1, 2]]}')
    with pytest.raises(ToolpathError) as err:
        load_toolpath(tmp_path / "p.json")
    assert str(err.value).startswith(f"{tmp_path / 'p.json'}: points[1]: expected [x, y, z]")
    with pytest.raises(ToolpathError) as err:  # without a name: as before
        parse_csv("x,y,z\n0,0,0\n1,a,0\n")
    assert str(err.value) == "line 3:2: field y: 'a' is not a number"


def test_polyline_coordinates_and_size_are_bounded(monkeypatch):
    with pytest.raises(ToolpathError, match=r"point 2: coordinate out of range \(\|x\|, \|y\|, "
                       r"\|z\| <= 1e\+06 mm\)") as err:
        parse_csv("x,y,z\n0,0,0\n0,1e7,0\n", source="f.csv")
    assert str(err.value).startswith("f.csv:3: ")
    with pytest.raises(ToolpathError, match="points\\[1\\]: coordinate out of range"):
        parse_json("[[0, 0, 0], [0, 0, -1e300]]")
    import feedplan.polyline as polyline

    monkeypatch.setattr(polyline, "MAX_SEGMENTS", 2)
    assert len(parse_csv("x,y,z\n0,0,0\n1,0,0\n2,0,0\n").segments) == 2
    with pytest.raises(ToolpathError, match="4 points: more than 2 moves"):
        parse_csv("x,y,z\n0,0,0\n1,0,0\n2,0,0\n3,0,0\n")
    with pytest.raises(ToolpathError, match="4 points: more than 2 moves"):
        parse_json("[[0,0,0],[1,0,0],[2,0,0],[3,0,0]]")


def test_shipped_programs_load(tmp_path):
    """Every G-code program under tests/data reads through load_toolpath like parse_gcode."""
    for f in sorted(DATA.glob("*.n*")):
        path = load_toolpath(f)
        direct = parse_gcode(f.read_text(), str(f))
        assert len(path.segments) == len(direct.segments) > 0


@pytest.mark.parametrize("text, message", [
    ("[[" + "9" * 400 + ", 0, 0], [0, 0, 1]]", "p.json: points[0].x: 999999"),
    ("[[" + "9" * 5000 + ", 0, 0], [0, 0, 1]]", "p.json: invalid JSON: a number has too many"),
    ("[" * 100000 + "]" * 100000, "p.json: invalid JSON: nested too deeply"),
    ("[[1e400, 0, 0], [0, 0, 1]]", "p.json: points[0].x: inf must be finite"),
])
def test_json_numbers_beyond_float64_and_deep_nesting(text, message):
    with pytest.raises(ToolpathError) as err:
        parse_json(text, source="p.json")
    assert str(err.value).startswith(message)


def test_a_toolpath_file_beyond_the_size_limit_is_refused_before_reading(tmp_path):
    from feedplan.read import read_file
    from oga.defaults import MAX_TOOLPATH_BYTES
    from oga.errors import ToolpathError

    big = tmp_path / "big.ngc"
    with open(big, "wb") as f:  # sparse: no disk used, and never read
        f.truncate(MAX_TOOLPATH_BYTES + 1)
    with pytest.raises(ToolpathError, match=f"big.ngc: file of {MAX_TOOLPATH_BYTES + 1} bytes"):
        read_file(big)
    ok = tmp_path / "ok.ngc"
    ok.write_text("G21 G90\nG1 X1 F100\n")
    assert read_file(ok) == ("G21 G90\nG1 X1 F100\n", "gcode")


@pytest.mark.parametrize("fmt, text, unit", [
    ("gcode", "\n", "lines"), ("csv", "0,0,0\n", "lines"), ("json", "[0,0,0],", "arrays")])
def test_line_and_array_counts_are_bounded_before_parsing(fmt, text, unit):
    from oga.defaults import MAX_TOOLPATH_LINES
    from oga.errors import ToolpathError

    big = text * (MAX_TOOLPATH_LINES + 1)
    with pytest.raises(ToolpathError, match=f"big: {MAX_TOOLPATH_LINES + 1} {unit}, more than"):
        read_toolpath(big, fmt, source="big")
