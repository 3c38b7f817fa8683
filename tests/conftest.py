"""Fixtures shared by the search and optimize tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from feedplan.plan import plan
from feedplan.read import load_toolpath
from oga.machine import load_machine

DATA = Path(__file__).parent / "data"

#: The test files of a minute or more on CI's two cores (pytest --durations, 2026-11-27),
#: longest first: they run first, so the workers end together (xdist hands out whole files in
#: collection order: the longest last left one worker alone for 3.5 of the suite's 14 min).
LONGEST_FIRST = ("test_identify_e2e.py", "test_cli.py", "test_gcode_cam.py", "test_docs.py",
                 "test_cluster_batch.py", "test_api.py", "test_lcnc_production.py",
                 "test_identify.py", "test_api_dask.py", "test_two_mass.py")


def pytest_collection_modifyitems(config, items):
    """The files of :data:`LONGEST_FIRST` first, in its order; the rest as collected."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="module")
def machine():
    """The reference machine ucp710."""
    return load_machine("ucp710")


@pytest.fixture(scope="module")
def short(machine):
    """A short XZ contour (line, concave and convex arc, line) planned for ucp710."""
    return plan(load_toolpath(DATA / "short_xz.ngc"), machine.planning_limits())
