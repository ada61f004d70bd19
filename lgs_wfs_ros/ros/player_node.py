"""player_node: a bag's frames, truths and sensor description back onto the contract topics.

Messages are published as the raw CDR stored in the bag (no decode), under the node's namespace
with the last component of their recorded name (``/wfs/frame`` -> ``frame``). Pacing: the
recorded rate (from the stamps), a fixed rate in Hz, or ``max``: as fast as the consumers keep
up, i.e. at most ``in_flight`` frames are out unanswered: the next frame goes out when every
topic in ``wait_for`` has returned the stamp of the frame ``in_flight`` back (or after
``wait_timeout_s``). ``in_flight`` 1 is lockstep; a few frames in flight keep a slow consumer
busy without ever overrunning its queue, so nothing is dropped.
"""

from __future__ import annotations

import collections
import json
import struct
import threading
import time

from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from .. import bags
from ..sensor import Sensor, SensorError
from ..transport import shm
from .frame_transport import FrameSource, declare_frame_transport, make_outlet
from .spinning import run_node
from . import health, parameters, qos

MSG_CLASSES = {"sensor_msgs/msg/Image": Image, "std_msgs/msg/String": String}
REPLAYED = ("frame", "true_slopes", "sensor")


def parse_rate(text: str) -> float | None:
    """'recorded' -> None, 'max' -> 0.0, a number -> Hz (> 0); ValueError otherwise."""
    text = str(text).strip().lower()
    if text == "recorded":
        return None
    if text == "max":
        return 0.0
    try:
        hz = float(text)
    except ValueError:
        raise ValueError(f"rate must be 'recorded', 'max' or a number of Hz, got {text!r}") from None
    if not hz > 0:
        raise ValueError(f"rate must be > 0 Hz, got {hz}")
    return hz


def restamp(cdr, shift_ns: int) -> bytes:
    """A message starting with a std_msgs/Header, its stamp moved by ``shift_ns`` (one copy)."""
    sec, nanosec = bags.cdr.split_stamp(bags.peek_stamp(cdr) + int(shift_ns))
    mv = memoryview(cdr)
    return b"".join((mv[:4], struct.pack("<iI", sec, nanosec), mv[12:]))


class PlaySchedule:
    """When each frame of a (looped) bag is due, on one clock for the whole run.

    A frame late because the player was starved goes out at once and the next ones keep
    their slots, so a 10 s run at 800 Hz offers 8,000 frames whatever the hiccups (each
    pass used to restart the clock: every pass's lateness was lost from the offered rate).
    Changing ``rate`` (or between a fixed rate and the recorded timing) starts the new
    pacing from the frame it applies to.

    Args:
        clock: seconds, monotonic (``time.monotonic``).
    """

    def __init__(self, clock=time.monotonic):
        self._clock = clock
        self._mode = None            # the rate the anchor was taken at (None: recorded)
        self._anchor = None          # (clock s, frames sent before it, bag ns before it)
        self.sent = 0                # frames scheduled so far

    def due(self, rate: float | None, elapsed_ns: int) -> float | None:
        """The clock time the next frame is due (None: now, ``rate`` 0 is 'max').

        Args:
            rate: Hz (> 0), None (the recorded timing) or 0.0 (as fast as consumers allow).
            elapsed_ns: recorded time of this frame since the first frame of the run, ns
                (pass ``k`` of a looped bag adds ``k`` bag lengths).
        """
        if self._anchor is None or rate != self._mode:
            self._mode = rate
            self._anchor = (self._clock(), self.sent, elapsed_ns)
        t0, n0, ns0 = self._anchor
        self.sent += 1
        if rate is None:
            return t0 + (elapsed_ns - ns0) * 1e-9
        if rate > 0:
            return t0 + (self.sent - 1 - n0) / rate
        return None


class PlayerNode(FrameSource, Node):
    def __init__(self, **kwargs):
        kwargs.setdefault("namespace", "wfs")
        super().__init__("player_node", **kwargs)
        parameters.declare(self, "bag", "", "MCAP bag to play.", read_only=True)
        parameters.declare(self, "rate", "recorded", "'recorded', 'max' or frames per second.")
        parameters.declare(self, "wait_for", ["/cog/slopes"], "With rate 'max': slopes topics "
                           "that must answer a frame before the next one is sent.")
        parameters.declare(self, "wait_timeout_s", 1.0, "With rate 'max': longest wait for an "
                           "answer.", low=0.001, high=60.0)
        parameters.declare(self, "in_flight", 1, "With rate 'max': frames sent but not yet "
                           "answered on every wait_for topic, at most (1: lockstep). Below the "
                           "frame queue depth (at least 100) nothing is dropped.", low=1, high=64)
        parameters.declare(self, "loop", False, "Start again at the end of the bag.")
        parameters.declare(self, "cache_mb", 512, "With loop: read a bag up to this size into "
                           "memory before the first frame (0: always read from the file).",
                           low=0, high=1 << 20, read_only=True)
        parameters.declare(self, "restamp_loops", True, "With loop: shift the stamps of each "
                           "pass by the bag's length so they keep increasing (consumers refuse "
                           "repeated stamps).")
        parameters.declare(self, "start_delay_s", 1.0, "Wait for subscribers this long first.",
                           low=0.0, high=60.0)
        declare_frame_transport(self)
        self.add_on_set_parameters_callback(self._validate)

        path = self.get_parameter("bag").value
        self.reader = bags.BagReader(path)   # BagError with a clear message if unusable
        kinds = {t.rsplit("/", 1)[-1]: (t, ty) for t, (ty, _n) in self.reader.topics().items()}
        missing = [k for k in ("frame",) if k not in kinds]
        if missing:
            raise bags.BagError(f"{path} has no frame topic (topics: {sorted(self.reader.topics())})")
        self.sources = {kinds[k][0]: k for k in REPLAYED if k in kinds}
        profiles = {k: qos.for_topic(k) for k in REPLAYED}
        sensor = self._bag_sensor()
        profiles["frame"] = qos.frame_qos(sensor)
        self.pubs = {k: self.create_publisher(MSG_CLASSES[kinds[k][1]], k, profiles[k])
                     for k in REPLAYED if k in kinds}
        self._outlet = make_outlet(self, self.pubs["frame"], sensor or Sensor())
        self._sensor_id = shm.sensor_id(sensor) if sensor is not None else 0
        self.published = {k: 0 for k in self.pubs}
        self.answers: dict[str, int] = {}
        self._answer = threading.Condition()
        for topic in self.get_parameter("wait_for").value:
            self.create_subscription(Image, topic, lambda cdr, t=topic: self._on_answer(t, cdr),
                                     qos.SLOPES, raw=True)
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._pass = 0
        self._span_ns = 0          # bag length in stamps (first pass), for restamp_loops
        self._schedule = PlaySchedule()
        self._first_stamp = None   # the first frame's recorded stamp (pass 0)
        self._cache = None         # [(kind, cdr)] of a looped bag that fits in cache_mb
        self.health = health.Health(self, lambda: {**self.published, "pass": self._pass})
        self.health.set_state(health.OK, f"playing {path}")
        self._thread = threading.Thread(target=self._play, name="player", daemon=True)
        self._thread.start()

    def _bag_sensor(self):
        """The bag's first sensor description (sizes the frame queue), None if it has none
        or it is unusable (the default frame QoS then)."""
        topics = [t for t, k in self.sources.items() if k == "sensor"]
        try:
            for _topic, _type, _log, _pub, cdr in self.reader.messages(topics):
                return Sensor.from_json(bags.decode_string(cdr))
        except (bags.BagError, SensorError, ValueError, TypeError):
            pass
        return None

    def _validate(self, params):
        for p in params:
            if p.name == "rate":
                try:
                    parse_rate(p.value)
                except ValueError as exc:
                    return parameters.refuse(str(exc))
        return parameters.accept()

    def _on_answer(self, topic, cdr):
        try:
            stamp = bags.peek_stamp(cdr)       # only the header's stamp is needed
        except Exception:
            return
        with self._answer:
            self.answers[topic] = stamp
            self._answer.notify_all()

    def _wait_answers(self, stamp_ns: int):
        topics = self.get_parameter("wait_for").value
        timeout = self.get_parameter("wait_timeout_s").value
        with self._answer:
            self._answer.wait_for(lambda: all(self.answers.get(t, -1) >= stamp_ns for t in topics)
                                  or self._stop.is_set(), timeout=timeout)

    def _publish_first_sensor(self):
        """The sensor description goes out before the start delay, so consumers are
        configured for the bag's sensor before its first frame arrives."""
        topics = [t for t, k in self.sources.items() if k == "sensor"]
        for _topic, _type, _log, _pub, cdr in self.reader.messages(topics):
            self.pubs["sensor"].publish(bytes(cdr))
            self.published["sensor"] += 1
            return

    def _play(self):
        try:
            self._publish_first_sensor()
        except bags.BagError as exc:
            self.health.set_state(health.ERROR, f"stopped: {exc}")
            self.finished.set()
            return
        start = time.monotonic()
        self._preload()
        self._stop.wait(max(0.0, self.get_parameter("start_delay_s").value
                            - (time.monotonic() - start)))
        try:
            while not self._stop.is_set():
                self._play_once()
                self._pass += 1
                if not self.get_parameter("loop").value:
                    break
        except bags.BagError as exc:
            self.health.set_state(health.ERROR, f"stopped: {exc}")
        except Exception:
            # SIGINT/SIGTERM shut the context down while this thread was publishing: the
            # publish fails, which here only means stop (anything else is a real error)
            if self.context.ok():
                self.finished.set()
                raise
        if self.context.ok() and not self._stop.is_set():
            self.health.set_state(health.OK, f"played {self.published}")
        self.finished.set()

    def _play_once(self):
        sent = 0
        window = self.get_parameter("in_flight").value
        pending = collections.deque(maxlen=window)   # stamps of the last frames sent
        skip_sensor = self.published.get("sensor", 0) == 1   # already sent by _publish_first_sensor
        shift = self._pass * self._span_ns if self.get_parameter("restamp_loops").value else 0
        stamps = []
        for kind, cdr in self._messages():
            if self._stop.is_set():
                return
            if kind == "sensor" and skip_sensor:
                skip_sensor = False
                continue
            rate = parse_rate(self.get_parameter("rate").value)
            if kind == "frame":
                recorded = bags.peek_stamp(cdr)
                stamps.append(recorded)
                if self._first_stamp is None:
                    self._first_stamp = recorded
                elapsed = self._pass * self._span_ns + recorded - self._first_stamp
                due = self._schedule.due(rate, elapsed)
                if due is not None:
                    delay = due - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
            if shift and kind != "sensor":
                cdr = restamp(cdr, shift)
            if kind == "frame":
                stamp = recorded + shift
            if kind == "frame" and self._outlet.shm is not None:   # decoded into the loan
                self._outlet.publish(bags.decode_image(cdr)[3], stamp, self._sensor_id,
                                     stop=self._stop.is_set)
            else:
                self.pubs[kind].publish(cdr if isinstance(cdr, bytes) else bytes(cdr))
            self.published[kind] += 1
            if kind == "frame":
                sent += 1
                pending.append(stamp)
                if rate == 0.0 and self.get_parameter("wait_for").value and len(pending) == window:
                    self._wait_answers(pending[0])
        if self._pass == 0 and len(stamps) > 1:   # one period past the last frame
            self._span_ns = (stamps[-1] - stamps[0]) * len(stamps) // (len(stamps) - 1)

    def _preload(self):
        """With ``loop``, read a bag that fits in ``cache_mb`` into memory before the first
        frame (during the start delay): read while playing, a chunk (CRC check and copy) cost
        ~1.1 ms a full-pupil frame, so at 800 Hz the whole first pass went out late and in
        bursts (40-66 frames more than 2 ms late, most of a 10 s run's 1 % latency tail)."""
        budget = self.get_parameter("cache_mb").value * 2**20
        if not self.get_parameter("loop").value or not budget or self._cache is not None:
            return
        size, cache, start = 0, [], time.monotonic()
        try:
            for topic, _type, _log, _pub, cdr in self.reader.messages(list(self.sources)):
                if self._stop.is_set():
                    return
                size += len(cdr)
                if size > budget:
                    self.get_logger().info(f"bag over cache_mb ({budget / 2**20:g} MB): "
                                           "every pass read from the file")
                    return
                cache.append((self.sources[topic], cdr))
        except bags.BagError:            # damaged: played from the file up to the damage,
            return                       # which is reported there
        self._cache = cache
        self.get_logger().info(f"bag read into memory: {len(cache)} messages, "
                               f"{size / 2**20:.0f} MB in {time.monotonic() - start:.1f} s")

    def _messages(self):
        """(kind, cdr bytes) of one pass over the bag: from memory when :meth:`_preload` kept
        it, else from the file."""
        if self._cache is not None:
            yield from self._cache
            return
        for topic, _type, _log, _pub, cdr in self.reader.messages(list(self.sources)):
            yield self.sources[topic], cdr

    def _wake(self):
        with self._answer:                   # a play thread waiting for answers
            self._answer.notify_all()


def _finish(node) -> None:
    node.stop()
    node.get_logger().info(f"final counts {json.dumps(node.published)}")


def main(args=None):
    return run_node("player_node", PlayerNode, done=lambda n: n.finished.is_set(),
                    refused=(bags.BagError, ValueError), finish=_finish, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
