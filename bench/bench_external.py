"""Full mode on a folder of real programs: MSE(CE) ratios, contour and following errors, speed.

Usage: python bench/bench_external.py [FOLDER] [--machine NAME] [--options JSON]

FOLDER defaults to ../shared/toolpaths/external relative to the repository root (real
programs from public projects, most GPL: they are read, never copied into the project).
Every figure comes from the verified replay. RT = motion time / CPU time of the whole
``optimize`` (the best-fixed grid included), one thread, after one warm-up run; RT grid
is the same for the best-fixed grid alone, RT search for the rest (search and verification:
the whole minus the grid). j/J base and j/J opt: the largest |second difference| / Te^2 of
the replayed velocity command over EVERY sample (rapids, dwells, start and end included;
the axis at rest before sample 0) as a ratio to the axis's jerk limit, worst axis, for the
baseline and the exported table (computed here with numpy, independently of verify).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path as FilePath

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from feedplan.plan import plan
from feedplan.read import SUFFIXES, load_toolpath
from oga import optimize
from oga.model.machine import load_machine
from oga.search.ranges import best_fixed_gains

ROOT = FilePath(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared" / "toolpaths" / "external"


def jerk_ratio(u: np.ndarray, te: float, jmax: np.ndarray) -> float:
    """Largest ``|u_k - 2 u_{k-1} + u_{k-2}| / (Te^2 Jmax)`` over all samples and axes.

    ``u`` (N, 3) m/s, the axes at rest before sample 0; ``jmax`` (3,) m/s^3 (0: axis absent).
    """
    full = np.vstack([np.zeros((2, 3)), u])
    j = np.abs(np.diff(full, 2, axis=0)).max(axis=0) / te**2
    return float(max(j[k] / jmax[k] if jmax[k] > 0 else (np.inf if j[k] > 0 else 0.0)
                     for k in range(3)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", default=str(DEFAULT))
    ap.add_argument("--machine", default="ucp710")
    ap.add_argument("--options", default='{"nominal": true}',
                    help="optimize options as JSON (default: the nominal search)")
    args = ap.parse_args(argv)
    machine = load_machine(args.machine)
    options = json.loads(args.options)
    files = sorted(f for f in FilePath(args.folder).iterdir() if f.suffix.lower() in SUFFIXES)
    if not files:
        print(f"no toolpath files in {args.folder}")
        return 1
    warm = plan(load_toolpath(ROOT / "examples" / "data" / "reference_xz.ngc"),
                machine.planning_limits())
    optimize(warm, machine, options)  # compile / load caches, stability ranges
    print(f"{'program':32s} {'motion s':>9s} {'ratio':>7s} {'rms0 um':>8s} {'rms um':>7s} "
          f"{'max0 um':>8s} {'max um':>7s} {'lag0 mm':>8s} {'lag mm':>7s} {'RT':>7s} "
          f"{'RT grid':>8s} {'RT search':>10s} {'j/J base':>8s} {'j/J opt':>7s}  status")
    jmax = machine.axis_limits().jmax_m_s3
    for f in files:
        sp = plan(load_toolpath(f), machine.planning_limits())
        t0 = time.process_time()
        r = optimize(sp, machine, options)
        t1 = time.process_time()
        best_fixed_gains(sp, machine)
        t2 = time.process_time()
        b, o = r.baseline.metrics, r.searched.metrics
        print(f"{f.name:32s} {sp.duration:9.1f} {r.search_ratio_mse:7.3f} {b.rms_m * 1e6:8.2f} "
              f"{o.rms_m * 1e6:7.2f} {b.max_abs_m * 1e6:8.1f} {o.max_abs_m * 1e6:7.1f} "
              f"{max(b.track_max_m) * 1e3:8.2f} {max(o.track_max_m) * 1e3:7.2f} "
              f"{sp.duration / (t1 - t0):6.1f}x {sp.duration / (t2 - t1):7.1f}x "
              f"{sp.duration / max(t1 - t0 - (t2 - t1), 1e-9):9.1f}x "
              f"{jerk_ratio(r.baseline.u, sp.dt, jmax):8.3f} "
              f"{jerk_ratio(r.optimized.u, sp.dt, jmax):7.3f}  "
              f"{r.searched.status}{' (kept baseline)' if r.kept_baseline else ''}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
