"""A LinuxCNC 2.9 servo-simulation configuration that ``tests/data/lcnc_sim.toml`` describes
exactly: LinuxCNC's ``servo_sim.hal`` pattern, ``pid`` -> simulated drive -> feedback, with the
drive a ``lowpass`` (the velocity) and an ``integ`` (the position), X, Y, Z on ``trivkins``.

The following error is checked as in any configuration (``FERROR``, ``MIN_FERROR``); the
fixed gains are the INI file's ``[JOINT_N] P`` and ``FF1``.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DRIVE_GAIN", "FERROR_MM", "MIN_FERROR_MM", "write_config"]

#: The lowpass gain of the simulated drive (the machine file's ARX: num [0.2], den [1, -0.8]).
DRIVE_GAIN = 0.2
#: LinuxCNC's following-error limits, mm: FERROR at MAX_VELOCITY, never below MIN_FERROR.
FERROR_MM, MIN_FERROR_MM = 2.0, 1.0

_JOINT = """
[AXIS_{A}]
MAX_VELOCITY = 100
MAX_ACCELERATION = 1000
MIN_LIMIT = -1000
MAX_LIMIT = 1000

[JOINT_{J}]
TYPE = LINEAR
HOME = {HOME}
MAX_VELOCITY = 100
MAX_ACCELERATION = 1000
FERROR = {FERROR}
MIN_FERROR = {MIN_FERROR}
MIN_LIMIT = -1000
MAX_LIMIT = 1000
HOME_SEQUENCE = 0
P = {P}
FF1 = {FF1}
"""

_INI = """[EMC]
VERSION = 1.1
MACHINE = oga-lcnc-sim
DEBUG = 0

[DISPLAY]
DISPLAY = dummy

[TASK]
TASK = milltask
CYCLE_TIME = 0.001

[RS274NGC]
PARAMETER_FILE = sim.var

[EMCMOT]
EMCMOT = motmod
COMM_TIMEOUT = 1.0
SERVO_PERIOD = 1000000

[EMCIO]
EMCIO = io
CYCLE_TIME = 0.100
TOOL_TABLE = tool.tbl

[HAL]
HALUI = halui
HALFILE = sim.hal
{EXTRA}
[TRAJ]
COORDINATES = X Y Z
LINEAR_UNITS = mm
ANGULAR_UNITS = degree
DEFAULT_LINEAR_VELOCITY = 50
MAX_LINEAR_VELOCITY = 100
NO_FORCE_HOMING = 1

[KINS]
KINEMATICS = trivkins coordinates=XYZ
JOINTS = 3
"""

_HAL = """# oga's LinuxCNC servo simulation: pid -> lowpass (velocity) -> integ (position)
loadrt [KINS]KINEMATICS
loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS
loadrt pid num_chan=3
loadrt lowpass names=drive-x,drive-y,drive-z
loadrt integ names=pos-x,pos-y,pos-z
addf motion-command-handler servo-thread
addf motion-controller servo-thread
addf pid.0.do-pid-calcs servo-thread
addf pid.1.do-pid-calcs servo-thread
addf pid.2.do-pid-calcs servo-thread
addf drive-x servo-thread
addf drive-y servo-thread
addf drive-z servo-thread
addf pos-x servo-thread
addf pos-y servo-thread
addf pos-z servo-thread
net estop-loop iocontrol.0.user-enable-out iocontrol.0.emc-enable-in
net tool-prep-loop iocontrol.0.tool-prepare iocontrol.0.tool-prepared
net tool-change-loop iocontrol.0.tool-change iocontrol.0.tool-changed
"""

_HAL_AXIS = """net {a}-pos-cmd joint.{j}.motor-pos-cmd => pid.{j}.command
net {a}-enable joint.{j}.amp-enable-out => pid.{j}.enable
net {a}-out pid.{j}.output => drive-{a}.in
net {a}-vel drive-{a}.out => pos-{a}.in
net {a}-pos-fb pos-{a}.out => pid.{j}.feedback joint.{j}.motor-pos-fb
setp drive-{a}.gain {gain!r}
setp pid.{j}.Pgain [JOINT_{j}]P
setp pid.{j}.FF1 [JOINT_{j}]FF1
"""


def write_config(folder: Path, kp_1_s: float, kf: float, extra_halfiles=(),
                 owner: int | None = None, home_mm: dict[str, float] | None = None) -> Path:
    """Write the configuration into ``folder``; its INI file. ``kp_1_s``, ``kf``: the fixed
    gains (pid Pgain, FF1); ``extra_halfiles`` are added after ``sim.hal``; ``owner``: the
    user the folder is given to (LinuxCNC writes its parameter file there)."""
    folder.mkdir(parents=True, exist_ok=True)
    home = {"x": 0.0, "y": 0.0, "z": 0.0, **(home_mm or {})}
    joints = "".join(_JOINT.format(A=a.upper(), J=j, FERROR=FERROR_MM, MIN_FERROR=MIN_FERROR_MM,
                                   P=repr(kp_1_s), FF1=repr(kf), HOME=repr(float(home[a])))
                     for j, a in enumerate("xyz"))
    extra = "".join(f"HALFILE = {f}\n" for f in extra_halfiles)
    (folder / "sim.ini").write_text(_INI.format(EXTRA=extra) + joints)
    (folder / "sim.hal").write_text(_HAL + "".join(
        _HAL_AXIS.format(a=a, j=j, gain=DRIVE_GAIN) for j, a in enumerate("xyz")))
    (folder / "tool.tbl").write_text("T1 P1 D0 Z0 ;\n")
    if owner is not None:
        for p in (folder, *folder.iterdir()):
            os.chown(p, owner, -1)
        folder.chmod(0o755)
    return folder / "sim.ini"
