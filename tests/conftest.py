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


@pytest.fixture(scope="module")
def short_xz(machine):
    """ucp710 and short_xz planned for it at a 20 um tolerance (the robust search's tests)."""
    from oga.pipeline import plan_toolpath
    return machine, plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), machine, feed_m_s=None,
                                  tol_m=2e-5)
