"""ONNX runner: metadata contract, normalisation, output scale and frame, conditioning,
model lookup and clear errors; models are tiny graphs built here with onnx.helper."""

import functools
import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.centroiding import options as table
from lgs_wfs_ros.centroiding.ann_model import resolve_model
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import sodium_line, spots

SENSOR = Sensor()
LAY = geometry.layout(SENSOR)
N = LAY.n_valid


def cog_weights(p=16):
    """``(p*p, 2)``: sum-normalised pixels @ W = centre of gravity from (p-1)/2."""
    y, x = np.indices((p, p), dtype=np.float32) - (p - 1) / 2
    return np.stack([x.ravel(), y.ravel()], axis=1)


def build(path, weights, meta, cond_width=None, input_name="pixels", batch="N", width=None):
    """Linear model ``out = pixels @ weights (+ e @ C)``, metadata JSON-encoded."""
    width = weights.shape[0] if width is None else width
    inputs = [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [batch, width])]
    inits = [numpy_helper.from_array(weights.astype(np.float32), "W")]
    nodes = [helper.make_node("MatMul", [input_name, "W"], ["lin"])]
    if cond_width:
        inputs.append(helper.make_tensor_value_info("e", TensorProto.FLOAT, [batch, cond_width]))
        c = np.zeros((cond_width, 2), np.float32)
        c[0, 0] = c[1, 1] = 1.0
        if cond_width > 2:
            c[2, 0] = 10.0
        inits.append(numpy_helper.from_array(c, "C"))
        nodes += [helper.make_node("MatMul", ["e", "C"], ["ec"]), helper.make_node("Add", ["lin", "ec"], ["out"])]
    else:
        nodes.append(helper.make_node("Identity", ["lin"], ["out"]))
    graph = helper.make_graph(nodes, "g", inputs,
                              [helper.make_tensor_value_info("out", TensorProto.FLOAT, [batch, 2])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in meta.items():
        model.metadata_props.add(key=f"lgs_wfs.{k}", value=json.dumps(v))
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


META = {"pixels": 16, "detector": "any", "input_norm": "sum", "output_scale": 1.0,
        "output_frame": "detector", "conditioning": "none", "training": {"note": "test"}}


def stack(seed=0, detector="cartesian"):
    rng = np.random.default_rng(seed)
    off, w = sodium_line(3.0, 11)
    e = LAY.e if detector == "cartesian" else np.tile([1.0, 0.0], (N, 1))
    return rng.poisson(spots(rng.uniform(-1, 1, (N, 2)), sigma=0.6, e=e, offsets=off, weights=w)).astype(np.float32)


def test_linear_model_reproduces_cog(tmp_path):
    path = build(tmp_path / "cog.onnx", cog_weights(), META)
    c = make_centroider("ann", SENSOR, model=str(path))
    st = stack()
    np.testing.assert_allclose(c.centroid(st), make_centroider("cog", SENSOR).centroid(st), atol=1e-5)
    d = c.describe()
    json.dumps(d)
    assert d["model"] == "cog" and d["model_metadata"]["training"] == {"note": "test"}
    assert str(tmp_path) not in json.dumps(d) and len(d["model_sha256"]) == 64
    assert c.session.get_session_options().intra_op_num_threads == 1


def test_output_scale_and_no_normalisation(tmp_path):
    st = stack(1)
    tot = st.reshape(N, -1).sum(1)
    # input_norm "none": the model sees raw counts; here it divides by a constant 1000
    path = build(tmp_path / "raw.onnx", cog_weights() / 1000.0, dict(META, input_norm="none", output_scale=2.0))
    out = make_centroider("ann", SENSOR, model=str(path)).centroid(st)
    np.testing.assert_allclose(out, make_centroider("cog", SENSOR).centroid(st) * tot[:, None] / 1000 * 2, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("detector", ["cartesian", "polar"])
def test_local_output_frame_is_rotated(tmp_path, detector):
    sensor = SENSOR.replace(detector=detector)
    st = stack(2, detector)
    path = build(tmp_path / "loc.onnx", cog_weights(), dict(META, output_frame="local"))
    out = make_centroider("ann", sensor, model=str(path)).centroid(st)
    cog_pixel_axes = make_centroider("cog", SENSOR).centroid(st)     # block pixel axes
    np.testing.assert_allclose(out, geometry.local_to_detector(cog_pixel_axes, LAY.e), atol=1e-5)
    # "detector" output on a polar sensor: the model's numbers are used as they are
    path2 = build(tmp_path / "det.onnx", cog_weights(), META)
    out2 = make_centroider("ann", sensor, model=str(path2)).centroid(st)
    np.testing.assert_allclose(out2, cog_pixel_axes, atol=1e-5)


@pytest.mark.parametrize("cond, width", [("e", 2), ("e_r", 3)])
def test_conditioning_input_gets_e(tmp_path, cond, width):
    path = build(tmp_path / "c.onnx", np.zeros((256, 2)), dict(META, conditioning=cond), cond_width=width)
    out = make_centroider("ann", SENSOR, model=str(path)).centroid(stack(3))
    expect = np.array(LAY.e, dtype=float)
    if cond == "e_r":
        expect[:, 0] += 10 * LAY.r_m / 15.0
    np.testing.assert_allclose(out, expect, atol=1e-5)


def test_bad_subapertures_nan(tmp_path):
    path = build(tmp_path / "cog.onnx", cog_weights(), META)
    st = stack(4)
    st[5, 3, 3] = np.nan
    st[6] = 0
    out = make_centroider("ann", SENSOR, model=str(path)).centroid(st)
    assert np.isnan(out[[5, 6]]).all() and np.isfinite(np.delete(out, [5, 6], axis=0)).all()


def test_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        make_centroider("ann", SENSOR, model=str(tmp_path / "missing.onnx"))
    with pytest.raises(ValueError, match="not found"):
        make_centroider("ann", SENSOR, model="no_such_model_name")
    bad = tmp_path / "corrupt.onnx"
    bad.write_bytes(b"\x08\x01garbage" * 50)
    with pytest.raises(ValueError, match="cannot load"):
        make_centroider("ann", SENSOR, model=str(bad))
    p8 = build(tmp_path / "p8.onnx", cog_weights(8), dict(META, pixels=8))
    with pytest.raises(ValueError, match="8 x 8"):
        make_centroider("ann", SENSOR, model=str(p8))
    lie = build(tmp_path / "lie.onnx", cog_weights(8), META)          # says 16, takes 64 values
    with pytest.raises(ValueError, match="pixel-count mismatch"):
        make_centroider("ann", SENSOR, model=str(lie))
    pol = build(tmp_path / "pol.onnx", cog_weights(), dict(META, detector="polar"))
    with pytest.raises(ValueError, match="polar detector"):
        make_centroider("ann", SENSOR, model=str(pol))
    make_centroider("ann", SENSOR.replace(detector="polar"), model=str(pol))   # fine
    nometa = build(tmp_path / "nometa.onnx", cog_weights(), {k: v for k, v in META.items() if k != "pixels"})
    with pytest.raises(ValueError, match="lgs_wfs.pixels"):
        make_centroider("ann", SENSOR, model=str(nometa))
    badnorm = build(tmp_path / "badnorm.onnx", cog_weights(), dict(META, input_norm="max"))
    with pytest.raises(ValueError, match="input_norm"):
        make_centroider("ann", SENSOR, model=str(badnorm))
    nocond = build(tmp_path / "nocond.onnx", cog_weights(), dict(META, conditioning="e"))
    with pytest.raises(ValueError, match="conditioning"):
        make_centroider("ann", SENSOR, model=str(nocond))
    fixed = build(tmp_path / "fixed.onnx", cog_weights(), META, batch=7)
    with pytest.raises(ValueError, match="fixed batch"):
        make_centroider("ann", SENSOR, model=str(fixed))


def test_model_lookup_by_name(tmp_path, monkeypatch):
    d = tmp_path / "models"
    d.mkdir()
    build(d / "tiny_cog.onnx", cog_weights(), META)
    monkeypatch.setenv("LGS_WFS_MODELS", str(d))
    assert resolve_model("tiny_cog") == d / "tiny_cog.onnx"
    assert resolve_model("tiny_cog.onnx") == d / "tiny_cog.onnx"
    c = make_centroider("ann", SENSOR, model="tiny_cog")
    assert c.path == d / "tiny_cog.onnx"
    # the default models (ann_conv on polar pixels, ann_grid, read through whole-pixel
    # grid sums, on cartesian ones) ship with the package, so they resolve by name and
    # run inside their domain ...
    from lgs_wfs_ros.centroiding import ann, ann_model
    assert ann.DEFAULT_MODELS == {"polar": "ann_conv", "cartesian": "ann_grid"}
    for name in ann.DEFAULT_MODELS.values():
        assert resolve_model(name) == ann_model.model_dirs()[0] / f"{name}.onnx"
    for det, name, bins in (("polar", "ann_conv", None), ("cartesian", "ann_grid", "grid")):
        c = make_centroider("ann", Sensor(detector=det))
        assert c.model_name == name and c.describe()["domain"]["out_of_domain_subapertures"] == 0
        assert c.describe().get("bins_projection") == bins
    # ... and where no directory holds them, the error says so (both paths always run)
    monkeypatch.setattr(ann_model, "model_dirs", lambda: [tmp_path / "empty"])
    with pytest.raises(ValueError, match="'ann_grid' not found"):
        make_centroider("ann", SENSOR)
    with pytest.raises(ValueError, match="'tiny_cog' not found"):
        resolve_model("tiny_cog")


def test_folded_normalisation_equals_plain_path(tmp_path):
    """The graph with the sum normalisation folded in gives what dividing in numpy gives,
    on stacks and on frames (every block of the grid, then the valid ones), and bad
    subapertures still come out NaN."""
    from lgs_wfs_ros.centroiding.ann_model import TOTAL_OUTPUT, fold_sum_normalisation
    meta = dict(META, conditioning="e_r")
    path = build(tmp_path / "cog.onnx", cog_weights(), meta, cond_width=3)
    folded = fold_sum_normalisation(onnx.load(str(path)), "pixels", 256)
    assert TOTAL_OUTPUT in [o.name for o in folded.graph.output]
    onnx.checker.check_model(folded)
    c = make_centroider("ann", SENSOR, model=str(path))
    assert c.folded is not None
    x = stack(3)
    x[5] = 0
    frame = geometry.stack_to_frame(x.astype(np.uint16), LAY)
    fast_stack, fast_frame = c.centroid(x), c.centroid(frame)
    c.folded = None
    plain = c.centroid(x)
    np.testing.assert_allclose(fast_stack, plain, atol=1e-5, equal_nan=True)
    np.testing.assert_allclose(fast_frame, plain, atol=1e-5, equal_nan=True)
    assert np.isnan(fast_frame[5]).all() and np.isfinite(np.delete(fast_frame, 5, axis=0)).all()


def test_unfoldable_graph_keeps_the_plain_path(tmp_path):
    """A pixel input used by something other than one constant MatMul is not folded."""
    from lgs_wfs_ros.centroiding.ann_model import fold_sum_normalisation
    path = tmp_path / "relu_first.onnx"
    inputs = [helper.make_tensor_value_info("pixels", TensorProto.FLOAT, ["N", 256])]
    nodes = [helper.make_node("Relu", ["pixels"], ["r"]), helper.make_node("MatMul", ["r", "W"], ["out"])]
    graph = helper.make_graph(nodes, "g", inputs, [helper.make_tensor_value_info("out", TensorProto.FLOAT, ["N", 2])],
                              [numpy_helper.from_array(cog_weights(), "W")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in META.items():
        model.metadata_props.add(key=f"lgs_wfs.{k}", value=json.dumps(v))
    onnx.save(model, str(path))
    assert fold_sum_normalisation(model, "pixels", 256) is None
    c = make_centroider("ann", SENSOR, model=str(path))
    assert c.folded is None
    x = stack(4)
    np.testing.assert_allclose(c.centroid(x), make_centroider("cog", SENSOR).centroid(x), atol=1e-4)


@functools.lru_cache(maxsize=None)
def _built(name, options):
    """One centroider per (name, options) for the dtypes below: stateless with a static
    reference, and the full pupil's model CMF takes ~20 s to build."""
    return make_centroider(name, SENSOR, **dict(options))


@pytest.mark.parametrize("name,options", [("cog", {}), ("cmf", {"reference": "model", "weighting": "model"})])
@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.float64])
def test_frame_fast_path_equals_stack_path(name, options, dtype):
    """CoG and the model-weighted CMF cast a frame block by block in one pass; the
    answer is the one the valid-block stack gives."""
    c = _built(name, tuple(sorted(options.items())))
    x = stack(5).astype(dtype)
    frame = geometry.stack_to_frame(x, LAY)
    np.testing.assert_allclose(c.centroid(frame), c.centroid(x), atol=1e-6)


@pytest.mark.parametrize("trans_b", [0, 1])
def test_gemm_first_layer_is_folded_too(tmp_path, trans_b):
    """A model whose first layer is a Gemm (weights, bias, beta) folds to the same output."""
    rng = np.random.default_rng(7)
    w1 = rng.normal(0, 0.3, (256, 8)).astype(np.float32)
    b1 = rng.normal(0, 0.1, 8).astype(np.float32)
    w2 = rng.normal(0, 0.3, (8, 2)).astype(np.float32)
    nodes = [helper.make_node("Gemm", ["pixels", "W1", "B1"], ["h"], beta=0.5, transB=trans_b),
             helper.make_node("Tanh", ["h"], ["t"]), helper.make_node("MatMul", ["t", "W2"], ["out"])]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("pixels", TensorProto.FLOAT, ["N", 256])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, ["N", 2])],
        [numpy_helper.from_array(w1.T.copy() if trans_b else w1, "W1"), numpy_helper.from_array(b1, "B1"),
         numpy_helper.from_array(w2, "W2")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in META.items():
        model.metadata_props.add(key=f"lgs_wfs.{k}", value=json.dumps(v))
    path = tmp_path / "gemm.onnx"
    onnx.save(model, str(path))
    c = make_centroider("ann", SENSOR, model=str(path))
    assert c.folded is not None
    x = stack(8)
    frame = geometry.stack_to_frame(x.astype(np.uint16), LAY)
    fast, fast_frame = c.centroid(x), c.centroid(frame)
    c.folded = None
    plain = c.centroid(x)
    np.testing.assert_allclose(fast, plain, atol=1e-5)
    np.testing.assert_allclose(fast_frame, plain, atol=1e-5)


def test_bias_option_needs_a_reference_reading_model():
    """``bias`` resolves per model (auto: pupil for the marginals models, none for the
    others) and is refused, with the reason, where the model reads no reference."""
    polar = Sensor(detector="polar")
    assert table.build("ann", polar, {}).describe()["options"]["bias"] == "pupil"    # ann_conv
    assert table.build("ann", Sensor(detector="cartesian"), {}).describe()["options"]["bias"] == "pupil"
    assert table.build("ann", Sensor(detector="cartesian"), {"model": "ann_ref"}).describe()["options"]["bias"] == "none"
    one = Sensor.paper_single("polar")
    assert table.build("ann", one, {"model": "ann_1k"}).describe()["options"]["bias"] == "none"
    with pytest.raises(ValueError, match="reads none"):
        table.build("ann", one, {"model": "ann_1k", "bias": "pupil"})
    with pytest.raises(ValueError, match="bias"):
        table.build("ann", polar, {"bias": "yes"})


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_ann_on_a_frame_equals_the_stack_path(tmp_path, dtype):
    """A folded network on a whole frame (an integer frame: the valid blocks cut and cast by
    the compiled pass; a float one: the whole block grid) gives what the valid-block stack
    gives, a dark block NaN; the compiled pass must place each block where the layout says
    (a block read from the wrong place moves its centroid by pixels)."""
    path = build(tmp_path / "cog.onnx", cog_weights(), META)
    c = make_centroider("ann", SENSOR, model=str(path))
    assert c.folded is not None
    x = np.rint(stack(5) * 100).astype(dtype)
    x[7] = 0
    frame = geometry.stack_to_frame(x, LAY)
    got = c.centroid(frame)
    want = c.centroid(x.astype(np.float32))
    assert np.isnan(got[7]).all() and np.isnan(want[7]).all()
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(got, make_centroider("cog", SENSOR).centroid(x), atol=1e-4)
