"""Setpoints another interpolator produced (a recording of the controller that will run the
program), read and checked, to optimise on instead of oga's own plan.

See :mod:`oga.recorded.read` (formats, checks) and :mod:`oga.recorded.lcnc` (LinuxCNC's
``motor-pos-cmd`` read with ``pid``'s law).
"""

from __future__ import annotations

from oga.recorded.check import SetpointsError
from oga.recorded.lcnc import HEADER, LinuxcncPeriods
from oga.recorded.read import (SETPOINT_FORMATS, UNITS, RecordedSetpoints, load_setpoints,
                               read_setpoints, read_setpoints_file)

__all__ = ["HEADER", "SETPOINT_FORMATS", "UNITS", "LinuxcncPeriods", "RecordedSetpoints",
           "SetpointsError", "load_setpoints", "read_setpoints", "read_setpoints_file"]
