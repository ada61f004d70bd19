"""ros.priority: every thread of a process lowered, later threads inheriting (in a child
process: a nice value cannot be raised back without privileges)."""

import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice")

CHILD = textwrap.dedent("""
    import os, threading, time
    from lgs_wfs_ros.ros import priority

    def nice_of(tid):
        return int(open(f"/proc/self/task/{tid}/stat").read().rsplit(")", 1)[1].split()[16])

    stop = threading.Event()
    before = threading.Thread(target=stop.wait)          # started before: like DDS's threads
    before.start()
    changed = priority.lower(7)
    after = threading.Thread(target=stop.wait)
    after.start()
    time.sleep(0.1)
    nices = sorted({nice_of(t) for t in os.listdir("/proc/self/task")})
    again = priority.lower(3)                             # never raised back
    stop.set()
    print(changed, nices, again, priority.current())
""")


def test_every_thread_is_lowered_and_later_threads_inherit():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                         check=True).stdout.split(maxsplit=1)
    changed, rest = int(out[0]), out[1]
    assert changed >= 2                          # the main thread and the one started before
    assert rest.strip() == "[7] 0 7"


def test_only_nice_values_0_to_19():
    from lgs_wfs_ros.ros import priority
    with pytest.raises(ValueError, match="0 to 19"):
        priority.lower(-5)
