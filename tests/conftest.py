"""Fixtures shared by the search and optimize tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from feedplan.plan import plan
from feedplan.read import load_toolpath
from oga.model.machine import load_machine

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def machine():
    """The reference machine ucp710."""
    return load_machine("ucp710")


@pytest.fixture(scope="module")
def short(machine):
    """A short XZ contour (line, concave and convex arc, line) planned for ucp710."""
    return plan(load_toolpath(DATA / "short_xz.ngc"), machine.planning_limits())
