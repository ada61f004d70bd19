"""Load a contract bag (docs/conventions.md section 5) into numpy arrays, joined by stamp.

Topics: ``/<wfs>/frame`` (mono16 or 32FC1, possibly decimated), ``/<wfs>/true_slopes``
(32FC2, G x G), ``/<wfs>/sensor`` (JSON), and per centroider namespace ``/<ns>/slopes``
(32FC2) and ``/<ns>/centroider`` (JSON, republished on every change). The label of a
namespace is its name; when its centroider changed during the bag its slopes are split into
one *segment* per description, labelled ``<ns>:<algorithm>`` (``#k`` added if repeated).

A recorder with ``frame_subapertures`` set writes ``/<wfs>/frame_subapertures`` (the blocks of
chosen subapertures, see :mod:`lgs_wfs_ros.bags.subapertures`) instead of or beside frames; the
blocks are read with :func:`lgs_wfs_ros.bags.read_subapertures`, and :class:`BagData` only
says what is there (``subapertures``).

Slopes and truths are kept as ``(F, G*G, 2)`` float32 grids (NaN where not valid); frames are
loaded only on request and at most ``max_frames`` of them, since a long full-pupil bag does
not fit in memory. Every user-fixable problem is a :class:`~lgs_wfs_ros.bags.BagError`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace

import numpy as np

from ..bags import BagError, BagReader, decode_image, decode_string, join_by_stamp
from ..bags import subapertures as subaps
from ..bags.reader import IMAGE, STRING
from ..sensor import Sensor, SensorError


@dataclass
class Stream:
    """Image messages of one topic, in file order.

    stamps: ``(F,)`` int64 header stamps, ns. log_ns: ``(F,)`` int64 receive times, ns.
    data: ``(F, ...)`` arrays (slopes ``(F, G*G, 2)`` float32; frames ``(F, H, W)``).
    """

    topic: str
    stamps: np.ndarray
    log_ns: np.ndarray
    data: np.ndarray

    def __len__(self):
        return int(self.stamps.shape[0])


@dataclass
class Segment:
    """The slopes of one namespace under one centroider description."""

    label: str
    namespace: str
    description: dict
    slopes: Stream


@dataclass
class BagData:
    """Everything a report needs from one bag.

    sensor: the :class:`Sensor` of ``/<wfs>/sensor`` (None if the bag has none);
    sensor_info: the raw JSON dict (with the simulator's extra keys);
    truth: truth stream; frames: frame stream (first ``max_frames``) or None;
    frame_count: frames in the bag; segments: list of :class:`Segment`;
    changes: ``{namespace: [(log_ns, description dict)]}``; topics: reader.topics();
    subapertures: ``{"topic", "count", "selections": [indices list, ...]}`` when the bag has
    subaperture frames (``/<wfs>/frame_subapertures``), else None.
    """

    path: str
    topics: dict
    sensor: Sensor | None
    sensor_info: dict
    truth: Stream | None
    frames: Stream | None
    frame_count: int
    segments: list = field(default_factory=list)
    changes: dict = field(default_factory=dict)
    subapertures: dict | None = None

    @property
    def mas_per_px(self) -> float:
        return self.sensor.mas_per_px if self.sensor is not None else 500.0


# -- topic discovery -----------------------------------------------------------------------
def find_topics(topics: dict) -> dict:
    """Name the contract's topics in a ``{topic: (type, count)}`` map.

    Returns ``{"frame": t|None, "truth": t|None, "sensor": t|None, "slopes": {ns: topic},
    "centroider": {ns: topic}, "frame_subapertures": t|None}``. The frame / truth / sensor topics are the ones under the
    namespace holding ``true_slopes`` (default ``/wfs``), else the first of their kind.
    """
    def leaf(t):
        return t.rstrip("/").rsplit("/", 1)[-1]

    def ns_of(t):
        return t.rstrip("/").rsplit("/", 1)[0].strip("/")

    by_leaf = {}
    for t, (ty, _) in sorted(topics.items()):
        by_leaf.setdefault(leaf(t), []).append((t, ty))
    truth = [t for t, ty in by_leaf.get("true_slopes", []) if ty == IMAGE]
    wfs = ns_of(truth[0]) if truth else "wfs"

    def pick(name, ty_wanted):
        cands = [t for t, ty in by_leaf.get(name, []) if ty == ty_wanted]
        same = [t for t in cands if ns_of(t) == wfs]
        return (same or cands or [None])[0]

    slopes = {ns_of(t) or "/": t for t, ty in by_leaf.get("slopes", []) if ty == IMAGE}
    cents = {ns_of(t) or "/": t for t, ty in by_leaf.get("centroider", []) if ty == STRING}
    return {"frame": pick("frame", IMAGE), "truth": truth[0] if truth else None,
            "sensor": pick("sensor", STRING), "slopes": slopes, "centroider": cents,
            "frame_subapertures": pick(subaps.LEAF, IMAGE)}


# -- reading --------------------------------------------------------------------------------
def read_stream(reader: BagReader, topic: str, max_messages: int | None = None,
                flatten_slopes: bool = False) -> Stream:
    """Decode an Image topic into a :class:`Stream` (first ``max_messages`` messages).

    flatten_slopes: reshape ``(G, G, 2)`` grids to ``(G*G, 2)`` float32.
    Raises BagError for undecodable messages or a shape that changes mid-topic.
    """
    stamps, logs, arrays = [], [], []
    shape = None
    for _, _, log, _, cdr in reader.messages([topic]):
        if max_messages is not None and len(arrays) >= max_messages:
            break
        try:
            stamp, _, enc, arr = decode_image(cdr)
        except ValueError as err:
            raise BagError(f"{reader.path}: {topic}: undecodable Image at log time {log}: {err}") from None
        if flatten_slopes:
            if enc != "32FC2":
                raise BagError(f"{reader.path}: {topic} has encoding {enc}, slopes must be 32FC2")
            arr = arr.reshape(-1, 2)
        if shape is None:
            shape = (arr.shape, arr.dtype)
        elif (arr.shape, arr.dtype) != shape:
            raise BagError(f"{reader.path}: {topic}: message at log time {log} has shape {arr.shape} "
                           f"{arr.dtype}, the first had {shape[0]} {shape[1]}")
        stamps.append(stamp)
        logs.append(log)
        arrays.append(np.array(arr))
    data = np.stack(arrays) if arrays else np.zeros((0, 0, 2), np.float32)
    return Stream(topic, np.asarray(stamps, np.int64), np.asarray(logs, np.int64), data)


def read_json_topic(reader: BagReader, topic: str) -> list[tuple[int, dict]]:
    """``[(log_ns, dict)]`` of a JSON String topic; BagError for text that is not a JSON object."""
    out = []
    for _, _, log, _, cdr in reader.messages([topic]):
        try:
            text = decode_string(cdr)
            d = json.loads(text)
        except (ValueError, json.JSONDecodeError) as err:
            raise BagError(f"{reader.path}: {topic}: message at log time {log} is not JSON: {err}") from None
        if not isinstance(d, dict):
            raise BagError(f"{reader.path}: {topic}: message at log time {log} is not a JSON object")
        out.append((log, d))
    return out


def sensor_from_info(info: dict, where: str = "sensor") -> Sensor:
    try:
        return Sensor.from_dict(info)
    except (SensorError, TypeError, ValueError) as err:
        raise BagError(f"{where}: the sensor description is unusable: {err}") from None


def _distinct(changes):
    """Drop republished descriptions equal to the previous one: ``[(log_ns, dict)]``."""
    out = []
    for log, d in changes:
        if not out or _key(out[-1][1]) != _key(d):
            out.append((log, d))
    return out


def _key(d):
    return json.dumps({k: d.get(k) for k in ("algorithm", "options", "model")}, sort_keys=True, default=str)


def split_segments(ns: str, slopes: Stream, changes: list) -> list[Segment]:
    """Split a namespace's slopes by centroider change (receive-time order).

    A slope belongs to the last description received at or before it (the first one for
    slopes recorded before any description). One segment, labelled ``ns``, when the
    centroider never changed.
    """
    changes = _distinct(sorted(changes, key=lambda c: c[0]))
    if len(changes) <= 1:
        return [Segment(ns, ns, changes[0][1] if changes else {}, slopes)]
    times = np.array([c[0] for c in changes], np.int64)
    which = np.clip(np.searchsorted(times, slopes.log_ns, side="right") - 1, 0, None)
    segs, seen = [], {}
    for k, (_, desc) in enumerate(changes):
        sel = which == k
        if not sel.any():
            continue
        alg = str(desc.get("algorithm", "?"))
        seen[alg] = seen.get(alg, 0) + 1
        label = f"{ns}:{alg}" + (f"#{seen[alg]}" if seen[alg] > 1 else "")
        segs.append(Segment(label, ns, desc, Stream(slopes.topic, slopes.stamps[sel],
                                                    slopes.log_ns[sel], slopes.data[sel])))
    return segs


def load_bag(path, *, max_frames: int | None = 0, need_truth: bool = True) -> BagData:
    """Read a contract bag.

    Args:
        path: the ``.mcap`` file.
        max_frames: frames to decode (0: none, None: all).
        need_truth: raise BagError when there is no ``true_slopes`` topic.
    """
    with BagReader(path) as reader:
        topics = reader.topics()
        names = find_topics(topics)
        if need_truth and names["truth"] is None:
            lacks = "" if names["slopes"] else " and no /<namespace>/slopes topic"
            raise BagError(f"{path}: not an lgs_wfs_ros contract bag: no /<wfs>/true_slopes topic "
                           f"(sensor_msgs/msg/Image, 32FC2) to compare with{lacks}; it has: "
                           f"{', '.join(sorted(topics)) or 'no topics'}")
        info, sensor = {}, None
        if names["sensor"] is not None:
            msgs = read_json_topic(reader, names["sensor"])
            if msgs:
                info = msgs[-1][1]
                sensor = sensor_from_info(info, f"{path}: {names['sensor']}")
        truth = read_stream(reader, names["truth"], flatten_slopes=True) if names["truth"] else None
        frames = None
        frame_count = topics[names["frame"]][1] if names["frame"] else 0
        if names["frame"] and (max_frames is None or max_frames > 0):
            frames = read_stream(reader, names["frame"], max_messages=max_frames)
        changes, segments = {}, []
        for ns, topic in sorted(names["slopes"].items()):
            ch = read_json_topic(reader, names["centroider"][ns]) if ns in names["centroider"] else []
            changes[ns] = ch
            segments += split_segments(ns, read_stream(reader, topic, flatten_slopes=True), ch)
        sub = None
        if names["frame_subapertures"]:
            t = names["frame_subapertures"]
            sub = {"topic": t, "count": topics[t][1],
                   "selections": [d["indices"] for _, d in subaps.selections(reader, t)]}
    if sensor is not None and truth is not None and len(truth) and \
            truth.data.shape[1] != sensor.grid ** 2:
        raise BagError(f"{path}: true_slopes grid has {truth.data.shape[1]} cells, the sensor "
                       f"description a {sensor.grid} x {sensor.grid} grid")
    return BagData(str(path), topics, sensor, info, truth, frames, frame_count, segments, changes, sub)


def _from_stamp(stream: Stream | None, cut: int) -> Stream | None:
    if stream is None:
        return None
    keep = stream.stamps >= cut
    return Stream(stream.topic, stream.stamps[keep], stream.log_ns[keep], stream.data[keep])


def skip_frames(data: BagData, frames: int) -> BagData:
    """``data`` without its first ``frames`` exposures (by the truth's stamps): truths,
    frames and every slope stream from the ``frames``-th truth on, e.g. a pupil
    calibration's warm-up before its first refit. ``data`` itself is not changed."""
    if frames < 0:
        raise ValueError(f"skip: frames must be >= 0, got {frames}")
    if frames == 0 or data.truth is None:
        return data
    stamps = np.unique(data.truth.stamps)
    if frames >= stamps.size:
        raise ValueError(f"skip: {frames} frames asked, the bag has {stamps.size} truths")
    cut = int(stamps[frames])
    segments = [replace(g, slopes=_from_stamp(g.slopes, cut)) for g in data.segments]
    return replace(data, truth=_from_stamp(data.truth, cut),
                               frames=_from_stamp(data.frames, cut), segments=segments)


def joined(truth: Stream, slopes: Stream):
    """Align a segment's slopes with the truths by stamp.

    Returns ``(stamps (K,), estimate (K, G*G, 2), truth (K, G*G, 2), join)`` with ``join``
    the :class:`~lgs_wfs_ros.bags.Join` (missing stamps and duplicates per side).
    """
    if len(truth) and len(slopes) and truth.data.shape[1:] != slopes.data.shape[1:]:
        raise BagError(f"{slopes.topic}: slope grid {slopes.data.shape[1:]} differs from the truth's "
                       f"{truth.data.shape[1:]}")
    j = join_by_stamp(truth.stamps, slopes.stamps)
    return j.stamps, slopes.data[j.indices[1]], truth.data[j.indices[0]], j


__all__ = ["BagData", "IMAGE", "STRING", "Segment", "Stream", "find_topics", "joined", "load_bag",
           "read_json_topic", "read_stream", "sensor_from_info", "skip_frames", "split_segments"]
