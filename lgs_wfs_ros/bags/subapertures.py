"""Frames cut down to chosen subapertures: the recorder's small alternative to full frames.

A full 960 x 960 mono16 frame is 1.8 MB; at 700 Hz that is more than one Python process can
write here (docs/bags.md). The recorder can instead keep, for each frame it records, only the
``p x p`` blocks of ``k`` chosen valid subapertures. Representation in a bag (contract section 5):

* ``/<ns>/frame_subapertures``: ``sensor_msgs/msg/Image`` with the frame's encoding (``mono16``
  or ``32FC1``), ``height = k * p``, ``width = p``: the ``k`` blocks stacked top to bottom in
  the order of the selection; header (stamp, frame_id) = the frame's. Reshaped to
  ``(k, p, p)`` these are ``geometry.frame_to_stack(frame, layout)[indices]``: the blocks a
  centroider sees (on a polar detector, blocks in their local frame as the layout defines).
* ``/<ns>/frame_subapertures_selection``: ``std_msgs/msg/String`` JSON (transient local)
  ``{"indices": [...], "ij": [[row, col], ...], "grid": G, "pixels": p, "n_valid": n,
  "detector": ..., "frame_shape": [H, W], "frame_topic": "/<ns>/frame", "topic":
  "/<ns>/frame_subapertures"}``. Written before the first blocks message of each selection
  (a new one whenever the selection or the sensor changes), with a log time 1 ns before that
  message's, so file order and log-time order agree: each blocks message belongs to the
  last selection before it.

``indices`` are positions in the contract's order of valid subapertures (row-major (i, j),
the order of ``frame_to_stack``, ``slopes_to_grid`` and every centroider).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cdr import decode_image, decode_string, encode_image, encode_string
from .errors import BagError
from .reader import IMAGE, STRING, BagReader

LEAF = "frame_subapertures"
SELECTION_SUFFIX = "_selection"


def selection_topic(topic: str) -> str:
    """The selection (JSON) topic that goes with a blocks topic."""
    return topic + SELECTION_SUFFIX


def blocks_topic(frame_topic: str) -> str:
    """``/<ns>/frame`` -> ``/<ns>/frame_subapertures``."""
    return frame_topic.rstrip("/").rsplit("/", 1)[0] + "/" + LEAF


def parse_indices(values, n_valid: int | None = None) -> np.ndarray:
    """Check a list of valid-subaperture indices; ``(k,)`` int64, read-only (k = 0: off).

    Raises ValueError naming the problem: not integers, negative, ``>= n_valid`` (when
    given), or repeated.
    """
    vals = list(values) if values is not None else []
    bad = [v for v in vals if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer))]
    if bad:
        raise ValueError(f"subaperture indices must be integers, got {bad[0]!r}")
    idx = np.asarray(vals, dtype=np.int64).reshape(-1)
    if (idx < 0).any():
        raise ValueError(f"subaperture index {int(idx[idx < 0][0])} is negative")
    if n_valid is not None and (idx >= n_valid).any():
        raise ValueError(f"subaperture index {int(idx[idx >= n_valid].max())} is out of range: the "
                         f"sensor has {n_valid} valid subapertures (0..{n_valid - 1})")
    uniq, counts = np.unique(idx, return_counts=True)
    if (counts > 1).any():
        dup = uniq[counts > 1]
        raise ValueError(f"subaperture index {int(dup[0])} appears {int(counts[counts > 1][0])} times"
                         + (f" ({len(dup)} indices repeated)" if len(dup) > 1 else ""))
    idx.setflags(write=False)
    return idx


def pixel_index(lay, indices: np.ndarray) -> np.ndarray:
    """``(k, p, p)`` flat positions in the ``(G*p, G*p)`` frame of the chosen blocks' pixels.

    ``frame.reshape(-1)[pixel_index(lay, idx)] == frame_to_stack(frame, lay)[idx]``.
    """
    p, w = lay.sensor.pixels, lay.grid * lay.sensor.pixels
    ij = lay.index[np.asarray(indices, dtype=np.intp)]                  # (k, 2) row, column
    base = ij[:, 0] * p * w + ij[:, 1] * p                               # (k,)
    offs = np.arange(p)[:, None] * w + np.arange(p)[None, :]            # (p, p)
    return base[:, None, None] + offs[None]


class Cutter:
    """Cut the chosen subapertures out of frames of one sensor.

    sensor: the :class:`~lgs_wfs_ros.sensor.Sensor`; indices: valid-subaperture indices
    (checked with :func:`parse_indices` against the sensor; ValueError when they do not fit).
    """

    def __init__(self, sensor, indices):
        from ..optics import geometry

        self.sensor = sensor
        self.layout = geometry.layout(sensor)
        self.indices = parse_indices(indices, self.layout.n_valid)
        if not len(self.indices):
            raise ValueError("no subapertures chosen")
        self.pixels = sensor.pixels
        self.frame_shape = tuple(sensor.frame_shape)
        self._where = pixel_index(self.layout, self.indices)

    @property
    def k(self) -> int:
        return int(self.indices.shape[0])

    def cut(self, frame: np.ndarray) -> np.ndarray:
        """``(H, W)`` frame -> ``(k, p, p)`` blocks (a new array; only those pixels are read)."""
        if frame.shape != self.frame_shape:
            raise ValueError(f"frame has shape {frame.shape}, the sensor expects {self.frame_shape}")
        return np.take(frame.reshape(-1), self._where)

    def message(self, cdr) -> bytes:
        """A frame's CDR (``sensor_msgs/Image``) -> the blocks message's CDR (same header and
        encoding, ``k*p`` x ``p``). The frame's pixels are read in place (a view into ``cdr``).
        ValueError for an undecodable frame or one of another shape."""
        stamp, frame_id, encoding, frame = decode_image(cdr)
        blocks = self.cut(frame)
        return encode_image(blocks.reshape(self.k * self.pixels, self.pixels), stamp,
                            frame_id=frame_id, encoding=encoding)

    def selection(self, frame_topic: str, topic: str | None = None) -> dict:
        """The selection description (see the module doc)."""
        return {"indices": self.indices.tolist(),
                "ij": self.layout.index[self.indices].tolist(),
                "grid": int(self.layout.grid), "pixels": int(self.pixels),
                "n_valid": int(self.layout.n_valid), "detector": self.sensor.detector,
                "frame_shape": list(self.frame_shape), "frame_topic": frame_topic,
                "topic": topic or blocks_topic(frame_topic)}

    def selection_json(self, frame_topic: str, topic: str | None = None) -> str:
        return json.dumps(self.selection(frame_topic, topic), sort_keys=True)


# -- writing ---------------------------------------------------------------------------------
BLOCKS_QOS = {"history": "keep_last", "depth": 100, "reliability": "reliable", "durability": "volatile"}
SELECTION_QOS = {"history": "keep_last", "depth": 1, "reliability": "reliable",
                 "durability": "transient_local"}


def write_blocks(writer, cutter: Cutter, frame_topic: str, cdr, log_ns: int, publish_ns: int | None = None,
                 *, new_selection: bool) -> list[str]:
    """Write one frame's blocks into a :class:`~lgs_wfs_ros.bags.BagWriter` as the contract
    lays them out: when ``new_selection``, first the selection JSON (1 ns before, transient
    local) and the topics; then the blocks message. The one writer of blocks: the recorder
    node and :class:`~lgs_wfs_ros.analysis.bagwrite.ContractBagWriter` both call it.

    cdr: the frame's ``sensor_msgs/Image`` CDR; log_ns / publish_ns: the frame's times.
    Returns the topics written, in order. ValueError (nothing written) for a frame the cutter
    cannot cut.
    """
    msg = cutter.message(cdr)
    out = blocks_topic(frame_topic)
    written = []
    if new_selection:
        sel = selection_topic(out)
        writer.add_topic(out, IMAGE, qos=BLOCKS_QOS)           # same topic and type again: a no-op
        writer.add_topic(sel, STRING, qos=SELECTION_QOS)
        writer.write(sel, encode_string(cutter.selection_json(frame_topic, out)), max(int(log_ns) - 1, 0))
        written.append(sel)
    writer.write(out, msg, log_ns, publish_ns)
    written.append(out)
    return written


# -- reading ---------------------------------------------------------------------------------
@dataclass
class SubapertureSegment:
    """The blocks recorded under one selection.

    selection: the selection dict; stamps ``(m,)`` int64 ns; log_ns ``(m,)`` int64;
    blocks ``(m, k, p, p)`` (the frame's dtype).
    """

    selection: dict
    stamps: np.ndarray
    log_ns: np.ndarray
    blocks: np.ndarray

    @property
    def indices(self) -> np.ndarray:
        return np.asarray(self.selection["indices"], dtype=np.int64)

    def __len__(self):
        return int(self.stamps.shape[0])


def find_blocks_topics(topics: dict) -> list[str]:
    """Blocks topics (leaf ``frame_subapertures``, Image) of a ``{topic: (type, count)}`` map,
    those under ``/wfs`` first."""
    found = [t for t, (ty, _) in topics.items()
             if t.rstrip("/").rsplit("/", 1)[-1] == LEAF and ty == IMAGE]
    return sorted(found, key=lambda t: (t.rsplit("/", 1)[0].strip("/") != "wfs", t))


def _parse_selection(text: str, where: str) -> dict:
    try:
        d = json.loads(text)
        if not isinstance(d, dict):
            raise ValueError("not a JSON object")
        d["indices"] = parse_indices(d.get("indices")).tolist()
        int(d["pixels"])
    except (ValueError, KeyError, TypeError) as err:
        raise BagError(f"{where}: unusable subaperture selection: {err}") from None
    return d


def selections(reader: BagReader, topic: str) -> list[tuple[int, dict]]:
    """``[(log_ns, selection dict)]`` of a blocks topic, read from its selection topic only
    (cheap: the blocks are not decoded). Empty when there is no selection topic."""
    sel_topic = selection_topic(topic)
    if sel_topic not in reader.topics():
        return []
    out = []
    for log, text in reader.strings(sel_topic):
        out.append((log, _parse_selection(text, f"{reader.path}: {sel_topic} at log time {log}")))
    return out


def _open(source):
    if isinstance(source, BagReader):
        return source, False
    return BagReader(Path(source)), True


def subaperture_segments(source, topic: str | None = None) -> list[SubapertureSegment]:
    """Every selection of a bag's blocks topic with its blocks, in file order.

    source: a path or an open :class:`BagReader`; topic: the blocks topic (default: the one
    :func:`find_blocks_topics` lists first). A selection with no blocks after it is kept
    with ``m = 0``. BagError when the bag has no such topic, a blocks message comes before
    any selection, or a message's size does not match its selection.
    """
    reader, own = _open(source)
    try:
        topics = reader.topics()
        if topic is None:
            found = find_blocks_topics(topics)
            if not found:
                raise BagError(f"{reader.path}: no {LEAF} topic (sensor_msgs/msg/Image); it has: "
                               f"{', '.join(sorted(topics)) or 'no topics'}")
            topic = found[0]
        sel_topic = selection_topic(topic)
        if sel_topic not in topics or topics[sel_topic][0] != STRING:
            raise BagError(f"{reader.path}: {topic} has no selection topic {sel_topic} "
                           "(std_msgs/msg/String JSON): the blocks cannot be placed")
        segs, acc = [], None
        for t, _, log, _, cdr in reader.messages([topic, sel_topic]):
            if t == sel_topic:
                try:
                    text = decode_string(cdr)
                except ValueError as err:
                    raise BagError(f"{reader.path}: {sel_topic}: undecodable String at log time {log}: "
                                   f"{err}") from None
                acc = (_parse_selection(text, f"{reader.path}: {sel_topic} at log time {log}"), [], [], [])
                segs.append(acc)
                continue
            if acc is None:
                raise BagError(f"{reader.path}: {topic}: a blocks message (log time {log}) comes before "
                               f"any selection on {sel_topic}")
            sel, stamps, logs, blocks = acc
            try:
                stamp, _, _, arr = decode_image(cdr)
            except ValueError as err:
                raise BagError(f"{reader.path}: {topic}: undecodable Image at log time {log}: {err}") from None
            k, p = len(sel["indices"]), int(sel["pixels"])
            if arr.shape != (k * p, p):
                raise BagError(f"{reader.path}: {topic}: message at log time {log} is {arr.shape}, its "
                               f"selection of {k} subapertures of {p} x {p} px needs {(k * p, p)}")
            stamps.append(stamp)
            logs.append(log)
            blocks.append(np.array(arr).reshape(k, p, p))
    finally:
        if own:
            reader.close()
    out = []
    for sel, stamps, logs, blocks in segs:
        k, p = len(sel["indices"]), int(sel["pixels"])
        data = np.stack(blocks) if blocks else np.zeros((0, k, p, p), np.uint16)
        out.append(SubapertureSegment(sel, np.asarray(stamps, np.int64), np.asarray(logs, np.int64), data))
    return out


def read_subapertures(source, topic: str | None = None, selection: int | None = None):
    """``(stamps (m,) int64 ns, indices (k,) int64, blocks (m, k, p, p))`` of a bag's
    subaperture frames.

    blocks[f, q] is subaperture ``indices[q]`` (contract order of valid subapertures) of
    the frame stamped ``stamps[f]``, as ``frame_to_stack`` cuts it. selection: which
    selection to read when the bag has several with blocks (0 first, -1 last); by default
    there must be exactly one, else BagError listing them.
    """
    segs = subaperture_segments(source, topic)
    used = [s for s in segs if len(s)] or segs[-1:]
    if selection is None:
        if len(used) > 1:
            desc = "; ".join(f"#{i}: {len(s.indices)} subapertures, {len(s)} frames"
                             for i, s in enumerate(used))
            raise BagError(f"the subaperture selection changed during the bag ({desc}); "
                           "choose one with selection=")
        seg = used[0]
    else:
        try:
            seg = used[selection]
        except IndexError:
            raise BagError(f"no subaperture selection #{selection}: the bag has {len(used)}") from None
    return seg.stamps, seg.indices, seg.blocks


__all__ = ["BLOCKS_QOS", "Cutter", "LEAF", "SELECTION_QOS", "SubapertureSegment", "blocks_topic", "find_blocks_topics",
           "parse_indices", "pixel_index", "read_subapertures", "selection_topic", "selections",
           "subaperture_segments", "write_blocks"]
