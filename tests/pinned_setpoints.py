"""Pinned planner output for the nominal-search pins: the search is tested on fixed setpoints.

``tests/test_robust_search_nominal.py`` and ``tests/test_robust_cli.py`` compare nominal
schedules with those computed on commit c417bb6 (kept as arrays: :mod:`references`), and
``tests/test_replay_speed.py`` whole replays with those of 7adc0aa. A schedule depends on the
setpoints as well as on the search, so those tests take the setpoints from
``tests/data/pinned/nominal_setpoints.npz`` (written at commit 7adc0aa, whose planner gives the
same setpoints for these programs as c417bb6's): a planner change (corner blending, speed
profile) then moves the plan pins of ``tests/test_plan_speed.py`` and leaves these alone.

Written once with ``PYTHONPATH=. python tests/pinned_setpoints.py`` at that commit; running it
with a later planner would pin other setpoints under the old schedules, so do not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from feedplan.setpoints import Setpoints

DATA = Path(__file__).resolve().parent / "data"
FILE = DATA / "pinned" / "nominal_setpoints.npz"
#: Programs of tests/data whose nominal schedules are pinned.
PROGRAMS = ("reference_xz.ngc", "short_xz.ngc", "corner_steps.ngc", "sharp_corners_xy.ngc",
            "rapids_xy.ngc")
_FIELDS = ("s", "pos", "vel", "acc", "jerk", "block", "rapid")


def pinned_setpoints(name: str) -> Setpoints:
    """The setpoints of program ``name`` (one of :data:`PROGRAMS`) as planned at 7adc0aa
    on ucp710's planning limits, default tolerance and period."""
    with np.load(FILE) as z:
        plane = str(z[f"{name}:plane"])
        return Setpoints(dt=float(z[f"{name}:dt"]), plane=plane or None,
                         source=f"tests/data/{name}",
                         **{f: z[f"{name}:{f}"] for f in _FIELDS})


def main() -> None:
    from feedplan.read import load_toolpath
    from oga.model.machine import load_machine
    from oga.pipeline import plan_toolpath

    m = load_machine("ucp710")
    arrays = {}
    for name in PROGRAMS:
        sp = plan_toolpath(load_toolpath(DATA / name), m, feed_m_s=None, tol_m=2e-5)
        arrays.update({f"{name}:{f}": getattr(sp, f) for f in _FIELDS})
        arrays[f"{name}:dt"] = np.float64(sp.dt)
        arrays[f"{name}:plane"] = np.str_(sp.plane or "")
    np.savez_compressed(FILE, **arrays)


if __name__ == "__main__":
    main()
