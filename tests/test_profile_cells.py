"""Inside the speed profile's cells and at its ends (:mod:`feedplan.profile`).

The profile imposes the limits at a few points per cell of its grid; these tests sample the
planned motion far more finely than that, or at the planner's 1 ms, and compare the finite
differences with the limits:

- a short line planned rest to rest peaks inside a cell: the jerk's tangent taken at the
  cell's faster end let the jerk through there (1.0053 of the limit, sampled every 0.1 ms,
  on a 1.2 mm line);
- a block ending in a few micrometres of another piece: the last (pure-jerk) rest cell held
  that piece, whose limits were checked nowhere (on line-contouring-xz, a 1.2 mm line ending
  in a 4 um move, blended: 18x the jerk limit at 1 ms).
"""

from __future__ import annotations

import numpy as np
import pytest

from feedplan import profile
from feedplan.fit import blocks_of
from feedplan.gcode import parse_gcode
from feedplan.limits import AxisLimits

LIMITS = AxisLimits(vmax_m_s=np.array([0.25, 0.2, 0.15]),
                    amax_m_s2=np.array([2.0, 1.5, 1.0]),
                    jmax_m_s3=np.array([40.0, 30.0, 20.0]))
FEED = 0.2  # m/s


def _solve(text: str, tol_m: float = 2e-5):
    (block,) = blocks_of(parse_gcode(text, source="cells"), tol_m)
    curve = block.curve
    return curve, profile.solve(curve, lambda u: np.full(np.shape(u), FEED), LIMITS)


def _ratio(curve, prof, dt: float, order: int) -> float:
    """Largest |difference of ``order``| / dt^order over the axis limits of that derivative
    (2: acceleration, 3: jerk), sampled every ``dt``."""
    pos = curve.evaluate(profile.sample(prof, dt), order=2)[0]
    diff = np.diff(pos, order, axis=0) / dt**order
    return float(np.max(np.abs(diff) / (LIMITS.amax_m_s2, LIMITS.jmax_m_s3)[order - 2]))


@pytest.mark.parametrize("length_mm", [1.2, 0.6, 2.5])
def test_a_short_line_keeps_the_jerk_inside_its_cells(length_mm):
    curve, prof = _solve(f"G21 G90 G94\nG0 X0 Y0 Z0\nG1 X{length_mm} F12000\nM2\n")
    assert prof.status == "optimal" and np.isfinite(prof.duration)
    # every 0.1 ms: the differences average the jerk over 0.3 ms, a cell lasts 5-30 ms
    assert _ratio(curve, prof, 1e-4, 3) <= profile.JERK_SHARE * (1 + 1e-3)


def test_a_piece_just_before_the_stop_keeps_the_acceleration():
    # a line into a tangent half circle of 5 um radius (16 um long) at its end
    text = "G21 G90 G94 G64\nG0 X0 Y0 Z0\nG1 X1.2 F12000\nG3 X1.2 Y0.01 I0 J0.005\nM2\n"
    curve, prof = _solve(text)
    assert len(curve.u0) == 3 and curve.u0[-1] - curve.u0[-2] < profile.REST_M
    assert prof.status == "optimal" and np.isfinite(prof.duration)
    # the last cell (pure jerk from rest) lies within the last piece
    assert prof.u[-2] >= curve.u0[-2] - 1e-12
    # the half circle's centripetal acceleration (the tangent jump of curvature there is the
    # planner's to average: spread_cap), sampled every 0.1 ms
    assert _ratio(curve, prof, 1e-4, 2) <= 1.0
