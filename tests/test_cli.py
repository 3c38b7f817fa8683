"""The ``oga`` command line as a user runs it: outputs, exit codes, one-line errors."""

from __future__ import annotations

import json
import os
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
                 "--gains", "kp", "--kp-range", "1.0,2.7", "--mode", "paper", "--nominal",
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
    assert main(["optimize", str(DATA / "short_xz.ngc"), "--machine", str(machine), "--nominal",
                 "--out", str(out), "--summary", str(summ)]) == 0
    printed = capsys.readouterr().out
    assert "(limit 150.0)" in printed and "limits ok" in printed
    s = json.loads(summ.read_text())
    assert s["optimized"]["track_max_um"]["x"] <= 150.0
    assert 0.0 < s["ferror_ratio_to_limit"]["x"] <= 1.0 and s["ferror_ratio_to_limit"]["z"] is None
    # a limit no equal fixed gains keep: exit 2, naming the option to give
    machine.write_text(text.replace("ferror_max_m = 1.5e-4", "ferror_max_m = 1e-6"))
    assert main(["optimize", str(DATA / "short_xz.ngc"), "--machine", str(machine), "--nominal",
                 "--out", str(out)]) == 2
    assert "following-error" in capsys.readouterr().err


@pytest.mark.parametrize(
    "text, needle",
    [("G21 G90\nG1 X1 F100\nM31\n", "3:1"), ("G21\nG1 X#1 F[1/0]\n", "2:"),
     ("G21\nG1 A3 F100\n", "2:")],
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
    assert main(["optimize", *args, "--kp-range", "1.0,9.0", "--baseline", "3.0,0.8",
                 "--nominal"]) == 2


def oga(*args: str, cwd=None) -> subprocess.CompletedProcess:
    """The installed ``oga`` command (``python -m oga`` where no script is installed)."""
    script = Path(sys.executable).with_name("oga")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "oga"]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=600, cwd=cwd)


def _one_line_error(r: subprocess.CompletedProcess, *needles: str) -> str:
    """Assert exit code 2 with exactly one line on stderr holding every needle."""
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _output_cases(tmp: Path) -> list[tuple[list[str], tuple[str, ...]]]:
    src = str(DATA / "short_xz.ngc")
    missing = tmp / "missing" / "dir"
    return [
        (["plan", src, "--out", str(tmp)], ("--out", str(tmp), "is a folder")),
        (["plan", src, "--out", "/proc/x.csv"], ("--out /proc/x.csv", "cannot write in /proc")),
        (["plan", src, "--out", str(missing / "x.csv")],
         ("--out", str(missing / "x.csv"), f"{missing} does not exist")),
        (["plan", src, "--out", ""], ("--out", "empty file name")),
        (["plan", src, "--out", str(tmp / "sp.csv"), "--summary", str(tmp)],
         ("--summary", "is a folder")),
        (["plan", src, "--out", str(tmp / "f.csv"), "--summary", str(tmp / "f.csv")],
         ("--summary", "the same file as --out")),
        (["plan", src, "--out", "/dev/null"], ("--out /dev/null", "not a regular file")),
        (["optimize", src, "--out", str(tmp / "t.csv"), "--report", str(missing / "r.html")],
         ("--report", "does not exist")),
        (["optimize", src, "--out", str(tmp / "t.csv"), "--summary", str(tmp)],
         ("--summary", "is a folder")),
        (["ranges", "--json", str(tmp)], ("--json", "is a folder")),
        (["compare", src, "--controllers", "fixed", "--json", "/proc/c.json"],
         ("--json /proc/c.json", "cannot write")),
        (["compare", src, "--controllers", "fixed", "--report", str(missing / "c.html")],
         ("--report", "does not exist")),
        (["batch", src, "--out", str(missing / "out")],
         ("--out", f"parent folder {missing} does not exist")),
        (["batch", src, "--out", src], ("--out", "not a folder")),
        (["plan", src, "--out", str(tmp / ("a" * 300 + ".csv"))],
         ("--out", "cannot write in", "File name too long")),
        (["batch", src, "--out", str(tmp / ("a" * 300))],
         ("--out", "cannot create the folder (File name too long)")),
        (["batch", str(tmp / ("a" * 300 + ".ngc")), "--out", str(tmp / "out")],
         ("a.ngc: no such file or folder",)),
    ]


def test_output_options_refused_before_any_work(tmp_path):
    """Row 6 and 16 of issue 18: a folder, /proc, a missing folder (never created)..."""
    for args, needles in _output_cases(tmp_path):
        _one_line_error(oga(*args), *needles)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written or created


def test_an_output_never_overwrites_the_toolpath(tmp_path):
    program = tmp_path / "part.ngc"
    program.write_text((DATA / "short_xz.ngc").read_text())
    before = program.read_text()
    _one_line_error(oga("plan", str(program), "--out", str(program)),
                    "--out", "the same file as the TOOLPATH")
    _one_line_error(oga("optimize", "part.ngc", "--out", "t.csv", "--summary", "./part.ngc",
                        cwd=tmp_path), "--summary ./part.ngc", "the same file as the TOOLPATH")
    # oga batch: a polyline input whose table (.json) would land on itself
    (tmp_path / "poly.json").write_text('{"points": [[0, 0, 0], [10, 0, 0]], '
                                        '"feed_mm_per_min": 3000}')
    _one_line_error(oga("batch", str(tmp_path / "poly.json"), "--out", str(tmp_path),
                        "--format", "json"), "--out", "poly.json would overwrite an input")
    assert program.read_text() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "part.ngc", "poly.json"]


def test_batch_creates_its_output_folder_but_not_its_parents(tmp_path):
    """`oga batch --out DIR` creates DIR (the folder of the outputs) when its parent exists."""
    r = oga("batch", str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "new"), "--np", "0")
    _one_line_error(r, "--np")  # bad options: refused before DIR is created
    assert not (tmp_path / "new").exists()
    r = oga("batch", str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "new"), "--nominal")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == [
        "short_xz.csv", "short_xz.summary.json"]


@pytest.mark.parametrize("command", ["optimize", "batch"])
def test_option_errors_name_the_flag_given(tmp_path, command):
    """Row 12 of issue 18: `--kp-range a,b` named "KP,KF"."""
    out = str(tmp_path / ("t.csv" if command == "optimize" else "out"))
    src = str(DATA / "short_xz.ngc")
    for args, needles in [
        (["--kp-range", "a,b"], ("--kp-range: expected two numbers LO,HI (got 'a,b')",)),
        (["--kp-range", "1"], ("--kp-range: expected two numbers LO,HI (got '1')",)),
        (["--kp-range", "3,1"], ("--kp-range: need 0 < LO <= HI (got '3,1')",)),
        (["--baseline", "1,x"], ("--baseline: expected 'best' or two numbers KP,KF",)),
        (["--baseline", "1,2"], ("--baseline: Kf must lie in [0, 1] (got '1,2')",)),
        (["--adjust", "x,q"], ("--adjust:", "(got 'x,q')")),
        (["--gains", ","], ("--gains: name at least one of kp, kf",)),
        (["--lam", "nan"], ("--lam: Input should be a finite number (got nan)",)),
        (["--mode", "paper", "--knot", "3"], ("--knot: only full mode",)),
        (["--np", "x"], ("argument --np: invalid int value: 'x'", f"see oga {command} --help")),
        (["--feed", "1e300"], ("--feed:", "(got 1e+300)")),
    ]:
        _one_line_error(oga(command, src, "--out", out, *args), *needles)
    assert not list(tmp_path.iterdir())


def test_plan_options_and_usage_errors_are_one_line(tmp_path):
    src, out = str(DATA / "short_xz.ngc"), str(tmp_path / "sp.csv")
    _one_line_error(oga("plan", src, "--out", out, "--dt", "nan"), "--dt", "nan")
    _one_line_error(oga("plan", src, "--out", out, "--dt=-1e-3"), "--dt", "-0.001")
    _one_line_error(oga("plan", src, "--out", out, "--bogus"), "unrecognized arguments: --bogus")
    _one_line_error(oga("plan", src), "the following arguments are required: --out")
    _one_line_error(oga("nosuch"), "invalid choice: 'nosuch'")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("command", ["plan", "optimize", "ranges", "compare"])
def test_toolpath_errors_name_the_file_once_first(tmp_path, command):
    """Row 12 of issue 18: a CSV error named no file, a non-UTF-8 one named it after the line."""
    files = {
        "poly.csv": (b"x,y,z\n0,0,0\n1,a,3\n", "poly.csv:3:"),
        "latin.ngc": (b"G21\nG1 X1 F100 (\xe9)\n", "latin.ngc:2:13: not UTF-8"),
        "poly.json": (b'{"points": 3}', "poly.json: "),
        "q.ngc": (b"G21 G90\nG1 X1 F100 Q\n", "q.ngc:2:12: "),
    }
    for name, (data, start) in files.items():
        (tmp_path / name).write_bytes(data)
        outs = ["--out", "o.csv"] if command in ("plan", "optimize") else []
        line = _one_line_error(oga(command, name, *outs, cwd=tmp_path))
        message = line.split(": error: ", 1)[1]
        assert message.startswith(start) and message.count(name) == 1, line


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_an_input_that_would_never_end_is_refused(tmp_path):
    """A FIFO or a device (named like a program or a machine file) would block or never end."""
    os.mkfifo(tmp_path / "fifo.ngc")
    os.mkfifo(tmp_path / "mill.toml")
    (tmp_path / "zero.ngc").symlink_to("/dev/zero")
    src, out = str(DATA / "short_xz.ngc"), str(tmp_path / "o.csv")
    for name in ("fifo.ngc", "zero.ngc"):
        for command in (["plan", "--out", out], ["optimize", "--out", out], ["ranges"],
                        ["compare"]):
            _one_line_error(oga(command[0], str(tmp_path / name), *command[1:]),
                            f"TOOLPATH {tmp_path / name}: not a regular file")
        _one_line_error(oga("batch", str(tmp_path / name), "--out", str(tmp_path / "b")),
                        f"{tmp_path / name}: not a regular file")
    machine = str(tmp_path / "mill.toml")
    _one_line_error(oga("ranges", "--machine", machine), f"--machine {machine}: not a regular")
    _one_line_error(oga("batch", src, "--machine", machine, "--out", str(tmp_path / "b")),
                    f"--machine {machine}: not a regular file")
    # plan, ranges and compare take --feed and --tolerance within oga optimize's bounds
    _one_line_error(oga("plan", src, "--out", out, "--feed", "1e300"), "--feed:", "1e+300")
    _one_line_error(oga("compare", src, "--tolerance", "0"), "--tolerance:", "(got 0.0)")
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "b").exists()


def test_readme_quickstart_command_into_a_missing_folder_is_refused(tmp_path):
    """The Quickstart's oga command, written into a folder that does not exist: refused, no
    silent mkdir. Its run and output: tests/test_docs.py runs the README's blocks."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    block = readme.split("## Quickstart", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    command = block.splitlines()[0].split(" && ", 1)[1]
    assert command.startswith("oga optimize ") and " --out table.csv " in command
    (tmp_path / "examples").symlink_to(Path(__file__).parents[1] / "examples")
    r = oga(*command.replace("--out table.csv", "--out out/table.csv").split()[1:], cwd=tmp_path)
    assert r.returncode == 2 and "folder out does not exist" in r.stderr
    assert not (tmp_path / "out").exists()


def test_an_unexpected_error_is_one_line_not_a_traceback(tmp_path, monkeypatch, capsys):
    """A bug reached by some input still ends with one line (exit 1), naming the exception."""
    import oga.cli.plan

    def broken(args):
        raise OverflowError("int too large to convert to float")

    monkeypatch.setattr(oga.cli.plan, "run", broken)
    assert main(["plan", str(DATA / "short_xz.ngc"), "--out", str(tmp_path / "o.csv")]) == 1
    err = capsys.readouterr().err
    assert err.splitlines() == [
        "oga plan: internal error: OverflowError: int too large to convert to float (a bug: "
        "please report it with the input; python -X dev -m oga ... shows where)"]


def test_toolpath_message_names_the_file_once_first_whatever_the_reader_said():
    """Readers name the file after the line, before the message, first, or not at all."""
    from oga.cli._common import toolpath_message
    from oga.errors import GcodeError, InputError, ToolpathError

    given = "dir/part.csv"
    for err, expected in [
        (ToolpathError("field y: 'a' is not a number", 3, 2),
         "dir/part.csv:3:2: field y: 'a' is not a number"),
        (ToolpathError("part.csv: not UTF-8 text (byte 0xe9)", 2, 13),
         "dir/part.csv:2:13: not UTF-8 text (byte 0xe9)"),
        (GcodeError("Q word: has no number", 2, 12, source="part.csv"),
         "dir/part.csv:2:12: Q word: has no number"),
        (ToolpathError("row 4: z missing", 4), "dir/part.csv:4: row 4: z missing"),
        (ToolpathError("part.csv:3:2: field y: bad"), "part.csv:3:2: field y: bad"),
        (InputError("dir/part.csv: cannot read the file (No such file or directory)"),
         "dir/part.csv: cannot read the file (No such file or directory)"),
        (ToolpathError("a JSON polyline is a list of points"),
         "dir/part.csv: a JSON polyline is a list of points"),
    ]:
        assert str(toolpath_message(err, given)) == expected
