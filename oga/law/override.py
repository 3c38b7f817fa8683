"""Feed overrides: a program replanned at a share of its programmed feeds.

A controller's feed override scales the programmed feed of every feed move (LinuxCNC's
``halui.feed-override``, MAX_FEED_OVERRIDE 1.2 by default); rapids keep their own speed.
The interpolator then plans the same path anew, within the same axis limits, so a
program at an override is the plan of its path with every feed move's ``F`` times the
share (:func:`override_path`, then :func:`oga.pipeline.plan_toolpath`), not the plan at
100 % played faster.
"""

from __future__ import annotations

import dataclasses

from feedplan.path import Path
from feedplan.setpoints import Setpoints
from oga import defaults
from oga.errors import OptionError
from oga.model.machine import Machine
from oga.pipeline import plan_toolpath

__all__ = ["override_path", "check_overrides", "plan_override"]


def check_overrides(overrides) -> tuple[float, ...]:
    """The overrides as sorted unique floats, each within
    :data:`oga.defaults.LAW_OVERRIDE_RANGE` and 1.0 among them.

    Raises
    ------
    OptionError
        Naming ``--overrides``.
    """
    try:
        out = tuple(sorted({float(o) for o in overrides}))
    except (TypeError, ValueError):
        raise OptionError(f"--overrides: shares of the feed expected, got {overrides!r}") from None
    lo, hi = defaults.LAW_OVERRIDE_RANGE
    if not out or any(not lo <= o <= hi for o in out):
        raise OptionError(f"--overrides: each must lie within {lo}..{hi} (1.0 = 100 %), "
                          f"got {list(overrides)!r}")
    if 1.0 not in out:
        raise OptionError(f"--overrides: must include 1.0 (the programmed feed), got {list(out)!r}")
    return out


def override_path(path: Path, share: float) -> Path:
    """``path`` with every feed move's programmed feed times ``share`` (rapids unchanged)."""
    segs = tuple(s if s.rapid else dataclasses.replace(s, feed_m_s=s.feed_m_s * share)
                 for s in path.segments)
    return dataclasses.replace(path, segments=segs)


def plan_override(path: Path, machine: Machine, share: float, tol_m: float) -> Setpoints:
    """The setpoints of ``path`` at feed override ``share`` on ``machine``."""
    return plan_toolpath(override_path(path, share), machine, feed_m_s=None, tol_m=tol_m)
