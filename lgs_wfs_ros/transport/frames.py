"""Frame source and sink objects the nodes use, whatever the transport.

:class:`FrameOutlet` (simulator, player): ``loan(shape, dtype)`` gives a buffer to render or
decode into (shared memory with ``shm``, a plain array with ``ros``), ``send(buf, stamp_ns)``
sends it. With ``shm`` the ROS ``frame`` topic still gets frames, decimated to
``publish_hz`` (0: none), so ``ros2 topic``, rviz, Foxglove and the recorder see them.
:class:`FrameInlet` (centroider): a thread that waits for shared-memory frames and hands each
one, read in place, to a callback ``on_frame(stamp_ns, image, sensor_id)``; the image is only
valid during the call.

Neither knows ROS beyond the publisher object it is given (``publish(bytes)``).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from .. import bags
from . import shm

DRAIN = 16       # shared-memory frames handled per wake-up at most (<= shm.MAX_BORROWED)


def topic_service(topic: str) -> str:
    """The shared-memory service of a resolved ROS topic (``/wfs/frame``)."""
    namespace, _, name = topic.rpartition("/")
    return shm.service_name(namespace, name)


class FrameOutlet:
    """Where a source's frames go.

    Args:
        transport: ``ros`` or ``shm``.
        ros_publisher: the node's ``frame`` publisher (gets every frame with ``ros``).
        topic: the resolved ``frame`` topic (names the shared-memory service).
        frame_bytes: the largest frame expected, bytes.
        publish_hz: with ``shm``, frames per second also published on ROS (0: none).
        lockstep: with ``shm``, wait for every acking reader instead of dropping.
    """

    def __init__(self, transport: str, ros_publisher, topic: str, frame_bytes: int,
                 publish_hz: float = 10.0, lockstep: bool = False):
        if transport not in ("ros", "shm"):
            raise ValueError(f"frame_transport must be 'ros' or 'shm', got {transport!r}")
        self.transport = transport
        self._ros = ros_publisher
        self.publish_hz = float(publish_hz)
        self._next_ros = 0.0
        self.shm = (shm.ShmFramePublisher(topic_service(topic), frame_bytes,
                                          lockstep=lockstep) if transport == "shm" else None)
        self.sent = 0            # frames sent on the transport
        self.ros_published = 0   # frames published on the ROS topic

    def wait_for_room(self, stop=None):
        """Lockstep: block until the next frame can go without a drop."""
        if self.shm is not None:
            self.shm.wait_for_room(stop)

    def loan(self, shape, dtype):
        """A buffer for one frame; write ``.image`` in place, then :meth:`send` it."""
        if self.shm is not None:
            return self.shm.loan(shape, dtype)
        return _Plain(np.empty(shape, dtype))

    def send(self, buf, stamp_ns: int, sensor_id: int = 0):
        image = buf.image
        if self.shm is None:
            self._ros.publish(bags.encode_image(image, stamp_ns))
            self.ros_published += 1
        else:
            now = time.monotonic()
            if self.publish_hz > 0 and now >= self._next_ros:   # before the loan goes
                period = 1.0 / self.publish_hz
                self._next_ros += period
                if self._next_ros < now:        # late or first: one period from now
                    self._next_ros = now + period
                self._ros.publish(bags.encode_image(image, stamp_ns))
                self.ros_published += 1
            self.shm.send(buf, stamp_ns, sensor_id)
        self.sent += 1

    def subscriber_count(self) -> int:
        """Readers of this transport's frames (ROS subscriptions of ``frame`` with ``ros``)."""
        if self.shm is not None:
            return self.shm.subscriber_count()
        return self._ros.get_subscription_count()

    def publish(self, image: np.ndarray, stamp_ns: int, sensor_id: int = 0, stop=None):
        """Send an existing array (one copy into the loan with ``shm``)."""
        self.wait_for_room(stop)
        buf = self.loan(image.shape, image.dtype)
        np.copyto(buf.image, image)
        self.send(buf, stamp_ns, sensor_id)

    def counters(self) -> dict:
        d = {"sent": self.sent, "ros_published": self.ros_published}
        if self.shm is not None:
            d.update(undelivered=self.shm.undelivered, stalled=self.shm.stalled)
        return d

    def close(self):
        if self.shm is not None:
            self.shm.close()
            self.shm = None


class _Plain:
    __slots__ = ("image",)

    def __init__(self, image):
        self.image = image


class FrameInlet:
    """Shared-memory frames of a resolved topic handed, up to ``DRAIN`` at a time, to
    ``on_frames([(stamp_ns, image, sensor_id)], lost)`` on a thread of its own (the images
    are valid during the call; ``lost``: frames the publisher sent that never came). Acks
    every released frame, so lockstep publishers wait for this reader."""

    def __init__(self, topic: str, on_frames, depth: int = shm.DEFAULT_DEPTH):
        self.depth = int(depth)
        self._sub = shm.ShmFrameSubscriber(topic_service(topic), depth=self.depth, ack=True)
        self._on_frames = on_frames
        self._stop = threading.Event()
        self._closed_in_thread = False
        self._thread = threading.Thread(target=self._run, name="frame-inlet", daemon=True)
        self._thread.start()

    def _run(self):
        try:
            self._loop()
        finally:
            if self._closed_in_thread:
                self._sub.close()

    def _loop(self):
        while not self._stop.is_set():
            if not self._sub.wait(0.1):
                continue
            held = []
            try:
                for _ in range(DRAIN):
                    frame = self._sub.take()
                    if frame is None:
                        break
                    held.append(frame)
                if held:
                    self._on_frames([(f.stamp_ns, f.image, f.sensor_id) for f in held],
                                    self._sub.lost)
            finally:
                for f in held:
                    f.release()

    def close(self):
        """Stop the thread and the subscriber; from the callback itself (a reader that stops
        on what it read), only stop: the thread ends after the call."""
        if threading.current_thread() is self._thread:
            self._closed_in_thread = True
            self._stop.set()
            return
        self._stop.set()
        self._thread.join(timeout=5)
        self._sub.close()
