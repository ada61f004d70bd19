"""Frames through iceoryx2 shared memory: loaned, written in place, read in place.

One publish-subscribe service per frame topic, named from the ROS domain, namespace and topic
(:func:`service_name`: ``lgs_wfs_ros/d44/wfs/frame``), so graphs in different ROS domains or
namespaces on one host stay apart as they do on DDS. The payload is the frame's pixels
(row-major, ``rows x cols`` of ``dtype``) as a byte slice; a fixed :class:`FrameHeader` beside
it carries the stamp (ns, the same stamp as the frame's ``true_slopes``), a sequence number
(1, 2, ... per publisher: gaps are lost frames) and the sensor's id (:func:`sensor_id`, a
64-bit hash of its description, which itself stays on the ROS ``sensor`` topic).

Publisher: :meth:`ShmFramePublisher.loan` gives a writable numpy view of a sample in shared
memory; the caller renders or decodes straight into it, then :meth:`ShmFramePublisher.send`
stamps the header, sends and wakes the subscribers (an iceoryx2 event). Subscriber:
:meth:`ShmFrameSubscriber.take` returns a :class:`ShmFrame` whose ``image`` is a read-only
numpy view of the publisher's sample (no copy), valid until :meth:`ShmFrame.release`.

Delivery: each subscriber has a queue of ``depth`` frames; a frame that finds it full is not
delivered to that subscriber (iceoryx2 ``DiscardData``; safe overflow off, so what is queued
is never overwritten), which counts the gap by sequence number (``lost``). Lockstep, which
never drops: a subscriber created with ``ack=True`` sends back the sequence of every frame it
has released (a small ``Ack`` service beside the frames), and a publisher created with
``lockstep=True`` sends frame ``n`` only when every acking subscriber has released frame
``n - depth`` (it waits, so the source runs at the pace of its slowest acking reader; a reader
silent for ``stall_s`` is counted in ``stalled`` and no longer waited for). iceoryx2's own
``RetryUntilDelivered`` is not used: its Python ``send`` blocks holding the GIL.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import time

import numpy as np

try:                                   # optional: the 'shm' extra
    import iceoryx2 as iox2
    AVAILABLE = True
except ImportError:                    # pragma: no cover - exercised where it is absent
    iox2 = None
    AVAILABLE = False

PREFIX = "lgs_wfs_ros"
MAX_DEPTH = 256          # the service's largest subscriber queue (frames; the publisher's
                         # segment holds this many per subscriber whatever they ask)
DEFAULT_DEPTH = 32       # a subscriber's queue: 40 ms at 800 Hz, 59 MB of full-pupil frames
MAX_SUBSCRIBERS = 8
MAX_BORROWED = 16       # frames a subscriber holds at once
MAX_PUBLISHERS = 2
ACK_QUEUE = 64
DTYPE_CODES = {np.dtype("<u2"): 1, np.dtype("<f4"): 2, np.dtype("u1"): 3, np.dtype("<f8"): 4}
CODE_DTYPES = {v: k for k, v in DTYPE_CODES.items()}


class ShmUnavailable(RuntimeError):
    """The shared-memory transport cannot be used here (iceoryx2 missing or refused)."""


class FrameHeader(ctypes.Structure):
    """What travels beside each frame's pixels (48 bytes, fixed layout)."""
    _fields_ = [("stamp_ns", ctypes.c_int64),      # exposure time, ns since the epoch
                ("sequence", ctypes.c_uint64),     # 1, 2, ... per publisher
                ("sensor_id", ctypes.c_uint64),    # sensor_id() of the sensor description
                ("rows", ctypes.c_uint32),
                ("cols", ctypes.c_uint32),
                ("dtype", ctypes.c_uint32),        # DTYPE_CODES
                ("flags", ctypes.c_uint32),        # reserved, 0
                ("sent_ns", ctypes.c_int64)]       # publisher's CLOCK_MONOTONIC at send, ns


class Ack(ctypes.Structure):
    """A subscriber's answer: it has released every frame up to ``sequence``."""
    _fields_ = [("token", ctypes.c_uint64),       # random, one per subscriber
                ("sequence", ctypes.c_uint64),    # FRESH: just connected
                ("depth", ctypes.c_uint64)]       # its queue, frames


FRESH = 2**64 - 1


def default_transport() -> str:
    """``shm`` where iceoryx2 imports, else ``ros`` (docs/transport.md has the numbers)."""
    return "shm" if AVAILABLE else "ros"


def sensor_id(sensor) -> int:
    """64-bit id of a :class:`~lgs_wfs_ros.sensor.Sensor` (its fields, canonical JSON)."""
    text = json.dumps(sensor.to_dict(), sort_keys=True, default=str)
    return int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "little")


def service_name(namespace: str, topic: str = "frame", domain: int | str | None = None) -> str:
    """iceoryx2 service of a ROS namespace's frame topic, e.g. ``lgs_wfs_ros/d44/wfs/frame``
    (``domain``: the ROS domain id; default ``ROS_DOMAIN_ID``, else 0)."""
    if domain is None:
        domain = os.environ.get("ROS_DOMAIN_ID", "0") or "0"
    parts = [p for p in f"{namespace}/{topic}".split("/") if p]
    return "/".join([PREFIX, f"d{int(domain)}"] + parts)


def _require():
    if not AVAILABLE:
        raise ShmUnavailable("frame_transport 'shm' needs iceoryx2 "
                             "(pip install 'lgs_wfs_ros[shm]'); use 'ros'")


def _node():
    iox2.set_log_level_from_env_or(iox2.LogLevel.Error)   # not its config-file notices
    # iceoryx2 must not take SIGINT/SIGTERM from rclpy, which shuts the nodes down in order
    return (iox2.NodeBuilder.new()
            .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
            .create(iox2.ServiceType.Ipc))


def _services(node, name: str):
    """(publish-subscribe service, event service) of one frame topic, the same settings in
    every process."""
    try:
        pubsub = (node.service_builder(iox2.ServiceName.new(name))
                  .publish_subscribe(iox2.Slice[ctypes.c_uint8])
                  .user_header(FrameHeader)
                  .enable_safe_overflow(False)
                  .subscriber_max_buffer_size(MAX_DEPTH)
                  .subscriber_max_borrowed_samples(MAX_BORROWED)
                  .max_subscribers(MAX_SUBSCRIBERS)
                  .max_publishers(MAX_PUBLISHERS)
                  .history_size(0)
                  .open_or_create())
        event = (node.service_builder(iox2.ServiceName.new(name + "/ready"))
                 .event().open_or_create())
        acks = (node.service_builder(iox2.ServiceName.new(name + "/ack"))
                .publish_subscribe(Ack)
                .subscriber_max_buffer_size(ACK_QUEUE)
                .max_publishers(MAX_SUBSCRIBERS)
                .max_subscribers(MAX_PUBLISHERS)
                .history_size(1)          # a publisher started later learns of its readers
                .open_or_create())
        acked = (node.service_builder(iox2.ServiceName.new(name + "/acked"))
                 .event().open_or_create())
    except Exception as exc:
        raise ShmUnavailable(f"iceoryx2 service {name!r}: {exc!r}") from exc
    return pubsub, event, acks, acked


def _view(ptr: int, shape, dtype: np.dtype) -> np.ndarray:
    """A numpy array over ``ptr`` (no copy); the caller keeps the memory alive."""
    nbytes = int(np.prod(shape)) * dtype.itemsize
    buf = (ctypes.c_uint8 * nbytes).from_address(ptr)
    return np.frombuffer(buf, dtype=dtype).reshape(shape)


class ShmLoan:
    """A loaned sample: ``image`` is a writable view of its pixels in shared memory."""

    __slots__ = ("sample", "image", "header")

    def __init__(self, sample, image: np.ndarray, header: FrameHeader):
        self.sample, self.image, self.header = sample, image, header


class ShmFramePublisher:
    """Publishes frames of one topic; see the module docstring.

    Args:
        name: the service (:func:`service_name`).
        frame_bytes: the largest frame expected, bytes (more grows the segment).
        lockstep: before each frame, wait for room in every acking subscriber's queue.
        stall_s: in lockstep, a subscriber silent this long is no longer waited for.
    """

    def __init__(self, name: str, frame_bytes: int, lockstep: bool = False,
                 stall_s: float = 2.0):
        _require()
        self.name = name
        self.lockstep = bool(lockstep)
        self.stall_s = float(stall_s)
        self._node = _node()
        self._pubsub, self._event, acks, acked = _services(self._node, name)
        self._pub = (self._pubsub.publisher_builder()
                     .initial_max_slice_len(max(int(frame_bytes), 1))
                     .allocation_strategy(iox2.AllocationStrategy.PowerOfTwo)
                     .backpressure_strategy(iox2.BackpressureStrategy.DiscardData)
                     .max_loaned_samples(4)
                     .create())
        self._notifier = self._event.notifier_builder().create()
        self._ack_service = acks
        self._acks = acks.subscriber_builder().history_request(1).create() if lockstep else None
        self._acked = acked.listener_builder().create() if lockstep else None
        self._readers: dict[int, list] = {}    # token -> [released sequence, depth, time]
        self.stalled = 0       # acking subscribers given up on (silent for stall_s)
        self.sequence = 0
        if lockstep:              # wakes acking readers, which then send their last ack
            self._notifier.notify()
        self.sent = 0          # frames sent
        self.undelivered = 0   # (frame, subscriber) deliveries refused: a full queue

    def subscriber_count(self) -> int:
        return int(self._pubsub.dynamic_config.number_of_subscribers)

    def loan(self, shape, dtype) -> ShmLoan:
        """A sample for one ``shape`` frame of ``dtype``; write ``loan.image``, then send."""
        dtype = np.dtype(dtype)
        if dtype not in DTYPE_CODES:
            raise ValueError(f"dtype {dtype} cannot travel (one of {list(DTYPE_CODES)})")
        rows, cols = shape
        sample = self._pub.loan_slice_uninit(int(rows) * int(cols) * dtype.itemsize)
        header = FrameHeader.from_address(sample.user_header_ptr)
        header.rows, header.cols, header.dtype, header.flags = rows, cols, DTYPE_CODES[dtype], 0
        return ShmLoan(sample, _view(sample.payload_ptr, (rows, cols), dtype), header)

    def _read_acks(self):
        now = time.monotonic()
        while True:
            sample = self._acks.receive()
            if sample is None:
                return
            a = sample.payload().contents
            token, seq, depth = a.token, a.sequence, a.depth
            sample.delete()
            if seq == FRESH:          # frames from the next one on reach it
                self._readers[token] = [self.sequence, depth, now]
            elif token in self._readers:
                r = self._readers[token]
                r[0], r[2] = max(r[0], seq), now
            else:
                self._readers[token] = [seq, depth, now]

    def wait_for_room(self, stop=None) -> None:
        """Lockstep: return when the next frame fits in every acking subscriber's queue
        (or ``stop()`` is true); a subscriber silent ``stall_s`` is dropped from the wait."""
        if not self.lockstep:
            return
        nxt = self.sequence + 1
        started = time.monotonic()
        while True:
            self._read_acks()
            now = time.monotonic()
            full = [t for t, (seq, depth, seen) in self._readers.items() if nxt - seq > depth]
            # acking readers not heard from yet (their ack publishers are counted)
            unheard = (self._ack_service.dynamic_config.number_of_publishers
                       > len(self._readers) and now - started < self.stall_s)
            if (not full and not unheard) or (stop is not None and stop()):
                return
            for t in full:
                if now - self._readers[t][2] > self.stall_s:
                    del self._readers[t]
                    self.stalled += 1
            self._acked.timed_wait(iox2.Duration.from_secs_f64(0.01))

    def send(self, loan: ShmLoan, stamp_ns: int, sensor: int = 0) -> int:
        """Send a loaned frame stamped ``stamp_ns``; the number of subscribers it reached.
        In lockstep, call :meth:`wait_for_room` first (before rendering into the loan)."""
        self.sequence += 1
        h = loan.header
        h.stamp_ns, h.sequence, h.sensor_id = int(stamp_ns), self.sequence, int(sensor)
        h.sent_ns = time.monotonic_ns()
        loan.image = loan.header = None          # the sample is no longer ours
        connected = self._pubsub.dynamic_config.number_of_subscribers
        reached = loan.sample.assume_init().send()
        loan.sample = None
        self._notifier.notify()
        self.sent += 1
        self.undelivered += max(0, connected - reached)
        return int(reached)

    def publish(self, image: np.ndarray, stamp_ns: int, sensor: int = 0) -> int:
        """Copy ``image`` into a loaned sample and send it (one copy; for a decoded bag)."""
        self.wait_for_room()
        loan = self.loan(image.shape, image.dtype)
        np.copyto(loan.image, image)
        return self.send(loan, stamp_ns, sensor)

    def close(self):
        for attr in ("_acked", "_acks", "_notifier", "_pub", "_event", "_pubsub", "_node"):
            obj = getattr(self, attr, None)
            if obj is not None and hasattr(obj, "delete"):
                obj.delete()
            setattr(self, attr, None)


class ShmFrame:
    """One received frame: header fields and ``image``, a read-only view of shared memory,
    valid until :meth:`release` (a context manager releases on exit)."""

    __slots__ = ("stamp_ns", "sequence", "sensor_id", "sent_ns", "image", "_sample", "_owner")

    def __init__(self, sample, owner=None):
        h = FrameHeader.from_address(sample.user_header_ptr)
        dtype = CODE_DTYPES.get(h.dtype)
        if dtype is None:
            sample.delete()
            raise ValueError(f"unknown dtype code {h.dtype} in a frame header")
        self.stamp_ns, self.sequence, self.sensor_id = h.stamp_ns, h.sequence, h.sensor_id
        self.sent_ns = h.sent_ns
        self.image = _view(sample.payload_ptr, (h.rows, h.cols), dtype)
        self.image.flags.writeable = False
        self._sample = sample
        self._owner = owner

    def release(self):
        """Give the sample back to the publisher (the view must not be used after)."""
        self.image = None
        if self._sample is not None:
            self._sample.delete()
            self._sample = None
            if self._owner is not None:
                self._owner._released(self.sequence)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


class ShmFrameSubscriber:
    """Receives frames of one topic in place; counts frames lost by sequence gaps.

    Args:
        name: the service (:func:`service_name`).
        depth: frames queued for this subscriber at most (1 to ``MAX_DEPTH``).
        ack: tell lockstep publishers which frames were released (they wait for it).
    """

    def __init__(self, name: str, depth: int = DEFAULT_DEPTH, ack: bool = False):
        _require()
        if not 1 <= int(depth) <= MAX_DEPTH:
            raise ValueError(f"depth must be 1 to {MAX_DEPTH}, got {depth}")
        self.name = name
        self._node = _node()
        self._pubsub, self._event, acks, acked = _services(self._node, name)
        self.depth = int(depth)
        self._sub = self._pubsub.subscriber_builder().buffer_size(self.depth).create()
        self._listener = self._event.listener_builder().create()
        self._ack_pub = self._notify_acked = None
        if ack:
            self._token = int.from_bytes(os.urandom(8), "little") & (FRESH - 1)
            self._ack_pub = acks.publisher_builder().create()
            self._notify_acked = acked.notifier_builder().create()
            self._ack(FRESH)
        self.received = 0       # frames taken
        self.lost = 0           # sequence gaps: frames sent but never received here
        self._last_seq = None

    def wait(self, timeout_s: float) -> bool:
        """Block until a frame is queued or ``timeout_s`` passes; True if one is queued."""
        if self._sub.has_samples():
            return True
        if self._ack_pub is not None:    # hands the last ack to publishers started since
            self._ack_pub.update_connections()
        self._listener.timed_wait(iox2.Duration.from_secs_f64(max(float(timeout_s), 0.0)))
        if self._ack_pub is not None:
            self._ack_pub.update_connections()
        return self._sub.has_samples()

    def take(self) -> ShmFrame | None:
        """The oldest queued frame, or None."""
        sample = self._sub.receive()
        if sample is None:
            return None
        frame = ShmFrame(sample, self if self._ack_pub is not None else None)
        seq = frame.sequence
        if self._last_seq is not None and seq > self._last_seq + 1:
            self.lost += seq - self._last_seq - 1
        # a lower sequence is a restarted publisher: start counting again from it
        self._last_seq = seq
        self.received += 1
        return frame

    def _ack(self, sequence: int):
        self._ack_pub.send_copy(Ack(self._token, sequence, self.depth))
        self._notify_acked.notify()

    def _released(self, sequence: int):
        if self._ack_pub is not None:
            self._ack(sequence)

    def drain(self, limit: int):
        """Yield up to ``limit`` queued frames (each released when the next is taken, or
        at the end: use a frame only inside the loop)."""
        for _ in range(limit):
            frame = self.take()
            if frame is None:
                return
            try:
                yield frame
            finally:
                frame.release()

    def close(self):
        for attr in ("_notify_acked", "_ack_pub", "_listener", "_sub", "_event", "_pubsub",
                     "_node"):
            obj = getattr(self, attr, None)
            if obj is not None and hasattr(obj, "delete"):
                obj.delete()
            setattr(self, attr, None)
