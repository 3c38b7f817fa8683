"""A Dask cluster for tests: ``dask scheduler`` and ``dask worker`` processes on loopback (one
thread each, no nanny: a killed worker stays dead)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from test_api_server import _free_port

#: The ``dask`` command of this interpreter's environment.
DASK = str(Path(sys.executable).parent / "dask")


class DaskCluster:
    """A scheduler on a free loopback port and ``workers`` workers; :attr:`address` is
    ``tcp://127.0.0.1:PORT``; logs in ``folder``."""

    def __init__(self, folder: Path, workers: int) -> None:
        self.folder = folder
        self.address = f"tcp://127.0.0.1:{_free_port()}"
        self.scheduler = self._start("scheduler", "scheduler", "--host", "127.0.0.1", "--port",
                                     self.address.rsplit(":", 1)[1], "--no-dashboard")
        self.workers = [self._start(f"worker{k}", "worker", self.address, "--nthreads", "1",
                                    "--no-nanny", "--no-dashboard", "--host", "127.0.0.1",
                                    "--name", f"w{k}")
                        for k in range(workers)]
        self.wait_for_workers(workers)

    def _start(self, log: str, *args: str) -> subprocess.Popen:
        with open(self.folder / f"{log}.log", "ab") as f:
            return subprocess.Popen([DASK, *args], stdout=f, stderr=subprocess.STDOUT,
                                    env=os.environ | {"DASK_DISTRIBUTED__WORKER__DAEMON":
                                                      "False"})

    def wait_for_workers(self, n: int, timeout_s: float = 120) -> None:
        from distributed import Client

        with Client(self.address, timeout=60, set_as_default=False) as client:
            client.wait_for_workers(n, timeout=timeout_s)

    def kill_worker(self, k: int) -> None:
        self.workers[k].send_signal(signal.SIGKILL)
        self.workers[k].wait()

    def stop(self) -> None:
        """Kill the workers (a graceful close takes seconds), then end the scheduler."""
        for p in self.workers:
            p.kill()
            p.wait()
        self.scheduler.terminate()
        try:
            self.scheduler.wait(10)
        except subprocess.TimeoutExpired:
            self.scheduler.kill()
            self.scheduler.wait()
