"""feedplan: read a toolpath, fit it, plan jerk-limited setpoints.

Pipeline: text (G-code / CSV / JSON) -> :class:`Path` (lines, arcs; metres)
-> :func:`plan` -> :class:`Setpoints` (uniform samples, per-axis p/v/a/j).
"""

from feedplan.path import Arc, Line, Path
from feedplan.setpoints import AXES, Setpoints

__all__ = ["AXES", "Arc", "Line", "Path", "Setpoints"]
