"""Sensor description and pupil geometry (docs/conventions.md sections 1-3)."""

import math

import numpy as np
import pytest

from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor, SensorError


def test_defaults_and_json_round_trip():
    s = Sensor()
    assert s.frame_shape == (960, 960)
    assert s.mas_per_px == 500.0
    back = Sensor.from_json(s.to_json(seed=3, profile="random"))
    assert back == s and hash(back) == hash(s)
    side = Sensor(launch_xy_m=[15.5, 0], outer_scale_m=25.0)
    assert Sensor.from_json(side.to_json()) == side


@pytest.mark.parametrize("bad", [dict(photons=-1), dict(detector="hex"), dict(pixels=3.5),
                                 dict(obstruction_m=40.0), dict(frame_rate_hz=float("nan")),
                                 dict(zenith_deg=95), dict(dtype="int8")])
def test_invalid_sensor_is_refused_with_reason(bad):
    with pytest.raises(SensorError) as err:
        Sensor(**bad)
    assert next(iter(bad)) in str(err.value)


def test_from_json_rejects_garbage():
    with pytest.raises(SensorError):
        Sensor.from_json("not json")
    with pytest.raises(SensorError):
        Sensor.from_json("[1, 2]")


def test_valid_subapertures_of_the_reference_pupil():
    lay = geometry.layout(Sensor())
    assert 2700 <= lay.n_valid <= 2900          # the contract expects about 2,800
    assert lay.valid.shape == (60, 60)
    assert np.array_equal(lay.valid, lay.valid[::-1]) and np.array_equal(lay.valid, lay.valid[:, ::-1])
    assert not lay.valid[29:31, 29:31].any()     # central obstruction
    i, j = lay.index[0]
    assert lay.centre_xy_m[0, 0] == pytest.approx((j - 29.5) * 0.5)
    assert lay.centre_xy_m[0, 1] == pytest.approx((i - 29.5) * 0.5)
    np.testing.assert_allclose(np.hypot(*lay.e.T), 1.0)
    np.testing.assert_allclose(lay.e * lay.r_m[:, None], lay.centre_xy_m)


def test_side_launch_and_zero_radius():
    s = Sensor(launch_xy_m=(0.25, 0.25), obstruction_m=0.0)
    lay = geometry.layout(s)
    k = np.flatnonzero(lay.r_m == 0)
    assert k.size == 1 and tuple(lay.e[k[0]]) == (1.0, 0.0)


def test_paper_single_subaperture():
    polar = Sensor.paper_single("polar")
    assert polar.frame_shape == (16, 16) and polar.grid == 1
    lay = geometry.layout(polar)
    assert lay.n_valid == 1 and lay.r_m[0] == pytest.approx(14.75)
    diag = geometry.layout(Sensor.paper_single("cartesian"))
    np.testing.assert_allclose(diag.e[0], [math.sqrt(0.5)] * 2)
    assert diag.r_m[0] == pytest.approx(14.75)


def test_frame_stack_round_trip_and_ownership():
    s = Sensor()
    lay = geometry.layout(s)
    frame = np.random.default_rng(1).integers(0, 60000, s.frame_shape).astype(np.uint16)
    stack = geometry.frame_to_stack(frame, lay)
    assert stack.shape == (lay.n_valid, 16, 16) and stack.dtype == np.uint16
    for k in (0, 100, lay.n_valid - 1):
        i, j = lay.index[k]
        np.testing.assert_array_equal(stack[k], frame[16 * i:16 * i + 16, 16 * j:16 * j + 16])
    back = geometry.stack_to_frame(stack, lay)
    mask = np.kron(lay.valid, np.ones((16, 16), bool))
    np.testing.assert_array_equal(back[mask], frame[mask])
    assert (back[~mask] == 0).all()
    with pytest.raises(ValueError, match="shape"):
        geometry.frame_to_stack(frame[:-1], lay)


def test_slope_grid_and_rotations():
    lay = geometry.layout(Sensor())
    slopes = np.random.default_rng(2).normal(size=(lay.n_valid, 2))
    grid = geometry.slopes_to_grid(slopes, lay)
    assert grid.dtype == np.float32 and np.isnan(grid[~lay.valid]).all()
    np.testing.assert_allclose(geometry.grid_to_slopes(grid, lay), slopes, rtol=1e-6)
    local = geometry.detector_to_local(slopes, lay.e)
    np.testing.assert_allclose(geometry.local_to_detector(local, lay.e), slopes, atol=1e-12)
    # local x is the component along e
    np.testing.assert_allclose(local[:, 0], np.sum(slopes * lay.e, axis=1))
