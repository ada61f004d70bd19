"""CoG, thresholded CoG and weighted CoG against imposed shifts and hand computations."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.optics.gaussian_spot import FWHM_PER_SIGMA, elongation_fwhm_px
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import sodium_line, spots

SENSOR = Sensor()
LAY = geometry.layout(SENSOR)
N = LAY.n_valid


def grid_shifts(amp=1.0, k=9):
    """All (sx, sy) on a k x k grid over +-amp, tiled to N rows."""
    g = np.linspace(-amp, amp, k)
    s = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    return np.resize(s, (N, 2))


@pytest.mark.parametrize("elongated", [False, True])
def test_cog_returns_imposed_shift_within_1px(elongated):
    """Noise-free symmetric spots (sigma 1 px; round, or a symmetric sodium line along e)."""
    shift = grid_shifts()
    kw = {}
    if elongated:
        off, w = sodium_line(2.5, 11)
        kw = dict(e=LAY.e, offsets=off, weights=w)
    st = spots(shift, sigma=1.0, **kw)
    out = make_centroider("cog", SENSOR).centroid(st)
    np.testing.assert_allclose(out, shift, atol=1e-3)


def test_cog_undersampled_core_has_only_the_known_sampling_bias():
    """FWHM 1.19 px spots: the CoG of a pixelised spot is biased by pixel sampling,
    a few 1e-3 px (a property of the image, not of the algorithm)."""
    shift = grid_shifts(0.5)
    out = make_centroider("cog", SENSOR).centroid(spots(shift, sigma=1.19 / FWHM_PER_SIGMA))
    err = np.abs(out - shift).max()
    assert 1e-4 < err < 5e-3


def test_cog_background_subtraction_restores_the_shift():
    shift = grid_shifts(0.7)
    st = spots(shift, sigma=1.0, background=5.0)
    plain = make_centroider("cog", SENSOR, background=0).centroid(st)
    fixed = make_centroider("cog", SENSOR, background=5.0).centroid(st)
    assert np.abs(plain - shift).max() > 0.1                    # background pulls to the centre
    np.testing.assert_allclose(fixed, shift, atol=1e-3)
    # the sensor's background is the default
    np.testing.assert_allclose(make_centroider("cog", SENSOR.replace(background_e=5.0)).centroid(st), fixed)


def test_tcog_matches_hand_computation():
    rng = np.random.default_rng(0)
    st = rng.uniform(0, 10, (N, 16, 16))
    y, x = np.indices((16, 16)) - 7.5
    for mode, t_img in (("subtract", np.maximum(st - 4, 0)), ("zero", np.where(st >= 4, st, 0))):
        out = make_centroider("tcog", SENSOR, threshold=4.0, mode=mode).centroid(st)
        tot = t_img.sum((1, 2))
        ref = np.stack([(t_img * x).sum((1, 2)) / tot, (t_img * y).sum((1, 2)) / tot], 1)
        np.testing.assert_allclose(out, ref, atol=1e-12)
    # threshold_rn: multiples of the read noise; threshold_frac: of each maximum
    s3 = SENSOR.replace(read_noise_e=2.0)
    np.testing.assert_allclose(make_centroider("tcog", s3, threshold_rn=2).centroid(st),
                               make_centroider("tcog", SENSOR, threshold=4.0).centroid(st))
    frac = make_centroider("tcog", SENSOR, threshold_frac=0.5).centroid(st)
    t = 0.5 * st.max((1, 2))[:, None, None]
    t_img = np.maximum(st - t, 0)
    tot = t_img.sum((1, 2))
    np.testing.assert_allclose(frac[:, 0], (t_img * x).sum((1, 2)) / tot, atol=1e-12)


def test_tcog_zero_threshold_is_cog_and_default_uses_read_noise():
    rng = np.random.default_rng(1)
    st = rng.poisson(spots(grid_shifts(0.5), sigma=1.0)).astype(float)
    np.testing.assert_allclose(make_centroider("tcog", SENSOR, threshold=0).centroid(st),
                               make_centroider("cog", SENSOR).centroid(st), atol=1e-12)
    c = make_centroider("tcog", SENSOR.replace(read_noise_e=3.0))
    assert c.describe()["threshold_counts"] == 9.0


def test_tcog_beats_cog_with_read_noise():
    """With 3 e- read noise the far pixels dominate the CoG error; thresholding removes them."""
    rng = np.random.default_rng(2)
    shift = rng.uniform(-0.5, 0.5, (N, 2))
    st = rng.poisson(spots(shift, sigma=1.0, photons=500)) + rng.normal(0, 3.0, (N, 16, 16))
    s = SENSOR.replace(read_noise_e=3.0)
    e_cog = np.sqrt(np.mean((make_centroider("cog", s).centroid(st) - shift) ** 2))
    e_tcog = np.sqrt(np.mean((make_centroider("tcog", s, threshold_rn=3).centroid(st) - shift) ** 2))
    assert e_tcog < 0.7 * e_cog


@pytest.mark.parametrize("detector", ["cartesian", "polar"])
def test_wcog_model_gain_returns_shift_near_centre(detector):
    """Noise-free spots matching WCoG's spot model (Gaussian core along a Gaussian sodium
    line) return their shift near the centre: the gain correction is right."""
    sensor = SENSOR.replace(detector=detector)
    c = make_centroider("wcog", sensor)
    e = c.e_pixel
    core = sensor.core_fwhm_px
    line = np.sqrt(c.spot_fwhm[:, 0] ** 2 - core ** 2) / FWHM_PER_SIGMA     # (n,) line sigma px
    t = np.linspace(-2, 2, 31)
    rng = np.random.default_rng(3)
    shift = rng.uniform(-0.05, 0.05, (N, 2))
    # spotgen takes one set of offsets: group subapertures by line length (few distinct radii)
    out_ref = np.empty((N, 2))
    st = np.empty((N, 16, 16))
    for val in np.unique(np.round(line, 9)):
        rows = np.isclose(line, val)
        st[rows] = spots(shift[rows], sigma=core / FWHM_PER_SIGMA, e=e[rows], offsets=val * t,
                         weights=np.exp(-0.5 * t ** 2))
    out_ref[:] = shift if detector == "cartesian" else geometry.local_to_detector(shift, LAY.e)
    out = c.centroid(st)
    np.testing.assert_allclose(out, out_ref, atol=2e-4)
    # the raw weighted centroid is clearly biased towards the centre
    raw = make_centroider("wcog", sensor, gain="none").centroid(st)
    assert np.mean(np.abs(raw)) < 0.8 * np.mean(np.abs(out))


def test_wcog_analytic_gain_for_well_sampled_round_spot():
    shift = grid_shifts(0.3)
    st = spots(shift, sigma=1.0)
    fw = 1.0 * FWHM_PER_SIGMA
    for gain in ("analytic", "model"):
        c = make_centroider("wcog", SENSOR, spot_fwhm_par_px=fw, spot_fwhm_perp_px=fw,
                            fwhm_par_px=3.0, fwhm_perp_px=3.0, gain=gain)
        np.testing.assert_allclose(c.centroid(st), shift, atol=2e-3)


def test_wcog_weight_is_aligned_with_e():
    c = make_centroider("wcog", SENSOR)
    i = int(np.argmax(LAY.r_m))
    w = c.weight[i].reshape(16, 16)
    y, x = np.indices((16, 16)) - 7.5
    # second moments of the weight: principal axis along e
    m = np.array([[(w * x * x).sum(), (w * x * y).sum()], [(w * x * y).sum(), (w * y * y).sum()]])
    vals, vecs = np.linalg.eigh(m)
    assert abs(abs(vecs[:, 1] @ LAY.e[i]) - 1) < 1e-6
    assert vals[1] > 2 * vals[0]
    # default spot length: the elongation of a 10 km layer, 7.64 px at r = 15 m (paper's numbers)
    L = elongation_fwhm_px(SENSOR)
    assert abs(L.max() / LAY.r_m.max() * 15 - 7.64) < 0.05
