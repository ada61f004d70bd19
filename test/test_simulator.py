"""Frame simulator: shapes, dtypes, truth, reproducibility, training batches."""

import json

import numpy as np
import pytest

from lgs_wfs_ros.optics import sodium
from lgs_wfs_ros.optics.geometry import frame_to_stack, layout, local_to_detector
from lgs_wfs_ros.optics.simulator import (Batch, SimulationConfig, Simulator,
                                          subaperture_batch)
from lgs_wfs_ros.optics.spots import light_centroid_px
from lgs_wfs_ros.sensor import Sensor


class RandomWalk:
    """A cheap stand-in for FrozenFlow: seeded normal displacements per frame index."""

    def __init__(self, n, seed=0, sigma=0.5):
        self.n, self.seed, self.sigma = n, seed, sigma

    def tilts_at(self, index):
        return np.random.default_rng([self.seed, index]).normal(0, self.sigma, (self.n, 2))


def simple_model():
    """A SodiumModel with hand-set statistics (independent normals)."""
    mean = np.array([[1.0, 86e3, 800.0], [1.0, 88e3, 1500.0], [1.0, 90e3, 2000.0],
                     [0.8, 92e3, 2000.0], [0.3, 95e3, 3000.0]])
    std = np.abs(mean) * np.array([0.3, 0.01, 0.2])
    return sodium.SodiumModel(mean, std, np.zeros(16), np.eye(16), method="independent")


@pytest.mark.parametrize("detector,dtype", [("cartesian", "uint16"), ("polar", "float32")])
def test_full_frame_shapes_dtypes_and_truth(detector, dtype):
    s = Sensor(detector=detector, dtype=dtype)
    lay = layout(s)
    sim = Simulator(s, SimulationConfig(profile="gaussian", seed=3),
                    displacements=RandomWalk(lay.n_valid))
    f0, f1 = sim.next(), sim.next()
    assert f0.frame.shape == (960, 960) and f0.frame.dtype == np.dtype(dtype)
    assert f0.truth.shape == (lay.n_valid, 2) and f0.truncated.shape == (lay.n_valid,)
    assert (f0.index, f1.index) == (0, 1) and f1.time_s == pytest.approx(1 / 700)
    np.testing.assert_array_equal(f1.truth, RandomWalk(lay.n_valid).tilts_at(1))
    assert f0.profile.shape == f0.altitude_m.shape
    # nothing outside valid subapertures; about photons per subaperture inside them
    blocks = f0.frame.reshape(60, 16, 60, 16).swapaxes(1, 2)
    assert blocks[~lay.valid].max() == 0
    tot = frame_to_stack(f0.frame, lay).reshape(lay.n_valid, -1).sum(1).astype(float)
    expect = s.photons * (1 - f0.truncated)
    assert tot.mean() == pytest.approx(expect.mean(), rel=0.01)


@pytest.mark.parametrize("detector", ["cartesian", "polar"])
def test_noise_free_frame_cog_is_truth_plus_profile_bias(detector):
    s = Sensor(detector=detector, dtype="float32")
    lay = layout(s)
    cfg = SimulationConfig(profile="gaussian", gaussian_fwhm_m=4000.0, noise=False,
                           turbulence=False, fixed_shift_px=(0.5, -1.0))
    f = Simulator(s, cfg).next()
    np.testing.assert_array_equal(f.truth, np.tile([0.5, -1.0], (lay.n_valid, 1)))
    st = frame_to_stack(f.frame, lay).astype(float)
    idx = np.arange(16) - 7.5
    tot = st.sum((1, 2))
    c = np.stack([(st.sum(1) * idx).sum(1) / tot, (st.sum(2) * idx).sum(1) / tot], 1)
    if detector == "polar":
        c = local_to_detector(c, lay.e)
    expect = f.truth + light_centroid_px(s, lay.r_m, f.altitude_m, f.profile)[:, None] * lay.e
    ok = f.truncated < 1e-6
    assert ok.sum() > 2000
    assert np.abs(c - expect)[ok].max() < 5e-3          # pixelisation bias of the core only


def test_same_seed_same_frames_bit_for_bit():
    s = Sensor()
    lay = layout(s)

    def run(seed):
        sim = Simulator(s, SimulationConfig(profile="uncentred", seed=seed),
                        displacements=RandomWalk(lay.n_valid, seed))
        return [f.frame for f in sim.frames(3)]

    a, b, c = run(7), run(7), run(8)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])
    assert not np.array_equal(a[0], a[1])


def test_single_subaperture_and_random_profiles_reproducible():
    s = Sensor.paper_single("polar")
    cfg = SimulationConfig(profile="random", random_every=2, seed=1, turbulence=False)
    fa = list(Simulator(s, cfg, sodium_model=simple_model()).frames(4))
    fb = list(Simulator(s, cfg, sodium_model=simple_model()).frames(4))
    assert fa[0].frame.shape == (16, 16) and fa[0].truth.shape == (1, 2)
    for x, y in zip(fa, fb):
        np.testing.assert_array_equal(x.frame, y.frame)
        np.testing.assert_array_equal(x.profile, y.profile)
    np.testing.assert_array_equal(fa[0].profile, fa[1].profile)        # every 2 frames
    assert not np.array_equal(fa[1].profile, fa[2].profile)


@pytest.mark.parametrize("profile", ["centred", "uncentred", "measured", "evolving"])
def test_profile_sources(profile):
    s = Sensor.paper_single("cartesian")
    cfg = SimulationConfig(profile=profile, turbulence=False, noise=False, measured_index=3)
    sim = Simulator(s, cfg)
    f = sim.next()
    assert f.frame.shape == (16, 16) and f.profile.ndim == 1 and f.profile.max() > 0
    if profile == "measured":
        np.testing.assert_array_equal(f.profile, sodium.load_measured()[1][3])


def test_explicit_profile_and_config_json_roundtrip():
    h = np.linspace(80e3, 100e3, 201)
    rho = np.exp(-0.5 * ((h - 90e3) / 2000) ** 2)
    cfg = SimulationConfig(profile="explicit", altitude_m=tuple(h), density=tuple(rho),
                           turbulence=False, fixed_shift_px=(0.25, 0.0), seed=4)
    back = SimulationConfig.from_dict(json.loads(cfg.to_json()))
    assert back == cfg
    sim = Simulator(Sensor.paper_single("polar"), back)
    f = sim.next()
    np.testing.assert_allclose(f.profile, rho)
    d = json.loads(json.dumps(sim.describe()))
    assert d["simulation"]["seed"] == 4 and d["detector"] == "polar"


@pytest.mark.parametrize("bad", [dict(profile="nope"), dict(seed=-1), dict(random_every=0),
                                 dict(profile="explicit"), dict(fixed_shift_px=(1.0,))])
def test_bad_config_raises(bad):
    with pytest.raises(ValueError):
        SimulationConfig(**bad)


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
def test_subaperture_batch(detector):
    s = Sensor.paper_single(detector)
    n = 3000
    b = subaperture_batch(s, np.random.default_rng(2), n, sigma_px=0.6, model=simple_model(),
                          chunk=1024)
    assert isinstance(b, Batch)
    assert b.images.shape == (n, 16, 16) and b.images.dtype == np.float32
    assert b.truth.shape == (n, 2)
    assert b.truth.std(0) == pytest.approx([0.6, 0.6], rel=0.06)
    tot = b.images.reshape(n, -1).sum(1)
    assert tot.mean() == pytest.approx((s.photons * (1 - b.truncated)).mean(), rel=0.01)
    again = subaperture_batch(s, np.random.default_rng(2), n, sigma_px=0.6, model=simple_model(),
                              chunk=1024)
    np.testing.assert_array_equal(b.images, again.images)
    # every sample has its own profile: noise-free images differ even at the same position
    nf = subaperture_batch(s, np.random.default_rng(3), 4, sigma_px=0.0, model=simple_model(),
                           noise=False)
    assert not np.allclose(nf.images[0], nf.images[1])


@pytest.mark.parametrize("sensor", [Sensor.paper_single("polar"), Sensor()])
def test_frozen_flow_frames_same_seed_bit_for_bit(sensor):
    """Turbulence on (FrozenFlow): same seed -> identical frames and truths."""
    cfg = SimulationConfig(profile="uncentred", seed=1)
    a = list(Simulator(sensor, cfg).frames(2))
    b = list(Simulator(sensor, cfg).frames(2))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.frame, y.frame)
        np.testing.assert_array_equal(x.truth, y.truth)
    assert not np.array_equal(a[0].truth, a[1].truth)
    if not sensor.is_single:
        assert 0.1 < a[0].truth.std() < 2.0                   # pixels: a sane tilt scale


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
@pytest.mark.parametrize("profile", ["evolving", "uncentred", "random"])
def test_next_batch_renders_what_next_renders(detector, profile):
    """Frames rendered in batches equal frames rendered one by one (noise-free), with the
    same truths, profiles, indices and times; with noise, the same mean counts."""
    from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator
    s = Sensor.paper_single(detector)
    one = Simulator(s, SimulationConfig(profile=profile, noise=False))
    many = Simulator(s, SimulationConfig(profile=profile, noise=False))
    a = [one.next() for _ in range(40)]
    b = many.next_batch(25) + many.next_batch(15)
    assert many.index == one.index == 40
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.frame, y.frame)
        np.testing.assert_array_equal(x.truth, y.truth)
        np.testing.assert_allclose(x.profile, y.profile)
        np.testing.assert_allclose(x.truncated, y.truncated)
        assert (x.index, x.time_s) == (y.index, y.time_s)
    noisy = Simulator(s, SimulationConfig(profile=profile, seed=3)).next_batch(400)
    mean = np.mean([f.frame.astype(float).sum() for f in noisy])
    assert abs(mean - s.photons) < 5 * np.sqrt(s.photons / 400)      # per_field photons
    with pytest.raises(ValueError, match="m must be"):
        many.next_batch(0)
