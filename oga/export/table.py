"""Export: setpoints and gain tables as text/bytes (full float precision)."""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES, Setpoints

__all__ = [
    "setpoints_csv",
    "table_columns",
    "table_csv",
    "TABLE_FORMATS",
    "GainTable",
    "gain_table",
    "table_from_npz",
    "render_table",
    "table_json",
    "table_npz",
    "table_c_header",
]

#: Gain-table formats: name -> (file suffix, media type).
TABLE_FORMATS: dict[str, tuple[str, str]] = {
    "csv": (".csv", "text/csv; charset=utf-8"),
    "json": (".json", "application/json"),
    "npz": (".npz", "application/octet-stream"),
    "c": (".h", "text/x-chdr; charset=utf-8"),
}

#: Default C identifier prefix of :func:`table_c_header`.
C_NAME = "oga_gain_table"


def _csv(header: list[str], columns: list[np.ndarray]) -> str:
    data = np.column_stack(columns)
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    # repr-precision floats: 17 significant digits round-trip float64 exactly
    np.savetxt(buf, data, delimiter=",", fmt="%.17g")
    return buf.getvalue()


def setpoints_csv(sp: Setpoints) -> str:
    """Setpoints as CSV: ``t_s, s_m``, then per axis pos, vel, acc, jerk (SI), one row per sample."""
    header = ["t_s", "s_m"]
    cols = [sp.t, sp.s]
    for k, a in enumerate(AXES):
        header += [f"{a}_pos_m", f"{a}_vel_m_s", f"{a}_acc_m_s2", f"{a}_jerk_m_s3"]
        cols += [sp.pos[:, k], sp.vel[:, k], sp.acc[:, k], sp.jerk[:, k]]
    return _csv(header, cols)


def table_columns(result) -> tuple[list[str], list[np.ndarray]]:
    """Header and columns of a gain table: ``t_s, s_m``, then per axis pos, vel, kp, kf.

    Parameters
    ----------
    result : OptimizeResult
        A verified result (``status == "ok"``).
    """
    sp = result.setpoints
    header = ["t_s", "s_m"]
    cols = [sp.t, sp.s]
    for k, a in enumerate(AXES):
        header += [f"{a}_pos_m", f"{a}_vel_m_s", f"{a}_kp_m_min_per_mm", f"{a}_kf"]
        cols += [sp.pos[:, k], sp.vel[:, k],
                 result.schedule.kp_m_min_per_mm[:, k], result.schedule.kf[:, k]]
    return header, cols


def table_csv(result) -> str:
    """The gain table as CSV text, one row per sample (full float precision).

    Raises
    ------
    OptimizeError
        The schedule failed verification: a failed table is never exported.
    """
    _require_ok(result)
    header, cols = table_columns(result)
    return _csv(header, cols)


def _require_ok(result) -> None:
    from oga.errors import OptimizeError

    if result.status != "ok":
        raise OptimizeError(
            "the schedule failed verification and is not exported: "
            + "; ".join(result.optimized.violations)
        )


#: Unit of a table column, by the end of its name.
_UNITS = (("_m_min_per_mm", "(m/min)/mm"), ("_kf", "1"), ("_m_s", "m/s"), ("_m", "m"), ("_s", "s"))


def _unit(column: str) -> str:
    return next(u for end, u in _UNITS if column.endswith(end))


@dataclass(frozen=True, eq=False)
class GainTable:
    """A verified gain table detached from its result: the columns and their metadata.

    Attributes
    ----------
    header : tuple of str
        Column names (:func:`table_columns`), the unit at the end of each name.
    data : ndarray, shape (N, C)
        One row per sample, float64, columns in ``header`` order.
    meta : dict
        JSON-able metadata: toolpath/setpoints/machine hashes, sample period ``sample_period_s``
        (s), ``axes`` order, ``units`` per column, ``samples``.
    """

    header: tuple[str, ...]
    data: np.ndarray
    meta: dict


def gain_table(result, *, toolpath_sha256: str | None = None,
               setpoints_source: dict | None = None) -> GainTable:
    """The table of a verified result with its metadata.

    Parameters
    ----------
    result : OptimizeResult
        A verified result (``status == "ok"``).
    toolpath_sha256 : str, optional
        SHA-256 of the submitted toolpath text (``Job.toolpath_sha256``), recorded in the metadata.
    setpoints_source : dict, optional
        Recorded setpoints: where they came from (``Job.recorded.source``: file, format,
        SHA-256), recorded in the metadata as ``setpoints_source``.

    Raises
    ------
    OptimizeError
        The schedule failed verification, or a value is not finite.
    """
    from oga import __version__
    from oga.errors import OptimizeError
    from oga.search.result import setpoints_digest

    _require_ok(result)
    header, cols = table_columns(result)
    data = np.column_stack(cols)
    if not np.isfinite(data).all():
        raise OptimizeError("the gain table holds non-finite values and is not exported")
    sp = result.setpoints
    meta = {
        "format": "oga-gain-table",
        "format_version": 1,
        "oga_version": __version__,
        "toolpath": sp.source,
        "toolpath_sha256": toolpath_sha256,
        "setpoints_sha256": setpoints_digest(sp),
        "machine": result.machine.name,
        "machine_sha256": result.machine.digest(),
        "sample_period_s": float(sp.dt),
        "samples": len(sp),
        "axes": list(AXES),
        "columns": header,
        "units": {c: _unit(c) for c in header},
    }
    if setpoints_source is not None:
        meta["setpoints_source"] = dict(setpoints_source)
    return GainTable(header=tuple(header), data=data, meta=meta)


def table_from_npz(blob: bytes) -> GainTable:
    """Read back a table written by :func:`table_npz` (exact float64 values)."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        header = tuple(meta["columns"])
        data = np.column_stack([z[c] for c in header])
    return GainTable(header=header, data=data, meta=meta)


def _table_json(table: GainTable) -> str:
    cols = {c: table.data[:, j].tolist() for j, c in enumerate(table.header)}
    return json.dumps({"meta": table.meta, "columns": cols}, allow_nan=False)


def _table_npz(table: GainTable) -> bytes:
    buf = io.BytesIO()
    arrays = {c: table.data[:, j] for j, c in enumerate(table.header)}
    np.savez_compressed(buf, meta=np.array(json.dumps(table.meta)), **arrays)
    return buf.getvalue()


def _c_string(text: str) -> str:
    """A C string literal of ``text`` (printable ASCII kept, every other byte as octal)."""
    out = []
    for b in text.encode("utf-8"):
        ch = chr(b)
        out.append("\\" + ch if ch in '"\\?' else ch if 32 <= b < 127 else f"\\{b:03o}")
    return '"' + "".join(out) + '"'


def _c_values(a: np.ndarray) -> str:
    """Initialiser body of a C array: one value (1-D) or one ``{...}`` row (2-D) per line."""
    text = np.char.mod("%.17g", a)
    if a.ndim == 1:
        return ",\n".join(text)
    return ",\n".join("{" + ", ".join(row) + "}" for row in text)


def _table_c(table: GainTable, name: str) -> str:
    from oga.errors import OptionError

    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,62}", name):
        raise OptionError(f"name: {name!r} is not a C identifier")
    m, macro = table.meta, name.upper()
    n = m["samples"]
    lines = [
        f"/* Gain table generated by oga {m['oga_version']}: replay one row per sample. */",
        "/* Units are in the names: m, m/s, s, Kp in (m/min)/mm, Kf dimensionless. */",
        f"#ifndef {macro}_H",
        f"#define {macro}_H",
        "",
        f"#define {macro}_SAMPLES {n}",
        f"#define {macro}_SAMPLE_PERIOD_S {m['sample_period_s']!r}",
        f"#define {macro}_AXES {len(m['axes'])}",
        f"#define {macro}_AXIS_ORDER {_c_string(''.join(m['axes']))}",
        f"#define {macro}_TOOLPATH {_c_string(m['toolpath'])}",
        f"#define {macro}_TOOLPATH_SHA256 {_c_string(m['toolpath_sha256'] or '')}",
        f"#define {macro}_SETPOINTS_SHA256 {_c_string(m['setpoints_sha256'])}",
        f"#define {macro}_MACHINE {_c_string(m['machine'])}",
        f"#define {macro}_MACHINE_SHA256 {_c_string(m['machine_sha256'])}",
    ]
    index = {c: j for j, c in enumerate(table.header)}
    seen = []
    for c in table.header:
        axis, _, quantity = c.partition("_")
        if axis in m["axes"]:
            if quantity in seen:
                continue
            seen.append(quantity)
            cols = [index[f"{a}_{quantity}"] for a in m["axes"]]
            dims, what = f"[{n}][{len(cols)}]", f"per axis in {macro}_AXIS_ORDER"
        else:
            quantity, cols, dims, what = c, [index[c]], f"[{n}]", "per sample"
        values = table.data[:, cols] if len(cols) > 1 else table.data[:, cols[0]]
        lines += ["", f"/* {quantity}: {what}, unit {_unit(c)} */",
                  f"static const double {name}_{quantity}{dims} = {{", _c_values(values), "};"]
    lines += ["", f"#endif /* {macro}_H */", ""]
    return "\n".join(lines)


def render_table(table: GainTable, fmt: str, *, name: str = C_NAME) -> bytes:
    """The table in one of :data:`TABLE_FORMATS` as bytes (text formats UTF-8).

    ``csv`` is byte-identical to :func:`table_csv`; ``name`` is the C identifier prefix
    of format ``c``.

    Raises
    ------
    OptionError
        Unknown format or a ``name`` that is not a C identifier.
    """
    from oga.errors import OptionError

    if fmt == "csv":
        return _csv(list(table.header), [table.data[:, j] for j in range(len(table.header))]).encode()
    if fmt == "json":
        return _table_json(table).encode()
    if fmt == "npz":
        return _table_npz(table)
    if fmt == "c":
        return _table_c(table, name).encode()
    raise OptionError(f"format: unknown table format {fmt!r} (expected one of "
                      f"{', '.join(TABLE_FORMATS)})")


def table_json(result, *, toolpath_sha256: str | None = None,
               setpoints_source: dict | None = None) -> str:
    """The gain table as JSON: ``{"meta": {...}, "columns": {name: [value per sample]}}``.

    Floats round-trip float64 exactly. Refuses a failed result (OptimizeError).
    """
    return _table_json(gain_table(result, toolpath_sha256=toolpath_sha256,
                                  setpoints_source=setpoints_source))


def table_npz(result, *, toolpath_sha256: str | None = None,
              setpoints_source: dict | None = None) -> bytes:
    """The gain table as a compressed NumPy ``.npz``: one float64 array per column and
    ``meta`` (a JSON string). Refuses a failed result (OptimizeError)."""
    return _table_npz(gain_table(result, toolpath_sha256=toolpath_sha256,
                                 setpoints_source=setpoints_source))


def table_c_header(result, name: str = C_NAME, *, toolpath_sha256: str | None = None) -> str:
    """The gain table as a C header for controller firmware.

    Macros ``<NAME>_SAMPLES``, ``_SAMPLE_PERIOD_S``, ``_AXES``, ``_AXIS_ORDER`` and the
    toolpath/setpoints/machine hashes; ``static const double`` arrays ``<name>_t_s[N]``,
    ``<name>_s_m[N]`` and, per axis in axis order, ``<name>_pos_m[N][3]``,
    ``_vel_m_s[N][3]``, ``_kp_m_min_per_mm[N][3]``, ``_kf[N][3]`` (exact float64 values).

    Raises
    ------
    OptimizeError
        The schedule failed verification.
    OptionError
        ``name`` is not a C identifier.
    """
    return _table_c(gain_table(result, toolpath_sha256=toolpath_sha256), name)
