"""The ``oga`` command line: one sub-command per module of this package.

Every sub-command module defines ``register(subparsers)``, which adds its
parser and sets ``func`` to a function ``run(args) -> int``. Errors a user can
cause (:class:`oga.errors.InputError`) end with exit code 2 and one line on
stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from oga import __version__
from oga.errors import InputError, OgaError

__all__ = ["main"]

#: Sub-commands, each a module ``oga.cli.<name>``.
COMMANDS: tuple[str, ...] = ("plan", "ranges", "optimize", "compare", "batch", "serve",
                             "excite", "identify")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered."""
    parser = argparse.ArgumentParser(
        prog="oga", description="Offline gain-schedule optimizer for CNC machine tools."
    )
    parser.add_argument("--version", action="version", version=f"oga {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"oga.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failure, 2 bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as err:
        print(f"oga {args.command}: error: {err}", file=sys.stderr)
        return 2
    except OgaError as err:
        print(f"oga {args.command}: failed: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"oga {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
