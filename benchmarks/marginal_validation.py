"""Validation families for the marginal networks: ``ml`` against networks along e (polar).

How ``ann_conv`` was chosen among its variants without looking at the accuracy benchmark's
test profiles. The benchmark's unseen families (``sodium.unseen_sequence``) map the measured
night's *test* block (profiles 66-87): moved to 100-105 km ("high"), given a sporadic thin
layer, stretched 2-2.5x ("broad") or squeezed to 0.15-0.25x ("narrow"). Here the same maps
are applied to the *training* block (profiles 0-65), one random profile per spot, so a
variant can be judged on families its prior leaves out without touching the test block.

Each spot: a polar block at ``r = 15 sqrt(U)`` m from a centre launch (the pupil's spread of
radii), a shift N(0, 0.46 px) along e (the benchmark's AR(1) rms), the image normalised to
its light inside the field and exposed to Poisson noise at 316 or 1000 photons (as the
benchmark does); the reference is the profile as the calibration gives it
(``refdata.calibrated``: stale by 50 m, 2 % stretch, node noise). ``ml`` here is the
likelihood on its 1/4 px grid with the climb and parabola of ``kernels.ml_search``, against
the same reference (``likelihood_readout``'s tables).

    python benchmarks/marginal_validation.py [--spots 4000] [--bias] MODEL [MODEL ...]

Prints, per family and photon level, the mean absolute error along e (px) of ``ml`` and of
each model, and each model's ratio to ``ml``. With ``--bias`` each model is run as the
centroider's ``bias: pupil`` runs it: less its reading of the noise-free reference at the
spot's flux. Needs no torch.
"""

from __future__ import annotations

import argparse

import numpy as np

from likelihood_readout import EXTENT_PX, STEP_PX, _PriorSpots, climb
from lgs_wfs_ros.centroiding.ml import Tables
from lgs_wfs_ros.learning import margtrain, refdata
from lgs_wfs_ros.optics import sodium
from lgs_wfs_ros.optics.detector import expose
from lgs_wfs_ros.optics.spots import SpotModel
from lgs_wfs_ros.sensor import Sensor

GRID = refdata.GRID
SHIFT_RMS_PX = 0.46                      # bench_accuracy.AR1_RMS_PX
PUPIL_RADIUS_M = 15.0


def family_profiles(rng: np.random.Generator, family: str, n: int) -> np.ndarray:
    """``(n, GRID.size)`` densities: training-block profiles under ``family``'s map
    (``sodium.family_map``, the maps of ``sodium.unseen_sequence``, drawn per spot)."""
    h_m, prof = sodium.load_measured()
    train = prof[sodium.measured_split("train", prof.shape[0])]
    out = np.zeros((n, GRID.size))
    for j, src in enumerate(train[rng.integers(0, train.shape[0], n)]):
        c0 = float(np.sum(h_m * src) / np.sum(src))
        scale, target, sporadic = sodium.family_map(family, rng, c0)
        out[j] = np.interp(c0 + (GRID - target) / scale, h_m, src, left=0.0, right=0.0) / scale
        if sporadic is not None:
            frac, centre, fwhm = sporadic
            layer = sodium.gaussian_profile(GRID, centre, fwhm)
            out[j] += layer * out[j].sum() * frac / (1 - frac) / layer.sum()
    return out


def spots(rng: np.random.Generator, n: int, family: str, photons: float,
          sensor: Sensor = Sensor(), margin_px: int = 0) -> tuple:
    """``(pairs, ml (n,), wide)``: ``n`` noisy spots of ``family`` as marginal pairs (the
    networks' input), ``ml``'s estimate along e, px, and with ``margin_px`` > 0 the
    references' column sums on a field that much wider each side (``(n, p + 2 margin)``,
    unit sum inside the field; else None)."""
    p = sensor.pixels
    render = sensor.replace(detector="cartesian")
    r = PUPIL_RADIUS_M * np.sqrt(rng.uniform(0.02, 1.0, size=n))
    e = np.tile([1.0, 0.0], (n, 1))
    t = np.clip(rng.normal(0.0, SHIFT_RMS_PX, size=(n, 2)), -2.4, 2.4)
    rho = family_profiles(rng, family, n)
    img, _ = SpotModel(render, r, e, GRID, rho, max_shift_px=2.4).images(t)
    ref = refdata.calibrated(rng, rho, refdata.MARGINAL_SPEC, sensor)
    refimg, _ = SpotModel(render, r, e, GRID, ref, max_shift_px=0.0).images(np.zeros((n, 2)))
    img = img / img.reshape(n, -1).sum(axis=1)[:, None, None]         # light inside the field
    counts = expose(img, np.full(n, float(photons)), rng, 0.0, 0.0, True, "float32")
    marg = counts.sum(axis=1).astype(np.float64)
    tot = marg.sum(axis=1)
    tab = Tables(lambda s: _PriorSpots(s, r, ref), sensor, STEP_PX, EXTENT_PX)
    ll = np.einsum("nu,nku->nk", marg, tab.rows(0)) - tot[:, None] * tab.norms[:, 0]
    kk = ll.shape[1]
    m = (kk - 1) // 2
    cog = marg @ (np.arange(p) - (p - 1) / 2) / np.maximum(tot, 1.0) - tab.bias[:, 0]
    k, edge = climb(ll, np.floor(cog / tab.step + 0.5).astype(int) + m)
    i = np.arange(n)
    zm, z0, zp = ll[i, k - 1], ll[i, k], ll[i, k + 1]
    den = zm + zp - 2 * z0
    off = np.where(den < 0, 0.5 * (zm - zp) / np.where(den < 0, den, -1.0), 0.0)
    ml = np.where(edge, cog, (k - m + np.clip(off, -0.5, 0.5)) * tab.step)
    refm = refimg.sum(axis=1)
    refm = refm / refm.sum(axis=1, keepdims=True)
    pairs = refdata.MarginalPairs(marg.astype(np.float32), refm.astype(np.float32),
                                  t[:, :1].astype(np.float32), r, np.full(n, float(photons)))
    wide = None
    if margin_px:
        big = render.replace(pixels=p + 2 * margin_px)
        w, _ = SpotModel(big, r, e, GRID, ref, max_shift_px=0.0).images(np.zeros((n, 2)))
        w = w.sum(axis=1)
        wide = (w / w[:, margin_px:margin_px + p].sum(axis=1, keepdims=True)).astype(np.float32)
    return pairs, ml, wide


def experiment_cli(doc: str, spots: int, epochs: int) -> tuple:
    """``(parser, data, train, validate)`` of an experiment script's three subcommands:
    ``data DIR [--spots]`` (cache training spots), ``train DIR OUT [--epochs]`` and
    ``validate [--spots 2000]`` (on these validation families); each script adds the rest."""
    from pathlib import Path
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    data = sub.add_parser("data")
    data.add_argument("dir", type=Path)
    data.add_argument("--spots", type=int, default=spots)
    train = sub.add_parser("train")
    train.add_argument("dir", type=Path)
    train.add_argument("out", type=Path)
    train.add_argument("--epochs", type=int, default=epochs)
    validate = sub.add_parser("validate")
    validate.add_argument("--spots", type=int, default=2000)
    return ap, data, train, validate


def shift(path, pairs: refdata.MarginalPairs, bias: bool = False) -> np.ndarray:
    """``(n,)`` a marginal model's shifts along e, px; with ``bias`` less its reading of each
    noise-free reference at the spot's total (the centroider's ``bias: pupil``)."""
    out = margtrain.predict(path, pairs)[:, 0]
    if bias:
        clean = refdata.MarginalPairs(pairs.refs * pairs.marg.sum(axis=1, keepdims=True),
                                      pairs.refs, pairs.y, pairs.r_m, pairs.photons)
        out = out - margtrain.predict(path, clean)[:, 0]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", help="marginal models (paths or names in models/)")
    ap.add_argument("--spots", type=int, default=4000, help="spots per family and photon level")
    ap.add_argument("--bias", action="store_true", help="each model less its reading of the "
                    "noise-free reference at the spot's flux (ann's bias: pupil)")
    a = ap.parse_args(argv)
    from lgs_wfs_ros.centroiding.ann_model import resolve_model
    paths = [resolve_model(m) for m in a.models]
    print("| family | photons | ml (px) | " + " | ".join(p.stem for p in paths) + " | "
          + " | ".join(f"{p.stem} / ml" for p in paths) + " |")
    print("|---|---|---|" + "---|" * (2 * len(paths)))
    for fi, family in enumerate(("measured", "high", "sporadic", "broad", "narrow")):
        for photons in (316, 1000):
            parts = [spots(np.random.default_rng([555, fi, photons, b]), 1000, family, photons)
                     for b in range(-(-a.spots // 1000))]
            pairs = refdata.MarginalPairs(*[np.concatenate([getattr(q[0], f) for q in parts])
                                            for f in ("marg", "refs", "y", "r_m", "photons")])
            ml = np.concatenate([q[1] for q in parts])
            y = pairs.y[:, 0]
            errs = [float(np.abs(ml - y).mean())] + [
                float(np.abs(shift(p, pairs, a.bias) - y).mean()) for p in paths]
            print(f"| {family} | {photons} | " + " | ".join(f"{v:.4f}" for v in errs) + " | "
                  + " | ".join(f"{v / errs[0]:.3f}" for v in errs[1:]) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
