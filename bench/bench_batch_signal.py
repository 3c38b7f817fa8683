"""How fast ``oga batch`` stops on SIGINT and SIGTERM (a benchmark, not a test).

Run: ``python bench/bench_batch_signal.py`` from the repository root. For each signal,
``oga batch --jobs 2`` starts on two programs that take tens of seconds each; 3 s after
both workers run, the signal goes to the whole process group (SIGINT: Ctrl-C, or
``timeout -s INT``) or to the batch process alone (SIGTERM: ``kill PID``). Prints the
exit code, the time from the signal to the batch's exit and to the end of its last
child process (issue 18's target: within 2 s, children included), and what remains in
the output folder.
"""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_batch import _running, _start_batch, _started, _zigzag  # noqa: E402


def stop_once(sig: signal.Signals, to_group: bool) -> tuple[int, float, float, list[str]]:
    """(exit code, s to exit, s until no child runs, files left) of one stopped batch."""
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp, "in"), Path(tmp, "out")
        src.mkdir()
        (src / "a.ngc").write_text(_zigzag(400))
        (src / "b.ngc").write_text(_zigzag(401))
        proc = _start_batch(src, out, "--jobs", "2")
        _started(proc)
        time.sleep(3.0)
        children = _started(proc)
        t0 = time.perf_counter()
        if to_group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        code = proc.wait()
        t_exit = time.perf_counter() - t0
        while any(_running(p) for p in children):
            time.sleep(0.005)
        t_children = time.perf_counter() - t0
        return code, t_exit, t_children, sorted(p.name for p in out.iterdir())


def main() -> None:
    print(f"{'signal':<8} {'sent to':<14} {'exit':>4} {'exit s':>7} {'children s':>10}  files left")
    for sig, to_group in ((signal.SIGINT, True), (signal.SIGTERM, False), (signal.SIGTERM, True)):
        code, t_exit, t_children, files = stop_once(sig, to_group)
        where = "process group" if to_group else "batch only"
        print(f"{sig.name:<8} {where:<14} {code:>4} {t_exit:>7.3f} {t_children:>10.3f}  "
              f"{files or 'none'}")


if __name__ == "__main__":
    main()
