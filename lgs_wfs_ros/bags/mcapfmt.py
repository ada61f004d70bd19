"""The MCAP records this package's writer packs (spec: https://mcap.dev/spec), as plain
struct packing; reading goes through the ``mcap`` library's record readers (bags/reader.py).
Every record is opcode (uint8), body length (uint64), body; strings are uint32 length +
UTF-8, byte arrays uint32/uint64 length + bytes, maps uint32 byte length + pairs. Little
endian throughout."""

import struct

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_ATTACHMENT = 0x09
OP_ATTACHMENT_INDEX = 0x0A
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

_U8, _U16, _U32, _U64 = (struct.Struct(f) for f in ("<B", "<H", "<I", "<Q"))


def s(text):
    raw = text.encode("utf-8")
    return _U32.pack(len(raw)) + raw


def str_map(d):
    body = b"".join(s(k) + s(v) for k, v in d.items())
    return _U32.pack(len(body)) + body


def record(op, *parts):
    body = b"".join(parts)
    return struct.pack("<BQ", op, len(body)) + body


def header(profile, library):
    return record(OP_HEADER, s(profile), s(library))


def schema(sid, name, encoding, data):
    return record(OP_SCHEMA, _U16.pack(sid), s(name), s(encoding), _U32.pack(len(data)), data)


def channel(cid, sid, topic, encoding, metadata):
    return record(OP_CHANNEL, _U16.pack(cid), _U16.pack(sid), s(topic), s(encoding), str_map(metadata))


MESSAGE_PREFIX = struct.Struct("<BQHIQQ")   # opcode, length, channel, sequence, log, publish


def message_prefix(cid, sequence, log_time, publish_time, size):
    return MESSAGE_PREFIX.pack(OP_MESSAGE, 22 + size, cid, sequence, log_time, publish_time)


def chunk_prefix(start, end, usize, crc, compression, csize):
    """Everything of a chunk record before its (compressed) records."""
    comp = s(compression)
    length = 8 + 8 + 8 + 4 + len(comp) + 8 + csize
    return struct.pack("<BQQQQI", OP_CHUNK, length, start, end, usize, crc) + comp + _U64.pack(csize)


def message_index(cid, pairs_bytes):
    """pairs_bytes: packed little-endian uint64 (log_time, offset) pairs."""
    return record(OP_MESSAGE_INDEX, _U16.pack(cid), _U32.pack(len(pairs_bytes)), pairs_bytes)


def chunk_index(start, end, offset, length, mi_offsets, mi_length, compression, csize, usize):
    mi = b"".join(struct.pack("<HQ", c, o) for c, o in mi_offsets.items())
    return record(OP_CHUNK_INDEX, struct.pack("<QQQQ", start, end, offset, length),
                  _U32.pack(len(mi)), mi, _U64.pack(mi_length), s(compression),
                  struct.pack("<QQ", csize, usize))


def metadata(name, data):
    return record(OP_METADATA, s(name), str_map(data))


def metadata_index(offset, length, name):
    return record(OP_METADATA_INDEX, struct.pack("<QQ", offset, length), s(name))


def statistics(message_count, schema_count, channel_count, metadata_count, chunk_count,
               start, end, channel_counts):
    counts = b"".join(struct.pack("<HQ", c, n) for c, n in channel_counts.items())
    return record(OP_STATISTICS, struct.pack("<QHIIII", message_count, schema_count, channel_count,
                                             0, metadata_count, chunk_count),
                  struct.pack("<QQ", start, end), _U32.pack(len(counts)), counts)


def summary_offset(op, start, length):
    return record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", op, start, length))


def data_end(crc=0):
    return record(OP_DATA_END, _U32.pack(crc))


FOOTER_PREFIX_LEN = 1 + 8 + 8 + 8   # opcode, length, summary_start, summary_offset_start


def footer_prefix(summary_start, summary_offset_start):
    return struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start)
