"""ann with a hyper marginals model (``lgs_wfs.hyper``): the reference sets per-subaperture
filters once per calibration refit (``learning/hypertrain.py``), the frame part reads them."""

import json

import numpy as np
import pytest
from onnx import TensorProto, helper, numpy_helper

from lgs_wfs_ros.centroiding import ann_model as ann_mod
from lgs_wfs_ros.centroiding import options
from lgs_wfs_ros.learning import margtrain, refdata
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from test_ann_marginals import DOMAIN
from test_ann_reference import P, frames
from pupils import SMALL


def linear_hyper_model(path, hyper=True, inp="marginals"):
    """A hyper model that is the pupil-calibrated CoG along block x: one filter, the pixel
    positions (whatever the reference), bias minus the reference's CoG."""
    u = ((np.arange(P) - (P - 1) / 2)).astype(np.float32)
    inits = [numpy_helper.from_array(u.reshape(1, 1, P), "W"),
             numpy_helper.from_array(-u.reshape(P, 1), "Wb"),
             numpy_helper.from_array(np.array([1], np.int64), "ax1"),
             numpy_helper.from_array(np.array([2], np.int64), "ax2"),
             numpy_helper.from_array(np.array([0.0], np.float32), "zero"),
             numpy_helper.from_array(np.array([1.0], np.float32), "one")]
    nodes = [helper.make_node("Mul", ["reference", "zero"], ["r0"]),
             helper.make_node("Unsqueeze", ["r0", "ax1"], ["r03"]),
             helper.make_node("Add", ["r03", "W"], ["filters"]),             # (n, 1, p)
             helper.make_node("MatMul", ["reference", "Wb"], ["fbias"]),     # (n, 1)
             helper.make_node("ReduceSum", ["marginals", "ax1"], ["total"], keepdims=1),
             helper.make_node("Max", ["total", "one"], ["safe"]),
             helper.make_node("Div", ["marginals", "safe"], ["unit"]),
             helper.make_node("Unsqueeze", ["unit", "ax2"], ["u3"]),
             helper.make_node("MatMul", ["filters", "u3"], ["z3"]),
             helper.make_node("Squeeze", ["z3", "ax2"], ["z"]),
             helper.make_node("Add", ["z", "fbias"], ["shift"])]
    g = helper.make_graph(nodes, "hyper_lin",
                          [helper.make_tensor_value_info("marginals", TensorProto.FLOAT, ["batch", P]),
                           helper.make_tensor_value_info("reference", TensorProto.FLOAT, ["batch", P])],
                          [helper.make_tensor_value_info("shift", TensorProto.FLOAT, ["batch", 1])], inits)
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    meta = {"lgs_wfs.pixels": P, "lgs_wfs.input": inp, "lgs_wfs.input_norm": "none",
            "lgs_wfs.conditioning": "reference", "lgs_wfs.conditioning_input": "reference",
            "lgs_wfs.input_name": "marginals", "lgs_wfs.output_frame": "block",
            "lgs_wfs.detector": "polar", "lgs_wfs.hyper": hyper, "lgs_wfs.domain": DOMAIN}
    helper.set_model_props(m, {k: json.dumps(v) for k, v in meta.items()})
    path.write_bytes(m.SerializeToString())
    return path


def test_linear_hyper_model_is_the_pupil_calibrated_cog(tmp_path):
    """Through refits (period 3), on frames and stacks, ann with the linear hyper model equals
    cog with bias = pupil (its bias alone; neither linearized): the refit part gets the calibration's references when it refits."""
    sensor = SMALL.replace(detector="polar", launch_xy_m=(16.0, 0.0))
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.0}
    ann = options.build("ann", sensor, {"model": str(linear_hyper_model(tmp_path / "h.onnx")),
                                        "linearize": False, **pup})
    cog = options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup})
    plain = options.build("cog", sensor, {})
    assert ann._refit is not None and set(ann.cond[1]) == {"filters", "fbias"}
    lay = geometry.layout(sensor)
    for k, f in enumerate(frames(sensor, 7)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)
        a, c, p = ann.centroid(data), cog.centroid(data), plain.centroid(data)
        np.testing.assert_allclose(a, c, atol=2e-4)
        if k >= 3:
            assert np.abs(a - p).mean() > 0.01
    assert ann.describe()["pupil_calibration"]["fits"] == 2
    ann.reset()
    np.testing.assert_allclose(ann.centroid(frames(sensor, 1, seed=5)[0]),
                               options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup}).centroid(
                                   frames(sensor, 1, seed=5)[0]), atol=2e-4)


def test_split_hyper_parts_compute_the_whole_graph(tmp_path):
    path = linear_hyper_model(tmp_path / "h.onnx")
    import onnx
    model = onnx.load(str(path))
    refit, frame = ann_mod.split_hyper(model, "reference", ["filters", "fbias"])
    assert [i.name for i in refit.graph.input] == ["reference"]
    assert sorted(i.name for i in frame.graph.input) == ["fbias", "filters", "marginals"]
    rng = np.random.default_rng(1)
    marg = rng.poisson(50, (9, P)).astype(np.float32)
    ref = rng.random((9, P)).astype(np.float32)
    ref /= ref.sum(axis=1, keepdims=True)
    whole = ann_mod.open_session(model.SerializeToString()).run(None, {"marginals": marg, "reference": ref})[0]
    f, b = ann_mod.open_session(refit.SerializeToString()).run(["filters", "fbias"], {"reference": ref})
    part = ann_mod.open_session(frame.SerializeToString()).run(
        None, {"marginals": marg, "filters": f, "fbias": b})[0]
    np.testing.assert_allclose(part, whole, rtol=1e-6)


@pytest.mark.parametrize("templates", [(), (-0.5, 0.5)])
def test_compiled_first_layer_gives_the_whole_graphs_shifts(templates, tmp_path):
    """A model that names its trunk (``lgs_wfs.hyper_trunk``, written by hypertrain's export)
    runs its filters in ``kernels.hyper_contract`` and the rest in onnxruntime: the same
    slopes as the whole frame graph, through refits, NaN frames included."""
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.centroiding import kernels
    from lgs_wfs_ros.learning import export, hypertrain
    spec = hypertrain.HyperSpec(k=4, conv=(8,), trunk=(6,), templates=templates, head_scale=1.0)
    net = hypertrain._torch_module(spec)
    with torch.no_grad():
        for prm in net.parameters():
            prm.normal_(0.0, 0.3)
    path = export.save(hypertrain.build_model(net, spec, {"lgs_wfs.domain": DOMAIN}), tmp_path / "c.onnx")
    sensor = SMALL.replace(detector="polar", photons=300.0)
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.02}
    fast = options.build("ann", sensor, {"model": str(path), **pup})
    whole = options.build("ann", sensor, {"model": str(path), **pup})
    whole._trunk = None
    assert fast._trunk is not None
    fr = frames(sensor, 7)
    bad = fr[4].astype(np.float32)
    bad[:20] = np.nan
    for f in [*fr[:4], bad, *fr[4:]]:
        a, b = fast.centroid(f), whole.centroid(f)
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
        assert np.isfinite(a).mean() > 0.9
    assert fast.describe()["pupil_calibration"]["fits"] >= 2
    # the kernel and its numpy form agree, NaN rows stay NaN
    rng = np.random.default_rng(3)
    x = rng.poisson(40, (5, P)).astype(np.float32)
    x[1] = 0.0
    x[2, 3] = np.nan
    f, c = rng.normal(size=(5, 3, P)).astype(np.float32), rng.normal(size=(5, 3)).astype(np.float32)
    z, safe = kernels.hyper_contract(x, f, c)
    tot = x.sum(axis=1, keepdims=True)
    want = np.einsum("nkp,np->nk", f, x) / np.maximum(tot, 1.0) + c
    np.testing.assert_allclose(z[[0, 1, 3, 4]], want[[0, 1, 3, 4]], rtol=1e-5, atol=1e-6)
    assert np.isnan(z[2]).all() and np.isnan(safe[2, 0]) and safe[1, 0] == 1.0


def linear_pixel_hyper_model(path, trunk=True):
    """A cartesian hyper model on whole blocks that is cog with bias = pupil: two filters,
    the pixels' x and y (whatever the reference), bias minus the reference's CoG; with
    ``trunk`` it names its first layer (``zc``, ``safe``) for the compiled pass."""
    c = np.arange(P) - (P - 1) / 2
    xy = np.stack([np.tile(c, P), np.repeat(c, P)]).astype(np.float32)        # (2, p*p)
    inits = [numpy_helper.from_array(xy[None], "W"), numpy_helper.from_array(-xy.T.copy(), "Wb"),
             numpy_helper.from_array(np.array([1], np.int64), "ax1"),
             numpy_helper.from_array(np.array([0.0], np.float32), "zero"),
             numpy_helper.from_array(np.array([1.0], np.float32), "one")]
    nodes = [helper.make_node("Mul", ["reference", "zero"], ["r0"]),
             helper.make_node("Unsqueeze", ["r0", "ax1"], ["r03"]),
             helper.make_node("Add", ["W", "r03"], ["filters"]),              # (n, 2, p*p)
             helper.make_node("MatMul", ["reference", "Wb"], ["fbias"]),      # (n, 2)
             helper.make_node("ReduceSum", ["image", "ax1"], ["total"], keepdims=1),
             helper.make_node("Max", ["total", "one"], ["safe"]),
             helper.make_node("Div", ["image", "safe"], ["unit"]),
             helper.make_node("Einsum", ["filters", "unit"], ["zu"], equation="nkp,np->nk"),
             helper.make_node("Add", ["zu", "fbias"], ["zc"]),
             helper.make_node("Mul", ["safe", "zero"], ["s0"]),
             helper.make_node("Add", ["zc", "s0"], ["shift"])]
    g = helper.make_graph(nodes, "hyper_pix",
                          [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", P * P]),
                           helper.make_tensor_value_info("reference", TensorProto.FLOAT, ["batch", P * P])],
                          [helper.make_tensor_value_info("shift", TensorProto.FLOAT, ["batch", 2])], inits)
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    meta = {"lgs_wfs.pixels": P, "lgs_wfs.input": "pixels", "lgs_wfs.input_norm": "none",
            "lgs_wfs.conditioning": "reference", "lgs_wfs.conditioning_input": "reference",
            "lgs_wfs.input_name": "image", "lgs_wfs.output_frame": "block",
            "lgs_wfs.detector": "cartesian", "lgs_wfs.hyper": True,
            "lgs_wfs.domain": {**DOMAIN, "detector": ["cartesian"], "input": "image+reference"}}
    if trunk:
        meta["lgs_wfs.hyper_trunk"] = {"z": "zc", "total": "safe"}
    helper.set_model_props(m, {k: json.dumps(v) for k, v in meta.items()})
    path.write_bytes(m.SerializeToString())
    return path


@pytest.mark.parametrize("trunk", [True, False])
def test_pixel_hyper_model_reads_whole_blocks_on_a_cartesian_detector(trunk, tmp_path):
    """A hyper model on whole blocks (cartesian; ``benchmarks/cartesian_filters.py`` exports
    them): its filters come from the calibration's reference images at each refit, the
    frame goes through them (compiled, or the whole frame graph) and the slopes equal cog
    with bias = pupil through refits, on frames and stacks; a block without light is NaN."""
    sensor = SMALL.replace(detector="cartesian", launch_xy_m=(16.0, 0.0))
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.0}
    ann = options.build("ann", sensor, {"model": str(linear_pixel_hyper_model(tmp_path / "p.onnx", trunk)), **pup})
    cog = options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup})
    plain = options.build("cog", sensor, {})
    assert (ann._trunk is not None) == trunk and not ann.marginals
    lay = geometry.layout(sensor)
    for k, f in enumerate(frames(sensor, 7)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)
        if k == 5:
            data = geometry.frame_to_stack(f, lay).copy()
            data[7] = 0
        a, c, p = ann.centroid(data), cog.centroid(data), plain.centroid(data)
        np.testing.assert_allclose(a, c, atol=2e-4)
        if k >= 3:
            assert np.abs(a - p)[np.isfinite(p)].mean() > 0.01
        if k == 5:
            assert np.isnan(a[7]).all() and np.isfinite(np.delete(a, 7, axis=0)).all()
    assert ann.describe()["pupil_calibration"]["fits"] == 2


def test_hyper_metadata_is_checked(tmp_path):
    with pytest.raises(ValueError, match="hyper"):
        ann_mod.read_metadata({"lgs_wfs.pixels": "16", "lgs_wfs.hyper": "true"})
    with pytest.raises(ValueError, match="true or false"):
        ann_mod.read_metadata({"lgs_wfs.pixels": "16", "lgs_wfs.hyper": '"yes"'})
    md = ann_mod.read_metadata({"lgs_wfs.pixels": "16"})
    assert md["hyper"] is False and md["hyper_trunk"] is None
    with pytest.raises(ValueError, match="hyper_trunk"):
        ann_mod.read_metadata({"lgs_wfs.pixels": "16", "lgs_wfs.hyper_trunk": '{"z": "zc"}'})


@pytest.mark.parametrize("conv", [(), (8, 8)])
def test_hypertrain_export_computes_the_trained_network(conv):
    """The exported graph (refit and frame parts, template rows and their N^a gains) equals
    the torch module on real polar spots, with the dense and the convolutional hyper network."""
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.learning import hypertrain
    spec = hypertrain.HyperSpec(k=4, hyper=(8,), conv=conv, trunk=(6,), templates=(-0.5, 0.5),
                                head_scale=1.0)
    net = hypertrain._torch_module(spec)
    with torch.no_grad():                    # non-trivial gains and scales
        net.tgain.copy_(torch.tensor([0.3, -0.2]))
        net.tscale.copy_(torch.tensor([1.5, 0.7]))
        net.tbias.copy_(torch.tensor([0.1, -0.1]))
        net.wn.copy_(torch.linspace(-1, 1, 6))
        if conv:                             # gains and biases from the pooled channels
            net.pool.weight.normal_(0.0, 0.5)
            net.pool.bias.normal_(0.0, 0.5)
    pairs = refdata.marginal_pairs(np.random.default_rng(4), 32)
    u, r, lf, _ = hypertrain._tensors(pairs)
    with torch.no_grad():
        want = net(u, r, lf).numpy()
    model = hypertrain.build_model(net, spec, {})
    np.testing.assert_allclose(margtrain.predict(model, pairs), want, rtol=1e-4, atol=1e-4)


def test_conv_hyper_network_reads_the_spot_wherever_it_sits():
    """The convolutional hyper network's filters move with the reference and its biases do
    not: a spot and its reference moved together by whole pixels (away from the field's
    edges) give the same shift. The dense network's do not (its map knows the pixels)."""
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.learning import hypertrain
    pairs = refdata.marginal_pairs(np.random.default_rng(5), 64)
    # a compact spot on pixels 6-9, then the same moved by -2 and +2 px: the filters' reach
    # (3 px) and the pooled channels' (2 px) never see the zero padding beyond the field
    r = np.zeros((64, P), np.float32)
    r[:, 6:10] = pairs.refs[:, 6:10] + 1e-3
    r /= r.sum(axis=1, keepdims=True)
    m = np.zeros_like(r)
    m[:, 6:10] = pairs.marg[:, 6:10] + 1.0
    lf = torch.zeros(64, 1)

    def out(net, shift):
        u = torch.from_numpy(np.roll(m / m.sum(axis=1, keepdims=True), shift, axis=1))
        with torch.no_grad():
            return net(u, torch.from_numpy(np.roll(r, shift, axis=1)), lf).numpy()
    spread = {}
    for conv in ((), (8, 8)):
        net = hypertrain._torch_module(hypertrain.HyperSpec(k=4, hyper=(8,), conv=conv, trunk=(6,),
                                                            kernel=3, head_scale=1.0))
        with torch.no_grad():
            for prm in net.parameters():
                prm.normal_(0.0, 0.3)
        spread[conv] = max(np.abs(out(net, s) - out(net, 0)).max() for s in (-2, 2))
    assert spread[(8, 8)] < 1e-5
    assert spread[()] > 1e-2


@pytest.mark.parametrize("name", ["ann_marg", "ann_hyper", "ann_conv"])
def test_lgs_wfs_train_writes_the_marginal_models_record(name, tmp_path):
    """``lgs-wfs train`` of either marginal recipe (one training record built for both by
    ``margtrain.record``): the model carries its recipe, data, prior and check error, the
    card names it, and the centroider runs it on a polar pupil's frame."""
    pytest.importorskip("torch")
    from lgs_wfs_ros import cli
    from lgs_wfs_ros.learning import card, export
    assert cli.main(["train", name, "--out", str(tmp_path), "--samples", "1500", "--quick"]) == 0
    path = tmp_path / f"{name}.onnx"
    meta = export.read_metadata(path)
    rec = meta["lgs_wfs.training"]
    assert rec["samples"] == 1500 and rec["quick"] is True and rec["seed"] == 16
    assert rec["recipe"]["name"] == name and rec["parameters"] > 0 and rec["epochs_run"] >= 2
    assert rec["photons_range"] == list(refdata.MARGINAL_SPEC.photons)
    assert rec["check"]["n"] == margtrain.CHECK_N and rec["check"]["seed"] == margtrain.CHECK_SEED
    dets = tuple(rec["recipe"]["detectors"])             # ann_conv: both detectors
    pairs = margtrain.generate(margtrain.CHECK_N, margtrain.CHECK_SEED, progress=False, detectors=dets)
    along = np.abs(margtrain.predict(path, pairs) - pairs.y).mean()
    assert rec["check"]["mean_err_px"] == pytest.approx(along, rel=1e-3)   # what the model does
    assert ("spec" in rec) == (name != "ann_marg")
    if name == "ann_conv":                   # the recipe's refit network and loss reach the spec
        assert rec["spec"]["conv"] == [16, 16] and rec["spec"]["weight_power"] == 1.0
    assert meta["lgs_wfs.domain"] == margtrain.domain(refdata.MARGINAL_SPEC, detectors=dets)
    text = (tmp_path / "README.md").read_text()
    assert f"`{name}`" in text and text == card.render(tmp_path)
    sensor = Sensor(detector="polar", photons=1000.0)
    c = options.build("ann", sensor, {"model": str(path)})
    counts = np.random.default_rng(2).poisson(5.0, sensor.frame_shape).astype(np.uint16)
    assert np.isfinite(c.centroid(counts)).all()


def test_hypertrain_experiment_cli_caches_data_and_exports(tmp_path, monkeypatch, capsys):
    """``python -m lgs_wfs_ros.learning.hypertrain --generate``: the cached chunk holds
    ``margtrain.generate``'s own batches, files already there are kept, and the exported
    ONNX computes the trained network (its check error equals the torch one)."""
    pytest.importorskip("torch")
    from lgs_wfs_ros.learning import hypertrain
    monkeypatch.setattr(hypertrain, "CHUNK_BATCHES", 2)
    monkeypatch.setattr(hypertrain, "BATCH", 48)
    monkeypatch.setattr(hypertrain, "MONITOR_N", 200)
    monkeypatch.setattr(margtrain, "CHECK_N", 150)
    data, out = tmp_path / "data", tmp_path / "h.onnx"
    argv = ["--data", str(data), "--chunks", "1", "--k", "4", "--hyper", "8", "--trunk", "6",
            "--epochs", "2", "--out", str(out), "--generate"]
    hypertrain.main(argv)
    chunk = hypertrain.load_pairs(data / "train_000.npz")
    assert chunk.y.shape[0] == 96
    second = refdata.marginal_pairs(np.random.default_rng([16, 1]), 48)
    np.testing.assert_array_equal(chunk.marg[48:], second.marg)
    np.testing.assert_array_equal(chunk.y[48:], second.y)
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["samples"] == 96 and record["check"]["n"] == 150
    assert record["spec"]["k"] == 4 and record["recipe"]["sizes"] == [4, 6, 1]   # train's schema
    assert set(record) >= {"recipe_line", "profiles", "photons_range", "epochs_run", "weights"}
    assert record["check_onnx_mae_px"] == pytest.approx(record["check"]["mean_err_px"], abs=1e-4)
    assert out.with_suffix(".pt").exists()
    stamp = (data / "train_000.npz").stat().st_mtime_ns
    hypertrain.cache_data(data, 1)
    assert (data / "train_000.npz").stat().st_mtime_ns == stamp


def test_fisher_weight_is_the_inverse_square_of_the_bound():
    """hypertrain.fisher on a sampled Gaussian marginal of sigma s px with N photons is the
    Cramer-Rao information N / s^2 (to the sampling's few per cent), and scales with N."""
    from lgs_wfs_ros.learning import hypertrain
    x = np.arange(P) - 7.3
    rows = []
    for s in (1.5, 2.5):
        g = np.exp(-0.5 * (x / s) ** 2)
        rows.append(g / g.sum())
    refs = np.array(rows, np.float32)
    marg = np.array([refs[0] * 1000, refs[1] * 250], np.float32)
    pairs = refdata.MarginalPairs(marg, refs, np.zeros((2, 1), np.float32), np.ones(2), np.ones(2))
    info = hypertrain.fisher(pairs)
    np.testing.assert_allclose(info, [1000 / 1.5 ** 2, 250 / 2.5 ** 2], rtol=0.06)
