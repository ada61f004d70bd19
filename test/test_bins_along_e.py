"""Bins along e with pixels split by overlap (centroiding/bins_along_e.py), and a marginals
model (ann_conv's kind) reading them on a cartesian detector."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import bins_along_e, kernels, make_centroider, options
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from test_ann_marginals import linear_marginal_model
from test_ann_reference import P, frames


def subpixel_projection(img, e, points=100_000, seed=0):
    """The bins by brute force: ``points`` uniform random points a pixel, each to the bin it
    falls in (a regular grid of points aliases at 45 deg)."""
    p = img.shape[0]
    rng = np.random.default_rng(seed)
    out = np.zeros(p)
    c = (p - 1) / 2
    for i, j in zip(*np.nonzero(img)):
        s = rng.random((points, 2)) - 0.5
        u = (j - c + s[:, 0]) * e[0] + (i - c + s[:, 1]) * e[1]
        out += img[i, j] * np.histogram(u, bins=p, range=(-p / 2, p / 2))[0] / points
    return out


def test_polar_bins_are_the_column_sums():
    rng = np.random.default_rng(0)
    img = rng.random((3, P, P))
    start, w = bins_along_e.overlap_weights(np.tile([1.0, 0.0], (3, 1)), P)
    np.testing.assert_allclose(bins_along_e.project(img.reshape(3, -1), start, w), img.sum(axis=1),
                               atol=1e-6)


@pytest.mark.parametrize("deg", [3.0, 22.5, 45.0, 117.0, 200.0])
def test_bins_split_each_pixel_by_its_overlap(deg):
    """At any angle, the bins equal a brute-force split of each pixel into random points
    (to its sampling noise), and light inside the bins' span is kept."""
    rng = np.random.default_rng(int(deg))
    e = np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])
    img = np.zeros((P, P))
    img[4:12, 3:13] = rng.random((8, 10))
    start, w = bins_along_e.overlap_weights(e[None], P)
    got = bins_along_e.project(img.reshape(1, -1), start, w)[0]
    want = subpixel_projection(img, e)
    np.testing.assert_allclose(got, want, atol=0.02 * img.max())
    assert got.sum() == pytest.approx(img.sum(), rel=1e-6)
    # whole pixels to the bin of their centre differ by far more
    assert np.abs(got - want).max() < 0.25 * np.abs(np.histogram(
        ((np.indices((P, P))[1] - 7.5) * e[0] + (np.indices((P, P))[0] - 7.5) * e[1]).ravel(),
        bins=P, range=(-P / 2, P / 2), weights=img.ravel())[0] - want).max()


def test_a_nan_pixel_makes_its_block_nan():
    start, w = bins_along_e.overlap_weights(np.array([[0.6, 0.8], [1.0, 0.0]]), P)
    flat = np.ones((2, P * P))
    flat[0, 5] = np.nan
    out = bins_along_e.project(flat, start, w)
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_compiled_bins_are_the_quantised_split_of_every_pixel():
    """The frame pass (corner pixels whose bins all lie outside included) gives the
    quantised split's bins, within 1/510 of each pixel's count of the exact split, and the
    block's moments exactly."""
    sensor = Sensor(detector="cartesian")
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(5)
    frame = rng.integers(0, 4000, size=sensor.frame_shape).astype(np.uint16)
    start, w = bins_along_e.overlap_weights(lay.e, P)
    s8, shares, wq = bins_along_e.quantised(start, w)
    bins, mom = kernels.block_bins(frame, kernels.block_origins(lay), P, s8, shares)
    flat = geometry.frame_to_stack(frame, lay).reshape(lay.n_valid, -1).astype(np.float64)
    np.testing.assert_allclose(bins, bins_along_e.project(flat, s8, wq), rtol=1e-5)
    exact = bins_along_e.project(flat, start, w)
    assert np.abs(bins - exact).max() <= 4000 * 3 * P / 510
    assert 0 < np.abs(bins - exact).max()
    y, x = np.indices((P, P))
    np.testing.assert_array_equal(mom, np.stack([flat.sum(1), flat @ x.ravel(), flat @ y.ravel()], 1))


def test_marginals_model_on_a_cartesian_detector_reads_bins_along_e(tmp_path):
    """A marginals model is refused on a cartesian detector by its domain guard (trained
    polar), and with out_of_domain = warn reads bins along e: the linear model (the CoG of
    its input less the reference's) gives along e the CoG of the spot's bins less that of
    the calibrated reference's bins, and across e the calibrated CoG, through refits and on
    frames and stacks; all subapertures are counted outside the domain."""
    sensor = Sensor(detector="cartesian", launch_xy_m=(16.0, 0.0), photons=1000.0)
    path = linear_marginal_model(tmp_path / "marg.onnx")
    with pytest.raises(ValueError, match="polar detector; the sensor is cartesian"):
        make_centroider("ann", sensor, model=str(path))
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.0}
    ann = options.build("ann", sensor, {"model": str(path), "out_of_domain": "warn", **pup})
    cog = options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup})
    lay = geometry.layout(sensor)
    e = np.asarray(lay.e)
    v = np.stack([-e[:, 1], e[:, 0]], axis=1)
    start, _, w = bins_along_e.quantised(*bins_along_e.overlap_weights(e, P))   # the centroider's split
    pos = np.arange(P) - (P - 1) / 2

    def bins_cog(stack):
        b = bins_along_e.project(stack.reshape(lay.n_valid, -1), start, w)
        return b @ pos / b.sum(axis=1)

    for k, f in enumerate(frames(sensor, 7)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)
        ref = ann.pupil.counts()[0]                   # the references this frame is read against
        a, c = ann.centroid(data), cog.centroid(data)
        if k % 3 == 2:                                # a refit installed new ones on this frame
            ref = ann.pupil.counts()[0]
        stack = geometry.frame_to_stack(f, lay).astype(float)
        along = bins_cog(stack) - bins_cog(ref)
        np.testing.assert_allclose((a * e).sum(axis=1), along, atol=2e-4)
        np.testing.assert_allclose((a * v).sum(axis=1), (c * v).sum(axis=1), atol=2e-4)
        # not the column sums: along e the bins' CoG differs from the plain block CoG's
        assert np.abs((a - c) * e).sum(axis=1).mean() > 0.01
    d = ann.describe()
    assert d["domain"]["out_of_domain_subapertures"] == lay.n_valid
    assert "polar" in d["warning"]
