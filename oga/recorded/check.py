"""Checks of recorded setpoints against a machine: its period and its axis limits."""

from __future__ import annotations

import numpy as np

from feedplan.setpoints import AXES
from oga.defaults import SETPOINTS_LIMIT_SLACK, TRACE_DT_REL_TOL
from oga.identify.trace import TraceError
from oga.model.machine import Machine

__all__ = ["SetpointsError", "check_period", "check_limits"]


class SetpointsError(TraceError):
    """Recorded setpoints that cannot be optimised on (the column and the row named)."""


def check_period(dt_s: float, te_s: float, column: str) -> None:
    """SetpointsError unless the file's period ``dt_s`` (s) is the position loop's ``te_s``."""
    if abs(dt_s - te_s) > TRACE_DT_REL_TOL * te_s:
        raise SetpointsError(
            f"column {column!r}: the setpoints are {dt_s:g} s apart, the position loop runs "
            f"every {te_s:g} s (the machine's Te): record them at Te")


def check_limits(pos_m: np.ndarray, dt_s: float, machine: Machine, columns: dict[str, str],
                 rows: np.ndarray) -> None:
    """SetpointsError at the first row where an axis's setpoints move faster, accelerate or
    jerk more than the machine's axis limits allow (finite differences of the positions,
    as the planner's own check; relative slack :data:`oga.defaults.SETPOINTS_LIMIT_SLACK`).

    Parameters
    ----------
    pos_m : ndarray, shape (N, 3)
        Position setpoints, m (columns x, y, z).
    dt_s : float
        Their period, s.
    machine : Machine
        Supplies the limits; an axis that moves must be one of its axes.
    columns : dict of str to str
        Axis -> name of the file's column it came from (for messages).
    rows : ndarray of int, shape (N,)
        File line of each sample (for messages).
    """
    lim = machine.axis_limits()
    for k, a in enumerate(AXES):
        x = pos_m[:, k]
        if np.ptp(x) <= 1e-9:
            continue
        if a not in machine.axes:
            raise SetpointsError(f"column {columns[a]!r}: axis {a} moves, machine "
                                 f"{machine.name!r} has no axis {a}")
        checks = (("velocity", 1, "m/s", lim.vmax_m_s[k], "vmax_m_s"),
                  ("acceleration", 2, "m/s^2", lim.amax_m_s2[k], "amax_m_s2"),
                  ("jerk", 3, "m/s^3", lim.jmax_m_s3[k], "jmax_m_s3"))
        for what, order, unit, limit, field in checks:
            d = np.abs(np.diff(x, n=order)) / dt_s**order
            over = np.flatnonzero(d > limit * (1.0 + SETPOINTS_LIMIT_SLACK))
            if over.size:
                j = int(over[0])
                hint = (" (LinuxCNC 2.9's planner changes the acceleration within one servo "
                        "period: the machine file's jerk limit must admit it)"
                        if order == 3 else "")
                raise SetpointsError(
                    f"column {columns[a]!r}, row {int(rows[j + order])}: setpoint {what} "
                    f"{d[j]:.4g} {unit} exceeds axis {a}'s limit {field} = {limit:g} of "
                    f"machine {machine.name!r}{hint}")

