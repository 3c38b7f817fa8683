"""Joints inside feed blocks blended G2 (:func:`feedplan.fit._costly_joint`): a line into a
tangent corner arc (a curvature jump), and a CAM's micrometre jitter move between two
chords (a kink inside a short run of micro-segments).

Independent references: the blended curve's curvature from finite differences of its
positions (no step where the pieces meet; the unblended curve's steps by ``1/R``), the exact
distance of its points to the programmed line and arc (point to segment and to arc, written
here), and the same program under G61 (joints kept, passed as the planner averages them):
the blended plan is faster, and the unblended one passes its joints no faster than the
analytic bound of a jump rounded by an average within the tolerance (``v^2 = J^(2/3)
(24 tol)^(1/3) / |d kappa|``: the average over ``T`` ramps the step ``v^2 d kappa`` at
``v^2 d kappa / T <= J`` and rounds the curve by ``v^2 kappa T^2 / 24 <= tol``).
"""

from __future__ import annotations

import math

import numpy as np

from feedplan.fit import Blending, blocks_of
from feedplan.gcode import parse_gcode
from feedplan.limits import AxisLimits
from feedplan.path import Arc, Line
from feedplan.plan import plan

#: ucp710's planning limits ([planner] shares 0.9 of A, 0.75 of J).
LIMITS = AxisLimits(vmax_m_s=np.array([0.5, 0.5, 0.5]), amax_m_s2=np.array([2.25, 2.25, 1.89]),
                    jmax_m_s3=np.array([7.5, 7.5, 75.0]))
TOL_M = 2e-5
L1, R, L2 = 10e-3, 0.75e-3, 8e-3
FEED = 0.1  # m/s: the jump's bound (about 15 mm/s) binds
LINE_ARC = (f"G21 G90 G17 {{mode}}\nG0 X0 Y0\nG1 X{L1 * 1e3:g} F{FEED * 60e3:g}\n"
            f"G3 X{(L1 + R) * 1e3:g} Y{R * 1e3:g} R{R * 1e3:g}\nG1 Y{(R + L2) * 1e3:g}\nM2\n")
#: Two chords of 0.4 and 0.7 mm turning 0.5 rad, a 5 um move turning 0.8 rad between them
#: (line-contouring-xz's CAM writes such jitter between its chords).
JITTER = ("G21 G90 G17 G64 P0.02\nG0 X0 Y0\nG1 X4 F3000\nX4.4\n"
          "X{x:.6f} Y{y:.6f}\nX{x2:.6f} Y{y2:.6f}\nX{x3:.6f} Y{y3:.6f}\nM2\n")


def _jitter() -> str:
    x, y = 4.4 + 0.005 * math.cos(0.8), 0.005 * math.sin(0.8)
    x2, y2 = x + 0.7 * math.cos(0.5), y + 0.7 * math.sin(0.5)
    return JITTER.format(x=x, y=y, x2=x2, y2=y2, x3=x2 + 4 * math.cos(0.5),
                         y3=y2 + 4 * math.sin(0.5))


def _feed_block(text: str):
    path = parse_gcode(text)
    (block,) = [b for b in blocks_of(path, TOL_M / 2, Blending(TOL_M / 2, LIMITS)) if not b.rapid]
    return path, block


def _fd_curvature_steps(block, h: float = 2e-6) -> float:
    """Largest change of the finite-difference d2r/du2 between neighbouring points h apart
    (1/m): ``h |d3r/du3|`` on a G2 curve, the jump itself where the curvature steps."""
    u = np.arange(0.0, block.curve.length, h)
    p = block.curve.evaluate(u, order=2)[0]
    d2 = (p[2:] - 2.0 * p[1:-1] + p[:-2]) / (h * h)
    return float(np.max(np.linalg.norm(np.diff(d2, axis=0), axis=1)))


def _distance(pts: np.ndarray, seg) -> np.ndarray:
    """Exact distance of points (N, 3) to a programmed line or XY arc (counter-clockwise)."""
    if isinstance(seg, Line):
        d = seg.end - seg.start
        t = np.clip((pts - seg.start) @ d / (d @ d), 0.0, 1.0)
        return np.linalg.norm(pts - seg.start - t[:, None] * d, axis=1)
    rel = pts[:, :2] - seg.center[:2]
    ang = np.mod(np.arctan2(rel[:, 1], rel[:, 0]) - seg.start_angle, 2 * np.pi)
    on = ang <= seg.sweep_rad
    ends = np.minimum(np.linalg.norm(pts - seg.start, axis=1), np.linalg.norm(pts - seg.end, axis=1))
    return np.where(on, np.abs(np.linalg.norm(rel, axis=1) - seg.radius), ends)


def test_line_arc_joints_blended_g2_within_the_tolerance():
    path, block = _feed_block(LINE_ARC.format(mode=f"G64 P{TOL_M * 1e3:g}"))
    # the joints are gone: the curvature's finite differences move by h |d3r/du3| at most
    # (measured 10.4 1/m per 2 um on the blends), where the unblended curve steps by 1/R
    assert _fd_curvature_steps(block) < 0.02 / R
    _, kept = _feed_block(LINE_ARC.format(mode="G61"))
    assert _fd_curvature_steps(kept) > 0.4 / R  # 728: 1333 split over two differences
    pts = block.curve.evaluate(np.linspace(0.0, block.curve.length, 20001), order=2)[0]
    feed = [s for s in path.segments if not s.rapid]
    assert isinstance(feed[1], Arc)
    dev = np.min([_distance(pts, s) for s in feed], axis=0)
    assert dev.max() <= TOL_M / 2, dev.max()


def test_line_arc_blended_plans_faster_than_the_joint():
    blended = plan(parse_gcode(LINE_ARC.format(mode=f"G64 P{TOL_M * 1e3:g}")), LIMITS,
                   tol_m=TOL_M)
    joint = plan(parse_gcode(LINE_ARC.format(mode="G61")), LIMITS, tol_m=TOL_M)
    # the unblended joints: no faster than the analytic bound of a rounded jump
    J = float(np.min(LIMITS.jmax_m_s3[:2]))
    v_bound = math.sqrt(J ** (2 / 3) * (24 * TOL_M) ** (1 / 3) * R)
    near = np.linalg.norm(joint.pos[:, :2] - [L1 + R, R], axis=1) < 1.5 * R
    v = np.linalg.norm(np.diff(joint.pos, axis=0), axis=1) / joint.dt
    assert v[near[1:]].min() <= v_bound  # measured 10.2 mm/s, the bound 15.0
    # measured: 0.723 s blended, 0.788 s with the averaged joints (main: both 0.788)
    assert blended.duration < 0.95 * joint.duration, (blended.duration, joint.duration)


def test_jitter_between_chords_is_dropped_and_the_corner_blended():
    path, block = _feed_block(_jitter())
    # no kink (measured 207 1/m per 2 um; main kept the kinks: 3.9e5, about turn / h)
    assert _fd_curvature_steps(block) < 1e3
    pts = block.curve.evaluate(np.linspace(0.0, block.curve.length, 20001), order=2)[0]
    feed = [s for s in path.segments if not s.rapid]
    dev = np.min([_distance(pts, s) for s in feed], axis=0)
    assert dev.max() <= TOL_M, dev.max()
