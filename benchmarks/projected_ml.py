"""Experiment: maximum likelihood along e on cartesian spots projected onto bins along e.

``cartesian_columns.py`` projects each cartesian block onto 1 px bins along its elongation
``e`` (pixels split by overlap) and its reference the same way. Which reference? Here the
Poisson likelihood of the projected counts (bins taken as Poisson, flux free) is maximised
over the shift along ``e`` (grid 0.05 px, parabola) against the true profile's spot
rendered at that shift and, across ``e``:

- ``zero``: no shift (what ``cartesian_columns`` trained on);
- ``true``: the spot's true shift across ``e``;
- ``cog``: the shift across ``e`` the calibrated CoG reads in the same counts.

Spots: ``marginal_validation``'s families at any angle, centre launch, shifts N(0, 0.46 px),
photons only; rms error along ``e`` over the rms Cramer-Rao bound along ``e`` of the whole
block (its shift across ``e`` a nuisance).

    python benchmarks/projected_ml.py [MODES] [FAMILIES] [--spots 1000] [--photons 1000]

Result (2026-11-26, docs/ann_ref.md "A cartesian ann_conv"): 1,000 spots a family at 1000
photons, ``zero`` / ``true`` / ``cog``: measured 1.024 / 1.021 / 1.020, high 1.621 / 1.064
/ 1.061, sporadic 1.056 / 1.020 / 1.019, broad 1.120 / 1.033 / 1.032, narrow 1.048 / 0.988 /
0.987 (each figure's standard error ~2 %). The projected bins keep the information, but only against a reference at the spot's
own shift across e; the calibrated CoG finds that shift well enough.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cartesian_columns import project  # noqa: E402
from cartesian_filters import cog, spot_fisher  # noqa: E402
from marginal_validation import PUPIL_RADIUS_M, SHIFT_RMS_PX, family_profiles  # noqa: E402
from lgs_wfs_ros.learning import refdata  # noqa: E402
from lgs_wfs_ros.optics.spots import SpotModel  # noqa: E402
from lgs_wfs_ros.sensor import Sensor  # noqa: E402

GRID = np.arange(-3.0, 3.0001, 0.05)            # px along e


def spots(rng, family: str, photons: float, n: int):
    """``(model, counts, e, v, t, crb_e)``: ``n`` cartesian spots, their Poisson counts, unit
    vectors along / across e, true shifts (px) and each block's bound along e (px^2)."""
    sensor = Sensor().replace(detector="cartesian")
    r = PUPIL_RADIUS_M * np.sqrt(rng.uniform(0.02, 1.0, size=n))
    e = refdata.any_angle(rng, n)
    v = np.stack([-e[:, 1], e[:, 0]], axis=1)
    t = np.clip(rng.normal(0.0, SHIFT_RMS_PX, size=(n, 2)), -2.3, 2.3)
    model = SpotModel(sensor, r, e, refdata.GRID, family_profiles(rng, family, n), max_shift_px=3.5)
    _, _, mu, fi = spot_fisher(model, t, photons)
    crb_e = np.einsum("ni,nij,nj->n", e, np.linalg.inv(fi), e)
    return model, rng.poisson(mu).astype(np.float32), e, v, t, crb_e


def ml_along_e(model, counts, e, across: np.ndarray) -> np.ndarray:
    """``(n,)`` px: the ML shift along e of the projected ``counts`` against the model's spots
    rendered at ``g e + across`` (``across (n, 2)``) for g on :data:`GRID`."""
    n = counts.shape[0]
    pc = project(counts, e).astype(float)
    ll = np.empty((n, GRID.size))
    for k, g in enumerate(GRID):
        m = project(model.images(g * e + across)[0].astype(np.float32), e).astype(float)
        m = np.maximum(m, 1e-9 * m.max(axis=1, keepdims=True))
        ll[:, k] = (pc * np.log(m)).sum(1) - pc.sum(1) * np.log(m.sum(1))
    k = np.clip(ll.argmax(1), 1, GRID.size - 2)
    a, b, c = (ll[np.arange(n), k + d] for d in (-1, 0, 1))
    den = a - 2 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return GRID[k] + np.clip(off, -1.0, 1.0) * (GRID[1] - GRID[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("modes", nargs="?", default="zero,true,cog")
    ap.add_argument("families", nargs="?", default="measured,high,sporadic,broad,narrow")
    ap.add_argument("--spots", type=int, default=1000)
    ap.add_argument("--photons", type=float, default=1000.0)
    a = ap.parse_args(argv)
    modes = a.modes.split(",")
    print("| family | photons | " + " | ".join(f"ML, reference across e: {m}" for m in modes) + " |")
    print("|---|---|" + "---|" * len(modes))
    for family in a.families.split(","):
        model, counts, e, v, t, crb_e = spots(np.random.default_rng([5, int(a.photons)]), family,
                                              a.photons, a.spots)
        sv = {"zero": np.zeros(len(e)), "true": (t * v).sum(1),
              "cog": ((cog(counts) - cog(model.images(np.zeros((len(e), 2)))[0])) * v).sum(1)}
        b = math.sqrt(np.mean(crb_e))
        se = (t * e).sum(1)
        vals = [math.sqrt(np.mean((ml_along_e(model, counts, e, sv[m][:, None] * v) - se) ** 2)) / b
                for m in modes]
        print(f"| {family} | {a.photons:g} | " + " | ".join(f"{x:.3f}" for x in vals) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
