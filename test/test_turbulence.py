"""Turbulence: spectra against theory, phase screens, frozen-flow G-tilts."""

import math

import numpy as np
import pytest
import scipy.integrate
import scipy.special

from lgs_wfs_ros.optics import turbulence as T
from lgs_wfs_ros.optics.geometry import layout
from lgs_wfs_ros.sensor import Sensor

R0 = 0.15
LAM0 = 500e-9


def small_sensor(**kw):
    """A 16 x 16 subaperture, 8 m pupil (d = 0.5 m) to keep screens small."""
    base = dict(diameter_m=8.0, obstruction_m=0.0, n_subaps=16)
    base.update(kw)
    return Sensor(**base)


# ----------------------------------------------------------------------------- theory
@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
def test_psd_normalisation_gives_kolmogorov_structure_function():
    # D(r) = 4 pi int Phi(k) (1 - J0(2 pi k r)) k dk must be 6.88 (r/r0)^(5/3).
    for r in (0.1, 1.0):
        f = lambda lk: (T.phase_psd(math.exp(lk), R0) * (1 - scipy.special.j0(2 * math.pi * math.exp(lk) * r))
                        * math.exp(2 * lk))
        edges = np.log([1e-8, 1e-3, 1e-1, 1, 10, 100, 1e3, 1e4])
        val = 4 * math.pi * sum(scipy.integrate.quad(f, a, b, limit=400)[0] for a, b in zip(edges[:-1], edges[1:]))
        assert val == pytest.approx(float(T.structure_function_theory(r, R0)), rel=5e-3)
    # von Karman lies below Kolmogorov; at small r, D_vK / D_K = 1 - 1.485 (r/L0)^(1/3) + ...
    r = np.array([1e-4, 0.01, 5.0])
    ratio = T.structure_function_theory(r, R0, 20.0) / T.structure_function_theory(r, R0)
    assert ratio[2] < 0.8
    assert np.allclose(ratio[:2], 1 - 1.485 * (r[:2] / 20.0) ** (1 / 3), atol=0.01)


def test_gtilt_theory_matches_classic_circular_and_square():
    unit = (LAM0 / 0.5) ** 2 * (0.5 / R0) ** (5 / 3)
    circ = T.gtilt_variance_theory(0.5, R0, LAM0, aperture="circle") / unit
    sq = T.gtilt_variance_theory(0.5, R0, LAM0, aperture="square") / unit
    assert circ == pytest.approx(0.170, abs=0.002)      # Tyler / Sasiela G-tilt per axis
    assert circ < 0.182                                 # below the Z-tilt
    assert sq == pytest.approx(0.1629, abs=0.001)
    assert 0.94 < sq / circ < 0.97


def test_gtilt_theory_scaling_achromatic_and_outer_scale():
    v = T.gtilt_variance_theory(0.5, R0, LAM0)
    # d^(-1/3) and r0^(-5/3) power laws for Kolmogorov
    assert T.gtilt_variance_theory(1.0, R0, LAM0) == pytest.approx(v * 2 ** (-1 / 3), rel=1e-9)
    assert T.gtilt_variance_theory(0.5, 2 * R0, LAM0) == pytest.approx(v * 2 ** (-5 / 3), rel=1e-9)
    # r0 scales as lambda^(6/5): the angle variance does not depend on the wavelength
    lam2 = 589e-9
    assert T.gtilt_variance_theory(0.5, R0 * (lam2 / LAM0) ** 1.2, lam2) == pytest.approx(v, rel=1e-9)
    # outer scale reduces it, monotonically, and L0 -> inf recovers Kolmogorov
    vk = [T.gtilt_variance_theory(0.5, R0, LAM0, L0) for L0 in (5.0, 25.0, 100.0, 1e6)]
    assert vk[0] < vk[1] < vk[2] < vk[3] < v
    assert vk[3] == pytest.approx(v, rel=0.02)


def test_turbulence_sigma_px_default_sensor():
    s = T.turbulence_sigma_px(Sensor())
    assert 0.3 < s < 0.5
    expected = math.sqrt(T.gtilt_variance_theory(0.5, 0.15, 500e-9)) / Sensor().pixel_scale_rad
    assert s == pytest.approx(expected, rel=1e-12)
    assert T.turbulence_sigma_px(Sensor(outer_scale_m=25.0)) < s


def test_random_displacements():
    rng = np.random.default_rng(3)
    d = T.random_displacements(rng, 200_000, 0.4)
    assert d.shape == (200_000, 2)
    assert np.allclose(d.std(axis=0), 0.4, rtol=0.01)
    assert np.allclose(d.mean(axis=0), 0.0, atol=0.005)
    assert np.array_equal(T.random_displacements(7, 10, 1.0), T.random_displacements(7, 10, 1.0))
    assert T.random_displacements(1, 0, 1.0).shape == (0, 2)
    with pytest.raises(ValueError):
        T.random_displacements(rng, -1, 1.0)
    with pytest.raises(ValueError):
        T.random_displacements(rng, 3, -0.1)


# ----------------------------------------------------------------------------- screens
def _structure(ph, lags):
    return np.array([0.5 * (np.mean((ph[:, l:] - ph[:, :-l]) ** 2) + np.mean((ph[l:] - ph[:-l]) ** 2))
                     for l in lags])


def test_phase_screen_structure_function_2cm_to_5m():
    """Average D(r) over many screens within 15 % of 6.88 (r/r0)^(5/3), 2 cm .. 5 m.

    Small separations on 2 cm-pixel screens (5 m wide), large ones on 10 cm-pixel screens
    (12.8 m wide); many seeds because a screen's largest scales are few random numbers.
    """
    lags_fine = np.array([1, 2, 5, 10, 25])                  # 2 cm .. 0.5 m
    fine = np.mean([_structure(T.phase_screen(256, 0.02, R0, seed=s), lags_fine) for s in range(60)], axis=0)
    lags_coarse = np.array([5, 10, 20, 50])                   # 0.5 m .. 5 m
    coarse = np.mean([_structure(T.phase_screen(128, 0.10, R0, seed=1000 + s), lags_coarse)
                      for s in range(300)], axis=0)
    r = np.concatenate([lags_fine * 0.02, lags_coarse * 0.10])
    ratio = np.concatenate([fine, coarse]) / T.structure_function_theory(r, R0)
    assert np.all(np.abs(ratio - 1) < 0.15), dict(zip(r.round(2), ratio.round(3)))


def test_phase_screen_reproducible_and_not_mutating():
    a = T.phase_screen(64, 0.05, R0, seed=5)
    b = T.phase_screen(64, 0.05, R0, seed=5)
    c = T.phase_screen(64, 0.05, R0, seed=6)
    assert np.array_equal(a, b) and not np.allclose(a, c)
    scr = T.PhaseScreen((64, 64), 0.05, R0, seed=1)
    assert not scr.torus.flags.writeable
    # the point evaluator agrees with the grid on sample points
    y, x = np.mgrid[0:5, 0:7] * 0.05
    assert np.allclose(scr.phase(x, y), scr.grid(5, 7), atol=1e-4)
    with pytest.raises(ValueError):
        T.PhaseScreen((4, 64), 0.05, R0)
    with pytest.raises(ValueError):
        T.phase_screen(64, 0.05, -1.0)
    with pytest.raises(ValueError):
        T.phase_screen(64, 0.05, R0, seed=-3)


# ----------------------------------------------------------------------------- frozen flow
def test_tilt_variance_matches_gtilt_theory():
    """d = 0.5 m, r0 = 0.15 m: mean square tilt over subapertures, frames, seeds within 15 %."""
    sensor = small_sensor()
    acc = []
    for seed in range(96):                                    # std of the mean ~4 %
        ff = T.FrozenFlow(sensor, seed, period_m=32.0)
        frames = np.arange(0, 2240, 70)                      # 1 m apart, one 32 m period
        t = np.stack([ff.tilts_at(int(k)) for k in frames])  # (F, n, 2) pixels
        acc.append(np.mean(t ** 2, axis=(0, 1)))
    var_px = np.mean(acc, axis=0)                             # per axis
    theory = T.gtilt_variance_theory(0.5, R0, LAM0) / sensor.pixel_scale_rad ** 2
    assert np.all(np.abs(var_px / theory - 1) < 0.15), var_px / theory


@pytest.mark.parametrize("L0", [math.inf, 25.0])
def test_screen_model_expected_tilt_variance_matches_theory(L0):
    """Noise-free check: the ensemble G-tilt variance of the discrete screen model (FFT cells
    through the trapezoid-edge filter + analytic modes) equals the theory within 2 %."""
    for sensor in (small_sensor(outer_scale_m=L0), Sensor(outer_scale_m=L0)):
        ff = T.FrozenFlow(sensor, 0, period_m=32.0)
        expected = ff.screen.expected_gtilt_variance(sensor.subap_pitch_m, ff.m)
        theory = T.gtilt_variance_theory(0.5, R0, 1.0, L0) * (2 * math.pi) ** 2
        assert np.allclose(expected / theory, 1.0, atol=0.02), expected / theory


def test_von_karman_reduces_tilt_variance():
    """L0 = 10 m against Kolmogorov on the same seeds: the ratio of mean-square G-tilts equals
    the screen model's exact expectation within 4 standard errors, the standard error taken
    from the seeds themselves (paired delta method, 3.5 % of the ratio with 64 seeds: a
    variance 17 % off fails), and that expectation equals the theory within 2 %."""
    kol_ms, vk_ms = [], []
    frames = range(0, 2240, 70)                               # 1 m apart, one 32 m period
    for seed in range(64):
        kol = T.FrozenFlow(small_sensor(), seed, period_m=32.0)
        vk = T.FrozenFlow(small_sensor(outer_scale_m=10.0), seed, period_m=32.0)
        kol_ms.append(np.mean([np.mean(kol.tilts_at(k) ** 2) for k in frames]))
        vk_ms.append(np.mean([np.mean(vk.tilts_at(k) ** 2) for k in frames]))
    a, b = np.array(kol_ms), np.array(vk_ms)
    ratio = b.mean() / a.mean()
    se = np.std(b - ratio * a, ddof=1) / math.sqrt(a.size) / a.mean()
    exact = float(np.mean(vk.screen.expected_gtilt_variance(0.5, vk.m)
                          / kol.screen.expected_gtilt_variance(0.5, kol.m)))
    theory = T.gtilt_variance_theory(0.5, R0, LAM0, 10.0) / T.gtilt_variance_theory(0.5, R0, LAM0)
    assert exact == pytest.approx(theory, rel=0.02)
    assert se < 0.05 * theory, se                             # resolving enough to mean something
    assert abs(ratio - exact) < 4 * se, (ratio, exact, se)


@pytest.mark.parametrize("direction,speed,shift", [(0.0, 10.0, (0, 1)), (90.0, 10.0, (1, 0)),
                                                   (180.0, 10.0, (0, -1)), (45.0, 10 * math.sqrt(2), (1, 1))])
def test_frozen_flow_moves_the_screen(direction, speed, shift):
    """Frame k+35 at subaperture (i, j) equals frame k at (i, j) - shift (0.5 m per axis at 700 Hz)."""
    sensor = small_sensor(wind_direction_deg=direction, wind_speed_mps=speed)
    ff = T.FrozenFlow(sensor, 11, period_m=32.0)
    lay = layout(sensor)
    pos = {tuple(ij): n for n, ij in enumerate(lay.index)}
    pairs = [(n, pos[(i - shift[0], j - shift[1])]) for n, (i, j) in enumerate(lay.index)
             if (i - shift[0], j - shift[1]) in pos]
    assert len(pairs) > 150
    now, prev = np.array(pairs).T
    for k in (0, 3, 1000):
        a, b = ff.tilts_at(k + 35), ff.tilts_at(k)
        assert np.allclose(a[now], b[prev], rtol=0, atol=1e-9)
        assert not np.allclose(a, b, atol=1e-3)             # the tilts really change
    # next_tilts / tilts walk the same sequence
    seq = ff.tilts(4)
    assert seq.shape == (4, lay.n_valid, 2)
    assert np.array_equal(seq[2], ff.tilts_at(2)) and ff.frame == 4
    assert np.array_equal(ff.next_tilts(), ff.tilts_at(4))


def test_same_seed_same_tilts_different_seed_different():
    s = small_sensor()
    a = T.FrozenFlow(s, 3, period_m=32.0).tilts(5)
    b = T.FrozenFlow(s, 3, period_m=32.0).tilts(5)
    c = T.FrozenFlow(s, 4, period_m=32.0).tilts(5)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    g1, g2 = np.random.default_rng(9), np.random.default_rng(9)
    assert np.array_equal(T.FrozenFlow(s, g1, period_m=32.0).tilts(2),
                          T.FrozenFlow(s, g2, period_m=32.0).tilts(2))


def test_gtilt_sign_units_and_exactness_on_known_screens():
    """Replace the screen by a ramp / a parabola in x: the G-tilt is known exactly."""
    sensor = small_sensor(wind_direction_deg=30.0)
    ff = T.FrozenFlow(sensor, 0, period_m=32.0)
    ff._mode_a = np.zeros_like(ff._mode_a)                   # no analytic modes
    ny, nx = ff._padded.shape
    x = np.arange(nx) * ff.pixel_m                            # torus x coordinate, m
    lam_over_pix = LAM0 / (2 * math.pi) / sensor.pixel_scale_rad
    lay = layout(sensor)
    # ramp: phase = g x  (OPD increasing along +x -> spot moves +x)
    g = 3.0                                                   # rad/m
    ff._padded = np.broadcast_to(g * x, (ny, nx)).astype(np.float32)
    t = ff.tilts_at(0)
    assert np.allclose(t[:, 0], g * lam_over_pix, rtol=1e-5) and np.allclose(t[:, 1], 0, atol=1e-6)
    # parabola: phase = a x^2 -> mean gradient over the square = 2 a x_centre, exact with the
    # trapezoid edges, also for a sub-pixel frozen-flow shift.
    a = 0.5
    ff._padded = np.broadcast_to(a * x ** 2, (ny, nx)).astype(np.float64)
    for k in (0, 1):
        ix, iy, fx, fy = ff._shift(k)
        col0 = ix % ff.screen.shape[1]                        # window start in the padded torus
        xc = (lay.index[:, 1] + 0.5) * ff.d + (col0 + fx) * ff.pixel_m   # torus coords
        t = ff.tilts_at(k)
        assert np.allclose(t[:, 0], 2 * a * xc * lam_over_pix, rtol=1e-9)
        assert np.allclose(t[:, 1], 0, atol=1e-9)
    assert ff._shift(1)[2] != 0.0                             # frame 1 really is sub-pixel


def test_single_subaperture_sensor():
    s = Sensor.paper_single("polar")
    ff = T.FrozenFlow(s, 2)
    t = ff.tilts(50)
    assert t.shape == (50, 1, 2) and np.all(np.isfinite(t))
    assert np.array_equal(t, T.FrozenFlow(s, 2).tilts(50))
    # rms over many frames and seeds is of the expected order
    flows = [T.FrozenFlow(s, seed, period_m=32.0) for seed in range(8)]
    rms = np.sqrt(np.mean([np.mean(ff.tilts_at(k) ** 2) for ff in flows for k in range(0, 2240, 35)]))
    assert 0.5 * T.turbulence_sigma_px(s) < rms < 1.5 * T.turbulence_sigma_px(s)


def test_frozen_flow_full_pupil_default_sensor():
    s = Sensor()
    ff = T.FrozenFlow(s, 0)
    t = ff.next_tilts()
    assert t.shape == (layout(s).n_valid, 2)
    assert ff.period_m == (64.0, 256.0) and ff.period_frames == pytest.approx(256.0 / (10 / 700))
    assert ff.nbytes < 64 * 2 ** 20


def test_frozen_flow_bad_input():
    with pytest.raises(ValueError):
        T.FrozenFlow("sensor", 0)
    with pytest.raises(ValueError):
        T.FrozenFlow(small_sensor(), 0, samples_per_subap=1)
    with pytest.raises(ValueError):
        T.FrozenFlow(small_sensor(), -1)
    ff = T.FrozenFlow(small_sensor(), 0, period_m=32.0)
    with pytest.raises(ValueError):
        ff.tilts_at(-1)
    with pytest.raises(ValueError):
        ff.tilts(-2)
