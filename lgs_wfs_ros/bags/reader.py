"""BagReader: read MCAP bags (ours or rosbag2's) without ROS; recover truncated ones.

Reads MCAP by the spec (https://mcap.dev/spec): Schema and Channel records in the data
section, inside chunks or in the summary; with or without summary and indexes; chunks
uncompressed, zstd or lz4. Records are parsed by the ``mcap`` library's record readers; the
walk over the file, the bounded chunk decompression and the summary CRC check are ours (see
docs/bags.md, "Reading"). Messages come out in file order. Every failure is a :class:`BagError` with a message for
users: not a file, not MCAP, truncated (no footer: e.g. the recorder was SIGKILLed),
corrupt (CRC mismatch, undecodable chunk, malformed record), unknown topic, wrong type.

``strict=True`` (default) refuses damaged files: at open when the end of the file is
missing or the summary is corrupt, while reading at the first corrupt chunk. With
``strict=False`` a reader returns everything readable: all complete chunks up to a
truncation, skipping corrupt chunks whose length is intact; ``problems`` lists what was
skipped. :func:`lgs_wfs_ros.bags.recovery.recover` uses that to copy a damaged bag into a
complete one.
"""

import io
import mmap
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from mcap import records
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError

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


class _Exact(ReadDataStream):
    """mcap's record reader over one record body that refuses short reads: a field that runs
    past its record is corruption, not a shorter string (mcap's ReadDataStream returns what
    is there)."""

    def read(self, length):
        if length > self._limit - self.count:
            raise _Corrupt(f"a field of {length} bytes runs past its record "
                           f"({self._limit - self.count} left)")
        return super().read(length)


def _exact(body):
    s = _Exact(io.BytesIO(body))
    s._limit = len(body)
    return s


_RECORDS = {fmt.OP_HEADER: records.Header, fmt.OP_FOOTER: records.Footer, fmt.OP_SCHEMA: records.Schema,
            fmt.OP_CHANNEL: records.Channel, fmt.OP_CHUNK_INDEX: records.ChunkIndex, fmt.OP_METADATA: records.Metadata,
            fmt.OP_METADATA_INDEX: records.MetadataIndex, fmt.OP_STATISTICS: records.Statistics}
# what mcap's record readers raise on bytes that are not a record (besides our _Corrupt)
_PARSE_ERRORS = (McapError, ValueError, struct.error, UnicodeDecodeError, OverflowError, KeyError)


_MESSAGE_HEAD = struct.Struct("<HIQQ")     # channel id, sequence, log time, publish time
_MAX_TIME = 2**63 - 1                      # times are handed out as int64 ns


def _message(body):
    """A Message record without copying its data (a memoryview into ``body``). The one record
    parsed by hand: through mcap's reader it costs two copies of every frame (docs/bags.md)."""
    if len(body) < _MESSAGE_HEAD.size:
        raise _Corrupt(f"Message record of {len(body)} bytes is shorter than its header")
    cid, seq, log, pub = _MESSAGE_HEAD.unpack_from(body)
    if log > _MAX_TIME or pub > _MAX_TIME:
        raise _Corrupt(f"Message time {max(log, pub)} ns is past 2262 (int64 ns): not a real time")
    return ("message", cid, seq, log, pub, memoryview(body)[_MESSAGE_HEAD.size:])


_CHUNK_HEAD = struct.Struct("<QQQI")       # start time, end time, uncompressed size, CRC


def _chunk(body):
    """(compression, uncompressed size, CRC, records (memoryview, compressed)) of a Chunk
    record, without copying its records (mcap's Chunk.read copies them once more)."""
    mv = memoryview(body)
    if len(mv) < _CHUNK_HEAD.size + 4:
        raise _Corrupt("Chunk record shorter than its header")
    _, _, usize, crc = _CHUNK_HEAD.unpack_from(mv)
    pos = _CHUNK_HEAD.size
    (n,) = struct.unpack_from("<I", mv, pos)
    pos += 4
    if n > len(mv) - pos - 8:
        raise _Corrupt("Chunk compression name runs past its record")
    try:
        kind = str(mv[pos:pos + n], "utf-8")
    except UnicodeDecodeError as err:
        raise _Corrupt(f"Chunk compression name is not UTF-8: {err}") from None
    pos += n
    (size,) = struct.unpack_from("<Q", mv, pos)
    pos += 8
    if size != len(mv) - pos:
        raise _Corrupt(f"Chunk says {size} bytes of records, its record holds {len(mv) - pos}")
    return kind, usize, crc, mv[pos:]


def parse_record(op, body):
    """The mcap library's record (``mcap.records``) of one record body, or None for an opcode
    this reader does not use. _Corrupt when the bytes do not parse within ``len(body)``."""
    cls = _RECORDS.get(op)
    if cls is None:
        return None
    stream = _exact(body)
    try:
        return cls.read(stream)
    except _Corrupt:
        raise
    except _PARSE_ERRORS as err:
        raise _Corrupt(f"malformed {cls.__name__} record: {err or type(err).__name__}") from None


def iter_records(data):
    """(opcode, body) of the records packed in ``data`` (a chunk's records, a summary)."""
    mv = memoryview(data)
    pos, end = 0, len(mv)
    while pos < end:
        if end - pos < 9:
            raise _Corrupt(f"{end - pos} stray bytes after the last record")
        op, length = struct.unpack_from("<BQ", mv, pos)
        if length > end - pos - 9:
            raise _Corrupt(f"record (opcode {op:#04x}) of {length} bytes runs past its container")
        yield op, mv[pos + 9:pos + 9 + length]
        pos += 9 + length


def _decompress(kind, data, size):
    """A chunk's records. Our own bounds rather than mcap's ``breakup_chunk``: the output is
    never larger than the chunk says (a flipped size cannot make zstd/lz4 allocate gigabytes)
    and must be exactly that size (mcap does not check it)."""
    if size > MAX_CHUNK_BYTES:
        raise _Corrupt(f"implausible uncompressed chunk size {size}")
    try:
        if kind == "":
            out = data
        elif kind == "zstd":
            import zstandard
            declared = zstandard.frame_content_size(data)
            if declared not in (-1, size):
                raise _Corrupt(f"zstd frame holds {declared} bytes, the chunk says {size}")
            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif kind == "lz4":
            import lz4.frame
            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
        else:
            raise _Corrupt(f"unsupported chunk compression {kind!r} (the MCAP spec names zstd and lz4)")
    except _Corrupt:
        raise
    except Exception as err:  # codec errors have many types
        raise _Corrupt(f"{kind} decompression failed: {err}") from None
    if len(out) != size:
        raise _Corrupt(f"chunk decompressed to {len(out)} bytes, its header says {size}")
    return out


MAX_CHUNK_BYTES = 4 * 2**30          # mcap's own record size limit
SCAN_SUMMARY_BYTES = 256 * 2**20   # summary() reads bags up to this size whole: exact per-topic rates


def _item(rec):
    """The reader's tuple for a library record (see BagReader._records)."""
    if isinstance(rec, records.Schema):
        return ("schema", rec.id, rec.name, rec.encoding, bytes(rec.data))
    if isinstance(rec, records.Channel):
        return ("channel", rec.id, rec.schema_id, rec.topic, rec.message_encoding, dict(rec.metadata))
    if isinstance(rec, records.Metadata):
        return ("metadata", rec.name, dict(rec.metadata))
    return None


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
            try:          # mapped: a frame is read in place, not copied out of the file (docs/bags.md)
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
        if bytes(self._read(0, 8)) != fmt.MAGIC:
            raise self._err("not an MCAP file (bad magic bytes)")
        try:
            op, body = self._read_record_at(8)
            if op != fmt.OP_HEADER:
                raise _Corrupt("first record is not an MCAP Header")
            header = parse_record(op, body)
            self.profile, self.library = header.profile, header.library
        except (_Truncated, _Corrupt) as err:
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
        except _Corrupt as err:
            self._problem(f"corrupt summary ({err})")

    def _problem(self, text):
        if self.strict:
            raise self._err(text)
        self.problems.append(text)

    def _read(self, offset, n):
        """``n`` bytes at ``offset`` (a view into the mapped file; callers check the bounds)."""
        return self._buf[offset:offset + n]

    def _read_record_at(self, offset):
        """(opcode, body bytes) of the record at a file offset; _Truncated past the end."""
        if offset + 9 > self.size:
            raise _Truncated(f"file ends inside a record header at byte {offset}")
        op, length = struct.unpack("<BQ", self._read(offset, 9))
        if length > self.size - offset - 9:
            raise _Truncated(f"record at byte {offset} (opcode {op:#04x}, {length} bytes) runs past "
                             f"the end of the file ({self.size} bytes)")
        return op, self._read(offset + 9, length)

    def _read_summary(self):
        """The summary section as dicts, None for a valid file without one. Parsed with mcap's
        record readers; the footer's summary CRC (which mcap does not check) is checked."""
        if self.size < self._data_start + _TRAILER:
            raise _Truncated("file too short for an MCAP footer")
        footer_at = self.size - _TRAILER
        tail = bytes(self._read(footer_at, _TRAILER))
        if tail[-8:] != fmt.MAGIC or tail[0] != fmt.OP_FOOTER:
            raise _Truncated("no footer at the end of the file")
        if struct.unpack_from("<Q", tail, 1)[0] != 20:
            raise _Corrupt("malformed footer")
        footer = parse_record(fmt.OP_FOOTER, tail[9:_FOOTER_LEN])
        if footer.summary_start == 0:
            return None            # a valid file without summary: scan
        if not self._data_start <= footer.summary_start <= footer_at:
            raise _Corrupt("footer points outside the file")
        blob = self._read(footer.summary_start, footer_at - footer.summary_start)
        if footer.summary_crc:
            if zlib.crc32(tail[:_FOOTER_LEN - 4], zlib.crc32(blob)) != footer.summary_crc:
                raise _Corrupt("summary CRC mismatch")
        out = {"schemas": {}, "channels": {}, "stats": None, "chunks": [], "metadata": []}
        for op, body in iter_records(blob):
            rec = parse_record(op, body)
            if isinstance(rec, records.Schema):
                out["schemas"][rec.id] = (rec.name, rec.encoding, bytes(rec.data))
            elif isinstance(rec, records.Channel):
                out["channels"][rec.id] = (rec.topic, rec.schema_id, rec.message_encoding, dict(rec.metadata))
            elif isinstance(rec, records.Statistics):
                out["stats"] = {"count": rec.message_count, "chunks": rec.chunk_count,
                                "start": rec.message_start_time, "end": rec.message_end_time,
                                "counts": dict(rec.channel_message_counts)}
            elif isinstance(rec, records.ChunkIndex):
                if rec.chunk_start_offset + rec.chunk_length > footer_at:
                    raise _Corrupt("chunk index points past the data section")
                out["chunks"].append((rec.chunk_start_offset, rec.chunk_length,
                                      set(rec.message_index_offsets)))
            elif isinstance(rec, records.MetadataIndex):
                out["metadata"].append((rec.offset, rec.length, rec.name))
        for cid, (topic, sid, _, _) in out["channels"].items():
            if sid and sid not in out["schemas"]:
                raise _Corrupt(f"channel {topic} refers to a missing schema")
        return out

    # -- scanning ---------------------------------------------------------------------
    def _skippable(self, channel_filter):
        """{chunk offset: channel ids} of chunks that may be skipped for channel_filter: only
        when the summary indexes every chunk's channels and knows every one of those channels
        (then a skipped chunk holds nothing the caller wants, not even a needed Channel)."""
        s = self._summary
        if channel_filter is None or s is None or not s["chunks"]:
            return None
        if any(not chans or not chans <= s["channels"].keys() for _, _, chans in s["chunks"]):
            return None
        return {off: chans for off, _, chans in s["chunks"]}

    def _records(self, channel_filter=None):
        """Yield ('schema'|'channel'|'message'|'metadata', ...) in file order, from the data
        section, inside chunks or not. Handles damage according to ``strict``; chunks holding
        none of channel_filter are skipped when the summary lists their channels.

        The walk over top-level records is ours (mcap's StreamReader stops at the first bad
        record and gives no offsets): it knows each record's offset and length, so a corrupt
        record whose length is intact is skipped, a cut is found before reading, and unwanted
        chunks are never read. Each record is parsed by mcap's record readers."""
        skip = self._skippable(channel_filter)
        offset = self._data_start
        while offset < self.size:
            try:
                if offset + 9 > self.size:
                    raise _Truncated(f"file ends inside a record header at byte {offset}")
                op, length = struct.unpack("<BQ", self._read(offset, 9))
                nxt = offset + 9 + length
                if nxt > self.size:
                    raise _Truncated(f"record at byte {offset} (opcode {op:#04x}) needs {length} bytes, "
                                     f"the file has {self.size - offset - 9} left")
                if op in (fmt.OP_DATA_END, fmt.OP_FOOTER):
                    return
                if op == fmt.OP_CHUNK and skip is not None and offset in skip \
                        and not (skip[offset] & channel_filter):
                    offset = nxt
                    continue
                if op not in (fmt.OP_SCHEMA, fmt.OP_CHANNEL, fmt.OP_MESSAGE, fmt.OP_CHUNK, fmt.OP_METADATA):
                    offset = nxt
                    continue
                try:
                    items = self._parse(op, self._read(offset + 9, length))
                except _Corrupt as err:
                    self._problem(f"corrupt record at byte {offset} (opcode {op:#04x}): {err}")
                    items = []
                yield from items
                offset = nxt
            except _Truncated as err:
                self._problem(f"truncated: {err}; everything before byte {offset} was read")
                return

    def _parse(self, op, body):
        """Items of one top-level record (a chunk: of each record inside it)."""
        if op == fmt.OP_MESSAGE:
            return [_message(body)]
        if op != fmt.OP_CHUNK:
            return [_item(parse_record(op, body))]
        kind, usize, crc, packed = _chunk(body)
        data = _decompress(kind, packed, usize)
        if crc and zlib.crc32(data) != crc:
            raise _Corrupt("chunk CRC mismatch")
        out = []
        for iop, ibody in iter_records(data):
            if iop == fmt.OP_MESSAGE:
                out.append(_message(ibody))
            elif iop in (fmt.OP_SCHEMA, fmt.OP_CHANNEL):
                out.append(_item(parse_record(iop, ibody)))
        return out

    def _iter(self, topics=None):
        """(topic, type, log, publish, memoryview) for messages of the wanted topics."""
        schemas, channels = {}, {}
        if self._summary is not None:          # the summary may hold channels the data section lacks
            schemas = {sid: v[0] for sid, v in self._summary["schemas"].items()}
            channels = {cid: (v[0], v[1]) for cid, v in self._summary["channels"].items()}
        want_ids = None
        if topics is not None:
            topics = set(topics)
            self._check_topics(topics)
            if self._summary is not None:
                want_ids = {cid for cid, ch in channels.items() if ch[0] in topics}
        for item in self._records(want_ids):
            kind = item[0]
            if kind == "schema":
                self._define(schemas, "Schema", item[1], item[2])
            elif kind == "channel":
                self._define(channels, "Channel", item[1], (item[3], item[2]))
            elif kind == "message":
                ch = channels.get(item[1])
                if ch is None:
                    self._problem(f"message on channel id {item[1]}, which no Channel record before it "
                                  "defines (corrupt file)")
                    continue
                if topics is None or ch[0] in topics:
                    yield ch[0], schemas.get(ch[1], ""), item[3], item[4], item[5]

    def _define(self, known, what, rid, value):
        """Record a Schema/Channel definition; the spec repeats them identically, so another
        definition of a known id is corruption (the first one, e.g. the summary's, is kept)."""
        if rid in known and known[rid] != value:
            self._problem(f"{what} id {rid} defined twice differently ({known[rid]} and {value}): "
                          "corrupt file")
            return
        known[rid] = value

    def _scan(self):
        if getattr(self, "_scanned", None) is None:
            schemas, channels, counts, meta = {}, {}, {}, []
            if self._summary is not None:
                schemas = {sid: v[0] for sid, v in self._summary["schemas"].items()}
                channels = {cid: (v[0], v[1]) for cid, v in self._summary["channels"].items()}
            start, end = None, 0
            first, last = {}, {}
            for item in self._records():
                if item[0] == "schema":
                    self._define(schemas, "Schema", item[1], item[2])
                elif item[0] == "channel":
                    self._define(channels, "Channel", item[1], (item[3], item[2]))
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
                    rec = parse_record(op, body)
                    out.append((rec.name, dict(rec.metadata)))
                except (_Truncated, _Corrupt) as err:
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
