"""QoS per topic of the contract (docs/conventions.md section 5).

What may drop and what may not:
- ``frame``: reliable, keep last N, where N holds 0.14 s of frames at the sensor's rate, or a
  whole second when a second of frames is at most 16 MiB (at least 100, at most 2000 frames
  and 192 MiB of payload: :func:`frame_depth`; 100 for the full pupil at 700 Hz, 109 at
  800 Hz, 700 for the paper's single subaperture at 700 Hz, 2000 at 6 kHz).
  A subscriber stalled longer than that still loses frames (a reliable KEEP_LAST writer
  overwrites what the reader has not taken); the centroider counts the gaps by stamp. The depth absorbs scheduling
  stalls of a loaded 2-core machine: 10 frames did not at 700 Hz, and a fixed 100 (17 ms) lost
  0.3 % of the frames at 6 kHz where 1000 lost none, and 100 (0.14 s) lost 249 of 350 frames
  at 700 Hz in a full test run on a loaded machine, where a second of 600-byte frames costs
  420 kB.
- ``true_slopes`` and ``slopes``: reliable, keep last 1000: small (28.8 kB full pupil), so a
  deep history absorbs a slow recorder for ~1.4 s at 700 Hz.
- ``sensor`` and ``centroider``: reliable, keep last 1, transient local, so a late joiner (the
  recorder, a centroider started later) still gets the current description.
"""

import math

import numpy as np
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

FRAME_QUEUE_S = 0.14             # a frame queue holds this long at the frame rate,
SMALL_QUEUE_S = 1.0              # or this long when that much is at most
SMALL_QUEUE_BYTES = 16 * 2**20   # this many bytes (small frames: a single subaperture)
FRAME_DEPTH_MIN, FRAME_DEPTH_MAX = 100, 2000
FRAME_QUEUE_BYTES = 192 * 2**20  # and at most this much payload (100 full-pupil frames: 184 MB)

FRAME = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=FRAME_DEPTH_MIN,
                   reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
SLOPES = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

# the slopes picture: only the latest matters (reliable, so rviz's default subscription matches)
PICTURE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

BY_NAME = {"frame": FRAME, "true_slopes": SLOPES, "slopes": SLOPES,
           "sensor": LATCHED, "centroider": LATCHED}
TYPES = {"frame": "sensor_msgs/msg/Image", "true_slopes": "sensor_msgs/msg/Image",
         "slopes": "sensor_msgs/msg/Image", "sensor": "std_msgs/msg/String",
         "centroider": "std_msgs/msg/String"}


def frame_depth(rate_hz: float, frame_bytes: int) -> int:
    """Depth of a frame queue: 0.14 s of frames at ``rate_hz`` (1 s when a second of
    ``frame_bytes``-byte messages is at most 16 MiB), 100 to 2000 frames, at most 192 MiB
    (never below 10)."""
    small = SMALL_QUEUE_S * float(rate_hz) * int(frame_bytes) <= SMALL_QUEUE_BYTES
    seconds = SMALL_QUEUE_S if small else FRAME_QUEUE_S
    want = min(FRAME_DEPTH_MAX, max(FRAME_DEPTH_MIN, math.ceil(seconds * float(rate_hz) - 1e-9)))
    return int(max(10, min(want, FRAME_QUEUE_BYTES // max(int(frame_bytes), 1))))


def frame_qos(sensor=None) -> QoSProfile:
    """The ``frame`` QoS for a :class:`~lgs_wfs_ros.sensor.Sensor` (FRAME if None)."""
    if sensor is None:
        return FRAME
    rows, cols = sensor.frame_shape
    depth = frame_depth(sensor.frame_rate_hz, rows * cols * np.dtype(sensor.dtype).itemsize + 64)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def for_topic(topic: str) -> QoSProfile:
    """The contract's QoS for a topic name (its last component), FRAME if unknown."""
    return BY_NAME.get(topic.rstrip("/").rsplit("/", 1)[-1], FRAME)


def describe(qos: QoSProfile) -> dict:
    """A plain dict of a profile, for bags (offered_qos_profiles) and logs."""
    return {"history": qos.history.name.lower(), "depth": qos.depth,
            "reliability": qos.reliability.name.lower(),
            "durability": qos.durability.name.lower()}


def replaceable() -> SubscriptionEventCallbacks:
    """Event callbacks for a subscription that a node destroys while its executor spins (a
    re-sized frame queue, the truth while nobody plots): none. rclpy's executors (Jazzy) add
    every event handler they gathered to the wait set even when its destruction was requested
    meanwhile (ros2/rclpy#1284): that raises ``InvalidHandle`` and ends a
    MultiThreadedExecutor's spin (21 create/destroy cycles from another thread here; none in
    10,630 without handlers). The handler this drops is rclpy's incompatible-QoS warning:
    :func:`incompatible` gives it back."""
    return SubscriptionEventCallbacks(use_default_callbacks=False)


def new_incompatible(node, sub, warned: set) -> list[str]:
    """:func:`incompatible` publishers of subscription ``sub`` not yet in ``warned`` (added
    to it): what a node warns of, once each."""
    new = [who for who in incompatible(node, sub.topic_name, sub.qos_profile) if who not in warned]
    warned.update(new)
    return new


def incompatible(node, topic: str, profile: QoSProfile) -> list[str]:
    """``"namespace/node (why)"`` for each publisher of ``topic`` (a resolved name) that a
    subscription with ``profile`` cannot hear: best effort against reliable, volatile
    against transient local."""
    out = []
    for info in node.get_publishers_info_by_topic(topic):
        offered, why = info.qos_profile, []
        if (profile.reliability == ReliabilityPolicy.RELIABLE
                and offered.reliability == ReliabilityPolicy.BEST_EFFORT):
            why.append("it offers best effort, this node needs reliable")
        if (profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                and offered.durability == DurabilityPolicy.VOLATILE):
            why.append("it offers volatile, this node needs transient local")
        if why:
            out.append(f"{info.node_namespace.rstrip('/')}/{info.node_name} ({'; '.join(why)})")
    return out
