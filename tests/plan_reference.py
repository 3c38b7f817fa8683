"""The programs whose planned setpoints the suite keeps, and how they are planned.

``tests/references.py`` stores, per program of :data:`PROGRAMS`, the sample count, source
lines, rapid flags and every :data:`STRIDE`-th position in ``tests/data/reference/plan.npz``;
``tests/test_plan_speed.py`` plans the programs again and compares (positions within a
tolerance measured across CPUs). Regenerate the arrays (one command, from the repository root)
when the planner's output is meant to change (corner handling, acceleration shares ...)::

    PYTHONPATH=. python tests/references.py regen plan

It plans at ucp710's planning limits with the default tolerance and sample period,
as ``oga plan`` does.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path as FilePath

import numpy as np

from feedplan.plan import plan
from feedplan.read import load_toolpath, read_toolpath
from feedplan.setpoints import Setpoints
from oga.model.machine import load_machine

ROOT = FilePath(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
#: Programs of tests/data (lines, arcs, helices, rapids, corners, fitted micro-segments).
FILES = ("reference_xz.ngc", "circle_r50_f3000.ngc", "helix_r20.ngc", "freeform_xz.ngc",
         "sharp_corners_xy.ngc", "corner_steps.ngc", "rapids_xy.ngc", "short_xz.ngc",
         "cncjs_toolpath.nc")
#: Generated micro-segment program (bench/bench_plan.py's freeform), segments.
MICRO_SEGMENTS = 2000
PROGRAMS = (*FILES, f"micro_{MICRO_SEGMENTS}")
#: Every STRIDE-th position is stored.
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
