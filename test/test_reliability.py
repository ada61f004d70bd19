"""Faults: signals and full disks during recording, existing outputs, bad frames and parameters."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import wait_for
from lgs_wfs_ros import bags
from lgs_wfs_ros.optics import geometry
from test_nodes import SMALL, Rig, small_frame

pytestmark = pytest.mark.ros


def start_recorder(tmp_path, out, extra=None):
    params = {"output": str(out), "discover": False, "frame_every": 1,
              "topics": ["/wfs/frame", "/wfs/sensor"], **(extra or {})}
    pfile = tmp_path / f"rec_{time.monotonic_ns()}.yaml"
    pfile.write_text(json.dumps({"/**": {"ros__parameters": params}}))
    log = open(tmp_path / f"{pfile.stem}.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "lgs_wfs_ros.ros.recorder_node", "--ros-args",
                             "-r", "__ns:=/wfs", "--params-file", str(pfile)],
                            stdout=log, stderr=subprocess.STDOUT)
    proc.log_path = log.name
    return proc


def feed(rig, proc, stop_after_s, frame):
    """Publish frames until the recorder has subscribed and then for ``stop_after_s``."""
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0 or proc.poll() is not None,
                    timeout=30)
    time.sleep(0.5)   # the writer sees the match before the reader does: let both settle
    sent, t_end, stamp = 0, time.monotonic() + stop_after_s, 1
    while time.monotonic() < t_end:
        rig.send(frame, stamp)
        stamp += 1
        sent += 1
        time.sleep(0.002)
    # a loaded machine can starve the recorder: make sure its reader has the frames (reliable
    # QoS acknowledges them) and give it a moment to take them, so the signal lands mid-recording
    from rclpy.duration import Duration
    assert rig.frame_pub.wait_for_all_acked(Duration(seconds=20))
    time.sleep(0.2)
    return sent


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize("after_s", [0.3, 1.1])
def test_signal_during_recording_gives_a_complete_bag(ros, tmp_path, sig, after_s):
    rig = Rig(ros)
    out = tmp_path / "sig.mcap"
    proc = start_recorder(tmp_path, out)
    frame = small_frame(SMALL, 0)
    sent = feed(rig, proc, after_s, frame)
    proc.send_signal(sig)
    assert proc.wait(timeout=30) in (0, -sig, 128 + sig), open(proc.log_path).read()
    reader = bags.BagReader(out)             # strict: refuses anything incomplete
    assert reader.complete
    stamps, images = reader.images("/wfs/frame")
    assert 0 < len(stamps) <= sent
    assert np.all(np.diff(stamps) > 0)
    np.testing.assert_array_equal(images[-1], frame)


def test_sigkill_leaves_complete_chunks_readable(ros, tmp_path):
    rig = Rig(ros)
    out = tmp_path / "killed.mcap"
    proc = start_recorder(tmp_path, out)
    frame = small_frame(SMALL, 1)
    sent = feed(rig, proc, 2.0, frame)
    proc.kill()
    proc.wait(timeout=10)
    with pytest.raises(bags.BagError, match="recover"):
        bags.BagReader(out)
    fixed = tmp_path / "fixed.mcap"
    stats = bags.recover(out, fixed)
    reader = bags.BagReader(fixed)
    stamps, images = reader.images("/wfs/frame") if "/wfs/frame" in reader.topics() else ([], [])
    assert stats["messages"] == sum(n for _t, n in reader.topics().values())
    assert len(stamps) <= sent
    for img in images:
        np.testing.assert_array_equal(img, frame)


def test_existing_output_is_never_overwritten(tmp_path):
    out = tmp_path / "exists.mcap"
    out.write_bytes(b"precious")
    proc = start_recorder(tmp_path, out)
    assert proc.wait(timeout=60) == 2
    assert "exists" in open(proc.log_path).read()
    assert out.read_bytes() == b"precious"


@pytest.mark.skipif(os.geteuid() != 0 or not os.path.exists("/bin/mount"), reason="needs root to mount a tmpfs")
def test_full_disk_is_reported_and_the_bag_stays_readable(ros, tmp_path):
    disk = tmp_path / "small"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)],
                             capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        rig = Rig(ros)
        out = disk / "full.mcap"
        # frames are 128 x 128 mono16 (32 kB): 1 MB fills after ~30 frames; small chunks
        proc = start_recorder(tmp_path, out, {"compression": "none", "chunk_kb": 128})
        frame = small_frame(SMALL, 2)
        feed(rig, proc, 3.0, frame)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
        log = open(proc.log_path).read()
        assert code == 1, log
        assert "No space left" in log or "full" in log.lower(), log
        with bags.BagReader(out, strict=False) as reader:
            stamps, images = reader.images("/wfs/frame")
        assert len(stamps) > 0
        for img in images:
            np.testing.assert_array_equal(img, frame)
    finally:
        if subprocess.run(["umount", str(disk)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(disk)], capture_output=True)   # still busy: detach


def test_nan_and_saturated_subapertures_flag_only_themselves(ros):
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode

    node = ros.add(CentroiderNode(context=ros.context))
    rig = Rig(ros)
    assert wait_for(lambda: node.sensor == SMALL, timeout=10)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0, timeout=10)
    lay = geometry.layout(SMALL)
    frame = small_frame(SMALL, 3).astype(np.float32)
    i, j = lay.index[0]
    frame[16 * i + 3, 16 * j + 4] = np.nan
    i, j = lay.index[1]
    frame[16 * i:16 * i + 16, 16 * j:16 * j + 16] = 0.0
    i, j = lay.index[2]
    frame[16 * i + 5, 16 * j:16 * j + 3] = np.inf
    rig.send(frame, 10, encoding="32FC1")
    rig.send(small_frame(SMALL, 4), 20)
    assert wait_for(lambda: 20 in rig.slopes, timeout=10)
    bad = geometry.grid_to_slopes(rig.slopes[10], lay)
    assert np.isnan(bad[:3]).all() and np.isfinite(bad[3:]).all()
    assert np.isfinite(geometry.grid_to_slopes(rig.slopes[20], lay)).all()


def test_out_of_range_and_wrong_type_parameters_are_refused(ros):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode

    node = ros.add(CentroiderNode(context=ros.context))
    before = {n: node.get_parameter(n).value for n in ("algorithm", "cmf.update_period",
                                                        "cmf.dither")}
    results = node.set_parameters([Parameter("cmf.update_period", value=0)])
    assert not results[0].successful
    results = node.set_parameters([Parameter("algorithm", value=5)])
    assert not results[0].successful
    results = node.set_parameters([Parameter("cmf.reference", value="yesterday")])
    assert not results[0].successful and "history" in results[0].reason
    results = node.set_parameters_atomically([Parameter("algorithm", value="cmf"),
                                              Parameter("cmf.dither", value=-1.0)])
    assert not results.successful and "dither" in results.reason
    after = {n: node.get_parameter(n).value for n in before}
    assert after == before and node.centroider.name == "cog"


def test_an_algorithm_fault_costs_one_frame_not_the_node(ros):
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode

    node = ros.add(CentroiderNode(context=ros.context))
    rig = Rig(ros)
    assert wait_for(lambda: node.sensor == SMALL, timeout=10)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0, timeout=10)
    real = node.centroider.centroid
    calls = []

    def flaky(frame):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("simulated onnxruntime failure")
        return real(frame)

    node.centroider.centroid = flaky
    rig.send(small_frame(SMALL, 5), 10)
    rig.send(small_frame(SMALL, 6), 20)
    assert wait_for(lambda: 20 in rig.slopes, timeout=10)
    assert 10 not in rig.slopes
    assert node.counters.rejected == 1 and "simulated" in node.counters.last_reason


def test_a_burst_of_full_frames_is_published_frame_by_frame(ros):
    """Full frames that queued up (a source that stalled, then caught up) are each published
    as soon as they are centroided, not after the whole burst; small frames of a burst are
    centroided in one call."""
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode

    node = ros.add(CentroiderNode(context=ros.context))
    events = []

    class Algorithm:
        name = "stub"

        def __init__(self, n):
            self.n = n

        def centroid(self, image):
            events.append("centroid")
            return np.zeros((self.n, 2))

        def centroid_many(self, images):
            events.append(f"centroid_many {len(images)}")
            return np.zeros((len(images), self.n, 2))

    class Publisher:
        def publish(self, cdr):
            events.append("publish")

    node._slopes_pub = Publisher()
    from lgs_wfs_ros.sensor import Sensor

    for sensor, want in ((SMALL, ["centroid", "publish"] * 3),                  # 128 x 128
                         (Sensor.paper_single("cartesian"), ["centroid_many 3"] + ["publish"] * 3)):
        events.clear()
        with node._lock:
            node.sensor, node.layout = sensor, geometry.layout(sensor)
            node.centroider = Algorithm(node.layout.n_valid)
        frames = [(k, np.zeros(sensor.frame_shape, np.uint16)) for k in (1, 2, 3)]
        node._centroid_and_publish(frames)
        assert events == want
