"""ann with a marginals model (polar): each block's row and column sums, one network row per
axis, references from the pupil calibration; and the compiled marginals kernel."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import kernels, make_centroider
from lgs_wfs_ros.learning import margtrain, refdata
from lgs_wfs_ros.learning.model import forward
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from test_ann_reference import P, beside_calibrated_cog, frames
from pupils import SMALL

DOMAIN = {"radius_m": [0.0, 40.0], "detector": ["polar"], "photons": [100, 3000],
          "profile_prior": "test", "input": "marginals+reference"}


def linear_marginal_model(path, log_weight=0.0, metadata=None):
    """One layer: shift = CoG(column sums) - CoG(reference's) (+ log_weight times the log
    feature): block x of cog with bias = pupil. ``metadata``: more ``lgs_wfs.*`` entries."""
    u = (np.arange(P) - (P - 1) / 2) / P
    w = np.zeros((2 * P + 1, 1))
    w[:P, 0] = u                                     # p (m / N - r) . u / p
    w[2 * P, 0] = log_weight
    model = margtrain.build_model([(w, np.zeros(1))], P, {"lgs_wfs.domain": DOMAIN, **(metadata or {})})
    import onnx
    onnx.save(model, str(path))
    return path


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_block_marginals_are_the_row_and_column_sums():
    sensor = Sensor(detector="polar")
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 65535, size=sensor.frame_shape).astype(np.uint16)
    o = kernels.block_origins(lay)
    stack = geometry.frame_to_stack(frame, lay).astype(np.float64)
    acc = np.ones((lay.n_valid, 2, P))
    m = kernels.block_marginals(frame, o, P, acc)
    np.testing.assert_array_equal(m[:, 0], stack.sum(axis=1))          # column sums: block x
    np.testing.assert_array_equal(m[:, 1], stack.sum(axis=2))
    np.testing.assert_array_equal(acc, 1 + m)
    np.testing.assert_array_equal(kernels.block_marginals(frame, o, P), m)


@pytest.mark.parametrize("bias", ["none", "pupil"])
@pytest.mark.parametrize("log_weight", [0.0, 0.7])
def test_linear_marginal_model_is_the_pupil_calibrated_cog(tmp_path, log_weight, bias):
    """Through refits (period 3), on frames (the compiled marginals) and stacks, ann with the
    linear marginal model equals cog with bias = pupil (block x from the network, block y
    the calibrated CoG of the row sums); the log-total input is the log10 of each block's
    counts (over 3, minus 0.8). With ``bias: pupil`` the model's reading of its noise-free
    reference is subtracted: here the log term at the calibration's flux."""
    sensor = SMALL.replace(detector="polar", launch_xy_m=(16.0, 0.0))
    ann, cog, plain = beside_calibrated_cog(
        sensor, linear_marginal_model(tmp_path / "marg.onnx", log_weight), bias=bias)
    assert ann.describe()["options"]["bias"] == bias
    lay = geometry.layout(sensor)
    for k, f in enumerate(frames(sensor, 7)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)
        a, c, p = ann.centroid(data), cog.centroid(data), plain.centroid(data)
        tot = geometry.frame_to_stack(f, lay).reshape(lay.n_valid, -1).sum(axis=1)
        extra = log_weight * (np.log10(tot) / 3 - margtrain.LOG_OFFSET)
        if bias == "pupil":                 # the reading of the reference at its flux
            flux = sensor.photons if ann.pupil.flux is None else ann.pupil.flux
            extra = extra - log_weight * (np.log10(flux) / 3 - margtrain.LOG_OFFSET)
        want = c + sensor_axes(sensor, extra)          # block x only
        np.testing.assert_allclose(a, want, atol=2e-4)
        if k >= 3:
            assert np.abs(a - p).mean() > 0.01
    assert ann.describe()["pupil_calibration"]["fits"] == 2
    assert ann.describe()["domain"]["out_of_domain_subapertures"] == 0


def sensor_axes(sensor, extra):
    """``extra (n,)`` along block x, as detector-axis slopes."""
    c = make_centroider("cog", sensor)
    return c.finish(np.stack([extra, 0 * extra], axis=1), np.ones(extra.size, bool))


def test_marginal_model_needs_a_polar_detector(tmp_path):
    path = linear_marginal_model(tmp_path / "marg.onnx")
    with pytest.raises(ValueError, match="polar"):
        make_centroider("ann", Sensor(detector="cartesian"), model=str(path))


def test_margtrain_export_computes_the_trained_network():
    """The exported graph (marginal, log-total and reference branches) equals the MLP on
    the features, for both axes of real polar spots."""
    rng = np.random.default_rng(3)
    layers = [(rng.normal(0, 0.2, (2 * P + 1, 8)), rng.normal(0, 0.1, 8)),
              (rng.normal(0, 0.3, (8, 1)), rng.normal(0, 0.1, 1))]
    model = margtrain.build_model(layers, P, {})
    pairs = refdata.marginal_pairs(np.random.default_rng(4), 32)
    assert pairs.marg.shape == (32, P) and pairs.y.shape == (32, 1)
    np.testing.assert_allclose(pairs.refs.sum(axis=1), 1.0, rtol=1e-5)
    want = forward(layers, margtrain.features(pairs.marg, pairs.refs).astype(np.float64))
    np.testing.assert_allclose(margtrain.predict(model, pairs), want, rtol=1e-4, atol=1e-4)
