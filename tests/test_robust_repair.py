"""The robust search's local repair (a table faded back to its baseline around the samples
where it alone breaks a limit) and the multi-plant search's floor (a searched plant's limits
never below its baseline's own command)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.model.machine import load_machine
from oga.model.response import simulate
from oga.options import options_from_dict
from oga.pipeline import plan_toolpath
from oga.search.robust.multi import _baseline_floor, multi_search
from oga.search.robust.plants import perturbed_machine, scenario_set
from oga.search.robust.search import robust_optimize
from oga.search.robust.repair import break_samples, fade, repaired
from oga.verify.certificate import certify, plant_bounds
from oga.verify.replay import command_ratios, verify

DATA = Path(__file__).parent / "data"


def _fixed(n, kp, kf):
    return np.full((n, 3), kp), np.full((n, 3), kf)


def test_fade_is_zero_near_a_marked_sample_and_a_raised_cosine_to_one():
    marked = np.zeros(400, dtype=bool)
    marked[[100, 104, 300]] = True
    w = fade(marked, 5, 20)
    # the distance to the nearest marked sample, by brute force
    dist = np.abs(np.arange(400)[:, None] - np.flatnonzero(marked)[None, :]).min(axis=1)
    x = np.clip((dist - 5) / 20, 0.0, 1.0)
    np.testing.assert_allclose(w, 0.5 - 0.5 * np.cos(np.pi * x), atol=1e-15)
    assert (w[95:110] == 0).all() and (w[295:306] == 0).all() and w[0] == w[200] == w[399] == 1
    assert np.all(np.diff(w[104:130]) >= 0) and np.all(np.diff(w[270:300]) <= 0)
    np.testing.assert_array_equal(fade(np.zeros(9, dtype=bool), 5, 20), np.ones(9))


def test_break_samples_are_where_a_replay_breaks_its_limits(short_xz):
    m, sp = short_xz
    n = len(sp)
    kp, kf = _fixed(n, 1.3, 0.9)
    kf[n // 2:, :] = 0.2  # a step of Kf at speed: a command step
    sim = simulate(sp, m, kp, kf)
    got = break_samples(sp, m, sim.u, sim.pos)
    ratio = command_ratios(sim.u, sp, m)
    assert ratio.max() > 1 and got.any()
    # every sample: its own eq. 2 ratios, from the commands before it (at rest before 0)
    u = np.vstack([np.zeros((2, 3)), sim.u])
    al = m.axis_limits()
    lim = np.column_stack([al.vmax_m_s, al.amax_m_s2, al.jmax_m_s3])
    want = np.zeros(n, dtype=bool)
    for k in range(n):
        d1 = (u[k + 2] - u[k + 1]) / sp.dt
        d2 = (u[k + 2] - 2 * u[k + 1] + u[k]) / sp.dt ** 2
        want[k] = ((np.abs(u[k + 2]) > lim[:, 0]) | (np.abs(d1) > lim[:, 1] * (1 + 1e-9))
                   | (np.abs(d2) > lim[:, 2] * (1 + 1e-9))).any()
    np.testing.assert_array_equal(got, want)
    assert abs(np.flatnonzero(got)[0] - n // 2) <= 2  # the step's samples


def test_a_table_that_breaks_a_limit_in_one_stretch_is_faded_there_and_kept_elsewhere():
    # a certified robust table whose Kf chatters at speed for 30 ms (the command's jerk far
    # above its limit, the contour error hardly moved): the repair fades it to the baseline
    # there only; its certificate, recomputed, passes
    m = load_machine("ucp710")
    sp = plan_toolpath(load_toolpath(DATA / "reference_xz.ngc"), m, feed_m_s=None, tol_m=2e-5)
    n = len(sp)
    scen = scenario_set(m, n=8, seed=9)
    good = robust_optimize(sp, m, scenarios=scen, threads=2)
    assert good.status == "ok"
    bkp, bkf = _fixed(n, good.baseline.kp, good.baseline.kf)
    bounds = plant_bounds(scen, ("x", "z"))
    base = tuple(verify(sp, p, bkp, bkf, b) for p, b in zip(scen.plants, bounds))
    kp, kf = good.schedule.kp_m_min_per_mm.copy(), good.schedule.kf.copy()
    k0 = int(np.argmax(np.abs(sp.vel[:, 0])))  # the x axis at its fastest
    kf[k0:k0 + 30, :] += 0.05 * (-1.0) ** np.arange(30)[:, None]  # Kf chatters: jerk, little CE
    cert = certify(sp, m, kp, kf, bkp, bkf, scen, bounds, base)
    assert cert.status == "failed" and cert.breaks("schedule-only")
    got = repaired(sp, m, (kp, kf), (bkp, bkf), scen, bounds, cert, base)
    assert got is not None
    kp_r, kf_r, cert_r = got
    again = certify(sp, m, kp_r, kf_r, bkp, bkf, scen, bounds, base)
    assert again.status == cert_r.status == "ok"
    np.testing.assert_allclose(again.ratio, cert_r.ratio, rtol=1e-12)
    changed = np.flatnonzero((kp_r != kp).any(axis=1) | (kf_r != kf).any(axis=1))
    assert changed[0] <= k0 <= changed[-1] and changed.size < n / 2  # a stretch only
    np.testing.assert_array_equal(kf_r[k0:k0 + 30], bkf[k0:k0 + 30])  # the baseline there
    for r, t, b in ((kp_r, kp, bkp), (kf_r, kf, bkf)):  # between the table and the baseline
        assert np.all((r - b) * (t - b) >= 0) and np.all(np.abs(r - b) <= np.abs(t - b))
    assert again.median < 1.0  # most of the table's gain kept
    # on plants the repair never saw (another seed), every sample: no limit the baseline keeps
    other = scenario_set(m, n=8, seed=10)
    for plant, kb in zip(other.plants, plant_bounds(other, ("x", "z"))):
        if verify(sp, plant, bkp, bkf, kb).limits_ok:
            assert verify(sp, plant, kp_r, kf_r, kb).limits_ok


def test_a_table_worse_than_the_baseline_without_a_break_is_not_repaired(short_xz):
    m, sp = short_xz
    n = len(sp)
    scen = scenario_set(m, n=8, seed=9)
    bounds = plant_bounds(scen, ("x", "z"))
    bkp, bkf = _fixed(n, 1.3, 0.9)
    base = tuple(verify(sp, p, bkp, bkf, b) for p, b in zip(scen.plants, bounds))
    kp, kf = _fixed(n, 1.3, 0.6)  # a lower constant Kf: worse on every plant, no break
    cert = certify(sp, m, kp, kf, bkp, bkf, scen, bounds, base)
    assert cert.status == "failed" and not cert.breaks("schedule-only")
    assert repaired(sp, m, (kp, kf), (bkp, bkf), scen, bounds, cert, base) is None


def test_the_floor_is_the_baselines_command_on_each_plant(short_xz):
    # each plant's floor at a sample: its baseline's largest |du|/Te, |d2u|/Te^2 within the
    # floor's samples either side (the commands of a fresh simulation, at rest before 0)
    from oga import defaults
    m, sp = short_xz
    n = len(sp)
    plants = (perturbed_machine(m, {}, 0, m.name), perturbed_machine(m, {}, 1))
    floor = _baseline_floor(sp, plants, 1.3, 0.9, n + 7)
    assert floor.shape == (2, 3, 2, n + 7) and (floor[..., n:] == 0).all()
    h = defaults.ROBUST_FLOOR_SAMPLES
    for s, p in enumerate(plants):
        u = np.vstack([np.zeros((2, 3)), simulate(sp, p, *_fixed(n, 1.3, 0.9)).u])
        d1 = np.abs(np.diff(u, axis=0))[1:] / sp.dt
        d2 = np.abs(np.diff(u, 2, axis=0)) / sp.dt ** 2
        for r, d in enumerate((d1, d2)):
            want = np.array([d[max(k - h, 0):k + h + 1].max(axis=0) for k in range(n)]).T
            np.testing.assert_allclose(floor[s, :, r, :n], want, rtol=1e-12, atol=1e-12)
    assert not np.array_equal(floor[0], floor[1])  # each plant its own


def test_with_the_floor_a_search_at_a_cut_reserve_serves_both_its_plants_better(monkeypatch):
    # cncjs_toolpath, the nominal plant and a fast corner with one sample more dead time, at
    # reserve 0.6 (the baseline's own jerk peaks at 0.87 and 0.78 of the limit there): the
    # floor (each plant's limits at least its baseline's command, sample by sample) against
    # the same search without it, both replayed afresh (measured: 0.575 / 0.763 against
    # 0.620 / 1.207, the corner worse than the baseline without the floor)
    import oga.search.robust.multi as multi
    m = load_machine("ucp710")
    sp = plan_toolpath(load_toolpath(DATA / "cncjs_toolpath.nc"), m, feed_m_s=None, tol_m=2e-5)
    n = len(sp)
    kp0, kf0 = 1.7602, 0.8518  # the robust baseline there
    plants = (perturbed_machine(m, {}, 0, m.name),
              perturbed_machine(m, {a: {"coulomb_n": 0.5, "static_n": 0.5, "mass_kg": 0.8,
                                        "kv_n_s_m": 1.2, "tn_s": 0.7} for a in "xyz"}, 1))
    kb = {a: (1.0, 2.0) for a in ("x", "y", "z")}
    bkp, bkf = _fixed(n, kp0, kf0)
    base = tuple(verify(sp, p, bkp, bkf, kb) for p in plants)
    assert min(b.command_ratio[:, 2].max() for b in base) > 0.6

    def ratios():
        f = multi_search(sp, plants, base, options_from_dict(None), kp0, kf0, (1.0, 2.0), 0.6)
        got = [verify(sp, p, f.kp, f.kf, kb) for p in plants]
        assert all(g.limits_ok for g in got)
        return np.array([g.metrics.mse_m2 / b.metrics.mse_m2 for g, b in zip(got, base)])

    floored = ratios()
    monkeypatch.setattr(multi, "_baseline_floor",
                        lambda sp, plants, *rest: np.zeros((len(plants), 3, 2, 0)))
    bare = ratios()
    assert np.all(floored < 1.0) and np.all(floored < bare)
