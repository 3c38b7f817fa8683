"""The words of one G-code line, as LinuxCNC reads them.

A line is: an optional ``/`` (block delete: LinuxCNC's switch is off, the block runs), an
optional ``N`` word, then words (a letter and a number: blanks and TABs anywhere inside,
leading and trailing dots, any letter case), ``( )`` comments anywhere (they do not nest: the
first ``)`` ends one) and ``;`` to the end of the line. Numbers have no exponent.

What the built-in reader does not read (``#`` parameters, ``[ ]`` expressions, O-words other
than a program number, ``@``/``^`` polar words) raises :class:`~oga.errors.GcodeError` with
``unsupported=True``: LinuxCNC's interpreter (``--reader linuxcnc``) reads them.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from oga.errors import GcodeError

__all__ = ["Word", "words", "unsupported"]

_TOKEN = re.compile(
    r"[ \t]*(?:(?P<comment>\((?:[^()]|\([^()]*\))*\))"
    r"|(?P<rest>;.*)"
    r"|(?P<letter>[A-Za-z])(?P<number>[-+0-9. \t]*)"
    r"|(?P<end>$)"
    r"|(?P<bad>.))"
)
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
#: A line of plain words only (no comment, blank inside a number, N, O or E word, and at most
#: 30 digits each side of the point: finite): read at once, as the tokens below read it.
_PLAIN = re.compile(r"(?:[ \t]*[A-DF-MP-Za-df-mp-z][-+]?(?:\d{1,30}\.?\d{0,30}|\.\d{1,30}))*[ \t]*")
_PLAIN_WORD = re.compile(r"([A-Za-z])([-+.0-9]+)")
_PROGRAM_NUMBER = re.compile(r"[ \t]*[Oo][ \t]*\d[\d \t]*(?:\([^)]*\)[ \t]*)*(?:;.*)?")
_UNSUPPORTED_CHAR = {
    "#": "# parameters",
    "[": "[ ] expressions",
    "@": "polar coordinates (@)",
    "^": "polar coordinates (^)",
}
_BAD_CHAR = {
    "(": "comment is not closed: ')' is missing (or nested more than one level)",
    "/": "block delete '/' is only allowed first on a line",
    ")": "')' without a '(' (comments do not nest)",
}


def unsupported(message: str, line: int, column: int, source: str) -> GcodeError:
    """A GcodeError for a construct LinuxCNC's interpreter reads and the built-in reader does
    not (``err.unsupported`` is True: ``--reader auto`` passes the program on)."""
    err = GcodeError(f"{message} (not in the built-in reader; --reader linuxcnc reads it)",
                     line, column, source)
    err.unsupported = True
    return err


@dataclass(frozen=True)
class Word:
    """One word: upper-case letter, value, 1-based column of the letter."""

    letter: str
    value: float
    column: int


def words(text: str, line: int, source: str, notes: list[str] | None = None) -> list[Word]:
    """The words of one program line (comments, block delete and the N word dropped).

    A line holding only an O program number (``O1234``, Fanuc style) has no words. A comment
    nested one level (``(drill (R))``, Estlcam's tool names) is read as one comment, and
    ``"nested comment"`` appended to ``notes`` (LinuxCNC refuses it).

    Raises
    ------
    GcodeError
        A character or number that does not parse (``unsupported`` set for what LinuxCNC
        reads: parameters, expressions, O-words, polar words).
    """
    if _PLAIN.fullmatch(text):
        return [Word(m[1].upper(), float(m[2]), m.start() + 1) for m in _PLAIN_WORD.finditer(text)]
    if _PROGRAM_NUMBER.fullmatch(text):
        return []
    start = len(text) - len(text.lstrip(" \t"))
    if text[start:start + 1] == "/":
        text = " " * (start + 1) + text[start + 1:]
    raw = []
    for m in _TOKEN.finditer(text):
        letter, number, bad = m.group("letter", "number", "bad")
        if letter is not None:
            column = m.start("letter") + 1
            if letter in "Oo":
                raise unsupported("O-words (subroutines, loops, conditions)", line, column, source)
            raw.append((letter.upper(), number, column))
        elif bad is not None:
            column = m.start("bad") + 1
            if bad in _UNSUPPORTED_CHAR:
                raise unsupported(_UNSUPPORTED_CHAR[bad], line, column, source)
            raise GcodeError(_BAD_CHAR.get(bad, f"unexpected character {bad!r}"), line, column,
                             source)
        elif m.group("rest") is not None or m.group("end") is not None:
            break
        elif notes is not None and "(" in m.group("comment")[1:]:
            notes.append("nested comment")
    out = []
    for k, (letter, number, column) in enumerate(raw):
        digits = number.replace(" ", "").replace("\t", "")
        if not _NUMBER.fullmatch(digits):
            what = f"number {digits!r} does not parse" if digits else "has no number"
            raise GcodeError(f"{letter} word: {what}", line, column, source)
        after = raw[k + 1] if k + 1 < len(raw) else None
        if after and after[0] == "E" and number and after[2] == column + 1 + len(number):
            raise GcodeError(f"{letter} word: {digits}E{after[1].strip()} has an exponent, which "
                             "G-code numbers do not have (coordinate out of range? write plain "
                             "digits)", line, column, source)
        value = float(digits)
        if not math.isfinite(value):
            raise GcodeError(f"{letter} word: number out of range ({len(digits)} digits)",
                             line, column, source)
        if letter == "N":
            if k != 0:
                raise GcodeError("N word (line number) is only allowed first on a line",
                                 line, column, source)
            continue
        out.append(Word(letter, value, column))
    return out
