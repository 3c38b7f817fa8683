"""``oga excite`` and ``oga identify`` end to end on a short synthetic trace, and their
answers to bad input (exit 2, one line naming what is wrong)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.cli import main
from oga.identify.sim import synthetic_trace
from oga.identify.trace import trace_csv
from oga.model.machine import load_machine
from oga.pipeline import plan_toolpath


@pytest.fixture(scope="module")
def trace_file(tmp_path_factory):
    """A 20 mm identification program of axis x run on ucp710 with Kv +20 % and Tn -30 %,
    recorded at Kp 3, Kf 0.8 with 0.1 um noise and quantum."""
    d = tmp_path_factory.mktemp("ident")
    assert main(["excite", "--machine", "ucp710", "--axes", "x", "--travel-mm", "20",
                 "--out", str(d / "excite.ngc")]) == 0
    base = load_machine("ucp710")
    cas = base.axis("x").cascade
    true = base.model_copy(update={"axes": {**base.axes, "x": base.axis("x").model_copy(update={
        "cascade": cas.model_copy(update={"kv_n_s_m": cas.kv_n_s_m * 1.2, "tn_s": cas.tn_s * 0.7})})}})
    sp = plan_toolpath(load_toolpath(d / "excite.ngc"), base, feed_m_s=None, tol_m=2e-5)
    ch = synthetic_trace(sp, true, ["x"], 3.0, 0.8, noise_m=1e-7, quantum_m=1e-7, seed=5)
    t = ch.pop("t_s")
    (d / "trace.csv").write_text(trace_csv(t, ch))
    return d, true


def test_identify_cli_writes_a_loadable_machine_with_intervals(trace_file, capsys):
    d, true = trace_file
    out = d / "mine.toml"
    code = main(["identify", str(d / "trace.csv"), "--machine", "ucp710", "--kp", "x=3.0",
                 "--kf", "0.8", "--out", str(out), "--summary", str(d / "fit.json"),
                 "--report", str(d / "fit.html")])
    printed = capsys.readouterr().out
    assert code == 0, printed
    mine = load_machine(out)
    cas, ref = mine.axis("x").cascade, true.axis("x").cascade
    assert cas.kv_n_s_m == pytest.approx(ref.kv_n_s_m, rel=0.05)
    assert cas.tn_s == pytest.approx(ref.tn_s, rel=0.05)
    assert mine.timing.dead_time_samples == 2
    text = out.read_text()
    assert "kv_n_s_m = " in text and "# 95 % CI [" in text and "position residual RMS" in text
    unc = mine.axis("x").uncertainty
    assert unc is not None and unc.kv_n_s_m[0] < 1.0 < unc.kv_n_s_m[1]
    summary = json.loads((d / "fit.json").read_text())
    assert summary["axes"]["x"]["dead_time_samples"] == 2 and "holdout" in summary["axes"]["x"]
    h = summary["axes"]["x"]["holdout"]
    assert h["rms_heldout_m"] < 5 * h["rms_fit_m"]
    html = (d / "fit.html").read_text()
    assert html.count("<svg") == 2 and "Held-out check" in html
    assert "x: mass 600.0 kg (base)" in printed


@pytest.mark.parametrize("edit, args, message", [
    (lambda s: "\n".join(ln if i != 5 else ln.split(",")[0] + ",nan," + ln.split(",", 2)[2]
               for i, ln in enumerate(s.splitlines())) + "\n",
     ["--kp", "3", "--kf", "0.8"], "column 'x_cmd_m', row 6: nan is not a finite number"),
    (lambda s: s, ["--kf", "0.8"], "no x_kp_m_min_per_mm column and no --kp"),
    (lambda s: s, ["--kp", "3", "--kf", "0.8", "--machine", "nosuch"], "unknown machine 'nosuch'"),
    (lambda s: s, ["--kp", "3", "--kf", "0.8", "--axes", "z"], "axis z: not in the trace"),
])
def test_identify_bad_input_exit_2(trace_file, tmp_path, capsys, edit, args, message):
    d, _ = trace_file
    bad = tmp_path / "bad.csv"
    bad.write_text(edit((d / "trace.csv").read_text()))
    code = main(["identify", str(bad), "--out", str(tmp_path / "m.toml"), *args])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_excite_bad_input_exit_2(tmp_path, capsys):
    assert main(["excite", "--axes", "x,q", "--out", str(tmp_path / "e.ngc")]) == 2
    assert "--axes: unknown axis 'q'" in capsys.readouterr().err
    assert main(["excite", "--axes", "x", "--travel-mm", "0", "--out", str(tmp_path / "e.ngc")]) == 2
    assert "--travel-mm must be in (1, 10000]" in capsys.readouterr().err
