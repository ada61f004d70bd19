"""The transport ceiling: a node that takes ``frame`` messages raw and does nothing else.

Run as a process next to ``player_node`` (``bench_transport.py`` does): it subscribes to
``/wfs/frame`` with the contract's frame QoS, takes every queued message as raw CDR (the
centroider's own path, :func:`lgs_wfs_ros.ros.spinning.take_queued`), counts them and
prints ``sink counts {"received": N}`` when interrupted. Whatever rate it reaches is the most
any centroider can reach on this machine with rclpy and Fast DDS, before any compute.
"""

from __future__ import annotations

import json
import signal

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from sensor_msgs.msg import Image

from lgs_wfs_ros.ros import qos
from lgs_wfs_ros.ros.spinning import DRAIN, take_queued


def main() -> int:
    rclpy.init()
    node = rclpy.create_node("frame_sink")
    count = {"received": 0}

    def on_frame(_raw):
        count["received"] += 1 + sum(1 for _ in take_queued(sub, Image, DRAIN))

    sub = node.create_subscription(Image, "/wfs/frame", on_frame, qos.FRAME, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    signal.signal(signal.SIGINT, lambda *_: rclpy.try_shutdown())
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        print("sink counts", json.dumps(count), flush=True)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
