"""ann_grid's network on a window of W > 16 grid bins (a diagonal block whole): an experiment.

On a block whose e is nearer a pixel diagonal, ``ann``'s 16 grid bins (1 px along the
diagonal direction d) hold 16 of the block's 22.6 px; a high layer at the pupil's edge
puts light beyond them (docs/ann_ref.md "Where the cartesian high layer's excess sits").
Here the same bins are read through a centred window of W bins (24 holds every diagonal
block; axis blocks and polar column sums are padded with empty bins), and ``ann_grid``'s
network (its recipe, torch) is trained on them, from scratch or from the shipped weights
(read back from models/ann_grid.onnx), against a control at W = 16 on the same spots and
budget. Validation as marginal_validation.py's families (the training block's profiles
under the unseen families' maps), on cartesian blocks at any angle, 4,000 spots, shifts
N(0, 0.46 px), references as the calibration gives them, each model less its reading of
its noise-free reference (``bias: pupil``); printed: rms error along d (px) on blocks
nearer a diagonal / an axis, all radii and beyond 10 m.

The loss weight of a W-bin spot is the Fisher information over the bins its reference
lights (``fisher_lit``): hypertrain.fisher's 1e-4 floor makes an empty padded bin beside the
light worth ~1e4 times its neighbours, which put 30 % of the weight on 1 % of the spots and
left the network worse everywhere.

    python benchmarks/diagonal_window.py check
    python benchmarks/diagonal_window.py scratch W SPOTS EPOCHS OUT.pt
    python benchmarks/diagonal_window.py train W SPOTS EPOCHS OUT.pt      (from the shipped weights)
    python benchmarks/diagonal_window.py scratch-diag W SPOTS EPOCHS OUT.pt   (diagonal blocks only)
    python benchmarks/diagonal_window.py validate 4000 NAME:OUT.pt:W ...

Not part of benchmarks/run.py (needs torch; about 25 min a training on one core).
"""
import sys, time, numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parent))
import onnx, torch
from onnx import numpy_helper
from lgs_wfs_ros.centroiding import bins_along_e
from lgs_wfs_ros.learning import hypertrain, refdata
from lgs_wfs_ros.learning.recipes import RECIPES
from lgs_wfs_ros.optics.detector import expose
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

P = 16
SHIPPED = str(Path(__file__).resolve().parents[1] / "models" / "ann_grid.onnx")
REC = RECIPES["ann_grid"]
SPEC = refdata.MARGINAL_SPEC


def project_wide(e, flat, W):
    """(n, W) grid bins along d (centred window of W 1-px bins), and d."""
    start, w, d = bins_along_e.grid_weights(e, P)
    n = flat.shape[0]
    pad = (W - P) // 2
    idx = start[..., None].astype(np.int64) + np.arange(w.shape[-1]) + pad
    vals = flat[..., None] * w
    ok = (idx >= 0) & (idx < W)
    fi = (np.arange(n)[:, None, None] * W + idx)[ok]
    return np.bincount(fi, weights=vals[ok], minlength=n * W).reshape(n, W), d


def reduce(e, counts, ref, polar, W):
    n = counts.shape[0]
    if polar:
        pad = (W - P) // 2
        marg = np.pad(counts.sum(axis=1), ((0, 0), (pad, W - P - pad)))
        refm = np.pad(ref.sum(axis=1), ((0, 0), (pad, W - P - pad)))
        along = e
    else:
        marg, along = project_wide(e, counts.reshape(n, -1), W)
        refm, _ = project_wide(e, ref.reshape(n, -1), W)
    tot = refm.sum(axis=1, keepdims=True)
    return marg.astype(np.float32), (refm / np.where(tot > 0, tot, np.inf)).astype(np.float32), along


def near_diagonal(rng, m):
    """``(m, 2)`` unit vectors within 22.5 deg of a pixel diagonal (uniform in angle)."""
    ang = np.pi / 4 + np.pi / 2 * rng.integers(0, 4, size=m) + rng.uniform(-np.pi / 8, np.pi / 8, size=m)
    return np.stack([np.cos(ang), np.sin(ang)], axis=1)


def batch(rng, m, det, W, diag=False):
    r = rng.uniform(*SPEC.radius_m, size=m)
    e = np.tile([1.0, 0.0], (m, 1)) if det == "polar" else \
        near_diagonal(rng, m) if diag else refdata.any_angle(rng, m)
    t, ref, ph, counts = refdata._spots(rng, SPEC, Sensor(), r, e)
    marg, refm, along = reduce(e, counts, ref, det == "polar", W)
    return refdata.MarginalPairs(marg, refm, (t * along).sum(axis=1, keepdims=True).astype(np.float32), r, ph)


def generate(n, seed, W, dets=REC.detectors, diag=False):
    parts = []
    for det, count in refdata.split(n, dets).items():
        done, kb = 0, 0
        while done < count:
            m = min(4096, count - done)
            parts.append(batch(np.random.default_rng([seed, kb, *refdata.STREAMS[det]]), m, det, W, diag))
            done, kb = done + m, kb + 1
    return refdata.MarginalPairs(*[np.concatenate([getattr(q, f) for q in parts]) for f in ("marg", "refs", "y", "r_m", "photons")])


def load_net(path):
    spec = hypertrain.spec_of(REC)
    net = hypertrain._torch_module(spec)
    w = {i.name: numpy_helper.to_array(i).astype(np.float64) for i in onnx.load(str(path)).graph.initializer}
    new = {"hyper.0.weight": w["cw0"], "hyper.0.bias": w["cb0"], "hyper.2.weight": w["cw1"], "hyper.2.bias": w["cb1"],
           "head.weight": w["headw"], "head.bias": w["headb"], "pool.weight": w["poolw"].T, "pool.bias": w["poolb"],
           "wn": w["c_wn"] / -0.8, "trunk.0.weight": w["tw0"].T, "trunk.0.bias": w["tb0"],
           "trunk.2.weight": w["tw1"].T, "trunk.2.bias": w["tb1"]}
    net.load_state_dict({k: torch.tensor(v, dtype=torch.float32) for k, v in new.items()})
    return net, spec


def predict(net, pairs, bias=True):
    with torch.no_grad():
        t = hypertrain._tensors(pairs)
        out = net(t[0], t[1], t[2]).numpy()[:, 0]
        if bias:
            clean = refdata.MarginalPairs(pairs.refs * pairs.marg.sum(axis=1, keepdims=True), pairs.refs,
                                          pairs.y, pairs.r_m, pairs.photons)
            c = hypertrain._tensors(clean)
            out = out - net(c[0], c[1], c[2]).numpy()[:, 0]
    return out


def fisher_lit(pairs):
    """hypertrain.fisher over the bins with light in the reference (a padded bin adds none)."""
    r = np.asarray(pairs.refs, np.float64)
    d = np.zeros_like(r)
    d[:, 1:-1] = (r[:, 2:] - r[:, :-2]) / 2
    d[:, 0], d[:, -1] = r[:, 1] / 2, -r[:, -2] / 2
    return pairs.marg.sum(axis=1, dtype=np.float64) * np.where(r > 0, d ** 2 / (r + 1e-4), 0.0).sum(axis=1)


def finetune(W, samples, epochs, out, lr=5e-4, seed=116, scratch=False, diag=False):
    torch.set_num_threads(1)
    hypertrain.fisher = fisher_lit          # the loss weights of fit (this process only)
    net, spec = load_net(SHIPPED)
    if scratch:
        net = hypertrain._torch_module(spec)
    t0 = time.time()
    dets = ("cartesian",) if diag else REC.detectors
    data, mon = generate(samples, seed, W, dets, diag), generate(20000, seed + 1000, W, dets, diag)
    print(f"W {W}: data {time.time() - t0:.0f} s; before: monitor mae {hypertrain._mae(net, hypertrain._tensors(mon)):.5f}", flush=True)
    tr, mt = hypertrain._tensors(data), hypertrain._tensors(mon)
    wt = hypertrain.loss_weights(data, spec.weight_power)
    def loss_of(idx):
        return (wt[idx] * (net(tr[0][idx], tr[1][idx], tr[2][idx]) - tr[3][idx]) ** 2).mean()
    hypertrain.adam_cosine(net, tr[0].shape[0], loss_of, lambda: hypertrain._mae(net, mt), epochs, lr,
                           spec.batch, spec.seed, lambda s: print(s, flush=True))
    torch.save(net.state_dict(), out)


def validation(family, n, photons, seed, W):
    """Cartesian blocks at any angle, training-block profiles under family's map."""
    from marginal_validation import family_profiles
    rng = np.random.default_rng([seed, 77])
    s = Sensor(); render = s.replace(detector="cartesian")
    r = 15.0 * np.sqrt(rng.uniform(0.02, 1.0, size=n))
    e = refdata.any_angle(rng, n)
    t = np.clip(rng.normal(0.0, 0.46, size=(n, 2)), -2.4, 2.4)
    rho = family_profiles(rng, family, n)
    img, _ = SpotModel(render, r, e, refdata.GRID, rho, max_shift_px=2.4).images(t)
    ref = refdata.calibrated(rng, rho, SPEC, s)
    refimg, _ = SpotModel(render, r, e, refdata.GRID, ref, max_shift_px=0.0).images(np.zeros((n, 2)))
    img = img / img.reshape(n, -1).sum(axis=1)[:, None, None]
    counts = expose(img, np.full(n, float(photons)), rng, 0.0, 0.0, True, "float32")
    marg, refm, d = reduce(e, counts, refimg, False, W)
    ang = np.degrees(np.arctan2(np.abs(e[:, 1]), np.abs(e[:, 0])))
    diag = np.abs(ang - 45) < 22.5
    return refdata.MarginalPairs(marg, refm, (t * d).sum(axis=1, keepdims=True).astype(np.float32), r,
                                 np.full(n, float(photons))), diag


if __name__ == "__main__":
    cmd = sys.argv[1]
    if cmd == "check":          # the W = 16 projection equals bins_along_e.project
        rng = np.random.default_rng(1); n = 50
        e = refdata.any_angle(rng, n); flat = rng.uniform(0, 5, (n, 256))
        a, _ = project_wide(e, flat, 16)
        start, w, _ = bins_along_e.grid_weights(e, 16)
        print("W16 vs project:", np.abs(a - bins_along_e.project(flat, start, w)).max())
        net, _ = load_net(SHIPPED)
        from lgs_wfs_ros.learning import margtrain
        chk = margtrain.generate(1000, margtrain.CHECK_SEED, progress=False, detectors=REC.detectors, projection="grid")
        print("torch vs onnx:", np.abs(predict(net, chk, False) - margtrain.predict(SHIPPED, chk)[:, 0]).max())
    elif cmd == "train":
        finetune(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5])
    elif cmd == "scratch":
        finetune(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], lr=2e-3, seed=216, scratch=True)
    elif cmd == "scratch-diag":     # cartesian blocks within 22.5 deg of a diagonal only
        finetune(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], lr=2e-3, seed=216,
                 scratch=True, diag=True)
    elif cmd == "validate":
        n = int(sys.argv[2])
        models = [("shipped", SHIPPED, 16)] + [tuple(a.split(":")) for a in sys.argv[3:]]
        for fam in ("high", "measured", "sporadic", "broad", "narrow"):
            for ph in (1000.0, 316.0):
                line = f"{fam:9s} {ph:5.0f}:"
                for name, path, W in models:
                    W = int(W)
                    pairs, diag = validation(fam, n, ph, 5, W)
                    if path.endswith(".onnx"):
                        net, _ = load_net(path)
                    else:
                        net, _ = load_net(SHIPPED); net.load_state_dict(torch.load(path))
                    err = predict(net, pairs) - pairs.y[:, 0]
                    edge = pairs.r_m > 10
                    rms = lambda m: np.sqrt(np.mean(err[m] ** 2))
                    line += f" | {name}: diag {rms(diag):.4f} axis {rms(~diag):.4f} (r>10: {rms(diag & edge):.4f} / {rms(~diag & edge):.4f})"
                print(line, flush=True)
