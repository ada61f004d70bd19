"""The recorder's ``frame_subapertures``: blocks of chosen subapertures instead of full frames.

In ROS (isolated domain): simulator -> recorder and synthetic frames -> recorder give blocks
equal to ``frame_to_stack`` of the full frames recorded beside them, with the same stamps; bad
index lists are refused with the reason and the node keeps its setting; the bag decodes with
the ``mcap`` reader + mcap-ros2-support. Offline: the cutter, the reader, inspect, report and
replay on bags with subaperture frames and no full frames.
"""

import json
import time

import numpy as np
import pytest

from conftest import set_param as conftest_set_param
from conftest import wait_for
from lgs_wfs_ros import bags, cli
from lgs_wfs_ros.analysis import bagdata, report
from lgs_wfs_ros.analysis.inspect import bag_info, inspect_bag
from lgs_wfs_ros.analysis.replay import replay_bag
from lgs_wfs_ros.bags import BagError
from lgs_wfs_ros.bags import subapertures as subaps
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor

SMALL = Sensor(diameter_m=4.0, obstruction_m=0.5, n_subaps=8, frame_rate_hz=100.0, detector="polar")
T0 = 1_700_000_000_000_000_000
DT = 1_428_571


def rand_frame(sensor, seed, dtype=np.uint16):
    rng = np.random.default_rng(seed)
    if dtype == np.uint16:
        return rng.integers(0, 65535, sensor.frame_shape, dtype=np.uint16)
    return rng.normal(100, 10, sensor.frame_shape).astype(np.float32)


# -- offline ---------------------------------------------------------------------------------
@pytest.mark.parametrize("detector", ["cartesian", "polar"])
def test_cutter_equals_frame_to_stack_full_pupil(detector):
    sensor = Sensor(detector=detector)
    lay = geometry.layout(sensor)
    idx = np.random.default_rng(3).permutation(lay.n_valid)[: lay.n_valid // 100]   # 1 %, any order
    cutter = subaps.Cutter(sensor, idx.tolist())
    for dtype in (np.uint16, np.float32):
        frame = rand_frame(sensor, 1, dtype)
        want = geometry.frame_to_stack(frame, lay)[idx]
        np.testing.assert_array_equal(cutter.cut(frame), want)
        stamp, frame_id, enc, arr = bags.decode_image(cutter.message(bags.encode_image(frame, 77, "cam")))
        assert (stamp, frame_id, enc) == (77, "cam", "mono16" if dtype == np.uint16 else "32FC1")
        assert arr.shape == (len(idx) * 16, 16)
        np.testing.assert_array_equal(arr.reshape(-1, 16, 16), want)
    sel = cutter.selection("/wfs/frame")
    assert sel["indices"] == idx.tolist() and sel["ij"] == lay.index[idx].tolist()
    assert sel["topic"] == "/wfs/frame_subapertures" and sel["n_valid"] == lay.n_valid


@pytest.mark.parametrize("bad, words", [([1, 1], "appears 2 times"), ([-2], "negative"),
                                        ([0, 52], "out of range"), ([1.5], "integers"),
                                        (["3"], "integers"), ([True], "integers")])
def test_parse_indices_refuses_with_the_reason(bad, words):
    with pytest.raises(ValueError, match=words):
        subaps.parse_indices(bad, 52)
    assert subaps.parse_indices([], 52).shape == (0,)
    with pytest.raises(ValueError, match="out of range"):
        subaps.Cutter(SMALL, [geometry.layout(SMALL).n_valid])


def write_offline_bag(path, sensor, frames, selections, *, full=False, slopes=True):
    """frames (F, H, W); selections: list of (first frame, indices)."""
    lay = geometry.layout(sensor)
    truths = np.random.default_rng(0).normal(0, 0.3, (len(frames), lay.n_valid, 2))
    with bagdata.ContractBagWriter(path, sensor, log_ns=T0) as w:
        w.centroider("cog", {"algorithm": "cog"}, T0)
        for k, f in enumerate(frames):
            stamp = T0 + k * DT
            idx = [s for first, s in selections if first <= k][-1]
            if full:
                w.frame(stamp, f)
            w.frame_subapertures(stamp, f, idx)
            w.truth(stamp, truths[k])
            if slopes:
                w.slopes("cog", stamp, truths[k] + 0.1, stamp + 1000)
    return truths


def test_reader_segments_and_selection_changes(tmp_path):
    frames = np.stack([rand_frame(SMALL, k) for k in range(7)])
    lay = geometry.layout(SMALL)
    a, b = [3, 0, 40], [51, 7]
    path = tmp_path / "s.mcap"
    write_offline_bag(path, SMALL, frames, [(0, a), (4, b)])
    with pytest.raises(BagError, match="selection changed"):
        bags.read_subapertures(path)
    stamps, idx, blocks = bags.read_subapertures(path, selection=0)
    assert idx.tolist() == a and blocks.shape == (4, 3, 16, 16) and blocks.dtype == np.uint16
    np.testing.assert_array_equal(stamps, T0 + DT * np.arange(4))
    np.testing.assert_array_equal(blocks, geometry.frame_to_stack(frames[:4], lay)[:, a])
    stamps, idx, blocks = bags.read_subapertures(path, selection=-1)
    assert idx.tolist() == b
    np.testing.assert_array_equal(blocks, geometry.frame_to_stack(frames[4:], lay)[:, b])
    # a bag without the selection topic is refused with the reason
    bare = tmp_path / "bare.mcap"
    with bags.BagWriter(bare) as w:
        w.add_topic("/wfs/frame_subapertures", "sensor_msgs/msg/Image")
        w.write("/wfs/frame_subapertures", bags.encode_image(np.zeros((32, 16), np.uint16), T0), T0)
    with pytest.raises(BagError, match="no selection topic"):
        bags.read_subapertures(bare)


def test_inspect_report_and_replay_on_a_subapertures_only_bag(tmp_path, capsys):
    sensor = Sensor(diameter_m=4.0, obstruction_m=0.5, n_subaps=8, dtype="float32")
    frames = np.stack([rand_frame(sensor, k, np.float32) for k in range(5)])
    path = tmp_path / "sub.mcap"
    write_offline_bag(path, sensor, frames, [(0, [5, 9])])

    info = bag_info(path)
    assert info["subapertures"]["/wfs/frame_subapertures"][0]["indices"] == [5, 9]
    assert info["topics"]["/wfs/frame_subapertures"]["count"] == 5
    text = inspect_bag(path)
    assert "/wfs/frame_subapertures" in text and "2 of 52 valid subapertures: [5, 9]" in text
    assert "`lgs-wfs replay` needs full frames" in text and "no frame topic" not in text

    res = report.analyse(bagdata.load_bag(path, max_frames=10))
    assert res["frames"] == 0 and res["subaperture_frames"]["count"] == 5
    assert res["algorithms"]["cog"]["mean_euclid"] == pytest.approx(0.1 * np.sqrt(2), rel=1e-5)
    assert "cut to 2 chosen subapertures" in report.format_report(res)
    assert cli.main(["report", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["subaperture_frames"]["selections"] == [[5, 9]]

    with pytest.raises(BagError, match="replay needs full frames"):
        replay_bag(path, ["cog"], out=tmp_path / "r.mcap", quiet=True)
    assert not (tmp_path / "r.mcap").exists()
    assert cli.main(["replay", str(path), "--out", str(tmp_path / "r.mcap")]) == 2
    assert "full frames" in capsys.readouterr().err

    # with full frames beside the blocks, replay works on the full frames as before
    both = tmp_path / "both.mcap"
    write_offline_bag(both, sensor, frames, [(0, [5, 9])], full=True)
    assert replay_bag(both, ["cog"], out=tmp_path / "r2.mcap", quiet=True)["frames"] == 5


# -- ROS ------------------------------------------------------------------------------------
def make_recorder(ros, out, **params):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.recorder_node import RecorderNode
    overrides = [Parameter("output", value=str(out)), Parameter("discover", value=False),
                 Parameter("compression", value="none")]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    return ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=overrides))


def set_param(ros, name, value):
    return conftest_set_param(ros, "/wfs/recorder_node", name, value)


class FramePublisher:
    def __init__(self, ros, sensor):
        from rclpy.node import Node
        from sensor_msgs.msg import Image
        from std_msgs.msg import String
        from lgs_wfs_ros.ros import qos
        self.node = ros.add(Node("frames_rig", context=ros.context))
        self.pub = self.node.create_publisher(Image, "/wfs/frame", qos.FRAME)
        self.sensor_pub = self.node.create_publisher(String, "/wfs/sensor", qos.LATCHED)
        self.sensor_pub.publish(String(data=sensor.to_json(seed=0)))

    def send(self, frame, stamp):
        self.pub.publish(bags.encode_image(frame, stamp))


def _full_and_blocks(path, idx):
    with bags.BagReader(path) as r:
        fstamps, frames = r.images("/wfs/frame")
    stamps, got_idx, blocks = bags.read_subapertures(path)
    assert got_idx.tolist() == list(idx)
    return fstamps, frames, stamps, blocks


@pytest.mark.ros
def test_simulator_to_recorder_blocks_equal_the_frames(ros, tmp_path):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.simulator_node import SimulatorNode

    out = tmp_path / "sim.mcap"
    idx = [12, 0, 31]
    rec = make_recorder(ros, out, frames=5, linger_s=0.5, frame_subapertures=idx, full_frame_every=1,
                        topics=["/wfs/frame", "/wfs/sensor", "/wfs/true_slopes"])
    overrides = [Parameter("diameter_m", value=4.0), Parameter("obstruction_m", value=0.5),
                 Parameter("n_subaps", value=8), Parameter("frames", value=5),
                 Parameter("detector", value="polar"), Parameter("turbulence", value=False),
                 Parameter("profile", value="centred"), Parameter("wait_for_subscribers", value=1),
                 Parameter("start_delay_s", value=1.0), Parameter("rate_hz", value=50.0)]
    sim = ros.add(SimulatorNode(context=ros.context, parameter_overrides=overrides))
    assert wait_for(lambda: sim.finished.is_set(), timeout=90)
    assert wait_for(lambda: rec.done, timeout=60)
    assert rec.blocks_skipped == 0, rec.skip_reason
    fstamps, frames, stamps, blocks = _full_and_blocks(out, idx)
    assert len(fstamps) == 5
    np.testing.assert_array_equal(stamps, fstamps)
    with bags.BagReader(out) as r:
        sensor = Sensor.from_json(r.strings("/wfs/sensor")[-1][1])
    assert sensor.detector == "polar" and sensor.n_subaps == 8
    np.testing.assert_array_equal(blocks, geometry.frame_to_stack(frames, geometry.layout(sensor))[:, idx])
    assert blocks.sum() > 0


@pytest.mark.ros
def test_recorder_refuses_bad_indices_and_changes_at_run_time(ros, tmp_path):
    out = tmp_path / "rec.mcap"
    lay = geometry.layout(SMALL)
    rig = FramePublisher(ros, SMALL)
    rec = make_recorder(ros, out, frames=8, linger_s=0.5, frame_subapertures=[4, 2],
                        full_frame_every=1, topics=["/wfs/frame"])
    assert wait_for(lambda: "/wfs" in rec.sensors, timeout=20)      # subscribed to the sensor itself
    assert rec.sensors["/wfs"] == SMALL
    assert wait_for(lambda: rig.pub.get_subscription_count() >= 1, timeout=20)
    time.sleep(0.5)
    frames = [rand_frame(SMALL, k) for k in range(8)]
    for k in range(4):
        rig.send(frames[k], T0 + k * DT)
    assert wait_for(lambda: rec.frames_seen == 4, timeout=30)

    for bad, words in (([1, 1, 3], "appears 2 times"), ([lay.n_valid], "out of range"),
                       ([-1], "negative"), (["a"], "integers"), ("7", "integer array")):
        result = set_param(ros, "frame_subapertures", bad)
        assert not result.successful and words in result.reason, (bad, result.reason)
        assert "frame_subapertures" in result.reason
        assert rec.get_parameter("frame_subapertures").value == [4, 2]
        assert rec.selection.tolist() == [4, 2]
    assert set_param(ros, "frame_subapertures", [lay.n_valid - 1]).successful
    assert rec.selection.tolist() == [lay.n_valid - 1]
    for k in range(4, 8):
        rig.send(frames[k], T0 + k * DT)
    assert wait_for(lambda: rec.done, timeout=30)
    assert rec.blocks_skipped == 0, rec.skip_reason

    segs = subaps.subaperture_segments(out)
    assert [s.indices.tolist() for s in segs] == [[4, 2], [lay.n_valid - 1]]
    with bags.BagReader(out) as r:
        fstamps, full = r.images("/wfs/frame")
    np.testing.assert_array_equal(fstamps, T0 + DT * np.arange(8))
    stack = geometry.frame_to_stack(np.stack(frames), lay)
    np.testing.assert_array_equal(segs[0].stamps, fstamps[:4])
    np.testing.assert_array_equal(segs[0].blocks, stack[:4][:, [4, 2]])
    np.testing.assert_array_equal(segs[1].stamps, fstamps[4:])
    np.testing.assert_array_equal(segs[1].blocks, stack[4:][:, [lay.n_valid - 1]])

    # the bag opens with the mcap reader and every message decodes with mcap-ros2-support
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    seen = {}
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "/wfs/frame_subapertures":
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                k = int(np.searchsorted(fstamps, stamp))
                sel = [4, 2] if k < 4 else [lay.n_valid - 1]
                got = np.frombuffer(bytes(msg.data), np.uint16).reshape(msg.height // 16, 16, 16)
                assert msg.encoding == "mono16" and fstamps[k] == stamp
                np.testing.assert_array_equal(got, stack[k][sel])
            elif channel.topic == "/wfs/frame_subapertures_selection":
                assert json.loads(msg.data)["topic"] == "/wfs/frame_subapertures"
    assert seen == {"/wfs/frame": 8, "/wfs/sensor": 1, "/wfs/frame_subapertures": 8,
                    "/wfs/frame_subapertures_selection": 2}


@pytest.mark.ros
def test_recorder_blocks_instead_of_frames(ros, tmp_path):
    """frame_every 2 keeps frames 0, 2, 4: all as blocks, every 2nd of them (0, 4) also in full."""
    lay = geometry.layout(SMALL)
    rig = FramePublisher(ros, SMALL)
    out = tmp_path / "only.mcap"
    rec = make_recorder(ros, out, frames=6, linger_s=0.5, frame_every=2, full_frame_every=2,
                        frame_subapertures=[0, 1, 2], topics=["/wfs/frame", "/wfs/sensor"])
    assert wait_for(lambda: "/wfs" in rec.sensors and rig.pub.get_subscription_count() >= 1, timeout=20)
    time.sleep(0.5)
    frames = [rand_frame(SMALL, 100 + k) for k in range(6)]
    for k, f in enumerate(frames):
        rig.send(f, T0 + k * DT)
    assert wait_for(lambda: rec.done, timeout=30)
    with bags.BagReader(out) as r:
        topics = r.topics()
        fstamps, _ = r.images("/wfs/frame")
    stamps, idx, blocks = bags.read_subapertures(out)
    np.testing.assert_array_equal(stamps, T0 + DT * np.array([0, 2, 4]))     # frame_every 2
    np.testing.assert_array_equal(fstamps, T0 + DT * np.array([0, 4]))       # every 2nd kept frame
    assert topics["/wfs/frame"][1] == 2 and idx.tolist() == [0, 1, 2]
    np.testing.assert_array_equal(blocks, geometry.frame_to_stack(np.stack(frames[::2]), lay)[:, :3])


@pytest.mark.ros
def test_recorder_refuses_a_bad_start_value(ros, tmp_path):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.recorder_node import RecorderNode
    out = tmp_path / "x.mcap"
    with pytest.raises(ValueError, match="frame_subapertures: subaperture index 3 appears 2 times"):
        RecorderNode(context=ros.context, parameter_overrides=[
            Parameter("output", value=str(out)), Parameter("frame_subapertures", value=[3, 3])])
    assert not out.exists()


@pytest.mark.ros
def test_sensor_change_that_breaks_the_selection_skips_blocks_with_the_reason(ros, tmp_path):
    from std_msgs.msg import String
    out = tmp_path / "chg.mcap"
    rig = FramePublisher(ros, SMALL)
    last = geometry.layout(SMALL).n_valid - 1
    rec = make_recorder(ros, out, frames=4, linger_s=0.5, frame_subapertures=[last], topics=["/wfs/frame"])
    assert wait_for(lambda: rec.sensors.get("/wfs") == SMALL and rig.pub.get_subscription_count() >= 1,
                    timeout=20)
    time.sleep(0.5)
    rig.send(rand_frame(SMALL, 0), T0)
    assert wait_for(lambda: rec.frames_seen == 1, timeout=30)
    smaller = SMALL.replace(n_subaps=4, diameter_m=2.0)              # 12 valid subapertures
    rig.sensor_pub.publish(String(data=smaller.to_json()))
    assert wait_for(lambda: rec.sensors["/wfs"] == smaller, timeout=20)
    rig.send(rand_frame(smaller, 1), T0 + DT)
    assert wait_for(lambda: rec.blocks_skipped == 1, timeout=30)
    assert "do not fit" in rec.skip_reason and "out of range" in rec.skip_reason
    # a change is now checked against the new sensor
    n = geometry.layout(smaller).n_valid
    assert not set_param(ros, "frame_subapertures", [n]).successful
    assert set_param(ros, "frame_subapertures", [n - 1, 0]).successful
    frames = [rand_frame(smaller, k) for k in (2, 3)]
    for k, f in enumerate(frames):
        rig.send(f, T0 + (2 + k) * DT)
    assert wait_for(lambda: rec.done, timeout=30)
    segs = subaps.subaperture_segments(out)
    assert [s.indices.tolist() for s in segs] == [[last], [n - 1, 0]]
    assert segs[1].selection["n_valid"] == n and len(segs[0]) == 1
    np.testing.assert_array_equal(segs[1].blocks,
                                  geometry.frame_to_stack(np.stack(frames), geometry.layout(smaller))[:, [n - 1, 0]])
    # full_frame_every 0: the frame topic is in the bag with no message; replay refuses, inspect says so
    with bags.BagReader(out) as r:
        assert r.topics()["/wfs/frame"][1] == 0
    with pytest.raises(BagError, match="replay needs full frames"):
        replay_bag(out, ["cog"], out=tmp_path / "r.mcap", quiet=True)
    text = inspect_bag(out)
    assert "2 of 12 valid subapertures: [11, 0]" in text and "`lgs-wfs replay` needs full frames" in text
