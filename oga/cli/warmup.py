"""``oga warmup``: compile every kernel now, so the first job runs at full speed."""

from __future__ import annotations

import argparse

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    from oga.warmup import GROUPS

    p = sub.add_parser(
        "warmup", help="compile every kernel ahead of the first job",
        description="Run one small job of each kind (plan, nominal, robust, law, paper, "
                    "compare, identify) so that numba compiles and caches every kernel; a "
                    "service image or cluster worker warmed at build time answers its first "
                    "job at full speed.")
    p.add_argument("--jobs", type=int, metavar="N",
                   help="processes compiling at once (default: 2, or 1 on one core)")
    p.add_argument("--only", metavar="G,...",
                   help=f"groups to compile (default all: {','.join(GROUPS)})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from oga.warmup import GROUPS, warmup

    groups = GROUPS if args.only is None else tuple(
        g.strip() for g in args.only.split(",") if g.strip())
    result = warmup(groups, jobs=args.jobs)  # OptionError (exit 2) names the option
    for name, s in result.seconds.items():
        print(f"{name:9s} {s:6.1f} s")
    print(f"kernels cached in {result.cache_dir or 'numba default cache'}")
    if result.status != "ok":
        print(f"oga warmup: {result.status}")
        return 1
    return 0
