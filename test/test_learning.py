"""Training pipeline: dataset generator, ONNX export, recipes, and tiny training runs."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from lgs_wfs_ros.learning import dataset, export, recipes
from lgs_wfs_ros.learning.model import forward, n_parameters
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.optics.spots import spot_images
from lgs_wfs_ros.sensor import Sensor


BLOCK_TORCH = ("import sys\n"
               "class Block:\n"
               "    def find_spec(self, name, path=None, target=None):\n"
               "        if name == 'torch' or name.startswith('torch.'):\n"
               "            raise ImportError('torch blocked')\n"
               "sys.meta_path.insert(0, Block())\n")


def run_without_torch(code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter in which ``import torch`` fails."""
    return subprocess.run([sys.executable, "-c", BLOCK_TORCH + code], capture_output=True, text=True)


def test_import_without_torch():
    out = run_without_torch("import lgs_wfs_ros.learning as L\n"
                            "from lgs_wfs_ros.learning import card, dataset, export, recipes, validate, train\n"
                            "assert 'torch' not in sys.modules\n"
                            "print(sorted(L.SHIPPED))")
    assert out.returncode == 0, out.stderr
    assert "ann_pupil" in out.stdout


def test_train_without_torch_names_the_extra(tmp_path):
    """``lgs-wfs train`` without torch: exit 2 and one line naming the 'train' extra."""
    out = run_without_torch("from lgs_wfs_ros import cli\n"
                            f"sys.exit(cli.main(['train', 'ann_1k', '--out', {str(tmp_path)!r}]))")
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert "'train' extra" in out.stderr and "lgs_wfs_ros[train]" in out.stderr
    assert not list(tmp_path.iterdir())


def test_train_never_overwrites_and_writes_the_card(tmp_path, capsys):
    """A tiny training run writes NAME.onnx and a README.md card generated from its
    metadata; a second run refuses (the file untouched, exit 2 from the CLI) unless --force."""
    pytest.importorskip("torch")
    from lgs_wfs_ros import cli
    from lgs_wfs_ros.learning import card, train
    kw = dict(samples=1500, quick=True, validate=False, progress=False)
    r = train.train_model("ann_diag", tmp_path, **kw)
    path = tmp_path / "ann_diag.onnx"
    assert r["path"] == str(path) and not list(tmp_path.glob("*.partial"))
    meta = export.read_metadata(path)["lgs_wfs.training"]
    text = (tmp_path / "README.md").read_text()
    assert text == card.render(tmp_path)
    assert f"| `ann_diag` | cartesian | 256-16-2 ({meta['parameters']} weights), adam | 1500 samples, " \
           f"1000 photons (quick run) | {meta['check']['mean_err_px']:.4f} |" in text
    assert meta["recipe_line"] in text
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="--force"):
        train.train_model("ann_diag", tmp_path, **kw)
    assert cli.main(["train", "ann_diag", "--out", str(tmp_path), "--samples", "1500", "--quick"]) == 2
    assert "exists" in capsys.readouterr().err
    assert path.read_bytes() == before
    train.train_model("ann_diag", tmp_path, seed=99, force=True, **kw)
    assert path.read_bytes() != before
    assert export.read_metadata(path)["lgs_wfs.training"]["seed"] == 99


def test_sample_shapes_normalisation_and_reproducibility():
    spec = dataset.DataSpec(Sensor.paper_single("polar"), photons=1000.0, sigma_px=0.5)
    a = dataset.sample(spec, np.random.default_rng(3), 64, input_gain=256.0)
    b = dataset.sample(spec, np.random.default_rng(3), 64, input_gain=256.0)
    assert a.x.shape == (64, 256) and a.x.dtype == np.float32
    assert a.y.shape == (64, 2) and a.cond.shape == (64, 3) and a.images.shape == (64, 16, 16)
    np.testing.assert_allclose(a.x.sum(axis=1), 256.0, rtol=1e-5)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.y, b.y)
    c = dataset.sample(spec, np.random.default_rng(4), 64)
    assert not np.array_equal(a.y, c.y)
    # photon counts: integers summing to about 1000 (Poisson)
    tot = a.images.reshape(64, -1).sum(axis=1)
    assert np.all(a.images == np.round(a.images))
    assert abs(tot.mean() - 1000) < 4 * math.sqrt(1000 / 64) + 30   # truncation loses a little
    # positions: N(0, 0.5) per axis
    big = dataset.sample(spec, np.random.default_rng(5), 4000)
    assert abs(big.y.std() - 0.5) < 0.03 and abs(big.y.mean()) < 0.03


def test_pupil_mode_mixes_detectors_and_conditions_on_pixel_axes():
    spec = dataset.DataSpec(Sensor(), photons=None, pupil=True, conditioning="e_r")
    s = dataset.sample(spec, np.random.default_rng(0), 2000)
    lay = geometry.layout(Sensor())
    polar_like = np.all(s.cond[:, :2] == np.array([1, 0], np.float32), axis=1)
    assert 0.4 < polar_like.mean() < 0.6                      # half polar (e_pix = (1, 0))
    np.testing.assert_allclose(np.hypot(s.cond[:, 0], s.cond[:, 1]), 1.0, atol=1e-6)
    r = s.cond[:, 2] * dataset.R_SCALE_M
    assert r.min() >= lay.r_m.min() - 1e-4 and r.max() <= lay.r_m.max() + 1e-4
    np.testing.assert_allclose(s.x.sum(axis=1), 1.0, rtol=1e-5)    # noise-free, gain 1


def test_polar_sample_equals_simulator_local_frame_image():
    """The dataset renders polar blocks as cartesian blocks with e = (1, 0): same image."""
    sensor = Sensor(detector="polar", single_subaperture_xy_m=(6.0, 8.0))   # e not along x
    lay = geometry.layout(sensor)
    spec = dataset.DataSpec(sensor, photons=None, sigma_px=0.5)
    h = dataset.training_altitude_grid()
    rho = np.exp(-0.5 * ((h - 91e3) / 3e3) ** 2)
    t_local = np.array([[0.3, -0.2]])
    s = dataset.sample(spec, np.random.default_rng(0), 1, density=rho, shift_px=t_local)
    t_det = geometry.local_to_detector(t_local, lay.e)
    ref, _ = spot_images(sensor, lay.r_m, lay.e, h, rho, t_det)
    np.testing.assert_allclose(s.images[0], ref[0], atol=1e-6)


def test_dataspec_rejects_bad_input():
    with pytest.raises(ValueError):
        dataset.DataSpec(Sensor.paper_single("polar"), photons=-1)
    with pytest.raises(ValueError):
        dataset.DataSpec(Sensor(), pupil=False)
    with pytest.raises(ValueError):
        dataset.DataSpec(Sensor.paper_single("polar"), pupil=True)
    with pytest.raises(ValueError):
        dataset.DataSpec(Sensor.paper_single("polar"), conditioning="xyz")
    spec = dataset.DataSpec(Sensor.paper_single("polar"))
    with pytest.raises(ValueError):
        dataset.sample(spec, 3, 10)
    with pytest.raises(ValueError):
        dataset.sample(spec, np.random.default_rng(0), 0)


def test_stream_batches_are_reproducible():
    spec = dataset.DataSpec(Sensor.paper_single("cartesian"), photons=316.0)
    a = dataset.generate(spec, 300, batch=128, seed=9, progress=False)
    b = list(dataset.stream(spec, 300, batch=128, seed=9, progress=False))
    assert [len(x) for x in b] == [128, 128, 44]
    np.testing.assert_array_equal(a["x"][128:256], b[1].x)


def test_training_positions_use_the_square_subaperture_gtilt():
    """One turbulence sigma for the whole package (optics.turbulence, square subaperture, the
    shape of a lenslet and of the simulator's G-tilt): the classic circular-aperture
    0.170 (lambda/d)^2 (d/r0)^(5/3) is about 2 % higher (square: 27 % more area averaged),
    and the check set of a model is drawn with it."""
    from lgs_wfs_ros.learning import train
    from lgs_wfs_ros.optics.turbulence import turbulence_sigma_px
    s = turbulence_sigma_px(Sensor())
    circle = math.sqrt(0.17 * 1e-12 * (0.5 / 0.15) ** (5 / 3)) * 206264.8 / 0.5
    assert 0.97 < s / circle < 0.99
    assert not hasattr(dataset, "turbulence_sigma_px")
    smp = train.check_set(recipes.get("ann_1k"), n=4000)
    assert np.std(smp.y, axis=0).mean() == pytest.approx(s, rel=0.04)


@pytest.mark.parametrize("cond,rotate", [("none", False), ("e_r", False), ("e_r", True)])
def test_export_matches_numpy_forward(cond, rotate):
    ort = pytest.importorskip("onnxruntime")
    rng = np.random.default_rng(1)
    nc = export.CONDITIONING_WIDTH[cond]
    sizes = (256 + nc, 8, 5, 2)
    layers = [(rng.normal(0, 0.3, (a, b)), rng.normal(0, 0.1, b)) for a, b in zip(sizes[:-1], sizes[1:])]
    model = export.build_model(layers, pixels=16, conditioning=cond, input_gain=256.0,
                               metadata={"lgs_wfs.detector": "polar"}, rotate_to_local=rotate)
    sess = export.session(model.SerializeToString())
    img = rng.random((20, 16, 16))
    c = None
    if nc:
        ang = rng.uniform(0, 2 * np.pi, 20)
        c = np.stack([np.cos(ang), np.sin(ang), rng.random(20)], axis=1)
    got = export.predict(sess, img, c)
    x = img.reshape(20, -1) / img.reshape(20, -1).sum(1, keepdims=True) * 256.0
    want = forward(layers, x if c is None else np.concatenate([x, c], axis=1))
    if rotate:
        ex, ey = c[:, 0], c[:, 1]
        want = np.stack([ex * want[:, 0] + ey * want[:, 1], ex * want[:, 1] - ey * want[:, 0]], 1)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
    meta = {p.key: json.loads(p.value) for p in model.metadata_props}
    assert meta["lgs_wfs.pixels"] == 16 and meta["lgs_wfs.conditioning"] == cond
    assert meta["lgs_wfs.detector"] == "polar" and meta["lgs_wfs.input_norm"] == "sum"


def test_export_rejects_bad_layers():
    with pytest.raises(ValueError):
        export.build_model([(np.zeros((256, 3)), np.zeros(3))], pixels=16)      # 3 outputs
    with pytest.raises(ValueError):
        export.build_model([(np.zeros((250, 2)), np.zeros(2))], pixels=16)      # wrong width
    with pytest.raises(ValueError):
        export.build_model([(np.zeros((256, 2)), np.zeros(2))], pixels=16, conditioning="q")


def test_recipes_are_complete():
    assert set(recipes.SHIPPED) == {"ann_1k", "ann_noiseless", "ann_diag", "ann_pupil", "ann_ref",
                                    "ann_marg", "ann_hyper", "ann_conv", "ann_grid"}
    assert n_parameters(recipes.PAPER_SIZES) == 4146
    for name in recipes.SHIPPED:
        r = recipes.get(name)
        assert name in r.line() and f"seed {r.seed}" in r.line()
    with pytest.raises(ValueError):
        recipes.get("nope")


def test_broad_prior_covers_the_issue_ranges_from_the_training_split_only():
    """ann_ref's prior: centroids 85-100 km, FWHM 3-20 km (sporadic layers narrower), and
    the references are not the profiles (stale, node-sampled)."""
    from lgs_wfs_ros.learning import refdata
    from lgs_wfs_ros.optics import sodium
    rng = np.random.default_rng(5)
    rho = refdata.broad_profiles(rng, 400)
    c = sodium.centroid_altitude(refdata.GRID, rho) / 1e3
    assert 84.0 < np.percentile(c, 2) and np.percentile(c, 98) < 101.5
    assert np.percentile(c, 90) - np.percentile(c, 10) > 10.0      # the whole 85-100 km range
    ref = refdata.calibrated(rng, rho)
    assert np.all(ref >= 0) and np.allclose(np.trapezoid(ref, refdata.GRID, axis=1), 1.0, atol=0.02)
    assert 0 < np.abs(ref - rho).sum(axis=1).min()
    p = refdata.pairs(np.random.default_rng(6), 256)
    assert p.r_m.max() > 30 and p.photons.min() >= 100 and p.photons.max() <= 3000
    assert np.allclose(p.refs.sum(axis=1), 1.0, atol=1e-4) and np.isfinite(p.images).all()


def test_tiny_adam_training_reduces_error():
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.learning import train
    from lgs_wfs_ros.learning.model import mlp
    torch.set_num_threads(1)
    rec = recipes.get("ann_1k")
    d = train.training_data(rec, 3000, seed=5, progress=False)
    m = train.training_data(rec, 500, seed=6, progress=False)
    x, y = torch.from_numpy(d["x"]), torch.from_numpy(d["y"])
    xv, yv = torch.from_numpy(m["x"]), torch.from_numpy(m["y"])
    net = mlp((256, 16, 2), seed=0)
    before = train._mean_error(net, xv, yv)
    hist = train.fit_adam(net, x, y, xv, yv, epochs=6, batch=128, lr=3e-3, seed=0, progress=False)
    assert hist[-1]["train_mse"] < hist[0]["train_mse"]
    assert train._mean_error(net, xv, yv) < 0.7 * before


def test_input_jacobian_matches_autograd():
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.learning.model import mlp
    from lgs_wfs_ros.learning.train import input_jacobian
    net = mlp((7, 5, 4, 2), seed=2).double()
    x = torch.randn(3, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    y, jac = input_jacobian(net, x)
    np.testing.assert_allclose(y.detach().numpy(), net(x).detach().numpy(), rtol=1e-12)
    for b in range(3):
        ref = torch.autograd.functional.jacobian(net, x[b:b + 1])[0, :, 0]
        np.testing.assert_allclose(jac[b].detach().numpy(), ref.numpy(), rtol=1e-10, atol=1e-12)


def test_poisson_penalty_equals_monte_carlo_output_variance():
    """First-order penalty = variance of the output of sum-normalised Poisson images."""
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.learning.model import mlp
    from lgs_wfs_ros.learning.train import input_jacobian, poisson_penalty
    rng = np.random.default_rng(0)
    n, gain, photons = 16, 16.0, 3000.0
    net = mlp((n, 6, 2), seed=3).double()
    p = rng.random(n) ** 2
    p /= p.sum()
    counts = rng.poisson(photons * p, size=(40_000, n)).astype(float)
    x = torch.from_numpy(dataset.normalise(counts[:, None, :], gain).astype(np.float64))
    with torch.no_grad():
        mc_var = net(x).numpy().var(axis=0)
    x0 = torch.from_numpy(p[None] * gain)
    with torch.no_grad():
        pen = poisson_penalty(input_jacobian(net, x0)[1], x0, photons, gain).numpy()[0]
    np.testing.assert_allclose(pen, mc_var, rtol=0.04)
    # without the sum-normalisation term (- (J x)^2) output 0 would be 13 % off
    with torch.no_grad():
        jac = input_jacobian(net, x0)[1]
        diag_only = (gain * (jac ** 2 * x0[:, None]).sum(-1) / photons).numpy()[0]
    assert abs(diag_only[0] - mc_var[0]) > 0.1 * mc_var[0]


def test_noise_penalty_training_is_noise_free_and_damps_noise():
    """fit_adam with the penalty at 100 photons, on noise-free images only, lowers the output
    noise variance and the error on real 100-photon images."""
    torch = pytest.importorskip("torch")
    from lgs_wfs_ros.learning import train
    from lgs_wfs_ros.learning.model import mlp
    torch.set_num_threads(1)
    rec = recipes.get("ann_noiseless")
    assert rec.photons is None and rec.noise_penalty_photons is not None
    line = rec.line()
    assert "noise-free" in line and "not as noisy samples" in line
    d = train.training_data(rec, 2000, seed=5, progress=False)
    noisy = dataset.generate(train.recipe_spec(rec).replace(photons=100.0), 1000, seed=6,
                             progress=False, input_gain=256.0)
    x, y = torch.from_numpy(d["x"]), torch.from_numpy(d["y"])
    xn, yn = torch.from_numpy(noisy["x"]), torch.from_numpy(noisy["y"])
    pens, noisy_mse = [], []
    for photons in (None, 100.0):
        net = mlp((256, 16, 2), seed=0)
        train.fit_adam(net, x, y, x[:300], y[:300], epochs=10, batch=128, lr=3e-3, seed=0,
                       progress=False, noise_penalty_photons=photons, pixels=256, input_gain=256.0)
        with torch.no_grad():
            pens.append(float(train.poisson_penalty(train.input_jacobian(net, x)[1], x, 100.0,
                                                    256.0).mean()))
            noisy_mse.append(float(((net(xn) - yn) ** 2).mean()))
    assert pens[1] < 0.6 * pens[0]
    assert noisy_mse[1] < 0.85 * noisy_mse[0]
