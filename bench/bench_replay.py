"""Cost of one replay: simulate, contour error, metrics and a whole verify, per sample.

Run:  python bench/bench_replay.py [--machine ucp710] [--only NAME,..]

Per program (reference_xz and cncjs_toolpath, tests/data) and plant (the nominal machine
and 4 plants of its seeded uncertainty set: two Monte Carlo draws and two corners, the
friction low and high), the CPU time (one thread, after a warm-up; the least of
``bench_optimize.REPEATS`` runs) per sample of :func:`oga.model.response.simulate` (all axes: ns
per sample, and per moving axis and sample), :func:`oga.model.contour.contour_error_of`,
:func:`oga.model.metrics.contour_metrics`, :func:`oga.verify.command_ratios` and a whole
:func:`oga.verify.verify`, with fixed gains of 3 (m/min)/mm and Kf 0.8. The figures of the
replays are the same to the last bit whatever the kernels' speed
(tests/test_replay_speed.py). A benchmark prints figures; it asserts nothing.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread, as the real-time target says

import numpy as np  # noqa: E402

from feedplan.read import load_toolpath  # noqa: E402
from oga.model.contour import contour_error_of  # noqa: E402
from oga.model.machine import load_machine  # noqa: E402
from oga.model.metrics import contour_metrics  # noqa: E402
from oga.pipeline import plan_toolpath  # noqa: E402
from oga.search.robust.plants import scenario_set  # noqa: E402
from oga.model.response import simulate  # noqa: E402
from oga.verify.replay import command_ratios, verify  # noqa: E402

from bench_optimize import timed  # noqa: E402  (the least CPU time of a few runs)

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
PROGRAMS = {"reference_xz": "reference_xz.ngc", "cncjs_toolpath": "cncjs_toolpath.nc"}


def _plants(machine):
    """(label, plant): the nominal machine and 4 plants of its uncertainty set."""
    scen = scenario_set(machine, n=64, seed=17)
    if scen.status != "ok":
        return [("nominal", machine)]
    corners = [i for i, lab in enumerate(scen.labels) if lab.startswith("corner")]
    lo = next(i for i in corners if "friction-lo" in scen.labels[i])
    hi = next(i for i in reversed(corners) if "friction-hi" in scen.labels[i])
    picks = [0, 1, lo, hi]
    return [("nominal", machine)] + [(scen.labels[i], scen.plants[i]) for i in picks]


def programs(description: str, argv: list[str] | None = None):
    """The replay benchmarks' options ``--machine`` (default ucp710) and ``--only NAME,..``:
    the machine, and ``(name, setpoints)`` of each program of :data:`PROGRAMS` chosen,
    planned as ``oga plan`` plans it, one by one as iterated."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--machine", default="ucp710")
    ap.add_argument("--only", default="")
    args = ap.parse_args(argv)
    machine = load_machine(args.machine)
    names = [n for n in PROGRAMS if not args.only or n in args.only.split(",")]
    return machine, ((name, plan_toolpath(load_toolpath(DATA / PROGRAMS[name]), machine,
                                          feed_m_s=None, tol_m=2e-5)) for name in names)


def main() -> None:
    machine, planned = programs(__doc__.splitlines()[0])
    print(f"{'program':16} {'plant':44} {'N':>6} {'sim':>6} {'/axis':>6} {'ce':>6} "
          f"{'metr':>6} {'ratio':>6} {'verify':>7}  (ns/sample, CPU)")
    for name, sp in planned:
        n = len(sp)
        bounds = {a: machine.gains.kp_bounds_m_min_per_mm for a in machine.axes}
        kp, kf = np.full((n, 3), 3.0), np.full((n, 3), 0.8)
        axes = sum(1 for c, a in enumerate("xyz") if a in machine.axes and np.ptp(sp.pos[:, c]))
        for label, plant in _plants(machine):
            verify(sp, plant, kp, kf, bounds)  # warm-up: compile, memos
            sim = simulate(sp, plant, kp, kf)
            ce = contour_error_of(sp, sim.pos)
            t_sim = timed(simulate, sp, plant, kp, kf)[1]
            t_ce = timed(contour_error_of, sp, sim.pos)[1]
            t_met = timed(contour_metrics, ce, sp.pos, sim.pos, ~sp.rapid)[1]
            t_rat = timed(command_ratios, sim.u, sp, plant)[1]
            t_ver = timed(verify, sp, plant, kp, kf, bounds)[1]
            ns = 1e9 / n
            print(f"{name:16} {label[:44]:44} {n:6d} {t_sim * ns:6.0f} "
                  f"{t_sim * ns / max(axes, 1):6.0f} {t_ce * ns:6.0f} {t_met * ns:6.0f} "
                  f"{t_rat * ns:6.1f} {t_ver * ns:7.0f}")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
