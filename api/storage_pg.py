"""The job store in PostgreSQL: several servers, on several hosts, share one queue.

The queries are :class:`api.storage.Store`'s; this backend gives the
connection (psycopg 3, autocommit outside explicit transactions), the schema's
spellings, and the claim's ``FOR UPDATE SKIP LOCKED``: two servers claiming at
once take two different jobs, neither waits for the other. The lease and
fencing rules (attempt number, heartbeat, requeue) are the SQLite store's.
"""

from __future__ import annotations

from contextlib import contextmanager

import psycopg
from psycopg.rows import dict_row

from api.storage import SCHEMA, Store
from oga.defaults import PG_CONNECT_S

__all__ = ["PgStore"]

#: Key of the advisory lock that serialises the schema's creation by servers starting at once.
_SCHEMA_LOCK = 0x6F6761  # "oga"


class _Connection:
    """A psycopg connection taking the store's ``?`` parameters (the store's SQL has no
    literal ``?`` nor ``%``)."""

    def __init__(self, conn: psycopg.Connection) -> None:
        self.conn = conn

    def execute(self, sql: str, args=()):
        return self.conn.execute(sql.replace("?", "%s"), args)

    def close(self) -> None:
        self.conn.close()


class PgStore(Store):
    """The jobs in a PostgreSQL database.

    Parameters
    ----------
    url : str
        ``postgresql://user:password@host:port/dbname`` (libpq's URL form).
    """

    _SEQ = "seq"
    _CLAIM_LOCK = " FOR UPDATE SKIP LOCKED"
    errors = (psycopg.Error,)

    def __init__(self, url: str) -> None:
        super().__init__()
        self.url = url
        schema = SCHEMA.format(seq="\n    seq BIGSERIAL NOT NULL,", real="DOUBLE PRECISION",
                               blob="BYTEA")
        with self._tx() as db:
            db.execute(f"SELECT pg_advisory_xact_lock({_SCHEMA_LOCK})")
            for statement in filter(str.strip, schema.split(";")):
                db.execute(statement)

    def _connect(self) -> _Connection:
        return _Connection(psycopg.connect(self.url, autocommit=True, row_factory=dict_row,
                                           connect_timeout=int(PG_CONNECT_S)))

    def _is_open(self, db: _Connection) -> bool:
        return not (db.conn.closed or db.conn.broken)

    @contextmanager
    def _tx(self):
        """One transaction (READ COMMITTED); rolled back on any exception."""
        db = self._db()
        with db.conn.transaction():
            yield db
