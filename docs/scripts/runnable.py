"""The code blocks of the README and the docs that are marked runnable: run them, compare
their output with the page, or write the output into the page.

A block is runnable when the line before its fence is ``<!-- runnable -->`` (options after a
colon: ``<!-- runnable: exit=2 free="[\\d.]+ s\\b" rtol=0.02 -->``):

- a ``console`` block: each line ``$ COMMAND`` (a trailing ``\\`` continues it on the next
  line) runs in bash; the lines after it, up to the next ``$``, are what it prints (stdout and
  stderr as one stream, as a terminal shows them);
- a ``python`` block runs as a script; a block right after it marked ``<!-- output -->`` is
  what it prints;
- any block with the option ``file=NAME`` (a machine file, say) is written to NAME for the
  blocks after it.

The blocks of one page run in order in one fresh folder holding links to the checkout's
``examples/``, ``tests/data/`` and ``oga/presets/`` (so a tutorial's later block reads an earlier one's files),
with ``oga`` and ``python`` of this interpreter first on the ``PATH``.

Output compares line by line after collapsing runs of blanks (columns realign when a figure
changes width): the text must be equal, and each number within ``rtol`` (default 0.01)
relative or one unit of its last printed digit, whichever is larger. ``free`` is a regular
expression whose matches are not compared (run times). A command must exit 0; ``exit=N``: the
block's last command must exit N.

``python docs/scripts/runnable.py [--update] [FILE.md ...]`` (default: the README and every
page under ``docs/``) runs the blocks and reports the differences; ``--update`` writes what
the commands print into the pages instead (after a change of the search or the planner).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MARK = re.compile(r"^<!-- runnable(?::(?P<opts>.*?))? -->\s*$")
OUTPUT_MARK = "<!-- output -->"
FENCE = re.compile(r"^(?P<fence>```+)(?P<lang>[\w-]*)")
NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
#: Folders of the checkout linked into a page's working folder (the examples read the presets
#: beside them).
LINKED = ("examples", "tests/data", "oga/presets")


@dataclass
class Block:
    """One runnable block of a page: where it is, what runs, what it should print."""

    path: Path
    lang: str
    start: int                 # index of the fence's first line
    end: int                   # index of the closing fence
    options: dict
    commands: list[str] = field(default_factory=list)   # console: commands
    written: list[list[str]] = field(default_factory=list)  # console: each command's lines
    expected: list[list[str]] = field(default_factory=list)  # console: output per command
    code: str = ""             # python: the script
    output: tuple[int, int] | None = None  # python: (start, end) of its output block

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT) if self.path.is_relative_to(ROOT) else self.path}:" \
               f"{self.start + 1}"


def _options(text: str | None) -> dict:
    opts = {"exit": 0, "rtol": 0.01, "free": None, "timeout": 600.0, "file": None}
    for item in shlex.split(text or ""):
        key, _, value = item.partition("=")
        if key not in opts:
            raise ValueError(f"unknown option {key!r} of a runnable block")
        opts[key] = type(opts[key])(value) if opts[key] is not None else value
    return opts


def _fence_end(lines: list[str], start: int) -> int:
    fence = FENCE.match(lines[start]).group("fence")
    for k in range(start + 1, len(lines)):
        if lines[k].strip() == fence:
            return k
    raise ValueError(f"line {start + 1}: code block never closed")


def blocks(path: Path) -> list[Block]:
    """The runnable blocks of a Markdown file, in order."""
    lines = path.read_text().splitlines()
    out = []
    for k, line in enumerate(lines):
        m = MARK.match(line)
        if not m:
            continue
        start = k + 1
        f = FENCE.match(lines[start]) if start < len(lines) else None
        opts = _options(m.group("opts"))
        if f is None or (f.group("lang") not in ("console", "python") and not opts["file"]):
            raise ValueError(f"{path}:{k + 1}: a runnable mark must precede a console or "
                             "python code block, or name the file= its block is")
        end = _fence_end(lines, start)
        b = Block(path, f.group("lang"), start, end, opts)
        body = lines[start + 1:end]
        if opts["file"]:
            b.lang, b.code = "file", "\n".join(body) + "\n"
        elif b.lang == "console":
            cmd = None
            for text in body:
                if cmd is not None and cmd.endswith("\\"):
                    cmd = cmd[:-1] + " " + text.strip()
                    b.commands[-1] = cmd
                    b.written[-1].append(text)
                elif text.startswith("$ "):
                    cmd = text[2:]
                    b.commands.append(cmd)
                    b.written.append([text])
                    b.expected.append([])
                elif b.commands:
                    b.expected[-1].append(text)
                    cmd = None
                else:
                    raise ValueError(f"{b.where}: output before the first command")
        else:
            b.code = "\n".join(body) + "\n"
            nxt = end + 1
            while nxt < len(lines) and not lines[nxt].strip():
                nxt += 1
            if nxt < len(lines) and lines[nxt].strip() == OUTPUT_MARK:
                o_start = nxt + 1
                b.output = (o_start, _fence_end(lines, o_start))
        out.append(b)
    return out


def workdir(tmp: Path) -> Path:
    """A fresh working folder for one page: links to the checkout's example data."""
    for name in LINKED:
        (tmp / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp / name).symlink_to(ROOT / name)
    return tmp


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(
        os.pathsep)
    env.pop("COLUMNS", None)
    return env


def run(block: Block, cwd: Path) -> list[tuple[str, int, list[str]]]:
    """Run a block in ``cwd``: (command or "python", exit code, output lines) per command."""
    env, timeout = _env(), block.options["timeout"]
    if block.lang == "file":
        (cwd / block.options["file"]).write_text(block.code)
        return []
    if block.lang == "python":
        r = subprocess.run([sys.executable, "-c", block.code], cwd=cwd, env=env, text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout)
        return [("python", r.returncode, r.stdout.splitlines())]
    results = []
    for cmd in block.commands:
        r = subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout)
        results.append((cmd, r.returncode, r.stdout.splitlines()))
    return results


def _numbers_close(want: str, got: str, rtol: float) -> bool:
    a, b = float(want), float(got)
    digits = want.split("e")[0].split("E")[0]
    unit = 10.0 ** -(len(digits.split(".")[1]) if "." in digits else 0)
    if "e" in want.lower():
        unit *= 10.0 ** int(re.split("[eE]", want)[1])
    return abs(a - b) <= max(rtol * max(abs(a), abs(b)), unit * 1.000001)


def line_differs(want: str, got: str, rtol: float, free: str | None) -> bool:
    """Whether an output line differs from the page's (module doc: the comparison)."""
    if free:
        want, got = re.sub(free, "<free>", want), re.sub(free, "<free>", got)
    want, got = " ".join(want.split()), " ".join(got.split())
    if NUMBER.sub("#", want) != NUMBER.sub("#", got):
        return True
    return not all(_numbers_close(w, g, rtol)
                   for w, g in zip(NUMBER.findall(want), NUMBER.findall(got)))


def differences(block: Block, results) -> list[str]:
    """What a run printed that the page does not say (empty: the page is right)."""
    out = []
    lines = block.path.read_text().splitlines()
    if block.lang == "python":
        expected = [lines[block.output[0] + 1:block.output[1]]] if block.output else [None]
    else:
        expected = block.expected
    for k, ((cmd, code, got), want) in enumerate(zip(results, expected)):
        exit_code = block.options["exit"] if k == len(results) - 1 else 0
        if code != exit_code:
            out.append(f"{block.where}: `{cmd}` exited {code}, not {exit_code}:\n"
                       + "\n".join(got[-20:]))
            continue
        if want is None:
            continue
        if len(want) != len(got):
            out.append(f"{block.where}: `{cmd}` printed {len(got)} lines, the page shows "
                       f"{len(want)}:\n" + "\n".join(got))
            continue
        for w, g in zip(want, got):
            if line_differs(w, g, block.options["rtol"], block.options["free"]):
                out.append(f"{block.where}: `{cmd}`\n  page: {w}\n  run:  {g}")
    return out


def update(path: Path, results_per_block: list[tuple[Block, list]]) -> None:
    """Write what the blocks printed into the page (the commands stay as they are)."""
    lines = path.read_text().splitlines()
    for block, results in sorted(results_per_block, key=lambda p: -p[0].start):
        if block.lang == "file":
            continue
        if block.lang == "python":
            if block.output:
                s, e = block.output
                lines[s + 1:e] = results[0][2]
            continue
        body = []
        for written, (_, _, got) in zip(block.written, results):
            body += written + got
        lines[block.start + 1:block.end] = body
    path.write_text("\n".join(lines) + "\n")


def pages() -> list[Path]:
    """The README and every Markdown page of the docs."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def check(paths, *, write: bool = False) -> list[str]:
    """Run every runnable block of ``paths``; the differences (or write the outputs)."""
    problems = []
    for path in paths:
        found = blocks(path)
        if not found:
            continue
        done = []
        with tempfile.TemporaryDirectory(prefix="oga-docs-") as tmp:
            cwd = workdir(Path(tmp))
            for b in found:
                results = run(b, cwd)
                done.append((b, results))
                problems += differences(b, results) if not write else [
                    p for p in differences(b, results) if " exited " in p.split("\n")[0]]
        if write:
            update(path, done)
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", type=Path, help="Markdown files (default: all)")
    ap.add_argument("--update", action="store_true", help="write the outputs into the pages")
    args = ap.parse_args(argv)
    problems = check([p.resolve() for p in args.files] or pages(), write=args.update)
    print("\n".join(problems) or "every runnable block prints what its page shows")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
