"""Paper mode's MSE(CE) ratio as a function of what limits it: candidate fractions, horizon, plant.

Run:  python bench/bench_paper.py [--quick]

Paper mode as published (Z only, Kp only, from Kp 1.6 / Kf 0.9, Kp in [1.0, 2.7],
Np 50, lambda 0.01, candidate fractions a1 0.01 / a2 0.05) on the XZ toolpaths of
tests/data, then one thing changed at a time:

- the horizon Np (100);
- the candidate fractions (a1 = a2 / 5) of the stability interval, each candidate
  then held inside the kinematic bound (:mod:`oga.search.paper`);
- the machine's velocity-loop bandwidth (ucp710 assumes 25 Hz: kv = m 2 pi f) and its
  Coulomb/Stribeck friction (off);
- for reference, full mode with the same freedom (Z's Kp only, no anchor): what the
  plant allows a schedule to reach.

Each row: the ratio of the verified replay's MSE(CE) to the fixed pair's, the largest
Z command jerk over its limit (eq. 2), the fixed pair's RMS contour error, and the
time of the whole ``optimize`` call (search, replays, and the stability range, which
dominates the first call on a new machine). The replaced fractions are a measurement
only: paper mode keeps the published ones. A benchmark prints figures; it asserts
nothing. --quick: reference_xz only.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from contextlib import contextmanager
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

from feedplan.plan import plan  # noqa: E402
from feedplan.read import load_toolpath  # noqa: E402
from oga import defaults  # noqa: E402
from oga.model.machine import load_machine, machine_from_dict  # noqa: E402
from oga.optimize import optimize  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
PAPER = dict(mode="paper", baseline="1.6,0.9", adjust="z", gains="kp", kp_range="1.0,2.7",
             nominal=True,
             np=50, lam=0.01)


@contextmanager
def fractions(a1: float, a2: float):
    """Candidate fractions replaced for one measurement, then restored."""
    saved = defaults.A1, defaults.A2
    defaults.A1, defaults.A2 = a1, a2
    try:
        yield
    finally:
        defaults.A1, defaults.A2 = saved


def variant(machine, bandwidth_hz: float | None = None, friction: bool = True):
    """The machine with every cascade axis's velocity loop at ``bandwidth_hz`` and/or no
    Coulomb/Stribeck friction."""
    data = machine.model_dump(mode="json", exclude_none=True)
    for axis in data["axes"].values():
        cas = axis["cascade"]
        if bandwidth_hz is not None:
            cas["kv_n_s_m"] = cas["mass_kg"] * 2.0 * math.pi * bandwidth_hz
        if not friction:
            cas["coulomb_n"] = cas["static_n"] = 0.0
    return machine_from_dict(data, where=f"{machine.name} variant")


def row(label: str, sp, machine, options: dict) -> None:
    t0 = time.perf_counter()
    r = optimize(sp, machine, options)
    call_s = time.perf_counter() - t0
    print(f"  {label:52s} {r.search_ratio_mse:7.3f} {r.searched.command_ratio[2][2]:9.2f} "
          f"{r.baseline.metrics.rms_m * 1e6:8.2f} {call_s:7.2f} s  {r.searched.status}",
          flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reference_xz only")
    args = ap.parse_args()
    machine = load_machine("ucp710")
    names = ["reference_xz"] if args.quick else ["reference_xz", "short_xz", "freeform_xz"]
    machines = {
        "ucp710 (25 Hz velocity loop)": machine,
        "velocity loop 35 Hz": variant(machine, 35.0),
        "velocity loop 50 Hz": variant(machine, 50.0),
        "velocity loop 100 Hz": variant(machine, 100.0),
        "no Coulomb/Stribeck friction": variant(machine, friction=False),
    }
    for name in names:
        sp = plan(load_toolpath(DATA / f"{name}.ngc"), machine.planning_limits())
        optimize(sp, machine, {**PAPER, "np": 5})  # compile / load caches
        print(f"\n{name} ({len(sp)} samples)\n  {'setting':52s} {'ratio':>7s} "
              f"{'z jerk/J':>9s} {'rms0 um':>8s} {'time':>9s}  status")
        row("published (Np 50, a1 0.01, a2 0.05)", sp, machine, PAPER)
        row("Np 100", sp, machine, {**PAPER, "np": 100})
        for a2 in (0.1, 0.2, 0.5, 1.0):
            with fractions(a2 / 5, a2):
                row(f"a1 {a2 / 5:g}, a2 {a2:g}", sp, machine, PAPER)
        for label, mach in list(machines.items())[1:]:
            row(label, sp, mach, PAPER)
            row(f"{label}, Np 100", sp, mach, {**PAPER, "np": 100})
        for label, mach in machines.items():
            if "Hz" in label:
                row(f"full mode, Z Kp only, {label}", sp, mach,
                    {**PAPER, "mode": "full", "anchor": 0.0})


if __name__ == "__main__":
    main()
