"""Dead time per axis, whole or fractional: the machine file, the simulation, the linear model
and stability, the uncertainty set's plants, and what identification writes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.errors import MachineError
from oga.model.linear import dead_line, position_open_loop
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.pipeline import plan_toolpath
from oga.search.robust.plants import perturbed_machine, scenario_set
from oga.model.simulate import axis_params, simulate_axis
from oga.model.response import simulate
from oga.model.stability import margins, stable_range

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")


def _with(changes: dict, timing: dict | None = None, base=UCP):
    """``base`` with per-axis fields ``{axis: {field: value}}`` and timing fields set."""
    data = base.model_dump(mode="json", exclude_none=True)
    for a, fields in changes.items():
        data["axes"][a].update(fields)
    data["timing"].update(timing or {})
    return machine_from_dict(data)


@pytest.fixture(scope="module")
def short():
    return plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), UCP, feed_m_s=None, tol_m=2e-5)


def test_the_axis_value_overrides_the_machine_value(short):
    own = _with({"x": {"dead_time_samples": 3}})  # the machine's stays 2
    everywhere = _with({}, {"dead_time_samples": 3})
    assert own.timing.dead_time_samples == 2 and own.dead_time_samples_of("x") == 3.0
    assert own.dead_time_samples_of("z") == 2.0 and UCP.axes["x"].dead_time_samples is None
    a, b, c = (simulate(short, m, 2.5, 0.8) for m in (own, everywhere, UCP))
    np.testing.assert_array_equal(a.pos[:, 0], b.pos[:, 0])  # x: the axis's own dead time
    np.testing.assert_array_equal(a.pos[:, 2], c.pos[:, 2])  # z: the machine's
    assert np.max(np.abs(a.pos[:, 0] - c.pos[:, 0])) > 1e-7
    for kp in (1.5, 2.5):
        assert margins(own, "x", kp) == margins(everywhere, "x", kp)
        assert margins(own, "z", kp) == margins(UCP, "z", kp)
    r1, r2 = stable_range(own, "x"), stable_range(everywhere, "x")
    assert (r1.kp_min, r1.kp_max) == (r2.kp_min, r2.kp_max)
    np.testing.assert_array_equal(r1.pm_deg, r2.pm_deg)


@pytest.mark.parametrize("value, message", [(-1, "greater than or equal to 0"),
                                            (101, "less than or equal to 100"),
                                            ("two", "valid number"), (math.nan, "finite")])
def test_a_bad_axis_dead_time_names_its_field(value, message):
    with pytest.raises(MachineError, match=rf"axes\.z\.dead_time_samples: .*{message}"):
        _with({"z": {"dead_time_samples": value}})


def test_a_fractional_dead_time_is_continuous_and_between_its_whole_neighbours(short):
    """d -> f u[k-L] + (1 - f) u[k-L+1]: a dead time of 2 + 1e-9 (or 3 - 1e-9) moves the
    positions by 1e-9 of what one sample moves them; 2.5 lies between 2 and 3."""
    def x_positions(d):
        return simulate(short, _with({"x": {"dead_time_samples": d}}), 2.5, 0.8).pos[:, 0]

    p2, p3 = x_positions(2), x_positions(3)
    step = np.max(np.abs(p3 - p2))
    assert step > 1e-6
    for d, near in ((2 + 1e-9, p2), (3 - 1e-9, p3)):
        assert np.max(np.abs(x_positions(d) - near)) < 1e-7 * step
    p_half = x_positions(2.5)
    gap = np.max(np.abs(p_half - 0.5 * (p2 + p3)))
    assert gap < 0.1 * step and np.max(np.abs(p_half - p2)) > 0.3 * step


@pytest.mark.parametrize("d", [0.3, 1.0, 1.6, 2.5])
def test_the_linear_model_holds_the_fractional_dead_time(d):
    """On the linear plant (no Coulomb friction, no force limit) the kernel is the lifted
    model with the dead-time line of :func:`oga.model.linear.position_open_loop`, closed by the
    position loop: positions within 1e-9 of the motion."""
    lin = _with({"x": {"dead_time_samples": d,
                       "cascade": {**UCP.axes["x"].cascade.model_dump(), "coulomb_n": 0.0,
                                   "static_n": 0.0, "force_limit_n": 1e12}}})
    line, frac = dead_line(lin, "x")
    assert (line, frac) == ((math.ceil(d), d - math.floor(d)) if frac else (int(d), 0.0))
    n = 600
    t = np.arange(n) * lin.te
    pd = 0.01 * (1 - np.cos(np.pi * np.minimum(t / 0.3, 1.0))) / 2
    vd = np.gradient(pd, lin.te)
    kp, kf = 2.5 * KP_SI_PER_M_MIN_PER_MM, 0.6
    a, b, c, _ = position_open_loop(lin, "x", 1.0)  # output: the position (Kp = 1 1/s)
    s = np.zeros(a.shape[0])
    ref = np.empty(n)
    for k in range(n):
        ref[k] = (c @ s)[0]
        s = a @ s + b[:, 0] * (kp * (pd[k] - ref[k]) + kf * vd[k])
    got, _ = simulate_axis(axis_params(lin, "x"), 0.0, pd, vd, kp, kf)
    assert np.max(np.abs(got - ref)) <= 1e-9 * 0.01


def test_a_half_sample_costs_half_a_sample_of_phase():
    """At the gain crossover the fractional line lags by about its dead time times w Te
    (its magnitude droop moves the crossover slightly): PM(2) - PM(2.5) is half of
    PM(2) - PM(3) within 2 %."""
    pm = {d: margins(_with({"x": {"dead_time_samples": d}}), "x", 2.0).pm_deg for d in (2, 2.5, 3)}
    assert pm[2] - pm[2.5] == pytest.approx(0.5 * (pm[2] - pm[3]), rel=0.02)


def test_a_plant_gets_extra_dead_time_only_on_axes_whose_range_allows_it():
    """x identified without doubt (range (0, 0)), z and y with the preset's (0, 1): every plant
    of the set keeps x's dead time; the corners give z its extra sample."""
    m = _with({"x": {"uncertainty": {**UCP.axes["x"].uncertainty.model_dump(),
                                     "dead_time_extra_samples": [0, 0]}},
               "z": {"dead_time_samples": 3}})
    s = scenario_set(m, n=8, seed=3)
    got_z = set()
    for plant, (_, extra) in zip(s.plants, s.draws):
        assert plant.dead_time_samples_of("x") == 2.0
        assert plant.dead_time_samples_of("z") == 3.0 + extra
        got_z.add(plant.dead_time_samples_of("z"))
    assert got_z == {3.0, 4.0}
    # ucp710's plants are as before: one dead time for all axes, in the timing
    p = perturbed_machine(UCP, {}, 1)
    assert p.timing.dead_time_samples == 3 and all(
        ax.dead_time_samples is None for ax in p.axes.values())
