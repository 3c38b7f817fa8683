"""Optimise the gain schedule of a program, compare it with the best fixed gains, export it.

Run:  python examples/02_optimize_gains.py
"""

from pathlib import Path

from feedplan import load_toolpath
from feedplan.plan import plan
from oga import load_machine, optimize
from oga.export.table import table_csv

here = Path(__file__).parent
machine = load_machine("ucp710")
setpoints = plan(load_toolpath(here / "data" / "reference_xz.ngc"), machine.planning_limits())

# full mode, all contouring axes, Kp and Kf; robust, as ucp710 has an uncertainty set
# (a minute or so; {"nominal": True}: the nominal model only, under a second)
result = optimize(setpoints, machine)
summary = result.summary()
print("best fixed gains:", summary["baseline"]["kp"], summary["baseline"]["kf"])
print(f"CE rms {summary['baseline']['rms_ce_um']:.2f} um -> {summary['optimized']['rms_ce_um']:.2f} um,"
      f" MSE ratio {result.ratio_mse:.3f}, verified: {result.status}")
if result.robust:  # the same table and baseline on the plants of the uncertainty set
    c = summary["certificate"]
    print(f"certificate {c['status']} on {c['plants']} plants: MSE ratio median "
          f"{c['ratio_median']:.3f}, p90 {c['ratio_p90']:.3f}, worst {c['ratio_worst']:.3f}")
if result.status == "ok":
    out = Path("out") / "reference_xz_table.csv"
    out.parent.mkdir(exist_ok=True)
    out.write_text(table_csv(result))
    print("table written to", out)
