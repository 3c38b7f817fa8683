"""The job store in PostgreSQL: several servers, on several hosts, share one queue.

The queries are :class:`api.store.Store`'s; this backend gives the
connections (psycopg 3, autocommit outside explicit transactions), the schema's
spellings, and the claim's ``FOR UPDATE SKIP LOCKED``: two servers claiming at
once take two different jobs, neither waits for the other. The lease and
fencing rules (attempt number, heartbeat, requeue) are the SQLite store's.

Connections come from a pool (psycopg_pool) of at most :data:`~oga.defaults.PG_POOL_MAX`
per process, lent for one statement or one transaction: a server's request
threads share a few connections instead of holding one each, and a broken
connection is replaced by the pool.
"""

from __future__ import annotations

from contextlib import contextmanager

import psycopg
from psycopg.rows import dict_row
from psycopg_pool import ConnectionPool

from api.store import SCHEMA, Store
from oga.defaults import PG_CONNECT_S, PG_POOL_MAX

__all__ = ["PgStore"]

#: Key of the advisory lock that serialises the schema's creation by servers starting at once.
_SCHEMA_LOCK = 0x6F6761  # "oga"


def _sql(sql: str) -> str:
    """The store's ``?`` parameters in psycopg's spelling (the store's SQL has no literal ``?``
    nor ``%``)."""
    return sql.replace("?", "%s")


class _Connection:
    """A connection held for one transaction, taking the store's ``?`` parameters."""

    def __init__(self, conn: psycopg.Connection) -> None:
        self.conn = conn

    def execute(self, sql: str, args=()):
        return self.conn.execute(_sql(sql), args)


class _Rows:
    """The fetched rows and row count of one statement (its connection is back in the pool)."""

    def __init__(self, rows: list, rowcount: int) -> None:
        self.rows, self.rowcount = rows, rowcount

    def fetchone(self):
        return self.rows[0] if self.rows else None

    def fetchall(self) -> list:
        return self.rows


class _Pooled:
    """The store's reads outside a transaction: each statement borrows a pooled connection."""

    def __init__(self, pool: ConnectionPool) -> None:
        self.pool = pool

    def execute(self, sql: str, args=()) -> _Rows:
        with self.pool.connection() as conn:
            cur = conn.execute(_sql(sql), args)
            return _Rows(cur.fetchall() if cur.description else [], cur.rowcount)


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
        self.url = url
        schema = SCHEMA.format(seq="\n    seq BIGSERIAL NOT NULL,", real="DOUBLE PRECISION",
                               blob="BYTEA")
        kwargs = {"autocommit": True, "row_factory": dict_row,
                  "connect_timeout": int(PG_CONNECT_S)}
        # one connection of its own first: an unusable URL fails here, with libpq's reason
        with psycopg.connect(url, **kwargs) as conn, conn.transaction():
            conn.execute(f"SELECT pg_advisory_xact_lock({_SCHEMA_LOCK})")
            for statement in filter(str.strip, schema.split(";")):
                conn.execute(statement)
        self.pool = ConnectionPool(url, kwargs=kwargs, min_size=1, max_size=PG_POOL_MAX,
                                   timeout=PG_CONNECT_S, name="oga", open=True)
        self._reads = _Pooled(self.pool)

    def _db(self) -> _Pooled:
        return self._reads

    @contextmanager
    def _tx(self):
        """One transaction (READ COMMITTED) on one pooled connection; rolled back on any
        exception."""
        with self.pool.connection() as conn, conn.transaction():
            yield _Connection(conn)

    def close(self) -> None:
        """Close the pool's connections."""
        self.pool.close()
