"""Common centroider interface: registry, shapes, dtypes, bad subapertures, axes, describe()."""

import json

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import ALGORITHMS, make_centroider
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import spots

SENSOR = Sensor()
LAY = geometry.layout(SENSOR)
N = LAY.n_valid
# every algorithm except "ann" (needs a model: see test_centroiding_ann.py)
BUILDERS = {
    "cog": {}, "tcog": {"threshold": 2.0}, "wcog": {},
    "cmf": {"reference": "history"}, "cmf_static": {"reference": "static", "weighting": "model"},
    "corr": {"reference": "history"},
}


def build(key, sensor=SENSOR):
    name = key.split("_")[0]
    c = make_centroider(name, sensor, **BUILDERS[key])
    if key.endswith("static"):
        c.set_reference(spots([0, 0], sigma=1.0, n=geometry.layout(sensor).n_valid))
    return c


def stack_with_shifts(rng, n=N, sigma=1.0, photons=1000.0, amp=0.5):
    shift = rng.uniform(-amp, amp, (n, 2))
    return spots(shift, sigma=sigma, photons=photons), shift


def test_registry_names():
    assert set(ALGORITHMS) == {"cog", "tcog", "wcog", "cmf", "corr", "ann", "ml", "gmf"}


@pytest.mark.parametrize("name, options, words", [
    ("nope", {}, "unknown centroiding algorithm"),
    ("cog", {"bogus": 1}, "unknown option"),
    ("cog", {"background": -1}, "background"),
    ("tcog", {"threshold": 1, "threshold_rn": 2}, "only one"),
    ("tcog", {"threshold_frac": 1.5}, "threshold_frac"),
    ("tcog", {"mode": "clip"}, "mode"),
    ("wcog", {"fwhm_par_px": 0}, "fwhm_par_px"),
    ("wcog", {"gain": "magic"}, "gain"),
    ("cmf", {"reference": "yesterday"}, "reference"),
    ("cmf", {"history": 0}, "history"),
    ("cmf", {"history": 2.5}, "history"),
    ("cmf", {"weighting": "flat"}, "weighting"),
    ("cmf", {"dither": 0}, "dither"),
    ("cmf", {"constrained": "yes"}, "constrained"),
    ("cmf", {"update_period": 0}, "update_period"),
    ("corr", {"peak": "lorentz"}, "peak"),
    ("corr", {"padding": 3}, "padding"),
    ("ann", {"model": "/nonexistent/model.onnx"}, "not found"),
])
def test_bad_options_raise_readable_valueerror(name, options, words):
    with pytest.raises(ValueError, match=words):
        make_centroider(name, SENSOR, **options)


@pytest.mark.parametrize("key", list(BUILDERS))
def test_wrong_shapes_raise(key):
    c = build(key)
    for bad in (np.zeros((15, 16)), np.zeros((N + 1, 16, 16)), np.zeros(256),
                np.zeros((N, 16, 15)), np.zeros(SENSOR.frame_shape, dtype=complex)):
        with pytest.raises(ValueError):
            c.centroid(bad)


@pytest.mark.parametrize("key", list(BUILDERS))
def test_bad_subapertures_get_nan_only_there(key):
    rng = np.random.default_rng(1)
    st, shift = stack_with_shifts(rng, amp=0.05)
    bad = {3: "nan", 10: "inf", 20: "zero", 30: "negative", 40: "neg_inf"}
    corrupt = st.copy()
    corrupt[3, 5, 5] = np.nan
    corrupt[10, 7, 7] = np.inf
    corrupt[20] = 0
    corrupt[30] = -corrupt[30]
    corrupt[40, 0, 0] = -np.inf
    c = build(key)
    out = c.centroid(corrupt)
    assert out.shape == (N, 2) and out.dtype == np.float64
    rows = np.array(sorted(bad))
    assert np.isnan(out[rows]).all()
    good = np.setdiff1d(np.arange(N), rows)
    assert np.isfinite(out[good]).all()
    # the good subapertures are unaffected by their bad neighbours
    clean = build(key).centroid(st)
    np.testing.assert_allclose(out[good], clean[good], atol=1e-9)
    # the next, clean frame is fine everywhere except where history is still empty
    out2 = c.centroid(st)
    if key in ("cmf", "corr"):
        assert np.isfinite(out2[good]).all()
    else:
        assert np.isfinite(out2).all()


@pytest.mark.parametrize("key", ["cog", "tcog", "wcog", "cmf_static", "corr"])
def test_frame_and_stack_and_dtypes_agree_and_inputs_untouched(key):
    rng = np.random.default_rng(2)
    st, _ = stack_with_shifts(rng)
    st = rng.poisson(st).astype(np.uint16)
    frame = geometry.stack_to_frame(st, LAY)
    frame_copy, st_copy = frame.copy(), st.copy()
    a = build(key).centroid(frame)
    b = build(key).centroid(st)
    c = build(key).centroid(st.astype(np.float32))
    d = build(key).centroid(st.astype(np.float64))
    np.testing.assert_array_equal(frame, frame_copy)
    np.testing.assert_array_equal(st, st_copy)
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(a, c, atol=1e-5)
    np.testing.assert_allclose(a, d, atol=1e-5)


@pytest.mark.parametrize("key", list(BUILDERS))
def test_describe_is_json(key):
    c = build(key)
    c.centroid(spots([0.1, 0.0], sigma=1.0, n=N))
    d = c.describe()
    assert d["algorithm"] == key.split("_")[0]
    json.dumps(d)


def test_polar_detector_slopes_are_rotated_back_to_detector_axes():
    """A polar frame samples each block along e; the slopes come out in detector axes."""
    sensor = Sensor(detector="polar")
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(3)
    shift_det = rng.uniform(-0.8, 0.8, (lay.n_valid, 2))
    shift_loc = geometry.detector_to_local(shift_det, lay.e)
    st = spots(shift_loc, sigma=1.0, offsets=[-2, -1, 0, 1, 2], weights=[1, 2, 3, 2, 1])
    out = make_centroider("cog", sensor).centroid(geometry.stack_to_frame(st, lay))
    np.testing.assert_allclose(out, shift_det, atol=1e-3)
    # the same images read as a cartesian detector give the local-frame numbers
    out_cart = make_centroider("cog", Sensor()).centroid(st)
    np.testing.assert_allclose(out_cart, shift_loc, atol=1e-3)
    assert np.abs(shift_loc - shift_det).max() > 0.1          # the rotation matters here
