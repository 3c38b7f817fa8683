"""Fixtures shared by the search and optimize tests, and the ``portable`` marker."""

from __future__ import annotations

from pathlib import Path

import pytest

#: Test files that compare numerical results with stored reference arrays or across code
#: paths (bit for bit, in one process): marked ``portable``. CI runs them a second time with
#: another CPU's rounding (.ci/run: numba's generic target, OpenBLAS's Haswell kernels,
#: numpy without AVX-512, glibc's libm without FMA), so that an assumption that holds on one
#: CPU only fails there (docs/explanation/portability.md).
PORTABLE = {"test_plan_speed.py", "test_robust_search_nominal.py", "test_replay_speed.py",
            "test_dead_time.py", "test_tangent.py", "test_simulate.py", "test_stability.py",
            "test_stability_walk.py", "test_friction_linear.py", "test_contour.py",
            "test_fixed_costs.py", "test_ranges_fused.py"}


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.name in PORTABLE or item.get_closest_marker("portable"):
            item.add_marker(pytest.mark.portable)

from feedplan.plan import plan
from feedplan.read import load_toolpath
from oga.machine import load_machine

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def machine():
    """The reference machine ucp710."""
    return load_machine("ucp710")


@pytest.fixture(scope="module")
def short(machine):
    """A short XZ contour (line, concave and convex arc, line) planned for ucp710."""
    return plan(load_toolpath(DATA / "short_xz.ngc"), machine.planning_limits())
