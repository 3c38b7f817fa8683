"""Gain laws against the robust baseline at feed overrides 50-120 %: one law per program and
one for all of them together.

Run:  python bench/bench_law.py [--kind lincurve|pl|mac] [--points N] [--only NAME,..]
      [--no-all] [--no-table]

Per program (the benchmark programs of bench_robust.py and two real programs of LinuxCNC,
read from ../shared/toolpaths/external, never copied: GPL), on ``ucp710`` and its
uncertainty set (96 plants: 64 Monte Carlo, seed 17, and 32 corners):

- ``table``: the robust table (:func:`oga.search.robust.search.robust_optimize`) at 100 % feed, its
  certificate's median ratio (a table is indexed by time: it runs at 100 % only);
- ``law``: the law searched on the program at every override (:func:`oga.law.search.
  search_law`), then certified on the whole set at every override against the program's
  robust baseline: per override the ratio's median, p90 and worst, the plants where the
  law, the baseline and the law alone break a check (eq. 2, the following-error limit, the
  plant's stable range), and the MSE ratio on the nominal plant. ``half`` says whether the
  law keeps at least half of the table's median MSE reduction at 100 % (``1 - median``).
- ``all``: one law for every program together, certified the same way on each against the
  programs' joint baseline (:func:`oga.law.baseline.joint_program_baseline`: the one fixed
  setting that keeps every plant's checks on all of them; no ``table`` or ``half``: the
  tables are judged against each program's own baseline).

CPU times are process times (one thread; the host may be shared: the figures swing with
the neighbours' load). A benchmark prints figures; it asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from bench_robust import PROGRAMS as ROBUST_PROGRAMS, _path  # noqa: E402
from oga import defaults  # noqa: E402
from oga.errors import OgaError  # noqa: E402
from oga.law.override import plan_override  # noqa: E402
from oga.law.search import Program, search_law  # noqa: E402
from oga.model.machine import load_machine  # noqa: E402
from oga.search.robust.plants import scenario_set  # noqa: E402
from oga.search.robust.search import robust_optimize  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The real programs (GPL: read in place): beside the repository, as in /work/main, or in the
#: shared folder of a worktree's host.
EXTERNAL = next((d for d in (ROOT.parent / "shared" / "toolpaths" / "external",
                             Path("/work/shared/toolpaths/external")) if d.exists()),
                ROOT.parent / "shared" / "toolpaths" / "external")
#: (name, file, lines kept or None for all): bench_robust.py's programs and two real ones.
PROGRAMS = tuple((n, f if f.exists() else EXTERNAL / f.name, k) for n, f, k in ROBUST_PROGRAMS) + (
    ("line-contouring-xz", EXTERNAL / "lcnc_line-contouring-xz.ngc", None),
    ("short_segments", EXTERNAL / "lcnc_short_segments_0.001.ngc", None),
)


def _rows(label, res, table_median=None) -> None:
    for (prog, o), c in res.certificate.cases.items():
        half = ""
        if table_median is not None and o == 1.0:
            half = "yes" if 1.0 - c.median >= 0.5 * (1.0 - table_median[prog]) else "NO"
        print(f"  {label:5s} {prog:19s} {o * 100:5.0f} {c.median:7.3f} {c.p90:7.3f} "
              f"{c.worst:7.3f} {len(c.breaks('schedule')):5d} {len(c.breaks('baseline')):5d} "
              f"{len(c.breaks('schedule-only')):5d} {res.nominal_ratio[(prog, o)]:8.3f} "
              f"{'' if table_median is None else f'{table_median[prog]:7.3f}'} {half}",
              flush=True)


def _tail(label, res) -> None:
    print(f"  {label}: {res.status}{' (' + res.reason[:200] + ')' if res.reason else ''}; "
          f"{res.rounds} rounds, {res.iterations} steps, alpha {res.alpha}, reserve "
          f"{res.reserve:.3f}, on {', '.join(res.active) or 'nominal only'}; CPU s search "
          f"{res.search_s:.1f}, certificates {res.certify_s:.1f}", flush=True)
    for a, ax in res.law.summary()["axes"].items():
        print(f"    {a}: v_mm_s {[round(x, 2) for x in ax['v_mm_s']]} a_mm_s2 "
              f"{[round(x) for x in ax['a_mm_s2']]} kp {[[round(x, 3) for x in r] for r in ax['kp_m_min_per_mm']]} "
              f"kf {[[round(x, 3) for x in r] for r in ax['kf']]}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", default="ucp710")
    ap.add_argument("--kind", default="lincurve", choices=defaults.LAW_KINDS)
    ap.add_argument("--points", type=int, default=None)
    ap.add_argument("--only", default="", help="comma-separated program names")
    ap.add_argument("--no-all", action="store_true", help="skip the law of all programs")
    ap.add_argument("--no-table", action="store_true", help="skip the robust tables")
    args = ap.parse_args(argv)
    machine = load_machine(args.machine)
    scen = scenario_set(machine)
    only = {s for s in args.only.split(",") if s}
    overrides = defaults.LAW_OVERRIDES
    print(f"machine {machine.name}: {len(scen)} plants ({scen.n_monte_carlo} Monte Carlo, seed "
          f"{scen.seed}, {scen.n_corners} corners); law {args.kind}, points "
          f"{args.points or defaults.LAW_POINTS[args.kind]}; overrides "
          f"{', '.join(f'{o * 100:g} %' for o in overrides)}")
    print(f"  {'':5s} {'program':19s} {'ovr %':>5s} {'median':>7s} {'p90':>7s} {'worst':>7s} "
          f"{'brk':>5s} {'brk b':>5s} {'only':>5s} {'nominal':>8s} {'table':>7s} half")
    programs, baselines, table_median = [], {}, {}
    for name, file, lines in PROGRAMS:
        if only and name not in only:
            continue
        if not file.exists():
            print(f"{name}: missing ({file})")
            continue
        path = _path(file, lines)
        t0 = time.process_time()
        prog = Program(name, {o: plan_override(path, machine, o, defaults.TOL_M)
                              for o in overrides})
        t_plan = time.process_time() - t0
        motion = {o: sp.duration for o, sp in prog.setpoints.items()}
        print(f"{name}: motion s {', '.join(f'{m:.1f}' for m in motion.values())} "
              f"(planned in {t_plan:.1f} CPU s)", flush=True)
        known = {}  # the table's robust baseline: the law's is the same function's result
        if not args.no_table:
            t0 = time.process_time()
            try:
                rob = robust_optimize(prog.setpoints[1.0], machine, scenarios=scen, threads=1)
                table_median[name] = rob.certificate.median
                known[name] = rob.baseline
                print(f"  table {rob.status}: median {rob.certificate.median:.3f} p90 "
                      f"{rob.certificate.p90:.3f} worst {rob.certificate.worst:.3f}, "
                      f"{time.process_time() - t0:.1f} CPU s", flush=True)
            except OgaError as err:
                print(f"  table failed: {err}", flush=True)
        try:
            res = search_law([prog], machine, args.kind, args.points, scenarios=scen,
                             baselines=known, threads=1)
        except OgaError as err:
            print(f"  law failed: {err}", flush=True)
            continue
        baselines.update(res.baselines)
        _rows("law", res, table_median if name in table_median else None)
        _tail("law", res)
        programs.append(prog)
    if len(programs) > 1 and not args.no_all:
        print(f"all {len(programs)} programs, one law:", flush=True)
        res = search_law(programs, machine, args.kind, args.points, scenarios=scen, threads=1)
        joint = next(iter(res.baselines.values()))
        print(f"  joint baseline: Kp {joint.kp:.4f} Kf {joint.kf:.4f} (own: "
              f"{', '.join(f'{p} {b.kp:.3f}/{b.kf:.3f}' for p, b in baselines.items())})",
              flush=True)
        _rows("all", res)  # against the joint baseline: no table to compare with
        _tail("all", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
