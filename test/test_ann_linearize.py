"""ann option ``linearize``: the curvature of the network's response along the bins
removed (its response to the noise-free calibrated reference moved along them, made at
every refit), its gain kept."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import ann as ann_mod
from lgs_wfs_ros.centroiding import kernels, options
from lgs_wfs_ros.optics import geometry
from pupils import SMALL

STILL = {"pupil_period": 10 ** 6}          # no refit: the references stay the calibration's first


def test_the_reading_of_a_moved_reference_is_a_straight_line():
    """Polar: the noise-free reference moved along the bins (block x) by ``s`` reads
    ``gain s`` (to the interpolation between the response's quarter-pixel knots), ``gain``
    the slope of the response over +-0.5 px; without the option the reading bends away
    from that line. The reference itself reads zero."""
    sensor = SMALL.replace(detector="polar")
    lin = options.build("ann", sensor, STILL)                         # the default
    bent = options.build("ann", sensor, {"linearize": False, **STILL})
    assert lin.describe()["options"]["linearize"] is True
    e = np.asarray(lin.layout.e)
    u = lin._bins_direction()                                         # block axes
    ok = np.isfinite(bent.centroid(lin.pupil.image_at(0.0 * u))).all(axis=1)
    moves = np.arange(-2, 3) * 0.25                     # the gain: the bent reading's slope
    along = np.stack([(bent.centroid(lin.pupil.image_at(t * u)) * e).sum(axis=1) for t in moves], 1)
    gain = (along - along.mean(axis=1, keepdims=True)) @ moves / (moves @ moves)
    assert 0.85 < np.median(gain[ok]) < 1.05 and np.ptp(gain[ok]) > 0.01
    for s in (-0.8, -0.5, -0.3, 0.1, 0.4, 0.6):
        line = (gain * s)[:, None] * e
        err = np.abs(lin.centroid(lin.pupil.image_at(s * u)) - line)[ok].max(axis=1)
        before = np.abs(bent.centroid(lin.pupil.image_at(s * u)) - line)[ok].max(axis=1)
        assert np.median(err) < 2e-3 and np.percentile(err, 95) < 5e-3, s
        if abs(s) >= 0.3:                       # the bend grows with the move
            assert np.median(before) > 2 * np.median(err), s
    assert np.abs(lin.centroid(lin.pupil.image_at(0.0 * u))[ok]).max() < 1e-4


def test_cartesian_bins_along_the_grid_direction_read_straight():
    """Cartesian (``ann_grid``, bins along the grid direction ``d``): the network's reading
    of the reference moved along ``d`` by ``s``, straightened, is ``gain s`` plus the
    reference's reading; the centroid differs from the bent one by exactly that change of
    the reading along ``d`` through the solve with the CoG across e."""
    sensor = SMALL.replace(detector="cartesian")
    lin = options.build("ann", sensor, STILL)
    bent = options.build("ann", sensor, {"linearize": False, **STILL})
    u = lin._bins_direction()
    r = lin._response[0]
    moves = np.arange(-2, 3) * 0.25                     # the gain: the bent reading's slope
    raw = np.stack([lin._marginals_out(lin._along(lin.pupil.image_at(t * u)))[:, 0]
                    for t in moves], axis=1) * lin.meta["output_scale"]
    gain = (raw - raw.mean(axis=1, keepdims=True)) @ moves / (moves @ moves)
    a, _ = lin._solve_ab()
    scale = lin.meta["output_scale"]
    for s in (-0.8, -0.5, 0.4, 0.6):
        img = lin.pupil.image_at(s * u)
        x = lin._marginals_out(lin._along(img))[:, 0] * scale
        straight = lin._straight(x) - r[:, r.shape[1] // 2]
        err = np.abs(straight - gain * s)
        assert np.median(err) < 2e-3 and np.percentile(err, 95) < 5e-3, s
        assert np.median(np.abs(x - r[:, r.shape[1] // 2] - gain * s)) > 2 * np.median(err), s
        np.testing.assert_allclose(lin.centroid(img) - bent.centroid(img),
                                   (lin._straight(x) - x)[:, None] * a, atol=2e-4)


def test_response_inverse_interpolates_extends_and_keeps():
    """Piecewise-linear inverse of each row, end segments extended, times the gain, plus
    the middle reading; a NaN gain or reading keeps the reading; compiled and numpy agree."""
    t = np.array([-1.0, 0.0, 1.0, 2.0])
    r = np.array([[-2.0, 0.5, 1.0, 3.0],        # middle move (index 2): 1.0
                  [-1.0, 0.0, 1.0, 2.0],
                  [0.0, 1.0, 2.0, 3.0]])
    x = np.array([0.75, 2.5, np.nan])
    gain = np.array([2.0, 1.0, 1.0])
    # row 0: 0.75 between 0.5 and 1.0 -> 0.5; 2 * 0.5 + 1.0. row 1: past the end -> 2.5
    want = np.array([2.0 * 0.5 + 1.0, 2.5 + 1.0, np.nan])
    np.testing.assert_allclose(kernels.response_inverse(x, r, t, gain), want)
    low = kernels.response_inverse(np.array([-3.0, -3.0, 5.0]), r, t, np.array([1.0, 1.0, np.nan]))
    np.testing.assert_allclose(low, [-1.0 - 1.0 / 2.5 + 1.0, -3.0 + 1.0, 5.0])
    if kernels.AVAILABLE:
        rng = np.random.default_rng(3)
        rr = np.cumsum(rng.uniform(0.1, 0.5, (50, 9)), axis=1) - 1.0
        xx = rng.normal(0.0, 1.5, 50)
        tt = np.arange(9) * 0.25 - 1.0
        gg = rng.uniform(0.9, 1.1, 50)
        gg[3] = np.nan
        got = kernels.response_inverse(xx, rr, tt, gg)
        try:
            kernels.AVAILABLE = False
            ref = kernels.response_inverse(xx, rr, tt, gg)
        finally:
            kernels.AVAILABLE = True
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
        assert got[3] == xx[3]


def test_linearize_is_checked_and_unused_where_it_cannot_apply():
    sensor = SMALL.replace(detector="cartesian")
    with pytest.raises(ValueError, match="linearize must be true or false"):
        ann_mod.ANN(sensor, linearize="yes")
    assert ann_mod.ANN(sensor, model="ann_ref").describe()["options"]["linearize"] is False
    assert ann_mod.ANN(sensor, bias="none").describe()["options"]["linearize"] is False


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_a_cartesian_frame_gives_what_the_stack_steps_give():
    """The compiled pass after the network on a cartesian frame (:func:`.kernels.bins_shifts`:
    scale, straightened response, CoG across e, the two combined, the reference's reading
    removed, NaN without light) gives what the numpy steps give on the same frame as floats,
    with the response and without it, and refuses mismatched shapes."""
    sensor = SMALL.replace(detector="cartesian")
    frames = _frames(sensor, 5, seed=11)
    frames[3][:16] = 0                                    # a row of dark blocks
    live = options.build("ann", sensor, {"pupil_period": 2})
    steps = options.build("ann", sensor, {"pupil_period": 2})
    for k, f in enumerate(frames):
        if k == 4:                                        # no refit on this frame
            live._response = steps._response = None
        got = live.centroid(f)
        want = steps.centroid(f.astype(np.float32))       # not a kernel frame: numpy
        assert np.array_equal(np.isnan(got), np.isnan(want))
        assert np.isnan(got).any() == (k == 3)
        np.testing.assert_allclose(got, want, atol=2e-4)
        assert np.nanstd(got) > 0.2                       # the shifts, not zeros
    assert live.pupil.fits == steps.pupil.fits == 2
    n = 3
    with pytest.raises(ValueError, match="bins_shifts"):
        kernels.bins_shifts(np.zeros((n, 1), np.float32), 1.0, None, np.ones((n, 2)), 7.5,
                            np.ones((n, 2)), np.ones((n, 2)), np.ones((n, 2)), None)


def _frames(sensor, k: int, seed: int) -> list:
    """``k`` uint16 frames: the first calibration's references at random shifts (0.4 px rms),
    with photon noise."""
    lay = geometry.layout(sensor)
    cal = options.build("ann", sensor, STILL).pupil
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(k):
        img = cal.image_at(rng.normal(0.0, 0.4, (lay.n_valid, 2)))
        img = img / img.reshape(lay.n_valid, -1).sum(axis=1)[:, None, None]
        out.append(geometry.stack_to_frame(rng.poisson(img * sensor.photons).astype(np.uint16), lay))
    return out
