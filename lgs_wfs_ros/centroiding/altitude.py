"""Follow the sodium layer's altitude between profile refits, from the slopes.

A change ``dh`` of the sodium layer's altitude moves every subaperture's spot along its
elongation by ``r cos z dh / h^2`` (docs/conventions.md section 3): one pupil-wide pattern,
``m_s = r_s e_s`` (``r_s`` the distance to the launch, ``e_s`` the unit vector along the
elongation, detector axes). The pupil calibration (:mod:`.pupil`) fixes the profile's
altitude from mean images over its time constant and installs it a period (or, live, a
period plus a lag) later, so between refits the references sit where the layer was, not
where it is. This tracker measures the slopes' component along ``m`` each frame,

    a_t = sum_s m_s . v_s,t / sum_s |m_s|^2        (px of displacement per metre of r)

averages it over ``time_constant_s`` (exponential, causal: frame t is corrected with the
average of frames before it) and subtracts ``a m_s`` from every slope. At each refit the
average is moved by the change the new references bring to ``a`` (their CoG along ``m``),
so it carries on without a jump.

What it assumes is what the calibration assumes, on a shorter time: the tilts averaged over
``time_constant_s`` carry no pupil-wide pattern along ``m``. With a centre launch ``m`` is
focus; with a side launch focus plus a tilt. So the slopes lose the atmosphere's focus
slower than ``time_constant_s`` (an LGS cannot tell it from the layer's altitude; LGS AO
takes focus from a natural guide star), and keep everything else.
"""

from __future__ import annotations

import math

import numpy as np

#: a refit that moves the references' CoG pattern by more than this (px, at the farthest
#: subaperture) restarts the average instead of moving it
RESTART_PX = 0.1


class AltitudeTracker:
    """Per-frame correction of the slopes for the sodium altitude's drift since the refit.

    Args:
        layout: the sensor's :class:`..optics.geometry.Layout` (``r_m (n,)``, ``e (n, 2)``).
        time_constant_s: memory of the average, seconds (> 0).
        frame_rate_hz: frames per second.
        to_detector: block-pixel-axes ``(n, 2)`` -> detector axes (the centroider's).
    """

    def __init__(self, layout, time_constant_s: float, frame_rate_hz: float, to_detector):
        self.mode = np.asarray(layout.r_m, float)[:, None] * np.asarray(layout.e, float)  # (n, 2)
        self._norm = float(np.vdot(self.mode, self.mode)) or 1.0
        self._reach = float(np.max(np.hypot(*self.mode.T), initial=0.0))   # m, largest |m|
        self.decay = math.exp(-1.0 / (time_constant_s * frame_rate_hz))
        self.to_detector = to_detector
        self.reset()

    def reset(self) -> None:
        """Forget the average (back to no correction)."""
        self.average = None          # px per metre of r
        self._version = None
        self._reference = 0.0
        self._fits = 0

    def coefficient(self, slopes: np.ndarray, ok: np.ndarray) -> float:
        """``a``: the least-squares amplitude of ``m`` in ``slopes (n, 2)`` over ``ok (n,)``."""
        if ok.all():
            return float(np.vdot(slopes, self.mode)) / self._norm
        m = self.mode[ok]
        den = float(np.vdot(m, m))
        return float(np.vdot(slopes[ok], m)) / den if den > 0 else 0.0

    def apply(self, slopes: np.ndarray, ok: np.ndarray, calibration) -> np.ndarray:
        """``(n, 2)`` detector-axes slopes corrected (a new array), NaN rows kept; updates
        the average with this frame's (uncorrected) slopes.

        Args:
            slopes: ``(n, 2)`` px, detector axes, as measured against the calibration's
                current references.
            ok: ``(n,)`` bool, subapertures measured this frame.
            calibration: the :class:`.pupil.PupilCalibration` whose references were used.
        """
        state = self._follow(calibration)
        if state == "off":
            return slopes
        out = slopes if self.average is None else slopes - self.average * self.mode
        if state == "refit":
            return out
        good = ok if ok.all() and np.isfinite(slopes).all() else ok & np.isfinite(slopes).all(axis=1)
        if good.any():
            a = self.coefficient(slopes, good)
            self.average = a if self.average is None else (
                self.decay * self.average + (1.0 - self.decay) * a)
        return out

    def _follow(self, calibration) -> str:
        """At a refit, move the average by what the new references change in the slopes'
        ``m`` component (minus the change of their CoG along ``m``); start again after a
        reset of the calibration, and at a refit that moves the references by more than
        ``RESTART_PX`` at the farthest subaperture (the first fits, from the prior: the
        slopes against the old references were not shifts of the new ones). Returns "off"
        while the calibration has not fitted yet (no correction against the prior),
        "refit" on the frame a refit is installed (whose slopes may have been measured
        against either references, so they do not enter the average), else "on"."""
        if calibration.fits < self._fits or calibration.fits == 0:
            self.reset()
        self._fits = calibration.fits
        if calibration.fits == 0:
            return "off"
        if calibration.version == self._version:
            return "on"
        bias = np.asarray(self.to_detector(calibration.cog_bias()), float)
        ref = self.coefficient(bias, np.isfinite(bias).all(axis=1))
        if self.average is not None and self._version is not None:
            step = ref - self._reference
            if abs(step) * self._reach > RESTART_PX:
                self.average = None
            else:
                self.average -= step
        self._version, self._reference = calibration.version, ref
        return "refit"


__all__ = ["AltitudeTracker"]
