"""BagWriter: MCAP files in rosbag2's layout from raw CDR messages (no rclpy, no re-encoding).

Layout written (see docs/bags.md): magic, Header (profile ``ros2``), then Schema and Channel
records at top level as topics are added, chunks (compressed message records, each followed by
its MessageIndex records), at close the ``rosbag2`` Metadata record, DataEnd, the summary
(schemas, channels, statistics, chunk indexes, metadata index, summary offsets), Footer, magic.

Every write to disk is a whole record group, so a process killed at any moment leaves a file
whose complete chunks are all readable (:func:`lgs_wfs_ros.bags.recover`). An ``OSError``
(disk full, RLIMIT_FSIZE, I/O error) truncates the file back to the end of its last complete
group, appends a small valid ending (DataEnd, Footer without summary) when it fits, closes it
and raises :class:`BagWriteError`.

With ``background=True`` chunks are compressed and written by one worker thread (zstd, lz4
and file writes release the GIL), so the caller only builds chunks in memory; at most
``queue_chunks`` full chunks wait (then ``write`` blocks: back-pressure, bounded memory). A
worker error is raised by the next ``write``/``flush``/``close``.
"""

import os
import queue
import threading
import zlib
from pathlib import Path

import numpy as np

from . import mcapfmt as fmt
from .errors import BagError, BagExistsError, BagWriteError
from .schema import full_type, message_definition, qos_profile, qos_yaml, to_yaml, type_hash

LIBRARY = "lgs_wfs_ros bags 0.1 (python)"
ROS_DISTRO = "jazzy"
_MAX_U64 = 2**64 - 1
try:
    _IOV_MAX = min(os.sysconf("SC_IOV_MAX"), 1024)     # writev's limit on buffers per call
except (AttributeError, ValueError, OSError):
    _IOV_MAX = 16
if _IOV_MAX <= 0:
    _IOV_MAX = 16


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


class _Failed(Exception):
    """Internal: the file was closed after an OSError; args = (strerror, errno, state)."""


class BagWriter:
    """Write an MCAP bag in rosbag2's layout.

    path: output file (``.mcap``); overwrite: replace an existing file (else BagExistsError);
    chunk_size: uncompressed bytes per chunk (a crash loses at most the open chunk);
    compression: "zstd", "lz4" or None; compression_level: codec level (zstd default 3,
    lz4 default 0); threads: zstd's own worker threads (0: none); crc: CRC32 of each chunk's
    records (detects corruption; ~4 GB/s); rosbag2_metadata: write the ``rosbag2`` metadata
    record at close; fsync: fsync the file at close; background: compress and write chunks
    in a worker thread; queue_chunks: full chunks allowed to wait for that worker.

    Use as a context manager, or call :meth:`close`. Call from one thread.
    """

    def __init__(self, path, *, overwrite=False, chunk_size=4 * 1024 * 1024, compression="zstd",
                 compression_level=None, threads=0, crc=True, rosbag2_metadata=True, fsync=False,
                 background=False, queue_chunks=2):
        self.path = Path(path)
        if int(chunk_size) <= 0:
            raise ValueError("chunk_size must be positive")
        if int(queue_chunks) < 1:
            raise ValueError("queue_chunks must be >= 1")
        self._chunk_size = int(chunk_size)
        self._comp_name, self._compress = _compressor(compression, compression_level, threads)
        self._crc = bool(crc)
        self._rosbag2 = bool(rosbag2_metadata)
        self._fsync = bool(fsync)
        if self.path.is_dir():
            raise BagError(f"{self.path} is a directory, not a bag file")
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        try:
            self._fd = os.open(self.path, flags, 0o644)
        except FileExistsError:
            raise BagExistsError(f"{self.path} exists; refusing to overwrite it (pass overwrite=True)") from None
        except OSError as err:
            raise BagError(f"cannot create {self.path}: {err.strerror}") from None
        self._closed = False
        self._failed = None       # _Failed once the file was closed after an error
        self._reported = False    # that failure was raised to the caller
        self._schemas = {}        # type -> schema id
        self._topics = {}         # topic -> dict(id, type, qos)
        self._accepted = 0        # messages accepted by write()
        self._schema_recs = []
        self._channel_recs = []
        # One entry per chunk on disk, appended as the single commit step after its write:
        # (chunk index record, message count, start, end, {channel: count}).
        self._chunks = []
        self._metadata_index_recs = []
        self._parts = []          # open chunk: (message prefix, data) tuples, one append each
        self._chunk_bytes = 0
        self._queue = None
        if background:
            self._queue = queue.Queue(maxsize=int(queue_chunks))
            self._worker = threading.Thread(target=self._work, name="bag-writer", daemon=True)
            self._worker.start()
        self._submit(self._write, [fmt.MAGIC, fmt.header("ros2", LIBRARY)])

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
        self._submit(self._write, recs)
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
        prefix = fmt.message_prefix(cid, int(sequence) & 0xFFFFFFFF, log, pub, len(data))
        # one list append is the commit: an exception (e.g. KeyboardInterrupt) before or after it
        # leaves the open chunk consistent; offsets and indexes are derived when it is stored
        self._parts.append((prefix, data))
        self._accepted += 1
        self._chunk_bytes += len(prefix) + len(data)
        if self._chunk_bytes >= self._chunk_size:
            self._submit_chunk()

    def flush(self):
        """Close the open chunk and hand it to the OS (bounds what a crash can lose). With
        ``background`` this also waits until the worker has written everything."""
        self._check_open()
        self._submit_chunk()
        if self._queue is not None:
            self._queue.join()
        self._raise_failure()

    @property
    def message_count(self):
        """Messages accepted so far (including those not yet on disk)."""
        return self._accepted

    @property
    def saved_count(self):
        """Messages in complete chunks on disk."""
        return sum(c[1] for c in self._chunks)

    @property
    def topics(self):
        """topic -> (type, messages on disk) so far."""
        counts = self._saved_counts()
        return {t: (v["type"], counts.get(v["id"], 0)) for t, v in self._topics.items()}

    def _saved_counts(self):
        counts = {}
        for c in self._chunks:
            for cid, n in c[4].items():
                counts[cid] = counts.get(cid, 0) + n
        return counts

    def _saved_span(self):
        if not self._chunks:
            return 0, 0
        return min(c[2] for c in self._chunks), max(c[3] for c in self._chunks)

    def close(self):
        """Write the last chunk, the rosbag2 metadata, the summary and the footer. Idempotent."""
        if self._closed:
            return
        try:
            if self._failed is None:
                self._submit_chunk()
                self._submit(self._finish)
        finally:
            if self._queue is not None:
                self._queue.put(None)
                self._worker.join()
            self._closed = True
            if self._failed is None:
                os.close(self._fd)
        if not self._reported:
            self._raise_failure()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if not self._closed:
            self.close()
        return False

    def rosbag2_metadata_yaml(self):
        """The ``serialized_metadata`` text (rosbag2 BagMetadata, version 9)."""
        start, end = self._saved_span()
        duration = end - start
        counts = self._saved_counts()
        count = sum(counts.values())
        topics = [{"topic_metadata": {"name": t, "type": v["type"], "serialization_format": "cdr",
                                      "offered_qos_profiles": v["qos"],
                                      "type_description_hash": type_hash(v["type"])},
                   "message_count": counts.get(v["id"], 0)} for t, v in self._topics.items()]
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

    # -- caller side --------------------------------------------------------------------
    def _check_open(self):
        self._raise_failure()
        if self._closed:
            raise BagError(f"{self.path}: writer is closed")

    def _raise_failure(self):
        if self._failed is None:
            return
        strerror, errno, state = self._failed.args
        kept = self.saved_count
        lost = self.message_count - kept
        self._reported = True
        raise BagWriteError(
            f"writing {self.path} failed: {strerror} (errno {errno}). The file was {state}: "
            f"{kept} messages are safe, {lost} were lost. Run `lgs-wfs recover {self.path} "
            f"OUT.mcap` (on a disk with space) for a complete bag with summary.",
            messages_kept=kept, messages_lost=lost)

    def _submit(self, fn, *args):
        if self._queue is None:
            try:
                fn(*args)
            except _Failed:
                pass
            self._raise_failure()
        else:
            self._raise_failure()
            self._queue.put((fn, args))

    def _submit_chunk(self):
        if not self._parts:
            return
        parts, self._parts, self._chunk_bytes = self._parts, [], 0
        self._submit(self._store_chunk, parts)

    # -- worker side (or inline) --------------------------------------------------------
    def _work(self):
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if self._failed is None:
                    fn, args = job
                    try:
                        fn(*args)
                    except _Failed:
                        pass
                    except Exception as err:      # never let the worker die silently
                        try:
                            self._fail(OSError(getattr(err, "errno", None) or 0, f"{type(err).__name__}: {err}"),
                                       self._tell())
                        except _Failed:
                            pass
            finally:
                self._queue.task_done()

    def _store_chunk(self, parts):
        """Compress and write one chunk and its message indexes; then commit it to _chunks."""
        index, counts, pos = {}, {}, 0
        start, end = None, 0
        for prefix, data in parts:
            cid, _, log = fmt.MESSAGE_PREFIX.unpack(prefix)[2:5]
            index.setdefault(cid, []).append((log, pos))
            counts[cid] = counts.get(cid, 0) + 1
            start = log if start is None else min(start, log)
            end = max(end, log)
            pos += len(prefix) + len(data)
        records = b"".join([p for pair in parts for p in pair])
        crc = zlib.crc32(records) if self._crc else 0
        data = self._compress(records) if self._compress else records
        prefix = fmt.chunk_prefix(start, end, len(records), crc, self._comp_name, len(data))
        chunk_offset = self._tell()
        chunk_len = len(prefix) + len(data)
        mi_offsets, mi_recs, pos = {}, [], chunk_offset + chunk_len
        for cid, pairs in index.items():
            rec = fmt.message_index(cid, np.asarray(pairs, dtype="<u8").tobytes())
            mi_offsets[cid] = pos
            pos += len(rec)
            mi_recs.append(rec)
        entry = (fmt.chunk_index(start, end, chunk_offset, chunk_len, mi_offsets, pos - chunk_offset - chunk_len,
                                 self._comp_name, len(data), len(records)),
                 len(parts), start, end, counts)
        self._write([prefix, data] + mi_recs)
        self._chunks.append(entry)

    def _finish(self):
        if self._rosbag2:
            meta = fmt.metadata("rosbag2", {"serialized_metadata": self.rosbag2_metadata_yaml()})
            rec = fmt.metadata_index(self._tell(), len(meta), "rosbag2")
            self._write([meta])
            self._metadata_index_recs.append(rec)
        self._write([fmt.data_end(0)])
        self._write(self._summary())
        if self._fsync:
            try:
                os.fsync(self._fd)
            except OSError as err:
                self._fail(err, self._tell())

    def _summary(self):
        summary_start = pos = self._tell()
        offsets, groups = [], []
        counts = self._saved_counts()
        counts = {v["id"]: counts.get(v["id"], 0) for v in self._topics.values()}
        start, end = self._saved_span()
        stats = fmt.statistics(self.saved_count, len(self._schemas), len(self._topics),
                               len(self._metadata_index_recs), len(self._chunks), start, end, counts)
        for op, recs in ((fmt.OP_SCHEMA, self._schema_recs), (fmt.OP_CHANNEL, self._channel_recs),
                         (fmt.OP_STATISTICS, [stats]), (fmt.OP_CHUNK_INDEX, [c[0] for c in self._chunks]),
                         (fmt.OP_METADATA_INDEX, self._metadata_index_recs)):
            if recs:
                size = sum(len(r) for r in recs)
                offsets.append(fmt.summary_offset(op, pos, size))
                groups += recs
                pos += size
        body = groups + offsets + [fmt.footer_prefix(summary_start, pos)]
        crc = 0
        for part in body:
            crc = zlib.crc32(part, crc)
        return body + [crc.to_bytes(4, "little"), fmt.MAGIC]

    def _tell(self):
        return os.lseek(self._fd, 0, os.SEEK_CUR)

    def _write(self, parts):
        """Write whole records with writev. On OSError cut back and raise _Failed; on any other
        exception (KeyboardInterrupt mid-write) cut back to the start of this group, re-raise."""
        parts = [p for p in parts if len(p)]
        begin = self._tell()
        try:
            i = 0
            while i < len(parts):
                n = os.writev(self._fd, parts[i:i + _IOV_MAX])
                while i < len(parts) and n >= len(parts[i]):     # drop what was written
                    n -= len(parts[i])
                    i += 1
                if n:                                             # partial write inside a part
                    parts[i] = memoryview(parts[i])[n:]
        except OSError as err:
            self._fail(err, begin)
        except BaseException:
            os.ftruncate(self._fd, begin)
            os.lseek(self._fd, begin, os.SEEK_SET)
            raise

    def _fail(self, err, good):
        """Truncate to the last complete group (offset ``good``), try a minimal valid ending,
        close the file, raise _Failed."""
        ending_ok = False
        try:
            os.ftruncate(self._fd, good)
            ending = fmt.data_end(0) + fmt.footer_prefix(0, 0) + b"\0\0\0\0" + fmt.MAGIC
            os.lseek(self._fd, good, os.SEEK_SET)
            ending_ok = os.write(self._fd, ending) == len(ending)
        except OSError:
            pass
        try:
            if not ending_ok:
                os.ftruncate(self._fd, good)
        except OSError:
            pass
        finally:
            os.close(self._fd)
        state = ("closed with a valid MCAP ending (no summary)" if ending_ok else
                 "cut at its last complete chunk")
        self._failed = _Failed(err.strerror or str(err), err.errno, state)
        raise self._failed
