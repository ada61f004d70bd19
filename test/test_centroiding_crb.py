"""Cramer-Rao bound: the textbook limit, nuisance flux, noise terms, finite differences."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import cog_covariance, crb, crb_covariance, crb_of, fisher, model_derivatives
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


def _cog(images):
    p = images.shape[-1]
    yy, xx = np.mgrid[0:p, 0:p]
    tot = images.sum(axis=(-1, -2))
    return np.stack([(images * xx).sum(axis=(-1, -2)) / tot, (images * yy).sum(axis=(-1, -2)) / tot], -1)


def test_cog_floor_is_the_calibrated_cogs_monte_carlo_covariance():
    """Two layers at 30 deg, one cut by the field's edge (CoG gain < 1), background: the
    covariance of the CoG with its response inverted, over 20,000 Poisson frames, is
    cog_covariance to 5 % in every element; above the CRB for two separated peaks."""
    e = (np.cos(np.pi / 6), np.sin(np.pi / 6))
    kw = dict(sigma=0.6, e=e, offsets=(-2.0, 8.3), weights=(1.0, 0.6))
    model = lambda sh: spots(np.atleast_2d(sh), photons=1000.0, **kw)
    mu, dx, dy = model_derivatives(model, 1, h=1e-4)
    cov = cog_covariance(mu, dx, dy, background_e=0.5)[0]
    rng = np.random.default_rng(3)
    frames = rng.poisson(mu[0] + 0.5, size=(20000, 16, 16)) - 0.5
    c0 = _cog(mu[0])
    jac = np.stack([(_cog(model((h, 0))[0]) - _cog(model((-h, 0))[0])) / (2 * h) for h in (1e-4,)]
                   + [(_cog(model((0, h))[0]) - _cog(model((0, -h))[0])) / (2 * h) for h in (1e-4,)], 1)
    assert jac[0, 0] < 0.9                          # the edge pulls the gain down
    est = (np.linalg.inv(jac) @ (_cog(frames) - c0).T).T
    emp = np.cov(est.T)
    np.testing.assert_allclose(cov, emp, rtol=0.05, atol=0.05 * np.sqrt(emp[0, 0] * emp[1, 1]))
    bound = crb_covariance(mu, dx, dy, background_e=0.5)[0]
    assert np.trace(cov) > 1.5 * np.trace(bound)


def test_cog_floor_of_a_round_gaussian_is_the_bound():
    """A round, finely sampled Gaussian with photon noise only: the CoG is efficient."""
    mu, dx, dy = model_derivatives(round_model(4.0, 64, 1000.0), 1, h=1e-3)
    np.testing.assert_allclose(cog_covariance(mu, dx, dy)[0], crb_covariance(mu, dx, dy)[0],
                               rtol=0.02, atol=1e-6)
