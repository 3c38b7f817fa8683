"""What binds the law search: at each round's optimum, per override and searched plant, the
MSE ratio and the largest share of each allowed limit (eq. 2's velocity, acceleration and
jerk of the command per axis, the following error), and which support values sit on their
range's ends.

Run:  python bench/bench_law_binding.py [bench_law.py's options]

It runs :mod:`bench_law` with :meth:`oga.law.search._Context.search` wrapped to print, after
each round's search, the exact replays of its law on the round's plants (key -1 the nominal
plant, else the set's index). A share near 1 is a limit the line search stopped on; "at hi"
lists the parameters (per law axis its Kp support values, then its Kf ones) at the top of
their range (Kp: the range stable on every plant). After each certificate that fails, per
case the plants where the law alone breaks a check, counted by what breaks (the replay's
first violation: the limit, and whether in a rapid or a feed move) with the first few in
full. CPU times are process times; the wrap replays every case once more per round. A
benchmark prints figures; it asserts nothing.
"""

from __future__ import annotations

import os
import sys

for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

import bench_law  # noqa: E402
from oga.law import search as law_search  # noqa: E402
from oga.law.law import law_gains  # noqa: E402

_SEARCH = law_search._Context.search
_CERTIFY = law_search.certify_law


def _binding(ctx, theta, keys, reserve, its) -> None:
    law = ctx.layout.law(theta, ctx.fixed_kp, ctx.fixed_kf)
    at = lambda b: np.flatnonzero(np.isclose(theta, b, atol=1e-4)).tolist()  # noqa: E731
    print(f"  [binding] plants {keys} reserve {reserve:.3f} steps {its}; at lo {at(ctx.lo)} "
          f"at hi {at(ctx.hi)}", flush=True)
    for c in ctx.cases:
        kp, kf = law_gains(law, c.sp)
        for key in keys:
            mse, cr, fr = ctx.exact(c, key, kp, kf)
            acr, afr = ctx.allowed(c, key, reserve)
            r = np.round(cr / acr, 3)
            print(f"    {c.program} {c.override * 100:4.0f} % plant {key:3d} ratio "
                  f"{mse / ctx.base_mse(c, key):.3f} vel {r[:, 0].tolist()} acc "
                  f"{r[:, 1].tolist()} jerk {r[:, 2].tolist()} ferror "
                  f"{np.round(fr / afr, 3).tolist()}", flush=True)


def _certify(law, cases, machine, scenarios, screen=True):
    cert = _CERTIFY(law, cases, machine, scenarios, screen)
    print(f"  [certificate] {cert.status} on {len(cert.plants)} plants", flush=True)
    for (prog, o), c in cert.cases.items():
        only = [p for p in c.plants if p.schedule_only_break]
        if not only:
            continue
        kinds: dict[str, int] = {}
        for p in only:
            v = p.schedule.violations[0] if p.schedule.violations else "stability"
            key = " ".join(v.split()[:4]) + (" (rapid)" if "rapid" in v else " (feed)")
            kinds[key] = kinds.get(key, 0) + 1
        print(f"    {prog} {o * 100:4.0f} %: {len(only)} law-only breaks: {kinds}", flush=True)
        for p in only[:3]:
            print(f"      {p.label}: {'; '.join(p.schedule.violations[:2])}", flush=True)
    return cert


def _search(self, theta0, keys, reserve):
    theta, its = _SEARCH(self, theta0, keys, reserve)
    _binding(self, theta, keys, reserve, its)
    return theta, its


if __name__ == "__main__":
    law_search._Context.search = _search
    law_search.certify_law = _certify
    raise SystemExit(bench_law.main(sys.argv[1:]))
