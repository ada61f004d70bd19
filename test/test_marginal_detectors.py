"""Training spots in bins along e on both detectors (learning/refdata.py, margtrain.py), and
the domain of a marginals network trained on both."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import bins_along_e, options
from lgs_wfs_ros.learning import domains, margtrain, recipes, refdata
from lgs_wfs_ros.sensor import Sensor


def bins_cog(a):
    """Each row's centre of light along its bins, px (NaN for a row without light)."""
    k = np.arange(a.shape[1])
    tot = a.sum(axis=1)
    return (a * k).sum(axis=1) / np.where(tot > 0, tot, np.nan)


def rendered_draws(seed, n):
    """``(e, t, ref, photons, counts)``: the cartesian draws ``marginal_pairs`` makes from
    ``default_rng(seed)``, rendered, before any projection."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(*refdata.MARGINAL_SPEC.radius_m, size=n)
    ang = rng.uniform(0.0, 2 * np.pi, size=n)
    e = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    t, ref, ph, counts = refdata._spots(rng, refdata.MARGINAL_SPEC, Sensor(), r, e)
    return e, t, ref, ph, counts


def test_cartesian_spots_are_read_along_their_e():
    """On cartesian pixels the bins follow each spot's own e: the bins' CoG less the
    reference's follows the shift along e (with the sign of e), and the bins are the
    overlap projection of a spot that keeps nearly all its light in the block."""
    pairs = refdata.marginal_pairs(np.random.default_rng(3), 300, detector="cartesian")
    assert pairs.marg.shape == pairs.refs.shape == (300, 16) and pairs.y.shape == (300, 1)
    np.testing.assert_allclose(pairs.refs.sum(axis=1), 1.0, atol=1e-5)
    bright = (pairs.photons > 600) & (pairs.marg.sum(axis=1) > 0.5 * pairs.photons)
    moved = (bins_cog(pairs.marg) - bins_cog(pairs.refs))[bright]
    r = np.corrcoef(moved, pairs.y[bright, 0])[0, 1]
    assert r > 0.8, r                 # e swapped to (e_y, e_x) or y = -t.e fail this


def test_cartesian_pairs_project_the_rendered_spot():
    """Same draws, rendered: the cartesian pairs are bins_along_e's projection of the very
    images refdata renders (centred windows by default; with window "reference", spot and
    reference through the window the stale reference places, as the centroider places it),
    and the shift is t . e."""
    centred = refdata.marginal_pairs(np.random.default_rng(7), 20, detector="cartesian")
    pairs = refdata.marginal_pairs(np.random.default_rng(7), 20, detector="cartesian", window="reference")
    e, t, ref, ph, counts = rendered_draws(7, 20)
    start, w = bins_along_e.overlap_weights(e, 16)
    np.testing.assert_allclose(centred.marg, bins_along_e.project(counts.reshape(20, -1), start, w), rtol=1e-5)
    start = bins_along_e.moved(start, bins_along_e.window_offsets(ref.reshape(20, -1), e))
    np.testing.assert_allclose(pairs.marg, bins_along_e.project(counts.reshape(20, -1), start, w), rtol=1e-5)
    refm = bins_along_e.project(ref.reshape(20, -1), start, w)
    np.testing.assert_allclose(pairs.refs, refm / refm.sum(axis=1, keepdims=True), rtol=1e-5, atol=1e-7)
    assert np.any(pairs.marg != centred.marg)
    with pytest.raises(ValueError, match="window"):
        refdata.marginal_pairs(np.random.default_rng(7), 2, detector="cartesian", window="left")
    np.testing.assert_allclose(pairs.y[:, 0], (t * e).sum(axis=1), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(pairs.photons, ph)


def test_polar_pairs_are_the_column_sums_as_before():
    pairs = refdata.marginal_pairs(np.random.default_rng(5), 10)
    rng = np.random.default_rng(5)
    r = rng.uniform(*refdata.MARGINAL_SPEC.radius_m, size=10)
    t, ref, ph, counts = refdata._spots(rng, refdata.MARGINAL_SPEC, Sensor(), r, np.tile([1.0, 0.0], (10, 1)))
    np.testing.assert_array_equal(pairs.marg, counts.sum(axis=1).astype(np.float32))
    np.testing.assert_array_equal(pairs.y[:, 0], t[:, 0].astype(np.float32))
    with pytest.raises(ValueError, match="polar or cartesian"):
        refdata.marginal_pairs(np.random.default_rng(5), 2, detector="hexagonal")


def test_reference_blur_widens_the_reference_alone_by_its_drawn_rms():
    """``PriorSpec.reference_blur_px``: the same spots, shifts and photons; each reference
    blurred along e by a normal of the rms drawn from the stream spawned off the batch's
    seed: the column sums of an untruncated reference gain that rms squared in variance."""
    import dataclasses
    n, top = 64, 0.3
    spec = dataclasses.replace(refdata.MARGINAL_SPEC, reference_blur_px=top)
    plain = refdata.marginal_pairs(np.random.default_rng(5), n)
    blurred = refdata.marginal_pairs(np.random.default_rng(5), n, spec=spec)
    for f in ("marg", "y", "photons", "r_m"):
        np.testing.assert_array_equal(getattr(blurred, f), getattr(plain, f))
    seq = np.random.default_rng(5).bit_generator.seed_seq.spawn(1)[0]
    rms = np.random.default_rng(seq).uniform(0.0, top, size=n)

    def variance(a):
        k = np.arange(a.shape[1])
        m = (a * k).sum(axis=1) / a.sum(axis=1)
        return (a * (k - m[:, None]) ** 2).sum(axis=1) / a.sum(axis=1)
    inside = plain.r_m < 4.0                       # short spots: the field cuts nothing
    assert inside.sum() >= 4
    added = variance(blurred.refs.astype(float)) - variance(plain.refs.astype(float))
    np.testing.assert_allclose(added[inside], rms[inside] ** 2, atol=4e-3)
    assert rms[inside].max() > 0.15                 # the test sees real blurs


def test_split_and_streams():
    """Detectors share the spots as often as they are listed; polar batches are the draws
    of a polar-only run, cartesian ones their own stream."""
    assert refdata.split(1_400_000, ("polar",) * 4 + ("cartesian",) * 3) == {"polar": 800_000,
                                                                             "cartesian": 600_000}
    assert refdata.split(7, ("cartesian", "polar")) == {"polar": 4, "cartesian": 3}
    with pytest.raises(ValueError, match="detectors"):
        refdata.split(5, ("hex",))
    both = margtrain.generate(10, 21, batch=3, progress=False, detectors=("polar", "cartesian"))
    polar = margtrain.generate(5, 21, batch=3, progress=False)
    np.testing.assert_array_equal(both.marg[:5], polar.marg)
    cart = refdata.marginal_pairs(np.random.default_rng([21, 1, 1]), 2, detector="cartesian")
    np.testing.assert_array_equal(both.marg[8:], cart.marg)


def test_domain_of_a_network_trained_on_both_detectors():
    """ann_conv's recipe trains on both: its domain lists both, and the centroider runs a
    marginals model declaring them on a cartesian sensor without an override; a polar-only
    marginals model there still refuses."""
    rec = recipes.get("ann_conv")
    assert set(rec.detectors) == {"polar", "cartesian"}
    assert domains.recipe_domain(rec)["detector"] == ["cartesian", "polar"]
    assert domains.recipe_domain(recipes.get("ann_marg"))["detector"] == ["polar"]
    assert "600000 cartesian" in rec.line()


def test_marginals_model_must_declare_polar_or_any():
    from lgs_wfs_ros.centroiding.ann_model import read_metadata
    base = {"lgs_wfs.pixels": "16", "lgs_wfs.input": '"marginals"', "lgs_wfs.conditioning": '"reference"',
            "lgs_wfs.input_norm": '"none"'}
    for det in ("polar", "any"):
        assert read_metadata({**base, "lgs_wfs.detector": f'"{det}"'})["detector"] == det
    with pytest.raises(ValueError, match="polar"):
        read_metadata({**base, "lgs_wfs.detector": '"cartesian"'})


def test_trained_on_both_runs_on_a_cartesian_sensor(tmp_path):
    """A quick ann_conv training (both detectors): the model declares detector any and both
    detectors in its domain, runs on a cartesian pupil with no subaperture outside its
    domain, and its recorded check error is what it does on the mixed check spots."""
    pytest.importorskip("torch")
    from lgs_wfs_ros import cli
    from lgs_wfs_ros.learning import export
    assert cli.main(["train", "ann_conv", "--out", str(tmp_path), "--samples", "700", "--quick"]) == 0
    path = tmp_path / "ann_conv.onnx"
    meta = export.read_metadata(path)
    assert meta["lgs_wfs.detector"] == "any"
    assert meta["lgs_wfs.domain"]["detector"] == ["cartesian", "polar"]
    dets = tuple(meta["lgs_wfs.training"]["recipe"]["detectors"])
    check = meta["lgs_wfs.training"]["check"]
    assert margtrain.check_error(path, check["n"], check["seed"], dets) == pytest.approx(
        check["mean_err_px"], rel=1e-3)
    sensor = Sensor(photons=1000.0)
    c = options.build("ann", sensor, {"model": str(path)})
    assert c.describe()["domain"]["out_of_domain_subapertures"] == 0
    counts = np.random.default_rng(2).poisson(5.0, sensor.frame_shape).astype(np.uint16)
    assert np.isfinite(c.centroid(counts)).all()


def test_grid_pairs_are_the_grid_sums_and_the_shift_along_their_direction():
    """With projection "grid" the same draws are read through whole-pixel sums along the
    pixel-grid direction d nearest to each e (the quantised split the frame pass uses) and
    the target is t . d, not t . e; polar pairs do not change; reference windows and an
    unknown projection are refused."""
    grid = refdata.marginal_pairs(np.random.default_rng(7), 20, detector="cartesian", projection="grid")
    e, t, ref, ph, counts = rendered_draws(7, 20)
    start, w, d = bins_along_e.grid_weights(e, 16)
    s8, _, wq = bins_along_e.quantised(start, w)
    np.testing.assert_allclose(grid.marg, bins_along_e.project(counts.reshape(20, -1), s8, wq), rtol=1e-5)
    np.testing.assert_allclose(grid.y[:, 0], (t * d).sum(axis=1), rtol=1e-5, atol=1e-6)
    assert np.abs((t * d).sum(axis=1) - (t * e).sum(axis=1)).max() > 0.01
    polar = refdata.marginal_pairs(np.random.default_rng(8), 5, detector="polar", projection="grid")
    same = refdata.marginal_pairs(np.random.default_rng(8), 5, detector="polar")
    np.testing.assert_array_equal(polar.marg, same.marg)
    with pytest.raises(ValueError, match="centred"):
        refdata.marginal_pairs(np.random.default_rng(7), 2, detector="cartesian", window="reference",
                               projection="grid")
    with pytest.raises(ValueError, match="projection"):
        refdata.marginal_pairs(np.random.default_rng(7), 2, detector="cartesian", projection="pixel")
    rec = recipes.RECIPES["ann_grid"]
    assert rec.bins_projection == "grid" and recipes.RECIPES["ann_conv"].bins_projection == "overlap"
