"""Shipped models: load, metadata contract, recorded check error reproduced (onnxruntime only)."""

import json
from pathlib import Path

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

from lgs_wfs_ros.centroiding import make_centroider  # noqa: E402
from lgs_wfs_ros.learning import dataset, export, recipes, train  # noqa: E402
from lgs_wfs_ros.sensor import Sensor  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "models"
SHIPPED = [n for n in recipes.SHIPPED if (MODELS / f"{n}.onnx").is_file()]
pytestmark = pytest.mark.skipif(not SHIPPED, reason="no shipped models in models/")


def test_all_shipped_models_present():
    assert sorted(SHIPPED) == sorted(recipes.SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_metadata_contract(name):
    path = MODELS / f"{name}.onnx"
    meta = export.read_metadata(path)
    rec = recipes.get(name)
    assert meta["lgs_wfs.pixels"] == 16
    assert meta["lgs_wfs.detector"] == rec.detector
    assert meta["lgs_wfs.input_norm"] == "sum"
    assert meta["lgs_wfs.output_scale"] == 1.0
    assert meta["lgs_wfs.conditioning"] == rec.conditioning
    assert meta["lgs_wfs.output_frame"] in ("local", "detector")
    tr = meta["lgs_wfs.training"]
    assert tr["recipe"]["name"] == name and tr["seed"] == rec.seed
    assert tr["photons"] == rec.photons and tr["parameters"] > 0
    assert tr["check"]["mean_err_px"] > 0
    sess = export.session(path)
    ins = {i.name: i.shape for i in sess.get_inputs()}
    assert ins[meta["lgs_wfs.input_name"]][1] == 256
    if rec.conditioning == "e_r":
        assert ins["e"][1] == 3
    else:
        assert len(ins) == 1
    # size: the paper's 4,146 weights, or the small full-pupil network
    assert path.stat().st_size < 200_000


@pytest.mark.parametrize("name", SHIPPED)
def test_recorded_check_error_is_reproduced(name):
    path = MODELS / f"{name}.onnx"
    rec = recipes.get(name)
    recorded = export.read_metadata(path)["lgs_wfs.training"]["check"]["mean_err_px"]
    got = train.check_error(path, rec)
    assert got == pytest.approx(recorded, rel=0.05, abs=0.003)


@pytest.mark.parametrize("name", SHIPPED)
def test_centroider_runs_model_on_its_sensor(name):
    """make_centroider('ann') on the training geometry beats a 0.3 px error at 1000 photons."""
    rec = recipes.get(name)
    det = "polar" if rec.detector == "any" else rec.detector
    sensor = Sensor.paper_single(det)
    c = make_centroider("ann", sensor, model=str(MODELS / f"{name}.onnx"))
    spec = dataset.DataSpec(sensor, photons=1000.0, sigma_px=0.46, profile_model="mvn")
    s = dataset.sample(spec, np.random.default_rng(123), 200)
    from lgs_wfs_ros.optics import geometry
    lay = geometry.layout(sensor)
    truth = geometry.local_to_detector(s.y.astype(float), lay.e) if det == "polar" else s.y
    est = np.array([c.centroid(img[None])[0] for img in s.images])
    err = np.linalg.norm(est - truth, axis=1).mean()
    assert err < 0.3


def test_readme_lists_every_shipped_model():
    text = (MODELS / "README.md").read_text()
    for name in SHIPPED:
        assert name in text
