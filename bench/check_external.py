"""Try the toolpath readers on a folder of real programs (a check script, not a test).

Usage: python bench/check_external.py [FOLDER]

FOLDER defaults to ../shared/toolpaths/external relative to the repository root.
Prints, per toolpath file, either the parsed counts (feed lines, arcs, rapids,
length in mm, parse time, warnings) or the refusal with its line:column.
Exit code 1 if a file fails any other way (a reader bug).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path as FilePath

from feedplan.path import Arc
from feedplan.read import SUFFIXES, load_toolpath
from oga.errors import InputError

DEFAULT = FilePath(__file__).resolve().parents[1].parent / "shared" / "toolpaths" / "external"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", default=str(DEFAULT))
    folder = FilePath(ap.parse_args(argv).folder)
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in SUFFIXES)
    if not files:
        print(f"no toolpath files in {folder}")
        return 1
    bugs = 0
    for f in files:
        t0 = time.perf_counter()
        try:
            path = load_toolpath(f)
        except InputError as err:
            print(f"{f.name:32s} REFUSED  {err}")
            continue
        except Exception as err:  # noqa: BLE001 - report a reader bug, keep going
            print(f"{f.name:32s} BUG      {type(err).__name__}: {err}")
            bugs += 1
            continue
        ms = (time.perf_counter() - t0) * 1e3
        arcs = sum(isinstance(s, Arc) for s in path.segments)
        rapids = sum(s.rapid for s in path.segments)
        lines = len(path.segments) - arcs - rapids
        print(f"{f.name:32s} OK       lines {lines:5d}  arcs {arcs:4d}  rapids {rapids:3d}  "
              f"length {path.length * 1e3:9.1f} mm (feed {path.feed_length * 1e3:9.1f})  "
              f"plane {path.plane}  {ms:6.1f} ms  warnings {len(path.warnings)}")
        for w in path.warnings:
            print(f"{'':41s}warning: {w}")
    return 1 if bugs else 0


if __name__ == "__main__":
    sys.exit(main())
