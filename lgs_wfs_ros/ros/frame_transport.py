"""The frame_transport parameters of a frame source (simulator, player) and the outlet they
configure (:class:`lgs_wfs_ros.transport.frames.FrameOutlet`)."""

from __future__ import annotations

import numpy as np

from ..transport import TRANSPORTS, frames, shm
from . import parameters


def declare_frame_transport(node):
    """The frame transport parameters of a frame source (simulator, player)."""
    parameters.declare(node, "frame_transport", "ros", "How frames reach the centroiders: "
                       "'ros' (the frame topic) or 'shm' (iceoryx2 shared memory, zero-copy; "
                       "the frame topic then gets frame_publish_hz of them).",
                       choices=TRANSPORTS, read_only=True)
    parameters.declare(node, "frame_publish_hz", 10.0, "With frame_transport shm: frames per "
                       "second also published on the frame topic (0: none).", low=0.0, high=1e5,
                       read_only=True)
    parameters.declare(node, "frame_lockstep", False, "With frame_transport shm: wait for the "
                       "readers instead of dropping frames (the source slows down).",
                       read_only=True)


def make_outlet(node, frame_pub, sensor) -> frames.FrameOutlet:
    """The node's :class:`~lgs_wfs_ros.transport.frames.FrameOutlet` from its parameters."""
    p = parameters.values(node, ("frame_transport", "frame_publish_hz", "frame_lockstep"))
    rows, cols = sensor.frame_shape
    try:
        return frames.FrameOutlet(
            p["frame_transport"], frame_pub, frame_pub.topic_name,
            rows * cols * np.dtype(sensor.dtype).itemsize, p["frame_publish_hz"],
            p["frame_lockstep"])
    except shm.ShmUnavailable as exc:
        raise ValueError(str(exc)) from exc


class FrameSource:
    """Mixin of the frame-source nodes (simulator, player): a frame thread ``_thread`` that
    watches ``_stop``, and an outlet ``_outlet``; stopped in that order before the node is
    destroyed. :meth:`_wake` rouses a thread waiting on something else than ``_stop``."""

    stop_timeout_s = 10.0

    def _wake(self) -> None:
        """Nothing to rouse by default."""

    def stop(self):
        self._stop.set()
        self._wake()
        self._thread.join(timeout=self.stop_timeout_s)
        self._outlet.close()

    def destroy_node(self):
        self.stop()                          # the frame thread and its shared memory first
        return super().destroy_node()
