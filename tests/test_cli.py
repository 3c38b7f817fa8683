"""The ``oga`` command line as a user runs it: outputs, exit codes, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from oga.cli import main

DATA = Path(__file__).parent / "data"


def test_plan_writes_setpoints_and_summary(tmp_path, capsys):
    out, summ = tmp_path / "sp.csv", tmp_path / "s.json"
    assert main(["plan", str(DATA / "short_xz.ngc"), "--machine", "ucp710",
                 "--out", str(out), "--summary", str(summ)]) == 0
    header = out.read_text().splitlines()[0].split(",")
    assert header[:6] == ["t_s", "s_m", "x_pos_m", "x_vel_m_s", "x_acc_m_s2", "x_jerk_m_s3"]
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    s = json.loads(summ.read_text())
    assert s["samples"] == data.shape[0] and s["limits_ok"] is True
    # independent finite-difference check of the CSV against ucp710's limits
    dt = data[1, 0] - data[0, 0]
    for col, (vmax, amax, jmax) in ((2, (0.5, 2.5, 10.0)), (10, (0.5, 2.1, 100.0))):
        p = data[:, col]
        v = np.diff(p) / dt
        assert np.abs(v).max() <= vmax
        assert np.abs(np.diff(v)).max() / dt <= amax
        assert np.abs(np.diff(v, 2)).max() / dt**2 <= jmax * (1 + 1e-9)


def test_optimize_writes_table_and_summary(tmp_path):
    out, summ = tmp_path / "t.csv", tmp_path / "s.json"
    code = main(["optimize", str(DATA / "short_xz.ngc"), "--baseline", "1.6,0.9", "--adjust", "z",
                 "--gains", "kp", "--kp-range", "1.0,2.7", "--mode", "paper",
                 "--out", str(out), "--summary", str(summ)])
    assert code == 0
    s = json.loads(summ.read_text())
    for key in ("toolpath", "machine", "samples", "duration_s", "adjusted", "gains", "baseline",
                "optimized", "ratio_mse", "limits_ok", "stability_ok", "max_dkp_per_sample",
                "optimize_time_s", "options", "toolpath_sha256", "machine_sha256"):
        assert key in s
    assert s["adjusted"] == ["z"] and s["gains"] == ["kp"] and s["limits_ok"]
    assert s["baseline"]["kp"]["x"] == 1.6 and s["options"]["mode"] == "paper"
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    assert table.shape[0] == s["samples"]
    assert np.all(table[:, 4] == 1.6)  # x_kp fixed


def test_optimize_with_a_following_error_limit_in_the_machine_file(tmp_path, capsys):
    preset = Path(__file__).parents[1] / "oga" / "presets" / "ucp710.toml"
    text = preset.read_text().replace("[axes.x.limits]", "[axes.x.limits]\nferror_max_m = 1.5e-4")
    machine = tmp_path / "mill.toml"
    machine.write_text(text)
    out, summ = tmp_path / "t.csv", tmp_path / "s.json"
    assert main(["optimize", str(DATA / "short_xz.ngc"), "--machine", str(machine),
                 "--out", str(out), "--summary", str(summ)]) == 0
    printed = capsys.readouterr().out
    assert "(limit 150.0)" in printed and "limits ok" in printed
    s = json.loads(summ.read_text())
    assert s["optimized"]["track_max_um"]["x"] <= 150.0
    assert 0.0 < s["ferror_ratio_to_limit"]["x"] <= 1.0 and s["ferror_ratio_to_limit"]["z"] is None
    # a limit no equal fixed gains keep: exit 2, naming the option to give
    machine.write_text(text.replace("ferror_max_m = 1.5e-4", "ferror_max_m = 1e-6"))
    assert main(["optimize", str(DATA / "short_xz.ngc"), "--machine", str(machine),
                 "--out", str(out)]) == 2
    assert "following-error" in capsys.readouterr().err


@pytest.mark.parametrize(
    "text, needle",
    [("G21 G90\nG1 X1 F100\nG91\n", "3:1"), ("G21\nG1 X#1 F100\n", "2:"), ("G21\nG1 A3 F100\n", "2:")],
)
def test_bad_gcode_exit_2_one_line(tmp_path, text, needle):
    bad = tmp_path / "bad.ngc"
    bad.write_text(text)
    proc = subprocess.run([sys.executable, "-m", "oga", "plan", str(bad), "--out",
                           str(tmp_path / "o.csv")], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in proc.stderr


def test_bad_machine_and_option_exit_2(tmp_path, capsys):
    args = [str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "o.csv")]
    assert main(["plan", *args, "--machine", "nosuch"]) == 2
    assert "nosuch" in capsys.readouterr().err
    assert main(["optimize", *args, "--np", "0"]) == 2
    assert "np" in capsys.readouterr().err
    assert main(["optimize", *args, "--kp-range", "1.0,9.0", "--baseline", "3.0,0.8"]) == 2
