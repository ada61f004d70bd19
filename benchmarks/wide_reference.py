"""Experiment: ``ann_conv``'s hyper network given the reference on a wider field (polar).

``ann_conv`` is 11 % behind ``ml`` on the high layer at 1000 photons (accuracy benchmark,
docs/ann_ref.md). What is left there is a bias on spots that sit at the field's edge. A
shift moves light across the edge. The likelihood knows how much, because ``ml``'s tables
are rendered on a field wider than the detector's. ``ann_conv`` only sees its reference
inside the field. Here the hyper network reads the reference's column sums on a field
``MARGIN`` px wider each side (unit sum inside the field, as the calibration would render
them); the filters are the middle ``p`` of its convolutions. A control with the same data,
architecture and training reads only the in-field part: the difference is the margin's
alone.

    python benchmarks/wide_reference.py data DIR [--spots 400000]
    python benchmarks/wide_reference.py train DIR OUT.pt [--epochs 40] [--control]
    python benchmarks/wide_reference.py validate WIDE.pt CONTROL.pt [--spots 2000]

``validate``: ``marginal_validation.py``'s families (the unseen maps applied to the
training block), each network's mean absolute error along e over ``ml``'s, beside the
shipped ``ann_conv``, and the mean error at r > 11 m. Needs torch. Results:
docs/ann_ref.md, "A wider reference". At 40 epochs the margin took the high layer at
1000 photons from 1.090 to 1.038x ``ml``; at 100 epochs the control caught up (1.053
against 1.050x), so the margin speeds the learning but does not move where it ends.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lgs_wfs_ros.learning import hypertrain, margtrain, refdata
from lgs_wfs_ros.optics.detector import expose
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

MARGIN = 4
P = Sensor().pixels
SPEC = refdata.MARGINAL_SPEC


def draw(rng: np.random.Generator, n: int, sensor: Sensor = Sensor()) -> dict:
    """``n`` polar spots of ``ann_conv``'s prior: ``marg (n, p)`` column sums of the counts,
    ``refw (n, p + 2 MARGIN)`` the reference's on the wider field (unit sum in the field),
    ``y (n, 1)`` the shift along e, px."""
    r = rng.uniform(*SPEC.radius_m, size=n)
    e = np.tile([1.0, 0.0], (n, 1))
    render = sensor.replace(detector="cartesian")
    t = np.clip(rng.normal(0.0, SPEC.sigma_px, size=(n, 2)), -2.4, 2.4)
    rho = refdata.broad_profiles(rng, n, SPEC)
    img, _ = SpotModel(render, r, e, refdata.GRID, rho, max_shift_px=2.4).images(t)
    ref_rho = refdata.calibrated(rng, rho, SPEC, sensor)
    wide = render.replace(pixels=P + 2 * MARGIN)
    ref, _ = SpotModel(wide, r, e, refdata.GRID, ref_rho, max_shift_px=0.0).images(np.zeros((n, 2)))
    ph = np.exp(rng.uniform(*np.log(SPEC.photons), size=n))
    counts = expose(np.clip(img, 0.0, None), ph, rng, 0.0, 0.0, True, "float32")
    refw = np.clip(ref, 0.0, None).sum(axis=1)
    refw /= np.maximum(refw[:, MARGIN:MARGIN + P].sum(axis=1, keepdims=True), 1e-12)
    return {"marg": counts.sum(axis=1).astype(np.float32), "refw": refw.astype(np.float32),
            "y": t[:, :1].astype(np.float32)}


def module(margin: int, k: int = 16, conv=(16, 16), kernel: int = 5, trunk=(32,), seed: int = 16):
    """``ann_conv``'s network (``hypertrain``'s conv form) reading a reference ``margin`` px
    wider each side; its filters are the middle ``p`` of the head convolution."""
    import torch
    from torch import nn

    class Wide(nn.Module):
        def __init__(self):
            super().__init__()
            torch.manual_seed(seed)
            self.k, self.m = k, margin
            widths = (2, *conv)
            layers = []
            for a, b in zip(widths[:-1], widths[1:]):
                layers += [nn.Conv1d(a, b, kernel, padding=kernel // 2), nn.Tanh()]
            self.hyper = nn.Sequential(*layers)
            self.head = nn.Conv1d(widths[-1], k, kernel, padding=kernel // 2)
            self.pool = nn.Linear(widths[-1], 2 * k)
            self.wn = nn.Parameter(torch.zeros(k))
            with torch.no_grad():
                self.pool.weight.mul_(0.1)
                self.pool.bias.zero_()
            self.trunk = hypertrain.tanh_mlp((k, *trunk), 1)

        def forward(self, u, rw, lf):
            pr = P * rw
            h = self.hyper(torch.stack([pr, torch.log(pr + hypertrain.EPS)], dim=1))
            g, c = self.pool(h.mean(dim=2)).split(self.k, dim=1)
            f = self.head(h)[:, :, self.m:self.m + P] * torch.exp(g).unsqueeze(2)
            z = torch.einsum("nkp,np->nk", f, P * (u - rw[:, self.m:self.m + P])) + c + self.wn * lf
            return self.trunk(torch.tanh(z))

    return Wide()


def _tensors(marg, refw, y):
    import torch
    tot = np.maximum(marg.sum(axis=1, keepdims=True, dtype=np.float64), 1.0)
    lf = (np.log10(tot) / 3.0 - margtrain.LOG_OFFSET).astype(np.float32)
    return [torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)) for a in (marg / tot, refw, lf, y)]


def predict(net, marg, refw) -> np.ndarray:
    """``(n,)`` shifts along e, px."""
    import torch
    t = _tensors(marg, refw, np.zeros((len(marg), 1)))
    with torch.no_grad():
        return torch.cat([net(t[0][a:a + 16384], t[1][a:a + 16384], t[2][a:a + 16384])
                          for a in range(0, len(marg), 16384)]).numpy()[:, 0]


def _crop(refw, margin):
    m = (refw.shape[1] - P) // 2 - margin
    return np.ascontiguousarray(refw[:, m:refw.shape[1] - m])


def fit(data: dict, monitor: dict, margin: int, epochs: int, lr: float = 2e-3, batch: int = 512,
        log=print):
    """Adam, cosine learning rate, the ``fisher`` loss of ``ann_conv``; best monitor kept."""
    import torch
    torch.set_num_threads(1)
    net = module(margin)
    refw, mon_refw = _crop(data["refw"], margin), _crop(monitor["refw"], margin)
    tr = _tensors(data["marg"], refw, data["y"])
    pairs = refdata.MarginalPairs(data["marg"], refw[:, margin:margin + P], data["y"], None, None)
    wt = hypertrain.loss_weights(pairs, 1.0)

    def loss_of(idx):
        return (wt[idx] * (net(tr[0][idx], tr[1][idx], tr[2][idx]) - tr[3][idx]) ** 2).mean()

    def monitor_err():
        return float(np.abs(predict(net, monitor["marg"], mon_refw) - monitor["y"][:, 0]).mean())

    hypertrain.adam_cosine(net, len(data["marg"]), loss_of, monitor_err, epochs, lr, batch, 16, log)
    return net


def load(path):
    import torch
    saved = torch.load(path, weights_only=False)
    net = module(saved["margin"])
    net.load_state_dict(saved["state"])
    return net.eval()


def validate(wide_path, control_path, spots: int) -> None:
    from marginal_validation import spots as val_spots
    from lgs_wfs_ros.centroiding.ann_model import resolve_model
    wide, ctl, conv = load(wide_path), load(control_path), resolve_model("ann_conv")
    print("| family | photons | ann_conv / ml | control / ml | wide / ml | mean error at r > 11 m, px: "
          "ml / ann_conv / control / wide |")
    print("|---|---|---|---|---|---|")
    for fi, fam in enumerate(("measured", "high", "sporadic", "broad", "narrow")):
        for photons in (316, 1000):
            pairs, ml, refw = val_spots(np.random.default_rng([555, fi, photons, 0]), spots, fam,
                                        photons, margin_px=MARGIN)
            y = pairs.y[:, 0]
            est = [ml, margtrain.predict(conv, pairs)[:, 0], predict(ctl, pairs.marg, pairs.refs),
                   predict(wide, pairs.marg, refw)]
            mae = [np.abs(v - y).mean() for v in est]
            big = pairs.r_m > 11
            print(f"| {fam} | {photons} | " + " | ".join(f"{v / mae[0]:.3f}" for v in mae[1:]) + " | "
                  + " / ".join(f"{np.mean((v - y)[big]):+.4f}" for v in est) + " |", flush=True)


def main(argv=None) -> int:
    from marginal_validation import experiment_cli
    ap, _, t, v = experiment_cli(__doc__, spots=400000, epochs=40)
    t.add_argument("--control", action="store_true", help="read the reference inside the field only")
    v.add_argument("wide", type=Path)
    v.add_argument("control", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "data":
        args.dir.mkdir(parents=True, exist_ok=True)
        for c in range(-(-args.spots // 20000)):
            if not (args.dir / f"train_{c:03d}.npz").exists():
                np.savez(args.dir / f"train_{c:03d}.npz", **draw(np.random.default_rng([216, c]), 20000))
        if not (args.dir / "monitor.npz").exists():
            np.savez(args.dir / "monitor.npz", **draw(np.random.default_rng([216, 999]), 10000))
    elif args.cmd == "train":
        import torch
        parts = [dict(np.load(f)) for f in sorted(args.dir.glob("train_*.npz"))]
        data = {k: np.concatenate([q[k] for q in parts]) for k in parts[0]}
        margin = 0 if args.control else MARGIN
        net = fit(data, dict(np.load(args.dir / "monitor.npz")), margin, args.epochs)
        torch.save({"margin": margin, "state": net.state_dict()}, args.out)
    else:
        validate(args.wide, args.control, args.spots)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
