"""Bags carry names, not paths (issue 17 item 7): bags.portable and the contract writer."""

import json

import numpy as np

from lgs_wfs_ros.analysis import bagwrite
from lgs_wfs_ros.bags import BagReader, encode_image, encode_string
from lgs_wfs_ros.bags.portable import is_path, portable, portable_cdr, scrub_bag
from lgs_wfs_ros.sensor import Sensor

ANN = {"algorithm": "ann", "options": {"model": "ann_1k"}, "model_path": "/home/someone/lgs/models/ann_1k.onnx",
       "model_sha256": "ab" * 32, "n_valid": 1,
       "training": {"data": "/tmp/run3/train.npz", "topic": "/wfs/frame", "note": "see /wfs/sensor"}}


def test_is_path_tells_files_from_ros_names():
    assert is_path("/work/main/models/ann_1k.onnx") and is_path("/tmp/x.npz")
    assert not is_path("/wfs/frame") and not is_path("/cog/centroider") and not is_path("ann_1k.onnx")
    assert not is_path("models/ann_1k.onnx") and not is_path(3.0)


def test_portable_names_the_model_and_cuts_paths():
    out = portable(ANN)
    assert "model_path" not in out and out["model_file"] == "ann_1k.onnx"
    assert out["model_sha256"] == "ab" * 32 and out["options"] == {"model": "ann_1k"}
    assert out["training"] == {"data": "train.npz", "topic": "/wfs/frame", "note": "see /wfs/sensor"}
    assert "model" not in out                     # the options name it already
    bare = portable({"algorithm": "ann", "model_path": "/x/y/my_net.onnx"})
    assert bare == {"algorithm": "ann", "model_file": "my_net.onnx", "model": "my_net"}
    assert portable({"algorithm": "cog", "options": {}}) == {"algorithm": "cog", "options": {}}
    assert ANN["model_path"].startswith("/home")  # the input is not modified


def test_portable_cdr_touches_only_json_strings():
    img = encode_image(np.zeros((2, 2), np.uint16), 5)
    assert portable_cdr("sensor_msgs/msg/Image", img) is img
    plain = encode_string("/tmp/not json.txt")
    assert portable_cdr("std_msgs/msg/String", plain) is plain
    new = portable_cdr("std_msgs/msg/String", encode_string(json.dumps(ANN)))
    from lgs_wfs_ros.bags import decode_string
    assert json.loads(decode_string(new)) == portable(ANN)


def test_contract_writer_and_scrub_store_names(tmp_path):
    sensor = Sensor.paper_single("polar", dtype="float32")
    p = tmp_path / "w.mcap"
    with bagwrite.ContractBagWriter(p, sensor, log_ns=10, sensor_extra={"profiles": "/data/na/profiles.npz"}) as w:
        w.centroider("ann", ANN, 10)
        w.truth(20, np.zeros((1, 2)))
    with BagReader(p) as r:
        desc = json.loads(r.strings("/ann/centroider")[0][1])
        sens = json.loads(r.strings("/wfs/sensor")[0][1])
    assert desc == portable(ANN) and sens["profiles"] == "profiles.npz"
    # a bag written before (raw paths) is scrubbed; every other message is copied unchanged
    raw = tmp_path / "raw.mcap"
    from lgs_wfs_ros.bags import BagWriter
    with BagWriter(raw) as w:
        w.add_topic("/ann/centroider", "std_msgs/msg/String")
        w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
        w.write("/ann/centroider", encode_string(json.dumps(ANN)), 1)
        w.write("/wfs/frame", encode_image(np.arange(4, dtype=np.uint16).reshape(2, 2), 7), 2)
    stats = scrub_bag(raw, tmp_path / "clean.mcap")
    assert stats["messages"] == 2
    with BagReader(raw) as a, BagReader(tmp_path / "clean.mcap") as b:
        assert json.loads(b.strings("/ann/centroider")[0][1]) == portable(ANN)
        assert [m[1:] for m in b.messages(["/wfs/frame"])] == [m[1:] for m in a.messages(["/wfs/frame"])]
        assert b.channel_metadata("/wfs/frame") == a.channel_metadata("/wfs/frame")
