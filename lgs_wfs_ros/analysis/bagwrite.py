"""Write a contract bag (docs/conventions.md section 5) from numpy arrays, without ROS: the
writer the tests, benchmarks and the sample bags use, and :func:`make_sample_bag` (simulate,
centroid, record in one call)."""

from __future__ import annotations

import json

import numpy as np

from ..bags import BagWriter, encode_image, encode_string
from ..bags import subapertures as subaps
from ..bags.portable import portable
from ..bags.reader import IMAGE, STRING
from ..sensor import Sensor

TRANSIENT = {"reliability": "reliable", "durability": "transient_local", "history": "keep_last", "depth": 1}
VOLATILE = {"reliability": "reliable", "durability": "volatile", "history": "keep_last", "depth": 100}


class ContractBagWriter:
    """Write a bag in the contract's layout from numpy arrays (no ROS).

    ``wfs`` is the namespace of frame / true_slopes / sensor. Slopes and truths are given
    per valid subaperture ``(n, 2)`` px and written as ``(G, G, 2)`` 32FC2 grids, NaN where
    not valid. Descriptions are stored with names, not paths
    (:func:`~lgs_wfs_ros.bags.portable.portable`). bag_options: further
    :class:`~lgs_wfs_ros.bags.BagWriter` arguments (chunk_size, crc, ...). Use as a context
    manager.
    """

    def __init__(self, path, sensor: Sensor, *, overwrite: bool = False, wfs: str = "wfs",
                 sensor_extra: dict | None = None, log_ns: int | None = None, compression="zstd",
                 **bag_options):
        from ..optics import geometry

        self.sensor = sensor
        self.layout = geometry.layout(sensor)
        self.wfs = wfs.strip("/")
        self.w = BagWriter(path, overwrite=overwrite, compression=compression, **bag_options)
        self._topics = set()
        self._cutter = None        # subaperture cutter of the current selection
        self.topic(f"/{self.wfs}/sensor", STRING, TRANSIENT)
        self.w.write(f"/{self.wfs}/sensor", encode_string(sensor.to_json(**portable(sensor_extra or {}))),
                     int(log_ns or 0))

    def topic(self, name: str, type_name: str, qos=None) -> None:
        if name not in self._topics:
            self.w.add_topic(name, type_name, qos=qos or VOLATILE)
            self._topics.add(name)

    def frame(self, stamp_ns: int, frame: np.ndarray, log_ns: int | None = None) -> None:
        t = f"/{self.wfs}/frame"
        self.topic(t, IMAGE, dict(VOLATILE, depth=10))
        self.w.write(t, encode_image(np.ascontiguousarray(frame), stamp_ns), _log(stamp_ns, log_ns), stamp_ns)

    def frame_subapertures(self, stamp_ns: int, frame: np.ndarray, indices, log_ns: int | None = None) -> None:
        """Write the blocks of the chosen subapertures of one frame, as the recorder does with
        ``frame_subapertures`` set (:func:`~lgs_wfs_ros.bags.subapertures.write_blocks`: the
        selection first whenever it changes)."""
        idx = subaps.parse_indices(indices)
        new = self._cutter is None or not np.array_equal(self._cutter.indices, idx)
        if new:
            self._cutter = subaps.Cutter(self.sensor, idx)
        cdr = encode_image(np.ascontiguousarray(frame), stamp_ns)
        subaps.write_blocks(self.w, self._cutter, f"/{self.wfs}/frame", cdr, _log(stamp_ns, log_ns), stamp_ns,
                            new_selection=new)

    def _grid(self, topic: str, stamp_ns: int, slopes: np.ndarray, log_ns) -> None:
        from ..optics import geometry
        self.topic(topic, IMAGE)
        grid = geometry.slopes_to_grid(np.asarray(slopes, dtype=np.float32), self.layout)
        self.w.write(topic, encode_image(grid, stamp_ns), _log(stamp_ns, log_ns), stamp_ns)

    def truth(self, stamp_ns: int, slopes: np.ndarray, log_ns: int | None = None) -> None:
        self._grid(f"/{self.wfs}/true_slopes", stamp_ns, slopes, log_ns)

    def slopes(self, ns: str, stamp_ns: int, slopes: np.ndarray, log_ns: int | None = None) -> None:
        self._grid(f"/{ns.strip('/')}/slopes", stamp_ns, slopes, log_ns)

    def centroider(self, ns: str, description: dict, log_ns: int) -> None:
        t = f"/{ns.strip('/')}/centroider"
        self.topic(t, STRING, TRANSIENT)
        text = json.dumps(portable(description), sort_keys=True, default=str)
        self.w.write(t, encode_string(text), int(log_ns))

    def close(self) -> None:
        self.w.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _log(stamp_ns, log_ns):
    return int(stamp_ns if log_ns is None else log_ns)


def simulate(sensor: Sensor, frames: int, seed: int = 0, profile: str = "evolving", **config):
    """``(frames (F, H, W), truths (F, n, 2) px, sensor extra dict)`` from the library's simulator.

    profile and config: :class:`~lgs_wfs_ros.optics.simulator.SimulationConfig` fields.
    """
    from ..optics.simulator import SimulationConfig, Simulator

    cfg = SimulationConfig(seed=seed, profile=profile, **config)
    sim = Simulator(sensor, cfg)
    imgs, truths = [], []
    for fr in sim.frames(frames):
        imgs.append(fr.frame)
        truths.append(fr.truth)
    return np.stack(imgs), np.stack(truths), {"simulation": cfg.to_dict()}


def make_sample_bag(path, frames: int = 40, *, sensor: Sensor | None = None,
                    algorithms=("cog", "cmf"), seed: int = 0, decimate: int = 1,
                    switch: tuple[str, int, str] | None = None, overwrite: bool = False,
                    profile: str = "evolving", start_ns: int = 1_700_000_000_000_000_000,
                    models: dict | None = None, **sim_config) -> dict:
    """Simulate frames, run centroiders over them and write a contract bag (no ROS).

    Args:
        path: output ``.mcap``.
        frames: frames simulated (every one gets a truth; with ``decimate`` k only every
            k-th frame is written, as a decimating recorder would, while the centroiders
            still see every frame).
        sensor: default ``Sensor.paper_single("polar")``.
        algorithms: centroider names; each runs in the namespace of its name.
        switch: ``(namespace, frame index, new algorithm)``: that namespace switches
            algorithm at that frame and republishes its ``centroider`` description.
        models: ``{algorithm: model name}`` for ann-type algorithms.
        profile, sim_config: passed to the simulator.

    Returns ``{"path", "frames", "frames_written", "algorithms", "sensor"}``.
    """
    from ..centroiding import make_centroider

    sensor = sensor or Sensor.paper_single("polar")
    if frames < 1 or decimate < 1:
        raise ValueError("frames and decimate must be >= 1")
    imgs, truths, settings = simulate(sensor, frames, seed, profile, **sim_config)
    settings["start_stamp_ns"] = int(start_ns)
    models = models or {}

    def build(alg):
        opts = {"model": models[alg]} if alg in models else {}
        return make_centroider(alg, sensor, **opts)

    cents = {alg: build(alg) for alg in algorithms}
    period = int(round(1e9 / sensor.frame_rate_hz))
    written = 0
    with ContractBagWriter(path, sensor, overwrite=overwrite, sensor_extra=settings,
                           log_ns=start_ns) as bag:
        for ns, c in cents.items():
            bag.centroider(ns, c.describe(), start_ns)
        for k in range(frames):
            stamp = start_ns + k * period
            if switch is not None and k == switch[1]:
                cents[switch[0]] = build(switch[2])
                bag.centroider(switch[0], cents[switch[0]].describe(), stamp)
            if k % decimate == 0:
                bag.frame(stamp, imgs[k])
                written += 1
            bag.truth(stamp, truths[k])
            for ns, c in cents.items():
                bag.slopes(ns, stamp, c.centroid(imgs[k]), stamp + 100_000)
    return {"path": str(path), "frames": frames, "frames_written": written,
            "algorithms": list(cents), "sensor": sensor}


__all__ = ["ContractBagWriter", "TRANSIENT", "VOLATILE", "make_sample_bag", "simulate"]
