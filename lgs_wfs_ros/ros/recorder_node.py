"""recorder_node: every contract topic to an MCAP bag in rosbag2's layout.

Raw subscriptions (``raw=True``): the serialized CDR goes to the file as it came, with log time =
receive time and publish time = source time. Topics come from the ``topics`` parameter and, with
``discover`` on, from the graph: any topic whose last name is a contract name (frame,
true_slopes, slopes, sensor, centroider) with the contract's type. Frames can be decimated
(``frame_every``) since full frames at 700 Hz are more than one Python process can write here.
With ``frame_transport: shm`` the frames come from the source's shared memory instead of the
ROS topic (read in place on a thread of the recorder's own, each acknowledged; only the kept
ones are encoded and written): no 1.84 MB copy through DDS for the frames a bag keeps, and
the source's ROS copy of the frame can be off (``frame_publish_hz: 0``).

``frame_subapertures`` (valid-subaperture indices in the contract's order; empty: off) writes
each kept frame as the blocks of those subapertures only, on ``/<ns>/frame_subapertures``
(Image, k*p x p, the frame's header), with the selection as JSON on
``/<ns>/frame_subapertures_selection`` (docs/conventions.md section 5, docs/bags.md);
``full_frame_every`` M also keeps every Mth kept frame in full beside its blocks. The pixels
are read in place from the CDR (numpy view) and gathered with one precomputed index. The
geometry comes from the recorded ``/<ns>/sensor`` topic (subscribed when a selection is set);
indices that do not fit the sensor are refused with the reason (or, if the sensor changes
under them, no blocks are written until they do, with an error logged).

The bag is closed (summary and index written) on SIGINT, SIGTERM, at the ``frames`` budget, or
when the disk fills up (reported; what was written stays readable).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from .. import bags
from ..bags import subapertures as subaps
from ..bags.portable import STRING, portable_cdr
from ..optics import geometry
from ..sensor import Sensor, SensorError
from ..transport import TRANSPORTS, frames as frame_transport, shm
from .handover import Handover, sequence
from .spinning import run_node, take_queued
from . import health, parameters, priority, qos

MSG_CLASSES = {"sensor_msgs/msg/Image": Image, "std_msgs/msg/String": String}
#: relative names resolve in the node's namespace (/wfs by default) and follow remappings
DEFAULT_TOPICS = ["frame", "true_slopes", "sensor"]

# The recorder is not latency-critical: it lets messages gather for 2 ms between executor
# rounds and takes up to 256 per topic per round (at 6 kHz single-subaperture the executor's
# per-round Python, not the writing, was most of its CPU).
SPIN_PAUSE_S = 0.002
RECORDER_DRAIN = 256
# On SIGINT/SIGTERM the recorder keeps recording this long before closing the bag: a launch
# file interrupts every node at once, and the producers' last messages (flushed by their own
# shutdown, ros/spinning.py) are still on their way. After it, it records on until nothing
# has arrived for spinning.STOP_QUIET_S (3 s at most): what DDS already acknowledged to the
# publishers but the recorder had not taken yet (a backlog on a loaded machine) reaches the
# bag. Once, in a loaded full run, the soak lost the last 17 slopes that way.
STOP_LINGER_S = 1.0
# after the frame budget, how often the linger checks whether every slopes topic is complete
LINGER_POLL_S = 0.05


def _namespace(topic: str) -> str:
    return topic.rstrip("/").rsplit("/", 1)[0]


def _indices_value(value) -> list:
    """A parameter value as a list for :func:`subaps.parse_indices` (any empty array: [])."""
    if value is None:
        return []
    if isinstance(value, (str, bytes, bool, int, float)):
        raise ValueError(f"frame_subapertures must be an integer array, got {value!r}")
    return list(value)


def default_output() -> str:
    return str(Path("bags") / time.strftime("lgs_wfs_%Y%m%d_%H%M%S.mcap"))


class RecorderNode(Node):
    def __init__(self, **kwargs):
        kwargs.setdefault("namespace", "wfs")
        super().__init__("recorder_node", **kwargs)
        parameters.declare(self, "output", default_output(), "Path of the MCAP bag to write.",
                           read_only=True)
        parameters.declare(self, "overwrite", False, "Replace an existing output file.",
                           read_only=True)
        parameters.declare(self, "topics", DEFAULT_TOPICS, "Topics to record (relative names resolve "
                           "in the node's namespace and follow remappings).",
                           read_only=True)
        parameters.declare(self, "discover", True, "Also record contract topics found in the "
                           "graph (checked every second).")
        parameters.declare(self, "frame_every", 1, "Record every Nth frame (0: no frames; "
                           "slopes and truths are always kept at full rate).", low=0, high=1000000)
        self.declare_parameter("frame_subapertures", [], ParameterDescriptor(
            dynamic_typing=True, description="Indices of valid subapertures (contract order) "
            "whose blocks are written for each kept frame, instead of the full frame, on "
            "<ns>/frame_subapertures (empty: off, full frames)."))
        parameters.declare(self, "full_frame_every", 0, "With frame_subapertures set: also "
                           "write every Nth kept frame in full (0: never, 1: every kept frame).",
                           low=0, high=1000000)
        parameters.declare(self, "frames", 0, "Stop after this many frames received "
                           "(0: record until interrupted).", low=0, high=2**31 - 1)
        parameters.declare(self, "linger_s", 1.0, "After the frame budget, keep recording until "
                           "every slopes (and truth) topic has one for each frame, this long at "
                           "most.",
                           low=0.0, high=60.0)
        parameters.declare(self, "chunk_kb", 4096, "MCAP chunk size, kB: a crash or a full disk "
                           "loses at most the open chunk.", low=16, high=1 << 20, read_only=True)
        parameters.declare(self, "compression", "zstd", "Chunk compression.",
                           choices=("zstd", "lz4", "none"), read_only=True)
        parameters.declare(self, "nice", 0, "CPU priority of the recorder's threads (0-19, "
                           "higher yields more): e.g. 10 lets the source and centroiders "
                           "preempt it on contended cores; the 800 Hz graph's latency tail "
                           "is shorter with it (docs/transport.md).", low=0, high=19,
                           read_only=True)
        parameters.declare(self, "frame_transport", "ros", "Where frames come from: 'ros' "
                           "(the frame topic) or 'shm' (the source's iceoryx2 shared memory, "
                           "read in place; only the kept frames are encoded).",
                           choices=TRANSPORTS, read_only=True)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)
        try:      # an override given at start (the on-set callback does not see it)
            self.selection = subaps.parse_indices(_indices_value(
                self.get_parameter("frame_subapertures").value))
        except ValueError as exc:
            raise ValueError(f"frame_subapertures: {exc}") from None

        p = parameters.values(self, ("output", "overwrite", "compression", "chunk_kb",
                                     "frame_transport"))
        self._shm_frames = p["frame_transport"] == "shm"
        if self._shm_frames and not shm.AVAILABLE:
            raise ValueError("frame_transport 'shm' needs iceoryx2 "
                             "(pip install 'lgs_wfs_ros[shm]'); use 'ros'")
        self._inlets = {}                        # frame topic -> FrameInlet (shm)
        self._shm_lost = {}                      # frame topic -> sequence gaps seen so far
        # the executor's thread and the inlets' write the bag: one writer at a time (an
        # RLock: a failed write closes the bag from inside the write)
        self._write_lock = threading.RLock()
        out = Path(p["output"])
        out.parent.mkdir(parents=True, exist_ok=True)
        self.path = out
        self.writer = bags.BagWriter(out, overwrite=p["overwrite"], chunk_size=p["chunk_kb"] * 1024,
                                     compression=None if p["compression"] == "none" else p["compression"])
        self.recorded: dict[str, int] = {}
        self.gaps: dict[str, int] = {}          # topic -> messages lost before the recorder
        self._sequence: dict[str, int] = {}     # topic -> last publication sequence number
        self.frames_seen = 0
        self.messages_taken = 0          # every message handed to _on_message (stop drain)
        self.failed = ""
        self.done = False        # the bag is closed
        self.closing = False     # no more writes
        self._close_lock = threading.Lock()
        self.budget_reached = False
        self._linger_timer = None
        self._subs = {}
        self._handovers = {}     # frame topic -> its queue change under way (handover.py)
        self.sensors: dict[str, Sensor] = {}      # namespace -> last sensor description
        self._selection_version = 0
        self._cutters = {}       # frame topic -> [version, sensor, Cutter | None, reason, announced]
        self._kept = {}          # frame topic -> frames kept (for full_frame_every)
        self.blocks_skipped = 0
        self.skip_reason = ""
        self.health = health.Health(self, self._diagnostic_values)
        for topic in self.get_parameter("topics").value:
            topic = self.resolve_topic_name(topic)
            self._subscribe(topic, qos.TYPES.get(topic.rsplit("/", 1)[-1]))
        self.incompatible_frame_publishers: set[str] = set()     # warned of, once each
        self._discover_timer = self.create_timer(1.0, self._discover)
        self._discover()
        nice = self.get_parameter("nice").value
        if nice:
            priority.lower(nice)
            self.get_logger().info(f"recording at nice {priority.current()}")
        self.health.set_state(health.OK, f"recording to {out}")

    def _diagnostic_values(self) -> dict:
        return {"output": str(self.path), "frames_seen": self.frames_seen,
                **{f"lost before the recorder {t}": n for t, n in sorted(self.gaps.items())},
                "blocks_skipped": self.blocks_skipped,
                **{f"recorded {t}": n for t, n in sorted(self.recorded.items())}}

    def _validate(self, params):
        for p in params:
            if p.name == "frame_every" and p.value < 0:
                return parameters.refuse("frame_every must be >= 0")
            if p.name == "frame_subapertures":
                reason = self._check_selection(p.value)
                if reason:
                    return parameters.refuse(f"frame_subapertures: {reason}")
        return parameters.accept()

    def _check_selection(self, value) -> str:
        """Why the indices cannot be used ('' when they can): type, repeats, and the range
        of every sensor description received so far."""
        try:
            idx = subaps.parse_indices(_indices_value(value))
            for ns, sensor in sorted(self.sensors.items()):
                n = geometry.layout(sensor).n_valid
                if len(idx) and idx.max() >= n:
                    raise ValueError(f"index {int(idx.max())} is out of range: {ns}/sensor has "
                                     f"{n} valid subapertures (0..{n - 1})")
        except ValueError as exc:
            return str(exc)
        return ""

    def _apply(self, params):
        for p in params:
            if p.name == "frame_subapertures":
                self.selection = subaps.parse_indices(_indices_value(p.value))
                self._selection_version += 1
                self.get_logger().info(f"frame_subapertures: {len(self.selection)} subapertures"
                                       + ("" if len(self.selection) else " (off: full frames)"))
                if len(self.selection):
                    for topic in list(self._subs):
                        if topic.rsplit("/", 1)[-1] == "frame":
                            self._subscribe(_namespace(topic) + "/sensor", qos.TYPES["sensor"])

    def _discover(self):
        self._check_frame_publishers()
        if not self.get_parameter("discover").value or self.closing:
            return
        for topic, types in self.get_topic_names_and_types():
            kind = topic.rsplit("/", 1)[-1]
            if kind in qos.TYPES and qos.TYPES[kind] in types and topic not in self._subs:
                self._subscribe(topic, qos.TYPES[kind])

    def _check_frame_publishers(self):
        """Warn once of each frame publisher a frame subscription cannot hear (those have no
        incompatible-QoS handler: :func:`.qos.replaceable`)."""
        for topic, sub in list(self._subs.items()):
            if sub is not None and topic.endswith("/frame"):
                for who in qos.new_incompatible(self, sub, self.incompatible_frame_publishers):
                    self.get_logger().warning(f"not recording {topic} from {who}")

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
        if kind == "frame":
            profile = qos.frame_qos(self.sensors.get(_namespace(topic)))
        self.writer.add_topic(topic, type_name, qos=qos.describe(profile))
        self.recorded[topic] = 0
        if kind == "frame" and self._shm_frames:
            self._subs[topic] = None             # taken: frames come through the inlet
            self._inlets[topic] = frame_transport.FrameInlet(
                topic, lambda frames, lost, topic=topic: self._on_shm_frames(topic, frames, lost),
                shm.MAX_DEPTH)
        else:
            self._create_subscription(topic, type_name, profile)
        self.get_logger().info(f"recording {topic} [{type_name}]")
        if kind == "frame" and len(self.selection):
            self._subscribe(_namespace(topic) + "/sensor", qos.TYPES["sensor"])

    def _create_subscription(self, topic: str, type_name: str, profile) -> None:
        kind = topic.rsplit("/", 1)[-1]

        def callback(cdr, info, topic=topic, kind=kind, msg_type=MSG_CLASSES[type_name]):
            hand = self._handovers.get(topic)
            if hand is not None:        # a queue change: every message of both queues, once
                taken = hand.take((cdr, info), sub is hand.new)
                if hand.over:
                    del self._handovers[topic]
            else:                       # what else is queued, without the executor's ~0.3 ms
                taken = [(cdr, info)] + list(take_queued(sub, msg_type, RECORDER_DRAIN))
            for cdr, info in taken:
                self._on_message(topic, kind, cdr, info)

        events = qos.replaceable() if kind == "frame" else None     # re-sized: handover.py
        sub = self.create_subscription(MSG_CLASSES[type_name], topic, callback, profile,
                                       raw=True, event_callbacks=events)
        self._subs[topic] = sub

    def _resize_frame_queue(self, ns: str, sensor: Sensor) -> None:
        """Give ``ns``'s frame subscription the queue its sensor needs (``qos.frame_qos``:
        0.14 s of frames). The old subscription is handed over, not dropped
        (:class:`handover.Handover`): no frame it holds or that is sent meanwhile is lost."""
        topic = ns + "/frame"
        old = self._subs.get(topic)
        profile = qos.frame_qos(sensor)
        if old is None or old.qos_profile.depth == profile.depth:     # None: shm frames
            return
        self._create_subscription(topic, qos.TYPES["frame"], profile)
        last = self._handovers.get(topic)
        self._handovers[topic] = Handover(self, old, self._subs[topic], Image)
        if last is not None:             # re-sized again before the last change ended
            for cdr, info in last.finish_old():
                self._on_message(topic, "frame", cdr, info)
            self._handovers[topic].seen |= last.seen
        self.get_logger().info(f"{topic}: frame queue resized to {profile.depth} for its sensor")

    def _count_gap(self, topic, info) -> None:
        """Messages of ``topic`` that never reached this subscription: gaps in the
        publisher's sequence numbers (a KEEP_LAST queue overwritten while the recorder
        stalled, or a writer gone before delivering). Counted per topic, for one publisher
        per topic (the contract's graphs); a sequence going back (a new publisher) restarts."""
        seq = sequence(info)
        if not seq:
            return
        last = self._sequence.get(topic)
        if last is not None and seq > last + 1:
            self.gaps[topic] = self.gaps.get(topic, 0) + seq - last - 1
            self.health.note(f"messages lost before the recorder on {topic}",
                             f"publication sequence jumped from {last} to {seq}")
        self._sequence[topic] = seq

    def _on_shm_frames(self, topic, frames, lost: int):
        """Frames read in place from shared memory (the inlet's thread): ``[(stamp_ns, image,
        sensor_id)]``, valid during this call; ``lost``: the source's frames that never came
        (sequence gaps). Every frame counts toward ``frame_every`` and ``frames``; only the
        kept ones are encoded (log time: now; publish time: the frame's stamp)."""
        with self._write_lock:
            if lost > self._shm_lost.get(topic, 0):
                self.gaps[topic] = self.gaps.get(topic, 0) + lost - self._shm_lost.get(topic, 0)
                self.health.note(f"messages lost before the recorder on {topic}",
                                 f"{lost} shared-memory frames never arrived")
                self._shm_lost[topic] = lost
            for stamp_ns, image, _sensor_id in frames:
                if self.closing or self.budget_reached:
                    return
                keep = self._count_frame()
                cdr = bags.encode_image(image, stamp_ns) if keep else None
                self._on_message(topic, "frame", cdr,
                                 {"received_timestamp": time.time_ns(),
                                  "source_timestamp": stamp_ns}, keep=keep)

    def _count_frame(self) -> bool:
        """One more frame seen: is it one ``frame_every`` keeps?"""
        self.frames_seen += 1
        every = self.get_parameter("frame_every").value
        return every > 0 and (self.frames_seen - 1) % every == 0

    def _on_message(self, topic, kind, cdr, info, keep=None):
        """Write one message (``keep``: a frame already counted, by the shm path)."""
        with self._write_lock:
            self._write_message(topic, kind, cdr, info, keep)

    def _write_message(self, topic, kind, cdr, info, keep):
        if self.closing:
            return
        self.messages_taken += 1
        self._count_gap(topic, info)
        if kind == "frame":
            if self.budget_reached:
                return
            if keep is None:
                keep = self._count_frame()
        else:
            keep = True
            if kind == "sensor":
                self._on_sensor(topic, cdr)
            if kind in ("sensor", "centroider"):   # bags carry names, not this machine's paths
                cdr = portable_cdr(STRING, cdr)
        if keep:
            received = int(info.get("received_timestamp", 0)) or time.time_ns()
            source = int(info.get("source_timestamp", 0)) or received
            full = True
            try:
                if kind == "frame" and len(self.selection):
                    kept = self._kept[topic] = self._kept.get(topic, 0) + 1
                    every_full = self.get_parameter("full_frame_every").value
                    full = every_full > 0 and (kept - 1) % every_full == 0
                    self._write_blocks(topic, cdr, received, source)
                if full:
                    self.writer.write(topic, cdr, received, source)
                    self.recorded[topic] += 1
            except OSError as exc:
                self._fail(f"writing {topic} failed: {exc}")
                return
        budget = self.get_parameter("frames").value
        if kind == "frame" and budget and self.frames_seen >= budget:
            self.budget_reached = True
            linger = self.get_parameter("linger_s").value
            self.get_logger().info(f"frame budget of {budget} reached; closing when every "
                                   f"slopes topic has {budget}, in {linger} s at most")
            self._linger_deadline = time.monotonic() + linger
            self._linger_timer = self.create_timer(LINGER_POLL_S, self._check_linger)

    def _on_sensor(self, topic, cdr):
        """Keep the namespace's sensor description (the geometry of its frames)."""
        try:
            sensor = Sensor.from_json(bags.decode_string(cdr))
        except (SensorError, TypeError, ValueError) as exc:
            self.get_logger().error(f"{topic}: unusable sensor description: {exc}")
            return
        ns = _namespace(topic)
        if self.sensors.get(ns) != sensor:
            self.sensors[ns] = sensor
            self._resize_frame_queue(ns, sensor)

    def _cutter(self, topic):
        """``[version, sensor, Cutter | None, reason it is None, selection written]`` for a
        frame topic under the current selection and sensor (rebuilt when either changes)."""
        sensor = self.sensors.get(_namespace(topic))
        entry = self._cutters.get(topic)
        if entry is not None and entry[0] == self._selection_version and entry[1] is sensor:
            return entry
        cutter, reason = None, ""
        if sensor is None:
            reason = f"no sensor description on {_namespace(topic)}/sensor yet"
        else:
            try:
                cutter = subaps.Cutter(sensor, self.selection)
            except ValueError as exc:
                reason = f"frame_subapertures do not fit {_namespace(topic)}/sensor: {exc}"
        entry = [self._selection_version, sensor, cutter, reason, False]
        self._cutters[topic] = entry
        return entry

    def _write_blocks(self, topic, cdr, received, source):
        """Write the chosen blocks of one frame (and, first, its selection when new)."""
        entry = self._cutter(topic)
        cutter = entry[2]
        if cutter is None:
            self._skip(f"{topic}: {entry[3]}")
            return
        try:
            written = subaps.write_blocks(self.writer, cutter, topic, cdr, received, source,
                                          new_selection=not entry[4])
        except ValueError as exc:
            self._skip(f"{topic}: {exc}")
            return
        for t in written:
            self.recorded[t] = self.recorded.get(t, 0) + 1
        if not entry[4]:
            entry[4] = True
            self.get_logger().info(f"recording {cutter.k} subapertures of {topic} on {written[-1]}")

    def _skip(self, reason):
        self.blocks_skipped += 1
        if reason != self.skip_reason:
            self.get_logger().error(f"frame not cut into subapertures (no blocks written): {reason}")
        self.skip_reason = reason

    def _check_linger(self):
        """After the frame budget: close once every recorded slopes topic has a slope for
        each frame of the budget (its centroider answered them all) and every truth topic
        a truth, or at ``linger_s``."""
        budget = self.get_parameter("frames").value
        kinds = {t: t.rsplit("/", 1)[-1] for t in self.recorded}
        per_frame = [t for t, k in kinds.items() if k in ("slopes", "true_slopes")]
        complete = ("slopes" in kinds.values()
                    and all(self.recorded[t] >= budget for t in per_frame))
        if complete or time.monotonic() >= self._linger_deadline:
            self._linger_timer.cancel()
            self.close()

    def _fail(self, reason: str):
        self.failed = reason
        self.health.set_state(health.ERROR, reason + "; closing the bag, what was written "
                              "stays readable")
        self.close()

    def close(self):
        """Finish the bag (idempotent); log what was recorded."""
        with self._close_lock:
            if self.closing:
                return
            self.closing = True
        for inlet in self._inlets.values():      # no more shm frames (not from their thread)
            inlet.close()
        try:
            with self._write_lock:
                self.writer.close()
        except OSError as exc:
            self.get_logger().error(f"closing {self.path} failed: {exc}")
        finally:
            self.done = True
        counts = ", ".join(f"{t}: {n}" for t, n in sorted(self.recorded.items()))
        saved = getattr(self.writer, "saved_count", None)
        self.get_logger().info(f"closed {self.path}: {saved} messages saved "
                               f"(received and written: {counts}); "
                               f"sequence gaps {json.dumps(self.gaps, sort_keys=True)}")


def _finish(node) -> int:
    node.close()
    return 1 if node.failed else 0


def main(args=None):
    # BagError: e.g. the output exists and overwrite is false
    return run_node("recorder_node", RecorderNode, done=lambda n: n.done,
                    refused=(bags.BagError, ValueError), finish=_finish, args=args,
                    pause_s=SPIN_PAUSE_S, stop_linger_s=STOP_LINGER_S,
                    activity=lambda n: n.messages_taken)


if __name__ == "__main__":
    raise SystemExit(main())
