"""Benchmark of ``oga compare``: every controller on the paper's circle tests and on reference_xz.

Run:  python bench/bench_compare.py [--quick]

- mcv-op (the CCC/ZPETC paper's ARX plant): the R50 circle (tests/data/circle_r50_f3000.ngc)
  at F1000, F3000, F5000 and F8000, the paper's four feeds;
- ucp710: reference_xz at its programmed feed (``--quick``: this one only).

For each, one row per controller (tuned on the toolpath like the best fixed gains):
RMS and largest |contour error| (um), MSE ratio to the best fixed gains, worst
velocity-command jerk ratio to the limits (paper eq. 2), whether the run stays
within the limits, and the time. ``*`` marks a law no setting of whose tuning grid
keeps the limits (its untuned run is shown). A benchmark prints; it asserts nothing.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

from feedplan.read import load_toolpath  # noqa: E402
from oga.controllers.compare import compare  # noqa: E402
from oga.defaults import TOL_M  # noqa: E402
from oga.model.machine import load_machine  # noqa: E402
from oga.pipeline import plan_toolpath  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"


def table(title: str, cmp) -> None:
    fixed = next(r for r in cmp.rows if r.name == "fixed")
    print(f"\n{title}: {len(cmp.setpoints)} samples")
    print(f"  {'controller':16s} {'RMS um':>8s} {'max um':>8s} {'MSE/fixed':>10s} {'jerk':>8s} "
          f"{'limits':>6s} {'time s':>7s}")
    for r in cmp.rows:
        name = r.name + ("*" if r.status == "untuned" else "")
        if r.status == "failed":
            print(f"  {name:16s} failed: {r.message[:90]}")
            continue
        print(f"  {name:16s} {r.rms_ce_um:8.3f} {r.max_ce_um:8.3f} "
              f"{r.mse_ce_um2 / fixed.mse_ce_um2:10.4f} {r.jerk_ratio:8.2f} "
              f"{'ok' if r.limits_ok else 'NO':>6s} {r.time_s:7.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reference_xz on ucp710 only")
    args = ap.parse_args()
    ucp = load_machine("ucp710")
    cases = [("reference_xz on ucp710", "reference_xz.ngc", ucp, None)]
    if not args.quick:
        mcv = load_machine("mcv-op")
        cases += [(f"R50 circle at F{f} on mcv-op", "circle_r50_f3000.ngc", mcv, f / 60000.0)
                  for f in (1000, 3000, 5000, 8000)]
    for title, name, machine, feed_m_s in cases:
        sp = plan_toolpath(load_toolpath(DATA / name), machine, feed_m_s=feed_m_s, tol_m=TOL_M)
        table(title, compare(sp, machine))


if __name__ == "__main__":
    main()
