"""Health and pictures in ROS's terms: /diagnostics, the slopes picture, the error series,
conditions logged once then counted, the true cause of a missing centroider."""

import time

import numpy as np
import pytest

from conftest import wait_for
from lgs_wfs_ros import bags
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.ros import picture
from test_nodes import SMALL, Rig, small_frame

pytestmark = pytest.mark.ros


def test_picture_colours_and_layout():
    grid = np.full((3, 3, 2), np.nan, dtype=np.float32)
    grid[0, 0] = (2.0, -2.0)       # beyond the range: clipped to full colour
    grid[1, 1] = (0.0, 0.5)
    pic = picture.slopes_picture(grid, range_px=1.0, cell=2)
    assert pic.shape == (6, 14, 3) and pic.dtype == np.uint8
    x_map, band, y_map = pic[:, :6], pic[:, 6:8], pic[:, 8:]
    assert (band == 0).all()
    np.testing.assert_array_equal(x_map[0, 0], picture.POSITIVE)
    np.testing.assert_array_equal(y_map[0, 0], picture.NEGATIVE)
    np.testing.assert_array_equal(x_map[2, 2], picture.ZERO)
    np.testing.assert_array_equal(y_map[2, 2], np.rint((picture.ZERO + picture.POSITIVE) / 2))
    np.testing.assert_array_equal(x_map[5, 5], picture.INVALID)        # NaN: not valid
    assert (x_map[:2, :2] == x_map[0, 0]).all()                        # one cell per subaperture


class FakeNode:
    """Just what Health uses, with a logger that records its calls."""

    def __init__(self):
        self.lines = []
        log = self

        class Logger:
            def info(self, m): log.lines.append(("info", m))
            def warning(self, m): log.lines.append(("warn", m))
            def error(self, m): log.lines.append(("error", m))
        self.logger = Logger()

    def get_logger(self):
        return self.logger

    def create_publisher(self, *a):
        return None

    def create_timer(self, *a):
        return None


def test_a_condition_is_logged_once_then_counted():
    from lgs_wfs_ros.ros.health import Health, WARN
    node = FakeNode()
    h = Health(node, period_s=0)
    for k in range(5):
        h.note("frames before the sensor description", f"frame {k}", WARN)
    h.note("another condition")
    assert h.counts == {"frames before the sensor description": 5, "another condition": 1}
    assert [lvl for lvl, _ in node.lines] == ["warn", "warn"]
    assert "frame 0" in node.lines[0][1] and "5" in h.summary()


def listen(ros, name, topics):
    """{topic: [messages]} of a listener node."""
    from rclpy.node import Node
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Vector3Stamped
    from sensor_msgs.msg import Image
    types = {"slopes_picture": Image, "slope_error": Vector3Stamped, "diagnostics": DiagnosticArray}
    node = ros.add(Node(name, context=ros.context))
    got = {t: [] for t in topics}
    for t in topics:
        node.create_subscription(types[t.rsplit("/", 1)[-1]], t, got[t].append, 10)
    return got


def test_centroider_picture_error_and_diagnostics(ros):
    from sensor_msgs.msg import Image
    from lgs_wfs_ros.ros import qos
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode

    node = ros.add(CentroiderNode(context=ros.context))
    rig = Rig(ros)
    truth_pub = rig.node.create_publisher(Image, "/wfs/true_slopes", qos.SLOPES)
    got = listen(ros, "health_listener", ["/wfs/slopes_picture", "/wfs/slope_error", "/diagnostics"])
    assert wait_for(lambda: node.sensor == SMALL and rig.frame_pub.get_subscription_count(), 10)
    assert wait_for(lambda: node._truth_sub is not None, timeout=10)   # follows subscribers
    assert wait_for(lambda: truth_pub.get_subscription_count(), timeout=10)
    lay = geometry.layout(SMALL)
    truth = np.zeros((lay.n_valid, 2))
    for k in range(3):
        stamp = 10**9 + k * 10**7
        rig.send(small_frame(SMALL, k), stamp)
        assert wait_for(lambda: stamp in rig.slopes, timeout=10)
        truth_pub.publish(bags.encode_image(geometry.slopes_to_grid(truth, lay), stamp))
        time.sleep(0.15)
    assert wait_for(lambda: got["/wfs/slopes_picture"] and got["/wfs/slope_error"], timeout=10)

    pic = got["/wfs/slopes_picture"][-1]
    stamp = pic.header.stamp.sec * 10**9 + pic.header.stamp.nanosec
    want = picture.slopes_picture(rig.slopes[stamp], node.get_parameter("picture_range_px").value)
    assert pic.encoding == "rgb8" and (pic.height, pic.width) == want.shape[:2]
    np.testing.assert_array_equal(np.frombuffer(bytes(pic.data), np.uint8).reshape(want.shape), want)

    err = got["/wfs/slope_error"][-1]
    stamp = err.header.stamp.sec * 10**9 + err.header.stamp.nanosec
    s = geometry.grid_to_slopes(rig.slopes[stamp], lay)              # truth is 0
    np.testing.assert_allclose([err.vector.x, err.vector.y],
                               np.sqrt(np.mean(s ** 2, axis=0)), rtol=1e-5)
    np.testing.assert_allclose(err.vector.z, np.hypot(err.vector.x, err.vector.y), rtol=1e-6)

    def mine():
        return [st for m in got["/diagnostics"] for st in m.status
                if st.name == "/wfs/centroider_node"
                and {kv.key: kv.value for kv in st.values}.get("processed") == "3"]
    assert wait_for(mine, timeout=10)
    status = mine()[-1]
    assert status.level == b"\x00" and status.message == "running"


def test_a_missing_model_is_named_with_the_paths_searched(ros):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    node = ros.add(CentroiderNode(context=ros.context, namespace="nomodel", parameter_overrides=[
        Parameter("algorithm", value="ann"), Parameter("ann.model", value="no_such_model")]))
    assert node.centroider is None
    assert node.health.level == b"\x02"
    assert "model missing" in node.health.message and "searched" in node.health.message
    assert "no_such_model" in node.health.message and "waiting" not in node.health.message
    # a sensor arriving does not hide the cause
    from rclpy.node import Node
    from std_msgs.msg import String
    from lgs_wfs_ros.ros import qos
    pub = ros.add(Node("nomodel_sensor", context=ros.context)).create_publisher(
        String, "/nomodel/sensor", qos.LATCHED)
    pub.publish(String(data=SMALL.to_json(seed=0)))
    assert wait_for(lambda: node._sensor_received, timeout=10)
    assert node.centroider is None and "model missing" in node.health.message


def test_foxglove_layout_opens_what_the_demo_graph_publishes(ros):
    """Every topic the layout shows is the simulator's frame or a topic each centroider of
    launch/demo.launch.py publishes under its namespace."""
    import json
    import re
    from pathlib import Path
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    root = Path(__file__).resolve().parents[1]
    layout = json.loads((root / "config" / "foxglove_layout.json").read_text())
    text = json.dumps(layout["configById"])
    topics = set(re.findall(r'"(/[a-z_/]+?)(?:\.[a-z.]+)?"', text))
    algorithms = re.search(r"ALGORITHMS = \(([^)]*)\)", (root / "launch" / "demo.launch.py").read_text())
    algorithms = re.findall(r'"(\w+)"', algorithms.group(1))
    node = ros.add(CentroiderNode(context=ros.context, namespace="layout"))
    published = {p.topic_name.rsplit("/", 1)[-1] for p in node.publishers}
    assert {"slopes_picture", "slope_error"} <= published
    shown = {"slopes_picture", "slope_error"}
    expect = {"/wfs/frame", "/diagnostics"} | {f"/{a}/{t}" for a in algorithms for t in shown}
    assert topics == expect
    # every panel of the configuration is placed in the layout tree
    assert set(layout["configById"]) == set(re.findall(r'"(\w+![\w]+)"', json.dumps(layout["layout"])))
