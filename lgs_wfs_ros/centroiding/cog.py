"""Centre-of-gravity family: plain (cog), thresholded (tcog) and weighted (wcog) CoG.

All three compute moments of the pixel counts about the subaperture centre in the
block's pixel axes (local frame on a polar detector). Background: ``background``
counts per pixel (default ``sensor.background_e``) are subtracted first.

Pixel origin: the slope is measured from ``(p-1)/2`` (7.5 for 16 px). aotools'
``centre_of_gravity`` measures from pixel index 0, so ``ours = aotools - 7.5``.
"""

from __future__ import annotations

import numpy as np

from . import kernels
from . import pupil as pupil_cal
from ..optics.gaussian_spot import FWHM_PER_SIGMA, elongation_fwhm_px, model_spots
from .base import Centroider, check_options, choice, finite_rows, flag, number, pixel_coords



class CoG(Centroider):
    """Plain centre of gravity.

    Options:
        background: counts per pixel subtracted before centroiding (default
            ``sensor.background_e``). Because the pixel offsets sum to zero, this only
            changes the denominator.
        bias: "none" (default: the plain CoG, the paper's baseline) | "pupil": subtract the
            CoG of each subaperture's reference spot rendered from the sodium profile
            estimated from the whole pupil (:mod:`.pupil`), i.e. the bias the profile
            implies, refreshed every ``pupil_period`` frames.
        linearize: with ``bias="pupil"``, invert the CoG's whole response to a shift of
            the calibrated spot (:meth:`.pupil.PupilCalibration.cog_response`: its bias,
            and the gain lost where the field's edge truncates the spot) instead of
            subtracting the bias alone (True).
        pupil_period, pupil_time_constant_s, pupil_stride, pupil_trend: the calibration's
            refit period (frames), memory (s), accumulation stride (frames) and drift
            extrapolation (:class:`.pupil.PupilCalibration`), for ``bias="pupil"``.
    """

    name = "cog"
    _allowed = ("background", "bias", *pupil_cal.OPTION_DEFAULTS, "linearize")

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._allowed)
        options.setdefault("background", float(sensor.background_e))
        if "bias" in self._allowed:                  # CoG itself, not TCoG/WCoG
            options.setdefault("bias", "none")
            for k, v in pupil_cal.OPTION_DEFAULTS.items():
                options.setdefault(k, v)
        if "linearize" in self._allowed:
            flag("linearize", options.setdefault("linearize", True))
        super().__init__(sensor, **options)
        self.background = number("background", options["background"], minimum=0)
        self.pupil = None
        self._response = None
        if choice("bias", options.get("bias", "none"), ("none", "pupil")) == "pupil":
            self.pupil = pupil_cal.from_options(sensor, options, self.background)
            self._bias = self.pupil.cog_bias()
            if options.get("linearize", False):
                self.pupil.reads += ("cog_response",)
                self._response = self.pupil.cog_response()
            if self.pupil.asynchronous:      # the drift's reading off the frame path too
                self.pupil.delegate(self._prepare_calibration, self.pupil.reads)
        x, y = pixel_coords(self.p, self.centre)
        self._xy = np.stack([x, y], axis=1)                   # (p*p, 2)
        self._xy32 = self._xy.astype(np.float32)
        self._w3 = np.stack([np.ones_like(x), x, y], axis=1)  # (p*p, 3): total and moments
        self._w332 = self._w3.astype(np.float32)
        kernels.warm_up()

    def centroid(self, data) -> np.ndarray:
        """As :meth:`Centroider.centroid`; one matrix product gives totals and moments."""
        rows = flat = None
        whole = kernels.fits(data, self.sensor.frame_shape)
        if whole:                                               # compiled, one pass, in place
            m = kernels.cog_moments(data, kernels.origins(self), self.p, self.centre)
        else:
            rows = self.frame_rows(data)
        if rows is not None:                                    # a frame: all blocks, then keep valid
            w = self._w3 if rows.dtype == np.float64 else self._w332
            m = (rows @ w)[self.valid_rows].astype(np.float64)  # (n, 3)
        elif not whole:
            flat = self.float_stack(data).reshape(self.n, -1)
            w = self._w3 if flat.dtype == np.float64 else self._w332
            m = (flat @ w).astype(np.float64)                   # (n, 3)
        denom = m[:, 0] - self.background * self.p * self.p
        ok = finite_rows(m) & (m[:, 0] > 0) & (denom > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = m[:, 1:] / denom[:, None]
        if self.pupil is not None:
            if whole:                                           # integer frame, as it is
                seen = self.pupil.observe_frame(data)
            elif flat is None:
                seen = self.pupil.observe_rows(rows, self.valid_rows)
            else:
                seen = self.pupil.observe(flat, ok)
            if seen:
                self._take_refit(self._calibrated)
            if self._response is None:
                out -= self._bias
            else:
                # smooth: one Newton step; beyond the scanned box the bias alone (raw
                # would keep it: px on a layer far from h_ref)
                out = self._response.invert(out, iterations=1, outside="offset")[0]
        return self.finish(out, ok)

    def centroid_many(self, frames) -> np.ndarray:
        """As :meth:`Centroider.centroid_many`, one matrix product for all frames."""
        stacks = self.many_stacks(frames)
        if stacks is None or not len(stacks) or self.pupil is not None:
            return super().centroid_many(frames)          # the calibration sees frames in order
        k = stacks.shape[0]
        flat = stacks.reshape(k * self.n, -1)
        flat = flat.astype(np.float64 if flat.dtype == np.float64 else np.float32, copy=False)
        w = self._w3 if flat.dtype == np.float64 else self._w332
        m = (flat @ w).astype(np.float64).reshape(k, self.n, 3)
        denom = m[..., 0] - self.background * self.p * self.p
        ok = np.isfinite(m).all(axis=-1) & (m[..., 0] > 0) & (denom > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = m[..., 1:] / denom[..., None]
        return self.finish(out, ok)

    def reset(self) -> None:
        if self.pupil is not None:
            self.pupil.reset()
            self._calibrated()

    def _prepare_calibration(self, calibration) -> dict:
        """Run in a background refit's thread on the refitted ``calibration`` (a snapshot):
        what :meth:`_calibrated` takes from it, made by a shallow copy of this estimator (the
        drift's reading held the install frame 5-6 ms a full pupil before, 2026-11-29).
        Nothing the frame path uses is written."""
        sh = self._copy_on(calibration)
        sh._calibrated()
        return {"_bias": sh._bias, "_response": sh._response, "_drift": sh._drift}

    def _calibrated(self) -> None:
        """Take the calibration's current bias and, linearised, its response, and follow
        the profile's drift (:meth:`Centroider._follow_drift`)."""
        self._bias = self.pupil.cog_bias()
        if self._response is not None:
            self._response = self.pupil.cog_response()
        self._follow_drift(self._reading)

    def _reading(self, counts: np.ndarray) -> np.ndarray:
        """``(n, 2)`` block axes, px: the calibrated CoG of noise-free ``counts (n, p, p)``
        (no background), as :meth:`centroid` reads a frame."""
        c = np.nan_to_num(self.pupil._cog(counts))
        if self._response is None:
            return c - self._bias
        return self._response.invert(c, iterations=1, outside="offset")[0]

    def describe(self) -> dict:
        d = super().describe()
        if self.pupil is not None:
            pupil_cal.describe_into(d, self.pupil)
        return d

    def _centroid_pixels(self, stack, total, ok):
        flat = stack.reshape(self.n, -1)
        xy = self._xy if flat.dtype == np.float64 else self._xy32
        moments = (flat @ xy).astype(np.float64)               # (n, 2)
        denom = total - self.background * self.p * self.p
        with np.errstate(divide="ignore", invalid="ignore"):
            out = moments / denom[:, None]
        out[denom <= 0] = np.nan
        return out


class TabledCoG(CoG):
    """A pupil-calibrated CoG whose refits also build per-profile tables (``ml``'s
    likelihood tables, ``gmf``'s filters). Subclasses give ``_prepare(calibration) ->
    payload`` (a dict with the calibration's ``version``; run in the refit thread when
    ``pupil_async``; :meth:`_with_drift` adds the drift read through its tables),
    ``_set_tables(payload)``, ``_follow_tables()`` (the drift, as ``_follow_drift``) and
    ``_install(payload)``, and call :meth:`_start_tables` once built."""

    #: what a background refit's thread reads after ``_prepare`` (``PupilCalibration.reads``):
    #: the drifted reference, which ``_with_drift`` has already read (a cached value since
    #: the drift comes with the payload; kept so that a ``_prepare`` without it stays off
    #: the frame path)
    refit_reads = ("drift_counts",)

    #: what :meth:`_with_drift`'s copy made besides the drift, handed to the frame path too
    _drift_keeps: tuple = ()

    def _start_tables(self) -> None:
        self.pupil.delegate(self._prepare, self.refit_reads)
        self._install(self._prepare(self.pupil))

    def _with_drift(self, calibration, payload: dict) -> dict:
        """``payload`` with ``drift``: :meth:`Centroider._follow_drift`'s move as read through
        the tables in it (``_set_tables(payload)``, then ``_follow_tables()``, on a shallow
        copy of this estimator holding them), where they are built: a background refit's
        thread, not the frame that installs them (the full pupil's two readings held it
        6.5 ms polar, 20 ms cartesian before, 2026-11-29). Nothing the frame path uses is
        written."""
        sh = self._copy_on(calibration)
        sh._set_tables(payload)
        sh._follow_tables()
        payload["drift"] = sh._drift
        payload.update({k: sh.__dict__[k] for k in self._drift_keeps})
        return payload

    def _refresh(self) -> None:
        """Tables of the calibration's current profile (a background refit's, or built now)."""
        payload, self.pupil.payload = self.pupil.payload, None
        if payload is not None and payload["version"] == self.pupil.version:
            self._install(payload)
        elif self._version != self.pupil.version:
            self._install(self._prepare(self.pupil))

    centroid_many = Centroider.centroid_many     # frame by frame: the calibration is stateful

    def reset(self) -> None:
        self.pupil.reset()
        self._install(self._prepare(self.pupil))


class TCoG(CoG):
    """Thresholded centre of gravity.

    Exactly one threshold option (default ``threshold_rn=3``):
        threshold: counts (after background subtraction).
        threshold_rn: multiples of ``sensor.read_noise_e`` (zero read noise -> plain CoG).
        threshold_frac: fraction of each subaperture's maximum pixel (aotools' meaning).
    Other options:
        mode: "subtract" (pixel -> max(pixel - T, 0), the usual TCoG; default) or
            "zero" (pixels below T -> 0, others kept, as aotools does on 3-D stacks).
        background: as for :class:`CoG`.
    """

    name = "tcog"
    centroid = Centroider.centroid
    centroid_many = Centroider.centroid_many
    _allowed = ("background", "threshold", "threshold_rn", "threshold_frac", "mode")

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._allowed)
        given = [k for k in ("threshold", "threshold_rn", "threshold_frac") if options.get(k) is not None]
        if len(given) > 1:
            raise ValueError(f"tcog: give only one of threshold, threshold_rn, threshold_frac (got {given})")
        if not given:
            options["threshold_rn"] = 3.0
            given = ["threshold_rn"]
        options.setdefault("mode", "subtract")
        super().__init__(sensor, **options)
        self.kind = given[0]
        self.value = number(self.kind, options[self.kind], minimum=0)
        if self.kind == "threshold_frac" and self.value > 1:
            raise ValueError(f"option threshold_frac must be in [0, 1], got {self.value}")
        self.mode = choice("mode", options["mode"], ("subtract", "zero"))

    def threshold_counts(self, stack) -> np.ndarray:
        """``(n,)`` threshold in counts for a background-subtracted stack."""
        if self.kind == "threshold":
            return np.full(self.n, self.value)
        if self.kind == "threshold_rn":
            return np.full(self.n, self.value * self.sensor.read_noise_e)
        return self.value * stack.reshape(self.n, -1).max(axis=1)

    def _centroid_pixels(self, stack, total, ok):
        img = stack - stack.dtype.type(self.background) if self.background else stack
        t = self.threshold_counts(img).astype(img.dtype)[:, None, None]
        if self.mode == "subtract":
            img = np.maximum(img - t, 0)
        else:
            img = np.where(img >= t, img, 0)
        flat = img.reshape(self.n, -1)
        xy = self._xy if flat.dtype == np.float64 else self._xy32
        moments = (flat @ xy).astype(np.float64)
        denom = flat.sum(axis=1, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = moments / denom[:, None]
        out[~(denom > 0)] = np.nan
        return out

    def describe(self):
        d = super().describe()
        if self.kind == "threshold_rn":
            d["threshold_counts"] = self.value * self.sensor.read_noise_e
        return d


class WCoG(CoG):
    """Weighted centre of gravity with an elongated Gaussian weight aligned with ``e``.

    The weight ``w(u) = exp(-u^T Sw^-1 u / 2)`` (``u`` = pixel offset from the centre) has
    FWHM ``fwhm_par_px`` along ``e`` and ``fwhm_perp_px`` across, fixed at the centre.
    A weighted centroid underestimates the shift; it is corrected by the inverse of its
    2 x 2 gain matrix at the centre, per subaperture:

    - ``gain="model"`` (default): the gain measured (central differences, +-0.01 px) on
      a model spot: a round Gaussian core of FWHM ``spot_fwhm_perp_px`` laid along ``e``
      with a Gaussian line of FWHM ``L = sqrt(spot_fwhm_par_px^2 - core^2)``, integrated
      exactly over the pixels (erf). A noise-free model spot returns its shift near the centre.
    - ``gain="analytic"``: ``Sw (Sw + S)^-1`` (product of Gaussians, ``S`` the spot
      covariance + I/12 for pixels); good for spots wider than ~1 px.
    - ``gain="none"``: the raw weighted centroid.

    Options (FWHM in pixels; ``None`` = default):
        spot_fwhm_par_px: assumed spot FWHM along e; default ``sqrt(core^2 + L^2)`` with
            ``L`` the elongation of a ``sodium_fwhm_m`` layer at that subaperture.
        spot_fwhm_perp_px: assumed spot FWHM across e; default ``sensor.core_fwhm_px``.
        fwhm_par_px, fwhm_perp_px: weight FWHM; default the spot's, at least 2 px (a
            narrower weight is under-sampled by the pixels).
        sodium_fwhm_m: layer thickness for the default elongation (10 km, the paper's).
        gain: "model" | "analytic" | "none".
        background: as for :class:`CoG`.
    """

    name = "wcog"
    centroid = Centroider.centroid
    centroid_many = Centroider.centroid_many
    _allowed = ("background", "fwhm_par_px", "fwhm_perp_px", "spot_fwhm_par_px",
                "spot_fwhm_perp_px", "sodium_fwhm_m", "gain")

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._allowed)
        options.setdefault("sodium_fwhm_m", 10e3)
        options.setdefault("gain", "model")
        super().__init__(sensor, **options)
        gain = choice("gain", options["gain"], ("model", "analytic", "none"))
        core = sensor.core_fwhm_px
        sod = number("sodium_fwhm_m", options["sodium_fwhm_m"], minimum=0)
        spot_par = self._width("spot_fwhm_par_px", np.hypot(core, elongation_fwhm_px(sensor, sod)))
        spot_perp = self._width("spot_fwhm_perp_px", np.full(self.n, core))
        w_par = self._width("fwhm_par_px", np.maximum(spot_par, 2.0))
        w_perp = self._width("fwhm_perp_px", np.maximum(spot_perp, 2.0))
        e = self.e_pixel
        sw = _covariance(e, w_par / FWHM_PER_SIGMA, w_perp / FWHM_PER_SIGMA)       # (n, 2, 2)
        x, y = pixel_coords(self.p, self.centre)
        u = np.stack([x, y], axis=1)                                                 # (pp, 2)
        swi = np.linalg.inv(sw)
        w = np.exp(-0.5 * np.einsum("pi,nij,pj->np", u, swi, u))                    # (n, pp)
        self.weight = w
        self._wm = np.stack([w, w * x, w * y], axis=1)                              # (n, 3, pp)
        self._wm32 = self._wm.astype(np.float32)
        self.gain = np.broadcast_to(np.eye(2), (self.n, 2, 2))
        if gain == "analytic":
            ss = _covariance(e, spot_par / FWHM_PER_SIGMA, spot_perp / FWHM_PER_SIGMA)
            self.gain = np.eye(2) + (ss + np.eye(2) / 12.0) @ swi                   # inverse gain
        elif gain == "model":
            self.gain = np.linalg.inv(self._model_gain(e, spot_par, spot_perp))
        self.spot_fwhm = np.stack([spot_par, spot_perp], axis=1)
        self.weight_fwhm = np.stack([w_par, w_perp], axis=1)

    def _width(self, name, default):
        v = self.options.get(name)
        if v is None:
            return np.broadcast_to(np.asarray(default, dtype=float), (self.n,)).copy()
        return np.full(self.n, number(name, v, minimum=0, strict=True))

    def _raw(self, flat):
        wm = self._wm if flat.dtype == np.float64 else self._wm32
        m = np.einsum("nkp,np->nk", wm, flat).astype(np.float64)                      # (n, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            raw = m[:, 1:] / m[:, :1]
        raw[~(m[:, 0] > 0)] = np.nan
        return raw

    def _model_gain(self, e, spot_par, spot_perp, h=0.01):
        """``(n, 2, 2)`` d(raw)/d(shift) of the model spots at the centre (columns x, y)."""
        cols = []
        for d in ((h, 0.0), (0.0, h)):
            d = np.broadcast_to(np.asarray(d), (self.n, 2))
            plus = model_spots(self.p, e, spot_perp, spot_par, d)
            minus = model_spots(self.p, e, spot_perp, spot_par, -d)
            cols.append((self._raw(plus.reshape(self.n, -1)) - self._raw(minus.reshape(self.n, -1))) / (2 * h))
        return np.stack(cols, axis=2)

    def _centroid_pixels(self, stack, total, ok):
        flat = stack.reshape(self.n, -1)
        if self.background:
            flat = flat - flat.dtype.type(self.background)
        return np.einsum("nij,nj->ni", self.gain, self._raw(flat))

    def describe(self):
        d = super().describe()
        d["weight_fwhm_px_median"] = np.median(self.weight_fwhm, axis=0).tolist()
        d["spot_fwhm_px_median"] = np.median(self.spot_fwhm, axis=0).tolist()
        return d


def _covariance(e: np.ndarray, s_par: np.ndarray, s_perp: np.ndarray) -> np.ndarray:
    """``(n, 2, 2)`` covariance with std ``s_par`` along unit ``e (n, 2)``, ``s_perp`` across."""
    ep = np.stack([-e[:, 1], e[:, 0]], axis=1)
    return (s_par[:, None, None] ** 2 * e[:, :, None] * e[:, None, :]
            + s_perp[:, None, None] ** 2 * ep[:, :, None] * ep[:, None, :])
