"""The Shack-Hartmann frame simulator: frames and their ground truth, reproducibly.

A :class:`Simulator` joins the pieces of :mod:`lgs_wfs_ros.optics`: a sodium profile
(:mod:`.sodium`), true spot displacements (:mod:`.turbulence`, frozen flow), noise-free
spots (:mod:`.spots`) and the detector (:mod:`.detector`), for the full pupil or the
one-subaperture sensor of the paper's figures (``Sensor.paper_single``, 16 x 16 frames).

Every frame carries its truth: ``(n_valid, 2)`` true displacements ``t`` in pixels,
detector axes (the image position of ``h_ref``, conventions section 3). Polar-detector
blocks are sampled in their local frame; the truth stays in detector axes.

Random streams: one ``SeedSequence(seed)`` is split into independent streams for the
turbulence, the profiles and the detector noise, so that switching noise off does not
change the turbulence, and the same seed gives the same frames bit for bit.

:func:`subaperture_batch` makes many single-subaperture images with random profiles and
random positions in one vectorised call (neural-network training sets).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field

import numpy as np

from ..sensor import Sensor
from . import fast_frames, sodium
from .detector import UINT16_MAX, expose
from .geometry import layout, stack_to_frame
from .knot_models import KnotModels
from .spots import SpotModel

PROFILE_SOURCES = ("centred", "uncentred", "measured", "evolving", "random", "gaussian",
                   "explicit")


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate besides the sensor (all JSON-able through :meth:`to_dict`).

    Attributes:
        profile: ``"centred"``/``"uncentred"`` (the paper's fixed cases; "centred" has its harmonic-mean altitude at h_ref so the light's CoG is unbiased, the paper's ideal case; on
            :func:`sodium.default_altitude_grid`), ``"measured"`` (row ``measured_index``
            of :func:`sodium.load_measured`), ``"evolving"`` (the measured sequence
            interpolated in time at the frame rate, ``seconds_per_profile`` apart),
            ``"random"`` (a :class:`sodium.SodiumModel` draw, renewed every
            ``random_every`` frames), ``"gaussian"`` (one layer at ``gaussian_centre_m``,
            FWHM ``gaussian_fwhm_m``) or ``"explicit"`` (``altitude_m``/``density`` given).
        turbulence: frozen-flow displacements (True) or a fixed shift (False).
        fixed_shift_px: ``(sx, sy)`` pixels, the displacement of every spot when
            ``turbulence`` is False.
        noise: photon (and read/background, from the sensor) noise; False gives the
            expected counts (use ``dtype="float32"`` on the sensor to keep them exact).
        seed: int >= 0.
        subtract_background: subtract the expected background from the counts.
        per_field: ``sensor.photons`` counts the photons detected inside the 16 x 16
            field (default, docs/conventions.md section 1, the paper's "total detected
            photons"); False: photons of the whole spot, truncated light lost.
    """

    profile: str = "uncentred"
    measured_index: int = 0
    seconds_per_profile: float = 1.0
    random_every: int = 1
    gaussian_centre_m: float = 90_000.0
    gaussian_fwhm_m: float = 10_000.0
    altitude_m: tuple | None = None
    density: tuple | None = None
    turbulence: bool = True
    fixed_shift_px: tuple = (0.0, 0.0)
    noise: bool = True
    seed: int = 0
    subtract_background: bool = True
    per_field: bool = True

    def __post_init__(self):
        if self.altitude_m is not None:
            object.__setattr__(self, "altitude_m", tuple(float(v) for v in self.altitude_m))
        if self.density is not None:
            object.__setattr__(self, "density", tuple(float(v) for v in self.density))
        object.__setattr__(self, "fixed_shift_px", tuple(float(v) for v in self.fixed_shift_px))
        p = []
        if self.profile not in PROFILE_SOURCES:
            p.append(f"profile must be one of {PROFILE_SOURCES}, got {self.profile!r}")
        if self.profile == "explicit" and (self.altitude_m is None or self.density is None
                                           or len(self.altitude_m) != len(self.density)):
            p.append("profile='explicit' needs altitude_m and density of the same length")
        if not (isinstance(self.seed, (int, np.integer)) and self.seed >= 0):
            p.append(f"seed must be an integer >= 0, got {self.seed!r}")
        if not (isinstance(self.random_every, (int, np.integer)) and self.random_every >= 1):
            p.append(f"random_every must be an integer >= 1, got {self.random_every!r}")
        if not (isinstance(self.measured_index, (int, np.integer)) and self.measured_index >= 0):
            p.append(f"measured_index must be an integer >= 0, got {self.measured_index!r}")
        if not self.seconds_per_profile > 0:
            p.append("seconds_per_profile must be > 0")
        if len(self.fixed_shift_px) != 2 or not all(math.isfinite(v) for v in self.fixed_shift_px):
            p.append("fixed_shift_px must be two finite numbers (pixels)")
        if p:
            raise ValueError("invalid simulation config: " + "; ".join(p))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("altitude_m", "density", "fixed_shift_px"):
            if d[k] is not None:
                d[k] = list(d[k])
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "SimulationConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def replace(self, **changes) -> "SimulationConfig":
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class Frame:
    """One simulated frame.

    Attributes:
        frame: ``(H, W)`` counts, ``sensor.dtype`` (uint16 or float32).
        truth: ``(n_valid, 2)`` true displacements (x, y), pixels, detector axes.
        index: frame number from 0.  time_s: ``index / frame_rate_hz``.
        truncated: ``(n_valid,)`` fraction of each spot's light outside its field.
        profile: ``(K,)`` density used (on ``altitude_m``).
        altitude_m: ``(K,)`` altitude grid of ``profile``.
        saturated: pixels clipped at 65535 (uint16).
    """

    frame: np.ndarray
    truth: np.ndarray
    index: int
    time_s: float
    truncated: np.ndarray
    profile: np.ndarray
    altitude_m: np.ndarray
    saturated: int = 0


def _largest_shift(truth) -> float:
    """The largest ``|shift|`` per axis of ``(n, 2)`` true displacements (px)."""
    return float(np.abs(truth).max()) if truth.size else 0.0


def _shift_margin(need: float) -> float:
    """A spot model's ``max_shift_px`` for shifts up to ``need`` px: >= 3 px, 1 px spare."""
    return max(3.0, math.ceil(need) + 1.0)


class Simulator:
    """Frames and truths for a sensor and a :class:`SimulationConfig`.

    Args:
        sensor: the sensor (full pupil or single subaperture).
        config: what to simulate (default :class:`SimulationConfig`()).
        sodium_model: the random-profile model for ``profile="random"`` (default
            :func:`sodium.load_model`, loaded when first needed).
        displacements: optional source of the true displacements when
            ``config.turbulence`` is on: any object with ``tilts_at(index) -> (n_valid, 2)``
            pixels (default a :class:`turbulence.FrozenFlow` seeded from ``config.seed``).
        fast: the compiled path for live graphs (:mod:`.fast_frames`): the same spots
            evaluated from per-profile tables (to < 2e-6 of the light), exact Poisson draws
            from another sampler (the same distribution, other draws; the same seed still
            gives the same frames), written straight into ``next(out=)``. Fused when the
            sensor has no read noise and no background, else ``expose(fast=True)``.
        threads: threads that render one frame on the fused path (>= 1): the frame is the
            same for any number (:class:`fast_frames.FastRenderer`); 2 halves the render's
            wall time on two free cores, at the same CPU a frame.
    """

    def __init__(self, sensor: Sensor, config: SimulationConfig | None = None, sodium_model=None,
                 displacements=None, fast: bool = False, threads: int = 1):
        if not isinstance(sensor, Sensor):
            raise ValueError(f"sensor must be a Sensor, got {type(sensor).__name__}")
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
            raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
        self.threads = int(threads)
        self.sensor = sensor
        self.config = config if config is not None else SimulationConfig()
        if not isinstance(self.config, SimulationConfig):
            raise ValueError("config must be a SimulationConfig")
        self.layout = layout(sensor)
        self.fast = bool(fast)
        ss = np.random.SeedSequence(self.config.seed)
        turb_ss, prof_ss, noise_ss = ss.spawn(3)
        self._noise_rng = np.random.default_rng(noise_ss)
        self._profile_ss = prof_ss
        self._turb_seed = turb_ss
        self._turb = displacements
        self._model = sodium_model
        self._evolving = None
        self._spots = None
        self._spots_key = None
        self._batch_model = None
        self._random_epoch = None
        self.index = 0
        self._renderer = None
        if self.fast and fast_frames.AVAILABLE and sensor.read_noise_e == 0 \
                and sensor.background_e == 0:
            self._renderer = fast_frames.FastRenderer(self.layout, self.threads)
            self._knots = KnotModels(self._build_knot)
            self._margin = 3.0
        self.altitude_m, self._static = self._profile_setup()
        for a in (self.altitude_m, self._static):          # shared by every Frame: read-only
            if a is not None:
                a.setflags(write=False)

    def close(self) -> None:
        """Stop the fused path's helper threads (the knot builder, the render helpers)."""
        if self._renderer is not None:
            self._knots.close()
            self._renderer.close()

    # -- profiles -----------------------------------------------------------------------
    def _profile_setup(self):
        c, h_ref = self.config, self.sensor.h_ref_m
        if c.profile == "explicit":
            return np.array(c.altitude_m), np.array(c.density)
        if c.profile in ("measured", "evolving"):
            h, prof = sodium.load_measured()
            if c.profile == "evolving":
                self._evolving = sodium.EvolvingProfile(h, prof, c.seconds_per_profile)
                return h, None
            if c.measured_index >= prof.shape[0]:
                raise ValueError(f"measured_index {c.measured_index} >= {prof.shape[0]} profiles")
            return h, prof[c.measured_index]
        h = sodium.default_altitude_grid()
        if c.profile in ("centred", "uncentred"):
            return h, sodium.paper_profile(c.profile, h, h_ref, self.sensor.pixel_scale_arcsec)
        if c.profile == "gaussian":
            return h, sodium.gaussian_profile(h, c.gaussian_centre_m, c.gaussian_fwhm_m)
        return h, None                                                  # random

    def model(self):
        """The random-profile model (loaded on first use)."""
        if self._model is None:
            self._model = sodium.load_model()
        return self._model

    def profile_at(self, index: int) -> tuple[np.ndarray, object]:
        """``(density (K,), key)`` for frame ``index``; ``key`` changes when it does.

        A function of ``index`` alone (whatever was asked before): a random profile is drawn
        from a stream of its own per epoch of ``random_every`` frames (was one stream drawn
        in call order, so asking for an earlier frame gave another profile)."""
        c = self.config
        if self._static is not None:
            return self._static, "static"
        if c.profile == "evolving":
            t = index / self.sensor.frame_rate_hz
            return self._evolving.at(t), ("evolving", index)
        epoch = index // c.random_every
        if self._random_epoch != epoch:
            self._random_profile = self._random_draw(epoch)
            self._random_epoch = epoch
        return self._random_profile, ("random", epoch)

    def _random_draw(self, epoch: int) -> np.ndarray:
        """The random profile of ``epoch`` (its own seeded stream: a pure function)."""
        ss = self._profile_ss
        rng = np.random.default_rng(np.random.SeedSequence(
            ss.entropy, spawn_key=tuple(ss.spawn_key) + (int(epoch),)))
        density = self.model().sample(rng, 1, self.altitude_m)[0]
        density.setflags(write=False)
        return density

    # -- displacements -------------------------------------------------------------------
    def truth_at(self, index: int) -> np.ndarray:
        """``(n_valid, 2)`` true displacements of frame ``index`` (pixels, detector axes)."""
        if not self.config.turbulence:
            return np.broadcast_to(np.array(self.config.fixed_shift_px), (self.layout.n_valid, 2)).copy()
        if self._turb is None:
            from .turbulence import FrozenFlow
            self._turb = FrozenFlow(self.sensor, self._turb_seed)
        return self._turb.tilts_at(index)

    # -- frames --------------------------------------------------------------------------
    def spots(self, density, key, truth) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free ``(n_valid, p, p)`` images and truncation (model cached per profile)."""
        return self.spot_model(density, key, truth).images(truth)

    def spot_model(self, density, key, truth) -> SpotModel:
        """The profile's :class:`SpotModel` (rebuilt when the profile changes or a shift
        exceeds its margin)."""
        need = _largest_shift(truth)
        if self._spots is None or key != self._spots_key or need > self._spots.max_shift_px:
            margin = _shift_margin(need)
            lay = self.layout
            self._spots = SpotModel(self.sensor, lay.r_m, lay.e, self.altitude_m, density, margin)
            self._spots_key = key
        return self._spots

    def _knot_margin(self, truth) -> float:
        """Shift margin of the fast path's knot models (px): grows, never shrinks, so the
        two blended knots always share it."""
        need = _largest_shift(truth)
        if need > self._margin:
            self._margin = _shift_margin(need)
        return self._margin

    def _build_knot(self, density, margin) -> SpotModel:
        """A knot's spot model and its render table (run ahead by :class:`KnotModels`)."""
        lay = self.layout
        model = SpotModel(self.sensor, lay.r_m, lay.e, self.altitude_m, density, margin)
        self._renderer.table(model)
        return model

    def _fused_models(self, i, truth, density, key):
        """``(model, blend)`` for :meth:`FastRenderer.render` on frame ``i``.

        Evolving: the two measured knots around the frame's time, blended with the weight
        that makes the light the blended density's (unit-light models weighted by each
        knot's column), the next knot built ahead. Random redrawn every N > 1 frames: the
        epoch's model, the next epoch's built ahead. Otherwise the frame's own model."""
        c = self.config
        if c.profile == "evolving":
            evo = self._evolving
            a, b, w = (v[0] for v in evo.knots_at(np.array([i / self.sensor.frame_rate_hz])))
            a, b, w = int(a), int(b), float(w)
            margin = self._knot_margin(truth)
            model = self._knots.get(("knot", a), lambda: evo.knot(a), margin)
            nxt = evo.next_knot(b)
            blend = None
            if b != a and w > 0.0:
                model_b = self._knots.get(("knot", b), lambda: evo.knot(b), margin)
                ca, cb = evo.knot_column(a), evo.knot_column(b)
                blend = (model_b, w * cb / ((1.0 - w) * ca + w * cb))
            self._knots.prefetch(("knot", nxt), lambda: evo.knot(nxt), margin)
            return model, blend
        if c.profile == "random" and c.random_every > 1:
            epoch = i // c.random_every
            margin = self._knot_margin(truth)
            model = self._knots.get(("random", epoch), lambda: density, margin)
            self._knots.prefetch(("random", epoch + 1), lambda: self._random_draw(epoch + 1),
                                 margin)
            return model, None
        return self.spot_model(density, key, truth), None

    def next(self, out: np.ndarray | None = None) -> Frame:
        """The next frame; with ``out`` (a ``sensor.frame_shape`` array of the sensor's dtype,
        e.g. a transport's loaned buffer) the frame is written there and ``Frame.frame`` is
        ``out``."""
        i = self.index
        truth = self.truth_at(i)
        density, key = self.profile_at(i)
        s = self.sensor
        if self._renderer is not None:
            return self._next_fused(i, truth, density, key, out)
        images, trunc = self.spots(density, key, truth)
        counts, clipped = expose(images, s.photons, self._noise_rng, s.read_noise_e, s.background_e,
                                 self.config.subtract_background, s.dtype,
                                 noise_free=not self.config.noise, per_field=self.config.per_field,
                                 return_clipped=True, fast=self.fast)
        frame = stack_to_frame(counts, self.layout) if out is None else self._into(counts, out)
        self.index += 1
        return Frame(frame, truth, i, i / s.frame_rate_hz, trunc, density, self.altitude_m,
                     clipped["saturated"])

    def _next_fused(self, i, truth, density, key, out) -> Frame:
        """The fast path: spots, noise and the write into the frame in one compiled pass
        (:mod:`.fast_frames`)."""
        s = self.sensor
        buf = np.empty(s.frame_shape, dtype=s.dtype) if out is None else out
        seed = int(self._noise_rng.integers(2**31 - 1)) if self.config.noise else 0
        model, blend = self._fused_models(i, truth, density, key)
        trunc, sat = self._renderer.render(model, truth, buf, s.photons, seed, self.config.noise,
                                           self.config.per_field, blend)
        self.index += 1
        return Frame(buf, truth, i, i / s.frame_rate_hz, trunc, density, self.altitude_m, sat)

    def __next__(self) -> Frame:
        return self.next()

    def _into(self, stack: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``stack`` (n, p, p) written into the frame ``out`` (zero outside the pupil)."""
        s, lay = self.sensor, self.layout
        if out.shape != s.frame_shape or out.dtype != np.dtype(s.dtype):
            raise ValueError(f"out must be {s.frame_shape} {s.dtype}, got {out.shape} {out.dtype}")
        g, p = lay.grid, s.pixels
        blocks = out.reshape(g, p, g, p).swapaxes(1, 2)          # a view of out
        blocks[lay.valid] = stack
        blocks[~lay.valid] = 0
        return out

    def next_batch(self, m: int) -> list[Frame]:
        """The next ``m`` frames, rendered together.

        One spot model holds the ``m * n_valid`` spots of the batch (each with its own
        frame's profile), one Poisson draw makes all their counts: for a small sensor
        (the paper's single subaperture) this costs a fraction of ``m`` calls of
        :meth:`next`, whose per-frame cost is mostly fixed overhead. Same distributions
        as :meth:`next` (same truths, profiles and noise model), not the same random draws.
        Pixels at 65535 are counted as saturated per frame.

        Args:
            m: frames (>= 1).
        """
        if not (isinstance(m, (int, np.integer)) and m >= 1):
            raise ValueError(f"m must be an integer >= 1, got {m!r}")
        m, i0, lay, s = int(m), self.index, self.layout, self.sensor
        n = lay.n_valid
        truths = np.stack([self.truth_at(i) for i in range(i0, i0 + m)])          # (m, n, 2)
        if self.config.profile == "evolving":                                      # vectorised
            dens = self._evolving.at_many(np.arange(i0, i0 + m) / s.frame_rate_hz)
            keys = tuple(("evolving", i) for i in range(i0, i0 + m))
        else:
            profiles = [self.profile_at(i) for i in range(i0, i0 + m)]
            dens = np.stack([d for d, _ in profiles])                                # (m, K)
            keys = tuple(k for _, k in profiles)
        need = float(np.abs(truths).max()) if truths.size else 0.0
        cached = self._batch_model
        if cached is None or cached[0] != keys or cached[1].max_shift_px < need:
            same = all(k == keys[0] for k in keys)
            rho = dens[0] if same else np.repeat(dens, n, axis=0)                    # (K,) | (m*n, K)
            model = SpotModel(s, np.tile(lay.r_m, m), np.tile(lay.e, (m, 1)), self.altitude_m, rho,
                              max(3.0, math.ceil(need) + 1.0))
            self._batch_model = cached = (keys, model)   # a static profile keeps it (same m)
        images, trunc = cached[1].images(truths.reshape(m * n, 2))
        counts = expose(images, s.photons, self._noise_rng, s.read_noise_e, s.background_e,
                        self.config.subtract_background, s.dtype, noise_free=not self.config.noise,
                        per_field=self.config.per_field, fast=self.fast
                        ).reshape(m, n, s.pixels, s.pixels)
        trunc = trunc.reshape(m, n)
        sat = (np.count_nonzero(counts == UINT16_MAX, axis=(1, 2, 3)) if s.dtype == "uint16"
               else np.zeros(m, dtype=int))
        out = []
        for j in range(m):                                   # per frame: assemble, no maths
            k = i0 + j
            out.append(Frame(stack_to_frame(counts[j], lay), truths[j], k, k / s.frame_rate_hz,
                             trunc[j], dens[j], self.altitude_m, int(sat[j])))
        self.index += m
        return out


    def __iter__(self):
        return self

    def frames(self, n: int):
        """Iterator over the next ``n`` frames."""
        if not (isinstance(n, (int, np.integer)) and n >= 0):
            raise ValueError(f"n must be an integer >= 0, got {n!r}")
        for _ in range(int(n)):
            yield self.next()

    def describe(self) -> dict:
        """JSON-able description: the sensor fields plus the config (for the ``sensor`` topic)."""
        d = self.sensor.to_dict()
        d["simulation"] = self.config.to_dict()
        return d

    def subaperture_batch(self, rng: np.random.Generator, n: int, **kwargs):
        """:func:`subaperture_batch` on this simulator's sensor (and sodium model)."""
        kwargs.setdefault("model", self._model)
        return subaperture_batch(self.sensor, rng, n, **kwargs)


@dataclass(frozen=True, eq=False)
class Batch:
    """Training samples: ``images (n, p, p)``, ``truth (n, 2)`` px detector axes,
    ``truncated (n,)``, ``photons (n,)`` expected photons used."""

    images: np.ndarray
    truth: np.ndarray
    truncated: np.ndarray
    photons: np.ndarray = field(default=None)


def subaperture_batch(sensor: Sensor, rng: np.random.Generator, n: int, sigma_px: float = 0.5,
                      model=None, altitude_m=None, density=None, photons=None, noise: bool = True,
                      dtype: str = "float32", subap: int = 0, max_shift_px: float | None = None,
                      chunk: int = 4096) -> Batch:
    """``n`` single-subaperture images with random profiles and random positions.

    Args:
        sensor: the sensor; the subaperture is its valid subaperture ``subap`` (the only
            one of ``Sensor.paper_single``): its ``r`` and ``e`` and the detector type.
        rng: ``numpy.random.Generator`` (advanced).
        n: number of samples.
        sigma_px: rms per axis of the normal random positions, pixels (detector axes).
        model: :class:`sodium.SodiumModel` for the random profiles (default
            :func:`sodium.training_model`); ignored if ``density`` is given.
        altitude_m: ``(K,)`` grid of the profiles (default :func:`sodium.default_altitude_grid`).
        density: ``(K,)`` fixed profile or ``(n, K)`` profiles instead of random ones.
        photons: expected photons per image: scalar, ``(n,)``, or None for ``sensor.photons``.
        noise: Poisson/read noise on (the sensor's read noise and background apply).
        dtype: output dtype of the images (``"float32"``, ``"float64"`` or ``"uint16"``).
        max_shift_px: positions are drawn normal and clipped to this (default 6 sigma).
        chunk: samples rendered at once (memory ``chunk x K`` for the profiles).
    Returns:
        :class:`Batch`; the same generator state gives the same batch bit for bit.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator")
    if not (isinstance(n, (int, np.integer)) and n >= 0):
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    if not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError("sigma_px must be finite and >= 0")
    lay = layout(sensor)
    if not 0 <= subap < lay.n_valid:
        raise ValueError(f"subap must be in 0..{lay.n_valid - 1}")
    h = sodium.default_altitude_grid() if altitude_m is None else np.asarray(altitude_m, float)
    fixed = None if density is None else np.asarray(density, dtype=float)
    if fixed is None and model is None:
        model = sodium.training_model()     # the training split's prior: never the test block
    ph = sensor.photons if photons is None else photons
    ph = np.broadcast_to(np.asarray(ph, dtype=float), (n,))
    smax = 6.0 * sigma_px if max_shift_px is None else float(max_shift_px)
    p = sensor.pixels
    out = np.empty((n, p, p), dtype=dtype)
    truth = np.empty((n, 2))
    trunc = np.empty(n)
    r = np.full(chunk, lay.r_m[subap])
    e = np.broadcast_to(lay.e[subap], (chunk, 2))
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        m = b - a
        t = np.clip(rng.normal(0.0, sigma_px, size=(m, 2)), -smax, smax)
        if fixed is None:
            rho = model.sample(rng, m, h)
        else:
            rho = fixed if fixed.ndim == 1 else fixed[a:b]
        spots = SpotModel(sensor, r[:m], e[:m], h, rho, max_shift_px=smax)
        img, tr = spots.images(t)
        out[a:b] = expose(img, ph[a:b], rng, sensor.read_noise_e, sensor.background_e, True,
                          dtype, noise_free=not noise)
        truth[a:b] = t
        trunc[a:b] = tr
    return Batch(out, truth, trunc, np.array(ph))


__all__ = ["SimulationConfig", "Simulator", "Frame", "Batch", "subaperture_batch", "PROFILE_SOURCES"]
