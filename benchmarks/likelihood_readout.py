"""Experiment: what a network can add to the likelihood's own peak (issue 15; not shipped).

``ml`` maximises, per block axis, the Poisson log-likelihood of the marginal counts against
the calibrated spot tabulated on a 1/4 px grid, then puts a parabola through the best grid
point and its neighbours. Here a small network reads the same log-likelihood around the best
grid point (five values, ``k - 2 .. k + 2``, less the value at ``k``) and is trained to
correct the parabola's sub-grid offset; if it cannot, nothing is left for a learned
read-out once the likelihood is computed, and a network that matches ``ml`` on profiles it
never saw has to compute that likelihood.

Samples (``learning/refdata.py``'s marginal prior, the one ``ann_marg`` and ``ann_hyper``
train on): profiles of the broad prior, stale node-sampled references, radius 0.3-35 m,
100-3000 photons (log-uniform), shifts N(0, 0.6 px), polar blocks; both block axes of each
spot are samples. The likelihood tables are ``ml.Tables`` of the reference profile
(extent 2.5 px), the climb starts at the calibrated CoG as ``kernels.ml_search`` does, and
samples whose climb leaves the grid are dropped (``ml`` returns the calibrated CoG there).

Read-out: features ``[d0, z-2 / c + 4 + 4 d0, z+2 / c + 4 - 4 d0, log10(c) / 2 - 1]``
(``d0`` the parabola's offset in grid steps, ``c`` the curvature: the last three are 0 for
a parabolic likelihood), tanh 4-32-32-1 whose output, initialised at 0, is added to ``d0``;
MSE on the true offset, Adam, cosine schedule.

    python benchmarks/likelihood_readout.py [--train 160000] [--test 20000] [--epochs 12]

Prints the rms error (grid steps of 0.25 px) of the parabola and of the network on the
held-out spots, overall and per axis and photon range. Needs the ``train`` extra (torch).
"""

from __future__ import annotations

import argparse

import numpy as np

from lgs_wfs_ros.centroiding.ml import Tables
from lgs_wfs_ros.learning import refdata
from lgs_wfs_ros.optics.detector import expose
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

STEP_PX, EXTENT_PX = 0.25, 2.5


class _PriorSpots:
    """``ml.Tables``' spot source for one reference profile per sample (polar blocks)."""

    def __init__(self, sensor: Sensor, r_m: np.ndarray, density: np.ndarray):
        e = np.tile([1.0, 0.0], (r_m.size, 1))
        self.model = SpotModel(sensor.replace(detector="cartesian"), r_m, e, refdata.GRID,
                               density, max_shift_px=1.0)
        self.n = r_m.size

    def image_at(self, shift: np.ndarray) -> np.ndarray:
        return self.model.images(shift)[0]


def climb(ll: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(k (m,), edge (m,))``: the hill climb of ``kernels.ml_search`` on full curves
    ``ll (m, K)`` from grid indices ``k``; ``edge`` where it ends at the grid's edge."""
    kk = ll.shape[1]
    i = np.arange(ll.shape[0])
    k = np.clip(k, 1, kk - 2)
    for _ in range(kk):
        left = ll[i, k - 1] > ll[i, k]
        right = ~left & (ll[i, k + 1] > ll[i, k])
        move = np.where(left & (k > 1), -1, np.where(right & (k < kk - 2), 1, 0))
        if not move.any():
            break
        k = k + move
    return k, (ll[i, k - 1] > ll[i, k]) | (ll[i, k + 1] > ll[i, k])


def samples(rng: np.random.Generator, n: int, sensor: Sensor = Sensor()) -> tuple:
    """``(windows (m, 5), target (m,), axis (m,), photons (m,))`` for ``n`` spots (``m`` <=
    ``2 n``): the log-likelihood at grid points ``k - 2 .. k + 2`` less its value at ``k``
    (mirrored where the grid ends) and the true shift from grid point ``k``, grid steps."""
    spec, p = refdata.MARGINAL_SPEC, sensor.pixels
    r = rng.uniform(*spec.radius_m, size=n)
    t = np.clip(rng.normal(0.0, spec.sigma_px, size=(n, 2)), -2.4, 2.4)
    rho = refdata.broad_profiles(rng, n, spec)
    img, _ = SpotModel(sensor.replace(detector="cartesian"), r, np.tile([1.0, 0.0], (n, 1)),
                       refdata.GRID, rho, max_shift_px=2.4).images(t)
    ref = refdata.calibrated(rng, rho, spec, sensor)
    ph = np.exp(rng.uniform(*np.log(spec.photons), size=n))
    counts = expose(np.clip(img, 0.0, None), ph, rng, 0.0, 0.0, True, "float32")
    tab = Tables(lambda s: _PriorSpots(s, r, ref), sensor, STEP_PX, EXTENT_PX)
    out = []
    for axis in (0, 1):
        marg = counts.sum(axis=1 if axis == 0 else 2).astype(np.float64)
        tot = marg.sum(axis=1)
        ll = np.einsum("nu,nku->nk", marg, tab.rows(axis)) - tot[:, None] * tab.norms[:, axis]
        kk = ll.shape[1]
        m = (kk - 1) // 2
        cog = marg @ (np.arange(p) - (p - 1) / 2) / np.maximum(tot, 1.0) - tab.bias[:, axis]
        k, edge = climb(ll, np.floor(cog / tab.step + 0.5).astype(int) + m)
        i = np.arange(n)
        win = np.stack([ll[i, np.clip(k + j, 0, kk - 1)] for j in range(-2, 3)], axis=1) \
            - ll[i, k][:, None]
        win[k < 2, 0] = win[k < 2, 4]
        win[k > kk - 3, 4] = win[k > kk - 3, 0]
        ok = ~edge & (tot > 0)
        out.append((win[ok], t[ok, axis] / tab.step - (k[ok] - m), np.full(ok.sum(), axis), ph[ok]))
    return tuple(np.concatenate(z) for z in zip(*out))


def features(win):
    """``(features (m, 4), d0 (m,))`` torch tensors from windows ``(m, 5)`` (see the doc)."""
    import torch
    w = torch.as_tensor(np.asarray(win), dtype=torch.float32)
    zm2, zm1, zp1, zp2 = w[:, 0], w[:, 1], w[:, 3], w[:, 4]
    den = zm1 + zp1
    c = torch.clamp(-0.5 * den, min=1e-3)
    d0 = torch.where(den < 0, 0.5 * (zm1 - zp1) / torch.where(den < 0, den, -1.0), 0.0)
    d0 = torch.clamp(d0, -0.5, 0.5)
    return torch.stack([d0, zm2 / c + 4 + 4 * d0, zp2 / c + 4 - 4 * d0,
                        torch.log10(c) / 2 - 1], 1), d0


def readout(hidden: int = 32):
    """tanh 4-h-h-1 read-out added to the parabola (its last layer starts at zero)."""
    import torch

    class Readout(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.body = torch.nn.Sequential(torch.nn.Linear(4, hidden), torch.nn.Tanh(),
                                            torch.nn.Linear(hidden, hidden), torch.nn.Tanh())
            self.out = torch.nn.Linear(hidden, 1)
            torch.nn.init.zeros_(self.out.weight)
            torch.nn.init.zeros_(self.out.bias)

        def forward(self, win):
            f, d0 = features(win)
            return d0 + self.out(self.body(f))[:, 0]
    return Readout()


def draw(n: int, seed: int, batch: int = 4000) -> tuple:
    parts = [samples(np.random.default_rng([seed, b]), min(batch, n - b * batch))
             for b in range(-(-n // batch))]
    return tuple(np.concatenate(z) for z in zip(*parts))


def main(argv=None) -> int:
    import torch
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=int, default=160_000, help="training spots")
    ap.add_argument("--test", type=int, default=20_000, help="held-out spots")
    ap.add_argument("--epochs", type=int, default=12)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    win, y, _, _ = draw(args.train, 7)
    keep = np.isfinite(win).all(axis=1) & (np.abs(y) < 3)
    x, y = torch.as_tensor(win[keep]), torch.as_tensor(y[keep], dtype=torch.float32)
    tw, ty, tax, tph = draw(args.test, 9)
    net = readout()
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.epochs)
    for _ in range(args.epochs):
        perm = torch.randperm(len(y))
        for i in range(0, len(y), 512):
            j = perm[i:i + 512]
            loss = ((net(x[j]) - y[j]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    with torch.no_grad():
        pred, d0 = net(torch.as_tensor(tw)).numpy(), features(tw)[1].numpy()
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))                       # noqa: E731
    print(f"{len(y)} training and {len(ty)} held-out axis samples; rms error, grid steps "
          f"({STEP_PX} px)")
    print(f"all: parabola {rms(d0 - ty):.4f}, network {rms(pred - ty):.4f}")
    for axis, name in ((0, "along e"), (1, "across e")):
        for lo, hi in ((100, 300), (300, 1000), (1000, 3000)):
            s = (tax == axis) & (tph >= lo) & (tph < hi)
            print(f"{name}, {lo}-{hi} photons ({s.sum()}): parabola {rms(d0[s] - ty[s]):.4f}, "
                  f"network {rms(pred[s] - ty[s]):.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
