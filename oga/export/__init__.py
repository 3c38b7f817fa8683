"""Export: a verified gain table in the files a controller reads.

- :mod:`oga.export.table`: the table as CSV, JSON, NPZ or a C header (``oga.export.table_csv``);
- :mod:`oga.export.linuxcnc`: the table as files LinuxCNC runs (HAL, streamer, motion).

The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

_TABLE = ("setpoints_csv", "table_columns", "table_csv", "TABLE_FORMATS", "GainTable",
          "gain_table", "table_from_npz", "render_table", "table_json", "table_npz",
          "table_c_header", "C_NAME")
# name -> module that defines it
_EXPORTS = {name: "oga.export.table" for name in _TABLE}
_SUBMODULES = ("table", "linuxcnc")

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS, _SUBMODULES)
