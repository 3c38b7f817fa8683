"""Run LinuxCNC's interpreter on one program and print its canonical calls (a child process).

Standard library only, so that any Python able to import LinuxCNC's ``gcode`` module runs it
(the project's, or Debian's ``/usr/bin/python3``). :mod:`feedplan.gcode.linuxcnc` starts it in
a temporary folder holding the program, the tool table and the parameter file, bounded in time,
memory and output, and reads what it prints:

=========================  ==========================================================
record                     canonical call (lengths in inches, as the module gives them)
=========================  ==========================================================
``N seq g... m...``        a new source line: its number, active G codes, M codes
``T x y z a b c u v w``    STRAIGHT_TRAVERSE (program coordinates)
``F x y z a b c u v w``    STRAIGHT_FEED (program coordinates)
``A e1 e2 c1 c2 r e3 ...`` ARC_FEED: end and centre in the plane, rotation, normal end
``P plane``                SELECT_PLANE (1 XY, 2 YZ, 3 XZ)
``R rate``                 SET_FEED_RATE, inches per minute
``D seconds``              DWELL
``C pocket``               CHANGE_TOOL
``O index x y z ...``      SET_G5X_OFFSET;  ``G x y z ...`` SET_G92_OFFSET
``X degrees``              SET_XY_ROTATION;  ``L x y z ...`` USE_TOOL_LENGTH_OFFSET
``E result line text``     the end: the interpreter's result code, line and message
=========================  ==========================================================

Usage: ``python _worker.py PROGRAM TOOLS PARAMS MAX_RECORDS SECONDS MODULE_PATH AXIS_MASK
MEMORY_BYTES`` (the worker bounds its own address space and writes no core file).
"""

import ctypes
import os
import resource
import sys
import time


def _tools(path):
    """Index -> (tool number, x, y, z, diameter) of the tool table written by the parent."""
    out = {}
    with open(path, encoding="ascii") as f:
        for index, text in enumerate(f, start=1):
            words = {w[0]: w[1:] for w in text.split()}
            out[index] = (int(words["T"]), float(words.get("X", 0)), float(words.get("Y", 0)),
                          float(words.get("Z", 0)), float(words.get("D", 0)))
    return out


class _TooMany(Exception):
    pass


class Canon:
    """The callbacks LinuxCNC's ``gcode.parse`` calls, printed as records."""

    def __init__(self, params, tools, max_records, deadline, mask):
        self.parameter_file = params
        self.mask = mask
        self.tools = tools
        self.spindle = None  # index of the tool in the spindle (AXIS's StatMixin does this)
        self.left = max_records
        self.deadline = deadline
        self.out = []

    def _put(self, *items):
        self.left -= 1
        if self.left < 0:
            raise _TooMany()
        self.out.append(" ".join([items[0], *map(repr, items[1:])]))

    # -- what the interpreter asks -------------------------------------------------------
    def get_external_angular_units(self):
        return 1.0

    def get_external_length_units(self):
        return 1.0  # mm per mm: the tool table and the parameters are in millimetres

    def get_axis_mask(self):
        return self.mask  # X 1, Y 2, Z 4: a word for another axis is an error

    def get_block_delete(self):
        return False

    def check_abort(self):
        return time.monotonic() > self.deadline

    def get_tool(self, index):
        t = self.tools.get(self.spindle if index == 0 and self.spindle else index)
        if t is None:
            return (-1,) + (0.0,) * 12 + (0,)
        return (t[0], t[1], t[2], t[3], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, t[4], 0.0, 0.0, 0)

    # -- what it reports -------------------------------------------------------------------
    def next_line(self, st):
        self.out.append("N " + " ".join(map(str, (st.sequence_number, *st.gcodes[1:],
                                                   *st.mcodes[1:]))))

    def straight_traverse(self, *p):
        self._put("T", *p)

    def straight_feed(self, *p):
        self._put("F", *p)

    def straight_probe(self, *p):
        raise ValueError("probing moves (G38) cannot be planned")

    def rigid_tap(self, *p):
        raise ValueError("rigid tapping (G33.1) cannot be planned")

    def arc_feed(self, *p):
        self._put("A", *p)

    def set_plane(self, plane):
        self._put("P", plane)

    def set_feed_rate(self, rate):
        self._put("R", rate)

    def dwell(self, seconds):
        self._put("D", seconds)

    def change_tool(self, pocket):
        self.spindle = pocket
        self._put("C", pocket)

    def set_g5x_offset(self, index, *p):
        self._put("O", index, *p)

    def set_g92_offset(self, *p):
        self._put("G", *p)

    def set_xy_rotation(self, degrees):
        self._put("X", degrees)

    def tool_offset(self, *p):
        self._put("L", *p)

    def __getattr__(self, name):  # comments, messages, user M codes, spindle, traverse rate
        if name.startswith("__"):
            raise AttributeError(name)
        return lambda *args: None


def main(argv):
    program, tool_file, params, max_records, seconds, module_path, mask, memory = argv[1:9]
    resource.setrlimit(resource.RLIMIT_AS, (int(memory), int(memory)))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    deadline = time.monotonic() + float(seconds)
    sys.path.append(module_path)
    os.environ["HOME"] = os.path.dirname(os.path.abspath(tool_file))  # the tool table's mmap
    lib = ctypes.CDLL("libtooldata.so.0")
    lib._Z17tool_mmap_creatorPK13EMC_TOOL_STATi(None, 0)
    lib._Z13tooldata_loadPKcPPc(tool_file.encode(), None)
    import gcode

    canon = Canon(params, _tools(tool_file), int(max_records), deadline, int(mask))
    try:
        result, line = gcode.parse(program, canon, "G21", "G64")
        message = gcode.strerror(result) if result > gcode.MIN_ERROR else ""
    except _TooMany:
        result, line, message = -1, 0, f"more than {max_records} canonical calls"
    except KeyboardInterrupt:
        result, line = -2, 0
        message = f"not finished within {float(seconds):g} s (an endless loop?)"
    except Exception as err:  # an error a callback raised (probing, tapping)
        result, line, message = -3, 0, str(err)
    canon.out.append(f"E {result} {line} {message}")
    sys.stdout.write("\n".join(canon.out) + "\n")
    sys.stdout.flush()
    lib._Z15tool_mmap_closev()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
