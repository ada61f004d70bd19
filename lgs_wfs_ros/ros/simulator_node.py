"""simulator_node: SH-WFS frames and their ground truth at a steady rate.

Publishes ``frame`` (mono16 or 32FC1), ``true_slopes`` (32FC2, G x G, NaN where not valid) with
the same stamp, and the transient-local ``sensor`` description (sensor fields + simulation
settings). Every field of :class:`~lgs_wfs_ros.sensor.Sensor` and of
:class:`~lgs_wfs_ros.optics.simulator.SimulationConfig` is a parameter; a change is validated by
building the new simulator in the on-set callback (refused with the reason if impossible) and
swapped in by the post-set callback, then announced on ``sensor``.

Stamps are exposure times on the sensor's clock: the wall time at start plus one frame period
per frame, so they are unique and strictly increasing whatever the publishing jitter. Frames
leave from a publishing thread on a steady-clock schedule (``rate_hz``; 0 = the sensor's frame
rate); when the simulation is slower than the schedule, frames go out as fast as it allows:
that is logged once with the rate it holds, then counted (frames sent late) in the
diagnostics and the final line. Counters and state go to ``/diagnostics``.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time

from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from .. import bags
from ..optics import geometry
from ..optics.simulator import PROFILE_SOURCES, SimulationConfig, Simulator
from ..sensor import DETECTORS, DTYPES, Sensor, SensorError
from ..transport import shm
from .frame_transport import FrameSource, declare_frame_transport, make_outlet
from .spinning import run_node
from . import health, parameters, qos

SENSOR_DOC = {
    "photons": "Expected detected photons per subaperture per frame.",
    "detector": "Detector type.",
    "read_noise_e": "Read noise per pixel, e- rms.",
    "background_e": "Background per pixel per frame, e-.",
    "r0_m": "Fried parameter at r0_wavelength_m, m.",
    "frame_rate_hz": "Frame rate of the sensor (sets the stamps and the frozen-flow step), Hz.",
}
CONFIG_PARAMS = ("profile", "measured_index", "seconds_per_profile", "random_every", "turbulence",
                 "noise", "seed", "per_field")
BUILD_PARAMS = CONFIG_PARAMS + ("single_subaperture", "render_threads")


def _sensor_params():
    """(name, default, description, choices) of every Sensor field exposed as a parameter."""
    out = []
    for f in dataclasses.fields(Sensor):
        if f.name == "single_subaperture_xy_m":
            continue
        default = f.default
        if isinstance(default, tuple):
            default = [float(v) for v in default]
        choices = DETECTORS if f.name == "detector" else DTYPES if f.name == "dtype" else None
        out.append((f.name, default, SENSOR_DOC.get(f.name, f"Sensor field {f.name}."), choices))
    return out


RENDER_THREADS = 2           # render_threads' default: the live graph's 200 Hz (docs/transport.md)
LATE_S = 1.0                 # a frame this late after its slot counts as behind the rate
BATCH_FRAMES = 32            # frames rendered together for a small sensor
BATCH_SUBAPERTURES = 1024    # ... as long as they hold at most this many spots


class SimulatorNode(FrameSource, Node):
    def __init__(self, **kwargs):
        kwargs.setdefault("namespace", "wfs")
        super().__init__("simulator_node", **kwargs)
        self._sensor_names = []
        for name, default, doc, choices in _sensor_params():
            parameters.declare(self, name, default, doc, choices=choices)
            self._sensor_names.append(name)
        parameters.declare(self, "single_subaperture", False, "Simulate only the paper's "
                           "outermost subaperture (16 x 16 frames) instead of the full pupil.")
        cfg = SimulationConfig()
        parameters.declare(self, "profile", "random", "Sodium profile source.",
                           choices=PROFILE_SOURCES)
        parameters.declare(self, "measured_index", cfg.measured_index,
                           "profile=measured: which measured profile.", low=0, high=100000)
        parameters.declare(self, "seconds_per_profile", cfg.seconds_per_profile,
                           "profile=evolving: seconds between measured profiles.", low=1e-3, high=1e4)
        parameters.declare(self, "random_every", cfg.random_every,
                           "profile=random: a new random profile every N frames.", low=1, high=10**9)
        parameters.declare(self, "turbulence", True, "Frozen-flow turbulence moves the spots.")
        parameters.declare(self, "noise", True, "Photon (and read) noise.")
        parameters.declare(self, "seed", 1, "Random seed: the same seed gives the same frames.",
                           low=0, high=2**31 - 1)
        parameters.declare(self, "per_field", True, "photons counts the light inside the 16 x 16 "
                           "field (docs/conventions.md) rather than the whole spot.")
        parameters.declare(self, "rate_hz", 0.0, "Publishing rate, Hz (0: frame_rate_hz).",
                           low=0.0, high=100000.0)
        parameters.declare(self, "frames", 0, "Frames to publish, then stop (0: forever).",
                           low=0, high=2**31 - 1)
        parameters.declare(self, "wait_for_subscribers", 0, "Wait until this many subscribers "
                           "listen to frame and to sensor before the first frame (a centroider "
                           "rejects frames that come before the sensor description).",
                           low=0, high=1000)
        parameters.declare(self, "start_delay_s", 0.0, "Extra wait before the first frame, s.",
                           low=0.0, high=600.0)
        parameters.declare(self, "render_threads", RENDER_THREADS, "Threads that render one "
                           "full-pupil frame (the frames are the same for any number; 2 halves "
                           "the render's wall time where two cores are free).", low=1, high=4)
        declare_frame_transport(self)

        self._lock = threading.Lock()
        self._pending = None
        self.sim = self._build({})
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)

        self._frame_pub = self.create_publisher(Image, "frame", qos.frame_qos(self.sim.sensor))
        self._outlet = make_outlet(self, self._frame_pub, self.sim.sensor)
        self._truth_pub = self.create_publisher(Image, "true_slopes", qos.SLOPES)
        self._sensor_pub = self.create_publisher(String, "sensor", qos.LATCHED)
        self.published = 0
        self.late = 0            # frames that went out more than LATE_S after their slot
        self.health = health.Health(self, self._diagnostic_values)
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._announce()
        self._thread = threading.Thread(target=self._run, name="simulator", daemon=True)
        self._thread.start()

    # -- configuration ---------------------------------------------------------------
    def _build(self, changes: dict) -> Simulator:
        """A simulator from the current parameters plus ``changes``; ValueError if impossible."""
        v = parameters.values(self, self._sensor_names + list(BUILD_PARAMS))
        v.update(changes)
        fields = {n: v[n] for n in self._sensor_names}
        for n in ("n_subaps", "pixels"):
            fields[n] = int(fields[n])
        try:
            sensor = Sensor(**fields)
            if v["single_subaperture"]:
                sensor = Sensor.paper_single(sensor.detector, **{
                    k: val for k, val in fields.items() if k != "detector"})
            config = SimulationConfig(**{n: v[n] for n in CONFIG_PARAMS})
            return Simulator(sensor, config, fast=True,       # compiled noise where numba is
                             threads=int(v["render_threads"]))
        except (SensorError, TypeError) as exc:
            raise ValueError(str(exc)) from exc

    def _validate(self, params):
        changes = {p.name: p.value for p in params}
        relevant = set(changes) & (set(self._sensor_names) | set(BUILD_PARAMS))
        if relevant:
            try:
                self._pending = self._build({k: changes[k] for k in relevant})
            except (ValueError, OSError) as exc:
                self._pending = None
                return parameters.refuse(str(exc))
        return parameters.accept()

    def _apply(self, params):
        if self._pending is not None:
            with self._lock:
                self.sim, self._pending = self._pending, None
            self._announce()

    def _announce(self):
        desc = self.sim.describe()
        self._sensor_pub.publish(String(data=json.dumps(desc, default=str)))
        s = self.sim.sensor
        self.health.set_state(health.OK, "publishing")
        self.get_logger().info(
            f"sensor: {s.grid}x{s.grid} subapertures, {s.detector}, {s.photons:g} photons, "
            f"profile {self.sim.config.profile}, turbulence {self.sim.config.turbulence}")

    # -- publishing -------------------------------------------------------------------
    def _wait_to_start(self):
        need = self.get_parameter("wait_for_subscribers").value
        while need and not self._stop.is_set() and (
                self._outlet.subscriber_count() < need
                or self._sensor_pub.get_subscription_count() < need):
            time.sleep(0.05)
        delay = self.get_parameter("start_delay_s").value
        self._stop.wait(delay)

    def _run(self):
        try:
            self._publish_frames()
        except Exception as exc:   # a dying context at shutdown, or a simulator bug: say so
            if not self._stop.is_set():
                self.get_logger().error(f"simulation stopped: {exc!r}")
        finally:
            self.finished.set()

    def _publish_frames(self):
        self._wait_to_start()
        stamp_ns = time.time_ns()
        due = time.monotonic()
        queue, source = [], None
        first = last = None
        while not self._stop.is_set():
            budget = self.get_parameter("frames").value
            if budget and self.published >= budget:
                break
            self._outlet.wait_for_room(self._stop.is_set)    # lockstep: before rendering
            with self._lock:
                sim = self.sim
                if sim is not source:                      # new parameters: drop the old batch
                    if source is not None:
                        source.close()                     # its helper threads
                    queue, source = [], sim
                    sensor_id = shm.sensor_id(sim.sensor)
                if not queue:
                    queue = self._make_frames(sim, budget - self.published if budget else None,
                                              self._outlet)
                frame, buf = queue.pop(0)
                layout = sim.layout
                period_s = 1.0 / sim.sensor.frame_rate_hz
            if first is None:          # the schedule starts with the first frame, not its set-up
                due = time.monotonic()
            truth = geometry.slopes_to_grid(frame.truth, layout)
            if buf is not None:                            # rendered straight into the loan
                self._outlet.send(buf, stamp_ns, sensor_id)
            else:
                self._outlet.publish(frame.frame, stamp_ns, sensor_id, stop=self._stop.is_set)
            self._truth_pub.publish(bags.encode_image(truth, stamp_ns))
            self.published += 1
            last = time.monotonic()
            first = last if first is None else first
            stamp_ns += int(round(period_s * 1e9))
            rate = self.get_parameter("rate_hz").value or 1.0 / period_s
            due += 1.0 / rate
            delay = due - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif -delay > LATE_S:
                self._behind(rate, first)
                due = time.monotonic()
        late = f", {self.late} of them late (behind {rate:g} Hz)" if self.late else ""
        if first is not None and last > first:
            span = last - first
            self.get_logger().info(f"published {self.published} frames in {span:.3f} s "
                                   f"({(self.published - 1) / span:.1f} Hz wall-clock){late}")
        else:
            self.get_logger().info(f"published {self.published} frames{late}")
        if source is not None:
            source.close()
        self.health.set_state(health.OK, "finished")

    def _behind(self, rate: float, first: float) -> None:
        """The schedule slipped by more than LATE_S: said once (with the pace held), then
        counted; the schedule restarts from now."""
        self.late += 1
        held = (self.published - 1) / max(time.monotonic() - first, 1e-9)
        if self.health.note(f"simulation slower than {rate:g} Hz", f"about {held:.0f} frames/s "
                            "here; frames go out as fast as it allows (stamps keep the sensor's "
                            "rate)") == 1:
            self.health.set_state(health.WARN, f"behind: about {held:.0f} of {rate:g} Hz",
                                  log=False)

    def _diagnostic_values(self) -> dict:
        s = self.sim.sensor
        return {"published": self.published, "late": self.late, "grid": s.grid,
                "detector": s.detector, "frame_rate_hz": s.frame_rate_hz}

    @staticmethod
    def _make_frames(sim, left, outlet):
        """The next ``[(frame, loaned buffer or None)]``: a batch of up to
        ``BATCH_SUBAPERTURES`` spots rendered together for a small sensor (the paper's single
        subaperture: ~0.3 ms instead of ~1 ms per frame), one frame at a time for the full
        pupil, rendered straight into the outlet's buffer (shared memory with ``shm``)."""
        k = max(1, min(BATCH_FRAMES, BATCH_SUBAPERTURES // sim.layout.n_valid))
        if left is not None:
            k = max(1, min(k, left))
        if k > 1:
            return [(f, None) for f in sim.next_batch(k)]
        buf = outlet.loan(sim.sensor.frame_shape, sim.sensor.dtype)
        return [(sim.next(out=buf.image), buf)]



def _published(node) -> bool:
    """Done once the frame budget is out and one more second has passed, so that reliable
    deliveries of the last frames finish."""
    if not node.finished.is_set():
        return False
    if getattr(node, "_linger_until", None) is None:
        node._linger_until = time.monotonic() + 1.0
    return time.monotonic() > node._linger_until


def main(args=None):
    return run_node("simulator_node", SimulatorNode, done=_published,
                    finish=lambda node: node.stop(), args=args)


if __name__ == "__main__":
    raise SystemExit(main())
