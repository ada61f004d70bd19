"""The iceoryx2 frame path (lgs_wfs_ros.transport.shm): frames and headers arrive intact and
in place, losses are counted by sequence, lockstep never drops, names keep graphs apart."""

import os
import subprocess
import sys
import textwrap
import uuid

import numpy as np
import pytest

from lgs_wfs_ros.sensor import Sensor
from lgs_wfs_ros.transport import shm

pytestmark = pytest.mark.skipif(not shm.AVAILABLE, reason="iceoryx2 not installed ('shm' extra)")


def _name():
    return shm.service_name("/test_" + uuid.uuid4().hex[:12], domain=os.environ.get("ROS_DOMAIN_ID", 0))


def test_service_name_from_domain_namespace_topic():
    assert shm.service_name("/wfs", "frame", domain=44) == "lgs_wfs_ros/d44/wfs/frame"
    assert shm.service_name("wfs/", domain=3) == "lgs_wfs_ros/d3/wfs/frame"
    assert shm.service_name("/a", domain=1) != shm.service_name("/a", domain=2)


def test_sensor_id_follows_the_description():
    a = Sensor()
    assert shm.sensor_id(a) == shm.sensor_id(Sensor.from_json(a.to_json()))
    assert shm.sensor_id(a) != shm.sensor_id(a.replace(photons=a.photons + 1))


def test_frames_arrive_in_place_with_their_header():
    name = _name()
    sub = shm.ShmFrameSubscriber(name, depth=8)
    pub = shm.ShmFramePublisher(name, 64 * 48 * 2)
    rng = np.random.default_rng(1)
    sent = [rng.integers(0, 65535, (64, 48), dtype=np.uint16) for _ in range(3)]
    for k, img in enumerate(sent):
        loan = pub.loan(img.shape, img.dtype)
        loan.image[...] = img            # rendered straight into shared memory
        assert pub.send(loan, 1_000 + k, sensor=42) == 1
    pub.publish(np.full((5, 7), 1.5, np.float32), 2_000, sensor=43)   # another shape and type
    assert sub.wait(1.0)
    for k, img in enumerate(sent):
        with sub.take() as frame:
            assert (frame.stamp_ns, frame.sequence, frame.sensor_id) == (1_000 + k, k + 1, 42)
            np.testing.assert_array_equal(frame.image, img)
            assert not frame.image.flags.writeable and not frame.image.flags.owndata
    with sub.take() as frame:
        assert frame.image.dtype == np.float32 and frame.image.shape == (5, 7)
        assert frame.stamp_ns == 2_000 and np.all(frame.image == 1.5)
    assert sub.take() is None
    assert (sub.received, sub.lost, pub.undelivered) == (4, 0, 0)
    pub.close(), sub.close()


def test_a_full_queue_loses_frames_and_counts_them():
    name = _name()
    sub = shm.ShmFrameSubscriber(name, depth=4)
    pub = shm.ShmFramePublisher(name, 16)
    for k in range(10):
        pub.publish(np.full((2, 4), k, np.uint16), 100 + k)
    seqs = [f.sequence for f in sub.drain(100)]
    assert seqs == [1, 2, 3, 4]               # the queue's four; the six newer ones refused
    assert pub.undelivered == 6
    pub.publish(np.zeros((2, 4), np.uint16), 200)
    assert [f.sequence for f in sub.drain(100)] == [11]
    assert sub.lost == 6 and sub.received == 5
    pub.close(), sub.close()


def test_drain_releases_each_frame():
    name = _name()
    sub = shm.ShmFrameSubscriber(name, depth=16)
    pub = shm.ShmFramePublisher(name, 16)
    for k in range(12):      # more than the borrowable limit: only released frames free it
        pub.publish(np.full((2, 4), k, np.uint16), 100 + k)
    assert [int(f.image[0, 0]) for f in sub.drain(100)] == list(range(12))
    pub.close(), sub.close()


READER = textwrap.dedent("""
    import sys, time
    from lgs_wfs_ros.transport import shm
    sub = shm.ShmFrameSubscriber(sys.argv[1], depth=3, ack=True)
    print("ready", flush=True)
    seqs, t0 = [], time.monotonic()
    while len(seqs) < int(sys.argv[2]) and time.monotonic() - t0 < 60:
        if sub.wait(0.2):
            f = sub.take()
            assert int(f.image[0, 0]) == f.sequence % 60000
            time.sleep(0.003)             # a slow reader
            seqs.append(f.sequence)
            f.release()
    print(len(seqs), sub.lost, seqs == list(range(1, len(seqs) + 1)), flush=True)
""")


@pytest.mark.parametrize("lockstep", [True, False])
def test_lockstep_never_drops_between_processes(lockstep):
    """A reader in another process, 3 ms a frame, queue of 3: the lockstep publisher waits
    for it and all 60 frames arrive in order; without lockstep most are lost (counted)."""
    name, n = _name(), 60
    proc = subprocess.Popen([sys.executable, "-c", READER, name, str(n)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        pub = shm.ShmFramePublisher(name, 32 * 32 * 2, lockstep=lockstep)
        for k in range(1, n + 1):
            pub.wait_for_room()
            loan = pub.loan((32, 32), np.uint16)
            loan.image[...] = k
            pub.send(loan, k)
        if lockstep:
            out = proc.communicate(timeout=60)[0].split()
            assert out == [str(n), "0", "True"]
            assert pub.undelivered == 0 and pub.stalled == 0
        else:
            assert pub.undelivered > n // 2
            proc.kill()
        pub.close()
    finally:
        proc.kill()
        proc.wait()
