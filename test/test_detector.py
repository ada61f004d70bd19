"""Detector noise against Poisson/Gaussian theory."""

import numpy as np
import pytest

from lgs_wfs_ros.optics.detector import POISSON_FLOOR, expose, poisson
from lgs_wfs_ros.optics.geometry import layout
from lgs_wfs_ros.optics.spots import spot_images
from lgs_wfs_ros.sensor import Sensor


def spot(detector="polar", shift=(0.3, -0.2)):
    s = Sensor.paper_single(detector)
    lay = layout(s)
    h = np.linspace(80e3, 100e3, 801)
    rho = np.exp(-0.5 * ((h - 90e3) / 2500) ** 2)
    img, tr = spot_images(s, lay.r_m, lay.e, h, rho, np.array([shift]))
    return img[0], tr[0]


@pytest.mark.parametrize("photons", [100.0, 1000.0, 30000.0])
def test_mean_total_and_poisson_variance(photons):
    img, tr = spot()
    n = 4000
    stack = np.broadcast_to(img, (n,) + img.shape)
    counts = expose(stack, photons, np.random.default_rng(5), dtype="float32")
    tot = counts.reshape(n, -1).sum(1).astype(float)
    expect = photons * (1 - tr)
    assert tot.mean() == pytest.approx(expect, rel=0.01)
    # variance of the total is Poisson: chi^2-consistent within 3 sigma of its estimate
    assert tot.var(ddof=1) == pytest.approx(expect, rel=3 * np.sqrt(2 / (n - 1)))
    # per pixel: mean and variance both equal the expectation where it is large enough
    lam = photons * img
    sel = lam > 20
    m, v = counts.mean(0)[sel], counts.var(0, ddof=1)[sel]
    np.testing.assert_allclose(m, lam[sel], rtol=5 / np.sqrt(n * 20))
    np.testing.assert_allclose(v / lam[sel], 1.0, atol=4 * np.sqrt(2 / n) + 0.02)


def test_per_field_counts_the_photons_inside_the_field():
    img = np.zeros((2, 4, 4))
    img[:, 1, 2] = 0.5                                     # half the light truncated
    a = expose(img, 1000.0, None, noise_free=True, dtype="float64")
    b = expose(img, 1000.0, None, noise_free=True, dtype="float64", per_field=True)
    assert a.sum() == pytest.approx(1000.0) and b.sum() == pytest.approx(2000.0)


def test_noise_free_background_and_read_noise():
    img, _ = spot()
    nf = expose(img, 1000.0, None, noise_free=True, dtype="float64")
    np.testing.assert_allclose(nf, 1000.0 * img, rtol=1e-15)
    n = 3000
    stack = np.broadcast_to(img, (n,) + img.shape)
    rng = np.random.default_rng(1)
    c = expose(stack, 1000.0, rng, read_noise_e=3.0, background_e=5.0, dtype="float32")
    # subtracted background: unbiased; variance = signal + background + read^2
    dark = img < 1e-12
    assert abs(c[:, dark].mean()) < 0.05
    assert c[:, dark].var() == pytest.approx(5.0 + 9.0, rel=0.03)
    keep = expose(stack[:200], 1000.0, rng, background_e=5.0, subtract_background=False,
                  dtype="float32")
    assert keep[:, dark].mean() == pytest.approx(5.0, rel=0.03)


def test_uint16_rounding_clipping_and_saturation_count():
    img = np.zeros((1, 4, 4))
    img[0, 0, 0] = 1.0
    c, clip = expose(img, 1e6, np.random.default_rng(0), return_clipped=True)
    assert c.dtype == np.uint16 and c[0, 0, 0] == 65535 and clip["saturated"] == 1
    c, clip = expose(np.zeros((1, 4, 4)), 1.0, np.random.default_rng(0), read_noise_e=3.0,
                     return_clipped=True)
    assert c.dtype == np.uint16 and clip["negative"] > 0 and c.min() == 0


def test_same_seed_same_counts_and_inputs_untouched():
    img, _ = spot()
    stack = np.stack([img] * 50)
    keep = stack.copy()
    a = expose(stack, 1000.0, np.random.default_rng(42), read_noise_e=1.0)
    b = expose(stack, 1000.0, np.random.default_rng(42), read_noise_e=1.0)
    c = expose(stack, 1000.0, np.random.default_rng(43), read_noise_e=1.0)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(stack, keep)


def test_poisson_floor_skips_only_negligible_pixels():
    lam = np.array([0.0, 1e-12, 5.0, 1e-8])
    rng = np.random.default_rng(0)
    draws = np.stack([poisson(lam, rng, POISSON_FLOOR) for _ in range(2000)])
    assert np.all(draws[:, :2] == 0)
    assert draws[:, 2].mean() == pytest.approx(5.0, rel=0.05)


def test_per_subaperture_photons():
    img = np.full((3, 2, 2), 0.25)
    out = expose(img, np.array([10.0, 100.0, 1000.0]), None, noise_free=True, dtype="float64")
    np.testing.assert_allclose(out.sum(axis=(1, 2)), [10, 100, 1000])


@pytest.mark.parametrize("kw", [dict(photons=-1.0), dict(dtype="int8"), dict(read_noise_e=-1.0),
                                dict(background_e=np.nan), dict(rng=None),
                                dict(photons=np.ones(5)), dict(images=-np.ones((2, 2)))])
def test_bad_input_raises(kw):
    args = dict(images=np.ones((3, 2, 2)) / 4, photons=100.0, rng=np.random.default_rng(0))
    args.update(kw)
    with pytest.raises(ValueError):
        expose(args.pop("images"), args.pop("photons"), **args)
