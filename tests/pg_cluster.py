"""A throwaway PostgreSQL cluster for tests: Debian's ``initdb`` and ``pg_ctl`` on a temporary
folder, listening on a free loopback port (as the unprivileged user ``nobody`` when the tests run
as root: ``initdb`` refuses root). No PostgreSQL installed is a failure, never a skip."""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from test_api_server import _free_port


def _bin(name: str) -> str:
    found = shutil.which(name) or next(iter(sorted(glob.glob(
        f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)), None)
    if found is None:
        raise AssertionError(f"PostgreSQL's {name} is missing: install Debian's postgresql package "
                             "(.ci/run does)")
    return found


class PgCluster:
    """``initdb`` + ``pg_ctl start`` in a fresh folder; :attr:`url` of its ``postgres`` database
    (trust authentication, loopback only); :meth:`stop` ends it and removes the folder."""

    def __init__(self) -> None:
        self.folder = Path(tempfile.mkdtemp(prefix="oga-pg-"))
        self.port = _free_port()
        self.user = "nobody" if os.geteuid() == 0 else None
        data = self.folder / "data"
        if self.user:
            os.chmod(self.folder, 0o755)
            shutil.chown(self.folder, self.user)
        self.data = data
        self._run(_bin("initdb"), "-D", str(data), "-A", "trust", "-U", "oga", "--no-sync",
                  "-E", "UTF8")
        self._run(_bin("pg_ctl"), "-D", str(data), "-l", str(self.folder / "log"), "-w",
                  "-t", "60", "-o", f"-h 127.0.0.1 -p {self.port} -k {self.folder} -F "
                  "-c max_connections=200", "start")
        self.url = f"postgresql://oga@127.0.0.1:{self.port}/postgres"

    def _run(self, *cmd: str) -> None:
        if self.user:
            cmd = ("runuser", "-u", self.user, "--", *cmd)
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=self.folder, timeout=120)
        if done.returncode:
            raise AssertionError(f"{' '.join(cmd)} failed: {done.stdout}{done.stderr}")

    def stop(self) -> None:
        try:
            self._run(_bin("pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.folder, ignore_errors=True)
