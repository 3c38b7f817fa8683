"""``oga ranges``: stable Kp range per axis; with a toolpath, the kinematically feasible
fixed gains per contouring axis and the best equal fixed gains."""

from __future__ import annotations

import argparse

from oga.cli._common import add_toolpath_args, check_files, load_inputs, write_json

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ranges",
        help="stable and kinematically feasible gain ranges, best fixed gains",
        description=(
            "Stable Kp range of every axis (phase and gain margins of the linearised "
            "position loop). With a TOOLPATH: every fixed (Kp, Kf) of the grid simulated "
            "on its setpoints, the kinematically feasible ones per contouring axis (eq. 2, "
            "and the machine's following-error limit where it sets one), the "
            "MSE of the contour error with equal gains on all contouring axes, and the "
            "best equal fixed gains."
        ),
    )
    add_toolpath_args(p, toolpath_required=False)
    p.add_argument("--json", metavar="OUT.json", help="write the ranges as JSON")
    p.set_defaults(func=run)


def _stability_table(machine, stability: dict) -> list[str]:
    names = list(stability)
    g = machine.gains
    lines = [
        f"machine {machine.name}: stable Kp (PM >= {g.pm_min_deg} deg, GM >= {g.gm_min_db} dB, "
        f"bounds {list(g.kp_bounds_m_min_per_mm)} (m/min)/mm); '*' = in the stable range",
        "  Kp (m/min)/mm" + "".join(f"  {a} PM deg  {a} GM dB" for a in names),
    ]
    first = stability[names[0]]
    for i, kp in enumerate(first.kp):
        cells = []
        for a in names:
            r = stability[a]
            mark = "*" if r.kp_min <= kp <= r.kp_max else " "
            cells.append(f"  {r.pm_deg[i]:8.1f}{mark} {r.gm_db[i]:7.1f}")
        lines.append(f"  {kp:13.1f}" + "".join(cells))
    lines += [f"  {stability[a].message}" for a in names]
    return lines


def _ranges_table(ranges, setpoints) -> list[str]:
    axes = ", ".join(ranges.axes)
    lines = [
        f"toolpath {setpoints.source or '-'}: {len(setpoints)} samples "
        f"({setpoints.duration:.3f} s), contouring axes {axes}",
        "kinematically feasible (Kp, Kf): "
        + ", ".join(f"{a} {k.count} of {k.feasible.size}" for a, k in ranges.kinematic.items()),
        f"MSE(CE) um^2 with equal gains on {axes} ('-': infeasible on some axis, '*': best)",
        "  Kp \\ Kf" + "".join(f"{kf:9.1f} " for kf in ranges.kf_grid).rstrip(),
    ]
    best = ranges.best_fixed
    a0 = ranges.axes[0]
    best_cell = (None, None) if best is None else (best.kp[a0], best.kf[a0])
    for i, kp in enumerate(ranges.kp_grid):
        cells = []
        for j, kf in enumerate(ranges.kf_grid):
            if not ranges.feasible[i, j]:
                cells.append(f"{'-':>9} ")
                continue
            mark = "*" if best_cell == (kp, kf) else " "
            cells.append(f"{ranges.mse_ce_m2[i, j] * 1e12:9.1f}{mark}")
        lines.append((f"  {kp:7.1f}" + "".join(cells)).rstrip())
    if best is None:
        lines.append(f"best fixed gains: none (no equal-gain configuration is feasible on {axes})")
    else:
        m = best.metrics.to_dict()
        lines.append(
            f"best fixed gains on {axes}: Kp {best.kp[a0]} (m/min)/mm, Kf {best.kf[a0]}: "
            f"MSE(CE) {m['mse_ce_um2']:.2f} um^2, RMS {m['rms_ce_um']:.2f} um, "
            f"max {m['max_ce_um']:.2f} um"
        )
    return lines


def run(args: argparse.Namespace) -> int:
    check_files(args, "json")  # before the compiled kernels load

    from oga.errors import OptionError
    from oga.model.machine import load_machine
    from oga.search.ranges import gain_ranges, stability_to_dict
    from oga.model.stability import stable_range

    if args.toolpath is None:
        given = [f"--{f}" for f in ("feed", "tolerance") if getattr(args, f) is not None]
        if given:
            raise OptionError(f"{' and '.join(given)}: meaningful only with a TOOLPATH")
        machine = load_machine(args.machine)
        stability = {a: stable_range(machine, a) for a in sorted(machine.axes)}
        print("\n".join(_stability_table(machine, stability)))
        data = {
            "machine": machine.name,
            "axes": {a: {"stability": stability_to_dict(r)} for a, r in stability.items()},
        }
    else:
        from oga.pipeline import plan_toolpath

        path, machine, feed_m_s, tol_m = load_inputs(args)
        setpoints = plan_toolpath(path, machine, feed_m_s=feed_m_s, tol_m=tol_m)
        ranges = gain_ranges(setpoints, machine)
        print("\n".join(_stability_table(machine, ranges.stability)))
        print("\n".join(_ranges_table(ranges, setpoints)))
        data = ranges.to_dict()
    if args.json:
        write_json(args.json, data)
    return 0

