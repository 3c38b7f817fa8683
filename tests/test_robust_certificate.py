"""The robustness certificate against fresh simulations on perturbed machine files.

The plants are rebuilt here from the preset's raw TOML and the certificate's draws,
written to TOML files and loaded back; each is simulated with ``oga.model.simulate``, its
contour error computed with ``oga.model.contour.contour_error`` and eq. 2 checked with numpy
differences, none of it through the certificate's or the verification's code.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.model.contour import contour_error
from oga.model.machine import PRESETS, load_machine
from oga.model.metrics import contour_metrics
from oga.optimize import optimize
from oga.pipeline import plan_toolpath
from oga.verify.certificate import certify, certify_result
from oga.search.robust.plants import scenario_set
from oga.model.response import simulate
from oga.model.stability import stable_range

DATA = Path(__file__).parent / "data"
PRESET = Path(__import__("oga").__file__).parent / "presets" / "ucp710.toml"


def _toml(data: dict, prefix: str = "") -> str:
    """A small TOML writer for a machine dict (tables of scalars and arrays)."""

    def value(v):
        if isinstance(v, str):
            return '"' + v.replace('"', '\\"') + '"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = [f"{k} = {value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    out = ([f"[{prefix}]"] if prefix and lines else []) + lines
    for k, v in data.items():
        if isinstance(v, dict):
            out.append(_toml(v, f"{prefix}.{k}" if prefix else k))
    return "\n".join(out)


def _plant_file(raw: dict, draw, path: Path):
    factors, dead = draw
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
    data["axes"] = {}
    for a, ax in raw["axes"].items():
        cas = dict(ax["cascade"])
        for f, x in factors.get(a, {}).items():
            cas[f] = cas[f] * x
        cas["static_n"] = max(cas["static_n"], cas["coulomb_n"])
        data["axes"][a] = {"limits": dict(ax["limits"]), "cascade": cas}
    data["timing"]["dead_time_samples"] = raw["timing"]["dead_time_samples"] + dead
    path.write_text(_toml(data))
    return load_machine(path)


def _replay(sp, plant, kp, kf):
    """MSE(CE), max |CE|, max following error per axis, eq. 2 ok, stability ok."""
    sim = simulate(sp, plant, kp, kf)
    ce = contour_error(sp.pos, sim.pos, sp.plane)
    feed = ~sp.rapid
    lim = plant.axis_limits()
    u = np.vstack([np.zeros((2, 3)), sim.u])
    ratios = [np.abs(u[2:]) / lim.vmax_m_s,
              np.abs(np.diff(u, axis=0)[1:]) / sp.dt / lim.amax_m_s2,
              np.abs(np.diff(u, 2, axis=0)) / sp.dt**2 / lim.jmax_m_s3]
    moving = [i for i in sp.moving_axes]
    limits_ok = all(r[feed][:, moving].max() <= 1 + 1e-9 for r in ratios)
    stab_ok = True
    for i in moving:
        rng = stable_range(plant, "xyz"[i])
        stab_ok &= rng.kp_min - 1e-12 <= kp[:, i].min() and kp[:, i].max() <= rng.kp_max + 1e-12
    track = np.abs(sp.pos - sim.pos)[feed].max(axis=0)
    return np.mean(ce[feed] ** 2), np.abs(ce[feed]).max(), track, limits_ok, stab_ok


@pytest.fixture(scope="module")
def case():
    m = load_machine("ucp710")
    sp = plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), m, feed_m_s=None, tol_m=2e-5)
    return m, sp, optimize(sp, m, {"nominal": True})


def fresh_certificate(sp, raw: dict, labels, draws, kp, kf, bkp, bkf, folder: Path) -> dict:
    """The certificate's summary figures recomputed on plant files: per plant (its draw
    applied to the raw TOML ``raw``, written to ``folder`` and loaded back) the schedule
    ``kp, kf`` and the baseline ``bkp, bkf`` simulated afresh (:func:`_replay`)."""
    ratios, sched, base, breaks = [], [], [], {"schedule": [], "baseline": [], "schedule-only": []}
    for i, (label, draw) in enumerate(zip(labels, draws)):
        plant = _plant_file(raw, draw, folder / f"plant{i}.toml")
        s, b = _replay(sp, plant, kp, kf), _replay(sp, plant, bkp, bkf)
        ratios.append(s[0] / b[0])
        sched.append(s)
        base.append(b)
        if not (s[3] and s[4]):
            breaks["schedule"].append(label)
        if not (b[3] and b[4]):
            breaks["baseline"].append(label)
        if (not s[3] and b[3]) or (not s[4] and b[4]):
            breaks["schedule-only"].append(label)
    ratios = np.array(ratios)

    def largest(runs):
        return {"max_ce_um": max(r[1] for r in runs) * 1e6,
                "track_max_um": {a: max(r[2][k] for r in runs) * 1e6 for k, a in enumerate("xyz")}}

    ok = ratios.max() <= 1.0 and not breaks["schedule-only"]
    return {"status": "ok" if ok else "failed", "plants": len(ratios),
            "ratio_median": np.median(ratios), "ratio_p90": np.percentile(ratios, 90),
            "ratio_worst": ratios.max(), "worst_plant": labels[int(np.argmax(ratios))],
            "breaks": breaks, "schedule": largest(sched), "baseline": largest(base),
            "ratio_per_plant": dict(zip(labels, ratios))}


#: The certificate replays its plants with their linear friction map at standstill, the fresh
#: simulations here on the exact kernel (plant files without the setting): every figure within
#: 1e-8 relative (tests/test_friction_linear.py's bound; measured below 2e-9 on cncjs_toolpath,
#: bench/bench_friction_linear.py), a ratio of two within twice that.
REL = 2e-8


def assert_same_certificate(summary: dict, fresh: dict) -> None:
    """A summary's certificate (JSON) equals the figures recomputed by :func:`fresh_certificate`
    (within :data:`REL`)."""
    for key in ("status", "plants", "worst_plant", "breaks"):
        assert summary[key] == fresh[key], key
    for key in ("ratio_median", "ratio_p90", "ratio_worst"):
        assert summary[key] == pytest.approx(fresh[key], rel=REL), key
    assert list(summary["ratio_per_plant"]) == list(fresh["ratio_per_plant"])
    np.testing.assert_allclose(list(summary["ratio_per_plant"].values()),
                               list(fresh["ratio_per_plant"].values()), rtol=REL)
    for who in ("schedule", "baseline"):
        assert summary[who]["max_ce_um"] == pytest.approx(fresh[who]["max_ce_um"], rel=REL)
        for a in "xyz":
            assert summary[who]["track_max_um"][a] == pytest.approx(
                fresh[who]["track_max_um"][a], rel=REL, abs=1e-9)
    assert (summary["status"] == "ok") == (not summary["reasons"])


def test_certificate_figures_match_fresh_simulations_on_machine_files(case, tmp_path):
    m, sp, res = case
    assert "ucp710" in PRESETS and m.axes["x"].uncertainty is not None
    scen = scenario_set(m, n=8, seed=4)
    cert = certify_result(res, scen)
    assert len(cert.plants) == 8 + 32
    raw = tomllib.loads(PRESET.read_text())
    n = len(sp)
    kp, kf = res.searched_schedule.kp_m_min_per_mm, res.searched_schedule.kf
    bkp = np.tile([res.baseline_kp[a] for a in "xyz"], (n, 1))
    bkf = np.tile([res.baseline_kf[a] for a in "xyz"], (n, 1))
    fresh = fresh_certificate(sp, raw, scen.labels, scen.draws, kp, kf, bkp, bkf, tmp_path)
    ratios = np.array(list(fresh["ratio_per_plant"].values()))
    np.testing.assert_allclose(cert.ratio, ratios, rtol=REL)
    assert cert.median == pytest.approx(np.median(ratios), rel=REL)
    assert cert.p90 == pytest.approx(np.percentile(ratios, 90), rel=REL)
    assert cert.worst == pytest.approx(ratios.max(), rel=REL)
    for which in ("schedule", "baseline", "schedule-only"):
        assert cert.breaks(which) == tuple(fresh["breaks"][which])
    # the summary's figures (JSON round trip), every one of them
    assert_same_certificate(json.loads(json.dumps(cert.summary())), fresh)
    # the set is not trivial: the plants differ, and the nominal schedule is not as good on all
    assert ratios.max() > 1.5 * ratios.min()


def test_the_baseline_certifies_itself_and_a_worse_schedule_fails(case):
    m, sp, res = case
    scen = scenario_set(m, n=4, seed=1, corners=False)
    n = len(sp)
    bkp = np.tile([res.baseline_kp[a] for a in "xyz"], (n, 1))
    bkf = np.tile([res.baseline_kf[a] for a in "xyz"], (n, 1))
    same = certify(sp, m, bkp, bkf, bkp, bkf, scen)
    np.testing.assert_array_equal(same.ratio, np.ones(4))
    assert not same.breaks("schedule-only")
    # no feed-forward: far worse than the baseline on every plant
    worse = certify(sp, m, bkp, np.zeros_like(bkf), bkp, bkf, scen)
    assert worse.status == "failed" and worse.ratio.min() > 1.0
    assert "worse than the fixed baseline" in worse.reasons[0]


def test_stable_range_is_found_on_every_plant_of_the_default_set():
    # a corner whose phase reaches -900 deg exactly at Nyquist once broke the crossing search
    from oga.search.robust.plants import corner_draws, perturbed_machine

    m = load_machine("ucp710")
    for plant in (perturbed_machine(m, f, d) for f, d in corner_draws(m)[1]):
        for a in ("x", "z"):
            rng = stable_range(plant, a)
            assert 1.0 <= rng.kp_max <= 5.0


def test_one_certificate_on_one_or_two_threads_with_progress(case):
    # the table prepared once for every plant (oga.verify.replay.ReplayGains) and the
    # replays submitted at once: the same replays, bit for bit, as simulate and
    # contour_error give each plant afresh, on 1 and 2 threads; the progress rises to 1
    m, sp, res = case
    scen = scenario_set(m, n=9, seed=3, corners=False)
    kp, kf = res.schedule.kp_m_min_per_mm, res.schedule.kf
    bkp = np.tile([res.baseline_kp[a] for a in "xyz"], (len(sp), 1))
    bkf = np.tile([res.baseline_kf[a] for a in "xyz"], (len(sp), 1))
    seen = {1: [], 2: []}
    certs = [certify(sp, m, kp, kf, bkp, bkf, scen, threads=t, progress=seen[t].append)
             for t in (1, 2)]
    for t, every in ((1, 4), (2, 8)):  # after every 4 plants per thread, and at the end
        np.testing.assert_allclose(seen[t], [*(k / 9 for k in range(every, 9, every)), 1.0])
    # the series are kept on the worst plant alone (the report draws it); every plant's
    # figures are those of its series
    worst = int(np.argmax(certs[0].ratio))
    for i, (plant, one, two) in enumerate(zip(scen.plants, *(c.plants for c in certs))):
        sim = simulate(sp, plant, kp, kf)
        ce = contour_error(sp.pos, sim.pos, sp.plane)
        for got in (one.schedule, two.schedule):
            assert (got.pos is not None) == (i == worst)
            if i == worst:
                np.testing.assert_array_equal(got.pos, sim.pos)
                np.testing.assert_array_equal(got.u, sim.u)
                np.testing.assert_array_equal(got.ce, ce)
            assert got.metrics == contour_metrics(ce, sp.pos, sim.pos, sp.counted)
            np.testing.assert_array_equal(got.max_dkp_per_sample,
                                          np.abs(np.diff(kp, axis=0)).max(axis=0))
    np.testing.assert_array_equal(certs[0].ratio, certs[1].ratio)
