"""Threads for independent work: the same results, in the same order, on any number of them.

The robust search replays one gain table on many plants, computes every plant's stable
range, and tries baseline candidates: each item is independent of the others, and most of
its time is spent in compiled kernels that release the GIL (``nogil``). :func:`thread_map`
runs such items on a pool of threads and returns their results in the items' order, so a
caller that combines them in that order gets the same bits whatever the thread count.

The default count (:func:`available_cores`) is the cores this process may run on; the
service and the Dask workers pass 1 per job unless told otherwise (they run jobs side by
side).

The window search runs on one thread (its windows follow each other, and each window's work
is too small for parallel loops: :func:`oga.search.window._each_run`); a job's threads are
its independent items'.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from oga.errors import OptionError

__all__ = ["available_cores", "resolve_threads", "thread_map"]

T = TypeVar("T")
R = TypeVar("R")

#: Most threads accepted (far above any workstation's cores; a typo such as 10000 is refused).
MAX_THREADS = 256


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def resolve_threads(threads: int | None, where: str = "threads") -> int:
    """``threads``, or :func:`available_cores` when None.

    Raises
    ------
    OptionError
        Not an integer in ``1 .. MAX_THREADS`` (named by ``where``).
    """
    if threads is None:
        return available_cores()
    if isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= MAX_THREADS:
        raise OptionError(f"{where}: need a whole number of threads in 1..{MAX_THREADS}, "
                          f"got {threads!r}")
    return threads


def thread_map(fn: Callable[[T], R], items: Iterable[T], threads: int = 1,
               done: Callable[[int], None] | None = None) -> list[R]:
    """``[fn(x) for x in items]``, on ``threads`` threads (results in the items' order).

    The first exception raised by ``fn`` (in the items' order) is raised here, after every
    item has ended. ``done``, when given, is called in the calling thread with the count of
    results collected, after each one in the items' order (a progress report that needs no
    barrier between batches of items).
    """
    items = list(items)
    out: list[R] = []
    if threads <= 1 or len(items) <= 1:
        for x in items:
            out.append(fn(x))
            if done is not None:
                done(len(out))
        return out
    with ThreadPoolExecutor(max_workers=min(threads, len(items))) as pool:
        futures = [pool.submit(fn, x) for x in items]
        for f in futures:
            out.append(f.result())
            if done is not None:
                done(len(out))
        return out
