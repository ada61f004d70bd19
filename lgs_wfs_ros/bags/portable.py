"""Bags carry names, not paths: a bag must not embed the file system of the machine that made it.

A model is named, with its SHA-256 (``{"model": "ann_1k", "model_file": "ann_1k.onnx",
"model_sha256": "..."}``), never ``/home/.../models/ann_1k.onnx``; any other absolute file
path in a JSON description is cut to its file name. The contract bag writer passes every
description through :func:`portable`, and :func:`scrub_bag` rewrites an existing bag's
JSON ``std_msgs/String`` messages the same way (everything else is copied byte for byte).
"""

from __future__ import annotations

import json
import os
from pathlib import PurePath

from .cdr import decode_string, encode_string
from .errors import BagError
from .reader import STRING


def is_path(value) -> bool:
    """An absolute file path (``/a/b/file.ext``), as opposed to a ROS name (``/wfs/frame``:
    ROS names cannot contain ``.``) or plain text."""
    return (isinstance(value, str) and os.path.isabs(value) and "." in PurePath(value).name
            and "\n" not in value)


def portable(obj):
    """A copy of a JSON-like description with names instead of absolute paths.

    ``model_path`` becomes ``model_file`` (the file name), with ``model`` set to its stem when
    the description names no model; any other absolute file path becomes its file name.
    Everything else is unchanged."""
    if isinstance(obj, list):
        return [portable(v) for v in obj]
    if not isinstance(obj, dict):
        return PurePath(obj).name if is_path(obj) else obj
    out = {}
    for key, value in obj.items():
        if key == "model_path" and isinstance(value, str):
            name = PurePath(value).name
            out.setdefault("model_file", name)
            opts = obj.get("options") if isinstance(obj.get("options"), dict) else {}
            if not obj.get("model") and not opts.get("model"):
                out["model"] = PurePath(name).stem
            continue
        out[key] = portable(value)
    return out


def portable_json(text: str) -> str:
    """:func:`portable` of a JSON object text; other text unchanged."""
    try:
        obj = json.loads(text)
    except ValueError:
        return text
    if not isinstance(obj, dict):
        return text
    new = portable(obj)
    return text if new == obj else json.dumps(new, sort_keys=True)


def portable_cdr(type_name: str, cdr):
    """A message's CDR with :func:`portable_json` applied when it is a ``std_msgs/String``."""
    if type_name != STRING:
        return cdr
    try:
        text = decode_string(cdr)
    except ValueError:
        return cdr
    new = portable_json(text)
    return cdr if new == text else encode_string(new)


def scrub_bag(src, dst, *, overwrite: bool = False, compression: str = "zstd") -> dict:
    """Copy a complete bag to ``dst`` with every JSON String message made portable.
    Returns the copy's statistics (:func:`~lgs_wfs_ros.bags.recover`'s); BagError for a
    damaged source (recover it first)."""
    from .recovery import recover
    stats = recover(src, dst, overwrite=overwrite, compression=compression, transform=portable_cdr)
    if stats["problems"] or not stats["source_complete"]:
        os.unlink(dst)
        raise BagError(f"{src}: damaged ({'; '.join(stats['problems']) or 'incomplete'}); "
                       f"run `lgs-wfs recover` first")
    return stats


__all__ = ["is_path", "portable", "portable_cdr", "portable_json", "scrub_bag"]
