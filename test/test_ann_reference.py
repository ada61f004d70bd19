"""ann with a reference-reading model: references from the pupil calibration, exactly as
cog's / cmf's pupil reference; graph split so the reference enters once per refit."""

import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from lgs_wfs_ros.centroiding import make_centroider, options
from lgs_wfs_ros.centroiding.ann_model import split_reference
from lgs_wfs_ros.learning import reftrain
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from pupils import SMALL

P = 16


def cog_matrix():
    y, x = np.indices((P, P), dtype=np.float32) - (P - 1) / 2
    return np.stack([x.ravel(), y.ravel()], axis=1)


def linear_reference_model(path, domain=None):
    """out = CoG(pixels) - CoG(reference), block axes: what cog with bias = pupil computes."""
    w = cog_matrix()
    g = helper.make_graph(
        [helper.make_node("MatMul", ["pixels", "Wp"], ["a"]),
         helper.make_node("MatMul", ["reference", "Wr"], ["b"]),
         helper.make_node("Add", ["a", "b"], ["slopes"])], "lin",
        [helper.make_tensor_value_info("pixels", TensorProto.FLOAT, ["batch", P * P]),
         helper.make_tensor_value_info("reference", TensorProto.FLOAT, ["batch", P * P])],
        [helper.make_tensor_value_info("slopes", TensorProto.FLOAT, ["batch", 2])],
        [numpy_helper.from_array(w, "Wp"), numpy_helper.from_array(-w, "Wr")])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    dom = domain or {"radius_m": [0.0, 40.0], "detector": ["polar", "cartesian"], "photons": [100, 3000],
                     "profile_prior": "test", "input": "image+reference"}
    meta = {"lgs_wfs.pixels": P, "lgs_wfs.input_norm": "sum", "lgs_wfs.conditioning": "reference",
            "lgs_wfs.conditioning_input": "reference", "lgs_wfs.output_frame": "block",
            "lgs_wfs.domain": dom}
    helper.set_model_props(m, {k: json.dumps(v) for k, v in meta.items()})
    onnx.save(m, str(path))
    return path


def frames(sensor, n, seed=0):
    """Poisson frames of a 12 km layer at 92 km (not the calibration's 10 km prior) with
    random tilts."""
    from lgs_wfs_ros.optics.sodium import gaussian_profile
    from lgs_wfs_ros.optics.spots import SpotModel
    lay = geometry.layout(sensor)
    h = np.linspace(70e3, 120e3, 1001)
    rng = np.random.default_rng(seed)
    model = SpotModel(sensor, lay.r_m, lay.e, h, gaussian_profile(h, 92e3, 12e3), max_shift_px=1.5)
    out = []
    for _ in range(n):
        img, _ = model.images(rng.normal(0, 0.3, (lay.n_valid, 2)))
        img = img / img.reshape(lay.n_valid, -1).sum(axis=1)[:, None, None]
        out.append(geometry.stack_to_frame(rng.poisson(img * 1000).astype(np.uint16), lay))
    return out


def beside_calibrated_cog(sensor, model, bias="auto"):
    """``(ann with model, cog with bias = pupil, plain cog)``, the two calibrated ones
    refitting every 3 frames with no averaging, neither linearized: what a linear model is
    checked against."""
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.0}
    return (options.build("ann", sensor, {"model": str(model), "bias": bias, "linearize": False, **pup}),
            options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup}),
            options.build("cog", sensor, {}))


@pytest.mark.parametrize("det,bias", [("polar", "auto"), ("cartesian", "auto"), ("cartesian", "pupil")])
def test_linear_reference_model_is_the_pupil_calibrated_cog(tmp_path, det, bias):
    """Through a refit (period 3), frame by frame and on stacks, ann with the linear model
    equals cog with bias = pupil: the same references, installed at the same frame (the
    model reads its own reference as 0, so ``bias: pupil`` changes nothing)."""
    sensor = SMALL.replace(detector=det, launch_xy_m=(16.0, 0.0))
    ann, cog, plain = beside_calibrated_cog(sensor, linear_reference_model(tmp_path / "lin.onnx"), bias)
    lay = geometry.layout(sensor)
    for k, f in enumerate(frames(sensor, 7)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)        # frame and stack paths
        a, c, p = ann.centroid(data), cog.centroid(data), plain.centroid(data)
        np.testing.assert_allclose(a, c, atol=2e-4)
        if k >= 3:                      # after the first refit the reference is not the prior
            assert np.abs(a - p).mean() > 0.01
    assert ann.describe()["pupil_calibration"]["fits"] == 2
    ann.reset()
    assert ann.describe()["pupil_calibration"]["fits"] == 0


def test_split_reference_moves_the_reference_product_out_of_the_graph(tmp_path):
    m = onnx.load(str(linear_reference_model(tmp_path / "lin.onnx")))
    split, w = split_reference(m, "reference")
    assert np.allclose(w, -cog_matrix())
    assert [i.name for i in split.graph.input] == ["pixels", "reference_code"]
    assert all(n.op_type != "MatMul" or "reference" not in n.input for n in split.graph.node)
    bad = onnx.load(str(tmp_path / "lin.onnx"))
    bad.graph.node[1].op_type = "Add"
    with pytest.raises(ValueError, match="one MatMul"):
        split_reference(bad, "reference")


def test_reference_model_outside_its_domain_refuses(tmp_path):
    path = linear_reference_model(tmp_path / "lin.onnx",
                                  {"radius_m": [0.0, 20.0], "detector": ["polar"], "photons": [100, 3000],
                                   "profile_prior": "test", "input": "image+reference"})
    with pytest.raises(ValueError, match="trained at r = 0-20 m"):
        make_centroider("ann", Sensor(detector="polar", launch_xy_m=(16.0, 0.0)), model=str(path))


def test_reftrain_export_computes_the_trained_network():
    """The exported graph (pixel and reference branches) equals the MLP on
    (G (image - reference), G reference)."""
    from lgs_wfs_ros.learning import refdata
    from lgs_wfs_ros.learning.model import forward
    rng = np.random.default_rng(3)
    layers = [(rng.normal(0, 0.05, (512, 8)), rng.normal(0, 0.1, 8)),
              (rng.normal(0, 0.3, (8, 2)), rng.normal(0, 0.1, 2))]
    model = reftrain.build_model(layers, P, 256.0, {})
    pairs = refdata.pairs(np.random.default_rng(4), 64)
    want = forward(layers, reftrain.features(pairs, 256.0).astype(np.float64))
    np.testing.assert_allclose(reftrain.predict(model, pairs), want, rtol=1e-4, atol=1e-4)
