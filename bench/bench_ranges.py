"""Gain-ranges speed: the full Kp x Kf grid on reference_xz (target: under 10 s), and the
best-fixed-gains stage of ``oga optimize`` before (``gain_ranges(..).best_fixed``) and
after (:func:`oga.search.ranges.best_fixed_gains`) per team toolpath, with its real-time factor
(toolpath duration over compute time; the whole optimize targets 20x).

Run: python bench/bench_ranges.py   (prints figures; no assertion)
"""

from __future__ import annotations

import time
from pathlib import Path

from feedplan.plan import plan
from feedplan.read import load_toolpath
from oga.defaults import TOL_M
from oga.model.machine import load_machine
from oga.search.ranges import best_fixed_gains, gain_ranges, kinematic_range
from oga.model.stability import stable_range

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
TOOLPATH = DATA / "reference_xz.ngc"
BEST_FIXED_TOOLPATHS = ("reference_xz", "circle_r50_f3000", "helix_r20", "freeform_xz")
TARGET_S = 10.0


def _best_of(fn, repeat=3):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    machine = load_machine("ucp710")
    sp = plan(load_toolpath(TOOLPATH), machine.axis_limits(), tol_m=TOL_M, dt=machine.te)
    t0 = time.perf_counter()
    gain_ranges(sp, machine)  # compile or load the caches
    print(f"first call (compile or cache load included): {time.perf_counter() - t0:.2f} s")
    t_all, r = _best_of(lambda: gain_ranges(sp, machine))
    t_stab, _ = _best_of(lambda: [stable_range(machine, a) for a in r.axes])
    configs = sum(k.feasible.size for k in r.kinematic.values())
    kx = r.kinematic["x"]
    t_kin, _ = _best_of(lambda: kinematic_range(sp, machine, "x", kx.kp_grid, kx.kf_grid))
    n_x = kx.feasible.size
    print(f"reference_xz: {len(sp)} samples, axes {', '.join(r.axes)}, "
          f"{len(r.kp_grid)} Kp x {len(r.kf_grid)} Kf")
    print(f"gain_ranges (full):           {t_all:6.2f} s  "
          f"({t_all / TARGET_S:.2f} of the 10 s target)")
    print(f"  stable ranges ({len(r.axes)} axes):     {t_stab:6.2f} s")
    print(f"  sweep ({configs} axis runs + {r.mse_ce_m2.size} CE series): {t_all - t_stab:6.2f} s")
    print(f"kinematic_range x alone ({n_x} runs, given grids): {t_kin:6.2f} s, "
          f"{n_x * len(sp) / t_kin / 1e6:.2f} M axis-samples/s")
    b = r.best_fixed
    if b is not None:
        print(f"best fixed: Kp {b.kp[r.axes[0]]} Kf {b.kf[r.axes[0]]}, "
              f"MSE(CE) {b.mse_ce_m2 * 1e12:.1f} um^2")

    print("\nbest fixed gains (the optimize stage): before = gain_ranges(..).best_fixed, "
          "after = best_fixed_gains; RT = toolpath duration / time")
    for name in BEST_FIXED_TOOLPATHS:
        sp = plan(load_toolpath(DATA / f"{name}.ngc"), machine.axis_limits(), tol_m=TOL_M,
                  dt=machine.te)
        best_fixed_gains(sp, machine)  # compile or load the caches
        t_old, old = _best_of(lambda: gain_ranges(sp, machine).best_fixed)
        t_new, new = _best_of(lambda: best_fixed_gains(sp, machine), repeat=5)
        same = (new.kp, new.kf, new.mse_ce_m2) == (old.kp, old.kf, old.mse_ce_m2)
        dur = len(sp) * machine.te
        print(f"  {name:18s} {dur:5.2f} s of motion: before {t_old:6.3f} s ({dur / t_old:5.1f}x RT)"
              f"  after {t_new:6.3f} s ({dur / t_new:5.1f}x RT)  speed-up {t_old / t_new:4.1f}"
              f"  same result: {same}")


if __name__ == "__main__":
    main()
