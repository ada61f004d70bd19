"""The recipes of the shipped models: data, network, optimiser, seed (pure Python).

Each :class:`Recipe` is everything :func:`lgs_wfs_ros.learning.train.train_model` needs to
rebuild a model from scratch; its ``line()`` is printed before training and stored in the
model's ``lgs_wfs.training`` metadata.

Training positions: normal, ``SIGMA_TRAIN_PX`` = 0.6 px per axis, clipped at 4 sigma.
The turbulence of the reference instrument (r0 = 0.15 m at 500 nm, d = 0.5 m) moves a
spot by 0.45 px rms per axis (:func:`..optics.turbulence.turbulence_sigma_px`); training 30 % wider
keeps the tails (|t| ~ 1.5 px, the paper's "limited to one pixel" histogram) well covered
while still concentrating samples where turbulence puts them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass

SIGMA_TRAIN_PX = 0.6
PAPER_SIZES = (256, 16, 2)
PUPIL_SIZES = (259, 80, 64, 2)


@dataclass(frozen=True)
class Recipe:
    """How to train one model.

    Attributes:
        name: file stem in ``models/``.
        detector: "polar" | "cartesian" (single-subaperture models) | "any" (pupil).
        pupil: draw random valid subapertures of the default pupil (else the paper's
            outermost subaperture, ``Sensor.paper_single(detector)``).
        radius_m: single-subaperture models only: put the subaperture at this distance
            from the launch (default: the outermost, 14.75 m), along +x (polar) or the
            diagonal (cartesian).
        photons: training photons per subaperture (None: noise-free).
        sigma_px: training position rms per axis, px.
        sizes: layer widths (input first).
        conditioning: "none" | "e_r".
        optimizer: "adam" (recorded in the metadata; the only one).
        samples: training samples (``quick`` runs use ``quick_samples``).
        epochs, batch, lr: Adam settings (cosine-decayed learning rate).
        profile_model, mix_fraction: random-profile draw (:func:`.dataset.random_profiles`).
        r_power: pupil models: subaperture draw probability proportional to r^-r_power.
        detectors: pupil models: detector of each sample, drawn uniformly from this tuple
            (repeat an entry to weight it).
        weight_decay: AdamW decoupled weight decay (0: plain Adam).
        monitor_photons: photons of the held-out monitor set that selects the kept weights
            (default: the training photons).
        noise_penalty_photons: Adam only: add to the squared error the first-order
            expected extra squared error of photon noise at this many photons, computed from
            the noise-free training images and the network's input Jacobian (Bishop 1995,
            :func:`.train.poisson_penalty`); the training set stays noise-free. None: no
            penalty.
        loss: Adam only: "mse" (the paper's), "euclid" (per sample, the root of the
            squared Euclidean error plus the noise penalty: the validation metric).; filter
            recipes also "fisher" (the squared error times the spot's Fisher information, i.e.
            (error / Cramer-Rao bound)^2: the bright, sharp spots count as much as the rest)
        seed: data seed (training stream) and initialisation seed.
        filters: marginal recipes: reference-conditioned filters per subaperture (the
            reference sets the first layer, :mod:`.hypertrain`; ``sizes`` is then the
            per-frame trunk, filters first); 0: a plain MLP on (sums, reference's).
        hyper_conv: filter recipes: hidden channels of a convolutional network over the
            reference's pixels that sets the filters (shift-equivariant: a spot far from the
            block centre is read as one at the centre); empty: a dense tanh 64-64 network.
        bins_window: marginal recipes on cartesian spots: "centred" (each block's window of
            bins along e centred on it) or "reference" (moved to the stale reference's light,
            :data:`.refdata.WINDOWS`; tried for ``ann_conv`` on 2026-11-27 and not kept:
            docs/ann_ref.md "Windows moved to the light").
        bins_projection: marginal recipes on cartesian spots: "overlap" (each pixel split
            along e by its footprint), "grid" (whole-pixel sums along the pixel-grid
            direction nearest to e: the frame pass without a split, half the cost) or
            "span" (grid, the bins along diagonals sqrt 2 px wide: the whole block).
        shipped: part of ``models/``.
        note: one sentence for the README table.
    """

    name: str
    detector: str
    pupil: bool = False
    radius_m: float | None = None
    photons: float | None = 1000.0
    sigma_px: float = SIGMA_TRAIN_PX
    sizes: tuple = PAPER_SIZES
    conditioning: str = "none"
    optimizer: str = "adam"
    samples: int = 200_000
    quick_samples: int = 20_000
    epochs: int = 40
    batch: int = 512
    lr: float = 3e-3
    profile_model: str = "mvn"
    mix_fraction: float = 0.5
    r_power: float = 0.0
    detectors: tuple = ("polar", "cartesian")
    weight_decay: float = 0.0
    monitor_photons: float | None = None
    noise_penalty_photons: float | None = None
    loss: str = "mse"
    seed: int = 1
    filters: int = 0
    hyper_conv: tuple = ()
    bins_window: str = "centred"
    bins_projection: str = "overlap"
    shipped: bool = True
    note: str = ""

    def line(self, samples: int | None = None) -> str:
        """The one-line recipe printed by ``lgs-wfs train``."""
        if self.conditioning == "marginals":
            from .refdata import MARGINAL_SPEC as pr
            polar = set(self.detectors) == {"polar"}
            cart = ("whole-pixel sums along the pixel-grid direction nearest to e on "
                    "cartesian ones, the shift read along that direction"
                    + (", sqrt 2 px bins along diagonals)" if self.bins_projection == "span" else ")")
                    if self.bins_projection in ("grid", "span") else
                    "each pixel split by its overlap on cartesian ones" + (
                        ", the window moved to the reference's light)"
                        if self.bins_window == "reference" else ")"))
            bins = ("column sums" if polar else
                    "light in 1 px bins along e (column sums on polar pixels, " + cart)
            form = (f"MLP {'-'.join(map(str, self.sizes))} tanh on a polar spot's column sums "
                    f"(along e): (sums / total - reference's, reference's, log10 total)"
                    ) if not self.filters else (
                    f"{self.filters} filters per subaperture set by its reference's {bins} "
                    f"({self._hyper_form()}; run at each calibration refit), applied to the "
                    f"spot's {'column sums' if polar else 'bins'} / total, then tanh {'-'.join(map(str, self.sizes))} with "
                    f"log10 total")
            n = samples or self.samples
            share = "" if polar else " (" + ", ".join(
                f"{k} {d}" for d, k in self._split(n).items()) + ", e at any angle on cartesian)"
            return (f"{self.name}: {form}; {n} spots{share} of the "
                    f"{pr.describe()}; references stale (layers moved {pr.stale_shift_m:g} m rms, "
                    f"stretched {pr.stale_stretch:.0%}) and seen through the pupil "
                    f"calibration's node basis ({pr.node_noise:.0%} node noise); "
                    f"r {pr.radius_m[0]:g}-{pr.radius_m[1]:g} m, "
                    f"{pr.photons[0]:g}-{pr.photons[1]:g} photons (log-uniform), positions "
                    f"N(0, {pr.sigma_px:g} px); Adam lr {self.lr:g} cosine, batch {self.batch}, "
                    f"{self.epochs} epochs, loss {self.loss}, seed {self.seed}")
        if self.conditioning == "reference":
            from .refdata import PriorSpec
            pr = PriorSpec()
            return (f"{self.name}: MLP {'-'.join(map(str, self.sizes))} tanh on (image - reference, "
                    f"reference), both sum-normalised; {samples or self.samples} pairs of the "
                    f"{pr.describe()}; references stale and seen through the pupil calibration's "
                    f"node basis; r {pr.radius_m[0]:g}-{pr.radius_m[1]:g} m from the launch, any "
                    f"angle, polar and cartesian, {pr.photons[0]:g}-{pr.photons[1]:g} photons "
                    f"(log-uniform), positions N(0, {pr.sigma_px:g} px); Adam lr {self.lr:g} "
                    f"cosine, batch {self.batch}, {self.epochs} epochs, loss {self.loss}, seed {self.seed}")
        ph = "noise-free" if self.photons is None else f"{self.photons:g} photons"
        where = ("random valid subapertures of the default pupil (probability ~ r^-"
                 f"{self.r_power:g}), detectors {'/'.join(self.detectors)}") if self.pupil \
            else f"{self.detector} subaperture at r = {self.radius_m or 14.75:g} m"
        opt = (f"Adam{'W wd ' + format(self.weight_decay, 'g') if self.weight_decay else ''} "
               f"lr {self.lr:g} cosine, batch {self.batch}, {self.epochs} epochs"
               f"{'' if self.monitor_photons is None else f', weights kept by a {self.monitor_photons:g}-photon monitor'}")
        if self.loss != "mse":
            opt += f", loss {self.loss}"
        if self.noise_penalty_photons is not None:
            opt += (f", trained on noise-free images only: photon noise enters as its known "
                    f"first-order Poisson variance at {self.noise_penalty_photons:g} photons "
                    f"(penalty J_k Cov(x) J_k^T, Cov(x) = (G diag(x) - x x^T) / N, Bishop 1995), "
                    f"not as noisy samples")
        return (f"{self.name}: MLP {'-'.join(map(str, self.sizes))} tanh (conditioning "
                f"{self.conditioning}), {samples or self.samples} samples of random 5-Gaussian "
                f"profiles ({self.profile_model}"
                f"{f' {self.mix_fraction:g}' if self.profile_model == 'mix' else ''}), {where}, {ph}, positions N(0, {self.sigma_px:g} px), {opt}, "
                f"seed {self.seed}")

    def _split(self, n: int) -> dict:
        from .refdata import split
        return split(n, self.detectors)

    def _hyper_form(self) -> str:
        if not self.hyper_conv:
            return "a tanh 64-64 network"
        return (f"tanh convolutions {'-'.join(map(str, self.hyper_conv))}, kernel 5, over its "
                f"pixels, a gain and a bias per filter from their mean")

    def to_dict(self) -> dict:
        return asdict(self)


# The paper networks draw 10 % of their profiles with the paper's independent-normal
# statistics (layer centroid spread ~1.2 km) and 90 % from the joint normal fitted to the
# measured night (spread 82 m): enough breadth to recognise the paper's uncentred layer,
# little enough that the networks still beat CoG on the measured profiles (docs/training.md).
PAPER_PROFILES = {"profile_model": "mix", "mix_fraction": 0.1}

RECIPES = {
    "ann_1k": Recipe("ann_1k", "polar", photons=1000.0, seed=11, **PAPER_PROFILES,
                     note="paper ANN 1k: polar, outermost subaperture, 1000 photons"),
    # Noise-free images only (no noisy image in training or monitor sets); photon noise
    # enters as its known first-order variance at 1000 photons (docs/training.md).
    "ann_noiseless": Recipe("ann_noiseless", "polar", photons=None, seed=12, **PAPER_PROFILES,
                            noise_penalty_photons=1000.0, loss="euclid",
                            note="paper ANN Noiseless: polar, outermost, noise-free images; "
                                 "first-order Poisson penalty at 1000 photons"),
    "ann_diag": Recipe("ann_diag", "cartesian", photons=1000.0, seed=13, **PAPER_PROFILES,
                       note="paper ANN Diag: cartesian, outermost diagonal, 1000 photons"),
    # ann_pupil: two thirds cartesian samples (a cartesian network must cover every angle
    # of e, a polar one only e = (1, 0)), 2.4M samples and lr 1e-3: the ring-criterion
    # measurements behind these choices are in docs/training.md.
    "ann_pupil": Recipe("ann_pupil", "any", pupil=True, sizes=PUPIL_SIZES, conditioning="e_r",
                        samples=2_400_000, epochs=36, batch=512, lr=1e-3, seed=14, r_power=1.0,
                        detectors=("polar", "cartesian", "cartesian"),
                        note="one network for every valid subaperture, polar and cartesian, "
                             "conditioned on (e, r/15); 1000 photons"),
}

# The reference-reading network (learning/reftrain.py, refdata.py): reads the image and the
# subaperture's current reference from the pupil calibration, one model for every
# subaperture, launch position, detector and photon level of its domain.
RECIPES["ann_ref"] = Recipe(
    "ann_ref", "any", pupil=True, sizes=(512, 32, 32, 2), conditioning="reference",
    samples=80_000, quick_samples=8_000, epochs=40, batch=256, lr=2e-3, loss="euclid", seed=15,
    note="reads the image and its reference from the pupil calibration (image - reference, "
         "reference): every radius to 35 m, both detectors, 100-3000 photons")

# The marginal reference-reading network (learning/margtrain.py): on a polar detector a spot
# is the outer product of its marginals; one small network reads one axis' marginal and the
# reference's, for both axes of every subaperture.
RECIPES["ann_marg"] = Recipe(
    "ann_marg", "polar", pupil=True, sizes=(33, 48, 48, 1), conditioning="marginals",
    samples=800_000, quick_samples=20_000, epochs=40, batch=512, lr=2e-3, loss="mse", seed=16,
    detectors=("polar",),
    note="polar: the column sums (along e) and the reference's from the pupil calibration; "
         "every radius to 35 m, 100-3000 photons")

# The marginal network whose first layer the reference sets (learning/hypertrain.py): at
# each calibration refit a small network turns a subaperture's reference into 8 filters for
# its column sums, so the per-frame part can match the spot against its own reference.
RECIPES["ann_hyper"] = Recipe(
    "ann_hyper", "polar", pupil=True, sizes=(8, 32, 1), conditioning="marginals", filters=8,
    samples=800_000, quick_samples=20_000, epochs=40, batch=512, lr=2e-3, loss="mse", seed=16,
    detectors=("polar",),
    note="polar: 8 filters per subaperture set by its reference from the pupil calibration, "
         "applied to the column sums (along e); every radius to 35 m, 100-3000 photons")

# ann_hyper with a shift-equivariant refit network (learning/hypertrain.py): the filters come
# from convolutions over the reference's pixels, so a spot far from the block centre (a layer
# above the prior's altitudes) is read as one at the centre; the loss weights each spot by
# its Fisher information, so bright sharp spots count as much as the rest.
RECIPES["ann_conv"] = Recipe(
    "ann_conv", "any", pupil=True, sizes=(16, 32, 1), conditioning="marginals", filters=16,
    hyper_conv=(16, 16), samples=1_400_000, quick_samples=20_000, epochs=100, batch=512, lr=2e-3,
    loss="fisher", seed=16, detectors=("polar",) * 4 + ("cartesian",) * 3,
    note="both detectors: 16 filters per subaperture set by convolutions over its reference from "
         "the pupil calibration, applied to the light in 1 px bins along e (polar: the column "
         "sums; cartesian, e at any angle: each pixel split by its overlap); every radius to "
         "35 m, 100-3000 photons")

# ann_conv read through whole-pixel sums along the pixel-grid direction nearest to e on
# cartesian pixels (no pixel split: the frame pass at half the cost); polar spots as ann_conv's.
# The cartesian default since 2026-11-27 (0.87 ms a frame against 1.40, 2.44 with background)
RECIPES["ann_grid"] = dataclasses.replace(
    RECIPES["ann_conv"], name="ann_grid", bins_projection="grid",
    note="ann_conv's network and data, the cartesian spots read through whole-pixel sums along "
         "the pixel-grid direction nearest to e (columns, rows or diagonals) and the shift "
         "along that direction: the frame pass splits no pixel")

# ann_grid with the bins along diagonals sqrt 2 px wide, so that they hold the whole block:
# the 1 px bins drop a diagonal block's far corners, where a high layer at the pupil's edge
# puts light. Tried 2026-11-28 and not shipped: cartesian high layer 1.104 -> 1.106x the
# CRB, sporadic 1.084 -> 1.143x (docs/ann_ref.md "Bins that span a diagonal block")
RECIPES["ann_span"] = dataclasses.replace(
    RECIPES["ann_grid"], name="ann_span", bins_projection="span", shipped=False,
    note="ann_grid's network and data, the bins along diagonals sqrt 2 px wide (each takes a "
         "diagonal sum whole and half of each neighbour) so that the 16 bins hold the whole "
         "block; columns and rows as ann_grid")

# The paper recipes with the paper's own profile prior (independent normals per Gaussian
# parameter: layer centroid spread ~1.2 km, extent stable), for the reproduction only: they
# reproduce the paper's gain on its uncentred profile and lose to CoG on the measured sky
# (docs/training.md). Not shipped as runtime models; written to models/paper_prior/ with
# `lgs-wfs train ann_1k_paper --out models/paper_prior`.
PAPER_PRIOR = {"profile_model": "independent", "samples": 300_000, "shipped": False}
RECIPES["ann_1k_paper"] = Recipe(
    "ann_1k_paper", "polar", photons=1000.0, seed=31, **PAPER_PRIOR,
    note="the paper's ANN 1k with the paper's own profile statistics (independent normals): reproduction only")
RECIPES["ann_diag_paper"] = Recipe(
    "ann_diag_paper", "cartesian", photons=1000.0, seed=33, **PAPER_PRIOR,
    note="the paper's ANN Diag with the paper's own profile statistics (independent normals): reproduction only")

# Dedicated single-subaperture networks for the ann_pupil criterion (not shipped): the
# paper recipe with ann_pupil's profile draw (mvn) at the outermost, middle and innermost rings.
for _det in ("polar", "cartesian"):
    for _ring, _r in (("outer", None), ("mid", 8.75), ("inner", 2.25)):
        _n = f"ref_{_det}_{_ring}"
        RECIPES[_n] = Recipe(_n, _det, radius_m=_r, photons=1000.0, seed=20 + len(RECIPES),
                             shipped=False, note=f"reference: {_det}, r = {_r or 14.75} m, 1000 photons")

SHIPPED = tuple(k for k, v in RECIPES.items() if v.shipped)


def get(name: str) -> Recipe:
    """The recipe called ``name`` (``ValueError`` naming the choices otherwise)."""
    if name not in RECIPES:
        raise ValueError(f"unknown model {name!r}; choose one of {', '.join(RECIPES)}")
    return RECIPES[name]


__all__ = ["Recipe", "RECIPES", "SHIPPED", "get", "SIGMA_TRAIN_PX"]
