"""The plant (``oga/model/plant.py``): a machine packed once, shared by every stage.

Checked against the packing it replaces (:func:`oga.model.simulate.axis_params`, the machine's
limits and dead times, :func:`oga.model.stability.stable_ends`) and by running the same replay
from a machine and from its plant (the same bits: the same kernels on the same numbers).
"""

from __future__ import annotations

import numpy as np
import pytest

from feedplan.setpoints import AXES
from oga.model.machine import load_machine
from oga.model.plant import Plant, PlantBatch, machine_of, plant_of
from oga.pipeline import plan_toolpath
from oga.search.robust.plants import scenario_set
from oga.model.simulate import axis_params
from oga.model.stability import stable_ends
from oga.verify.replay import verify
from feedplan.read import load_toolpath

from conftest import DATA


@pytest.fixture(scope="module")
def machine():
    return load_machine("ucp710")


def test_plant_holds_the_packing_limits_and_dead_time_of_its_machine(machine):
    plant = plant_of(machine)
    assert isinstance(plant, Plant) and plant.digest == machine.digest()
    assert plant_of(machine) is plant and plant_of(plant) is plant
    assert plant_of(load_machine("ucp710")) is plant  # an equal machine: the same plant
    assert machine_of(plant).digest() == machine.digest() and machine_of(machine) is machine
    lim = machine.axis_limits()
    for c, a in enumerate(AXES):
        if a in machine.axes:
            assert np.array_equal(plant.params[c], axis_params(machine, a))
            assert np.array_equal(plant.axis_params(a), axis_params(machine, a))
            assert plant.dead_samples[c] == machine.dead_time_samples_of(a)
        else:
            assert not plant.params[c].any() and plant.dead_samples[c] == 0
        assert list(plant.limits[c]) == [lim.vmax_m_s[c], lim.amax_m_s2[c], lim.jmax_m_s3[c]]
    assert not plant.params.flags.writeable and not plant.limits.flags.writeable
    assert plant.te_s == machine.te
    assert plant.stable_kp == {a: stable_ends(machine, a) for a in machine.axes}


def test_a_replay_from_the_plant_is_the_replay_from_the_machine(machine):
    sp = plan_toolpath(load_toolpath(DATA / "reference_xz.ngc"), machine, feed_m_s=None,
                       tol_m=2e-5)
    n = len(sp)
    kp, kf = np.full((n, 3), 2.5), np.full((n, 3), 0.7)
    bounds = {a: machine.gains.kp_bounds_m_min_per_mm for a in machine.axes}
    a, b = verify(sp, machine, kp, kf, bounds), verify(sp, plant_of(machine), kp, kf, bounds)
    assert np.array_equal(a.pos, b.pos) and np.array_equal(a.ce, b.ce)
    assert np.array_equal(a.command_ratio, b.command_ratio) and a.violations == b.violations


def test_a_scenario_set_is_a_batch_of_plants_packed_once_each(machine):
    scen = scenario_set(machine, n=6, seed=3)
    batch = scen.batch
    assert isinstance(batch, PlantBatch) and scen.batch is batch and len(batch) == len(scen)
    assert batch.params.shape[:2] == (len(scen), 3) and batch.limits.shape == (len(scen), 3, 3)
    assert batch.machines == scen.plants and batch.labels == scen.labels
    assert batch.te_s == machine.te
    for s, m in enumerate(scen.plants):
        for c, a in enumerate(AXES):
            if a in m.axes:
                assert np.array_equal(batch.params[s, c], axis_params(m, a))
                assert batch.dead_samples[s, c] == m.dead_time_samples_of(a)
    # the set's extra dead time shows in the stacked dead times (the corners reach both ends)
    assert len(set(batch.dead_samples[:, 0])) > 1
    with pytest.raises(ValueError, match="labels"):
        PlantBatch.of(scen.plants, ("one",))
