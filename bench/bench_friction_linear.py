"""The linear friction map at standstill (``timing.friction_linear_below_m_s``): speed and accuracy.

Run:  python bench/bench_friction_linear.py [--machine ucp710] [--only NAME,..]

The robust search's scenario plants set the simulation setting
``timing.friction_linear_below_m_s`` (:data:`oga.defaults.ROBUST_FRICTION_LINEAR_BELOW_M_S`):
where an axis stands still the kernel advances a period with one linear map (the friction
taken as its tangent at rest) instead of the sub-steps. Per program (reference_xz,
cncjs_toolpath) over the 96 plants of the machine's seeded set, each with the setting and
without it (the exact kernel), three fixed gain pairs:

- CPU per replay (:func:`oga.model.response.simulate`, all axes; the least of
  ``bench_optimize.REPEATS`` sweeps over the plants, one thread, after a warm-up);
- the largest ``|dp|`` (m) and ``|du|`` (m/s) between the two, and the largest relative
  change of MSE(CE), of the eq. 2 command ratios and of the largest following error;
- the certificate of the nominal schedule (:func:`oga.verify.certificate.certify_result`) on
  the plants with and without the setting: median, p90, worst, breaks, and the largest
  relative change of a plant's ratio.

A benchmark prints figures; it asserts nothing.
"""

from __future__ import annotations

import dataclasses
import os
import time

for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread, as the real-time target says

import numpy as np  # noqa: E402

from oga.model.contour import contour_error_of  # noqa: E402
from oga.model.metrics import contour_metrics  # noqa: E402
from oga.optimize import optimize  # noqa: E402
from oga.verify.certificate import certify_result  # noqa: E402
from oga.search.robust.plants import scenario_set  # noqa: E402
from oga.model.response import simulate  # noqa: E402
from oga.verify.replay import command_ratios  # noqa: E402

from bench_optimize import REPEATS  # noqa: E402
from bench_replay import programs  # noqa: E402  (--machine, --only and the programs)

GAINS = ((2.0, 0.7), (4.0, 1.0), (1.0, 0.0))


def _exact(plant):
    """``plant`` without the setting: the exact kernel."""
    timing = plant.timing.model_copy(update={"friction_linear_below_m_s": None})
    return plant.model_copy(update={"timing": timing})


def _sweep(sp, plants, gains):
    """CPU time (s) of one replay of every gain pair on every plant."""
    t0 = time.process_time()
    for plant in plants:
        for kp, kf in gains:
            simulate(sp, plant, kp, kf)
    return time.process_time() - t0


def _figures(sp, sim, plant, moving):
    met = contour_metrics(contour_error_of(sp, sim.pos), sp.pos, sim.pos, ~sp.rapid)
    return (met.mse_m2, command_ratios(sim.u, sp, plant)[moving],
            np.array(met.track_max_m)[moving])


def main() -> None:
    machine, planned = programs(__doc__.splitlines()[0])
    scen = scenario_set(machine)
    fast = scen.plants
    exact = tuple(_exact(p) for p in fast)
    print(f"machine {machine.name}: {len(fast)} plants, setting "
          f"{fast[0].timing.friction_linear_below_m_s} m/s; gains {GAINS}")
    for name, sp in planned:
        n = len(sp)
        moving = list(sp.moving_axes)
        gains = [(np.full((n, 3), kp), np.full((n, 3), kf)) for kp, kf in GAINS]
        _sweep(sp, fast[:1] + exact[:1], gains[:1])  # warm-up: compile, memos
        for plants in (fast, exact):  # the packed parameters once (memo), outside the timing
            _sweep(sp, plants, gains[:1])
        t_fast = t_exact = float("inf")
        for _ in range(REPEATS):  # A/B interleaved
            t_fast = min(t_fast, _sweep(sp, fast, gains))
            t_exact = min(t_exact, _sweep(sp, exact, gains))
        runs = len(fast) * len(gains)
        dp = du = r_mse = r_cmd = r_track = 0.0
        for pf, pe in zip(fast, exact):
            for kp, kf in gains:
                a, b = simulate(sp, pf, kp, kf), simulate(sp, pe, kp, kf)
                dp = max(dp, np.max(np.abs(a.pos - b.pos)))
                du = max(du, np.max(np.abs(a.u - b.u)))
                (ma, ca, ta), (mb, cb, tb) = _figures(sp, a, pf, moving), _figures(sp, b, pe,
                                                                                  moving)
                r_mse = max(r_mse, abs(ma / mb - 1.0))
                r_cmd = max(r_cmd, np.max(np.abs(ca / cb - 1.0)))
                r_track = max(r_track, np.max(np.abs(ta / tb - 1.0)))
        print(f"{name}: {n} samples; CPU per replay {t_fast / runs * 1e3:.2f} ms with the "
              f"setting, {t_exact / runs * 1e3:.2f} ms exact ({t_exact / t_fast:.2f}x)")
        print(f"  largest |dp| {dp:.2e} m, |du| {du:.2e} m/s; relative change: MSE(CE) "
              f"{r_mse:.1e}, eq. 2 ratios {r_cmd:.1e}, following error {r_track:.1e}")
        res = optimize(sp, machine, {"nominal": True})
        certs = [certify_result(res, dataclasses.replace(scen, plants=p)) for p in (fast, exact)]
        for label, c in zip(("setting", "exact"), certs):
            s = c.summary()
            print(f"  certificate ({label:7s}): median {c.median:.6f} p90 {c.p90:.6f} worst "
                  f"{c.worst:.6f} breaks {len(c.breaks('schedule'))}/"
                  f"{len(c.breaks('baseline'))}/{len(c.breaks('schedule-only'))} max CE "
                  f"{s['schedule']['max_ce_um']:.4f} um")
        ra, rb = (np.array(list(c.summary()["ratio_per_plant"].values())) for c in certs)
        print(f"  certificate ratios per plant: largest relative change "
              f"{np.max(np.abs(ra / rb - 1.0)):.1e}")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
