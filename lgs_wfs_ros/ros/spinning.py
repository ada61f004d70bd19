"""Spinning a node until it is done or the process is asked to stop (SIGINT / SIGTERM)."""

import rclpy
from rclpy.executors import ExternalShutdownException


def spin_until(node, done, timeout_sec: float = 0.1) -> None:
    """Spin ``node`` until ``done()`` is true or the context shuts down.

    rclpy's signal handler shuts the context down on SIGINT and SIGTERM; a spin that was
    waiting then fails with an RCLError about an invalid context, which here just means stop.
    """
    while not done():
        try:
            rclpy.spin_once(node, timeout_sec=timeout_sec)
        except ExternalShutdownException:
            return
        except Exception:
            if not rclpy.ok(context=node.context):
                return
            raise
        if not rclpy.ok(context=node.context):
            return
