"""A node process's CPU priority: the nice value of every one of its threads.

On Linux nice is a property of each thread, and a thread starts with its creator's. rclpy
and Fast DDS start their threads when the context and the node are made, before a node can
read its parameters, so lowering the priority of a running node means setting every thread
listed in ``/proc/self/task``; threads started afterwards inherit it. A node that is not
latency-critical (the recorder) can so yield the CPU to the real-time path (source,
centroiders) when the cores are contended: the kernel's scheduler weighs nice 10 about 10
times below nice 0.
"""

from __future__ import annotations

import os
from pathlib import Path

TASKS = Path("/proc/self/task")


def lower(nice: int) -> int:
    """Every thread of this process at ``nice`` (0-19) at least; never raised (that needs
    privileges). Returns the threads changed. Where the OS has no per-thread list, the
    calling thread alone (and the threads it starts later)."""
    if not 0 <= int(nice) <= 19:
        raise ValueError(f"nice must be 0 to 19, got {nice}")
    tids = [int(t) for t in os.listdir(TASKS)] if TASKS.is_dir() else [0]
    changed = 0
    for tid in tids:
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) < nice:
                os.setpriority(os.PRIO_PROCESS, tid, int(nice))
                changed += 1
        except (ProcessLookupError, PermissionError):     # a thread that just ended
            continue
    return changed


def current() -> int:
    """The calling thread's nice value."""
    return os.getpriority(os.PRIO_PROCESS, 0)
