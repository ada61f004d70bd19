"""Response linearisation (centroiding/linearize.py) on analytic responses."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import kernels
from lgs_wfs_ros.centroiding.linearize import ResponseMap, chebyshev_basis, transform_covariance


def response(s):
    """A smooth, coupled, compressive response like a CMF's: ``(n, 2)`` -> ``(n, 2)``."""
    x, y = s[:, 0], s[:, 1]
    return np.stack([x - 0.08 * x ** 3 - 0.05 * x * y ** 2, 0.9 * y - 0.1 * y ** 3 + 0.03 * x * y], axis=1)


def test_chebyshev_basis_matches_numpy():
    u = np.linspace(-1, 1, 7)
    t, d = chebyshev_basis(u, 6)
    for k in range(7):
        ck = np.zeros(k + 1)
        ck[k] = 1
        np.testing.assert_allclose(t[k], np.polynomial.chebyshev.chebval(u, ck), atol=1e-12)
        np.testing.assert_allclose(d[k], np.polynomial.chebyshev.chebval(u, np.polynomial.chebyshev.chebder(ck)), atol=1e-11)


def test_fit_and_invert_analytic_response():
    n = 50
    rm = ResponseMap.fit(response, n, extent=1.1, points=12, degree=8)
    assert rm.fit_error < 1e-10                       # a cubic is inside the basis
    s = np.random.default_rng(0).uniform(-1, 1, (n, 2))
    est, jac = rm.invert(response(s))
    np.testing.assert_allclose(est, s, atol=1e-5)      # float32 evaluation
    h = 1e-6
    num = np.stack([(response(s + [h, 0]) - response(s - [h, 0])) / (2 * h),
                    (response(s + [0, h]) - response(s - [0, h])) / (2 * h)], axis=2)
    np.testing.assert_allclose(jac, num, atol=1e-5)   # at the last Newton iterate


def test_outside_the_box_and_nan_rows():
    rm = ResponseMap.fit(response, 3, extent=1.1, points=10, degree=6)
    m = np.array([[5.0, -4.0], [np.nan, 0.1], [0.2, 0.1]])
    est, jac = rm.invert(m)
    np.testing.assert_array_equal(est[0], m[0])       # outside the calibration: unchanged
    np.testing.assert_array_equal(jac[0], np.eye(2))
    assert np.isnan(est[1]).any()
    assert np.isfinite(est[2]).all()


@pytest.mark.parametrize("use_kernel", [True, False])
def test_offset_fallback_and_a_row_whose_response_cannot_be_measured(use_kernel):
    """A row with no reading at some scanned shifts (a spot leaving the field) fits to NaN
    without breaking the others; ``outside="offset"`` returns ``m - f(0)`` where the
    solution leaves the box (a CoG's bias removed) and inverts as usual inside it."""
    if use_kernel and not kernels.AVAILABLE:
        pytest.skip("numba (the fast extra) not installed")
    offset = np.array([[3.0, -2.0], [0.5, 0.25], [-1.0, 1.0]])

    def resp(s):
        out = response(s) + offset
        out[1, :] = np.where(s[1, 0] > 0.5, np.nan, out[1, :])     # row 1: no reading there
        return out
    rm = ResponseMap.fit(resp, 3, extent=1.1, points=10, degree=6)
    rm.use_kernel = use_kernel
    assert np.isnan(rm.coef[1]).all() and np.isfinite(rm.coef[[0, 2]]).all()
    inside = np.array([[0.3, -0.2], [0.1, 0.1], [-0.5, 0.4]])
    m = resp(inside)
    m[1] = [0.6, 0.35]
    est, _ = rm.invert(m, outside="offset")
    np.testing.assert_allclose(est[[0, 2]], inside[[0, 2]], atol=1e-4)
    assert np.isnan(est[1]).all()
    far = np.array([[9.0, -8.0], [0.0, 0.0], [-1.0, 1.0]])         # row 0 far outside
    est, jac = rm.invert(far, outside="offset")
    np.testing.assert_allclose(est[0], far[0] - offset[0], atol=1e-4)
    np.testing.assert_array_equal(jac[0], np.eye(2))
    np.testing.assert_allclose(est[2], [0.0, 0.0], atol=1e-4)      # inside: inverted
    np.testing.assert_array_equal(rm.invert(far)[0][0], far[0])   # the default: raw
    with pytest.raises(ValueError, match="outside"):
        rm.invert(far, outside="clip")


def test_covariance_transform():
    jac = np.array([[[2.0, 0.0], [0.0, 0.5]]])
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]]])
    np.testing.assert_allclose(transform_covariance(cov, jac), [[[1.0, 0.0], [0.0, 4.0]]])


def test_bad_degree_refused():
    with pytest.raises(ValueError, match="degree"):
        ResponseMap.fit(response, 2, points=5, degree=5)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba (the fast extra) not installed")
@pytest.mark.parametrize("with_guess", [True, False])
def test_compiled_inversion_matches_numpy(with_guess):
    """The numba kernel and the numpy fallback give the same shifts (1e-6 px) and Jacobians,
    per subaperture (responses differ between rows), outside the box and on NaN rows."""
    n = 300
    gain = 1.0 + 0.3 * np.arange(n)[:, None] / n

    def resp(s):
        return response(s) * gain
    rm = ResponseMap.fit(resp, n, extent=1.1, points=12, degree=8)
    if not with_guess:
        rm.guess = None
    m = resp(np.random.default_rng(2).uniform(-1.05, 1.05, (n, 2)))
    m[:4] = [[5.0, -4.0], [np.nan, 0.1], [0.2, np.inf], [0.0, 0.0]]
    fast, slow = ResponseMap(rm.coef, rm.extent), ResponseMap(rm.coef, rm.extent)
    fast.guess = slow.guess = rm.guess
    fast.use_kernel, slow.use_kernel = True, False
    s1, j1 = fast.invert(m)
    s0, j0 = slow.invert(m)
    np.testing.assert_allclose(s1, s0, atol=1e-6)
    np.testing.assert_allclose(j1, j0, atol=1e-5)
    assert np.isnan(s1[1, 0]) and (s1[0] == m[0]).all()
    assert np.abs(s1[4:] - m[4:]).max() > 0.01          # the inversion did something
