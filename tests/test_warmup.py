"""``oga warmup`` compiles the kernels a job needs: afterwards the job compiles nothing."""

from __future__ import annotations

import os
import subprocess
import sys

from oga.cli import main

#: Plans the warm-up's program in a fresh interpreter and prints how many kernels numba compiled.
_COUNT_COMPILES = """
from numba.core import event
n = [0]
class Count(event.Listener):
    def on_start(self, e): n[0] += 1
    def on_end(self, e): pass
event.register("numba:compile", Count())
from feedplan.read import read_toolpath
from oga.model.machine import load_machine
from oga.pipeline import plan_toolpath
from oga.warmup import _PROGRAM
sp = plan_toolpath(read_toolpath(_PROGRAM, "gcode"), load_machine("ucp710"), feed_m_s=None,
                   tol_m=2e-5)
planned = n[0]
import numba
numba.njit(lambda x: x + 1)(1)  # one compile the listener must see
print(planned, n[0] - planned, len(sp.pos))
"""


def _run(args, cache):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    return subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True,
                          timeout=600)


def test_a_planned_job_compiles_nothing_after_warmup(tmp_path):
    warm = _run(["-m", "oga", "warmup", "--only", "plan", "--jobs", "1"], tmp_path / "warm")
    assert warm.returncode == 0, warm.stdout + warm.stderr
    assert warm.stdout.startswith("plan ") and str(tmp_path / "warm") in warm.stdout
    after = _run(["-c", _COUNT_COMPILES], tmp_path / "warm")
    assert after.returncode == 0, after.stderr
    planned, control, samples = map(int, after.stdout.split())
    assert (planned, control) == (0, 1) and samples > 500
    assert any(p.suffix == ".nbi" for p in (tmp_path / "warm").rglob("*"))


def test_bad_options_exit_2_naming_them(capsys):
    assert main(["warmup", "--only", "plan,nope"]) == 2
    err = capsys.readouterr().err
    assert "--only" in err and "nope" in err and "identify" in err  # the known groups listed
    assert main(["warmup", "--jobs", "0"]) == 2
    assert "--jobs" in capsys.readouterr().err
