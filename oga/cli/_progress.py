"""A minimal terminal progress bar (stderr, only when it is a terminal)."""

from __future__ import annotations

import sys
import time

__all__ = ["ProgressBar"]


class ProgressBar:
    """Context manager; ``update(fraction)`` redraws one line on stderr when enabled."""

    def __init__(self, label: str, *, enabled: bool, width: int = 30) -> None:
        self.label = label
        self.enabled = enabled
        self.width = width
        self._t0 = time.perf_counter()

    def update(self, fraction: float) -> None:
        if not self.enabled:
            return
        fraction = min(max(fraction, 0.0), 1.0)
        n = int(round(fraction * self.width))
        el = time.perf_counter() - self._t0
        sys.stderr.write(f"\r{self.label} [{'#' * n}{'.' * (self.width - n)}] "
                         f"{fraction * 100:5.1f}% {el:6.1f} s")
        sys.stderr.flush()

    def clear(self) -> None:
        """Erase the bar's line (before a line is printed; the next update redraws it)."""
        if self.enabled:
            sys.stderr.write("\r\033[K")
            sys.stderr.flush()

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()
