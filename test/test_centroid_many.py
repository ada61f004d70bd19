"""centroid_many: several frames at once give what one call per frame gives."""

from dataclasses import replace

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import make_centroider
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import sodium_line, spots

CASES = [("cog", {}), ("tcog", {"threshold": 2.0}), ("wcog", {}),
         ("cmf", {}), ("cmf", {"reference": "model", "weighting": "model"}),
         ("ann", {"model": "ann_1k"}), ("ann", {"model": "ann_pupil"})]


def frames(sensor, k, seed=0):
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(seed)
    off, w = sodium_line(3.0, 9)
    e = lay.e if sensor.detector == "cartesian" else np.tile([1.0, 0.0], (lay.n_valid, 1))
    out = []
    for _ in range(k):
        st = rng.poisson(spots(rng.uniform(-0.8, 0.8, (lay.n_valid, 2)), e=e, offsets=off, weights=w))
        out.append(geometry.stack_to_frame(st.astype(np.uint16), lay))
    out = np.stack(out)
    out[1] = 0                                   # an empty frame: NaN slopes, nothing else
    return out


SENSORS = {"single-polar": Sensor.paper_single("polar"),
           "8x8-cartesian": replace(Sensor(), n_subaps=8, pixels=16, detector="cartesian")}
PAIRS = [(s, n, o) for s in SENSORS for n, o in CASES
         if not (o.get("model") == "ann_1k" and SENSORS[s].detector != "polar")]   # a polar model


@pytest.mark.parametrize("sensor_id,name,options", PAIRS)
def test_centroid_many_equals_one_call_per_frame(sensor_id, name, options):
    sensor = SENSORS[sensor_id]
    f = frames(sensor, 6)
    one = make_centroider(name, sensor, **options)
    many = make_centroider(name, sensor, **options)
    expect = np.stack([one.centroid(x) for x in f])
    got = many.centroid_many(f)
    assert got.shape == (6, one.n, 2)
    np.testing.assert_allclose(got, expect, atol=1e-5, equal_nan=True)
    assert np.isnan(got[1]).all() and np.isfinite(np.delete(got, 1, axis=0)).all()
    stacks = geometry.frame_to_stack(f, geometry.layout(sensor)).astype(np.float32)
    np.testing.assert_allclose(make_centroider(name, sensor, **options).centroid_many(stacks), expect,
                               atol=1e-4, equal_nan=True)


def test_centroid_many_refuses_what_centroid_refuses():
    c = make_centroider("cog", Sensor.paper_single("polar"))
    with pytest.raises(ValueError, match="shape"):
        c.centroid_many(np.zeros((2, 15, 15)))
    assert c.centroid_many([]).shape == (0, 1, 2)
