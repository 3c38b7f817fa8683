"""Threads for independent work: the same results, in the same order, on any number of them.

The robust search replays one gain table on many plants, computes every plant's stable
range, and tries baseline candidates: each item is independent of the others, and most of
its time is spent in compiled kernels that release the GIL (``nogil``). :func:`thread_map`
runs such items on a pool of threads and returns their results in the items' order, so a
caller that combines them in that order gets the same bits whatever the thread count.

The default count (:func:`available_cores`) is the cores this process may run on; the
service and the Dask workers pass 1 per job unless told otherwise (they run jobs side by
side).

The window search's simulations run in numba ``prange`` loops (:func:`kernel_threads`), also
from several of these threads at once: numba's default ``workqueue`` layer is not safe for
that (it aborts), so this module, imported before any parallel kernel runs, selects the
``threadsafe`` layer (OpenMP, ``libgomp.so.1``: Debian's ``libgomp1``; or TBB) unless
``NUMBA_THREADING_LAYER`` names one; without either, :func:`kernel_threads` raises
:class:`ThreadingLayerError` saying what to install.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import numba

from oga.errors import OgaError, OptionError

__all__ = ["available_cores", "resolve_threads", "thread_map", "kernel_threads",
           "ThreadingLayerError"]

#: Numba's layers that are safe to enter from several threads at once.
SAFE_LAYERS = ("threadsafe", "omp", "tbb", "safe")
os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")  # kept by numba's config reloads
numba.config.THREADING_LAYER = os.environ["NUMBA_THREADING_LAYER"]
# OpenMP's idle threads sleep instead of spinning (read when numba loads the layer): the
# window search enters thousands of short parallel loops, and spinning threads on a busy
# host took the cores from the work (short_xz, 2 plants, load 6.7 on 2 cores: 3.6 s on 2
# threads spinning, 0.38 s sleeping, 0.46-0.59 s on 1)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


class ThreadingLayerError(OgaError, RuntimeError):
    """Numba has no thread-safe threading layer (OpenMP or TBB) on this machine."""

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


@contextmanager
def kernel_threads(threads: int) -> Iterator[None]:
    """Run the compiled kernels' parallel loops (numba ``prange``) of the calling thread on
    ``threads`` threads (at most numba's pool, ``NUMBA_NUM_THREADS``) inside the block; the
    count before is restored after it. Numba keeps the count per calling thread, so jobs on
    other threads are not affected."""
    if numba.config.THREADING_LAYER not in SAFE_LAYERS:
        raise ThreadingLayerError(
            f"NUMBA_THREADING_LAYER={numba.config.THREADING_LAYER!r} is not safe from several "
            f"threads at once: use one of {', '.join(SAFE_LAYERS)} (or leave it unset)")
    try:
        before = numba.get_num_threads()  # loads the layer on first use
    except ValueError as e:  # numba: "No threading layer could be loaded"
        raise ThreadingLayerError(
            "numba found no thread-safe threading layer: install OpenMP's runtime (Debian, "
            "Ubuntu: apt-get install libgomp1) or TBB (pip install tbb)") from e
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)
