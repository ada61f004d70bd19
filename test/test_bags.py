"""MCAP bags in rosbag2 layout: CDR parity with rclpy, schema text, mcap-ros2 decoding, rosbag2
metadata, overwrite refusal, truncation/SIGKILL recovery, full disk, join by stamp (the fuzz is
test/test_bag_fuzz.py)."""

import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import yaml

from lgs_wfs_ros.bags import (BagError, BagExistsError, BagReader, BagWriteError, BagWriter,
                              decode_image, decode_string, encode_image, encode_string,
                              join_by_stamp, message_definition, peek_stamp, recover, type_hash)
from lgs_wfs_ros.bags import schema as schema_mod

T0 = 1_700_000_000_123_456_789
FRAME, TRUTH, SENSOR = "/wfs/frame", "/wfs/true_slopes", "/wfs/sensor"


def _frames(n, shape=(32, 48), seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 65535, size=(n,) + shape, dtype=np.uint16)


def _slopes(n, seed=1):
    s = np.random.default_rng(seed).normal(size=(n, 6, 6, 2)).astype(np.float32)
    s[:, 0, 0] = np.nan
    return s


def _write_bag(path, n=20, chunk_size=20_000, compression="zstd", **kw):
    frames, slopes = _frames(n), _slopes(n)
    stamps = T0 + np.arange(n, dtype=np.int64) * 1_428_571
    with BagWriter(path, chunk_size=chunk_size, compression=compression, **kw) as w:
        w.add_topic(FRAME, "sensor_msgs/msg/Image")
        w.add_topic(TRUTH, "sensor_msgs/msg/Image", qos={"depth": 100})
        w.add_topic(SENSOR, "std_msgs/msg/String", qos={"durability": "transient_local", "depth": 1})
        w.write(SENSOR, encode_string('{"n_sub": 6}'), T0 - 5, T0 - 5)
        for i in range(n):
            st = int(stamps[i])
            w.write(FRAME, encode_image(frames[i], st), st + 1000, st)
            w.write(TRUTH, encode_image(slopes[i], st), st + 2000, st)
    return frames, slopes, stamps


# --- CDR ---------------------------------------------------------------------------------

def _rclpy_image(arr, stamp_ns, frame_id, encoding, step=None, data=None, bigendian=0):
    from sensor_msgs.msg import Image
    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    m.header.frame_id = frame_id
    m.height, m.width = arr.shape[:2]
    m.encoding = encoding
    m.is_bigendian = bigendian
    m.step = step if step is not None else arr.shape[1] * arr.itemsize * (arr.shape[2] if arr.ndim == 3 else 1)
    m.data = data if data is not None else arr.tobytes()
    return m


def _padding_positions(cdr):
    """Byte positions of CDR alignment padding in an Image message (after frame_id, after
    encoding + is_bigendian): rclpy (Fast-CDR) leaves these bytes uninitialised."""
    import struct
    out = []
    n = struct.unpack_from("<I", cdr, 12)[0]
    end = 16 + n
    out += range(end, end + (-(end - 4)) % 4)
    pos = end + (-(end - 4)) % 4 + 8
    n = struct.unpack_from("<I", cdr, pos)[0]
    end = pos + 4 + n + 1                                   # + is_bigendian
    out += range(end, end + (-(end - 4)) % 4)
    return set(out)


@pytest.mark.parametrize("frame_id", ["", "w", "wfs", "wfs_", "a_longer_frame_id"])
@pytest.mark.parametrize("kind", ["mono16", "32FC1", "32FC2"])
def test_image_cdr_matches_rclpy_byte_for_byte(kind, frame_id):
    pytest.importorskip("rclpy")
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image
    rng = np.random.default_rng(3)
    arr = {"mono16": rng.integers(0, 65535, (5, 7), dtype=np.uint16),
           "32FC1": rng.normal(size=(3, 5)).astype(np.float32),
           "32FC2": rng.normal(size=(4, 3, 2)).astype(np.float32)}[kind]
    ours = encode_image(arr, T0, frame_id=frame_id)
    ref = serialize_message(_rclpy_image(arr, T0, frame_id, kind))
    assert len(ours) == len(ref)
    pad = _padding_positions(ours)
    diff = {i for i in range(len(ours)) if ours[i] != ref[i]}
    assert diff <= pad                                       # identical except padding bytes
    assert all(ours[i] == 0 for i in pad)                    # which we write as zeros
    back = deserialize_message(ours, Image)
    assert back.encoding == kind and back.header.frame_id == frame_id
    stamp, fid, enc, dec = decode_image(ref)
    assert (stamp, fid, enc) == (T0, frame_id, kind)
    np.testing.assert_array_equal(dec, arr)
    assert peek_stamp(ref) == T0


@pytest.mark.parametrize("text", ["", "x", "abc", "abcd", '{"algorithm": "cmf", "µ": 1}'])
def test_string_cdr_matches_rclpy(text):
    pytest.importorskip("rclpy")
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String
    ref = serialize_message(String(data=text))
    assert encode_string(text) == ref
    assert decode_string(ref) == text


def test_decode_is_zero_copy_and_handles_padding_and_big_endian():
    pytest.importorskip("rclpy")
    from rclpy.serialization import serialize_message
    arr = np.arange(20, dtype=np.uint16).reshape(4, 5)
    cdr = encode_image(arr, 5)
    _, _, _, view = decode_image(cdr)
    assert not view.flags.owndata and not view.flags.writeable   # a view into the bytes
    # rows padded to 16 bytes (step > width * 2)
    padded = np.zeros((4, 8), np.uint16)
    padded[:, :5] = arr
    m = _rclpy_image(arr, 5, "wfs", "mono16", step=16, data=padded.tobytes())
    np.testing.assert_array_equal(decode_image(serialize_message(m))[3], arr)
    # big-endian pixel data
    m = _rclpy_image(arr, 5, "wfs", "mono16", data=arr.astype(">u2").tobytes(), bigendian=1)
    np.testing.assert_array_equal(decode_image(serialize_message(m))[3], arr)


def test_encode_refuses_bad_arrays_and_decode_refuses_bad_bytes():
    with pytest.raises(ValueError):
        encode_image(np.zeros((3, 3), np.int64), 0)
    with pytest.raises(ValueError):
        encode_image(np.zeros((3, 3), np.float32), 0, encoding="mono16")
    with pytest.raises(ValueError):
        encode_image(np.zeros((3, 3, 3), np.float32), 0)
    with pytest.raises(ValueError):
        encode_image(np.zeros((3, 3), np.uint16), 2**31 * 10**9)       # int32 seconds overflow
    good = encode_image(np.zeros((3, 3), np.uint16), 0)
    for bad in (good[:-1], good[:10], b"\x01\x00\x00\x00" + good[4:], b""):
        with pytest.raises(ValueError):
            decode_image(bad)
    # the stamp splits into ROS (sec, nanosec) also for stamps before the epoch
    assert decode_image(encode_image(np.zeros((1, 1), np.uint16), -1))[0] == -1


# --- writing: layout, schema, metadata ---------------------------------------------------

@pytest.mark.parametrize("background", [False, True])
def test_round_trip_images_and_strings(tmp_path, background):
    p = tmp_path / "b.mcap"
    frames, slopes, stamps = _write_bag(p, background=background)
    with BagReader(p) as r:
        assert r.complete and r.problems == []
        assert r.topics() == {FRAME: ("sensor_msgs/msg/Image", 20), TRUTH: ("sensor_msgs/msg/Image", 20),
                              SENSOR: ("std_msgs/msg/String", 1)}
        st, arr = r.images(FRAME)
        np.testing.assert_array_equal(st, stamps)
        np.testing.assert_array_equal(arr, frames)
        st, arr = r.images(TRUTH)
        np.testing.assert_array_equal(arr, slopes)          # NaN positions equal too
        assert arr.shape == (20, 6, 6, 2) and arr.dtype == np.float32
        assert r.strings(SENSOR) == [(T0 - 5, '{"n_sub": 6}')]
        msgs = list(r.messages([FRAME]))
        assert [m[2] for m in msgs] == list(stamps + 1000) and [m[3] for m in msgs] == list(stamps)
        assert msgs[3][4] == encode_image(frames[3], int(stamps[3]))
        s = r.summary()
        assert s["message_count"] == 41 and s["start_ns"] == T0 - 5 and s["end_ns"] == stamps[-1] + 2000
        assert s["topics"][FRAME]["count"] == 20
        assert s["types"] == ["sensor_msgs/msg/Image", "std_msgs/msg/String"]
        streamed = list(r.iter_images(TRUTH))
        assert [m[0] for m in streamed] == list(stamps) and streamed[0][1:3] == ("wfs", "32FC2")
        np.testing.assert_array_equal(streamed[7][3], slopes[7])


def test_schema_text_has_full_definitions_with_separators(tmp_path):
    text = message_definition("sensor_msgs/msg/Image")
    sep = "\n" + "=" * 80 + "\n"
    parts = text.split(sep)
    assert len(parts) == 3                                   # Image, then Header, then Time once each
    assert parts[1].startswith("MSG: std_msgs/Header\n") and "builtin_interfaces/Time stamp" in parts[1]
    assert parts[2].startswith("MSG: builtin_interfaces/Time\n") and "uint32 nanosec" in parts[2]
    assert "uint8[] data" in parts[0] and "std_msgs/Header header" in parts[0]
    f = schema_mod.find_interface_file("sensor_msgs/msg/Image", "msg")
    if f is not None:                                        # identical to rosbag2's construction
        share = f.parents[2]
        expect = (f.read_text() + sep + "MSG: std_msgs/Header\n" + (share / "std_msgs/msg/Header.msg").read_text()
                  + sep + "MSG: builtin_interfaces/Time\n" + (share / "builtin_interfaces/msg/Time.msg").read_text())
        assert text == expect
    p = tmp_path / "b.mcap"
    _write_bag(p, n=2)
    with BagReader(p) as r:
        assert r.schema_text(FRAME) == text
        assert r.schema_text(SENSOR) == message_definition("std_msgs/msg/String")


def test_builtin_definitions_without_ros(monkeypatch):
    monkeypatch.setattr(schema_mod, "find_interface_file", lambda *a: None)
    for fn in (schema_mod._msg_text, schema_mod.message_definition, schema_mod.type_hash):
        fn.cache_clear()
    try:
        text = schema_mod.message_definition("sensor_msgs/msg/Image")
        assert text.count("=" * 80) == 2 and "MSG: std_msgs/Header" in text and "int32 sec" in text
        assert schema_mod.type_hash("std_msgs/msg/String").startswith("RIHS01_")
        with pytest.raises(LookupError):
            schema_mod.message_definition("geometry_msgs/msg/Point")
    finally:
        for fn in (schema_mod._msg_text, schema_mod.message_definition, schema_mod.type_hash):
            fn.cache_clear()


@pytest.mark.parametrize("compression", ["zstd", "lz4", None])
def test_mcap_ros2_support_decodes_every_message(tmp_path, compression):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    p = tmp_path / "b.mcap"
    frames, slopes, stamps = _write_bag(p, compression=compression)
    n = 0
    with open(p, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages():
            n += 1
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            if channel.topic == SENSOR:
                assert msg.data == '{"n_sub": 6}'
                continue
            i = int(np.searchsorted(stamps, message.publish_time))
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamps[i]
            ref = frames[i] if channel.topic == FRAME else slopes[i]
            got = np.frombuffer(bytes(msg.data), ref.dtype).reshape(ref.shape)
            np.testing.assert_array_equal(got, ref)
    assert n == 41


def test_rosbag2_profile_encodings_and_metadata(tmp_path):
    from mcap.reader import make_reader
    p = tmp_path / "b.mcap"
    _write_bag(p)
    with open(p, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        assert header.profile == "ros2" and header.library.startswith("lgs_wfs_ros")
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {s.name for s in summary.schemas.values()} == {"sensor_msgs/msg/Image", "std_msgs/msg/String"}
        by_topic = {c.topic: c for c in summary.channels.values()}
        assert len(summary.schemas) == 2 and len(by_topic) == 3          # one schema per type
        for topic, c in by_topic.items():
            assert c.message_encoding == "cdr"
            qos = yaml.safe_load(c.metadata["offered_qos_profiles"])
            assert isinstance(qos, list) and qos[0]["reliability"] == "reliable"
            assert set(qos[0]) >= {"history", "depth", "durability", "deadline", "lifespan", "liveliness"}
        assert yaml.safe_load(by_topic[SENSOR].metadata["offered_qos_profiles"])[0]["durability"] == "transient_local"
        assert by_topic[FRAME].metadata["topic_type_hash"] == type_hash("sensor_msgs/msg/Image")
        f_json = schema_mod.find_interface_file("sensor_msgs/msg/Image", "json")
        if f_json is not None:
            hashes = json.loads(f_json.read_text())["type_hashes"]
            assert by_topic[FRAME].metadata["topic_type_hash"] == hashes[0]["hash_string"]
        assert summary.statistics.message_count == 41
        meta = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        assert len(meta) == 1
    doc = yaml.safe_load(meta[0].metadata["serialized_metadata"])
    assert doc["version"] == 9 and doc["storage_identifier"] == "mcap" and doc["message_count"] == 41
    assert doc["starting_time"]["nanoseconds_since_epoch"] == summary.statistics.message_start_time
    assert doc["duration"]["nanoseconds"] == (summary.statistics.message_end_time
                                               - summary.statistics.message_start_time)
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in doc["topics_with_message_count"]}
    assert counts == {FRAME: 20, TRUTH: 20, SENSOR: 1}
    tm = doc["topics_with_message_count"][0]["topic_metadata"]
    assert tm["serialization_format"] == "cdr" and tm["type_description_hash"].startswith("RIHS01_")
    assert doc["files"][0]["path"] == "b.mcap" and doc["relative_file_paths"] == ["b.mcap"]


def test_existing_path_is_never_overwritten(tmp_path):
    p = tmp_path / "b.mcap"
    _write_bag(p, n=2)
    before = p.read_bytes()
    with pytest.raises(BagExistsError) as err:
        BagWriter(p)
    assert isinstance(err.value, FileExistsError) and "overwrite" in str(err.value)
    assert p.read_bytes() == before
    with BagWriter(p, overwrite=True) as w:
        w.add_topic(SENSOR, "std_msgs/msg/String")
    with BagReader(p) as r:
        assert r.topics() == {SENSOR: ("std_msgs/msg/String", 0)}


def test_writer_refuses_misuse(tmp_path):
    with pytest.raises(ValueError):
        BagWriter(tmp_path / "x.mcap", compression="gzip")
    with BagWriter(tmp_path / "a.mcap") as w:
        w.add_topic(FRAME, "sensor_msgs/msg/Image")
        assert w.add_topic(FRAME, "sensor_msgs/Image") == 1              # same type: same channel
        with pytest.raises(ValueError):
            w.add_topic(FRAME, "std_msgs/msg/String")
        with pytest.raises(ValueError):
            w.write("/nope", b"\x00\x01\x00\x00", 0)
        with pytest.raises(ValueError):
            w.write(FRAME, b"\x00\x01\x00\x00", -1)
        with pytest.raises(ValueError):
            w.add_topic("/p", "geometry_msgs/msg/NoSuchType")
        with pytest.raises(ValueError):
            w.add_topic("/q", "std_msgs/msg/String", qos={"reliability": "sometimes"})
    with pytest.raises(BagError):
        w.write(FRAME, b"\x00\x01\x00\x00", 0)
    with pytest.raises(BagError):
        BagWriter(tmp_path)                                               # a directory


# --- reading damaged and wrong bags -------------------------------------------------------

def _chunk_ends(path):
    """[(end offset of chunk record, messages in chunks so far)] from the summary (mcap lib)."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        cis = make_reader(f).get_summary().chunk_indexes
    out, total = [], 0
    with open(path, "rb") as f:
        from mcap.stream_reader import breakup_chunk
        from mcap.records import Chunk
        from mcap.data_stream import ReadDataStream
        for ci in cis:
            f.seek(ci.chunk_start_offset + 9)
            chunk = Chunk.read(ReadDataStream(f))
            total += sum(1 for r in breakup_chunk(chunk) if type(r).__name__ == "Message")
            out.append((ci.chunk_start_offset + ci.chunk_length, total))
    return out


def test_truncated_bag_reads_to_last_complete_chunk_and_recovers(tmp_path):
    p = tmp_path / "b.mcap"
    _write_bag(p, n=30)
    data = p.read_bytes()
    ends = _chunk_ends(p)
    assert len(ends) >= 5
    for cut in (ends[2][0] - 1, ends[2][0], ends[2][0] + 7, ends[-1][0] - 100, len(data) - 10):
        t = tmp_path / f"cut{cut}.mcap"
        t.write_bytes(data[:cut])
        with pytest.raises(BagError, match="truncated"):
            BagReader(t)
        expect = max([n for e, n in ends if e <= cut], default=0)
        with BagReader(t, strict=False) as r:
            assert len(list(r.messages())) == expect
            assert not r.complete and r.problems
        out = tmp_path / f"rec{cut}.mcap"
        with pytest.raises(BagError):
            recover(t, t, overwrite=True)                                 # never onto the source
        stats = recover(t, out)
        assert stats["messages"] == expect and not stats["source_complete"]
        with BagReader(out) as r:                                         # strict: complete again
            assert r.complete and sum(n for _, n in r.topics().values()) == expect
            st, arr = r.images(FRAME)
            np.testing.assert_array_equal(arr, _frames(30)[:len(st)])


def test_both_recover_commands_are_one(tmp_path, capsys):
    """`lgs-wfs recover` and `python -m lgs_wfs_ros.bags recover` print the same statistics
    and exit alike: 0 intact source, 1 cut source, 2 refused (not MCAP, output exists)."""
    from lgs_wfs_ros import cli
    from lgs_wfs_ros.bags.__main__ import main as bags_main
    p = tmp_path / "b.mcap"
    _write_bag(p, n=30)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(p.read_bytes()[:_chunk_ends(p)[2][0] + 5])
    (tmp_path / "text.mcap").write_text("not a bag\n" * 10)
    for src, code in ((p, 0), (cut, 1), (tmp_path / "text.mcap", 2)):
        outs = []
        for k, run in enumerate((cli.main, bags_main)):
            dst = tmp_path / f"rec_{src.stem}_{k}.mcap"
            assert run(["recover", str(src), str(dst)]) == code, (src, run)
            out, err = capsys.readouterr()
            if code == 2:
                assert not dst.exists() and "not an MCAP" in err and "Traceback" not in err
                continue
            outs.append(json.loads(out))
            with BagReader(dst) as r:
                assert r.complete and sum(n for _, n in r.topics().values()) == outs[-1]["messages"]
            assert run(["recover", str(src), str(dst)]) == 2                 # dst exists
            assert "exists" in capsys.readouterr().err
            assert run(["recover", str(src), str(dst), "--overwrite"]) == code
            capsys.readouterr()
        if outs:
            assert outs[0] == outs[1] and outs[0]["source_complete"] == (code == 0)


def test_sigkill_leaves_readable_chunks(tmp_path):
    p = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import sys, numpy as np
        from lgs_wfs_ros.bags import BagWriter, encode_image
        w = BagWriter({str(p)!r}, chunk_size=50_000)
        w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
        i = 0
        while True:
            w.write("/wfs/frame", encode_image(np.full((64, 64), i % 65535, np.uint16), i), i, i)
            if i == 200:
                print("ready", flush=True)
            i += 1
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    with pytest.raises(BagError):
        BagReader(p)
    stats = recover(p, tmp_path / "rec.mcap")
    assert stats["messages"] >= 180
    with BagReader(tmp_path / "rec.mcap") as r:
        st, arr = r.images("/wfs/frame")
        np.testing.assert_array_equal(st, np.arange(len(st)))           # no gaps, in order
        np.testing.assert_array_equal(arr[:, 0, 0], np.arange(len(st)) % 65535)


def test_clear_errors_for_wrong_inputs(tmp_path):
    with pytest.raises(BagError, match="no such file"):
        BagReader(tmp_path / "missing.mcap")
    with pytest.raises(BagError, match="no .mcap file in it, not a bag file"):
        BagReader(tmp_path)
    (tmp_path / "text.mcap").write_text("hello, this is not a bag at all\n" * 10)
    with pytest.raises(BagError, match="not an MCAP"):
        BagReader(tmp_path / "text.mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError):
        BagReader(tmp_path / "empty.mcap")
    p = tmp_path / "b.mcap"
    _write_bag(p, n=2)
    with BagReader(p) as r:
        with pytest.raises(BagError, match="no topic /wfs/slopes"):
            r.images("/wfs/slopes")
        with pytest.raises(BagError, match="has type std_msgs/msg/String"):
            r.images(SENSOR)
        with pytest.raises(BagError, match="expected std_msgs/msg/String"):
            r.strings(FRAME)


def test_corrupt_chunk_is_reported_or_skipped(tmp_path):
    p = tmp_path / "b.mcap"
    _write_bag(p, n=30, compression=None)
    data = bytearray(p.read_bytes())
    ends = _chunk_ends(p)
    data[ends[1][0] - 50] ^= 0xFF                  # inside the second chunk's records
    t = tmp_path / "flip.mcap"
    t.write_bytes(bytes(data))
    with BagReader(t) as r:                         # summary intact: opens
        with pytest.raises(BagError, match="CRC"):
            list(r.messages())
    with BagReader(t, strict=False) as r:
        n = len(list(r.messages()))
        assert n == ends[-1][1] - (ends[1][1] - ends[0][1])                 # all but chunk 2
        assert any("CRC" in s for s in r.problems)


# --- full disk -----------------------------------------------------------------------------

@pytest.mark.parametrize("background", [False, True])
def test_full_disk_is_reported_and_keeps_what_was_written(tmp_path, background):
    """RLIMIT_FSIZE in a subprocess (SIGXFSZ ignored) makes write() fail with EFBIG, the same
    path as ENOSPC: the writer must raise BagWriteError and leave a readable file."""
    p = tmp_path / "full.mcap"
    limit = 300_000
    script = textwrap.dedent(f"""
        import json, resource, signal, numpy as np
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
        from lgs_wfs_ros.bags import BagWriter, BagWriteError, encode_image
        w = BagWriter({str(p)!r}, chunk_size=40_000, compression=None, background={background})
        w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
        i = 0
        try:
            while i < 10_000:
                w.write("/wfs/frame", encode_image(np.full((64, 64), i, np.uint16), i), i, i)
                i += 1
            w.close()
            print(json.dumps({{"error": None}}))
        except BagWriteError as err:
            w.close()                                   # quiet after the error was reported
            print(json.dumps({{"error": str(err), "kept": err.messages_kept, "lost": err.messages_lost,
                               "written": i + 1, "oserror": isinstance(err, OSError)}}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["error"] and "File too large" in res["error"] and res["oserror"]
    assert res["kept"] > 0
    # inline: the failing write() accepted its message, then its chunk failed; background: a
    # later call reports the worker's failure before accepting its message
    assert res["kept"] + res["lost"] == res["written"] - (1 if background else 0)
    assert p.stat().st_size <= limit
    with BagReader(p) as r:                          # valid ending written: opens strictly
        st, arr = r.images("/wfs/frame")
    assert len(st) == res["kept"]
    np.testing.assert_array_equal(st, np.arange(res["kept"]))
    np.testing.assert_array_equal(arr[:, 5, 5], np.arange(res["kept"]).astype(np.uint16))
    stats = recover(p, tmp_path / "rec.mcap")
    assert stats["messages"] == res["kept"]
    from mcap.reader import make_reader
    with open(tmp_path / "rec.mcap", "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count == res["kept"]


# --- join ----------------------------------------------------------------------------------

def test_join_by_stamp_with_missing_and_duplicates():
    a = np.array([10, 20, 30, 40, 50])
    b = np.array([20, 10, 40, 40, 50, 60])          # unordered, 40 twice, 30 missing, 60 extra
    c = np.array([50, 40, 30, 20, 10, 10, 10])
    j = join_by_stamp(a, b, c)
    np.testing.assert_array_equal(j.stamps, [10, 20, 40, 50])
    for arr, idx in zip((a, b, c), j.indices):
        np.testing.assert_array_equal(arr[idx], j.stamps)
    assert j.indices[1].tolist() == [1, 0, 2, 4]      # first 40 kept
    assert j.indices[2].tolist() == [4, 3, 1, 0]      # first 10 kept
    assert j.duplicates == (0, 1, 2)
    assert [m.tolist() for m in j.missing] == [[60], [30], [60]]
    assert j.n_missing == (1, 1, 1)
    empty = join_by_stamp(a, np.array([], np.int64))
    assert empty.stamps.size == 0 and empty.n_missing == (0, 5)
    with pytest.raises(ValueError):
        join_by_stamp(np.array([1.5]))
    with pytest.raises(ValueError):
        join_by_stamp()


def test_join_aligns_bag_topics(tmp_path):
    p = tmp_path / "b.mcap"
    stamps = T0 + np.arange(10) * 1000
    with BagWriter(p) as w:
        w.add_topic(FRAME, "sensor_msgs/msg/Image")
        w.add_topic(TRUTH, "sensor_msgs/msg/Image")
        for i, s in enumerate(stamps):
            if i != 3:                                             # frame 3 dropped
                w.write(FRAME, encode_image(np.full((2, 2), i, np.uint16), int(s)), int(s))
        for i in (0, 1, 2, 3, 4, 4, 5, 6, 7, 8, 9):               # truth 4 duplicated
            w.write(TRUTH, encode_image(np.full((2, 2, 2), i, np.float32), int(stamps[i])), int(stamps[i]))
    with BagReader(p) as r:
        fs, frames = r.images(FRAME)
        ts, truths = r.images(TRUTH)
    j = join_by_stamp(fs, ts)
    assert len(j.stamps) == 9 and j.duplicates == (0, 1) and j.missing[0].tolist() == [stamps[3]]
    np.testing.assert_array_equal(frames[j.indices[0], 0, 0], truths[j.indices[1], 0, 0, 0])


def test_full_tmpfs_gives_enospc_and_a_readable_bag(tmp_path):
    """The same on a real full file system: a 256 kB tmpfs (needs root and mount; else skipped)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                             capture_output=True).returncode == 0 if os.geteuid() == 0 else False
    if not mounted:
        pytest.skip("cannot mount a tmpfs here (needs root); RLIMIT_FSIZE test covers the path")
    try:
        p = disk / "full.mcap"
        written = 0
        with pytest.raises(BagWriteError, match="No space left") as err:
            with BagWriter(p, chunk_size=30_000, compression=None) as w:
                w.add_topic(FRAME, "sensor_msgs/msg/Image")
                for i in range(10_000):
                    w.write(FRAME, encode_image(np.full((64, 64), i, np.uint16), i), i, i)
                    written += 1
        kept = err.value.messages_kept
        assert kept > 0 and kept + err.value.messages_lost == written + 1
        with BagReader(p, strict=False) as r:
            st, arr = r.images(FRAME)
        np.testing.assert_array_equal(st, np.arange(kept))
        np.testing.assert_array_equal(arr[:, 1, 1], np.arange(kept).astype(np.uint16))
    finally:
        if subprocess.run(["umount", str(disk)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(disk)], capture_output=True)   # still busy: detach


def test_wrong_message_encoding_is_refused(tmp_path):
    from mcap.writer import Writer
    p = tmp_path / "json.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="other")
        sid = w.register_schema("sensor_msgs/msg/Image", "ros2msg", b"")
        cid = w.register_channel("/cam", "json", sid)
        w.add_message(cid, log_time=1, data=b'{"height": 1}', publish_time=1)
        w.finish()
    with BagReader(p) as r:
        with pytest.raises(BagError, match="encoded as 'json'"):
            r.images("/cam")


@pytest.mark.parametrize("chunked", [True, False])
def test_reads_bags_written_by_the_mcap_library(tmp_path, chunked):
    """Other tools put Schema/Channel records inside chunks, or write no chunks at all."""
    from mcap.writer import CompressionType, Writer
    p = tmp_path / "other.mcap"
    frames = _frames(5)
    with open(p, "wb") as f:
        w = Writer(f, chunk_size=10_000, compression=CompressionType.LZ4, use_chunking=chunked)
        w.start(profile="ros2", library="other")
        sid = w.register_schema("sensor_msgs/msg/Image", "ros2msg",
                                message_definition("sensor_msgs/msg/Image").encode())
        cid = w.register_channel("/cam", "cdr", sid)
        for i in range(5):
            w.add_message(cid, log_time=100 + i, data=encode_image(frames[i], i), publish_time=i)
        w.finish()
    with BagReader(p) as r:
        assert r.topics() == {"/cam": ("sensor_msgs/msg/Image", 5)} and r.library == "other"
        st, arr = r.images("/cam")
    np.testing.assert_array_equal(st, np.arange(5))
    np.testing.assert_array_equal(arr, frames)


def _consistent(path):
    """The bag opens strictly; its statistics, rosbag2 metadata and a full scan agree; the
    frames are 0..n-1 without gaps. Returns n."""
    with BagReader(path) as r:
        assert r.complete
        counts = r.topics()
        st, arr = r.images(FRAME)
        meta = yaml.safe_load(dict(r.metadata())["rosbag2"]["serialized_metadata"])
    n = len(st)
    assert counts[FRAME][1] == n and meta["message_count"] == n
    np.testing.assert_array_equal(st, np.arange(n))
    np.testing.assert_array_equal(arr[:, 0, 0], (np.arange(n) % 65535).astype(np.uint16))  # writers store i % 65535
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages()) == n
    return n


def test_keyboard_interrupt_inside_writes_leaves_a_consistent_bag(tmp_path, monkeypatch):
    """An exception in the middle of writev (as a SIGINT handler raising KeyboardInterrupt
    would) rolls the file back to its last complete chunk; close() then finishes it."""
    from lgs_wfs_ros.bags import writer as writer_mod
    real = os.writev
    calls = {"n": 0}

    def flaky(fd, parts):
        calls["n"] += 1
        if calls["n"] == 6:
            real(fd, [parts[0][: len(parts[0]) // 2]])       # half a chunk reaches the disk
            raise KeyboardInterrupt
        return real(fd, parts)

    monkeypatch.setattr(writer_mod.os, "writev", flaky)
    p = tmp_path / "int.mcap"
    w = BagWriter(p, chunk_size=20_000, compression=None)
    w.add_topic(FRAME, "sensor_msgs/msg/Image")
    with pytest.raises(KeyboardInterrupt):
        for i in range(1000):
            w.write(FRAME, encode_image(np.full((40, 40), i, np.uint16), i), i, i)
    w.close()
    monkeypatch.setattr(writer_mod.os, "writev", real)
    n = _consistent(p)
    assert 0 < n < w.message_count


@pytest.mark.parametrize("sig,delay", [(signal.SIGINT, 0.3), (signal.SIGINT, 0.55), (signal.SIGINT, 0.8),
                                       (signal.SIGTERM, 0.4), (signal.SIGTERM, 0.7)])
def test_sigint_at_random_moments_gives_a_complete_bag(tmp_path, sig, delay):
    """Python's default SIGINT handler raises KeyboardInterrupt at any bytecode, also inside
    write() (SIGTERM here gets a handler raising SystemExit, as a recorder would install); the
    pattern `try: ... finally: close()` must still give a complete bag."""
    p = tmp_path / "sigint.mcap"
    script = textwrap.dedent(f"""
        import signal, sys
        import numpy as np
        from lgs_wfs_ros.bags import BagWriter, encode_image
        signal.signal(signal.SIGTERM, lambda *a: sys.exit(0))
        # Python's own SIGINT handler even when started with SIGINT ignored (as a job put
        # in the background by a non-interactive shell is: the test then timed out)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        w = BagWriter({str(p)!r}, chunk_size=30_000, compression="lz4")
        try:
            w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
            i = 0
            print("ready", flush=True)
            while True:
                w.write("/wfs/frame", encode_image(np.full((40, 40), i % 65535, np.uint16), i), i, i)
                i += 1
        except (KeyboardInterrupt, SystemExit):
            pass
        finally:
            w.close()
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        import time
        time.sleep(delay)
        proc.send_signal(sig)
        assert proc.wait(timeout=30) == 0
    finally:                     # a child that missed the signal writes on forever: end it
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert _consistent(p) > 0


def test_many_chunks(tmp_path):
    """More chunk indexes than writev takes buffers in one call (IOV_MAX, 1024 on Linux)."""
    p = tmp_path / "many.mcap"
    with BagWriter(p, chunk_size=1, compression=None) as w:
        w.add_topic(FRAME, "sensor_msgs/msg/Image")
        for i in range(2100):
            w.write(FRAME, encode_image(np.full((1, 1), i, np.uint16), i), i, i)
    assert _consistent(p) == 2100
    with BagReader(p) as r:
        assert r._summary["stats"]["chunks"] == 2100
