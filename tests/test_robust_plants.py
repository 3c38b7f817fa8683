"""Scenario plants of an uncertainty set: the draw's law, the corners, the perturbed values."""

from __future__ import annotations

import numpy as np
import pytest

from oga.defaults import ROBUST_FRICTION_LINEAR_BELOW_M_S
from oga.errors import MachineError
from oga.model.machine import FACTOR_FIELDS, PRESETS, load_machine, machine_from_dict
from oga.search.robust.plants import (
    corner_draws,
    monte_carlo_draws,
    perturbed_machine,
    scenario_set,
)

ROBUST = load_machine("ucp710")
_data = ROBUST.model_dump(mode="json", exclude_none=True)
for _ax in _data["axes"].values():
    _ax.pop("uncertainty")
NOMINAL = machine_from_dict(_data)


def test_ucp710_preset_carries_the_documented_set():
    a = ROBUST.model_dump(exclude={"name", "source"})
    b = NOMINAL.model_dump(exclude={"name", "source"})
    assert "ucp710-robust" not in PRESETS  # the set lives in ucp710 itself
    assert load_machine("mcv-op").axes["x"].uncertainty is None  # ARX axes: no set (preset doc)
    for ax in a["axes"].values():
        unc = ax.pop("uncertainty")
        assert unc["coulomb_n"] == unc["static_n"] == unc["viscous_n_s_m"] == (0.5, 1.5)
        assert unc["mass_kg"] == unc["kv_n_s_m"] == (0.8, 1.2) and unc["tn_s"] == (0.7, 1.3)
        assert unc["force_lag_s"] == unc["stribeck_m_s"] == (0.5, 2.0)
        assert unc["dead_time_extra_samples"] == (0, 1)
    for ax in b["axes"].values():
        assert ax.pop("uncertainty") is None
    assert a == b


def test_monte_carlo_is_seeded_inside_the_set_and_log_uniform():
    draws = monte_carlo_draws(ROBUST, 3000, seed=5)
    assert draws == monte_carlo_draws(ROBUST, 3000, seed=5)
    assert draws[:10] != monte_carlo_draws(ROBUST, 10, seed=6)
    for a in ("x", "y", "z"):
        unc = ROBUST.axes[a].uncertainty
        for f in FACTOR_FIELDS:
            x = np.array([d[0][a][f] for d in draws])
            lo, hi = getattr(unc, f)
            assert lo <= x.min() and x.max() <= hi
            # uniform in log: the share below the log-midpoint is 1/2, the log-mean is the
            # midpoint (3000 draws: standard errors 0.009 and 0.005 of the log-width)
            mid = 0.5 * (np.log(lo) + np.log(hi))
            width = np.log(hi) - np.log(lo)
            assert abs(np.mean(np.log(x) < mid) - 0.5) < 0.04
            assert abs((np.log(x).mean() - mid) / width) < 0.02
            # and each quarter of the log-range holds a quarter of the draws
            q = np.floor((np.log(x) - np.log(lo)) / width * 4).clip(0, 3)
            assert np.all(np.abs(np.bincount(q.astype(int), minlength=4) / len(x) - 0.25) < 0.03)
    dead = np.array([d[1] for d in draws])
    assert set(dead) == {0, 1} and abs(dead.mean() - 0.5) < 0.04


def test_perturbed_values_are_nominal_times_factor_and_keep_static_above_coulomb():
    f = {"x": {"coulomb_n": 1.5, "static_n": 0.5, "kv_n_s_m": 1.2}, "z": {"tn_s": 0.7}}
    m = perturbed_machine(ROBUST, f, 1, "p")
    x, z, nx = m.axes["x"].cascade, m.axes["z"].cascade, NOMINAL.axes["x"].cascade
    assert x.coulomb_n == 90.0 and x.static_n == 90.0  # 40 N raised to the Coulomb level
    assert x.kv_n_s_m == nx.kv_n_s_m * 1.2 and x.mass_kg == nx.mass_kg
    assert z.tn_s == NOMINAL.axes["z"].cascade.tn_s * 0.7
    assert m.timing.dead_time_samples == 3 and m.name == "p"
    # the simulation setting: the robust default, the machine's own value, or none
    assert m.timing.friction_linear_below_m_s == ROBUST_FRICTION_LINEAR_BELOW_M_S
    assert ROBUST.timing.friction_linear_below_m_s is None
    assert perturbed_machine(ROBUST, f, friction_linear_below_m_s=None).timing == \
        ROBUST.timing
    own = ROBUST.model_copy(update={"timing": ROBUST.timing.model_copy(
        update={"friction_linear_below_m_s": 5e-7})})
    assert perturbed_machine(own, f).timing.friction_linear_below_m_s == 5e-7
    assert all(ax.uncertainty is None for ax in m.axes.values())
    for draw_f, _ in monte_carlo_draws(ROBUST, 200, 1):
        p = perturbed_machine(ROBUST, draw_f)
        assert all(ax.cascade.static_n >= ax.cascade.coulomb_n for ax in p.axes.values())
    with pytest.raises(MachineError, match="unknown parameter 'kp'"):
        perturbed_machine(ROBUST, {"x": {"kp": 2.0}})
    with pytest.raises(MachineError, match="axis 'q'"):
        perturbed_machine(ROBUST, {"q": {"mass_kg": 2.0}})


def test_corners_are_the_ends_of_the_groups_that_matter_the_rest_nominal():
    labels, draws = corner_draws(ROBUST)
    assert len(draws) == 32 == len(set(labels))
    seen = set()
    for lab, (per_axis, dead) in zip(labels, draws):
        words = dict(w.rsplit("-", 1) for w in lab.split()[1:])
        assert set(words) == {"friction", "mass", "kv", "tn", "dead"}
        assert dead == (0 if words["dead"] == "lo" else 1)
        for a in ("x", "y", "z"):
            unc = ROBUST.axes[a].uncertainty
            want = {"coulomb_n": unc.coulomb_n, "static_n": unc.static_n, "mass_kg": unc.mass_kg,
                    "kv_n_s_m": unc.kv_n_s_m, "tn_s": unc.tn_s}
            key = {"coulomb_n": "friction", "static_n": "friction", "mass_kg": "mass",
                   "kv_n_s_m": "kv", "tn_s": "tn"}
            assert set(per_axis[a]) == set(want)
            for f, (lo, hi) in want.items():
                assert per_axis[a][f] == (lo if words[key[f]] == "lo" else hi)
            plant = perturbed_machine(ROBUST, per_axis, dead)
            for f in ("force_lag_s", "stribeck_m_s", "viscous_n_s_m"):
                assert getattr(plant.axes[a].cascade, f) == getattr(NOMINAL.axes[a].cascade, f)
        seen.add(tuple(sorted(words.items())))
    assert len(seen) == 32
    # a group with a single-point range adds no corners
    one = ROBUST.model_copy(update={"axes": {
        a: ax.model_copy(update={"uncertainty": ax.uncertainty.model_copy(
            update={"dead_time_extra_samples": (0, 0)})}) for a, ax in ROBUST.axes.items()}})
    assert len(corner_draws(one)[1]) == 16


def test_scenario_set_holds_the_draws_and_corners_and_nominal_without_a_set():
    s = scenario_set(ROBUST, n=64, seed=3)
    assert s.status == "ok" and len(s) == 96 and (s.n_monte_carlo, s.n_corners) == (64, 32)
    assert s.labels[0] == "mc-0000" and s.labels[64].startswith("corner")
    f, d = s.draws[7]
    assert s.plants[7].axes["z"].cascade.mass_kg == NOMINAL.axes["z"].cascade.mass_kg * f["z"]["mass_kg"]
    assert s.plants[7].timing.dead_time_samples == 2 + d
    s0 = scenario_set(NOMINAL)
    assert s0.status == "nominal-only" and len(s0) == 1
    plant, nominal = (m.model_dump(exclude={"name"}) for m in (s0.plants[0], NOMINAL))
    assert plant["timing"].pop("friction_linear_below_m_s") == ROBUST_FRICTION_LINEAR_BELOW_M_S
    assert nominal["timing"].pop("friction_linear_below_m_s") is None
    assert plant == nominal
    with pytest.raises(MachineError, match="at least 1"):
        scenario_set(ROBUST, n=0)
