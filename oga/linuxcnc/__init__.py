"""LinuxCNC: a verified gain table as a ``streamer`` file and HAL files for the ``pid`` loops.

See :mod:`oga.linuxcnc.export`; ``docs/tutorials/linuxcnc.md`` says how a machine or a bench
runs them.
"""

from __future__ import annotations

from oga.linuxcnc.export import (
    BENCH_HAL,
    STREAM,
    TABLE_HAL,
    UNIT_M,
    LinuxcncExport,
    export_table,
    linuxcnc_export,
    replay_feedback,
)

__all__ = ["BENCH_HAL", "STREAM", "TABLE_HAL", "UNIT_M", "LinuxcncExport", "export_table",
           "linuxcnc_export", "replay_feedback"]
