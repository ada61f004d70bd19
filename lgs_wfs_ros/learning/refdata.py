"""Training pairs for the reference-reading network: (image, its current reference) -> shift.

The network is told where the spot should be: the reference is the noise-free spot of the
sodium profile the pupil calibration estimated (:mod:`..centroiding.pupil`), rendered at
zero shift for that subaperture. It measures the shift of the image from the reference,
not the profile. Samples (all in block pixel axes):

- profiles from a **broad prior** built on the training split only
  (:func:`sodium.training_model`, fitted to measured profiles 0-65): each draw is moved to
  a centroid uniform in 85-100 km and stretched to an equivalent FWHM log-uniform in 3-20
  km; a quarter get a second peak 3-10 km away, a third a sporadic thin layer (FWHM
  0.3-1.5 km, 10-50 % of the light) at 85-102 km. The unseen families of the accuracy
  benchmark and the measured test block are never used;
- geometry: distance to the launch uniform in 0.3-35 m (a centre or side launch), the
  elongation at any angle (cartesian) or along the pixel rows (polar);
- photons per subaperture log-uniform 100-3000 (Poisson), positions normal 0.6 px rms;
- the reference as the calibration produces it: the profile a moment earlier (a blend
  with a perturbed copy: layers moved by ~150 m, widths changed by ~5 %), seen through the
  calibration's thin-layer basis (the density sampled on its 120 nodes, even in 1/h, and
  piecewise linear between them, with 5 % node noise), rendered noise-free, unit light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..centroiding import bins_along_e
from ..optics import sodium
from ..optics.detector import expose
from ..optics.gaussian_spot import FWHM_PER_SIGMA
from ..optics.model_spot import altitude_nodes
from ..optics.spots import SpotModel
from ..sensor import Sensor

GRID = np.linspace(65e3, 125e3, 601)         # 100 m steps; holds 100 km centroids + 20 km widths


@dataclass(frozen=True)
class PriorSpec:
    """The broad prior and the sample ranges (defaults: the issue's)."""

    centroid_km: tuple = (85.0, 100.0)
    fwhm_km: tuple = (3.0, 20.0)
    double_fraction: float = 0.25
    sporadic_fraction: float = 0.3
    radius_m: tuple = (0.3, 35.0)
    photons: tuple = (100.0, 3000.0)
    sigma_px: float = 0.6
    polar_fraction: float = 0.5
    stale_shift_m: float = 150.0
    stale_stretch: float = 0.05
    node_noise: float = 0.05
    reference_blur_px: float = 0.0

    def describe(self) -> str:
        return (f"broad prior from measured profiles 0-65 (the training split): centroid "
                f"{self.centroid_km[0]:g}-{self.centroid_km[1]:g} km, FWHM {self.fwhm_km[0]:g}-"
                f"{self.fwhm_km[1]:g} km, {self.double_fraction:.0%} double peaks, "
                f"{self.sporadic_fraction:.0%} sporadic thin layers")


def _mass(h, rho):
    w = np.gradient(h)
    return (rho * w).sum(axis=-1)


def broad_profiles(rng: np.random.Generator, n: int, spec: PriorSpec = PriorSpec()) -> np.ndarray:
    """``(n, K)`` unit-mass densities on :data:`GRID` (per metre)."""
    h = GRID
    base_h = sodium.default_altitude_grid()
    base = np.clip(np.nan_to_num(sodium.training_model().sample(rng, n, base_h)), 0.0, None)
    w = np.gradient(base_h)
    m = (base * w).sum(axis=1, keepdims=True)
    c = (base * w * base_h).sum(axis=1, keepdims=True) / m
    sd = np.sqrt((base * w * (base_h - c) ** 2).sum(axis=1, keepdims=True) / m)
    target_c = rng.uniform(*spec.centroid_km, size=(n, 1)) * 1e3
    lo, hi = np.log(spec.fwhm_km)
    target_sd = np.exp(rng.uniform(lo, hi, size=(n, 1))) * 1e3 / FWHM_PER_SIGMA
    scale = target_sd / sd
    out = np.empty((n, h.size))
    for i in range(n):                       # 1-D interpolation per profile (n ~ 1e4 per batch)
        out[i] = np.interp(c[i, 0] + (h - target_c[i, 0]) / scale[i, 0], base_h, base[i],
                           left=0.0, right=0.0) / scale[i, 0]
    dbl = rng.random(n) < spec.double_fraction
    for i in np.flatnonzero(dbl):
        d = rng.uniform(3e3, 10e3) * rng.choice([-1.0, 1.0])
        out[i] += rng.uniform(0.3, 1.0) * np.interp(h - d, h, out[i], left=0.0, right=0.0)
    out /= _mass(h, out)[:, None]
    spo = rng.random(n) < spec.sporadic_fraction
    k = int(spo.sum())
    if k:
        frac = rng.uniform(0.1, 0.5, size=(k, 1))
        layer = np.stack([sodium.gaussian_profile(h, rng.uniform(85e3, 102e3), rng.uniform(300.0, 1500.0))
                          for _ in range(k)])
        layer /= _mass(h, layer)[:, None]
        out[spo] = (1 - frac) * out[spo] + frac * layer
    return np.clip(np.nan_to_num(out), 0.0, None)


def calibrated(rng: np.random.Generator, rho: np.ndarray, spec: PriorSpec = PriorSpec(),
               sensor: Sensor = Sensor()) -> np.ndarray:
    """``(n, K)`` the reference profiles the calibration would hold for densities ``rho``:
    slightly stale (blended with a perturbed copy) and seen through its node basis."""
    h = GRID
    n = rho.shape[0]
    shift = rng.normal(0.0, spec.stale_shift_m, size=(n, 1))
    stretch = 1.0 + rng.normal(0.0, spec.stale_stretch, size=(n, 1))
    c = (rho * h).sum(axis=1, keepdims=True) / rho.sum(axis=1, keepdims=True)
    pert = np.empty_like(rho)
    for i in range(n):
        pert[i] = np.interp(c[i, 0] + (h - c[i, 0] - shift[i, 0]) / stretch[i, 0], h, rho[i],
                            left=0.0, right=0.0)
    a = rng.uniform(0.0, 0.5, size=(n, 1))
    stale = (1 - a) * rho + a * pert
    nodes = altitude_nodes(sensor)
    at_nodes = np.stack([np.interp(nodes, h, s) for s in stale])
    at_nodes *= np.clip(1.0 + spec.node_noise * rng.normal(size=at_nodes.shape), 0.0, None)
    ref = np.stack([np.interp(h, nodes, s, left=0.0, right=0.0) for s in at_nodes])
    ref = np.clip(np.nan_to_num(ref), 0.0, None)
    return ref / np.maximum(_mass(h, ref), 1e-300)[:, None]


@dataclass
class Pairs:
    """``n`` samples, block pixel axes: ``images (n, p*p)`` float32 sum-normalised noisy
    images, ``refs (n, p*p)`` float32 unit-sum references, ``y (n, 2)`` float32 shifts (px),
    ``r_m (n,)``, ``e_pix (n, 2)``, ``photons (n,)``."""

    images: np.ndarray
    refs: np.ndarray
    y: np.ndarray
    r_m: np.ndarray
    e_pix: np.ndarray
    photons: np.ndarray


def _unit(a: np.ndarray) -> np.ndarray:
    flat = np.asarray(a, dtype=np.float64).reshape(a.shape[0], -1)
    tot = flat.sum(axis=1, keepdims=True)
    return (flat / np.where(tot > 0, tot, np.inf)).astype(np.float32)


def any_angle(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n, 2)`` unit vectors at angles uniform in 0-360 deg (one draw of ``n`` numbers)."""
    ang = rng.uniform(0.0, 2 * math.pi, size=n)
    return np.stack([np.cos(ang), np.sin(ang)], axis=1)


def pairs(rng: np.random.Generator, n: int, spec: PriorSpec = PriorSpec(),
          sensor: Sensor = Sensor()) -> Pairs:
    """Draw ``n`` training pairs (see the module doc)."""
    r = rng.uniform(*spec.radius_m, size=n)
    e = any_angle(rng, n)
    e[rng.random(n) < spec.polar_fraction] = (1.0, 0.0)
    t, ref, ph, counts = _spots(rng, spec, sensor, r, e)
    return Pairs(_unit(counts), _unit(ref), t.astype(np.float32), r, e, ph)


def _spots(rng, spec: PriorSpec, sensor: Sensor, r: np.ndarray, e: np.ndarray,
           profiles: bool = False) -> tuple:
    """The draws after the geometry (``r (n,)`` m, ``e (n, 2)`` pixel axes): ``(t (n, 2)``
    shifts px, ``ref (n, p, p)`` the stale references at zero shift, ``ph (n,)`` photons,
    ``counts (n, p, p)`` the noisy images``)``, rendered as cartesian spots along ``e``;
    with ``profiles`` a fifth item, the references' densities ``(n, K)`` on :data:`GRID`."""
    n = r.size
    render = sensor.replace(detector="cartesian")
    t = np.clip(rng.normal(0.0, spec.sigma_px, size=(n, 2)), -2.4, 2.4)
    rho = broad_profiles(rng, n, spec)
    img, _ = SpotModel(render, r, e, GRID, rho, max_shift_px=2.4).images(t)
    ref_rho = calibrated(rng, rho, spec, sensor)
    ref = _reference(rng, spec, render, r, e, ref_rho)
    ph = np.exp(rng.uniform(*np.log(spec.photons), size=n))
    counts = expose(np.clip(img, 0.0, None), ph, rng, sensor.read_noise_e, sensor.background_e,
                    True, "float32")
    out = (t, np.clip(ref, 0.0, None), ph, counts)
    return (*out, ref_rho) if profiles else out


#: Gauss-Hermite rule of three points for a normal blur: nodes in units of its rms, weights
BLUR_NODES, BLUR_WEIGHTS = np.array([0.0, math.sqrt(3.0), -math.sqrt(3.0)]), (2 / 3, 1 / 6, 1 / 6)


def _reference(rng, spec: PriorSpec, render: Sensor, r: np.ndarray, e: np.ndarray,
               ref_rho: np.ndarray) -> np.ndarray:
    """``(n, p, p)`` noise-free references at zero shift of densities ``ref_rho (n, K)``;
    with ``spec.reference_blur_px`` each also blurred along e by a normal of rms uniform in
    0 to that many px (the wider spot a calibration leaves when it takes the tilts' blur for
    less than it is, docs/ann_ref.md), by three renders (:data:`BLUR_NODES`). Those rms
    come from a stream spawned off ``rng``'s seed, so every other draw stays as without."""
    n = r.size
    if spec.reference_blur_px <= 0:
        return SpotModel(render, r, e, GRID, ref_rho, max_shift_px=0.0).images(np.zeros((n, 2)))[0]
    side = np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])
    rms = side.uniform(0.0, spec.reference_blur_px, size=n)
    model = SpotModel(render, r, e, GRID, ref_rho, max_shift_px=float(BLUR_NODES.max() * rms.max()))
    return sum(w * model.images((rms * a)[:, None] * e)[0] for a, w in zip(BLUR_NODES, BLUR_WEIGHTS))


@dataclass
class MarginalPairs:
    """``n`` spots seen along e: ``marg (n, p)`` float32 the light of a noisy image in 1 px
    bins along e (on a polar detector its column sums: Poisson counts), ``refs (n, p)``
    float32 the same bins of its reference, unit sum, ``y (n, 1)`` float32 the shift along e
    (px), ``r_m (n,)``, ``photons (n,)``."""

    marg: np.ndarray
    refs: np.ndarray
    y: np.ndarray
    r_m: np.ndarray
    photons: np.ndarray


#: the marginal network's prior: shifts N(0, 0.6 px) as every network here (with N(0, 1 px)
#: it was 0.1-0.4x the bound further on sporadic, broad and narrow spots, 0.1x closer on a
#: layer far above h_ref), references perturbed less than ann_ref's (50 m, 2 %, 2 % node
#: noise: ml, which takes the calibration's references as exact, is at 1.00-1.08x the
#: Cramer-Rao bound on unseen profiles, so they are close)
MARGINAL_SPEC = PriorSpec(stale_shift_m=50.0, stale_stretch=0.02, node_noise=0.02)


#: each detector's random stream: its batch ``k`` is drawn from ``default_rng([seed, k, *stream])``
#: (polar spots are those drawn before cartesian ones were added)
STREAMS = {"polar": (), "cartesian": (1,)}


def split(n: int, detectors=("polar",)) -> dict:
    """``{detector: spots}``: ``n`` shared among ``detectors`` as often as each is listed
    (``("polar",) * 4 + ("cartesian",) * 3``: 4 / 7 polar), in :data:`STREAMS` order."""
    dets = [d for d in STREAMS if d in detectors]
    unknown = set(detectors) - set(STREAMS)
    if unknown or not dets:
        raise ValueError(f"detectors must name {' or '.join(STREAMS)}, got {tuple(detectors)!r}")
    out = {d: n * list(detectors).count(d) // len(detectors) for d in dets}
    out[dets[0]] += n - sum(out.values())
    return out


#: where a cartesian block's window of bins along e sits (every shipped model: "centred")
WINDOWS = bins_along_e.WINDOWS


def marginal_pairs(rng: np.random.Generator, n: int, spec: PriorSpec = MARGINAL_SPEC,
                   sensor: Sensor = Sensor(), detector: str = "polar",
                   window: str = "centred", projection: str = "overlap") -> MarginalPairs:
    """Draw ``n`` spots as :class:`MarginalPairs`: the prior, geometry and noise of
    :func:`pairs` (with ``spec``), each image and reference reduced to its light in 1 px
    bins along e. ``detector`` "polar": e along block x, the bins are the column sums (a
    polar spot is the outer product of its marginals); "cartesian": e at any angle, each
    pixel split over the bins by the overlap of its footprint
    (:func:`..centroiding.bins_along_e.overlap_weights`, what the centroider reads there),
    the spot and its reference through the same window (``window``, :data:`WINDOWS`); with
    ``projection`` "grid", whole pixels summed along the pixel-grid direction ``d`` nearest
    to e instead (:func:`..centroiding.bins_along_e.grid_weights`, centred windows), the
    target then the shift along ``d``; "span" as grid with bins sqrt 2 px wide along
    diagonals, the target in those bins."""
    if window not in WINDOWS:
        raise ValueError(f"marginal_pairs: window must be one of {WINDOWS}, not {window!r}")
    if projection not in bins_along_e.PROJECTIONS:
        raise ValueError(f"marginal_pairs: projection must be one of {bins_along_e.PROJECTIONS}, "
                         f"not {projection!r}")
    if projection in bins_along_e.GRID_PROJECTIONS and window != "centred":
        raise ValueError(f"marginal_pairs: {projection} bins are read through centred windows")
    r = rng.uniform(*spec.radius_m, size=n)
    if detector == "polar":
        e = np.tile([1.0, 0.0], (n, 1))
    elif detector == "cartesian":
        e = any_angle(rng, n)
    else:
        raise ValueError(f"marginal_pairs: detector must be polar or cartesian, not {detector!r}")
    t, ref, ph, counts = _spots(rng, spec, sensor, r, e)
    along = e
    if detector == "polar":
        marg, refm = counts.sum(axis=1), ref.sum(axis=1)
    elif projection in bins_along_e.GRID_PROJECTIONS:
        start, w, along = bins_along_e.grid_weights(e, sensor.pixels, span=projection == "span")
        start, _, w = bins_along_e.quantised(start, w)          # as the frame pass splits
        marg = bins_along_e.project(counts.reshape(n, -1), start, w)
        refm = bins_along_e.project(ref.reshape(n, -1), start, w)
    else:
        start, w = bins_along_e.overlap_weights(e, sensor.pixels)
        if window == "reference":
            start = bins_along_e.moved(start, bins_along_e.window_offsets(ref.reshape(n, -1), e))
        marg = bins_along_e.project(counts.reshape(n, -1), start, w)
        refm = bins_along_e.project(ref.reshape(n, -1), start, w)
    tot = refm.sum(axis=1, keepdims=True)
    return MarginalPairs(np.asarray(marg, dtype=np.float32),
                         (refm / np.where(tot > 0, tot, np.inf)).astype(np.float32),
                         (t * along).sum(axis=1, keepdims=True).astype(np.float32), r, ph)


__all__ = ["PriorSpec", "broad_profiles", "calibrated", "pairs", "Pairs", "marginal_pairs",
           "MarginalPairs", "MARGINAL_SPEC", "GRID", "STREAMS", "WINDOWS", "split", "any_angle"]
