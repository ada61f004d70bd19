"""frame_transport 'shm' in the nodes: simulator and player send frames through shared memory,
the centroider reads them in place; slopes join truths by stamp exactly as with 'ros', the ROS
frame topic keeps a decimated copy, and the counters account for every frame."""

import time

import numpy as np
import pytest

from conftest import wait_for
from lgs_wfs_ros import bags
from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from lgs_wfs_ros.transport import shm

pytestmark = pytest.mark.skipif(not shm.AVAILABLE, reason="iceoryx2 not installed ('shm' extra)")

REMAP = ["--ros-args", "-r", "frame:=/wfs/frame", "-r", "sensor:=/wfs/sensor"]
SMALL = dict(diameter_m=4.0, obstruction_m=0.5, n_subaps=8)


def _listen(ros, topics):
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.ros import qos
    got = {t: {} for t in topics}
    arrived = {t: [] for t in topics}           # monotonic arrival times, s

    def take(cdr, t):
        got[t].__setitem__(*bags.decode_image(cdr)[::3])
        arrived[t].append(time.monotonic())
    node = ros.add(Node("listener", context=ros.context))
    for t in topics:
        node.create_subscription(Image, t, lambda cdr, t=t: take(cdr, t),
                                 qos.for_topic(t) if not t.endswith("frame") else qos.FRAME,
                                 raw=True)
    got["_arrived"] = arrived
    return got


@pytest.mark.parametrize("publish_hz", [1e5, 10.0])
def test_simulator_to_centroider_through_shared_memory(ros, publish_hz):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    from lgs_wfs_ros.ros.simulator_node import SimulatorNode

    n = 40
    got = _listen(ros, ["/cog/slopes", "/wfs/true_slopes", "/wfs/frame"])
    arrived = got.pop("_arrived")
    cog = ros.add(CentroiderNode(context=ros.context, namespace="cog", cli_args=REMAP,
                                 parameter_overrides=[Parameter("frame_transport", value="shm")]))
    overrides = [Parameter(k, value=v) for k, v in SMALL.items()] + [
        Parameter("frames", value=n), Parameter("rate_hz", value=100.0),
        Parameter("wait_for_subscribers", value=1), Parameter("start_delay_s", value=1.0),
        Parameter("frame_transport", value="shm"), Parameter("frame_lockstep", value=True),
        Parameter("frame_publish_hz", value=publish_hz)]
    sim = ros.add(SimulatorNode(context=ros.context, parameter_overrides=overrides))
    assert wait_for(lambda: sim.finished.is_set(), timeout=60)
    assert wait_for(lambda: len(got["/cog/slopes"]) == n and len(got["/wfs/true_slopes"]) == n,
                    timeout=20)
    assert sorted(got["/cog/slopes"]) == sorted(got["/wfs/true_slopes"])   # joined by stamp
    c = cog.counters.as_dict()
    assert (c["taken"], c["computed"], c["published"]) == (n, n, n)
    assert c["dropped"] == c["rejected"] == c["transport_lost"] == 0
    assert sim._outlet.counters()["undelivered"] == 0
    frames = got["/wfs/frame"]
    sensor = sim.sim.sensor
    if publish_hz >= 100:       # every frame also on ROS: the slopes are the library's
        assert wait_for(lambda: len(frames) == n, timeout=10), (len(frames), sim._outlet.counters())
        lib, lay = make_centroider("cog", sensor), geometry.layout(sensor)
        for stamp, frame in frames.items():
            np.testing.assert_allclose(geometry.grid_to_slopes(got["/cog/slopes"][stamp], lay),
                                       lib.centroid(frame), atol=1e-5)
    else:                       # ~0.4 s of frames at 10 Hz on ROS: about 5, not 40
        # the decimation runs on the wall clock, and a loaded machine stretches the 0.4 s
        # (8 frames were seen in a full run): bound it by the span the truths arrived over
        span = max(arrived["/wfs/true_slopes"]) - min(arrived["/wfs/true_slopes"])
        assert 2 <= len(frames) <= 10.0 * span + 2 and len(frames) < n, (len(frames), span)
        assert set(frames) <= set(got["/wfs/true_slopes"])


def test_player_through_shared_memory(ros, tmp_path):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.analysis.bagdata import ContractBagWriter
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    from lgs_wfs_ros.ros.player_node import PlayerNode

    sensor = Sensor(**SMALL)
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(3)
    frames = {1000 + 10 * k: rng.poisson(50, sensor.frame_shape).astype(np.uint16)
              for k in range(25)}
    path = tmp_path / "in.mcap"
    with ContractBagWriter(path, sensor) as bag:
        for stamp, f in frames.items():
            bag.frame(stamp, f)
            bag.truth(stamp, np.zeros((lay.n_valid, 2)))
    got = _listen(ros, ["/cog/slopes"])
    cog = ros.add(CentroiderNode(context=ros.context, namespace="cog", cli_args=REMAP,
                                 parameter_overrides=[Parameter("frame_transport", value="shm")]))
    player = ros.add(PlayerNode(context=ros.context, parameter_overrides=[
        Parameter("bag", value=str(path)), Parameter("rate", value="500"),
        Parameter("frame_transport", value="shm"), Parameter("frame_lockstep", value=True),
        Parameter("start_delay_s", value=1.0)]))
    assert wait_for(lambda: player.finished.is_set(), timeout=60)
    assert wait_for(lambda: len(got["/cog/slopes"]) == 25, timeout=10)
    lib = make_centroider("cog", sensor)
    for stamp, f in frames.items():
        np.testing.assert_allclose(geometry.grid_to_slopes(got["/cog/slopes"][stamp], lay),
                                   lib.centroid(f), atol=1e-5)
    assert cog.counters.transport_lost == 0 and cog.counters.rejected == 0


def _shm_graph(ros, out, n, recorder, source):
    """recorder (``/wfs``, the listed topics plus ``recorder`` parameters), a cog centroider
    (``/cog``) and a simulator of ``n`` small frames at 100 Hz in lockstep over shared
    memory (plus ``source`` parameters): ``(recorder, centroider, simulator)``."""
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    from lgs_wfs_ros.ros.recorder_node import RecorderNode
    from lgs_wfs_ros.ros.simulator_node import SimulatorNode

    rec = ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(out)), Parameter("discover", value=False)] + [
        Parameter(k, value=v) for k, v in recorder.items()]))
    cog = ros.add(CentroiderNode(context=ros.context, namespace="cog", cli_args=REMAP,
                                 parameter_overrides=[Parameter("frame_transport", value="shm")]))
    sim = ros.add(SimulatorNode(context=ros.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in {**SMALL, "frames": n, "rate_hz": 100.0,
                                           "start_delay_s": 1.5, "frame_transport": "shm",
                                           "frame_lockstep": True, **source}.items()]))
    return rec, cog, sim


def test_a_bag_recorded_from_the_shm_path_joins_as_today(ros, tmp_path):
    """simulator --shm--> centroider, recorder on the ROS topics: the bag loads with the
    analysis reader, every slope joins its truth by stamp, and the decimated frames are
    frames of the run (their stamps among the truths')."""
    from lgs_wfs_ros.analysis.bagdata import joined, load_bag

    out, n = tmp_path / "shm.mcap", 60
    rec, cog, sim = _shm_graph(ros, out, n, {"topics": [
        "/wfs/frame", "/wfs/true_slopes", "/wfs/sensor", "/cog/slopes", "/cog/centroider"]},
        {"wait_for_subscribers": 1, "frame_publish_hz": 20.0})
    assert wait_for(lambda: sim.finished.is_set(), timeout=60)
    assert wait_for(lambda: cog.counters.published == n, timeout=20)
    assert wait_for(lambda: rec.recorded.get("/cog/slopes", 0) == n, timeout=20)
    rec.close()
    data = load_bag(out, max_frames=None)
    assert len(data.truth) == n and len(data.segments) == 1
    stamps, est, truth, join = joined(data.truth, data.segments[0].slopes)
    assert len(stamps) == n and np.isfinite(est).any()
    # 20 Hz of wall time over a run of 60 frames at 100 Hz: ~12 (lockstep under load makes
    # the run longer: 21 seen once; a loaded CI host gave 5), far fewer than the 60 sent.
    # How many depends on wall time, which a test must not assert: some, and decimated
    assert 1 <= data.frame_count < n // 2
    assert set(data.frames.stamps) <= set(data.truth.stamps)
    assert data.frames.data.shape[1:] == sim.sim.sensor.frame_shape


def test_the_recorder_records_frames_from_shared_memory(ros, tmp_path):
    """recorder with frame_transport shm: frames from the source's shared memory (no ROS
    copy of the frame at all: frame_publish_hz 0), every 5th kept, each the frame sent with
    that stamp; slopes and truths from ROS as before."""
    from lgs_wfs_ros.analysis.bagdata import load_bag

    out, n, every = tmp_path / "shm_frames.mcap", 40, 5
    rec, cog, sim = _shm_graph(ros, out, n, {
        "frame_transport": "shm", "frame_every": every,
        "topics": ["/wfs/frame", "/wfs/true_slopes", "/wfs/sensor", "/cog/slopes"]},
        {"wait_for_subscribers": 2, "frame_publish_hz": 0.0})
    sent = {}
    real_send = sim._outlet.send

    def send(buf, stamp_ns, sensor_id=0):            # what went out, before the loan goes
        sent[stamp_ns] = buf.image.copy()
        return real_send(buf, stamp_ns, sensor_id)

    sim._outlet.send = send
    assert wait_for(lambda: sim.finished.is_set(), timeout=60)
    assert wait_for(lambda: rec.frames_seen == n, timeout=20)
    assert wait_for(lambda: rec.recorded.get("/cog/slopes", 0) == n, timeout=20)
    assert sim._outlet.ros_published == 0
    rec.close()
    data = load_bag(out, max_frames=None)
    order = sorted(sent)
    assert list(data.frames.stamps) == order[::every]                 # 1st, 6th, ... frame
    for stamp, frame in zip(data.frames.stamps, data.frames.data):
        np.testing.assert_array_equal(frame, sent[stamp])
    assert len(data.truth) == n and rec.gaps == {}
    assert cog.counters.published == n
