"""Experiment: reference-set 2-D filters for a cartesian detector (``ann_conv`` in 2-D).

On a cartesian detector the spot lies along ``e`` at any angle and is not separable in the
pixel axes, so ``ann_conv``'s column sums do not apply (marginals projected on ``e`` lost
1.3-2.8x against the same spots on polar pixels with the polar network: the pixel footprint
and the shift across ``e`` leak into them). Here the filters are 2-D: at each calibration
refit a convolutional hyper network maps the subaperture's reference image ``r`` (16 x 16,
unit sum) to ``K`` filters ``F (K, 16, 16)``, a gain and a bias each; per frame::

    z_k = exp(g_k) sum_ij F_kij p^2 (u_ij - r_ij) + c_k + w_k lf,   u = counts / N
    (dx, dy) = tanh MLP (tanh z)                                      (px, pixel axes)

(the hyper network: tanh 2-D convolutions over ``[p^2 r, log(p^2 r + EPS)]``, zero padded,
so a reference moved by whole pixels gives the same filters moved with it). Loss: the error
weighted by the spot's 2 x 2 Fisher matrix from its reference, ``err^T I err`` (the 2-D
``fisher`` loss of ``ann_conv``). Per frame the cost is K products of 256 pixels a block:
measured 0.36 / 0.64 ms a full frame for K = 4 / 8 with int16 filters in one numba pass.

    python benchmarks/cartesian_filters.py data DIR [--spots 240000]
    python benchmarks/cartesian_filters.py train DIR MODEL.pt [--k 8 --epochs 30]
    python benchmarks/cartesian_filters.py validate MODEL.pt [...] [--spots 2000]

``validate`` scores on the validation families of ``marginal_validation.py`` (the unseen
families' maps applied to the measured night's *training* block), cartesian spots at any
angle from a centre launch: rms 2-D error over the rms Cramer-Rao bound of the same spots
(from the noise-free spot's exact derivatives), beside the calibrated CoG (CoG minus the
reference's CoG). Needs torch.

Result (2026-11-26, docs/ann_ref.md "A cartesian ann_conv"): K = 8, 8-8 channels, 200,000
spots, 20 epochs (~15 min), with or without ``--residual`` (the output added to the
calibrated CoG): 1.03-2.95x the bound, noisier than the calibrated CoG it starts from on
measured and narrow profiles (across e 0.020-0.022 px rms where the CoG has 0.018); 60 epochs
gained 1-11 % (1.01-2.47x). Not a
model: ``ann_conv`` needed 80 million spot-steps on polar pixels, this had 4 million at
about 5x the cost a step.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from lgs_wfs_ros.learning import hypertrain, margtrain, refdata
from lgs_wfs_ros.optics.detector import expose
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

EPS = 0.02
P = Sensor().pixels


# -- data ------------------------------------------------------------------------------------
def draw(rng: np.random.Generator, n: int, spec=refdata.MARGINAL_SPEC, sensor: Sensor = Sensor()) -> dict:
    """``n`` cartesian spots of ``ann_conv``'s prior at any angle: ``counts (n, p, p)``,
    ``refs (n, p, p)`` unit sum, ``y (n, 2)`` px, ``r_m``, ``e (n, 2)``, ``photons``."""
    r = rng.uniform(*spec.radius_m, size=n)
    e = refdata.any_angle(rng, n)
    t, ref, ph, counts = refdata._spots(rng, spec, sensor, r, e)
    ref = ref / np.maximum(ref.sum(axis=(1, 2), keepdims=True), 1e-12)
    return {"counts": counts.astype(np.float32), "refs": ref.astype(np.float32),
            "y": t.astype(np.float32), "r_m": r, "e": e, "photons": ph}


def cache(out: Path, spots: int, chunk: int = 20000, seed: int = 216) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for c in range(-(-spots // chunk)):
        f = out / f"train_{c:03d}.npz"
        if not f.exists():
            t0 = time.process_time()
            np.savez(f, **draw(np.random.default_rng([seed, c]), chunk))
            print(f"{f.name}: {time.process_time() - t0:.0f} s", flush=True)
    f = out / "monitor.npz"
    if not f.exists():
        np.savez(f, **draw(np.random.default_rng([seed, 999]), 10000))


def load(paths) -> dict:
    parts = [dict(np.load(p)) for p in paths]
    return {k: np.concatenate([q[k] for q in parts]) for k in parts[0]}


def fisher2(counts_total: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """``(n, 2, 2)`` Fisher matrix of a shift, px^-2: ``N sum grad r grad r^T / r`` from the
    unit-sum reference (central differences, 1e-4 floor)."""
    r = np.asarray(refs, np.float64)
    gy, gx = np.gradient(r, axis=(1, 2))
    w = 1.0 / (r + 1e-4)
    i = np.empty((r.shape[0], 2, 2))
    i[:, 0, 0] = (gx * gx * w).sum(axis=(1, 2))
    i[:, 1, 1] = (gy * gy * w).sum(axis=(1, 2))
    i[:, 0, 1] = i[:, 1, 0] = (gx * gy * w).sum(axis=(1, 2))
    return counts_total[:, None, None] * i


# -- model -----------------------------------------------------------------------------------
def module(k: int = 8, channels=(8, 8), kernel: int = 5, trunk=(32,), seed: int = 16,
           residual: bool = False):
    """The torch network; ``residual``: its output is added to the calibrated CoG (the CoG of
    ``u`` minus the reference's), so it starts as that estimator and learns the correction."""
    import torch
    from torch import nn

    class Filters2D(nn.Module):
        def __init__(self):
            super().__init__()
            torch.manual_seed(seed)
            self.k = k
            widths = (2, *channels)
            layers = []
            for a, b in zip(widths[:-1], widths[1:]):
                layers += [nn.Conv2d(a, b, kernel, padding=kernel // 2), nn.Tanh()]
            self.hyper = nn.Sequential(*layers)
            self.head = nn.Conv2d(widths[-1], k, 3, padding=1)
            self.pool = nn.Linear(widths[-1], 2 * k)
            self.wn = nn.Parameter(torch.zeros(k))
            with torch.no_grad():
                self.head.weight.mul_(0.5)
                self.pool.weight.mul_(0.1)
                self.pool.bias.zero_()
            self.trunk = hypertrain.tanh_mlp((k, *trunk), 2)
            self.residual = residual
            c = torch.arange(P, dtype=torch.float32) - (P - 1) / 2
            self.register_buffer("xy", torch.stack([c.repeat(P), c.repeat_interleave(P)]).reshape(2, P, P),
                                 persistent=False)
            if residual:
                with torch.no_grad():
                    self.trunk[-1].weight.mul_(0.1)
                    self.trunk[-1].bias.zero_()

        def filters(self, r):
            pr = (P * P) * r
            h = self.hyper(torch.stack([pr, torch.log(pr + EPS)], dim=1))
            g, c = self.pool(h.mean(dim=(2, 3))).split(self.k, dim=1)
            return self.head(h) * torch.exp(g)[:, :, None, None], c

        def forward(self, u, r, lf):
            f, c = self.filters(r)
            z = torch.einsum("nkij,nij->nk", f, (P * P) * (u - r)) + c + self.wn * lf
            out = self.trunk(torch.tanh(z))
            if self.residual:
                out = out + torch.einsum("aij,nij->na", self.xy, u - r)
            return out

    net = Filters2D()
    net.config = {"k": k, "channels": list(channels), "kernel": kernel, "trunk": list(trunk),
                  "residual": residual}
    return net


def load_net(path):
    import torch
    saved = torch.load(path, weights_only=False)
    net = module(**saved["config"])
    net.load_state_dict(saved["state"])
    return net.eval()


def tensors(d: dict):
    import torch
    tot = np.maximum(d["counts"].sum(axis=(1, 2), dtype=np.float64), 1.0)
    u = (d["counts"] / tot[:, None, None]).astype(np.float32)
    lf = (np.log10(tot) / 3.0 - margtrain.LOG_OFFSET).astype(np.float32)[:, None]
    return [torch.from_numpy(a) for a in (u, np.ascontiguousarray(d["refs"]), lf, d["y"])], tot


def predict(net, d: dict) -> np.ndarray:
    import torch
    t, _ = tensors(d)
    with torch.no_grad():
        return torch.cat([net(t[0][a:a + 8192], t[1][a:a + 8192], t[2][a:a + 8192])
                          for a in range(0, t[0].shape[0], 8192)]).numpy()


def fit(data: dict, monitor: dict, k: int, epochs: int, lr: float = 2e-3, batch: int = 512,
        channels=(8, 8), kernel: int = 5, residual: bool = False, log=print):
    import torch
    torch.set_num_threads(1)
    net = module(k, channels, kernel, residual=residual)
    tr, tot = tensors(data)
    fi = fisher2(tot, data["refs"])
    fi = torch.from_numpy((fi / np.trace(fi, axis1=1, axis2=2).mean()).astype(np.float32))

    def loss_of(idx):
        err = net(tr[0][idx], tr[1][idx], tr[2][idx]) - tr[3][idx]
        return torch.einsum("ni,nij,nj->n", err, fi[idx], err).mean()

    def monitor_err():
        return float(np.abs(predict(net, monitor) - monitor["y"]).sum(axis=1).mean())

    hypertrain.adam_cosine(net, tr[0].shape[0], loss_of, monitor_err, epochs, lr, batch, 16, log)
    return net


# -- export ----------------------------------------------------------------------------------
def build_onnx(net, domain: dict, training: dict | None = None):
    """The ONNX graph of a :func:`module` (the contract of ``hypertrain.build_model`` with a
    cartesian block): inputs ``image (batch, p*p)`` raw counts and ``reference (batch, p*p)``
    unit sum; ``filters (batch, K, p*p)`` acting on ``image / safe`` and ``fbias (batch, K)``
    from the reference alone; ``zc`` the first layer before the log-flux term, ``safe =
    max(sum image, 1)``; output ``shift (batch, 2)`` px, block (= detector) axes."""
    cfg = net.config
    k, pp, kern = cfg["k"], P * P, cfg["kernel"]
    st = {n_: v.detach().cpu().numpy().astype(np.float64) for n_, v in net.state_dict().items()}
    gb = hypertrain.Graph()
    init, node, inits, nodes = gb.init, gb.node, gb.inits, gb.nodes

    pr = node("Mul", ["reference", init([pp], "c_pp")], ["pr"])                       # (n, pp)
    img4 = init([-1, 1, P, P], "shp4", np.int64)
    x0 = node("Concat", [node("Reshape", [pr, img4], ["pr4"]),
                         node("Reshape", [node("Log", [node("Add", [pr, init([EPS], "c_eps")], ["pre"])],
                                               ["lpr"]), img4], ["lpr4"])], ["x0"], axis=1)
    h, pad = x0, kern // 2
    for i, m in enumerate([m for m in net.hyper if hasattr(m, "weight")]):
        h = node("Tanh", [node("Conv", [h, init(st[f"hyper.{2 * i}.weight"], f"cw{i}"),
                                        init(st[f"hyper.{2 * i}.bias"], f"cb{i}")], [f"cz{i}"],
                               pads=[pad] * 4)], [f"ch{i}"])
    raw = node("Conv", [h, init(st["head.weight"], "headw"), init(st["head.bias"], "headb")], ["Fraw"],
               pads=[1] * 4)
    pooled = node("ReduceMean", [h], ["hmean"], axes=[2, 3], keepdims=0)
    gc = node("Add", [node("MatMul", [pooled, init(st["pool.weight"].T, "poolw")], ["gcm"]),
                      init(st["pool.bias"], "poolb")], ["gc"])
    ax1 = init([1], "ax1", np.int64)
    g = node("Slice", [gc, init([0], "s0", np.int64), init([k], "sk", np.int64), ax1], ["g"])
    c = node("Slice", [gc, "sk", init([2 * k], "s2k", np.int64), ax1], ["cd"])
    f4 = node("Mul", [raw, node("Reshape", [node("Exp", [g], ["expg"]), init([-1, k, 1, 1], "shpg", np.int64)],
                                ["expg4"])], ["F4"])
    fu = node("Mul", [node("Reshape", [f4, init([-1, k, pp], "shpk", np.int64)], ["F"]), init([pp], "c_pp2")],
              ["Fu"])                                                                # acting on u
    ax2 = init([2], "ax2", np.int64)
    fr = node("Squeeze", [node("MatMul", [fu, node("Unsqueeze", ["reference", ax2], ["r3"])], ["fr3"]), ax2], ["fr"])
    wn = st["wn"]
    fb = node("Sub", [node("Add", [c, init(-0.8 * wn, "c_wn")], ["c2"]), fr], ["fb"])
    res = bool(cfg.get("residual"))
    if res:                 # two more rows: the pixels' x and y, bias minus the reference's CoG
        cc = np.arange(P) - (P - 1) / 2
        xy = np.stack([np.tile(cc, P), np.repeat(cc, P)])
        zero3 = node("Mul", [node("Slice", [fu, init([0], "z0s", np.int64), init([2], "z2s", np.int64), ax1],
                                  ["fu2"]), init([0.0], "c_0")], ["zero3"])       # (n, 2, pp) zeros
        fu = node("Concat", [fu, node("Add", [zero3, init(xy[None], "XY")], ["xy3"])], ["Fres"], axis=1)
        fb = node("Concat", [fb, node("MatMul", ["reference", init(-xy.T, "mXYt")], ["mcog"])], ["fbres"], axis=1)
        wn = np.concatenate([wn, [0.0, 0.0]])
    node("Identity", [fu], ["filters"])
    node("Identity", [fb], ["fbias"])
    tot = node("Max", [node("ReduceSum", ["image", ax1], ["total"], keepdims=1), init([1.0], "one")], ["safe"])
    u = node("Div", ["image", tot], ["unit"])
    z = node("Add", [node("Einsum", ["filters", u], ["zu"], equation="nkp,np->nk"), "fbias"], ["zc"])
    logn = node("Log", [tot], ["logn"])
    z = node("Add", [z, node("Mul", [logn, init((wn / (3 * math.log(10.0))).reshape(1, -1), "wN")], ["wnl"])],
             ["z0"])
    if res:
        zk = node("Slice", [z, init([0], "q0", np.int64), init([k], "qk", np.int64), ax1], ["zk"])
        cogd = node("Slice", [z, init([k], "qk0", np.int64), init([k + 2], "qk2", np.int64), ax1], ["cogd"])
        z = zk
    hh = node("Tanh", [z], ["t0"])
    idx = [i for i, m in enumerate(net.trunk) if hasattr(m, "weight")]
    for n_, i in enumerate(idx):
        last = n_ == len(idx) - 1
        zz = node("Add", [node("MatMul", [hh, init(st[f"trunk.{i}.weight"].T, f"tw{n_}")], [f"tm{n_}"]),
                          init(st[f"trunk.{i}.bias"], f"tb{n_}")],
                  ["trunk_out" if last and res else "shift" if last else f"tz{n_}"])
        if not last:
            hh = node("Tanh", [zz], [f"th{n_}"])
    if res:
        node("Add", ["trunk_out", cogd], ["shift"])
    meta = {"lgs_wfs.domain": domain}
    if training is not None:
        meta["lgs_wfs.training"] = training
    return hypertrain.package(nodes, inits, "ann_cart", "image", P, 2, "cartesian", meta)


# -- validation ------------------------------------------------------------------------------
def spot_fisher(model, t: np.ndarray, photons: float) -> tuple:
    """``(img, tot, mu, fisher)`` of ``model``'s spots at shifts ``t (n, 2)`` px: the images,
    their light in the field, the expected counts at ``photons`` in the field and the
    ``(n, 2, 2)`` Fisher matrix of a shift (central differences of renders, 0.02 px; the flux
    held fixed, a small under-estimate of the bound)."""
    img, _ = model.images(t)
    tot = img.sum(axis=(1, 2))
    h = 0.02
    grads = [(model.images(t + h * d)[0] - model.images(t - h * d)[0]) / (2 * h)
             for d in (np.array([1.0, 0.0]), np.array([0.0, 1.0]))]
    mu = photons * img / tot[:, None, None]
    gr = [photons * g_ / tot[:, None, None] for g_ in grads]
    w = 1.0 / np.maximum(mu, 1e-9)
    fi = np.array([[(gr[a] * gr[b] * w).sum(axis=(1, 2)) for b in range(2)] for a in range(2)])
    return img, tot, mu, np.moveaxis(fi, 2, 0)


def validation_spots(rng: np.random.Generator, n: int, family: str, photons: float,
                     sensor: Sensor = Sensor(), phased: bool = False,
                     exact: bool = False) -> tuple[dict, np.ndarray]:
    """``(spots, crb (n,))``: cartesian spots of a validation family (the training block under
    the family's map), any angle, centre launch, shifts N(0, 0.46 px), the image normalised to
    its light in the field, and each spot's 2-D Cramer-Rao bound (trace of I^-1), px^2.
    ``phased``: each reference is rendered at the spot's shift across e as the calibrated CoG
    reads it (:func:`phase_shift`) instead of at zero; ``exact``: references of the true
    profile instead of the calibration's stale estimate (``refdata.calibrated``)."""
    from marginal_validation import PUPIL_RADIUS_M, SHIFT_RMS_PX, family_profiles
    render = sensor.replace(detector="cartesian")
    r = PUPIL_RADIUS_M * np.sqrt(rng.uniform(0.02, 1.0, size=n))
    e = refdata.any_angle(rng, n)
    t = np.clip(rng.normal(0.0, SHIFT_RMS_PX, size=(n, 2)), -2.3, 2.3)
    rho = family_profiles(rng, family, n)
    model = SpotModel(render, r, e, refdata.GRID, rho, max_shift_px=2.4)
    img, tot, mu, fi = spot_fisher(model, t, photons)
    crb = np.trace(np.linalg.inv(fi), axis1=1, axis2=2)
    ref_rho = rho if exact else refdata.calibrated(rng, rho, refdata.MARGINAL_SPEC, sensor)
    ref, _ = SpotModel(render, r, e, refdata.GRID, ref_rho, max_shift_px=0.0).images(np.zeros((n, 2)))
    ref = ref / ref.sum(axis=(1, 2), keepdims=True)
    counts = expose(img / tot[:, None, None], np.full(n, float(photons)), rng, 0.0, 0.0, True, "float32")
    if phased:
        ref = rephase(render, r, e, ref_rho, ref, counts)
    return {"counts": counts.astype(np.float32), "refs": ref.astype(np.float32),
            "y": t.astype(np.float32), "r_m": r, "e": e, "photons": np.full(n, float(photons)),
            "fisher": fi}, crb


def phase_shift(counts: np.ndarray, refs: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``(n, 2)`` px: the spot's shift across ``e`` as the calibrated CoG reads it (the CoG
    of ``counts`` less that of the zero-shift ``refs``, projected on the normal of ``e``),
    as a 2-D shift."""
    v = np.stack([-e[:, 1], e[:, 0]], axis=1)
    sv = np.clip(((cog(counts) - cog(refs)) * v).sum(axis=1), -2.4, 2.4)
    return sv[:, None] * v


def rephase(render, r, e, ref_rho, refs, counts) -> np.ndarray:
    """``(n, p, p)`` unit-sum references of profiles ``ref_rho`` rendered at the shift across
    e the calibrated CoG reads in ``counts`` (:func:`phase_shift`)."""
    s = phase_shift(counts, refs, e)
    out, _ = SpotModel(render, r, e, refdata.GRID, ref_rho, max_shift_px=2.5).images(s)
    out = np.clip(out, 0.0, None)
    return out / np.maximum(out.sum(axis=(1, 2), keepdims=True), 1e-12)


def cog(a: np.ndarray) -> np.ndarray:
    c = np.arange(P) - (P - 1) / 2
    s = np.maximum(a.sum(axis=(1, 2)), 1e-12)
    return np.stack([(a.sum(axis=1) * c).sum(axis=1) / s, (a.sum(axis=2) * c).sum(axis=1) / s], 1)


def validate(paths, spots: int) -> None:
    import torch
    nets = [load_net(p) for p in paths]
    print("| family | photons | CRB rms (px) | calibrated CoG / CRB | "
          + " | ".join(f"{Path(p).stem} / CRB" for p in paths) + " |")
    print("|---|---|---|---|" + "---|" * len(paths))
    for fi, family in enumerate(("measured", "high", "sporadic", "broad", "narrow")):
        for photons in (316, 1000):
            d, crb = validation_spots(np.random.default_rng([556, fi, photons]), spots, family, photons)
            bound = math.sqrt(crb.mean())
            rms = lambda est: math.sqrt(((est - d["y"]) ** 2).sum(axis=1).mean())
            vals = [rms(cog(d["counts"]) - cog(d["refs"]))] + [rms(predict(n_, d)) for n_ in nets]
            print(f"| {family} | {photons} | {bound:.4f} | "
                  + " | ".join(f"{v / bound:.3f}" for v in vals) + " |", flush=True)


def main(argv=None) -> int:
    from marginal_validation import experiment_cli
    ap, _, t, v = experiment_cli(__doc__, spots=240000, epochs=30)
    t.add_argument("--k", type=int, default=8)
    t.add_argument("--chunks", type=int, default=0, help="train chunks to use (0: all)")
    t.add_argument("--channels", type=int, nargs="+", default=[8, 8])
    t.add_argument("--kernel", type=int, default=5)
    t.add_argument("--residual", action="store_true", help="the output adds to the calibrated CoG")
    v.add_argument("models", type=Path, nargs="+")
    args = ap.parse_args(argv)
    if args.cmd == "data":
        cache(args.dir, args.spots)
    elif args.cmd == "train":
        import torch
        files = sorted(args.dir.glob("train_*.npz"))
        files = files[:args.chunks] if args.chunks else files
        net = fit(load(files), load([args.dir / "monitor.npz"]), args.k, args.epochs,
                  channels=tuple(args.channels), kernel=args.kernel, residual=args.residual)
        torch.save({"config": net.config, "state": net.state_dict()}, args.out)
    else:
        validate(args.models, args.spots)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
