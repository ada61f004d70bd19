"""Offline analysis: joins by stamp, metrics on bags with known answers, CRB, inspect, report,
replay, and refusal of bad bags through the CLI (one line, exit code 2, no traceback)."""

import json
import math
import re

import numpy as np
import pytest

from lgs_wfs_ros import cli
from lgs_wfs_ros.analysis import bagload, bagwrite, report
from lgs_wfs_ros.analysis.inspect import bag_info, inspect_bag
from lgs_wfs_ros.analysis.replay import replay_bag
from lgs_wfs_ros.bags import BagError, BagReader, BagWriter, encode_string
from lgs_wfs_ros.centroiding.crb import crb_of
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor

from spotgen import spots

T0 = 1_700_000_000_000_000_000
DT = 1_428_571                      # ~700 Hz
SIGMA = 1.19 / 2.3548


def single():
    return Sensor.paper_single("polar", dtype="float32")


def small_pupil():
    return Sensor(n_subaps=8, diameter_m=4.0, obstruction_m=0.5, detector="cartesian", dtype="float32")


def write_bag(path, sensor, truths, slopes, *, frames=None, truth_stamps=None, changes=None):
    """truths (F, n, 2); slopes {ns: (stamps, (K, n, 2))}; frames (F, H, W) or None."""
    stamps = T0 + DT * np.arange(len(truths)) if truth_stamps is None else truth_stamps
    with bagwrite.ContractBagWriter(path, sensor, sensor_extra={"profile": "test"}, log_ns=T0) as w:
        for ns, desc in (changes or {}).items():
            for log, d in desc:
                w.centroider(ns, d, log)
        for k, s in enumerate(stamps):
            if frames is not None:
                w.frame(int(s), frames[k])
            w.truth(int(s), truths[k])
        for ns, (st, sl) in slopes.items():
            for s, v in zip(st, sl):
                w.slopes(ns, int(s), v, int(s) + 1000)
    return path


# -- join and metrics with known answers -------------------------------------------------------
def test_known_errors_two_algorithms(tmp_path):
    rng = np.random.default_rng(1)
    truths = rng.normal(0, 0.5, size=(50, 1, 2))
    stamps = T0 + DT * np.arange(50)
    a = truths + np.array([0.3, -0.4])                    # constant error: |err| = 0.5
    sign = np.where(np.arange(50) % 2, 1.0, -1.0)[:, None, None]
    b = truths + sign * np.array([0.1, 0.0])              # +-0.1 px in x: mean 0.1, bias 0
    path = write_bag(tmp_path / "k.mcap", single(), truths, {"cog": (stamps, a), "cmf": (stamps, b)},
                     changes={"cog": [(T0, {"algorithm": "cog"})], "cmf": [(T0, {"algorithm": "cmf"})]})
    res = report.analyse(bagload.load_bag(path), crb=False)
    cog, cmf = res["algorithms"]["cog"], res["algorithms"]["cmf"]
    assert cog["mean_euclid"] == pytest.approx(0.5, abs=1e-6)
    assert cog["mae"] == pytest.approx(0.35, abs=1e-6)
    assert cog["bias_x"] == pytest.approx(0.3, abs=1e-6) and cog["bias_y"] == pytest.approx(-0.4, abs=1e-6)
    assert cog["mean_euclid_mas"] == pytest.approx(250.0, abs=1e-3)
    assert cmf["mean_euclid"] == pytest.approx(0.1, abs=1e-6)
    assert cmf["bias_x"] == pytest.approx(0.0, abs=1e-6)
    assert cmf["ratio_to_cog"] == pytest.approx(0.2, abs=1e-5)
    assert cog["n"] == 50 and cog["join"]["joined"] == 50


def test_join_missing_and_duplicate_stamps(tmp_path):
    truths = np.zeros((10, 1, 2))
    stamps = T0 + DT * np.arange(10)
    # slopes: stamp 3 missing, stamp 5 repeated (first copy error 0.2, second 9.0), one stray
    st = np.array([stamps[0], stamps[1], stamps[2], stamps[4], stamps[5], stamps[5], stamps[6],
                   stamps[7], stamps[8], stamps[9], T0 + 10**12])
    sl = np.full((len(st), 1, 2), [0.2, 0.0])
    sl[5] = [9.0, 0.0]
    path = write_bag(tmp_path / "j.mcap", single(), truths, {"cog": (st, sl)})
    s = report.analyse(bagload.load_bag(path), crb=False)["algorithms"]["cog"]
    assert s["join"] == {"slopes": 11, "joined": 9, "truth_without_slopes": 1, "slopes_without_truth": 1,
                         "duplicate_slope_stamps": 1, "duplicate_truth_stamps": 0}
    assert s["n"] == 9
    assert s["mean_euclid"] == pytest.approx(0.2, abs=1e-6)      # the first copy of stamp 5 counts


def test_skip_leaves_out_the_first_exposures_by_stamp(tmp_path, capsys):
    """A warm-up of 10 exposures with error 1 px, then 30 with 0.1 px: skipping 10 scores
    the 30 alone, joined by stamp (cmf's slopes arrive out of order and lack exposure 12)."""
    n, warm = 40, 10
    truths = np.zeros((n, 1, 2))
    st = T0 + DT * np.arange(n)
    err = np.where(np.arange(n) < warm, 1.0, 0.1)[:, None, None] * np.array([1.0, 0.0])
    order = np.r_[np.arange(n)[::-1][:-1], 0]                     # shuffled file order
    order = order[order != 12]
    path = write_bag(tmp_path / "w.mcap", single(), truths,
                     {"cog": (st, truths + err), "cmf": (st[order], (truths + err)[order])})
    full = report.analyse(bagload.load_bag(path), crb=False)["algorithms"]
    assert full["cog"]["mean_euclid"] == pytest.approx((warm * 1.0 + 30 * 0.1) / n, abs=1e-6)
    data = bagload.load_bag(path)
    cut = bagload.skip_frames(data, warm)
    assert len(data.truth) == n                                     # not changed in place
    res = report.analyse(cut, crb=False)["algorithms"]
    assert res["cog"]["n"] == 30 and res["cmf"]["n"] == 29
    assert res["cog"]["mean_euclid"] == pytest.approx(0.1, abs=1e-6)
    assert res["cmf"]["mean_euclid"] == pytest.approx(0.1, abs=1e-6)
    assert cli.main(["report", str(path), "--skip", str(warm)]) == 0
    assert f"{n - warm} truths, scored after the first {warm} exposures" in capsys.readouterr().out
    with pytest.raises(ValueError, match="40 truths"):
        bagload.skip_frames(data, n)


def test_nan_slopes_are_counted_not_averaged(tmp_path):
    truths = np.zeros((4, 1, 2))
    st = T0 + DT * np.arange(4)
    sl = np.array([[[0.1, 0]], [[np.nan, np.nan]], [[0.3, 0]], [[0.2, 0]]])
    path = write_bag(tmp_path / "n.mcap", single(), truths, {"cog": (st, sl)})
    s = report.analyse(bagload.load_bag(path), crb=False)["algorithms"]["cog"]
    assert s["n"] == 3 and s["n_nan"] == 1
    assert s["mean_euclid"] == pytest.approx(0.2, abs=1e-6)


def test_ratios_are_taken_on_the_same_frames(tmp_path):
    """cog measures every frame, cmf only the second half, where every error is 4x larger:
    over the frames both measured cmf equals cog (ratio 1), over all frames it would not."""
    n = 40
    truths = np.zeros((n, 1, 2))
    st = T0 + DT * np.arange(n)
    scale = np.where(np.arange(n) < n // 2, 0.05, 0.2)[:, None, None]
    est = truths + scale * np.array([1.0, 0.0])
    path = write_bag(tmp_path / "r.mcap", single(), truths, {"cog": (st, est), "cmf": (st[n // 2:], est[n // 2:])},
                     changes={"cog": [(T0, {"algorithm": "cog"})], "cmf": [(T0, {"algorithm": "cmf"})]})
    data = bagload.load_bag(path)
    res = report.analyse(data, crb=False)
    cmf = res["algorithms"]["cmf"]
    assert cmf["mean_euclid"] / res["algorithms"]["cog"]["mean_euclid"] == pytest.approx(1.6)
    assert cmf["ratio_to_cog"] == pytest.approx(1.0) and cmf["mae_ratio_to_cog"] == pytest.approx(1.0)
    assert cmf["ratio_to_cog_basis"] == f"{n // 2} frames measured by both"
    # CRB known at frames 0, 10, 20, 30 (expected |err| 0.1 px each): cmf has 20 and 30 only
    cst = st[::10]
    model = (lambda k, s: None, truths[::10], "fake", cst)
    fake = np.broadcast_to(np.eye(2) * 0.01, (4, 2, 2)).copy()      # sigma 0.1 px per axis
    orig = report.bound_covariances
    report.bound_covariances = lambda sensor, image_at, t: {"crb": fake, "cog": 1.44 * fake}
    try:
        res = report.analyse(data, image_model=model)
    finally:
        report.bound_covariances = orig
    d = float(report.mean_abs_norm(fake[0]))
    assert res["algorithms"]["cmf"]["ratio_to_crb"] == pytest.approx(0.2 / d)
    assert res["algorithms"]["cog"]["ratio_to_crb"] == pytest.approx((0.05 * 2 + 0.2 * 2) / 4 / d)
    assert res["algorithms"]["cmf"]["ratio_to_crb_basis"] == "2 frames"
    assert "x CRB on 2 frames" in report.format_report(res)
    # the CoG floor beside it: 1.2x the bound's expected |err| here
    assert res["crb"]["cog_floor"]["mean_euclid"] == pytest.approx(1.2 * d)
    assert re.search(r"CoG floor\s+" + f"{1.2 * d:.4f}", report.format_report(res))


def test_binned_time_series_decimates_without_bias():
    """2,100 frames become at most TIME_BINS bins whose medians and bands follow the data."""
    t = np.linspace(0, 3, 2100)
    y = np.where(t < 1.5, 1.0, 3.0) + np.random.default_rng(0).normal(0, 0.1, t.size)
    y[5] = np.nan
    c, med, lo, hi = report.binned(t, y)
    assert len(c) <= report.TIME_BINS and len(c) >= report.TIME_BINS - 1
    tol = 5 * 1.2533 * 0.1 / math.sqrt(2100 / report.TIME_BINS)    # 5 sigma of a bin's median
    np.testing.assert_allclose(med[c < 1.4], 1.0, atol=tol)
    np.testing.assert_allclose(med[c > 1.6], 3.0, atol=tol)
    assert np.all(lo <= med) and np.all(med <= hi)
    np.testing.assert_allclose(np.median(hi[c > 1.6] - lo[c > 1.6]), 0.2, rtol=0.2)   # +-1 sigma
    c, med, lo, hi = report.binned(t[:50], y[:50])
    assert len(c) == 49 and np.array_equal(med, lo)                  # few points: drawn as they are


def test_crb_frame_count_scales_with_subapertures():
    assert report.crb_frame_count(2100, 1) == 256
    assert report.crb_frame_count(30, 2784) == 16
    assert report.crb_frame_count(10, 1) == 10
    assert report.crb_frame_count(2100, 100) == 256 and report.crb_frame_count(2100, 1000) == 45


def test_a_centroider_without_slopes_is_named_not_a_crash(tmp_path):
    """A centroider whose slopes topic was recorded empty (it started too late for a short
    run) is listed as such beside the others; with nothing else the report refuses with
    that reason (it raised an IndexError)."""
    from lgs_wfs_ros.analysis.bagload import IMAGE

    def bag(name, with_cog):
        with bagwrite.ContractBagWriter(tmp_path / name, single(), log_ns=T0) as w:
            w.centroider("cmf", {"algorithm": "cmf"}, T0)
            w.topic("/cmf/slopes", IMAGE)                  # subscribed, nothing came
            for k in range(10):
                stamp = T0 + DT * k
                w.truth(stamp, np.zeros((1, 2)))
                if with_cog:
                    w.slopes("cog", stamp, np.full((1, 2), 0.1), stamp + 1000)
        return tmp_path / name

    res = report.analyse(bagload.load_bag(bag("w.mcap", True)), crb=False)
    assert list(res["algorithms"]) == ["cog"] and res["without_slopes"] == ["cmf"]
    assert "no slopes recorded: cmf" in report.format_report(res)
    with pytest.raises(ValueError, match="no slopes recorded"):
        report.analyse(bagload.load_bag(bag("n.mcap", False)), crb=False)


def test_centroider_switch_splits_segments(tmp_path):
    truths = np.zeros((20, 1, 2))
    st = T0 + DT * np.arange(20)
    sl = np.where(np.arange(20)[:, None, None] < 8, 0.5, 0.1) * np.array([1.0, 0.0])
    changes = {"wfs": [(T0, {"algorithm": "cog"}), (T0 + 1, {"algorithm": "cog"}),   # republished
                       (int(st[8]), {"algorithm": "cmf", "options": {"history": 5}})]}
    path = write_bag(tmp_path / "s.mcap", single(), truths, {"wfs": (st, sl)}, changes=changes)
    res = report.analyse(bagload.load_bag(path), crb=False)
    assert list(res["algorithms"]) == ["wfs:cog", "wfs:cmf"]
    assert res["algorithms"]["wfs:cog"]["n"] == 8
    assert res["algorithms"]["wfs:cog"]["mean_euclid"] == pytest.approx(0.5, abs=1e-6)
    assert res["algorithms"]["wfs:cmf"]["n"] == 12
    assert res["algorithms"]["wfs:cmf"]["mean_euclid"] == pytest.approx(0.1, abs=1e-6)
    assert res["algorithms"]["wfs:cmf"]["ratio_to_cog"] == pytest.approx(0.2, abs=1e-5)
    assert res["algorithms"]["wfs:cmf"]["ratio_to_cog_basis"] == "each on its own frames (none in common)"


def test_full_pupil_by_radius(tmp_path):
    sensor = small_pupil()
    lay = geometry.layout(sensor)
    truths = np.zeros((3, lay.n_valid, 2))
    err = np.stack([lay.r_m / 10, np.zeros(lay.n_valid)], axis=1)       # error grows with r
    st = T0 + DT * np.arange(3)
    path = write_bag(tmp_path / "p.mcap", sensor, truths, {"cog": (st, truths + err)})
    res = report.analyse(bagload.load_bag(path), crb=False)
    rings = res["algorithms"]["cog"]["by_radius"]
    assert len(rings) >= 2
    for ring in rings:
        sel = (lay.r_m >= ring["r_min_m"]) & (lay.r_m < ring["r_max_m"])
        if sel.any():
            assert ring["mean_euclid"] == pytest.approx((lay.r_m[sel] / 10).mean(), rel=1e-5)
    assert res["algorithms"]["cog"]["n"] == 3 * lay.n_valid


def test_report_removes_pupil_wide_tip_tilt_and_focus(tmp_path, capsys):
    """cmf = cog's error plus a tip and a focus (slope proportional to position, as a sodium
    altitude change gives): raw it is far worse, with the three modes removed the two are
    the same. Removing tip and tilt only, or fitting one axis, leaves cmf worse."""
    sensor = small_pupil()
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(2)
    n, k = lay.n_valid, 4
    truths = np.zeros((k, n, 2))
    noise = rng.normal(0, 0.05, (k, n, 2))
    modes = 0.3 + 0.2 * np.asarray(lay.centre_xy_m)[None] * np.array([1.0, -0.5, 2.0, 0.7])[:, None, None]
    st = T0 + DT * np.arange(k)
    path = write_bag(tmp_path / "ttf.mcap", sensor, truths,
                     {"cog": (st, truths + noise), "cmf": (st, truths + noise + modes)})
    res = report.analyse(bagload.load_bag(path), crb=False)
    cog, cmf = res["algorithms"]["cog"], res["algorithms"]["cmf"]
    assert cmf["ratio_to_cog"] > 3
    assert cmf["ttf"]["ratio_to_cog"] == pytest.approx(1.0, abs=1e-6)
    assert cog["ttf"]["mean_euclid"] < cog["mean_euclid"]          # its own modes go too
    assert cog["ttf"]["mean_euclid"] > 0.8 * cog["mean_euclid"]    # not much else
    text = report.format_report(res)
    assert "tip, tilt and focus removed" in text
    # by radius too: raw, cmf's focus grows outward; removed, cmf's rings are cog's
    raw, clean = cmf["by_radius"], cmf["ttf"]["by_radius"]
    assert len(clean) == len(raw) >= 2 and raw[-1]["mean_euclid"] > raw[0]["mean_euclid"] + 0.1
    assert all(a["mean_euclid"] < 0.3 * b["mean_euclid"] for a, b in zip(clean, raw))
    for a, b in zip(clean, cog["ttf"]["by_radius"]):
        assert a["n"] == b["n"] and a["mean_euclid"] == pytest.approx(b["mean_euclid"], abs=1e-6)
    assert "the same with the pupil-wide tip, tilt and focus removed" in text


# -- CRB ------------------------------------------------------------------------------------------
def test_mean_abs_norm_known_cases():
    s = 0.3
    cov = np.array([[[s * s, 0], [0, s * s]], [[s * s, 0], [0, 0]], [[0.04, 0.0], [0.0, 0.01]]])
    got = report.mean_abs_norm(cov)
    assert got[0] == pytest.approx(s * math.sqrt(math.pi / 2), rel=1e-9)
    assert got[1] == pytest.approx(s * math.sqrt(2 / math.pi), rel=1e-9)
    rng = np.random.default_rng(0)
    v = rng.normal(0, [0.2, 0.1], size=(400000, 2))
    assert got[2] == pytest.approx(np.hypot(v[:, 0], v[:, 1]).mean(), rel=0.005)


def test_report_crb_matches_model_crb(tmp_path):
    sensor = single()
    rng = np.random.default_rng(3)
    f, photons = 200, 1000.0
    truths = rng.normal(0, 0.3, size=(f, 1, 2))
    imgs = spots(truths[:, 0], photons=photons, sigma=SIGMA, rng=rng).astype(np.float32)
    est = truths + rng.normal(0, 0.05, size=truths.shape)
    path = write_bag(tmp_path / "c.mcap", sensor, truths, {"cog": (T0 + DT * np.arange(f), est)},
                     frames=imgs)
    model = lambda s: spots(s, photons=photons, sigma=SIGMA)               # noqa: E731
    data = bagload.load_bag(path)
    res = report.analyse(data, image_model=(lambda k, s: model(s), truths[:10], "test model"))
    exact = crb_of(model, 1)[0]                                       # (sx, sy) px at 0
    assert res["crb"]["sigma_x"] == pytest.approx(exact[0], rel=0.1)
    assert res["crb"]["sigma_y"] == pytest.approx(exact[1], rel=0.1)
    assert res["crb"]["mean_euclid"] == pytest.approx(
        float(np.mean(report.mean_abs_norm(report.crb_covariances(sensor, lambda k, s: model(s),
                                                                   truths[:10])))), rel=1e-9)
    # a round Gaussian on 1 px pixels: about sqrt(sigma^2 + 1/12) / sqrt(N)
    assert res["crb"]["sigma_x"] == pytest.approx(math.sqrt(SIGMA ** 2 + 1 / 12) / math.sqrt(photons), rel=0.03)
    assert res["algorithms"]["cog"]["ratio_to_crb"] > 1.0


# -- inspect, report output, replay -----------------------------------------------------------
def _frames_bag(tmp_path, name="f.mcap", f=30, sensor=None):
    sensor = sensor or single()
    rng = np.random.default_rng(5)
    truths = rng.normal(0, 0.3, size=(f, 1, 2))
    imgs = spots(truths[:, 0], photons=1000, sigma=SIGMA, rng=rng).astype(np.float32)
    return write_bag(tmp_path / name, sensor, truths, {}, frames=imgs), truths, imgs


def test_inspect_lists_topics_sensor_and_changes(tmp_path):
    truths = np.zeros((5, 1, 2))
    st = T0 + DT * np.arange(5)
    path = write_bag(tmp_path / "i.mcap", single(), truths, {"cog": (st, truths)},
                     changes={"cog": [(T0, {"algorithm": "cog"}), (int(st[3]), {"algorithm": "tcog"})]})
    info = bag_info(path)
    assert info["topics"]["/wfs/true_slopes"]["count"] == 5
    assert info["topics"]["/cog/slopes"]["type"] == "sensor_msgs/msg/Image"
    assert [c["description"]["algorithm"] for c in info["centroiders"]["cog"]] == ["cog", "tcog"]
    assert info["centroiders"]["cog"][1]["t_s"] == pytest.approx(3 * DT / 1e9, abs=1e-9)
    text = inspect_bag(path)
    assert "polar detector" in text and "tcog" in text and "/wfs/true_slopes" in text
    assert json.loads(inspect_bag(path, as_json=True))["sensor"]["detector"] == "polar"


def test_report_writes_json_and_plots(tmp_path, capsys):
    sensor = small_pupil()
    lay = geometry.layout(sensor)
    truths = np.zeros((4, lay.n_valid, 2))
    st = T0 + DT * np.arange(4)
    path = write_bag(tmp_path / "r.mcap", sensor, truths, {"cog": (st, truths + 0.1)})
    out = tmp_path / "rep"
    assert cli.main(["report", str(path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "cog" in text and "mean |err|" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["algorithms"]["cog"]["mean_euclid"] == pytest.approx(0.1 * math.sqrt(2), rel=1e-5)
    for name in ("error_timeseries", "error_by_radius", "error_distribution", "error_ratios"):
        assert (out / f"{name}.png").stat().st_size > 1000, name
    assert sorted(summary["plots"]) == sorted(str(p) for p in out.glob("*.png"))
    assert cli.main(["report", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["algorithms"]["cog"]["n"] == 4 * lay.n_valid


def test_replay_adds_slopes_that_match_the_library(tmp_path, capsys):
    from lgs_wfs_ros.centroiding import make_centroider
    path, truths, imgs = _frames_bag(tmp_path)
    out = tmp_path / "out.mcap"
    res = replay_bag(path, ["cog", "cmf"], out=out)
    assert res["frames"] == 30 and res["skipped"] == 0
    data = bagload.load_bag(out)
    segs = {s.label: s for s in data.segments}
    assert set(segs) == {"cog", "cmf"}
    direct = np.stack([make_centroider("cog", single()).centroid(im) for im in imgs])
    np.testing.assert_allclose(segs["cog"].slopes.data[:, 0], direct[:, 0], atol=1e-6)
    # the original messages were copied
    with BagReader(out) as r, BagReader(path) as r0:
        for t, (ty, n) in r0.topics().items():
            assert r.topics()[t] == (ty, n)
    # an existing output is refused without --overwrite; a second replay gets new namespaces
    assert cli.main(["replay", str(path), "--algorithms", "cog", "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    res2 = replay_bag(out, ["cog"], out=tmp_path / "out2.mcap", quiet=True)
    assert res2["namespaces"] == {"cog": "cog_replay"}


# -- bad bags through the CLI ------------------------------------------------------------------
def _bad_files(tmp_path):
    good, _, _ = _frames_bag(tmp_path, "good.mcap", f=12)
    raw = good.read_bytes()
    files = {}
    files["random"] = tmp_path / "random.mcap"
    files["random"].write_bytes(np.random.default_rng(0).bytes(5000))
    files["empty"] = tmp_path / "empty.mcap"
    files["empty"].write_bytes(b"")
    files["truncated"] = tmp_path / "trunc.mcap"
    files["truncated"].write_bytes(raw[: len(raw) // 2])
    files["text"] = tmp_path / "notes.txt"
    files["text"].write_text("hello, not a bag\n" * 50)
    files["missing"] = tmp_path / "nope.mcap"
    files["directory"] = tmp_path
    wrong = tmp_path / "wrong_schema.mcap"
    with BagWriter(wrong) as w:          # true_slopes as a String, no frames, no sensor
        w.add_topic("/wfs/true_slopes", "std_msgs/msg/String")
        w.write("/wfs/true_slopes", encode_string("not an image"), T0)
    files["wrong_schema"] = wrong
    bare = tmp_path / "frames_only.mcap"
    with BagWriter(bare) as w:           # frames but no sensor description and no truths
        from lgs_wfs_ros.bags import encode_image
        w.add_topic("/wfs/frame", "sensor_msgs/msg/Image")
        w.write("/wfs/frame", encode_image(np.zeros((16, 16), np.uint16), T0), T0)
    files["frames_only"] = bare
    return files


@pytest.mark.parametrize("verb", ["inspect", "report", "replay"])
def test_cli_refuses_bad_bags(tmp_path, capsys, verb):
    for kind, path in _bad_files(tmp_path).items():
        if verb == "inspect" and kind in ("wrong_schema", "frames_only"):
            continue                            # a valid MCAP file: inspect describes it
        args = [verb, str(path)] + (["--out", str(tmp_path / f"o_{kind}.mcap")] if verb == "replay" else [])
        code = cli.main(args)
        err = capsys.readouterr().err
        assert code == 2, (kind, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"lgs-wfs {verb}: "), (kind, err)
        assert "Traceback" not in err
        if verb == "replay":
            assert not (tmp_path / f"o_{kind}.mcap").exists(), kind


def test_inspect_flags_wrong_schema(tmp_path):
    files = _bad_files(tmp_path)
    text = inspect_bag(files["wrong_schema"])
    assert "std_msgs/msg/String" in text and "not an lgs_wfs_ros contract bag" in text


def test_replay_skips_bad_frames_and_keeps_going(tmp_path):
    """A frame of the wrong size or an all-zero frame does not stop a replay: the wrong-size
    one gets no slopes (counted), the all-zero one gets NaN slopes, the good ones are measured."""
    sensor = single()
    rng = np.random.default_rng(2)
    truths = rng.normal(0, 0.3, size=(6, 1, 2))
    imgs = spots(truths[:, 0], photons=1000, sigma=SIGMA, rng=rng).astype(np.float32)
    path = tmp_path / "bad_frames.mcap"
    with bagwrite.ContractBagWriter(path, sensor, log_ns=T0) as w:
        for k in range(6):
            s = T0 + DT * k
            frame = imgs[k]
            if k == 2:
                frame = np.zeros((8, 8), np.float32)          # wrong size
            if k == 4:
                frame = np.zeros_like(imgs[k])                # no light
            w.frame(s, frame)
            w.truth(s, truths[k])
    res = replay_bag(path, ["cog"], out=tmp_path / "o.mcap", quiet=True)
    assert res["frames"] == 5 and res["skipped"] == 1
    seg = bagload.load_bag(tmp_path / "o.mcap").segments[0]
    assert len(seg.slopes) == 5
    nan_rows = ~np.isfinite(seg.slopes.data[:, 0]).all(axis=1)
    assert nan_rows.tolist() == [False, False, False, True, False]
