"""``lgs-wfs demo``: simulator + centroiders side by side + recorder, then the error table.

Two runs, each a graph of separate node processes (what launch/demo.launch.py starts on a ROS
install), on this machine's isolated localhost domain:

1. the paper's single-subaperture case (outermost subaperture, polar detector, evolving
   measured sodium profile, frozen-flow turbulence, 1000 photons) at 700 Hz, every frame
   recorded (the simulator renders 32 frames at a time, so the five node processes hold
   700 Hz on this 2-core machine; the run prints the simulator's achieved pace);
2. the full 60 x 60 pupil on measured sodium profiles evolving in time (none of the networks
   was trained on them), at the highest rate the simulator holds here, slopes and truths at
   every frame and every 10th frame; the centroiders at their defaults (``cmf`` and ``ann``
   calibrate the profile from the pupil), their refits in the background as a live node's
   should be; the error table leaves out the first :data:`WARM_UP` frames (five refits)
   and shows the errors with the pupil-wide tip, tilt and focus removed beside the raw ones
   (a calibrated profile's altitude is focus: docs/accuracy.md).

Each run writes a bag under ``out_dir``, checks that the bag holds every frame, truth and slope
the run produced (nothing lost), and prints the per-algorithm error table from it.
"""

from __future__ import annotations

import re

import json
import os
import time
from pathlib import Path

from ..centroiding import options
from .graph import Graph, NodeSpec

SIMULATOR_KEY = "wfs/simulator_node"
RECORDER_KEY = "wfs/recorder_node"
#: Full pupil: exposures left out of the error table, five of the pupil calibration's default
#: periods (``pupil_period``), as the accuracy benchmark's warm-up: its profile estimate
#: averages over ~0.3 s and its first refit, in the background, builds its basis
WARM_UP = 5 * options.option("cmf", "pupil_period").default
#: Full pupil: exposures scored after the warm-up (0.4 s of sky at 700 Hz)
SCORED = 280
#: Full pupil: the turbulence's outer scale, m
FULL_OUTER_SCALE_M = 30.0


def centroider_params(case: str, name: str) -> dict:
    """The parameters of centroider ``name`` in a demo run.

    The full pupil runs every centroider at its defaults, its refits off the frame path as a
    live node at the frame rate wants them (README: the first builds the calibration's
    basis, seconds that would hold the node and lose frames inline). The paper's single
    subaperture runs the paper's MLP and a CMF a real system can run at full rate: a
    reference from the spot model, model noise weighting, no response inversion (linearize
    costs ~1 ms a frame more: docs/accuracy.md); the paper's idealised "history" reference
    follows the moving spot and so reports ~0 under turbulence (docs/reproduction.md)."""
    params = {"algorithm": name}
    if case != "single":
        if any(o.name == "pupil_async" for o in options.OPTIONS.get(name, ())):
            params[f"{name}.pupil_async"] = True
    elif name == "ann":
        params["ann.model"] = "ann_1k"
    elif name == "cmf":
        params.update({"cmf.reference": "model", "cmf.weighting": "model",
                       "cmf.linearize": False})
    return params


def graph_specs(case: str, bag: Path, frames: int, rate_hz: float, algorithms, seed: int = 1,
                frame_every: int = 1, sim_params: dict | None = None) -> list[NodeSpec]:
    """The node processes of one demo run."""
    sim = {"frames": frames, "rate_hz": float(rate_hz), "seed": seed, "turbulence": True,
           "wait_for_subscribers": len(algorithms) + 1, "start_delay_s": 2.0}
    if case == "single":
        sim.update(single_subaperture=True, detector="polar", profile="evolving")
    else:
        # an outer scale of 30 m, as measured at large telescopes' sites: with an infinite one
        # the turbulence's focus over seconds dominates the raw error of every estimator that
        # calibrates the profile, which cannot tell it from the layer's altitude
        sim.update(single_subaperture=False, detector="cartesian", profile="evolving",
                   outer_scale_m=FULL_OUTER_SCALE_M)
    sim.update(sim_params or {})
    topics = ["/wfs/frame", "/wfs/true_slopes", "/wfs/sensor"]
    topics += [f"/{a}/{t}" for a in algorithms for t in ("slopes", "centroider")]
    specs = [NodeSpec("recorder_node", "wfs", {
        "output": str(bag), "overwrite": True, "topics": topics, "discover": False,
        # closes as soon as every centroider has answered every frame; 15 s for a slow start
        "frames": frames, "frame_every": frame_every, "linger_s": 15.0})]
    for name in algorithms:
        params = centroider_params(case, name)
        specs.append(NodeSpec("centroider_node", name, params,
                              {"frame": "/wfs/frame", "sensor": "/wfs/sensor",
                               "true_slopes": "/wfs/true_slopes"}))
    specs.append(NodeSpec("simulator_node", "wfs", sim))
    return specs


def run_case(case: str, bag: Path, frames: int, rate_hz: float, algorithms, **kw) -> dict:
    """Run one graph until the recorder has its frames; return what was recorded."""
    from .. import bags

    specs = graph_specs(case, bag, frames, rate_hz, algorithms, **kw)
    timeout = 60.0 + 3.0 * frames / max(rate_hz, 1.0)
    with Graph(specs, log_dir=bag.parent / (bag.stem + "_logs")) as graph:
        code = graph.wait(RECORDER_KEY, timeout=timeout)
        graph.stop()
        if code is None:
            raise RuntimeError(f"{case}: the recorder did not finish in {timeout:.0f} s; "
                               f"logs in {graph.log_dir}\n" + graph.log(RECORDER_KEY)[-2000:])
        sim_log = graph.log("wfs/simulator_node")
    summary = bags.BagReader(bag).summary()
    counts = {t: v["count"] for t, v in summary["topics"].items()}
    paced = re.findall(r"published \d+ frames in [\d.]+ s \(([\d.]+) Hz wall-clock\)", sim_log)
    if paced:          # the simulator's own pace, first to last publish
        achieved, how = float(paced[-1]), "published"
    else:              # the recorder's receive times
        achieved = summary["topics"].get("/wfs/true_slopes", {}).get("rate_hz", 0.0)
        how = "received"
    print(f"{how} at {achieved:.0f} Hz wall-clock of the {rate_hz:g} Hz asked "
          "(stamps are exposure times at the sensor's frame rate whatever the pace)", flush=True)
    return counts


def check_complete(counts: dict, frames: int, frame_every: int, algorithms) -> list[str]:
    """What the bag is missing of what the run promised to record."""
    problems = []
    expect = {"/wfs/true_slopes": frames, "/wfs/frame": -(-frames // frame_every)}
    expect.update({f"/{a}/slopes": frames for a in algorithms})
    for topic, n in expect.items():
        if counts.get(topic, 0) != n:
            problems.append(f"{topic}: {counts.get(topic, 0)} recorded, {n} expected")
    return problems


def measure_full_rate(seconds: float = 3.0) -> float:
    """Frames per second the full-pupil simulator holds here (one core), with margin."""
    from ..optics.simulator import SimulationConfig, Simulator
    from ..sensor import Sensor

    sim = Simulator(Sensor(), SimulationConfig(profile="evolving", turbulence=True, seed=0))
    sim.next()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        sim.next()
        n += 1
    fps = n / (time.perf_counter() - t0)
    return max(1.0, round(0.6 * fps))   # the centroiders and the recorder share the 2 cores


def run_demo(out_dir="bags", single_frames: int = 2100, full_frames: int = WARM_UP + SCORED,
             full_rate_hz: float = 0.0, algorithms=("cog", "cmf", "ann")) -> int:
    from ..analysis.report import report_bag

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    algorithms = [a for a in algorithms if a]
    failures = 0
    runs = []
    if single_frames > 0:
        runs.append(("single", out / "demo_single.mcap", single_frames, 700.0, 1))
    if full_frames > 0:
        rate = full_rate_hz or measure_full_rate()
        runs.append(("full", out / "demo_full_pupil.mcap", full_frames, rate, 10))
    for case, bag, frames, rate, every in runs:
        label = ("paper single subaperture, polar, evolving measured profile" if case == "single"
                 else "full 60 x 60 pupil, cartesian, evolving measured profiles, every "
                      "centroider at its defaults")
        print(f"\n=== {label}: {frames} frames at {rate:g} Hz -> {bag}", flush=True)
        t0 = time.monotonic()
        counts = run_case(case, bag, frames, rate, algorithms, frame_every=every)
        print(f"recorded in {time.monotonic() - t0:.1f} s: "
              + json.dumps({t: n for t, n in sorted(counts.items())}))
        problems = check_complete(counts, frames, every, algorithms)
        if problems:
            failures += 1
            print("LOST: " + "; ".join(problems))
        else:
            print("nothing lost: every frame, truth and slope of the run is in the bag")
        skip = WARM_UP if case == "full" and frames > WARM_UP else 0
        if skip:
            print(f"(the first {skip} exposures left out: the pupil calibration's warm-up)")
        report_bag(bag, skip=skip)
    return 1 if failures else 0
