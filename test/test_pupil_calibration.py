"""Pupil calibration: the profile from the whole pupil, the estimators that use it, replay."""

from pathlib import Path

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import options as table
from lgs_wfs_ros.centroiding import pupil as pupil_cal
from lgs_wfs_ros.centroiding.linearize import ResponseMap
from lgs_wfs_ros.centroiding.pupil import PupilCalibration
from lgs_wfs_ros.optics import geometry, sodium
from lgs_wfs_ros.optics.model_spot import Projection, projected_hats, shift_to_detector
from lgs_wfs_ros.optics.spots import NO_LIGHT, SpotModel
from lgs_wfs_ros.sensor import Sensor
from pupils import SMALL


def true_spots(sensor, family, seed=2):
    lay = geometry.layout(sensor)
    h, d = sodium.unseen_profiles(family, 1, 700.0, seed=seed)
    return h, d[0], SpotModel(sensor, lay.r_m, lay.e, h, d[0], max_shift_px=3.5)


def core_altitude(h, d, frac=0.05):
    """Harmonic altitude of the part of a profile above ``frac`` of its peak (the faint
    lidar floor far from the layer falls outside every field: no pupil can see it)."""
    return sodium.harmonic_altitude(h, np.where(d > frac * d.max(), d, 0.0))


def cog_block(img):
    """``(n, 2)`` CoG of unit images, block pixel axes."""
    p = img.shape[-1]
    y, x = np.indices((p, p), dtype=float)
    flat = img.reshape(img.shape[0], -1)
    return np.stack([flat @ (x.ravel() - (p - 1) / 2), flat @ (y.ravel() - (p - 1) / 2)], 1) \
        / flat.sum(1)[:, None]


@pytest.mark.parametrize("detector,launch,zenith,family", [
    ("polar", 0.0, 0.0, "narrow"), ("cartesian", 16.0, 30.0, "measured"),
    ("polar", 16.0, 0.0, "sporadic"), ("polar", 0.0, 0.0, "high")])
def test_noise_free_pupil_gives_profile_origin_and_bias(detector, launch, zenith, family):
    """One noise-free frame at zero tilt: the fitted profile has the true harmonic altitude
    (the origin) and width, and the CoG bias it implies is the true one to 1e-3 px, whatever
    the launch, zenith angle and truncation."""
    s = SMALL.replace(detector=detector, launch_xy_m=(launch, 0.0), zenith_deg=zenith)
    h, d, sm = true_spots(s, family)
    n = geometry.layout(s).n_valid
    img, trunc = sm.images(np.zeros((n, 2)))
    cal = PupilCalibration(s, period=1)
    assert cal.observe(img.reshape(n, -1) * 1000.0)
    he, de = cal.profile
    assert abs(core_altitude(he, de) - core_altitude(h, d)) < 40.0
    fw = sodium.fwhm(h, d)                  # nodes are ~450 m apart near 90 km
    assert abs(sodium.fwhm(he, de) - fw) < max(0.25 * fw, 300.0)
    true_bias = cog_block(img)
    assert np.abs(true_bias).max() > 0.1                       # a bias to remove
    assert np.abs(cal.cog_bias() - true_bias).max() < 0.01
    # the prior alone (no calibration) is off: the test can fail
    assert np.abs(PupilCalibration(s).cog_bias() - true_bias).max() > 0.03


def test_tilted_frames_of_truncated_spots_give_the_true_profile():
    """Frames under independent random tilts (0.46 px rms per axis, as a closed loop leaves
    them), each counted inside its field (docs/conventions.md), of a layer at 100-105 km whose
    outer spots the field cuts: the fit models the tilt blur and the outward pull of the
    per-frame normalisation, so the CoG bias it implies matches the true spot's at zero tilt.
    (The fit without that pull was off by 0.038 px on the truncated spots.)"""
    s = SMALL.replace(detector="polar")
    h, d, sm = true_spots(s, "high")
    n = geometry.layout(s).n_valid
    img0, trunc = sm.images(np.zeros((n, 2)))
    frac = img0.reshape(n, -1).sum(axis=1)
    assert (frac < 0.9).sum() > 100                            # truncated spots in the pupil
    rng = np.random.default_rng(5)
    cal = PupilCalibration(s, period=300, time_constant_s=0.0)
    for _ in range(300):
        img, _ = sm.images(rng.normal(0.0, 0.46, (n, 2)))
        flat = img.reshape(n, -1)
        cal.observe(flat / flat.sum(axis=1, keepdims=True) * 1000.0)
    assert cal.fits == 1 and 0.40 < cal.blur_px < 0.52
    err = np.abs(cal.cog_bias() - cog_block(img0))[:, 0]
    cut = frac < 0.9
    assert err[cut].max() < 0.022 and err[~cut].max() < 0.012


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
def test_a_block_moved_by_node_steps_is_its_spot_rendered_moved(detector):
    """Nodes are even in 1/h, so a step along them moves every thin layer's spot of a block
    by the same ``delta_s`` px along e: the basis read ``0.8 / delta_s`` nodes on is the
    basis rendered 0.8 px along e, to 2 % (unmoved it is 80 % off, moved the wrong way
    120 %). What the fit moves a block's model by when its lasting tilt is large."""
    s = SMALL.replace(detector=detector, launch_xy_m=(8.0, 0.0))
    cal = PupilCalibration(s)
    b, lay = cal.basis, cal.layout
    k = b.shape[2]
    rendered = projected_hats(s, lay.r_m, lay.e, cal.nodes_m, cal.projection, 0.8 * cal._e_pix, lay)
    nodes = 0.8 / cal._node_step_px(lay.r_m)
    rows = np.flatnonzero(nodes < pupil_cal.MAX_NODE_SHIFT * k)
    assert rows.size > 0.95 * nodes.size
    inside = np.arange(k)[None, :] + np.ceil(nodes[rows])[:, None] < k - 1   # reads within the nodes
    keep = np.broadcast_to(inside[:, None, :], (rows.size,) + b.shape[1:])
    want = rendered[rows][keep]

    def off(model):
        return np.linalg.norm(model[keep] - want) / np.linalg.norm(want)
    assert off(pupil_cal._node_shifted(b[rows], nodes[rows])) < 0.025
    assert off(b[rows]) > 0.5 and off(pupil_cal._node_shifted(b[rows], -nodes[rows])) > 0.5


def test_a_window_of_large_lasting_tilts_settles_once_the_models_move(monkeypatch):
    """A side launch (16 m) under frozen flow: one refit's unit-light projected means of the
    full cartesian pupil, taken from the simulator's frames (seed 3, L0 infinite, evolving
    measured profiles, 1000 photons; lasting tilts 0.45 px rms along e, up to 1.4 px;
    test/data/side_launch_frozen_window.npz). With every shift carried by the first-order
    term the iterates alternate between two zig-zag profiles (light on every other node);
    once the largest shifts move their blocks' models the fit settles on a smooth one."""
    data = np.load(Path(__file__).parent / "data" / "side_launch_frozen_window.npz")
    cal = PupilCalibration(Sensor(detector="cartesian", launch_xy_m=(16.0, 0.0)))
    cal.blur_px = float(data["blur_px"])
    z = data["z"].astype(float)
    ok = np.ones(cal.n, dtype=bool)

    def iterates():
        xs = [cal.solve(z, ok, iterations=it) for it in (8, 9, 10)]
        step = max(np.abs(b - a).max() / a.max() for a, b in zip(xs, xs[1:]))
        return step, np.abs(np.diff(xs[-1], 2)).sum()     # light is unit: the zig-zag's share
    step, rough = iterates()
    assert step < 0.01 and rough < 0.25
    monkeypatch.setattr(pupil_cal, "MOVE_AFTER", 99)                  # first order only
    step, rough = iterates()
    assert step > 0.3 and rough > 0.8


@pytest.mark.parametrize("family", ["measured", "narrow", "sporadic"])
def test_each_subapertures_lasting_tilt_is_left_free(family):
    """One noise-free frame whose spots sit displaced along e by lasting tilts (0.15 px rms,
    as the mean of a window of closed-loop residuals leaves them), opposite in each pair of
    subapertures mirrored through the launch (so no altitude pattern: the pupil cannot tell
    that one from the profile): the fit leaves each block's shift free, so the CoG bias it
    implies is the untilted spot's. (Fitted as part of the profile, those shifts left
    0.011 px rms on each family.)"""
    s = SMALL.replace(detector="polar")
    h, d, sm = true_spots(s, family)
    lay = geometry.layout(s)
    n = lay.n_valid
    xy = np.round(np.asarray(lay.centre_xy_m) * 2).astype(int)
    index = {tuple(p): i for i, p in enumerate(xy)}
    mirror = np.array([index[(-a, -b)] for a, b in xy])
    mu = np.random.default_rng(0).normal(0.0, 0.15, n)
    mu = np.where(np.arange(n) < mirror, mu, -mu[mirror])
    img, _ = sm.images(np.stack([mu, np.zeros(n)], axis=1))       # block x is e (polar)
    flat = img.reshape(n, -1)
    cal = PupilCalibration(s, period=1)
    cal.observe(flat / flat.sum(axis=1, keepdims=True) * 1000.0)
    assert cal.blur_px < 0.1                        # shifts along e only: no blur across it
    err = cal.cog_bias() - cog_block(sm.images(np.zeros((n, 2)))[0])
    assert np.sqrt(np.mean(err ** 2)) < 0.007


def test_noisy_tilted_frames_converge_and_follow_the_average():
    """AR(1) tilts (0.46 px rms, independent) and 1000 photons: 280 frames remove 90 % of the
    CoG bias of a layer far above h_ref."""
    s = SMALL.replace(detector="polar")
    h, d, sm = true_spots(s, "high")
    n = geometry.layout(s).n_valid
    rng = np.random.default_rng(1)
    cal = PupilCalibration(s, period=70, time_constant_s=0.5)
    t = rng.normal(0, 0.46, (n, 2))
    for _ in range(280):
        t = 0.95 * t + np.sqrt(1 - 0.95 ** 2) * rng.normal(0, 0.46, (n, 2))
        img, _ = sm.images(np.clip(t, -3.4, 3.4))
        img /= img.reshape(n, -1).sum(1)[:, None, None]
        cal.observe(rng.poisson(img * 1000.0).reshape(n, -1).astype(np.float32))
    assert cal.fits == 4
    img0, _ = sm.images(np.zeros((n, 2)))
    true_bias = cog_block(img0)
    resid = cal.cog_bias() - true_bias
    assert np.sqrt(np.mean(resid ** 2)) < 0.1 * np.sqrt(np.mean(true_bias ** 2))
    he, de = cal.profile
    # the layer sits 14 km above h_ref, truncated in the outer subapertures: its altitude
    # comes out within 5 % of that offset
    off = core_altitude(h, d) - s.h_ref_m
    assert off > 10e3 and abs(core_altitude(he, de) - core_altitude(h, d)) < 0.05 * off
    # reset forgets it all
    cal.reset()
    assert cal.fits == 0 and np.allclose(cal.light, cal.prior)


def test_trend_follows_a_drifting_profile_without_lag():
    """A layer rising at 1 km/s (noise-free, no tilt; refits every 0.1 s frame, time
    constant 0.2 s): the exponential average alone fits it ~256 m behind the frame it will
    serve (its lag, 0.256 s); with ``trend`` the two averages' drift puts it there to 20 m.
    (A wrong sign, a horizon half a period short or one average used twice: 50 m or more.)"""
    s = Sensor(n_subaps=16, subap_pitch_m=1.0, detector="polar", frame_rate_hz=10.0)
    lay = geometry.layout(s)
    h = np.linspace(70e3, 120e3, 2001)

    def layer(k):                                   # frame k's profile (centre at 0.1 k s)
        return sodium.gaussian_profile(h, 90e3 + 1000.0 * k / 10.0, 8e3)
    frames = []
    for k in range(25):
        img, _ = SpotModel(s, lay.r_m, lay.e, h, layer(k), max_shift_px=3.5).images(
            np.zeros((lay.n_valid, 2)))
        frames.append(img.reshape(lay.n_valid, -1) * 1000.0)
    served = sodium.harmonic_altitude(h, layer(25))  # the next frame, which the refit serves
    error = {}
    for trend in (False, True):
        cal = PupilCalibration(s, period=1, time_constant_s=0.2, trend=trend)
        for f in frames:
            cal.observe(f)
        error[trend] = sodium.harmonic_altitude(*cal.profile) - served
    assert -300.0 < error[False] < -200.0
    assert abs(error[True]) < 20.0
    with pytest.raises(ValueError, match="pupil_trend"):
        PupilCalibration(s, trend="yes")


def _rising_layer_errors(name, options, sensor, frames):
    """``((frames,), centroider)``: the radius-weighted mean error along e (px) of estimator
    ``name`` on noise-free ``frames`` whose truth is zero shift everywhere."""
    lay = geometry.layout(sensor)
    c = table.build(name, sensor, dict(options, pupil_period=6, pupil_time_constant_s=0.4))
    e = np.array([c.centroid(f) for f in frames])
    return (e * lay.e).sum(axis=-1) @ (lay.r_m / (lay.r_m ** 2).sum()), c


@pytest.mark.parametrize("name,options", [("cog", {"bias": "pupil"}), ("cmf", {}), ("ml", {}), ("corr", {}),
                                          ("ann", {"out_of_domain": "warn"})])
def test_estimators_follow_the_profile_drift_between_refits(name, options, monkeypatch):
    """A layer rising at 1 km/s (noise-free, no tilt, polar 16 x 16, 10 Hz; refits every 6
    frames): between refits the spots move on while the references stay, so a reading's
    error climbs through each period by the spots' whole move (a sawtooth). With the trend
    the calibration also fits the profile at the period's end, and the estimators move their
    offsets toward it frame by frame: in the last period the error's climb is cut to under
    0.3 of it, and it stays centred. (Not following: the full climb; the move's sign flipped:
    twice the climb; the phase one off: the error offset by the half-period's move.)"""
    s = Sensor(n_subaps=16, subap_pitch_m=1.0, detector="polar", frame_rate_hz=10.0)
    lay = geometry.layout(s)
    h = np.linspace(70e3, 120e3, 2001)
    frames = [SpotModel(s, lay.r_m, lay.e, h, sodium.gaussian_profile(h, 90e3 + 100.0 * k, 8e3),
                        max_shift_px=3.5).images(np.zeros((lay.n_valid, 2)))[0] * 1000.0
              for k in range(36)]
    # the last whole period: cog and ann take a refit on the frame that completes a period
    # (the 30th), cmf and ml from the next frame on
    last = slice(29, 35) if name not in ("cmf", "ml") else slice(30, 36)
    err, c = _rising_layer_errors(name, options, s, frames)
    err = err[last]
    # the half period's rise, 300 m, in the calibration's description
    assert 200.0 < c.describe()["pupil_calibration"]["altitude_drift_m"] < 400.0
    monkeypatch.setattr(PupilCalibration, "drift_counts", lambda self: None)
    monkeypatch.setattr(PupilCalibration, "drift_marginals", lambda self: None)   # ml's
    still = _rising_layer_errors(name, options, s, frames)[0][last]
    climb = np.ptp(still)
    assert climb > 0.015                          # the spots' move over a period, px
    assert np.ptp(err) < 0.3 * climb              # cog, cmf, ml, ann ~0.1; corr 0.25
    assert abs(err.mean()) < 0.15 * climb
    assert np.all(np.diff(err) > 0)               # what is left climbs the same way


@pytest.mark.parametrize("detector,launch", [("polar", 0.0), ("cartesian", 16.0)])
def test_linearised_cog_reads_the_shift_of_spots_the_field_truncates(detector, launch):
    """A layer at 100-105 km puts the spots at the field's edge, where a CoG reads less than
    the shift: calibrated on one noise-free frame, the CoG with its response inverted reads
    noise-free shifted spots to 0.06 px where the field keeps 95 % of the light, and cuts the
    error of the bias alone by a third or more where the field loses 5-50 % (the rest: the
    profile's tail, fitted from fewer subapertures); the response at zero shift is the bias."""
    s = SMALL.replace(detector=detector, launch_xy_m=(launch, 0.0))
    n = geometry.layout(s).n_valid
    _, _, sm = true_spots(s, "high")
    lin = table.build("cog", s, {"bias": "pupil", "pupil_period": 3})
    off = table.build("cog", s, {"bias": "pupil", "pupil_period": 3, "linearize": False})
    zero, lost = sm.images(np.zeros((n, 2)))
    zero = zero * 1000.0
    for c in (lin, off):                       # a refit at the 3rd frame, none at the 4th, 5th
        for _ in range(3):
            c.centroid(zero)
        assert c.pupil.fits == 1
    dark = lost > 0.5          # side launch: spots mostly beyond the field are not scored
    assert (lost[~dark] > 0.2).sum() > 20
    f0 = lin.pupil.cog_response().at_zero()
    assert np.abs(f0 - lin.pupil.cog_bias())[~dark].max() < 0.01
    shift = np.random.default_rng(5).uniform(-0.9, 0.9, (n, 2))          # detector axes
    img = sm.images(shift)[0] * 1000.0
    err_lin = lin.centroid(img) - shift
    err_off = off.centroid(img) - shift
    assert np.isfinite(err_lin[~dark]).all()
    whole, cut = lost < 0.05, ~dark & (lost >= 0.05)
    assert np.abs(err_lin[whole]).max() < 0.06 and np.abs(err_lin[cut]).max() < 0.12
    assert np.median(np.abs(err_lin[cut])) < 0.7 * np.median(np.abs(err_off[cut]))
    assert np.abs(err_off[~dark]).max() > 0.2
    # beyond the scanned box (+-1.4 px) it falls back on the bias alone, not the raw CoG
    far = np.zeros((n, 2))
    far[:, 0] = 2.0
    img = sm.images(far)[0] * 1000.0
    err_far = np.abs(lin.centroid(img) - far)[~dark]
    err_far_off = np.abs(off.centroid(img) - far)[~dark]
    assert err_far.max() < 2.0 and np.median(err_far) < np.median(err_far_off) + 0.02
    assert lin.pupil.fits == 1


@pytest.mark.parametrize("detector,atol", [("polar", 1e-9), ("cartesian", 2e-4)])
def test_response_scan_from_partial_renders_is_the_full_scan(detector, atol):
    """On polar pixels the CoG along each block axis depends on the shift along it alone,
    and on cartesian ones each node's light is a line along one pixel axis times a core
    along the other: the response fitted from the diagonal's renders (polar) or from the
    moments of 1-D renders (cartesian, float32) is the one the whole grid's renders give
    (a side launch and a layer far above h_ref: spots the field cuts)."""
    s = SMALL.replace(detector=detector, launch_xy_m=(16.0, 0.0))
    n = geometry.layout(s).n_valid
    _, _, sm = true_spots(s, "high")
    c = table.build("cog", s, {"bias": "pupil", "pupil_period": 1})
    c.centroid(sm.images(np.zeros((n, 2)))[0] * 1000.0)
    cal = c.pupil
    spots, p = cal.spots(), s.pixels
    y, x = np.indices((p, p), dtype=float)
    w = np.stack([np.ones(p * p), x.ravel() - (p - 1) / 2, y.ravel() - (p - 1) / 2], axis=1)

    def measure(shift):
        m = spots.image_at(shift).reshape(n, -1) @ w
        floor = NO_LIGHT if detector == "cartesian" else 0.0    # float32 renders: rounding
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(m[:, :1] > floor, m[:, 1:] / m[:, :1], np.nan)
    full = ResponseMap.fit(measure, n, pupil_cal.COG_RESPONSE_EXTENT_PX,
                           *pupil_cal.COG_RESPONSE_GRID)
    fast = cal.cog_response()
    ok = np.isfinite(full.coef).all(axis=(1, 2, 3))
    assert ok.sum() > 0.75 * n
    np.testing.assert_array_equal(np.isfinite(fast.coef).all(axis=(1, 2, 3)), ok)
    np.testing.assert_allclose(fast.coef[ok], full.coef[ok], atol=atol)
    assert np.abs(full.coef[ok][:, 0, 1:, 0]).max() > 0.05      # a response along x to fit
    assert np.abs(full.coef[ok][:, 1, 0, 1:]).max() > 0.05      # and along y


def test_projection_is_linear_and_keeps_light():
    s = SMALL.replace(detector="cartesian")
    lay = geometry.layout(s)
    proj = Projection(s, lay.e)
    rng = np.random.default_rng(0)
    a, b = rng.random((2, lay.n_valid, 256))
    np.testing.assert_allclose(proj(a + 2 * b), proj(a) + 2 * proj(b))
    np.testing.assert_allclose(proj(a).sum(-1), a.sum(-1))
    polar = Projection(s.replace(detector="polar"), np.tile([1.0, 0.0], (lay.n_valid, 1)))
    cols = a.reshape(-1, 16, 16).sum(1)
    p = polar(a)
    np.testing.assert_allclose(p[:, 3:19], cols)              # polar bins are the columns


def _run(sensor, cents, sm, frames, rng, warm):
    n = geometry.layout(sensor).n_valid
    errs = {k: [] for k in cents}
    t = rng.normal(0, 0.46, (n, 2))
    for k in range(frames):
        t = 0.95 * t + np.sqrt(1 - 0.95 ** 2) * rng.normal(0, 0.46, (n, 2))
        tt = np.clip(t, -3.4, 3.4)
        img, _ = sm.images(tt)
        img /= img.reshape(n, -1).sum(1)[:, None, None]
        counts = rng.poisson(img * sensor.photons).astype(np.float32)
        for name, c in cents.items():
            est = c.centroid(counts)
            if k >= warm:
                errs[name].append(est - tt)
    return {k: np.array(v) for k, v in errs.items()}


@pytest.mark.slow
@pytest.mark.parametrize("detector,launch", [("polar", 0.0), ("cartesian", 16.0)])
def test_calibrated_estimators_are_unbiased_on_a_held_out_family(detector, launch):
    """On the 'broad' family (a layer twice as thick as any training profile) the plain CoG
    and the CMF with a model reference are biased; the pupil-calibrated CoG and the default
    CMF (pupil reference) remove at least 80 % of that bias, and are more accurate."""
    s = SMALL.replace(detector=detector, launch_xy_m=(launch, 0.0), photons=1000.0)
    _, _, sm = true_spots(s, "broad")
    cents = {"cog": table.build("cog", s), "cog_pupil": table.build("cog", s, {"bias": "pupil",
                                                                                "pupil_period": 70}),
             "cmf_model": table.build("cmf", s, {"reference": "model"}),
             "cmf": table.build("cmf", s, {"pupil_period": 70})}
    errs = _run(s, cents, sm, 280, np.random.default_rng(3), warm=140)
    # a CoG's gain drops where the field cuts the spot (its mean error then follows the mean
    # tilt, which no bias removes): score the subapertures that keep 95 % of their light
    n = geometry.layout(s).n_valid
    keep = sm.images(np.zeros((n, 2)))[1] < 0.05
    assert keep.sum() > 100
    bias = {k: np.sqrt(np.mean(np.nanmean(e[:, keep], axis=0) ** 2)) for k, e in errs.items()}
    mean2d = {k: np.nanmean(np.hypot(e[..., 0], e[..., 1])) for k, e in errs.items()}
    assert bias["cog"] > 0.1 and bias["cmf_model"] > 0.1
    assert bias["cog_pupil"] < 0.2 * bias["cog"]
    assert bias["cmf"] < 0.2 * bias["cmf_model"]
    assert mean2d["cog_pupil"] < 0.8 * mean2d["cog"] and mean2d["cmf"] < 0.8 * mean2d["cmf_model"]
    assert cents["cmf"].describe()["pupil_calibration"]["fits"] == 4


def test_pupil_reference_installs_exact_derivatives_and_follows_refits():
    s = SMALL.replace(detector="polar")
    c = table.build("cmf", s, {"pupil_period": 2, "filters": "single"})
    assert c.options["reference"] == "pupil" and c.weighting == "model" and c.linearize
    img, dx, dy, flux = c.pupil.counts()
    np.testing.assert_allclose(c.ref.images, img + c.background)
    np.testing.assert_allclose(c.ref.derivatives[0], dx)
    h = 1e-3
    n = c.n
    ex = np.tile([h, 0.0], (n, 1))
    num = (c.pupil.image_at(ex) - c.pupil.image_at(-ex)) / (2 * h)
    np.testing.assert_allclose(num, dx, atol=1e-3 * np.abs(dx).max())
    v0 = c.ref.version
    _, _, sm = true_spots(s, "narrow")
    frame = sm.images(np.zeros((n, 2)))[0] * 1000.0
    c.centroid(frame)
    assert c.ref.version == v0
    c.centroid(frame)                                          # frame 2: a refit
    assert c.ref.version > v0 and c.pupil.fits == 1
    # the refit reference is the narrow profile's spot: the CMF reads ~0 on its own image
    np.testing.assert_allclose(c.centroid(c.pupil.image_at(np.zeros((n, 2))) + c.background),
                               0.0, atol=2e-3)


def test_reference_image_is_the_reference_rendered_once_per_profile(monkeypatch):
    s = SMALL.replace(detector="polar")
    cal = PupilCalibration(s, period=2)
    renders = []
    spots = cal.spots()
    real = type(spots).image_at
    monkeypatch.setattr(type(spots), "image_at", lambda self, shift: renders.append(1) or real(self, shift))
    img = cal.reference_image()
    assert len(renders) == 1                                    # the image alone, no derivatives
    assert cal.reference_image() is img and len(renders) == 1   # cached for this profile
    full = cal.reference()
    assert full[0] is img and len(renders) == 5                 # derivatives added, image reused
    zero = np.zeros((cal.n, 2))                                 # counts at no shift: no render
    np.testing.assert_array_equal(cal.image_at(zero), real(spots, zero) * cal._to_counts(img))
    assert len(renders) == 5
    cal.image_at(zero + [0.1, 0.0])
    assert len(renders) == 6
    _, _, sm = true_spots(s, "narrow")
    frame = sm.images(np.zeros((cal.n, 2)))[0] * 1000.0
    for _ in range(2):
        cal.observe(frame.reshape(cal.n, -1))                    # a refit: a new profile
    new = cal.reference_image()
    assert not np.array_equal(new, img)
    np.testing.assert_array_equal(new, cal.spots().image_at(np.zeros((cal.n, 2))))
    np.testing.assert_array_equal(cal.reference()[0], new)


def test_options_table_offers_the_pupil_and_every_row_has_a_help():
    for alg in ("cmf", "corr"):
        assert table.option(alg, "reference").default == "pupil"
    assert table.option("cog", "bias").choices == ("none", "pupil")
    for alg in ("cog", "cmf", "corr"):
        for k, v in pupil_cal.OPTION_DEFAULTS.items():
            assert table.option(alg, k).default == v
    with pytest.raises(ValueError, match="bias"):
        table.build("cog", SMALL, {"bias": "profile"})


def test_replay_uses_the_options_recorded_in_the_bag(tmp_path, monkeypatch):
    """A bag recorded with non-default options (pupil_period 3) replays to the same slopes
    without being told them; given --options it runs those instead."""
    from lgs_wfs_ros.analysis import bagdata
    from lgs_wfs_ros.analysis.replay import replay_bag
    from lgs_wfs_ros import cli

    path = tmp_path / "live.mcap"
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_period", 3)
    bagdata.make_sample_bag(path, frames=24, algorithms=("cmf",))
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_period", 140)
    res = replay_bag(path, ["cmf"], out=tmp_path / "r.mcap", quiet=True)
    assert res["options"]["cmf"]["source"] == "bag"
    assert res["options"]["cmf"]["options"]["pupil_period"] == 3
    segs = {sg.label: sg for sg in bagdata.load_bag(tmp_path / "r.mcap").segments}
    live, replayed = segs["cmf"].slopes.data, segs["cmf_replay"].slopes.data
    np.testing.assert_allclose(replayed, live, atol=1e-6)
    assert segs["cmf_replay"].description["options"]["pupil_period"] == 3
    # the table's defaults (pupil_period 140) give other slopes: the options mattered
    assert cli.main(["replay", str(path), "--algorithms", "cmf", "--out", str(tmp_path / "d.mcap"),
                     "--options", '{"cmf": {}}']) == 0
    segs = {sg.label: sg for sg in bagdata.load_bag(tmp_path / "d.mcap").segments}
    assert np.abs(segs["cmf_replay"].slopes.data - live).max() > 1e-3
    assert cli.main(["replay", str(path), "--out", str(tmp_path / "e.mcap"),
                     "--options", "{not json"]) == 2


def test_a_cmf_recorded_before_the_grid_default_replays_as_its_single_filter(tmp_path,
                                                                              monkeypatch):
    """A bag whose cmf description has no ``filters`` (recorded when the single filter was
    cmf's default) replays through the single filter, giving the live slopes, not through
    today's default grid."""
    import lgs_wfs_ros.centroiding as centroiding
    from lgs_wfs_ros.analysis import bagdata
    from lgs_wfs_ros.analysis.replay import replay_bag
    from lgs_wfs_ros.centroiding.cmf import CMF

    path = tmp_path / "old.mcap"
    with monkeypatch.context() as m:          # the old registry and the old description
        m.setattr(centroiding, "uses_grid", lambda options: False)
        describe = CMF.describe
        m.setattr(CMF, "describe", lambda self: {**describe(self), "options": {
            k: v for k, v in describe(self)["options"].items() if k != "filters"}})
        bagdata.make_sample_bag(path, frames=12, algorithms=("cmf",))
    res = replay_bag(path, ["cmf"], out=tmp_path / "r.mcap", quiet=True)
    assert res["options"]["cmf"]["options"]["filters"] == "single"
    segs = {sg.label: sg for sg in bagdata.load_bag(tmp_path / "r.mcap").segments}
    np.testing.assert_allclose(segs["cmf_replay"].slopes.data, segs["cmf"].slopes.data,
                               atol=1e-6)
    assert segs["cmf_replay"].description["options"]["filters"] == "single"


def replayed_as_recorded(tmp_path, monkeypatch, cls, alg: str, live: dict, hidden=None) -> tuple:
    """Record a 10-frame bag of ``alg`` run with the options ``live`` (its description
    without the option ``hidden``: a bag recorded before that option existed) and replay it
    with the bag's options: ``(replay result, live slopes, replayed slopes)``."""
    import lgs_wfs_ros.centroiding as centroiding
    from lgs_wfs_ros.analysis import bagdata, replay

    make = centroiding.make_centroider
    path = tmp_path / f"{alg}_{hidden}.mcap"
    with monkeypatch.context() as m:
        m.setattr(centroiding, "make_centroider",
                  lambda a, sensor, **o: make(a, sensor, **{**o, **live}))
        if hidden is not None:
            describe = cls.describe
            m.setattr(cls, "describe", lambda self: {**describe(self), "options": {
                k: v for k, v in describe(self)["options"].items() if k != hidden}})
        bagdata.make_sample_bag(path, frames=10, sensor=SMALL.replace(detector="polar"),
                                algorithms=(alg,))
    out = path.with_name("r_" + path.name)
    res = replay.replay_bag(path, [alg], out=out, quiet=True)
    segs = {sg.label: sg for sg in bagdata.load_bag(out).segments}
    return res, segs[alg].slopes.data, segs[alg + "_replay"].slopes.data


def test_a_calibrated_cog_recorded_before_its_response_replays_with_its_bias_alone(
        tmp_path, monkeypatch):
    """A bag whose cog (bias: pupil) description has no ``linearize`` (recorded when the
    calibrated CoG subtracted its bias alone) replays that way, giving the live slopes; a
    bag recorded today replays with the response inverted."""
    from lgs_wfs_ros.analysis import replay
    from lgs_wfs_ros.centroiding.cog import CoG

    for old in (True, False):
        res, live, again = replayed_as_recorded(
            tmp_path, monkeypatch, CoG, "cog", {"bias": "pupil", "pupil_period": 4, "linearize": not old},
            "linearize" if old else None)
        np.testing.assert_allclose(again, live, atol=1e-6)
        assert res["options"]["cog"]["options"].get("linearize", True) is (not old)
    assert replay.recorded_defaults({"cog": {"bias": "none"}}) == {"cog": {"bias": "none"}}


def test_shift_to_detector_rotates_only_on_polar():
    e = np.array([[0.6, 0.8]])
    v = np.array([[1.0, 0.0]])
    np.testing.assert_allclose(shift_to_detector(SMALL.replace(detector="polar"), e, v), e)
    np.testing.assert_allclose(shift_to_detector(SMALL, e, v), v)


def test_frame_row_and_stack_accumulation_agree():
    """The three ways of feeding frames (integer frame, float32 row buffer, stack) give the
    same profile."""
    s = SMALL.replace(detector="polar")
    lay = geometry.layout(s)
    _, _, sm = true_spots(s, "narrow")
    rng = np.random.default_rng(4)
    frames = [geometry.stack_to_frame(rng.poisson(sm.images(rng.normal(0, 0.3, (lay.n_valid, 2)))[0]
                                                  * 1000).astype(np.uint16), lay) for _ in range(4)]
    cals = [PupilCalibration(s, period=4) for _ in range(3)]
    g, p = s.grid, s.pixels
    valid = np.flatnonzero(lay.valid.ravel())
    for f in frames:
        cals[0].observe_frame(f)
        rows = f.reshape(g, p, g, p).swapaxes(1, 2).reshape(g * g, p * p).astype(np.float32)
        cals[1].observe_rows(rows, valid)
        cals[2].observe(geometry.frame_to_stack(f, lay).reshape(lay.n_valid, -1))
    assert all(c.fits == 1 for c in cals)
    np.testing.assert_allclose(cals[0].light, cals[2].light, atol=1e-9)
    np.testing.assert_allclose(cals[1].light, cals[2].light, atol=1e-6)
    np.testing.assert_allclose(cals[0].flux, cals[2].flux)


def _narrow_polar_frames(seed: int, count: int):
    """The small polar sensor and ``count`` noisy frames (1000 ph) of the narrow family with
    independent tilts of 0.3 px rms."""
    s = SMALL.replace(detector="polar")
    n = geometry.layout(s).n_valid
    _, _, sm = true_spots(s, "narrow")
    rng = np.random.default_rng(seed)
    return s, [rng.poisson(sm.images(rng.normal(0, 0.3, (n, 2)))[0] * 1000.0).astype(float)
               for _ in range(count)]


def test_background_refit_never_blocks_frames_and_installs_the_inline_result():
    """pupil_async: while a refit is held in its thread, frames keep being centroided with
    the old reference (none waits for it); once finished, the next frame installs it, and
    that frame's slopes equal those of the inline (deterministic) mode, which refitted from
    the same frames."""
    import threading
    s, frames = _narrow_polar_frames(seed=5, count=6)
    inline = table.build("cmf", s, {"pupil_period": 2, "filters": "single"})
    live = table.build("cmf", s, {"pupil_period": 2, "pupil_async": True, "filters": "single"})
    gate, prepare = threading.Event(), live.pupil.prepare
    live.pupil.prepare = lambda cal: (gate.wait(60), prepare(cal))[1]
    v0 = live.ref.version
    ref_inline = [inline.centroid(f) for f in frames]
    before = table.build("cmf", s, {"pupil_period": 1000, "filters": "single"})  # never refits
    ref_before = [before.centroid(f) for f in frames]
    for k, f in enumerate(frames[:5]):                           # the refit starts at frame 2
        np.testing.assert_array_equal(live.centroid(f), ref_before[k])
    assert live.pupil.fits == 0 and live.ref.version == v0 and not gate.is_set()
    gate.set()
    live.pupil.wait()
    out = live.centroid(frames[2])                               # installs, then measures
    assert live.pupil.fits == 1 and live.ref.version > v0
    np.testing.assert_array_equal(out, ref_inline[2])
    assert np.abs(out - ref_before[2]).max() > 1e-3              # the refit changed something
    live.pupil.wait()


def _refitted_in_the_background(alg: str, s, opts: dict, frames) -> tuple:
    """``(inline, live, want)``: ``alg`` refitting every 2 frames inline, and with
    ``pupil_async`` fed the first two frames (its refit finished in its thread, not yet
    installed); ``want`` the inline mode's slopes of every frame."""
    inline = table.build(alg, s, {**opts, "pupil_period": 2})
    live = table.build(alg, s, {**opts, "pupil_period": 2, "pupil_async": True})
    want = [inline.centroid(f) for f in frames]
    live.centroid(frames[0])
    live.centroid(frames[1])
    live.pupil.wait()
    return inline, live, want


def test_background_refit_gives_the_calibrated_cog_the_inline_bias():
    """cog with bias='pupil' and pupil_async: after the refit lands, the bias it subtracts and
    the response it inverts are the inline mode's, refitted from the same frames, computed in
    the refit's thread (not on the install frame) and cached (the bias read-only)."""
    s = SMALL.replace(detector="polar")
    n = geometry.layout(s).n_valid
    _, _, sm = true_spots(s, "high")
    frames = [sm.images(np.zeros((n, 2)))[0] * 1000.0 for _ in range(3)]
    inline, live, want = _refitted_in_the_background("cog", s, {"bias": "pupil"}, frames)
    prior = live._bias.copy()

    def no_render(*args, **kwargs):
        raise AssertionError("the reference was rendered on the frame path")
    live.pupil.reference_image = no_render           # the thread computed the bias already
    live.pupil.spots = no_render                     # and the response's scan
    got = live.centroid(frames[2])
    del live.pupil.reference_image, live.pupil.spots
    assert live._response is live.pupil.cog_response()
    assert live.pupil.fits == 1 and np.abs(live._bias - prior).max() > 0.03
    assert live.pupil.cog_bias() is live._bias and not live._bias.flags.writeable
    np.testing.assert_array_equal(live._bias, inline._bias)
    np.testing.assert_array_equal(got, want[2])
    live.pupil.wait()


@pytest.mark.parametrize("alg, opts", [("corr", {}), ("cog", {"bias": "pupil"})])
def test_background_refit_renders_only_the_image_the_estimator_reads(monkeypatch, alg, opts):
    """corr and the calibrated cog read the reference's image alone: a background refit
    renders no derivative (four renders of the full pupil each) and installs what the
    inline mode gives."""
    from lgs_wfs_ros.optics.model_spot import ProfileSpots
    s = SMALL.replace(detector="polar")
    n = geometry.layout(s).n_valid
    _, _, sm = true_spots(s, "high")
    frames = [sm.images(np.zeros((n, 2)))[0] * 1000.0 for _ in range(3)]

    def no_derivatives(*args, **kwargs):
        raise AssertionError("the refit rendered the reference's derivatives")
    monkeypatch.setattr(ProfileSpots, "reference", no_derivatives)
    inline, live, want = _refitted_in_the_background(alg, s, opts, frames)
    got = live.centroid(frames[2])                   # installs (re-raises a refit's error)
    assert live.pupil.fits == 1
    np.testing.assert_array_equal(got, want[2])
    live.pupil.wait()


def test_background_refit_makes_the_correlations_references_in_its_thread():
    """corr with pupil_async on integer frames (its compiled pass): the new references'
    validity, the pass's rows and the drift's reading are made in the refit's thread; the
    frame that installs the second refit (the first with a drift to follow) reads no
    reference, computes no correlation map and no reference FFT (which held a full pupil's
    install frame 0.11-0.17 s), and its slopes are the inline mode's."""
    s, stacks = _narrow_polar_frames(seed=8, count=5)
    lay = geometry.layout(s)
    frames = [geometry.stack_to_frame(st.astype(np.uint16), lay) for st in stacks]
    inline = table.build("corr", s, {"pupil_period": 2})
    live = table.build("corr", s, {"pupil_period": 2, "pupil_async": True})
    want = [inline.centroid(f) for f in frames]
    for f in frames[:4]:
        live.centroid(f)
        live.pupil.wait()
    assert live.pupil.fits == 1 and live.pupil._job is not None     # the second: done, not in
    before = live._kernel_ref[0][0].copy()

    def on_frame_path(*args, **kwargs):
        raise AssertionError("the correlation's references were made on the frame path")
    live.correlation_map = live._ref_fft = live._take_pupil_reference = on_frame_path
    live.pupil.reference_counts = live.pupil.drift_counts = on_frame_path
    got = live.centroid(frames[4])
    del live.correlation_map, live._ref_fft, live._take_pupil_reference
    del live.pupil.reference_counts, live.pupil.drift_counts
    assert live.pupil.fits == 2 and np.abs(live._drift).max() > 0
    assert np.abs(live._kernel_ref[0][0].astype(int) - before).max() > 0     # refitted rows
    np.testing.assert_array_equal(got, want[4])
    live.pupil.wait()


@pytest.mark.parametrize("alg, detector, opts, reading", [
    ("cmf", "cartesian", {}, "_numpy_slopes"), ("ml", "polar", {}, "_marginals_reading"),
    ("cog", "cartesian", {"bias": "pupil"}, "_reading")])
def test_background_refit_reads_the_drift_in_its_thread(alg, detector, opts, reading):
    """The grid of filters (cmf's default), ml and the calibrated CoG with pupil_async: the
    drift between refits is read through the new tables (bias, response) in the refit's
    thread; the frame that installs the second refit (the first with a drift) reads nothing
    through them beyond its own blocks, and the drift it installs is the one they read on
    that frame."""
    s = SMALL.replace(detector=detector)
    lay = geometry.layout(s)
    _, _, sm = true_spots(s, "high")
    rng = np.random.default_rng(9)
    frames = [geometry.stack_to_frame(rng.poisson(sm.images(rng.normal(0, 0.3, (lay.n_valid, 2)))[0]
                                                  * 1000.0).astype(np.uint16), lay)
              for _ in range(5)]
    live = table.build(alg, s, {**opts, "pupil_period": 2, "pupil_async": True})
    for f in frames[:4]:
        live.centroid(f)
        live.pupil.wait()
    assert live.pupil.fits == 1 and live.pupil._job is not None     # the second: done, not in
    assert live._drift is None                       # the first refit: no trend yet

    def on_frame_path(*args, **kwargs):
        raise AssertionError("the drift was read on the install frame")
    frame_path = (reading, "_follow_drift", "_follow_tables", "_calibrated")
    for name in frame_path:
        setattr(live, name, on_frame_path)
    live.centroid(frames[4])
    for name in frame_path:
        delattr(live, name)
    assert live.pupil.fits == 2 and np.abs(live._drift).max() > 0
    installed = live._drift.copy()
    if alg == "cog":                                 # read now, through what is installed
        live._follow_drift(live._reading)
    else:
        live._follow_tables()
    np.testing.assert_array_equal(installed, live._drift)
    live.pupil.wait()


def test_background_refit_gives_ml_the_drift_marginals_it_reads():
    """ml with pupil_async follows the drift from the drifted and the current reference's
    marginals: a background refit makes both in its thread, so the frame that installs it
    renders none (each a pass over the full pupil's spots), and reads what rendering them
    on that frame gives."""
    from lgs_wfs_ros.optics.model_spot import ProfileSpots
    s = SMALL.replace(detector="polar")
    n = geometry.layout(s).n_valid
    _, _, sm = true_spots(s, "high")
    rng = np.random.default_rng(3)
    frames = [sm.images(rng.normal(0.0, 0.3, (n, 2)))[0] * 1000.0 for _ in range(5)]

    def second_install(render_allowed: bool):
        live = table.build("ml", s, {"pupil_period": 2, "pupil_async": True})
        for f in frames[:4]:
            live.centroid(f)
            live.pupil.wait()
        assert live.pupil.fits == 1 and live.pupil._job is not None   # the second: done, not in
        if render_allowed:                           # as before: the install frame renders
            clone = live.pupil._job.result()[0]
            clone._ref_margs = None
            return live.centroid(frames[4]), live

        def no_marginals(*args, **kwargs):
            raise AssertionError("the install frame rendered marginals")
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(ProfileSpots, "marginals_at", no_marginals)
            return live.centroid(frames[4]), live          # installs the second refit
    got, live = second_install(False)
    assert live.pupil.fits == 2 and live._drift is not None and np.abs(live._drift).max() > 0
    want, _ = second_install(True)
    np.testing.assert_array_equal(got, want)


def test_background_refit_makes_the_networks_references_in_its_thread():
    """ann with pupil_async: the network's part of a refit (its filters from the new
    references, its reading of them, the straightened response) is made in the refit's
    thread; the install frame renders nothing and runs none of it, and its slopes are the
    inline mode's, refitted from the same frames."""
    s, frames = _narrow_polar_frames(seed=7, count=3)
    _, live, want = _refitted_in_the_background("ann", s, {"out_of_domain": "warn"}, frames)
    before = (live.cond[1], live._offset, live._response)

    def on_frame_path(*args, **kwargs):
        raise AssertionError("the network's references were made on the frame path")
    live.pupil.image_at = live.pupil.reference_image = live.pupil.counts = on_frame_path
    live._prepare_reference = on_frame_path
    got = live.centroid(frames[2])
    del live.pupil.image_at, live.pupil.reference_image, live.pupil.counts, live._prepare_reference
    assert live.pupil.fits == 1 and live._response is not None
    for now, then in ((live.cond[1]["filters"], before[0]["filters"]), (live._offset, before[1]),
                      (live._response[0], before[2][0])):         # all of it refitted
        assert np.abs(now - then).max() > 1e-4
    np.testing.assert_array_equal(got, want[2])
    live.pupil.wait()


def test_a_failed_background_refit_costs_one_frame_not_the_centroider():
    """pupil_async: a refit that raises in its thread (here its prepare, once) re-raises on
    the frame that would install it, once; the frames after it are centroided with the
    calibration in use, and the next period's refit installs as usual."""
    s, stacks = _narrow_polar_frames(seed=10, count=8)
    live = table.build("cmf", s, {"pupil_period": 2, "pupil_async": True, "filters": "single"})
    prepare, calls = live.pupil.prepare, []

    def fails_once(cal):
        calls.append(1)
        if len(calls) == 1:
            raise np.linalg.LinAlgError("injected")
        return prepare(cal)
    live.pupil.prepare = fails_once
    raised = []
    for k, f in enumerate(stacks):
        try:
            out = live.centroid(f)
            assert np.isfinite(out).all()
        except np.linalg.LinAlgError:
            raised.append(k)
        live.pupil.wait()
    assert raised == [2]                     # the first refit's install frame, once
    assert live.pupil.fits >= 2 and len(calls) >= 3


def test_background_refit_with_a_lag_lands_on_the_same_frame_however_slow():
    """pupil_async_lag: each refit is installed exactly lag frames after it started, so a
    refit that is slow (held 0.3 s in its thread) and one that is not give the same slopes
    frame for frame, and none before the lag."""
    import time
    s, frames = _narrow_polar_frames(seed=6, count=9)
    opts = {"pupil_period": 2, "pupil_async": True, "pupil_async_lag": 3}
    fast, slow = table.build("cmf", s, opts), table.build("cmf", s, opts)
    prepare = slow.pupil.prepare
    slow.pupil.prepare = lambda cal: (time.sleep(0.3), prepare(cal))[1]
    fits = []
    for f in frames:
        np.testing.assert_array_equal(fast.centroid(f), slow.centroid(f))
        fits.append(slow.pupil.fits)
        assert fast.pupil.fits == slow.pupil.fits
    assert fits == [0, 0, 0, 0, 1, 1, 1, 2, 2]     # started at frames 2, 5, 8; lag 3
    slow.pupil.wait()
    fast.pupil.wait()


def test_description_says_how_late_the_profile_in_use_is():
    """``describe()``'s pupil calibration (and a node's /diagnostics) says how many frames
    the profile in use lags behind the frames seen and how long the last refit took: inline,
    0 on the frame that refits; with ``pupil_async_lag`` 3, 3 on the frame that installs
    (and one more each frame after); None before the first fit."""
    from lgs_wfs_ros.ros.centroider_node import pupil_values
    s, frames = _narrow_polar_frames(seed=6, count=6)
    inline = table.build("cmf", s, {"pupil_period": 2, "filters": "single"})
    late = table.build("cmf", s, {"pupil_period": 2, "pupil_async": True, "pupil_async_lag": 3,
                                  "filters": "single"})
    assert inline.describe()["pupil_calibration"]["profile_age_frames"] is None
    ages = []
    for f in frames:
        inline.centroid(f)
        late.centroid(f)
        ages.append((inline.describe()["pupil_calibration"]["profile_age_frames"],
                     late.describe()["pupil_calibration"]["profile_age_frames"]))
    # inline refits end frames 2, 4, 6; the late ones start at 2 and 5 and land 3 after
    assert ages == [(None, None), (0, None), (1, None), (0, None), (1, 3), (0, 4)]
    d = late.describe()["pupil_calibration"]
    assert d["asynchronous"] and d["lag"] == 3 and 0 < d["last_refit_s"] < 60
    vals = pupil_values(late)
    assert vals["pupil refits"] == 1 and vals["pupil profile age frames"] == 4
    assert pupil_values(table.build("cog", s, {})) == {}
    late.pupil.wait()


def test_shipped_network_less_its_reading_of_the_reference_reads_truncated_spots():
    """``ann_conv`` (the default polar network) reads compact spots half out of the field
    (a layer at 100-105 km) ~0.05 px short along e at r > 11 m; less its own reading of the
    calibrated noise-free reference (``bias: pupil``, the default for marginals models) that
    mean error falls below 0.025 px, nothing lost inside (noise-free shifted spots, up to
    +-0.9 px; calibrated on three noise-free frames)."""
    s = SMALL.replace(detector="polar", photons=1000.0)
    lay = geometry.layout(s)
    n = lay.n_valid
    _, _, sm = true_spots(s, "high")
    cs = {b: table.build("ann", s, {"bias": b, "pupil_period": 3}) for b in ("auto", "none")}
    assert cs["auto"].describe()["options"]["bias"] == "pupil"
    zero = sm.images(np.zeros((n, 2)))[0] * 1000.0
    for c in cs.values():
        for _ in range(3):
            c.centroid(zero)
        assert c.pupil.fits == 1
    shift = np.random.default_rng(5).uniform(-0.9, 0.9, (n, 2))
    img = sm.images(shift)[0] * 1000.0
    along = {b: c.to_pixel_axes(c.centroid(img) - shift)[:, 0] for b, c in cs.items()}
    outer = lay.r_m > 11.0
    assert along["none"][outer].mean() < -0.04                     # the network's own bias
    assert abs(along["auto"][outer].mean()) < 0.025
    assert np.abs(along["auto"][outer]).mean() < 0.6 * np.abs(along["none"][outer]).mean()
    assert np.abs(along["auto"][~outer]).mean() < np.abs(along["none"][~outer]).mean() + 0.002


def test_an_ann_recorded_before_its_bias_option_replays_without_it(tmp_path, monkeypatch):
    """A bag whose ann description has no ``bias`` (recorded before the network's reading of
    its reference was subtracted) replays with ``bias: none``, giving the live slopes; one
    recorded today replays with the recorded ``pupil``. Another model given to replay takes
    its own default instead of the recorded model's setting."""
    from lgs_wfs_ros.analysis import replay
    from lgs_wfs_ros.centroiding.ann import ANN

    for old in (True, False):
        res, live, again = replayed_as_recorded(
            tmp_path, monkeypatch, ANN, "ann", {"pupil_period": 4, "bias": "none" if old else "pupil"},
            "bias" if old else None)
        np.testing.assert_allclose(again, live, atol=1e-6)
        assert res["options"]["ann"]["options"]["bias"] == ("none" if old else "pupil")
    plan = replay._plan(["ann"], ["ann_1k"], {}, {"ann": {"model": "ann_conv", "bias": "pupil"}})
    assert plan[0][2] == {"model": "ann_1k", "bias": "auto"}


def test_one_radius_cannot_tell_a_lasting_tilt_from_the_profile_and_says_so():
    """The paper's single subaperture, a tilt of 0.5 px along e held for the whole memory:
    the calibrated CoG follows the spot (reads ~0 after its first refit) while the plain CoG
    less its true bias reads the tilt; the description carries a warning (the node logs it), a full pupil's none."""
    s = Sensor.paper_single("polar")
    h, d, sm = true_spots(s, "measured")
    cal_cog = table.build("cog", s, {"bias": "pupil", "pupil_period": 70})
    plain = table.build("cog", s, {})
    lay = geometry.layout(s)
    tilt = np.array([[0.5, 0.0]])                   # block x is e on a polar detector
    img, _ = sm.images(tilt)
    frame = geometry.stack_to_frame((img / img.sum() * 1e5).astype(np.uint16), lay)
    for _ in range(700):                            # 1 s: three time constants
        got, ref = cal_cog.centroid(frame), plain.centroid(frame)
    assert abs(got[0, 0]) < 0.05                   # the tilt went into the profile
    assert abs(ref[0, 0] - cog_block(sm.images(np.zeros((1, 2)))[0])[0, 0] - 0.5) < 0.05
    warning = cal_cog.describe()["warning"]
    assert "one radius" in warning and "0.3 s" in warning
    assert "warning" not in table.build("cog", SMALL, {"bias": "pupil"}).describe()
    assert "warning" not in plain.describe()


def test_calibrations_of_the_same_optics_share_their_thin_layer_spots():
    """The projected thin-layer spots (the first refit's long part) are built once for
    calibrations whose sensors differ only in photometry and frame rate, read-only, equal
    to a fresh build; other optics (the launch) get their own."""
    a = PupilCalibration(SMALL.replace(photons=100.0))
    b = PupilCalibration(SMALL.replace(photons=3000.0, frame_rate_hz=500.0, background_e=2.0))
    side = PupilCalibration(SMALL.replace(launch_xy_m=(8.0, 0.0)))
    assert a.basis is b.basis and a._gram is b._gram
    assert side.basis is not a.basis and not np.allclose(side.basis, a.basis)
    fresh = a._hats_of(a.sensor)
    for got, want in zip((a.basis, a._dbasis, a._colsum, a._dcolsum, a._gram), fresh):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="read-only"):
        a.basis[0, 0, 0] = 1.0


def test_a_bag_recorded_with_unlagged_background_refits_replays_them_inline(tmp_path, monkeypatch,
                                                                            capsys):
    """cmf recorded with pupil_async and no lag (refits installed whenever ready: frames the
    bag does not record) replays with its refits inline, says so, and gives the same slopes
    at every replay; recorded with a lag it replays with that lag, in the background."""
    from lgs_wfs_ros.analysis import bagdata
    from lgs_wfs_ros.analysis.replay import INLINE
    from lgs_wfs_ros import cli

    path = tmp_path / "live.mcap"
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_period", 3)
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_async", True)
    bagdata.make_sample_bag(path, frames=24, algorithms=("cmf",))
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_period", 140)
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_async", False)
    runs = []
    for k in range(2):
        out = tmp_path / f"r{k}.mcap"
        assert cli.main(["replay", str(path), "--algorithms", "cmf", "--out", str(out)]) == 0
        seg = {sg.label: sg for sg in bagdata.load_bag(out).segments}["cmf_replay"]
        assert seg.description["options"]["pupil_async"] is False
        assert seg.description["options_source"] == INLINE
        runs.append(seg.slopes.data)
    assert "replayed with its refits inline" in capsys.readouterr().out
    np.testing.assert_array_equal(runs[0], runs[1])
    data = bagdata.load_bag(path, max_frames=None)
    inline = table.build("cmf", data.sensor, {"pupil_period": 3})
    frames = data.frames.data
    lay = geometry.layout(data.sensor)
    want = np.stack([inline.centroid(f) for f in frames])
    np.testing.assert_allclose(runs[0][:, lay.valid.ravel()], want, atol=1e-5)
    lagged = tmp_path / "lagged.mcap"
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_period", 3)
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_async", True)
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_async_lag", 2)
    bagdata.make_sample_bag(lagged, frames=12, algorithms=("cmf",))
    monkeypatch.setitem(pupil_cal.OPTION_DEFAULTS, "pupil_async_lag", 0)
    from lgs_wfs_ros.analysis.replay import replay_bag
    res = replay_bag(lagged, ["cmf"], out=tmp_path / "l.mcap", quiet=True)
    assert res["options"]["cmf"]["source"] == "bag"
    assert res["options"]["cmf"]["options"]["pupil_async"] is True


@pytest.mark.skipif(not pupil_cal.kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_the_thin_layer_basis_from_the_compiled_renderer_is_the_exact_one(monkeypatch):
    """On a cartesian detector the calibration's thin-layer basis and its derivative come
    from the simulator's compiled renderer (FastRenderer.canvas) instead of exact renders:
    the same projected hats within 1e-6 of a hat's light (the derivative, a difference over
    0.02 px, within 1e-4); hats rendered one block off in the layout are far from them."""
    from lgs_wfs_ros.optics.model_spot import altitude_nodes, projected_hats
    sensor = SMALL.replace(core_fwhm_px=1.5)
    lay = geometry.layout(sensor)
    nodes = altitude_nodes(sensor, count=24)
    proj = Projection(sensor, lay.e)
    e_pix = np.asarray(lay.e)
    for shift in (None, 0.02 * e_pix):
        exact = projected_hats(sensor, lay.r_m, lay.e, nodes, proj, shift)
        fast = projected_hats(sensor, lay.r_m, lay.e, nodes, proj, shift, lay)
        assert exact.max() > 0.1
        np.testing.assert_allclose(fast, exact, atol=1e-6)
    db = (fast - projected_hats(sensor, lay.r_m, lay.e, nodes, proj, None, lay)) / 0.02
    db_exact = (exact - projected_hats(sensor, lay.r_m, lay.e, nodes, proj)) / 0.02
    np.testing.assert_allclose(db, db_exact, atol=1e-4)
    assert np.abs(np.roll(fast, 1, axis=0) - exact).max() > 0.05
