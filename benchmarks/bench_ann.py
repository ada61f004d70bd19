"""Neural-network centroider inference time per full-pupil frame (onnxruntime, one thread).

Times the shipped models on the default sensor's 2,784 valid subapertures: the raw
``session.run`` (the network itself) and the whole ``ann`` centroider call
(normalisation, conditioning, rotation to detector axes). Targets (issue 5): the paper
MLP under 1 ms, the full-pupil model under 2 ms.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

MODELS = Path(__file__).resolve().parents[1] / "models"
TARGETS_MS = {"ann_1k": 1.0, "ann_noiseless": 1.0, "ann_diag": 1.0, "ann_pupil": 2.0}


def _best_median(fn, repeats: int) -> tuple[float, float]:
    for _ in range(max(3, repeats // 10)):
        fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts), float(np.median(ts))


def run(quick: bool = False) -> list[dict]:
    from lgs_wfs_ros.centroiding import make_centroider
    from lgs_wfs_ros.learning import export
    from lgs_wfs_ros.optics.geometry import layout
    from lgs_wfs_ros.sensor import Sensor

    repeats = 30 if quick else 200
    rng = np.random.default_rng(0)
    out = []
    for name, target in TARGETS_MS.items():
        path = MODELS / f"{name}.onnx"
        if not path.is_file():
            continue
        meta = export.read_metadata(path)
        det = meta.get("lgs_wfs.detector", "any")
        sensor = Sensor(detector="polar" if det == "any" else det)
        lay = layout(sensor)
        n, p = lay.n_valid, sensor.pixels
        stack = rng.poisson(1000.0 / (p * p), size=(n, p, p)).astype(np.float32)
        sess = export.session(path, threads=1)
        feeds = {"pixels": (stack.reshape(n, -1) / stack.reshape(n, -1).sum(1, keepdims=True))}
        if meta.get("lgs_wfs.conditioning", "none") != "none":
            feeds["e"] = rng.random((n, 3)).astype(np.float32)
        best, med = _best_median(lambda: sess.run(None, feeds), repeats)
        out.append({"name": f"{name}_onnx_full_pupil", "value": med * 1e3, "unit": "ms",
                    "target": f"< {target:g} ms",
                    "note": f"session.run on {n} subapertures, 1 thread; best {best * 1e3:.3f} ms"})
        c = make_centroider("ann", sensor, model=str(path),
                            out_of_domain="warn")   # timing only: a model for one radius on the whole pupil
        best, med = _best_median(lambda: c.centroid(stack), repeats)
        out.append({"name": f"{name}_centroider_full_pupil", "value": med * 1e3, "unit": "ms",
                    "target": f"< {target:g} ms (network only)",
                    "note": f"make_centroider('ann').centroid on a {sensor.detector} stack incl. "
                            f"normalisation and rotation; best {best * 1e3:.3f} ms"})
    return out


if __name__ == "__main__":
    import os
    import sys
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    for row in run(quick="--quick" in sys.argv):
        print(f"{row['name']:40s} {row['value']:8.3f} {row['unit']:3s} target {row['target']:28s} {row['note']}")
