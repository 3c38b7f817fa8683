#!/usr/bin/python3
"""oga's headless LinuxCNC display: runs a program and records HAL pins, no GUI.

This file is a script for LinuxCNC's own Python (its ``linuxcnc`` and ``hal`` modules);
it imports nothing of oga. ``oga.export.linuxcnc.session`` copies it next to a configuration and
names it as the ``[DISPLAY] DISPLAY`` program, so LinuxCNC's start script runs it as any
display: ``display.py -ini INIFILE``. The job is the JSON file named by ``[OGA] JOB``:

- ``program``: the G-code file; ``home``: home all joints first (if not homed);
- ``sampler``: ``{"channel": N, "types": "ffs..."}``: the ``sampler`` whose FIFO is read
  (enabled from just before each run's start to ``tail_s`` after its end);
- ``read``: pin or parameter names read once after the machine is on; ``read_files``:
  files beside the job file (written by the job's HAL files) returned in the status;
- ``runs``: per run ``prepare`` (steps before the start, in order: ``{"setp": {pin:
  value}}``, ``{"mdi": "G0 X0"}`` (run and waited for), ``{"wait_pin": name}`` (until
  TRUE), ``{"sleep": s}``, ``{"back_to_start": {"X": k, ...}}`` (G53 G0 to the previous
  run's first sampled positions, columns k), ``{"tool_of_run": j}`` (``M61 Q``: the tool in
  the spindle at run j's start, set without a tool change: a program with ``M6`` then starts
  every run as run j did)), ``actions`` (``{"after_s": t, "do":
  "feed_override" | "rapid_override" | "pause" | "resume" | "abort" | "estop" | "setp",
  "value": .., "name": .., "part": i}``, ``t`` seconds after the start of motion number
  ``i``, 0 by default: the first; a motion starts a new one after STOP_S at rest), ``tail_s``,
  ``timeout_s``, ``retry`` (``{"column": k, "min_rows": m, "attempts": a}``: run again, up
  to ``a`` times in all, while fewer than ``m`` sampled rows have the bit column ``k``
  TRUE);
- ``auto_resume`` (default TRUE): a pause the program itself makes (``M0``, or ``M1`` with
  the optional stop on) is resumed (``AUTO_RESUME``) as soon as the task reports it, and
  listed in the run's ``pauses`` (seconds after the start, how long it lasted); FALSE:
  such a pause ends the session with an error saying when (a headless run has
  no operator to press cycle start: it never waits for one). A ``pause`` action of the job
  is the job's, never resumed but by its ``resume`` action;
- ``out``: folder for ``run<i>.txt`` (one sampled row per servo period, exact values) and
  ``status.json`` (what happened: errors of LinuxCNC's error channel, the program's
  messages to the operator, rows, overruns, pauses resumed).

When it exits, LinuxCNC shuts down.
"""

import json
import os
import sys
import time
import traceback

import hal
import linuxcnc

#: A motion that starts after this long at rest starts a new part of the program (an action's
#: ``part``), s.
STOP_S = 0.05


def _ini_job():
    ini = sys.argv[sys.argv.index("-ini") + 1]
    path = linuxcnc.ini(ini).find("OGA", "JOB")
    with open(path) as f:
        return {**json.load(f), "dir": os.path.dirname(path)}


class Display:
    def __init__(self, job):
        self.job = job
        self.s = linuxcnc.stat()
        self.c = linuxcnc.command()
        self.e = linuxcnc.error_channel()
        self.errors, self.messages = [], []
        self.held = False  # paused by a "pause" action of the job
        self.tools = {}  # per run, the tool in the spindle at its start
        self.comp = hal.component("oga-display")
        self.comp.ready()
        sm = job.get("sampler")
        self.stream = None if sm is None else hal.stream(
            self.comp, hal.sampler_base + sm["channel"], sm["types"])

    def poll_errors(self):
        """Errors apart from the program's messages to the operator (``(MSG, ...)``,
        ``(DEBUG, ...)``: texts and displays, no fault), which go to ``messages``."""
        while True:
            m = self.e.poll()
            if not m:
                return
            fault = m[0] in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR)
            (self.errors if fault else self.messages).append([m[0], m[1]])

    def wait(self, cond, timeout, what):
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            self.s.poll()
            self.poll_errors()
            if cond():
                return
            time.sleep(0.005)
        raise RuntimeError(f"timed out after {timeout} s waiting for {what}")

    def machine_on(self):
        s, c = self.s, self.c
        c.state(linuxcnc.STATE_ESTOP_RESET)
        c.wait_complete()
        c.state(linuxcnc.STATE_ON)
        c.wait_complete()
        self.wait(lambda: s.task_state == linuxcnc.STATE_ON, 10, "the machine to turn on")

    def home(self):
        s, c = self.s, self.c
        s.poll()
        if all(s.homed[j] for j in range(s.joints)):
            return
        c.mode(linuxcnc.MODE_MANUAL)
        c.wait_complete()
        c.home(-1)
        self.wait(lambda: all(s.homed[j] for j in range(s.joints)), 60, "homing")

    def drain(self, rows):
        if self.stream is None:
            return
        while True:
            r = self.stream.read()
            if r is None:
                return
            rows.append(r)

    def act(self, a):
        do, c = a["do"], self.c
        if do == "feed_override":
            c.feedrate(float(a["value"]))
        elif do == "rapid_override":
            c.rapidrate(float(a["value"]))
        elif do == "pause":
            self.held = True
            c.auto(linuxcnc.AUTO_PAUSE)
        elif do == "resume":
            self.held = False
            c.auto(linuxcnc.AUTO_RESUME)
        elif do == "abort":
            c.abort()
        elif do == "estop":
            c.state(linuxcnc.STATE_ESTOP)
        elif do == "setp":
            hal.set_p(a["name"], str(a["value"]))
        else:
            raise ValueError(f"unknown action {do!r}")

    def idle(self):
        s = self.s
        return s.interp_state == linuxcnc.INTERP_IDLE and s.queue == 0 and s.inpos

    def prepare(self, step):
        s, c = self.s, self.c
        if "setp" in step:
            for name, value in step["setp"].items():
                hal.set_p(name, str(value))
        elif "mdi" in step:
            c.mode(linuxcnc.MODE_MDI)
            c.wait_complete()
            c.mdi(step["mdi"])
            c.wait_complete()
            self.wait(lambda: self.idle(), 60, f"MDI {step['mdi']!r}")
        elif "back_to_start" in step:  # the first sampled position of the previous run
            with open(os.path.join(self.job["out"], f"run{self.last}.txt")) as f:
                first = f.readline().split()
            words = " ".join(f"{axis}{float(first[k])!r}"
                             for axis, k in step["back_to_start"].items())
            self.prepare({"mdi": f"G53 G0 {words}"})
        elif "tool_of_run" in step:
            self.prepare({"mdi": f"M61 Q{self.tools[int(step['tool_of_run'])]}"})
        elif "wait_pin" in step:
            self.wait(lambda: bool(hal.get_value(step["wait_pin"])), 60, step["wait_pin"])
        elif "sleep" in step:
            time.sleep(float(step["sleep"]))
        else:
            raise ValueError(f"unknown step {step!r}")

    def run(self, i, spec):
        s, c, job = self.s, self.c, self.job
        s.poll()
        if s.task_state != linuxcnc.STATE_ON:
            self.machine_on()
        c.feedrate(1.0)
        c.rapidrate(1.0)
        self.tools.setdefault(i, s.tool_in_spindle)  # a retry starts as the run's first try
        for step in spec.get("prepare", []):
            self.prepare(step)
        c.mode(linuxcnc.MODE_AUTO)
        c.wait_complete()
        c.program_open(job["program"])
        c.wait_complete()
        sm = job.get("sampler")
        rows = []
        if sm is not None:
            self.drain([])
            hal.set_p(f"sampler.{sm['channel']}.enable", "1")
        t0 = time.monotonic()
        c.auto(linuxcnc.AUTO_RUN, 0)
        actions = sorted(spec.get("actions", []), key=lambda a: (a.get("part", 0), a["after_s"]))
        done, t_motion, timeout = [], None, float(spec.get("timeout_s", 600))
        starts, still_since = [], t0  # when each motion after a stop started
        pauses, pause = [], None  # the program's own M0/M1 pauses; the one under way
        self.held = False
        while True:
            time.sleep(0.002)
            s.poll()
            self.poll_errors()
            self.drain(rows)
            now = time.monotonic()
            if s.current_vel > 0:  # a motion starts after a stop (at least STOP_S at rest)
                if still_since is not None and (not starts or now - still_since >= STOP_S):
                    starts.append(now)
                still_since = None
            elif still_since is None:
                still_since = now
            t_motion = starts[0] if starts else None
            while actions and len(starts) > actions[0].get("part", 0) \
                    and now - starts[actions[0].get("part", 0)] >= actions[0]["after_s"]:
                a = actions.pop(0)
                self.act(a)
                done.append({**a, "at_s": now - starts[a.get("part", 0)]})
            if pause is None and s.task_paused and not self.held:  # M0, or M1
                # (LinuxCNC's status names no line for it: the interpreter has read on)
                if not job.get("auto_resume", True):
                    raise RuntimeError(f"run {i}: the program paused (M0 or M1) {now - t0:.3f} s "
                                       "after its start and auto_resume is off")
                pause = {"at_s": now - t0}
                c.auto(linuxcnc.AUTO_RESUME)
            elif pause is not None and not s.task_paused:
                pause["lasted_s"] = now - t0 - pause["at_s"]
                pauses.append(pause)
                pause = None
            if now - t0 > 0.1 and self.idle() and not actions:
                break
            if now - t0 > timeout:
                raise RuntimeError(f"run {i}: the program did not end within {timeout} s")
        t_end = time.monotonic()
        while time.monotonic() - t_end < float(spec.get("tail_s", 0.2)):
            time.sleep(0.002)
            self.drain(rows)
        if sm is not None:
            hal.set_p(f"sampler.{sm['channel']}.enable", "0")
            time.sleep(0.02)
            self.drain(rows)
        with open(os.path.join(job["out"], f"run{i}.txt"), "w") as f:
            for r in rows:
                f.write(" ".join(repr(v) for v in r) + "\n")
        c.feedrate(1.0)
        c.rapidrate(1.0)
        return {"rows": len(rows), "actions": done, "pauses": pauses, "tool": self.tools[i],
                "duration_s": t_end - t0,
                "motion_after_s": None if t_motion is None else t_motion - t0,
                "overruns": None if self.stream is None else self.stream.num_overruns}

    def valid_rows(self, i, column):
        with open(os.path.join(self.job["out"], f"run{i}.txt")) as f:
            return sum(1 for line in f if line.split()[column] == "True")

    def main(self):
        job = self.job
        status = {"version": getattr(linuxcnc, "version", ""), "runs": [], "read": {},
                  "auto_resume": bool(job.get("auto_resume", True))}
        try:
            self.machine_on()
            if job.get("home", True):
                self.home()
            for name in job.get("read", []):
                status["read"][name] = hal.get_value(name)
            status["files"] = {}
            for name in job.get("read_files", []):  # written by the job's HAL files
                with open(os.path.join(job["dir"], name)) as f:
                    status["files"][name] = f.read()
            for i, spec in enumerate(job.get("runs", [{}])):
                retry = spec.get("retry")
                tries = 1 if retry is None else int(retry["attempts"])
                for attempt in range(tries):
                    done = self.run(i, spec)
                    self.last = i
                    done["attempt"] = attempt + 1
                    if retry is None or self.valid_rows(i, retry["column"]) >= retry["min_rows"]:
                        break
                status["runs"].append(done)
            status["ok"] = True
        except Exception as err:  # reported to oga in status.json, then LinuxCNC shuts down
            status["ok"] = False
            status["exception"] = f"{type(err).__name__}: {err}"
            status["traceback"] = traceback.format_exc()
        self.poll_errors()
        status["errors"], status["messages"] = self.errors, self.messages
        with open(os.path.join(job["out"], "status.json"), "w") as f:
            json.dump(status, f)


if __name__ == "__main__":
    Display(_ini_job()).main()
