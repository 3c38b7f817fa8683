"""The compiled walk of the stable Kp range (``oga.model.stability._walk_modal``) gives the ends of
the Python walk over :func:`oga.model.stability._margins` (brentq, numpy eigenvalues), on the plants
of ucp710's default set (Monte Carlo and corners, dead time +0 and +1 sample) and under
stricter criteria and narrower bounds that move the ends; the ARX axes of mcv-op (no modal
form) keep the Python walk, whose ends are :func:`oga.model.stability.stable_range`'s."""

from collections import OrderedDict

import numpy as np
import pytest

import oga.model.stability as stability
from oga.model.machine import load_machine, machine_from_dict
from oga.search.robust.plants import scenario_set

UCP = load_machine("ucp710")
PLANTS = scenario_set(UCP, n=12, seed=23).plants


@pytest.fixture(autouse=True)
def fresh_memo(monkeypatch):
    for name in ("_LOOPS", "_TABLES", "_ENDS"):
        monkeypatch.setattr(stability, name, OrderedDict())


def _with_gains(machine, **gains):
    data = machine.model_dump(mode="json", exclude_none=True)
    data["gains"].update(gains)
    return machine_from_dict(data)


def _both(machine, axis):
    loop = stability._Loop(machine, axis)
    assert loop.modal is not None
    return stability._walk_compiled(loop, machine.gains), stability._walk(loop, machine.gains)


def _same(a, b):
    return all((np.isnan(x) and np.isnan(y)) or x == y for x, y in zip(a, b))


def test_compiled_walk_equals_the_python_walk_on_the_set():
    ends = []
    for plant in PLANTS:
        for axis in ("x", "z"):
            fast, slow = _both(plant, axis)
            assert _same(fast, slow), (plant.name, axis, fast, slow)
            ends.append(fast)
    assert len(set(ends)) > 3  # the plants do have different ranges
    assert {p.timing.dead_time_samples for p in PLANTS} == {UCP.timing.dead_time_samples,
                                                             UCP.timing.dead_time_samples + 1}


@pytest.mark.parametrize("gains", [{"pm_min_deg": 60.0}, {"pm_min_deg": 20.0, "gm_min_db": 3.0},
                                   {"kp_bounds_m_min_per_mm": [1.2, 2.1]},
                                   {"pm_min_deg": 89.9}])
def test_compiled_walk_equals_the_python_walk_under_other_criteria(gains):
    seen = []
    for plant in PLANTS[::3] + (UCP,):
        fast, slow = _both(_with_gains(plant, **gains), "x")
        assert _same(fast, slow), (plant.name, gains, fast, slow)
        seen.append(fast)
    if gains.get("pm_min_deg") == 89.9:  # nothing qualifies: both say so
        assert all(np.isnan(e).all() for e in seen)
    else:
        assert all(np.isfinite(e).all() for e in seen)


def test_arx_axes_walk_to_the_ends_of_the_stable_range():
    # mcv-op's ARX loops have near-defective poles: no modal form, the Python walk is used
    mcv = load_machine("mcv-op")
    for axis in ("x", "y"):
        assert mcv.axes[axis].kind == "arx"
        assert stability._Loop(mcv, axis).modal is None
        ends = stability.stable_ends(mcv, axis)
        stability._TABLES.clear()
        r = stability.stable_range(mcv, axis)
        assert _same(ends, (r.kp_min, r.kp_max)) and np.isfinite(ends).all()
