"""The grid matched filter (centroiding/gmf.py) on small pupils of both detectors."""

import functools

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import kernels, options as table
from lgs_wfs_ros.centroiding.gmf import GMF
from lgs_wfs_ros.optics import fast_frames
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.optics.model_spot import ProfileSpots
from lgs_wfs_ros.sensor import Sensor

# 12 m pupil, 24 x 24 subapertures, launch 10 m off axis: r from 4 to 16 m (spots 2-6 px long)
SMALL = dict(diameter_m=12.0, obstruction_m=1.5, n_subaps=24, launch_xy_m=(10.0, 0.0))
DETECTORS = ("polar", "cartesian")


def small(detector, **kw) -> Sensor:
    return Sensor(detector=detector, **{**SMALL, **kw})


def counts_at(c, truth, photons=50000.0, background=0.0):
    """Noise-free counts of the calibration's current spots at ``truth (n, 2)`` (block axes)."""
    spots = ProfileSpots(c.sensor, c.layout.r_m, c.layout.e, c.pupil.nodes_m, c.pupil.light, 4.0)
    img = spots.image_at(truth)
    return np.round(img / img.reshape(c.n, -1).sum(axis=1)[:, None, None] * photons + background)


def frame_of(sensor, counts):
    return geometry.stack_to_frame(counts.astype(np.uint16), geometry.layout(sensor))


@pytest.mark.parametrize("detector", DETECTORS)
def test_noise_free_spots_are_found_on_both_paths_and_the_grid_is_what_does_it(detector):
    """Spots of the calibration's own profile up to 1.1 px away on both axes: found to 0.01 px
    by the compiled pass (a frame) and by numpy (a float stack), which agree. One filter at the
    centre (grid 1) misses the displaced spots by more than 0.05 px: a linear filter is
    exact only near its reference. A swapped axis or a wrong grid origin misses by 0.25 px."""
    sensor = small(detector)
    gmf = table.build("gmf", sensor)
    truth = np.random.default_rng(3).uniform(-1.1, 1.1, (gmf.n, 2))        # block axes
    counts = counts_at(gmf, truth)
    est_stack = gmf.to_pixel_axes(gmf.centroid(counts.astype(np.float32)))
    assert np.abs(est_stack - truth).max() < 0.01
    one = table.build("gmf", sensor, {"grid": 1})
    assert np.abs(one.to_pixel_axes(one.centroid(counts.astype(np.float32))) - truth).max() > 0.05
    if kernels.AVAILABLE:
        est_frame = gmf.to_pixel_axes(table.build("gmf", sensor).centroid(frame_of(sensor, counts)))
        np.testing.assert_allclose(est_frame, est_stack, atol=1e-9)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("detector", DETECTORS)
def test_compiled_pass_equals_numpy_on_noisy_frames_and_a_dark_block_is_nan(detector):
    sensor = small(detector)
    a, b = table.build("gmf", sensor), table.build("gmf", sensor)
    rng = np.random.default_rng(5)
    truth = rng.normal(0.0, 0.46, (a.n, 2))
    counts = rng.poisson(counts_at(a, truth, photons=1000.0)).astype(float)
    counts[7] = 0.0
    est_frame = a.centroid(frame_of(sensor, counts))
    est_stack = b.centroid(counts.astype(np.float32))
    assert np.isnan(est_frame[7]).all() and np.isnan(est_stack[7]).all()
    np.testing.assert_allclose(est_frame, est_stack, atol=1e-9)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_blocks_brighter_than_65535_counts_take_the_wide_sums():
    """The compiled pass sums a block's filter products in 32 bits when its pixel sum is at
    most 65535 (exact there) and in 64 bits above: spots of 40,000 and of 300,000 counts
    (the second past int32 in 32-bit sums: a filter coefficient of 32767 times 300,000)
    give numpy's shifts on both sides of the switch."""
    sensor = small("cartesian")
    a, b = table.build("gmf", sensor), table.build("gmf", sensor)
    truth = np.random.default_rng(6).uniform(-0.9, 0.9, (a.n, 2))
    for photons in (4.0e4, 3.0e5):
        counts = np.minimum(counts_at(a, truth, photons=photons), 65535.0)
        est_frame = a.centroid(frame_of(sensor, counts))
        est_stack = b.centroid(counts.astype(np.float32))
        assert np.abs(a.to_pixel_axes(est_frame) - truth).max() < 0.01
        np.testing.assert_allclose(est_frame, est_stack, atol=1e-9)


@pytest.mark.parametrize("detector", DETECTORS)
def test_a_uniform_background_is_removed(detector):
    """Counts with 50 background counts a pixel (a quarter of the light), given as the
    background: the shifts to 0.025 px (the flatter weighting leaves ~0.013 px of the
    filters' non-linearity a quarter pixel from their reference, 0.005 without background).
    The same counts with the background not given are off by ~0.11 px."""
    sensor = small(detector)
    gmf = table.build("gmf", sensor, {"background": 50.0})
    truth = np.random.default_rng(4).uniform(-0.9, 0.9, (gmf.n, 2))
    counts = counts_at(gmf, truth, background=50.0)
    est = gmf.to_pixel_axes(gmf.centroid(counts.astype(np.float32)))
    assert np.abs(est - truth).max() < 0.025
    if kernels.AVAILABLE:                     # the compiled pass: the same formula
        again = gmf.to_pixel_axes(table.build("gmf", sensor, {"background": 50.0})
                                  .centroid(frame_of(sensor, counts)))
        np.testing.assert_allclose(again, est, atol=1e-9)
    blind = table.build("gmf", sensor)
    assert np.abs(blind.to_pixel_axes(blind.centroid(counts.astype(np.float32))) - truth).max() > 0.08


@pytest.mark.parametrize("detector", DETECTORS)
def test_the_second_pick_recovers_from_a_wrong_first_choice(detector):
    """The calibrated CoG made 0.45 px wrong on both axes (as it is for spots the field
    truncates): with one pick many blocks use a filter up to ~0.7 px from the spot and miss
    by more than 0.05 px (0.06-0.07); the second pick (the default), chosen by that filter's
    measurement, finds every spot to 0.01 px, on both paths (a pick from the estimate of
    the wrong filter, or no second filter applied, would not)."""
    sensor = small(detector)
    truth = np.random.default_rng(9).uniform(-0.9, 0.9, (table.build("gmf", sensor).n, 2))
    est = {}
    for picks in (1, 2):
        for path in ("stack", "frame") if kernels.AVAILABLE else ("stack",):
            gmf = table.build("gmf", sensor, {"picks": picks})
            counts = counts_at(gmf, truth)
            gmf._bias = gmf._bias + 0.45                        # block axes, both
            data = counts.astype(np.float32) if path == "stack" else frame_of(sensor, counts)
            est[picks, path] = gmf.to_pixel_axes(gmf.centroid(data))
    for path in ("stack", "frame") if kernels.AVAILABLE else ("stack",):
        assert np.abs(est[1, path] - truth).max() > 0.05
        assert np.abs(est[2, path] - truth).max() < 0.01
        np.testing.assert_allclose(est[2, path], est[2, "stack"], atol=1e-9)


@pytest.mark.skipif(not fast_frames.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_the_grid_rendered_on_canvases_gives_the_renders_of_each_position(monkeypatch):
    """On cartesian pixels a refit renders each sub-pixel phase of the grid once, with its
    derivatives, on a wider canvas and crops the whole-pixel moves from it: every position's
    image is the one its own render gives, bit for bit, and its derivatives are the central
    differences of renders 0.01 px either side to 1e-3 of their largest value, on the
    default grid and on a 3 x 3 grid 1 px apart (one phase); a crop a pixel off, or the
    derivatives along x and y swapped, are far from them."""
    sensor = small("cartesian")

    for opts in ({}, {"grid": 3, "spacing_px": 1.0}):
        c = table.build("gmf", sensor, opts)
        new = {k: v for k, *v in c._position_images(c.pupil)}
        old = {k: v for k, *v in c._position_images(c.pupil, canvas=False)}
        assert sorted(new) == sorted(old) == list(range(c.positions.size ** 2))
        for k in new:
            np.testing.assert_array_equal(new[k][0], old[k][0])
            for a in (1, 2):
                top = np.abs(old[k][a]).max()
                assert np.abs(new[k][a] - old[k][a]).max() < 1e-3 * top
            assert np.abs(new[k][1] - old[k][2]).max() > 0.1 * top            # x is not y
            assert np.abs(np.roll(new[k][0], 1, axis=2) - old[k][0]).max() > 0.1 * old[k][0].max()
        built = c._prepare(c.pupil)
        with monkeypatch.context() as m:
            m.setattr(GMF, "_position_images", functools.partialmethod(GMF._position_images,
                                                                       canvas=False))
            rendered = c._prepare(c.pupil)
        np.testing.assert_array_equal(built["ok"], rendered["ok"])
        np.testing.assert_allclose(built["scale"], rendered["scale"], rtol=5e-3)


def test_options_are_checked():
    sensor = small("cartesian")
    with pytest.raises(ValueError, match="odd"):
        table.build("gmf", sensor, {"grid": 4})
    with pytest.raises(ValueError, match="beyond half the field"):
        table.build("gmf", sensor, {"grid": 9, "spacing_px": 3.0})
    with pytest.raises(ValueError, match="gmf"):
        table.build("gmf", sensor, {"reference": "history"})
    with pytest.raises(ValueError, match="picks"):
        table.build("gmf", sensor, {"picks": 4})
    d = table.build("gmf", sensor, {"grid": 3, "spacing_px": 0.25}).describe()
    assert d["filter_grid"] == {"positions_per_axis": 3, "spacing_px": 0.25}


def test_a_refit_rebuilds_the_filters_for_the_next_frame():
    """After ``pupil_period`` frames the calibration refits and the filters of its new
    profile are installed (its version), built from the refitted references."""
    sensor = small("polar")
    gmf = table.build("gmf", sensor, {"pupil_period": 3})
    before, v0 = gmf._filters, gmf.pupil.version
    counts = np.random.default_rng(6).poisson(counts_at(gmf, np.zeros((gmf.n, 2)), 1000.0))
    for _ in range(3):
        gmf.centroid(counts.astype(np.float32))
    assert gmf.pupil.version > v0 and gmf._version == gmf.pupil.version
    assert gmf._filters is not before and not np.array_equal(gmf._filters, before)


@pytest.mark.parametrize("detector", DETECTORS)
def test_refits_take_turns_with_two_tables_and_fill_them_whole(detector):
    """A refit fills the tables the refit before last filled (no 72 MB allocated and
    faulted in each time), never those the frames read, and every entry of them: the
    filters installed are those of tables built new for the same calibration."""
    sensor = small(detector)
    gmf = table.build("gmf", sensor, {"pupil_period": 3})
    rng = np.random.default_rng(6)
    installed, contents = [gmf._filters], [gmf._filters.copy()]
    for k in range(3):              # spots moved each period: each refit's filters differ
        counts = rng.poisson(counts_at(gmf, np.full((gmf.n, 2), 0.4 * k), 1000.0))
        for _ in range(3):
            gmf.centroid(counts.astype(np.float32))
        assert gmf._version == gmf.pupil.version
        assert gmf._spare is not None and gmf._spare[0] is not gmf._filters
        installed.append(gmf._filters)
        contents.append(gmf._filters.copy())
    assert installed[2] is installed[0] and installed[3] is installed[1]
    assert installed[1] is not installed[0]
    assert not np.array_equal(contents[3], contents[1])
    gmf._spare = None                                             # a new table for the same fit
    fresh = gmf._prepare(gmf.pupil)
    assert fresh["filters"] is not gmf._filters
    np.testing.assert_array_equal(fresh["filters"], gmf._filters)
    np.testing.assert_array_equal(fresh["scale"], gmf._scale)
    np.testing.assert_array_equal(fresh["rsum"], gmf._rsum)
    np.testing.assert_array_equal(fresh["ok"], gmf._ok)
    wrong = (np.empty((2, 2, 16), dtype=np.float32), np.empty((2, 2)), np.empty((2, 2)),
             np.empty(2, dtype=bool))                            # float filters: refused
    with pytest.raises(ValueError, match="out must be"):
        kernels.position_filters(*np.ones((3, 2, 4, 4)), 1.0, 1.0, out=wrong)


def test_quantized_rows_are_the_filters_to_half_a_step():
    from lgs_wfs_ros.centroiding.kernels import quantize
    r = np.random.default_rng(8).normal(0.0, 1e-3, (3, 5, 2, 256))
    r[1, 2, 0] = 0.0                                          # an empty row stays empty
    q, scale = quantize(r)
    assert q.dtype == np.int16 and np.abs(q).max() == 32767
    err = np.abs(q * scale[..., None] - r)
    assert np.all(err <= 0.5 * scale[..., None] + 1e-18)
    assert np.all(q[1, 2, 0] == 0) and np.all(np.isfinite(scale))


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("detector", DETECTORS)
def test_the_compiled_build_gives_the_numpy_filters(monkeypatch, detector):
    """A refit's filters built in one compiled pass a position (kernels.position_filters)
    are solve_filter's, quantized: the same int16 rows, scales and sums to 1e-12, the same
    ok; a block without light gets zero rows and is not ok on both paths. Weights of 1 /
    counts without the variance floor, or the flux column left out, change the rows."""
    sensor = small(detector)
    c = table.build("gmf", sensor, {"read_noise_e": 1.5, "background": 2.0})
    new = c._prepare(c.pupil)
    with monkeypatch.context() as m:
        m.setattr(kernels, "AVAILABLE", False)
        old = c._prepare(c.pupil)
    np.testing.assert_array_equal(new["filters"], old["filters"])
    np.testing.assert_allclose(new["scale"], old["scale"], rtol=1e-12)
    np.testing.assert_allclose(new["rsum"], old["rsum"], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(new["ok"], old["ok"])
    assert new["ok"].all()

    _, *img = next(iter(c._position_images(c.pupil)))
    img = np.array(img)                                                   # (3, n, p, p)
    img[:, 3] = 0.0                                                       # a dark block
    f, s, rs, ok = kernels.position_filters(*img, 3.5, 1.0)
    assert not ok[3] and np.all(f[3] == 0) and np.all(rs[3] == 0) and ok[np.arange(c.n) != 3].all()
    # a plausibly wrong build: derivatives off by 2 (the step's; gain 2), or no variance floor
    doubled = kernels.position_filters(img[0], 2 * img[1], 2 * img[2], 3.5, 1.0)[1]
    assert not np.allclose(s, doubled, rtol=0.1)
    assert not np.array_equal(f, kernels.position_filters(*img, 0.0, 1e-9)[0])


@pytest.mark.skipif(not (fast_frames.AVAILABLE and kernels.AVAILABLE),
                    reason="numba not installed ('fast' extra)")
def test_polar_filters_from_lines_are_those_of_the_renders(monkeypatch):
    """On a polar detector a refit builds the grid's filters from each spot's line and core
    (kernels.separable_filters on FastRenderer.polar_lines) instead of 125 renders: the
    same int16 rows, scales, sums and ok bit for bit, on the default grid and a 3 x 3 one;
    a core moved a pixel changes them."""
    sensor = small("polar", read_noise_e=1.0)
    for opts in ({}, {"grid": 3, "spacing_px": 1.0}):
        c = table.build("gmf", sensor, opts)
        new = c._prepare(c.pupil)
        with monkeypatch.context() as m:
            m.setattr(GMF, "_separable", lambda self: False)
            old = c._prepare(c.pupil)
        for key in ("filters", "scale", "rsum", "ok"):
            np.testing.assert_array_equal(new[key], old[key])
    real = GMF._position_lines

    def moved(self, calibration):
        for k, lines, cores, counts in real(self, calibration):
            yield k, lines, np.roll(cores, 1, axis=2), counts
    monkeypatch.setattr(GMF, "_position_lines", moved)
    assert not np.array_equal(c._prepare(c.pupil)["filters"], old["filters"])
