"""Benchmark: how much of the axis limits the position loop's velocity command needs above the
setpoints, on the robust plant set (the planner's reserve, ``[planner]`` of a machine).

Run: ``python bench/bench_reserve.py [--only NAME,...] [--plants N] [--shared DIR]`` from the
repository root. A benchmark, not a test: it prints figures and asserts nothing.

The planner plans with shares of the axis acceleration and jerk (``[planner]``
``accel_fraction``, ``jerk_fraction``); the rest is left to the position loop, whose velocity
command ``u = Kp (pd - p) + Kf vd`` must keep paper eq. 2 too (``|u| <= V``, ``|du|/Te <= A``,
``|d2u|/Te^2 <= J`` at every sample). Per program (``bench_plan``'s, planned as ``oga plan``
plans them) this takes the nominal best fixed gains (:func:`oga.search.ranges.best_fixed_gains`, the
baseline every search starts from) and simulates them on every plant of the machine's robust
scenario set (:func:`oga.search.robust.plants.scenario_set`: Monte Carlo draws and corners) and on the
nominal plant. Per plant and moving axis it takes the command's peaks over every sample
(:func:`oga.model.kinematics.command_peaks`) and the setpoints' own peaks (finite differences of the
positions, as the planner checks them), and prints, over the plants:

- ``eq2 a/j``: the largest command acceleration and jerk over the axis limits (<= 1: eq. 2 holds
  with these gains on every plant);
- ``over a/j``: the largest command peak over the setpoints' peak (how much the loop adds);
- ``share a/j``: the largest planner share that keeps eq. 2 on every plant with the same gains,
  the current share over ``eq2``: the setpoints' peaks scale with the share (the loop is
  linear but for friction, which the peaks do not follow), so the command's do too.

The program classes (contours of lines and arcs, fitted CAM freeform, corners and short lines)
are those of the docs page on cycle time; the smallest ``share`` of a class is the reserve that
class needs.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path as FilePath

import numpy as np

sys.path.insert(0, str(FilePath(__file__).resolve().parent))
from bench_plan import MACHINE, ROOT, programs  # noqa: E402

from feedplan.gcode import parse_gcode  # noqa: E402
from feedplan.plan import plan  # noqa: E402
from oga.model.kinematics import command_peaks  # noqa: E402
from oga.search.ranges import best_fixed_gains  # noqa: E402
from oga.search.robust.plants import scenario_set  # noqa: E402
from oga.model.response import simulate  # noqa: E402

#: Program classes (bench_plan's names).
CLASSES = {
    "contour": ("reference_xz", "circle_r50_f3000", "helix_r20", "arcspiral", "lathe_pawn"),
    "freeform": ("freeform_xz", "test_12mmflat", "line-contouring-xz", "micro_2k"),
    "corners": ("cncjs_toolpath", "short_segments_0.001", "plasmatest", "51MeanderAve"),
}
#: Programs measured by default (the longest two, arcspiral and lathe_pawn, by --only).
DEFAULT = ("reference_xz", "circle_r50_f3000", "helix_r20", "freeform_xz", "micro_2k",
           "test_12mmflat", "line-contouring-xz", "cncjs_toolpath", "short_segments_0.001",
           "plasmatest", "51MeanderAve")


def _setpoint_peaks(pos: np.ndarray, dt: float) -> np.ndarray:
    """Largest |a|, |j| per axis of positions (N, 3) at rest before and after: (3, 2)."""
    p = np.concatenate([np.repeat(pos[:1], 3, axis=0), pos, np.repeat(pos[-1:], 3, axis=0)])
    a = np.diff(p, 2, axis=0) / dt**2
    j = np.diff(p, 3, axis=0) / dt**3
    return np.stack([np.abs(a).max(axis=0), np.abs(j).max(axis=0)], axis=1)


def measure(name: str, text: str, machine, n_plants: int) -> dict:
    """Plan one program at ``machine``'s shares, find its nominal best fixed gains, replay them
    on the plant set."""
    c0 = time.process_time()
    sp = plan(parse_gcode(text, source=name), machine.planning_limits())
    best = best_fixed_gains(sp, machine)
    if best is None:
        return dict(name=name, status="no feasible fixed gains", plan_s=sp.duration)
    kp, kf = next(iter(best.kp.values())), next(iter(best.kf.values()))  # equal on every axis
    axes = list(sp.moving_axes)
    full = machine.axis_limits()
    lim = np.stack([full.amax_m_s2, full.jmax_m_s3], axis=1)  # (3, 2)
    sp_pk = _setpoint_peaks(sp.pos, sp.dt)
    plants = scenario_set(machine, n=n_plants).plants + (machine,)
    eq2 = np.zeros((len(plants), 2))
    check = np.ones(len(sp), dtype=bool)
    for q, plant in enumerate(plants):
        sim = simulate(sp, plant, kp, kf)
        for k in axes:
            _, a_pk, j_pk = command_peaks(np.ascontiguousarray(sim.u[:, k]), check, sp.dt)
            eq2[q] = np.maximum(eq2[q], np.array([a_pk, j_pk]) / lim[k])
    return dict(name=name, status="ok", plan_s=sp.duration, kp=kp, kf=kf,
                rms_um=math.sqrt(best.mse_ce_m2) * 1e6, plants=len(plants),
                eq2=eq2.max(axis=0), eq2_nominal=eq2[-1], held=int(np.sum(eq2.max(axis=1) <= 1.0)),
                sp=np.max(sp_pk[axes] / lim[axes], axis=0), cpu=time.process_time() - c0)


def with_shares(machine, accel: float, jerk: float):
    """``machine`` with ``[planner]`` shares ``accel`` and ``jerk``."""
    return machine.model_copy(update={"planner": machine.planner.model_copy(
        update={"accel_fraction": accel, "jerk_fraction": jerk})})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="comma-separated program names (bench_plan's)")
    ap.add_argument("--plants", type=int, default=64, help="Monte Carlo plants (plus corners)")
    ap.add_argument("--shares", default="0.9:0.75,1:0.9,1:1",
                    help="acceleration:jerk shares to plan with, comma-separated")
    ap.add_argument("--shared", type=FilePath, default=ROOT.parent / "shared",
                    help="the shared folder holding toolpaths/external (default ../shared)")
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else set(DEFAULT)
    shares = [tuple(float(x) for x in pair.split(":")) for pair in args.shares.split(",")]
    print(f"{MACHINE.name}: nominal best fixed gains at each [planner] share, replayed on the "
          f"robust set ({args.plants} Monte Carlo plants, corners, nominal); load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    head = (f"{'program':22s} {'class':>8s} {'a:j share':>9s} {'plan_s':>8s} {'Kp':>4s} "
            f"{'Kf':>4s} {'ce_rms_um':>9s} {'sp a/j':>11s} {'nominal a/j':>11s} "
            f"{'worst a/j':>11s} {'held':>7s} {'cpu_s':>6s}")
    print(head)
    print("-" * len(head))
    rows = []
    f2 = lambda x: f"{x[0]:.3f}/{x[1]:.3f}"  # noqa: E731
    for name, text in programs(args.shared, only):
        cls = next((c for c, ns in CLASSES.items() if name in ns), "-")
        for a_sh, j_sh in shares:
            r = measure(name, text, with_shares(MACHINE, a_sh, j_sh), args.plants)
            r["cls"], r["shares"] = cls, (a_sh, j_sh)
            rows.append(r)
            lab = f"{a_sh:g}:{j_sh:g}"
            if r["status"] != "ok":
                print(f"{name:22s} {cls:>8s} {lab:>9s} {r['plan_s']:8.3f} {r['status']}")
                continue
            print(f"{name:22s} {cls:>8s} {lab:>9s} {r['plan_s']:8.3f} {r['kp']:4.1f} "
                  f"{r['kf']:4.1f} {r['rms_um']:9.3f} {f2(r['sp']):>11s} "
                  f"{f2(r['eq2_nominal']):>11s} {f2(r['eq2']):>11s} "
                  f"{r['held']:3d}/{r['plants']:<3d} {r['cpu']:6.1f}", flush=True)
    print("(plan_s: cycle time; Kp, Kf, ce_rms_um: the nominal best fixed gains and their RMS "
          "contour error; sp: the setpoints' peak acceleration / jerk over the full limits; "
          "nominal, worst: the command's on the nominal plant and on the worst plant; held: "
          "plants where these gains keep eq. 2)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
