"""The sodium-altitude tracker between profile refits (``centroiding/altitude.py``)."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import options
from lgs_wfs_ros.centroiding.altitude import AltitudeTracker
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from pupils import SMALL

SENSOR = SMALL.replace(detector="cartesian", launch_xy_m=(16.0, 0.0))
LAYOUT = geometry.layout(SENSOR)
MODE = LAYOUT.r_m[:, None] * LAYOUT.e                 # what an altitude change moves


class FakeCalibration:
    """What the tracker reads of a pupil calibration: fits, version and the CoG bias of
    its references (block axes; cartesian: the detector's)."""

    def __init__(self):
        self.fits, self.version, self.bias = 1, 1, np.zeros((LAYOUT.n_valid, 2))

    def refit(self, moved_by: float):
        """A refit whose references sit ``moved_by`` px per metre of r further along m."""
        self.fits += 1
        self.version += 1
        self.bias = self.bias + moved_by * MODE

    def cog_bias(self):
        return self.bias


def test_tracker_follows_a_drifting_altitude_and_carries_on_through_refits():
    """Slopes = independent tilts + the altitude pattern of a slowly drifting layer measured
    against references that each refit (every 140 frames) puts at the layer give or take a
    random error, as a calibration's prediction does: corrected, the references' errors are
    gone (well below the uncorrected error), and a refit brings no jump (a wrong sign in
    the tracker's follow-up would double it)."""
    rng = np.random.default_rng(3)
    cal = FakeCalibration()
    tr = AltitudeTracker(LAYOUT, 0.05, 700.0, lambda v: v)
    ok = np.ones(LAYOUT.n_valid, bool)
    ref = 0.0                                         # where the references put the layer
    raw_err, new_err, jumps = [], [], []
    prev = None
    for k in range(700):
        layer = 2e-3 * np.sin(k / 2000.0)             # px per metre of r: ~0.03 px at 16 m
        if k % 140 == 139:
            new = layer + rng.normal(0.0, 1e-3)      # the refit's reference, with its error
            cal.refit(new - ref)
            ref = new
        tilt = rng.normal(0.0, 0.3, (LAYOUT.n_valid, 2))
        slopes = tilt + (layer - ref) * MODE
        out = tr.apply(slopes, ok, cal)
        if k >= 100:
            raw_err.append(np.abs(slopes - tilt).mean())
            new_err.append(np.abs(out - tilt).mean())
            if prev is not None and k % 140 == 139:
                jumps.append(np.abs((out - tilt) - prev).max())
        prev = out - tilt
    assert np.mean(new_err) < 0.25 * np.mean(raw_err)
    assert max(jumps) < 0.01                          # px: no step at the refits


def test_tracker_keeps_a_frame_without_the_pattern_and_nan_rows():
    cal = FakeCalibration()
    tr = AltitudeTracker(LAYOUT, 0.05, 700.0, lambda v: v)
    slopes = np.random.default_rng(1).normal(0.0, 0.3, (LAYOUT.n_valid, 2))
    ok = np.ones(LAYOUT.n_valid, bool)
    first = tr.apply(slopes, ok, cal)
    np.testing.assert_array_equal(first, slopes)      # nothing known yet: unchanged
    bad = slopes.copy()
    bad[5] = np.nan
    ok[5] = False
    out = tr.apply(bad, ok, cal)
    assert np.isnan(out[5]).all() and np.isfinite(np.delete(out, 5, axis=0)).all()
    assert tr.coefficient(slopes + 0.01 * MODE, np.ones_like(ok)) == pytest.approx(
        tr.coefficient(slopes, np.ones_like(ok)) + 0.01)


def test_tracker_waits_for_the_first_fit_and_restarts_on_a_large_refit():
    """Against the prior (no fit yet) nothing is corrected; a refit that moves the
    references by more than RESTART_PX restarts the average (the old slopes were not
    shifts of the new references), a small one moves it."""
    from lgs_wfs_ros.centroiding import altitude
    rng = np.random.default_rng(5)
    cal = FakeCalibration()
    cal.fits = 0
    tr = AltitudeTracker(LAYOUT, 0.05, 700.0, lambda v: v)
    ok = np.ones(LAYOUT.n_valid, bool)
    frame = lambda a: rng.normal(0.0, 0.05, (LAYOUT.n_valid, 2)) + a * MODE  # noqa: E731
    s = frame(0.01)
    np.testing.assert_array_equal(tr.apply(s, ok, cal), s)
    assert tr.average is None
    cal.refit(0.0)                                    # the first fit
    tr.apply(frame(0.05), ok, cal)                    # its install frame does not count
    assert tr.average is None
    tr.apply(frame(2e-3), ok, cal)
    assert tr.average == pytest.approx(2e-3, abs=2e-4)
    reach = np.hypot(*MODE.T).max()
    cal.refit(0.5 * altitude.RESTART_PX / reach)      # small: the average moves with it
    tr.apply(frame(2e-3), ok, cal)
    tr.apply(frame(2e-3 - 0.5 * altitude.RESTART_PX / reach), ok, cal)
    expected = 2e-3 - 0.5 * altitude.RESTART_PX / reach
    assert tr.average == pytest.approx(expected, abs=3e-4)
    cal.refit(3.0 * altitude.RESTART_PX / reach)      # large: start again after this frame
    tr.apply(frame(0.05), ok, cal)
    assert tr.average is None
    tr.apply(frame(-1e-3), ok, cal)
    assert tr.average == pytest.approx(-1e-3, abs=2e-4)


def test_option_applies_the_tracker_to_a_calibrated_estimator():
    """``pupil_altitude_s`` through the options table: off, the slopes are today's; on, they
    differ from them by a multiple of the altitude pattern only."""
    sensor = Sensor(detector="polar", photons=1000.0)
    lay = geometry.layout(sensor)
    off = options.build("cog", sensor, {"bias": "pupil"})
    on = options.build("cog", sensor, {"bias": "pupil", "pupil_altitude_s": 0.01})
    assert off.pupil.altitude_s == 0.0 and on.pupil.altitude_s == 0.01
    rng = np.random.default_rng(0)
    mode = lay.r_m[:, None] * lay.e
    for k in range(5):
        frame = rng.poisson(3.0, sensor.frame_shape).astype(np.uint16)
        if k == 1:                                    # one fit for both (no correction before)
            off.pupil.refit()
            on.pupil.refit()
        a, b = off.centroid(frame), on.centroid(frame)
        coef = ((a - b) * mode).sum() / (mode * mode).sum()
        np.testing.assert_allclose(a - b, coef * mode, atol=1e-9)
        if k >= 3:
            assert abs(coef) > 0                      # it did correct (not before the fit's
                                                      # install frame has passed)
    with pytest.raises(ValueError, match="pupil_altitude_s"):
        options.build("cog", sensor, {"bias": "pupil", "pupil_altitude_s": -1.0})
