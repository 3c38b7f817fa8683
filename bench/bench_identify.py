"""Identification: recovery of random plants, and the time of a one-axis fit.

For each of ``--draws`` seeded draws (default 100), axis x of ucp710 gets a cascade drawn over
wide ranges (:func:`oga.identify.sim.random_cascade`: mass 100-2000 kg, friction 0-500 N,
velocity loop 10-80 Hz, Tn 5-30 ms, dead time 0-4 samples); the identification program of
axis x (about 57 s of motion) is simulated on it at a Kp inside its stable range, Kf 0.8,
with 0.1 um RMS position noise, 0.1 um quantisation and 1 N RMS force noise; the fit's
relative errors, CPU time, position residual over the noise estimate, force residual as a
share of the force's RMS and status are printed, then the share of draws within the issue's
bounds (mass, Kv, Tn 5 %, Coulomb 10 % or 2 N, dead time exact) and the residuals of the fits
within and out of them (what the ``poor`` thresholds are chosen from).

    python bench/bench_identify.py [--draws N | --only 30,48] [--seed S] [--jobs J]
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from functools import partial

import numpy as np

from feedplan.read import read_toolpath
from oga.identify.excite import excite_program
from oga.identify.fit import fit_axis
from oga.identify.sim import random_cascade, synthetic_trace
from oga.identify.trace import AxisTrace
from oga.model.machine import load_machine
from oga.pipeline import plan_toolpath


def _draw(base, sp, seed: int, k: int):
    """Fit draw ``k``: (relative errors, Coulomb relative and absolute error, dead time
    right, CPU s, within the bounds, residual / noise, status, the printed row)."""
    n = len(sp)
    rng = np.random.default_rng(seed + k)
    true_m, kp = random_cascade(base, "x", rng)
    ch = synthetic_trace(sp, true_m, ["x"], kp, 0.8, noise_m=1e-7, quantum_m=1e-7,
                         seed=seed + k, force_noise_n=1.0)
    tr = AxisTrace(cmd_m=ch["x_cmd_m"], act_m=ch["x_act_m"], kp_m_min_per_mm=np.full(n, kp),
                   kf=np.full(n, 0.8), force_n=ch["x_force_n"])
    t0 = time.process_time()
    fit = fit_axis(base, "x", tr, sp.dt)
    cpu = time.process_time() - t0
    true = true_m.axis("x").cascade
    err = {p: fit.values[p] / getattr(true, p) - 1 for p in ("mass_kg", "kv_n_s_m", "tn_s")}
    fc_abs = fit.values["coulomb_n"] - true.coulomb_n
    fc_rel = fc_abs / true.coulomb_n if true.coulomb_n > 0 else np.nan
    d_ok = fit.dead_time_samples == true_m.timing.dead_time_samples and fit.lag_samples == 0
    ok = (all(abs(e) <= 0.05 for e in err.values()) and d_ok
          and (abs(fc_abs) <= 2.0 or abs(fc_rel) <= 0.10))
    bw = true.kv_n_s_m / true.mass_kg / (2 * np.pi)
    noise_ratio = fit.residual_rms_m / max(fit.noise_rms_m, 1e-12)
    f_share = fit.force_residual_rms_n / float(np.sqrt(np.mean(ch["x_force_n"] ** 2)))
    row = (f"{k:4d} {true.mass_kg:8.0f} {bw:6.1f} {true.coulomb_n:6.0f} "
           f"{true_m.timing.dead_time_samples:2d} {kp:5.2f} | "
           f"{err['mass_kg'] * 100:7.3f} {err['kv_n_s_m'] * 100:7.3f} {err['tn_s'] * 100:7.3f} "
           f"{fc_rel * 100:7.2f} {fc_abs:6.2f} {'ok' if d_ok else fit.dead_time_samples:>3} "
           f"{cpu:6.1f} {noise_ratio:6.2f} {f_share * 100:6.2f} {fit.status:>4}{'' if ok else '  OUT'}")
    return err, fc_rel, fc_abs, d_ok, cpu, ok, noise_ratio, fit.status, f_share, row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--only", default="",
                    help="comma-separated draw indices to fit (e.g. the failing ones); "
                         "default: 0 .. draws-1")
    ap.add_argument("--jobs", type=int, default=1,
                    help="draws fitted at once in separate processes (each fit on one core; "
                         "its CPU time is its own process's)")
    args = ap.parse_args()
    base = load_machine("ucp710")
    sp = plan_toolpath(read_toolpath(excite_program(base, ["x"]), "gcode"), base,
                       feed_m_s=None, tol_m=2e-5)
    n = len(sp)
    print(f"identification program of axis x: {n} samples ({n * sp.dt:.1f} s); "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {args.jobs} job(s)")
    print(f"{'draw':>4} {'mass kg':>8} {'bw Hz':>6} {'Fc N':>6} {'d':>2} {'Kp':>5} | "
          f"{'mass %':>7} {'Kv %':>7} {'Tn %':>7} {'Fc %':>7} {'Fc N':>6} {'d':>3} {'CPU s':>6} "
          f"{'res/noise':>6} {'F res %':>6} status")
    draw = partial(_draw, base, sp, args.seed)
    try:
        ks = [int(k) for k in args.only.split(",")] if args.only else list(range(args.draws))
    except ValueError:
        ap.error(f"--only {args.only!r}: not a comma-separated list of draw indices")
    rows = []
    with ProcessPoolExecutor(args.jobs) if args.jobs > 1 else nullcontext() as pool:
        for r in (pool.map(draw, ks) if pool else map(draw, ks)):
            rows.append(r)
            print(r[-1], flush=True)
    n_ok = sum(r[5] for r in rows)
    print(f"\n{n_ok}/{len(rows)} draws within the bounds; dead time exact in "
          f"{sum(r[3] for r in rows)}/{len(rows)}")
    print("|error| % over the draws:      max      p95   median")
    for p in ("mass_kg", "kv_n_s_m", "tn_s"):
        e = np.abs([r[0][p] for r in rows]) * 100
        print(f"  {p:<24} {e.max():8.3f} {np.percentile(e, 95):8.3f} {np.median(e):8.3f}")
    e = np.abs([r[1] for r in rows if np.isfinite(r[1])]) * 100
    a = np.abs([r[2] for r in rows])
    print(f"  {'coulomb_n (%)':<24} {e.max():8.3f} {np.percentile(e, 95):8.3f} {np.median(e):8.3f}")
    print(f"  {'coulomb_n (N, absolute)':<24} {a.max():8.3f} {np.percentile(a, 95):8.3f} "
          f"{np.median(a):8.3f}")
    q = np.array([r[6] for r in rows])
    good = np.array([r[5] for r in rows])
    for name, sel in (("within the bounds", good), ("out of the bounds", ~good)):
        if sel.any():
            fs = np.array([r[8] for r in rows])[sel] * 100
            print(f"{name} ({sel.sum()}, status ok {sum(r[7] == 'ok' for r, s in zip(rows, sel) if s)}):"
                  f" residual / noise estimate max {q[sel].max():.2f}, p95 "
                  f"{np.percentile(q[sel], 95):.2f}, median {np.median(q[sel]):.2f}, min "
                  f"{q[sel].min():.2f}; force residual % of the force RMS max {fs.max():.2f}, "
                  f"p95 {np.percentile(fs, 95):.2f}, median {np.median(fs):.2f}, min {fs.min():.2f}")
    cpus = np.array([r[4] for r in rows])
    print(f"load average at the end {os.getloadavg()[0]:.1f}")
    print(f"fit CPU time per axis ({n * sp.dt:.0f} s trace, one core): median {np.median(cpus):.1f} s,"
          f" max {cpus.max():.1f} s; per 60 s of trace (the cost is linear in its length): "
          f"median {np.median(cpus) * 60 / (n * sp.dt):.1f} s, max {cpus.max() * 60 / (n * sp.dt):.1f} s")

if __name__ == "__main__":
    main()
