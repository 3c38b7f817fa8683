"""SIGINT and SIGTERM in ``oga batch``: the signals that stop it, held back while a
program's outputs are written (so they are all there or all absent)."""

from __future__ import annotations

import signal
from contextlib import contextmanager

__all__ = ["STOP_SIGNALS", "signals_deferred"]

#: Signals that stop a batch: the workers are killed, finished outputs kept.
STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


@contextmanager
def signals_deferred():
    """SIGINT and SIGTERM held back (delivered at the end of the block)."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
