"""The simulator's fast path (compiled Poisson noise, frames written into a given buffer) is
statistically today's; profiles are a function of the frame index alone."""

import numpy as np
import pytest

from lgs_wfs_ros.optics import detector, fast_frames
from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator
from lgs_wfs_ros.sensor import Sensor


def test_profile_at_is_a_function_of_the_index():
    sim = Simulator(Sensor.paper_single("polar"), SimulationConfig(profile="random",
                                                                     random_every=3, seed=2))
    first = [sim.profile_at(i)[0].copy() for i in (0, 4, 7)]
    again = [sim.profile_at(i)[0].copy() for i in (7, 0, 4)]      # another order
    for a, b in zip(first, [again[1], again[2], again[0]]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sim.profile_at(1)[0], first[0])   # same epoch
    assert not np.array_equal(first[0], first[1])
    other = Simulator(sim.sensor, sim.config.replace(seed=3))
    assert not np.array_equal(other.profile_at(0)[0], first[0])


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("lam", [0.02, 0.7, 3.0, 11.9, 12.1, 40.0, 300.0])
def test_fast_poisson_has_the_poisson_distribution(lam):
    """200k draws: mean, variance and the histogram against the Poisson pmf (chi-square)."""
    from scipy import stats
    n = 200_000
    k = detector.poisson(np.full(n, lam), np.random.default_rng(1), fast=True)
    assert k.dtype == np.int64
    assert abs(k.mean() - lam) < 5 * np.sqrt(lam / n)
    assert abs(k.var() / lam - 1) < 5 * np.sqrt(2.0 / n) + 0.01
    lo, hi = int(stats.poisson.ppf(1e-4, lam)), int(stats.poisson.ppf(1 - 1e-4, lam))
    edges = np.arange(lo, hi + 2)
    obs = np.histogram(k, bins=edges - 0.5)[0]
    exp = n * np.diff(stats.poisson.cdf(edges - 1, lam))
    keep = exp > 5
    chi2 = ((obs[keep] - exp[keep]) ** 2 / exp[keep]).sum()
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-4


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_fast_poisson_reproducible_and_floor():
    lam = np.array([[0.0, 1e-12], [5.0, 1e-8]])
    a = detector.poisson(lam, np.random.default_rng(4), detector.POISSON_FLOOR, fast=True)
    b = detector.poisson(lam, np.random.default_rng(4), detector.POISSON_FLOOR, fast=True)
    np.testing.assert_array_equal(a, b)
    assert a.shape == lam.shape and a[0, 0] == a[0, 1] == 0


@pytest.mark.parametrize("detector_kind", ["polar", "cartesian"])
def test_fast_frames_are_statistically_todays(detector_kind):
    """Same sensor, same spots (fixed shift, centred profile): per-pixel means and variances
    of 200 fast frames match 200 frames of today's path within their sampling errors."""
    s = Sensor(detector=detector_kind, diameter_m=8.0, obstruction_m=1.0, n_subaps=6)
    cfg = SimulationConfig(profile="centred", turbulence=False, fixed_shift_px=(0.3, -0.2))
    fast, slow = Simulator(s, cfg.replace(seed=5), fast=True), Simulator(s, cfg.replace(seed=6))
    out = np.empty(s.frame_shape, np.uint16)
    a = np.stack([fast.next(out=out).frame.astype(float) for _ in range(200)])
    b = np.stack([slow.next().frame.astype(float) for _ in range(200)])
    assert fast.next(out=out).frame is out
    expect = Simulator(s.replace(dtype="float32"), cfg.replace(noise=False)).next().frame.astype(float)
    lit = expect > 2
    for x in (a, b):
        z = (x.mean(0) - expect)[lit] / np.sqrt(expect[lit] / 200)
        assert abs(z.mean()) < 0.2 and 0.8 < z.std() < 1.2     # unbiased, Poisson-sized
        assert abs(np.median(x.var(0)[lit] / expect[lit]) - 1) < 0.15
    np.testing.assert_array_equal(a[:, expect == 0], 0)
    assert abs(a.sum() / b.sum() - 1) < 3e-3


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("cfg", [
    SimulationConfig(profile="uncentred", seed=3, noise=False),                  # frozen flow
    SimulationConfig(profile="measured", measured_index=40, noise=False, turbulence=False,
                     fixed_shift_px=(2.6, -1.9)),                                # large shift
])
def test_fast_polar_noise_free_frames_equal_the_exact_ones(cfg):
    """Full pupil, polar: the tabulated line (cubic Hermite reads) gives the exact path's
    expected counts to 2e-6 of a subaperture's light per pixel (measured ~4e-7) and its
    truncation to 1e-6; the blocks outside the pupil are zeroed in a dirty buffer."""
    s = Sensor(detector="polar", dtype="float32")
    exact = Simulator(s, cfg).next()
    fast_sim = Simulator(s, cfg, fast=True)
    assert fast_sim._renderer is not None                          # the fused path is tested
    buf = np.full(s.frame_shape, 7.0, np.float32)
    fast = fast_sim.next(out=buf)
    assert fast.frame is buf
    np.testing.assert_allclose(fast.frame, exact.frame, rtol=0, atol=2e-6 * s.photons)
    np.testing.assert_allclose(fast.truncated, exact.truncated, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(fast.truth, exact.truth)
    assert exact.frame.max() > 100 and np.count_nonzero(buf == 7.0) == 0


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_fast_cartesian_noise_free_frames_equal_the_exact_ones():
    """Full pupil, cartesian: the compiled banded node sum (the same nodes, the same core
    table) gives the exact path's expected counts to 2e-6 of a subaperture's light per
    pixel (measured ~1.6e-7 of the peak pixel), its truncation to 1e-6."""
    s = Sensor(detector="cartesian", dtype="float32")
    cfg = SimulationConfig(profile="uncentred", seed=2, noise=False)
    a = Simulator(s, cfg, fast=True).next(out=np.full(s.frame_shape, 9.0, np.float32))
    b = Simulator(s, cfg).next()
    np.testing.assert_allclose(a.frame, b.frame, rtol=0, atol=2e-6 * s.photons)
    np.testing.assert_allclose(a.truncated, b.truncated, rtol=0, atol=1e-6)
    assert b.frame.max() > 100 and np.count_nonzero(a.frame == 9.0) == 0


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_a_canvas_crop_is_the_block_of_a_spot_moved_by_whole_pixels():
    """FastRenderer.canvas on a 2 px margin: the crop ``[2 - dy:, 2 - dx:]`` of spots
    rendered at (0.3, -0.2) px is the block the frame path renders for the same spots at
    (0.3 + dx, -0.2 + dy), for whole moves up to 2 px either way (to float32, the frame's
    precision); a crop a pixel off is not. Polar models are refused."""
    from lgs_wfs_ros.optics import geometry
    from lgs_wfs_ros.optics.model_spot import ProfileSpots
    s = Sensor(detector="cartesian", dtype="float32", diameter_m=12.0, obstruction_m=1.5,
               n_subaps=24, launch_xy_m=(10.0, 0.0))
    lay = geometry.layout(s)
    alt = np.linspace(80e3, 100e3, 41)
    spots = ProfileSpots(s, lay.r_m, lay.e, alt, np.exp(-0.5 * ((alt - 91e3) / 3e3) ** 2), 4.0)
    r = fast_frames.FastRenderer(lay)
    base = np.tile([0.3, -0.2], (lay.n_valid, 1))
    canvas = r.canvas(spots.model, base, 2)
    assert canvas.shape == (lay.n_valid, s.pixels + 4, s.pixels + 4)
    p, frame = s.pixels, np.empty(s.frame_shape, np.float32)
    for dx, dy in ((0, 0), (1, 0), (-2, 1), (2, -2), (0, -1)):
        r.render(spots.model, base + [dx, dy], frame, 1.0, 0, noise=False, per_field=False)
        block = geometry.frame_to_stack(frame, lay)
        crop = canvas[:, 2 - dy:2 - dy + p, 2 - dx:2 - dx + p].astype(np.float32)
        np.testing.assert_array_equal(crop, block)
        q = 2 - dx + (1 if dx >= 0 else -1)                      # a pixel off
        assert np.abs(canvas[:, 2 - dy:2 - dy + p, q:q + p] - block).max() > 1e-3
    polar = s.replace(detector="polar")
    pl = geometry.layout(polar)
    with pytest.raises(ValueError, match="cartesian"):
        fast_frames.FastRenderer(pl).canvas(ProfileSpots(polar, pl.r_m, pl.e, alt, np.ones(41), 4.0).model,
                                            base, 2)


def test_fast_with_background_takes_the_general_path():
    """Read noise or background: not the fused kernel, expose's general path."""
    s = Sensor(detector="polar", diameter_m=8.0, obstruction_m=1.0, n_subaps=6, background_e=2.0)
    sim = Simulator(s, SimulationConfig(profile="centred", seed=1), fast=True)
    assert sim._renderer is None and sim.next().frame.shape == s.frame_shape


# --- the tabulated sampler (detector.poisson_tables, _draw): exact at every branch ------------

def _chi2_pvalue(k, lam):
    """Chi-square p-value of the draws ``k`` against the Poisson(lam) pmf (bins with an
    expected count > 5; the tails beyond 1e-6 pooled into the end bins)."""
    from scipy import stats
    n = k.size
    lo, hi = int(stats.poisson.ppf(1e-6, lam)), int(stats.poisson.ppf(1 - 1e-6, lam))
    obs = np.bincount(np.clip(k, lo, hi) - lo, minlength=hi - lo + 1).astype(float)
    cdf = stats.poisson.cdf(np.arange(lo, hi + 1), lam)
    pmf = np.diff(np.concatenate([[0.0], cdf]))
    pmf[-1] += stats.poisson.sf(hi, lam)                     # the pooled upper tail
    exp = n * pmf
    keep = exp > 5
    rest = ~keep                                              # pool the thin bins together
    o = np.append(obs[keep], obs[rest].sum())
    e = np.append(exp[keep], exp[rest].sum())
    if e[-1] < 5:
        o, e = o[:-1], e[:-1]
    chi2 = ((o - e) ** 2 / e).sum()
    return stats.chi2.sf(chi2, max(o.size - 1, 1))


D, M = detector.DELTA, detector.LAM_MAX
BOUNDARY_MEANS = [
    0.5 * D, np.nextafter(D, 0), D, np.nextafter(D, 1), D + 0.5 * D,      # DELTA
    1.0, 3.0 - 1e-12, 3.0, 3.0 + 1e-12, 3.0 + 0.06, 3.0 + D - 1e-12,      # grid points
    7.3, np.nextafter(12.0, 0), 12.0, 12.0 + 1e-9, 12.06,                   # old INVERSION_MAX
    40.06, np.nextafter(64.0, 0), 64.0, 64.06,                              # old LAM_MAX
    M - 0.06, np.nextafter(M, 0), M, np.nextafter(M, 2 * M), M + 0.06, 300.0,   # LAM_MAX
]


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("lam", BOUNDARY_MEANS)
def test_table_sampler_is_poisson_at_every_branch_boundary(lam):
    """300k draws at means just below / at / above each switch of the sampler (DELTA, grid
    points, the old inversion limit 12, LAM_MAX) and mid-cell (a dropped residual biases the
    mean by up to DELTA: > 15 sigma there): mean, variance and the histogram (chi-square)."""
    n = 300_000
    k = detector.poisson(np.full(n, lam), np.random.default_rng(11), fast=True)
    assert abs(k.mean() - lam) < 4.5 * np.sqrt(lam / n)
    assert abs(k.var() / lam - 1) < 4.5 * np.sqrt((2.0 + 1.0 / lam) / n)
    assert _chi2_pvalue(k, lam) > 1e-5


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_table_sampler_on_a_shuffled_mixture_is_poisson_and_independent():
    """Eleven means from every branch interleaved at random (as along a frame's rows): each
    mean's draws follow its Poisson law, and successive draws are uncorrelated (a branch that
    failed to carry the generator's state would repeat a uniform)."""
    means = np.array([0.001, 0.02, 0.11, 0.3, 1.06, 5.5, 12.0, 33.3, 90.0,
                      detector.LAM_MAX - 0.01, 200.0])
    rng = np.random.default_rng(3)
    idx = rng.integers(0, means.size, 1_200_000)
    lam = means[idx]
    k = detector.poisson(lam, rng, detector.POISSON_FLOOR, fast=True)
    for j, m in enumerate(means):
        kj = k[idx == j]
        assert abs(kj.mean() - m) < 4.5 * np.sqrt(m / kj.size)
        assert _chi2_pvalue(kj, m) > 1e-5
    z = (k - lam) / np.sqrt(lam)
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 4.5 / np.sqrt(z.size)


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_poisson_tables_are_the_exact_cdf():
    """Each row's thresholds are ceil(2^53 F_c(k)) for the Poisson CDF F_c (scipy, to its
    ~1e-15) ending at 2^53; the guide is the first k above each bucket's lowest uniform; the
    32-bit copy is the top bits."""
    from scipy import stats
    thr, hi, lo, guide, start = detector.poisson_tables()
    nb = 1 << detector.GUIDE_BITS
    ends = np.append(start[1:], thr.size)
    assert start[0] == 0 and np.all(np.diff(start) > 0)
    for g in [g for g in (0, 1, 2, 7, 8, 24, 95, 96, 97, 300, 511, 512, 1023) if g < start.size]:
        row = thr[start[g]:ends[g]].astype(np.float64)
        c = g * detector.DELTA
        f = stats.poisson.cdf(np.arange(row.size), c)
        assert row[-1] == 2.0**53 and np.all(np.diff(row) >= 0)
        assert 1 - f[-1] <= 2.0**-53 and (row.size == 1 or 1 - f[-2] > 2.0**-53 / 2)
        np.testing.assert_allclose(row[:-1] / 2.0**53, f[:-1], rtol=0, atol=2e-15)
        r = thr[start[g]:ends[g]]
        bucket = np.arange(nb, dtype=np.uint64) << np.uint64(53 - detector.GUIDE_BITS)
        gd = guide[g * nb:(g + 1) * nb].astype(np.int64)
        assert np.all(r[gd] > bucket)
        assert np.all((gd == 0) | (r[np.maximum(gd - 1, 0)] <= bucket))
    np.testing.assert_array_equal(hi, np.minimum(thr >> np.uint64(21), 2**32 - 1))
    top = thr == 2**53                                        # lo 2^21: never reached
    np.testing.assert_array_equal(lo[~top], thr[~top] & np.uint64(2**21 - 1))
    assert np.all(lo[top] == 2**21)


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
def test_fused_polar_draws_are_the_samplers_in_batches():
    """Full pupil (many draw batches): the fused kernel's noisy float64 frame is exactly,
    chunk by chunk, the sampler run once over the chunk's lit rows' expected counts in
    block order from the chunk's own seed (the batches carry the generator's state: none
    restarts or skips a draw), and it is reproducible."""
    s = Sensor(detector="polar", dtype="float32")
    sim = Simulator(s, SimulationConfig(profile="uncentred", seed=4), fast=True)
    r, p, seed = sim._renderer, s.pixels, 12345
    r._check = lambda out: None                    # float64 frames: the exact expected counts
    truth = sim.truth_at(0)
    model = sim.spot_model(*sim.profile_at(0), truth)
    expect = np.full(s.frame_shape, 7.0)
    r.render(model, truth, expect, s.photons, 0, noise=False)
    a = np.full(s.frame_shape, 3.0)
    b = np.full(s.frame_shape, 5.0)
    r.render(model, truth, a, s.photons, seed)
    r.render(model, truth, b, s.photons, seed)
    np.testing.assert_array_equal(a, b)
    ref = np.zeros(s.frame_shape)
    seeds = fast_frames.chunk_seeds(seed, r.CHUNKS)
    assert len(set(seeds)) == r.CHUNKS and len(r._ranges) == r.CHUNKS
    for (b0, b1), chunk_seed in zip(r._ranges, seeds):
        rows = []
        for br, bc in zip(r.rows[b0:b1], r.cols[b0:b1]):
            blk = expect[br * p:(br + 1) * p, bc * p:(bc + 1) * p]
            rows += [(br * p + j, bc * p) for j in range(p)
                     if blk[j].max() > detector.POISSON_FLOOR]
        lam = np.concatenate([expect[i, j:j + p] for i, j in rows])
        assert lam.size > 2 * 8192                            # several batches a chunk
        out = np.empty(lam.size, np.int64)
        detector._poisson_fast(lam, detector.POISSON_FLOOR, chunk_seed, out)
        for n, (i, j) in enumerate(rows):
            ref[i, j:j + p] = out[n * p:(n + 1) * p]
    np.testing.assert_array_equal(a, ref)


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("detector_kind", ["polar", "cartesian"])
def test_render_threads_give_the_same_frames(detector_kind):
    """A frame rendered by 2 or 4 threads (its chunks in parallel) is the one rendered by
    one thread: the draws follow the chunks, not the threads; the evolving profile's
    blended knots included."""
    s = Sensor(detector=detector_kind)
    cfg = SimulationConfig(profile="evolving", seed=6)
    n = 3 if detector_kind == "polar" else 2
    frames = {}
    for threads in (1, 2, 4):
        sim = Simulator(s, cfg, fast=True, threads=threads)
        try:
            sim.index = 150                              # between two knots: a blend
            frames[threads] = [sim.next().frame.copy() for _ in range(n)]
        finally:
            sim.close()
    for threads in (2, 4):
        for f1, ft in zip(frames[1], frames[threads]):
            np.testing.assert_array_equal(ft, f1)
    assert frames[1][0].sum() > 0 and not np.array_equal(frames[1][0], frames[1][1])


def test_render_threads_are_checked():
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        Simulator(Sensor(detector="polar"), SimulationConfig(profile="uncentred"), fast=True,
                  threads=0)


def test_chunk_seeds_are_distinct_and_a_function_of_the_seed():
    a = fast_frames.chunk_seeds(7, 4)
    assert a == fast_frames.chunk_seeds(7, 4) and len(set(a)) == 4
    assert all(0 <= v < 2**63 for v in a)
    assert set(a).isdisjoint(fast_frames.chunk_seeds(8, 4))


@pytest.mark.skipif(not detector.FAST_AVAILABLE, reason="numba not installed ('fast' extra)")
@pytest.mark.parametrize("detector_kind", ["polar", "cartesian"])
def test_fast_frames_same_seed_same_frames(detector_kind):
    s = Sensor(detector=detector_kind, diameter_m=8.0, obstruction_m=1.0, n_subaps=10)
    cfg = SimulationConfig(profile="uncentred", seed=8)
    out = np.empty(s.frame_shape, np.uint16)
    a = [Simulator(s, cfg, fast=True).next(out=out).frame.copy() for _ in range(2)]
    c = Simulator(s, cfg.replace(seed=9), fast=True).next(out=out).frame
    np.testing.assert_array_equal(a[0], a[1])
    assert a[0].sum() > 1000 and not np.array_equal(a[0], c)
