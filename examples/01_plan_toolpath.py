"""Plan jerk-limited 1 ms setpoints for a G-code program and check them.

Run:  python examples/01_plan_toolpath.py
"""

from pathlib import Path

from feedplan import load_toolpath
from feedplan.check import check_setpoints
from feedplan.plan import plan
from oga import load_machine

here = Path(__file__).parent
machine = load_machine("ucp710")
path = load_toolpath(here / "data" / "reference_xz.ngc")
setpoints = plan(path, machine.planning_limits())  # the interpolator keeps a reserve for the loop
check = check_setpoints(setpoints, path, machine.axis_limits())

print(f"{len(path.segments)} segments, {path.length * 1e3:.1f} mm, plane {setpoints.plane}")
print(f"{len(setpoints)} samples, {setpoints.duration:.3f} s, "
      f"max deviation {check.max_deviation_m * 1e6:.2f} um, limits ok: {check.ok}")
