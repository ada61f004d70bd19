"""Reference images shared by the matched filter and correlation: where they come from, how they shift.

A reference is an ``(n, p, p)`` image per subaperture, in counts, in the block's pixel axes
(local frame on a polar detector). Three sources (option ``reference``):

- ``"history"``: the mean of the last ``history`` frames of that subaperture (the paper's
  CMF: 5 frames, refreshed every frame). With ``include_current=True`` (default, the
  paper's "average of the last 5 images") the frame being measured is one of them; with
  ``False`` only earlier frames are used (the very first frame then uses itself).
  Subapertures that were bad in a frame are left out of that frame's contribution.
- ``"static"``: images given once with ``set_reference`` (e.g. a simulator's noise-free
  model at zero tip/tilt); what a real system could run.
- ``"model"``: a static reference built from the sensor description: Gaussian core of
  ``sensor.core_fwhm_px`` along a Gaussian sodium line of ``sodium_fwhm_m`` (10 km),
  ``sensor.photons`` counts, centred.
- ``"pupil"``: the spot of the sodium profile estimated from the whole pupil
  (:mod:`.pupil`), rendered exactly through each subaperture's geometry at the true
  centre and installed (with exact derivatives) by the algorithm after every refit.

Modelling point: a matched filter or a correlation measures the displacement of the
image *relative to its reference*; we report that displacement as the slope, i.e. the
reference is taken to sit at the subaperture centre. That is exact for a static
reference made at zero tip/tilt; for ``"history"`` it is the paper's idealised closed-loop
assumption (the recent spots are centred on average), so a stationary off-centre spot
reads ~0. With ``include_current=True`` the measured frame is 1/5 of its own reference,
which pulls the estimate towards 0 (by ~1/5 of any displacement, and removes part of the
noise): part of why the paper calls this setting idealised.

Sub-pixel shifts use Fourier phase ramps (periodic over the p x p block; the Nyquist
terms get no derivative); whole-pixel shifts are exact, zero-filled.
"""

from __future__ import annotations

import numpy as np

from .base import choice, flag, number

REFERENCE_SOURCES = ("history", "static", "model", "pupil")


def fourier_derivatives(stack: np.ndarray, dither: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Dithered-difference derivatives of images with respect to a shift of the image.

    ``g_x = (I(shifted +dither in x) - I(shifted -dither in x)) / (2 dither)``, with the
    shifts done by Fourier phase ramps; computed in one inverse FFT per axis as
    ``IFFT(F * (-i sin(2 pi k dither) / dither))`` (identical to the four dithered images).

    Args:
        stack: ``(n, p, p)`` images.
        dither: shift amplitude in pixels (0.02, as the paper).

    Returns:
        ``(gx, gy)``, each ``(n, p, p)`` float64: d(image)/d(shift) in counts per pixel.
    """
    n, p, q = stack.shape
    f = np.fft.rfft2(stack)
    ky = np.fft.fftfreq(p)
    kx = np.fft.rfftfreq(q)
    fy = -1j * np.sin(2 * np.pi * ky * dither) / dither
    fx = -1j * np.sin(2 * np.pi * kx * dither) / dither
    if p % 2 == 0:
        fy[p // 2] = 0
    if q % 2 == 0:
        fx[-1] = 0
    gx = np.fft.irfft2(f * fx[None, None, :], s=(p, q))
    gy = np.fft.irfft2(f * fy[None, :, None], s=(p, q))
    return gx, gy


def fourier_shift(stack: np.ndarray, shift) -> np.ndarray:
    """Shift ``(n, p, p)`` images by ``shift`` = (dx, dy) px (``(2,)`` or ``(n, 2)``), periodic."""
    n, p, q = stack.shape
    shift = np.broadcast_to(np.asarray(shift, dtype=float), (n, 2))
    f = np.fft.rfft2(stack)
    ky = np.fft.fftfreq(p)
    kx = np.fft.rfftfreq(q)
    ry = np.exp(-2j * np.pi * ky[None, :] * shift[:, 1, None])           # (n, p)
    rx = np.exp(-2j * np.pi * kx[None, :] * shift[:, 0, None])           # (n, q//2+1)
    if p % 2 == 0:                      # Nyquist: keep the real (cosine) part of the ramp
        ry[:, p // 2] = ry[:, p // 2].real
    if q % 2 == 0:
        rx[:, -1] = rx[:, -1].real
    ramp = ry[:, :, None] * rx[:, None, :]
    return np.fft.irfft2(f * ramp, s=(p, q))


def integer_shift(stack: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """Shift ``(n, p, p)`` images by whole pixels (x = columns, y = rows), zero-filled."""
    out = np.zeros_like(stack)
    p, q = stack.shape[-2:]
    src_y = slice(max(0, -dy), p - max(0, dy))
    dst_y = slice(max(0, dy), p - max(0, -dy))
    src_x = slice(max(0, -dx), q - max(0, dx))
    dst_x = slice(max(0, dx), q - max(0, -dx))
    out[..., dst_y, dst_x] = stack[..., src_y, src_x]
    return out


class ReferenceSource:
    """Keeps the reference images of one algorithm instance.

    Args:
        n, p: subapertures and pixels per side.
        source: "history" | "static" | "model".
        history: frames averaged (history mode).
        include_current: whether the frame being measured is part of the history mean.
        update_period: the reference is refreshed every this many frames (1 = every frame).
        model: ``(n, p, p)`` counts for source "model" (built by the caller).
    """

    def __init__(self, n: int, p: int, source: str = "history", history: int = 5,
                 include_current: bool = True, update_period: int = 1, model=None):
        self.n, self.p = n, p
        self.source = choice("reference", source, REFERENCE_SOURCES)
        self.history = number("history", history, minimum=1, integer=True)
        self.update_period = number("update_period", update_period, minimum=1, integer=True)
        self.include_current = flag("include_current", include_current)
        self._model = model
        self.reset()

    def reset(self) -> None:
        h, n, p = self.history, self.n, self.p
        if self.source == "history":
            self._buf = np.zeros((h, n, p, p))
            self._valid = np.zeros((h, n), dtype=bool)
        self._next = 0
        self.frames = 0
        if not hasattr(self, "derivatives"):
            self.derivatives = None
        if self.source == "history":
            self.images = None
        elif self.source == "model":
            self.images = np.array(self._model, dtype=float)
        else:                                   # static, pupil: keep an installed reference
            self.images = getattr(self, "images", None)
        self.version = getattr(self, "version", 0) + 1

    def set(self, images, dx=None, dy=None) -> None:
        """Install a reference ``(n, p, p)`` counts, optionally with its derivatives.

        ``dx, dy`` (``(n, p, p)``, counts per pixel of shift) replace the Fourier-dither
        derivatives, e.g. from a simulator's dithered noise-free images; they are kept
        until the next ``set``. In history mode the next frame replaces the images.
        """
        shape = (self.n, self.p, self.p)
        arrays = []
        for label, a in (("reference images", images), ("dx", dx), ("dy", dy)):
            if a is None:
                arrays.append(None)
                continue
            a = np.array(a, dtype=float)
            if a.shape != shape:
                raise ValueError(f"{label} have shape {a.shape}, expected {shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"{label} contain NaN or inf")
            arrays.append(a)
        if (arrays[1] is None) != (arrays[2] is None):
            raise ValueError("give both dx and dy, or neither")
        self.images = arrays[0]
        self.derivatives = None if arrays[1] is None else (arrays[1], arrays[2])
        self.version += 1

    def _push(self, stack, ok) -> None:
        self._buf[self._next] = np.where(ok[:, None, None], stack, 0.0)
        self._valid[self._next] = ok
        self._next = (self._next + 1) % self.history

    def _mean(self) -> np.ndarray:
        count = self._valid.sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            mean = self._buf.sum(axis=0) / count[:, None, None]
        mean[count == 0] = 0.0
        return mean

    def observe(self, stack: np.ndarray, ok: np.ndarray) -> bool:
        """Account for one frame ``(n, p, p)`` (bad rows flagged by ``ok``) before it is measured.

        Returns:
            True when the reference changed (filters must be rebuilt).
        """
        if self.source != "history":
            self.frames += 1
            if self.images is None:
                raise ValueError(f"reference={self.source!r} needs set_reference(images) before the first frame")
            return False
        first = self.frames == 0
        due = self.frames % self.update_period == 0
        if self.include_current:
            self._push(stack, ok)
            if due:
                self.images = self._mean()
        else:
            if due:
                self.images = np.where(ok[:, None, None], stack, 0.0) if first else self._mean()
            self._push(stack, ok)
        self.frames += 1
        if due:
            self.version += 1
        return due
