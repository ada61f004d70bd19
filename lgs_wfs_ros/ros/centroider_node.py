"""centroider_node: frames in, per-subaperture slopes out, algorithm switchable at run time.

Subscribes to ``frame`` (raw CDR, decoded with numpy, no copy) and ``sensor``; publishes
``slopes`` (32FC2, G x G, the frame's stamp) and the transient-local ``centroider`` description.
Parameter changes are validated by building the new centroider in the on-set callback (a change
that cannot apply is refused with the reason and the old algorithm stays); the post-set callback
swaps it in, so it applies from the next frame.

Parameters: ``algorithm`` and one typed parameter per algorithm option, ``<algorithm>.<option>``
(``cmf.reference``, ``ann.model``, ...), generated from ``centroiding.options.OPTIONS`` with
its descriptions, ranges, choices and read-only flags; the centroider is
``options.build(algorithm, sensor, options.from_parameters(algorithm, values))``, the same
call replay and the Python API make. Also publishes ``slopes_picture`` (rgb8, x and y maps
side by side, a few Hz) and ``slope_error`` (Vector3Stamped: rms error against
``true_slopes`` in x, y and total, pixels, ~10 Hz), each only while someone subscribes, and
its state on ``/diagnostics``.
A centroider that cannot be built (model missing, a sensor it cannot run on) leaves the node
running, its cause logged once and on ``/diagnostics``, until a parameter or sensor fixes it.
"""

from __future__ import annotations

import collections
import json
import threading
import time

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from .. import bags
from ..centroiding import ALGORITHMS, notice_of, options
from ..centroiding.ann_model import ModelNotFoundError
from ..optics import geometry
from ..sensor import Sensor, SensorError
from ..transport import TRANSPORTS, frames as frame_transport, shm
from .handover import Handover
from .spinning import DRAIN, run_node, take_queued
from . import health, parameters, picture, qos


def option_rows() -> dict:
    """Every algorithm option as ``{"<algorithm>.<option>": Option}`` (centroiding.options)."""
    return {opt.parameter: opt for rows in options.OPTIONS.values() for opt in rows}


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
#: an inline refit that holds the frame path longer than this (s) and is followed by missing
#: frames is named as their likely cause, once (:meth:`CentroiderNode._note_inline_refit`)
INLINE_REFIT_NOTE_S = 0.05


class CentroiderNode(Node):
    def __init__(self, **kwargs):
        kwargs.setdefault("namespace", "wfs")
        super().__init__("centroider_node", **kwargs)
        parameters.declare(self, "algorithm", "cog", "Centroiding algorithm; its options are "
                           "the <algorithm>.<option> parameters.", choices=ALGORITHMS)
        self.option_rows = option_rows()
        for opt in self.option_rows.values():
            parameters.declare_option(self, opt)
        parameters.declare(self, "sensor_json", "", "Sensor description to use until one "
                           "arrives on the sensor topic (empty: the default sensor).")
        parameters.declare(self, "log_period_s", 10.0, "Seconds between counter log lines "
                           "(written only when the counters changed).",
                           low=0.1, high=3600.0)
        parameters.declare(self, "picture_hz", 5.0, "Rate of the slopes_picture image "
                           "(rgb8: x and y slope maps side by side; 0: off), Hz.",
                           low=0.0, high=100.0)
        parameters.declare(self, "error_hz", 10.0, "Rate of slope_error (rms of slopes - "
                           "true_slopes over the valid subapertures, pixels: vector x, y and "
                           "z = total), computed only while someone subscribes; 0: off), Hz.",
                           low=0.0, high=1000.0)
        parameters.declare(self, "picture_range_px", 2.0, "Slope shown at full colour in "
                           "slopes_picture (blue -range, white 0, red +range), pixels.",
                           low=1e-3, high=100.0)
        parameters.declare(self, "frame_transport", "ros", "Where frames come from: 'ros' (the "
                           "frame topic) or 'shm' (iceoryx2 shared memory, read in place).",
                           choices=TRANSPORTS, read_only=True)

        self.counters = FrameCounters()
        self.health = health.Health(self, self._diagnostic_values)
        self._lock = threading.Lock()
        self._pending = None
        self._last_stamp = None
        self._sensor_received = False
        self._next_picture = 0.0
        self._last_line = ""
        self._notice = ""        # the centroider's notice last announced (Centroider.notice)
        self._held_s = 0.0       # the longest inline refit on the frame path since a drop
        self.sensor = self._initial_sensor()
        self.layout = geometry.layout(self.sensor)
        self.centroider = None
        self.problem = ""        # why there is no centroider ("" when there is one)
        try:
            self.centroider = self._build(self._settings())
        except ModelNotFoundError as exc:
            self._no_centroider(f"model missing: {exc}")
        except ValueError as exc:
            if self.get_parameter("algorithm").value not in ALGORITHMS:
                raise
            # e.g. a polar-only model on the default (cartesian) sensor: the real sensor
            # description usually arrives on the sensor topic a moment later.
            # normal at start-up, hence INFO and an OK state; an ERROR if the sensor that
            # comes cannot run it either (_on_sensor)
            self._no_centroider(f"{self.get_parameter('algorithm').value} cannot run on the "
                                f"default sensor, waiting for one on the sensor topic: {exc}",
                                health.OK)

        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)

        self._slopes_pub = self.create_publisher(Image, "slopes", qos.SLOPES)
        self._picture_pub = self.create_publisher(Image, "slopes_picture", qos.PICTURE)
        self._desc_pub = self.create_publisher(String, "centroider", qos.LATCHED)
        self._error_pub = self.create_publisher(Vector3Stamped, "slope_error", qos.SLOPES)
        self._truth_sub = None
        self._truth = None                           # (stamp, grid) waiting for its slopes
        self._recent = collections.OrderedDict()     # stamp -> slopes grid, while measured
        self._next_error = 0.0
        self.create_timer(1.0, self._follow_error_subscribers)
        self.incompatible_frame_publishers: set[str] = set()     # warned of, once each
        self.create_timer(1.0, self._check_frame_publishers)
        self._frame_sub = self._inlet = None
        self._handover = None            # a frame queue change under way (handover.py)
        self._sensor_id = shm.sensor_id(self.sensor)
        self._shm = self.get_parameter("frame_transport").value == "shm"
        self._subscribe_frames(self.sensor)
        self._sensor_sub = self.create_subscription(String, "sensor", self._on_sensor,
                                                    qos.LATCHED)
        self._log_timer = self.create_timer(self.get_parameter("log_period_s").value,
                                            self._log_counters)
        self._announce("start")

    # -- configuration ---------------------------------------------------------------
    def _initial_sensor(self) -> Sensor:
        text = self.get_parameter("sensor_json").value
        return Sensor.from_json(text) if text else Sensor()

    def _no_centroider(self, why: str, level=health.ERROR):
        self.problem = why
        self.health.set_state(level, f"no centroider: {why}")

    def _settings(self, overrides: dict | None = None) -> dict:
        s = parameters.values(self, ("algorithm",) + tuple(self.option_rows))
        s.update(overrides or {})
        return s

    def _build(self, settings: dict, sensor: Sensor | None = None):
        """Make the centroider the settings ask for; ValueError with the reason if impossible."""
        name = settings["algorithm"]
        return options.build(name, sensor or self.sensor, options.from_parameters(name, settings))

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
        try:
            for name in set(changes) & set(self.option_rows):
                options.coerce(self.option_rows[name], changes[name])
        except ValueError as exc:
            return parameters.refuse(str(exc))
        algorithm = changes.get("algorithm", self.get_parameter("algorithm").value)
        if "algorithm" in changes or any(n.startswith(algorithm + ".") for n in changes):
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
            self.problem = ""
            self._announce("parameter change")

    def _announce(self, why: str):
        if self.centroider is None:
            return
        try:
            desc = self.centroider.describe()
        except Exception as exc:  # describe() must never take the node down
            desc = {"algorithm": self.get_parameter("algorithm").value, "error": str(exc)}
        self._notice = notice_of(self.centroider)
        desc.update(reason=why, time_ns=time.time_ns(), sensor_grid=self.sensor.grid)
        self._desc_pub.publish(String(data=json.dumps(desc, default=str)))
        self.get_logger().info(f"centroider: {desc.get('algorithm')} ({why})")
        if desc.get("warning"):          # e.g. ann run outside its model's training domain
            self.get_logger().warning(str(desc["warning"]))
        self.health.set_state(health.OK, "running", log=False)

    def _on_sensor(self, msg: String):
        try:
            sensor = Sensor.from_json(msg.data)
        except (SensorError, TypeError) as exc:
            self.health.note("invalid sensor description ignored", str(exc), health.ERROR)
            return
        self._sensor_received = True
        if sensor == self.sensor and self.centroider is not None:
            return
        try:
            centroider = self._build(self._settings(), sensor)
        except ModelNotFoundError as exc:
            self._no_centroider(f"model missing: {exc}")
            return
        except (ValueError, OSError, RuntimeError) as exc:
            self._no_centroider(f"the algorithm cannot run on the sensor received: {exc}")
            return
        self._subscribe_frames(sensor)
        with self._lock:
            self.sensor, self.layout, self.centroider = sensor, geometry.layout(sensor), centroider
            self._sensor_id = shm.sensor_id(sensor)
            self._last_stamp = None
        self.problem = ""
        self._announce("new sensor")

    def _subscribe_frames(self, sensor: Sensor):
        """(Re)create the frame subscription with a queue sized for the sensor's rate and
        frame size (``qos.frame_qos``: 0.14 s of frames); kept when the depth is unchanged.
        The old subscription is handed over, not dropped (:class:`handover.Handover`)."""
        if self._shm:       # frames come through shared memory: one inlet, never recreated
            if self._inlet is None:      # (that would lose its queue; the depth is the most
                try:                     # the service allows, whatever the sensor)
                    self._inlet = frame_transport.FrameInlet(
                        self.resolve_topic_name("frame"), self._on_shm_frames, shm.MAX_DEPTH)
                except shm.ShmUnavailable as exc:
                    raise ValueError(str(exc)) from exc
            return
        profile = qos.frame_qos(sensor)
        old = self._frame_sub
        if old is not None and old.qos_profile.depth == profile.depth:
            return
        new = self.create_subscription(
            Image, "frame", lambda cdr, info: self._on_frame(cdr, info, new), profile, raw=True,
            event_callbacks=qos.replaceable())
        self._frame_sub = new
        if old is None:
            return
        last, self._handover = self._handover, Handover(self, old, new, Image)
        if last is not None:             # changed again before the last change ended
            self._centroid_taken(last.finish_old())
            self._handover.seen |= last.seen

    def _take_waiting_sensor(self):
        """Apply a sensor description already waiting on the sensor topic: after a slow
        start the executor may serve the frame queue first, and its frames would be judged
        against the default sensor."""
        for msg, _ in take_queued(self._sensor_sub, String, 1, raw=False):
            self._on_sensor(msg)

    # -- frames ---------------------------------------------------------------------
    def _reject(self, condition: str, detail: str = "", level=health.WARN):
        """Count a rejected frame; its condition is logged the first time only."""
        self.counters.rejected += 1
        self.counters.last_reason = condition + (f": {detail}" if detail else "")
        self.health.note(f"frames rejected, {condition}", detail, level)

    def _on_frame(self, cdr: bytes, info: dict, sub):
        """One frame from the executor (``info``: its message info; ``sub``: the subscription
        that gave it), then up to DRAIN more taken directly: rclpy's executor costs ~0.3 ms
        of Python per message (wait set, task), more than a single-subaperture frame's whole
        budget at 5 kHz. The accepted small frames of one drain are centroided in one
        vectorised call (``centroid_many``), in time order; full frames one by one (batching
        them only adds memory traffic and latency). During a queue change the handover
        decides what is taken (every frame of both queues, once)."""
        if not self._sensor_received:
            self._take_waiting_sensor()
        hand = self._handover
        if hand is not None:
            taken = hand.take((cdr, info), sub is hand.new)
            if hand.over:
                self._handover = None
        else:
            taken = [(cdr, info)] + list(take_queued(sub, Image, DRAIN))
        self._centroid_taken(taken)

    def _centroid_taken(self, taken) -> None:
        """Check, centroid and publish ``[(cdr, info)]`` taken from the frame queue."""
        batch = [self._accept(cdr) for cdr, _ in taken]
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
        """Centroid ``[(stamp_ns, image)]`` and publish their slopes, in order. Small frames
        of a batch are centroided in one call, then published; full frames one at a time,
        each published before the next is centroided (a burst of 16 full frames after a
        stalled source would otherwise hold the first frame's slopes ~8 ms)."""
        if not batch:
            return
        if len(batch) > 1 and np.prod(self.sensor.frame_shape) <= BATCH_PIXELS:
            self._publish(self._centroid(batch))
        else:
            for frame in batch:
                self._publish(self._centroid([frame]))
        self._follow_notice()

    def _follow_notice(self) -> None:
        """Republish the description, and log it once, when the centroider's notice
        changes (e.g. a network's calibrated sky leaving its training profiles, or coming
        back, at a refit)."""
        centroider = self.centroider
        if centroider is not None and notice_of(centroider) != self._notice:
            self._announce("notice" if notice_of(centroider) else "notice cleared")

    def _centroid(self, batch) -> list:
        """``[(stamp_ns, slope grid)]`` of ``[(stamp_ns, image)]``; a frame the algorithm
        fails on is counted and left out."""
        with self._lock:
            centroider, layout = self.centroider, self.layout
            pupil = getattr(centroider, "pupil", None)
            fits = pupil.fits if pupil is not None else None
            started = time.monotonic()
            slopes = None
            if len(batch) > 1:
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
                        self._reject(f"{centroider.name} failed on a frame", repr(exc), health.ERROR)
                        continue
                results.append((stamp_ns, geometry.slopes_to_grid(s, layout)))
            if pupil is not None and pupil.fits != fits and not pupil.asynchronous:
                self._held_s = max(self._held_s, time.monotonic() - started)
        self.counters.computed += len(results)
        return results

    def _publish(self, results) -> None:
        """Publish ``[(stamp_ns, slope grid)]``, then the picture and error if due."""
        for stamp_ns, grid in results:
            self._slopes_pub.publish(bags.encode_image(grid, stamp_ns))
            self.counters.processed += 1
            self.counters.published += 1
        if results:
            self._maybe_picture(*results[-1])
            if self._truth_sub is not None:
                for stamp_ns, grid in results:
                    self._recent[stamp_ns] = grid
                while len(self._recent) > 64:
                    self._recent.popitem(last=False)
                self._publish_error()

    def _check_frame_publishers(self):
        """Warn once of each frame publisher this node cannot hear (its subscription has no
        incompatible-QoS handler: :func:`.qos.replaceable`)."""
        sub = self._frame_sub
        if sub is not None:
            for who in qos.new_incompatible(self, sub, self.incompatible_frame_publishers):
                self.get_logger().warning(f"no frames from {who} on {sub.topic_name}")

    # -- error against the truth, for plots (only while slope_error has subscribers) ------
    def _follow_error_subscribers(self):
        """Subscribe to true_slopes while slope_error has subscribers (a 700 Hz callback
        costs CPU nobody would use otherwise)."""
        want = (self.get_parameter("error_hz").value > 0
                and self._error_pub.get_subscription_count() > 0)
        if want and self._truth_sub is None:
            self._truth_sub = self.create_subscription(Image, "true_slopes", self._on_truth,
                                                       qos.SLOPES, raw=True,
                                                       event_callbacks=qos.replaceable())
        elif not want and self._truth_sub is not None:
            self.destroy_subscription(self._truth_sub)
            self._truth_sub, self._truth = None, None
            self._recent.clear()

    def _on_truth(self, cdr: bytes):
        if time.monotonic() < self._next_error:
            return
        try:
            stamp_ns, _, _, truth = bags.decode_image(cdr)
        except Exception as exc:
            self.health.note("undecodable true_slopes ignored", str(exc))
            return
        self._truth = (stamp_ns, np.array(truth))
        self._publish_error()

    def _publish_error(self):
        """rms (slopes - truth) of the waiting truth's frame, once its slopes exist."""
        if self._truth is None or self._truth[0] not in self._recent:
            return
        stamp_ns, truth = self._truth
        grid = self._recent[stamp_ns]
        self._truth = None
        if grid.shape != truth.shape:
            return
        d = grid - truth
        d = d[np.isfinite(d).all(axis=-1)]          # (n valid, 2)
        if not len(d):
            return
        ex, ey = np.sqrt(np.mean(d ** 2, axis=0)).tolist()
        msg = Vector3Stamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 10**9)
        msg.header.frame_id = "wfs"
        msg.vector.x, msg.vector.y, msg.vector.z = ex, ey, float(np.hypot(ex, ey))
        self._error_pub.publish(msg)
        self._next_error = time.monotonic() + 1.0 / self.get_parameter("error_hz").value

    def _accept(self, cdr: bytes):
        """Decode and check one frame: ``(stamp_ns, image)``, or None (counted as rejected)."""
        self.counters.received += 1
        try:
            stamp_ns, _frame_id, encoding, image = bags.decode_image(cdr)
        except Exception as exc:
            self._reject("undecodable Image", str(exc))
            return None
        if encoding not in ("mono16", "32FC1"):
            self._reject(f"encoding {encoding}", "expected mono16 or 32FC1")
            return None
        return self._check(stamp_ns, image)

    def _check(self, stamp_ns: int, image):
        """``(stamp_ns, image)`` if the frame fits the sensor and comes after the last one;
        None otherwise (counted as rejected; stamp gaps counted as dropped)."""
        with self._lock:
            if image.shape != self.sensor.frame_shape:
                if not self._sensor_received:
                    self._reject("frames before the sensor description",
                                 f"shape {image.shape}; waiting for the sensor topic", health.OK)
                else:
                    self._reject(f"shape {image.shape}",
                                 f"the sensor expects {self.sensor.frame_shape}")
                return None
            if self._last_stamp is not None and stamp_ns <= self._last_stamp:
                self._reject("stamp not after the previous one",
                             f"{stamp_ns} after {self._last_stamp}")
                return None
            if self._last_stamp is not None:
                period_ns = 1e9 / self.sensor.frame_rate_hz
                gap = max(0, int(round((stamp_ns - self._last_stamp) / period_ns)) - 1)
                self.counters.dropped += gap
                if gap and self._held_s > INLINE_REFIT_NOTE_S:
                    self._note_inline_refit(gap)
            if self.centroider is None:
                self._reject("no centroider", self.problem, health.OK)
                return None
            self._last_stamp = stamp_ns
        return stamp_ns, image

    def _note_inline_refit(self, gap: int) -> None:
        """Frames went missing after an inline profile refit held the frame path: say why
        once, with the cure, then count (the refit runs on the frame path by default so that
        replay reproduces the node; a live node at the frame rate wants it in the background)."""
        alg = self.get_parameter("algorithm").value
        self.health.note("frames dropped after an inline profile refit",
                         f"a refit of the pupil calibration held the frame path {self._held_s:.2f} s "
                         f"and {gap} frame(s) after it were not received; set {alg}.pupil_async: "
                         f"true to refit in the background (and {alg}.pupil_async_lag for a "
                         f"replay that reproduces it)")
        self._held_s = 0.0

    def _maybe_picture(self, stamp_ns: int, grid: np.ndarray):
        """Publish ``slopes_picture`` (rgb8) at ``picture_hz`` at most, if anyone listens."""
        hz = self.get_parameter("picture_hz").value
        now = time.monotonic()
        if hz <= 0 or now < self._next_picture or not self._picture_pub.get_subscription_count():
            return
        self._next_picture = now + 1.0 / hz
        rgb = picture.slopes_picture(grid, self.get_parameter("picture_range_px").value)
        msg = Image(height=rgb.shape[0], width=rgb.shape[1], encoding="rgb8", is_bigendian=0,
                    step=rgb.shape[1] * 3, data=rgb.tobytes())
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 10**9)
        msg.header.frame_id = "wfs"
        self._picture_pub.publish(msg)

    def _diagnostic_values(self) -> dict:
        return {**self.counters.as_dict(), "algorithm": self.get_parameter("algorithm").value,
                "frame_shape": "x".join(map(str, self.sensor.frame_shape)),
                **pupil_values(self.centroider)}

    def destroy_node(self):
        if self._inlet is not None:          # stop reading shared memory first
            self._inlet.close()
            self._inlet = None
        return super().destroy_node()

    def _log_counters(self):
        """The counters every log_period_s, when they changed (silent while idle)."""
        c = self.counters
        extra = self.health.summary()
        line = (f"frames received {c.received}, processed {c.processed}, dropped {c.dropped}, "
                f"rejected {c.rejected}" + (f" ({extra})" if extra else ""))
        if c.received and line != self._last_line:
            self.get_logger().info(line)
        self._last_line = line


def pupil_values(centroider) -> dict:
    """``/diagnostics`` values of a centroider's pupil calibration (none without one): its
    refits, the wall seconds of the last (in its thread when ``pupil_async``) and how many
    frames the profile in use lags behind the frames seen (a period or two when the refits
    keep up)."""
    pupil = getattr(centroider, "pupil", None)
    if pupil is None:
        return {}
    d = pupil.describe()
    return {"pupil refits": d["fits"], "pupil last refit s": d["last_refit_s"],
            "pupil profile age frames": d["profile_age_frames"], "pupil period": d["period"]}


def _final_counts(node) -> None:
    node.get_logger().info(f"final counts {json.dumps(node.counters.as_dict())}")


def main(args=None):
    return run_node("centroider_node", CentroiderNode, refused=(ValueError, SensorError),
                    finish=_final_counts, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
