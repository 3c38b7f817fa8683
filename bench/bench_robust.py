"""Robustness of the schedules: the certificate of each benchmark program's table.

Run:  python bench/bench_robust.py [--machine ucp710] [--plants 64] [--only NAME,..]

Per program, on the machine (default ``ucp710``: ucp710 with its documented default
uncertainty set): today's schedule searched on the nominal model (``optimize``, ``nominal``:
it ignores the set), its nominal MSE ratio against the best fixed gains, then its certificate
(:func:`oga.robust.certificate.certify_result`): the schedule and those fixed gains
replayed on the seeded Monte Carlo plants of the set plus its 32 corners, the ratio's
median / p90 / worst, the plants where the schedule, the baseline, and the schedule alone
break a check (eq. 2, the following-error limit, the plant's stable Kp range), and the
largest contour error of both over the set. RT = motion time / CPU time (one thread,
after a warm-up) of the nominal ``optimize``, and of the certificate (the set's stable
ranges and the 192 replays: work every robust optimize does besides its search, since it
certifies its table on the same set, so about the bound of its RT). Every program
starts cold, as a fresh ``oga optimize`` process does: the memos of stable ranges and
packed axis parameters are emptied first (a server that sees the set again is faster).
Then the robust search (:func:`oga.robust.search.robust_optimize`: rounds of the
multi-scenario window search on the nominal plant and the plants where the last schedule did
worst): its certificate against the robust baseline, and the price on the nominal plant:
MSE(CE) of the robust table over that of the nominal best fixed gains (the "nominal"
column's denominator; the nominal schedule's own figure is that column), with its RT (the
set's stable ranges, the baseline, every round's search and certificate, the shrink
included: the whole robust optimize). The tail gives the rounds, the shares kept
(``alpha``, 1: no shrink), the baseline, the limit reserve and the plants searched on
besides the nominal one.

Programs: reference_xz, freeform_xz, helix_r20, circle_r50_f3000 and cncjs_toolpath (MIT,
tests/data), and LinuxCNC's arcspiral (GPL: read from ../shared/toolpaths/external, never
copied; its first 40 lines, 20 s of arcs at 24 in/min, with an axis reversal at every
quadrant; the whole program is 254 s of motion). A benchmark prints figures; it asserts
nothing.
"""

from __future__ import annotations

import argparse
import importlib
import os
import time
from pathlib import Path

for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread, as the real-time target says

from feedplan.read import load_toolpath, read_toolpath  # noqa: E402
from oga.errors import OgaError  # noqa: E402
from oga.machine import load_machine  # noqa: E402
from oga.optimize import optimize  # noqa: E402
from oga.pipeline import plan_toolpath  # noqa: E402
from oga.robust.certificate import certify_result  # noqa: E402
from oga.robust.plants import scenario_set  # noqa: E402
from oga.robust.search import robust_optimize  # noqa: E402
from oga.verify import verify  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
EXTERNAL = ROOT.parent / "shared" / "toolpaths" / "external"
#: (name, file, lines kept or None for all)
PROGRAMS = (
    ("reference_xz", DATA / "reference_xz.ngc", None),
    ("freeform_xz", DATA / "freeform_xz.ngc", None),
    ("helix_r20", DATA / "helix_r20.ngc", None),
    ("circle_r50_f3000", DATA / "circle_r50_f3000.ngc", None),
    ("cncjs_toolpath", DATA / "cncjs_toolpath.nc", None),
    ("arcspiral[:40]", EXTERNAL / "lcnc_arcspiral.ngc", 40),
)


def _path(file: Path, lines: int | None):
    if lines is None:
        return load_toolpath(file)
    text = "\n".join(file.read_text().splitlines()[:lines])
    return read_toolpath(text, "gcode", source=f"{file.name}[:{lines}]")


def _cold() -> None:
    """Empty the in-process memos (module doc): the stability loops, margin tables and
    ends, the packed axis parameters, the sub-step matrices and the machines' digests and
    limits."""
    stability = importlib.import_module("oga.stability")
    simulate = importlib.import_module("oga.simulate")  # the module, not oga's function
    linear = importlib.import_module("oga.linear")
    machine = importlib.import_module("oga.machine")
    for memo in (stability._LOOPS, stability._TABLES, stability._ENDS, simulate._PARAMS,
                 machine._MACHINE_MEMOS):
        memo.clear()
    for cached in (linear._matrices, linear._sequence, stability._unit_circle):
        cached.cache_clear()


def _row(name, motion, nominal, cert, rt, rt_cert, tail) -> None:
    s = cert.summary()
    print(f"{name:18s} {motion} {nominal:8.3f} {cert.median:7.3f} {cert.p90:7.3f} "
          f"{cert.worst:7.3f} {len(cert.breaks('schedule')):7d} {len(cert.breaks('baseline')):8d} "
          f"{len(cert.breaks('schedule-only')):8d} {s['schedule']['max_ce_um']:9.2f} "
          f"{s['baseline']['max_ce_um']:10.2f} {rt:7.2f} {rt_cert}  {tail}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", default="ucp710")
    ap.add_argument("--plants", type=int, default=64, help="Monte Carlo plants (+ corners)")
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--only", default="", help="comma-separated program names")
    args = ap.parse_args(argv)
    machine = load_machine(args.machine)
    scen = scenario_set(machine, n=args.plants, seed=args.seed)
    only = {s for s in args.only.split(",") if s}
    warm = plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), machine, feed_m_s=None, tol_m=2e-5)
    certify_result(optimize(warm, machine, {"nominal": True}),
                   scenario_set(machine, n=1, corners=False))
    print(f"machine {machine.name}: {len(scen)} plants ({scen.n_monte_carlo} Monte Carlo, seed "
          f"{scen.seed}, {scen.n_corners} corners)")
    print(f"{'program':18s} {'motion s':>8s} {'nominal':>8s} {'median':>7s} {'p90':>7s} "
          f"{'worst':>7s} {'brk sch':>7s} {'brk base':>8s} {'sch only':>8s} {'maxCE sch':>9s} "
          f"{'maxCE base':>10s} {'RT opt':>7s} {'RT cert':>7s}  worst plant")
    for name, file, lines in PROGRAMS:
        if only and name not in only:
            continue
        if not file.exists():
            print(f"{name:18s} (missing: {file})")
            continue
        sp = plan_toolpath(_path(file, lines), machine, feed_m_s=None, tol_m=2e-5)
        _cold()
        t0 = time.process_time()
        res = optimize(sp, machine, {"nominal": True})
        t1 = time.process_time()
        cert = certify_result(res, scen)
        t2 = time.process_time()
        _row(name, f"{sp.duration:8.1f}", res.search_ratio_mse, cert, sp.duration / (t1 - t0),
             f"{sp.duration / (t2 - t1):7.2f}", cert.worst_plant.label)
        _cold()
        t0 = time.process_time()
        try:
            rob = robust_optimize(sp, machine, scenarios=scen)
        except OgaError as err:
            print(f"{'  robust':18s} failed: {err}", flush=True)
            continue
        t1 = time.process_time()
        price = verify(sp, machine, rob.schedule.kp_m_min_per_mm, rob.schedule.kf,
                       res.kp_bounds).metrics.mse_m2 / res.baseline.metrics.mse_m2
        a = "xyz"[sp.moving_axes[0]]
        _row("  robust", f"{'':8s}", price, rob.certificate, sp.duration / (t1 - t0), f"{'':7s}",
             f"{rob.status} rounds {rob.rounds} alpha {rob.alpha} base Kp "
             f"{rob.result.baseline_kp[a]} Kf {rob.result.baseline_kf[a]} reserve "
             f"{rob.reserve:.3f} on {', '.join(x.removeprefix('corner ') for x in rob.active)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
