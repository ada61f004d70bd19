"""Message definitions, type hashes and QoS text as rosbag2 writes them into MCAP.

* :func:`message_definition` builds the ``ros2msg`` schema text exactly as rosbag2's
  ``LocalMessageDefinitionSource``: the root .msg text, then for each dependency once (depth
  first, each message's dependencies in sorted order) a newline, a line of 80 ``=``, a line
  ``MSG: pkg/Type`` (the name as written in the field) and that type's .msg text.
* :func:`type_hash` reads the RIHS01 hash from ``share/<pkg>/msg/<Type>.json``.
* :func:`qos_yaml` renders ``offered_qos_profiles`` in rosbag2's (metadata version 9) form.

The .msg/.json files are searched with ament_index_python (when importable and
``AMENT_PREFIX_PATH`` is set), then under ``sys.prefix/share`` and each
``$AMENT_PREFIX_PATH/share``. Without any ROS interface package installed the contract's
types (Image, String, Header, Time) fall back to built-in copies (comments stripped) and
their Jazzy hashes, so offline tools write valid bags with no ROS at all.
"""

import functools
import json
import os
import re
import sys
from pathlib import Path

SEPARATOR = "=" * 80

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
               "int32", "uint32", "int64", "uint64", "string"}
_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:([A-Za-z][A-Za-z0-9_]*)/)?([A-Za-z][A-Za-z0-9_]*)$")

_BUILTIN_MSG = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/String": "string data\n",
    "sensor_msgs/msg/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\n"
                              "string encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n"),
}
_BUILTIN_HASH = {
    "builtin_interfaces/msg/Time":
        "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    "std_msgs/msg/Header":
        "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "std_msgs/msg/String":
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "sensor_msgs/msg/Image":
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
}


def split_type(type_name):
    """'pkg/msg/Type' or 'pkg/Type' -> (pkg, 'msg', Type); ValueError otherwise."""
    m = _NAME.match(str(type_name))
    if not m:
        raise ValueError(f"not a ROS message type name: {type_name!r} (expected pkg/msg/Type)")
    return m.group(1), m.group(2) or "msg", m.group(3)


def full_type(type_name):
    """Normalise to 'pkg/msg/Type'."""
    return "/".join(split_type(type_name))


def _share_dirs(package):
    dirs = []
    try:
        from ament_index_python.packages import get_package_share_directory
        dirs.append(Path(get_package_share_directory(package)))
    except Exception:  # not importable, not indexed, or AMENT_PREFIX_PATH unset
        pass
    prefixes = [sys.prefix] + [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    dirs += [Path(p) / "share" / package for p in prefixes]
    return dirs


@functools.lru_cache(maxsize=None)
def find_interface_file(type_name, ext):
    """Path of the installed ``share/<pkg>/<ns>/<Type>.<ext>`` or None."""
    pkg, ns, name = split_type(type_name)
    for d in _share_dirs(pkg):
        f = d / ns / f"{name}.{ext}"
        if f.is_file():
            return f
    return None


@functools.lru_cache(maxsize=None)
def _msg_text(type_name):
    f = find_interface_file(type_name, "msg")
    if f is not None:
        return f.read_text(encoding="utf-8")
    key = full_type(type_name)
    if key in _BUILTIN_MSG:
        return _BUILTIN_MSG[key]
    raise LookupError(f"no .msg definition found for {type_name} (searched ament index, "
                      f"{sys.prefix}/share and $AMENT_PREFIX_PATH)")


def _dependencies(text, package):
    deps = set()
    for m in _FIELD_TYPE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{package}/{t}")
    return sorted(deps)


@functools.lru_cache(maxsize=None)
def message_definition(type_name):
    """The complete ``ros2msg`` definition of a type (see module doc). LookupError if a .msg
    file is missing."""
    seen = set()

    def walk(name, depth):
        if depth <= 0:
            raise LookupError(f"recursion too deep resolving {type_name}")
        text = _msg_text(name)
        out = text
        for dep in _dependencies(text, split_type(name)[0]):
            if dep not in seen:
                seen.add(dep)
                out += f"\n{SEPARATOR}\nMSG: {dep}\n" + walk(dep, depth - 1)
        return out

    return walk(full_type(type_name), 50)


@functools.lru_cache(maxsize=None)
def type_hash(type_name):
    """The RIHS01 type hash of a type, or '' when its .json file is not installed."""
    key = full_type(type_name)
    f = find_interface_file(type_name, "json")
    if f is not None:
        try:
            for entry in json.loads(f.read_text(encoding="utf-8"))["type_hashes"]:
                if entry["type_name"] == key:
                    return entry["hash_string"]
        except (ValueError, KeyError, TypeError):
            pass
    return _BUILTIN_HASH.get(key, "")


#: rmw's "infinite" duration as rosbag2 records it.
INFINITE = {"sec": 9223372036, "nsec": 854775807}
_QOS_DEFAULT = {"history": "keep_last", "depth": 10, "reliability": "reliable",
                "durability": "volatile", "deadline": INFINITE, "lifespan": INFINITE,
                "liveliness": "automatic", "liveliness_lease_duration": INFINITE,
                "avoid_ros_namespace_conventions": False}
_QOS_CHOICES = {"history": {"keep_last", "keep_all", "system_default", "unknown"},
                "reliability": {"reliable", "best_effort", "system_default", "best_available", "unknown"},
                "durability": {"volatile", "transient_local", "system_default", "best_available", "unknown"},
                "liveliness": {"automatic", "manual_by_topic", "system_default", "best_available", "unknown"}}


def qos_profile(qos=None):
    """A full rosbag2 QoS dict from a partial one (defaults: reliable, volatile, keep_last 10).

    Durations may be given as {"sec", "nsec"} dicts or float seconds. ValueError for unknown
    keys or values."""
    out = dict(_QOS_DEFAULT)
    for key, value in (qos or {}).items():
        if key not in out:
            raise ValueError(f"unknown QoS key {key!r}; known: {sorted(out)}")
        if key in _QOS_CHOICES:
            value = str(value).lower()
            if value not in _QOS_CHOICES[key]:
                raise ValueError(f"QoS {key}={value!r} not one of {sorted(_QOS_CHOICES[key])}")
        elif key == "depth":
            value = int(value)
            if value < 0:
                raise ValueError("QoS depth must be >= 0")
        elif key == "avoid_ros_namespace_conventions":
            value = bool(value)
        elif not isinstance(value, dict):
            sec = float(value)
            value = {"sec": int(sec), "nsec": int(round((sec - int(sec)) * 1e9))}
        else:
            value = {"sec": int(value["sec"]), "nsec": int(value["nsec"])}
        out[key] = value
    return out


def _yaml_scalar(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    s = str(v)
    if s == "" or re.search(r"[:#\[\]{},&*!|>'\"%@`\n]|^\s|\s$|^[-?]", s) or \
            s.lower() in ("null", "~", "true", "false", "yes", "no", "on", "off") or \
            re.fullmatch(r"[-+.\d][\d._eE+-]*", s):
        return '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    return s


def to_yaml(obj, indent=0):
    """Block-style YAML for dicts, lists and scalars (the shapes rosbag2 metadata uses)."""
    pad = " " * indent
    if isinstance(obj, dict):
        if not obj:
            return pad + "{}\n"
        lines = []
        for k, v in obj.items():
            if isinstance(v, (dict, list)) and v:
                lines.append(f"{pad}{k}:\n" + to_yaml(v, indent + 2))
            else:
                lines.append(f"{pad}{k}: " + (to_yaml(v).strip() if isinstance(v, (dict, list)) else _yaml_scalar(v)) + "\n")
        return "".join(lines)
    if isinstance(obj, list):
        if not obj:
            return pad + "[]\n"
        lines = []
        for v in obj:
            body = to_yaml(v, indent + 2) if isinstance(v, (dict, list)) else pad + "  " + _yaml_scalar(v) + "\n"
            lines.append(pad + "- " + body[indent + 2:])
        return "".join(lines)
    return pad + _yaml_scalar(obj) + "\n"


def qos_yaml(qos=None):
    """``offered_qos_profiles`` channel metadata: a YAML list with one full QoS profile."""
    profiles = qos if isinstance(qos, list) else [qos]
    return to_yaml([qos_profile(q) for q in profiles])
