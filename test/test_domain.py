"""Model training domains: the shipped models declare theirs, the ann centroider refuses a
sensor outside it with the reason, and with out_of_domain = warn runs and counts."""

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper

from lgs_wfs_ros.centroiding import make_centroider, options
from lgs_wfs_ros.centroiding import domain as dom
from lgs_wfs_ros.learning import domains, export, recipes, refdata
from lgs_wfs_ros.optics import geometry, sodium
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor
from pupils import SMALL

MODELS = Path(__file__).resolve().parents[1] / "models"
POLAR = Sensor(detector="polar")


def test_ann_1k_on_a_full_pupil_refuses_with_the_reason():
    with pytest.raises(ValueError) as exc:
        make_centroider("ann", POLAR, model="ann_1k")
    msg = str(exc.value)
    print("refusal:", msg)
    r = geometry.layout(POLAR).r_m
    assert "ann_1k was trained at r = 14.75 m" in msg
    assert f"its radii run {r.min():.2f}-{r.max():.2f} m" in msg
    assert "out_of_domain = warn" in msg


def test_ann_1k_on_a_full_pupil_runs_when_overridden_and_counts():
    c = options.build("ann", POLAR, {"model": "ann_1k", "out_of_domain": "warn"})
    d = json.loads(json.dumps(c.describe()))          # what the node publishes
    r = np.asarray(geometry.layout(POLAR).r_m)
    expected = int(np.count_nonzero(np.abs(r - 14.75) > dom.RADIUS_TOL_M))
    print("count:", d["domain"]["out_of_domain_subapertures"], "warning:", d["warning"])
    assert d["domain"]["out_of_domain_subapertures"] == expected == r.size
    assert d["warning"].startswith(f"{expected} of {r.size} subapertures outside ann_1k")
    assert d["options"]["out_of_domain"] == "warn"
    frame = np.zeros(POLAR.frame_shape, dtype=np.float32) + 1.0
    assert c.centroid(frame).shape == (r.size, 2)


def test_side_launch_counts_only_the_subapertures_beyond_the_training_radii():
    """ann_pupil (radii of the centre-launch pupil) with the launch 16 m off axis: exactly
    the subapertures whose distance to the launch leaves [1.90, 14.95] m are counted."""
    sensor = Sensor(detector="polar", launch_xy_m=(16.0, 0.0))
    with pytest.raises(ValueError, match="ann_pupil was trained at r = 1.90"):
        make_centroider("ann", sensor, model="ann_pupil")
    c = make_centroider("ann", sensor, model="ann_pupil", out_of_domain="warn")
    lo, hi = export.read_metadata(MODELS / "ann_pupil.onnx")["lgs_wfs.domain"]["radius_m"]
    r = np.asarray(geometry.layout(sensor).r_m)
    outside = (r < lo - dom.RADIUS_TOL_M) | (r > hi + dom.RADIUS_TOL_M)
    assert 0 < outside.sum() < r.size
    assert np.array_equal(c.domain.outside, outside)
    assert c.describe()["domain"]["out_of_domain_subapertures"] == int(outside.sum())


def test_inside_the_domain_nothing_is_counted_and_photons_only_warn():
    c = make_centroider("ann", Sensor.paper_single("polar", photons=316.0), model="ann_1k")
    d = c.describe()
    assert d["domain"]["out_of_domain_subapertures"] == 0 and "warning" not in d
    assert any("316" in w for w in d["domain"]["warnings"])
    cart = make_centroider("ann", Sensor.paper_single("cartesian"), model="ann_diag")
    assert cart.describe()["domain"]["reasons"] == []


def test_cartesian_single_subaperture_model_refuses_other_elongation_angles():
    sensor = Sensor(detector="cartesian", single_subaperture_xy_m=(14.75, 0.0))
    with pytest.raises(ValueError, match="elongation at 45 deg"):
        make_centroider("ann", sensor, model="ann_diag")


def _without_domain(tmp_path, name="ann_1k"):
    m = onnx.load(str(MODELS / f"{name}.onnx"))
    props = {p.key: p.value for p in m.metadata_props if p.key != "lgs_wfs.domain"}
    del m.metadata_props[:]
    helper.set_model_props(m, props)
    path = tmp_path / f"{name}_nodomain.onnx"
    onnx.save(m, str(path))
    return path


def test_a_model_without_a_domain_runs_unchecked_with_a_warning(tmp_path):
    c = make_centroider("ann", POLAR, model=str(_without_domain(tmp_path)))
    d = c.describe()["domain"]
    assert d["known"] is False and d["out_of_domain_subapertures"] == 0
    assert "declares no training domain" in d["warnings"][0]


@pytest.mark.parametrize("bad", [{"detector": ["polar"], "input": "image"},
                                 {"radius_m": [15, 14], "detector": ["polar"], "input": "image"},
                                 {"radius_m": [0, 15], "detector": ["sideways"], "input": "image"},
                                 {"radius_m": [0, 15], "detector": ["polar"], "input": "profile"},
                                 "everywhere"])
def test_a_malformed_domain_is_refused(tmp_path, bad):
    path = _without_domain(tmp_path)
    export.update_metadata(path, {"lgs_wfs.domain": bad})
    with pytest.raises(ValueError, match="lgs_wfs.domain"):
        make_centroider("ann", Sensor.paper_single("polar"), model=str(path))


def test_out_of_domain_option_row_and_bad_values():
    row = options.option("ann", "out_of_domain")
    assert row.default == "refuse" and set(row.choices) == {"refuse", "warn"}
    with pytest.raises(ValueError, match="out_of_domain"):
        make_centroider("ann", Sensor.paper_single("polar"), model="ann_1k", out_of_domain="ignore")


@pytest.mark.parametrize("where", [MODELS, MODELS / "paper_prior"])
def test_every_model_file_declares_the_domain_its_training_recorded(where):
    names = [f.stem for f in sorted(where.glob("*.onnx"))]
    assert names
    for name in names:
        meta = export.read_metadata(where / f"{name}.onnx")
        assert "lgs_wfs.domain" in meta, f"{name} declares no domain"
        stored = dom.parse(meta["lgs_wfs.domain"])
        if name in recipes.RECIPES:
            assert meta["lgs_wfs.domain"] == domains.recipe_domain(recipes.get(name),
                                                                   meta.get("lgs_wfs.training"))
        assert stored["input"] in dom.INPUT_KINDS


def test_profile_moments_read_a_gaussian_layers_centroid_and_fwhm():
    h = np.linspace(60e3, 130e3, 2801)
    for centre, fwhm in ((95e3, 10e3), (102e3, 2.5e3)):
        c, f = dom.profile_moments(h, sodium.gaussian_profile(h, centre, fwhm))
        assert c == pytest.approx(centre / 1e3, abs=0.01) and f == pytest.approx(fwhm / 1e3, rel=0.01)


def test_check_profile_names_each_range_the_profile_leaves():
    h = np.linspace(60e3, 130e3, 2801)
    d = {"profile_centroid_km": [84.0, 100.5], "profile_fwhm_km": [3.0, 19.5]}
    assert dom.check_profile(d, h, sodium.gaussian_profile(h, 92e3, 9e3), "m").ok
    high = dom.check_profile(d, h, sodium.gaussian_profile(h, 103e3, 9e3), "m")
    assert [r.split(";")[0] for r in high.reasons] == [
        "m was trained on sodium profiles of centroid 84-100.5 km"]
    assert "103.0 km" in high.reasons[0]
    thin = dom.check_profile(d, h, sodium.gaussian_profile(h, 92e3, 1.5e3), "m")
    assert len(thin.reasons) == 1 and "FWHM 3-19.5 km" in thin.reasons[0]
    assert dom.check_profile({"radius_m": [0, 1]}, h, sodium.gaussian_profile(h, 92e3, 9e3)) is None


def test_reference_models_declare_the_spread_of_their_training_profiles():
    """The profile ranges are the central 98 % of the training prior's draws (double peaks and
    sporadic layers reach beyond the main layer's nominal 85-100 km, 3-20 km)."""
    got = domains.profile_ranges(refdata.MARGINAL_SPEC)
    assert 83.0 < got["profile_centroid_km"][0] < 85.0 and 100.0 < got["profile_centroid_km"][1] < 102.0
    assert 2.5 < got["profile_fwhm_km"][0] < 3.5 and 18.5 < got["profile_fwhm_km"][1] < 20.5
    for name in ("ann_ref", "ann_marg", "ann_hyper", "ann_conv", "ann_grid"):
        stored = export.read_metadata(MODELS / f"{name}.onnx")["lgs_wfs.domain"]
        assert {k: stored[k] for k in dom.PROFILE_KEYS} == got, name


@pytest.mark.parametrize("family,reason", [("measured", None), ("high", "centroid 84-100.5 km"),
                                           ("narrow", "FWHM 3-19.5 km")])
def test_a_network_says_when_the_calibrated_sky_leaves_its_training_profiles(family, reason):
    """The default polar ann (ann_conv) on a small pupil, refitted on three frames of an
    unseen family: the calibrated profile is checked against the model's profile ranges at
    each install of references; outside, describe() carries the reason and the count and
    the centroider's notice says it (a node logs each change)."""
    sensor = SMALL.replace(detector="polar")
    lay = geometry.layout(sensor)
    h, d = sodium.unseen_profiles(family, 1, 700.0, seed=2)
    sm = SpotModel(sensor, lay.r_m, lay.e, h, d[0], max_shift_px=3.5)
    rng = np.random.default_rng(0)
    c = make_centroider("ann", sensor, pupil_period=3)
    first = c.describe()["domain"]["profile"]              # the calibration's prior: inside
    assert first["inside"] and first["checked"] == 1 and c.notice == ""
    for _ in range(3):
        c.centroid(rng.poisson(sm.images(rng.normal(0, 0.3, (lay.n_valid, 2)))[0] * 1000.0)
                   .astype(float))
    desc = json.loads(json.dumps(c.describe()))
    prof = desc["domain"]["profile"]
    truth_c, truth_f = dom.profile_moments(h, d[0])
    print(family, prof, "truth", round(truth_c, 2), round(truth_f, 2))
    assert prof["checked"] == 2 and abs(prof["centroid_km"] - truth_c) < 2.0
    if reason is None:
        assert prof["inside"] and prof["outside"] == 0 and c.notice == "" and "warning" not in desc
    else:
        assert not prof["inside"] and prof["outside"] == 1
        assert reason in c.notice and "km" not in c.notice.split(reason)[1]   # no value: stable
        assert reason in desc["warning"] and "the calibrated profile's is" in desc["warning"]


def test_replay_records_the_notice_once_when_the_sky_leaves_the_training_profiles(tmp_path):
    """Replay does what the node does: the description again, with reason notice, on the
    frame whose refit found the sky outside the network's training profiles, and not at the
    next refit that finds it outside again (the notice names the range, not the value)."""
    from lgs_wfs_ros.analysis.bagload import read_json_topic
    from lgs_wfs_ros.analysis.bagwrite import ContractBagWriter
    from lgs_wfs_ros.analysis.replay import replay_bag
    from lgs_wfs_ros.bags import BagReader

    sensor = SMALL.replace(detector="polar")
    lay = geometry.layout(sensor)
    h, d = sodium.unseen_profiles("high", 1, 700.0, seed=2)
    sm = SpotModel(sensor, lay.r_m, lay.e, h, d[0], max_shift_px=3.5)
    rng = np.random.default_rng(0)
    path = tmp_path / "high.mcap"
    with ContractBagWriter(path, sensor) as w:
        for k in range(7):                     # refits at frames 3 and 6: outside at both
            img = rng.poisson(sm.images(rng.normal(0, 0.3, (lay.n_valid, 2)))[0] * 1000.0)
            w.frame(k + 1, geometry.stack_to_frame(img.astype(np.uint16), lay))
    res = replay_bag(path, ["ann"], out=tmp_path / "r.mcap", quiet=True,
                     options={"ann": {"pupil_period": 3}})
    with BagReader(res["out"]) as reader:
        descs = [dd for _, dd in read_json_topic(reader, f"/{res['namespaces']['ann']}/centroider")]
    assert [dd["reason"] for dd in descs] == ["replay", "notice"]     # not again at frame 6
    assert descs[0]["domain"]["profile"]["inside"] and not descs[1]["domain"]["profile"]["inside"]
    assert "centroid 84-100.5 km" in descs[1]["warning"]
