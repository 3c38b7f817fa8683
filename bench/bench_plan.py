"""Benchmark of the feed planner on the shared toolpaths (a benchmark, not a test).

Run: ``python bench/bench_plan.py`` from the repository root. Prints one row per
toolpath: samples, cycle time, its lower bound, their ratio, the largest deviation
from the programmed geometry, the worst finite-difference limit ratio per axis
(velocity / acceleration / jerk, x y z) and the planning time (numba compiled
before timing).

The bound
---------
A lower bound of the cycle time that a planner honouring the limits could reach
if curvature cost nothing::

    bound = sum over rapids of the time-optimal rest-to-rest time along the line
          + sum over feed moves of length / feed
          + extra(start) / 2 + extra(end) / 2

``extra(d)`` is what a 1-D time-optimal jerk-limited rest-to-rest profile
(computed by ruckig, from rest to rest over 1 m, cruise speed the feed) takes
beyond ``1 m / feed``, with the acceleration and jerk limits of the axes projected
on the feed path's start (or end) direction ``d``: ``min_i A_i / |d_i|``,
``min_i J_i / |d_i|``. Half of it is the price of starting, half of stopping.
Rapids use the same construction with every limit projected on their line. The
issue's targets are ``cycle / bound <= 1.10`` on reference_xz and ``<= 1.05`` on
circle_r50_f3000.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path as FilePath

import numpy as np
from ruckig import InputParameter, Ruckig, Trajectory

from feedplan.check import check_setpoints
from feedplan.gcode import parse_gcode
from feedplan.limits import AxisLimits
from feedplan.path import Line, Path
from feedplan.plan import plan
from oga.machine import load_machine

ROOT = FilePath(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
MACHINE = load_machine("ucp710")


def rest_to_rest_s(length_m: float, v: float, a: float, j: float) -> float:
    """Duration of the 1-D time-optimal jerk-limited rest-to-rest move (ruckig)."""
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [length_m]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v], [a], [j]
    traj = Trajectory(1)
    Ruckig(1).calculate(inp, traj)
    return traj.duration


def _projected(d: np.ndarray, lim: np.ndarray) -> float:
    m = np.abs(d) > 1e-12
    return float(np.min(lim[m] / np.abs(d[m])))


def _direction(seg, at_end: bool) -> np.ndarray:
    p0, p1 = (seg.point(0.999), seg.point(1.0)) if at_end else (seg.point(0.0), seg.point(0.001))
    d = np.asarray(p1 - p0, dtype=float)
    return d / np.linalg.norm(d)


def bound_s(path: Path, limits: AxisLimits) -> float:
    """The cycle-time bound defined in the module docstring, seconds."""
    total = 0.0
    feed = [s for s in path.segments if not s.rapid and s.length > 0]
    for s in path.segments:
        if s.rapid and s.length > 0:
            d = _direction(s, False)
            lims = (limits.vmax_m_s, limits.amax_m_s2, limits.jmax_m_s3)
            total += rest_to_rest_s(s.length, *(_projected(d, x) for x in lims))
    if not feed:
        return total
    total += sum(s.length / s.feed_m_s for s in feed)
    for seg, at_end in ((feed[0], False), (feed[-1], True)):
        d, f = _direction(seg, at_end), seg.feed_m_s
        a, j = _projected(d, limits.amax_m_s2), _projected(d, limits.jmax_m_s3)
        extra = rest_to_rest_s(1.0, f, a, j) - 1.0 / f
        total += extra / 2
    return total


def synthetic_program(n: int = 20000) -> str:
    """An XZ freeform finishing pass of ``n`` G1 segments, 0.05 mm in X, rounded to 1 um."""
    x = np.arange(n + 1) * 0.05
    z = 2.0 * np.sin(2 * np.pi * x / 40.0) + 0.8 * np.sin(2 * np.pi * x / 9.0 + 1.0)
    lines = [f"(synthetic freeform, {n} segments)", "G21 G90 G18 G94", f"G0 X0.000 Z{z[0]:.3f}"]
    lines.append("G1 F3000")
    lines += [f"G1 X{a:.3f} Z{b:.3f}" for a, b in zip(x[1:], z[1:])]
    lines.append("M2")
    return "\n".join(lines) + "\n"


def table(programs: list[tuple[str, str]], limits: AxisLimits, check_limits: AxisLimits) -> None:
    """Plan each program with ``limits``, check against ``check_limits``, print one row each."""
    head = (
        f"{'toolpath':18s} {'samples':>7s} {'cycle_s':>8s} {'bound_s':>8s} {'ratio':>6s} "
        f"{'dev_um':>7s}  {'v ratio x/y/z':>17s}  {'a ratio x/y/z':>17s}  "
        f"{'j ratio x/y/z':>17s}  {'plan_s':>6s} ok"
    )
    print(head)
    print("-" * len(head))
    for name, text in programs:
        path = parse_gcode(text, source=name)
        t0 = time.perf_counter()
        sp = plan(path, limits)
        dt = time.perf_counter() - t0
        chk = check_setpoints(sp, path, check_limits)
        b = bound_s(path, limits)
        ratios = (chk.vel_ratio, chk.acc_ratio, chk.jerk_ratio)
        v, a, j = ("/".join(f"{x:.3f}" for x in r) for r in ratios)
        print(
            f"{name:18s} {len(sp):7d} {sp.duration:8.3f} {b:8.3f} {sp.duration / b:6.3f} "
            f"{chk.max_deviation_m * 1e6:7.2f}  {v:>17s}  {a:>17s}  {j:>17s}  {dt:6.2f} {chk.ok}"
        )
        for msg in chk.violations:
            print("    violation:", msg)


def main() -> int:
    names = ("reference_xz", "circle_r50_f3000", "helix_r20", "freeform_xz")
    programs = [(name, (DATA / f"{name}.ngc").read_text()) for name in names]
    programs += [(f"synthetic_{n}", synthetic_program(n)) for n in (2000, 20000, 100000)]
    full, planning = MACHINE.axis_limits(), MACHINE.planning_limits()
    plan(parse_gcode(programs[0][1]), full)  # compile numba kernels before timing
    print("ucp710 axis limits (bound and ratios at these limits):")
    table(programs, full, full)
    print()
    print(
        "ucp710 planning limits as `oga plan` uses them (acceleration x "
        f"{MACHINE.planner.accel_fraction}, jerk x {MACHINE.planner.jerk_fraction}; "
        "bound at the planning limits, ratios to the axis limits):"
    )
    table(programs, planning, full)
    print()
    straight(planning)
    return 0


def straight(limits: AxisLimits) -> None:
    """Lone feed lines (planned by ruckig) against ruckig's rest-to-rest time, one row each."""
    print("lone feed lines at the planning limits: planned vs ruckig (ratio; +3 samples of the "
          "sample grid and the 1e-3 margin)")
    for axis, length_mm, feed in ((0, 0.04, 3000), (0, 1, 10), (0, 1, 1000), (0, 11, 30000),
                                  (0, 11, 1e8), (2, 200, 30000)):
        end = np.zeros(3)
        end[axis] = length_mm * 1e-3
        path = Path(np.zeros(3), (Line(np.zeros(3), end, feed / 60e3, line=1),))
        sp = plan(path, limits)
        v = min(feed / 60e3, float(limits.vmax_m_s[axis]))
        best = rest_to_rest_s(length_mm * 1e-3, v, float(limits.amax_m_s2[axis]),
                              float(limits.jmax_m_s3[axis]))
        print(f"  {'xyz'[axis]} {length_mm:7.2f} mm at F{feed:<10.6g} {sp.duration:8.3f} s "
              f"{best:8.3f} s  {sp.duration / best:6.3f}")


if __name__ == "__main__":
    sys.exit(main())
