"""Simulator speed: full 60 x 60 frames (2,784 valid, 1000 photons, turbulence on).

    python benchmarks/bench_simulator.py [--quick]

Reports frames/s on one core for the cartesian and the polar detector, the time per frame
of each stage (turbulence, spots, noise, assembly), the one-off cost of a new profile
(SpotModel build: what a per-frame evolving/random profile pays every frame) and the
rate of :func:`subaperture_batch` (training samples/s). Median of several repeats.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from lgs_wfs_ros.optics.detector import expose  # noqa: E402
from lgs_wfs_ros.optics.geometry import stack_to_frame  # noqa: E402
from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator, subaperture_batch  # noqa: E402
from lgs_wfs_ros.optics.spots import SpotModel  # noqa: E402
from lgs_wfs_ros.sensor import Sensor  # noqa: E402


def _median(fn, repeats, clock=time.perf_counter):
    times = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return float(np.median(times))


def _detector_rows(detector, repeats):
    s = Sensor(detector=detector)
    sim = Simulator(s, SimulationConfig(profile="uncentred", seed=1))
    sim.next()                                            # screens, spot model, caches
    t_frame = _median(sim.next, repeats)
    t_cpu = _median(sim.next, repeats, time.process_time)     # robust to a loaded machine
    lay = sim.layout
    idx = [sim.index]

    def turb():
        idx[0] += 1
        return sim.truth_at(idx[0])

    t_turb = _median(turb, repeats)
    truth = sim.truth_at(idx[0])
    density, key = sim.profile_at(0)
    model = sim._spots
    t_spots = _median(lambda: model.images(truth), repeats)
    images, _ = model.images(truth)
    rng = np.random.default_rng(0)
    t_noise = _median(lambda: expose(images, s.photons, rng, dtype=s.dtype), repeats)
    counts = expose(images, s.photons, rng, dtype=s.dtype)
    t_asm = _median(lambda: stack_to_frame(counts, lay), repeats)
    t_build = _median(lambda: SpotModel(s, lay.r_m, lay.e, sim.altitude_m, density, 3.0),
                      max(2, repeats // 3))
    # the live graph's path: compiled noise, the frame written into a (loaned) buffer
    fast = Simulator(s, SimulationConfig(profile="uncentred", seed=1), fast=True)
    buf = np.empty(s.frame_shape, dtype=s.dtype)
    for _ in range(5):                                    # compile, tables, caches
        fast.next(out=buf)
    n_fast = 100                                          # CPU time over >= 100 frames
    c0 = time.process_time()
    for _ in range(n_fast):
        fast.next(out=buf)
    t_fast = (time.process_time() - c0) / n_fast
    t_fast_noise = _median(lambda: expose(images, s.photons, rng, dtype=s.dtype, fast=True),
                           repeats, time.process_time)
    t_evo, w_evo, n_evo = _evolving_fast(detector, 200.0)
    t_evo2, w_evo2, _ = _evolving_fast(detector, 200.0, threads=2)
    ms = lambda t: round(t * 1e3, 3)  # noqa: E731
    note = (f"{lay.n_valid} valid subaps, 1000 photons, frozen-flow turbulence; per frame: "
            f"turbulence {ms(t_turb)} ms, spots {ms(t_spots)} ms, noise {ms(t_noise)} ms, "
            f"assembly {ms(t_asm)} ms")
    return [
        {"name": f"full frame {detector}", "value": 1.0 / t_frame, "unit": "frames/s",
         "target": ">= 100", "note": note},
        {"name": f"full frame {detector} (CPU time)", "value": 1.0 / t_cpu, "unit": "frames/s",
         "target": ">= 100", "note": "same, timed with process_time (excludes waiting for a "
                                      "core on a shared machine)"},
        {"name": f"full frame {detector} fast, into a buffer (CPU time)", "value": 1.0 / t_fast,
         "unit": "frames/s", "target": ">= 200 (issue 18)",
         "note": f"Simulator(fast=True).next(out=), {ms(t_fast)} ms/frame CPU over {n_fast} "
                 f"frames: " + ("tabulated line (fast_frames.PolarTable), spots, Poisson draws "
                                "and the write in one compiled pass" if detector == "polar" else
                                "compiled banded node sum (fast_frames.CartesianNodes), then "
                                "Poisson draws and the write in one compiled pass") +
                 f"; expose(fast=True) alone {ms(t_fast_noise)} ms/frame (numpy's: {ms(t_noise)} ms)"},
        {"name": f"full frame {detector} fast, evolving profile (CPU time)",
         "value": 1.0 / t_evo, "unit": "frames/s", "target": ">= 200 (issue 18)",
         "note": f"profile=evolving (measured, 1 s apart) at 200 Hz, {ms(t_evo)} ms/frame CPU of "
                 f"all threads over {n_evo} frames (3 knot crossings): two knots' tables "
                 "blended, the next knot's model built in a background thread"},
        {"name": f"full frame {detector} fast, evolving, 2 render threads (wall)",
         "value": 1.0 / w_evo2, "unit": "frames/s", "target": ">= 200 (issue 18)",
         "note": f"the same with Simulator(threads=2) (the simulator node's render_threads "
                 f"default): {ms(w_evo2)} ms/frame wall (1 thread: {ms(w_evo)} ms), "
                 f"{ms(t_evo2)} ms/frame CPU of all threads; the frames are the same"},
        {"name": f"  turbulence ({detector})", "value": ms(t_turb), "unit": "ms/frame",
         "target": "", "note": "FrozenFlow.tilts_at: G-tilts of 2,784 subapertures"},
        {"name": f"  spots ({detector})", "value": ms(t_spots), "unit": "ms/frame",
         "target": "", "note": "SpotModel.images: node sums with exact pixel integration (erf)"},
        {"name": f"  noise ({detector})", "value": ms(t_noise), "unit": "ms/frame",
         "target": "", "note": "expose: exact Poisson on pixels with > 1e-9 expected photons"},
        {"name": f"  assembly ({detector})", "value": ms(t_asm), "unit": "ms/frame",
         "target": "", "note": "stack_to_frame"},
        {"name": f"  new profile ({detector})", "value": ms(t_build), "unit": "ms",
         "target": "", "note": "SpotModel build (paid per frame by evolving/random-every-frame)"},
    ]


def _evolving_fast(detector, rate_hz, threads=1):
    """``(CPU s a frame of all threads, wall s a frame, frames)`` of the fast path with the
    measured profiles evolving, over 3 s of frames after the first two knots are built."""
    s = Sensor(detector=detector, frame_rate_hz=rate_hz)
    sim = Simulator(s, SimulationConfig(profile="evolving", seed=1), fast=True, threads=threads)
    buf = np.empty(s.frame_shape, dtype=s.dtype)
    try:
        for _ in range(3):
            sim.next(out=buf)
        n = int(3 * rate_hz)
        c0, w0 = time.process_time(), time.perf_counter()
        for _ in range(n):
            sim.next(out=buf)
        return (time.process_time() - c0) / n, (time.perf_counter() - w0) / n, n
    finally:
        sim.close()


def _batch_rows(repeats):
    rows = []
    for det in ("polar", "cartesian"):
        s = Sensor.paper_single(det)
        n = 8192
        rng = np.random.default_rng(0)
        t = _median(lambda: subaperture_batch(s, rng, n, sigma_px=0.5), max(1, repeats // 3))
        rows.append({"name": f"subaperture_batch {det}", "value": n / t, "unit": "samples/s",
                     "target": "1e6 samples in minutes",
                     "note": "random 5-Gaussian profile + normal position + Poisson, 16x16"})
    return rows


def run(quick: bool = False) -> list[dict]:
    repeats = 5 if quick else 15
    rows = []
    for det in ("cartesian", "polar"):
        rows += _detector_rows(det, repeats)
    rows += _batch_rows(repeats)
    return rows


if __name__ == "__main__":
    for r in run(quick="--quick" in sys.argv):
        print(f"{r['name']:<34} {r['value']:>12.4g} {r['unit']:<10} target {r['target']:<22} {r['note']}")
