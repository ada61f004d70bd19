"""``lgs-wfs replay BAG --algorithms cog,cmf,ann [--out BAG2]``: centroid a bag's frames offline.

Copies every message of the input bag into a new bag and, as each frame goes by (file
order, so stateful algorithms such as the CMF see the frames in sequence), writes each
chosen centroider's slopes under its own namespace with the frame's stamp, plus its
``centroider`` description: exactly what the live centroider node would have recorded.
A namespace already in the bag gets the suffix ``_replay``. Needs the bag's ``sensor``
description to cut frames into subapertures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from ..bags import BagError, BagReader, BagWriter, decode_image, encode_image, encode_string
from ..optics import geometry
from .bagdata import IMAGE, STRING, TRANSIENT, VOLATILE, find_topics, read_json_topic, sensor_from_info


def _qos(reader, topic):
    try:
        text = reader.channel_metadata(topic).get("offered_qos_profiles", "")
        data = yaml.safe_load(text) if text else None
        if isinstance(data, list) and data and all(isinstance(d, dict) for d in data):
            return data
    except (yaml.YAMLError, BagError):
        pass
    return None


def _namespaces(algorithms, existing):
    out = {}
    for alg in algorithms:
        ns = alg
        while ns in existing or ns in out.values():
            ns += "_replay"
        out[alg] = ns
    return out


def replay_bag(path, algorithms=("cog", "cmf"), out=None, overwrite: bool = False, model=None,
               quiet: bool = False) -> dict:
    """Run centroiders over a bag's frames and write their slopes into a new bag.

    Args:
        path: input ``.mcap`` (a contract bag with ``frame`` and ``sensor`` topics).
        algorithms: registry names (``lgs_wfs_ros.centroiding.ALGORITHMS``).
        out: output path (default ``<stem>_replay.mcap`` beside the input).
        overwrite: replace an existing output (else BagError).
        model: ONNX model (path or name) for ``ann``.

    Returns ``{"out", "frames", "skipped", "namespaces": {algorithm: namespace}}``; frames that
    cannot be centroided (wrong size, undecodable) get no slopes and are counted in ``skipped``.
    """
    from ..centroiding import make_centroider

    algorithms = [a.strip() for a in algorithms if a and a.strip()]
    if not algorithms:
        raise ValueError("replay needs at least one algorithm")
    src = Path(path)
    out = Path(out) if out is not None else src.with_name(src.stem + "_replay.mcap")
    if out.resolve() == src.resolve():
        raise ValueError("replay output must differ from the input bag")
    with BagReader(src) as reader:
        topics = reader.topics()
        names = find_topics(topics)
        no_frames = names["frame"] is None or topics[names["frame"]][1] == 0
        if no_frames and names["frame_subapertures"] is not None:
            raise BagError(f"{src}: replay needs full frames, and this bag has only the blocks of chosen "
                           f"subapertures ({names['frame_subapertures']}: recorded with the recorder's "
                           "frame_subapertures set); record with full_frame_every >= 1 to replay")
        if names["frame"] is None:
            raise BagError(f"{src}: no frame topic (sensor_msgs/msg/Image); it has: "
                           f"{', '.join(sorted(topics)) or 'no topics'}")
        if names["sensor"] is None:
            raise BagError(f"{src}: no sensor topic (std_msgs/msg/String JSON); replay needs the "
                           "sensor description to cut frames into subapertures")
        msgs = read_json_topic(reader, names["sensor"])
        if not msgs:
            raise BagError(f"{src}: the sensor topic has no message")
        sensor = sensor_from_info(msgs[-1][1], f"{src}: {names['sensor']}")
        cents = {}
        for alg in algorithms:
            opts = {"model": model} if (alg == "ann" and model is not None) else {}
            cents[alg] = make_centroider(alg, sensor, **opts)
        lay = geometry.layout(sensor)
        existing = set(names["slopes"]) | set(names["centroider"])
        spaces = _namespaces(algorithms, existing)
        counts = {"frames": 0, "skipped": 0}
        w = BagWriter(out, overwrite=overwrite)
        try:
            for t, (ty, _) in topics.items():
                w.add_topic(t, ty, qos=_qos(reader, t))
            for alg, ns in spaces.items():
                w.add_topic(f"/{ns}/slopes", IMAGE, qos=VOLATILE)
                w.add_topic(f"/{ns}/centroider", STRING, qos=TRANSIENT)
            described = False
            for topic, _, log, pub, cdr in reader.messages():
                if not described:
                    for alg, ns in spaces.items():
                        d = dict(cents[alg].describe(), replayed_from=str(src))
                        w.write(f"/{ns}/centroider", encode_string(_json(d)), log)
                    described = True
                w.write(topic, cdr, log, pub)
                if topic != names["frame"]:
                    continue
                try:
                    stamp, _, _, frame = decode_image(cdr)
                    results = {alg: c.centroid(frame) for alg, c in cents.items()}
                except ValueError:
                    counts["skipped"] += 1
                    continue
                counts["frames"] += 1
                for alg, slopes in results.items():
                    grid = geometry.slopes_to_grid(slopes.astype(np.float32), lay)
                    w.write(f"/{spaces[alg]}/slopes", encode_image(grid, stamp), log, pub)
        except BaseException:
            _discard(w, out)
            raise
        w.close()
    result = {"out": str(out), **counts, "namespaces": spaces}
    if not quiet:
        print(f"replayed {counts['frames']} frames of {src} with "
              f"{', '.join(f'{a} -> /{n}' for a, n in spaces.items())} into {out}"
              + (f" ({counts['skipped']} frames skipped: wrong size or undecodable)" if counts["skipped"] else ""))
    return result


def _discard(writer, out):
    """Close and delete a half-written output (it was created by this call)."""
    try:
        writer.close()
    except Exception:
        pass
    Path(out).unlink(missing_ok=True)


def _json(d):
    import json
    return json.dumps(d, sort_keys=True, default=str)


__all__ = ["replay_bag"]
