"""Elongated Gaussian model spots: the closed-form approximation behind the weighted CoG's
weights and the CMF's ``model`` reference (the exact spots, from a sodium profile, are
:mod:`.spots` and :mod:`.model_spot`).

A model spot is a round Gaussian core convolved with a Gaussian line along the elongation
direction ``e`` whose length is what a sodium layer of a given FWHM spans at each
subaperture's distance from the launch (docs/conventions.md section 3).
"""

from __future__ import annotations

import math

import numpy as np

from ..sensor import Sensor
from . import geometry

FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def elongation_fwhm_px(sensor: Sensor, sodium_fwhm_m: float = 10e3) -> np.ndarray:
    """``(n,)`` length (pixels) of a sodium layer of the given thickness seen by each subaperture.

    Exact geometry of the contract (section 3): ``r cos z (1/h_lo - 1/h_hi)`` radians with
    ``h = h_ref -/+ fwhm/2``, converted with the pixel scale.
    """
    lay = geometry.layout(sensor)
    cz = math.cos(math.radians(sensor.zenith_deg))
    h_lo, h_hi = sensor.h_ref_m - sodium_fwhm_m / 2, sensor.h_ref_m + sodium_fwhm_m / 2
    return np.asarray(lay.r_m) * cz * (1 / h_lo - 1 / h_hi) / sensor.pixel_scale_rad



def model_spots(p: int, e: np.ndarray, core_fwhm: np.ndarray, par_fwhm: np.ndarray,
                shift: np.ndarray, m: int = 31) -> np.ndarray:
    """``(n, p, p)`` unit-flux model spots, exact pixel integrals (erf).

    A round Gaussian core (FWHM ``core_fwhm (n,)``) convolved with a Gaussian line along
    ``e (n, 2)`` of FWHM ``sqrt(par_fwhm^2 - core_fwhm^2)`` (sampled at ``m`` points over
    +-2 line sigma), shifted by ``shift (n, 2)`` px from the centre ``(p-1)/2``.
    """
    from scipy.special import erf
    sc = np.asarray(core_fwhm, float) / FWHM_PER_SIGMA                               # (n,)
    sl = np.sqrt(np.maximum(np.asarray(par_fwhm, float) ** 2 - np.asarray(core_fwhm, float) ** 2, 0)) / FWHM_PER_SIGMA
    t = np.linspace(-2.0, 2.0, m)
    wt = np.exp(-0.5 * t ** 2)
    wt /= wt.sum()
    pos = (p - 1) / 2 + shift[:, None, :] + (sl[:, None, None] * t[None, :, None]) * e[:, None, :]  # (n, m, 2)
    edges = np.arange(p + 1) - 0.5
    z = (edges[None, None, :] - pos[..., None]) / (np.sqrt(2.0) * sc[:, None, None, None])         # (n, m, 2, p+1)
    f = np.diff(0.5 * erf(z), axis=-1)                                                              # (n, m, 2, p)
    fy = np.swapaxes(f[:, :, 1], 1, 2) * wt                                                         # (n, p, m)
    return fy @ f[:, :, 0]                                                                          # (n, p, p)
