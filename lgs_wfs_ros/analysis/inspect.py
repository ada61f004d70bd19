"""``lgs-wfs inspect BAG``: topics, types, counts, rates, duration, sensor, centroider changes.

A corrupt, truncated or non-MCAP file raises :class:`~lgs_wfs_ros.bags.BagError` with a
one-line reason (the CLI prints it and exits with code 2).
"""

from __future__ import annotations

import json

from ..bags import BagReader
from ..bags import subapertures as subaps
from .bagload import STRING, find_topics, read_json_topic, sensor_from_info


def bag_info(path) -> dict:
    """Machine-readable description of a bag.

    Returns the reader's ``summary()`` (path, size_bytes, complete, profile, library,
    message_count, start_ns, end_ns, duration_s, topics {topic: {type, count, rate_hz}},
    problems) plus ``sensor`` (the JSON dict or None), ``sensor_summary`` (a one-line text)
    and ``centroiders`` ``{namespace: [{"t_s": seconds from the bag start, "log_ns", "description"}]}``
    and ``subapertures`` ``{blocks topic: [{"t_s", "log_ns", "indices", "n_valid", "pixels"}]}``
    (the selections of subaperture frames, see docs/bags.md).
    """
    with BagReader(path) as reader:
        info = reader.summary()
        names = find_topics(reader.topics())
        start = info["start_ns"]
        sensor = None
        if names["sensor"] is not None:
            msgs = read_json_topic(reader, names["sensor"])
            sensor = msgs[-1][1] if msgs else None
        cents = {}
        for ns, topic in sorted(names["centroider"].items()):
            cents[ns] = [{"t_s": (log - start) / 1e9, "log_ns": log, "description": d}
                         for log, d in read_json_topic(reader, topic)]
        sub = {}
        for topic in subaps.find_blocks_topics(reader.topics()):
            sub[topic] = [{"t_s": (log - start) / 1e9, "log_ns": log, "indices": d["indices"],
                           "n_valid": d.get("n_valid"), "pixels": d.get("pixels")}
                          for log, d in subaps.selections(reader, topic)]
    info["sensor"] = sensor
    info["sensor_summary"] = _sensor_line(sensor, str(path)) if sensor is not None else None
    info["centroiders"] = cents
    info["subapertures"] = sub
    info["roles"] = {"frame": names["frame"], "true_slopes": names["truth"], "sensor": names["sensor"],
                     "slopes": names["slopes"], "frame_subapertures": names["frame_subapertures"]}
    return info


def _sensor_line(d: dict, where: str) -> str:
    s = sensor_from_info(d, where)
    mode = (f"single subaperture at ({s.single_subaperture_xy_m[0]:.2f}, "
            f"{s.single_subaperture_xy_m[1]:.2f}) m" if s.is_single else
            f"{s.n_subaps} x {s.n_subaps} subapertures")
    extra = {k: v for k, v in d.items() if k not in s.to_dict()}
    tail = ", ".join(f"{k}={v}" for k, v in sorted(extra.items()) if not isinstance(v, (dict, list)))
    return (f"{s.detector} detector, {mode}, {s.pixels} px/subap at {s.pixel_scale_arcsec}\"/px, "
            f"{s.photons:g} photons, D = {s.diameter_m:g} m, h_ref = {s.h_ref_m / 1e3:g} km, "
            f"r0 = {s.r0_m:g} m, wind {s.wind_speed_mps:g} m/s, {s.frame_rate_hz:g} Hz, "
            f"read noise {s.read_noise_e:g} e-" + (f"; {tail}" if tail else ""))


def _describe(d: dict) -> str:
    alg = d.get("algorithm", "?")
    opts = d.get("options") or {}
    short = {k: v for k, v in opts.items() if not isinstance(v, (list, dict))}
    model = d.get("model") or opts.get("model")
    return f"{alg}" + (f" model={model}" if model and "model" not in short else "") + \
        (" " + json.dumps(short, sort_keys=True, default=str) if short else "")


def format_info(info: dict) -> str:
    """The human-readable text of :func:`bag_info`."""
    lines = [f"bag       {info['path']}",
             f"size      {info['size_bytes'] / 1e6:.2f} MB, profile {info['profile'] or '?'}, "
             f"written by {info['library'] or '?'}, {'complete' if info['complete'] else 'INCOMPLETE'}",
             f"duration  {info['duration_s']:.3f} s, {info['message_count']} messages"]
    lines.append("")
    w = max([len(t) for t in info["topics"]] + [5])
    lines.append(f"{'topic':<{w}}  {'type':<24}{'count':>8}{'rate Hz':>10}")
    for t, v in sorted(info["topics"].items()):
        lines.append(f"{t:<{w}}  {v['type']:<24}{v['count']:>8}{v['rate_hz']:>10.1f}")
    lines.append("")
    lines.append("sensor    " + (info["sensor_summary"] or "none (no sensor topic)"))
    for ns, changes in info["centroiders"].items():
        lines.append(f"centroider /{ns}: {len(changes)} description(s)")
        for c in changes:
            lines.append(f"  t = {c['t_s']:9.3f} s  {_describe(c['description'])}")
    for topic, sels in info.get("subapertures", {}).items():
        count = info["topics"][topic]["count"]
        lines.append(f"subapertures {topic}: {count} frames cut to chosen subapertures, "
                     f"{len(sels)} selection(s)" + ("" if sels else " (NO selection topic: unusable)"))
        for c in sels:
            lines.append(f"  t = {c['t_s']:9.3f} s  {len(c['indices'])} of {c['n_valid']} valid "
                         f"subapertures: {_short_list(c['indices'])}")
    for p in info.get("problems", []):
        lines.append(f"problem   {p}")
    roles = info["roles"]
    missing = [k for k in ("frame", "true_slopes", "sensor") if roles[k] is None
               and not (k == "frame" and roles.get("frame_subapertures"))]
    if missing:
        lines.append("note      not an lgs_wfs_ros contract bag (docs/conventions.md section 5): no "
                     + ", ".join(missing) + " topic" + ("" if roles["slopes"] else ", no slopes topic"))
    no_frames = roles["frame"] is None or info["topics"][roles["frame"]]["count"] == 0
    if no_frames and roles.get("frame_subapertures"):
        lines.append("note      no full frames, only chosen subapertures: `lgs-wfs replay` needs full frames")
    return "\n".join(lines)


def _short_list(values, most: int = 24) -> str:
    """``[3, 17, 40]``; long lists keep their first and last entries around ``...``."""
    vals = [str(v) for v in values]
    if len(vals) > most:
        vals = vals[:most // 2] + ["..."] + vals[-most // 2:]
    return "[" + ", ".join(vals) + "]"


def inspect_bag(path, as_json: bool = False) -> str:
    """Text (or JSON text) describing a bag; BagError when it is not a readable MCAP bag."""
    info = bag_info(path)
    if as_json:
        return json.dumps(info, indent=2, sort_keys=True, default=str)
    return format_info(info)


__all__ = ["inspect_bag", "bag_info", "format_info", "STRING"]
