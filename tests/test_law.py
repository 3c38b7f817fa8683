"""Gain laws (oga.law): evaluation, derivatives, search, certificate, exports, CLI and API."""

from __future__ import annotations

import io
import json
import socket
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api import Settings, create_app
from api.storage import Owner
from api.workers import run_claimed
from feedplan.read import load_toolpath
from feedplan.setpoints import AXES
from oga.cli import main
from oga.model.contour import contour_error_of, path_index
from oga.law.export import law_files
from oga.law.export.heidenhain import heidenhain_text
from oga.law.export.linuxcnc import law_hal
from oga.law.export.twincat import twincat_files
from oga.law.gradient import axis_tangent, ce_offsets, gauss_newton
from oga.law.law import (AxisLaw, Law, basis, curve_basis, interp, law_gains, quantized,
                         signed_support_points)
from oga.law.override import override_path, plan_override
from oga.law.search import Program, search_law
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.errors import OptionError
from oga.search.robust.baseline import robust_baseline
from oga.search.robust.plants import scenario_set
from oga.model.response import simulate
from oga.verify.certificate import plant_bounds
from oga.verify.replay import verify

DATA = Path(__file__).parent / "data"
MACHINE = load_machine("ucp710")


@pytest.fixture(scope="module")
def short():
    path = load_toolpath(DATA / "short_xz.ngc")
    return path, {o: plan_override(path, MACHINE, o, 2e-5) for o in (0.8, 1.0, 1.2)}


def _mac_law(sp):
    """A Heidenhain-style law on a 3 x 3 grid of |v| and |a| with distinct values."""
    axes = {}
    rng = np.random.default_rng(3)
    for a in ("x", "z"):
        i = AXES.index(a)
        v = np.array([0.0, 0.4, 1.0]) * np.abs(sp.vel[:, i]).max()
        acc = np.array([0.0, 0.3, 1.0]) * np.abs(sp.acc[:, i]).max()
        axes[a] = AxisLaw(v_m_s=v, a_m_s2=acc, kp_m_min_per_mm=rng.uniform(1.2, 2.0, (3, 3)),
                          kf=rng.uniform(0.7, 0.95, (3, 3)))
    return Law(kind="mac", axes=axes, fixed_kp={"y": 1.3}, fixed_kf={"y": 0.9})


def test_interp_is_lincurve_and_the_basis_gives_the_same_gains(short):
    """``interp`` against numpy's (the same clamping as lincurve); the search's weights
    (``basis``) against the evaluation, on a bilinear law (two code paths)."""
    rng = np.random.default_rng(1)
    xs = np.sort(rng.uniform(0, 1, 6))
    ys = rng.uniform(-1, 1, 6)
    x = rng.uniform(-0.5, 1.5, 1000)
    assert np.allclose(interp(xs, ys, x), np.interp(x, xs, ys), rtol=0, atol=1e-15)
    sp = short[1][1.0]
    law = _mac_law(sp)
    kp, kf = law_gains(law, sp)
    for a, ax in law.axes.items():
        i = AXES.index(a)
        w = basis(ax, ax.kp_m_min_per_mm.shape, sp.vel[:, i], sp.acc[:, i])
        assert np.allclose(w.sum(axis=1), 1.0)
        assert np.allclose(w @ ax.kp_m_min_per_mm.ravel(), kp[:, i], atol=1e-12)
        assert np.allclose(w @ ax.kf.ravel(), kf[:, i], atol=1e-12)
        # bilinear by hand at one sample inside the grid
        k = int(np.argmax((np.abs(sp.vel[:, i]) > ax.v_m_s[1]) & (np.abs(sp.acc[:, i]) > 0)
                          & (np.abs(sp.acc[:, i]) < ax.a_m_s2[1])))
        fv = (abs(sp.vel[k, i]) - ax.v_m_s[1]) / (ax.v_m_s[2] - ax.v_m_s[1])
        fa = abs(sp.acc[k, i]) / ax.a_m_s2[1]
        t = ax.kp_m_min_per_mm
        want = ((1 - fa) * ((1 - fv) * t[0, 1] + fv * t[0, 2])
                + fa * ((1 - fv) * t[1, 1] + fv * t[1, 2]))
        assert kp[k, i] == pytest.approx(want, rel=1e-12)
    assert (kp[:, 1] == 1.3).all() and (kf[:, 1] == 0.9).all()


def test_signed_acceleration_law():
    """``lincurve-sa``: Kf is numpy's interpolation on ``a`` where ``v >= 0`` and on ``-a``
    where ``v < 0`` (an independent reference), the search's weights give the same Kf, the
    support points are symmetric; no MAC or TwinCAT file can state it. zigzag_xz: both axes
    speed up and brake in both directions."""
    sp = plan_override(load_toolpath(DATA / "zigzag_xz.ngc"), MACHINE, 1.0, 2e-5)
    axes = {}
    for a, kf in (("x", [0.9, 0.7, 0.8, 0.95]), ("z", [0.75, 0.9, 0.85, 0.8])):
        i = AXES.index(a)
        acc = signed_support_points([sp.acc[:, i]], 4)
        assert np.allclose(acc, -acc[::-1]) and (np.diff(acc) > 0).all()
        axes[a] = AxisLaw(v_m_s=np.array([0.0, 0.02, 0.04]), a_m_s2=acc,
                          kp_m_min_per_mm=np.array([[1.5, 1.8, 2.0]]), kf=np.array([kf]))
    law = Law(kind="lincurve-sa", axes=axes, fixed_kp={"y": 1.3}, fixed_kf={"y": 0.9})
    kp, kf = law_gains(law, sp)
    for a, ax in axes.items():
        i = AXES.index(a)
        s = np.where(sp.vel[:, i] < 0, -sp.acc[:, i], sp.acc[:, i])
        assert ((sp.vel[:, i] < 0) & (s < 0.5 * s.min())).any()
        assert ((sp.vel[:, i] < 0) & (s > 0.5 * s.max())).any()
        want = np.interp(s, ax.a_m_s2, ax.kf[0])
        assert np.allclose(kf[:, i], want, rtol=0, atol=1e-15) and np.ptp(want) > 0.05
        assert np.allclose(curve_basis(ax.a_m_s2, s) @ ax.kf[0], want, rtol=0, atol=1e-15)
        assert np.allclose(kp[:, i], np.interp(np.abs(sp.vel[:, i]), ax.v_m_s,
                                               ax.kp_m_min_per_mm[0]), rtol=0, atol=1e-15)
    with pytest.raises(OptionError, match="Heidenhain MAC cannot express a lincurve-sa"):
        heidenhain_text(law, [])
    with pytest.raises(OptionError, match="TwinCAT"):
        twincat_files(law, [])


def test_derivatives_match_finite_differences(short):
    """The tangent sensitivities of positions and commands, and the Gauss-Newton gradient of
    the squared contour error, against central differences of fresh replays."""
    sp = short[1][1.0]
    law = _mac_law(sp)
    kp, kf = law_gains(law, sp)
    pd = np.ascontiguousarray(sp.pos)
    ws, sens, cols, start = {}, {}, {}, 0
    for a, ax in law.axes.items():
        i = AXES.index(a)
        ws[i] = (basis(ax, (3, 3), sp.vel[:, i], sp.acc[:, i]),
                 basis(ax, (3, 3), sp.vel[:, i], sp.acc[:, i]))
        p, u, s_p, s_u = axis_tangent(MACHINE, a, i, pd, sp.vel, kp[:, i], kf[:, i], *ws[i])
        sim = simulate(sp, MACHINE, kp, kf)
        assert np.array_equal(p, sim.pos[:, i]) and np.array_equal(u, sim.u[:, i])
        sens[i] = s_p
        cols[i] = slice(start, start + 18)
        start += 18
        for j in (4, 13):  # a Kp and a Kf support value
            h = 1e-5
            w = ws[i][0][:, j] if j < 9 else ws[i][1][:, j - 9]
            kp2, kf2 = kp.copy(), kf.copy()
            res = []
            for sgn in (1, -1):
                kp2[:, i], kf2[:, i] = kp[:, i], kf[:, i]
                if j < 9:
                    kp2[:, i] = kp[:, i] + sgn * h * w
                else:
                    kf2[:, i] = kf[:, i] + sgn * h * w
                res.append(simulate(sp, MACHINE, kp2, kf2))
            fd_p = (res[0].pos[:, i] - res[1].pos[:, i]) / (2 * h)
            fd_u = (res[0].u[:, i] - res[1].u[:, i]) / (2 * h)
            assert np.abs(s_p[:, j] - fd_p).max() <= 1e-4 * np.abs(fd_p).max() + 1e-15
            assert np.abs(s_u[:, j] - fd_u).max() <= 1e-4 * np.abs(fd_u).max() + 1e-15
    # the gradient of sum CE^2 (feed samples) along a Kp support value of x
    feed = ~sp.rapid
    tree, lo, hi = path_index(pd, 200)
    sim = simulate(sp, MACHINE, kp, kf)
    dq, tang = np.empty((len(sp), 3)), np.empty((len(sp), 3))
    total = ce_offsets(pd, tree, lo, hi, feed, np.ascontiguousarray(sim.pos), dq, tang)
    ce = contour_error_of(sp, sim.pos)
    assert total == pytest.approx(float(np.sum(ce[feed] ** 2)), rel=1e-9)
    _h, g, _s = gauss_newton(dq, tang, feed, sens, cols, 36)
    j, h = 4, 1e-5
    vals = []
    for sgn in (1, -1):
        kp2 = kp.copy()
        kp2[:, 0] = kp[:, 0] + sgn * h * ws[0][0][:, j]
        ce2 = contour_error_of(sp, simulate(sp, MACHINE, kp2, kf).pos)
        vals.append(float(np.sum(ce2[feed] ** 2)))
    fd = (vals[0] - vals[1]) / (2 * h)
    assert 2 * g[j] == pytest.approx(fd, rel=2e-3)


def test_override_scales_the_feed_moves_only(short):
    path, sps = short
    fast = override_path(path, 1.2)
    for a, b in zip(path.segments, fast.segments):
        assert b.feed_m_s == (a.feed_m_s if a.rapid else pytest.approx(1.2 * a.feed_m_s))
    top = {o: float(np.linalg.norm(sp.vel[~sp.rapid], axis=1).max()) for o, sp in sps.items()}
    assert top[0.8] < top[1.0] < top[1.2]  # (the cycle time need not fall: the blends change)
    with pytest.raises(OptionError, match="--overrides"):
        from oga.law.override import check_overrides
        check_overrides([0.5, 0.8])


@pytest.fixture(scope="module")
def searched(short):
    """A lincurve law of short_xz at 80/100/120 % on a small set (8 Monte Carlo plants and
    the 32 corners: the search's and certificate's code, fewer replays)."""
    _path, sps = short
    scen = scenario_set(MACHINE, n=8)
    return search_law([Program("short_xz", sps)], MACHINE, "lincurve", 3, scenarios=scen), scen


def test_search_certifies_a_law_better_than_the_baseline(searched, short):
    res, scen = searched
    assert res.status == "ok" and res.certificate.full
    for (prog, o), cert in res.certificate.cases.items():
        assert cert.worst <= 1.0 and not cert.breaks("schedule-only")
        assert cert.median < 0.9, (o, cert.median)
    # the certificate's ratio on a plant, replayed afresh from the law and the baseline
    sp = short[1][1.2]
    base = res.baselines["short_xz"]
    kp, kf = law_gains(res.law, sp)
    n = len(sp)
    cert = res.certificate.cases[("short_xz", 1.2)]
    p = cert.plants[-1]
    law_v = verify(sp, scen.plants[-1], kp, kf, p.kp_bounds)
    base_v = verify(sp, scen.plants[-1], np.full((n, 3), base.kp),
                    np.full((n, 3), base.kf), p.kp_bounds)
    assert law_v.metrics.mse_m2 / base_v.metrics.mse_m2 == pytest.approx(cert.ratio[-1], rel=1e-12)
    assert law_v.ok
    # the replays keep their series on the worst plant only (the report draws it; 96 plants'
    # series at four overrides held cncjs_toolpath's law at 1.5 GB)
    for c in res.certificate.cases.values():
        worst = int(np.argmax(c.ratio))
        for i, p in enumerate(c.plants):
            assert (p.baseline.pos is None) == (p.schedule.pos is None) == (i != worst)
    assert np.array_equal(cert.plants[-1].baseline.metrics.track_max_m, base_v.metrics.track_max_m)
    # what is certified is what is exported: the law is its own quantization
    q = quantized(res.law)
    for a in res.law.axes:
        assert np.array_equal(q.axes[a].kp_m_min_per_mm, res.law.axes[a].kp_m_min_per_mm)


def test_the_search_cost_keeps_searched_plants_under_their_baseline(searched, short):
    """The law search's exact cost is the weighted mean ratio over the searched plants plus
    LAW_WORST_WEIGHT times each ratio's excess over LAW_WORST_RATIO squared, recomputed here
    from fresh replays of the law and the baseline; its Gauss-Newton gradient matches central
    differences of that cost (the worst-plant term dominates it here)."""
    from oga import defaults
    from oga.law.search import _context
    res, scen = searched
    _path, sps = short
    ctx, theta0, base = _context([Program("short_xz", sps)], MACHINE, "lincurve", 3, scen,
                                 res.baselines, 1)
    keys = (-1, 0, 1)  # the nominal plant and two of the set
    theta = np.clip(theta0 + ctx.layout.constant(0.6, -0.1), ctx.lo, ctx.hi)
    b = base["short_xz"]
    cost, excess = 0.0, []
    for o, sp in sps.items():
        kp, kf = law_gains(ctx.layout.law(theta, ctx.fixed_kp, ctx.fixed_kf), sp)
        n = len(sp)
        for key, w in zip(keys, (0.5, 0.25, 0.25)):
            plant = scen.plants[key] if key >= 0 else MACHINE
            mse = [float(np.mean(contour_error_of(sp, simulate(sp, plant, p, f).pos)[sp.counted]
                                 ** 2)) for p, f in ((kp, kf), (np.full((n, 3), b.kp),
                                                                np.full((n, 3), b.kf)))]
            r = mse[0] / mse[1]
            excess.append(r - defaults.LAW_WORST_RATIO)
            cost += (w * r + defaults.LAW_WORST_WEIGHT * max(excess[-1], 0.0) ** 2) / len(sps)
    assert max(excess) > 0.1  # the term is at work
    assert ctx.evaluate(theta, keys, 1.0)[0] == pytest.approx(cost, rel=1e-9)
    _h, g, _checks, _cost = ctx.linearise(theta, keys, 1.0)
    for j in (ctx.layout.kp_cols[0].start + 1, ctx.layout.kf_cols[0].start + 1):  # x's Kp, Kf
        step = np.zeros_like(theta)
        step[j] = 1e-5
        fd = (ctx.evaluate(theta + step, keys, 1.0)[0]
              - ctx.evaluate(theta - step, keys, 1.0)[0]) / 2e-5
        assert g[j] == pytest.approx(fd, rel=1e-2)


def test_the_laws_baseline_is_the_robust_searchs(searched, short):
    """The law is judged against the robust baseline itself: the same gains and replays as
    :func:`oga.search.robust.baseline.robust_baseline` called directly (its own bounds and Kp range,
    on one thread where the law's ran on the default)."""
    res, scen = searched
    law_base = res.baselines["short_xz"]
    direct = robust_baseline(short[1][1.0], MACHINE, scen, threads=1)
    assert direct.ok and (law_base.kp, law_base.kf) == (direct.kp, direct.kf)
    assert law_base.mse_m2 == direct.mse_m2
    assert ([v.metrics.mse_m2 for v in law_base.replays]
            == [v.metrics.mse_m2 for v in direct.replays])


def test_no_baseline_is_the_laws_error_naming_the_program_and_the_remedy():
    d = MACHINE.model_dump(mode="json", exclude_none=True)
    for ax in d["axes"].values():  # mass and Kv far more uncertain (test_robust_baseline's)
        ax["uncertainty"] |= {"mass_kg": [0.2, 5.0], "kv_n_s_m": [0.2, 3.0]}
    m = machine_from_dict(d)
    sp = plan_override(load_toolpath(DATA / "short_xz.ngc"), m, 1.0, 2e-5)
    with pytest.raises(OptionError) as err:
        search_law([Program("short_xz", {1.0: sp})], m, "lincurve", 3,
                   scenarios=scenario_set(m, n=16), threads=1)
    msg = str(err.value)
    assert msg.startswith("short_xz: baseline: no equal fixed gains"), msg
    assert all(w in msg for w in ("accel_fraction", "uncertainty", "no nominal mode")), msg


def test_exports_state_the_law_in_each_controllers_units(searched, short):
    res, scen = searched
    files = law_files(res, "ucp710", len(scen))
    hal = files["oga_law.hal"]
    assert "what the certificate covers" in hal.lower() and "short_xz at 120 % feed" in hal
    ax = res.law.axes["x"]
    for k, v in enumerate(ax.v_m_s):
        assert f"setp oga-law-x-kp.x-val-{k:02d} {float(v) * 1e3!r}" in hal
        assert (f"setp oga-law-x-kp.y-val-{k:02d} "
                f"{float(ax.kp_m_min_per_mm[0, k]) * KP_SI_PER_M_MIN_PER_MM!r}") in hal
    # TwinCAT: a two-point pl law in 0.01/s and um/s
    law = Law(kind="pl", axes={"x": AxisLaw(np.array([0.004, 0.05]), np.zeros(1),
                                            np.array([[1.8, 1.5]]), np.array([[0.86]]))})
    tw = twincat_files(quantized(law), ["c"])["oga_law_twincat_x.txt"]
    assert "getriebe[0].dyn_kv.kv1              3000" in tw
    assert "getriebe[0].dyn_kv.v2               50000" in tw
    assert "vorsteuer.vs_v_faktor       860" in tw
    with pytest.raises(OptionError, match="--kind"):
        twincat_files(Law(kind="pl", axes={"x": AxisLaw(np.array([0.0, 0.01, 0.05]), np.zeros(1),
                                                         np.ones((1, 3)), np.ones((1, 1)))}), [])
    mac = quantized(_mac_law(short[1][1.0]))
    txt = heidenhain_text(mac, ["c"])
    assert "[axis X]" in txt and "MP1396.0" in txt and len(txt.splitlines()) == 1 + 2 * 12
    with pytest.raises(OptionError, match="--kind"):
        law_hal(mac, [])


def test_cli_refuses_bad_options(tmp_path, capsys):
    prog = str(DATA / "short_xz.ngc")
    for flags, what in ((["--kind", "siemens"], "--kind"), (["--points", "17"], "--points"),
                        (["--kind", "pl", "--points", "3"], "--points"),
                        (["--overrides", "0.5,0.8"], "--overrides"),
                        (["--overrides", "0.5,1,5"], "--overrides"),
                        (["--tolerance", "100"], "--tolerance"), (["--units", "m"], "--units"),
                        (["--joints", "q=1"], "--joints")):
        assert main(["law", prog, "--out", str(tmp_path / "o"), *flags]) == 2
        assert capsys.readouterr().err.startswith(f"oga law: error: {what}")
    assert main(["law", str(tmp_path / "missing.ngc"), "--out", str(tmp_path / "o")]) == 2


def test_api_law_job(tmp_path):
    """POST /v1/law: 422 naming a bad option; a job's zip holds the controller files."""
    app = create_app(Settings(db_path=str(tmp_path / "l.db"), workers=0))
    text = (DATA / "short_xz.ngc").read_text()
    body = {"programs": [{"format": "gcode", "content": text, "name": "short_xz"}],
            "kind": "pl", "points": 2, "overrides": [1.0]}
    with TestClient(app) as client:
        for bad, field in (({"points": 5}, "points"), ({"overrides": [0.5]}, "overrides"),
                           ({"kind": "x"}, "kind"), ({"tolerance": 50}, "tolerance"),
                           ({"extra": 1}, "extra")):
            r = client.post("/v1/law", json={**body, **bad})
            assert r.status_code == 422 and field in json.dumps(r.json()), r.json()
        bad_prog = {**body, "programs": [{"format": "gcode", "content": "G1 X1 Q#", "name": "b"}]}
        r = client.post("/v1/law", json=bad_prog)
        assert r.status_code == 422 and "b:1:" in r.json()["message"]
        r = client.post("/v1/law", json=body)
        assert r.status_code == 202
        job = r.json()["id"]
        owner = Owner(socket.gethostname(), 12345, "t", 12345)
        assert run_claimed(app.state.store, app.state.store.claim(owner)) == "succeeded"
        r = client.get(f"/v1/jobs/{job}/law")
        assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
        names = zipfile.ZipFile(io.BytesIO(r.content)).namelist()
        assert "oga_law.hal" in names and "oga_law_twincat_x.txt" in names
        summary = client.get(f"/v1/jobs/{job}/summary").json()
        assert summary["law"]["kind"] == "pl" and summary["certificate"]["cases"]
        assert client.get(f"/v1/jobs/{job}/table").status_code == 409
        # two programs: one law, judged against their joint baseline (the same gains on both)
        circle = (DATA / "circle_r50_f3000.ngc").read_text()
        two = {**body, "programs": body["programs"] + [
            {"format": "gcode", "content": circle, "name": "circle"}]}
        job = client.post("/v1/law", json=two).json()["id"]
        assert run_claimed(app.state.store, app.state.store.claim(owner)) == "succeeded"
        summary = client.get(f"/v1/jobs/{job}/summary").json()
        bases = summary["baselines"]
        assert len(bases) == 2 and len({(b["kp_m_min_per_mm"], b["kf"]) for b in bases.values()}) == 1
        assert {c["program"] for c in summary["certificate"]["cases"]} == set(bases)


def test_one_law_for_two_programs_is_judged_against_their_joint_baseline(short):
    """A law for several programs is certified against the one fixed setting that keeps every
    plant's checks on all of them (oga.law.baseline), recomputed here: the joint baseline
    called directly, and a certificate's ratio on each program from fresh replays of the law
    and those gains. Per-program baselines (different gains) are refused, naming why."""
    from oga.search.robust.baseline import joint_baseline

    scen = scenario_set(MACHINE, n=8)
    # (short_xz with circle_r50_f3000, certified until the profile's jerk share of 2026-11-29,
    # now ends without a law: a search's outcome, not what this test is about)
    ref = plan_override(load_toolpath(DATA / "reference_xz.ngc"), MACHINE, 1.0, 2e-5)
    programs = [Program("short_xz", {1.0: short[1][1.0]}), Program("reference_xz", {1.0: ref})]
    res = search_law(programs, MACHINE, "pl", 2, scenarios=scen, threads=2)
    assert res.status == "ok" and res.alpha > 0.0  # a law, not the baseline's constant
    direct = joint_baseline({p.name: p.setpoints[1.0] for p in programs}, MACHINE, scen,
                            threads=1)
    assert [(b.kp, b.kf, b.mse_m2) for b in res.baselines.values()] == [
        (b.kp, b.kf, b.mse_m2) for b in direct]
    kp_b, kf_b = direct[0].kp, direct[0].kf
    for p in programs:
        sp = p.setpoints[1.0]
        cert = res.certificate.cases[(p.name, 1.0)]
        kp, kf = law_gains(res.law, sp)
        q = int(np.argmax(cert.ratio))
        bounds = cert.plants[q].kp_bounds
        law_v = verify(sp, scen.plants[q], kp, kf, bounds)
        base_v = verify(sp, scen.plants[q], np.full((len(sp), 3), kp_b),
                        np.full((len(sp), 3), kf_b), bounds)
        assert law_v.metrics.mse_m2 / base_v.metrics.mse_m2 == pytest.approx(cert.ratio[q],
                                                                              rel=1e-12)
        assert base_v.ok
    # on plants the search never saw (another seed, no corners), every sample replayed: the
    # law breaks no check the joint baseline keeps, on either program
    unseen = scenario_set(MACHINE, n=8, seed=99, corners=False)
    for p in programs:
        sp = p.setpoints[1.0]
        kp, kf = law_gains(res.law, sp)
        moving = tuple(AXES[i] for i in sp.moving_axes)
        for plant, bounds in zip(unseen.plants, plant_bounds(unseen, moving)):
            base_v = verify(sp, plant, np.full((len(sp), 3), kp_b), np.full((len(sp), 3), kf_b),
                            bounds, series=False)
            law_v = verify(sp, plant, kp, kf, bounds, series=False)
            assert base_v.ok and law_v.ok, (p.name, law_v.violations)
    hal = law_files(res, "ucp710", len(scen))["oga_law.hal"]  # the export names the gains
    assert f"joint baseline of short_xz, reference_xz: Kp {kp_b:g} (m/min)/mm, Kf {kf_b:g}" in hal
    own = {p.name: robust_baseline(p.setpoints[1.0], MACHINE, scen, threads=1) for p in programs}
    assert len({(b.kp, b.kf) for b in own.values()}) == 2
    with pytest.raises(OptionError, match="joint baseline"):
        search_law(programs, MACHINE, "pl", 2, scenarios=scen, baselines=own, threads=1)
    with pytest.raises(OptionError, match="for all or none"):
        search_law(programs, MACHINE, "pl", 2, scenarios=scen,
                   baselines={"short_xz": own["short_xz"]}, threads=1)


def test_a_search_that_stays_at_the_baseline_is_no_law_found(short, monkeypatch):
    """Where a round's search takes no step (the law is the baseline's constant), that is not a
    certified law: the result is ``failed``, exports the baseline and says why, its
    certificate the baseline's own (ratio 1 on every plant, replayed)."""
    import oga.law.search as law_search

    monkeypatch.setattr(law_search._Context, "search",
                        lambda self, theta0, keys, reserve: (theta0.copy(), 0))
    scen = scenario_set(MACHINE, n=8)
    res = search_law([Program("short_xz", {1.0: short[1][1.0]})], MACHINE, "pl", 2,
                     scenarios=scen, threads=1)
    assert res.status == "failed" and res.rounds == 1 and res.alpha == 0.0
    assert "stayed at the baseline" in res.reason
    base = res.baselines["short_xz"]
    for ax in res.law.axes.values():  # a constant law (the baseline's, at the resolution)
        assert np.ptp(ax.kp_m_min_per_mm) == 0.0 and np.ptp(ax.kf) == 0.0
    kp, kf = law_gains(res.law, short[1][1.0])
    moving = list(short[1][1.0].moving_axes)
    assert np.allclose(kp[:, moving], base.kp, atol=0.01) and np.allclose(kf[:, moving], base.kf,
                                                                          atol=0.01)
    cert = res.certificate.cases[("short_xz", 1.0)]
    assert cert.worst == pytest.approx(1.0, abs=0.02) and not cert.breaks("schedule-only")
