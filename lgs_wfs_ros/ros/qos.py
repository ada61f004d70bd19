"""QoS per topic of the contract (docs/conventions.md section 5).

What may drop and what may not:
- ``frame``: reliable, keep last 100 (0.14 s at 700 Hz). A subscriber stalled longer than that
  still loses frames (a reliable KEEP_LAST writer overwrites what the reader has not taken);
  the centroider counts the gaps by stamp. The depth absorbs scheduling stalls of a loaded
  2-core machine, which a depth of 10 (14 ms) did not.
- ``true_slopes`` and ``slopes``: reliable, keep last 1000: small (28.8 kB full pupil), so a
  deep history absorbs a slow recorder for ~1.4 s at 700 Hz.
- ``sensor`` and ``centroider``: reliable, keep last 1, transient local, so a late joiner (the
  recorder, a centroider started later) still gets the current description.
"""

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

FRAME = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                   reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
SLOPES = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

BY_NAME = {"frame": FRAME, "true_slopes": SLOPES, "slopes": SLOPES,
           "sensor": LATCHED, "centroider": LATCHED}
TYPES = {"frame": "sensor_msgs/msg/Image", "true_slopes": "sensor_msgs/msg/Image",
         "slopes": "sensor_msgs/msg/Image", "sensor": "std_msgs/msg/String",
         "centroider": "std_msgs/msg/String"}


def for_topic(topic: str) -> QoSProfile:
    """The contract's QoS for a topic name (its last component), FRAME if unknown."""
    return BY_NAME.get(topic.rstrip("/").rsplit("/", 1)[-1], FRAME)


def describe(qos: QoSProfile) -> dict:
    """A plain dict of a profile, for bags (offered_qos_profiles) and logs."""
    return {"history": qos.history.name.lower(), "depth": qos.depth,
            "reliability": qos.reliability.name.lower(),
            "durability": qos.durability.name.lower()}
