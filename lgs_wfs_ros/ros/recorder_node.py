"""recorder_node: every contract topic to an MCAP bag in rosbag2's layout.

Raw subscriptions (``raw=True``): the serialized CDR goes to the file as it came, with log time =
receive time and publish time = source time. Topics come from the ``topics`` parameter and, with
``discover`` on, from the graph: any topic whose last name is a contract name (frame,
true_slopes, slopes, sensor, centroider) with the contract's type. Frames can be decimated
(``frame_every``) since full frames at 700 Hz are more than one Python process can write here.

The bag is closed (summary and index written) on SIGINT, SIGTERM, at the ``frames`` budget, or
when the disk fills up (reported; what was written stays readable).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from .. import bags
from .spinning import DRAIN, run_node, take_queued
from . import parameters, qos

MSG_CLASSES = {"sensor_msgs/msg/Image": Image, "std_msgs/msg/String": String}
DEFAULT_TOPICS = ["/wfs/frame", "/wfs/true_slopes", "/wfs/sensor"]




def default_output() -> str:
    return str(Path("bags") / time.strftime("lgs_wfs_%Y%m%d_%H%M%S.mcap"))


class RecorderNode(Node):
    def __init__(self, **kwargs):
        super().__init__("recorder_node", **kwargs)
        parameters.declare(self, "output", default_output(), "Path of the MCAP bag to write.",
                           read_only=True)
        parameters.declare(self, "overwrite", False, "Replace an existing output file.",
                           read_only=True)
        parameters.declare(self, "topics", DEFAULT_TOPICS, "Topics to record (absolute names).",
                           read_only=True)
        parameters.declare(self, "discover", True, "Also record contract topics found in the "
                           "graph (checked every second).")
        parameters.declare(self, "frame_every", 1, "Record every Nth frame (0: no frames; "
                           "slopes and truths are always kept at full rate).", low=0, high=1000000)
        parameters.declare(self, "frames", 0, "Stop after this many frames received "
                           "(0: record until interrupted).", low=0, high=2**31 - 1)
        parameters.declare(self, "linger_s", 1.0, "After the frame budget, keep recording this "
                           "long so slopes of the last frames arrive.", low=0.0, high=60.0)
        parameters.declare(self, "chunk_kb", 4096, "MCAP chunk size, kB: a crash or a full disk "
                           "loses at most the open chunk.", low=16, high=1 << 20, read_only=True)
        parameters.declare(self, "compression", "zstd", "Chunk compression.",
                           choices=("zstd", "lz4", "none"), read_only=True)
        self.add_on_set_parameters_callback(self._validate)

        p = parameters.values(self, ("output", "overwrite", "compression", "chunk_kb"))
        out = Path(p["output"])
        out.parent.mkdir(parents=True, exist_ok=True)
        self.path = out
        self.writer = bags.BagWriter(out, overwrite=p["overwrite"], chunk_size=p["chunk_kb"] * 1024,
                                     compression=None if p["compression"] == "none" else p["compression"])
        self.recorded: dict[str, int] = {}
        self.frames_seen = 0
        self.failed = ""
        self.done = False        # the bag is closed
        self.closing = False     # no more writes
        self._close_lock = threading.Lock()
        self.budget_reached = False
        self._linger_timer = None
        self._subs = {}
        for topic in self.get_parameter("topics").value:
            self._subscribe(topic, qos.TYPES.get(topic.rsplit("/", 1)[-1]))
        self._discover_timer = self.create_timer(1.0, self._discover)
        self._discover()
        self.get_logger().info(f"recording to {out}")

    def _validate(self, params):
        for p in params:
            if p.name == "frame_every" and p.value < 0:
                return parameters.refuse("frame_every must be >= 0")
        return parameters.accept()

    def _discover(self):
        if not self.get_parameter("discover").value or self.closing:
            return
        for topic, types in self.get_topic_names_and_types():
            kind = topic.rsplit("/", 1)[-1]
            if kind in qos.TYPES and qos.TYPES[kind] in types and topic not in self._subs:
                self._subscribe(topic, qos.TYPES[kind])

    def _subscribe(self, topic: str, type_name: str | None):
        if type_name is None or topic in self._subs:
            if type_name is None:
                self.get_logger().error(f"not recording {topic}: not a contract topic name")
            return
        kind = topic.rsplit("/", 1)[-1]
        if kind == "frame" and self.get_parameter("frame_every").value == 0 \
                and self.get_parameter("frames").value == 0:
            return
        profile = qos.for_topic(topic)
        self.writer.add_topic(topic, type_name, qos=qos.describe(profile))
        self.recorded[topic] = 0

        def callback(cdr, info, topic=topic, kind=kind, msg_type=MSG_CLASSES[type_name]):
            self._on_message(topic, kind, cdr, info)
            # what else is queued, without the executor's ~0.3 ms per message
            for cdr, info in take_queued(self._subs[topic], msg_type, DRAIN):
                self._on_message(topic, kind, cdr, info)

        self._subs[topic] = self.create_subscription(MSG_CLASSES[type_name], topic, callback,
                                                     profile, raw=True)
        self.get_logger().info(f"recording {topic} [{type_name}]")

    def _on_message(self, topic, kind, cdr, info):
        if self.closing:
            return
        if kind == "frame":
            if self.budget_reached:
                return
            self.frames_seen += 1
            every = self.get_parameter("frame_every").value
            keep = every > 0 and (self.frames_seen - 1) % every == 0
        else:
            keep = True
        if keep:
            received = int(info.get("received_timestamp", 0)) or time.time_ns()
            source = int(info.get("source_timestamp", 0)) or received
            try:
                self.writer.write(topic, cdr, received, source)
            except OSError as exc:
                self._fail(f"writing {topic} failed: {exc}")
                return
            self.recorded[topic] += 1
        budget = self.get_parameter("frames").value
        if kind == "frame" and budget and self.frames_seen >= budget:
            self.budget_reached = True
            linger = self.get_parameter("linger_s").value
            self.get_logger().info(f"frame budget of {budget} reached; closing in {linger} s")
            self._linger_timer = self.create_timer(linger, self._end_linger)

    def _end_linger(self):
        self._linger_timer.cancel()
        self.close()

    def _fail(self, reason: str):
        self.failed = reason
        self.get_logger().error(reason + "; closing the bag, what was written stays readable")
        self.close()

    def close(self):
        """Finish the bag (idempotent); log what was recorded."""
        with self._close_lock:
            if self.closing:
                return
            self.closing = True
        try:
            self.writer.close()
        except OSError as exc:
            self.get_logger().error(f"closing {self.path} failed: {exc}")
        finally:
            self.done = True
        counts = ", ".join(f"{t}: {n}" for t, n in sorted(self.recorded.items()))
        saved = getattr(self.writer, "saved_count", None)
        self.get_logger().info(f"closed {self.path}: {saved} messages saved "
                               f"(received and written: {counts})")


def _finish(node) -> int:
    node.close()
    return 1 if node.failed else 0


def main(args=None):
    # BagError: e.g. the output exists and overwrite is false
    return run_node("recorder_node", RecorderNode, done=lambda n: n.done,
                    refused=(bags.BagError, ValueError), finish=_finish, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
