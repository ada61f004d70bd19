"""Deep fuzz of the bag readers: mutations AFTER a valid MCAP header, aimed at chunk headers,
record length fields, the records inside chunks, Message headers, CDR payloads (headers,
string lengths, pixels), message indexes, the summary and the footer.

Every case must end in a typed error (:class:`lgs_wfs_ros.bags.BagError`) or a correct read:
  * strict reader on a CRC-protected bag: the messages are exactly the original ones (a
    mutation the reader cannot see, e.g. in a MessageIndex it does not use, changes nothing);
  * lenient reader on a CRC-protected bag: the messages are an in-order subsequence of the
    original ones (damage costs whole chunks, never yields altered messages);
  * bags without CRCs (mutated CDR reaches the decoders): decoders raise BagError or return
    what the CDR says;
  * ``load_bag`` raises BagError, ``analyse`` BagError or its documented ValueError (nothing
    to compare).
Never another exception, never a hang (each case under an alarm). 1,200 cases, fixed seed.
"""

import random
import signal
import struct

import numpy as np
import pytest

from lgs_wfs_ros.analysis import bagload, bagwrite, report
from lgs_wfs_ros.bags import BagError, BagReader
from lgs_wfs_ros.sensor import Sensor

T0 = 1_700_000_000_000_000_000
DT = 1_428_571
CASES_PER_BASE = 240
CASE_SECONDS = 10


def _contract(path, *, compression=None, crc=True, chunk_size=1500, frames=8):
    sensor = Sensor.paper_single("polar", dtype="float32")
    rng = np.random.default_rng(3)
    with bagwrite.ContractBagWriter(path, sensor, log_ns=T0, compression=compression, crc=crc,
                                   chunk_size=chunk_size) as w:
        w.centroider("cog", {"algorithm": "cog", "options": {}}, T0)
        for k in range(frames):
            s = T0 + DT * k
            w.frame(s, rng.poisson(20, size=(16, 16)).astype(np.float32))
            t = rng.normal(0, 0.3, size=(1, 2))
            w.truth(s, t)
            w.slopes("cog", s, t + rng.normal(0, 0.1, (1, 2)), s + 1000)
    return path


def _mcap_writer(path, src, compression, crcs=True, summary=True):
    """Schemas and channels inside chunks (the mcap library's layout)."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, IndexType, Writer
    comp = {"lz4": CompressionType.LZ4, "none": CompressionType.NONE, "zstd": CompressionType.ZSTD}[compression]
    extra = {} if summary else dict(index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
                                    use_statistics=False, use_summary_offsets=False)
    with open(src, "rb") as f, open(path, "wb") as out:
        w = Writer(out, chunk_size=1500, compression=comp, enable_crcs=crcs, **extra)
        w.start(profile="ros2", library="mcap")
        sids, cids = {}, {}
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=False):
            if schema.name not in sids:
                sids[schema.name] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.topic not in cids:
                cids[channel.topic] = w.register_channel(channel.topic, "cdr", sids[schema.name],
                                                         channel.metadata)
            w.add_message(cids[channel.topic], log_time=msg.log_time, data=msg.data,
                          publish_time=msg.publish_time)
        w.finish()
    return path


# -- where to aim ---------------------------------------------------------------------------------
def layout(data):
    """Regions {kind: [(start, end)]} and length/size fields [(pos, width)] of an MCAP file,
    walked by hand (independently of the reader under test)."""
    regions, fields = {}, []

    def add(kind, a, b):
        if b > a:
            regions.setdefault(kind, []).append((a, b))

    pos = 8
    _, hlen = struct.unpack_from("<BQ", data, pos)
    pos += 9 + hlen                                   # the header stays valid
    while pos + 9 <= len(data) - 8:
        op, length = struct.unpack_from("<BQ", data, pos)
        body, end = pos + 9, pos + 9 + length
        fields.append((pos + 1, 8))
        add("record_head", pos, body)
        if op == 0x06:                                # chunk
            fields += [(body + 16, 8), (body + 24, 4), (body + 28, 4)]
            add("chunk_head", body, body + 28)
            (n,) = struct.unpack_from("<I", data, body + 28)
            comp = data[body + 32:body + 32 + n]
            rs = body + 32 + n + 8
            fields.append((rs - 8, 8))
            if comp:
                add("compressed", rs, end)
            else:
                _inner(data, rs, end, add, fields)
        else:
            add({0x05: "message", 0x07: "message_index", 0x03: "schema", 0x04: "channel",
                 0x0C: "metadata", 0x0F: "data_end", 0x02: "footer"}.get(op, "summary"), body, end)
        pos = end
    return regions, fields


def _inner(data, pos, end, add, fields):
    while pos + 9 <= end:
        op, length = struct.unpack_from("<BQ", data, pos)
        fields.append((pos + 1, 8))
        add("inner_head", pos, pos + 9)
        body = pos + 9
        if op == 0x05:
            add("message_head", body, body + 22)
            cdr = body + 22
            add("cdr_head", cdr, min(cdr + 48, body + length))      # encapsulation, stamp, strings
            add("cdr_data", cdr + 48, body + length)
            fields.append((cdr + 12, 4))                                # frame_id length
        elif op in (0x03, 0x04):
            add("inner_schema_channel", body, body + length)
            fields += [(body + 4, 4)] if op == 0x04 else [(body + 2, 4)]
        pos = body + length


def mutate(data, regions, fields, rng):
    """One mutation after the header: (bytes, description)."""
    buf = bytearray(data)
    how = rng.choice(["flip", "flip", "field", "cut", "splice"])
    if how == "field":
        pos, width = rng.choice(fields)
        old = int.from_bytes(buf[pos:pos + width], "little")
        new = rng.choice([0, 1, old + rng.randint(1, 64), max(old - rng.randint(1, 64), 0),
                          2**(8 * width - 1), 2**(8 * width) - 1, rng.getrandbits(8 * width)])
        buf[pos:pos + width] = (new % 2**(8 * width)).to_bytes(width, "little")
        return bytes(buf), f"field@{pos}/{width} {old}->{new}"
    kind = rng.choice(sorted(regions))
    a, b = rng.choice(regions[kind])
    pos = rng.randrange(a, b)
    if how == "flip":
        for _ in range(rng.randint(1, 3)):
            p = rng.randrange(a, b)
            buf[p] ^= rng.randint(1, 255)
        return bytes(buf), f"flip {kind}@{pos}"
    if how == "cut":
        return bytes(buf[:pos]), f"cut {kind}@{pos}"
    n = rng.randint(1, 16)
    if rng.random() < 0.5:
        del buf[pos:pos + n]
        return bytes(buf), f"delete {n} {kind}@{pos}"
    buf[pos:pos] = bytes(rng.getrandbits(8) for _ in range(n))
    return bytes(buf), f"insert {n} {kind}@{pos}"


# -- oracle ---------------------------------------------------------------------------------------
class _Hang(Exception):
    pass


def _alarm(*_):
    raise _Hang()


def _subsequence(got, orig):
    it = iter(orig)
    return all(any(g == o for o in it) for g in got)


def _decode_all(r):
    for topic, (ty, _) in r.topics().items():
        if ty == "sensor_msgs/msg/Image":
            _, arr = r.images(topic)
            assert arr.ndim >= 3 or arr.size == 0
        elif ty == "std_msgs/msg/String":
            assert all(isinstance(t, str) for _, t in r.strings(topic))


CAUSES = {"undecodable": "cdr decoder", "CRC": "chunk CRC", "decompress": "codec",
          "truncated": "truncation", "malformed": "record parser", "runs past": "record parser"}


def _cause(err, path):
    """Which layer refused: the word in the message (without the file's name) that names it."""
    text = str(err).replace(str(path), "")
    return next((v for k, v in CAUSES.items() if k in text), "other")


def exercise(path, orig, crc, outcome):
    """Run every reader path on one mutated file; record how each ended in ``outcome``."""
    try:
        with BagReader(path) as r:
            got = [m[:5] for m in r.messages()]
            if crc:
                assert got == orig, "strict read of a CRC-protected bag returned altered messages"
            _decode_all(r)
            r.summary()
            r.metadata()
        outcome["strict ok"] += 1
    except BagError as err:
        assert str(err) and "Traceback" not in str(err)
        outcome["strict BagError"] += 1
        outcome[_cause(err, path)] += 1
    try:
        with BagReader(path, strict=False) as r:
            got = [m[:5] for m in r.messages()]
            if crc:
                assert _subsequence(got, orig), "lenient read returned a message the bag never had"
            outcome["lenient messages"] += len(got)
            _decode_all(r)
            r.summary()
        outcome["lenient ok"] += 1
    except BagError as err:
        outcome["lenient BagError"] += 1
        outcome[_cause(err, path)] += 1
    try:
        data = bagload.load_bag(path, max_frames=None)
    except BagError:
        outcome["load BagError"] += 1
        return
    try:
        report.analyse(data, crb=False)
        outcome["analyse ok"] += 1
    except (BagError, ValueError):
        outcome["analyse refused"] += 1


BASES = {
    "ours, uncompressed, CRC": lambda p, src: _contract(p),
    "ours, uncompressed, no CRC (CDR reaches the decoders)": lambda p, src: _contract(p, crc=False),
    "ours, zstd, CRC": lambda p, src: _contract(p, compression="zstd"),
    "mcap Writer, lz4, schemas in chunks": lambda p, src: _mcap_writer(p, src, "lz4"),
    "mcap Writer, uncompressed, no CRC, no summary": lambda p, src: _mcap_writer(p, src, "none", False, False),
}


@pytest.mark.parametrize("base", sorted(BASES))
def test_deep_fuzz(tmp_path, base):
    src = _contract(tmp_path / "src.mcap")
    good = BASES[base](tmp_path / "good.mcap", src)
    data = good.read_bytes()
    crc = "no CRC" not in base
    with BagReader(good) as r:
        orig = [m[:5] for m in r.messages()]
    assert len(orig) >= 20
    regions, fields = layout(data)
    rng = random.Random(f"lgs-wfs bag fuzz {base}")
    outcome = dict.fromkeys(["strict ok", "strict BagError", "lenient ok", "lenient BagError",
                             "lenient messages", "load BagError", "analyse ok", "analyse refused",
                             "other", *CAUSES.values()], 0)
    kinds = {}
    path = tmp_path / "case.mcap"
    old = signal.signal(signal.SIGALRM, _alarm)
    try:
        for case in range(CASES_PER_BASE):
            buf, what = mutate(data, regions, fields, rng)
            kinds[what.split()[0].split("@")[0]] = kinds.get(what.split()[0].split("@")[0], 0) + 1
            path.write_bytes(buf)
            signal.alarm(CASE_SECONDS)
            try:
                exercise(path, orig, crc, outcome)
            except _Hang:
                pytest.fail(f"case {case} ({what}) took over {CASE_SECONDS} s")
            except AssertionError as err:
                raise AssertionError(f"case {case} ({what}): {err}") from None
            except Exception as err:
                pytest.fail(f"case {case} ({what}): {type(err).__name__}: {err}")
            finally:
                signal.alarm(0)
    finally:
        signal.signal(signal.SIGALRM, old)
    print(base, outcome, kinds)
    # the fuzz reaches past the open: most cases are read (fully or partly), many are refused deep
    assert outcome["lenient ok"] > CASES_PER_BASE // 2
    assert outcome["lenient messages"] > 5 * CASES_PER_BASE
    assert outcome["strict BagError"] > CASES_PER_BASE // 10
    assert outcome["analyse ok"] > CASES_PER_BASE // 20
    # ... by the layer that owns the damage: chunk CRCs where there are CRCs, else the record
    # parsers and the CDR decoders
    deep = ("chunk CRC",) if crc else ("record parser", "cdr decoder")
    for cause in deep:
        assert outcome[cause] > 0, cause
    if "zstd" in base or "lz4" in base:
        assert outcome["codec"] + outcome["chunk CRC"] > CASES_PER_BASE // 10
