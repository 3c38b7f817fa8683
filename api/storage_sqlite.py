"""The job store in one SQLite file (WAL): one host, zero setup; the default.

The queries are :class:`api.store.Store`'s; this backend gives one connection per
thread and ``BEGIN IMMEDIATE`` transactions (the one writer).
"""

from __future__ import annotations

import os
import sqlite3
import threading
from contextlib import contextmanager
from pathlib import Path as FilePath

from api.store import SCHEMA, Store

__all__ = ["SqliteStore", "default_db_path"]


def default_db_path() -> FilePath:
    """``$XDG_DATA_HOME/oga/oga.db``, else ``~/.local/share/oga/oga.db``."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return FilePath(base) / "oga" / "oga.db"


class SqliteStore(Store):
    """The jobs in one SQLite file (WAL); one connection per thread.

    Parameters
    ----------
    path : path-like
        SQLite file; created with its folder if missing.
    """

    errors = (OSError, sqlite3.Error)

    def __init__(self, path: str | os.PathLike) -> None:
        self._local = threading.local()
        self.path = FilePath(path)
        self.url = os.path.abspath(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db().executescript(SCHEMA.format(seq="", real="REAL", blob="BLOB"))

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.execute("PRAGMA foreign_keys=ON")
        return db

    def _db(self) -> sqlite3.Connection:
        """This thread's connection (opened on first use)."""
        db = getattr(self._local, "db", None)
        if db is None:
            db = self._local.db = self._connect()
        return db

    @contextmanager
    def _tx(self):
        """BEGIN IMMEDIATE (the one writer), COMMIT, or ROLLBACK on any exception."""
        db = self._db()
        db.execute("BEGIN IMMEDIATE")
        try:
            yield db
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")

    def close(self) -> None:
        """Close this thread's connection."""
        db = getattr(self._local, "db", None)
        if db is not None:
            db.close()
            self._local.db = None
