"""The centroider and recorder nodes on an isolated domain (in-process, one executor thread)."""

import json
import time

import numpy as np
import pytest

from conftest import set_param as conftest_set_param
from conftest import wait_for
from lgs_wfs_ros import bags
from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import spots

pytestmark = pytest.mark.ros

SMALL = Sensor(diameter_m=4.0, obstruction_m=0.5, n_subaps=8, frame_rate_hz=100.0)


def small_frame(sensor, seed, dtype=np.uint16):
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(seed)
    shift = rng.normal(0, 0.5, (lay.n_valid, 2))
    stack = spots(shift, photons=1000.0, e=lay.e, offsets=np.linspace(-2, 2, 9), rng=rng)
    return geometry.stack_to_frame(stack.astype(dtype), lay)


class Rig:
    """A frame/sensor publisher and a slopes/centroider listener around one node under test."""

    def __init__(self, ros, sensor=SMALL):
        from rclpy.node import Node
        from sensor_msgs.msg import Image
        from std_msgs.msg import String
        from lgs_wfs_ros.ros import qos

        self.node = ros.add(Node("rig", namespace="wfs", context=ros.context))
        self.frame_pub = self.node.create_publisher(Image, "/wfs/frame", qos.frame_qos(sensor))
        self.sensor_pub = self.node.create_publisher(String, "/wfs/sensor", qos.LATCHED)
        self.sensor_pub.publish(String(data=sensor.to_json(seed=0)))
        self.slopes, self.descriptions = {}, []
        self.node.create_subscription(Image, "/wfs/slopes", self._on_slopes, qos.SLOPES, raw=True)
        self.node.create_subscription(String, "/wfs/centroider",
                                      lambda m: self.descriptions.append(json.loads(m.data)),
                                      qos.LATCHED)

    def _on_slopes(self, cdr):
        stamp, _, enc, grid = bags.decode_image(cdr)
        self.slopes[stamp] = grid.copy()

    def send(self, frame, stamp_ns, encoding=None):
        self.frame_pub.publish(bags.encode_image(frame, stamp_ns, encoding=encoding))


@pytest.fixture
def centroider(ros):
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    node = ros.add(CentroiderNode(context=ros.context))
    rig = Rig(ros)
    assert wait_for(lambda: node.sensor == SMALL, timeout=10)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0, timeout=10)
    assert wait_for(lambda: rig.descriptions, timeout=10)
    return node, rig


def set_param(ros, name, value):
    return conftest_set_param(ros, "/wfs/centroider_node", name, value)


def test_slopes_match_the_library(centroider):
    node, rig = centroider
    lay = geometry.layout(SMALL)
    frames = [small_frame(SMALL, k) for k in range(5)]
    for k, f in enumerate(frames):
        rig.send(f, 1_000_000_000 + k * 10_000_000)
        time.sleep(0.02)
    assert wait_for(lambda: len(rig.slopes) == 5, timeout=10)
    cog = make_centroider("cog", SMALL)
    for k, f in enumerate(frames):
        grid = rig.slopes[1_000_000_000 + k * 10_000_000]
        assert grid.shape == (8, 8, 2) and np.isnan(grid[~lay.valid]).all()
        np.testing.assert_allclose(geometry.grid_to_slopes(grid, lay), cog.centroid(f), atol=1e-5)
    assert node.counters.processed == 5 and node.counters.dropped == 0


def test_switch_algorithm_at_run_time_and_refusals(centroider, ros):
    node, rig = centroider
    frame = small_frame(SMALL, 1)
    rig.send(frame, 10)
    assert wait_for(lambda: 10 in rig.slopes)

    result = set_param(ros, "algorithm", "wcog")
    assert result.successful
    assert wait_for(lambda: rig.descriptions[-1].get("algorithm") == "wcog")
    rig.send(frame, 20)
    assert wait_for(lambda: 20 in rig.slopes)
    lay = geometry.layout(SMALL)
    wcog = make_centroider("wcog", SMALL).centroid(frame)
    np.testing.assert_allclose(geometry.grid_to_slopes(rig.slopes[20], lay), wcog, atol=1e-5)
    assert not np.allclose(rig.slopes[10], rig.slopes[20], equal_nan=True)

    bad = set_param(ros, "algorithm", "bogus")
    assert not bad.successful and "bogus" in bad.reason
    # an option of an algorithm not in use is only checked for type, range and choices ...
    missing = set_param(ros, "ann.model", "/nonexistent/model.onnx")
    assert missing.successful
    # ... and refused, with the cause, when the algorithm is switched to
    refused = set_param(ros, "algorithm", "ann")
    assert not refused.successful and "/nonexistent/model.onnx" in refused.reason
    assert "not found" in refused.reason
    assert set_param(ros, "ann.model", "").successful
    assert node.get_parameter("algorithm").value == "wcog"
    rig.send(frame, 30)
    assert wait_for(lambda: 30 in rig.slopes)
    np.testing.assert_allclose(geometry.grid_to_slopes(rig.slopes[30], lay), wcog, atol=1e-5)


def test_bad_frames_are_counted_and_skipped(centroider):
    node, rig = centroider
    good = small_frame(SMALL, 2)
    rig.send(good[:-16], 100)                                   # wrong size
    rig.send(good.astype(np.float32)[..., None].repeat(2, -1), 200)   # 32FC2: wrong encoding
    rig.send(good, 300)
    rig.send(good, 300)                                          # repeated stamp
    rig.send(good, 250)                                          # out of order
    rig.send(good, 400)
    assert wait_for(lambda: 400 in rig.slopes, timeout=10)
    assert wait_for(lambda: node.counters.rejected == 4, timeout=5)
    assert node.counters.processed == 2
    assert sorted(rig.slopes) == [300, 400]


def test_recorder_writes_a_readable_bag(ros, tmp_path):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    from lgs_wfs_ros.ros.recorder_node import RecorderNode

    out = tmp_path / "rec.mcap"
    ros.add(CentroiderNode(context=ros.context))
    rig = Rig(ros)
    rec = ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(out)), Parameter("frames", value=6),
        Parameter("linger_s", value=1.0),
        Parameter("topics", value=["/wfs/frame", "/wfs/sensor", "/wfs/slopes", "/wfs/centroider"])]))
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() >= 2, timeout=10)
    time.sleep(0.5)
    frames = [small_frame(SMALL, k) for k in range(6)]
    for k, f in enumerate(frames):
        rig.send(f, 1000 + k)
        time.sleep(0.02)
    assert wait_for(lambda: rec.done, timeout=15)
    reader = bags.BagReader(out)
    topics = reader.topics()
    assert topics["/wfs/frame"][1] == 6 and topics["/wfs/slopes"][1] == 6
    assert topics["/wfs/sensor"][1] == 1
    stamps, images = reader.images("/wfs/frame")
    assert list(stamps) == [1000 + k for k in range(6)]
    np.testing.assert_array_equal(images[3], frames[3])


def test_recorder_lingers_until_every_frame_has_its_slopes(ros, tmp_path):
    """After the frame budget the recorder closes as soon as the slopes topic has a slope
    for each frame (not after the whole linger_s), and waits while one is missing."""
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.ros import qos
    from lgs_wfs_ros.ros.recorder_node import RecorderNode

    out = tmp_path / "rec.mcap"
    rig = Rig(ros)
    slopes_pub = rig.node.create_publisher(Image, "/cog/slopes", qos.SLOPES)
    rec = ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(out)), Parameter("frames", value=3),
        Parameter("linger_s", value=30.0), Parameter("discover", value=False),
        Parameter("topics", value=["/wfs/frame", "/wfs/sensor", "/cog/slopes"])]))
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() >= 1, timeout=10)
    assert wait_for(lambda: slopes_pub.get_subscription_count() >= 1, timeout=10)
    grid = np.zeros((SMALL.grid, SMALL.grid, 2), np.float32)
    for k in range(3):
        rig.send(small_frame(SMALL, k), 1000 + k)
        if k < 2:
            slopes_pub.publish(bags.encode_image(grid, 1000 + k))
    assert wait_for(lambda: rec.budget_reached, timeout=10)
    time.sleep(1.0)
    assert not rec.done                                # the last frame's slope is missing
    start = time.monotonic()
    slopes_pub.publish(bags.encode_image(grid, 1002))
    assert wait_for(lambda: rec.done, timeout=10)
    assert time.monotonic() - start < 5.0              # not the 30 s linger
    assert bags.BagReader(out).topics()["/cog/slopes"][1] == 3


def test_recorder_keeps_names_not_paths_of_descriptions(ros, tmp_path):
    """A centroider description naming a model by its absolute path is recorded with the
    file name only (bags carry names, not this machine's paths); other fields untouched."""
    from rclpy.parameter import Parameter
    from std_msgs.msg import String
    from lgs_wfs_ros.ros import qos
    from lgs_wfs_ros.ros.recorder_node import RecorderNode

    out = tmp_path / "rec.mcap"
    rig = Rig(ros)
    pub = rig.node.create_publisher(String, "/wfs/centroider", qos.LATCHED)
    desc = {"algorithm": "ann", "model_path": "/home/someone/work/models/ann_1k.onnx",
            "topic": "/wfs/frame"}
    pub.publish(String(data=json.dumps(desc)))
    rec = ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(out)), Parameter("frames", value=2),
        Parameter("linger_s", value=0.5),
        Parameter("topics", value=["/wfs/frame", "/wfs/sensor", "/wfs/centroider"])]))
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() >= 1, timeout=10)
    time.sleep(0.5)
    for k in range(2):
        rig.send(small_frame(SMALL, k), 1000 + k)
        time.sleep(0.02)
    assert wait_for(lambda: rec.done, timeout=15)
    texts = [t for _stamp, t in bags.BagReader(out).strings("/wfs/centroider")]
    assert texts, "the description was not recorded"
    recorded = json.loads(texts[-1])
    assert "/home/someone" not in texts[-1]
    assert recorded["algorithm"] == "ann" and recorded["topic"] == "/wfs/frame"
    assert "ann_1k.onnx" in json.dumps(recorded)


def test_recorder_sizes_its_frame_queue_for_the_sensor(ros, tmp_path):
    """A 6 kHz single-subaperture sensor: the recorder's frame subscription gets the
    2000-frame queue, and a burst of 500 frames sent back to back is recorded whole."""
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.recorder_node import RecorderNode

    fast = Sensor.paper_single("polar", frame_rate_hz=6000.0)
    out = tmp_path / "rec.mcap"
    rec = ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(out)), Parameter("frames", value=500),
        Parameter("linger_s", value=1.0), Parameter("topics", value=["/wfs/frame", "/wfs/sensor"])]))
    rig = Rig(ros, sensor=fast)
    assert wait_for(lambda: "/wfs" in rec.sensors, timeout=10)
    # the subscription is re-created just after the description is stored
    assert wait_for(lambda: rec._subs["/wfs/frame"].qos_profile.depth == 2000, timeout=10)
    # both the old queue (100) and the new one (2000) matched: frames sent while only the old
    # one is matched are at its depth's mercy (ci94 lost 21 of a burst that began so), which
    # is what the recorder had before it knew the sensor, not what this test is about
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() >= 2, timeout=10)
    frame = small_frame(fast, 1)
    for k in range(500):
        rig.send(frame, 1000 + k)
    assert wait_for(lambda: rec.done, timeout=30), (rec.frames_seen, rec.recorded, rec.gaps)
    assert not any(rec.gaps.values()), rec.gaps
    stamps, _ = bags.BagReader(out).images("/wfs/frame")
    assert list(stamps) == [1000 + k for k in range(500)]


def test_simulator_publishes_frames_truths_and_sensor(ros):
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from lgs_wfs_ros.ros import qos
    from lgs_wfs_ros.ros.simulator_node import SimulatorNode

    listener = ros.add(Node("listener", context=ros.context))
    got = {"frame": {}, "true_slopes": {}, "sensor": []}
    for kind in ("frame", "true_slopes"):
        listener.create_subscription(
            Image, f"/wfs/{kind}",
            lambda cdr, k=kind: got[k].__setitem__(bags.decode_image(cdr)[0], bags.decode_image(cdr)),
            qos.for_topic(kind), raw=True)
    listener.create_subscription(String, "/wfs/sensor", lambda m: got["sensor"].append(m.data),
                                 qos.LATCHED)
    overrides = [Parameter("diameter_m", value=4.0), Parameter("obstruction_m", value=0.5),
                 Parameter("n_subaps", value=8), Parameter("frames", value=5),
                 Parameter("turbulence", value=False), Parameter("profile", value="centred"),
                 Parameter("wait_for_subscribers", value=1), Parameter("rate_hz", value=50.0)]
    sim = ros.add(SimulatorNode(context=ros.context, parameter_overrides=overrides))
    assert wait_for(lambda: sim.finished.is_set(), timeout=60)
    assert wait_for(lambda: len(got["true_slopes"]) == 5, timeout=10)
    assert sorted(got["frame"]) == sorted(got["true_slopes"])
    stamps = sorted(got["frame"])
    assert np.all(np.diff(stamps) == round(1e9 / 700.0))
    _, frame_id, enc, frame = got["frame"][stamps[0]]
    assert frame_id == "wfs" and enc == "mono16" and frame.shape == (128, 128)
    _, _, enc, truth = got["true_slopes"][stamps[0]]
    assert enc == "32FC2" and truth.shape == (8, 8, 2)
    sensor = Sensor.from_json(got["sensor"][-1])
    assert sensor.n_subaps == 8 and sensor.diameter_m == 4.0
    lay = geometry.layout(sensor)
    assert np.isnan(truth[~lay.valid]).all()
    np.testing.assert_allclose(truth[lay.valid], 0.0)   # no turbulence: spots at the centre

    # an invalid change is refused with the reason and leaves the sensor as it was
    result = sim.set_parameters([Parameter("photons", value=-5.0)])[0]
    assert not result.successful and "photons" in result.reason
    result = sim.set_parameters([Parameter("detector", value="hexagonal")])[0]
    assert not result.successful and "detector" in result.reason
    assert sim.sim.sensor == sensor


def _play_through_centroider(ros, path, frames, ns, params=(), timeout=60):
    """Write ``frames`` ``{stamp: frame}`` (SMALL sensor, zero truth) to ``path``, play it at
    full rate through a centroider node in namespace ``ns`` (extra ``params``: Parameters),
    and return ``(node, player, {stamp: slopes grid})``."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.analysis.bagdata import ContractBagWriter
    from lgs_wfs_ros.ros import qos
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    from lgs_wfs_ros.ros.player_node import PlayerNode

    with ContractBagWriter(path, SMALL) as bag:
        for stamp, f in frames.items():
            bag.frame(stamp, f)
            bag.truth(stamp, np.zeros((geometry.layout(SMALL).n_valid, 2)))
    remap = ["--ros-args", "-r", "frame:=/wfs/frame", "-r", "sensor:=/wfs/sensor"]
    node = ros.add(CentroiderNode(context=ros.context, namespace=ns, cli_args=remap,
                                  parameter_overrides=list(params)))
    out = {}
    listener = ros.add(Node(f"listen_{ns}", context=ros.context))
    listener.create_subscription(Image, f"/{ns}/slopes",
                                 lambda cdr: out.__setitem__(*bags.decode_image(cdr)[::3]),
                                 qos.SLOPES, raw=True)
    player = ros.add(PlayerNode(context=ros.context, parameter_overrides=[
        Parameter("bag", value=str(path)), Parameter("rate", value="max"),
        Parameter("wait_for", value=[f"/{ns}/slopes"]), Parameter("start_delay_s", value=1.0)]))
    assert wait_for(lambda: player.finished.is_set(), timeout=timeout)
    assert wait_for(lambda: len(out) == len(frames), timeout=10)
    return node, player, out


def test_player_replays_a_bag_through_a_centroider(ros, tmp_path):
    frames = {1000 + 10 * k: small_frame(SMALL, 10 + k) for k in range(20)}
    cog, player, out = _play_through_centroider(ros, tmp_path / "in.mcap", frames, "cog")
    assert player.published["frame"] == 20 and player.published["sensor"] == 1
    assert cog.counters.processed == 20 and cog.counters.rejected == 0
    lib = make_centroider("cog", SMALL)
    lay = geometry.layout(SMALL)
    for stamp, f in frames.items():
        np.testing.assert_allclose(geometry.grid_to_slopes(out[stamp], lay), lib.centroid(f), atol=1e-5)


def test_default_cmf_live_through_refits_equals_its_replay(ros, tmp_path):
    """The centroider node running cmf's default (the grid of filters, pupil calibration
    refitted every 5 frames) on a played bag gives, frame for frame, what `lgs-wfs replay`
    gives for that bag with the same options."""
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.analysis import bagdata
    from lgs_wfs_ros.analysis.replay import replay_bag

    path = tmp_path / "in.mcap"
    stamps = [1000 + 10 * k for k in range(20)]
    frames = {stamp: small_frame(SMALL, 40 + k) for k, stamp in enumerate(stamps)}
    node, _, out = _play_through_centroider(
        ros, path, frames, "cmf", [Parameter("algorithm", value="cmf"),
                                   Parameter("cmf.pupil_period", value=5)], timeout=90)
    desc = node.centroider.describe()
    assert desc["options"]["filters"] == "grid" and desc["pupil_calibration"]["fits"] == 4
    res = replay_bag(path, ["cmf"], out=tmp_path / "r.mcap", quiet=True,
                     options={"cmf": {"pupil_period": 5}})
    assert res["options"]["cmf"]["source"] == "given"
    replayed = {sg.label: sg for sg in bagdata.load_bag(tmp_path / "r.mcap").segments}["cmf"]
    lay = geometry.layout(SMALL)
    live = np.stack([geometry.grid_to_slopes(out[s], lay) for s in stamps])
    np.testing.assert_allclose(live, replayed.slopes.data[:, lay.valid.ravel()], atol=1e-5)
    # the refits mattered: the table's default period (no refit in 20 frames) differs
    plain = make_centroider("cmf", SMALL)
    first = np.stack([plain.centroid(frames[s]) for s in stamps])
    assert np.abs(first - live).max() > 1e-3


def test_player_keeps_at_most_in_flight_frames_unanswered(ros, tmp_path):
    """rate 'max' with in_flight 3: three frames go out, then the player waits for the
    first one's answer; each answer lets exactly one more frame out."""
    import time
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.analysis.bagdata import ContractBagWriter
    from lgs_wfs_ros.ros import qos
    from lgs_wfs_ros.ros.player_node import PlayerNode

    path = tmp_path / "in.mcap"
    stamps = [1000 + 10 * k for k in range(10)]
    with ContractBagWriter(path, SMALL) as bag:
        for k, stamp in enumerate(stamps):
            bag.frame(stamp, small_frame(SMALL, k))
    answer = ros.add(Node("answer", context=ros.context))
    pub = answer.create_publisher(Image, "/fake/slopes", qos.SLOPES)
    player = ros.add(PlayerNode(context=ros.context, parameter_overrides=[
        Parameter("bag", value=str(path)), Parameter("rate", value="max"),
        Parameter("wait_for", value=["/fake/slopes"]), Parameter("in_flight", value=3),
        Parameter("wait_timeout_s", value=30.0), Parameter("start_delay_s", value=0.5)]))
    assert wait_for(lambda: player.published["frame"] == 3, timeout=10)
    time.sleep(1.0)
    assert player.published["frame"] == 3            # waits for the first frame's answer

    def reply(stamp):
        msg = Image()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        pub.publish(msg)

    assert wait_for(lambda: player.answers or reply(stamps[0]), timeout=10, interval=0.2)
    assert wait_for(lambda: player.published["frame"] == 4, timeout=10)
    time.sleep(0.5)
    assert player.published["frame"] == 4
    reply(stamps[2])                                  # answers up to the third frame: two more
    assert wait_for(lambda: player.published["frame"] == 6, timeout=10)
    time.sleep(0.5)
    assert player.published["frame"] == 6
    result = player.set_parameters([Parameter("in_flight", value=0)])[0]
    assert not result.successful
    player.stop()


def test_looped_player_reads_the_bag_into_memory_before_its_first_frame(ros, tmp_path):
    """With loop, a bag within cache_mb is read during the start delay (read while playing,
    the first pass went out late at 800 Hz); a bigger one streams every pass."""
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.analysis.bagdata import ContractBagWriter
    from lgs_wfs_ros.ros.player_node import PlayerNode

    path = tmp_path / "in.mcap"
    with ContractBagWriter(path, SMALL) as bag:
        for k in range(6):
            bag.frame(1000 + 10 * k, small_frame(SMALL, k))
    played = {}
    for cache_mb in (1, 0):
        player = ros.add(PlayerNode(context=ros.context, parameter_overrides=[
            Parameter("bag", value=str(path)), Parameter("rate", value="100"),
            Parameter("loop", value=True), Parameter("cache_mb", value=cache_mb),
            Parameter("start_delay_s", value=1.0)]))
        assert wait_for(lambda: player._cache is not None or cache_mb == 0, timeout=5)
        assert player.published["frame"] == 0          # still in the start delay
        if cache_mb:
            kinds = [kind for kind, _ in player._cache]
            assert kinds.count("frame") == 6 and kinds.count("sensor") == 1
        assert wait_for(lambda: player.published["frame"] >= 14, timeout=20)
        assert player._cache is None if cache_mb == 0 else player._cache is not None
        player.stop()
        played[cache_mb] = player.published["frame"]
    assert min(played.values()) >= 14


def test_frame_queue_holds_a_fixed_time():
    from lgs_wfs_ros.ros import qos
    assert qos.frame_depth(700.0, 1_843_264) == 100            # full pupil: 0.14 s
    assert qos.frame_depth(800.0, 1_843_264) == 109            # 192 MiB
    assert qos.frame_depth(6000.0, 600) == 2000                # paper's subaperture at 6 kHz
    assert qos.frame_depth(700.0, 600) == 700                  # ... at 700 Hz: one second
    assert qos.frame_depth(100.0, 600) == 100                  # never below 100 frames
    assert qos.frame_depth(1e6, 600) == 2000                   # nor above 2000
    assert qos.frame_depth(700.0, 4 * 1_843_264) == 27         # 192 MiB of payload at most
    assert qos.frame_qos(Sensor.paper_single("polar", frame_rate_hz=6000.0)).depth == 2000
    assert qos.frame_qos(None) is qos.FRAME


def test_centroider_sizes_its_frame_queue_for_the_sensor(ros):
    """A 6 kHz single-subaperture sensor arriving on the sensor topic re-creates the frame
    subscription with a 2000-frame queue; frames keep flowing through it."""
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    fast = Sensor.paper_single("polar", frame_rate_hz=6000.0)
    node = ros.add(CentroiderNode(context=ros.context))
    assert node._frame_sub.qos_profile.depth == 100             # the default sensor, 700 Hz
    rig = Rig(ros, sensor=fast)
    assert wait_for(lambda: node.sensor == fast, timeout=10)
    assert node._frame_sub.qos_profile.depth == 2000
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0, timeout=10)
    frame = small_frame(fast, 3)
    assert wait_for(lambda: rig.slopes or rig.send(frame, 10**9), timeout=10, interval=0.2)
    np.testing.assert_allclose(geometry.grid_to_slopes(next(iter(rig.slopes.values())), geometry.layout(fast)),
                               make_centroider("cog", fast).centroid(frame), atol=1e-5)


def test_player_refuses_a_bad_bag(ros, tmp_path):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.player_node import PlayerNode

    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a bag at all" * 10)
    with pytest.raises(bags.BagError):
        PlayerNode(context=ros.context, parameter_overrides=[Parameter("bag", value=str(junk))])


def test_frames_waiting_before_the_first_spin_all_get_slopes(ros):
    """A slow first start (the live demo lost 32 of 140 slopes so on a loaded CI host): the
    sensor description and 60 frames wait in the node's queues before it first spins. The
    sensor applies before those frames are judged by shape, the frame queue is re-sized for it
    without dropping what the old queue holds, and every frame, then and after, has slopes."""
    from rclpy.duration import Duration
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    single = Sensor.paper_single("polar")        # 700 Hz: a 700-frame queue, not the default 100
    node = CentroiderNode(context=ros.context)   # built, not spinning yet
    ros.nodes.append(node)                       # (destroyed with the harness)
    assert node._frame_sub.qos_profile.depth == 100
    rig = Rig(ros, sensor=single)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0
                    and rig.sensor_pub.get_subscription_count() > 0, timeout=10)
    assert rig.sensor_pub.wait_for_all_acked(Duration(seconds=10))
    stamps = [10**9 + k * 1_428_571 for k in range(120)]
    frames = [small_frame(single, k) for k in range(120)]
    for k in range(60):
        rig.send(frames[k], stamps[k])
    assert rig.frame_pub.wait_for_all_acked(Duration(seconds=10))   # in the node's queue
    ros.executor.add_node(node)
    assert wait_for(lambda: node.sensor == single, timeout=10)
    for k in range(60, 120):
        rig.send(frames[k], stamps[k])
        time.sleep(0.002)
    assert wait_for(lambda: len(rig.slopes) >= 120, timeout=20), (len(rig.slopes), node.counters.as_dict())
    assert sorted(rig.slopes) == stamps
    assert node._frame_sub.qos_profile.depth == 700
    c = node.counters
    assert (c.received, c.rejected, c.dropped, c.published) == (120, 0, 0, 120), c.as_dict()
    cog = make_centroider("cog", single)
    lay = geometry.layout(single)
    for k in (0, 59, 60, 119):
        np.testing.assert_allclose(geometry.grid_to_slopes(rig.slopes[stamps[k]], lay),
                                   cog.centroid(frames[k]), atol=1e-5)


def test_a_frame_queue_change_loses_and_repeats_no_frame(ros):
    """Make before break: frames only the old queue holds (sent before the new one matched)
    and frames both hold (sent after) are each centroided once when the sensor changes."""
    from rclpy.duration import Duration
    from std_msgs.msg import String
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    single = Sensor.paper_single("polar")
    node = CentroiderNode(context=ros.context)   # not spinning: the test orders the events
    ros.nodes.append(node)
    rig = Rig(ros, sensor=single)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() == 1, timeout=10)
    stamps = [10**9 + k * 1_428_571 for k in range(60)]
    frames = [small_frame(single, k) for k in range(60)]
    for k in range(30):                          # into the default sensor's queue only
        rig.send(frames[k], stamps[k])
    assert rig.frame_pub.wait_for_all_acked(Duration(seconds=10))
    node._on_sensor(String(data=single.to_json(seed=0)))      # the new queue, the old kept
    assert node._frame_sub.qos_profile.depth == 700 and node._handover is not None
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() == 2, timeout=10)
    for k in range(30, 60):                      # into both queues
        rig.send(frames[k], stamps[k])
    assert rig.frame_pub.wait_for_all_acked(Duration(seconds=10))
    ros.executor.add_node(node)
    assert wait_for(lambda: len(rig.slopes) >= 60, timeout=20), (len(rig.slopes), node.counters.as_dict())
    time.sleep(0.3)                              # no repeat comes later
    assert sorted(rig.slopes) == stamps and node._handover is None
    assert rig.frame_pub.get_subscription_count() == 1
    c = node.counters
    assert (c.received, c.rejected, c.dropped, c.published) == (60, 0, 0, 60), c.as_dict()


def test_recorder_frame_queue_change_loses_and_repeats_no_frame(ros, tmp_path):
    """The recorder's make before break: frames only its old queue holds and frames both
    queues hold are each written once, in order, when the sensor re-sizes the queue."""
    from rclpy.duration import Duration
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.bags.cdr import encode_string
    from lgs_wfs_ros.ros.recorder_node import RecorderNode
    single = Sensor.paper_single("polar")
    out = tmp_path / "rec.mcap"
    rec = RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(out)), Parameter("frames", value=60),
        Parameter("linger_s", value=0.5), Parameter("topics", value=["/wfs/frame"])])
    ros.nodes.append(rec)
    rig = Rig(ros, sensor=single)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() == 1, timeout=10)
    frame = small_frame(single, 1)
    for k in range(30):                          # into the default sensor's queue only
        rig.send(frame, 1000 + k)
    assert rig.frame_pub.wait_for_all_acked(Duration(seconds=10))
    rec._on_sensor("/wfs/sensor", encode_string(single.to_json(seed=0)))
    assert rec._subs["/wfs/frame"].qos_profile.depth == 700
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() == 2, timeout=10)
    for k in range(30, 60):                      # into both queues
        rig.send(frame, 1000 + k)
    assert rig.frame_pub.wait_for_all_acked(Duration(seconds=10))
    ros.executor.add_node(rec)
    assert wait_for(lambda: rec.done, timeout=30)
    stamps, _ = bags.BagReader(out).images("/wfs/frame")
    assert list(stamps) == [1000 + k for k in range(60)]
    assert rec.gaps == {} and rec.frames_seen == 60 and not rec._handovers
    assert rec._subs["/wfs/frame"].event_handlers == []      # replaceable (rclpy#1284)


def test_repeated_frame_queue_changes_keep_a_multithreaded_executor_spinning(ros):
    """rclpy's executors add a destroyed subscription's event handlers to their wait set
    (ros2/rclpy#1284) and a MultiThreadedExecutor's spin dies of it: the frame queues a node
    replaces have none, so sensor changes back and forth, each destroying a queue while
    frames flow, leave the executor spinning and the frames centroided."""
    from std_msgs.msg import String
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    fast = SMALL.replace(frame_rate_hz=6000.0)               # another queue depth, same frames
    node = ros.add(CentroiderNode(context=ros.context))
    rig = Rig(ros)
    assert wait_for(lambda: node.sensor == SMALL, timeout=10)
    assert node._frame_sub.event_handlers == []
    frame, stamp = small_frame(SMALL, 5), 10**9
    for k in range(40):
        sensor = fast if k % 2 == 0 else SMALL
        rig.sensor_pub.publish(String(data=sensor.to_json(seed=0)))
        assert wait_for(lambda: node.sensor == sensor, timeout=10)
        for _ in range(3):
            stamp += 1000
            rig.send(frame, stamp)
        assert wait_for(lambda: stamp in rig.slopes or not ros._thread.is_alive(), timeout=10)
        assert ros._thread.is_alive(), f"the executor died at change {k}"
    assert node._frame_sub.event_handlers == []


def test_a_centroider_notice_is_announced_once_each_time_it_changes(centroider):
    """A centroider's notice (a network's calibrated sky leaving its training profiles, set
    at a refit) is republished on the centroider topic once when it appears, not again while
    it stays, and once more when it clears."""
    node, rig = centroider
    real = node.centroider

    class Noticing:                       # the node's centroider, with a notice set here
        notice = ""

        def __getattr__(self, name):
            return getattr(real, name)

    fake = Noticing()
    with node._lock:
        node.centroider = fake
    frame = small_frame(SMALL, 0)

    def send_and_settle(stamps):
        for st in stamps:
            rig.send(frame, st)
        assert wait_for(lambda: all(st in rig.slopes for st in stamps), timeout=10)
        time.sleep(0.3)

    before = len(rig.descriptions)
    send_and_settle([1, 2])
    assert len(rig.descriptions) == before                   # no notice: nothing announced
    fake.notice = "sky outside the training profiles"
    send_and_settle([3, 4, 5])
    assert [d["reason"] for d in rig.descriptions[before:]] == ["notice"]
    fake.notice = ""
    send_and_settle([6, 7])
    assert [d["reason"] for d in rig.descriptions[before:]] == ["notice", "notice cleared"]


def test_a_frame_publisher_the_node_cannot_hear_is_warned_of_once(ros):
    """The frame queues have no incompatible-QoS handler (see above), so the centroider
    checks the frame publishers itself: a best-effort one (a camera driver's sensor-data
    QoS) is named once, with the reason."""
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    node = ros.add(CentroiderNode(context=ros.context))
    Rig(ros)                                                     # a reliable one: fine
    assert wait_for(lambda: node.sensor == SMALL, timeout=10)
    camera = ros.add(Node("camera", namespace="wfs", context=ros.context))
    camera.create_publisher(Image, "/wfs/frame", qos_profile_sensor_data)
    assert wait_for(lambda: node.incompatible_frame_publishers, timeout=10)
    time.sleep(1.5)                                              # checked again: not repeated
    assert node.incompatible_frame_publishers == {
        "/wfs/camera (it offers best effort, this node needs reliable)"}


def test_the_recorder_names_a_frame_publisher_it_cannot_hear(ros, tmp_path):
    """The recorder's frame queues have no incompatible-QoS handler either: a best-effort
    frame publisher is named once."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.ros.recorder_node import RecorderNode
    rec = ros.add(RecorderNode(context=ros.context, namespace="wfs", parameter_overrides=[
        Parameter("output", value=str(tmp_path / "rec.mcap")), Parameter("frames", value=5),
        Parameter("topics", value=["/wfs/frame"])]))
    camera = ros.add(Node("camera", namespace="wfs", context=ros.context))
    camera.create_publisher(Image, "/wfs/frame", qos_profile_sensor_data)
    assert wait_for(lambda: rec.incompatible_frame_publishers, timeout=10)
    time.sleep(1.5)
    assert rec.incompatible_frame_publishers == {
        "/wfs/camera (it offers best effort, this node needs reliable)"}


def test_frames_lost_to_a_slow_inline_refit_are_named_once(ros, monkeypatch):
    """A gap in the frame stamps right after an inline profile refit that held the frame
    path is logged once with its cause and cure (pupil_async), then counted; a gap without
    such a refit is only counted as dropped."""
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.centroiding.pupil import PupilCalibration
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode

    refit = PupilCalibration.refit
    monkeypatch.setattr(PupilCalibration, "refit", lambda self: (time.sleep(0.2), refit(self))[1])
    node = ros.add(CentroiderNode(context=ros.context, parameter_overrides=[
        Parameter("algorithm", value="cmf"), Parameter("cmf.pupil_period", value=3)]))
    rig = Rig(ros)
    assert wait_for(lambda: node.sensor == SMALL and node.centroider is not None, timeout=10)
    assert wait_for(lambda: rig.frame_pub.get_subscription_count() > 0, timeout=10)
    period = round(1e9 / SMALL.frame_rate_hz)
    condition = "frames dropped after an inline profile refit"
    for k in (0, 2, 3):                       # a gap before any refit; the third frame refits
        rig.send(small_frame(SMALL, k), 10**9 + k * period)
        assert wait_for(lambda: 10**9 + k * period in rig.slopes, timeout=20)
    assert node.centroider.pupil.fits == 1
    assert node.counters.dropped == 1 and condition not in node.health.counts
    rig.send(small_frame(SMALL, 5), 10**9 + 5 * period)        # frame 4 lost after the refit
    assert wait_for(lambda: 10**9 + 5 * period in rig.slopes, timeout=20)
    assert node.counters.dropped == 2 and node.health.counts[condition] == 1
