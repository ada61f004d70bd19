"""BagReader, `lgs-wfs inspect` and `lgs-wfs report` on MCAP written by other tools: mcap's
Writer (Schema/Channel records inside chunks, every compression, with and without summary,
indexes, statistics), mcap-ros2-support, rosbags, and rosbag2's own test bags
(test/data/rosbag2, see its README).

A contract bag is written by our writer, then re-recorded by each foreign writer from what
the ``mcap`` library reads (not from our reader); the report of every copy must equal the
original's, number for number."""

import json
from pathlib import Path

import numpy as np
import pytest

from lgs_wfs_ros import cli
from lgs_wfs_ros.analysis import bagload, bagwrite, report
from lgs_wfs_ros.analysis.inspect import bag_info
from lgs_wfs_ros.bags import BagError, BagReader
from lgs_wfs_ros.sensor import Sensor

T0 = 1_700_000_000_000_000_000
DT = 1_428_571
ROSBAG2 = Path(__file__).parent / "data" / "rosbag2"
FIXTURES = sorted(ROSBAG2.glob("*.mcap"))


@pytest.fixture(scope="module")
def contract_bag(tmp_path_factory):
    """A small contract bag (single subaperture, cog and cmf slopes = truth + known noise, the
    cog centroider switching once); returns (path, report numbers)."""
    path = tmp_path_factory.mktemp("interop") / "contract.mcap"
    sensor = Sensor.paper_single("polar", dtype="float32")
    rng = np.random.default_rng(5)
    n = 40
    truths = rng.normal(0, 0.3, size=(n, 1, 2))
    with bagwrite.ContractBagWriter(path, sensor, log_ns=T0, compression=None) as w:
        w.centroider("cog", {"algorithm": "cog", "options": {}}, T0)
        w.centroider("cmf", {"algorithm": "cmf", "options": {}}, T0)
        for k in range(n):
            s = T0 + DT * k
            if k == 25:
                w.centroider("cog", {"algorithm": "tcog", "options": {"threshold": 0.1}}, s)
            w.truth(s, truths[k])
            w.slopes("cog", s, truths[k] + rng.normal(0, 0.2, (1, 2)), s + 1000)
            if k % 4:                                    # cmf misses every 4th frame
                w.slopes("cmf", s, truths[k] + rng.normal(0, 0.1, (1, 2)), s + 2000)
    return path, _numbers(path)


def _numbers(path):
    res = report.analyse(bagload.load_bag(path), crb=False)
    return {name: (v["n"], round(v["mean_euclid"], 12), round(v["rms"], 12), v["join"]["joined"])
            for name, v in res["algorithms"].items()}


def _library_messages(path):
    """(schema, channel, message) in file order, read by the mcap library alone."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        return list(make_reader(f).iter_messages(log_time_order=False))


# -- writers ------------------------------------------------------------------------------------
def _write_mcap(src, dst, compression, chunked=True, summary=True):
    """mcap's Writer registers each schema and channel when first used: with chunking they land
    inside chunks (the layout that broke our reader). summary=False: no summary section."""
    from mcap.writer import CompressionType, IndexType, Writer
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
    extra = {} if summary else dict(index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
                                    use_statistics=False, use_summary_offsets=False)
    with open(dst, "wb") as f:
        w = Writer(f, chunk_size=2000, compression=comp, use_chunking=chunked, **extra)
        w.start(profile="ros2", library="mcap python writer")
        sids, cids = {}, {}
        for schema, channel, msg in _library_messages(src):
            if schema.name not in sids:
                sids[schema.name] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.topic not in cids:
                cids[channel.topic] = w.register_channel(channel.topic, channel.message_encoding,
                                                         sids[schema.name], channel.metadata)
            w.add_message(cids[channel.topic], log_time=msg.log_time, data=msg.data,
                          publish_time=msg.publish_time, sequence=msg.sequence)
        w.finish()


def _write_mcap_ros2(src, dst):
    """mcap-ros2-support: decodes each message with its schema and serializes it again."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from mcap_ros2.writer import Writer
    with open(src, "rb") as f, open(dst, "wb") as out:
        w = Writer(out, chunk_size=2000)
        schemas = {}
        for schema, channel, msg, obj in make_reader(f, decoder_factories=[DecoderFactory()]) \
                .iter_decoded_messages(log_time_order=False):
            if schema.name not in schemas:
                schemas[schema.name] = w.register_msgdef(schema.name, schema.data.decode())
            w.write_message(channel.topic, schemas[schema.name], obj, log_time=msg.log_time,
                            publish_time=msg.publish_time, sequence=msg.sequence)
        w.finish()


def _write_rosbags(src, dst_dir):
    """rosbags' rosbag2 writer (storage plugin mcap): a bag directory; returns its .mcap."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    with Writer(dst_dir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for schema, channel, msg in _library_messages(src):
            if channel.topic not in conns:
                conns[channel.topic] = w.add_connection(channel.topic, schema.name,
                                                        msgdef=schema.data.decode(),
                                                        rihs01=channel.metadata.get("topic_type_hash", ""))
            w.write(conns[channel.topic], msg.log_time, msg.data)
    found = sorted(Path(dst_dir).glob("*.mcap"))
    assert len(found) == 1, found
    return found[0]


def _layout(path):
    """(compressions of the chunks, Schema/Channel records inside chunks, summary present),
    seen by the mcap library's stream reader."""
    from mcap.records import Channel, Chunk, Footer, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk
    comps, inside, summary = set(), 0, None
    with open(path, "rb") as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                comps.add(rec.compression)
                inside += sum(isinstance(r, (Schema, Channel)) for r in breakup_chunk(rec))
            elif isinstance(rec, Footer):
                summary = rec.summary_start != 0
    return comps, inside, summary


def _check_copy(copy, contract_bag, capsys, tmp_path):
    src, numbers = contract_bag
    assert _numbers(copy) == numbers
    with BagReader(src) as a, BagReader(copy) as b:
        assert {t: v for t, v in b.topics().items()} == a.topics()
        for topic in ("/wfs/true_slopes", "/cog/slopes"):
            sa, xa = a.images(topic)
            sb, xb = b.images(topic)
            np.testing.assert_array_equal(sb, sa)
            np.testing.assert_array_equal(xb, xa)
        assert [t for _, t in b.strings("/cog/centroider")] == [t for _, t in a.strings("/cog/centroider")]
    assert cli.main(["inspect", str(copy)]) == 0
    text = capsys.readouterr().out
    assert "/cog/slopes" in text and "tcog" in text
    assert cli.main(["report", str(copy), "--out", str(tmp_path / "rep")]) == 0
    text = capsys.readouterr().out
    assert "cog:tcog" in text and "cmf" in text


@pytest.mark.parametrize("compression,chunked,summary", [
    (c, True, s) for c in ("zstd", "lz4", "none") for s in (True, False)] + [
    ("none", False, True), ("none", False, False)])      # compression applies to chunks only
def test_mcap_writer_bags(contract_bag, tmp_path, capsys, compression, chunked, summary):
    copy = tmp_path / "mcap_writer.mcap"
    _write_mcap(contract_bag[0], copy, compression, chunked, summary)
    comps, inside, has_summary = _layout(copy)
    assert has_summary == summary
    if chunked:                                  # the layouts under test really are there
        assert comps == {"" if compression == "none" else compression} and inside >= 8
    else:
        assert comps == set()
    _check_copy(copy, contract_bag, capsys, tmp_path)


def test_mcap_ros2_support_bag(contract_bag, tmp_path, capsys):
    copy = tmp_path / "mcap_ros2.mcap"
    _write_mcap_ros2(contract_bag[0], copy)
    assert _layout(copy)[1] >= 8
    _check_copy(copy, contract_bag, capsys, tmp_path)


def test_rosbags_bag(contract_bag, tmp_path, capsys):
    copy = _write_rosbags(contract_bag[0], tmp_path / "rosbags_bag")
    with BagReader(copy) as r:
        assert "rosbags" in r.library
    _check_copy(copy, contract_bag, capsys, tmp_path)


def test_channel_defined_in_an_unwanted_chunk(tmp_path):
    """The bug of issue 17: a topic's Channel record sits in a chunk holding only another
    topic's messages; reading that topic alone must still know the channel."""
    from mcap.writer import Writer
    from lgs_wfs_ros.bags import encode_string, message_definition
    p = tmp_path / "split.mcap"
    with open(p, "wb") as f:
        w = Writer(f, chunk_size=1)                 # one message per chunk
        w.start(profile="ros2", library="t")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", message_definition("std_msgs/msg/String").encode())
        a = w.register_channel("/a", "cdr", sid)
        b = w.register_channel("/b", "cdr", sid)     # defined now, first message much later
        for i in range(5):
            w.add_message(a, log_time=i, data=encode_string(f"a{i}"), publish_time=i)
        for i in range(3):
            w.add_message(b, log_time=10 + i, data=encode_string(f"b{i}"), publish_time=10 + i)
        w.finish()
    assert _layout(p)[1] == 3                        # schema and both channels in chunk 1
    with BagReader(p) as r:
        assert [t for _, t in r.strings("/b")] == ["b0", "b1", "b2"]
        assert [t for _, t in r.strings("/a")] == [f"a{i}" for i in range(5)]


# -- rosbag2's own bags --------------------------------------------------------------------------
def test_rosbag2_fixtures_are_there():
    assert {p.name for p in FIXTURES} == {"talker.mcap", "cdr_test_0.mcap", "only_services.mcap"}
    assert (ROSBAG2 / "LICENSE").read_text().lstrip().startswith("Apache License")


@pytest.mark.parametrize("path", FIXTURES, ids=lambda p: p.name)
def test_rosbag2_fixture_reads_like_the_mcap_library(path):
    expected = _library_messages(path)
    with BagReader(path) as r:
        assert r.complete and not r.problems
        got = list(r.messages())
        counts = {t: n for t, (_, n) in r.topics().items()}
    assert [(t, log, pub, data) for t, _, log, pub, data in got] == \
        [(c.topic, m.log_time, m.publish_time, m.data) for _, c, m in expected]
    assert [ty for _, ty, _, _, _ in got] == [s.name for s, _, _ in expected]
    lib = {}
    for _, c, _ in expected:
        lib[c.topic] = lib.get(c.topic, 0) + 1
    assert {t: n for t, n in counts.items() if n} == lib


def test_rosbag2_talker_strings():
    """talker.mcap (mcap go, zstd): its std_msgs/String messages decode as mcap-ros2 does."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path = ROSBAG2 / "talker.mcap"
    with open(path, "rb") as f:
        want = [obj.data for _, c, _, obj in make_reader(f, decoder_factories=[DecoderFactory()])
                .iter_decoded_messages(topics=["/topic"], log_time_order=False)]
    with BagReader(path) as r:
        got = [t for _, t in r.strings("/topic")]
    assert got == want and len(got) == 10 and got[0].startswith("Hello")


@pytest.mark.parametrize("path", FIXTURES, ids=lambda p: p.name)
def test_rosbag2_fixture_inspect_and_report(path, capsys, tmp_path):
    """inspect describes the bag; report says what the bag lacks (exit 2, one line)."""
    assert cli.main(["inspect", str(path)]) == 0
    text = capsys.readouterr().out
    info = bag_info(path)
    for topic, v in info["topics"].items():
        assert topic in text
    assert "not an lgs_wfs_ros contract bag" in text
    assert cli.main(["inspect", "--json", str(path)]) == 0
    assert json.loads(capsys.readouterr().out)["topics"] == json.loads(json.dumps(info["topics"]))
    code = cli.main(["report", str(path), "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    line, = err.strip().splitlines()
    assert "true_slopes" in line and "slopes" in line and "it has:" in line
    with pytest.raises(BagError, match="true_slopes"):
        bagload.load_bag(path)
