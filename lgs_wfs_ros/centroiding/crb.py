"""Cramer-Rao bound of the spot position, per subaperture, from an expected-image model.

Parameters per subaperture: the shift (sx, sy) in pixels and the flux F (a nuisance
parameter; ``dmu/dF = mu/F``). Pixels are independent with mean ``mu + b`` (``mu`` the
spot counts, ``b`` the background) and variance ``mu + b + s^2`` (``s`` the read noise):
Poisson, plus Gaussian read noise in the shifted-Poisson approximation, which is exact for
``s = 0`` and the usual CCD model otherwise. Fisher information::

    I_jk = sum_pixels (dmu/dtheta_j)(dmu/dtheta_k) / (mu + b + s^2)

and the bound on the shift is ``sqrt(diag(I^-1)[:2])`` pixels. For a round unpixelised
Gaussian of std sigma and N photons with no noise but the photons it is ``sigma/sqrt(N)``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np


def fisher(model, dmodel_dx, dmodel_dy, read_noise_e: float = 0.0, background_e: float = 0.0,
           flux_nuisance: bool = True) -> np.ndarray:
    """Fisher information matrices.

    Args:
        model: ``(n, p, p)`` expected spot counts (no background).
        dmodel_dx, dmodel_dy: ``(n, p, p)`` derivatives of ``model`` with respect to the
            shift, counts per pixel of shift.
        read_noise_e: read-noise std, counts.
        background_e: background counts per pixel.
        flux_nuisance: include the flux as a third (nuisance) parameter.

    Returns:
        ``(n, k, k)`` with ``k`` = 3 (x, y, flux) or 2.
    """
    mu = np.asarray(model, dtype=float)
    if mu.ndim != 3:
        raise ValueError(f"model must be (n, p, p), got shape {mu.shape}")
    cols = [np.asarray(dmodel_dx, dtype=float), np.asarray(dmodel_dy, dtype=float)]
    for c in cols:
        if c.shape != mu.shape:
            raise ValueError(f"derivatives have shape {c.shape}, model has {mu.shape}")
    if read_noise_e < 0 or background_e < 0:
        raise ValueError("read_noise_e and background_e must be >= 0")
    if flux_nuisance:
        flux = mu.sum(axis=(1, 2), keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            cols.append(np.where(flux > 0, mu / flux, 0.0))
    n = mu.shape[0]
    d = np.stack([c.reshape(n, -1) for c in cols], axis=2)            # (n, pp, k)
    var = np.maximum(mu, 0).reshape(n, -1) + background_e + read_noise_e ** 2
    inv = np.where(var > 0, 1.0 / np.where(var > 0, var, 1.0), 0.0)
    return np.einsum("npj,np,npk->njk", d, inv, d)


def crb_covariance(model, dmodel_dx, dmodel_dy, read_noise_e: float = 0.0,
                   background_e: float = 0.0, flux_nuisance: bool = True) -> np.ndarray:
    """``(n, 2, 2)`` lower bound on the shift estimate covariance, px^2 (NaN if singular)."""
    f = fisher(model, dmodel_dx, dmodel_dy, read_noise_e, background_e, flux_nuisance)
    out = np.full((f.shape[0], 2, 2), np.nan)
    det = np.linalg.det(f)
    ok = np.isfinite(det) & (np.abs(det) > 0)
    out[ok] = np.linalg.inv(f[ok])[:, :2, :2]
    return out


def cog_covariance(model, dmodel_dx, dmodel_dy, read_noise_e: float = 0.0,
                   background_e: float = 0.0) -> np.ndarray:
    """``(n, 2, 2)`` covariance of the CoG whose response is inverted, px^2 (NaN if singular).

    The photon-noise floor of every calibrated CoG (``cog`` with ``bias = pupil``): the plain
    CoG ``c = sum x n / sum n`` of background-subtracted counts has, to first order in the
    noise, the covariance ``S = sum var (x - c)(x - c)^T / N^2`` (``var = mu + b + s^2`` per
    pixel, ``N`` the spot's counts); a calibration that inverts its response ``J = dc/ds``
    (2 x 2, from the derivatives) turns it into ``J^-1 S J^-T``, in the derivatives' axes.
    No calibration of a CoG gets under it: a spot whose light is spread (two layers, a broad
    profile) keeps its second moment in ``S`` while the bound, :func:`crb_covariance`, reads
    its sharp edges. Args as :func:`fisher` (``model`` in block pixel axes, column index x).
    """
    mu = np.asarray(model, dtype=float)
    if mu.ndim != 3:
        raise ValueError(f"model must be (n, p, p), got shape {mu.shape}")
    n, p, q = mu.shape
    yy, xx = np.mgrid[0:p, 0:q].astype(float)
    flat = mu.reshape(n, -1)
    coords = np.stack([xx.ravel(), yy.ravel()], axis=1)                # (pp, 2)
    tot = flat.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = flat @ coords / tot[:, None]                                # (n, 2)
        dev = coords[None] - c[:, None, :]                              # (n, pp, 2)
        var = np.maximum(flat, 0) + background_e + read_noise_e ** 2
        s = np.einsum("np,npi,npj->nij", var, dev, dev) / tot[:, None, None] ** 2
        d = np.stack([np.asarray(dmodel_dx, float).reshape(n, -1),
                      np.asarray(dmodel_dy, float).reshape(n, -1)], axis=2)     # (n, pp, 2)
        jac = np.einsum("npi,npa->nia", dev, d) / tot[:, None, None]    # dc_i / ds_a
    out = np.full((n, 2, 2), np.nan)
    det = np.linalg.det(np.nan_to_num(jac))
    ok = np.isfinite(det) & (np.abs(det) > 0) & (tot > 0)
    ji = np.linalg.inv(jac[ok])
    out[ok] = ji @ s[ok] @ np.swapaxes(ji, 1, 2)
    return out


def crb(model, dmodel_dx, dmodel_dy, read_noise_e: float = 0.0, background_e: float = 0.0,
        flux_nuisance: bool = True) -> np.ndarray:
    """``(n, 2)`` Cramer-Rao bound on the std of (sx, sy), pixels, in the model's axes."""
    cov = crb_covariance(model, dmodel_dx, dmodel_dy, read_noise_e, background_e, flux_nuisance)
    return np.sqrt(np.einsum("nii->ni", cov))


def model_derivatives(image_at: Callable[[np.ndarray], np.ndarray], n: int, h: float = 1e-3,
                      shift=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Model and its shift derivatives by central finite differences.

    Args:
        image_at: callable, ``shift (n, 2) px -> (n, p, p)`` expected counts.
        n: number of subapertures.
        h: difference step, pixels.
        shift: ``(n, 2)`` point of evaluation (default zeros).

    Returns:
        ``(model, dmodel_dx, dmodel_dy)``, each ``(n, p, p)``.
    """
    s0 = np.zeros((n, 2)) if shift is None else np.asarray(shift, dtype=float).reshape(n, 2)
    ex = np.array([h, 0.0])
    ey = np.array([0.0, h])
    model = np.asarray(image_at(s0), dtype=float)
    dx = (np.asarray(image_at(s0 + ex), float) - np.asarray(image_at(s0 - ex), float)) / (2 * h)
    dy = (np.asarray(image_at(s0 + ey), float) - np.asarray(image_at(s0 - ey), float)) / (2 * h)
    return model, dx, dy


def crb_of(image_at: Callable[[np.ndarray], np.ndarray], n: int, read_noise_e: float = 0.0,
           background_e: float = 0.0, h: float = 1e-3, shift=None) -> np.ndarray:
    """``(n, 2)`` CRB (px) of a spot model given as ``image_at(shift (n, 2)) -> (n, p, p)``."""
    model, dx, dy = model_derivatives(image_at, n, h, shift)
    return crb(model, dx, dy, read_noise_e, background_e)
