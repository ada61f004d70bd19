"""CDR (XCDR1, little endian) encoding of the contract's messages without rclpy.

``sensor_msgs/msg/Image`` and ``std_msgs/msg/String``, byte for byte as rclpy serialises them
(checked in ``test/test_bags.py``). Pixel data goes through numpy in one copy on encode and
none on decode (the returned array is a read-only view into the message bytes).

Image layout after the 4-byte encapsulation header ``00 01 00 00`` (offsets aligned relative
to the byte after it): int32 sec, uint32 nanosec, string frame_id, uint32 height, uint32
width, string encoding, uint8 is_bigendian, uint32 step, uint32 data length, data.
A CDR string is uint32 length (including the NUL), the bytes, NUL.
"""

import struct

import numpy as np

CDR_LE = b"\x00\x01\x00\x00"
_NS = 1_000_000_000

#: encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
    "32FC2": (np.dtype(np.float32), 2),
    "64FC1": (np.dtype(np.float64), 1),
}


def split_stamp(stamp_ns):
    """Nanoseconds (int) -> (sec int32, nanosec uint32) as ROS's builtin_interfaces/Time."""
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, _NS)
    if not -2**31 <= sec < 2**31:
        raise ValueError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return sec, nanosec


def _put_string(buf, text):
    raw = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if b"\x00" in raw:
        raise ValueError("CDR strings cannot contain NUL characters")
    buf += b"\x00" * (-(len(buf) - 4) % 4)
    buf += struct.pack("<I", len(raw) + 1)
    buf += raw
    buf += b"\x00"


def infer_encoding(array):
    """The image encoding of an array: uint16 (H, W) -> mono16, float32 (H, W) -> 32FC1,
    float32 (H, W, 2) -> 32FC2, uint8 (H, W) -> mono8, float64 (H, W) -> 64FC1."""
    a = np.asarray(array)
    if a.ndim == 2:
        table = {np.uint16: "mono16", np.float32: "32FC1", np.uint8: "mono8", np.float64: "64FC1"}
        for t, enc in table.items():
            if a.dtype == t:
                return enc
    elif a.ndim == 3 and a.shape[2] == 2 and a.dtype == np.float32:
        return "32FC2"
    raise ValueError(f"no image encoding for an array of shape {a.shape} and dtype {a.dtype}; "
                     "expected uint16/float32 (H, W) or float32 (H, W, 2)")


def encode_image(array, stamp_ns, frame_id="wfs", encoding=None):
    """Serialise an array as a ``sensor_msgs/msg/Image`` CDR message.

    array: (H, W) uint16/float32/uint8/float64 or (H, W, 2) float32; stamp_ns: header stamp in
    ns since the epoch; encoding: inferred from the array when None, else must match it.
    Returns bytes (little endian, ``is_bigendian`` 0, ``step`` = W * channels * itemsize).
    """
    a = np.asarray(array)
    enc = infer_encoding(a) if encoding is None else str(encoding)
    if enc not in IMAGE_ENCODINGS:
        raise ValueError(f"unsupported image encoding {enc!r}; known: {sorted(IMAGE_ENCODINGS)}")
    dtype, channels = IMAGE_ENCODINGS[enc]
    if a.dtype != dtype or a.ndim != (2 if channels == 1 else 3) or (channels > 1 and a.shape[2] != channels):
        raise ValueError(f"encoding {enc} needs dtype {dtype} and shape (H, W"
                         f"{', %d' % channels if channels > 1 else ''}), got {a.dtype} {a.shape}")
    a = np.ascontiguousarray(a, dtype=dtype.newbyteorder("<"))
    height, width = a.shape[:2]
    step = width * channels * dtype.itemsize
    sec, nanosec = split_stamp(stamp_ns)
    buf = bytearray(CDR_LE)
    buf += struct.pack("<iI", sec, nanosec)
    _put_string(buf, frame_id)
    buf += b"\x00" * (-(len(buf) - 4) % 4)
    buf += struct.pack("<II", height, width)
    _put_string(buf, enc)
    buf += b"\x00"                                   # is_bigendian
    buf += b"\x00" * (-(len(buf) - 4) % 4)
    buf += struct.pack("<II", step, a.nbytes)
    return b"".join((buf, a.reshape(-1).view(np.uint8)))


def _get_string(mv, pos):
    pos += -(pos - 4) % 4
    if pos + 4 > len(mv):
        raise ValueError("truncated CDR message (string length)")
    (n,) = struct.unpack_from("<I", mv, pos)
    end = pos + 4 + n
    if n == 0 or end > len(mv):
        raise ValueError("truncated or malformed CDR string")
    raw = bytes(mv[pos + 4:end - 1])
    try:
        return raw.decode("utf-8"), end
    except UnicodeDecodeError as err:
        raise ValueError(f"CDR string is not UTF-8: {err}") from None


def _check_header(mv):
    if len(mv) < 8:
        raise ValueError(f"CDR message of {len(mv)} bytes is too short")
    if bytes(mv[:2]) != CDR_LE[:2]:
        raise ValueError(f"unsupported CDR encapsulation {bytes(mv[:4]).hex()} (only little-endian "
                         "CDR, 00 01, is supported)")


def peek_stamp(cdr):
    """The header stamp (ns) of any message that starts with a ``std_msgs/Header``."""
    mv = memoryview(cdr).cast("B")
    _check_header(mv)
    if len(mv) < 12:
        raise ValueError("truncated CDR message (stamp)")
    sec, nanosec = struct.unpack_from("<iI", mv, 4)
    return sec * _NS + nanosec


def decode_image(cdr):
    """Parse a ``sensor_msgs/msg/Image`` CDR message.

    Returns (stamp_ns int, frame_id str, encoding str, array) where array is (H, W) or
    (H, W, C) of the encoding's dtype: a read-only view into ``cdr`` when rows are unpadded
    and the data little endian, else a copy. Raises ValueError for malformed messages or
    unknown encodings.
    """
    mv = memoryview(cdr).cast("B")
    _check_header(mv)
    stamp = peek_stamp(mv)
    frame_id, pos = _get_string(mv, 12)
    pos += -(pos - 4) % 4
    if pos + 8 > len(mv):
        raise ValueError("truncated Image message (height/width)")
    height, width = struct.unpack_from("<II", mv, pos)
    encoding, pos = _get_string(mv, pos + 8)
    if pos + 1 > len(mv):
        raise ValueError("truncated Image message (is_bigendian)")
    bigendian = mv[pos]
    pos += 1
    pos += -(pos - 4) % 4
    if pos + 8 > len(mv):
        raise ValueError("truncated Image message (step)")
    step, n = struct.unpack_from("<II", mv, pos)
    pos += 8
    if pos + n > len(mv):
        raise ValueError(f"truncated Image message: data needs {n} bytes, {len(mv) - pos} left")
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r}; known: {sorted(IMAGE_ENCODINGS)}")
    dtype, channels = IMAGE_ENCODINGS[encoding]
    dtype = dtype.newbyteorder(">" if bigendian else "<")
    row = width * channels * dtype.itemsize
    if step < row or n < step * height:
        raise ValueError(f"Image {height}x{width} {encoding}: step {step} / data {n} bytes too small")
    shape = (height, width) if channels == 1 else (height, width, channels)
    if step == row:
        arr = np.frombuffer(mv, dtype=dtype, count=height * width * channels, offset=pos)
    else:
        rows = np.frombuffer(mv, dtype=np.uint8, count=step * height, offset=pos).reshape(height, step)
        arr = np.ascontiguousarray(rows[:, :row]).view(dtype)
    arr = arr.reshape(shape)
    if bigendian:
        arr = arr.astype(dtype.newbyteorder("="))
    return stamp, frame_id, encoding, arr


def encode_string(text):
    """Serialise a ``std_msgs/msg/String`` CDR message."""
    buf = bytearray(CDR_LE)
    _put_string(buf, text)
    return bytes(buf)


def decode_string(cdr):
    """Parse a ``std_msgs/msg/String`` CDR message -> str."""
    mv = memoryview(cdr).cast("B")
    _check_header(mv)
    text, _ = _get_string(mv, 4)
    return text
