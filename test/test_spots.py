"""Spot images against theory: centroid, elongation, orientation, truncation, brute force."""

import math

import numpy as np
import pytest
from scipy.special import ndtr

from lgs_wfs_ros.optics.geometry import detector_to_local, layout, local_to_detector
from lgs_wfs_ros.optics.spots import (SIGMA_PER_FWHM, SpotModel, elongation_px,
                                      exact_elongation_arcsec, light_centroid_px,
                                      linear_elongation_arcsec, spot_images)
from lgs_wfs_ros.sensor import Sensor

DETECTORS = ("cartesian", "polar")


def single(detector, r_m, angle_deg):
    a = math.radians(angle_deg)
    return Sensor(detector=detector, single_subaperture_xy_m=(r_m * math.cos(a), r_m * math.sin(a)))


def cog(images):
    """Plain CoG of (n, p, p) images: (x, y) relative to the block centre, in block axes."""
    n, p, _ = images.shape
    idx = np.arange(p) - (p - 1) / 2
    tot = images.sum(axis=(1, 2))
    return np.stack([(images.sum(axis=1) * idx).sum(1) / tot,
                     (images.sum(axis=2) * idx).sum(1) / tot], axis=1)


def cog_detector(images, sensor, e):
    c = cog(images)
    return local_to_detector(c, e) if sensor.detector == "polar" else c


def symmetric_in_u(sensor, r_m, half_px=2.5, step_m=5.0):
    """Altitudes and a density whose light is a cos^2 bump of half-width half_px in u."""
    h = np.arange(70e3, 120e3, step_m)
    u = elongation_px(sensor, r_m, h)
    du_dh = r_m * math.cos(math.radians(sensor.zenith_deg)) / h ** 2 / sensor.pixel_scale_rad
    f = np.where(np.abs(u) < half_px, np.cos(np.pi * u / (2 * half_px)) ** 2, 0.0)
    return h, f * du_dh


def brute(sensor, r, e, h, rho, shift, nfine=60000):
    """Reference renderer: fine point sources, each an exactly pixel-integrated Gaussian."""
    hf = np.linspace(h[0], h[-1], nfine + 1)
    hc = 0.5 * (hf[1:] + hf[:-1])
    mass = np.interp(hc, h, rho) * np.diff(hf)
    mass /= np.trapezoid(rho, h)
    p, sig = sensor.pixels, sensor.core_fwhm_px * SIGMA_PER_FWHM
    c = (p - 1) / 2
    edges = np.arange(p + 1) - 0.5
    out = []
    for i in range(len(r)):
        u = elongation_px(sensor, r[i], hc)
        if sensor.detector == "polar":
            sl = detector_to_local(shift[i:i + 1], e[i:i + 1])[0]
            x, y = c + u + sl[0], c + sl[1] + 0 * u
        else:
            x, y = c + u * e[i, 0] + shift[i, 0], c + u * e[i, 1] + shift[i, 1]
        gx = np.diff(ndtr((edges[None] - x[:, None]) / sig), axis=1)
        gy = np.diff(ndtr((edges[None] - y[:, None]) / sig), axis=1)
        out.append((gy * mass[:, None]).T @ gx)
    return np.array(out)


@pytest.mark.parametrize("detector", DETECTORS)
def test_cog_equals_shift_on_half_pixel_grid(detector):
    """Light symmetric about h_ref's image: CoG == imposed shift (no pixelisation bias
    on the half-pixel grid, where the pixel lattice is symmetric about the spot)."""
    s = single(detector, 10.0, 33.0)
    lay = layout(s)
    h, rho = symmetric_in_u(s, lay.r_m[0])
    g = np.arange(-2.0, 2.01, 0.5)
    shifts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    n = len(shifts)
    r, e = np.full(n, lay.r_m[0]), np.repeat(lay.e, n, axis=0)
    if detector == "polar":                 # the grid is on the pixel axes: local frame
        shifts = local_to_detector(shifts, e)
    img, trunc = spot_images(s, r, e, h, rho, shifts)
    assert np.all(trunc < 1e-6)                       # float32 rounding of the sums
    err = cog_detector(img, s, e) - shifts
    assert np.abs(err).max() < 1e-4, np.abs(err).max()


@pytest.mark.parametrize("detector", DETECTORS)
def test_subpixel_shifts_match_brute_force_and_cog(detector):
    """Any sub-pixel shift within +-2 px: images equal a brute-force render, and the CoG
    equals the shift to within the pixelisation bias of a 1.19 px Gaussian core (2.0e-3 px)."""
    s = single(detector, 10.0, 33.0)
    lay = layout(s)
    h, rho = symmetric_in_u(s, lay.r_m[0], step_m=20.0)
    rng = np.random.default_rng(1)
    shifts = rng.uniform(-2, 2, size=(12, 2))
    r, e = np.full(12, lay.r_m[0]), np.repeat(lay.e, 12, axis=0)
    img, _ = spot_images(s, r, e, h, rho, shifts)
    ref = brute(s, r, e, h, rho, shifts)
    assert np.abs(img - ref).max() < 3e-4 * ref.max()
    c = cog_detector(img, s, e)
    assert np.abs(c - cog_detector(ref, s, e)).max() < 1e-5
    assert np.abs(c - shifts).max() < 2.1e-3


@pytest.mark.parametrize("detector", DETECTORS)
def test_full_pupil_matches_brute_force(detector):
    s = Sensor(detector=detector)
    lay = layout(s)
    sel = np.array([0, 333, 1000, 1391, 1392, 2100, lay.n_valid - 1])
    h = np.linspace(80e3, 100e3, 801)
    rho = np.exp(-0.5 * ((h - 90e3) / 3000) ** 2) + 0.5 * np.exp(-0.5 * ((h - 86e3) / 300) ** 2)
    shifts = np.random.default_rng(2).normal(0, 1, (len(sel), 2))
    img, trunc = spot_images(s, lay.r_m[sel], lay.e[sel], h, rho, shifts)
    ref = brute(s, lay.r_m[sel], lay.e[sel], h, rho, shifts)
    assert np.abs(img - ref).max() < 3e-4 * ref.max()
    np.testing.assert_allclose(img.sum(axis=(1, 2)), 1 - trunc, atol=1e-12)
    np.testing.assert_allclose(trunc, 1 - ref.sum(axis=(1, 2)), atol=2e-5)


@pytest.mark.parametrize("detector", DETECTORS)
def test_gaussian_at_href_cog_is_exact_geometry_centroid(detector):
    """A layer symmetric in h about h_ref: the CoG is the shift plus the exact-geometry
    centroid offset r cos z (1/h_ref - <1/h>) (negative, ~ -r sigma_h^2 / h_ref^3)."""
    s = single(detector, 8.0, 120.0)
    lay = layout(s)
    h = np.linspace(75e3, 105e3, 3001)
    sig_h = 6000 / 2.3548
    rho = np.exp(-0.5 * ((h - s.h_ref_m) / sig_h) ** 2)
    g = np.arange(-1.0, 1.01, 0.5)
    shifts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    n = len(shifts)
    e = np.repeat(lay.e, n, axis=0)
    if detector == "polar":                 # half-pixel grid on the pixel axes
        shifts = local_to_detector(shifts, e)
    img, trunc = spot_images(s, np.full(n, lay.r_m[0]), e, h, rho, shifts)
    off = light_centroid_px(s, lay.r_m[0], h, rho)[0]
    approx = -lay.r_m[0] * sig_h ** 2 / s.h_ref_m ** 3 / s.pixel_scale_rad
    assert off == pytest.approx(approx, rel=0.03)
    assert off < -0.02                                  # far from negligible
    expected = shifts + off * e
    assert np.abs(cog_detector(img, s, e) - expected).max() < 1e-3


def test_elongation_helpers():
    lin = linear_elongation_arcsec(15.0, 10e3, 90e3)
    assert lin == pytest.approx(3.82, abs=0.005)
    ex = exact_elongation_arcsec(15.0, 85e3, 95e3)
    assert ex / lin == pytest.approx(1 / (1 - (5e3 / 90e3) ** 2), rel=1e-12)
    assert ex / lin - 1 == pytest.approx(0.0031, abs=0.0001)


@pytest.mark.parametrize("detector,angle", [("polar", 0.0), ("cartesian", 45.0), ("cartesian", 0.0)])
def test_elongation_length_r15_10km(detector, angle):
    """Two thin layers 10 km apart, r = 15 m: their images are 3.832" apart (exact form),
    which is the paper's linear 3.82" within the documented 0.31 % difference."""
    s = single(detector, 15.0, angle)
    lay = layout(s)
    h = np.arange(80e3, 100e3, 5.0)
    rho = np.exp(-0.5 * ((h - 85e3) / 20) ** 2) + np.exp(-0.5 * ((h - 95e3) / 20) ** 2)
    img, trunc = spot_images(s, lay.r_m, lay.e, h, rho, np.zeros((1, 2)))
    assert trunc[0] < 1e-6
    p = s.pixels
    yy, xx = np.mgrid[0:p, 0:p] - (p - 1) / 2
    along = xx if detector == "polar" else xx * lay.e[0, 0] + yy * lay.e[0, 1]
    im = img[0]
    lo, hi = along < 0, along > 0
    sep_px = (im[hi] * along[hi]).sum() / im[hi].sum() - (im[lo] * along[lo]).sum() / im[lo].sum()
    sep = sep_px * s.pixel_scale_arcsec
    exact = exact_elongation_arcsec(15.0, 85e3, 95e3)
    lin = linear_elongation_arcsec(15.0, 10e3, 90e3)
    assert abs(sep - exact) < 0.003                      # 0.006 px: pixelisation of two cores
    assert abs(sep / lin - 1) < (exact / lin - 1) + 0.001


@pytest.mark.parametrize("detector", DETECTORS)
def test_principal_axis_along_e_all_round_pupil(detector):
    s = Sensor(detector=detector)
    lay = layout(s)
    h = np.linspace(80e3, 100e3, 2001)
    rho = np.exp(-0.5 * ((h - 90e3) / 1700) ** 2)
    sel = np.flatnonzero(lay.r_m > 8.0)
    img, trunc = spot_images(s, lay.r_m[sel], lay.e[sel], h, rho, np.zeros((sel.size, 2)))
    assert trunc.max() < 1e-3
    p = s.pixels
    yy, xx = np.mgrid[0:p, 0:p] - (p - 1) / 2
    tot = img.sum(axis=(1, 2))
    mx, my = (img * xx).sum((1, 2)) / tot, (img * yy).sum((1, 2)) / tot
    sxx = (img * xx ** 2).sum((1, 2)) / tot - mx ** 2
    syy = (img * yy ** 2).sum((1, 2)) / tot - my ** 2
    sxy = (img * xx * yy).sum((1, 2)) / tot - mx * my
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    want = np.zeros(sel.size) if detector == "polar" else np.arctan2(lay.e[sel, 1], lay.e[sel, 0])
    diff = np.angle(np.exp(2j * (angle - want))) / 2                 # modulo pi
    assert np.degrees(np.abs(diff)).max() < 0.5
    assert np.all(sxx + syy > 0.255 + 1 / 12 + 0.5)                  # elongated, not round
    # every direction round the pupil is represented
    az = np.degrees(np.arctan2(lay.e[sel, 1], lay.e[sel, 0]))
    assert np.histogram(az, bins=12, range=(-180, 180))[0].min() > 0


@pytest.mark.parametrize("detector", DETECTORS)
def test_truncation_flagged_and_counted(detector):
    s = Sensor.paper_single(detector)
    lay = layout(s)
    h = np.linspace(70e3, 125e3, 2201)
    wide = np.exp(-0.5 * ((h - 92e3) / 8000) ** 2)                   # spills out of the field
    compact = np.exp(-0.5 * ((h - 90e3) / 1000) ** 2)
    img, trunc = spot_images(s, np.repeat(lay.r_m, 3), np.repeat(lay.e, 3, 0), h,
                             np.stack([wide, compact, compact]),
                             np.array([[0, 0], [0, 0], [8.0, 3.0]]))
    assert trunc[0] > 0.02
    assert trunc[1] < 1e-6
    assert trunc[2] > 0.3                                            # shifted off the field
    np.testing.assert_allclose(img.sum(axis=(1, 2)), 1 - trunc, atol=1e-12)
    ref = brute(s, np.repeat(lay.r_m, 1), lay.e, h, wide, np.zeros((1, 2)))
    assert trunc[0] == pytest.approx(1 - ref.sum(), abs=1e-5)


def test_per_subaperture_profiles_match_single_calls():
    s = Sensor.paper_single("cartesian")
    lay = layout(s)
    h = np.linspace(80e3, 100e3, 401)
    rho = np.stack([np.exp(-0.5 * ((h - c) / 2000) ** 2) for c in (87e3, 90e3, 93e3)])
    sh = np.array([[0.3, -0.2], [1.1, 0.4], [-0.7, 0.9]])
    img, tr = spot_images(s, np.repeat(lay.r_m, 3), np.repeat(lay.e, 3, 0), h, rho, sh)
    for i in range(3):
        one, t1 = spot_images(s, lay.r_m, lay.e, h, rho[i], sh[i:i + 1])
        np.testing.assert_allclose(img[i], one[0], atol=1e-14)


def test_centre_subaperture_r0_is_exact_gaussian_and_inputs_untouched():
    """r = 0: no elongation; the image is the exactly pixel-integrated round core."""
    s = Sensor(single_subaperture_xy_m=(0.0, 0.0))
    lay = layout(s)
    h = np.linspace(80e3, 100e3, 101)
    rho = np.exp(-0.5 * ((h - 90e3) / 3000) ** 2)
    rho0, sh = rho.copy(), np.array([[0.25, -0.5]])
    img, tr = spot_images(s, lay.r_m, lay.e, h, rho, sh)
    np.testing.assert_array_equal(rho, rho0)
    np.testing.assert_array_equal(sh, [[0.25, -0.5]])
    p, sig = s.pixels, 1.19 * SIGMA_PER_FWHM
    edges = np.arange(p + 1) - 0.5 - (p - 1) / 2
    gx = np.diff(ndtr((edges - 0.25) / sig))
    gy = np.diff(ndtr((edges + 0.5) / sig))
    np.testing.assert_allclose(img[0], np.outer(gy, gx), atol=1e-7)       # core table accuracy
    assert tr[0] < 1e-6


def test_model_reuse_and_shift_limit():
    s = Sensor(detector="polar")
    lay = layout(s)
    h = np.linspace(80e3, 100e3, 401)
    rho = np.exp(-0.5 * ((h - 90e3) / 3000) ** 2)
    m = SpotModel(s, lay.r_m, lay.e, h, rho, max_shift_px=2.0)
    sh = np.random.default_rng(0).uniform(-2, 2, (lay.n_valid, 2))
    a, _ = m.images(sh)
    b, _ = spot_images(s, lay.r_m, lay.e, h, rho, sh)
    np.testing.assert_allclose(a, b, atol=1e-15)
    with pytest.raises(ValueError):
        m.images(sh * 2)


@pytest.mark.parametrize("bad", [
    dict(r_m=[-1.0]), dict(e=[[1.0, 1.0]]), dict(altitude_m=[90e3, 80e3]),
    dict(density=[-1.0, 1.0]), dict(density=[0.0, 0.0]), dict(shift_px=[[np.nan, 0]]),
    dict(shift_px=[0.0, 0.0]), dict(density=[[1.0, 1.0, 1.0]]),
])
def test_bad_input_raises(bad):
    s = Sensor.paper_single("polar")
    kw = dict(r_m=[14.75], e=[[1.0, 0.0]], altitude_m=[80e3, 100e3], density=[1.0, 1.0],
              shift_px=[[0.0, 0.0]])
    kw.update(bad)
    with pytest.raises(ValueError):
        spot_images(s, **kw)


@pytest.mark.parametrize("detector", DETECTORS)
def test_side_launch_zenith_short_and_long_lines_match_brute_force(detector):
    """Side launch (r from 1 to 31 m), z = 30 deg, a multi-layer profile: every image,
    including the nearly round ones next to the launch, within 5e-4 of its peak."""
    s = Sensor(detector=detector, launch_xy_m=(15.5, -3.0), zenith_deg=30.0)
    lay = layout(s)
    sel = np.argsort(lay.r_m)[[0, 5, 1000, 2000, -1]]
    h = np.linspace(78e3, 110e3, 1281)
    rho = (np.exp(-0.5 * ((h - 90e3) / 3000) ** 2) + 0.6 * np.exp(-0.5 * ((h - 85e3) / 300) ** 2)
           + 0.02 * np.exp(-0.5 * ((h - 99e3) / 6000) ** 2))
    sh = np.random.default_rng(0).normal(0, 1, (sel.size, 2))
    img, tr = spot_images(s, lay.r_m[sel], lay.e[sel], h, rho, sh)
    ref = brute(s, lay.r_m[sel], lay.e[sel], h, rho, sh)
    err = np.abs(img - ref).max(axis=(1, 2)) / ref.max(axis=(1, 2))
    assert err.max() < 5e-4, err
    np.testing.assert_allclose(tr, 1 - ref.sum(axis=(1, 2)), atol=2e-5)


def small_pupil(detector):
    """An 8 m pupil of 16 x 16 subapertures, launch 6 m off axis, its layout, and a layered
    profile (a 3 km Gaussian at 92 km and a thin layer at 100 km): (sensor, layout, h, rho)."""
    sensor = Sensor(detector=detector, diameter_m=8.0, obstruction_m=1.0, n_subaps=16,
                    launch_xy_m=(6.0, 0.0))
    h = np.linspace(80e3, 110e3, 300)
    rho = np.exp(-0.5 * ((h - 92e3) / 3e3) ** 2) + 0.5 * np.exp(-0.5 * ((h - 100e3) / 400.0) ** 2)
    return sensor, layout(sensor), h, rho


@pytest.mark.parametrize("detector", DETECTORS)
def test_compiled_node_weights_are_numpys_bit_for_bit(monkeypatch, detector):
    """The node weights a model deposits its elements on (compiled where numba is) are the
    numpy path's bit for bit, for a profile shared by the pupil and one per subaperture
    (frames drawn from them must not move; an element's variance left out of its moments, or
    its four weights summed in another order, fails this)."""
    from lgs_wfs_ros.optics import spots as module
    if module._deposit_compiled is None:
        pytest.skip("numba not installed ('fast' extra)")
    sensor, lay, h, rho = small_pupil(detector)
    per_subap = rho * (1 + 0.2 * np.random.default_rng(0).random((lay.n_valid, 1)))

    def weights():
        return [np.concatenate([g["w"].ravel() for g in SpotModel(sensor, lay.r_m, lay.e, h, d).groups])
                for d in (rho, per_subap)]
    compiled = weights()
    with monkeypatch.context() as m:
        m.setattr(module, "_deposit_compiled", None)
        reference = weights()
    for a, b in zip(compiled, reference):
        assert a.shape == b.shape and np.array_equal(a, b)



def test_polar_marginals_are_the_images_sums_without_the_images():
    """SpotModel.marginals gives each polar spot's column sums (along local x) and row sums
    (along local y) of the images it would render, to rounding, at shifts on and off the
    pixel grid and for truncated spots; the two are told apart (swapped, they differ); a
    cartesian model refuses (its spots are not separable)."""
    sensor, lay, h, rho = small_pupil("polar")
    model = SpotModel(sensor, lay.r_m, lay.e, h, rho, max_shift_px=2.0)
    shift = np.random.default_rng(3).uniform(-2.0, 2.0, (lay.n_valid, 2))
    img, trunc = model.images(shift)
    m = model.marginals(shift)
    assert trunc.max() > 1e-5                       # some light leaves the field
    np.testing.assert_allclose(m[:, 0], img.sum(axis=1), rtol=0, atol=1e-14)
    np.testing.assert_allclose(m[:, 1], img.sum(axis=2), rtol=0, atol=1e-14)
    assert np.abs(m[:, 0] - m[:, 1]).max() > 0.05
    with pytest.raises(ValueError, match="polar"):
        SpotModel(Sensor(detector="cartesian", diameter_m=8.0, obstruction_m=1.0, n_subaps=16),
                  np.array([3.0]), np.array([[1.0, 0.0]]), h, rho).marginals(np.zeros((1, 2)))


def test_compiled_core_lookups_are_numpys_bit_for_bit(monkeypatch):
    """Cartesian spots' core across the major axis read from its table by a compiled loop
    (no (g, K, p) index array): images, truncation and the CoG grid the same bit for bit as
    numpy's take with clipped indices, for spots moved up to 2 px (some leave the field)."""
    from lgs_wfs_ros.optics import spots as module
    if module._minor_compiled is None:
        pytest.skip("numba not installed ('fast' extra)")
    sensor, lay, h, rho = small_pupil("cartesian")
    model = SpotModel(sensor, lay.r_m, lay.e, h, rho, max_shift_px=2.0)
    shift = np.random.default_rng(5).uniform(-2.0, 2.0, (lay.n_valid, 2))
    t = np.linspace(-1.4, 1.4, 6)
    img, trunc = model.images(shift)
    grid = model.cog_grid(t)
    monkeypatch.setattr(module, "_minor_compiled", None)
    img0, trunc0 = model.images(shift)
    assert np.array_equal(img, img0) and np.array_equal(trunc, trunc0)
    assert np.array_equal(grid, model.cog_grid(t), equal_nan=True)
    assert trunc.max() > 1e-4
