"""The equal-gain search with the moving axes run side by side (:func:`oga.model.simulate.run_axes`
per chunk, ARX axes one by one) against the per-axis path of the full tables
(:func:`oga.search.ranges.gain_ranges`: each axis alone through :func:`oga.model.simulate.simulate_axis`):
the same best gains, MSE and metrics to the last bit, on nominal, perturbed and mixed
(cascade and ARX) machines; and the peaks and sums the search keeps for each complete
configuration against a fresh per-axis replay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from feedplan.setpoints import AXES
from oga.model.contour import contour_error_of
from oga.defaults import TOL_M
from oga.model.kinematics import command_peaks
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.pipeline import plan_toolpath
from feedplan.read import load_toolpath
from oga.search.ranges import EqualGainMemo, best_fixed_gains, gain_ranges
from oga.search.robust.plants import scenario_set
from oga.model.simulate import axis_params, simulate_axis

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")
MCV = load_machine("mcv-op")
SCEN = scenario_set(UCP, n=8, seed=3)
#: the corner "friction-lo mass-lo kv-hi tn-lo dead-hi" (an extra sample of dead time),
#: a Monte Carlo plant
DEAD_HI, MC = SCEN.plants[8 + 5], SCEN.plants[5]


def _mixed():
    """ucp710 with mcv-op's ARX x loop as its z axis."""
    data = UCP.model_dump(exclude_none=True)
    data["axes"]["z"] = MCV.model_dump(exclude_none=True)["axes"]["x"]
    return machine_from_dict(data)


MIXED = _mixed()


def _planned(name, machine):
    return plan_toolpath(load_toolpath(DATA / name), machine, feed_m_s=None, tol_m=TOL_M)


def test_the_plants_differ_from_the_nominal_one():
    assert DEAD_HI.timing.dead_time_samples == UCP.timing.dead_time_samples + 1
    for plant in (DEAD_HI, MC):
        assert not np.array_equal(axis_params(plant, "x"), axis_params(UCP, "x"))
    assert MIXED.axes["z"].kind == "arx" and MIXED.axes["x"].kind == "cascade"


@pytest.mark.parametrize("machine, name", [
    (DEAD_HI, "short_xz.ngc"), (DEAD_HI, "circle_r50_f3000.ngc"),
    (MC, "short_xz.ngc"), (MC, "circle_r50_f3000.ngc"),
    (MIXED, "short_xz.ngc"), (UCP, "short_xz.ngc"),
])
def test_best_fixed_gains_equal_the_per_axis_tables(machine, name):
    sp = _planned(name, machine)
    full = gain_ranges(sp, machine)
    ref = full.best_fixed
    memo = EqualGainMemo()
    fast = best_fixed_gains(sp, machine, memo=memo)
    assert ref is not None and fast is not None
    assert fast.kp == ref.kp and fast.kf == ref.kf
    assert fast.mse_ce_m2 == ref.mse_ce_m2  # the same bits
    assert fast.metrics == ref.metrics
    # what the search learnt agrees with the tables: a configuration that broke a limit is
    # infeasible there, one simulated to the end feasible
    assert memo.status.shape == full.feasible.shape
    assert not full.feasible[memo.status == 1].any()
    assert full.feasible[memo.status == 3].all()
    assert (memo.status == 3).any()
    # it learnt a break where the tables have one (MIXED: its Kp range is narrower)
    assert (memo.status == 1).any() == (not full.feasible.all()) or machine is MIXED


@pytest.mark.parametrize("machine, name", [(DEAD_HI, "short_xz.ngc"),
                                           (MIXED, "short_xz.ngc"),
                                           (MC, "circle_r50_f3000.ngc")])
def test_kept_peaks_and_sums_are_those_of_a_per_axis_replay(machine, name):
    sp = _planned(name, machine)
    memo = EqualGainMemo()
    best_fixed_gains(sp, machine, memo=memo)
    full = gain_ranges(sp, machine)
    feed = ~sp.rapid
    axes = [AXES[c] for c in sp.moving_axes]
    done = np.argwhere(memo.status == 3)
    assert len(done) >= 1
    for i, j in done[:: max(1, len(done) // 4)]:
        kp, kf = float(full.kp_grid[i]), float(full.kf_grid[j])
        pa = np.array(sp.pos)
        for a, axis in enumerate(axes):
            c = AXES.index(axis)
            pd = np.ascontiguousarray(sp.pos[:, c])
            p, u = simulate_axis(axis_params(machine, axis), pd[0], pd,
                                 np.ascontiguousarray(sp.vel[:, c]),
                                 kp * KP_SI_PER_M_MIN_PER_MM, kf)
            pa[:, c] = p
            v_pk, a_pk, j_pk = command_peaks(u, np.ones(len(u), dtype=bool), machine.te)
            np.testing.assert_array_equal(memo.peaks[i, j, a],
                                          [v_pk, a_pk, j_pk, np.abs(pd - p).max()])
        ce = contour_error_of(sp, pa)[feed]
        assert memo.sse[i, j] == pytest.approx(float(np.sum(ce * ce)), rel=1e-12)
