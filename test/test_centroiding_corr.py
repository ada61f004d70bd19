"""Correlation centroiding: shift recovery, reference sources, peak fit, aotools parity."""

import numpy as np
import pytest
from aotools.image_processing import centroiders as aoc

from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.centroiding.correlation import _parabola_peak
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import sodium_line, spots

SENSOR = Sensor()
LAY = geometry.layout(SENSOR)
N = LAY.n_valid


def image_at_factory(sigma=1.0, length=0.0):
    off, w = sodium_line(length, 11) if length else ((0.0,), None)
    return lambda sh: spots(sh, sigma=sigma, e=LAY.e, offsets=off, weights=w)


@pytest.mark.parametrize("sigma, length, peak", [
    (1.0, 0.0, "gauss"), (1.0, 2.5, "gauss"), (0.8, 3.0, "gauss"),
    (2.0, 0.0, "parabola"), (2.0, 2.5, "parabola")])
def test_noise_free_shift_within_002px(sigma, length, peak):
    """3 x 3 peak fit; measured worst errors: gauss 1e-4 (sigma 1) to 2e-3 (sigma 0.8),
    0.034 for the 1.19 px core; parabola 0.024 at sigma 1.5, 0.048 at 1, 0.11 at the core."""
    image_at = image_at_factory(sigma, length)
    c = make_centroider("corr", SENSOR, reference="static", peak=peak)
    c.set_reference(image_at(np.zeros((N, 2))))
    shift = np.random.default_rng(0).uniform(-1, 1, (N, 2))
    np.testing.assert_allclose(c.centroid(image_at(shift)), shift, atol=0.02)
    # exactly zero for the reference itself
    np.testing.assert_allclose(c.centroid(image_at(np.zeros((N, 2)))), 0, atol=1e-9)


@pytest.mark.parametrize("peak", ["gauss", "parabola"])
def test_drift_reading_is_the_whole_maps_reading(peak):
    """The reading a refit's drift is followed with (the 3 x 3 lags around zero summed
    directly, the whole maps where their centre is not the largest) is the FFT maps' reading
    of the same noise-free spots: moved less than half a pixel, more (the maps' path), and
    the reference itself (zero)."""
    image_at = image_at_factory(1.0, 2.5)
    c = make_centroider("corr", SENSOR, reference="static", peak=peak)
    c.set_reference(image_at(np.zeros((N, 2))))
    rng = np.random.default_rng(4)
    shift = rng.uniform(-0.4, 0.4, (N, 2))
    shift[::7] = rng.uniform(0.7, 1.6, (len(shift[::7]), 2)) * rng.choice([-1, 1], (len(shift[::7]), 2))
    for s in (shift, np.zeros((N, 2))):
        counts = image_at(s)
        want = c._map_reading(counts + c.background)
        np.testing.assert_allclose(c._drift_reading(counts), want, atol=1e-10)
    assert np.abs(want).max() < 1e-9 and np.abs(c._map_reading(image_at(shift))).max() > 1.0


def test_peak_fit_is_exact_for_quadratics_and_gaussians():
    y, x = np.indices((32, 32), dtype=float)
    peaks = np.array([[16.3, 15.8], [10.0, 20.45], [3.49, 28.5]])
    q = [-(x - px) ** 2 - 2 * (y - py) ** 2 + 0.8 * (x - px) * (y - py) for px, py in peaks]
    np.testing.assert_allclose(_parabola_peak(np.stack(q) + 100), peaks, atol=1e-12)
    np.testing.assert_allclose(_parabola_peak(np.exp(np.stack(q) / 3), log=True), peaks, atol=1e-9)


def test_reference_from_the_cmf_and_history_mode():
    image_at = image_at_factory(1.0, 2.0)
    cmf = make_centroider("cmf", SENSOR, reference="history")
    frames = [image_at(np.full((N, 2), 0.1 * k)) for k in range(5)]
    for f in frames:
        cmf.centroid(f)
    corr = make_centroider("corr", SENSOR, reference="static")
    corr.set_reference(cmf.reference)
    mean_shift = 0.2                                     # mean of 0, 0.1, ..., 0.4
    out = corr.centroid(image_at(np.full((N, 2), 0.5)))
    np.testing.assert_allclose(out, 0.5 - mean_shift, atol=0.02)
    # history mode behaves like the CMF's: a stationary spot reads ~0
    h = make_centroider("corr", SENSOR, reference="history")
    for _ in range(3):
        out = h.centroid(frames[-1])
    np.testing.assert_allclose(out, 0, atol=1e-9)


def test_polar_rotation_and_model_reference():
    sensor = SENSOR.replace(detector="polar")
    c = make_centroider("corr", sensor, reference="model")
    ref = c.reference
    shift_det = np.random.default_rng(1).uniform(-0.5, 0.5, (N, 2))
    shift_loc = geometry.detector_to_local(shift_det, LAY.e)
    from lgs_wfs_ros.centroiding.reference import fourier_shift
    img = np.clip(fourier_shift(ref, shift_loc), 0, None)
    np.testing.assert_allclose(c.centroid(img), shift_det, atol=0.05)


@pytest.mark.parametrize("padding", [1, 2])
@pytest.mark.parametrize("threshold", [0.0, 0.3])
def test_matches_aotools_correlation_centroid(padding, threshold):
    """aotools.correlation_centroid: min subtracted, CoG of the (thresholded) correlation
    map, origin at index 0 of the fftshifted map whose zero lag is p/2 = 8: ours = aotools - 8."""
    rng = np.random.default_rng(2)
    n = 60
    sensor = Sensor.paper_single("cartesian")
    shift = rng.uniform(-1, 1, (n, 2))
    st = rng.poisson(spots(shift, sigma=1.0, photons=2000, background=3.0)).astype(float)
    ref = spots([0.0, 0.0], sigma=1.0, photons=2000)[0]
    expect = aoc.correlation_centroid(st.copy(), ref.copy(), threshold=threshold, padding=padding)
    c = make_centroider("corr", sensor, reference="static", peak="cog", threshold=threshold,
                        padding=padding, subtract_min=True)
    c.set_reference(ref[None])
    ours = np.array([c.centroid(st[i:i + 1])[0] for i in range(n)])
    np.testing.assert_allclose(ours, expect.T - 8.0, atol=1e-4)
