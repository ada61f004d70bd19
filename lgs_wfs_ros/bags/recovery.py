"""The recovery command: copy every readable message of a damaged bag into a new, complete
bag. One implementation for ``lgs-wfs recover`` and ``python -m lgs_wfs_ros.bags recover``
(same output, same exit codes: 0 the source was intact, 1 something was skipped or cut, 2
refused: the callers print the BagError and return 2)."""

import json
import os
import sys
from pathlib import Path

from .errors import BagError
from .reader import BagReader
from .writer import BagWriter


def recover_command(src, dst, *, overwrite=False, out=None) -> int:
    """Run :func:`recover`, print its statistics as JSON to ``out`` (default stdout) and
    return the exit code (0 intact, 1 problems). BagError propagates."""
    stats = recover(src, dst, overwrite=overwrite)
    print(json.dumps(stats, indent=2), file=out or sys.stdout)
    return 1 if stats["problems"] else 0


def recover(src, dst, *, overwrite=False, compression="zstd", transform=None):
    """Copy every readable message of a (possibly truncated or damaged) bag into a new,
    complete bag. Returns {"messages": n, "topics": {topic: n}, "problems": [...],
    "source_complete": bool}. This is the recovery command (``lgs-wfs recover SRC DST``).

    transform: ``f(type_name, cdr) -> cdr`` applied to every message on the way (e.g.
    :func:`lgs_wfs_ros.bags.portable.portable_cdr`); default: copied as they are."""
    if Path(dst).exists() and Path(src).exists() and os.path.samefile(src, dst):
        raise BagError(f"{dst}: recovery must write a new file, not the damaged source")
    reader = BagReader(src, strict=False)
    counts = {}
    try:
        schemas, channels = {}, {}
        types = {}                  # topic -> type name
        with BagWriter(dst, overwrite=overwrite, compression=compression) as w:
            for item in reader._records():
                if item[0] == "schema":
                    schemas[item[1]] = item[2]
                elif item[0] == "channel":
                    cid, sid, topic, _, meta = item[1:]
                    channels[cid] = topic
                    types[topic] = schemas.get(sid, "")
                    if topic not in w.topics:
                        qos = _qos_from_yaml(meta.get("offered_qos_profiles", ""))
                        try:
                            try:
                                w.add_topic(topic, schemas.get(sid, ""), qos=qos)
                            except ValueError:
                                w.add_topic(topic, schemas.get(sid, ""))
                        except ValueError as err:
                            reader.problems.append(f"topic {topic} skipped: {err}")
                elif item[0] == "message":
                    topic = channels.get(item[1])
                    if topic is None or topic not in w.topics:
                        continue
                    data = item[5] if transform is None else transform(types[topic], item[5])
                    w.write(topic, data, item[3], item[4], sequence=item[2])
                    counts[topic] = counts.get(topic, 0) + 1
    finally:
        reader.close()
    return {"messages": sum(counts.values()), "topics": counts, "problems": list(reader.problems),
            "source_complete": reader.complete}


def _qos_from_yaml(text):
    """Parse offered_qos_profiles back into dicts (None when absent or unreadable)."""
    try:
        import yaml
        data = yaml.safe_load(text) if text else None
        if isinstance(data, list) and data and all(isinstance(d, dict) for d in data):
            return data
    except Exception:
        pass
    return None
