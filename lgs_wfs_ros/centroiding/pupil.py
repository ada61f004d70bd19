"""Pupil calibration: a running estimate of the sodium profile from the whole pupil.

Every subaperture sees the same sodium profile through a known geometry: sodium at
altitude ``h`` images at ``r cos z (1/h_ref - 1/h)`` along ``e`` (docs/conventions.md
section 3). Tilts differ from subaperture to subaperture and average out over the pupil
and over time, so the mean images of all subapertures, fitted together, give the profile,
and with it every subaperture's reference spot and the bias of any fixed estimator.

Method (plain numpy, vectorised over subapertures; docs/accuracy.md):

1. Accumulate: every ``stride``-th frame, the background-subtracted counts of each valid
   subaperture are added up (``(n, p*p)``, one addition per frame).
2. Every ``period`` frames: each subaperture's mean image is normalised to unit light,
   projected on 1-px bins along its elongation (:class:`.model_spot.Projection`: tilts
   across ``e`` drop out) and blended into an exponential average with time constant
   ``time_constant_s`` (the profile evolves over seconds).
3. Fit: non-negative least squares of all subapertures' projected means against thin
   layers (hats on ``nodes`` altitudes evenly spaced in 1/h, 70-130 km) rendered through
   each subaperture's exact geometry (launch position, zenith angle, detector type,
   truncation at the field edge): ``z_s c_s = B_s x``, ``c_s = 1^T B_s x`` the fraction
   of the light inside subaperture s's field (iterated), with a light second-difference
   smoothing. ``x`` is the light per layer: the profile. ``B`` is blurred by the tilts
   (their spread about the block centre), each truncated spot's model is moved by the
   pull of the per-frame normalisation, and each block's mean tilt along e is a free
   shift (:meth:`PupilCalibration.solve`).
4. From ``x``: each subaperture's noise-free reference (:class:`.model_spot.ProfileSpots`,
   rendered exactly, with exact derivatives) and the CoG bias it implies (the CoG of that
   reference: what a plain CoG reads for a spot at the true centre).

What fixes the origin: the blocks' free shifts are held to no pupil-wide pattern
``proportional to r along e`` from the launch, i.e. the fit assumes the tilts averaged over
the window carry none. That pattern is focus (for a centre launch) and is exactly a
change of the profile's altitude: an LGS cannot tell them apart, and LGS AO takes focus
from a natural-guide-star sensor. Everything else along e (tip, tilt, higher modes,
independent tilts) is each block's free shift; across e it drops out of the projection.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.optimize import nnls

from ..optics import geometry
from ..optics.gaussian_spot import FWHM_PER_SIGMA
from ..optics.model_spot import ProfileSpots, Projection, altitude_nodes, node_density, projected_hats
from ..optics.sodium import gaussian_profile, harmonic_altitude
from . import kernels
from .base import flag, number
from .linearize import ResponseMap, chebyshev_nodes



class PupilCalibration:
    """Running sodium-profile estimate of one sensor and the references it implies.

    Args:
        sensor: the :class:`lgs_wfs_ros.sensor.Sensor` (full pupil; a single subaperture
            works too, but one radius cannot separate the profile from its tilt).
        period: frames between profile refits (and reference updates).
        time_constant_s: time constant of the exponential average of the projected mean
            images, seconds (the profile's memory).
        stride: accumulate every ``stride``-th frame (1: all).
        nodes: thin layers of the profile basis (70-130 km, even in 1/h).
        smoothing: weight of the second-difference penalty, relative to the mean diagonal
            of the normal matrix.
        prior_fwhm_m: FWHM of the Gaussian profile (harmonic altitude at h_ref) used until
            the first fit.
        max_shift_px: largest shift the reference renderer must handle (linearisation).
        background: counts per pixel in the frames given to :meth:`observe`, removed from
            the mean images.
        asynchronous: run each refit in a background thread on a snapshot of the period's
            accumulated frames and install its result at the first frame boundary after it
            finishes (:meth:`observe` returns True on that frame); the frame path only swaps
            buffers. The install frame then depends on timing, so results are not
            reproducible frame for frame: False (default) refits inline at the end of each
            period, deterministic (replay, benchmarks). While a refit runs, frames keep
            accumulating; the next one starts when it is installed (a period may grow).
        lag: with ``asynchronous``, install each refit exactly ``lag`` frames after the
            period end that started it, waiting for it then if it is late: reproducible
            frame for frame (a replay gives the live numbers) and no stall as long as a
            refit takes less than ``lag`` frames. 0: install whenever it is ready.
        trend: fit the average extrapolated, from the drift between it and a second
            average of time constant ``2 time_constant_s``, to the middle of the period the
            refit will serve (True, default: no lag behind a steadily evolving profile, a
            little more focus noise on a steady one), and also to its end
            (``light_drift``), which the estimators follow frame by frame between refits
            (:meth:`drift_phase`, :meth:`.Centroider._follow_drift`); False: the average
            itself, held for the period.
        altitude_s: time constant (s) of the estimators' :class:`.altitude.AltitudeTracker`,
            which follows the layer's altitude between refits from the slopes (0: off). The
            calibration only carries the setting; the centroider applies it.
    """

    def __init__(self, sensor, period: int = 140, time_constant_s: float = 0.3, stride: int = 1,
                 nodes: int = 120, smoothing: float = 1e-3, prior_fwhm_m: float = 10e3,
                 max_shift_px: float = 2.0, background: float = 0.0, asynchronous: bool = False,
                 lag: int = 0, trend: bool = True, altitude_s: float = 0.0):
        self.sensor = sensor
        self.altitude_s = number("pupil_altitude_s", altitude_s, minimum=0)
        self.asynchronous = flag("pupil_async", asynchronous)
        self.trend = flag("pupil_trend", trend)
        self.lag = number("pupil_async_lag", lag, minimum=0, integer=True)
        self.prepare = None          # optional callable(calibration) -> payload, run by _work
        #: what the estimator's frame path reads of a refit beside ``prepare``'s payload: the
        #: names of this class's cached methods, which a background refit calls after
        #: ``prepare`` (off the frame path); an estimator with its own tables declares both
        #: with :meth:`delegate`
        self.reads = ("reference_image", "cog_bias", "drift_counts")
        self.payload = None
        self._pool = None
        self._job = None
        self.background = number("background", background, minimum=0)
        self.layout = geometry.layout(sensor)
        self.n = self.layout.n_valid
        self.period = number("pupil_period", period, minimum=1, integer=True)
        self.time_constant_s = number("pupil_time_constant_s", time_constant_s, minimum=0)
        self.stride = number("pupil_stride", stride, minimum=1, integer=True)
        self.smoothing = number("pupil_smoothing", smoothing, minimum=0)
        self.max_shift_px = number("max_shift_px", max_shift_px, minimum=0)
        nodes = number("pupil_nodes", nodes, minimum=8, integer=True)
        self.nodes_m = altitude_nodes(sensor, nodes)
        polar = sensor.detector == "polar"
        e_pix = np.tile([1.0, 0.0], (self.n, 1)) if polar else np.asarray(self.layout.e, float)
        self.projection = Projection(sensor, e_pix, 1.0)
        self._e_pix = e_pix
        self._basis = None
        self.blur_px = 0.0
        y, x = np.indices((sensor.pixels, sensor.pixels), dtype=float)
        c = (sensor.pixels - 1) / 2
        self._u_perp = (-(x.ravel() - c)[None, :] * e_pix[:, 1:]
                        + (y.ravel() - c)[None, :] * e_pix[:, :1])              # (n, pp) across e
        self.prior = self._prior_light(number("prior_fwhm_m", prior_fwhm_m, minimum=0, strict=True))
        self.reset()

    # -- state ------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything seen: back to the prior profile (a refit under way is waited
        for and dropped)."""
        if getattr(self, "_job", None) is not None:
            self._job.exception()
            self._job = None
        self.payload = None
        self._taken_at = 0
        self._acc = np.zeros((self.n, self.sensor.pixels ** 2))
        self._acc_rows = None                    # (G*G, p*p) float32, see observe_rows
        self._acc_frame = None                   # a detector frame's shape, see observe_frame
        self._acc_marg = None                    # (n, 2, p) float64, see marginal_buffer
        self._count = np.zeros(self.n)
        self._frames = 0
        self.state = None
        self.state_slow = None
        self.flux = None
        self._state_ok = np.zeros(self.n, dtype=bool)
        self.light = self.prior.copy()
        self.light_drift = None
        self._drift_at = (0.0, 1.0)              # (frame light is predicted for, frames to light_drift's)
        self._drift_refs = None                  # (version, counts of light_drift's reference)
        self._drift_margs = None                 # (version, its marginals in counts)
        self._ref_margs = None                   # (version, the reference's marginals in counts)
        self.fits = 0
        self.version = getattr(self, "version", 0) + 1
        self._refs = None
        self.refit_s = None                      # wall s of the last refit (see describe)
        self._fit_end = 0                        # frames seen when its accumulators were taken
        self._bias = None        # (version, cog_bias)
        self._response = None    # (version, cog_response)

    def _prior_light(self, fwhm_m: float) -> np.ndarray:
        """Light per node of a Gaussian layer whose harmonic altitude is h_ref."""
        h = self.nodes_m
        centre = self.sensor.h_ref_m
        for _ in range(3):                                   # harmonic altitude -> h_ref
            dens = gaussian_profile(h, centre, fwhm_m)
            centre += self.sensor.h_ref_m - harmonic_altitude(h, dens)
        ext, _ = node_density(h, np.ones_like(h))
        width = 0.5 * (ext[2:] - ext[:-2])
        light = gaussian_profile(h, centre, fwhm_m) * width
        return light / light.sum()

    @property
    def basis(self) -> np.ndarray:
        """``(n, nb, K)`` projected thin-layer spots (built on first use, 2-5 s polar, ~5 s
        cartesian, then shared: :func:`shared_hats`), and with them ``_dbasis``, their
        derivative with respect to a shift along e (px^-1, a forward difference over 0.02
        px: one more render)."""
        if self._basis is None:
            # the mean image of a spot under random tilts of rms s per axis is the spot with
            # its Gaussian core widened by s: fit the means against spots so blurred
            sensor = self.sensor.replace(
                core_fwhm_px=math.hypot(self.sensor.core_fwhm_px, FWHM_PER_SIGMA * self.blur_px))
            (self._basis, self._dbasis, self._colsum, self._dcolsum,
             self._gram) = shared_hats(sensor, self.nodes_m, self._hats_of)
            k = self._basis.shape[2]
            d2 = np.diff(np.eye(k), 2, axis=0)
            self._rough = d2.T @ d2
        return self._basis

    def _hats_of(self, sensor) -> tuple:
        """``(basis, dbasis, colsum, dcolsum, gram)`` of :attr:`basis` for ``sensor`` (the
        calibration's, its core widened by the tilt blur), built."""
        hats = lambda shift: projected_hats(sensor, self.layout.r_m, self.layout.e,  # noqa: E731
                                            self.nodes_m, self.projection, shift, self.layout)
        b, h = hats(None), 0.02
        db = (hats(h * self._e_pix) - b) / h
        flat = b.reshape(-1, b.shape[2])
        return b, db, b.sum(axis=1), db.sum(axis=1), flat.T @ flat

    # -- per frame --------------------------------------------------------------------
    def observe(self, flat: np.ndarray, ok: np.ndarray | None = None) -> bool:
        """Account for one frame before it is measured.

        Args:
            flat: ``(n, p*p)`` background-subtracted counts of the valid subapertures.
            ok: ``(n,)`` bool, subapertures usable in this frame (default: finite, > 0).

        Returns:
            True when this frame completed a period and the profile was refitted.
        """
        if self._frames % self.stride == 0:
            f = np.asarray(flat)
            if ok is None:
                tot = f.sum(axis=1)
                ok = np.isfinite(tot) & (tot > 0)
            if ok.all():
                self._acc += f
                self._count += 1
            else:
                self._acc[ok] += f[ok]
                self._count[ok] += 1
        return self._tick()

    def observe_rows(self, rows: np.ndarray, valid_rows: np.ndarray) -> bool:
        """As :meth:`observe` for every block of a frame, ``rows (G*G, p*p)`` float32 (a
        centroider's cast-and-cut buffer), valid ones at ``valid_rows (n,)``: one float32
        addition, no gather (the cheapest per-frame path). A subaperture with a bad pixel
        in a period is left out of that period's mean."""
        self._rows_index = valid_rows
        return self._add_whole("_acc_rows", rows, np.float32)

    def observe_frame(self, frame: np.ndarray) -> bool:
        """As :meth:`observe` for a whole detector frame ``(G*p, G*p)`` of integer counts:
        added as it is into an integer accumulator (no cut, no float copy), cut into
        subapertures only at the refit."""
        kind = np.uint32 if frame.dtype.kind == "u" and frame.dtype.itemsize <= 2 else np.float64
        return self._add_whole("_acc_frame", frame, kind)

    def marginal_buffer(self) -> np.ndarray | None:
        """Polar detector only: ``(n, 2, p)`` float64 sums to add this frame's block
        marginals into (``[:, 0]`` column sums, along e; ``[:, 1]`` row sums, across e), or
        None when ``pupil_stride`` skips this frame; then call :meth:`observed_marginals`.
        On a polar detector the fit reads the mean images only through their column sums
        (the bins along e) and row moments (the tilt blur across e), so the marginals are
        all it needs: 2,784 x 32 numbers a frame instead of the whole frame."""
        if self.sensor.detector != "polar":
            raise ValueError("marginals describe the mean images only on a polar detector")
        if self._frames % self.stride:
            return None
        if self._acc_marg is None:
            self._acc_marg = np.zeros((self.n, 2, self.sensor.pixels))
        return self._acc_marg

    def observed_marginals(self, added: bool) -> bool:
        """Count a frame whose marginals went (``added``) or not into :meth:`marginal_buffer`;
        True when a refit was installed on it."""
        if added:
            self._count += 1
        return self._tick()

    def _add_whole(self, name: str, data: np.ndarray, dtype) -> bool:
        """Add a whole array into the accumulator ``name`` (made on first use)."""
        if self._frames % self.stride == 0:
            buf = getattr(self, name)
            if buf is None or buf.shape != data.shape:
                buf = np.zeros(data.shape, dtype=dtype)
                setattr(self, name, buf)
            if not kernels.add_counts(buf, data):
                np.add(buf, data, out=buf, casting="unsafe")
            self._count += 1
        return self._tick()

    def _tick(self) -> bool:
        """Count a frame; refit at the end of a period (returns True when a refit was
        installed on this frame)."""
        self._frames += 1
        if self.asynchronous:
            due = not self.lag or self._frames - self._taken_at >= self.lag
            if self.lag and due and self._job is not None:
                self._job.exception()                        # due now: wait if it is late
            installed = self._poll() if due else False
            if self._job is None and self._frames - self._taken_at >= self.period:
                self._start()
            return installed
        if self._frames % self.period == 0:
            self.refit()
            return True
        return False

    # -- fit --------------------------------------------------------------------------
    def _take(self) -> tuple:
        """Hand over the accumulators (fresh zero ones stay): ``(acc, count, acc_frame,
        acc_rows, rows_index, frames since the last take, acc_marg, frames seen)``."""
        snap = (self._acc, self._count, self._acc_frame, self._acc_rows,
                getattr(self, "_rows_index", None), self._frames - self._taken_at,
                self._acc_marg, self._frames)
        self._acc = np.zeros_like(self._acc)
        self._count = np.zeros_like(self._count)
        if self._acc_frame is not None:
            self._acc_frame = np.zeros_like(self._acc_frame)
        if self._acc_rows is not None:
            self._acc_rows = np.zeros_like(self._acc_rows)
        if self._acc_marg is not None:
            self._acc_marg = np.zeros_like(self._acc_marg)
        self._taken_at = self._frames
        return snap

    def refit(self) -> None:
        """Blend the accumulated mean images into the average and refit the profile, now
        (inline, whatever ``asynchronous`` says)."""
        snap = self._take()
        t0 = time.perf_counter()
        fitted = self._fit(snap, self.period)
        self.refit_s = time.perf_counter() - t0
        if not fitted:                                       # nothing usable: keep it
            self._acc += snap[0]
            self._count += snap[1]

    def _start(self) -> None:
        """Start a background refit on a snapshot: a copy of the fit state works on the
        taken accumulators, then ``prepare`` (if set) runs on it in the same thread."""
        clone = copy.copy(self)
        for name in ("state", "state_slow", "flux", "_state_ok", "light"):
            value = getattr(self, name)
            setattr(clone, name, None if value is None else value.copy())
        clone._pool = clone._job = None
        snap = self._take()
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pupil-refit")
        self._job = self._pool.submit(self._work, clone, snap)

    def delegate(self, prepare, reads: tuple) -> None:
        """Hand a background refit ``prepare(calibration) -> payload`` (the estimator's own
        tables, built in the refit's thread) and the cached methods ``reads`` its frame path
        reads beside them (see ``reads``)."""
        self.prepare, self.reads = prepare, tuple(reads)

    def _work(self, clone, snap):
        """A background refit: the fit, ``prepare``'s payload, then what ``reads`` names (and
        the CoG bias the altitude tracker reads), all cached on ``clone``."""
        t0 = time.perf_counter()
        clone._fit(snap, snap[5])
        payload = None if self.prepare is None else self.prepare(clone)
        for name in self.reads + (("cog_bias",) if self.altitude_s > 0 else ()):
            getattr(clone, name)()
        clone.refit_s = time.perf_counter() - t0
        return clone, payload

    def _poll(self) -> bool:
        """Install a finished background refit (fit state and ``payload``); True if so. A
        refit that failed re-raises its error here, once, as an inline refit's would (that
        frame is lost); the calibration in use stays and the next period refits again."""
        if self._job is None or not self._job.done():
            return False
        job, self._job = self._job, None
        clone, payload = job.result()                        # re-raises a refit's error
        for name in _FIT_STATE:
            if name in clone.__dict__:
                setattr(self, name, clone.__dict__[name])
        self.payload = payload
        return True

    def wait(self) -> None:
        """Block until a background refit under way has finished (offline use: tests, a
        replay that wants a given install frame); the next observed frame installs it."""
        if self._job is not None:
            self._job.exception()

    def _fit(self, snap: tuple, frames: int) -> bool:
        """Refit from a :meth:`_take` snapshot covering ``frames`` frames; False if it held
        no usable subaperture (nothing changed)."""
        acc, count, acc_frame, acc_rows, rows_index, _, acc_marg, end = snap
        if acc_marg is not None:           # an image with those marginals: outer(rows, cols) / sum
            tot = acc_marg[:, 0].sum(axis=1)
            img = acc_marg[:, 1, :, None] * acc_marg[:, 0, None, :]
            acc += (img / np.where(tot > 0, tot, 1.0)[:, None, None]).reshape(self.n, -1)
        if acc_frame is not None:
            acc += geometry.frame_to_stack(acc_frame, self.layout).reshape(self.n, -1)
        if acc_rows is not None:
            acc += acc_rows[rows_index]
        good = (count > 0) & np.isfinite(acc).all(axis=1)
        if not good.any():
            return False
        mean = acc / np.maximum(count, 1)[:, None] - self.background
        proj = self.projection(mean)                                            # (n, nb)
        tot = proj.sum(axis=1)
        good &= np.isfinite(tot) & (tot > 0)
        z = np.where(good[:, None], proj / np.where(good, tot, 1.0)[:, None], 0.0)
        self._update_blur(mean, good)
        a, a_slow = self._decays(frames)
        first = self.state is None
        if first:
            self.state, self.flux = z, np.where(good, tot, self.sensor.photons)
            self.state_slow = z.copy()
        else:
            fresh = good & ~self._state_ok
            blend = good & self._state_ok
            self.state[blend] = a * self.state[blend] + (1 - a) * z[blend]
            self.state[fresh] = z[fresh]
            self.state_slow[blend] = a_slow * self.state_slow[blend] + (1 - a_slow) * z[blend]
            self.state_slow[fresh] = z[fresh]
            self.flux[blend] = a * self.flux[blend] + (1 - a) * tot[blend]
            self.flux[fresh] = tot[fresh]
        self._state_ok |= good
        start, self.light = self.light, self.solve(self._predicted(frames, a, a_slow),
                                                   self._state_ok, self.light)
        self._fit_drift(frames, a, a_slow, end, start, first)
        self.fits += 1
        self.version += 1
        self._refs = None
        self._fit_end = end
        return True

    def _decays(self, frames: int) -> tuple[float, float]:
        """Per-refit weights of the old average: time constant ``tau`` and ``2 tau``."""
        if self.time_constant_s <= 0:
            return 0.0, 0.0
        steps = frames / (self.time_constant_s * self.sensor.frame_rate_hz)
        return math.exp(-steps), math.exp(-steps / 2)

    def _fit_drift(self, frames: int, a: float, a_slow: float, end: int, start: np.ndarray,
                   first: bool) -> None:
        """With ``trend``: the profile at the end of the period the refit serves
        (``light_drift``: the same extrapolation ``frames / 2`` frames further, solved from
        the same ``start`` as ``light``, so that only the data differ), so that the
        estimators follow the drift between refits (:meth:`drift_phase`); None on the first
        fit (no drift seen yet) and without ``trend``."""
        self._drift_at = (end + self.lag + frames / 2, frames / 2)
        if first or not self.trend or not 0 < a < 1:
            self.light_drift = None
            return
        later = self._predicted(frames, a, a_slow, frames / 2 / self.sensor.frame_rate_hz)
        self.light_drift = self.solve(later, self._state_ok, start)

    def drift_phase(self, pending: int = 0) -> float:
        """Where the frame last observed sits between ``light`` (0, the middle of the period
        the refit serves) and ``light_drift`` (1, its end): -1 on the refit's own frame;
        ``pending``: frames read but not observed yet (1 for an estimator that reads a
        frame before it feeds the calibration)."""
        mid, half = self._drift_at
        return (self._frames + pending - mid) / half

    def drift_counts(self) -> np.ndarray | None:
        """``(n, p, p)`` the reference of ``light_drift`` in counts, on the scale of
        :meth:`counts` (cached per refit), or None without a drift."""
        if self.light_drift is None:
            return None
        if self._drift_refs is None or self._drift_refs[0] != self.version:
            ps = self._spots_of(self.light_drift)
            img = ps.image_at(np.zeros((self.n, 2)))
            self._drift_refs = (self.version, img * self._to_counts(img))
        return self._drift_refs[1]

    def drift_marginals(self) -> np.ndarray | None:
        """``(n, 2, p)`` polar detector: :meth:`drift_counts`' column and row sums (as
        :meth:`marginal_buffer` lays them out), from the spot model without the images
        (cached per refit), or None without a drift."""
        if self.light_drift is None:
            return None
        if self._drift_margs is None or self._drift_margs[0] != self.version:
            ps = self._spots_of(self.light_drift)
            self._drift_margs = (self.version,
                                 self.marginals_in_counts(ps.marginals_at(np.zeros((self.n, 2)))))
        return self._drift_margs[1]

    def drift_marginal_pair(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(drift_marginals(), reference_marginals())``, both ``(n, 2, p)``: what ``ml``
        reads to follow the drift, or None without a drift (the reference's then not
        rendered)."""
        drifted = self.drift_marginals()
        return None if drifted is None else (drifted, self.reference_marginals())

    def reference_marginals(self) -> np.ndarray:
        """``(n, 2, p)`` polar detector: :meth:`reference_counts`' column and row sums, from
        the spot model without the image (the same render path as :meth:`drift_marginals`,
        so that their difference is the drift alone)."""
        if self._ref_margs is None or self._ref_margs[0] != self.version:    # cached per refit
            self._ref_margs = (self.version, self.marginals_in_counts(
                self.spots().marginals_at(np.zeros((self.n, 2)))))
        return self._ref_margs[1]

    def _spots_of(self, light: np.ndarray) -> ProfileSpots:
        """Noise-free spots of every subaperture for node light ``light (K,)``."""
        return ProfileSpots(self.sensor, self.layout.r_m, self.layout.e, self.nodes_m, light,
                            self.max_shift_px)

    def marginals_in_counts(self, marginals: np.ndarray) -> np.ndarray:
        """``marginals (n, 2, p)`` of unit-light spots (column sums first) scaled to counts as
        :meth:`counts` scales their images: the field's light at :meth:`_flux`."""
        tot = marginals[:, 0].sum(axis=1)
        return marginals * (self._flux() / np.where(tot > 0, tot, 1.0))[:, None, None]

    def _predicted(self, frames: int, a: float, a_slow: float, later_s: float = 0.0) -> np.ndarray:
        """The projected means the fit uses: the average itself, or (``trend``) extrapolated
        to the middle of the period the refit will serve. For a profile drifting linearly,
        an average over periods of ``P`` s that keeps ``a`` of itself each period lags the
        period's end by ``L = P/2 + P a/(1-a)``; two averages (``tau``, ``2 tau``) give the
        drift, ``(state - slow) / (L_slow - L)``, and the profile at the period end plus
        ``lag`` frames plus ``P/2`` is ``state + drift (L + lag + P/2)``; ``later_s``
        seconds further with ``later_s``."""
        if not self.trend or not 0 < a < 1:
            return self.state
        period = frames / self.sensor.frame_rate_hz
        lag = period / 2 + period * a / (1 - a)
        lag_slow = period / 2 + period * a_slow / (1 - a_slow)
        ahead = lag + self.lag / self.sensor.frame_rate_hz + period / 2 + later_s
        return self.state + (self.state - self.state_slow) * (ahead / (lag_slow - lag))

    def _update_blur(self, mean: np.ndarray, good: np.ndarray) -> None:
        """Tilt blur of the mean images from their spread across e (where the profile does
        not reach): the pupil median of the across-e variance about the block centre (the
        true centre: each subaperture's mean tilt over the window counts; about each
        block's own mean, the period's spread falls short of the one the fitted average
        holds, docs/accuracy.md), inverted through the pixel-integrated core widened by a
        blur; the basis is rebuilt when it moves by more than 0.05 px."""
        if good.sum() < 3:
            return
        m = np.maximum(mean[good], 0.0)
        tot = m.sum(axis=1)
        u = self._u_perp[good]
        var = (m * u * u).sum(axis=1) / tot
        blur = float(np.interp(np.median(var), *self._spread_table()))
        if abs(blur - self.blur_px) > 0.05:
            self.blur_px = blur
            self._basis = None

    def _spread_table(self) -> tuple[np.ndarray, np.ndarray]:
        """``(variance (S,), blur (S,))``: across-e variance (px^2, about the block centre,
        pixel centres) of the pixel-integrated core widened by a tilt blur of rms ``blur``
        px: an under-sampled core is not ``sigma^2 + 1/12``."""
        if not hasattr(self, "_spread"):
            from scipy.special import ndtr
            p = self.sensor.pixels
            j = np.arange(p) - (p - 1) / 2
            blur = np.linspace(0.0, 3.0, 301)
            sig = np.hypot(self.sensor.core_fwhm_px / FWHM_PER_SIGMA, blur)[:, None]
            g = ndtr((j + 0.5) / sig) - ndtr((j - 0.5) / sig)                # (S, p)
            var = (g * j ** 2).sum(axis=1) / g.sum(axis=1)
            self._spread = (var, blur)
        return self._spread

    def solve(self, z: np.ndarray, ok: np.ndarray, start: np.ndarray | None = None,
              iterations: int = 6) -> np.ndarray:
        """Light per node ``(K,)`` from unit-light projected means ``z (n, nb)`` of the
        subapertures ``ok (n,)``; ``start`` gives the first field fractions.

        Each frame's light is counted inside the field (docs/conventions.md), so a frame
        whose tilt pushes a spot out of its field is scaled up: the mean of frames tilted by
        ``t ~ N(0, s^2)`` along e is, to first order, the blurred spot ``B x`` displaced by
        ``d = -s^2 kappa`` (``kappa = d ln c / dt``, ``c(t)`` the light the field keeps):
        ``(B + d B') x``, with ``B'`` the basis' derivative along e. Without that term the
        spots the field truncates pull the profile (docs/accuracy.md).

        Each subaperture's mean tilt over the window ``mu`` moves its mean image along e
        without saying anything about the profile, so it is left free
        (:meth:`_free_shift_terms`): only its weighted sum along the altitude's pattern
        (``r`` from the launch) is held at zero, which fixes the origin. The shifts are
        carried by the first-order term ``mu B' x``; if from the ``MOVE_AFTER``-th solve on the
        profile still moves by more than ``PROFILE_TOL`` of its largest node and by more than
        ``STALL`` times the solve before's move (the iterates do not settle), a shift beyond
        the core's rms width (a window's mean tilt under frozen flow reaches 1 px) moves the
        block's model instead from then on: its basis is the thin layers' spots ``mu /
        delta_s`` nodes further along (nodes are even in 1/h, so each moves block s's spot
        by the same ``delta_s`` px, :meth:`_node_step_px`; within 2 % of the spots rendered
        moved), and the next iterate solves for what is left.
        (With every shift carried by the first-order term about the block centre, the
        iterates alternated between two profiles on such windows, docs/accuracy.md.) ``d``,
        the field fractions, the shift directions and the moved shifts come from the
        previous iterate (``start`` first: the last refit's profile, so a steady profile
        needs one solve; at most ``iterations``, stopping when they move by less than
        ``PULL_TOL_PX``, ``FRACTION_TOL``, ``DIRECTION_TOL`` and ``SHIFT_TOL_PX``); ``d`` is
        applied where it exceeds ``PULL_TOL_PX``, and kept within +-s (a spot almost out of
        its field, whose ``kappa`` is large, is beyond a first-order model)."""
        b, db = self.basis, self._dbasis
        k = b.shape[2]
        x = self.prior if start is None else start
        base = self._gram.copy()
        if (~ok).any():
            flat = b[~ok].reshape(-1, k)
            base -= flat.T @ flat
        if ok.all():                                         # no copies of the basis
            bo, dbo, zo, cs0, cs1 = b, db, z, self._colsum, self._dcolsum
            r = self.layout.r_m
        else:
            bo, dbo, zo = b[ok], db[ok], z[ok]
            cs0, cs1, r = self._colsum[ok], self._dcolsum[ok], self.layout.r_m[ok]
        core = MOVE_CORES * self.sensor.core_fwhm_px / FWHM_PER_SIGMA   # px: beyond, move
        node_px = self._node_step_px(r)                      # (m,) px a node step moves a spot
        reach = node_px * k * MAX_NODE_SHIFT                 # px a model may move (nodes)
        held = np.zeros(bo.shape[0])                         # the shifts the models are moved by
        used, step, moving, change = None, 0.0, False, np.inf
        for it in range(iterations):
            mv = np.flatnonzero(held)
            nodes = held[mv] / node_px[mv]
            bm, dbm = _node_shifted(bo[mv], nodes), _node_shifted(dbo[mv], nodes)
            c0, c1 = cs0 @ x, cs1 @ x
            c0[mv], c1[mv] = _node_shifted(cs0[mv], nodes) @ x, _node_shifted(cs1[mv], nodes) @ x
            d = self._pull(c0, c1)
            c = (c0 + d * c1) / max(x.sum(), 1e-300)                  # light inside the field
            g = np.einsum("snk,k->sn", dbo, x)              # (m, nb) the shift's direction
            g[mv] = np.einsum("snk,k->sn", dbm, x)
            if used is not None and (step <= SHIFT_TOL_PX
                                     and np.abs(d - used[0]).max() <= PULL_TOL_PX
                                     and np.abs(c - used[1]).max() <= FRACTION_TOL
                                     and _turned(g, used[2]) <= DIRECTION_TOL):
                break                                        # what the last solve used
            used = d, c, g
            w = zo * c[:, None]                                                  # (m, nb)
            rows = np.flatnonzero((d != 0) | (held != 0))    # models that are not the basis
            old = bo[rows]
            model = _row_models(old, dbo, rows, d, mv, bm, dbm)
            norm = np.sqrt(np.einsum("sn,sn->s", g, g))
            live = norm > 1e-12 * max(float(norm.max(initial=0.0)), 1e-300)
            u = np.where(live[:, None], g / np.where(live, norm, 1.0)[:, None], 0.0)
            v = np.einsum("snk,sn->sk", bo, u)               # (m, K) each model along its u
            v[rows] = np.einsum("snk,sn->sk", model, u[rows])
            uw = np.einsum("sn,sn->s", u, w)
            gram_free, rhs_free, pin = self._free_shift_terms(v, uw, np.where(live, norm, 0.0),
                                                              r, held)
            gram = base + _row_gram(old, model) + gram_free
            lam = self.smoothing * np.trace(gram) / k
            chol, _ = cho_factor(gram + lam * self._rough + 1e-12 * np.trace(gram) * np.eye(k),
                                 lower=True)
            low = np.tril(chol)
            rhs = (np.einsum("snk,sn->k", bo, w) + rhs_free
                   + np.einsum("snk,sn->k", model - old, w[rows]))
            last, x = x, nnls(low.T, solve_triangular(low, rhs, lower=True), maxiter=50 * k)[0]
            if x.sum() <= 0:
                return self.prior.copy()
            change, before = _changed(x, last), change
            moving = moving or (it + 1 >= MOVE_AFTER and change > PROFILE_TOL
                                and change > STALL * before)         # not settling
            if not moving:                                   # first-order iterates settle
                continue
            mu = np.clip(held + _shift_steps(x, *pin), -MAX_SHIFT_PX, MAX_SHIFT_PX)
            moved = np.where(((np.abs(mu) > core) | (held != 0)) & (np.abs(mu) <= reach),
                             mu, 0.0)                        # once moved, moved
            step, held = float(np.abs(moved - held).max(initial=0.0)), moved
        return x / x.sum()

    def _node_step_px(self, r: np.ndarray) -> np.ndarray:
        """``(m,)`` px: how far one node step (even in 1/h) moves the spot of a block at
        ``r (m,)`` m from the launch along its e, ``r cos z d(1/h)`` in pixels."""
        step = abs(1.0 / self.nodes_m[0] - 1.0 / self.nodes_m[1])
        return (np.asarray(r, float) * math.cos(math.radians(self.sensor.zenith_deg)) * step
                / self.sensor.pixel_scale_rad)

    @staticmethod
    def _free_shift_terms(v: np.ndarray, uw: np.ndarray, norm: np.ndarray, r: np.ndarray,
                          held: np.ndarray) -> tuple:
        """``(K, K)``, ``(K,)`` and what :func:`_shift_steps` reads: what leaving each
        subaperture's shift along e free adds to the normal matrix and right-hand side.

        Subaperture s's data ``w_s (nb,)`` is modelled as ``M_s x + nu_s u_s``, ``M_s`` its
        model (``(nb, K)``: moved by the pull and the held shift), ``u_s`` the direction of
        its derivative ``g_s`` along e (``norm (m,)``: ``|g_s|``, 0 where it has none) and
        ``nu_s / |g_s|`` the shift beyond ``held (m,)`` px, subject to ``sum_s r_s |g_s|^2
        mu_s = 0`` on the whole shifts ``mu`` (the tilts' information-weighted pattern along
        ``r e`` is zero: what fixes the profile's altitude, docs/accuracy.md). Minimising
        over ``nu`` (variable projection) leaves a quadratic in ``x``: each residual loses
        its component along ``u_s`` (``- V^T V``, ``v (m, K)``: ``V_s = M_s^T u_s``; ``uw
        (m,)``: ``u_s . w_s``) and the constraint gives it back along the altitude's pattern
        (``+ Q Q^T / A``, ``Q = sum_s q_s V_s``, ``q_s = r_s |g_s|``, ``A = q^T q``, offset
        by the held shifts' share ``q^T (|g| held)``): two rank-``m`` products."""
        q = r * norm
        a = max(float(q @ q), 1e-300)
        offset = float(q @ (norm * held))
        qv = q @ v
        gram = np.outer(qv, qv) / a - v.T @ v
        rhs = qv * (q @ uw + offset) / a - v.T @ uw
        return gram, rhs, (v, uw, q, a, offset, np.where(norm > 0, norm, np.inf))

    def _pull(self, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """``(m,)`` px: the normalisation's first-order pull ``-s^2 c'/c`` along e from the
        field fractions ``c0`` and their derivatives ``c1``, kept within +-s (beyond that a
        first-order model does not hold), zero below ``PULL_TOL_PX``."""
        d = np.where(c0 > 0, -self.blur_px ** 2 * c1 / np.where(c0 > 0, c0, 1.0), 0.0)
        d = np.clip(d, -self.blur_px, self.blur_px)
        d[np.abs(d) <= PULL_TOL_PX] = 0.0
        return d

    # -- what the profile implies -------------------------------------------------------
    @property
    def profile(self) -> tuple[np.ndarray, np.ndarray]:
        """``(altitude_m (K+2,), density (K+2,))`` of the current estimate (unit light)."""
        return node_density(self.nodes_m, self.light)

    def spots(self) -> ProfileSpots:
        """Noise-free spots of the current profile for every subaperture (cached)."""
        if self._refs is None or self._refs[0] != self.version:
            ps = self._spots_of(self.light)
            self._refs = (self.version, ps, None, None)   # (version, spots, reference, image)
        return self._refs[1]

    def reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(image, d/dx, d/dy)``, each ``(n, p, p)``, unit light at zero shift, block axes."""
        spots = self.spots()
        if self._refs[2] is None:
            self._refs = (self._refs[0], spots, spots.reference(image=self._refs[3]), None)
        return self._refs[2]

    def reference_image(self) -> np.ndarray:
        """``(n, p, p)``: the image of :meth:`reference` alone (one render instead of five;
        what the CoG bias, the networks and the grid's filters start from)."""
        spots = self.spots()
        if self._refs[2] is not None:
            return self._refs[2][0]
        if self._refs[3] is None:
            self._refs = (*self._refs[:3], spots.image_at(np.zeros((self.n, 2))))
        return self._refs[3]

    def cog_bias(self) -> np.ndarray:
        """``(n, 2)`` CoG of each reference, px, block axes: a plain CoG's reading of a spot
        at the true centre, to subtract (cached per refit, read-only; a background refit
        computes it off the frame path)."""
        if self._bias is not None and self._bias[0] == self.version:
            return self._bias[1]
        out = self._cog(self.reference_image())
        out = np.where(np.isfinite(out), out, 0.0)
        out.flags.writeable = False
        self._bias = (self.version, out)
        return out

    def cog_response(self) -> ResponseMap:
        """The plain CoG's response to a shift of each reference, fitted over
        ``+-COG_RESPONSE_EXTENT_PX`` (block axes; :class:`.linearize.ResponseMap`): its
        value at 0 is :meth:`cog_bias`, its slope the gain the field's edge takes (a spot
        truncated by the field reads less than its shift). Cached per refit; a background
        refit fits it off the frame path when ``reads`` names it.

        On a polar detector a block's spot is the product of a function of block x and one
        of block y, and so is the field: the CoG along x depends on the shift along x
        alone. The scan's ``points^2`` positions then need ``points`` renders (the
        diagonal: each gives both axes) and give the same numbers. On a cartesian one each
        node's light is a line along one pixel axis times a core along the other, so the
        moments of all ``points^2`` positions come from ``2 points`` partial renders
        (:meth:`.SpotModel.cog_grid`, the same to ~1e-4 px). Full pupil, process time a
        refit: ~0.3 s polar, ~0.4 s cartesian on a quiet host (36 whole renders took
        ~2.7 s; beside two benchmark processes 0.8 s against 3.2 s)."""
        if self._response is not None and self._response[0] == self.version:
            return self._response[1]
        spots = self.spots()
        points, degree = COG_RESPONSE_GRID
        nodes = chebyshev_nodes(points, COG_RESPONSE_EXTENT_PX)
        if self.sensor.detector == "polar":     # (n, points, 2): each render gives both axes
            d = np.stack([self._cog(spots.image_at(np.full((self.n, 2), t))) for t in nodes], axis=1)
            grid = np.stack(np.broadcast_arrays(d[:, :, None, 0], d[:, None, :, 1]), axis=-1)
        else:
            grid = spots.model.cog_grid(nodes)     # block axes are the detector's
        # (n, points, points, 2): the CoG at (nodes[kx], nodes[ky])

        def scan(shift):
            kx, ky = (int(np.argmin(np.abs(nodes - shift[0, a]))) for a in (0, 1))
            return grid[:, kx, ky]
        out = ResponseMap.fit(scan, self.n, COG_RESPONSE_EXTENT_PX, points, degree)
        self._response = (self.version, out)
        return out

    def _cog(self, images: np.ndarray) -> np.ndarray:
        """``(n, 2)`` CoG of ``images (n, p, p)``, px from the block's centre, block axes
        (NaN where an image has no light)."""
        p = self.sensor.pixels
        y, x = np.indices((p, p), dtype=float)
        c = (p - 1) / 2
        w = np.stack([np.ones(p * p), x.ravel() - c, y.ravel() - c], axis=1)
        m = images.reshape(self.n, -1) @ w                                      # (n, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            return m[:, 1:] / m[:, :1]

    def counts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(image, d/dx, d/dy, flux)``: the reference in counts (the observed mean flux of
        each subaperture, ``sensor.photons`` before the first fit), background not included;
        ``flux (n,)``."""
        img, dx, dy = self.reference()
        scale = self._to_counts(img)
        return img * scale, dx * scale, dy * scale, self._flux()

    def reference_counts(self) -> np.ndarray:
        """``(n, p, p)``: :meth:`counts`' image alone (no derivative renders)."""
        img = self.reference_image()
        return img * self._to_counts(img)

    def image_at(self, shift_block: np.ndarray) -> np.ndarray:
        """``(n, p, p)`` noise-free counts of the current reference displaced by
        ``shift_block (n, 2)`` px (block axes), on the scale of :meth:`counts` (no shift:
        :meth:`reference_counts`, the same render, not made again)."""
        if not np.any(shift_block):
            return self.reference_counts()
        return self.spots().image_at(shift_block) * self._to_counts(self.reference_image())

    def marginals_at(self, shift_block: np.ndarray) -> np.ndarray:
        """``(n, 2, p)``: the column and row sums of :meth:`image_at`'s images, polar
        detector only (:meth:`.model_spot.ProfileSpots.marginals_at`: no image formed)."""
        return self.spots().marginals_at(shift_block) * self._to_counts(self.reference_image())

    def _flux(self) -> np.ndarray:
        """``(n,)`` the observed mean flux of each subaperture (``sensor.photons`` before
        the first fit)."""
        return np.full(self.n, float(self.sensor.photons)) if self.flux is None else self.flux

    def _to_counts(self, img0: np.ndarray) -> np.ndarray:
        """``(n, 1, 1)``: what scales images rendered as ``img0 (n, p, p)`` (unit light, the
        field's share of it) to counts at :meth:`_flux`."""
        tot = img0.reshape(self.n, -1).sum(axis=1)
        return (self._flux() / np.where(tot > 0, tot, 1.0))[:, None, None]

    @property
    def warning(self) -> str:
        """What this calibration cannot do on its sensor ('' when nothing): with a single
        radius a tilt along e that lasts longer than the memory is indistinguishable from
        the profile (measured on the paper's single subaperture with frozen flow: the
        calibrated estimators at 1.8-2.5x the plain CoG's error, docs/accuracy.md)."""
        radii = np.unique(np.round(np.asarray(self.layout.r_m, float), 2))
        if radii.size >= 2:
            return ""
        return (f"pupil calibration on {self.n} subaperture(s) at one radius: a tilt along the "
                f"elongation that outlasts its memory ({self.time_constant_s:g} s) enters the "
                f"profile and the references follow the spot (the paper's single subaperture "
                f"with frozen flow: 1.8-2.5x the plain cog's error, docs/accuracy.md); "
                f"independent tilts average out")

    def describe(self) -> dict:
        h, d = self.profile
        alt = float(harmonic_altitude(h, d))
        drift = None                          # the fitted altitude's move to the period's end
        if self.light_drift is not None:
            drift = round(float(harmonic_altitude(*node_density(self.nodes_m, self.light_drift))) - alt, 1)
        return {"fits": self.fits, "frames_seen": self._frames, "period": self.period,
                "asynchronous": self.asynchronous, "lag": self.lag,
                # wall s of the last refit: in its thread the fit and what the estimator
                # builds from it, inline the fit alone (the estimator's part follows)
                "last_refit_s": None if self.refit_s is None else round(self.refit_s, 3),
                # frames since the accumulators the profile in use was fitted from were
                # taken: what a live node's references lag behind the sky
                "profile_age_frames": self._frames - self._fit_end if self.fits else None,
                "tilt_blur_px": round(self.blur_px, 3),
                "time_constant_s": self.time_constant_s, "stride": self.stride,
                "trend": self.trend, "altitude_s": self.altitude_s,
                "nodes": int(self.nodes_m.size),
                "harmonic_altitude_m": round(alt, 1), "altitude_drift_m": drift}


def _node_shifted(arr: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """``arr (m, ..., K)`` with each row's node axis read ``nodes (m,)`` nodes further on
    (fractional: linear between nodes; zero beyond the last): the thin-layer spots of row s
    moved by ``nodes_s`` node steps, i.e. by ``nodes_s * delta_s`` px along e."""
    k = arr.shape[-1]
    lo = np.floor(nodes).astype(int)
    frac = nodes - lo
    shape = (arr.shape[0],) + (1,) * (arr.ndim - 2) + (k,)
    out = np.zeros(arr.shape)
    for off, weight in ((0, 1.0 - frac), (1, frac)):
        j = np.arange(k)[None, :] + (lo + off)[:, None]              # (m, K) columns read
        inside = (j >= 0) & (j < k)
        taken = np.take_along_axis(arr, np.clip(j, 0, k - 1).reshape(shape), axis=-1)
        out += taken * (inside * weight[:, None]).reshape(shape)
    return out


def _row_models(b_rows: np.ndarray, db: np.ndarray, rows: np.ndarray, d: np.ndarray,
                moved: np.ndarray, b_moved: np.ndarray, db_moved: np.ndarray) -> np.ndarray:
    """``(R, nb, K)``: the models ``B_s + d_s B'_s`` of ``rows (R,)`` (``b_rows (R, nb, K)``
    their basis, ``db (m, nb, K)`` every block's derivative, ``d (m,)`` px), with the basis
    of the blocks ``moved`` (a subset of ``rows``) replaced by ``b_moved`` and ``db_moved``."""
    bm, dbm = b_rows.copy(), db[rows]
    if moved.size:
        at = np.searchsorted(rows, moved)
        bm[at], dbm[at] = b_moved, db_moved
    dbm *= d[rows, None, None]
    bm += dbm
    return bm


def _row_gram(b_rows: np.ndarray, model: np.ndarray) -> np.ndarray:
    """``(K, K)``: what replacing the basis ``b_rows (R, nb, K)`` of some blocks by their
    ``model`` (the same shape) changes in the normal matrix: two products over those rows
    (none on a steady pupil's unmoved models)."""
    k = b_rows.shape[2]
    if b_rows.shape[0] == 0:
        return np.zeros((k, k))
    old, new = b_rows.reshape(-1, k), model.reshape(-1, k)
    return new.T @ new - old.T @ old


def _shift_steps(x: np.ndarray, v: np.ndarray, uw: np.ndarray, q: np.ndarray, a: float,
                 offset: float, norm: np.ndarray) -> np.ndarray:
    """``(m,)`` px: each block's shift beyond the held one at the solved profile ``x (K,)``
    (the variable projection's minimiser, :meth:`PupilCalibration._free_shift_terms`): its
    residual along ``u_s``, ``uw_s - V_s x``, less the constraint's share along ``q``; 0
    where the model has no derivative (``norm`` inf)."""
    res = uw - v @ x
    return (res - q * (q @ res + offset) / a) / norm


def _changed(x: np.ndarray, last: np.ndarray) -> float:
    """The largest change of a node's share of the light between two profiles ``(K,)``, as
    a fraction of the largest share."""
    a, b = x / max(x.sum(), 1e-300), last / max(last.sum(), 1e-300)
    return float(np.abs(a - b).max() / max(b.max(), 1e-300))


def _turned(g: np.ndarray, g_used: np.ndarray) -> float:
    """The largest change of direction (1 - cosine) between two sets of shift directions
    ``(m, nb)``, per row."""
    dot = np.einsum("sn,sn->s", g, g_used)
    nn = np.sqrt(np.einsum("sn,sn->s", g, g) * np.einsum("sn,sn->s", g_used, g_used))
    live = nn > 0
    return float(np.max(1.0 - dot[live] / nn[live], initial=0.0))


# The normalisation's pull below this (px) is not applied, and the solve stops once the pull
# its last iterate implies is within this of the one it used (one solve a refit when steady).
PULL_TOL_PX = 1e-3
SHIFT_TOL_PX = 0.02      # nor do the shifts the model is moved by (an error e costs ~e^2)
MAX_SHIFT_PX = 2.0       # the free shifts are kept within this
MOVE_AFTER = 3           # first-order solves before a model may move, if the profile
PROFILE_TOL = 0.01       # still changes by more than this (of its largest node) a solve,
STALL = 0.8              # and by more than this fraction of the solve before's change
MOVE_CORES = 1.0         # a shift beyond this many rms widths of the core moves the model
MAX_NODE_SHIFT = 0.25    # a block whose move would run this fraction of the nodes stays unmoved
FRACTION_TOL = 1e-4      # nor does the light inside each field (a fraction of the whole)
DIRECTION_TOL = 1e-6     # nor do the subapertures' shift directions (1 - cosine)

#: how many sets of projected thin-layer spots :func:`shared_hats` keeps (130 MB for the
#: full cartesian pupil: 2 x 2,784 blocks x 23 bins x 120 nodes)
HATS_KEPT = 2
_HATS: OrderedDict = OrderedDict()
_HATS_LOCK = threading.Lock()
#: process CPU seconds spent building shared bases (:func:`shared_hats`) so far: a benchmark
#: that times refits takes it out of the refit that happened to build one for everyone
HATS_BUILD_CPU_S = [0.0]
#: sensor fields a noise-free spot of unit light does not depend on
_NOT_OPTICS = ("photons", "read_noise_e", "background_e", "frame_rate_hz", "dtype", "r0_m",
               "r0_wavelength_m", "outer_scale_m", "wind_speed_mps", "wind_direction_deg")


def shared_hats(sensor, nodes_m: np.ndarray, build) -> tuple:
    """``build(sensor)``'s read-only arrays, built once for every calibration of the same
    optics and nodes in this process (the benchmark's and replay's many estimators, a
    centroider switched at run time: each first refit rendered them anew, 2-20 s); the
    :data:`HATS_KEPT` latest are kept. Photometry, noise, frame rate and turbulence do
    not enter the key: a spot of unit light does not depend on them."""
    defaults = {f.name: f.default for f in dataclasses.fields(sensor) if f.name in _NOT_OPTICS}
    key = (sensor.replace(**defaults), np.asarray(nodes_m, dtype=np.float64).tobytes())
    with _HATS_LOCK:
        if key in _HATS:
            _HATS.move_to_end(key)
            return _HATS[key]
    t0 = time.process_time()
    out = tuple(build(sensor))
    HATS_BUILD_CPU_S[0] += time.process_time() - t0
    for a in out:
        a.flags.writeable = False
    with _HATS_LOCK:
        _HATS[key] = out
        while len(_HATS) > HATS_KEPT:
            _HATS.popitem(last=False)
    return out


# What a background refit changes (installed at a frame boundary, see PupilCalibration._poll).
_FIT_STATE = ("state", "state_slow", "flux", "_state_ok", "light", "fits", "version", "_refs",
              "refit_s", "_fit_end",
              "_bias", "_response", "blur_px", "_basis", "_dbasis", "_colsum", "_dcolsum",
              "_gram", "_rough", "_spread", "light_drift", "_drift_at", "_drift_refs",
              "_drift_margs", "_ref_margs")

# The CoG's response (cog_response): scanned over +-1.4 px per block axis (3 sigma of the
# shifts a closed loop leaves, 0.46 px rms per axis; a corner, rotated to the detector's
# axes, stays inside the spots' 2 px margin; beyond it the CoG falls back on its bias) on a
# 6 x 6 Chebyshev grid, degree 4 per axis (36 renders a refit; 8 x 8 and degree 6 took
# twice as long for 1e-3 px: the inversions agreed to 0.005 px on truncated spots).
COG_RESPONSE_EXTENT_PX = 1.4
COG_RESPONSE_GRID = (6, 4)

# Options every estimator that uses the calibration takes (names as in options.py).
OPTION_DEFAULTS = {"pupil_period": 140, "pupil_time_constant_s": 0.3, "pupil_stride": 1,
                   "pupil_async": False, "pupil_async_lag": 0, "pupil_trend": True,
                   "pupil_altitude_s": 0.0}


def from_options(sensor, options: dict, background: float) -> PupilCalibration:
    """The calibration an estimator's ``pupil_*`` options describe."""
    o = {**OPTION_DEFAULTS, **{k: v for k, v in options.items() if k in OPTION_DEFAULTS}}
    return PupilCalibration(sensor, period=o["pupil_period"],
                            time_constant_s=o["pupil_time_constant_s"], stride=o["pupil_stride"],
                            background=background, asynchronous=o["pupil_async"],
                            lag=o["pupil_async_lag"], trend=o["pupil_trend"],
                            altitude_s=o["pupil_altitude_s"])


def describe_into(d: dict, pupil: PupilCalibration) -> dict:
    """``d`` (a centroider's description) with ``pupil``'s under ``pupil_calibration`` and its
    :attr:`PupilCalibration.warning`, if any, joined to ``d["warning"]`` (a node logs it)."""
    d["pupil_calibration"] = pupil.describe()
    if pupil.warning:
        d["warning"] = "; ".join(w for w in (d.get("warning"), pupil.warning) if w)
    return d


__all__ = ["PupilCalibration", "OPTION_DEFAULTS", "from_options", "describe_into"]
