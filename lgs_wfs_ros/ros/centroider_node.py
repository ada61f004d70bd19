"""centroider_node: frames in, per-subaperture slopes out, algorithm switchable at run time.

Subscribes to ``frame`` (raw CDR, decoded with numpy, no copy) and ``sensor``; publishes
``slopes`` (32FC2, G x G, the frame's stamp) and the transient-local ``centroider`` description.
Parameter changes are validated by building the new centroider in the on-set callback (a change
that cannot apply is refused with the reason and the old algorithm stays); the post-set callback
swaps it in, so it applies from the next frame.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from .. import bags
from ..centroiding import ALGORITHMS, make_centroider
from ..optics import geometry
from ..sensor import Sensor, SensorError
from ..transport import TRANSPORTS, frames as frame_transport, shm
from .spinning import DRAIN, run_node, take_queued
from . import parameters, qos

OPTION_PARAMS = ("model", "cmf_update_period", "cmf_reference", "tcog_threshold", "options")


class FrameCounters:
    """What happened to the frames this node saw."""

    def __init__(self):
        self.received = self.processed = self.dropped = self.rejected = 0
        self.computed = self.published = 0      # centroids computed, slopes published
        self.transport_lost = 0                 # shm: frames sent that never arrived (sequence)
        self.last_reason = ""

    def as_dict(self) -> dict:
        return {"received": self.received, "processed": self.processed,
                "dropped": self.dropped, "rejected": self.rejected,
                "taken": self.received, "computed": self.computed,
                "published": self.published, "transport_lost": self.transport_lost}

# frames up to this many pixels (the paper's single subaperture, small test pupils) are
# centroided in batches when several are queued
BATCH_PIXELS = 64 * 64


class CentroiderNode(Node):
    def __init__(self, **kwargs):
        kwargs.setdefault("namespace", "wfs")
        super().__init__("centroider_node", **kwargs)
        parameters.declare(self, "algorithm", "cog", "Centroiding algorithm.", choices=ALGORITHMS)
        parameters.declare(self, "model", "", "ann: ONNX model path or name in models/ "
                           "(empty: the default model).")
        parameters.declare(self, "cmf_update_period", 1, "cmf: frames between filter updates.",
                           low=1, high=100000)
        parameters.declare(self, "cmf_reference", "history", "cmf: where the reference comes from.",
                           choices=("history", "model"))
        parameters.declare(self, "tcog_threshold", 0.0, "tcog: threshold in counts.",
                           low=0.0, high=65535.0)
        parameters.declare(self, "options", "{}", "Extra algorithm options as a JSON object.")
        parameters.declare(self, "sensor_json", "", "Sensor description to use until one "
                           "arrives on the sensor topic (empty: the default sensor).")
        parameters.declare(self, "log_period_s", 5.0, "Seconds between counter log lines.",
                           low=0.1, high=3600.0)
        parameters.declare(self, "frame_transport", "ros", "Where frames come from: 'ros' (the "
                           "frame topic) or 'shm' (iceoryx2 shared memory, read in place).",
                           choices=TRANSPORTS, read_only=True)

        self.counters = FrameCounters()
        self._lock = threading.Lock()
        self._pending = None
        self._last_stamp = None
        self.sensor = self._initial_sensor()
        self.layout = geometry.layout(self.sensor)
        self.centroider = None
        try:
            self.centroider = self._build(self._settings())
        except ValueError as exc:
            if self.get_parameter("algorithm").value not in ALGORITHMS:
                raise
            # e.g. a polar-only model on the default (cartesian) sensor: the real sensor
            # description usually arrives on the sensor topic a moment later.
            self.get_logger().warning(f"waiting for a sensor this algorithm can run on: {exc}")

        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)

        self._slopes_pub = self.create_publisher(Image, "slopes", qos.SLOPES)
        self._desc_pub = self.create_publisher(String, "centroider", qos.LATCHED)
        self._frame_sub = self._inlet = None
        self._sensor_id = shm.sensor_id(self.sensor)
        self._shm = self.get_parameter("frame_transport").value == "shm"
        self._subscribe_frames(self.sensor)
        self.create_subscription(String, "sensor", self._on_sensor, qos.LATCHED)
        self._log_timer = self.create_timer(self.get_parameter("log_period_s").value,
                                            self._log_counters)
        self._announce("start")

    # -- configuration ---------------------------------------------------------------
    def _initial_sensor(self) -> Sensor:
        text = self.get_parameter("sensor_json").value
        return Sensor.from_json(text) if text else Sensor()

    def _settings(self, overrides: dict | None = None) -> dict:
        s = parameters.values(self, ("algorithm",) + OPTION_PARAMS)
        s.update(overrides or {})
        return s

    def _build(self, settings: dict, sensor: Sensor | None = None):
        """Make the centroider the settings ask for; ValueError with the reason if impossible."""
        sensor = sensor or self.sensor
        name = settings["algorithm"]
        try:
            options = json.loads(settings["options"] or "{}")
        except json.JSONDecodeError as exc:
            raise ValueError(f"options is not a JSON object: {exc}") from exc
        if not isinstance(options, dict):
            raise ValueError("options must be a JSON object")
        if name == "ann" and settings["model"]:
            options.setdefault("model", settings["model"])
        elif name == "cmf":
            options.setdefault("update_period", int(settings["cmf_update_period"]))
            options.setdefault("reference", settings["cmf_reference"])
        elif name == "tcog" and settings["tcog_threshold"] > 0:
            options.setdefault("threshold", float(settings["tcog_threshold"]))
        return make_centroider(name, sensor, **options)

    def _validate(self, params):
        changes = {p.name: p.value for p in params}
        if "algorithm" in changes and changes["algorithm"] not in ALGORITHMS:
            return parameters.refuse(f"unknown algorithm {changes['algorithm']!r}; "
                                     f"choose one of {', '.join(ALGORITHMS)}")
        if "sensor_json" in changes and changes["sensor_json"]:
            try:
                Sensor.from_json(changes["sensor_json"])
            except (SensorError, TypeError) as exc:
                return parameters.refuse(str(exc))
        if set(changes) & ({"algorithm"} | set(OPTION_PARAMS)):
            try:
                self._pending = self._build(self._settings(changes))
            except (ValueError, OSError, RuntimeError) as exc:
                self._pending = None
                return parameters.refuse(f"cannot apply: {exc}")
        return parameters.accept()

    def _apply(self, params):
        if self._pending is not None:
            with self._lock:
                self.centroider, self._pending = self._pending, None
            self._announce("parameter change")

    def _announce(self, why: str):
        if self.centroider is None:
            return
        try:
            desc = self.centroider.describe()
        except Exception as exc:  # describe() must never take the node down
            desc = {"algorithm": self.get_parameter("algorithm").value, "error": str(exc)}
        desc.update(reason=why, time_ns=time.time_ns(), sensor_grid=self.sensor.grid)
        self._desc_pub.publish(String(data=json.dumps(desc, default=str)))
        self.get_logger().info(f"centroider: {desc.get('algorithm')} ({why})")

    def _on_sensor(self, msg: String):
        try:
            sensor = Sensor.from_json(msg.data)
        except (SensorError, TypeError) as exc:
            self.get_logger().error(f"ignoring an invalid sensor description: {exc}")
            return
        if sensor == self.sensor:
            return
        try:
            centroider = self._build(self._settings(), sensor)
        except (ValueError, OSError, RuntimeError) as exc:
            self.get_logger().error(f"new sensor arrived but the algorithm cannot run on it: {exc}")
            return
        self._subscribe_frames(sensor)
        with self._lock:
            self.sensor, self.layout, self.centroider = sensor, geometry.layout(sensor), centroider
            self._sensor_id = shm.sensor_id(sensor)
            self._last_stamp = None
        self._announce("new sensor")

    def _subscribe_frames(self, sensor: Sensor):
        """(Re)create the frame subscription with a queue sized for the sensor's rate and
        frame size (``qos.frame_qos``: 0.14 s of frames); kept when the depth is unchanged."""
        if self._shm:       # frames come through shared memory: one inlet, never recreated
            if self._inlet is None:      # (that would lose its queue; the depth is the most
                try:                     # the service allows, whatever the sensor)
                    self._inlet = frame_transport.FrameInlet(
                        self.resolve_topic_name("frame"), self._on_shm_frames, shm.MAX_DEPTH)
                except shm.ShmUnavailable as exc:
                    raise ValueError(str(exc)) from exc
            return
        profile = qos.frame_qos(sensor)
        if self._frame_sub is not None:
            if self._frame_sub.qos_profile.depth == profile.depth:
                return
            self.destroy_subscription(self._frame_sub)
        self._frame_sub = self.create_subscription(Image, "frame", self._on_frame, profile,
                                                   raw=True)

    # -- frames ---------------------------------------------------------------------
    def _reject(self, reason: str):
        self.counters.rejected += 1
        self.counters.last_reason = reason
        self.get_logger().warning(f"frame rejected: {reason}", throttle_duration_sec=2.0)

    def _on_frame(self, cdr: bytes):
        """One frame from the executor, then up to DRAIN more taken directly: rclpy's executor
        costs ~0.3 ms of Python per message (wait set, task), more than a single-subaperture
        frame's whole budget at 5 kHz. The accepted small frames of one drain are centroided
        in one vectorised call (``centroid_many``), in time order; full frames one by one
        (batching them only adds memory traffic and latency)."""
        batch = [self._accept(cdr)]
        for queued in take_queued(self._frame_sub, Image, DRAIN):
            batch.append(self._accept(queued[0]))
        self._centroid_and_publish([b for b in batch if b is not None])

    def _on_shm_frames(self, frames, lost: int):
        """Frames read in place from shared memory (the inlet's thread): ``[(stamp_ns,
        image, sensor_id)]``, valid during this call; small ones centroided together."""
        self.counters.transport_lost = lost
        accepted = []
        for stamp_ns, image, sensor_id in frames:
            self.counters.received += 1
            if sensor_id and sensor_id != self._sensor_id:
                self._await_sensor(sensor_id)
            if sensor_id and sensor_id != self._sensor_id:
                self._reject(f"frame of another sensor (id {sensor_id:x}, expected "
                             f"{self._sensor_id:x}): its description has not arrived yet")
                continue
            ok = self._check(stamp_ns, image)
            if ok is not None:
                accepted.append(ok)
        try:
            self._centroid_and_publish(accepted)
        except Exception:      # a publish after SIGINT shut the context down
            if self.context.ok():
                raise

    def _await_sensor(self, sensor_id: int, timeout_s: float = 2.0):
        """Shared-memory frames can overtake the sensor description (a ROS topic): wait for
        it once per unknown sensor id (this is the inlet's thread; the frames queue)."""
        waited = self.__dict__.setdefault("_sensor_ids_waited", set())
        if sensor_id in waited:
            return
        waited.add(sensor_id)
        deadline = time.monotonic() + timeout_s
        while sensor_id != self._sensor_id and time.monotonic() < deadline:
            time.sleep(0.005)

    def _centroid_and_publish(self, batch):
        """Centroid ``[(stamp_ns, image)]`` and publish their slopes, in order."""
        if not batch:
            return
        with self._lock:
            centroider, layout = self.centroider, self.layout
            slopes = None
            if len(batch) > 1 and np.prod(self.sensor.frame_shape) <= BATCH_PIXELS:
                try:
                    slopes = centroider.centroid_many([image for _, image in batch])
                except Exception:      # find the frame at fault: one call per frame below
                    slopes = None
            results = []
            for j, (stamp_ns, image) in enumerate(batch):
                if slopes is not None:
                    s = slopes[j]
                else:
                    try:
                        s = centroider.centroid(image)
                    except Exception as exc:   # an algorithm fault costs this frame, not the node
                        self._reject(f"{centroider.name} failed on this frame: {exc!r}")
                        continue
                results.append((stamp_ns, geometry.slopes_to_grid(s, layout)))
        self.counters.computed += len(results)
        for stamp_ns, grid in results:
            self._slopes_pub.publish(bags.encode_image(grid, stamp_ns))
            self.counters.processed += 1
            self.counters.published += 1

    def _accept(self, cdr: bytes):
        """Decode and check one frame: ``(stamp_ns, image)``, or None (counted as rejected)."""
        self.counters.received += 1
        try:
            stamp_ns, _frame_id, encoding, image = bags.decode_image(cdr)
        except Exception as exc:
            self._reject(f"undecodable Image: {exc}")
            return None
        if encoding not in ("mono16", "32FC1"):
            self._reject(f"encoding {encoding!r}, expected mono16 or 32FC1")
            return None
        return self._check(stamp_ns, image)

    def _check(self, stamp_ns: int, image):
        """``(stamp_ns, image)`` if the frame fits the sensor and comes after the last one;
        None otherwise (counted as rejected; stamp gaps counted as dropped)."""
        with self._lock:
            if image.shape != self.sensor.frame_shape:
                self._reject(f"shape {image.shape}, the sensor expects {self.sensor.frame_shape}")
                return None
            if self._last_stamp is not None and stamp_ns <= self._last_stamp:
                self._reject(f"stamp {stamp_ns} not after the previous {self._last_stamp}")
                return None
            if self._last_stamp is not None:
                period_ns = 1e9 / self.sensor.frame_rate_hz
                self.counters.dropped += max(0, int(round((stamp_ns - self._last_stamp) / period_ns)) - 1)
            if self.centroider is None:
                self._reject("no centroider yet: the algorithm cannot run on the current sensor")
                return None
            self._last_stamp = stamp_ns
        return stamp_ns, image

    def destroy_node(self):
        if self._inlet is not None:          # stop reading shared memory first
            self._inlet.close()
            self._inlet = None
        return super().destroy_node()

    def _log_counters(self):
        c = self.counters
        self.get_logger().info(
            f"frames received {c.received}, processed {c.processed}, dropped {c.dropped}, "
            f"rejected {c.rejected}" + (f" (last: {c.last_reason})" if c.rejected else ""))


def _final_counts(node) -> None:
    print(f"centroider_node: final counts {json.dumps(node.counters.as_dict())}", flush=True)


def main(args=None):
    return run_node("centroider_node", CentroiderNode, refused=(ValueError, SensorError),
                    finish=_final_counts, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
