"""Benchmark of feedplan.lp's banded interior point solver against HiGHS on the planner's LPs.

Run: ``python bench/bench_lp.py [--only NAME,...] [--shared DIR] [--min-nodes N]`` from the
repository root. A benchmark, not a test: it prints figures and asserts nothing.

It plans the programs of ``bench_plan.py`` (``--only``; default the five whose blocks the
speed profile plans: freeform_xz, micro_2k, line-contouring-xz, plasmatest, 51MeanderAve, and
a generated 9 000-segment micro program, one block of about 3 000 grid nodes), records every
linear program :func:`feedplan.profile.solve` hands to :func:`feedplan.lp.banded_lp` with at
least ``--min-nodes`` grid nodes, and solves each again with
:func:`scipy.optimize.linprog` (HiGHS dual simplex, and HiGHS's interior point) on the same
sparse matrix. Per program: LPs, nodes, CPU time of each solver (process time), the largest
relative objective difference and HiGHS's largest constraint violation.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path as FilePath

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

sys.path.insert(0, str(FilePath(__file__).resolve().parent))
import bench_plan as bp  # noqa: E402

import feedplan.profile as prof  # noqa: E402
from feedplan.gcode import parse_gcode  # noqa: E402
from feedplan.lp import banded_lp  # noqa: E402
from feedplan.plan import plan  # noqa: E402

DEFAULT = "freeform_xz,micro_2k,line-contouring-xz,plasmatest,51MeanderAve,micro_9k"


def record(programs, limits) -> list[dict]:
    """Every LP the profile solves while planning ``programs`` ((name, G-code) pairs)."""
    out, orig, name = [], prof.banded_lp, [""]

    def wrap(c, col0, val, b, lo, hi, **k):
        out.append(dict(name=name[0], c=c, col0=col0, val=val, b=b, lo=lo, hi=hi, k=k))
        return orig(c, col0, val, b, lo, hi, **k)

    prof.banded_lp = wrap
    try:
        for name[0], text in programs:
            plan(parse_gcode(text, source=name[0]), limits)
    finally:
        prof.banded_lp = orig
    return out


def compare(lp: dict) -> tuple:
    """(nodes, own s, simplex s, ipm s, objective rel. difference to ipm, HiGHS violation)."""
    c, col0, val, b, lo, hi, k = (lp[f] for f in ("c", "col0", "val", "b", "lo", "hi", "k"))
    n, m, w = c.size, b.size, val.shape[1]
    t0 = time.process_time()
    own = banded_lp(c, col0, val, b, lo, hi, **k)
    t1 = time.process_time()
    A = sp.csr_array((val.ravel(), (np.repeat(np.arange(m), w),
                                    (col0[:, None] + np.arange(w)).ravel())), shape=(m, n))
    act, z0 = k["active"], k["z0"]
    lb, ub = np.where(act, lo, z0), np.where(act, hi, z0)
    bounds = np.column_stack([lb, ub])
    simplex = linprog(c, A_ub=A, b_ub=b, bounds=bounds, method="highs-ds")
    t2 = time.process_time()
    ipm = linprog(c, A_ub=A, b_ub=b, bounds=bounds, method="highs-ipm")
    t3 = time.process_time()
    viol = max(float(np.max(A @ simplex.x - b)), float(np.max(lb - simplex.x)),
               float(np.max(simplex.x - ub)), 0.0)
    rel = abs(c @ own.z - ipm.fun) / abs(ipm.fun)
    return n // 2, t1 - t0, t2 - t1, t3 - t2, rel, viol


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=DEFAULT, help="comma-separated program names")
    ap.add_argument("--shared", type=FilePath, default=bp.ROOT.parent / "shared")
    ap.add_argument("--min-nodes", type=int, default=200)
    args = ap.parse_args(argv)
    only = set(args.only.split(","))
    progs = bp.programs(args.shared, only)
    if "micro_9k" in only:
        progs.append(("micro_9k", bp.synthetic_program(9000)))
    limits = bp.MACHINE.planning_limits()
    plan(parse_gcode((bp.DATA / bp.DATA_PROGRAMS[0]).read_text()), limits)  # compile
    by = defaultdict(list)
    for lp in record(progs, limits):
        if lp["c"].size // 2 >= args.min_nodes:
            by[lp["name"]].append(compare(lp))
    print(f"{'program':20s} {'LPs':>4s} {'nodes':>10s} {'own_s':>7s} {'simplex_s':>9s} "
          f"{'ipm_s':>7s} {'rel_obj':>8s} {'viol':>8s}")
    for name, rows in by.items():
        r = np.array(rows)
        print(f"{name:20s} {len(r):4d} {int(r[:, 0].min()):4d}-{int(r[:, 0].max()):<5d} "
              f"{r[:, 1].sum():7.3f} {r[:, 2].sum():9.3f} {r[:, 3].sum():7.3f} "
              f"{r[:, 4].max():8.1e} {r[:, 5].max():8.1e}")
    print("CPU time (process time) of the solves alone; own: feedplan.lp.banded_lp, simplex/ipm: "
          "scipy.optimize.linprog method highs-ds / highs-ipm; rel_obj: own objective against "
          "highs-ipm's, relative; viol: the simplex solution's largest constraint violation")
    return 0


if __name__ == "__main__":
    sys.exit(main())
