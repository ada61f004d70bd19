"""The simulator's fast path (compiled Poisson noise, frames written into a given buffer) is
statistically today's; profiles are a function of the frame index alone."""

import numpy as np
import pytest

from lgs_wfs_ros.optics import detector
from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator
from lgs_wfs_ros.sensor import Sensor


def test_profile_at_is_a_function_of_the_index():
    sim = Simulator(Sensor.paper_single("polar"), SimulationConfig(profile="random",
                                                                     random_every=3, seed=2))
    first = [sim.profile_at(i)[0].copy() for i in (0, 4, 7)]
    again = [sim.profile_at(i)[0].copy() for i in (7, 0, 4)]      # another order
    for a, b in zip(first, [again[1], again[2], again[0]]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sim.profile_at(1)[0], first[0])   # same epoch
    assert not np.array_equal(first[0], first[1])
    other = Simulator(sim.sensor, sim.config.replace(seed=3))
    assert not np.array_equal(other.profile_at(0)[0], first[0])


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("lam", [0.02, 0.7, 3.0, 11.9, 12.1, 40.0, 300.0])
def test_fast_poisson_has_the_poisson_distribution(lam):
    """200k draws: mean, variance and the histogram against the Poisson pmf (chi-square)."""
    from scipy import stats
    n = 200_000
    k = detector.poisson(np.full(n, lam), np.random.default_rng(1), fast=True)
    assert k.dtype == np.int64
    assert abs(k.mean() - lam) < 5 * np.sqrt(lam / n)
    assert abs(k.var() / lam - 1) < 5 * np.sqrt(2.0 / n) + 0.01
    lo, hi = int(stats.poisson.ppf(1e-4, lam)), int(stats.poisson.ppf(1 - 1e-4, lam))
    edges = np.arange(lo, hi + 2)
    obs = np.histogram(k, bins=edges - 0.5)[0]
    exp = n * np.diff(stats.poisson.cdf(edges - 1, lam))
    keep = exp > 5
    chi2 = ((obs[keep] - exp[keep]) ** 2 / exp[keep]).sum()
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-4


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_fast_poisson_reproducible_and_floor():
    lam = np.array([[0.0, 1e-12], [5.0, 1e-8]])
    a = detector.poisson(lam, np.random.default_rng(4), detector.POISSON_FLOOR, fast=True)
    b = detector.poisson(lam, np.random.default_rng(4), detector.POISSON_FLOOR, fast=True)
    np.testing.assert_array_equal(a, b)
    assert a.shape == lam.shape and a[0, 0] == a[0, 1] == 0


@pytest.mark.parametrize("detector_kind", ["polar", "cartesian"])
def test_fast_frames_are_statistically_todays(detector_kind):
    """Same sensor, same spots (fixed shift, centred profile): per-pixel means and variances
    of 200 fast frames match 200 frames of today's path within their sampling errors."""
    s = Sensor(detector=detector_kind, diameter_m=8.0, obstruction_m=1.0, n_subaps=6)
    cfg = SimulationConfig(profile="centred", turbulence=False, fixed_shift_px=(0.3, -0.2))
    fast, slow = Simulator(s, cfg.replace(seed=5), fast=True), Simulator(s, cfg.replace(seed=6))
    out = np.empty(s.frame_shape, np.uint16)
    a = np.stack([fast.next(out=out).frame.astype(float) for _ in range(200)])
    b = np.stack([slow.next().frame.astype(float) for _ in range(200)])
    assert fast.next(out=out).frame is out
    expect = Simulator(s.replace(dtype="float32"), cfg.replace(noise=False)).next().frame.astype(float)
    lit = expect > 2
    for x in (a, b):
        z = (x.mean(0) - expect)[lit] / np.sqrt(expect[lit] / 200)
        assert abs(z.mean()) < 0.2 and 0.8 < z.std() < 1.2     # unbiased, Poisson-sized
        assert abs(np.median(x.var(0)[lit] / expect[lit]) - 1) < 0.15
    np.testing.assert_array_equal(a[:, expect == 0], 0)
    assert abs(a.sum() / b.sum() - 1) < 3e-3


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("cfg", [
    SimulationConfig(profile="uncentred", seed=3, noise=False),                  # frozen flow
    SimulationConfig(profile="measured", measured_index=40, noise=False, turbulence=False,
                     fixed_shift_px=(2.6, -1.9)),                                # large shift
])
def test_fast_polar_noise_free_frames_equal_the_exact_ones(cfg):
    """Full pupil, polar: the tabulated line (cubic Hermite reads) gives the exact path's
    expected counts to 2e-6 of a subaperture's light per pixel (measured ~4e-7) and its
    truncation to 1e-6; the blocks outside the pupil are zeroed in a dirty buffer."""
    s = Sensor(detector="polar", dtype="float32")
    exact = Simulator(s, cfg).next()
    fast_sim = Simulator(s, cfg, fast=True)
    assert fast_sim._renderer is not None                          # the fused path is tested
    buf = np.full(s.frame_shape, 7.0, np.float32)
    fast = fast_sim.next(out=buf)
    assert fast.frame is buf
    np.testing.assert_allclose(fast.frame, exact.frame, rtol=0, atol=2e-6 * s.photons)
    np.testing.assert_allclose(fast.truncated, exact.truncated, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(fast.truth, exact.truth)
    assert exact.frame.max() > 100 and np.count_nonzero(buf == 7.0) == 0


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_fast_cartesian_noise_free_frames_equal_the_exact_ones():
    """Full pupil, cartesian: the compiled banded node sum (the same nodes, the same core
    table) gives the exact path's expected counts to 2e-6 of a subaperture's light per
    pixel (measured ~1.6e-7 of the peak pixel), its truncation to 1e-6."""
    s = Sensor(detector="cartesian", dtype="float32")
    cfg = SimulationConfig(profile="uncentred", seed=2, noise=False)
    a = Simulator(s, cfg, fast=True).next(out=np.full(s.frame_shape, 9.0, np.float32))
    b = Simulator(s, cfg).next()
    np.testing.assert_allclose(a.frame, b.frame, rtol=0, atol=2e-6 * s.photons)
    np.testing.assert_allclose(a.truncated, b.truncated, rtol=0, atol=1e-6)
    assert b.frame.max() > 100 and np.count_nonzero(a.frame == 9.0) == 0


def test_fast_with_background_takes_the_general_path():
    """Read noise or background: not the fused kernel, expose's general path."""
    s = Sensor(detector="polar", diameter_m=8.0, obstruction_m=1.0, n_subaps=6, background_e=2.0)
    sim = Simulator(s, SimulationConfig(profile="centred", seed=1), fast=True)
    assert sim._renderer is None and sim.next().frame.shape == s.frame_shape
