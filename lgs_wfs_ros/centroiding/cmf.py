"""Constrained matched filter (Gilles & Ellerbroek 2008), vectorised over subapertures.

For each subaperture, with the unit-flux reference ``T = ref / sum(ref)`` (background
removed) and its derivatives ``gx, gy`` (0.02 px Fourier dither, see
:mod:`.reference`), the design matrix is (``pp = p*p`` rows)::

    A = [gx, gy, T, T(+c x), T(-c x), T(+c y), T(-c y)]       (pp, 7)   constrained
    A = [gx, gy, T]                                            (pp, 3)   constrained=False
    M = [[1, 0, 0,  c, -c, 0,  0],
         [0, 1, 0,  0,  0, c, -c]]                             (2, 7)

(``T(+c x)`` = the reference shifted by ``c`` = ``constraint_px`` = 1 whole pixel,
zero-filled.) The filter is ``R = M (A^T W A)^+ A^T W`` so that ``R A = M``: unit gain,
insensitivity to flux (``R T = 0``) and the right answer for the reference shifted by
+-1 px (the linearity constraints of the CMF). ``W = diag(1 / v)`` with the pixel
variance ``v`` (counts^2) from the image being processed (``weighting="image"``, the
paper's choice) or from the reference model (``"model"``), plus ``background`` and
``read_noise^2``, floored at ``var_floor``.

The slope is ``R x / sum(x)`` for the background-subtracted image ``x`` (so the filter
gain does not depend on the flux), i.e. ``R/F`` is the filter in counts, and the
predicted noise-equivalent angle is ``NEA = (R/F) W^-1 (R/F)^T`` px^2 (``F`` the image
flux), available after each call as :attr:`CMF.nea` (``(n, 2, 2)``, detector axes).

Linearisation (``linearize=True``, static or model reference): the filter's non-linear
response between the constraint points (0.02 px at +-0.5 px, 0.2 px in the +-1 px corners
for the 1.19 px core) is calibrated once on noise-free shifted references and inverted per
frame (:mod:`.linearize`), which makes the CMF exact to ~1e-3 px over +-1 px.

Cost: with ``weighting="model"`` and a static reference (or ``update_period`` > 1 with
model weighting) the per-frame work is one ``(n, 2, pp)`` contraction (compiled, with the
flux, :func:`.kernels.filter_flux`) and, linearised, one compiled inversion pass
(:func:`.kernels.invert_response`); the paper's setting (history reference, image
weighting) rebuilds every filter every frame.

This class is ``cmf``'s single filter (``filters="single"``, or any reference but the
pupil's). With the pupil reference ``cmf`` is by default a grid of such filters built at
reference positions around the spot, the nearest applied (:class:`.gmf.GridCMF`): a filter
loses efficiency as the spot moves from its reference (1.1-3x the Cramer-Rao bound under
0.46 px rms tilts on unseen profiles, against 1.02-1.08x for the grid; docs/accuracy.md).
"""

from __future__ import annotations

import copy

import numpy as np

from ..optics.gaussian_spot import elongation_fwhm_px, model_spots
from . import kernels
from .base import Centroider, check_options, choice, finite_rows, flag, number
from . import pupil as pupil_cal
from .linearize import ResponseMap, transform_covariance
from .reference import ReferenceSource, fourier_derivatives, integer_shift


def design(template: np.ndarray, dither: float = 0.02, constrained: bool = True,
           constraint_px: int = 1, derivatives=None, out=None) -> tuple[np.ndarray, np.ndarray]:
    """Design matrix and constraint matrix of the (constrained) matched filter.

    Args:
        template: ``(n, p, p)`` reference images (any flux scale).
        dither: derivative dither, pixels.
        constrained: add the +-``constraint_px`` shifted references.
        derivatives: optional ``(gx, gy)`` ``(n, p, p)`` to use instead of the Fourier
            dither of ``template`` (same flux scale as ``template``).
        out: optional ``(n, k, p*p)`` float64 buffer to fill (saves a large allocation
            per frame when the filter is rebuilt every frame).

    Returns:
        ``A (n, p*p, k)`` and ``M (2, k)`` with ``k`` = 7 (constrained) or 3.
    """
    n, p, _ = template.shape
    gx, gy = fourier_derivatives(template, dither) if derivatives is None else derivatives
    cols = [gx, gy, template]
    m = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    if constrained:
        c = int(constraint_px)
        cols += [integer_shift(template, c, 0), integer_shift(template, -c, 0),
                 integer_shift(template, 0, c), integer_shift(template, 0, -c)]
        m[0] += [c, -c, 0.0, 0.0]
        m[1] += [0.0, 0.0, c, -c]
    k = len(cols)
    if out is None or out.shape != (n, k, p * p):
        out = np.empty((n, k, p * p))
    for j, col in enumerate(cols):                                      # (n, k, pp)
        out[:, j, :] = col.reshape(n, p * p)
    return np.swapaxes(out, 1, 2), np.array(m)


def solve_filter(a: np.ndarray, m: np.ndarray, var: np.ndarray, work=None) -> tuple[np.ndarray, np.ndarray]:
    """``R = M (A^T W A)^+ A^T W`` for every subaperture.

    Args:
        a: ``(n, pp, k)`` design matrices.
        m: ``(2, k)`` constraint values.
        var: ``(n, pp)`` pixel variances (``W = 1/var``), > 0.
        work: optional ``(n, k, pp)`` float64 scratch buffer.

    Returns:
        ``R (n, 2, pp)`` and ``ok (n,)``: True where ``R A = M`` holds (to 1e-6).
    """
    at = np.swapaxes(a, 1, 2)                                      # (n, k, pp), a view
    if work is None or work.shape != at.shape:
        work = np.empty(at.shape)
    atw = np.divide(at, var[:, None, :], out=work)
    g = atw @ a                                                    # (n, k, k)
    # Scale to unit diagonal (conditioning); singular subapertures (e.g. an empty
    # reference) get the pseudo-inverse.
    d = np.sqrt(np.einsum("nkk->nk", g))
    good = np.all(d > 0, axis=1) & np.all(np.isfinite(g), axis=(1, 2))
    d = np.where(good[:, None], d, 1.0)
    gs = g / d[:, :, None] / d[:, None, :]
    gs[~good] = np.eye(g.shape[1])
    try:
        gi = np.linalg.inv(gs)
    except np.linalg.LinAlgError:
        gi = np.linalg.pinv(gs, rcond=1e-12, hermitian=True)
    gi = gi / d[:, :, None] / d[:, None, :]
    r = (m @ gi) @ atw                                             # (n, 2, pp)
    resid = np.abs(r @ a - m).max(axis=(1, 2))
    scale = np.abs(m).max()
    ok = good & np.isfinite(resid) & (resid <= 1e-6 * scale)
    return r, ok


#: ``cmf``'s ``filters`` option: one filter per subaperture at its reference (single, this
#: class), filters at a grid of reference positions (grid, :class:`.gmf.GridCMF`), or auto:
#: grid with the pupil reference, single with any other
FILTERS = ("auto", "grid", "single")
#: the grid's options and defaults (:class:`.gmf.GMF`)
GRID_DEFAULTS = {"grid": 5, "spacing_px": 0.5, "picks": 2}


def uses_grid(options) -> bool:
    """True when ``cmf`` options ask for the grid of filters: ``filters`` "grid", or "auto"
    (the default) with the pupil reference (the default)."""
    filters = options.get("filters", "auto")
    return filters == "grid" or (filters == "auto" and options.get("reference", "pupil") == "pupil")


class CMF(Centroider):
    """Constrained matched filter (``constrained=False``: plain matched filter).

    Options:
        filters: "single" (this class; "auto" is accepted and means single here: the registry
            builds :class:`.gmf.GridCMF` for auto with the pupil reference). ``grid``,
            ``spacing_px``, ``picks`` are the grid's and accepted at their defaults only.
        reference: "pupil" (default: the spot of the profile estimated from the whole
            pupil, :mod:`.pupil`, with exact derivatives, refreshed every
            ``pupil_period`` frames) | "history" (the paper's) | "static"
            (``set_reference``) | "model".
        pupil_async: refit in a background thread (the new reference, filter and response
            are built there and swapped in at a frame boundary; not reproducible frame for
            frame) instead of inline at the end of each period (False); with
            ``pupil_async_lag`` N > 0 each refit is installed exactly N frames after it
            started (waited for if late): reproducible.
        pupil_period, pupil_time_constant_s, pupil_stride, pupil_trend: the pupil
            calibration's refit period (frames), memory (s), accumulation stride (frames)
            and drift extrapolation (:class:`.pupil.PupilCalibration`).
        history: frames in the history mean (5).
        include_current: the measured frame is part of the history (True, paper).
        update_period: reference/derivatives refreshed every N frames (1).
        dither: derivative dither in px (0.02, paper).
        constrained: True (CMF) | False (plain MF with flux column).
        constraint_px: whole-pixel shift of the linearity constraints (1).
        weighting: "auto" (default: "image" with a history reference, the paper's; else
            "model", whose filter is fixed between reference updates) | "image" | "model".
        read_noise_e, background: counts; default the sensor's.
        var_floor: lower bound on the pixel variance, counts^2 (1.0).
        sodium_fwhm_m: layer thickness for ``reference="model"`` (10 km).
        derivative: "fourier" (Fourier-shift dither of the reference, or the derivative
            images given to ``set_reference``) | "dither" (the paper's: dithered images
            supplied with :meth:`push_dither`, averaged over the last ``history`` pushes).
        linearize: invert the calibrated response (True). Applies to fixed references
            (static, model, pupil) with Fourier derivatives and is off otherwise; the model
            and pupil references calibrate themselves, a static one needs
            :meth:`calibrate_response`.
        linearize_extent: half-width of the calibrated box, px (1.1).
    """

    name = "cmf"
    #: the options only this single filter takes, with their defaults (``filters="grid"``
    #: accepts them at these values only: :class:`.gmf.GridCMF`)
    SINGLE_DEFAULTS = {"reference": "pupil", "history": 5, "include_current": True,
                       "update_period": 1, "dither": 0.02, "constrained": True,
                       "constraint_px": 1, "weighting": "auto", "sodium_fwhm_m": 10e3,
                       "derivative": "fourier", "linearize": True, "linearize_extent": 1.1}
    _allowed = (*SINGLE_DEFAULTS, "read_noise_e", "background", "var_floor", "filters",
                *GRID_DEFAULTS, *pupil_cal.OPTION_DEFAULTS)

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._allowed)
        filters = choice("filters", options.pop("filters", "single"), FILTERS)
        if filters == "grid":
            raise ValueError("cmf: this class is the single filter; filters=grid is "
                             "gmf.GridCMF (make_centroider('cmf', ...) picks it)")
        for key, default in GRID_DEFAULTS.items():
            if options.pop(key, default) != default:
                raise ValueError(f"cmf: option {key} applies to filters=grid, not to the "
                                 f"single filter (filters={filters})")
        kernels.warm_up()
        o = {**self.SINGLE_DEFAULTS, "read_noise_e": float(sensor.read_noise_e),
             "background": float(sensor.background_e), "var_floor": 1.0,
             **pupil_cal.OPTION_DEFAULTS}
        o.update(options)
        super().__init__(sensor, **o)
        self.options["filters"] = "single"
        self.dither = number("dither", o["dither"], minimum=0, strict=True)
        self.constrained = flag("constrained", o["constrained"])
        self.constraint_px = number("constraint_px", o["constraint_px"], minimum=1, integer=True)
        if self.constraint_px >= self.p:
            raise ValueError(f"option constraint_px must be < {self.p} pixels")
        self.weighting = choice("weighting", o["weighting"], ("auto", "image", "model"))
        if self.weighting == "auto":            # the paper's image weighting with a history
            self.weighting = "image" if o["reference"] == "history" else "model"
        self.read_noise = number("read_noise_e", o["read_noise_e"], minimum=0)
        self.background = number("background", o["background"], minimum=0)
        self.var_floor = number("var_floor", o["var_floor"], minimum=0, strict=True)
        self.derivative = choice("derivative", o["derivative"], ("fourier", "dither"))
        # a reference that changes every frame (history) or pushed dither derivatives
        # would need a new calibration every frame: linearize applies to fixed references
        self.linearize = flag("linearize", o["linearize"]) and o["reference"] != "history" \
            and self.derivative == "fourier"
        self.linearize_extent = number("linearize_extent", o["linearize_extent"], minimum=0, strict=True)
        self._dithers = []
        self._image_at = None
        self._response = None
        model = None
        if o["reference"] == "model":
            fwhm = number("sodium_fwhm_m", o["sodium_fwhm_m"], minimum=0)
            model = self.model_reference(fwhm)
            self._image_at = lambda shift: self.model_images(fwhm, shift)
        self.ref = ReferenceSource(self.n, self.p, o["reference"], o["history"],
                                   o["include_current"], o["update_period"], model)
        self._nea_state = None
        self._built_version = -1
        self.pupil = None
        if o["reference"] == "pupil":
            self.pupil = pupil_cal.from_options(sensor, o, self.background)
            self._install_pupil()
            if self.pupil.asynchronous:      # the filter and its response built off the frame path
                self.pupil.delegate(self._prepare_pupil, ("drift_counts",))
        if self.linearize and self._image_at is not None:
            self.calibrate_response()        # at construction, not on a live node's first frame
        if self.weighting == "model" and self.ref.images is not None \
                and self.derivative == "fourier":     # dither derivatives come with frames
            # the filter too (~0.2 s for the full pupil): built on the first frame, it held
            # a live node's first frame that long and queued ~250 frames behind it at 800 Hz
            self._model_filter()

    # -- pupil reference ----------------------------------------------------------------
    def _install_pupil(self) -> None:
        """Install the calibration's current reference (counts + background) and renderer."""
        img, dx, dy, _ = self.pupil.counts()
        self.ref.set(img + self.background, dx, dy)
        self._image_at = lambda shift: self.pupil.image_at(shift) + self.background

    def _observe_pupil(self, flat) -> None:
        """Feed one frame's ``(n, p*p)`` counts (background included) to the calibration;
        a refit installs the new reference."""
        if self.pupil is not None and self.pupil.observe(flat):
            self._pupil_refitted()

    def _pupil_refitted(self) -> None:
        """Install what a refit gives: inline, the reference (the filter and its response
        are rebuilt lazily); from a background refit, the filter and response it built."""
        self._take_refit(self._install_pupil)

    # what a background refit builds and the frame path swaps in (see _prepare_pupil)
    _REFIT_STATE = ("ref", "A", "M", "_at_buf", "_ref_ok", "_ref_counts", "_built_version",
                    "_model_R", "_response", "_response_version", "_image_at")

    def _prepare_pupil(self, calibration) -> dict:
        """Run in the refit thread on the refitted ``calibration`` (a snapshot): a shallow
        copy of this centroider with its own reference, design buffers and filter builds
        the new reference, filter and response calibration; returns the attributes to
        swap in. Nothing the frame path uses is written."""
        sh = self._copy_on(calibration, ref=copy.copy(self.ref), _at_buf=None, _work=None,
                           _model_R=None)
        sh._install_pupil()
        sh._rebuild_design()
        if sh.weighting == "model":
            sh._model_filter()
        if sh.linearize:
            sh.calibrate_response()
        return {k: sh.__dict__[k] for k in self._REFIT_STATE if k in sh.__dict__}

    def model_reference(self, sodium_fwhm_m: float) -> np.ndarray:
        """``(n, p, p)`` centred model spots, ``sensor.photons`` counts plus the background,
        block pixel axes."""
        return self.model_images(sodium_fwhm_m, np.zeros((self.n, 2)))

    def model_images(self, sodium_fwhm_m: float, shift: np.ndarray) -> np.ndarray:
        """``(n, p, p)`` model spots displaced by ``shift (n, 2)`` px (block pixel axes),
        counts as :meth:`model_reference`."""
        core = np.full(self.n, self.sensor.core_fwhm_px)
        par = np.hypot(core, elongation_fwhm_px(self.sensor, sodium_fwhm_m))
        img = model_spots(self.p, self.e_pixel, core, par, np.asarray(shift, dtype=float))
        return img * self.sensor.photons + self.background

    # -- response linearisation ---------------------------------------------------------
    def calibrate_response(self, image_at=None, points: int | None = None,
                           degree: int | None = None) -> float:
        """Scan the filter's response on noise-free shifted references and fit it.

        Args:
            image_at: callable ``shift (n, 2) px -> (n, p, p)`` noise-free images of the
                reference displaced by ``shift`` (block pixel axes, counts with the
                background, as the frames); default the model images of
                ``reference="model"``. Kept, and re-run after a new ``set_reference``.
            points, degree: scan grid per axis and Chebyshev degree (:mod:`.linearize`);
                default 12 and 8, or 8 and 6 for the pupil reference (re-run at every
                refit: 64 renders instead of 144).

        Returns:
            The largest fit residual of the response over the scan, px.
        """
        if image_at is not None:
            self._image_at = image_at
        if self._image_at is None:
            raise ValueError("cmf: calibrate_response needs image_at(shift) for a static reference")
        if self._built_version != self.ref.version:
            self._rebuild_design()
        dp, dd = (8, 6) if self.pupil is not None else (12, 8)
        self._response = ResponseMap.fit(lambda sh: self._raw(self._image_at(sh)), self.n,
                                         self.linearize_extent, points or dp, degree or dd)
        self._response_version = self.ref.version
        return self._response.fit_error

    def _raw(self, images) -> np.ndarray:
        """``(n, 2)`` unlinearised estimates of noise-free ``images (n, p, p)``, block axes."""
        flat = np.asarray(images, dtype=float).reshape(self.n, -1) - self.background
        r, ok, _ = self._filter(flat)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.einsum("nkp,np->nk", r, flat) / flat.sum(axis=1)[:, None]
        out[~ok] = np.nan
        return out

    def _linearized(self, out: np.ndarray) -> np.ndarray:
        """Invert the calibrated response (no-op unless ``linearize``)."""
        if not self.linearize:
            return out
        if self._response is None or self._response_version != self.ref.version:
            if self._image_at is None:      # a static reference never calibrated: raw
                self._jac = None
                return out
            self.calibrate_response()
        s, self._jac = self._response.invert(out)
        return s

    # -- reference ------------------------------------------------------------------
    def set_reference(self, images, dx=None, dy=None) -> None:
        """Install a static reference: ``(n_valid, p, p)`` expected counts in block pixel
        axes (local frame on a polar detector), background included as in the frames.

        ``dx, dy``: optional derivative images (counts per pixel of shift, same axes),
        e.g. from a simulator's dithered images; otherwise the Fourier dither is used.
        The Fourier derivative is accurate for well-sampled spots (FWHM >= ~2.3 px: 1.5 %
        error at sigma = 1 px) but not for the under-sampled 1.19 px core (about 30 %
        gain error across the elongation), so pass exact derivatives when you have them.
        """
        self.ref.set(images, dx, dy)

    def push_dither(self, images) -> None:
        """Give the dithered images of the current frame (``derivative="dither"``).

        Args:
            images: ``(4, n_valid, p, p)`` counts: the spot shifted by +dither and -dither
                in x, then +dither and -dither in y (block pixel axes), e.g. simulated
                frames with the tip-tilt dither applied. The last ``history`` pushes are
                averaged (the paper: "the dithered images were also averaged"); the
                derivative is ``(mean(+) - mean(-)) / (2 dither)``. Call before
                :meth:`centroid` of the frame they belong to.
        """
        images = np.array(images, dtype=float)
        if images.shape != (4, self.n, self.p, self.p):
            raise ValueError(f"dither images have shape {images.shape}, expected {(4, self.n, self.p, self.p)}")
        self._dithers.append(np.where(np.isfinite(images), images, 0.0) - self.background)
        del self._dithers[:-self.ref.history]
        self.ref.version += 1

    def _dither_derivatives(self, flux):
        if not self._dithers:
            raise ValueError("cmf: derivative='dither' needs push_dither(images) before the first frame")
        mean = np.mean(self._dithers, axis=0)                              # (4, n, p, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(self._ref_ok, 1.0 / (2 * self.dither * flux), 0.0)[:, None, None]
        return (mean[0] - mean[1]) * scale, (mean[2] - mean[3]) * scale

    @property
    def reference(self) -> np.ndarray | None:
        """Current reference images ``(n, p, p)`` counts (None before the first frame)."""
        return None if self.ref.images is None else self.ref.images.copy()

    def reset(self) -> None:
        self.ref.reset()
        if self.pupil is not None:
            self.pupil.reset()
            self._install_pupil()
        self._dithers = []
        self._nea_state = None
        self._built_version = -1

    def _rebuild_design(self) -> None:
        ref = np.maximum(self.ref.images - self.background, 0.0)
        flux = ref.reshape(self.n, -1).sum(axis=1)
        self._ref_ok = flux > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            tmpl = np.where(self._ref_ok[:, None, None], ref / flux[:, None, None], 0.0)
        derivs = None
        if self.ref.derivatives is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                derivs = tuple(np.where(self._ref_ok[:, None, None], g / flux[:, None, None], 0.0)
                               for g in self.ref.derivatives)
        if self.derivative == "dither":
            derivs = self._dither_derivatives(flux)
        self._at_buf = getattr(self, "_at_buf", None)
        self.A, self.M = design(tmpl, self.dither, self.constrained, self.constraint_px, derivs,
                                out=self._at_buf)
        self._at_buf = np.swapaxes(self.A, 1, 2)
        self._ref_counts = ref.reshape(self.n, -1)
        self._built_version = self.ref.version
        self._model_R = None

    def _variance(self, signal: np.ndarray) -> np.ndarray:
        v = np.maximum(signal, 0.0) + self.background + self.read_noise ** 2
        return np.maximum(v, self.var_floor)

    def _filter(self, flat: np.ndarray):
        """(R (n,2,pp), ok (n,), var (n,pp)) for this frame."""
        if self._built_version != self.ref.version:
            self._rebuild_design()
        if self.weighting == "model":
            return self._model_filter()[:3]
        var = self._variance(flat)
        if getattr(self, "_work", None) is None or self._work.shape != self._at_buf.shape:
            self._work = np.empty(self._at_buf.shape)
        r, ok = solve_filter(self.A, self.M, var, self._work)
        return r, ok & self._ref_ok, var

    def _model_filter(self):
        """Cached model-weighted filter: (R, ok, var, [R; 1] float64, float32, R var R^T, R 1,
        R as int16 rows and their scales (:func:`.kernels.quantize`, for
        :func:`.kernels.filter_flux`: half the bytes of float32 read a frame, slopes within
        ~1e-4 px))."""
        if self._built_version != self.ref.version:
            self._rebuild_design()
        if self._model_R is None:
            var = self._variance(self._ref_counts)
            r, ok = solve_filter(self.A, self.M, var)
            r3 = np.concatenate([r, np.ones((self.n, 1, r.shape[2]))], axis=1)
            q = np.einsum("nkp,np,nlp->nkl", r, var, r)
            self._model_R = (r, ok & self._ref_ok, var, r3, r3.astype(np.float32), q, r.sum(axis=2),
                             kernels.quantize(r))
        return self._model_R

    def _stack_products(self, data):
        """Model weighting on the valid blocks: ``([R; 1] x (n, 3), cached filter)``."""
        stack = self.float_stack(data)
        flat = stack.reshape(self.n, -1)
        if self.ref.source == "history":
            total = flat.sum(axis=1).astype(np.float64)
            self.ref.observe(stack, np.isfinite(total) & (total > 0))
        else:
            self._observe_pupil(flat)
            self.ref.observe(None, None)
        filt = self._model_filter()
        r3, r3_32 = filt[3], filt[4]
        m = np.einsum("nkp,np->nk", r3 if flat.dtype == np.float64 else r3_32, flat).astype(np.float64)
        return m, filt

    def centroid(self, data) -> np.ndarray:
        """As :meth:`Centroider.centroid`. With model weighting the filter only changes with
        the reference, so a frame costs one ``(n, 3, pp)`` contraction (slopes and flux)."""
        if self.weighting != "model":
            return super().centroid(data)
        raw = np.asarray(data)
        if self.ref.source != "history" and raw.dtype.kind in "ui":
            # integer counts (a mono16 frame): gather the valid blocks and let the
            # contraction convert them on the fly, no float copy of the stack (the filter
            # rows are the bulk of the memory traffic: read as int16, 2.9 MB for the full
            # pupil instead of 5.7 MB in float32)
            flat = None
            if self.pupil is not None:
                if raw.shape == self.sensor.frame_shape:
                    if self.pupil.observe_frame(raw):        # integer accumulation, no copy
                        self._pupil_refitted()
                else:
                    flat = self.as_stack(raw).reshape(self.n, -1)
                    self._observe_pupil(flat)
            self.ref.observe(None, None)
            r, fok, _, r3, r3_32, q, rsum, (r16, r16_scale) = self._model_filter()
            stack = kernels.stack_view(raw, self.n, self.p)
            if kernels.fits(raw, self.sensor.frame_shape):     # compiled, one pass, in place
                # R's two rows and a plain pixel sum for the flux: no row of ones to read
                m = kernels.filter_flux(raw, kernels.origins(self), r16, scale=r16_scale)
            elif stack is not None:                            # the same sums for a stack
                m = kernels.filter_flux(stack, kernels.stack_origins(self.n, self.p), r16,
                                        scale=r16_scale)
            else:
                if flat is None:
                    flat = self.as_stack(raw).reshape(self.n, -1)
                m = np.einsum("nkp,np->nk", r3_32, flat).astype(np.float64)
        else:
            m, (r, fok, _, r3, r3_32, q, rsum, _) = self._stack_products(data)
        flux = m[:, 2] - self.background * self.p * self.p
        ok = finite_rows(m) & (m[:, 2] > 0) & (flux > 0) & fok
        with np.errstate(divide="ignore", invalid="ignore"):
            out = (m[:, :2] - self.background * rsum) / flux[:, None]
        self._nea_state = ("q", q, flux, ok)
        return self.finish(self._linearized(out), ok)

    def _centroid_pixels(self, stack, total, ok):
        flat = stack.reshape(self.n, -1)
        if self.pupil is not None:
            self._observe_pupil(flat)
        self.ref.observe(stack, ok)
        if self.background:
            flat = flat - flat.dtype.type(self.background)
        r, fok, var = self._filter(flat)
        flux = total - self.background * self.p * self.p
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.einsum("nkp,np->nk", r, flat) / flux[:, None]
        good = fok & (flux > 0) & ok
        out[~good] = np.nan
        self._nea_state = ("full", r, var, flux, good)
        return self._linearized(out)

    @property
    def nea(self) -> np.ndarray | None:
        """Predicted noise-equivalent angle of the last frame: ``(n, 2, 2)`` covariance,
        px^2, detector axes, ``(R/F) W^-1 (R/F)^T``; NaN for bad subapertures."""
        st = self._nea_state
        if st is None:
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            if st[0] == "q":
                _, q, flux, ok = st
                nea = q / flux[:, None, None] ** 2
            else:
                _, r, var, flux, ok = st
                rf = r / flux[:, None, None]
                nea = np.einsum("nkp,np,nlp->nkl", rf, var, rf)
        nea[~ok] = np.nan
        if self.linearize and getattr(self, "_jac", None) is not None:
            nea = transform_covariance(nea, self._jac)
        if self.polar:
            rot = _rotation(self.layout.e)
            nea = rot @ nea @ np.swapaxes(rot, 1, 2)
        return nea

    def describe(self):
        d = super().describe()
        d["reference_frames_seen"] = self.ref.frames
        if self.pupil is not None:
            pupil_cal.describe_into(d, self.pupil)
        if self.linearize:
            d["linearize"] = (f"response calibrated over +-{self.linearize_extent:g} px, "
                              "inverted per frame")
        d["design_columns"] = (["gx", "gy", "T", "T+cx", "T-cx", "T+cy", "T-cy"] if self.constrained
                               else ["gx", "gy", "T"])
        if self.derivative == "dither":
            d["derivative"] = f"pushed dithered images +-{self.dither} px, mean of last {self.ref.history}"
        else:
            d["derivative"] = ("given derivative images" if self.ref.derivatives is not None
                               else f"Fourier-shift dither +-{self.dither} px")
        return d


def _rotation(e: np.ndarray) -> np.ndarray:
    """``(n, 2, 2)`` matrices taking local-frame vectors to detector axes."""
    ex, ey = e[:, 0], e[:, 1]
    return np.stack([np.stack([ex, -ey], axis=1), np.stack([ey, ex], axis=1)], axis=1)
