"""Opening the job store: the backend chosen from the ``--db`` value (the edge).

``postgresql://`` or ``postgres://`` URLs open :class:`api.storage_pg.PgStore`
(several servers on several hosts share one queue); a path without a scheme opens
:class:`api.storage_sqlite.SqliteStore` (one file, one host; the default); any
other ``scheme://`` is refused. Both backends implement :class:`api.store.Store`
(the queries, the claim and its fencing), whose names are re-exported here.
"""

from __future__ import annotations

import importlib
import os
import re

from api.storage_sqlite import SqliteStore, default_db_path
from api.store import (
    FINISHED,
    STATUSES,
    TRACE_PREFIX,
    JobRow,
    Owner,
    Store,
    StoreError,
    is_identification,
)

__all__ = ["STATUSES", "FINISHED", "TRACE_PREFIX", "Owner", "JobRow", "Store", "SqliteStore",
           "open_store", "store_class", "is_identification", "without_password",
           "default_db_path", "StoreError"]

#: The backends of a URL scheme: module and class (imported when used: psycopg is only
#: needed for PostgreSQL).
BACKENDS = {"postgresql": ("api.storage_pg", "PgStore"),
            "postgres": ("api.storage_pg", "PgStore")}

_SCHEME = re.compile(r"([A-Za-z][A-Za-z0-9+.-]*)://")


def without_password(db: str | os.PathLike) -> str:
    """``db`` as it may be printed: a URL's password replaced by ``***``."""
    text = re.sub(r"(://[^:/@]*):[^@]*@", r"\1:***@", str(db))
    return re.sub(r"(?i)(password=)[^&\s]*", r"\1***", text)  # libpq's ?password=...


def store_class(db: str | os.PathLike) -> type[Store]:
    """The backend of ``db``: by its URL scheme, SQLite for a path without one.

    Raises
    ------
    StoreError
        For a scheme no backend serves.
    """
    match = _SCHEME.match(str(db))
    if match is None:
        return SqliteStore
    backend = BACKENDS.get(match.group(1).lower())
    if backend is None:
        raise StoreError(f"{without_password(db)}: unknown database scheme "
                         f"{match.group(1)!r}: expected an SQLite file's path or a "
                         "postgresql:// URL")
    module, name = backend
    return getattr(importlib.import_module(module), name)


def open_store(db: str | os.PathLike) -> Store:
    """The store at ``db``: a PostgreSQL URL, else an SQLite file.

    Raises
    ------
    StoreError
        When it cannot be opened or created, or its scheme is unknown (the URL's password
        is never in the message).
    """
    kind = store_class(db)
    try:
        return kind(db)
    except kind.errors as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise StoreError(f"{without_password(db)}: cannot open the database: {reason}") from None
