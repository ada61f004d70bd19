"""BagWriter: MCAP files in rosbag2's layout from raw CDR messages (no rclpy, no re-encoding).

Layout written (see docs/bags.md): magic, Header (profile ``ros2``), then Schema and Channel
records at top level as topics are added, chunks (compressed message records, each followed by
its MessageIndex records), at close the ``rosbag2`` Metadata record, DataEnd, the summary
(schemas, channels, statistics, chunk indexes, metadata index, summary offsets), Footer, magic.

Every write to disk is a whole record group, so a process killed at any moment leaves a file
whose complete chunks are all readable (:func:`lgs_wfs_ros.bags.recover`). An ``OSError``
(disk full, RLIMIT_FSIZE, I/O error) truncates the file back to the end of its last complete
group, appends a small valid ending when it fits, closes it and raises :class:`BagWriteError`.
"""

import os
import time
import zlib
from pathlib import Path

import numpy as np

from . import mcapfmt as fmt
from .errors import BagError, BagExistsError, BagWriteError
from .schema import full_type, message_definition, qos_profile, qos_yaml, to_yaml, type_hash

LIBRARY = "lgs_wfs_ros bags 0.1 (python)"
ROS_DISTRO = "jazzy"
_MAX_U64 = 2**64 - 1


def _compressor(kind, level, threads):
    if kind in (None, "", "none"):
        return "", None
    if kind == "zstd":
        import zstandard
        c = zstandard.ZstdCompressor(level=3 if level is None else int(level), threads=int(threads),
                                     write_content_size=True)
        return "zstd", c.compress
    if kind == "lz4":
        import lz4.frame
        lvl = 0 if level is None else int(level)
        return "lz4", lambda data: lz4.frame.compress(data, compression_level=lvl)
    raise ValueError(f"compression must be 'zstd', 'lz4' or None, not {kind!r}")


class BagWriter:
    """Write an MCAP bag in rosbag2's layout.

    path: output file (``.mcap``); overwrite: replace an existing file (else BagExistsError);
    chunk_size: uncompressed bytes per chunk (a crash loses at most the open chunk);
    compression: "zstd", "lz4" or None; compression_level: codec level (zstd default 3,
    lz4 default 0); threads: zstd worker threads (0 = compress in the calling thread);
    crc: CRC32 of each chunk's records (detects corruption, ~4 GB/s); rosbag2_metadata: write
    the ``rosbag2`` metadata record at close; fsync: fsync the file at close.

    Use as a context manager, or call :meth:`close`. Not thread safe: one writer per thread.
    """

    def __init__(self, path, *, overwrite=False, chunk_size=4 * 1024 * 1024, compression="zstd",
                 compression_level=None, threads=0, crc=True, rosbag2_metadata=True, fsync=False):
        self.path = Path(path)
        if int(chunk_size) <= 0:
            raise ValueError("chunk_size must be positive")
        self._chunk_size = int(chunk_size)
        self._comp_name, self._compress = _compressor(compression, compression_level, threads)
        self._crc = bool(crc)
        self._rosbag2 = bool(rosbag2_metadata)
        self._fsync = bool(fsync)
        if self.path.is_dir():
            raise BagError(f"{self.path} is a directory, not a bag file")
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL), 0o644)
        except FileExistsError:
            raise BagExistsError(f"{self.path} exists; refusing to overwrite it (pass overwrite=True)") from None
        except OSError as err:
            raise BagError(f"cannot create {self.path}: {err.strerror}") from None
        self._offset = 0          # bytes in the file
        self._good = 0            # end of the last complete record group
        self._closed = False
        self._failed = None
        self._schemas = {}        # type -> schema id
        self._topics = {}         # topic -> dict(id, type, qos)
        self._counts = {}         # channel id -> messages written (incl. open chunk)
        self._saved = 0           # messages in complete chunks on disk
        self._start = None
        self._end = 0
        self._schema_recs = []
        self._channel_recs = []
        self._chunk_index_recs = []
        self._metadata_index_recs = []
        self._chunk_count = 0
        self._reset_chunk()
        self._write([fmt.MAGIC, fmt.header("ros2", LIBRARY)])

    # -- public -----------------------------------------------------------------------
    def add_topic(self, topic, type_name, qos=None):
        """Register a topic; returns its channel id. type_name e.g. "sensor_msgs/msg/Image";
        qos: dict of rosbag2 QoS fields (history, depth, reliability, durability, ...) or a
        list of them, default reliable / volatile / keep_last 10. Adding a topic again with the
        same type returns the same id; with another type raises ValueError."""
        self._check_open()
        tname = full_type(type_name)
        if topic in self._topics:
            if self._topics[topic]["type"] != tname:
                raise ValueError(f"topic {topic} already added with type {self._topics[topic]['type']}")
            return self._topics[topic]["id"]
        if not isinstance(topic, str) or not topic:
            raise ValueError(f"topic must be a non-empty string, not {topic!r}")
        profiles = [qos_profile(q) for q in (qos if isinstance(qos, list) else [qos])]
        recs = []
        if tname not in self._schemas:
            try:
                definition = message_definition(tname)
            except LookupError as err:
                raise ValueError(str(err)) from None
            sid = len(self._schemas) + 1
            self._schemas[tname] = sid
            rec = fmt.schema(sid, tname, "ros2msg", definition.encode("utf-8"))
            self._schema_recs.append(rec)
            recs.append(rec)
        cid = len(self._topics) + 1
        meta = {"offered_qos_profiles": qos_yaml(profiles), "topic_type_hash": type_hash(tname)}
        rec = fmt.channel(cid, self._schemas[tname], topic, "cdr", meta)
        self._channel_recs.append(rec)
        recs.append(rec)
        self._topics[topic] = {"id": cid, "type": tname, "qos": profiles}
        self._counts[cid] = 0
        self._write(recs)
        return cid

    def write(self, topic, cdr, log_time_ns, publish_time_ns=None, sequence=0):
        """Append one serialized message (bytes, bytearray, memoryview; stored as is).

        log_time_ns: receive time (ns, >= 0); publish_time_ns: source time (default log time).
        Mutable buffers are copied; bytes are kept by reference until their chunk is written."""
        self._check_open()
        try:
            cid = self._topics[topic]["id"]
        except KeyError:
            raise ValueError(f"topic {topic!r} was not added (call add_topic first)") from None
        log = int(log_time_ns)
        pub = log if publish_time_ns is None else int(publish_time_ns)
        if not (0 <= log <= _MAX_U64 and 0 <= pub <= _MAX_U64):
            raise ValueError(f"times must be in [0, 2**64) ns, got log {log}, publish {pub}")
        data = cdr if isinstance(cdr, bytes) else bytes(cdr)
        self._parts.append(fmt.message_prefix(cid, int(sequence) & 0xFFFFFFFF, log, pub, len(data)))
        self._parts.append(data)
        self._index.setdefault(cid, []).append((log, self._chunk_bytes))
        self._chunk_bytes += fmt.MESSAGE_PREFIX.size + len(data)
        self._chunk_n += 1
        self._chunk_start = log if self._chunk_start is None else min(self._chunk_start, log)
        self._chunk_end = max(self._chunk_end, log)
        self._counts[cid] += 1
        if self._chunk_bytes >= self._chunk_size:
            self._flush_chunk()

    def flush(self):
        """Close the open chunk and hand it to the OS (bounds what a crash can lose)."""
        self._check_open()
        self._flush_chunk()

    @property
    def message_count(self):
        """Messages accepted so far (including the open chunk)."""
        return sum(self._counts.values())

    @property
    def topics(self):
        """topic -> (type, count) of what was written so far."""
        return {t: (v["type"], self._counts[v["id"]]) for t, v in self._topics.items()}

    def close(self):
        """Write the last chunk, the rosbag2 metadata, the summary and the footer. Idempotent."""
        if self._closed:
            return
        try:
            self._flush_chunk()
            if self._rosbag2:
                meta = fmt.metadata("rosbag2", {"serialized_metadata": self.rosbag2_metadata_yaml()})
                self._metadata_index_recs.append(fmt.metadata_index(self._offset, len(meta), "rosbag2"))
                self._write([meta])
            self._write([fmt.data_end(0)])
            self._write(self._summary())
            if self._fsync:
                os.fsync(self._fd)
        finally:
            if not self._closed:
                self._closed = True
                os.close(self._fd)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if not self._closed:
            self.close()
        return False

    def rosbag2_metadata_yaml(self):
        """The ``serialized_metadata`` text (rosbag2 BagMetadata, version 9)."""
        start = self._start or 0
        duration = max(self._end - start, 0) if self._start is not None else 0
        count = self.message_count
        topics = [{"topic_metadata": {"name": t, "type": v["type"], "serialization_format": "cdr",
                                      "offered_qos_profiles": v["qos"],
                                      "type_description_hash": type_hash(v["type"])},
                   "message_count": self._counts[v["id"]]} for t, v in self._topics.items()]
        doc = {"version": 9, "storage_identifier": "mcap",
               "duration": {"nanoseconds": duration},
               "starting_time": {"nanoseconds_since_epoch": start},
               "message_count": count, "topics_with_message_count": topics,
               "compression_format": "", "compression_mode": "",
               "relative_file_paths": [self.path.name],
               "files": [{"path": self.path.name, "starting_time": {"nanoseconds_since_epoch": start},
                          "duration": {"nanoseconds": duration}, "message_count": count}],
               "custom_data": {}, "ros_distro": ROS_DISTRO}
        return to_yaml(doc)

    # -- internals --------------------------------------------------------------------
    def _check_open(self):
        if self._failed is not None:
            raise BagWriteError(f"{self.path}: writer stopped after an earlier error: {self._failed}")
        if self._closed:
            raise BagError(f"{self.path}: writer is closed")

    def _reset_chunk(self):
        self._parts = []
        self._index = {}
        self._chunk_bytes = 0
        self._chunk_n = 0
        self._chunk_start = None
        self._chunk_end = 0

    def _flush_chunk(self):
        if self._chunk_n == 0:
            return
        records = b"".join(self._parts)
        crc = zlib.crc32(records) if self._crc else 0
        data = self._compress(records) if self._compress else records
        prefix = fmt.chunk_prefix(self._chunk_start, self._chunk_end, len(records), crc,
                                  self._comp_name, len(data))
        chunk_offset = self._offset
        chunk_len = len(prefix) + len(data)
        mi_offsets, mi_recs, pos = {}, [], chunk_offset + chunk_len
        for cid, pairs in self._index.items():
            rec = fmt.message_index(cid, np.asarray(pairs, dtype="<u8").tobytes())
            mi_offsets[cid] = pos
            pos += len(rec)
            mi_recs.append(rec)
        n, start, end = self._chunk_n, self._chunk_start, self._chunk_end
        self._reset_chunk()
        self._write([prefix, data] + mi_recs, lost=n)
        self._saved += n
        self._chunk_count += 1
        self._start = start if self._start is None else min(self._start, start)
        self._end = max(self._end, end)
        self._chunk_index_recs.append(fmt.chunk_index(start, end, chunk_offset, chunk_len, mi_offsets,
                                                      pos - chunk_offset - chunk_len, self._comp_name,
                                                      len(data), len(records)))

    def _summary(self):
        groups, offsets, pos = [], [], self._offset
        counts = {self._topics[t]["id"]: self._counts[self._topics[t]["id"]] for t in self._topics}
        stats = fmt.statistics(self._saved, len(self._schemas), len(self._topics),
                               len(self._metadata_index_recs), self._chunk_count,
                               self._start or 0, self._end, counts)
        for op, recs in ((fmt.OP_SCHEMA, self._schema_recs), (fmt.OP_CHANNEL, self._channel_recs),
                         (fmt.OP_STATISTICS, [stats]), (fmt.OP_CHUNK_INDEX, self._chunk_index_recs),
                         (fmt.OP_METADATA_INDEX, self._metadata_index_recs)):
            if recs:
                size = sum(len(r) for r in recs)
                offsets.append(fmt.summary_offset(op, pos, size))
                groups += recs
                pos += size
        summary_start = self._offset
        offset_start = pos
        body = groups + offsets + [fmt.footer_prefix(summary_start, offset_start)]
        crc = 0
        for part in body:
            crc = zlib.crc32(part, crc)
        return body + [crc.to_bytes(4, "little"), fmt.MAGIC]

    def _write(self, parts, lost=0):
        """Write whole records; on OSError cut back to the last good offset and raise."""
        parts = [p for p in parts if len(p)]
        total = sum(len(p) for p in parts)
        try:
            done = 0
            while done < total:
                n = os.writev(self._fd, parts)
                done += n
                if done < total:          # partial write: drop what was written
                    while n and n >= len(parts[0]):
                        n -= len(parts[0])
                        parts.pop(0)
                    if n:
                        parts[0] = memoryview(parts[0])[n:]
        except OSError as err:
            self._fail(err, lost)
        self._offset += total
        self._good = self._offset

    def _fail(self, err, lost):
        """Truncate to the last complete group, try a minimal valid ending, close, raise."""
        lost += self._chunk_n
        self._failed = err.strerror or str(err)
        ending_ok = False
        try:
            os.ftruncate(self._fd, self._good)
            ending = fmt.data_end(0) + fmt.footer_prefix(0, 0) + b"\0\0\0\0" + fmt.MAGIC
            os.lseek(self._fd, self._good, os.SEEK_SET)
            ending_ok = os.write(self._fd, ending) == len(ending)
        except OSError:
            pass
        try:
            if not ending_ok:
                os.ftruncate(self._fd, self._good)
        except OSError:
            pass
        finally:
            os.close(self._fd)
            self._closed = True
        state = ("closed with a valid MCAP ending (no summary)" if ending_ok else
                 "cut at its last complete chunk")
        raise BagWriteError(
            f"writing {self.path} failed: {self._failed} (errno {err.errno}). The file was {state}: "
            f"{self._saved} messages are safe, {lost} were lost. Run `lgs-wfs recover {self.path} "
            f"OUT.mcap` on a disk with space to get a complete bag with summary.",
            messages_kept=self._saved, messages_lost=lost) from None
