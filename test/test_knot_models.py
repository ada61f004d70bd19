"""The fast simulator's knot models: blended evolving profiles and models built ahead."""

import numpy as np
import pytest

from lgs_wfs_ros.optics import fast_frames
from lgs_wfs_ros.optics.knot_models import KnotModels
from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

pytestmark = pytest.mark.skipif(not fast_frames.AVAILABLE,
                                reason="numba not installed ('fast' extra)")
RATE = 700.0


def _evolving(detector="polar", dtype="float32", noise=False, frames_per_knot=4, **kw):
    s = Sensor(detector=detector, dtype=dtype, photons=1.0 if not noise else 1000.0)
    cfg = SimulationConfig(profile="evolving", seed=3, noise=noise, turbulence=False,
                           seconds_per_profile=frames_per_knot / s.frame_rate_hz, **kw)
    return s, Simulator(s, cfg, fast=True)


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
def test_blended_knots_give_the_blended_profiles_spots(detector):
    """Frame 6 sits halfway between measured knots 1 and 2, whose columns differ by 14 %:
    the blend of their unit-light models, weighted by column, is the spot of the blended
    density (2.7e-5 of a spot's light at worst, the models' own discretisation); weighting
    by time alone is 3.4e-4 off."""
    s, sim = _evolving(detector)
    buf = np.empty(s.frame_shape, np.float32)
    for _ in range(7):
        sim.next(out=buf)
    density, _ = sim.profile_at(6)
    direct = SpotModel(s, sim.layout.r_m, sim.layout.e, sim.altitude_m, density, sim._margin)
    ref = np.empty_like(buf)
    sim._renderer.render(direct, sim.truth_at(6), ref, 1.0, 0, False, True)
    assert np.abs(buf - ref).max() < 1e-4
    ma = sim._knots.get(("knot", 1), None, sim._margin)
    mb = sim._knots.get(("knot", 2), None, sim._margin)
    sim._renderer.render(ma, sim.truth_at(6), buf, 1.0, 0, False, True, (mb, 0.5))
    assert np.abs(buf - ref).max() > 2e-4            # the time-only weight: what the test catches


def test_models_built_ahead_give_the_same_frames():
    """The next knot's model comes from the background thread, and the noisy frames are
    bit for bit those of a simulator that builds every model when it needs it."""
    s, ahead = _evolving(dtype="uint16", noise=True, frames_per_knot=3)
    _, inline = _evolving(dtype="uint16", noise=True, frames_per_knot=3)
    inline._knots.prefetch = lambda *a: None
    a, b = (np.empty(s.frame_shape, np.uint16) for _ in range(2))
    for _ in range(10):
        ahead.next(out=a)
        inline.next(out=b)
        np.testing.assert_array_equal(a, b)
    assert ahead._knots.built_ahead >= 2 and inline._knots.built_ahead == 0
    assert inline._knots.built_inline >= 4
    ahead._knots.close()


def test_random_profile_every_n_frames_matches_the_reference_path():
    """profile=random, random_every=4: the fast path's epoch models (the next built ahead)
    render the slow path's spots of each epoch's profile."""
    s = Sensor(detector="polar", dtype="float32", photons=1.0)
    cfg = SimulationConfig(profile="random", random_every=4, seed=5, noise=False)
    fast, slow = Simulator(s, cfg, fast=True), Simulator(s, cfg)
    buf = np.empty(s.frame_shape, np.float32)
    for _ in range(9):
        f = fast.next(out=buf)
        g = slow.next()
        np.testing.assert_array_equal(f.profile, g.profile)
        assert np.abs(buf - g.frame).max() < 1e-5
    assert fast._knots.built_ahead >= 1


def test_knot_models_keep_the_newest_and_build_once():
    built = []

    def build(density, margin):
        built.append((float(density[0]), margin))
        return object()

    k = KnotModels(build, keep=2)
    m1 = k.get("a", lambda: np.array([1.0]), 3.0)
    assert k.get("a", lambda: np.array([9.0]), 3.0) is m1          # held: not rebuilt
    k.prefetch("b", lambda: np.array([2.0]), 3.0)
    k.get("b", None, 3.0)
    k.get("c", lambda: np.array([3.0]), 3.0)                       # evicts "a"
    k.get("a", lambda: np.array([1.0]), 4.0)                       # another margin: a new model
    assert built == [(1.0, 3.0), (2.0, 3.0), (3.0, 3.0), (1.0, 4.0)]
    assert (k.built_ahead, k.built_inline) == (1, 3)
    k.close()
