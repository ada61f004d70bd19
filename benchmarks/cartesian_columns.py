"""Experiment: ``ann_conv``'s column-sum network on cartesian pixels projected along e.

``projection_information.py`` showed that bins along e with each pixel split by its
overlap keep the block's information along e (1.00-1.006x its Cramer-Rao bound). Here each
cartesian spot of ``cartesian_filters.py``'s data (``ann_conv``'s prior at any angle) and its
reference are projected onto ``BINS`` 1 px bins along their e (8 x 8 sub-points a pixel),
and an ``ann_conv``-shaped hyper network (conv refit 16-16, 16 filters, Fisher-weighted
loss) is trained on them from scratch to read the shift along e. Validation: the
families' maps on the training block (``cartesian_filters.validation_spots``), rms error
along e over the rms Cramer-Rao bound along e of the same spots (the whole block's, its
shift across e a nuisance), beside the calibrated CoG along e.

    python benchmarks/cartesian_columns.py train DATA_DIR MODEL.pt [--epochs 40] [--chunks 0]
    python benchmarks/cartesian_columns.py validate MODEL.pt [--spots 2000]

``DATA_DIR``: ``cartesian_filters.py data DIR`` chunks. Needs torch.

Result (2026-11-26, docs/ann_ref.md "A cartesian ann_conv"): 600,000 spots, 60 epochs (9 min
on one core): 0.92-1.68x the bound along e, noisier than the calibrated CoG on narrow
profiles; the shipped polar ann_conv on the spots within 3 deg of a pixel axis scores
1.05-1.42x on the same metric (stale references, the true spot's bound). Not a model.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cartesian_filters import P, load  # noqa: E402
from lgs_wfs_ros.learning import hypertrain, refdata  # noqa: E402

BINS = 24                       # 1 px bins along e over +-12 px (the field's diagonal: 22.6)
SUB = 8                         # sub-points a pixel side for the overlap


def project(a: np.ndarray, e: np.ndarray, batch: int = 500) -> np.ndarray:
    """``(n, BINS)`` float32 sums of ``a (n, p, p)`` over 1 px bins along ``e (n, 2)`` (pixel
    axes), each pixel split by the share of its area in each bin."""
    n, p = a.shape[0], a.shape[1]
    sub = (np.arange(SUB) + 0.5) / SUB - 0.5
    yy, xx = np.indices((p, p), dtype=np.float32) - (p - 1) / 2
    shape = (p, p, SUB, SUB)
    sx = np.broadcast_to(xx[..., None, None] + sub[None, None, None, :], shape).reshape(p * p, -1)
    sy = np.broadcast_to(yy[..., None, None] + sub[None, None, :, None], shape).reshape(p * p, -1)
    out = np.empty((n, BINS), dtype=np.float32)
    for i in range(0, n, batch):
        ee = e[i:i + batch].astype(np.float32)
        u = sx[None] * ee[:, 0, None, None] + sy[None] * ee[:, 1, None, None]   # (b, p*p, S)
        b = np.clip(np.floor(u + BINS / 2).astype(np.int32), 0, BINS - 1)
        w = np.repeat(a[i:i + batch].reshape(-1, p * p, 1) / SUB ** 2, SUB * SUB, axis=2)
        rows = (np.arange(b.shape[0], dtype=np.int32)[:, None, None] * BINS + b).ravel()
        out[i:i + batch] = np.bincount(rows, w.ravel(), b.shape[0] * BINS).reshape(-1, BINS)
    return out


def pairs(d: dict) -> refdata.MarginalPairs:
    """Projected :class:`.refdata.MarginalPairs` of a ``cartesian_filters`` data dict."""
    e = np.asarray(d["e"], dtype=np.float64)
    marg = project(d["counts"], e)
    refs = project(d["refs"], e)
    refs = refs / np.maximum(refs.sum(axis=1, keepdims=True), 1e-12)
    y = (np.asarray(d["y"], np.float64) * e).sum(axis=1, keepdims=True)
    return refdata.MarginalPairs(marg, refs.astype(np.float32), y.astype(np.float32),
                                 np.asarray(d["r_m"]), np.asarray(d["photons"]))


def draw_phased(rng: np.random.Generator, n: int) -> dict:
    """``cartesian_filters.draw`` with each reference rendered at the spot's shift across e as
    the calibrated CoG reads it (``cartesian_filters.rephase``), not at zero."""
    from cartesian_filters import rephase
    from lgs_wfs_ros.sensor import Sensor
    spec, sensor = refdata.MARGINAL_SPEC, Sensor()
    render = sensor.replace(detector="cartesian")
    r = rng.uniform(*spec.radius_m, size=n)
    e = refdata.any_angle(rng, n)
    t, ref0, ph, counts, ref_rho = refdata._spots(rng, spec, sensor, r, e, profiles=True)
    ref0 = ref0 / np.maximum(ref0.sum(axis=(1, 2), keepdims=True), 1e-12)
    refs = rephase(render, r, e, ref_rho, ref0, counts)
    return {"counts": counts.astype(np.float32), "refs": refs.astype(np.float32),
            "y": t.astype(np.float32), "r_m": r, "e": e, "photons": ph}


def cache_phased(out: Path, spots: int, part: int, parts: int, chunk: int = 20000,
                 seed: int = 217) -> None:
    """Chunks ``part, part + parts, ...`` of ``spots`` phased spots (and the monitor set with
    part 0) as ``out/train_NNN.npz``."""
    import time
    out.mkdir(parents=True, exist_ok=True)
    for c in range(part, -(-spots // chunk), parts):
        f = out / f"train_{c:03d}.npz"
        if not f.exists():
            t0 = time.process_time()
            np.savez(f, **draw_phased(np.random.default_rng([seed, c]), chunk))
            print(f"{f.name}: {time.process_time() - t0:.0f} s", flush=True)
    if part == 0 and not (out / "monitor.npz").exists():
        np.savez(out / "monitor.npz", **draw_phased(np.random.default_rng([seed, 999]), 10000))


def validation(rng, n: int, family: str, photons: float, phased: bool = False,
               exact: bool = False):
    """``(pairs, crb_e (n,) px^2, cog_e (n,) px)``: projected validation spots, each block's
    Cramer-Rao bound along e (``e^T I^-1 e``, its shift across e a nuisance) and the
    calibrated CoG along e (``phased``: references at the spot's shift across e; ``exact``:
    references of the true profile)."""
    from cartesian_filters import cog, validation_spots
    d, _ = validation_spots(rng, n, family, photons, phased=phased, exact=exact)
    e = d["e"]
    crb_e = np.einsum("ni,nij,nj->n", e, np.linalg.inv(d["fisher"]), e)
    cog_e = ((cog(d["counts"]) - cog(d["refs"])) * e).sum(axis=1)   # (phased: the across part cancels)
    return pairs(d), crb_e, cog_e


def spec(epochs: int, k: int = 16, trunk: tuple = (32,), conv: tuple = (16, 16)) -> hypertrain.HyperSpec:
    return hypertrain.HyperSpec(pixels=BINS, k=k, trunk=tuple(trunk), conv=tuple(conv), kernel=5,
                                weight_power=1.0, epochs=epochs)


def main(argv=None) -> int:
    import torch
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("dir", type=Path)
    t.add_argument("out", type=Path)
    t.add_argument("--epochs", type=int, default=40)
    t.add_argument("--chunks", type=int, default=0)
    t.add_argument("--k", type=int, default=16, help="filters")
    t.add_argument("--trunk", type=int, nargs="+", default=[32])
    t.add_argument("--conv", type=int, nargs="+", default=[16, 16])
    g = sub.add_parser("data")
    g.add_argument("dir", type=Path)
    g.add_argument("--spots", type=int, default=600000)
    g.add_argument("--part", type=int, default=0)
    g.add_argument("--parts", type=int, default=1)
    v = sub.add_parser("validate")
    v.add_argument("--phased", action="store_true")
    v.add_argument("--exact", action="store_true", help="references of the true profile")
    v.add_argument("model", type=Path)
    v.add_argument("--spots", type=int, default=2000)
    a = ap.parse_args(argv)
    if a.cmd == "data":
        cache_phased(a.dir, a.spots, a.part, a.parts)
        return 0
    if a.cmd == "train":
        files = sorted(a.dir.glob("train_*.npz"))
        files = files[:a.chunks] if a.chunks else files
        data, mon = pairs(load(files)), pairs(load([a.dir / "monitor.npz"]))
        print(f"{data.y.shape[0]} spots projected", flush=True)
        net, _ = hypertrain.fit(spec(a.epochs, a.k, a.trunk, a.conv), data, mon)
        torch.save({"epochs": a.epochs, "k": a.k, "trunk": a.trunk, "conv": a.conv,
                    "state": net.state_dict()}, a.out)
        return 0
    saved = torch.load(a.model)
    net = hypertrain._torch_module(spec(saved["epochs"], saved.get("k", 16), saved.get("trunk", (32,)),
                                       saved.get("conv", (16, 16))))
    net.load_state_dict(saved["state"])
    net.eval()
    print("| family | photons | bound along e, rms (px) | calibrated CoG / bound | network / bound "
          "| network less its reading of the reference / bound |")
    print("|---|---|---|---|---|---|")
    for fi, family in enumerate(("measured", "high", "sporadic", "broad", "narrow")):
        for photons in (316, 1000):
            pr, crb_e, cog_e = validation(np.random.default_rng([557, fi, photons]), a.spots, family,
                                          photons, a.phased, a.exact)
            flat = refdata.MarginalPairs(pr.refs * pr.marg.sum(axis=1, keepdims=True), pr.refs,
                                         pr.y, pr.r_m, pr.photons)     # the noise-free reference
            with torch.no_grad():
                tt, t0 = hypertrain._tensors(pr), hypertrain._tensors(flat)
                est = net(tt[0], tt[1], tt[2]).numpy()[:, 0]
                own = net(t0[0], t0[1], t0[2]).numpy()[:, 0]
            y = pr.y[:, 0]
            b = math.sqrt(crb_e.mean())
            rms = lambda x: math.sqrt(np.mean((x - y) ** 2))
            print(f"| {family} | {photons} | {b:.4f} | {rms(cog_e) / b:.3f} | {rms(est) / b:.3f} "
                  f"| {rms(est - own) / b:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
