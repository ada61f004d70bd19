"""The node-test fixture: one message through rclpy on an isolated domain, then a clean shutdown."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from conftest import wait_for

pytestmark = pytest.mark.ros


def test_publish_and_receive_image(ros):
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    pub_node = ros.add(Node("harness_pub", context=ros.context))
    sub_node = ros.add(Node("harness_sub", context=ros.context))
    got = []
    sub_node.create_subscription(Image, "harness_frame", got.append, 10)
    pub = pub_node.create_publisher(Image, "harness_frame", 10)
    wait_for(lambda: pub.get_subscription_count() > 0, timeout=10)

    frame = np.arange(16 * 16, dtype=np.uint16).reshape(16, 16)
    msg = Image(height=16, width=16, encoding="mono16", step=32)
    msg.data = frame.tobytes()
    assert wait_for(lambda: (pub.publish(msg), bool(got))[1], timeout=10, interval=0.1)
    back = np.frombuffer(got[0].data, dtype=np.uint16).reshape(16, 16)
    np.testing.assert_array_equal(back, frame)


def test_domain_is_isolated():
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert 0 <= int(os.environ["ROS_DOMAIN_ID"]) <= 101


def test_clean_exit_in_a_subprocess(tmp_path):
    """A process that spins, tears down in order and exits must not abort ('terminate called')."""
    script = tmp_path / "run.py"
    script.write_text(textwrap.dedent("""
        import sys
        sys.path.insert(0, %r)
        from conftest import RosHarness
        from rclpy.node import Node
        from std_msgs.msg import String
        h = RosHarness()
        n = h.add(Node("exit_check", context=h.context))
        n.create_publisher(String, "exit_check", 1).publish(String(data="x"))
        h.shutdown()
        print("clean")
    """ % os.path.dirname(__file__)))
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "clean" in proc.stdout
    assert "terminate called" not in proc.stderr


def test_package_imports_without_ros():
    """The library must import with rclpy absent: only lgs_wfs_ros.ros imports it."""
    code = textwrap.dedent("""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split('.')[0] in ('rclpy', 'sensor_msgs', 'std_msgs'):
                    raise ImportError('blocked ' + name)
        sys.meta_path.insert(0, Block())
        import lgs_wfs_ros, lgs_wfs_ros.sensor, lgs_wfs_ros.optics.geometry
        import pkgutil, importlib
        for m in pkgutil.walk_packages(lgs_wfs_ros.__path__, 'lgs_wfs_ros.'):
            if m.name.startswith('lgs_wfs_ros.ros') or m.name.startswith('lgs_wfs_ros.learning'):
                continue
            importlib.import_module(m.name)
        print('ok')
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
