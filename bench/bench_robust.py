"""Robust tables: their certificate, its confidence bound, and the real-time factor on 1 and 2
threads.

Run:  python bench/bench_robust.py [--only NAME,..] [--threads 1,2] [--certify N] [--nominal]
                                   [--kernels]

Per program, on the machine (default ``ucp710``, with its documented default uncertainty set),
the robust ``oga optimize`` (:func:`oga.search.robust.search.robust_optimize`: the set's stable
ranges, the robust baseline, the rounds of the multi-scenario search and their certificates,
the shrink) is run once per thread count, every run from cold memos as a fresh ``oga
optimize`` process starts (the stable ranges, packed parameters and sub-step matrices
emptied; numba's compiled kernels are warm). It prints:

- the certificate of the exported schedule against the robust baseline on the set's Monte
  Carlo plants and corners: the MSE ratio's median, p90 and worst, the plants where the
  schedule alone breaks a check, the status, and the confidence bound (the one-sided exact
  binomial upper bound at 95 % on the share of the set's machines where the table is worse
  than the baseline or breaks a check the baseline keeps);
- the price: MSE(CE) of the exported table on the nominal machine over that of the nominal
  best fixed gains (:func:`oga.search.ranges.best_fixed_gains`);
- RT = motion time / time taken: ``RT cpu`` over the process's CPU time on one thread, ``par``
  the share of that CPU time spent in the independent replays that run on threads (the
  rest, the multi-plant window search above all, runs on one), ``RT 2*`` the RT on two
  threads that share would give at best (Amdahl: the serial CPU time plus half the
  parallel one); ``RT 1``, ``RT 2``.. over the wall time on that many threads (on a shared
  host, only as good as its load); ``same``: every thread count gave the first one's
  schedule and certificate, bit for bit;
- the robust baseline (Kp, Kf), the rounds, the shrink's shares (1: none) and the plants
  searched on besides the nominal one;
- on the next lines, per thread count, the run's CPU and wall time by phase: the set's
  stable ranges, the robust baseline, the multi-plant window searches, the certificates
  (the shrink's included) and the rest;
- with ``--kernels``, on one more line, the one-thread run's compiled calls: per kernel the
  calls, their CPU time in all and per call (the tangent and limit replays of the baseline,
  the simulations of :func:`oga.verify.verify` (the confirmations and certificates), the
  multi-plant window searches; the contour error is not wrapped: ``ce_indexed`` is also
  called from compiled code, which cannot call a Python wrapper).

``--nominal`` adds the nominal table (the search on the nominal model only) and its
certificate against the nominal best fixed gains on the same set. A benchmark prints
figures; it asserts nothing. Wall times on a shared host are only as good as its load.

Programs: reference_xz, freeform_xz, helix_r20, circle_r50_f3000 and cncjs_toolpath (MIT,
tests/data), and LinuxCNC's arcspiral (GPL: read from ../shared/toolpaths/external, never
copied; its first 40 lines, 20 s of arcs at 24 in/min, with an axis reversal at every
quadrant; the whole program is 254 s of motion).
"""

from __future__ import annotations

import argparse
import importlib
import os
import time
from pathlib import Path

if __name__ == "__main__":  # not in a process that imports it (bench_perturb, bench_law)
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_var, "1")  # the threads are the robust search's own

import numpy as np  # noqa: E402

from feedplan.read import load_toolpath, read_toolpath  # noqa: E402
from oga.errors import OgaError  # noqa: E402
from oga.model.machine import load_machine  # noqa: E402
from oga.optimize import optimize  # noqa: E402
from oga.pipeline import plan_toolpath  # noqa: E402
from oga.search.ranges import best_fixed_gains  # noqa: E402
from oga.verify.certificate import certify_result  # noqa: E402
from oga.search.robust.plants import scenario_set  # noqa: E402
from oga.search.robust.search import robust_optimize  # noqa: E402
from oga.verify.replay import verify  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
#: ../shared beside the checkout (/work/main), or beside the worktrees' folder (/work/wt/NAME)
EXTERNAL = next((p / "shared" / "toolpaths" / "external" for p in ROOT.parents[:2]
                 if (p / "shared" / "toolpaths" / "external").is_dir()),
                ROOT.parent / "shared" / "toolpaths" / "external")
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
    ends, the packed axis parameters and plants, the sub-step matrices and the machines'
    digests and limits."""
    stability = importlib.import_module("oga.model.stability")
    simulate = importlib.import_module("oga.model.simulate")  # the module, not oga's function
    linear = importlib.import_module("oga.model.linear")
    machine = importlib.import_module("oga.model.machine")
    plant = importlib.import_module("oga.model.plant")
    for memo in (stability._LOOPS, stability._TABLES, stability._ENDS, simulate._PARAMS,
                 machine._MACHINE_MEMOS, plant._PLANTS):
        memo.clear()
    for cached in (linear._matrices, linear._sequence, stability._unit_circle):
        cached.cache_clear()


def _timed(f, add, clock=time.process_time):
    """``f`` that hands the time of each call on ``clock`` to ``add`` (seconds; default CPU)."""
    def timed(*args, **kw):
        t0 = clock()
        try:
            return f(*args, **kw)
        finally:
            add(clock() - t0)
    return timed


class _Timed:
    """``thread_map`` of the robust modules, timed: the wall time spent inside it."""

    modules = ("oga.verify.certificate", "oga.search.robust.baseline")

    def __init__(self):
        self.inside = 0.0
        self._orig = {m: importlib.import_module(m).thread_map for m in self.modules}
        for m, f in self._orig.items():
            importlib.import_module(m).thread_map = self._wrap(f)

    def _wrap(self, f):
        def add(dt):
            self.inside += dt
        return _timed(f, add, time.perf_counter)


class _Phases:
    """The CPU and wall time spent in each phase of :func:`robust_optimize` (its module's
    names of them wrapped), seconds."""

    names = {"plant_bounds": "ranges", "robust_baseline": "baseline", "multi_search": "window",
             "certify": "certificates"}

    def __init__(self):
        self.clear()
        module = importlib.import_module("oga.search.robust.search")
        for name, phase in self.names.items():
            setattr(module, name, self._wrap(getattr(module, name), phase))

    def clear(self) -> None:
        self.cpu = dict.fromkeys(self.names.values(), 0.0)
        self.wall = dict.fromkeys(self.names.values(), 0.0)

    def _wrap(self, f, phase):
        def add_cpu(dt):
            self.cpu[phase] += dt

        def add_wall(dt):
            self.wall[phase] += dt
        return _timed(_timed(f, add_cpu), add_wall, time.perf_counter)

    def line(self, threads: int, cpu: float, wall: float) -> str:
        """The phases' CPU / wall time of a run of ``threads`` threads that took ``cpu`` and
        ``wall`` seconds in all (``rest``: outside the phases)."""
        rest = (cpu - sum(self.cpu.values()), wall - sum(self.wall.values()))
        return f"  {threads} thread(s), cpu / wall by phase: " + ", ".join(
            f"{k} {c:.2f} / {w:.2f} s" for k, c, w in
            (*((k, self.cpu[k], self.wall[k]) for k in self.cpu), ("rest", *rest)))


class _Kernels:
    """The calls of the compiled kernels called from Python in the robust search and their
    CPU time (the module globals its callers look them up by, wrapped)."""

    names = (("oga.search.robust.baseline", "_tangent_replay", "tangent"),
             ("oga.search.robust.baseline", "_replay", "limits"),
             ("oga.model.response", "run_axes", "simulate"),
             ("oga.search.robust.multi", "window_search", "window"))

    def __init__(self):
        self.calls = {label: [0, 0.0] for _m, _n, label in self.names}
        for module, name, label in self.names:
            mod = importlib.import_module(module)
            setattr(mod, name, self._wrap(getattr(mod, name), label))

    def clear(self) -> None:
        for v in self.calls.values():
            v[:] = [0, 0.0]

    def _wrap(self, f, label):
        def add(dt):
            self.calls[label][0] += 1
            self.calls[label][1] += dt
        return _timed(f, add)

    def line(self) -> str:
        return "  kernels: " + ", ".join(
            f"{k} {n} x {1e3 * t / max(n, 1):.1f} ms = {t:.2f} s"
            for k, (n, t) in self.calls.items())


def _same(a, b) -> bool:
    """The two robust results give the same schedule and certificate, bit for bit."""
    return (np.array_equal(a.schedule.kp_m_min_per_mm, b.schedule.kp_m_min_per_mm)
            and np.array_equal(a.schedule.kf, b.schedule.kf)
            and np.array_equal(a.certificate.ratio, b.certificate.ratio))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", default="ucp710")
    ap.add_argument("--certify", type=int, default=None,
                    help="Monte Carlo plants (+ corners; default the search's)")
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    ap.add_argument("--only", default="", help="comma-separated program names")
    ap.add_argument("--nominal", action="store_true", help="also the nominal table's certificate")
    ap.add_argument("--kernels", action="store_true",
                    help="also the compiled calls' counts and CPU time (one thread)")
    args = ap.parse_args(argv)
    machine = load_machine(args.machine)
    threads = [int(t) for t in args.threads.split(",")]
    options = {} if args.certify is None else {"certify": args.certify}
    scen = scenario_set(machine, **({} if args.certify is None else {"n": args.certify}),
                        seed=args.seed)
    only = {s for s in args.only.split(",") if s}
    timed, phases = _Timed(), _Phases()
    kernels = _Kernels() if args.kernels else None
    warm = plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), machine, feed_m_s=None, tol_m=2e-5)
    for t in threads:  # compile (or load) every kernel first
        robust_optimize(warm, machine, scenarios=scenario_set(machine, n=2), threads=t)
    print(f"machine {machine.name}: {len(scen)} plants ({scen.n_monte_carlo} Monte Carlo, seed "
          f"{scen.seed}, {scen.n_corners} corners); {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.1f}")
    print(f"{'program':18s} {'motion s':>8s} {'median':>7s} {'p90':>7s} {'worst':>7s} "
          f"{'sch only':>8s} {'bound':>7s} {'price':>7s} {'RT cpu':>7s} {'par':>5s} {'RT 2*':>6s} "
          + " ".join(f"{'RT ' + str(t):>6s}" for t in threads)
          + f" {'same':>5s}  status, baseline, rounds, shares, searched on")
    for name, file, lines in PROGRAMS:
        if only and name not in only:
            continue
        if not file.exists():
            print(f"{name:18s} (missing: {file})")
            continue
        sp = plan_toolpath(_path(file, lines), machine, feed_m_s=None, tol_m=2e-5)
        runs, walls, cpu, par, split = [], [], None, None, []
        try:
            for t in threads:
                _cold()
                timed.inside = 0.0
                phases.clear()
                if kernels is not None and t == 1:
                    kernels.clear()
                w0, c0 = time.perf_counter(), time.process_time()
                runs.append(robust_optimize(sp, machine, options, scenarios=scen, threads=t))
                walls.append(time.perf_counter() - w0)
                split.append(phases.line(t, time.process_time() - c0, walls[-1]))
                if t == 1:  # on one thread the time inside thread_map is its CPU time, roughly
                    cpu = time.process_time() - c0
                    par = min(timed.inside / walls[-1], 1.0)
                    if kernels is not None:
                        split.append(kernels.line())
        except OgaError as err:
            print(f"{name:18s} {sp.duration:8.1f} failed: {err}", flush=True)
            continue
        rob = runs[0]
        cert = rob.certificate
        fixed = best_fixed_gains(sp, machine)
        a = "xyz"[sp.moving_axes[0]]
        price = verify(sp, machine, rob.schedule.kp_m_min_per_mm, rob.schedule.kf,
                       rob.result.kp_bounds).metrics.mse_m2 / fixed.mse_ce_m2
        bound = cert.confidence()["share_bound"]
        print(f"{name:18s} {sp.duration:8.1f} {cert.median:7.3f} {cert.p90:7.3f} "
              f"{cert.worst:7.3f} {len(cert.breaks('schedule-only')):8d} "
              f"{bound * 100:6.2f}% {price:7.3f} "
              f"{sp.duration / cpu if cpu else float('nan'):7.2f} "
              f"{par if par is not None else float('nan'):5.2f} "
              f"{sp.duration / (cpu * (1 - par / 2)) if cpu else float('nan'):6.2f} "
              + " ".join(f"{sp.duration / w:6.2f}" for w in walls)
              + f" {'yes' if all(_same(rob, r) for r in runs[1:]) else 'NO':>5s}  {rob.status}, "
              f"Kp {rob.result.baseline_kp[a]:.4f} Kf {rob.result.baseline_kf[a]:.4f}, "
              f"{rob.rounds} rounds, {rob.alpha}, on "
              f"{', '.join(x.removeprefix('corner ') for x in rob.active) or '-'}", flush=True)
        print("\n".join(split), flush=True)
        if args.nominal:
            res = optimize(sp, machine, {"nominal": True})
            c = certify_result(res, scen, threads=max(threads))
            print(f"{'  nominal table':18s} {'':8s} {c.median:7.3f} {c.p90:7.3f} {c.worst:7.3f} "
                  f"{len(c.breaks('schedule-only')):8d} against the nominal best fixed gains "
                  f"(its ratio there {res.search_ratio_mse:.3f})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
