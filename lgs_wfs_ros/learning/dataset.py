"""Training and validation samples for the neural-network centroiders (pure numpy).

A sample is one subaperture image with a random sodium profile (the 5-Gaussian model of
:mod:`lgs_wfs_ros.optics.sodium`, or given profiles) at a random position drawn from a
normal distribution (the paper's training draw), rendered by
:class:`lgs_wfs_ros.optics.spots.SpotModel` and exposed by
:func:`lgs_wfs_ros.optics.detector.expose` (the simulator's own image model, so the
network learns exactly what the simulator and the ROS pipeline produce).

Everything is expressed in the block's pixel axes ("local" frame of the model metadata):
on a polar detector the block is sampled in its local frame (x along the elongation), so
its pixel-axes elongation vector is ``(1, 0)``; on a cartesian detector it is the
subaperture's ``e``. A polar image is therefore the cartesian image of ``e = (1, 0)`` at
the same ``r``, which is how the full-pupil data mixes both detectors: every sample is
rendered on a cartesian copy of the sensor with its pixel-axes ``e``.

Network inputs: ``x = image / image.sum() * input_gain`` ``(n, p*p)`` float32 and, for
conditioned models, ``c = (ex, ey, r_m / R_SCALE_M)`` ``(n, 3)`` (pixel axes). Targets:
the true displacement in pixel axes, pixels, ``(n, 2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..optics import geometry, sodium
from ..optics.detector import expose
from ..optics.spots import SpotModel
from ..sensor import Sensor

R_SCALE_M = 15.0          # conditioning r is r_m / 15 (0..1 over a 30 m pupil)
SIGMA_CLIP = 4.0          # positions are clipped at this many sigma (and 3.5 px)
MAX_SHIFT_PX = 3.5


def training_altitude_grid() -> np.ndarray:
    """Grid random training profiles are drawn on: 75-115 km every 50 m, ``(801,)``.

    Half the density of :func:`sodium.default_altitude_grid` (25 m), which halves the
    cost of drawing and binning a profile; one step is 0.04 px at r = 15 m and the
    narrowest model Gaussian (c = 200 m, sigma 141 m) still spans ~6 steps, and the
    renderer integrates the piecewise-linear density exactly.
    """
    return np.linspace(75e3, 115e3, 801)


@dataclass(frozen=True)
class DataSpec:
    """What samples to draw.

    Attributes:
        sensor: the training sensor. A single-subaperture sensor (``Sensor.paper_single``)
            gives that subaperture's ``r`` and ``e``; a full-pupil sensor with
            ``pupil=True`` draws a random valid subaperture per sample.
        photons: expected photons per subaperture, or None for noise-free images.
        sigma_px: rms per axis of the normal random positions, pixels.
        pupil: draw subapertures over the valid pupil (full-pupil model).
        detectors: detector types drawn in pupil mode (equal odds); single mode uses
            ``sensor.detector``.
        conditioning: "none" or "e_r" (the ``(ex, ey, r/15)`` second input).
        photons_range: optional ``(lo, hi)``: photons drawn log-uniform per sample instead
            of the fixed ``photons``.
        profile_model: how random profiles are drawn from the fitted statistics (see
            :func:`random_profiles`): "mvn" (joint normal of the fit parameters: the
            measured night's narrow spread, layer centroid 90.33 +- 0.08 km), "independent"
            (the paper's independent normal per parameter: centroid spread ~1.2 km) or
            "mix" (a fraction ``mix_fraction`` independent, the rest mvn). Default "mvn".
        mix_fraction: share of "independent" draws in "mix".
        r_power: pupil mode: a subaperture is drawn with probability proportional to
            ``r ** -r_power`` (0: every valid subaperture equally; 1: uniform in r, the
            inner rings as often as the outer ones).
    """

    sensor: Sensor
    photons: float | None = 1000.0
    sigma_px: float = 0.6
    pupil: bool = False
    detectors: tuple = ("polar", "cartesian")
    conditioning: str = "none"
    photons_range: tuple | None = None
    profile_model: str = "mvn"
    mix_fraction: float = 0.5
    r_power: float = 0.0

    def __post_init__(self):
        if self.profile_model not in PROFILE_MODELS:
            raise ValueError(f"profile_model must be one of {PROFILE_MODELS}, got {self.profile_model!r}")
        if not isinstance(self.sensor, Sensor):
            raise ValueError("sensor must be a Sensor")
        if self.photons is not None and not (math.isfinite(self.photons) and self.photons > 0):
            raise ValueError(f"photons must be > 0 or None (noise-free), got {self.photons!r}")
        if not (math.isfinite(self.sigma_px) and self.sigma_px >= 0):
            raise ValueError(f"sigma_px must be finite and >= 0, got {self.sigma_px!r}")
        if self.conditioning not in ("none", "e_r"):
            raise ValueError(f"conditioning must be 'none' or 'e_r', got {self.conditioning!r}")
        if self.pupil and self.sensor.is_single:
            raise ValueError("pupil=True needs a full-pupil sensor (not single_subaperture)")
        if not self.pupil and not self.sensor.is_single:
            raise ValueError("a single-subaperture model needs Sensor.paper_single(...) "
                             "(or pupil=True for a full-pupil sensor)")
        bad = set(self.detectors) - {"polar", "cartesian"}
        if not self.detectors or bad:
            raise ValueError(f"detectors must be a non-empty subset of polar/cartesian, got {self.detectors}")
        if self.photons_range is not None:
            lo, hi = self.photons_range
            if not (0 < lo <= hi):
                raise ValueError(f"photons_range must be (lo, hi) with 0 < lo <= hi, got {self.photons_range}")
        object.__setattr__(self, "detectors", tuple(self.detectors))

    @property
    def cond_width(self) -> int:
        return 3 if self.conditioning == "e_r" else 0

    def to_dict(self) -> dict:
        return {"sensor": self.sensor.to_dict(), "photons": self.photons,
                "sigma_px": self.sigma_px, "pupil": self.pupil,
                "detectors": list(self.detectors), "conditioning": self.conditioning,
                "photons_range": None if self.photons_range is None else list(self.photons_range),
                "profile_model": self.profile_model, "mix_fraction": self.mix_fraction,
                "r_power": self.r_power}

    def replace(self, **changes) -> "DataSpec":
        return replace(self, **changes)


@dataclass(frozen=True, eq=False)
class Samples:
    """A batch of samples (arrays of length ``n`` on the first axis).

    Attributes:
        images: ``(n, p, p)`` float32 counts (or noise-free photon-normalised images).
        x: ``(n, p*p)`` float32 network pixel input (sum-normalised times ``input_gain``).
        cond: ``(n, 3)`` float32 conditioning ``(ex, ey, r/15)`` in pixel axes (always
            filled; used only by conditioned models).
        y: ``(n, 2)`` float32 true displacement, pixels, block pixel axes.
        r_m: ``(n,)`` subaperture distance from the launch, m.
        e_pix: ``(n, 2)`` elongation unit vector, pixel axes.
    """

    images: np.ndarray
    x: np.ndarray
    cond: np.ndarray
    y: np.ndarray
    r_m: np.ndarray
    e_pix: np.ndarray

    def __len__(self) -> int:
        return int(self.y.shape[0])


# Measured profiles held out for validation: the test block of the one split of the
# measured night (sodium.measured_split: contiguous, so time-correlated neighbours are not
# split across sets).
MEASURED_VALIDATION = tuple(int(i) for i in sodium.measured_split("test"))


def measured_split(n_profiles: int = 88) -> tuple[np.ndarray, np.ndarray]:
    """``(train_idx, validation_idx)`` of the measured profiles (:func:`sodium.measured_split`)."""
    return sodium.measured_split("train", n_profiles), sodium.measured_split("test", n_profiles)


PROFILE_MODELS = ("mvn", "independent", "mix")


def random_profiles(rng: np.random.Generator, n: int, altitude_m, how: str = "mvn",
                    fraction: float = 0.5) -> np.ndarray:
    """``(n, K)`` random training profiles.

    The measured set is one night's 88 consecutive profiles whose density centroid moves
    by only 82 m rms; the joint-normal ("mvn") draw reproduces that, so a network trained
    on it alone learns a tight prior on the layer altitude and fails on any layer that
    sits elsewhere (the paper's uncentred case is 9 sigma away). The paper's own draw
    (independent normals per Gaussian parameter) spreads the centroid over ~1.2 km.
    "mix" draws each profile from "independent" with probability ``fraction``, else "mvn".
    """
    m = _model()
    if how == "mvn":
        return m.sample(rng, n, altitude_m)
    if how == "independent":
        return m.with_method("independent").sample(rng, n, altitude_m)
    if how != "mix":
        raise ValueError(f"unknown profile model {how!r}")
    pick = rng.random(n) < fraction
    out = m.sample(rng, n, altitude_m)
    k = int(pick.sum())
    if k:
        out[pick] = m.with_method("independent").sample(rng, k, altitude_m)
    return out


def _model():
    """The random-profile model of the training sets: :func:`sodium.training_model`, the
    fitted statistics of the training split only, so no test profile informs training."""
    return sodium.training_model()


def normalise(images: np.ndarray, input_gain: float = 1.0) -> np.ndarray:
    """``(n, p, p)`` images -> ``(n, p*p)`` float32, each divided by its total (x gain).

    A non-positive total gives a zero row (no light: nothing to measure).
    """
    flat = np.asarray(images, dtype=np.float64).reshape(len(images), -1)
    tot = flat.sum(axis=1, keepdims=True)
    safe = np.where(tot > 0, tot, np.inf)
    return (flat * (input_gain / safe)).astype(np.float32)


def subaperture_geometry(spec: DataSpec, rng: np.random.Generator, n: int):
    """``(r_m (n,), e_pix (n, 2))`` of the samples' subapertures (pixel axes)."""
    lay = geometry.layout(spec.sensor)
    if not spec.pupil:
        r = np.full(n, lay.r_m[0])
        e = lay.e[0] if spec.sensor.detector == "cartesian" else np.array([1.0, 0.0])
        return r, np.tile(e, (n, 1))
    if spec.r_power:
        w = np.asarray(lay.r_m) ** -spec.r_power
        idx = rng.choice(lay.n_valid, size=n, p=w / w.sum())
    else:
        idx = rng.integers(0, lay.n_valid, size=n)
    polar = rng.integers(0, len(spec.detectors), size=n)
    polar = np.array([d == "polar" for d in spec.detectors])[polar]
    r = np.asarray(lay.r_m)[idx]
    e = np.array(lay.e)[idx]
    e[polar] = (1.0, 0.0)
    return r, e


def sample(spec: DataSpec, rng: np.random.Generator, n: int, *, density=None, altitude_m=None,
           shift_px=None, input_gain: float = 1.0, r_m=None, e_pix=None) -> Samples:
    """Draw ``n`` samples.

    Args:
        spec: what to draw.
        rng: ``numpy.random.Generator`` (advanced); the same state gives the same samples.
        n: number of samples (>= 1).
        density: optional ``(K,)`` fixed profile or ``(n, K)`` profiles (default: random
            5-Gaussian profiles from :func:`sodium.load_model`).
        altitude_m: ``(K,)`` grid of ``density`` (default :func:`training_altitude_grid`).
        shift_px: optional ``(n, 2)`` positions (pixel axes) instead of the normal draw.
        input_gain: multiplies the sum-normalised pixel input.
        r_m, e_pix: optional ``(n,)`` / ``(n, 2)`` subaperture geometry (pixel axes)
            instead of the spec's draw.

    Returns:
        :class:`Samples`.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator")
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    n = int(n)
    h = training_altitude_grid() if altitude_m is None else np.asarray(altitude_m, float)
    if r_m is None or e_pix is None:
        r, e = subaperture_geometry(spec, rng, n)
    else:
        r, e = np.asarray(r_m, float).reshape(n), np.asarray(e_pix, float).reshape(n, 2)
    if shift_px is None:
        smax = min(MAX_SHIFT_PX, SIGMA_CLIP * spec.sigma_px) if spec.sigma_px > 0 else 0.0
        t = np.clip(rng.normal(0.0, spec.sigma_px, size=(n, 2)), -smax, smax)
    else:
        t = np.asarray(shift_px, dtype=float).reshape(n, 2)
        smax = float(np.abs(t).max())
    rho = random_profiles(rng, n, h, spec.profile_model, spec.mix_fraction) if density is None \
        else np.asarray(density, dtype=float)
    render = spec.sensor.replace(detector="cartesian")
    spots = SpotModel(render, r, e, h, rho, max_shift_px=smax)
    img, _ = spots.images(t)
    # the renderer's second-order sharpening can leave -1e-6-level negatives in far pixels
    img = np.clip(img, 0.0, None)
    if spec.photons_range is not None:
        lo, hi = spec.photons_range
        ph = np.exp(rng.uniform(math.log(lo), math.log(hi), size=n))
    else:
        ph = spec.photons
    if ph is None:
        counts = img.astype(np.float32)
    else:
        counts = expose(img, ph, rng, spec.sensor.read_noise_e, spec.sensor.background_e,
                        True, "float32")
    cond = np.concatenate([e, (r / R_SCALE_M)[:, None]], axis=1).astype(np.float32)
    return Samples(counts, normalise(counts, input_gain), cond, t.astype(np.float32), r, e)


def stream(spec: DataSpec, total: int, batch: int = 8192, seed: int = 0, *, progress: bool = True,
           input_gain: float = 1.0, desc: str = "samples"):
    """Yield :class:`Samples` batches until ``total`` samples, with a tqdm progress bar.

    Batch ``k`` uses ``numpy.random.default_rng([seed, k])``, so a stream is reproducible
    and any batch can be regenerated alone.
    """
    from tqdm.auto import tqdm

    if total < 1 or batch < 1:
        raise ValueError("total and batch must be >= 1")
    with tqdm(total=total, desc=desc, unit="spot", disable=not progress, mininterval=2.0) as bar:
        done, k = 0, 0
        while done < total:
            m = min(batch, total - done)
            yield sample(spec, np.random.default_rng([seed, k]), m, input_gain=input_gain)
            done += m
            k += 1
            bar.update(m)


def generate(spec: DataSpec, total: int, batch: int = 8192, seed: int = 0, *,
             progress: bool = True, input_gain: float = 1.0) -> dict:
    """Materialise a stream: ``{"x", "cond", "y", "r_m"}`` arrays of length ``total``."""
    parts = list(stream(spec, total, batch, seed, progress=progress, input_gain=input_gain))
    return {"x": np.concatenate([s.x for s in parts]),
            "cond": np.concatenate([s.cond for s in parts]),
            "y": np.concatenate([s.y for s in parts]),
            "r_m": np.concatenate([s.r_m for s in parts])}


__all__ = ["DataSpec", "Samples", "sample", "stream", "generate", "normalise",
           "subaperture_geometry", "R_SCALE_M"]
