"""Tiny analytic spot generator for the centroiding tests (independent of optics/spots.py).

A spot is a sum of round Gaussians (std ``sigma`` px) laid along a direction ``e`` at
offsets ``offsets`` px with weights ``weights`` (a crude sodium profile), shifted by
``shift`` px from the subaperture centre ``((p-1)/2, (p-1)/2)``, integrated exactly over
each square pixel (erf, separable per component), normalised to ``photons`` in an
unbounded field (light falling outside the ``p x p`` box is lost), optionally Poisson.
Pixel axes: x = column, y = row. For a polar detector, pass ``e = (1, 0)`` (local frame).
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf


def _pixel_integral(edges: np.ndarray, mu: np.ndarray, sigma: float) -> np.ndarray:
    """``(..., p)`` fraction of a 1-D Gaussian (mean ``mu (...)``) in each pixel."""
    z = (edges - mu[..., None]) / (np.sqrt(2.0) * sigma)
    c = 0.5 * erf(z)
    return np.diff(c, axis=-1)


def spots(shift, *, photons=1000.0, sigma=0.505, p=16, e=(1.0, 0.0), offsets=(0.0,),
          weights=None, background=0.0, rng=None, n=None) -> np.ndarray:
    """Expected (or Poisson) counts of ``n`` spots.

    Args:
        shift: ``(n, 2)`` or ``(2,)`` displacement (sx, sy) px from the centre.
        photons: scalar or ``(n,)`` total photons of the unbounded spot.
        sigma: std (px) of each Gaussian component (default: FWHM 1.19 px).
        p: pixels per side.
        e: ``(2,)`` or ``(n, 2)`` unit elongation direction.
        offsets: ``(m,)`` positions (px) of the components along ``e``.
        weights: ``(m,)`` relative component weights (default equal).
        background: counts per pixel added.
        rng: ``numpy.random.Generator`` for Poisson noise, or None for expected counts.
        n: number of spots when ``shift`` is a single ``(2,)`` vector.

    Returns:
        ``(n, p, p)`` float64 counts.
    """
    shift = np.atleast_2d(np.asarray(shift, dtype=float))
    if n is not None and shift.shape[0] == 1:
        shift = np.repeat(shift, n, axis=0)
    n = shift.shape[0]
    e = np.broadcast_to(np.asarray(e, dtype=float), (n, 2))
    offsets = np.asarray(offsets, dtype=float)
    w = np.ones_like(offsets) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    c = (p - 1) / 2.0
    edges = np.arange(p + 1) - 0.5
    # component centres (n, m, 2)
    pos = c + shift[:, None, :] + offsets[None, :, None] * e[:, None, :]
    fx = _pixel_integral(edges, pos[..., 0], sigma)            # (n, m, p)
    fy = _pixel_integral(edges, pos[..., 1], sigma)
    img = np.einsum("m,nmy,nmx->nyx", w, fy, fx)
    img = img * np.broadcast_to(np.asarray(photons, dtype=float), (n,))[:, None, None] + background
    if rng is not None:
        img = rng.poisson(img).astype(float)
    return img


def sodium_line(length_px: float, m: int = 15, asym: float = 0.0):
    """Offsets and weights of a crude sodium profile of FWHM-ish ``length_px``.

    A Gaussian envelope of FWHM ``length_px`` sampled at ``m`` points over
    ``+-length_px``; ``asym`` tilts the weights linearly (0 = symmetric).
    """
    off = np.linspace(-length_px, length_px, m)
    s = max(length_px, 1e-9) / 2.3548
    w = np.exp(-0.5 * (off / s) ** 2) * (1 + asym * off / max(length_px, 1e-9))
    return off, np.clip(w, 0, None)
