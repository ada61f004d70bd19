"""Correlation centroiding against a reference image, with a 3 x 3 parabolic peak fit.

For each subaperture the image ``x`` (background removed) is cross-correlated with its
reference ``r`` by FFT, ``c(tau) = sum_u x(u + tau) r(u)`` (zero-padded by ``padding``:
2 = linear correlation, 1 = circular), so the peak sits at the displacement of the image
relative to the reference. The peak is located to a whole lag by the maximum, then
refined by a 2-D quadratic through the 3 x 3 neighbourhood, fitted to the log of the map
(``peak="gauss"``, default: a 3-point Gaussian fit) or to the map (``peak="parabola"``), or
by a (thresholded) centre of gravity of the whole map (``peak="cog"``, aotools' method).

The reference comes from :class:`.reference.ReferenceSource` (the CMF's sources:
"history", "static" with ``set_reference`` — e.g. ``cmf.reference`` — or "model") and is
taken to sit at the subaperture centre (see :mod:`.reference`).

aotools' ``correlation_centroid`` reports the fftshifted map's CoG from index 0, whose
zero lag is at ``p/2`` (8 for 16 px) whatever the padding: ``ours = aotools - p/2``.
It also subtracts each image's and the reference's minimum first (``subtract_min=True``
here) and takes ``abs`` of the inverse FFT (identical for non-negative images).

Cost: the FFT maps take ~50 ms a full frame, the compiled pass ~0.75-0.8 ms (0.91-0.94 ms
the whole per-frame part with the pupil calibration's accumulation, 2026-11-29). An integer
frame with a fixed reference (the default pupil one), linear correlation and the 3 x 3 fits
goes through one compiled pass instead (:func:`.kernels.corr_peak`): only the 9 lags the
fit reads are evaluated, in one sweep over the reference, around the whole lag next to the CoG's
prediction where a spot like the reference would peak (the metric of the reference's own
correlation: on a spot elongated along a pixel diagonal the nearest whole lag is often a
step off), moved to the local maximum if it is not one, the reference read as int16 (one
scale a block, which the fit does not see). Where the map has one maximum that is the map's
fit (polar pixels: equal to 1e-4 px, the float32 sums and the int16 reference); where a
spot elongated across the pixel axes makes a ridge with several local maxima (0.7 % of the
full cartesian pupil's blocks, at the field's edge, on the simulator's frames) it is the
one that start climbs to, no further from the truth than the map's largest.
"""

from __future__ import annotations

import copy

import numpy as np

from . import kernels
from . import pupil as pupil_cal
from .base import Centroider, check_options, choice, finite_rows, flag, number
from .cmf import CMF
from .reference import ReferenceSource


class Correlation(Centroider):
    """Correlation centroider.

    Options:
        reference, history, include_current, update_period, sodium_fwhm_m, pupil_period,
            pupil_time_constant_s, pupil_stride: as :class:`CMF` (default reference
            "pupil": the spot of the profile estimated from the whole pupil; "history"
            is the paper's 5-frame mean).
        peak: "gauss" (default: 3 x 3 quadratic fit to the log of the map, exact for
            Gaussian peaks) | "parabola" (the same fit to the map itself; peak-locking
            of 0.05 px for sigma = 1 px spots, 0.11 px for the 1.19 px-FWHM core) |
            "cog" (CoG of the map, aotools).
        threshold: for ``peak="cog"``: fraction of the map maximum subtracted (aotools), 0.
        padding: 1 (circular) or 2 (linear, default).
        subtract_min: subtract each image's and reference's minimum first (False).
        background: counts per pixel removed from images and reference (sensor's).
    """

    name = "corr"
    _allowed = ("reference", "history", "include_current", "update_period", "sodium_fwhm_m",
                "peak", "threshold", "padding", "subtract_min", "background",
                *pupil_cal.OPTION_DEFAULTS)

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._allowed)
        o = {"reference": "pupil", "history": 5, "include_current": True, "update_period": 1,
             "sodium_fwhm_m": 10e3, "peak": "gauss", "threshold": 0.0, "padding": 2,
             "subtract_min": False, "background": float(sensor.background_e),
             **pupil_cal.OPTION_DEFAULTS}
        o.update(options)
        super().__init__(sensor, **o)
        self.peak = choice("peak", o["peak"], ("parabola", "gauss", "cog"))
        self.threshold = number("threshold", o["threshold"], minimum=0)
        if self.threshold >= 1:
            raise ValueError(f"option threshold must be in [0, 1), got {self.threshold}")
        self.padding = int(choice("padding", o["padding"], (1, 2)))
        self.subtract_min = flag("subtract_min", o["subtract_min"])
        self.background = number("background", o["background"], minimum=0)
        model = None
        if o["reference"] == "model":
            helper = CMF(sensor, reference="history")
            model = helper.model_reference(number("sodium_fwhm_m", o["sodium_fwhm_m"], minimum=0))
        self.ref = ReferenceSource(self.n, self.p, o["reference"], o["history"],
                                   o["include_current"], o["update_period"], model)
        self._ref_version = self._ok_version = -1
        self.pupil = None
        if o["reference"] == "pupil":
            self.pupil = pupil_cal.from_options(sensor, o, self.background)
            self._take_pupil_reference()
            if self.pupil.asynchronous:      # the references' maps and rows off the frame path
                self.pupil.delegate(self._prepare_pupil, ("drift_counts",))

    def _take_pupil_reference(self) -> None:
        """The calibration's current references (counts plus the background), and the drift
        of their reading to follow (:meth:`Centroider._follow_drift`)."""
        self.ref.set(self.pupil.reference_counts() + self.background)
        self._follow_drift(self._drift_reading)

    # what a background refit builds and the frame path swaps in (see _prepare_pupil)
    _REFIT_STATE = ("ref", "_drift", "_ok_version", "_ref_ok", "_ref_version", "_fr",
                    "_kernel_version", "_kernel_ref")

    def _prepare_pupil(self, calibration) -> dict:
        """Run in the refit thread on the refitted ``calibration`` (a snapshot): a shallow
        copy of this centroider with its own reference takes the new references, their
        validity, the compiled pass's rows and the drift's reading (on the install frame
        these held a full cartesian pupil's frame path 0.11-0.17 s, 2026-11-29); returns the
        attributes to swap in. Nothing the frame path uses is written."""
        sh = self._copy_on(calibration, ref=copy.copy(self.ref))
        sh._take_pupil_reference()
        sh._ref_kernel()
        return {k: sh.__dict__[k] for k in self._REFIT_STATE if k in sh.__dict__}

    def _pupil_refitted(self) -> None:
        """Install what a refit gives: inline, the references (their maps and rows built
        here); from a background refit, what its thread built."""
        self._take_refit(self._take_pupil_reference)

    def set_reference(self, images) -> None:
        """Install a static reference ``(n_valid, p, p)`` counts, block pixel axes."""
        self.ref.set(images)

    @property
    def reference(self):
        return None if self.ref.images is None else self.ref.images.copy()

    def reset(self) -> None:
        self.ref.reset()
        if self.pupil is not None:
            self.pupil.reset()
            self._take_pupil_reference()
        self._ref_version = self._ok_version = -1

    def describe(self) -> dict:
        d = super().describe()
        if self.pupil is not None:
            pupil_cal.describe_into(d, self.pupil)
        return d

    def centroid(self, data) -> np.ndarray:
        """As :meth:`Centroider.centroid`. An integer frame with a fixed reference (pupil,
        static, model), linear correlation and a 3 x 3 peak fit goes through one compiled
        pass (:func:`.kernels.corr_peak`: the map only at the 3 x 3 lags around the peak,
        found from the CoG, instead of the whole FFT map; the same values and fit where the
        map has one maximum); anything else through the FFT maps."""
        if not (kernels.fits(data, self.sensor.frame_shape) and self.padding == 2
                and self.peak != "cog" and not self.subtract_min
                and self.ref.source != "history" and self.ref.images is not None):
            return super().centroid(data)
        if self.pupil is not None and self.pupil.observe_frame(data):
            self._pupil_refitted()
        self.ref.frames += 1
        refs, ref_cog = self._ref_kernel()
        out = kernels.corr_peak(data, kernels.origins(self), self.p, refs, ref_cog,
                                self.background, log=self.peak == "gauss")
        return self.finish(out, finite_rows(out) & self._ref_ok)

    def _ref_kernel(self):
        """``(refw, ref_cog (n, 2))``: the references less the background, laid out for
        :func:`.kernels.corr_peak` (``refw``: the ``(rows, spans, metric)`` of
        :func:`.kernels.corr_rows`), and their CoGs (px from the block centre)."""
        self._ref_valid()                            # the references' validity, cached
        if getattr(self, "_kernel_version", None) != self.ref.version:
            ref = self._prep(np.asarray(self.ref.images, dtype=float))
            ref = np.where(self._ref_ok[:, None, None], ref, 0.0)
            tot = ref.sum(axis=(1, 2))
            pos = np.arange(self.p) - self.centre
            with np.errstate(divide="ignore", invalid="ignore"):
                cog = np.stack([ref.sum(axis=1) @ pos, ref.sum(axis=2) @ pos], 1) / tot[:, None]
            self._kernel_ref = (kernels.corr_rows(ref), np.nan_to_num(cog))
            self._kernel_version = self.ref.version
        return self._kernel_ref

    def _prep(self, img):
        img = img - self.background if self.background else img
        if self.subtract_min:
            img = img - img.min(axis=(1, 2), keepdims=True)
        return img

    def _ref_valid(self) -> np.ndarray:
        """``(n,)`` bool: the references that can be read (finite, a positive total less the
        background), cached per reference version."""
        if self._ok_version != self.ref.version:
            ref = self._prep(np.asarray(self.ref.images, dtype=float))
            self._ref_ok = np.isfinite(ref).all(axis=(1, 2)) & (ref.sum(axis=(1, 2)) > 0)
            self._ok_version = self.ref.version
        return self._ref_ok

    def _ref_fft(self):
        """The references' conjugate FFTs ``(n, P, P // 2 + 1)`` (zero where unusable),
        cached per reference version (only the FFT maps read them)."""
        if self._ref_version != self.ref.version:
            size = (self.p * self.padding,) * 2
            ref = self._prep(np.asarray(self.ref.images, dtype=float))
            ok = self._ref_valid()
            self._fr = np.conj(np.fft.rfft2(np.where(ok[:, None, None], ref, 0.0), s=size))
            self._ref_version = self.ref.version
        return self._fr

    def correlation_map(self, stack, rows=None) -> np.ndarray:
        """``(n, P, P)`` fftshifted correlation maps, ``P = p * padding``; zero lag at ``P/2``
        (``rows``: the blocks ``stack`` holds, an index into the references; all by default)."""
        size = (self.p * self.padding,) * 2
        fx = np.fft.rfft2(self._prep(np.asarray(stack, dtype=float)), s=size)
        fr = self._ref_fft() if rows is None else self._ref_fft()[rows]
        c = np.fft.irfft2(fx * fr, s=size)
        return np.fft.fftshift(c, axes=(1, 2))

    def _centroid_pixels(self, stack, total, ok):
        if self.pupil is not None and self.pupil.observe(stack.reshape(self.n, -1), ok):
            self._pupil_refitted()
        self.ref.observe(stack, ok)
        return self._map_reading(stack)

    def _map_reading(self, stack) -> np.ndarray:
        """``(n, 2)`` block axes, px: the correlation maps' peaks of ``stack (n, p, p)``
        against the current references (NaN where a reference is unusable)."""
        c = self.correlation_map(stack)
        big = c.shape[-1]
        if self.peak == "cog":
            out = _map_cog(c, self.threshold) - big / 2
        else:
            out = _parabola_peak(c, log=self.peak == "gauss") - big / 2
        out[~self._ref_valid()] = np.nan
        return out

    def _drift_reading(self, counts: np.ndarray) -> np.ndarray:
        """``(n, 2)`` block axes, px: :meth:`_map_reading` of noise-free ``counts (n, p, p)``
        (no background) near their references, as :meth:`_follow_drift` reads a refit's
        drifted and current spots: the quadratic through the map at the 3 x 3 lags around
        zero, summed directly, wherever the centre is their largest (a spot within half a
        pixel of its reference: the whole map's maximum there); the whole maps for the other
        blocks, and for any peak fit but the quadratic or a circular map. Two FFT map sets
        of a full cartesian pupil take ~0.1 s; this ~0.01 s (2026-11-29)."""
        if self.peak == "cog" or self.padding != 2:
            return self._map_reading(counts + self.background)
        x = self._prep(np.asarray(counts, dtype=float) + self.background)
        block = kernels.lags_around_zero(x, self._prep(np.asarray(self.ref.images, dtype=float)))
        out = _vertex(block, log=self.peak == "gauss")
        far = np.flatnonzero(block.argmax(axis=1) != 4)
        if far.size:
            big = self.p * self.padding
            c = self.correlation_map(np.asarray(counts, dtype=float)[far] + self.background,
                                     rows=far)
            out[far] = _parabola_peak(c, log=self.peak == "gauss") - big / 2
        out[~self._ref_valid()] = np.nan
        return out


def _map_cog(c: np.ndarray, threshold: float) -> np.ndarray:
    """``(n, 2)`` (x, y) CoG of ``(n, P, P)`` maps from index 0, aotools' thresholding."""
    if threshold > 0:
        t = threshold * c.max(axis=(1, 2), keepdims=True)
        c = np.where(c > t, c - t, 0.0)
    big = c.shape[-1]
    idx = np.arange(big, dtype=float)
    tot = c.sum(axis=(1, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (c.sum(axis=1) @ idx) / tot
        y = (c.sum(axis=2) @ idx) / tot
    return np.stack([x, y], axis=1)


_OFFSETS = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])   # (9, 2) row-major


def _parabola_peak(c: np.ndarray, log: bool = False) -> np.ndarray:
    """``(n, 2)`` (x, y) sub-lag peak positions from the 3 x 3 block around the maximum.

    The vertex of the 2-D quadratic through the centre and its four neighbours (the
    classic 3-point parabolas) with the cross term from the four corners, so that a peak
    ridge tilted along ``e`` is handled. With ``log`` the quadratic is fitted to the log
    of the map (a 3-point Gaussian fit; blocks with a non-positive value fall back to the
    plain fit). Offsets are clipped to +-1 lag; where the quadratic has no maximum the
    1-D parabolas along x and y are used.
    """
    n, big, _ = c.shape
    flat = c.reshape(n, -1).argmax(axis=1)
    iy, ix = np.divmod(flat, big)
    rows = np.arange(n)[:, None]
    yy = (iy[:, None] + _OFFSETS[:, 0]) % big
    xx = (ix[:, None] + _OFFSETS[:, 1]) % big
    return np.stack([ix, iy], axis=1) + _vertex(c[rows, yy, xx], log)


def _vertex(block: np.ndarray, log: bool = False) -> np.ndarray:
    """``(n, 2)`` (x, y) offsets, lags, of the quadratic's vertex from the centre of the
    3 x 3 values ``block (n, 9)`` (row-major, as ``_OFFSETS``): :func:`_parabola_peak`'s fit."""
    if log:
        positive = (block > 0).all(axis=1)
        block = np.where(positive[:, None], np.log(np.where(block > 0, block, 1.0)), block)
    b = (block[:, 5] - block[:, 3]) / 2
    d = (block[:, 5] + block[:, 3]) / 2 - block[:, 4]
    cc = (block[:, 7] - block[:, 1]) / 2
    f = (block[:, 7] + block[:, 1]) / 2 - block[:, 4]
    e = (block[:, 8] - block[:, 6] - block[:, 2] + block[:, 0]) / 4
    det = 4 * d * f - e * e
    with np.errstate(divide="ignore", invalid="ignore"):
        dx2 = (e * cc - 2 * f * b) / det
        dy2 = (e * b - 2 * d * cc) / det
        dx1 = np.where(d < 0, -b / (2 * d), 0.0)
        dy1 = np.where(f < 0, -cc / (2 * f), 0.0)
    peak = (d < 0) & (det > 0)
    dx = np.clip(np.where(peak, dx2, dx1), -1, 1)
    dy = np.clip(np.where(peak, dy2, dy1), -1, 1)
    return np.stack([dx, dy], axis=1)
