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
