"""Turbulence benchmark: FrozenFlow.next_tilts() for the full default pupil, screen memory.

    python benchmarks/bench_turbulence.py [--quick]
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from lgs_wfs_ros.optics.turbulence import FrozenFlow  # noqa: E402
from lgs_wfs_ros.sensor import Sensor  # noqa: E402


def _per_call_ms(fn, n: int, repeats: int) -> tuple[float, float]:
    """(best, median) milliseconds per call over ``repeats`` batches of ``n`` calls."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        times.append((time.perf_counter() - t0) / n * 1e3)
    return min(times), statistics.median(times)


def run(quick: bool = False) -> list[dict]:
    sensor = Sensor()
    t0 = time.perf_counter()
    ff = FrozenFlow(sensor, 0)
    init_s = time.perf_counter() - t0
    ff.next_tilts()                                            # warm up
    n, repeats = (50, 3) if quick else (200, 7)
    best, median = _per_call_ms(ff.next_tilts, n, repeats)
    wind = sensor.wind_speed_mps
    note = (f"{ff.n_valid} valid subapertures, screen {ff.screen.shape[0]}x{ff.screen.shape[1]} "
            f"at {ff.pixel_m * 100:.3f} cm, {len(ff.screen.mode_c)} analytic modes")
    return [
        {"name": "turbulence next_tilts full pupil (best)", "value": best, "unit": "ms/frame",
         "target": "< 2 ms (800 Hz budget share)", "note": note},
        {"name": "turbulence next_tilts full pupil (median)", "value": median, "unit": "ms/frame",
         "target": "< 2 ms", "note": f"median of {repeats} batches of {n} frames"},
        {"name": "turbulence screen memory", "value": ff.nbytes / 2 ** 20, "unit": "MiB",
         "target": "bounded (< 100 MiB)",
         "note": f"period {ff.period_m[1]:.0f} m along the wind = {ff.period_frames / sensor.frame_rate_hz:.1f} s "
                 f"at {wind:g} m/s"},
        {"name": "turbulence FrozenFlow construction", "value": init_s, "unit": "s",
         "target": "-", "note": "FFT torus + sub-harmonics + tables"},
    ]


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv[1:]):
        print(f"{row['name']:45s} {row['value']:10.3f} {row['unit']:9s} target {row['target']:28s} {row['note']}")
