"""The nominal search (one plant) gives the schedules it gave before the multi-scenario kernel.

The schedules were pinned first as SHA-256 digests on commit c417bb6; digests of floats pin
one CPU (OpenBLAS's kernels and numpy's SIMD differ from one to another), so they are kept
as arrays in ``tests/data/reference/search.npz`` (regenerated at this commit from the same
schedules: ``PYTHONPATH=. python tests/references.py regen search``) and compared within
:data:`references.TOL` (measured across CPU configurations). The setpoints are those planned
at 7adc0aa (:mod:`pinned_setpoints`: the planner may change, the search may not).
"""

from __future__ import annotations

import pytest

import references
from pinned_setpoints import pinned_setpoints


@pytest.mark.parametrize("name", references.SEARCH_PROGRAMS)
def test_nominal_schedule_is_the_stored_one(name):
    want_n = {"reference_xz.ngc": 3004, "short_xz.ngc": 1070, "corner_steps.ngc": 783,
              "sharp_corners_xy.ngc": 3379, "rapids_xy.ngc": 5080}[name]
    assert len(pinned_setpoints(name)) == want_n
    got = references.cases("search")[name]()
    assert references.compare("search", name, got) == []
