"""Speed of the compiled axis kernel (oga.model.simulate): ``run`` and ``window``, one thread.

Two motions, each axis separately, figures after warm-up (compilation excluded):

- ``circle``: the X axis of a circle of radius 50 mm at F3000 (50 mm/s), 100 s: the
  axis velocity sweeps 0..50 mm/s and reverses every pi seconds; on ucp710 (cascade)
  and on mcv-op (ARX velocity loop, the paper's 8th-order Vx; no lifted variant);
- ``reference_xz``: tests/data/reference_xz.ngc planned at F3000 by feedplan (X and Z;
  Z stands still about 40 % of the time, where friction's smooth region near zero
  velocity must be evaluated at every sub-step).

Printed per motion and axis:

- ``run``: samples per second with the lifted step where it is exact (the default)
  and with sub-steps only, and their ratio;
- ``window``: Np = 50 windows called from compiled code as the gain search calls them
  (five candidate gains from the true state at every sample, then one ``step``):
  windows and simulated samples per second, and the real-time factor this allows a
  search with C candidate windows per axis and sample on two such axes (C = 5: one
  gain; C = 25: Kp x Kf, 5 x 5), counting the windows only.

Usage: ``python bench/bench_kernel.py [--repeat R]``.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from numba import njit

from feedplan import load_toolpath
from feedplan.plan import plan
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.model.simulate import axis_params, rest_state, run, step, window

NP = 50
KP = 3.0 * KP_SI_PER_M_MIN_PER_MM
KF = 0.8
#: Candidate gains around Kp (the paper's 1 % and 5 % steps).
CAND_KP = KP * (1.0 + np.array([-0.05, -0.01, 0.0, 0.01, 0.05]))
CAND_KF = np.full(CAND_KP.size, KF)
REFERENCE = Path(__file__).resolve().parents[1] / "tests" / "data" / "reference_xz.ngc"


@njit(cache=True)
def _search_like(state, params, pd, vd, kp_si, kf, out):
    """Every sample k: one window per candidate gain from the state, then one step."""
    for k in range(pd.shape[0] - NP):
        for c in range(kp_si.shape[0]):
            window(state, params, pd, vd, k, NP, kp_si[c], kf[c], out[c])
        step(state, params, pd[k], vd[k], kp_si[0], kf[0])


def _best_of(fn, repeat):
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _bench_axis(label, machine, axis, pd, vd, repeat):
    te = machine.te
    n = pd.size
    p_act, u = np.empty(n), np.empty(n)
    kp_a, kf_a = np.full(n, KP), np.full(n, KF)
    t_run = {}
    variants = (False, True) if machine.axis(axis).kind == "cascade" else (True,)
    for lifted in variants:
        params = axis_params(machine, axis, lifted)

        def do_run():
            run(rest_state(params, pd[0]), params, pd, vd, kp_a, kf_a, p_act, u)

        do_run()  # compile / load the cache
        t_run[lifted] = _best_of(do_run, repeat)
    print(f"{label} {machine.name} {axis}: {n} samples")
    names = {False: "sub-steps only", True: "lifted where exact"}
    if len(variants) == 1:
        names = {True: machine.axis(axis).kind}
    for lifted, t in t_run.items():
        print(f"  run ({names[lifted]:18s}) {n / t / 1e6:6.2f} M samples/s "
              f"({t * 1e9 / n:6.1f} ns per sample, {n * te / t:6.0f}x real time)")
    if len(variants) == 2:
        print(f"  lifted / sub-steps speed ratio: {t_run[False] / t_run[True]:.2f}")

    params = axis_params(machine, axis)
    out = np.empty((CAND_KP.size, NP))
    _search_like(rest_state(params, pd[0]), params, pd[:2 * NP], vd[:2 * NP], CAND_KP,
                 CAND_KF, out)

    def do_windows():
        _search_like(rest_state(params, pd[0]), params, pd, vd, CAND_KP, CAND_KF, out)

    t_win = _best_of(do_windows, repeat)
    count = (n - NP) * CAND_KP.size
    sps = count * NP / t_win
    print(f"  window {count / t_win / 1e3:7.1f} k windows/s (Np={NP}), "
          f"{sps / 1e6:6.2f} M samples/s")
    for c in (5, 25):
        print(f"  a search on two such axes, {c:2d} windows per axis and sample: "
              f"{te / (2 * c * NP / sps):6.1f}x real time (windows only)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    machine = load_machine("ucp710")

    t = np.arange(100_000) * machine.te
    radius, speed = 0.05, 0.05
    pd = radius * np.cos(speed / radius * t)
    vd = -speed * np.sin(speed / radius * t)
    _bench_axis("circle", machine, "x", pd, vd, args.repeat)
    _bench_axis("circle", load_machine("mcv-op"), "x", pd, vd, args.repeat)

    sp = plan(load_toolpath(REFERENCE), machine.axis_limits(), feed_m_s=0.05)
    for c, axis in ((0, "x"), (2, "z")):
        pd = np.ascontiguousarray(sp.pos[:, c])
        vd = np.ascontiguousarray(sp.vel[:, c])
        _bench_axis("reference_xz", machine, axis, pd, vd, args.repeat)


if __name__ == "__main__":
    main()
