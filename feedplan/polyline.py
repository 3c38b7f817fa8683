"""Polyline readers: points in mm (optional feed in mm/min) as CSV or JSON -> Path of lines.

The first point is where the tool starts at rest; every following point ends a
straight feed move from the previous one. Zero-length moves are dropped.

Feed
----
A point's feed (mm/min) is the feed of the segment ending at that point and of
the following ones until another point gives one (modal, as G-code F); a feed
on the first point applies from the first segment on. A polyline without any
feed gets ``feed_m_s = nan`` on every segment (the planner then needs an
override feed). Feeds given only from some later point on are refused: the
earlier segments would have none.

CSV
---
A header row then one row per point, comma-separated::

    x,y,z,feed
    0,0,0,3000
    10,0,0,
    10,5,0,1500

Columns are ``x,y,z`` or ``x,y,z,feed`` in that order (also spelled ``x_mm``,
``y_mm``, ``z_mm``, ``feed_mm_per_min``; any case). A feed cell may be empty
or left out.
Blank lines are skipped. ``Segment.line`` is the text line of the row ending it.

JSON
----
Either an object ``{"points": [...], "feed_mm_per_min": 3000}`` (the feed is
optional and acts as a feed given before the first point) or the bare list of
points. A point is ``[x, y, z]``, ``[x, y, z, feed]`` or an object with keys
``x``, ``y``, ``z`` and optionally ``feed`` (same spellings as the CSV header).
``Segment.line`` is the 1-based point number.
"""

from __future__ import annotations

import csv
import functools
import json
import math

import numpy as np

from feedplan.path import Line, Path
from oga.defaults import MAX_COORD_M, MAX_SEGMENTS
from oga.errors import ToolpathError

__all__ = ["parse_csv", "parse_json"]

#: Accepted names of each field (CSV header cells, JSON point keys).
_FIELDS = {"x": "x", "x_mm": "x", "y": "y", "y_mm": "y", "z": "z", "z_mm": "z",
           "feed": "feed", "feed_mm_per_min": "feed"}
_XYZ = ("x", "y", "z")


def _number(value, what: str, line: int = 0, column: int = 0, positive: bool = False) -> float:
    """``value`` (str or JSON number) as a finite float, else ToolpathError naming ``what``."""
    try:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise ValueError
        x = float(value)
    except OverflowError:  # an int beyond float64
        raise ToolpathError(f"{what}: {str(value)[:20]}... is out of range", line, column) from None
    except ValueError:
        raise ToolpathError(f"{what}: {value!r} is not a number", line, column) from None
    if not math.isfinite(x) or (positive and x <= 0):
        need = "a positive number" if positive else "finite"
        raise ToolpathError(f"{what}: {value!r} must be {need}", line, column)
    return x


def _polyline(points_mm: list, feeds: list, lines: list[int], where: list[str],
              first_feed: float | None, source: str) -> Path:
    """Path of the lines joining consecutive points.

    Parameters
    ----------
    points_mm : list of (x, y, z), length n
        Points in mm.
    feeds : list of float or None, length n
        Feed given at each point, mm/min (None: the previous one continues).
    lines, where : list, length n
        Source line (or point number) and a name of each point, for segments and messages.
    first_feed : float or None
        Feed given before the first point, mm/min.
    source : str
        Name of the input.
    """
    if len(points_mm) < 2:
        raise ToolpathError(f"a polyline needs at least 2 points, got {len(points_mm)}")
    p = np.asarray(points_mm, dtype=np.float64) * 1e-3
    far = np.flatnonzero(np.any(np.abs(p) > MAX_COORD_M, axis=1))
    if far.size:
        k = int(far[0])
        raise ToolpathError(f"{where[k]}: coordinate out of range (|x|, |y|, |z| <= "
                            f"{MAX_COORD_M * 1e3:g} mm)", lines[k])
    feed = first_feed
    seg_feed = []
    for k, f in enumerate(feeds):
        feed = f if f is not None else feed
        if k:
            seg_feed.append(feed)
    if any(f is not None for f in seg_feed) and None in seg_feed:
        k = seg_feed.index(None) + 1
        raise ToolpathError(f"{where[k]}: the segment ending here has no feed while later "
                            "points give one; give a feed on the first points", lines[k])
    segments = tuple(
        Line(p[k - 1], p[k], math.nan if seg_feed[k - 1] is None else seg_feed[k - 1] / 60e3,
             line=lines[k])
        for k in range(1, len(p)) if not np.array_equal(p[k - 1], p[k]))
    return Path(start=p[0], segments=segments, source=source)


def _too_many(points: int) -> None:
    if points > MAX_SEGMENTS + 1:
        raise ToolpathError(f"{points} points: more than {MAX_SEGMENTS} moves (the limit of one "
                            "toolpath)")


def _named(reader):
    """Puts the input's name (``source``) first in the reader's ToolpathErrors."""

    @functools.wraps(reader)
    def wrapper(text: str, source: str = "") -> Path:
        try:
            return reader(text, source)
        except ToolpathError as err:
            if not source or err.source:
                raise
            raise ToolpathError(err.message, err.line, err.column, source) from None

    return wrapper


@_named
def parse_csv(text: str, source: str = "") -> Path:
    """Read a CSV polyline (header ``x,y,z[,feed]``; mm and mm/min; see the module notes).

    Parameters
    ----------
    text : str
        The CSV text.
    source : str, optional
        Its name, for ``Path.source``.

    Returns
    -------
    Path
        Straight feed moves in metres, feeds in m/s (``nan`` when none is given).

    Raises
    ------
    ToolpathError
        Bad header, row length, number or feed; the line and column are named.
    """
    try:
        rows = [(n, row) for n, row in enumerate(
                    csv.reader(line.rstrip("\r") for line in text.split("\n")), start=1)
                if any(cell.strip() for cell in row)]
    except csv.Error as err:
        raise ToolpathError(f"CSV not readable: {err}") from None
    if not rows:
        raise ToolpathError("empty CSV: expected a header x,y,z[,feed] and rows of points")
    _too_many(len(rows) - 1)
    n0, header = rows[0]
    names = [_FIELDS.get(cell.strip().lower()) for cell in header]
    if names not in (["x", "y", "z"], ["x", "y", "z", "feed"]):
        raise ToolpathError(f"CSV header must be x,y,z or x,y,z,feed (mm, mm/min), got "
                            f"{','.join(header)!r}", n0, 1)
    points, feeds, lines, where = [], [], [], []
    for n, row in rows[1:]:
        if not 3 <= len(row) <= len(names):
            raise ToolpathError(f"row has {len(row)} fields, the header {len(names)}", n, 1)
        points.append([_number(row[c].strip(), f"field {name}", n, c + 1)
                       for c, name in enumerate(_XYZ)])
        cell = row[3].strip() if len(row) == 4 else ""
        feeds.append(_number(cell, "field feed", n, 4, positive=True) if cell else None)
        lines.append(n)
        where.append(f"point {len(lines)}")
    return _polyline(points, feeds, lines, where, None, source)


def _json_point(item, k: int) -> tuple[list[float], float | None]:
    """(xyz mm, feed mm/min or None) of the JSON point ``points[k]``."""
    what = f"points[{k}]"
    if isinstance(item, list):
        if len(item) not in (3, 4):
            raise ToolpathError(f"{what}: expected [x, y, z] or [x, y, z, feed], got "
                                f"{len(item)} values")
        fields = dict(zip(("x", "y", "z", "feed"), item))
    elif isinstance(item, dict):
        fields = {}
        for key, value in item.items():
            name = _FIELDS.get(key)
            if name is None or name in fields:
                raise ToolpathError(f"{what}: unknown or repeated key {key!r} (expected x, y, "
                                    "z and optionally feed)")
            fields[name] = value
        missing = [a for a in _XYZ if a not in fields]
        if missing:
            raise ToolpathError(f"{what}: missing {', '.join(missing)}")
    else:
        raise ToolpathError(f"{what}: expected a list [x, y, z] or an object with x, y, z")
    xyz = [_number(fields[a], f"{what}.{a}") for a in _XYZ]
    feed = fields.get("feed")
    return xyz, None if feed is None else _number(feed, f"{what}.feed", positive=True)


@_named
def parse_json(text: str, source: str = "") -> Path:
    """Read a JSON polyline (points in mm, optional feeds in mm/min; see the module notes).

    Parameters
    ----------
    text : str
        The JSON text.
    source : str, optional
        Its name, for ``Path.source``.

    Returns
    -------
    Path
        Straight feed moves in metres, feeds in m/s (``nan`` when none is given).

    Raises
    ------
    ToolpathError
        Invalid JSON (line and column named) or a bad point (``points[k].field`` named).
    """
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise ToolpathError(f"invalid JSON: {err.msg}", err.lineno, err.colno) from None
    except RecursionError:
        raise ToolpathError("invalid JSON: nested too deeply") from None
    except ValueError:  # an integer beyond Python's 4300 digits
        raise ToolpathError("invalid JSON: a number has too many digits") from None
    first_feed = None
    if isinstance(doc, dict):
        unknown = set(doc) - {"points", "feed_mm_per_min"}
        if unknown or "points" not in doc:
            raise ToolpathError("a JSON polyline object has the keys 'points' and optionally "
                                f"'feed_mm_per_min', got {sorted(doc)}")
        if doc.get("feed_mm_per_min") is not None:
            first_feed = _number(doc["feed_mm_per_min"], "feed_mm_per_min", positive=True)
        doc = doc["points"]
    if not isinstance(doc, list):
        raise ToolpathError("a JSON polyline is a list of points or an object with 'points'")
    _too_many(len(doc))
    parsed = [_json_point(item, k) for k, item in enumerate(doc)]
    return _polyline([p for p, _ in parsed], [f for _, f in parsed],
                     list(range(1, len(parsed) + 1)),
                     [f"points[{k}]" for k in range(len(parsed))], first_feed, source)
