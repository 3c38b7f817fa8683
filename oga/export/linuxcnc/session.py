"""A headless LinuxCNC session: a configuration started with oga's display, a program run.

The session starts ``linuxcnc`` (the start script: ``milltask``, ``io``, ``halui``, the
realtime ``motmod``, the configuration's HAL files) on a copy of the user's INI file, written
next to it (its relative paths stay valid) with ``[DISPLAY] DISPLAY`` set to oga's display
(:mod:`oga.export.linuxcnc.display`, a script for LinuxCNC's own Python), ``[OGA] JOB`` naming the
job, and oga's HAL files added after the configuration's. Standard input is closed and the
whole session bounded by a timeout.

LinuxCNC runs as an unprivileged user (its realtime part refuses a real root user). Run as
root (a CI container), the session runs it as the owner of the INI file, or ``nobody``, in
private PID, IPC and mount namespaces with a private ``/tmp``: LinuxCNC's lock file, HAL's
shared memory and its start script's clean-up (which ends processes by name) then reach
nothing outside the session, and ending the namespace's first process ends every process
LinuxCNC started. Run as a user, LinuxCNC runs as that user; the session refuses to start while
another LinuxCNC holds ``/tmp/linuxcnc.lock``.
"""

from __future__ import annotations

import json
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from oga.errors import InputError, OgaError

__all__ = ["LinuxcncError", "SessionResult", "linuxcnc_python", "edit_ini", "run_session",
           "rows_array"]

#: LinuxCNC's lock file (its start script's, fixed).
LOCKFILE = "/tmp/linuxcnc.lock"


class LinuxcncError(OgaError, RuntimeError):
    """LinuxCNC is missing, did not start, or the program did not run as asked."""


def linuxcnc_python() -> str:
    """A Python that imports LinuxCNC's ``linuxcnc`` and ``hal`` modules (Debian's
    ``/usr/bin/python3``, else ``python3`` on the PATH); LinuxcncError if none does."""
    seen = []
    for cand in ("/usr/bin/python3", shutil.which("python3")):
        if cand and cand not in seen and os.path.exists(cand):
            seen.append(cand)
            ok = subprocess.run([cand, "-c", "import linuxcnc, hal"], capture_output=True,
                                env={k: v for k, v in os.environ.items()
                                     if k not in ("PYTHONPATH", "PYTHONHOME")})
            if ok.returncode == 0:
                return cand
    raise LinuxcncError("no Python here imports LinuxCNC's linuxcnc and hal modules (tried "
                        f"{', '.join(seen) or 'python3'}): install LinuxCNC (linuxcnc-uspace)")


def edit_ini(text: str, *, display: str, job: str, halfiles: tuple[str, ...] = ()) -> str:
    """An INI file's text with ``[DISPLAY] DISPLAY`` replaced by ``display``, ``halfiles``
    added after its last ``[HAL] HALFILE`` and ``[OGA] JOB = job``."""
    out, section, display_done = [], None, False
    lines = text.splitlines()
    last_hal = max((i for i, ln in enumerate(lines)
                    if _key(ln) == "HALFILE" and _section_at(lines, i) == "HAL"), default=None)
    for i, line in enumerate(lines):
        s = line.strip()
        if s.startswith("[") and s.endswith("]"):
            if section == "DISPLAY" and not display_done:
                out.append(f"DISPLAY = {display}")
                display_done = True
            section = s[1:-1].strip()
        if section == "DISPLAY" and _key(line) == "DISPLAY":
            if not display_done:
                out.append(f"DISPLAY = {display}")
                display_done = True
            continue
        out.append(line)
        if i == last_hal:
            out += [f"HALFILE = {f}" for f in halfiles]
    if section == "DISPLAY" and not display_done:
        out.append(f"DISPLAY = {display}")
        display_done = True
    if not display_done:
        out += ["", "[DISPLAY]", f"DISPLAY = {display}"]
    if last_hal is None:
        out += ["", "[HAL]", *(f"HALFILE = {f}" for f in halfiles)]
    out += ["", "[OGA]", f"JOB = {job}", ""]
    return "\n".join(out)


def _key(line: str) -> str | None:
    s = line.strip()
    if not s or s[0] in "#;[" or "=" not in s:
        return None
    return s.split("=", 1)[0].strip()


def _section_at(lines: list[str], i: int) -> str | None:
    for ln in reversed(lines[:i]):
        s = ln.strip()
        if s.startswith("[") and s.endswith("]"):
            return s[1:-1].strip()
    return None


def rows_array(path: Path) -> np.ndarray:
    """The rows the display wrote (``repr`` of HAL values; TRUE/FALSE as 1/0), float64."""
    out = []
    with open(path) as f:
        for line in f:
            out.append([1.0 if c == "True" else 0.0 if c == "False" else float(c)
                        for c in line.split()])
    if not out:  # a run without sampler, or no row
        return np.zeros((0, 0))
    return np.array(out, dtype=np.float64).reshape(len(out), -1)


@dataclass(frozen=True, eq=False)
class SessionResult:
    """What a session recorded.

    Attributes
    ----------
    status : dict
        The display's report: ``ok``, ``runs`` (rows, actions done, durations), ``errors``
        (LinuxCNC's error channel), ``read`` (pins read once).
    runs : list of ndarray, shape (R, C)
        Per run, the sampled rows (one per servo period).
    log : str
        The start script's output.
    seconds : float
        Wall time of the session, s.
    """

    status: dict
    runs: list
    log: str
    seconds: float


def _user_for(ini: Path) -> pwd.struct_passwd:
    owner = os.stat(ini).st_uid
    if owner != 0:
        return pwd.getpwuid(owner)
    try:
        return pwd.getpwnam("nobody")
    except KeyError:
        raise LinuxcncError("LinuxCNC must not run as root and there is no user 'nobody' to "
                            "run it as: run oga as the configuration's owner") from None


def _namespaces_work() -> bool:
    if not shutil.which("unshare"):
        return False
    probe = subprocess.run(["unshare", "--pid", "--fork", "--kill-child", "--mount-proc",
                            "--ipc", "--mount", "true"], capture_output=True)
    return probe.returncode == 0


def run_session(ini: str | os.PathLike, job: dict, *, halfiles: dict[str, str] | None = None,
                files: dict[str, str] | None = None, timeout_s: float = 600.0) -> SessionResult:
    """Start LinuxCNC on a configuration, run the display's job, and shut it down.

    Parameters
    ----------
    ini : path
        The configuration's INI file.
    job : dict
        The display's job (:mod:`oga.export.linuxcnc.display`) without ``out``; its ``program`` is
        copied into the session (LinuxCNC runs the copy).
    halfiles : dict of str to str, optional
        HAL files (name -> text; ``.hal`` or ``.tcl``) added after the configuration's.
    files : dict of str to str, optional
        Other files written beside them (e.g. a stream).
    timeout_s : float
        Longest session, s.

    Returns
    -------
    SessionResult

    Raises
    ------
    LinuxcncError
        LinuxCNC is missing, did not start, timed out, or the display failed.
    InputError
        The INI file cannot be read.
    """
    ini = Path(ini).absolute()
    if not ini.is_file():
        raise InputError(f"--ini {ini}: no such file")
    script = shutil.which("linuxcnc")
    if script is None:
        raise LinuxcncError("LinuxCNC is not installed (no 'linuxcnc' on the PATH): install "
                            "linuxcnc-uspace")
    python = linuxcnc_python()
    root = os.geteuid() == 0
    isolate = root and _namespaces_work()
    user = _user_for(ini) if root else pwd.getpwuid(os.getuid())
    if not isolate and os.path.exists(LOCKFILE):
        raise LinuxcncError(f"another LinuxCNC is running ({LOCKFILE} exists): stop it, or "
                            "remove the file if it is stale")
    session = Path(tempfile.mkdtemp(prefix="oga-lcnc-"))
    priv = session / "tmp"  # /tmp inside the namespaces
    work, home = priv / "oga", priv / "home"
    out = work / "out"
    for d in (priv, work, out, home):
        d.mkdir(parents=True, exist_ok=True)
    inside = (lambda p: "/tmp/" + str(Path(p).relative_to(priv))) if isolate else str
    ini_copy = ini.with_name(f".oga-session-{session.name}.ini")
    t0 = time.monotonic()
    try:
        _write_session(ini, ini_copy, work, inside, python, job, halfiles, files)
        if root:
            for d in (session, priv, work, out, home):
                os.chown(d, user.pw_uid, user.pw_gid)
        env = _session_env(python, script, inside(home) if root else None, user)
        if isolate:
            cmd = _isolated_command(ini, priv, user, script, ini_copy)
        elif root:
            cmd = ["setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}",
                   "--clear-groups", script, str(ini_copy)]
        else:
            cmd = [script, str(ini_copy)]
        log_path = session / "linuxcnc.log"
        code = _run_linuxcnc(cmd, ini.parent, env, log_path, timeout_s)
        with open(log_path, "a") as log:  # the start script's logs, kept on an error
            for f in (home / "linuxcnc_debug.txt", home / "linuxcnc_print.txt"):
                if f.exists():
                    log.write(f"\n--- {f.name}\n" + f.read_text(errors="replace"))
        log_text = log_path.read_text(errors="replace")
        status, runs = _display_report(out, code, log_text, log_path)
        return SessionResult(status=status, runs=runs, log=log_text,
                             seconds=time.monotonic() - t0)
    finally:
        ini_copy.unlink(missing_ok=True)
        shutil.rmtree(session, ignore_errors=True)


def _write_session(ini: Path, ini_copy: Path, work: Path, inside, python: str, job: dict,
                   halfiles: dict[str, str] | None, files: dict[str, str] | None) -> None:
    """The display (for LinuxCNC's Python), the HAL and other files, the job and the edited
    INI copy, written into the session; ``inside`` names a path as LinuxCNC sees it."""
    display = work / "display.py"
    source = resources.files("oga.export.linuxcnc").joinpath("display.py").read_text()
    display.write_text(f"#!{python}\n" + source.split("\n", 1)[1])
    display.chmod(0o755)
    hal_paths = []
    for name, text in (halfiles or {}).items():
        (work / name).write_text(text)
        hal_paths.append(inside(work / name))
    for name, text in (files or {}).items():
        (work / name).write_text(text)
    job = {**job, "out": inside(work / "out")}
    if "program" in job:  # a copy LinuxCNC reads wherever the program is (/tmp is private)
        program = Path(job["program"])
        (work / program.name).write_bytes(program.read_bytes())
        job["program"] = inside(work / program.name)
    (work / "job.json").write_text(json.dumps(job))
    ini_copy.write_text(edit_ini(ini.read_text(), display=inside(display),
                                 job=inside(work / "job.json"), halfiles=tuple(hal_paths)))


def _session_env(python: str, script: str, home: str | None,
                 user: pwd.struct_passwd) -> dict[str, str]:
    """LinuxCNC's environment: none of oga's Python; its HOME in the session as root."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "DISPLAY")}
    env["PATH"] = ":".join(dict.fromkeys([os.path.dirname(python), os.path.dirname(script),
                                          "/usr/local/bin", "/usr/bin", "/bin", "/usr/sbin",
                                          "/sbin"]))
    if home is not None:  # LinuxCNC's start script leaves its logs in HOME on an error
        env.update(HOME=home, USER=user.pw_name, LOGNAME=user.pw_name)
    return env


def _isolated_command(ini: Path, priv: Path, user: pwd.struct_passwd, script: str,
                      ini_copy: Path) -> list[str]:
    """LinuxCNC as ``user`` in its own PID, IPC and mount namespaces, ``priv`` as /tmp (a
    configuration under /tmp bound inside)."""
    cfg = ini.parent
    binds = ""
    if str(cfg).startswith("/tmp/") and not str(cfg).startswith(str(priv)):
        rel = cfg.relative_to("/tmp")
        (priv / rel).mkdir(parents=True, exist_ok=True)
        binds = f'mount --bind "{cfg}" "{priv / rel}"; '
    shell = (f'{binds}mount --rbind "{priv}" /tmp && exec setpriv '
             f"--reuid={user.pw_uid} --regid={user.pw_gid} --clear-groups "
             f'"{script}" "{ini_copy}"')
    return ["unshare", "--pid", "--fork", "--kill-child", "--mount-proc", "--ipc",
            "--mount", "sh", "-c", shell]


def _run_linuxcnc(cmd: list[str], cwd: Path, env: dict, log_path: Path,
                  timeout_s: float) -> int:
    """Run the session's command (its output into ``log_path``) to its end: its exit status.
    Stopped, with a LinuxcncError, after ``timeout_s``; stopped on any other exception."""
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, cwd=str(cwd), env=env, stdin=subprocess.DEVNULL,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _stop(proc)
            raise LinuxcncError(f"LinuxCNC did not finish within {timeout_s:g} s; its "
                                f"output ends: {_tail(log_path)}") from None
        finally:
            if proc.poll() is None:
                _stop(proc)
    return proc.returncode


def _display_report(out: Path, code: int, log_text: str, log_path: Path):
    """The display's status (dict) and its runs' rows (:func:`rows_array`); a LinuxcncError
    where it did not report or failed."""
    status_path = out / "status.json"
    if not status_path.exists():
        raise LinuxcncError(f"LinuxCNC ended (exit status {code}) before the "
                            f"display reported: {_errors(log_text) or _tail(log_path)}")
    status = json.loads(status_path.read_text())
    if not status.get("ok"):
        raise LinuxcncError(f"the display failed: {status.get('exception')}; LinuxCNC "
                            f"reported {status.get('errors')}")
    return status, [rows_array(out / f"run{i}.txt") for i in range(len(status["runs"]))]


def _stop(proc: subprocess.Popen) -> None:
    """End the session started as ``proc`` (its own process group): SIGTERM (the start
    script cleans up), then SIGKILL."""
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 10.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _errors(log: str, most: int = 8) -> str:
    """The lines of LinuxCNC's logs that report an error, joined ("" if none)."""
    keys = ("error", "fail", "can't", "cannot", "not found", "no such")
    found = [ln.strip() for ln in log.splitlines()
             if any(k in ln.lower() for k in keys) and "=" not in ln.split(" ", 1)[0]]
    return " | ".join(list(dict.fromkeys(found))[:most])


def _tail(path: Path, n: int = 1500) -> str:
    try:
        return path.read_text(errors="replace")[-n:].strip() or "(nothing)"
    except OSError:
        return "(no output)"
