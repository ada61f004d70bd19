"""The shipped sample bags open, join completely and report, through the CLI as a user runs it."""

import json
from pathlib import Path

import pytest

from lgs_wfs_ros import bags
from lgs_wfs_ros.cli import main

BAGS = Path(__file__).resolve().parents[1] / "bags"


@pytest.mark.parametrize("name", ["sample.mcap", "sample_full_pupil.mcap"])
def test_sample_bag_reports(name, capsys, tmp_path):
    path = BAGS / name
    reader = bags.BagReader(path)
    topics = reader.topics()
    n_truth = topics["/wfs/true_slopes"][1]
    for ns in ("cog", "cmf", "ann"):
        assert topics[f"/{ns}/slopes"][1] == n_truth      # nothing lost while recording
    assert main(["inspect", str(path)]) == 0
    capsys.readouterr()
    assert main(["report", str(path), "--json", "--out", str(tmp_path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    text = json.dumps(summary)
    for alg in ("cog", "cmf", "ann"):
        assert alg in text
    assert (tmp_path / "summary.json").is_file()


def _strings(value):
    if isinstance(value, dict):
        for v in value.values():
            yield from _strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v)
    elif isinstance(value, str):
        yield value


@pytest.mark.parametrize("name", ["sample.mcap", "sample_full_pupil.mcap"])
def test_sample_bags_carry_names_not_paths(name):
    """Issue 17 item 7: no absolute file path of the machine that recorded them; a model is
    named with its SHA-256."""
    from lgs_wfs_ros.bags.portable import is_path
    with bags.BagReader(BAGS / name) as reader:
        texts = [t for topic, (ty, _) in reader.topics().items() if ty == "std_msgs/msg/String"
                 for _, t in reader.strings(topic)]
        texts += [v for _, d in reader.metadata() for v in d.values()]
        ann = json.loads(reader.strings("/ann/centroider")[-1][1])
    found = [s for t in texts for s in _strings(json.loads(t) if t.startswith("{") else t) if is_path(s)]
    assert not found
    assert not any("/work/" in t or "/home/" in t for t in texts)
    model = ann.get("model") or ann["options"]["model"]
    assert model in ("ann_1k", "ann_pupil") and ann["model_file"] == model + ".onnx"
    assert len(ann["model_sha256"]) == 64
