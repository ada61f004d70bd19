"""Process environment for the nodes: localhost-only discovery and the Fast DDS profile.

Both are defaults: a value already in the environment wins, so a user can open discovery to a
network (``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``) or bring their own DDS profile.
Call :func:`configure` before ``rclpy.init``.
"""

import os
from pathlib import Path

PROFILE = Path(__file__).resolve().parent.parent / "config" / "fastdds_profile.xml"


def configure(environ=os.environ) -> dict:
    """Set the defaults that are not already set; return what was set."""
    applied = {}
    defaults = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    if PROFILE.is_file():
        defaults["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(PROFILE)
    for key, value in defaults.items():
        if not environ.get(key):
            environ[key] = value
            applied[key] = value
    return applied
