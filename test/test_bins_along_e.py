"""Bins along e with pixels split by overlap (centroiding/bins_along_e.py), and a marginals
model (ann_conv's kind) reading them on a cartesian detector."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import bins_along_e, kernels, make_centroider, options
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from test_ann_marginals import linear_marginal_model
from test_ann_reference import P, frames
from pupils import SMALL

#: a side launch 16 m off axis: long spots the field cuts
SIDE = SMALL.replace(detector="cartesian", launch_xy_m=(16.0, 0.0))


def subpixel_projection(img, e, points=100_000, seed=0):
    """The bins by brute force: ``points`` uniform random points a pixel, each to the bin it
    falls in (a regular grid of points aliases at 45 deg)."""
    p = img.shape[0]
    rng = np.random.default_rng(seed)
    out = np.zeros(p)
    c = (p - 1) / 2
    for i, j in zip(*np.nonzero(img)):
        s = rng.random((points, 2)) - 0.5
        u = (j - c + s[:, 0]) * e[0] + (i - c + s[:, 1]) * e[1]
        out += img[i, j] * np.histogram(u, bins=p, range=(-p / 2, p / 2))[0] / points
    return out


def test_polar_bins_are_the_column_sums():
    rng = np.random.default_rng(0)
    img = rng.random((3, P, P))
    start, w = bins_along_e.overlap_weights(np.tile([1.0, 0.0], (3, 1)), P)
    np.testing.assert_allclose(bins_along_e.project(img.reshape(3, -1), start, w), img.sum(axis=1),
                               atol=1e-6)


@pytest.mark.parametrize("deg", [3.0, 22.5, 45.0, 117.0, 200.0])
def test_bins_split_each_pixel_by_its_overlap(deg):
    """At any angle, the bins equal a brute-force split of each pixel into random points
    (to its sampling noise), and light inside the bins' span is kept."""
    rng = np.random.default_rng(int(deg))
    e = np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])
    img = np.zeros((P, P))
    img[4:12, 3:13] = rng.random((8, 10))
    start, w = bins_along_e.overlap_weights(e[None], P)
    got = bins_along_e.project(img.reshape(1, -1), start, w)[0]
    want = subpixel_projection(img, e)
    np.testing.assert_allclose(got, want, atol=0.02 * img.max())
    assert got.sum() == pytest.approx(img.sum(), rel=1e-6)
    # whole pixels to the bin of their centre differ by far more
    assert np.abs(got - want).max() < 0.25 * np.abs(np.histogram(
        ((np.indices((P, P))[1] - 7.5) * e[0] + (np.indices((P, P))[0] - 7.5) * e[1]).ravel(),
        bins=P, range=(-P / 2, P / 2), weights=img.ravel())[0] - want).max()


def test_a_moved_window_reads_the_same_light_a_whole_bin_further():
    """Windows moved by o px along e (moved) read what the centred one reads, o bins on:
    a wrong sign or a re-split pixel fails; light the centred window drops at a diagonal
    block's far end comes back."""
    rng = np.random.default_rng(2)
    e = np.array([[np.cos(0.8), np.sin(0.8)], [np.cos(2.0), np.sin(2.0)]])
    img = rng.random((2, P * P))
    start, w = bins_along_e.overlap_weights(e, P)
    centred = bins_along_e.project(img, start, w)
    for o in (1, 3, -2):
        off = np.array([o, -o])
        got = bins_along_e.project(img, bins_along_e.moved(start, off), w)
        for b in range(2):
            k = np.arange(P)
            inside = (k + off[b] >= 0) & (k + off[b] < P)
            np.testing.assert_allclose(got[b, inside], centred[b, k[inside] + off[b]], rtol=1e-9)
            assert got[b, ~inside].sum() > 0          # light beyond the centred window's end
    far = np.zeros((1, P, P))
    far[0, 13:, 13:] = 1.0                            # a diagonal block's far corner
    diag = np.array([[np.sqrt(0.5), np.sqrt(0.5)]])
    s0, w0 = bins_along_e.overlap_weights(diag, P)
    kept0 = bins_along_e.project(far.reshape(1, -1), s0, w0).sum()
    kept3 = bins_along_e.project(far.reshape(1, -1), bins_along_e.moved(s0, [3]), w0).sum()
    assert kept0 < 0.2 * far.sum() and kept3 > 0.98 * far.sum()     # (the last corner: 11.3 px)


@pytest.mark.parametrize("deg, centre, want", [(45.0, 5.0, 3), (45.0, -2.2, -2), (45.0, 0.4, 0),
                                               (0.0, 5.0, 0), (90.0, -5.0, 0), (18.0, 5.0, 2),
                                               (225.0, 5.0, 3)])
def test_window_offsets_follow_the_references_light_within_the_blocks_reach(deg, centre, want):
    """The window sits at the reference's light centre along e, rounded, held within the
    block's reach along e (none along a pixel axis, +-3 px on a diagonal)."""
    e = np.array([[np.cos(np.radians(deg)), np.sin(np.radians(deg))]])
    y, x = np.indices((P, P)) - (P - 1) / 2
    u = x * e[0, 0] + y * e[0, 1]
    ref = np.exp(-0.5 * ((u - centre) / 1.5) ** 2 - 0.5 * ((-x * e[0, 1] + y * e[0, 0]) / 1.5) ** 2)
    assert bins_along_e.window_offsets(ref.reshape(1, -1), e)[0] == want
    assert bins_along_e.window_offsets(np.zeros((1, P * P)), e)[0] == 0


def test_a_nan_pixel_makes_its_block_nan():
    start, w = bins_along_e.overlap_weights(np.array([[0.6, 0.8], [1.0, 0.0]]), P)
    flat = np.ones((2, P * P))
    flat[0, 5] = np.nan
    out = bins_along_e.project(flat, start, w)
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
def test_compiled_bins_are_the_quantised_split_of_every_pixel():
    """The frame pass (corner pixels whose bins all lie outside included) gives the
    quantised split's bins, within 1/510 of each pixel's count of the exact split, and the
    block's moments exactly."""
    sensor = Sensor(detector="cartesian")
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(5)
    frame = rng.integers(0, 4000, size=sensor.frame_shape).astype(np.uint16)
    start, w = bins_along_e.overlap_weights(lay.e, P)
    s8, shares, wq = bins_along_e.quantised(start, w)
    bins, mom = kernels.block_bins(frame, kernels.block_origins(lay), P, s8, shares)
    flat = geometry.frame_to_stack(frame, lay).reshape(lay.n_valid, -1).astype(np.float64)
    np.testing.assert_allclose(bins, bins_along_e.project(flat, s8, wq), rtol=1e-5)
    exact = bins_along_e.project(flat, start, w)
    assert np.abs(bins - exact).max() <= 4000 * 3 * P / 510
    assert 0 < np.abs(bins - exact).max()
    y, x = np.indices((P, P))
    np.testing.assert_array_equal(mom, np.stack([flat.sum(1), flat @ x.ravel(), flat @ y.ravel()], 1))


def test_marginals_model_on_a_cartesian_detector_reads_bins_along_e(tmp_path):
    """A marginals model is refused on a cartesian detector by its domain guard (trained
    polar), and with out_of_domain = warn reads bins along e: the linear model (the CoG of
    its input less the reference's) gives along e the CoG of the spot's bins less that of
    the calibrated reference's bins (not linearized), and across e the calibrated CoG (which reads v^T J s, J
    its response: :meth:`ANN._solve_ab`), through refits and on
    frames and stacks, through windows moved to the references' light (the model declares
    lgs_wfs.bins_window reference); all subapertures are counted outside the domain."""
    sensor = SIDE
    path = linear_marginal_model(tmp_path / "marg.onnx", metadata={"lgs_wfs.bins_window": "reference"})
    with pytest.raises(ValueError, match="polar detector; the sensor is cartesian"):
        make_centroider("ann", sensor, model=str(path))
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.0}
    ann = options.build("ann", sensor, {"model": str(path), "out_of_domain": "warn",
                                        "linearize": False, **pup})
    cog = options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup})
    lay = geometry.layout(sensor)
    e = np.asarray(lay.e)
    v = np.stack([-e[:, 1], e[:, 0]], axis=1)
    centred = bins_along_e.overlap_weights(e, P)
    pos = np.arange(P) - (P - 1) / 2

    def bins_cog(stack):                              # through the centroider's windows
        start, _, w = bins_along_e.quantised(bins_along_e.moved(centred[0], ann._window), centred[1])
        b = bins_along_e.project(stack.reshape(lay.n_valid, -1), start, w)
        return b @ pos / b.sum(axis=1)

    for k, f in enumerate(frames(sensor, 7)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)
        ref = ann.pupil.counts()[0]                   # the references this frame is read against
        a, c = ann.centroid(data), cog.centroid(data)
        if k % 3 == 2:                                # a refit installed new ones on this frame
            ref = ann.pupil.counts()[0]
        stack = geometry.frame_to_stack(f, lay).astype(float)
        along = bins_cog(stack) - bins_cog(ref)
        np.testing.assert_allclose((a * e).sum(axis=1), along, atol=2e-4)
        vj = np.einsum("ni,nij->nj", v, cog.pupil.cog_response().forward(np.zeros((lay.n_valid, 2)))[1])
        np.testing.assert_allclose((a * vj).sum(axis=1), (c * v).sum(axis=1), atol=2e-4)
        # not the column sums: along e the bins' CoG differs from the plain block CoG's
        assert np.abs((a - c) * e).sum(axis=1).mean() > 0.01
    # the windows sit where the refitted references' light is (the layer at 92 km is
    # above h_ref: off centre along e far from the 16 m side launch)
    np.testing.assert_array_equal(ann._window, bins_along_e.window_offsets(
        ann.pupil.reference_image().reshape(lay.n_valid, -1), e))
    assert np.count_nonzero(ann._window) > 100
    d = ann.describe()
    assert d["domain"]["out_of_domain_subapertures"] == lay.n_valid
    assert "polar" in d["warning"]


def test_a_model_trained_on_centred_windows_keeps_them(tmp_path):
    """A model without lgs_wfs.bins_window (trained on windows centred on the blocks, as
    every model before 2026-11-27) reads centred windows through refits, where a model
    declaring reference windows moves them."""
    sensor = SIDE
    pup = {"pupil_period": 2, "pupil_time_constant_s": 0.0, "out_of_domain": "warn"}
    old = options.build("ann", sensor, {"model": str(linear_marginal_model(tmp_path / "a.onnx")), **pup})
    new = options.build("ann", sensor, {"model": str(linear_marginal_model(
        tmp_path / "b.onnx", metadata={"lgs_wfs.bins_window": "reference"})), **pup})
    for f in frames(sensor, 2):
        old.centroid(f), new.centroid(f)
    assert old.meta["bins_window"] == "centred" and not np.any(old._window)
    assert np.count_nonzero(new._window) > 100
    assert old.describe()["bins_window"] == {"kind": "centred", "moved_subapertures": 0}
    assert new.describe()["bins_window"] == {"kind": "reference",
                                             "moved_subapertures": np.count_nonzero(new._window)}
    with pytest.raises(ValueError, match="bins_window"):
        linear_marginal_model(tmp_path / "c.onnx", metadata={"lgs_wfs.bins_window": "left"})
        options.build("ann", sensor, {"model": str(tmp_path / "c.onnx"), **pup})


def test_grid_direction_is_the_nearest_pixel_grid_direction_along_e():
    """Of the eight signed grid directions (columns, rows, diagonals, each either way) the
    one nearest to e: at most 22.5 deg from it, never pointing against it."""
    deg = np.linspace(0.0, 360.0, 721)[:-1] + 0.1
    e = np.stack([np.cos(np.radians(deg)), np.sin(np.radians(deg))], axis=1)
    d = bins_along_e.grid_direction(e)
    eight = np.concatenate([bins_along_e.GRID_DIRECTIONS, -bins_along_e.GRID_DIRECTIONS])
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose((d * e).sum(axis=1), (e @ eight.T).max(axis=1))
    assert (d * e).sum(axis=1).min() >= np.cos(np.radians(22.5)) - 1e-12
    assert set(bins_along_e.grid_code(d)) == {0, 1, 2, 3}


def _sums_on_unit_bins(img, d):
    """Bins along d by brute force: each pixel's light spread evenly over its unit square
    (many points), the points projected on d and histogrammed in 1 px bins. Every pixel of
    a whole-pixel sum along the grid has the same spread (a box 1 px wide on a column or
    row, a triangle sqrt 2 px wide on a diagonal)."""
    p = img.shape[0]
    c = (p - 1) / 2
    y, x = np.indices((p, p))
    u = ((x - c) * d[0] + (y - c) * d[1]).ravel()             # every pixel of a sum: one u
    t = (np.arange(501) + 0.5) / 501 - 0.5
    spread = (t[:, None] * d[0] + t[None, :] * d[1]).ravel()  # the square's points along d
    out = np.zeros(p)
    for value, ui in zip(img.ravel(), u):
        out += value * np.histogram(ui + spread, bins=p, range=(-p / 2, p / 2))[0] / spread.size
    return out


@pytest.mark.parametrize("deg", [10.0, 40.0, 100.0, 130.0, 200.0, 318.0])
def test_grid_bins_are_whole_pixel_sums_along_the_grid_direction(deg):
    """Columns, rows, diagonals and anti-diagonals, either way along e: whole-pixel sums on
    1 px bins along the grid direction (a column sum is a bin; a diagonal sum spread by
    its pixels' triangle footprint), every pixel of a sum split alike; not the overlap
    split along e."""
    rng = np.random.default_rng(int(deg))
    e = np.array([[np.cos(np.radians(deg)), np.sin(np.radians(deg))]])
    img = np.zeros((P, P))
    img[3:13, 2:14] = rng.random((10, 12))
    start, w, d = bins_along_e.grid_weights(e, P)
    got = bins_along_e.project(img.reshape(1, -1), start, w)[0]
    # the brute force's points are good to ~5e-3; a diagonal sum spread as a 1 / sqrt 2 px
    # box instead of its triangle is 0.1-0.16 off
    np.testing.assert_allclose(got, _sums_on_unit_bins(img, d[0]), atol=1e-2 * img.max())
    if bins_along_e.grid_code(d)[0] in (0, 2):               # an axis: the plain sums
        sums = img.sum(axis=0) if abs(d[0, 0]) > 0.5 else img.sum(axis=1)
        np.testing.assert_allclose(got, sums if d[0].sum() > 0 else sums[::-1], atol=1e-12)
    overlap = bins_along_e.project(img.reshape(1, -1), *bins_along_e.overlap_weights(e, P))[0]
    assert np.abs(got - overlap).max() > 0.05 * img.max()


@pytest.mark.parametrize("deg", [10.0, 40.0, 100.0, 130.0, 200.0, 318.0])
def test_span_bins_hold_the_whole_block_in_sqrt_2_px_bins_along_diagonals(deg):
    """With span a diagonal's bins are sqrt 2 px wide: the brute-force split of each pixel's
    square on bins of that pitch along d, every sum whole (bin k: diagonal 2k and half of
    each neighbour), so a block lit into its corners keeps all its light, which 1 px bins
    lose; columns and rows are grid's bins."""
    rng = np.random.default_rng(int(deg))
    e = np.array([[np.cos(np.radians(deg)), np.sin(np.radians(deg))]])
    img = rng.random((P, P))
    start, w, u = bins_along_e.grid_weights(e, P, span=True)
    got = bins_along_e.project(img.reshape(1, -1), start, w)[0]
    np.testing.assert_allclose(got, _sums_on_unit_bins(img, u[0]), atol=1e-2 * img.max())
    grid = bins_along_e.project(img.reshape(1, -1), *bins_along_e.grid_weights(e, P)[:2])[0]
    d = bins_along_e.grid_direction(e)
    if bins_along_e.grid_code(d)[0] in (0, 2):
        np.testing.assert_array_equal(u, d)
        np.testing.assert_allclose(got, grid, atol=1e-12)
    else:
        np.testing.assert_allclose(u, d / np.sqrt(2))
        np.testing.assert_allclose(bins_along_e.bins_step(u), d * np.sqrt(2))
        np.testing.assert_allclose(got.sum(), img.sum(), rtol=1e-9)
        assert grid.sum() < 0.95 * img.sum()                   # the corners: ~9 %
        y, x = np.indices((P, P)) - (P - 1) / 2
        m = np.rint(2 * (x * u[0, 0] + y * u[0, 1]) + P - 1).astype(int)   # diagonals, in order along d
        diag = np.bincount(m.ravel(), img.ravel(), 2 * P - 1)
        want = diag[0::2][:P] + 0.5 * (np.r_[0.0, diag[1::2]][:P] + np.r_[diag[1::2], 0.0][:P])
        np.testing.assert_allclose(got, want, atol=1e-9)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("span", [False, True])
def test_compiled_grid_bins_are_the_quantised_split_of_the_sums(span):
    """The frame pass for the grid bins (whole-row sums, then each sum's split) gives the
    quantised split of every pixel of the full cartesian pupil (all four kinds of sums, both
    ways; 1 px bins, or sqrt 2 px ones along diagonals), and the block's moments exactly."""
    sensor = Sensor(detector="cartesian")
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(6)
    frame = rng.integers(0, 4000, size=sensor.frame_shape).astype(np.uint16)
    start, w, d = bins_along_e.grid_weights(lay.e, P, span=span)
    s8, _, wq = bins_along_e.quantised(start, w)
    code, sums, shares = bins_along_e.grid_tables(d, s8, wq)
    assert set(code) == {0, 1, 2, 3}
    bins, mom = kernels.grid_bins(frame, kernels.block_origins(lay), P, code, sums, shares)
    flat = geometry.frame_to_stack(frame, lay).reshape(lay.n_valid, -1).astype(np.float64)
    np.testing.assert_allclose(bins, bins_along_e.project(flat, s8, wq), rtol=1e-5, atol=1e-3)
    y, x = np.indices((P, P))
    np.testing.assert_array_equal(mom, np.stack([flat.sum(1), flat @ x.ravel(), flat @ y.ravel()], 1))


@pytest.mark.parametrize("bins", ["grid", "span"])
def test_a_column_sum_model_reads_the_grid_bins_and_the_shift_along_the_grid_direction(tmp_path, bins):
    """With bins = grid the linear model (the CoG of its bins less the reference's; not
    linearized) gives
    the shift along the grid direction d, s . d, and the calibrated CoG across e reads
    v^T J s, J the calibrated CoG's response (the field's edge makes it differ from v . s
    on the outer blocks); on frames (the compiled pass) as on stacks. With bins = span the
    reading is in the bins' pitch (sqrt 2 px along diagonals): s . u, u = d / pitch."""
    sensor = SIDE                                                   # long spots
    path = linear_marginal_model(tmp_path / "marg.onnx")
    pup = {"pupil_period": 3, "pupil_time_constant_s": 0.0}
    ann = options.build("ann", sensor, {"model": str(path), "out_of_domain": "warn", "bins": bins,
                                        "linearize": False, **pup})
    cog = options.build("cog", sensor, {"bias": "pupil", "linearize": False, **pup})
    lay = geometry.layout(sensor)
    e = np.asarray(lay.e)
    v = np.stack([-e[:, 1], e[:, 0]], axis=1)
    start, w, d = bins_along_e.grid_weights(e, P, span=bins == "span")
    assert (np.abs((d * d).sum(axis=1) - 0.5) < 1e-12).any() == (bins == "span")
    s8, _, wq = bins_along_e.quantised(start, w)
    pos = np.arange(P) - (P - 1) / 2

    def bins_cog(stack):
        b = bins_along_e.project(stack.reshape(lay.n_valid, -1), s8, wq)
        return b @ pos / b.sum(axis=1)

    for k, f in enumerate(frames(sensor, 5)):
        data = f if k % 2 else geometry.frame_to_stack(f, lay)
        ref = ann.pupil.counts()[0]
        a, c = ann.centroid(data), cog.centroid(data)
        if k % 3 == 2:
            ref = ann.pupil.counts()[0]
        stack = geometry.frame_to_stack(f, lay).astype(float)
        np.testing.assert_allclose((a * d).sum(axis=1), bins_cog(stack) - bins_cog(ref), atol=2e-4)
        vj = np.einsum("ni,nij->nj", v, cog.pupil.cog_response().forward(np.zeros((lay.n_valid, 2)))[1])
        assert np.abs(vj - v).max() > 2e-3                    # the field cuts some spots
        np.testing.assert_allclose((a * vj).sum(axis=1), (c * v).sum(axis=1), atol=2e-4)
    assert ann.describe()["options"]["bins"] == ann.describe()["bins_projection"] == bins
    with pytest.raises(ValueError, match="bins"):
        options.build("ann", sensor, {"model": str(path), "out_of_domain": "warn", "bins": "diagonal"})


def test_a_model_trained_on_grid_sums_reads_them_by_itself(tmp_path):
    """A model declaring lgs_wfs.bins_projection grid reads grid bins without the option
    (bins = auto), as bins = grid makes an overlap-trained one do; bins = overlap
    overrides it; a bad declaration is refused."""
    sensor = Sensor(detector="cartesian", photons=1000.0)
    grid = linear_marginal_model(tmp_path / "g.onnx", metadata={"lgs_wfs.bins_projection": "grid"})
    plain = linear_marginal_model(tmp_path / "p.onnx")
    pup = {"pupil_period": 3, "out_of_domain": "warn"}
    f = frames(sensor, 1)[0]
    by_itself = options.build("ann", sensor, {"model": str(grid), **pup})
    told = options.build("ann", sensor, {"model": str(plain), "bins": "grid", **pup})
    overlap = options.build("ann", sensor, {"model": str(grid), "bins": "overlap", **pup})
    assert by_itself._dir is not None and overlap._dir is None
    assert by_itself.describe()["bins_projection"] == "grid"
    assert overlap.describe()["bins_projection"] == "overlap"
    np.testing.assert_allclose(by_itself.centroid(f), told.centroid(f), atol=1e-9)
    assert np.abs(overlap.centroid(f) - by_itself.centroid(f)).max() > 1e-3
    bad = linear_marginal_model(tmp_path / "b.onnx", metadata={"lgs_wfs.bins_projection": "sideways"})
    with pytest.raises(ValueError, match="bins_projection"):
        options.build("ann", sensor, {"model": str(bad), **pup})


def _bincount_projection(flat, start, w):
    """Each pixel's shares added into its bins one by one (bins outside the window
    dropped): the sums a projection must give."""
    n, pp = flat.shape
    p = int(round(pp ** 0.5))
    k = start[..., None].astype(np.int64) + np.arange(w.shape[2])
    rows = np.where((k >= 0) & (k < p), k + p * np.arange(n)[:, None, None], n * p)
    return np.bincount(rows.ravel(), (flat[..., None] * w).ravel(), n * p + 1)[:n * p].reshape(n, p)


def test_the_sparse_projector_gives_project_s_sums():
    """:class:`.bins_along_e.Projector` (the split as a sparse matrix, for a refit's many
    projections; :func:`.bins_along_e.project` builds one) gives each pixel's shares summed
    into its bins, for the overlap and the grid splits of the full cartesian pupil, a block
    with a NaN pixel all NaN."""
    lay = geometry.layout(Sensor(detector="cartesian"))
    rng = np.random.default_rng(9)
    flat = rng.gamma(2.0, 10.0, (lay.n_valid, P * P))
    flat[5, 17] = np.nan
    for start, w in (bins_along_e.overlap_weights(lay.e, P), bins_along_e.grid_weights(lay.e, P)[:2]):
        proj = bins_along_e.Projector(start, w)
        got, want = proj(flat), _bincount_projection(flat, start, w)
        want[5] = np.nan
        assert np.isnan(got[5]).all() and np.isfinite(np.delete(got, 5, axis=0)).all()
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
        assert proj.split[0] is start
