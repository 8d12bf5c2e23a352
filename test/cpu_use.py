"""
How busy the machine was during a real-time test: the node tests and the live tests.

A claim that holds only where the nodes got their CPU (a command rate, a ramp's timing by
the wall clock) is required where the cores had room and reported, with the figures, where
they were measured saturated.
"""

import os
from pathlib import Path


#: The share of the machine's CPU time busy over a run at which the nodes count as starved.
SATURATED_SHARE = 0.9
#: 1-minute load per core above which the machine cannot run the five nodes in real time.
LOADED_PER_CORE = 4.0


class CpuUse:
    """
    The machine's CPU use from its start to :meth:`busy_share` (/proc/stat, every core).

    The share of all cores' time spent busy (not idle or waiting for I/O): a run of the nodes
    at 0.9 or more had no core to spare, so the nodes could be starved, however the 1-minute
    load (a lagging average) reads.
    """

    def __init__(self):
        self.start = self._times()

    @staticmethod
    def _times():
        try:
            fields = Path('/proc/stat').read_text().split('\n', 1)[0].split()[1:]
        except OSError:
            return None
        ticks = [int(v) for v in fields]
        idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)       # idle + iowait
        return sum(ticks[:8]) - idle, sum(ticks[:8])

    def busy_share(self):
        """Return the busy share of all cores since the start (0 where /proc/stat is missing)."""
        end = self._times()
        if self.start is None or end is None or end[1] <= self.start[1]:
            return 0.0
        return (end[0] - self.start[0]) / (end[1] - self.start[1])


def starved(load, busy_share):
    """Return whether a run at this peak 1-minute load and CPU busy share was starved of CPU."""
    return busy_share >= SATURATED_SHARE or load > LOADED_PER_CORE * (os.cpu_count() or 1)
