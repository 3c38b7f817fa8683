"""Writing HAL configuration: ``halcmd`` commands as a ``.hal`` file or a Tcl HALFILE.

LinuxCNC runs a ``[HAL] HALFILE`` ending in ``.tcl`` with ``haltcl``, where every
``halcmd`` command is the Tcl command ``hal <command>`` and LinuxCNC's
``hal_procs_lib.tcl`` can ask what a pin is connected to and where a function runs. The
exports write their commands once, through :class:`HalCommands`.
"""

from __future__ import annotations

__all__ = ["HalCommands", "printable", "hal_number"]


def printable(text: str) -> str:
    """``text`` for a comment line: printable ASCII kept, anything else (a newline would end
    the comment and start a command) as ``?``."""
    return "".join(c if " " <= c <= "~" else "?" for c in text)


def hal_number(x: float) -> str:
    """A float as HAL reads it back exactly (``repr``: the shortest round-trip form)."""
    return repr(float(x))


class HalCommands:
    """An ordered list of ``halcmd`` commands and comment lines.

    Methods add one command each; :meth:`hal` renders a ``.hal`` file, :meth:`tcl` the
    lines of a Tcl HALFILE (each command as ``hal ...``; ``raw`` lines are Tcl as given).
    """

    def __init__(self) -> None:
        self._lines: list[tuple[str, str]] = []

    def comment(self, *lines: str) -> None:
        self._lines += [("#", printable(line)) for line in lines]

    def blank(self) -> None:
        self._lines.append(("#", None))

    def cmd(self, *words) -> None:
        self._lines.append(("cmd", " ".join(str(w) for w in words)))

    def raw(self, tcl: str) -> None:
        """A line of Tcl (Tcl HALFILE only)."""
        self._lines.append(("tcl", tcl))

    def loadrt(self, comp: str, **args) -> None:
        self.cmd("loadrt", comp, *(f"{k}={v}" for k, v in args.items()))

    def setp(self, pin: str, value) -> None:
        self.cmd("setp", pin, hal_number(value) if isinstance(value, float) else value)

    def net(self, signal: str, *pins: str) -> None:
        self.cmd("net", signal, *pins)

    def hal(self) -> str:
        out = []
        for kind, text in self._lines:
            if kind == "tcl":
                raise ValueError("a .hal file cannot hold Tcl lines")
            out.append("" if text is None else (f"# {text}" if kind == "#" else text))
        return "\n".join(out) + "\n"

    def tcl(self) -> str:
        out = []
        for kind, text in self._lines:
            if text is None:
                out.append("")
            elif kind == "#":
                out.append(f"# {text}")
            elif kind == "cmd":
                out.append(f"hal {text}")
            else:
                out.append(text)
        return "\n".join(out) + "\n"
