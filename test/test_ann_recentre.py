"""ann option ``recentre``: each block read against its calibrated reference moved to the
nearest quarter pixel of its CoG along the bins (filter sets made at every refit)."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import ann as ann_mod
from lgs_wfs_ros.centroiding import kernels, options
from lgs_wfs_ros.sensor import Sensor

#: no refit (the references stay the calibration's first); option recentre alone
STILL = {"pupil_period": 10 ** 6, "linearize": False}


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
def test_a_spot_at_a_moved_reference_reads_the_move(detector):
    """The calibrated reference moved by a set's shift along e reads that shift (the set's
    own reading of it is what it subtracts); between sets, a spot that picks the centre set
    reads as without the option."""
    sensor = Sensor(detector=detector, photons=1000.0)
    moved = options.build("ann", sensor, {"recentre": True, **STILL})
    plain = options.build("ann", sensor, STILL)
    e = np.asarray(moved.layout.e)
    u = np.tile([1.0, 0.0], (moved.n, 1)) if detector == "polar" else e    # block axes
    ok = np.isfinite(plain.centroid(moved.pupil.image_at(0.0 * u))).all(axis=1)
    for s in (-0.5, -0.25, 0.25, 0.5):
        got = moved.centroid(moved.pupil.image_at(s * u))
        err = np.abs(got - s * e)[ok].max(axis=1)
        assert np.median(err) < 2e-3 and np.percentile(err, 95) < 6e-3, s
        before = np.abs(plain.centroid(moved.pupil.image_at(s * u)) - s * e)[ok].max(axis=1)
        assert np.median(before) > 3 * np.median(err)
    spot = moved.pupil.image_at(0.08 * u)
    np.testing.assert_allclose(moved.centroid(spot)[ok], plain.centroid(spot)[ok], atol=2e-5)
    assert moved.describe()["options"]["recentre"] is True


def test_the_kernel_takes_the_set_nearest_the_cog():
    """``hyper_contract_moved``: set ``S // 2 + round((CoG - cbias) / step)``, clipped; a
    block without light or with a NaN takes the centre set; compiled and numpy agree."""
    rng = np.random.default_rng(5)
    n, sets, k, p = 40, 5, 3, 16
    x = rng.poisson(30, (n, p)).astype(np.float32)
    x[1] = 0.0
    x[2, 4] = np.nan
    f = rng.normal(size=(n, sets, k, p)).astype(np.float32)
    b = rng.normal(size=(n, sets, k)).astype(np.float32)
    cbias = rng.normal(0.0, 0.4, n)
    z, safe, chosen = kernels.hyper_contract_moved(x, f, b, cbias, 0.25)
    pos = np.arange(p) - (p - 1) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (x @ pos / x.sum(axis=1) - cbias) / 0.25
    want = np.clip(2 + np.floor(np.nan_to_num(t) + 0.5), 0, 4).astype(int)
    want[[1, 2]] = 2
    np.testing.assert_array_equal(chosen, want)
    assert len(set(chosen.tolist())) == sets
    i = np.arange(n)
    ref = np.einsum("nkp,np->nk", f[i, want], x) / np.maximum(x.sum(axis=1), 1.0)[:, None] + b[i, want]
    good = np.isfinite(ref).all(axis=1)
    np.testing.assert_allclose(z[good], ref[good], rtol=1e-5, atol=1e-5)
    assert np.isnan(z[2]).all()
    if kernels.AVAILABLE:
        try:
            kernels.AVAILABLE = False
            z2, _, c2 = kernels.hyper_contract_moved(x, f, b, cbias, 0.25)
        finally:
            kernels.AVAILABLE = True
        np.testing.assert_array_equal(c2, chosen)
        np.testing.assert_allclose(z2[good], z[good], rtol=1e-5, atol=1e-5)


def test_recentre_is_checked():
    sensor = Sensor(detector="cartesian", photons=1000.0)
    with pytest.raises(ValueError, match="recentre needs a model whose filters"):
        ann_mod.ANN(sensor, model="ann_ref", recentre=True)
    with pytest.raises(ValueError, match="recentre must be true or false"):
        ann_mod.ANN(sensor, recentre="yes")
