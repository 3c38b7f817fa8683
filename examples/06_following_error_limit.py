"""Bound the following error: the schedule may lag along straight moves, a limit keeps it.

Controllers stop the machine when an axis lags its setpoint by more than their
following-error limit (LinuxCNC: FERROR / MIN_FERROR). Set that limit in the machine
file, per axis, as ``ferror_max_m``: the best fixed gains, the search and the
verification then keep every feed sample within it.

Run:  python examples/06_following_error_limit.py
"""

import tomllib
from pathlib import Path

from feedplan import load_toolpath
from feedplan.plan import plan
from oga import optimize
from oga.model.machine import machine_from_dict

here = Path(__file__).parent
data = tomllib.loads((here.parent / "oga" / "presets" / "ucp710.toml").read_text())
free = machine_from_dict(data)
setpoints = plan(load_toolpath(here / "data" / "reference_xz.ngc"), free.planning_limits())

data["name"] = "ucp710-ferror"
for axis in ("x", "z"):
    data["axes"][axis]["limits"]["ferror_max_m"] = 0.4e-3  # 0.4 mm
limited = machine_from_dict(data)

for machine in (free, limited):
    result = optimize(setpoints, machine, {"nominal": True})  # the exact-model search
    s = result.summary()
    lag = ", ".join(f"{a} {s['baseline']['track_max_um'][a] / 1e3:.3f} -> "
                    f"{s['optimized']['track_max_um'][a] / 1e3:.3f} mm" for a in ("x", "z"))
    print(f"{machine.name}: MSE ratio {result.ratio_mse:.3f} ({result.status}), "
          f"largest following error {lag}")
