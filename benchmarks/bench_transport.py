"""Frames end to end: source -> centroider -> recorder as separate processes, per transport.

    python benchmarks/bench_transport.py --transport ros,shm --algorithms cog,cmf,ann \
        --source simulator,player --rate 800 --seconds 10 --json OUT.json

Each case is a graph of three node processes (``lgs_wfs_ros.ros.graph``) on an isolated
localhost domain: a source (``player``: an uncompressed bag of distinct simulated frames in a
loop, stamps shifted every pass; or ``simulator``: frames simulated live) offering frames at a
fixed rate, one centroider (cog; cmf with model weighting and reference, the real-time
setting; ann), and the recorder writing slopes and truths at full rate (with ``shm`` also the
decimated ROS ``frame`` topic, 10 Hz). Frames travel with ``frame_transport`` ``ros`` (Fast
DDS) or ``shm`` (iceoryx2, read in place). The full pupil runs at ``--rate``, the paper's
single subaperture at ``--single-rate`` (``--sizes``).

One JSON row per case: ``transport, algorithm, source, size, offered_hz, delivered_hz``
(slopes per second reaching the recorder), ``lost`` (a dict per stage: ``source`` frames the
source did not produce on schedule, ``transport`` sent but never taken by the centroider,
``centroider`` taken but no slopes, ``recorder`` slopes published but not recorded,
``truths`` sent but not recorded), ``latency_ms_p50, latency_ms_p99`` (a frame's slopes
against its truth, both as received by the recorder: source publish -> slopes in the
recorder), ``cpu_ms_per_frame`` (a dict per process: user + system CPU of all its threads,
from /proc, over its own frames). ``run(quick)`` (for ``benchmarks/run.py``) runs a smaller
grid and returns the rows flattened to ``name/value/unit/target/note`` with the case beside.
The machine may be shared: the load average is in every row. The bags (the player's and
the recorder's) go to /dev/shm where it has room, else to the temporary directory
(``--out-dir`` chooses; ``bag_dir`` in every row): on this VM's disk the recorder's file
writes took CPU from the graph being measured.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lgs_wfs_ros import bags
from lgs_wfs_ros.analysis import bagdata
from lgs_wfs_ros.centroiding import make_centroider, resolve_model
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.ros.graph import Graph, NodeSpec
from lgs_wfs_ros.sensor import Sensor

START_NS = 1_700_000_000_000_000_000
PLAYER, RECORDER = "wfs/player_node", "wfs/recorder_node"


def loadavg() -> str:
    return "load %.2f %.2f %.2f" % os.getloadavg()


# -- inputs ------------------------------------------------------------------------------------
# The source starts this long after the nodes: with 3 s the centroider's slopes publisher
# sometimes matched the recorder's subscription 0.4 s after the first frames (the first 334
# slopes of a run published before the match, never recorded, counted as recorder losses).
START_DELAY_S = 8.0


def full_sensor(rate_hz: float) -> Sensor:
    return Sensor(frame_rate_hz=float(rate_hz))


def single_sensor(rate_hz: float) -> Sensor:
    return Sensor.paper_single("polar", frame_rate_hz=float(rate_hz))


def make_bag(path, sensor: Sensor, distinct: int, frames: int, seed: int = 0) -> Path:
    """An uncompressed contract bag: ``frames`` frames (+ truths) cycling over ``distinct``
    simulated ones, stamps one frame period apart. Uncompressed so the player only copies."""
    profile = "evolving" if sensor.is_single else "random"
    imgs, truths, extra = bagdata.simulate(sensor, distinct, seed=seed, profile=profile)
    period = int(round(1e9 / sensor.frame_rate_hz))
    with bagdata.ContractBagWriter(path, sensor, overwrite=True, sensor_extra=extra,
                                   log_ns=START_NS, compression=None) as w:
        for i in range(frames):
            stamp = START_NS + i * period
            w.frame(stamp, imgs[i % distinct])
            w.truth(stamp, truths[i % distinct])
    return Path(path)


def ann_model(sensor: Sensor, tmp: Path) -> str:
    """models/ann_pupil.onnx (full pupil) or ann_1k (single) if shipped, else a small MLP."""
    name = "ann_1k" if sensor.is_single else "ann_pupil"
    try:
        resolve_model(name)
        return name
    except ValueError:
        pass
    import onnx
    from onnx import TensorProto, helper

    rng = np.random.default_rng(0)
    n_in, n_hid = sensor.subap_px ** 2, 32
    w1 = helper.make_tensor("w1", TensorProto.FLOAT, (n_in, n_hid), rng.normal(0, 0.01, (n_in, n_hid)).astype(np.float32).ravel())
    w2 = helper.make_tensor("w2", TensorProto.FLOAT, (n_hid, 2), rng.normal(0, 0.1, (n_hid, 2)).astype(np.float32).ravel())
    nodes = [helper.make_node("MatMul", ["x", "w1"], ["h"]), helper.make_node("Tanh", ["h"], ["t"]),
             helper.make_node("MatMul", ["t", "w2"], ["y"])]
    graph = helper.make_graph(nodes, "mlp", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", n_in])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 2])], [w1, w2])
    path = tmp / "bench_mlp.onnx"
    onnx.save(helper.make_model(graph), str(path))
    return str(path)


ALGORITHMS = {  # name -> (algorithm, extra params); cmf: static model reference and weighting,
    # the real-time setting (its paper setting, history reference + image weighting, rebuilds
    # every filter every frame: ~100 ms at full pupil)
    "cog": ("cog", {}),
    "cmf": ("cmf", {"cmf.weighting": "model", "cmf.reference": "model", "cmf.linearize": False}),
    "ann": ("ann", {}),
    "ml": ("ml", {}),            # polar only: the live simulator's sensor, not the player's bag
    # refits in a thread, each installed as soon as it is ready (lag 0: the frame path never
    # waits; the first refit builds the thin-layer basis, ~3 s)
    "ml_async": ("ml", {"ml.pupil_async": True, "ml.pupil_async_lag": 0}),
    # matched filters at a grid of positions, refits (125 renders, ~1-3 s) in a thread every
    # 1400 frames (7 s at 200 Hz: the profile evolves over seconds)
    "gmf_async": ("gmf", {"gmf.pupil_async": True, "gmf.pupil_period": 1400}),
    # the default network (ann_grid on cartesian pixels) with its refits, and since
    # 2026-11-27 the network's part of them (filters, offset, straightened response), in a
    # thread, each installed as soon as it is ready
    "ann_async": ("ann", {"ann.pupil_async": True, "ann.pupil_async_lag": 0}),
}


# -- the graph ---------------------------------------------------------------------------------
def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all its threads), s, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def final_counts(log: str) -> dict:
    m = re.findall(r"final counts (\{.*\})", log)
    return json.loads(m[-1]) if m else {}


def specs(transport: str, alg: str, source: str, sensor: Sensor, rate: float, out: Path,
          bag: Path | None, params: dict, lockstep: bool) -> list[NodeSpec]:
    """Recorder, centroider and source of one case."""
    shm = transport == "shm"
    topics = ["/wfs/true_slopes", "/wfs/sensor", f"/{alg}/slopes", f"/{alg}/centroider"]
    # the recorder at nice 10: the source and the centroider preempt it on the 2 cores
    # (cog at 800 Hz over shm: p99 2.5-4.7 ms in 8 runs, 2.9-7.0 ms in 16 runs at nice 0)
    rec = NodeSpec("recorder_node", "wfs", {
        "output": str(out), "overwrite": True, "discover": False, "compression": "none",
        "nice": 10,
        "frame_every": 1 if shm else 0, "topics": topics + (["/wfs/frame"] if shm else [])})
    cen = NodeSpec("centroider_node", alg, {"algorithm": ALGORITHMS[alg][0], "log_period_s": 0.5,
                                            "frame_transport": transport, **params},
                   {"frame": "/wfs/frame", "sensor": "/wfs/sensor"})
    tp = {"frame_transport": transport, "frame_publish_hz": 10.0, "frame_lockstep": lockstep}
    if source == "player":
        src = NodeSpec("player_node", "wfs", {"bag": str(bag), "rate": str(rate), "loop": True,
                                              "wait_for": ["/unused/slopes"],
                                              "start_delay_s": START_DELAY_S, **tp})
    else:
        # the live sensor: polar detector (the separable spots of the fast path), measured
        # profiles evolving 1 s apart (blended between knots, the next built ahead)
        fields = {"single_subaperture": True} if sensor.is_single else {}
        src = NodeSpec("simulator_node", "wfs", {
            "frame_rate_hz": float(rate), "rate_hz": 0.0, "profile": "evolving",
            "detector": "polar", "start_delay_s": START_DELAY_S, **fields, **tp})
    return [rec, cen, src]


def wait_started(g: Graph, cen_key: str, src_key: str, timeout: float = 120.0) -> None:
    """Until the centroider logs frames received (its counters, every 0.5 s), then 1 s more."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if re.search(r"frames received [1-9]", g.log(cen_key)):
            time.sleep(1.0)
            return
        time.sleep(0.2)
    raise RuntimeError(f"no frame reached the centroider in {timeout:.0f} s:\n"
                       + g.log(cen_key)[-2000:] + g.log(src_key)[-2000:])


def percentile_ms(values_ns, q) -> float:
    return round(float(np.percentile(values_ns, q)) * 1e-6, 3) if len(values_ns) else float("nan")


def run_case(transport: str, alg: str, source: str, size: str, rate: float, seconds: float,
             tmp: Path, bag: Path | None = None, lockstep: bool = False) -> dict:
    """One graph for ``seconds`` of frames, then the source is stopped, the rest drains, and
    everything is counted by stamp from the recorded bag. The issue-18 row."""
    sensor = full_sensor(rate) if size == "full" else single_sensor(rate)
    name, params = ALGORITHMS[alg]
    if alg == "ann":
        params = {"ann.model": ann_model(sensor, tmp)}
    out = tmp / f"out_{transport}_{alg}_{source}_{time.monotonic_ns()}.mcap"
    src_key, cen_key = f"wfs/{source}_node", f"{alg}/centroider_node"
    with Graph(specs(transport, alg, source, sensor, rate, out, bag, params, lockstep),
               log_dir=tmp / "logs") as g:
        wait_started(g, cen_key, src_key)
        pids = {k.split("/")[1]: p.pid for k, p in g.procs.items()}
        cpu0 = {k: cpu_seconds(pid) for k, pid in pids.items()}
        t0 = time.monotonic()
        time.sleep(seconds)
        span_s = time.monotonic() - t0
        cpu = {k: cpu_seconds(pid) - cpu0[k] for k, pid in pids.items()}
        g.procs[src_key].send_signal(signal.SIGINT)
        g.wait(src_key, 15)
        time.sleep(2.0)                                   # the last frames through
        g.stop()
        cen = final_counts(g.log(cen_key))
        src_counts = final_counts(g.log(src_key))
        src_sent = src_counts.get("frame")                        # the player says
        src_truths = src_counts.get("true_slopes")
        reasons = re.findall(r"\(last: (.*)\)", g.log(cen_key))
    reader = bags.BagReader(out)
    log = {t: {} for t in ("/wfs/true_slopes", f"/{alg}/slopes")}
    for topic, _ty, log_ns, _pub, cdr in reader.messages(list(log)):
        log[topic][bags.peek_stamp(cdr)] = log_ns
    frames_recorded = reader.topics().get("/wfs/frame", (None, 0))[1]
    out.unlink()
    truths, slopes = log["/wfs/true_slopes"], log[f"/{alg}/slopes"]
    # frames sent: the player's own count; the simulator's from its truths (each frame's
    # truth goes out after the frame, and the recorder keeps every truth it receives)
    sent = src_sent if src_sent is not None else len(truths)
    # truths the source published (a player stopped between a frame and its truth sent one
    # truth fewer than frames: not a loss at the recorder)
    truths_sent = src_truths if src_truths is not None else sent
    tt = sorted(truths.values())
    sent_hz = (len(tt) - 1) / ((tt[-1] - tt[0]) * 1e-9) if len(tt) > 1 else float("nan")
    st = sorted(slopes.values())
    delivered_hz = (len(st) - 1) / ((st[-1] - st[0]) * 1e-9) if len(st) > 1 else float("nan")
    lat = [slopes[s] - truths[s] for s in slopes if s in truths]
    taken = cen.get("taken", cen.get("received", 0))
    published = cen.get("published", cen.get("processed", 0))
    offered = int(round(rate * (tt[-1] - tt[0]) * 1e-9)) + 1 if len(tt) > 1 else 0
    per_frame = {"source": sent_hz, "centroider": delivered_hz, "recorder": sent_hz}
    roles = {f"{source}_node": "source", "centroider_node": "centroider",
             "recorder_node": "recorder"}
    cpu_ms = {k: round(1e3 * (v / span_s) / per_frame[roles[k]], 3)
              for k, v in cpu.items() if per_frame[roles[k]] > 0}
    return {"transport": transport, "algorithm": alg, "source": source, "size": size,
            "offered_hz": float(rate), "delivered_hz": round(delivered_hz, 1),
            "sent_hz": round(sent_hz, 1),
            "lost": {"source": max(0, offered - sent), "transport": sent - taken,
                     "centroider": taken - published, "recorder": published - len(slopes),
                     "recorder_truths": truths_sent - len(truths)},
            "latency_ms_p50": percentile_ms(lat, 50), "latency_ms_p99": percentile_ms(lat, 99),
            "cpu_ms_per_frame": cpu_ms,
            "cpu_cores": {k: round(v / span_s, 2) for k, v in cpu.items()},
            "counts": {"sent": sent, "taken": taken, "published": published,
                       "recorded": len(slopes), "frames_recorded": frames_recorded,
                       "centroider": cen, "last_reject": reasons[-1] if reasons else ""},
            "lockstep": lockstep, "seconds": seconds, "load": os.getloadavg()[0]}


# The bags (the player's and the recorder's, ~0.5 GB a 10 s case) go to RAM where the host
# has it: written to this VM's ext4 disk, the recorder's 53 MB/s cost it 0.22-0.26 ms of CPU
# a frame instead of 0.16-0.20 and put file-system work on the 2 cores the graph is measured
# on (cmf at 800 Hz over shm, runs alternated: p99 <= 5 ms in 9 of 10 runs in RAM, 5 of 7
# on disk; docs/transport.md). ``--out-dir`` chooses; each row says where.
RAM_DIR = Path("/dev/shm")
RAM_NEEDED = 2 << 30


def bag_dir(out_dir: str | None = None) -> str | None:
    """Where the case's bags go: ``out_dir`` if given, else /dev/shm when it has 2 GiB
    free, else the system's temporary directory (None)."""
    if out_dir:
        return out_dir
    try:
        st = os.statvfs(RAM_DIR)
    except OSError:
        return None
    free = st.f_bavail * st.f_frsize
    return str(RAM_DIR) if free >= RAM_NEEDED and os.access(RAM_DIR, os.W_OK) else None


def grid(transports, algorithms, sources, sizes, rate, single_rate, seconds, lockstep=False,
         log=print, out_dir: str | None = None) -> list[dict]:
    """Every case of the grid (bags made once per size, in :func:`bag_dir`)."""
    rows = []
    where = bag_dir(out_dir)
    with tempfile.TemporaryDirectory(prefix="bench_transport_", dir=where) as d:
        tmp = Path(d)
        for size in sizes:
            r = rate if size == "full" else single_rate
            sensor = full_sensor(r) if size == "full" else single_sensor(r)
            bag = None
            if "player" in sources:
                distinct, frames = (32, 128) if size == "full" else (64, 6000)
                bag = make_bag(tmp / f"{size}.mcap", sensor, distinct, frames)
            for source in sources:
                for transport in transports:
                    for alg in algorithms:
                        row = run_case(transport, alg, source, size, r, seconds, tmp, bag,
                                       lockstep)
                        row["bag_dir"] = where or tempfile.gettempdir()
                        log(json.dumps(row))
                        rows.append(row)
    return rows


def flat_rows(case: dict) -> list[dict]:
    """A case as ``benchmarks/results.json`` rows (the case itself beside the first)."""
    label = (f"{case['size']} {case['algorithm']} {case['source']} {case['transport']} "
             f"@{case['offered_hz']:g} Hz" + (" lockstep" if case.get("lockstep") else ""))
    lost = sum(case["lost"].values())
    cpu = ", ".join(f"{k.split('_')[0]} {v:.3g}" for k, v in case["cpu_ms_per_frame"].items())
    note = (f"lost {json.dumps(case['lost'])}; CPU ms/frame {cpu}; latency p50 "
            f"{case['latency_ms_p50']} ms; load {case['load']:.2f}"
            + (f"; bags in {case['bag_dir']}" if case.get("bag_dir") else ""))
    return [{"name": f"{label} delivered", "value": case["delivered_hz"], "unit": "Hz",
             "target": f">= {0.99 * case['offered_hz']:g} Hz, 0 lost", "note": note, "case": case},
            {"name": f"{label} lost", "value": float(lost), "unit": "frames", "target": "0",
             "note": json.dumps(case["lost"])},
            {"name": f"{label} latency p99", "value": case["latency_ms_p99"], "unit": "ms",
             "target": "<= 5", "note": "slopes vs truth as received by the recorder"}]


# -- per-stage breakdown (this process, one thread) --------------------------------------------
def _best_us(fn, repeats: int, number: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t) / number)
    return best * 1e6


def stage_rows(sensor: Sensor, label: str, tmp: Path, quick: bool) -> list[dict]:
    imgs, _truths, _ = bagdata.simulate(sensor, 2, seed=3,
                                        profile="evolving" if sensor.is_single else "random")
    cdr = bags.encode_image(imgs[0], START_NS)
    lay = geometry.layout(sensor)
    reps, num = (3, 20) if quick else (5, 100)
    rows = []

    def add(stage, us, note=""):
        rows.append({"name": f"{label} stage {stage}", "value": round(us, 2), "unit": "us/frame",
                     "target": f"sum < {1e6 / (800 if not sensor.is_single else 5000):.0f} us",
                     "note": note})

    add("assign bytes (copy)", _best_us(lambda: bytes(bytearray(cdr)), reps, num),
        f"{len(cdr)} B message")
    add("decode", _best_us(lambda: bags.decode_image(cdr), reps, num), "zero-copy view")
    image = bags.decode_image(cdr)[3]
    slopes = None
    for name, (alg, params) in ALGORITHMS.items():
        if alg == "ml" and sensor.detector != "polar":      # refused there (not separable)
            continue
        opts = {k.split(".", 1)[1]: v for k, v in params.items() if k.startswith(alg + ".")}
        if alg == "ann":
            opts["model"] = ann_model(sensor, tmp)
        c = make_centroider(alg, sensor, **opts)
        c.centroid(image)
        add(f"compute {name}", _best_us(lambda: c.centroid(image), reps, max(5, num // 5)),
            json.dumps(opts)[:80])
        slopes = c.centroid(image)
    add("grid + encode slopes",
        _best_us(lambda: bags.encode_image(geometry.slopes_to_grid(slopes, lay), START_NS), reps, num))
    msg = bags.encode_image(geometry.slopes_to_grid(slopes, lay), START_NS)
    w = bags.BagWriter(tmp / "stage.mcap", overwrite=True, compression=None)
    w.add_topic("/cog/slopes", "sensor_msgs/msg/Image")
    t = [0]

    def write():
        t[0] += 1
        w.write("/cog/slopes", msg, t[0], t[0])
    add("recorder write slopes", _best_us(write, reps, num), f"{len(msg)} B, uncompressed")
    w.close()
    return rows


# -- run -----------------------------------------------------------------------------------------
def run(quick: bool = False) -> list[dict]:
    """For ``benchmarks/run.py``: stage costs, then full pupil at 800 Hz (player; cog, cmf,
    ann over shm and ros; cog from the live simulator over shm) and the single subaperture
    at 6 kHz (player, cog, both transports)."""
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    seconds = 4.0 if quick else 10.0
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_transport_stages_") as d:
        for sensor, label in ((full_sensor(800.0), "full pupil"), (single_sensor(6000.0), "single subap")):
            rows += stage_rows(sensor, label, Path(d), quick)
    cases = grid(["shm", "ros"], ["cog", "cmf", "ann"], ["player"], ["full"], 800.0, 6000.0, seconds)
    cases += grid(["shm"], ["cog"], ["simulator"], ["full"], 200.0, 6000.0, seconds)
    cases += grid(["shm", "ros"], ["cog"], ["player"], ["single"], 800.0, 6000.0, seconds)
    for case in cases:
        rows += flat_rows(case)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--transport", default="ros,shm")
    ap.add_argument("--algorithms", default="cog,cmf,ann")
    ap.add_argument("--source", default="player")
    ap.add_argument("--sizes", default="full,single", help="full (960 x 960) and/or single")
    ap.add_argument("--rate", type=float, default=800.0, help="full-pupil rate offered, Hz")
    ap.add_argument("--single-rate", type=float, default=6000.0, help="single subaperture, Hz")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--lockstep", action="store_true", help="shm sources wait for the readers")
    ap.add_argument("--json", default="", help="write the rows here (a JSON list)")
    ap.add_argument("--out-dir", default="", help="directory for the bags (default: /dev/shm "
                    "if it has 2 GiB free, else the system's temporary directory)")
    a = ap.parse_args(argv)
    split = lambda text: [t.strip() for t in text.split(",") if t.strip()]  # noqa: E731
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    rows = grid(split(a.transport), split(a.algorithms), split(a.source), split(a.sizes),
                a.rate, a.single_rate, a.seconds, a.lockstep, out_dir=a.out_dir or None)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1) + "\n")
        print(f"wrote {len(rows)} rows to {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
