"""``lgs-wfs replay BAG --algorithms cog,cmf,ann [--out BAG2]``: centroid a bag's frames offline.

Copies every message of the input bag into a new bag and, as each frame goes by (file
order, so stateful algorithms such as the CMF see the frames in sequence), writes each
chosen centroider's slopes under its own namespace with the frame's stamp, plus its
``centroider`` description: exactly what the live centroider node would have recorded.
A namespace already in the bag gets the suffix ``_replay``. Needs the bag's ``sensor``
description to cut frames into subapertures.

Options: every centroider is built by :func:`lgs_wfs_ros.centroiding.options.build` (the
defaults of the node, the demo and the Python API). For an algorithm whose ``centroider``
description is recorded in the bag, replay uses the options recorded there (the last
description of that algorithm: what the node ran live), so the replayed slopes are the
live ones; ``options`` overrides that per algorithm. ``models`` runs ``ann`` once per model.
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


def recorded_options(reader, names) -> dict:
    """``{algorithm: options}`` from the bag's centroider descriptions (the last one of each
    algorithm, in file order), restricted to the options the table knows, with the defaults
    the bag was recorded under (:func:`recorded_defaults`)."""
    from ..centroiding import options as table
    out = {}
    for topic in names["centroider"].values():
        for _, d in read_json_topic(reader, topic):
            alg = d.get("algorithm")
            if alg in table.OPTIONS and isinstance(d.get("options"), dict):
                known = {o.name for o in table.OPTIONS[alg]}
                out[alg] = {k: v for k, v in d["options"].items() if k in known}
    return recorded_defaults(out)


def recorded_defaults(options: dict) -> dict:
    """``{algorithm: options}`` recorded under older defaults, completed with them (in
    place): a cmf without ``filters`` (recorded before the grid of filters became its
    default) is the single filter it was live; a cog with ``bias: pupil`` and no
    ``linearize`` (recorded before it inverted its response, 2026-11-26) subtracted the
    bias alone; an ann without ``bias`` (recorded before it subtracted its reading of the
    calibrated reference, 2026-11-26) subtracted nothing."""
    if "cmf" in options and "filters" not in options["cmf"]:
        options["cmf"]["filters"] = "single"
    cog = options.get("cog")
    if cog is not None and cog.get("bias") == "pupil" and "linearize" not in cog:
        cog["linearize"] = False
    if "ann" in options and "bias" not in options["ann"]:
        options["ann"]["bias"] = "none"
    return options


#: the options source of an algorithm recorded with background refits and no lag, replayed
#: with its refits inline (:func:`_plan`)
INLINE = "bag, refits inline"


def _plan(algorithms, models, given, recorded):
    """``[(label, algorithm, options, source)]``: one entry per algorithm (per model for ann).

    An algorithm recorded with ``pupil_async`` and no ``pupil_async_lag`` installed each refit
    whenever it was ready, at frames the bag does not record: replayed so, its slopes would
    depend on this machine's speed and differ from run to run, so it is replayed with its
    refits inline (source :data:`INLINE`), reproducible, as the benchmarks run."""
    plan = []
    for alg in algorithms:
        opts, source = (dict(given[alg]), "given") if alg in given else \
            (dict(recorded[alg]), "bag") if alg in recorded else ({}, "defaults")
        if source == "bag" and opts.get("pupil_async") and not opts.get("pupil_async_lag"):
            opts["pupil_async"], source = False, INLINE
        if alg == "ann" and models:
            for m in models:
                label = "ann" if len(models) == 1 else "ann_" + "".join(
                    ch if ch.isalnum() else "_" for ch in Path(str(m)).with_suffix("").as_posix())
                run = {**opts, "model": str(m)}
                if run.get("bias") == "pupil" and str(m) != opts.get("model"):
                    run["bias"] = "auto"        # the recorded model's setting, not this one's
                plan.append((label, alg, run, "given"))
        else:
            plan.append((alg, alg, opts, source))
    return plan


def replay_bag(path, algorithms=("cog", "cmf"), out=None, overwrite: bool = False, model=None,
               quiet: bool = False, models=None, options=None) -> dict:
    """Run centroiders over a bag's frames and write their slopes into a new bag.

    Args:
        path: input ``.mcap`` (a contract bag with ``frame`` and ``sensor`` topics).
        algorithms: registry names (``lgs_wfs_ros.centroiding.ALGORITHMS``).
        out: output path (default ``<stem>_replay.mcap`` beside the input).
        overwrite: replace an existing output (else BagError).
        model: ONNX model (path or name) for ``ann`` (same as ``models=[model]``).
        models: several ONNX models: ``ann`` runs once per model, namespaces ``ann_<name>``.
        options: ``{algorithm: {option: value}}`` replacing the options recorded in the bag
            for those algorithms (others keep the recorded ones, or the defaults).

    Returns ``{"out", "frames", "skipped", "namespaces": {label: namespace},
    "options": {label: {"algorithm", "options", "source"}}}`` (source: "bag", "given" or
    "defaults"); frames that cannot be centroided (wrong size, undecodable) get no slopes
    and are counted in ``skipped``.
    """
    from ..centroiding import notice_of
    from ..centroiding import options as table

    algorithms = [a.strip() for a in algorithms if a and a.strip()]
    if not algorithms:
        raise ValueError("replay needs at least one algorithm")
    models = list(models or []) + ([model] if model is not None else [])
    given = dict(options or {})
    for alg, opts in given.items():
        if alg not in table.OPTIONS or not isinstance(opts, dict):
            raise ValueError(f"replay options must be {{algorithm: {{option: value}}}} with algorithms "
                             f"among {', '.join(table.OPTIONS)}; got {alg!r}: {opts!r}")
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
        plan = _plan(algorithms, models, given, recorded_options(reader, names))
        cents = {label: table.build(alg, sensor, opts) for label, alg, opts, _ in plan}
        used = {label: {"algorithm": alg, "options": opts, "source": source}
                for label, alg, opts, source in plan}
        lay = geometry.layout(sensor)
        existing = set(names["slopes"]) | set(names["centroider"])
        spaces = _namespaces(list(cents), existing)
        counts = {"frames": 0, "skipped": 0}
        w = BagWriter(out, overwrite=overwrite)
        try:
            for t, (ty, _) in topics.items():
                w.add_topic(t, ty, qos=_qos(reader, t))
            for alg, ns in spaces.items():
                w.add_topic(f"/{ns}/slopes", IMAGE, qos=VOLATILE)
                w.add_topic(f"/{ns}/centroider", STRING, qos=TRANSIENT)
            described = False
            notices = {alg: "" for alg in cents}

            def describe(alg, log, reason):
                d = dict(cents[alg].describe(), replayed_from=src.name,
                         options_source=used[alg]["source"], reason=reason)
                w.write(f"/{spaces[alg]}/centroider", encode_string(_json(d)), log)
                notices[alg] = notice_of(cents[alg])
                if reason != "replay" and not quiet:
                    print(f"{alg}: {d.get('warning', '') if notices[alg] else 'notice cleared'} "
                          f"(frame {counts['frames']})")

            for topic, _, log, pub, cdr in reader.messages():
                if not described:
                    for alg in spaces:
                        describe(alg, log, "replay")
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
                    if notice_of(cents[alg]) != notices[alg]:      # as the node: once a change
                        describe(alg, log, "notice" if notice_of(cents[alg]) else "notice cleared")
        except BaseException:
            _discard(w, out)
            raise
        w.close()
    result = {"out": str(out), **counts, "namespaces": spaces, "options": used}
    if not quiet:
        for alg, u in used.items():
            if u["source"] == INLINE:
                hint = _json({u["algorithm"]: {"pupil_async": True, "pupil_async_lag": 140}})
                print(f"{alg}: recorded with pupil_async and no pupil_async_lag (each refit "
                      f"installed when ready, at frames the bag does not record): replayed with "
                      f"its refits inline, reproducible but not the live slopes; --options "
                      f"'{hint}' replays refits installed 140 frames after each period's end")
        what = ", ".join(f"{a} -> /{n} ({used[a]['source']} options)" for a, n in spaces.items())
        print(f"replayed {counts['frames']} frames of {src} with {what} into {out}"
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


__all__ = ["replay_bag", "recorded_options"]
