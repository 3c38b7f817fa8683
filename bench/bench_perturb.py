"""Continuity of the robust search in the machine: its tables for machines perturbed by
+-1e-4 and +-1e-3.

Run:  python bench/bench_perturb.py [--only NAME,..] [--fields kv_n_s_m,..] [--axes x,z]
                                    [--scales 0.999,0.9999,1.0001,1.001] [--threads N] [--log]

Per program of ``bench/bench_robust.py`` and per cascade value of a moving axis (every
field of :data:`oga.model.machine.FACTOR_FIELDS`), the machine (default ``ucp710``) with that one
value scaled, its uncertainty set kept (the set's plants scale with it), is searched by the
robust ``oga optimize`` (:func:`oga.search.robust.search.robust_optimize`). Per run: the baseline,
the status, the exported table's certificate median / p90 / worst (1 where the baseline is
kept), and its MSE(CE) ratio on the machine itself (its "predicted ratio"); per program, the largest departure of each figure from
the unperturbed machine's, and the runs that left the band (``--band``: the ratios within
``band`` of the unperturbed ones, relative; default 0.1 for 1e-4 and 0.2 for 1e-3). Each
run's line ends with its rounds, the kept round's reserve and plants, the shrink's share and
the searched table's certificate (also where the baseline is exported); ``--log`` prints every
round before it (reserve, plants, certificate, largest limit ratio). A benchmark prints
figures; it asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # not in a process that imports it (tests/test_robust_continuity.py)
    for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_robust import PROGRAMS, _path  # noqa: E402
from oga.errors import OgaError  # noqa: E402
from oga.model.machine import FACTOR_FIELDS, Machine, load_machine, machine_from_dict  # noqa: E402
from oga.pipeline import plan_toolpath  # noqa: E402
from oga.search.robust.search import robust_optimize  # noqa: E402

#: Relative band of the ratios around the unperturbed machine's, per size of the change.
BAND = {1e-4: 0.1, 1e-3: 0.2}


def scaled(machine: Machine, axis: str, field: str, factor: float) -> Machine:
    """``machine`` with ``axis``'s cascade value ``field`` times ``factor`` (static friction
    kept at least the Coulomb level), its uncertainty section kept."""
    data = machine.model_dump(mode="json", exclude_none=True)
    cas = data["axes"][axis]["cascade"]
    cas[field] = cas[field] * factor
    cas["static_n"] = max(cas["static_n"], cas["coulomb_n"])
    return machine_from_dict(data, where=f"{machine.name} with {axis}.{field} x {factor}")


def figures(rob) -> dict:
    """The figures compared, of the exported table: its certificate's median, p90 and worst
    (1: the baseline kept), and its ratio on the machine itself."""
    c, res = rob.certificate, rob.result
    ok = rob.status == "ok"
    return {"median": c.median if ok else 1.0, "p90": c.p90 if ok else 1.0,
            "worst": c.worst if ok else 1.0,
            "nominal": res.optimized.metrics.mse_m2 / res.baseline.metrics.mse_m2}


def _rounds(rob) -> str:
    """The rounds, the kept round's reserve and plants, and the searched table's certificate
    (also where the baseline is exported)."""
    c = rob.certificate
    return (f"rounds {rob.rounds}, reserve {rob.reserve:.4f}, alpha {rob.alpha[0]:.3f}, "
            f"searched {c.median:.4f}/{c.p90:.4f}/{c.worst:.4f}, active {list(rob.active)}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", default="ucp710")
    ap.add_argument("--only", default="", help="comma-separated program names")
    ap.add_argument("--fields", default=",".join(FACTOR_FIELDS))
    ap.add_argument("--axes", default="", help="default: the program's moving axes")
    ap.add_argument("--scales", default="0.999,0.9999,1.0001,1.001")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--log", action="store_true", help="log the rounds (debug level)")
    args = ap.parse_args(argv)
    if args.log:
        logging.basicConfig(format="    %(message)s")
        logging.getLogger("oga.search.robust.search").setLevel(logging.DEBUG)
    machine = load_machine(args.machine)
    only = {s for s in args.only.split(",") if s}
    fields = [f for f in args.fields.split(",") if f]
    scales = [float(s) for s in args.scales.split(",")]
    for name, file, lines in PROGRAMS:
        if (only and name not in only) or not file.exists():
            continue
        sp = plan_toolpath(_path(file, lines), machine, feed_m_s=None, tol_m=2e-5)
        axes = [a for a in args.axes.split(",") if a] or ["xyz"[i] for i in sp.moving_axes]
        t0 = time.perf_counter()
        ref = robust_optimize(sp, machine, threads=args.threads)
        f0 = figures(ref)
        a0 = axes[0]
        print(f"{name}: unperturbed {ref.status}, baseline Kp {ref.result.baseline_kp[a0]:.4f} "
              f"Kf {ref.result.baseline_kf[a0]:.4f}, " + ", ".join(f"{k} {v:.4f}"
                                                                    for k, v in f0.items())
              + f" ({time.perf_counter() - t0:.1f} s); {_rounds(ref)}", flush=True)
        worst = {k: 0.0 for k in f0}
        out = []
        for axis in axes:
            for field in fields:
                for s in scales:
                    try:
                        rob = robust_optimize(sp, scaled(machine, axis, field, s),
                                              threads=args.threads)
                    except OgaError as err:
                        print(f"  {axis}.{field} x {s}: {err}", flush=True)
                        continue
                    f = figures(rob)
                    dev = {k: abs(f[k] / f0[k] - 1.0) for k in f}
                    for k in f:
                        worst[k] = max(worst[k], dev[k])
                    size = 1e-3 if abs(s - 1.0) > 5e-4 else 1e-4
                    if max(dev.values()) > BAND[size]:
                        out.append(f"{axis}.{field} x {s}")
                    print(f"  {axis}.{field} x {s}: {rob.status}, baseline Kp "
                          f"{rob.result.baseline_kp[a0]:.4f} Kf {rob.result.baseline_kf[a0]:.4f}, "
                          + ", ".join(f"{k} {v:.4f} ({dev[k] * 100:+.1f} %)"
                                      for k, v in f.items()) + f"; {_rounds(rob)}", flush=True)
        print(f"{name}: largest relative departure " + ", ".join(
            f"{k} {v * 100:.1f} %" for k, v in worst.items())
              + f"; outside the band ({BAND}): {len(out)} {out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
