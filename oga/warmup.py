"""Compile every kernel ahead of its first use (``oga warmup``).

numba compiles a kernel on its first call and caches it (:mod:`oga._jitcache`); cold, the
nominal search alone costs about 2 min of CPU (measured: 124 s) before its first table. A
service image, a cluster worker or a CI run that warms up at build time answers its first job
at full speed. Each group runs one small job the way a user would (the CLI on a built-in
program, the identification on a short synthetic trace); groups that share kernels form a
chain run in one process, one group after the other, so no kernel is compiled twice, and the
chains run in parallel processes.
"""

from __future__ import annotations

import contextlib
import io
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

__all__ = ["CHAINS", "GROUPS", "WarmupResult", "warmup"]

#: A short XZ contour (line, arc, line, rapid back; about 1 s of motion).
_PROGRAM = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X8\nG2 X13 Z5 I0 K5\nG1 X25 Z5\nG0 X0 Z0\nM2\n"

#: Groups in chains: a chain's groups share kernels (the search's), so they run in order in one
#: process; chains run in parallel.
CHAINS: tuple[tuple[str, ...], ...] = (
    ("plan", "nominal", "robust", "law"),
    ("paper", "compare", "identify"),
)
GROUPS: tuple[str, ...] = tuple(g for chain in CHAINS for g in chain)


@dataclass(frozen=True)
class WarmupResult:
    """Seconds (wall) per group, in the order run; ``status`` "ok" or "failed: <group>: ..."."""

    status: str
    seconds: dict[str, float]
    cache_dir: str | None


def _cli(folder: str, *argv: str) -> None:
    from oga.cli import main

    program = os.path.join(folder, "warmup.ngc")
    if not os.path.exists(program):
        with open(program, "w") as f:
            f.write(_PROGRAM)
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            code = main([a.replace("{program}", program).replace("{dir}", folder) for a in argv])
        except SystemExit as stop:  # argparse's usage errors
            code = stop.code
    if code != 0:
        raise RuntimeError(f"oga {argv[0]} exited with {code}: {err.getvalue().strip()}")


def _identify(folder: str) -> None:
    from feedplan.read import read_toolpath
    from oga.identify.excite import excite_program
    from oga.identify.sim import synthetic_trace
    from oga.identify.trace import read_trace, trace_csv
    from oga.identify.workflow import identify
    from oga.model.machine import load_machine
    from oga.pipeline import plan_toolpath

    machine = load_machine("ucp710")
    program = excite_program(machine, ["x"], travel_mm=10.0, pass_s=0.3)
    sp = plan_toolpath(read_toolpath(program, "gcode"), machine, feed_m_s=None, tol_m=2e-5)
    channels = synthetic_trace(sp, machine, ["x"], 3.0, 0.8, noise_m=1e-7, seed=1)
    t = channels.pop("t_s")
    identify(read_trace(trace_csv(t, channels), kp=3.0, kf=0.8), machine)


def _run_group(name: str, folder: str) -> None:
    if name == "identify":
        return _identify(folder)
    argv = {
        "plan": ("plan", "{program}", "--out", "{dir}/s.csv"),
        "nominal": ("optimize", "{program}", "--nominal", "--out", "{dir}/n.csv"),
        "paper": ("optimize", "{program}", "--nominal", "--mode", "paper", "--out", "{dir}/p.csv"),
        "robust": ("optimize", "{program}", "--certify", "1", "--threads", "1",
                   "--out", "{dir}/r.csv"),
        "law": ("law", "{program}", "--kind", "pl", "--points", "2", "--overrides", "1",
                "--out", "{dir}/law"),
        "compare": ("compare", "{program}", "--no-tune"),
    }[name]
    _cli(folder, *argv)


def _run_chain(names: tuple[str, ...]) -> tuple[dict[str, float], str | None]:
    seconds: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="oga-warmup-") as folder:
        for name in names:
            t0 = time.perf_counter()
            try:
                _run_group(name, folder)
            except Exception as err:  # reported with the group's name, the others still run
                return seconds, f"{name}: {type(err).__name__}: {err}"
            seconds[name] = time.perf_counter() - t0
    return seconds, None


def warmup(groups: tuple[str, ...] = GROUPS, jobs: int | None = None) -> WarmupResult:
    """Compile the kernels of ``groups`` (names of :data:`GROUPS`) in up to ``jobs`` processes
    (None: one per chain, at most the cores this process may use).

    Raises OptionError naming an unknown group or a ``jobs`` below 1.
    """
    from oga.errors import OptionError
    from oga.parallel import available_cores

    unknown = sorted(set(groups) - set(GROUPS))
    if unknown:
        raise OptionError(f"--only: unknown group(s) {', '.join(unknown)}; known: "
                          f"{', '.join(GROUPS)}")
    if jobs is None:
        jobs = min(len(CHAINS), available_cores())
    if jobs < 1:
        raise OptionError(f"--jobs: must be at least 1, got {jobs}")
    chains = [tuple(g for g in chain if g in groups) for chain in CHAINS]
    chains = [c for c in chains if c]
    if jobs == 1:
        chains = [tuple(g for c in chains for g in c)]
    seconds: dict[str, float] = {}
    failures = []
    # spawn: each chain compiles in a fresh interpreter (numba's state is not fork-safe)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(jobs, len(chains)), mp_context=ctx) as pool:
        for done, failure in pool.map(_run_chain, chains):
            seconds.update(done)
            if failure:
                failures.append(failure)
    status = "ok" if not failures else "failed: " + "; ".join(failures)
    return WarmupResult(status, seconds, os.environ.get("NUMBA_CACHE_DIR"))
