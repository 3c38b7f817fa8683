#!/usr/bin/env python3
"""oga's table feeder: keeps a gain table ready in a LinuxCNC ``streamer`` for every run.

A script for LinuxCNC's own Python (its ``hal`` module); it imports nothing of oga.
``oga export --recording`` writes it next to ``oga_table.tcl``, which starts it:
``loadusr -Wn oga-feeder python3 oga_feeder.py oga_table.stream CHANNEL``.

Why a component of its own: LinuxCNC's ``halstreamer`` loads a stream once, but a table must
start from its first row at every run of its program, and the rows a fallback left in the
FIFO must go first; no LinuxCNC component rewinds a stream. This one holds the table's rows
(the stream file's numbers, exactly) and, through LinuxCNC's stream API:

- writes rows into the FIFO whenever it has room (the realtime side reads one per servo
  period once the table runs), and raises ``oga-feeder.ready`` once the FIFO holds the
  table's first rows (all of them, or as many as it takes);
- once the table has run and ended (``oga-feeder.used`` and ``oga-feeder.done``: its end or a
  fallback) and the program is idle (``oga-feeder.idle``, ``halui.program.is-idle``, seen
  running since the table started, or idle for :data:`SETTLE_S`: halui reports the state
  some milliseconds late): lowers ``ready`` (the realtime side then reads no more),
  discards what is left in the FIFO, pulses ``oga-feeder.rearm`` (it clears the table's
  start and fallback latches), and loads the table again from its first row.
"""

import sys
import time

import hal

#: Poll period, s.
POLL_S = float(sys.argv[3]) if len(sys.argv) > 3 else 0.02
#: A program idle this long after the table ended has ended, s.
SETTLE_S = 1.0


def _rows(path, types):
    rows = []
    with open(path) as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            cells = line.split()
            rows.append(tuple(int(float(c)) if t in "bsu" else float(c) for c, t in zip(cells, types)))
    return rows


def main():
    path, channel = sys.argv[1], int(sys.argv[2])
    comp = hal.component("oga-feeder")
    comp.newpin("ready", hal.HAL_BIT, hal.HAL_OUT)
    comp.newpin("rearm", hal.HAL_BIT, hal.HAL_OUT)
    comp.newpin("used", hal.HAL_BIT, hal.HAL_IN)
    comp.newpin("done", hal.HAL_BIT, hal.HAL_IN)
    comp.newpin("idle", hal.HAL_BIT, hal.HAL_IN)
    comp.newpin("loads", hal.HAL_S32, hal.HAL_OUT)
    comp.newpin("underfull", hal.HAL_S32, hal.HAL_OUT)
    stream = hal.stream(comp, hal.streamer_base + channel)
    types = stream.element_types.decode() if isinstance(stream.element_types, bytes) \
        else stream.element_types
    rows = _rows(path, types)
    first = min(len(rows), stream.maxdepth - 1)
    comp.ready()
    nxt = 0

    def fill():
        nonlocal nxt
        while nxt < len(rows) and stream.writable:
            stream.write(rows[nxt])
            nxt += 1

    def load():
        nonlocal nxt
        comp["ready"] = False
        time.sleep(4 * POLL_S)  # the realtime side has seen ready FALSE: it reads no more
        while stream.read() is not None:  # rows a fallback left
            pass
        nxt = 0
        fill()
        comp["rearm"] = True
        time.sleep(4 * POLL_S)
        comp["rearm"] = False
        comp["loads"] += 1
        if nxt < first:  # the FIFO could not take the first rows (should not happen)
            comp["underfull"] += 1
            return
        comp["ready"] = True

    load()
    running, idle_since = False, None
    while True:
        time.sleep(POLL_S)
        fill()
        if not comp["used"]:
            running, idle_since = False, None
            continue
        now = time.monotonic()
        if not comp["idle"]:
            running, idle_since = True, None
        elif idle_since is None:
            idle_since = now
        if comp["done"] and comp["idle"] and (running or now - idle_since >= SETTLE_S):
            load()
            running, idle_since = False, None


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        pass
