"""The CAM corpus (tests/data/cam) whole: both G-code readers, then the plan and its check.

For each program: moves read (built-in reader), whether LinuxCNC's interpreter gives the same
path (each end point within 1e-9 m, arcs the same arcs) or refuses it (its message), the
warnings, then the plan on ucp710 (auto reader): samples, motion time, the check (limits,
tolerance, the programmed feed on every sample) and the CPU time of reading and planning.
The tests plan stretches of the long programs; this plans every program whole.

Usage: ``python bench/check_cam.py [PROGRAM ...]`` (default: the whole corpus). CPU times are
process times; a shared host inflates wall-clock times, not these much.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path as FilePath

import numpy as np

ROOT = FilePath(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feedplan.check import check_setpoints  # noqa: E402
from feedplan.gcode import parse_gcode  # noqa: E402
from feedplan.path import Arc  # noqa: E402
from feedplan.plan import program_tolerance_m  # noqa: E402
from oga.defaults import TOL_M  # noqa: E402
from oga.errors import GcodeError  # noqa: E402
from oga.model.machine import load_machine  # noqa: E402
from oga.pipeline import plan_toolpath  # noqa: E402

CAM = ROOT / "tests" / "data" / "cam"


def worst_difference_m(a, b) -> float:
    """Largest distance between the two paths' end points, start and arc centres (inf when the
    moves differ in number, kind, line or arc direction)."""
    if len(a.segments) != len(b.segments):
        return float("inf")
    worst = float(np.abs(a.start - b.start).max())
    for s, t in zip(a.segments, b.segments):
        if (type(s), s.line, s.rapid) != (type(t), t.line, t.rapid):
            return float("inf")
        worst = max(worst, float(np.abs(s.end - t.end).max()))
        if isinstance(s, Arc):
            if s.plane != t.plane or np.sign(s.sweep_rad) != np.sign(t.sweep_rad):
                return float("inf")
            worst = max(worst, float(np.abs(s.center - t.center).max()),
                        abs(s.sweep_rad - t.sweep_rad) * s.radius)
    return worst


def main(names: list[str]) -> int:
    machine = load_machine("ucp710")
    files = [FilePath(n) for n in names] or sorted(
        p for p in CAM.iterdir() if p.suffix in (".ngc", ".nc", ".gcode", ".tap"))
    print(f"{'program':34s} {'moves':>6s} {'linuxcnc':>22s} {'samples':>8s} {'motion s':>9s} "
          f"{'speed/F':>8s} {'dev um':>7s} {'check':>6s} {'read s':>7s} {'plan s':>7s}")
    failed = 0
    for f in files:
        text = f.read_text()
        t0 = time.process_time()
        builtin = parse_gcode(text, f.name, reader="builtin")
        t_read = time.process_time() - t0
        try:
            diff = worst_difference_m(builtin, parse_gcode(text, f.name, reader="linuxcnc"))
            lcnc = f"same, {diff:.1e} m" if diff <= 1e-9 else f"DIFFERS {diff:.1e} m"
            failed += diff > 1e-9
        except GcodeError as err:
            lcnc = f"refuses {err.line}:{err.column}"
        path = parse_gcode(text, f.name)
        t0 = time.process_time()
        sp = plan_toolpath(path, machine, feed_m_s=None, tol_m=TOL_M)
        check = check_setpoints(sp, path, machine.axis_limits(),
                                tol_m=program_tolerance_m(path, TOL_M))
        t_plan = time.process_time() - t0
        failed += not check.ok
        print(f"{f.name:34s} {len(builtin.segments):6d} {lcnc:>22s} {len(sp):8d} "
              f"{sp.duration:9.1f} {check.speed_ratio:8.4f} {check.max_deviation_m * 1e6:7.2f} "
              f"{'ok' if check.ok else 'FAIL':>6s} {t_read:7.2f} {t_plan:7.1f}")
        for w in path.warnings:
            print(f"{'':36s}warning: {w}")
        for v in check.violations:
            print(f"{'':36s}VIOLATION: {v}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
