"""Contour-error kernel speed: samples per second on a 100 000-sample circle.

Run: python bench/bench_contour.py   (prints figures; no assertion)
"""

from __future__ import annotations

import time

import numpy as np

from oga.model.contour import contour_error
from oga.defaults import CE_WINDOW_SAMPLES

N = 100_000
TARGET_S = 1.0  # "100 000 samples in well under a second"


def main() -> None:
    th = np.linspace(0.0, 2 * np.pi * 5, N)  # five turns of R 50 mm: comes back on itself
    r = 0.05
    pd = np.column_stack([r * np.cos(th), r * np.sin(th), np.zeros(N)])
    lag = 40
    k = np.maximum(np.arange(N) - lag, 0)
    pa = np.column_stack([(r + 5e-6) * np.cos(th[k]), (r + 5e-6) * np.sin(th[k]), np.zeros(N)])
    t0 = time.perf_counter()
    contour_error(pd[:100], pa[:100], "xy")  # compile or load the cache
    t_first = time.perf_counter() - t0
    for window in (50, CE_WINDOW_SAMPLES, 300):
        best = np.inf
        for _ in range(5):
            t0 = time.perf_counter()
            contour_error(pd, pa, "xy", window=window)
            best = min(best, time.perf_counter() - t0)
        print(
            f"contour_error N={N} window=+-{window:3d}: {best * 1e3:7.1f} ms, "
            f"{N / best / 1e6:6.2f} M samples/s, {best / TARGET_S:.3f} of the 1 s target"
        )
    print(f"first call (compile or cache load): {t_first:.2f} s")


if __name__ == "__main__":
    main()
