"""LinuxCNC: a verified gain table as files LinuxCNC runs.

- :mod:`oga.export.linuxcnc.export`: a ``streamer`` file and HAL files for the ``pid`` loops (a bench
  run, or a machine whose joints the stream drives);
- :mod:`oga.export.linuxcnc.motion`: production: LinuxCNC's motion controller runs the program, the
  table drives only ``Pgain`` and ``FF1`` while the motion is the recorded one;
- :mod:`oga.export.linuxcnc.record`: a program run headless in the user's configuration and its
  setpoints recorded (``oga lcnc-record``), in a :mod:`oga.export.linuxcnc.session`;
- :mod:`oga.export.linuxcnc.halfile`: writing HAL commands (``.hal`` or Tcl HALFILEs).

``docs/tutorials/linuxcnc.md`` says how a machine or a bench runs them.
"""

from __future__ import annotations

from oga.export.linuxcnc.export import (
    BENCH_HAL,
    STREAM,
    TABLE_HAL,
    UNIT_M,
    LinuxcncExport,
    baseline_gains,
    export_table,
    linuxcnc_export,
    replay_feedback,
)
from oga.export.linuxcnc.halfile import HalCommands
from oga.export.linuxcnc.motion import FEEDER, MOTION_TCL, motion_export
from oga.export.linuxcnc.record import Recording, record_program
from oga.export.linuxcnc.session import LinuxcncError, run_session

__all__ = ["BENCH_HAL", "FEEDER", "MOTION_TCL", "STREAM", "TABLE_HAL", "UNIT_M", "HalCommands",
           "LinuxcncError", "LinuxcncExport", "Recording", "baseline_gains", "export_table",
           "linuxcnc_export", "motion_export", "record_program", "replay_feedback",
           "run_session"]
