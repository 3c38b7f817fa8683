"""The fixed gains, OGA and the controllers of the literature on one circle of the mcv-op plant.

Run:  python examples/05_compare_controllers.py
"""

from pathlib import Path

from feedplan.read import load_toolpath
from oga.controllers.compare import compare
from oga.defaults import TOL_M
from oga.model.machine import load_machine
from oga.pipeline import plan_toolpath

machine = load_machine("mcv-op")  # the CCC/ZPETC paper's ARX velocity loops
circle = Path(__file__).parents[1] / "tests" / "data" / "circle_r50_f3000.ngc"
setpoints = plan_toolpath(load_toolpath(circle), machine, feed_m_s=3000 / 60000, tol_m=TOL_M)
result = compare(setpoints, machine, ["fixed", "oga", "ccc", "afsmc"])
for row in result.rows:
    print(f"{row.name:6s} RMS CE {row.rms_ce_um:6.3f} um, max {row.max_ce_um:6.3f} um, "
          f"jerk ratio {row.jerk_ratio:.2f}, needs firmware: {row.needs_firmware}")
