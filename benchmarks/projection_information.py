"""How much of a cartesian block's information along e survives projection onto bins along e.

The column-sum networks (``ann_conv``) read a polar block's sums along e. A cartesian block
can be brought to that form by projecting each pixel onto bins along its subaperture's e:
either the whole pixel into the bin its centre falls in ("centre"), or split by the area of
the pixel that falls in each bin ("overlap", 8 x 8 sub-points a pixel). This computes, for
noise-free spots of an unseen family on random subapertures of the full cartesian pupil, the
Cramer-Rao bound along e of the projected bins over that of the whole block:

- the block: the 2 x 2 Fisher matrix of the Poisson pixels (shift along e and across it, the
  second a nuisance), bound ``[J^-1]_ee``;
- the bins: the Gaussian Fisher information ``m'^T C^-1 m'`` with ``C = W diag(mu) W^T`` (the
  bins of an overlap projection share pixels, so their covariance is not diagonal; "centre"
  bins are independent Poisson sums).

A third projection, "grid", splits no pixel: it sums whole pixels along the pixel-grid
direction nearest to e (columns, rows, diagonals or anti-diagonals; :func:`grid_sums`), the
bins then lying along that direction, up to 22.5 deg from e. Its bound is for the shift
along e with the shift across e known (across e the spot is narrow and its CoG well
measured; a shift across e moves these bins by ``sin`` of the angle between the two).

Printed: the square root of the ratio of the bounds (an error ratio), by family, projection
and bin width, over all sampled subapertures and by the angle of e from the nearest pixel
axis. Needs only numpy; about a minute a family.

    python benchmarks/projection_information.py [--families measured,high] [--subaps 300]
"""

from __future__ import annotations

import argparse

import numpy as np

from lgs_wfs_ros.optics import geometry, sodium
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

PHOTONS = 1000.0
STEP_PX = 0.01                  # finite-difference shift for the derivative images
SPAN_PX = 24.0                  # bins cover +-12 px along e (the field's diagonal is 22.6 px)
SUB = 8                         # sub-points per pixel side for the overlap weights


def block_bound(sm: SpotModel, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mu (n, p*p) counts, d mu / d s_e (n, p*p), bound along e (n,) px^2)`` of the
    whole blocks, the shift across e a nuisance."""
    n = e.shape[0]
    zero = sm.images(np.zeros((n, 2)))[0].reshape(n, -1)
    scale = PHOTONS / zero.sum(axis=1, keepdims=True)            # light inside the field

    def deriv(v):
        a = sm.images(STEP_PX * v)[0].reshape(n, -1)
        b = sm.images(-STEP_PX * v)[0].reshape(n, -1)
        return (a - b) / (2 * STEP_PX) * scale
    mu = np.maximum(zero * scale, 1e-12)
    d_e = deriv(e)
    d_p = deriv(np.stack([-e[:, 1], e[:, 0]], axis=1))
    j = np.empty((n, 2, 2))
    j[:, 0, 0] = (d_e * d_e / mu).sum(axis=1)
    j[:, 0, 1] = j[:, 1, 0] = (d_e * d_p / mu).sum(axis=1)
    j[:, 1, 1] = (d_p * d_p / mu).sum(axis=1)
    return mu, d_e, np.linalg.inv(j)[:, 0, 0]


def grid_sums(e: np.ndarray, p: int) -> np.ndarray:
    """``(nb, p*p)``: whole pixels summed along the pixel-grid direction nearest to ``e
    (2,)``, of columns (bins along x), rows, diagonals ``i + j`` or anti-diagonals ``i - j``
    (bins 1 / sqrt 2 px wide along the diagonal: 2p - 1 of them). No pixel is split: the
    sums a compiled pass makes with whole-row additions, no scatter."""
    yy, xx = np.indices((p, p))
    k = int(np.round((np.degrees(np.arctan2(e[1], e[0])) % 180) / 45)) % 4
    idx = (xx, xx + yy, yy, xx - yy + p - 1)[k].ravel()
    w = np.zeros((idx.max() + 1, p * p))
    w[idx, np.arange(p * p)] = 1.0
    return w


def weights(e: np.ndarray, p: int, width: float, how: str) -> np.ndarray:
    """``(nb, p*p)`` share of each pixel in each bin along ``e (2,)`` (``how``: "centre",
    "overlap", or "grid": :func:`grid_sums`, ``width`` unused)."""
    if how == "grid":
        return grid_sums(e, p)
    nb = int(np.ceil(SPAN_PX / width))
    c = (p - 1) / 2
    yy, xx = np.indices((p, p), dtype=float) - c
    if how == "centre":
        u = (xx * e[0] + yy * e[1]).ravel()
        b = np.floor(u / width + nb / 2).astype(int)
        w = np.zeros((nb, p * p))
        w[np.clip(b, 0, nb - 1), np.arange(p * p)] = 1.0
        return w
    sub = (np.arange(SUB) + 0.5) / SUB - 0.5
    u = ((xx[..., None, None] + sub[None, None, None, :]) * e[0]
         + (yy[..., None, None] + sub[None, None, :, None]) * e[1]).reshape(p * p, -1)
    b = np.clip(np.floor(u / width + nb / 2).astype(int), 0, nb - 1)
    w = np.zeros((nb, p * p))
    for k in range(nb):
        w[k] = (b == k).mean(axis=1)
    return w


def bins_bound(mu: np.ndarray, d_e: np.ndarray, w: np.ndarray) -> float:
    """Bound along e (px^2) of the bins ``w @ x`` of one block's pixels ``x``."""
    dm = w @ d_e
    cov = (w * mu[None, :]) @ w.T
    ok = np.diag(cov) > 1e-9
    cov, dm = cov[np.ix_(ok, ok)], dm[ok]
    return 1.0 / float(dm @ np.linalg.solve(cov + 1e-12 * np.eye(dm.size), dm))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default=",".join(sodium.FAMILIES))
    ap.add_argument("--subaps", type=int, default=300)
    a = ap.parse_args(argv)
    sensor = Sensor(detector="cartesian", photons=PHOTONS)
    lay = geometry.layout(sensor)
    rng = np.random.default_rng(3)
    idx = rng.choice(lay.n_valid, a.subaps, replace=False)
    r, e = lay.r_m[idx], lay.e[idx]
    angle = np.degrees(np.arctan2(np.abs(e[:, 1]), np.abs(e[:, 0])))
    angle = np.minimum(angle, 90.0 - angle)                      # from the nearest pixel axis
    print("| family | projection | bin (px) | all | e within 10 deg of an axis | 35-45 deg | worst |")
    print("|---|---|---|---|---|---|---|")
    for fam in a.families.split(","):
        h, d = sodium.unseen_profiles(fam, 1, 700.0, seed=2)
        sm = SpotModel(sensor, r, e, h, d[0], max_shift_px=2 * STEP_PX)
        mu, d_e, bound = block_bound(sm, e)
        for how, width in (("centre", 1.0), ("overlap", 1.0), ("overlap", 0.5), ("grid", 0.0)):
            ratio = np.sqrt(np.array([bins_bound(mu[k], d_e[k], weights(e[k], sensor.pixels, width, how))
                                      for k in range(idx.size)]) / bound)
            bin_px = f"{width:g}" if width else "1 (axes), 0.71 (diagonals)"
            print(f"| {fam} | {how} | {bin_px} | {ratio.mean():.3f} | {ratio[angle < 10].mean():.3f} | "
                  f"{ratio[angle > 35].mean():.3f} | {ratio.max():.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
