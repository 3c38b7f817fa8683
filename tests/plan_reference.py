"""Pinned planner output: the setpoints of a few programs, to prove speed work changes nothing.

``tests/data/pinned/plan_reference.npz`` holds, per program of :data:`PROGRAMS`, the SHA-256 of
the planned positions (float64 bytes), source lines and rapid flags, the sample count,
and every :data:`STRIDE`-th position (to say by how much a changed plan differs).
``tests/test_plan_speed.py`` plans the programs again and compares.

Regenerate it (one command, from the repository root) when the planner's output is
meant to change (corner handling, acceleration shares ...)::

    PYTHONPATH=. python tests/plan_reference.py

It plans at ucp710's planning limits with the default tolerance and sample period,
as ``oga plan`` does.
"""

from __future__ import annotations

import hashlib
import importlib.util
import sys
from pathlib import Path as FilePath

import numpy as np

from feedplan.plan import plan
from feedplan.read import load_toolpath, read_toolpath
from feedplan.setpoints import Setpoints
from oga.machine import load_machine

ROOT = FilePath(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
REFERENCE = DATA / "pinned" / "plan_reference.npz"  # not beside the programs (globbed)
#: Programs of tests/data (lines, arcs, helices, rapids, corners, fitted micro-segments).
FILES = ("reference_xz.ngc", "circle_r50_f3000.ngc", "helix_r20.ngc", "freeform_xz.ngc",
         "sharp_corners_xy.ngc", "corner_steps.ngc", "rapids_xy.ngc", "short_xz.ngc",
         "cncjs_toolpath.nc")
#: Generated micro-segment program (bench/bench_plan.py's freeform), segments.
MICRO_SEGMENTS = 2000
PROGRAMS = (*FILES, f"micro_{MICRO_SEGMENTS}")
#: Every STRIDE-th position is stored as well.
STRIDE = 50


def _bench():
    spec = importlib.util.spec_from_file_location("bench_plan", ROOT / "bench" / "bench_plan.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def micro_program(n: int) -> str:
    """The bench's generated freeform program of ``n`` G1 micro-segments (G-code text)."""
    return _bench().synthetic_program(n)


def plan_program(name: str) -> Setpoints:
    """Plan one program of :data:`PROGRAMS` as ``oga plan`` does (ucp710)."""
    limits = load_machine("ucp710").planning_limits()
    if name.startswith("micro_"):
        path = read_toolpath(micro_program(int(name[6:])), "gcode", source=name)
    else:
        path = load_toolpath(DATA / name)
    return plan(path, limits)


def digest(sp: Setpoints) -> str:
    """SHA-256 of the planned positions, source lines and rapid flags (exact bytes)."""
    h = hashlib.sha256()
    for a in (sp.pos, sp.block, sp.rapid):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def main() -> int:
    out = {}
    for name in PROGRAMS:
        sp = plan_program(name)
        out[f"{name}/sha256"] = np.array(digest(sp))
        out[f"{name}/samples"] = np.array(len(sp))
        out[f"{name}/pos"] = sp.pos[::STRIDE]
        print(f"{name}: {len(sp)} samples, {digest(sp)[:16]}")
    np.savez_compressed(REFERENCE, **out)
    print(f"wrote {REFERENCE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
