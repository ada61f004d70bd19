"""BagReader: read MCAP bags (ours or rosbag2's) without ROS; recover truncated ones.

Reads the summary section when the file is complete, else scans records from the start.
Messages come out in file order. Every failure is a :class:`BagError` with a message for
users: not a file, not MCAP, truncated (no footer: e.g. the recorder was SIGKILLed),
corrupt (CRC mismatch, undecodable chunk, malformed record), unknown topic, wrong type.

``strict=True`` (default) refuses damaged files: at open when the end of the file is
missing or the summary is corrupt, while reading at the first corrupt chunk. With
``strict=False`` a reader returns everything readable: all complete chunks up to a
truncation, skipping corrupt chunks whose length is intact; ``problems`` lists what was
skipped. :func:`recover` uses that to copy a damaged bag into a complete one.
"""

import mmap
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from . import mcapfmt as fmt
from .cdr import decode_image, decode_string
from .errors import BagError

IMAGE = "sensor_msgs/msg/Image"
STRING = "std_msgs/msg/String"
_FOOTER_LEN = 1 + 8 + 20   # opcode, length, body
_TRAILER = _FOOTER_LEN + len(fmt.MAGIC)


class _Truncated(Exception):
    pass


class _Corrupt(Exception):
    pass


def _decompress(kind, data, size):
    try:
        if kind == "":
            return data
        if kind == "zstd":
            import zstandard
            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif kind == "lz4":
            import lz4.frame
            out = lz4.frame.decompress(data)
        else:
            raise _Corrupt(f"unsupported chunk compression {kind!r}")
    except _Corrupt:
        raise
    except Exception as err:  # codec errors have many types
        raise _Corrupt(f"{kind} decompression failed: {err}") from None
    if len(out) != size:
        raise _Corrupt(f"chunk decompressed to {len(out)} bytes, header says {size}")
    return out


SCAN_SUMMARY_BYTES = 256 * 2**20   # summary() reads bags up to this size whole: exact per-topic rates


class BagReader:
    """Read an MCAP bag. path: the .mcap file; strict: see module doc.

    Attributes: path, size, profile, library, complete (footer and summary intact),
    problems (list of str: what a non-strict read skipped)."""

    def __init__(self, path, *, strict=True):
        self.path = Path(path)
        self.strict = bool(strict)
        self.problems = []
        if not self.path.exists():
            raise BagError(f"{self.path}: no such file")
        if not self.path.is_file():
            raise BagError(f"{self.path}: not a file")
        try:
            self._f = open(self.path, "rb")
        except OSError as err:
            raise BagError(f"{self.path}: cannot open: {err.strerror}") from None
        self.size = os.fstat(self._f.fileno()).st_size
        self._mm = None
        try:
            if self.size < 8:
                raise self._err(f"not an MCAP file (only {self.size} bytes)")
            try:
                self._mm = mmap.mmap(self._f.fileno(), 0, access=mmap.ACCESS_READ)
            except (OSError, ValueError) as err:
                raise self._err(f"cannot map the file: {err}") from None
            self._buf = memoryview(self._mm)
            self._open()
        except BagError:
            self.close()
            raise

    # -- opening ----------------------------------------------------------------------
    def _err(self, what):
        return BagError(f"{self.path}: {what}")

    def _open(self):
        if bytes(self._buf[:8]) != fmt.MAGIC:
            raise self._err("not an MCAP file (bad magic bytes)")
        try:
            op, body = self._read_record_at(8)
            if op != fmt.OP_HEADER:
                raise _Corrupt("first record is not an MCAP Header")
            c = fmt.Cursor(body)
            self.profile, self.library = c.string(), c.string()
        except (_Truncated, _Corrupt, ValueError, struct.error) as err:
            raise self._err(f"unreadable MCAP header: {err}") from None
        self._data_start = 8 + 9 + len(body)
        self._summary = None
        self.complete = False
        try:
            self._summary = self._read_summary()
            self.complete = True
        except _Truncated as err:
            self._problem(f"truncated ({err}); the complete chunks before the cut are readable: "
                          f"run `lgs-wfs recover {self.path} OUT.mcap`")
        except (_Corrupt, ValueError, struct.error) as err:
            self._problem(f"corrupt summary ({err})")

    def _problem(self, text):
        if self.strict:
            raise self._err(text)
        self.problems.append(text)

    def _read_record_at(self, offset):
        """(opcode, body bytes) of the record at a file offset; _Truncated past the end."""
        if offset + 9 > self.size:
            raise _Truncated(f"file ends inside a record header at byte {offset}")
        op, length = struct.unpack_from("<BQ", self._buf, offset)
        if offset + 9 + length > self.size:
            raise _Truncated(f"record at byte {offset} (opcode {op:#04x}, {length} bytes) runs past "
                             f"the end of the file ({self.size} bytes)")
        return op, self._buf[offset + 9:offset + 9 + length]

    def _read_summary(self):
        if self.size < self._data_start + _TRAILER:
            raise _Truncated("file too short for an MCAP footer")
        tail = bytes(self._buf[self.size - _TRAILER:])
        if tail[-8:] != fmt.MAGIC or tail[0] != fmt.OP_FOOTER:
            raise _Truncated("no footer at the end of the file")
        _, length, sstart, ostart, crc = struct.unpack("<BQQQI", tail[:_FOOTER_LEN])
        if length != 20:
            raise _Corrupt("malformed footer")
        footer_at = self.size - _TRAILER
        out = {"schemas": {}, "channels": {}, "stats": None, "chunks": [], "metadata": []}
        if sstart == 0:
            return None            # a valid file without summary: scan
        if not self._data_start <= sstart <= footer_at:
            raise _Corrupt("footer points outside the file")
        blob = self._buf[sstart:footer_at]
        if crc:
            calc = zlib.crc32(tail[:_FOOTER_LEN - 4], zlib.crc32(blob))
            if calc != crc:
                raise _Corrupt("summary CRC mismatch")
        c = fmt.Cursor(blob)
        while c.pos < c.end:
            op = c.u8()
            body = fmt.Cursor(c.take(c.u64()))
            if op == fmt.OP_SCHEMA:
                sid, name, enc, data = fmt.parse_schema(body)
                out["schemas"][sid] = (name, enc, data)
            elif op == fmt.OP_CHANNEL:
                cid, sid, topic, enc, meta = fmt.parse_channel(body)
                out["channels"][cid] = (topic, sid, enc, meta)
            elif op == fmt.OP_STATISTICS:
                n, _, _, _, _, nchunks = struct.unpack("<QHIIII", body.take(26))
                start, end = body.u64(), body.u64()
                m = body.u32()
                counts = dict(struct.iter_unpack("<HQ", body.take(m))) if m % 10 == 0 else None
                if counts is None:
                    raise _Corrupt("malformed statistics")
                out["stats"] = {"count": n, "chunks": nchunks, "start": start, "end": end, "counts": counts}
            elif op == fmt.OP_CHUNK_INDEX:
                start, end, off, length = struct.unpack("<QQQQ", body.take(32))
                m = body.u32()
                chans = {cid for cid, _ in struct.iter_unpack("<HQ", body.take(m))} if m % 10 == 0 else None
                if chans is None or off + length > footer_at:
                    raise _Corrupt("malformed chunk index")
                out["chunks"].append((off, length, chans))
            elif op == fmt.OP_METADATA_INDEX:
                off, length = body.u64(), body.u64()
                out["metadata"].append((off, length, body.string()))
        for cid, (topic, sid, _, _) in out["channels"].items():
            if sid and sid not in out["schemas"]:
                raise _Corrupt(f"channel {topic} refers to a missing schema")
        return out

    # -- scanning ---------------------------------------------------------------------
    def _records(self, channel_filter=None):
        """Yield ('schema'|'channel'|'message'|'metadata', ...) in file order. Handles damage
        according to ``strict``; chunks holding none of channel_filter are skipped when the
        summary lists their channels."""
        chunk_chans = None
        if channel_filter is not None and self._summary is not None and self._summary["chunks"]:
            chunk_chans = {off: chans for off, _, chans in self._summary["chunks"]}
        offset = self._data_start
        while offset < self.size:
            try:
                if offset + 9 > self.size:
                    raise _Truncated(f"file ends inside a record header at byte {offset}")
                op, length = struct.unpack_from("<BQ", self._buf, offset)
                nxt = offset + 9 + length
                if nxt > self.size:
                    raise _Truncated(f"record at byte {offset} (opcode {op:#04x}) needs {length} bytes, "
                                     f"the file has {self.size - offset - 9} left")
                if op in (fmt.OP_DATA_END, fmt.OP_FOOTER):
                    return
                if op == fmt.OP_CHUNK and chunk_chans is not None and offset in chunk_chans \
                        and not (chunk_chans[offset] & channel_filter):
                    offset = nxt
                    continue
                if op not in (fmt.OP_SCHEMA, fmt.OP_CHANNEL, fmt.OP_MESSAGE, fmt.OP_CHUNK, fmt.OP_METADATA):
                    offset = nxt
                    continue
                body = self._buf[offset + 9:nxt]
                try:
                    items = list(self._parse(op, body))
                except (_Corrupt, ValueError, struct.error, UnicodeDecodeError) as err:
                    self._problem(f"corrupt record at byte {offset} (opcode {op:#04x}): {err}")
                    items = []
                yield from items
                offset = nxt
            except _Truncated as err:
                self._problem(f"truncated: {err}; everything before byte {offset} was read")
                return

    def _parse(self, op, body):
        if op == fmt.OP_CHUNK:
            c = fmt.Cursor(body)
            _, _, usize, crc = struct.unpack("<QQQI", c.take(28))
            kind = c.string()
            data = c.take(c.u64())
            if usize > 2**34:
                raise _Corrupt(f"implausible uncompressed chunk size {usize}")
            records = _decompress(kind, data, usize)
            if crc and zlib.crc32(records) != crc:
                raise _Corrupt("chunk CRC mismatch")
            inner = fmt.Cursor(records)
            out = []
            while inner.pos < inner.end:
                iop = inner.u8()
                rec = inner.take(inner.u64())
                if iop in (fmt.OP_SCHEMA, fmt.OP_CHANNEL, fmt.OP_MESSAGE):
                    out += self._parse(iop, rec)
            return out
        c = fmt.Cursor(body)
        if op == fmt.OP_SCHEMA:
            return [("schema",) + fmt.parse_schema(c)]
        if op == fmt.OP_CHANNEL:
            return [("channel",) + fmt.parse_channel(c)]
        if op == fmt.OP_MESSAGE:
            cid, seq, log, pub = struct.unpack("<HIQQ", c.take(22))
            return [("message", cid, seq, log, pub, c.mv[c.pos:])]
        if op == fmt.OP_METADATA:
            return [("metadata", c.string(), c.str_map())]
        return []

    def _iter(self, topics=None):
        """(topic, type, log, publish, memoryview) for messages of the wanted topics."""
        schemas, channels = {}, {}
        want_ids = None
        if topics is not None:
            topics = set(topics)
            self._check_topics(topics)
            if self._summary is not None:
                want_ids = {cid for cid, ch in self._summary["channels"].items() if ch[0] in topics}
        for item in self._records(want_ids):
            kind = item[0]
            if kind == "schema":
                schemas[item[1]] = item[2]
            elif kind == "channel":
                channels[item[1]] = (item[3], item[2])
            elif kind == "message":
                ch = channels.get(item[1])
                if ch is None:
                    self._problem(f"message on unknown channel id {item[1]} (corrupt file)")
                    continue
                if topics is None or ch[0] in topics:
                    yield ch[0], schemas.get(ch[1], ""), item[3], item[4], item[5]

    def _scan(self):
        if getattr(self, "_scanned", None) is None:
            schemas, channels, counts, meta = {}, {}, {}, []
            start, end = None, 0
            first, last = {}, {}
            for item in self._records():
                if item[0] == "schema":
                    schemas[item[1]] = item[2]
                elif item[0] == "channel":
                    channels[item[1]] = (item[3], item[2])
                elif item[0] == "message":
                    cid, log = item[1], item[3]
                    counts[cid] = counts.get(cid, 0) + 1
                    first.setdefault(cid, log)
                    last[cid] = log
                    start = log if start is None else min(start, log)
                    end = max(end, log)
                elif item[0] == "metadata":
                    meta.append((item[1], item[2]))
            topics = {}
            for cid, (topic, sid) in channels.items():
                topics[topic] = (schemas.get(sid, ""), counts.get(cid, 0), first.get(cid), last.get(cid))
            self._scanned = {"topics": topics, "start": start or 0, "end": end, "metadata": meta}
        return self._scanned

    # -- public -----------------------------------------------------------------------
    def topics(self):
        """dict topic -> (type name, message count)."""
        if self._summary is not None and self._summary["stats"] is not None:
            s = self._summary
            return {topic: (s["schemas"].get(sid, ("",))[0], s["stats"]["counts"].get(cid, 0))
                    for cid, (topic, sid, _, _) in s["channels"].items()}
        return {t: v[:2] for t, v in self._scan()["topics"].items()}

    def channel_metadata(self, topic):
        """The channel's metadata dict (offered_qos_profiles, topic_type_hash)."""
        self._check_topics({topic})
        chans = self._summary["channels"].values() if self._summary else None
        if chans is None:
            chans = [(i[3], i[2], i[4], i[5]) for i in self._records() if i[0] == "channel"]
        for topic_, _, _, meta in chans:
            if topic_ == topic:
                return dict(meta)
        return {}

    def schema_text(self, topic):
        """The ros2msg definition stored for a topic's type."""
        self._check_topics({topic})
        name = self.topics()[topic][0]
        if self._summary is not None:
            found = [d for n, _, d in self._summary["schemas"].values() if n == name]
        else:
            found = [i[4] for i in self._records() if i[0] == "schema" and i[2] == name]
        return found[0].decode("utf-8", "replace") if found else ""

    def metadata(self):
        """list of (name, dict) Metadata records (e.g. ('rosbag2', {'serialized_metadata': ...}))."""
        if self._summary is not None and self._summary["metadata"]:
            out = []
            for off, _, _ in self._summary["metadata"]:
                try:
                    op, body = self._read_record_at(off)
                    if op != fmt.OP_METADATA:
                        raise _Corrupt("metadata index points at another record")
                    c = fmt.Cursor(body)
                    out.append((c.string(), c.str_map()))
                except (_Truncated, _Corrupt, ValueError, UnicodeDecodeError) as err:
                    self._problem(f"unreadable metadata record at byte {off}: {err}")
            return out
        return self._scan()["metadata"]

    def summary(self):
        """dict: path, size_bytes, complete, types, profile, library, message_count, start_ns, end_ns,
        duration_s, topics {topic: {type, count, rate_hz}}, problems. rate_hz is count - 1 over
        the topic's first-to-last log time when scanned (every bag up to SCAN_SUMMARY_BYTES, and
        every bag without a summary), else over the bag's whole span (the MCAP summary has no
        per-topic times, and a start delay before the first frame then lowers the rate)."""
        if self._summary is not None and self._summary["stats"] is not None \
                and self.size > SCAN_SUMMARY_BYTES:
            st = self._summary["stats"]
            start, end = st["start"], st["end"]
            span = (end - start) / 1e9
            topics = {t: {"type": ty, "count": n, "rate_hz": ((n - 1) / span if span > 0 and n > 1 else 0.0)}
                      for t, (ty, n) in self.topics().items()}
        else:
            sc = self._scan()
            start, end = sc["start"], sc["end"]
            topics = {}
            for t, (ty, n, a, b) in sc["topics"].items():
                rate = (n - 1) / ((b - a) / 1e9) if n > 1 and b > a else 0.0
                topics[t] = {"type": ty, "count": n, "rate_hz": rate}
        return {"path": str(self.path), "size_bytes": self.size, "complete": self.complete,
                "types": sorted({v["type"] for v in topics.values()}),
                "profile": self.profile, "library": self.library,
                "message_count": sum(v["count"] for v in topics.values()),
                "start_ns": start, "end_ns": end, "duration_s": max(end - start, 0) / 1e9,
                "topics": topics, "problems": list(self.problems)}

    def messages(self, topics=None):
        """Yield (topic, type, log_time_ns, publish_time_ns, cdr bytes) in file order."""
        for topic, ty, log, pub, mv in self._iter(topics):
            yield topic, ty, log, pub, bytes(mv)

    def _check_topics(self, wanted):
        have = self.topics()
        missing = sorted(set(wanted) - set(have))
        if missing:
            raise self._err(f"no topic {', '.join(missing)} in the bag; it has: "
                            f"{', '.join(sorted(have)) or 'no topics'}")

    def _check_type(self, topic, expected):
        ty = self.topics()[topic][0]
        if ty != expected:
            raise self._err(f"topic {topic} has type {ty or 'unknown'}, expected {expected}")
        if self._summary is not None:
            encs = [enc for t, _, enc, _ in self._summary["channels"].values() if t == topic]
        else:
            encs = [i[4] for i in self._records() if i[0] == "channel" and i[3] == topic]
        bad = [e for e in encs if e != "cdr"]
        if bad:
            raise self._err(f"topic {topic} is encoded as {bad[0]!r}, expected 'cdr'")

    def images(self, topic):
        """Header stamps and pixels of an Image topic: (stamps_ns (F,) int64, arrays (F, H, W)
        or (F, H, W, C)). All frames must share shape and encoding."""
        self._check_topics({topic})
        self._check_type(topic, IMAGE)
        stamps, arrays = [], []
        for _, _, log, _, mv in self._iter([topic]):
            try:
                stamp, _, enc, arr = decode_image(mv)
            except ValueError as err:
                raise self._err(f"{topic}: undecodable Image at log time {log}: {err}") from None
            if arrays and (arr.shape != arrays[0].shape or arr.dtype != arrays[0].dtype):
                raise self._err(f"{topic}: image {arr.shape} {enc} differs from the first "
                                f"{arrays[0].shape} {arrays[0].dtype}; read them with messages()")
            stamps.append(stamp)
            arrays.append(arr)
        if not arrays:
            return np.zeros(0, np.int64), np.zeros((0, 0, 0))
        return np.asarray(stamps, np.int64), np.stack(arrays)

    def iter_images(self, topic):
        """Stream an Image topic: yield (stamp_ns, frame_id, encoding, array) one message at a
        time (arrays are read-only views, valid while the reader is open), for bags too big
        to hold in memory."""
        self._check_topics({topic})
        self._check_type(topic, IMAGE)
        for _, _, log, _, mv in self._iter([topic]):
            try:
                yield decode_image(mv)
            except ValueError as err:
                raise self._err(f"{topic}: undecodable Image at log time {log}: {err}") from None

    def strings(self, topic):
        """[(log_time_ns, text)] of a String topic (String has no header stamp)."""
        self._check_topics({topic})
        self._check_type(topic, STRING)
        out = []
        for _, _, log, _, mv in self._iter([topic]):
            try:
                out.append((log, decode_string(mv)))
            except ValueError as err:
                raise self._err(f"{topic}: undecodable String at log time {log}: {err}") from None
        return out

    def close(self):
        """Release the file. Arrays from images() are copies and stay valid."""
        self._buf = None
        if self._mm is not None:
            try:
                self._mm.close()
            except BufferError:      # a caller still holds a view; the map closes with it
                pass
            self._mm = None
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def recover(src, dst, *, overwrite=False, compression="zstd"):
    """Copy every readable message of a (possibly truncated or damaged) bag into a new,
    complete bag. Returns {"messages": n, "topics": {topic: n}, "problems": [...],
    "source_complete": bool}. This is the recovery command (``lgs-wfs recover SRC DST``)."""
    from .writer import BagWriter
    if Path(dst).exists() and Path(src).exists() and os.path.samefile(src, dst):
        raise BagError(f"{dst}: recovery must write a new file, not the damaged source")
    reader = BagReader(src, strict=False)
    counts = {}
    try:
        schemas, channels = {}, {}
        with BagWriter(dst, overwrite=overwrite, compression=compression) as w:
            for item in reader._records():
                if item[0] == "schema":
                    schemas[item[1]] = item[2]
                elif item[0] == "channel":
                    cid, sid, topic, _, meta = item[1:]
                    channels[cid] = topic
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
                    w.write(topic, item[5], item[3], item[4], sequence=item[2])
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
