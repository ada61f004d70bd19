"""Bag throughput: CDR encode/decode, MCAP writing (zstd, lz4, none) and reading back of
960 x 960 mono16 frames (1.8 MB) and 60 x 60 x 2 float32 slopes (28.8 kB).

Frames are photon-noise images of a 60 x 60 grid of spots (realistic entropy for compression).
The recorder entries time what ``recorder_node`` does per kept frame after taking it from DDS
(that take, ~1 ms per full frame, is paid either way): write the full frame, or cut the chosen
subapertures out of the CDR (``bags.subapertures.Cutter``) and write that small message.
Files go to a temporary directory (page cache; the disk's own speed is measured separately as
``raw file write``). Best of ``repeats`` runs; one thread.
"""

import os
import tempfile
import time

import numpy as np

from lgs_wfs_ros.bags import BagReader, BagWriter, decode_image, encode_image
from lgs_wfs_ros.bags.subapertures import Cutter
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor

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


def _record(path, msgs, n, cutter=None, **kw):
    """What the recorder does per kept frame (n frames, cycling msgs): write it, or cut it and
    write the blocks."""
    if os.path.exists(path):
        os.remove(path)
    with BagWriter(path, **kw) as w:
        w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
        w.add_topic("/wfs/frame_subapertures", "sensor_msgs/msg/Image")
        for i in range(n):
            m = msgs[i % len(msgs)]
            if cutter is None:
                w.write("/wfs/frame", m, i, i)
            else:
                w.write("/wfs/frame_subapertures", cutter.message(m), i, i)


def _recorder(add, frame_msgs, tmp, repeats, quick):
    """Recorder CPU per kept frame: full frame vs 1 % and all of the valid subapertures."""
    sensor = Sensor()                                   # 60 x 60, 16 px: 960 x 960
    n = geometry.layout(sensor).n_valid
    one_pc = Cutter(sensor, list(range(0, n, 100)))      # 1 % spread over the pupil
    every = Cutter(sensor, list(range(n)))
    path = os.path.join(tmp, "rec.mcap")
    t = _best(lambda: [one_pc.message(frame_msgs[0]) for _ in range(200)], repeats) / 200
    add(f"recorder cut {one_pc.k} of {n} subapertures from a frame's CDR", t * 1e6, "us",
        "< 1428 us (700 Hz)", "decode header (a view) + gather k*256 px + encode_image")
    for comp, kw in (("zstd-3 (recorder default)", dict(compression="zstd")),
                     ("none", dict(compression=None))):
        for what, cutter in (("full frame", None), (f"1 % subapertures ({one_pc.k} of {n})", one_pc),
                             (f"all {n} subapertures", every)):
            if cutter is every and comp.startswith("zstd"):
                continue
            count = len(frame_msgs) if cutter is not one_pc else (300 if quick else 2000)
            t = _best(lambda: _record(path, frame_msgs, count, cutter, **kw), repeats) / count
            size = os.path.getsize(path) / count
            note = ("excludes the DDS take (~1 ms per full frame, paid either way); "
                    + (f"{size / 1e3:.1f} kB per frame in the bag" if kw["compression"] is None or cutter is None
                       else "(4 distinct frames cycled: compressed size not representative)"))
            add(f"recorder per kept frame, {what}, {comp}", t * 1e6, "us", "< 1428 us (700 Hz)", note)


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
        _recorder(add, frame_msgs, tmp, repeats, quick)
    return results


if __name__ == "__main__":
    import sys
    for r in run(quick="--quick" in sys.argv):
        print(f"{r['name']:<50} {r['value']:>12.1f} {r['unit']:<6} target {r['target']:<38} {r['note']}")
