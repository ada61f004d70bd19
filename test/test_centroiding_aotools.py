"""Parity with aotools' centroiders where the definitions agree.

Pixel origin: aotools measures from pixel index 0, we from the subaperture centre
(p-1)/2 = 7.5, so ours = aotools - 7.5 for centre_of_gravity. (correlation_centroid's
origin is p/2 = 8: see test_centroiding_corr.py.) aotools' 3-D thresholding zeroes
pixels below threshold * max without subtracting (our tcog mode="zero",
threshold_frac); its 2-D branch subtracts (our default mode="subtract").
"""

import numpy as np
import pytest
from aotools.image_processing import centroiders as aoc

from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import sodium_line, spots

SENSOR = Sensor()
LAY = geometry.layout(SENSOR)
N = LAY.n_valid


def noisy_stack(seed=0):
    rng = np.random.default_rng(seed)
    off, w = sodium_line(3.0, 11)
    shift = rng.uniform(-1.5, 1.5, (N, 2))
    return rng.poisson(spots(shift, sigma=0.6, e=LAY.e, offsets=off, weights=w, background=1.0)).astype(float)


def test_cog_matches_aotools_centre_of_gravity():
    st = noisy_stack()
    expect = aoc.centre_of_gravity(st.copy()).T - 7.5            # (2, n) -> (n, 2)
    ours = make_centroider("cog", SENSOR).centroid(st)
    np.testing.assert_allclose(ours, expect, atol=1e-4)
    # uint16 frame input gives the same
    frame = geometry.stack_to_frame(st.astype(np.uint16), LAY)
    np.testing.assert_allclose(make_centroider("cog", SENSOR).centroid(frame), expect, atol=1e-4)


@pytest.mark.parametrize("frac", [0.1, 0.3])
def test_tcog_zero_mode_matches_aotools_threshold(frac):
    st = noisy_stack(1)
    expect = aoc.centre_of_gravity(st.copy(), threshold=frac).T - 7.5
    ours = make_centroider("tcog", SENSOR, threshold_frac=frac, mode="zero").centroid(st)
    np.testing.assert_allclose(ours, expect, atol=1e-4)


def test_tcog_subtract_mode_matches_aotools_2d_threshold():
    st = noisy_stack(2)[:50]
    expect = np.array([aoc.centre_of_gravity(im.copy(), threshold=0.2) for im in st]) - 7.5
    sensor = Sensor.paper_single("cartesian")
    c = make_centroider("tcog", sensor, threshold_frac=0.2)
    ours = np.array([c.centroid(im[None])[0] for im in st])
    np.testing.assert_allclose(ours, expect, atol=1e-4)
