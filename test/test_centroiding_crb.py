"""Cramer-Rao bound: the textbook limit, nuisance flux, noise terms, finite differences."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import crb, crb_covariance, crb_of, fisher, model_derivatives
from spotgen import spots


def round_model(sigma, p, photons, shift=(0.0, 0.0)):
    return lambda sh: spots(np.asarray(sh) + shift, sigma=sigma, p=p, photons=photons)


@pytest.mark.parametrize("photons", [100.0, 1000.0, 30000.0])
def test_round_gaussian_limit_is_sigma_over_sqrt_n(photons):
    """Fine pixels (sigma = 4 px), big field (64 px): CRB = sigma / sqrt(N) within 2 %."""
    sigma = 4.0
    bound = crb_of(round_model(sigma, 64, photons), 1, h=1e-3)
    np.testing.assert_allclose(bound[0], sigma / np.sqrt(photons), rtol=0.02)


def test_pixel_size_raises_the_bound():
    """Coarse pixels lose information: the 1.19 px core has a higher bound than sigma/sqrt(N)."""
    s = 1.19 / 2.3548
    b = crb_of(round_model(s, 16, 1000.0), 1, h=1e-4)[0, 0]
    assert b > 1.1 * s / np.sqrt(1000)


def test_analytic_derivatives_match_finite_differences():
    model, dx, dy = model_derivatives(round_model(1.0, 16, 1000.0, (0.3, -0.2)), 1, h=1e-4)
    # derivative of a centred Gaussian's pixel integrals along x: antisymmetric about x0
    assert abs(dx.sum()) < 1e-6 * np.abs(dx).sum() + 1e-9
    # sum over pixels of x * d(model)/dx = flux (first moment moves one-for-one)
    x = np.arange(16)[None, None, :]
    y = np.arange(16)[None, :, None]
    np.testing.assert_allclose((x * dx).sum(), 1000.0, rtol=1e-4)
    np.testing.assert_allclose((y * dy).sum(), 1000.0, rtol=1e-4)


def test_read_noise_and_background_raise_the_bound_and_flux_is_a_nuisance():
    model, dx, dy = model_derivatives(round_model(1.0, 16, 1000.0), 1, h=1e-4)
    b0 = crb(model, dx, dy)
    b_rn = crb(model, dx, dy, read_noise_e=3.0)
    b_bg = crb(model, dx, dy, background_e=5.0)
    assert (b_rn > 1.05 * b0).all() and (b_bg > 1.05 * b0).all()
    # for a centred symmetric spot, flux and position are uncorrelated
    np.testing.assert_allclose(crb(model, dx, dy, flux_nuisance=False), b0, rtol=1e-9)
    # off centre in a truncated field they correlate: the nuisance can only raise the bound
    m2, dx2, dy2 = model_derivatives(round_model(2.0, 16, 1000.0, (3.0, 0.0)), 1, h=1e-4)
    assert crb(m2, dx2, dy2)[0, 0] >= crb(m2, dx2, dy2, flux_nuisance=False)[0, 0]
    f = fisher(model, dx, dy)
    assert f.shape == (1, 3, 3) and np.allclose(f, np.swapaxes(f, 1, 2))


def test_vectorised_and_bad_input():
    n = 5
    sig = np.linspace(1, 2, n)

    def image_at(sh):
        return np.concatenate([spots(sh[i], sigma=sig[i], photons=1000.0) for i in range(n)])

    b = crb_of(image_at, n, h=1e-4)
    assert b.shape == (n, 2) and np.all(np.diff(b[:, 0]) > 0)      # wider spots, larger bound
    zero = np.zeros((1, 16, 16))
    assert np.isnan(crb_covariance(zero, zero, zero)).all()
    with pytest.raises(ValueError):
        crb(np.zeros((16, 16)), np.zeros((16, 16)), np.zeros((16, 16)))
    with pytest.raises(ValueError):
        crb(zero, np.zeros((1, 8, 8)), zero)
