"""Compiled single-pass kernels (centroiding.kernels) against the numpy implementations."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import kernels, make_centroider
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from pupils import SMALL

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")

SENSORS = [Sensor(), Sensor(detector="polar"), Sensor(diameter_m=4.0, obstruction_m=0.5,
                                                      n_subaps=8, pixels=12)]


def _frame(sensor, seed, high=False):
    rng = np.random.default_rng(seed)
    f = rng.poisson(40, sensor.frame_shape)
    if high:                  # saturated blocks: the integer sums must not overflow
        f[: sensor.pixels * 3] = 65535
    return f.astype(np.uint16)


@pytest.mark.parametrize("sensor", SENSORS, ids=["cartesian", "polar", "small_p12"])
def test_cog_moments_equal_the_numpy_products(sensor):
    cog = make_centroider("cog", sensor)
    for seed, high in ((1, False), (2, True)):
        frame = _frame(sensor, seed, high)
        stack = geometry.frame_to_stack(frame, geometry.layout(sensor)).reshape(cog.n, -1)
        want = stack.astype(np.float64) @ cog._w3
        got = kernels.cog_moments(frame, kernels.origins(cog), cog.p, cog.centre)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-6)


@pytest.mark.parametrize("sensor", SENSORS, ids=["cartesian", "polar", "small_p12"])
def test_cog_with_the_kernel_equals_cog_without(sensor, monkeypatch):
    cog = make_centroider("cog", sensor)
    frames = [_frame(sensor, s) for s in (3, 4)]
    fast = [cog.centroid(f) for f in frames]
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    slow = [cog.centroid(f) for f in frames]
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        assert np.isfinite(a).all()


def test_block_contract_equals_einsum():
    sensor = SENSORS[1]
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(5)
    w = rng.normal(size=(lay.n_valid, 3, sensor.pixels ** 2)).astype(np.float32)
    frame = _frame(sensor, 6, high=True)
    flat = geometry.frame_to_stack(frame, lay).reshape(lay.n_valid, -1).astype(np.float64)
    want = np.einsum("nkp,np->nk", w.astype(np.float64), flat)
    got = kernels.block_contract(frame, kernels.block_origins(lay), w)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-3 * np.abs(want).max() * 1e-3)


def test_filter_flux_equals_the_contraction_with_a_row_of_ones():
    """The CMF's two filter rows plus the flux (the plain pixel sum, exact even for saturated
    blocks) equal block_contract with [R; 1], per block."""
    sensor = SENSORS[1]
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(8)
    w = rng.normal(size=(lay.n_valid, 2, sensor.pixels ** 2)).astype(np.float32)
    frame = _frame(sensor, 9, high=True)
    ones = np.ones((lay.n_valid, 1, sensor.pixels ** 2), np.float32)
    want = kernels.block_contract(frame, kernels.block_origins(lay), np.concatenate([w, ones], 1))
    got = kernels.filter_flux(frame, kernels.block_origins(lay), w)
    np.testing.assert_array_equal(got[:, 2], want[:, 2])
    assert got[:, 2].max() > 65535 * sensor.pixels                  # a saturated block summed
    np.testing.assert_allclose(got[:, :2], want[:, :2], rtol=1e-9, atol=1e-9 * np.abs(want).max())
    with pytest.raises(ValueError, match="2 filter rows"):
        kernels.filter_flux(frame, kernels.block_origins(lay), np.concatenate([w, ones], 1))


def test_filter_flux_with_int16_rows_sums_the_quantized_filter_exactly():
    """int16 rows with one scale each (what the CMF reads a frame): the sums are the exact
    products of the integer rows and pixels, scaled; the flux is the plain pixel sum."""
    sensor = SENSORS[0]
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(10)
    r = rng.normal(size=(lay.n_valid, 2, sensor.pixels ** 2))
    q, scale = kernels.quantize(r)
    assert q.dtype == np.int16 and np.abs(q).max() == 32767
    np.testing.assert_allclose(q * scale[..., None], r, atol=0.51 * scale.max())
    frame = _frame(sensor, 11, high=True)
    stack = geometry.frame_to_stack(frame, lay).reshape(lay.n_valid, -1).astype(np.int64)
    exact = np.einsum("nkp,np->nk", q.astype(np.int64), stack)           # integers
    got = kernels.filter_flux(frame, kernels.block_origins(lay), q, scale=scale)
    np.testing.assert_allclose(got[:, :2], exact * scale, rtol=1e-15)
    np.testing.assert_array_equal(got[:, 2], stack.sum(axis=1))
    with pytest.raises(ValueError, match="scale"):
        kernels.filter_flux(frame, kernels.block_origins(lay), q)


def test_warm_up_compiles_the_frame_kernels_for_read_only_frames():
    """Shared-memory frames are read-only views: another numba signature, which must be
    compiled by warm_up, not on a live node's first frame."""
    kernels.warm_up()
    for disp in (kernels.blocks._cog_moments, kernels.filters._filter_flux,
                 kernels.filters._filter_flux_q, kernels.filters._grid_filter,
                 kernels.ml._ml_search, kernels.blocks._block_marginals,
                 kernels.corr._corr_lags):
        frames = {sig[0].mutable for sig in disp.signatures}
        assert frames >= {True, False}, disp


def test_cmf_model_with_the_kernel_equals_cmf_without(monkeypatch):
    sensor = SMALL.replace(detector="polar")
    cmf = make_centroider("cmf", sensor, weighting="model", reference="model")
    frame = _frame(sensor, 7)
    fast = cmf.centroid(frame)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    slow = cmf.centroid(frame)
    np.testing.assert_allclose(fast, slow, rtol=1e-4, atol=1e-5)


def test_only_plain_integer_frames_take_the_kernel():
    s = SENSORS[0]
    f = _frame(s, 8)
    assert kernels.fits(f, s.frame_shape)
    assert not kernels.fits(f.astype(np.float32), s.frame_shape)
    assert not kernels.fits(f[:, ::-1], s.frame_shape)           # columns not contiguous
    assert not kernels.fits(f[:-16], s.frame_shape)
    ro = f.copy()
    ro.flags.writeable = False                                   # a shared-memory view is fine
    assert kernels.fits(ro, s.frame_shape)


def _simulated(detector, frames=3, truths=False):
    """``(sensor, frames)`` of the simulator on SMALL, and with ``truths`` their true
    slopes ``(frames, n, 2)`` px."""
    from lgs_wfs_ros.optics.simulator import Simulator
    sensor = SMALL.replace(detector=detector)
    sim = Simulator(sensor)
    got = [sim.next() for _ in range(frames)]
    out = sensor, [f.frame.copy() for f in got]
    return (*out, np.array([f.truth for f in got])) if truths else out


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
def test_corr_with_the_kernel_equals_the_fft_maps(detector, monkeypatch):
    """The compiled correlation (the map only at the 3 x 3 lags around the peak, reached
    from the CoG) gives the FFT map's peak fit; on cartesian pixels a spot elongated
    across the pixel axes makes a ridge in the map, where a few blocks (noise-made local
    maxima; at the field's edge, here 1.5 % of them) may take another maximum of the
    ridge, and those are no further from the truth than the map's largest."""
    sensor, frames, truths = _simulated(detector, truths=True)
    fast_c = make_centroider("corr", sensor, pupil_period=2)
    slow_c = make_centroider("corr", sensor, pupil_period=2)
    fast = np.array([fast_c.centroid(f) for f in frames])
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    slow = np.array([slow_c.centroid(f) for f in frames])
    assert fast_c.pupil.fits == slow_c.pupil.fits == 1                  # a refit on the way
    d = np.abs(fast - slow).max(axis=2)
    assert np.isfinite(fast).all()
    if detector == "polar":
        assert d.max() < 1e-4
    else:
        other = d > 1e-4
        assert 0 < other.mean() < 0.03
        assert np.median(d) < 1e-5
        err = lambda est: np.hypot(*(est - truths)[other].T).mean()      # noqa: E731
        assert err(fast) <= 1.05 * err(slow)


def _gauss_spot(p, shift, sigma_along, sigma_across, angle):
    """``(p, p)`` an elliptical Gaussian at ``shift`` px (x, y) from the block centre, its
    long axis at ``angle`` rad, sampled at the pixel centres."""
    y, x = np.indices((p, p)) - (p - 1) / 2
    x, y = x - shift[0], y - shift[1]
    c, s = np.cos(angle), np.sin(angle)
    u, v = c * x + s * y, -s * x + c * y
    return np.exp(-0.5 * ((u / sigma_along) ** 2 + (v / sigma_across) ** 2))


def _lag_value(img, ref, tx, ty):
    """``sum_u img(u + t) ref(u)``, zero outside the block."""
    p = img.shape[0]
    pad = np.pad(img, p)
    return float((pad[p + ty:2 * p + ty, p + tx:2 * p + tx] * ref).sum())


@pytest.mark.parametrize("angle", [np.pi / 4, -np.pi / 4, np.pi / 6])
def test_corr_starts_at_the_whole_lag_where_a_spot_like_its_reference_peaks(angle):
    """The pass starts each block at the corner of the unit cell around its predicted lag
    where the map of a spot shaped like its reference is largest (start_metric: the
    reference's own correlation), not at the nearest whole lag, which on a spot elongated
    across the pixel axes is often a step off (each such block then climbed)."""
    p, rng = 16, np.random.default_rng(4)
    ref = _gauss_spot(p, (0.0, 0.0), 2.5, 0.7, angle)
    q = kernels.corr.start_metric(ref[None])[0]
    hits = nearest = 0
    shifts = rng.uniform(-1.5, 1.5, (200, 2))
    for sx, sy in shifts:
        img = _gauss_spot(p, (sx, sy), 2.5, 0.7, angle)
        fx, fy = int(np.floor(sx)), int(np.floor(sy))
        corners = [(fx + kx, fy + ky) for ky in (0, 1) for kx in (0, 1)]
        best = max(corners, key=lambda t: _lag_value(img, ref, *t))
        hits += kernels.corr._start_lag_impl(sx, sy, q) == best
        nearest += (int(np.floor(sx + 0.5)), int(np.floor(sy + 0.5))) == best
    assert hits >= 0.97 * len(shifts)
    assert nearest <= 0.9 * len(shifts)              # what the metric is for
    flat = kernels.corr.start_metric(np.zeros((1, p, p)))[0]
    np.testing.assert_array_equal(flat, [1.0, 0.0, 1.0])    # no light: the nearest lag


def test_corr_kernel_climbs_to_the_peak_from_a_wrong_start():
    """Started 2 or 5 lags off (a wrong reference CoG), the climb reaches the map's maximum."""
    sensor, frames = _simulated("polar", 1)
    corr = make_centroider("corr", sensor)
    refs, ref_cog = corr._ref_kernel()
    o = kernels.origins(corr)
    want = kernels.corr_peak(frames[0], o, corr.p, refs, ref_cog, corr.background)
    off = kernels.corr_peak(frames[0], o, corr.p, refs, ref_cog + [2.0, -2.0], corr.background)
    np.testing.assert_allclose(off, want, atol=1e-4)     # the same lags, float32 sums in
                                                         # another order (a lag off: > 0.01)
    far = kernels.corr_peak(frames[0], o, corr.p, refs, ref_cog + [-5.0, 0.0], corr.background,
                            climbs=8)            # lags beyond the padding: the direct sums
    np.testing.assert_allclose(far, want, atol=1e-5)
    stuck = kernels.corr_peak(frames[0], o, corr.p, refs, ref_cog + [2.0, -2.0],
                              corr.background, climbs=0)
    assert np.abs(stuck - want).max() > 0.5


def test_add_counts_adds_a_frame_as_numpy_does_and_refuses_what_it_cannot_add():
    """The pupil calibration's per-frame accumulation: uint16 counts into uint32, exact
    (65535 counts a pixel, many frames); a non-contiguous view is refused (False, nothing
    added), not added into a copy."""
    frame = _frame(SENSORS[0], 3, high=True)
    acc = np.zeros(frame.shape, np.uint32)
    for _ in range(3):
        assert kernels.add_counts(acc, frame)
    np.testing.assert_array_equal(acc, 3 * frame.astype(np.uint32))
    before = acc.copy()
    assert not kernels.add_counts(acc, frame[:, ::-1])
    assert not kernels.add_counts(acc, frame.astype(np.int32))
    np.testing.assert_array_equal(acc, before)


def test_corr_kernel_reads_its_references_at_int16_without_moving_the_peak():
    """The references go to the pass quantised (int16, one scale each), swept only from
    their first to their last non-zero entry; the peak fit does not see the scale, and the
    quantisation moves no centroid by more than 1e-3 px from the FFT map's fit."""
    sensor, frames = _simulated("polar", 1)
    corr = make_centroider("corr", sensor)
    refs, ref_cog = corr._ref_kernel()
    rows, spans, _ = refs
    assert rows.dtype == np.int16 and np.abs(rows).max(axis=1).min() == 32767
    assert (spans[:, 1] - spans[:, 0]).mean() < 0.7 * rows.shape[1]    # polar: rows skipped
    for b in (0, 300, 700):                       # nothing non-zero outside a span
        assert not rows[b, :spans[b, 0]].any() and not rows[b, spans[b, 1]:].any()
        assert rows[b, spans[b, 0]] != 0 and rows[b, spans[b, 1] - 1] != 0
    o = kernels.origins(corr)
    got = kernels.corr_peak(frames[0], o, corr.p, refs, ref_cog, corr.background)
    exact = corr.correlation_map(geometry.frame_to_stack(frames[0], geometry.layout(sensor)))
    from lgs_wfs_ros.centroiding.correlation import _parabola_peak
    want = _parabola_peak(exact, log=True) - exact.shape[-1] / 2
    assert np.abs(got - want).max() < 1e-3


def test_turning_the_flag_off_takes_every_wrapper_to_numpy(monkeypatch):
    """The tests above compare each estimator with and without its compiled pass by turning
    ``kernels.AVAILABLE`` off: every wrapper must read that one flag at each call (a module
    of the package reading a flag of its own left them comparing the kernel with itself)."""
    s = SENSORS[2]
    f = _frame(s, 9)
    stack = np.zeros((2, 4, 4), np.uint16)
    r, t, g = np.array([[-1.0, 0.0, 1.0]]), np.array([-1.0, 0.0, 1.0]), np.ones(1)
    assert kernels.fits(f, s.frame_shape) and kernels.stack_view(stack, 2, 4) is not None
    assert kernels.add_counts(np.zeros(4, np.uint32), np.zeros(4, np.uint16))
    monkeypatch.setattr(kernels.bins, "_response_inverse", None)       # a compiled call fails
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    assert not kernels.fits(f, s.frame_shape) and kernels.stack_view(stack, 2, 4) is None
    assert not kernels.add_counts(np.zeros(4, np.uint32), np.zeros(4, np.uint16))
    np.testing.assert_allclose(kernels.response_inverse(np.array([0.5]), r, t, g), [0.5])
