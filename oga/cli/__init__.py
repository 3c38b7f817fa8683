"""The ``oga`` command line: one sub-command per module of this package.

Every sub-command module defines ``register(subparsers)``, which adds its
parser and sets ``func`` to a function ``run(args) -> int``. Errors a user can
cause (:class:`oga.errors.InputError`) end with exit code 2 and one line on
stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

from oga import __version__
from oga.errors import InputError, OgaError

__all__ = ["main"]

#: Sub-commands, each a module ``oga.cli.<name>``.
COMMANDS: tuple[str, ...] = ("plan", "ranges", "optimize", "compare", "batch", "serve",
                             "export", "excite", "identify", "lcnc_record", "law", "warmup")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (exit code 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered."""
    parser = _Parser(
        prog="oga", description="Offline gain-schedule optimizer for CNC machine tools."
    )
    parser.add_argument("--version", action="version", version=f"oga {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"oga.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failure, 2 bad input, 128 + N on signal N)."""
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
    except BrokenPipeError:  # stdout closed early (`oga batch ... | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except MemoryError:
        print(f"oga {args.command}: failed: out of memory", file=sys.stderr)
        return 1
    except Exception as err:  # a bug: one line (python -X dev oga ... shows the traceback)
        if sys.flags.dev_mode:
            raise
        print(f"oga {args.command}: internal error: {type(err).__name__}: {err} (a bug: "
              "please report it with the input; python -X dev -m oga ... shows where)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
