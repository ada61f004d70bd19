"""Sodium layer profiles: statistics, fitter, fitted model, fixed cases, evolving profile."""

import math

import numpy as np
import pytest

from lgs_wfs_ros.optics import sodium as na


@pytest.fixture(scope="module")
def measured():
    return na.load_measured()


@pytest.fixture(scope="module")
def grid():
    return na.default_altitude_grid()


# -- loading and statistics ---------------------------------------------------------------
def test_load_measured_shapes_and_clipping(measured):
    h, prof = measured
    assert h.shape == (1584,) and prof.shape == (88, 1584)
    assert np.all(np.diff(h) > 0) and 80e3 < h[0] < 82e3 and 118e3 < h[-1] < 120e3
    assert prof.min() == 0.0                      # raw file has negative noise values


def test_load_measured_missing_file_is_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="sodium profiles not found"):
        na.load_measured(tmp_path / "nope.npz")


def test_statistics_of_a_gaussian(grid):
    rho = na.gaussian_profile(grid, 95e3, 8e3)           # edges at 5.9 sigma: no truncation
    assert na.centroid_altitude(grid, rho) == pytest.approx(95e3, abs=0.01)
    assert na.fwhm(grid, rho) == pytest.approx(8e3, abs=1.0)         # 25 m grid, linear crossing
    sigma = 8e3 / (2 * math.sqrt(2 * math.log(2)))
    assert na.rms_width(grid, rho) == pytest.approx(sigma, rel=1e-4)
    # vectorised over leading axes, inputs untouched
    stack = np.stack([rho, 2 * rho])
    before = stack.copy()
    np.testing.assert_allclose(na.fwhm(grid, stack), [8e3, 8e3], atol=1.0)
    np.testing.assert_array_equal(stack, before)


def test_fwhm_of_whole_layer_spans_two_peaks(grid):
    rho = na.gaussian_profile(grid, 86e3, 2e3) + na.gaussian_profile(grid, 94e3, 2e3)
    assert na.fwhm(grid, rho) == pytest.approx(8e3 + 2e3, abs=2.0)


def test_bad_input_raises(grid):
    with pytest.raises(ValueError):
        na.centroid_altitude(grid[::-1], np.ones(grid.size))
    with pytest.raises(ValueError):
        na.centroid_altitude(grid, np.ones(grid.size + 1))
    with pytest.raises(ValueError):
        na.fwhm(grid, np.zeros(grid.size))


def test_cog_offset_matches_exact_geometry(grid):
    # a narrow layer at 95 km images at r (1/h_ref - 1/h) rad
    rho = na.gaussian_profile(grid, 95e3, 300.0)
    expect = 14.75 * (1 / 90e3 - 1 / 95e3) * na.ARCSEC_PER_RAD / 0.5
    assert na.cog_offset_px(grid, rho) == pytest.approx(expect, rel=2e-4)


# -- fitter -----------------------------------------------------------------------------------
def test_fitter_recovers_known_parameters():
    h = np.arange(81e3, 119e3, 24.0)
    truth = np.array([[60.0, 84500.0, 500.0], [90.0, 86200.0, 1200.0], [120.0, 88900.0, 2000.0],
                      [110.0, 92300.0, 2600.0], [25.0, 95500.0, 900.0]])
    y = na.gaussian_sum(h, truth)
    fit = na.fit_five_gaussians(h, y)
    assert fit.shape == (5, 3)
    np.testing.assert_allclose(fit[:, 0], truth[:, 0], rtol=1e-3)
    np.testing.assert_allclose(fit[:, 1], truth[:, 1], atol=2.0)
    np.testing.assert_allclose(fit[:, 2], truth[:, 2], atol=2.0)


def test_fitter_with_noise_stays_close():
    rng = np.random.default_rng(3)
    h = np.arange(81e3, 119e3, 24.0)
    truth = np.array([[60.0, 84500.0, 500.0], [90.0, 86200.0, 1200.0], [120.0, 88900.0, 2000.0],
                      [110.0, 92300.0, 2600.0], [25.0, 95500.0, 900.0]])
    y = rng.poisson(na.gaussian_sum(h, truth)).astype(float)
    fit = na.fit_five_gaussians(h, y)
    assert np.all(np.diff(fit[:, 1]) > 0)                      # sorted by b
    assert np.all(fit[:, 2] >= na.C_MIN_M) and np.all(fit[:, 0] >= 0)
    # the fitted layer keeps the true centroid and width (the parameters may trade off)
    assert na.centroid_altitude(h, na.gaussian_sum(h, fit)) == pytest.approx(
        na.centroid_altitude(h, na.gaussian_sum(h, truth)), abs=20.0)
    assert na.fwhm(h, na.gaussian_sum(h, fit)) == pytest.approx(
        na.fwhm(h, na.gaussian_sum(h, truth)), rel=0.03)


# -- fitted model ------------------------------------------------------------------------------
def _sample_stats(model, grid, n=20000, chunk=2000, seed=7):
    rng = np.random.default_rng(seed)
    cen, fw = [], []
    for _ in range(n // chunk):
        d = model.sample(rng, chunk, grid)
        cen.append(na.centroid_altitude(grid, d))
        fw.append(na.fwhm(grid, d))
    return np.concatenate(cen), np.concatenate(fw)


def test_model_reproduces_measured_statistics(measured, grid):
    h, prof = measured
    model = na.load_model()
    cen, fw = _sample_stats(model, grid)
    m_cen, m_fw = na.centroid_altitude(h, prof), na.fwhm(h, prof)
    assert cen.mean() == pytest.approx(m_cen.mean(), rel=0.10)
    assert cen.std() == pytest.approx(m_cen.std(), rel=0.10)
    assert fw.mean() == pytest.approx(m_fw.mean(), rel=0.10)
    assert fw.std() == pytest.approx(m_fw.std(), rel=0.10)
    # and much tighter than 10 % on the mean altitude (the tolerance above is loose)
    assert abs(cen.mean() - m_cen.mean()) < 20.0


def test_model_sampling_reproducible_and_physical(grid):
    model = na.load_model()
    a = model.sample(np.random.default_rng(42), 500, grid)
    b = model.sample(np.random.default_rng(42), 500, grid)
    assert a.shape == (500, grid.size)
    np.testing.assert_array_equal(a, b)
    assert np.all(a >= 0) and np.all(np.isfinite(a))
    assert not np.array_equal(a, model.sample(np.random.default_rng(43), 500, grid))
    p = model.with_method("independent").sample_params(np.random.default_rng(1), 5000)
    assert np.all(p[..., 0] >= 0) and np.all(p[..., 2] > 0)


def test_model_json_round_trip(tmp_path):
    model = na.load_model()
    again = na.SodiumModel.from_json(model.to_json())
    np.testing.assert_array_equal(again.mean, model.mean)
    np.testing.assert_array_equal(again.z_cov, model.z_cov)
    r1 = model.sample(np.random.default_rng(5), 10)
    r2 = again.sample(np.random.default_rng(5), 10)
    np.testing.assert_array_equal(r1, r2)
    with pytest.raises(ValueError):
        na.SodiumModel.from_json('{"mean": 1}')


def test_model_from_fits_matches_paper_statistics():
    rng = np.random.default_rng(0)
    truth = np.array([[60.0, 84500.0, 500.0], [90.0, 86200.0, 1200.0], [120.0, 88900.0, 2000.0],
                      [110.0, 92300.0, 2600.0], [5.0, 99000.0, 8000.0]])
    fits = truth * (1 + 0.05 * rng.standard_normal((200, 5, 3)))
    model = na.model_from_fits(fits, na._analytic_centroid(fits))
    np.testing.assert_allclose(model.mean, fits.mean(0))
    np.testing.assert_allclose(model.std, fits.std(0, ddof=1))
    # drawn parameters follow the fits' statistics (log-normal vs normal: loose)
    p = model.sample_params(np.random.default_rng(1), 20000)
    np.testing.assert_allclose(p.mean(0), fits.mean(0), rtol=0.02)


# -- fixed cases ------------------------------------------------------------------------------------
@pytest.mark.parametrize("h_ref", [88e3, 90e3, 92e3])
def test_centred_profile_centroid_is_h_ref(grid, h_ref):
    rho = na.centred_profile(grid, h_ref)
    assert na.centroid_altitude(grid, rho) == pytest.approx(h_ref, abs=1.0)
    assert np.all(rho >= 0)
    # not a symmetric profile: mirror image about h_ref differs
    mirrored = np.interp(2 * h_ref - grid, grid, rho)
    assert np.max(np.abs(mirrored - rho)) > 0.2 * rho.max()
    harm = na.centred_profile(grid, h_ref, centre="harmonic")
    assert na.cog_offset_px(grid, harm, h_ref_m=h_ref) == pytest.approx(0.0, abs=1e-3)


def test_centred_profile_on_measured_grid(measured):
    h, _ = measured
    assert na.centroid_altitude(h, na.centred_profile(h)) == pytest.approx(90e3, abs=1.0)


def test_uncentred_profile_bias(grid, measured):
    for h in (grid, measured[0]):
        rho = na.uncentred_profile(h)
        assert na.centroid_altitude(h, rho) < 90e3 - 300.0
        low = rho[(h >= 80e3) & (h < 90e3)].mean()
        high = rho[(h >= 90e3) & (h < 100e3)].mean()
        assert low > 1.3 * high                          # denser in its lower part
        # CoG bias of the outermost subaperture (r = 14.75 m, 0.5"/px): the paper's
        # ~0.45 px; tolerance 0.01 px (the profile is tuned to it)
        bias = na.cog_offset_px(h, rho, r_m=14.75, h_ref_m=90e3, pixel_scale_arcsec=0.5)
        assert bias == pytest.approx(-0.45, abs=0.01)
        # cross-check against a direct light centroid in pixels (no helper)
        delta_px = 14.75 * (1 / 90e3 - 1 / h) * 206264.806 / 0.5
        w = rho * np.gradient(h)
        assert np.sum(w * delta_px) / np.sum(w) == pytest.approx(bias, abs=1e-4)


def test_uncentred_profile_model_shape(grid):
    """shape="model": the model's mean Gaussians, only the lower three brightened."""
    rho = na.uncentred_profile(grid, shape="model")
    assert na.cog_offset_px(grid, rho, r_m=14.75) == pytest.approx(-0.45, abs=1e-6)
    assert rho.max() == pytest.approx(1.0)
    mean = na.load_model().mean
    # the brightening is a common factor on the lower three amplitudes: dividing it out
    # (least squares against the five mean Gaussians) gives the model's mean profile
    basis = np.stack([na.gaussian_sum(grid, mean[k:k + 1]) for k in range(5)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, rho, rcond=None)
    f = coef[:3] / coef[3]
    assert f == pytest.approx(np.full(3, f[0]), rel=1e-6)
    assert f[0] > 1.5                                     # denser in its lower part
    assert coef[4] / coef[3] == pytest.approx(1.0, rel=1e-6)
    with pytest.raises(ValueError, match="shape"):
        na.uncentred_profile(grid, shape="flat")


# -- evolving profile ------------------------------------------------------------------------------
def test_evolving_profile_interpolates(grid):
    rng = np.random.default_rng(2)
    prof = rng.random((4, grid.size))
    ev = na.EvolvingProfile(grid, prof, seconds_per_profile=0.5)
    assert ev.duration_s == 1.5
    for i in range(4):
        np.testing.assert_array_equal(ev.at(0.5 * i), prof[i])
    np.testing.assert_allclose(ev.at(0.6), 0.8 * prof[1] + 0.2 * prof[2], rtol=1e-12)
    t = np.array([0.0, 0.1, 0.25, 0.75, 1.2, 1.5])
    many = ev.at_many(t)
    assert many.shape == (6, grid.size)
    for k, tk in enumerate(t):
        np.testing.assert_allclose(many[k], ev.at(tk), rtol=1e-12)
    # linear in time between knots: the midpoint is the mean of the neighbours
    np.testing.assert_allclose(ev.at(0.25), 0.5 * (prof[0] + prof[1]), rtol=1e-12)
    # clamped outside
    np.testing.assert_array_equal(ev.at(-3.0), prof[0])
    np.testing.assert_array_equal(ev.at(9.0), prof[3])


def test_evolving_profile_wraps(grid):
    prof = np.random.default_rng(3).random((3, grid.size))
    ev = na.EvolvingProfile(grid, prof, end="wrap")
    assert ev.duration_s == 3.0
    np.testing.assert_allclose(ev.at(2.5), 0.5 * (prof[2] + prof[0]), rtol=1e-12)
    np.testing.assert_allclose(ev.at(4.0), prof[1], rtol=1e-12)
    np.testing.assert_allclose(ev.at(-1.0), prof[2], rtol=1e-12)


def test_evolving_measured_at_frame_rate():
    ev = na.EvolvingProfile.measured()
    t = np.arange(0, 2.0, 1 / 700)
    d = ev.at_many(t)
    assert d.shape == (1400, 1584) and np.all(d >= 0)


# -- splits and unseen families -------------------------------------------------------------
def test_measured_split_is_contiguous_disjoint_and_used_by_training():
    from lgs_wfs_ros.learning import dataset
    train, test = na.measured_split("train"), na.measured_split("test")
    assert np.array_equal(np.concatenate([train, test]), np.arange(88))
    assert np.all(np.diff(train) == 1) and np.all(np.diff(test) == 1)
    tr, va = dataset.measured_split(88)
    assert np.array_equal(tr, train) and np.array_equal(va, test)
    # the training prior is fitted on the train block only
    full, m = na.load_model(), na.training_model()
    assert m.fits.shape[0] == train.size
    np.testing.assert_array_equal(m.measured_centroid_m, full.measured_centroid_m[train])
    assert dataset._model() is m
    with pytest.raises(ValueError, match="unknown split"):
        na.measured_split("validation")


def test_subaperture_batch_default_prior_is_the_training_model(monkeypatch):
    from lgs_wfs_ros.optics import simulator
    from lgs_wfs_ros.sensor import Sensor
    seen = []
    real = na.training_model

    def spy():
        seen.append(1)
        return real()
    monkeypatch.setattr(na, "training_model", spy)
    simulator.subaperture_batch(Sensor.paper_single("polar"), np.random.default_rng(0), 3)
    assert seen


def test_unseen_families_sit_where_training_does_not(measured):
    h_m, prof = measured
    train_c = na.centroid_altitude(h_m, prof[na.measured_split("train")])
    train_w = na.fwhm(h_m, prof[na.measured_split("train")], smooth_m=300)
    out = {}
    for fam in na.FAMILIES:
        h, d = na.unseen_profiles(fam, 700, 700.0, seed=3)
        assert d.shape == (700, h.size) and np.all(d >= 0)
        out[fam] = (na.centroid_altitude(h, d), na.fwhm(h, d, smooth_m=300))
        assert np.std(out[fam][0]) > 0 or fam == "sporadic"     # evolving, not frozen
    assert np.all((out["high"][0] > 99.5e3) & (out["high"][0] < 105.5e3))
    assert out["broad"][1].min() > 1.25 * train_w.max()
    assert out["narrow"][1].max() < 0.5 * train_w.min()
    assert out["sporadic"][1].max() < 1.5e3                  # the thin layer sets the maximum
    c = out["measured"][0]
    assert abs(c.mean() - train_c.mean()) < 1e3             # same night, other block
    # the test block is what it draws from: it equals the evolving test block at t0 (clamp)
    h, d = na.unseen_profiles("measured", 1, 700.0, seed=3)
    evo = na.EvolvingProfile(h_m, prof[na.measured_split("test")])
    ts = np.linspace(0, evo.duration_s, 2001)
    best = min(np.abs(na._interp_rows(h_m, evo.at_many(ts[i:i + 1]), h) - d).max()
               for i in range(0, 2001, 1))
    assert best < 0.05 * d.max()
    with pytest.raises(ValueError, match="unknown profile family"):
        na.unseen_profiles("wide", 3, 700.0)


def test_paper_profiles_are_one_place_for_simulator_and_reproduction():
    """The simulator's fixed cases are sodium.paper_profile's arrays; the centred one gives an
    unbiased CoG and the uncentred one the paper's -0.45 px at the outermost subaperture."""
    from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator
    from lgs_wfs_ros.sensor import Sensor
    sensor = Sensor.paper_single("polar")
    h = na.default_altitude_grid()
    for name in ("centred", "uncentred"):
        hs, rho = Simulator(sensor, SimulationConfig(profile=name, seed=0))._profile_setup()
        np.testing.assert_array_equal(hs, h)
        np.testing.assert_array_equal(rho, na.paper_profile(name, h))
    assert abs(na.cog_offset_px(h, na.paper_profile("centred", h), r_m=14.75)) < 0.01
    assert abs(na.cog_offset_px(h, na.paper_profile("uncentred", h), r_m=14.75) + 0.45) < 0.01
    with pytest.raises(ValueError, match="uncentred_model"):
        na.paper_profile("nope", h)
