"""ROS transport: frames per second through player -> centroider -> recorder, and where the time goes.

Each case is a graph of three node processes (``lgs_wfs_ros.ros.graph``) on an isolated
localhost domain with the package's Fast DDS profile (64 MB shared-memory segment):

- the player replays an uncompressed bag of distinct simulated frames in a loop (stamps
  shifted every pass, ``restamp_loops``) at a fixed rate (800 Hz full pupil, 6 kHz single
  subaperture) for a few seconds;
- one centroider (cog, cmf with model weighting, ann) computes slopes;
- the recorder writes slopes and truths at full rate (frames not recorded: ``frame_every`` 0).

Flow-controlled runs: the player at rate ``max`` with a few frames in flight (``in_flight``:
4 full pupil, 64 single subaperture): the next frame goes out when the centroider has answered
the one that many frames back, so its queue never overflows; the highest rate with nothing
lost.

A further graph per case replaces centroider and recorder by ``frame_sink.py``, which only
takes the raw frames: the rate it receives is the ceiling of rclpy + Fast DDS on this
machine, before any compute.

Rows per case: frames sent by the player (its achieved rate), slopes out of the centroider
per second, frames lost before the centroider (sent - received, incl. the gaps it counted),
slopes lost between centroider and recorder (processed - recorded; the QoS promise is 0).

The breakdown rows time the per-frame stages in this process, one thread: the copy that
assigns a message's bytes, CDR decode (zero-copy view), compute, slopes -> grid + CDR encode,
and the recorder's ``BagWriter.write`` of one slopes message; plus a cProfile of the
centroider node process at the full-pupil rate (its share in rclpy's take = DDS + executor).
Load average of the shared machine is in every note.
"""

from __future__ import annotations

import cProfile  # noqa: F401  (the profile run uses ``python -m cProfile``)
import json
import os
import pstats
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
    "cmf": ("cmf", {"cmf.weighting": "model", "cmf.reference": "model"}),
    "ann": ("ann", {}),
}


# -- the graph ---------------------------------------------------------------------------------
class ProfiledSpec(NodeSpec):
    """A node process run under ``python -m cProfile -o <out>``."""

    def __init__(self, *a, profile_out: str, **kw):
        super().__init__(*a, **kw)
        self.profile_out = profile_out

    def command(self, workdir):
        cmd = super().command(workdir)
        return [cmd[0], "-m", "cProfile", "-o", self.profile_out] + cmd[1:]


def specs(bag: Path, out: Path, alg: str, params: dict, rate: str, profile_out: str | None = None,
          profile_node: str = "centroider_node", in_flight: int = 1):
    rec = NodeSpec("recorder_node", "wfs", {
        "output": str(out), "overwrite": True, "discover": False, "frame_every": 0,
        "compression": "none",
        "topics": ["/wfs/true_slopes", "/wfs/sensor", f"/{alg}/slopes", f"/{alg}/centroider"]})
    cparams = {"algorithm": alg, "log_period_s": 0.5, **params}
    remaps = {"frame": "/wfs/frame", "sensor": "/wfs/sensor"}
    cen = (ProfiledSpec("centroider_node", alg, cparams, remaps, profile_out=profile_out)
           if profile_out and profile_node == "centroider_node"
           else NodeSpec("centroider_node", alg, cparams, remaps))
    pspec = (lambda *a: ProfiledSpec(*a, profile_out=profile_out)) \
        if profile_out and profile_node == "player_node" else NodeSpec
    player = pspec("player_node", "wfs", {"bag": str(bag), "rate": rate, "loop": True,
                                             "wait_for": [f"/{alg}/slopes" if rate == "max" else "/unused/slopes"],
                                             "start_delay_s": 3.0, "in_flight": in_flight})
    return [rec, cen, player]


class SinkSpec(NodeSpec):
    """``benchmarks/frame_sink.py``: takes ``/wfs/frame`` raw, counts, nothing else."""

    def command(self, workdir):
        return [sys.executable, str(Path(__file__).with_name("frame_sink.py"))]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all its threads), s, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_started(g: Graph, cen_key: str, timeout: float = 90.0) -> None:
    """Until the centroider logs frames received (its counters, every 0.5 s), then 1 s more."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if re.search(r"frames received [1-9]", g.log(cen_key)):
            time.sleep(1.0)
            return
        time.sleep(0.2)
    raise RuntimeError(f"no frame reached the centroider in {timeout:.0f} s:\n"
                       + g.log(cen_key)[-2000:] + g.log(PLAYER)[-2000:])


def final_counts(log: str) -> dict:
    m = re.findall(r"final counts (\{.*\})", log)
    return json.loads(m[-1]) if m else {}


def measure_then_stop(g: Graph, seconds: float, drain_s: float) -> dict:
    """CPU cores each process of ``g`` uses over the next ``seconds``; then interrupt the
    player, wait ``drain_s`` for what is in flight, and stop the graph."""
    pids = {k.split("/")[1]: p.pid for k, p in g.procs.items()}
    cpu0 = {k: cpu_seconds(pid) for k, pid in pids.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    cpu = {k: (cpu_seconds(pid) - cpu0[k]) / (time.monotonic() - t0) for k, pid in pids.items()}
    g.procs[PLAYER].send_signal(signal.SIGINT)
    g.wait(PLAYER, 10)
    time.sleep(drain_s)
    g.stop()
    return cpu


def run_pipeline(bag: Path, sensor: Sensor, alg: str, params: dict, rate: str, seconds: float,
                 profile_out: str | None = None, profile_node: str = "centroider_node",
                 in_flight: int = 1) -> dict:
    """Run the graph; stop the player after ``seconds`` of frames, let the rest drain, count."""
    out = bag.parent / f"out_{alg}_{time.monotonic_ns()}.mcap"
    cen_key = f"{alg}/centroider_node"
    with Graph(specs(bag, out, alg, params, rate, profile_out, profile_node, in_flight),
               log_dir=bag.parent / "logs") as g:
        wait_started(g, cen_key)                 # start delay, discovery, first frames
        cpu = measure_then_stop(g, seconds, drain_s=2.0)   # drain: last frames through the centroider
        player, cen = final_counts(g.log(PLAYER)), final_counts(g.log(cen_key))
    reader = bags.BagReader(out)
    counts = {t: n for t, (_ty, n) in reader.topics().items()}
    recorded = counts.get(f"/{alg}/slopes", 0)
    log_ns = [log for _t, _ty, log, _p, _c in reader.messages([f"/{alg}/slopes"])]
    t_log = [log for _t, _ty, log, _p, _c in reader.messages(["/wfs/true_slopes"])]
    out.unlink()
    span = (log_ns[-1] - log_ns[0]) * 1e-9 if len(log_ns) > 1 else float("nan")
    t_span = (t_log[-1] - t_log[0]) * 1e-9 if len(t_log) > 1 else float("nan")
    sent = player.get("frame", 0)
    return {"sent": sent, "sent_hz": (len(t_log) - 1) / t_span if t_span > 0 else float("nan"),
            "received": cen.get("received", 0), "processed": cen.get("processed", 0),
            "dropped_counted": cen.get("dropped", 0), "rejected": cen.get("rejected", 0),
            "recorded": recorded, "slopes_hz": (len(log_ns) - 1) / span if span > 0 else float("nan"),
            "truths_recorded": counts.get("/wfs/true_slopes", 0),
            "cpu_cores": {k: round(v, 2) for k, v in cpu.items()}}


def run_sink(bag: Path, rate: str, seconds: float) -> dict:
    """Player -> frame_sink only: frames sent and received, CPU of both, over ``seconds``."""
    player = NodeSpec("player_node", "wfs", {"bag": str(bag), "rate": rate, "loop": True,
                                             "wait_for": ["/unused/slopes"], "start_delay_s": 3.0})
    with Graph([SinkSpec("frame_sink", "sink"), player], log_dir=bag.parent / "logs") as g:
        time.sleep(6.0)                          # start delay, discovery, first frames
        cpu = measure_then_stop(g, seconds, drain_s=1.0)
        sent = final_counts(g.log(PLAYER)).get("frame", 0)
        m = re.findall(r"sink counts (\{.*\})", g.log("sink/frame_sink"))
        received = json.loads(m[-1])["received"] if m else 0
    return {"sent": sent, "received": received, "cpu_cores": {k: round(v, 2) for k, v in cpu.items()}}


def sink_rows(label: str, r: dict, target_hz: float) -> list[dict]:
    share = r["received"] / max(r["sent"], 1)
    cpu = ", ".join(f"{k.split('_')[0]} {v:.2f}" for k, v in r["cpu_cores"].items())
    return [{"name": f"{label} transport ceiling (raw sink, no compute)",
             "value": round(100.0 * share, 1), "unit": "% received", "target": "100",
             "note": f"sent {r['sent']}, received {r['received']}; the most any centroider can "
                     f"take here: {share * target_hz:.0f} Hz of {target_hz:g}; CPU cores used: "
                     f"{cpu}; {loadavg()}"}]


def pipeline_rows(label: str, r: dict, target_hz: float, rate: str) -> list[dict]:
    lost_before = r["sent"] - r["processed"] - r["rejected"]
    lost_after = r["processed"] - r["recorded"]
    cpu = ", ".join(f"{k.split('_')[0]} {v:.2f}" for k, v in r.get("cpu_cores", {}).items())
    note = (f"player rate {rate}; CPU cores used: {cpu}; sent {r['sent']} (at {r['sent_hz']:.0f} Hz), received {r['received']}, "
            f"processed {r['processed']}, recorded {r['recorded']}; {loadavg()}")
    target = f">= {target_hz:g} Hz, 0 drops"
    return [
        {"name": f"{label} slopes rate", "value": round(r["slopes_hz"], 1), "unit": "Hz",
         "target": target, "note": note},
        {"name": f"{label} frames lost before centroider", "value": float(lost_before),
         "unit": "frames", "target": "0", "note": f"of {r['sent']} sent "
         f"({100.0 * lost_before / max(r['sent'], 1):.1f} %); centroider counted {r['dropped_counted']} by stamp gaps"},
        {"name": f"{label} slopes lost before recorder", "value": float(lost_after), "unit": "msgs",
         "target": "0", "note": "QoS promise: every processed frame's slopes are recorded"},
    ] + cpu_rows(label, r, target_hz)


def cpu_rows(label: str, r: dict, target_hz: float) -> list[dict]:
    """CPU time per frame of each node process (robust on a shared machine) and the rate the
    pipeline would hold on 2 idle cores from those costs."""
    cores = r.get("cpu_cores", {})
    per = {"player_node": r["sent_hz"], "centroider_node": r["slopes_hz"],
           "recorder_node": r["sent_hz"]}
    ms = {k: 1e3 * cores[k] / per[k] for k in per if k in cores and per[k] > 0}
    rows = [{"name": f"{label} CPU {k.split('_')[0]}", "value": round(v, 3), "unit": "ms/frame",
             "target": f"< {1e3 / target_hz:.3g}", "note": "all threads, user + system, /proc"}
            for k, v in ms.items()]
    if len(ms) == 3:
        bound = min(1e3 / max(ms.values()), 2e3 / sum(ms.values()))
        rows.append({"name": f"{label} CPU-bound rate on 2 idle cores", "value": round(bound, 1),
                     "unit": "Hz", "target": f">= {target_hz:g}",
                     "note": "min(1 / slowest process, 2 cores / sum of the three)"})
    return rows


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


def profile_rows(pstats_file: str, label: str, processed: int) -> list[dict]:
    """Where the centroider node process spent its time (cumulative, per processed frame)."""
    st = pstats.Stats(pstats_file)
    want = {  # stage -> (file suffix or "" for built-ins, function name)
        "wait for a message (idle or starved)": ("", "<built-in method rclpy._rclpy_pybind11.wait>"),
        "take (DDS -> bytes)": ("", "<built-in method rclpy._rclpy_pybind11.take_message>"),
        "callback total": ("centroider_node.py", "_on_frame"),
        "decode": ("cdr.py", "decode_image"),
        "compute": ("centroiding", "centroid"),
        "grid": ("geometry.py", "slopes_to_grid"),
        "encode slopes": ("cdr.py", "encode_image"),
        "publish slopes": ("", "<built-in method rclpy._rclpy_pybind11.publish_raw>"),
    }
    found = {}
    for (file, _line, func), (_cc, _nc, _tt, ct, _callers) in st.stats.items():
        for stage, (where, name) in want.items():
            if func == name and where in file:
                found[stage] = max(found.get(stage, 0.0), ct)
    total = st.total_tt
    rows = []
    for stage, ct in found.items():
        rows.append({"name": f"{label} node profile {stage}", "value": round(1e6 * ct / max(processed, 1), 1),
                     "unit": "us/frame", "target": "", "note": f"{100 * ct / total:.0f} % of the "
                     f"process's {total:.1f} s (cProfile, cumulative)"})
    return rows


# -- run -----------------------------------------------------------------------------------------
def run(quick: bool = False) -> list[dict]:
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    seconds = 4.0 if quick else 10.0
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_transport_") as d:
        tmp = Path(d)
        # label, sensor, fixed rate offered, target, distinct frames, bag frames, in_flight
        cases = [("full pupil", full_sensor(800.0), "800", 800.0, 32, 128, 4),
                 ("single subap", single_sensor(6000.0), "6000", 5000.0, 64, 6000, 64)]
        for label, sensor, rate, target, distinct, frames, window in cases:
            rows += stage_rows(sensor, label, tmp, quick)
            bag = make_bag(tmp / f"{label.replace(' ', '_')}.mcap", sensor, distinct, frames)
            rows += sink_rows(f"{label} @{rate} Hz", run_sink(bag, rate, seconds), float(rate))
            for name, (alg, params) in ALGORITHMS.items():
                if alg == "ann":
                    params = {"ann.model": ann_model(sensor, tmp)}
                r = run_pipeline(bag, sensor, alg, params, rate, seconds)
                rows += pipeline_rows(f"{label} {name} @{rate} Hz", r, target, rate)
                # flow control: the player keeps `window` frames in flight (rate 'max'), so
                # the centroider is never overrun: the highest rate with nothing lost
                if label == "full pupil" or (name == "cog" and not quick):
                    r = run_pipeline(bag, sensor, alg, params, "max", seconds, in_flight=window)
                    rows += pipeline_rows(f"{label} {name} flow-controlled ({window} in flight)",
                                          r, target, "max")
            if not quick:
                r = run_pipeline(bag, sensor, "cog", {}, "max", seconds)
                rows += pipeline_rows(f"{label} cog lockstep", r, target, "max")
            if label == "full pupil":
                prof = str(tmp / "centroider.pstats")
                r = run_pipeline(bag, sensor, "cog", {}, rate, seconds, profile_out=prof)
                if Path(prof).exists():
                    rows += profile_rows(prof, f"{label} cog", r["processed"])
            bag.unlink()
    return rows


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv):
        print(f"{row['name']:<52} {row['value']:>10.4g} {row['unit']:<8} {row['target']:<18} {row['note']}")
