"""The robust search as users meet it: ``oga optimize`` on ucp710 (its default uncertainty set).

- ``--nominal`` / ``nominal=True`` is the search before issue 17 (schedules computed on commit
  c417bb6, before the robust default existed, kept as arrays: :mod:`references`), and on a
  machine without a set it is the same search bit for bit;
- the robust default prints the certificate and writes it to the summary and the report, every
  figure recomputed here from fresh simulations of the written table on the set's plants, each
  written as a machine file and loaded back (:func:`test_robust_certificate.fresh_certificate`);
- a table the certificate refuses is not exported: the baseline is, and the summary says why.

Short programs only: the robust search costs tens of seconds where the nominal one costs one.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from feedplan.plan import plan
from feedplan.read import load_toolpath
from oga.cli import main
from oga.errors import OptionError
from oga.model.machine import load_machine, machine_from_dict
from oga.optimize import GainSchedule, optimize
from oga.search.robust.plants import scenario_set
import references
from pinned_setpoints import pinned_setpoints
from test_robust_certificate import PRESET, assert_same_certificate, fresh_certificate

DATA = Path(__file__).parent / "data"
PROGRAM = DATA / "short_xz.ngc"


def _arrays(r):
    return (r.schedule.kp_m_min_per_mm, r.schedule.kf, r.searched_schedule.kp_m_min_per_mm,
            r.searched_schedule.kf)


def _without_set(machine):
    data = machine.model_dump(mode="json", exclude_none=True)
    for ax in data["axes"].values():
        ax.pop("uncertainty", None)
    return machine_from_dict(data)


def _table_gains(path: Path, summary: dict):
    """Kp, Kf (N, 3) of a written table, and the baseline's, per the summary."""
    head = path.read_text().split("\n", 1)[0].split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    kp = data[:, [head.index(f"{a}_kp_m_min_per_mm") for a in "xyz"]]
    kf = data[:, [head.index(f"{a}_kf") for a in "xyz"]]
    n = len(data)
    bkp = np.tile([summary["baseline"]["kp"][a] for a in "xyz"], (n, 1))
    bkf = np.tile([summary["baseline"]["kf"][a] for a in "xyz"], (n, 1))
    return kp, kf, bkp, bkf


def test_nominal_is_the_search_before_the_robust_default():
    m = load_machine("ucp710")
    bare = _without_set(m)
    sp = pinned_setpoints(PROGRAM.name)  # as planned then: the planner may change, the search not
    for mode in ("full", "paper"):
        r = optimize(sp, m, {"mode": mode, "nominal": True})
        assert not r.robust and r.summary()["certificate"]["status"] == "none"
        case = PROGRAM.name + ("" if mode == "full" else " paper")
        assert references.compare("search", case, references.search_arrays(r)) == []
        # a machine without a set is searched nominally whatever the option says
        ref = optimize(sp, bare, {"mode": mode})
        assert not ref.robust
        for a, b in zip(_arrays(r), _arrays(ref)):
            np.testing.assert_array_equal(a, b)


def test_robust_refuses_options_that_only_mean_something_nominally():
    m = load_machine("ucp710")
    sp = plan(load_toolpath(PROGRAM), m.planning_limits())
    for opts, field in (({"mode": "paper"}, "mode"), ({"baseline": "3.0,0.8"}, "baseline")):
        with pytest.raises(OptionError, match=f"^{field}: .*uncertainty set.*--nominal"):
            optimize(sp, m, opts)
    with pytest.raises(OptionError, match="nominal"):
        optimize(sp, m, {"nominal": "yes"})  # a bool, not a word


def test_robust_default_prints_and_writes_a_certificate_fresh_simulations_confirm(
        tmp_path, capsys):
    d = tmp_path
    out, summ, report = d / "t.csv", d / "s.json", d / "r.html"
    assert main(["optimize", str(PROGRAM), "--out", str(out), "--summary", str(summ),
                 "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    s = json.loads(summ.read_text())
    c = s["certificate"]
    assert s["search"]["kind"] == "robust" and s["options"]["nominal"] is False
    assert c["plants"] == 96 and c["monte_carlo"] == 64 and c["corners"] == 32
    assert not s["kept_baseline"] and s["kept_baseline_reason"] == "" and c["status"] == "ok"
    # printed: the same figures
    assert (f"certificate ok: 96 plants of the uncertainty set (64 Monte Carlo, seed "
            f"{c['seed']}; 32 corners)") in printed
    assert (f"MSE ratio to the fixed baseline: median {c['ratio_median']:.3f}, p90 "
            f"{c['ratio_p90']:.3f}, worst {c['ratio_worst']:.3f} ({c['worst_plant']})") in printed
    assert (f"plants where a limit breaks: schedule {len(c['breaks']['schedule'])}, baseline "
            f"{len(c['breaks']['baseline'])}, schedule only 0") in printed
    assert f"largest CE (um): schedule {c['schedule']['max_ce_um']:.3f}" in printed
    assert printed.splitlines()[-1] == f"limits ok, stability ok -> {out}"
    # every figure again, from the written table on plant files (no certificate code)
    kp, kf, bkp, bkf = _table_gains(out, s)
    m = load_machine("ucp710")
    sp = plan(load_toolpath(PROGRAM), m.planning_limits())
    assert len(sp) == len(kp)
    scen = scenario_set(m)  # for its labels and draws only (the seeded set of the summary)
    assert scen.seed == c["seed"]
    fresh = fresh_certificate(sp, tomllib.loads(PRESET.read_text()), scen.labels, scen.draws,
                              kp, kf, bkp, bkf, d)
    assert_same_certificate(c, fresh)
    assert fresh["ratio_worst"] <= 1.0 and not fresh["breaks"]["schedule-only"]
    # the report: figures 7 (ratio distribution) and 8 (contour error on the worst plant)
    html = report.read_text()
    assert html.count("<figure") == 8
    assert "Figure 7. Certificate ok" in html and f"{c['ratio_worst']:.3f}" in html
    fig8 = html.split('<figure id="fig8">')[1].split("</figure>")[0]
    assert c["worst_plant"] in fig8 and fig8.count("<path") >= 2
    # the service rebuilds the report of a stored job from its table and summary alone
    from oga.report.optimize import render_report, replay_report_data

    rebuilt = render_report(replay_report_data(sp, m, kp, kf, s))
    for n in (7, 8):
        assert (rebuilt.split(f'<figure id="fig{n}">')[1].split("</figure>")[0]
                == html.split(f'<figure id="fig{n}">')[1].split("</figure>")[0])


def test_a_table_the_certificate_refuses_is_not_exported_the_baseline_is(tmp_path, capsys,
                                                                         monkeypatch):
    """The search proposes a schedule the certificate must refuse (the robust schedule
    without its feed-forward: worse than the baseline on every plant, as the real
    :func:`oga.verify.certificate.certify` finds on the whole set): the table holds the
    baseline, the summary and the output say why, exit 0 as for any kept baseline. (A wider
    set does not force a refusal: a search may always fall back to the baseline.)"""
    import oga.search.robust.search as rs
    from oga.verify.certificate import certify

    real = rs.robust_optimize

    def worse(setpoints, machine, options=None, scenarios=None, progress=None):
        rob = real(setpoints, machine, options, scenarios, progress)
        n = len(setpoints)
        bkp = np.tile([rob.result.baseline_kp[a] for a in "xyz"], (n, 1))
        bkf = np.tile([rob.result.baseline_kf[a] for a in "xyz"], (n, 1))
        cert = certify(setpoints, machine, rob.schedule.kp_m_min_per_mm,
                       np.zeros_like(rob.schedule.kf), bkp, bkf)
        assert cert.status == "failed"
        return dataclasses.replace(rob, status="failed", certificate=cert,
                                   schedule=GainSchedule(kp_m_min_per_mm=bkp, kf=bkf))

    monkeypatch.setattr(rs, "robust_optimize", worse)
    out, summ = tmp_path / "t.csv", tmp_path / "s.json"
    assert main(["optimize", str(PROGRAM), "--out", str(out), "--summary", str(summ)]) == 0
    printed = capsys.readouterr().out
    s = json.loads(summ.read_text())
    assert s["certificate"]["status"] == "failed" and s["kept_baseline"] and s["status"] == "ok"
    assert s["certificate"]["ratio_worst"] > 1.0
    assert s["kept_baseline_reason"] == ("robustness certificate failed: "
                                         + "; ".join(s["certificate"]["reasons"]))
    assert "worse than the fixed baseline on plant" in s["kept_baseline_reason"]
    assert ("warning: the searched schedule was not kept (robustness certificate failed: "
            in printed) and "certificate failed: 96 plants" in printed
    kp, kf, bkp, bkf = _table_gains(out, s)
    np.testing.assert_array_equal(kp, bkp)
    np.testing.assert_array_equal(kf, bkf)
    assert s["ratio_mse"] == 1.0
    # nor does the controller export: oga export of the table streams the baseline's gains
    from oga.export.linuxcnc import STREAM

    assert main(["export", str(out), "--summary", str(summ), "--out", str(tmp_path / "lc")]) == 0
    rows = np.array([[float(v) for v in ln.split()] for ln in
                     (tmp_path / "lc" / STREAM).read_text().splitlines() if not ln.startswith("#")])
    for k, a in enumerate(s["contouring_axes"]):  # per axis: command, command-deriv, Pgain, FF1
        np.testing.assert_allclose(rows[:, 4 * k + 2], s["baseline"]["kp"][a] * 1000 / 60)
        np.testing.assert_allclose(rows[:, 4 * k + 3], s["baseline"]["kf"][a])
