"""Bag throughput: CDR encode/decode, MCAP writing (zstd, lz4, none) and reading back of
960 x 960 mono16 frames (1.8 MB) and 60 x 60 x 2 float32 slopes (28.8 kB).

Frames are photon-noise images of a 60 x 60 grid of spots (realistic entropy for compression).
Files go to a temporary directory (page cache; the disk's own speed is measured separately as
``raw file write``). Best of ``repeats`` runs; one thread.
"""

import os
import tempfile
import time

import numpy as np

from lgs_wfs_ros.bags import BagReader, BagWriter, decode_image, encode_image

FRAME_SHAPE = (960, 960)


def _frames(n_distinct, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:16, 0:16]
    out = []
    for _ in range(n_distinct):
        cx, cy = 7.5 + rng.normal(0, 1, (2, 60, 60))
        spot = np.exp(-((x[None, None] - cx[..., None, None]) ** 2 / 8
                        + (y[None, None] - cy[..., None, None]) ** 2 / 2))
        spot *= 1000 / spot.sum(axis=(2, 3), keepdims=True)
        img = spot.transpose(0, 2, 1, 3).reshape(FRAME_SHAPE) + 3
        out.append(rng.poisson(img).astype(np.uint16))
    return out


def _slopes(n, seed=1):
    """n distinct slope maps: Gaussian errors inside a 30 m pupil (3.6 m obstruction), NaN outside."""
    rng = np.random.default_rng(seed)
    c = (np.arange(60) - 29.5) * 0.5
    r = np.hypot(*np.meshgrid(c, c))
    outside = (r > 15) | (r < 1.8)
    s = rng.normal(0, 0.3, (n, 60, 60, 2)).astype(np.float32)
    s[:, outside] = np.nan
    return list(s)


def _best(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _write(path, msgs, **kw):
    if os.path.exists(path):
        os.remove(path)
    with BagWriter(path, **kw) as w:
        w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
        for i, m in enumerate(msgs):
            w.write("/wfs/frame", m, i, i)


def run(quick: bool = False) -> list[dict]:
    repeats = 2 if quick else 3
    n_frames = 16 if quick else 120
    n_slopes = 400 if quick else 4000
    frames = _frames(4)
    slopes = _slopes(n_slopes)
    frame_msgs = [encode_image(frames[i % 4], i) for i in range(n_frames)]
    slope_msgs = [encode_image(slopes[i], i) for i in range(n_slopes)]
    fbytes, sbytes = len(frame_msgs[0]), len(slope_msgs[0])
    results = []

    def add(name, value, unit, target, note):
        results.append({"name": name, "value": float(value), "unit": unit, "target": target, "note": note})

    t = _best(lambda: [encode_image(frames[0], 5) for _ in range(50)], repeats) / 50
    add("encode_image 960x960 mono16", t * 1e6, "us", "< 1428 us (700 Hz)", f"{fbytes / t / 1e9:.2f} GB/s, one copy")
    t = _best(lambda: [decode_image(frame_msgs[0]) for _ in range(200)], repeats) / 200
    add("decode_image 960x960 mono16", t * 1e6, "us", "< 1428 us (700 Hz)", "zero-copy view into the message")

    with tempfile.TemporaryDirectory(prefix="bench_bags_") as tmp:
        raw = os.path.join(tmp, "raw.bin")
        block = b"\x01" * (64 * 2**20)

        def raw_write():
            with open(raw, "wb") as f:
                for _ in range(4 if quick else 8):
                    f.write(block)
        t = _best(raw_write, repeats)
        add("raw file write (this disk, page cache)", (4 if quick else 8) * len(block) / t / 1e6, "MB/s",
            ">= 1290 MB/s (960x960 mono16 at 700 Hz)", "upper bound for any uncompressed recorder")
        os.remove(raw)

        configs = [("none", dict(compression=None)), ("lz4", dict(compression="lz4")),
                   ("zstd-1", dict(compression="zstd", compression_level=1)),
                   ("zstd-3", dict(compression="zstd")),
                   ("none background", dict(compression=None, background=True)),
                   ("lz4 background", dict(compression="lz4", background=True)),
                   ("zstd-1 background", dict(compression="zstd", compression_level=1, background=True))]
        path = os.path.join(tmp, "b.mcap")
        for label, kw in configs:
            for what, msgs, size, target in (("frames 960x960 mono16", frame_msgs, fbytes, ">= 700 msg/s"),
                                             ("slopes 60x60x2 float32", slope_msgs, sbytes, ">= 2800 msg/s (4 topics at 700 Hz)")):
                t = _best(lambda: _write(path, msgs, **kw), repeats)
                ratio = os.path.getsize(path) / (size * len(msgs))
                add(f"write {what} {label}", len(msgs) / t, "msg/s", target,
                    f"{size * len(msgs) / t / 1e6:.0f} MB/s in, file/raw {ratio:.2f}")
                if label in ("none", "zstd-1", "lz4"):
                    def read():
                        with BagReader(path) as r:
                            r.images("/wfs/frame")
                    t = _best(read, repeats)
                    add(f"read {what} {label}", len(msgs) / t, "msg/s", target,
                        f"{size * len(msgs) / t / 1e6:.0f} MB/s, images() into one array")
    return results


if __name__ == "__main__":
    import sys
    for r in run(quick="--quick" in sys.argv):
        print(f"{r['name']:<50} {r['value']:>12.1f} {r['unit']:<6} target {r['target']:<38} {r['note']}")
