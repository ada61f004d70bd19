"""Noise-free LGS spot images: the sodium profile laid along the elongation, core, pixels.

Physics (docs/conventions.md section 3, docs/simulator.md): sodium at altitude ``h``
images at ``delta(h) = r cos z (1/h_ref - 1/h) e`` radians from the true centre ``t`` (the
image of ``h_ref``), the EXACT form, not the paper's linear one. The spot is that line of
light, convolved with the Gaussian core (FWHM ``sensor.core_fwhm_px``), shifted by the
true displacement, and integrated over square pixels (erf differences, i.e. exactly, not
oversample-then-bin). Images are normalised to ``1 - truncated``: the light that falls
outside the ``p x p`` field is lost and reported as ``truncated``.

Numerical method (all vectorised over subapertures; details and accuracy in
docs/simulator.md):

1. Elements: each altitude cell of the piecewise-linear density becomes a point element
   with its exact mass, mean and variance (cells merged or split to ~0.35 node each).
2. Nodes ``u_k = k s`` along ``e``: elements are deposited with 4-point cubic Lagrange
   weights, which keep each element's mass and first three moments.
   ``s = 1 / (m |e_major|)`` puts the nodes exactly ``1/m`` px apart along the detector
   axis closest to ``e`` (m = 4, or 8/16 for lines shorter than 5/1.5 px).
3. A Gaussian integrated over a square pixel is separable along detector axes, so an image
   is ``Gy^T diag(w) Gx``, a batched matmul. Along the major axis the ``1/m`` px spacing
   makes ``Gx`` a Toeplitz view of one vector of ``m p + K`` core-CDF values per
   subaperture; along the minor axis the pixel-integrated core comes from a fine table
   (error < 4e-8). Polar detector: the block is sampled in its local frame (x along e),
   the line is along a pixel axis and the image is an outer product of two 1-D profiles.

Accuracy against a brute-force renderer: < 3e-4 of the peak pixel (converging as s^4).
What depends only on the profile (nodes, weights) is built once in :class:`SpotModel`;
per frame only the shift changes. :func:`spot_images` is the one-call form.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.lib.stride_tricks import as_strided, sliding_window_view
from scipy.special import ndtr

from ..sensor import Sensor
from . import detector
from .geometry import detector_to_local

SIGMA_PER_FWHM = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
NODES_PER_PX = 4          # nodes per pixel along the detector axis closest to e
CORE_SIGMAS = 6.5         # the core is cut at this many sigma (Phi(-6.5) = 4e-11)
N_GROUPS = 4              # subapertures are grouped by node count to save work
NO_LIGHT = 1e-6           # below this light in the field a float32 render's CoG is rounding


# ---------------------------------------------------------------------------------------
# geometry helpers (also used by tests and docs)
# ---------------------------------------------------------------------------------------
def elongation_px(sensor: Sensor, r_m, altitude_m) -> np.ndarray:
    """Exact offset along ``e`` of the image of each altitude, pixels.

    ``u = r cos z (1/h_ref - 1/h) / pixel_scale_rad``.

    Args:
        sensor: gives ``h_ref_m``, ``zenith_deg`` and ``pixel_scale_rad``.
        r_m: ``(n,)`` (or scalar) distance from the launch, m.
        altitude_m: ``(K,)`` altitudes above the telescope, m.
    Returns:
        ``(n, K)`` (or ``(K,)`` for scalar ``r_m``) offsets in pixels.
    """
    r = np.asarray(r_m, dtype=float)
    h = np.asarray(altitude_m, dtype=float)
    cz = math.cos(math.radians(sensor.zenith_deg))
    g = cz * (1.0 / sensor.h_ref_m - 1.0 / h) / sensor.pixel_scale_rad
    return r[..., None] * g if r.ndim else float(r) * g


def linear_elongation_arcsec(r_m: float, thickness_m: float, h0_m: float,
                             zenith_deg: float = 0.0) -> float:
    """The paper's linear elongation ``theta = r t cos z / h0^2`` (arcsec)."""
    return r_m * thickness_m * math.cos(math.radians(zenith_deg)) / h0_m ** 2 * 206264.80624709636


def exact_elongation_arcsec(r_m: float, h_low_m: float, h_high_m: float,
                            zenith_deg: float = 0.0) -> float:
    """Exact angular length of the image of the slab ``[h_low, h_high]`` (arcsec).

    ``r cos z (1/h_low - 1/h_high)``; for a slab of thickness ``t`` centred on ``h0`` this
    is the linear form times ``1 / (1 - (t / 2 h0)^2)`` (0.31 % more for 10 km at 90 km).
    """
    cz = math.cos(math.radians(zenith_deg))
    return r_m * cz * (1.0 / h_low_m - 1.0 / h_high_m) * 206264.80624709636


def light_centroid_px(sensor: Sensor, r_m, altitude_m, density) -> np.ndarray:
    """Centroid of the untruncated light along ``e`` (pixels) for a piecewise-linear density.

    This is where a perfect, untruncated CoG puts the spot relative to the true centre:
    ``r cos z (1/h_ref - <1/h>)``; zero only when the light-weighted harmonic mean
    altitude equals ``h_ref`` (a profile symmetric in ``h`` about ``h_ref`` is NOT enough
    under the exact geometry). Shape ``(n,)``.
    """
    h, rho = _check_profile(altitude_m, density)
    r = np.atleast_1d(np.asarray(r_m, dtype=float))
    # integral of rho(h)/h over a linear cell, exactly, divided by the cell mass
    h0, h1 = h[:-1], h[1:]
    d = h1 - h0
    ln = np.log(h1 / h0)
    r0, r1 = rho[..., :-1], rho[..., 1:]
    slope = (r1 - r0) / d
    inv_int = (r0 - slope * h0) * ln + slope * d            # int (r0 + slope (h - h0)) / h dh
    mass = 0.5 * (r0 + r1) * d
    mean_inv = inv_int.sum(-1) / mass.sum(-1)
    cz = math.cos(math.radians(sensor.zenith_deg))
    return r * cz * (1.0 / sensor.h_ref_m - mean_inv) / sensor.pixel_scale_rad


# ---------------------------------------------------------------------------------------
# input checks
# ---------------------------------------------------------------------------------------
def _check_profile(altitude_m, density) -> tuple[np.ndarray, np.ndarray]:
    h = np.asarray(altitude_m, dtype=float)
    if h.ndim != 1 or h.size < 2 or not np.all(np.isfinite(h)) or np.any(np.diff(h) <= 0) \
            or h[0] <= 0:
        raise ValueError("altitude_m must be a 1-D, finite, strictly ascending array of >= 2 "
                         "positive altitudes (m)")
    rho = np.asarray(density, dtype=float)
    if rho.ndim not in (1, 2) or rho.shape[-1] != h.size:
        raise ValueError(f"density must have shape ({h.size},) or (n, {h.size}), got {rho.shape}")
    if not np.all(np.isfinite(rho)) or np.any(rho < 0):
        raise ValueError("density must be finite and >= 0")
    if np.any(rho.sum(-1) <= 0):
        raise ValueError("density must have a positive total (an empty profile has no spot)")
    return h, rho


def _check_subaps(r_m, e) -> tuple[np.ndarray, np.ndarray]:
    r = np.atleast_1d(np.asarray(r_m, dtype=float))
    ev = np.asarray(e, dtype=float)
    if r.ndim != 1 or not np.all(np.isfinite(r)) or np.any(r < 0):
        raise ValueError("r_m must be a 1-D array of finite distances >= 0 (m)")
    if ev.shape != (r.size, 2) or not np.all(np.isfinite(ev)):
        raise ValueError(f"e must have shape ({r.size}, 2) and be finite, got {ev.shape}")
    if np.any(np.abs(np.hypot(ev[:, 0], ev[:, 1]) - 1.0) > 1e-6):
        raise ValueError("e must hold unit vectors")
    return r, ev


def _check_shift(shift_px, n: int) -> np.ndarray:
    s = np.asarray(shift_px, dtype=float)
    if s.shape != (n, 2) or not np.all(np.isfinite(s)):
        raise ValueError(f"shift_px must be a finite ({n}, 2) array (pixels), got {s.shape}")
    return s


# ---------------------------------------------------------------------------------------
# the light as point elements (one per altitude cell)
# ---------------------------------------------------------------------------------------
MAX_ELEMENT_NODES = 0.35  # altitude cells are split (or merged) so each spans about this many nodes
LIGHT_CUT = 1e-12         # light beyond these cumulative fractions at either end is dropped


def _elements(h: np.ndarray, rho: np.ndarray, refine: int = 1, merge: int = 1):
    """A piecewise-linear density as point elements with exact mass, mean and variance.

    Every altitude cell is split in ``refine`` (linear interpolation of the density), then
    runs of ``merge`` consecutive cells are joined into one element.

    Returns ``(h_c (..., J), var_h (..., J), mass (..., J))``: each element's light-weighted
    mean altitude (m), its variance about it (m^2) and its mass (total 1).
    """
    if refine > 1:
        hf = np.concatenate([np.linspace(h[i], h[i + 1], refine, endpoint=False)
                             for i in range(h.size - 1)] + [h[-1:]])
        rho = np.stack([np.interp(hf, h, r) for r in np.atleast_2d(rho)]).reshape(
            rho.shape[:-1] + hf.shape)
        h = hf
    d = np.diff(h)
    r0, r1 = rho[..., :-1], rho[..., 1:]
    m0 = (r0 + r1) * (d / 2)                       # mass of each cell
    m1 = (r0 + 2 * r1) * (d ** 2 / 6)              # first moment about the cell start
    m2 = (r0 + 3 * r1) * (d ** 3 / 12)             # second moment about the cell start
    start = h[:-1]
    ncell = d.size
    j = ncell // merge * merge
    if merge > 1:
        def grp(a):
            return a[..., :j].reshape(a.shape[:-1] + (-1, merge))

        g0 = start[:j].reshape(-1, merge)[:, 0]
        off = start[:j].reshape(-1, merge) - g0[:, None]           # (J, merge)
        a0, a1, a2 = grp(m0), grp(m1), grp(m2)
        big0 = a0.sum(-1)
        big1 = (a1 + a0 * off).sum(-1)
        big2 = (a2 + 2 * off * a1 + off ** 2 * a0).sum(-1)
        if j < ncell:
            big0 = np.concatenate([big0, m0[..., j:]], -1)
            big1 = np.concatenate([big1, m1[..., j:]], -1)
            big2 = np.concatenate([big2, m2[..., j:]], -1)
            g0 = np.concatenate([g0, start[j:]])
    else:
        big0, big1, big2, g0 = m0, m1, m2, start
    safe = np.where(big0 > 0, big0, 1.0)
    mean = big1 / safe
    var = np.maximum(big2 / safe - mean ** 2, 0.0)
    return g0 + mean, var, big0 / big0.sum(axis=-1, keepdims=True)


TABLE_STEP_PX = 1.0 / 2048  # core table step, a power of 2 (interpolation error < 4e-8)


@lru_cache(maxsize=8)
def _pixel_core_table(sigma_px: float):
    """``P(z) = Phi((z + 1/2)/sigma) - Phi((z - 1/2)/sigma)``, the light of a core centred
    at ``-z`` px in a pixel, tabulated on ``[z0, -z0]`` every ``TABLE_STEP_PX``.

    Returns ``(P, dP, z0, 1/step)``; ``P[i] + f dP[i]`` interpolates linearly (max error
    ``step^2 / 8 max|P''|`` < 4e-8 of the spot's light for the 1.19 px core); the table
    ends where ``P`` < 1e-11, and indices beyond it clip to those ends.
    """
    z0 = -(0.5 + CORE_SIGMAS * sigma_px + 1.0)
    z = z0 + TABLE_STEP_PX * np.arange(int(round(-2 * z0 / TABLE_STEP_PX)) + 2)
    tab = ndtr((z + 0.5) / sigma_px) - ndtr((z - 0.5) / sigma_px)
    tab[[0, -1]] = 0.0
    dtab = np.append(np.diff(tab), 0.0)
    tab[-1] = 0.0
    tab, dtab = tab.astype(np.float32), dtab.astype(np.float32)
    for a in (tab, dtab):
        a.setflags(write=False)
    return tab, dtab, z0, 1.0 / TABLE_STEP_PX


@lru_cache(maxsize=8)
def _core_cdf_table(sigma_px: float):
    """``Phi(z / sigma)`` on ``[z0, -z0]`` every ``TABLE_STEP_PX`` and its increments."""
    z0 = -(CORE_SIGMAS * sigma_px + 1.0)
    z = z0 + TABLE_STEP_PX * np.arange(int(round(-2 * z0 / TABLE_STEP_PX)) + 1)
    tab = ndtr(z / sigma_px)
    tab[0], tab[-1] = 0.0, 1.0
    dtab = np.append(np.diff(tab), 0.0)
    for a in (tab, dtab):
        a.setflags(write=False)
    return tab, dtab, z0, 1.0 / TABLE_STEP_PX


def _core_cdf(z: np.ndarray, sigma_px: float) -> np.ndarray:
    """``Phi(z / sigma)`` by linear interpolation in a fine table (error < 3e-8; 0 and 1
    beyond 6.5 sigma + 1 px, where the exact value is within 1e-11 of them)."""
    tab, dtab, z0, inv_h = _core_cdf_table(sigma_px)
    y = (z - z0) * inv_h
    np.clip(y, 0.0, tab.size - 1, out=y)
    i = y.astype(np.intp)
    y -= i
    out = tab.take(i)
    out += y * dtab.take(i)
    return out


# ---------------------------------------------------------------------------------------
# the spot model
# ---------------------------------------------------------------------------------------
class SpotModel:
    """Node weights of the light of each subaperture, built once per profile.

    Args:
        sensor: pixels, pixel scale, core, h_ref, zenith, detector type.
        r_m: ``(n,)`` distances from the launch (m).
        e: ``(n, 2)`` unit elongation vectors, detector axes (x, y).
        altitude_m: ``(K,)`` ascending altitudes (m).
        density: ``(K,)`` common profile or ``(n, K)`` one per subaperture (>= 0).
        max_shift_px: largest ``|shift|`` (per axis, px) :meth:`images` must handle
            exactly; light farther than that (plus the core) from the field is not kept.

    :meth:`images` takes the per-frame shifts and returns ``(images, truncated)``.
    """

    def __init__(self, sensor: Sensor, r_m, e, altitude_m, density, max_shift_px: float = 4.0):
        self.sensor = sensor
        self.r_m, self.e = _check_subaps(r_m, e)
        self.altitude_m, rho = _check_profile(altitude_m, density)
        if rho.ndim == 2 and rho.shape[0] != self.r_m.size:
            raise ValueError(f"density has {rho.shape[0]} rows for {self.r_m.size} subapertures")
        if not (math.isfinite(max_shift_px) and max_shift_px >= 0):
            raise ValueError("max_shift_px must be finite and >= 0")
        self.max_shift_px = float(max_shift_px)
        self.n = self.r_m.size
        self.polar = sensor.detector == "polar"
        self.sigma_px = sensor.core_fwhm_px * SIGMA_PER_FWHM
        self._build(rho)

    # -- construction -----------------------------------------------------------------
    def _build(self, rho):
        sensor, p = self.sensor, self.sensor.pixels
        h = self.altitude_m
        if self.polar:
            e_maj = np.ones(self.n)
            major_y = np.zeros(self.n, dtype=bool)
        else:
            major_y = np.abs(self.e[:, 1]) > np.abs(self.e[:, 0])
            e_maj = np.where(major_y, self.e[:, 1], self.e[:, 0])
        # nodes per pixel: 4 for long lines, more for short ones (whose error does not
        # average out over many node phases; their extra nodes are few)
        span = self._light_span_px(rho)
        m = np.where(span < 1.5, 4 * NODES_PER_PX, np.where(span < 5.0, 2 * NODES_PER_PX,
                                                             NODES_PER_PX)).astype(np.int64)
        step = 1.0 / (m * np.abs(e_maj))                      # node spacing along e, px
        cz = math.cos(math.radians(sensor.zenith_deg))
        # elements: split or merge altitude cells to about MAX_ELEMENT_NODES nodes each
        dgdh = cz / h ** 2 / sensor.pixel_scale_rad                 # px per m of altitude, per m of r
        span = (np.diff(h) * dgdh[:-1]).max() * (self.r_m / step).max(initial=0.0)
        refine = int(min(64, max(1, math.ceil(span / MAX_ELEMENT_NODES))))
        merge = int(min(h.size, max(1, math.floor(MAX_ELEMENT_NODES / max(span, 1e-300)))))
        h_c, var_h, mass = _elements(h, rho, refine, merge if refine == 1 else 1)
        # where the light is (cumulative in (LIGHT_CUT, 1 - LIGHT_CUT)), per profile
        cum = np.cumsum(mass, axis=-1)
        inside = (cum > LIGHT_CUT) & (cum - mass < 1 - LIGHT_CUT)
        mass = np.where(inside, mass, 0.0)
        hc2 = np.broadcast_to(h_c, mass.shape)
        h_lo = np.where(inside, hc2, np.inf).min(-1)
        h_hi = np.where(inside, hc2, -np.inf).max(-1)
        u_lo = self.r_m * cz * (1.0 / sensor.h_ref_m - 1.0 / h_lo) / sensor.pixel_scale_rad
        u_hi = self.r_m * cz * (1.0 / sensor.h_ref_m - 1.0 / h_hi) / sensor.pixel_scale_rad
        # window that can reach the field along the major axis
        reach = (p / 2 + self.max_shift_px + CORE_SIGMAS * self.sigma_px) / np.abs(e_maj)
        lo = np.maximum(np.floor(np.minimum(u_lo, 0) / step), -np.ceil(reach / step)) - 1
        hi = np.minimum(np.ceil(np.maximum(u_hi, 0) / step), np.ceil(reach / step)) + 1
        lo, hi = lo.astype(np.int64), hi.astype(np.int64)
        count = hi - lo + 1
        g_c = cz * (1.0 / sensor.h_ref_m - 1.0 / h_c) / sensor.pixel_scale_rad   # px per m of r
        dg_c = cz / h_c ** 2 / sensor.pixel_scale_rad
        self.groups = []
        for idx in self._grouping(m, count):
            k = int(count[idx].max()) + 3                              # nodes lo-1 .. lo+K+1
            k0 = lo[idx] - 1
            alpha = self.r_m[idx] / step[idx]                           # nodes per (px per m of r)
            w = self._deposit(alpha, k0, k, g_c, dg_c, var_h, mass, idx if rho.ndim == 2 else None)
            grp = self._group(idx, k0, w, step[idx], e_maj[idx], major_y[idx])
            grp["m"] = int(m[idx[0]])
            self.groups.append(grp)

    def _light_span_px(self, rho) -> np.ndarray:
        """``(n,)`` length (px along e) of the part of each line holding the light."""
        h, s = self.altitude_m, self.sensor
        c = np.cumsum(0.5 * (rho[..., 1:] + rho[..., :-1]) * np.diff(h), axis=-1)
        c = c / c[..., -1:]
        i_lo = np.argmax(c > 1e-6, axis=-1)
        i_hi = np.argmax(c >= 1 - 1e-6, axis=-1) + 1
        g = math.cos(math.radians(s.zenith_deg)) * (1.0 / h[i_lo] - 1.0 / h[i_hi]) / s.pixel_scale_rad
        return self.r_m * np.abs(g)

    def _grouping(self, m, count):
        """Index groups: same nodes per pixel, similar node counts (at most N_GROUPS each)."""
        out = []
        for mv in np.unique(m):
            sel = np.flatnonzero(m == mv)
            order = sel[np.argsort(count[sel], kind="stable")]
            ng = max(1, min(N_GROUPS, int(round(N_GROUPS * sel.size / max(self.n, 1))), sel.size))
            out += [i for i in np.array_split(order, ng) if i.size]
        return out

    @staticmethod
    def _deposit(alpha, k0, k, g_c, dg_c, var_h, mass, rows):
        """Node weights ``(g, k)`` from point elements, preserving for every element its
        mass and first three moments (4-point cubic Lagrange weights, with each element's
        own variance folded into its second and third moments). Compiled where numba is
        (:func:`_deposit_nodes`, the same numbers bit for bit: 12-17 -> ~4 ms a group)."""
        g = alpha.size
        if rows is not None:                                            # one profile per subaperture
            g_c, dg_c, var_h, mass = g_c[rows], dg_c[rows], var_h[rows], mass[rows]
        if _deposit_compiled is not None:
            ne = np.shape(g_c)[-1]
            out = np.zeros((4, g * k + 1))
            _deposit_compiled(np.asarray(alpha, dtype=np.float64), np.asarray(k0, dtype=np.int64),
                              int(k), *(np.broadcast_to(np.asarray(a, dtype=np.float64), (g, ne))
                                        for a in (g_c, dg_c, var_h, mass)), out)
            # numpy's order: a zero array plus each offset's sums in turn
            return (((out[0] + out[1]) + out[2]) + out[3])[:g * k].reshape(g, k)
        x = alpha[:, None] * g_c                                        # element position, nodes
        v = (alpha[:, None] * dg_c) ** 2 * var_h
        m = np.broadcast_to(mass, x.shape)
        left = np.floor(x)
        t = x - left
        t2 = t * t + v
        t3 = t * (t * t + 3 * v)
        node = left.astype(np.int64) - k0[:, None]                      # local index of floor(x)
        out = np.zeros(g * k + 1)                                       # last bin: overflow
        base = (np.arange(g) * k)[:, None]
        weights = ((-1, -(t3 - 3 * t2 + 2 * t) / 6), (0, (t3 - 2 * t2 - t + 2) / 2),
                   (1, -(t3 - t2 - 2 * t) / 2), (2, (t3 - t) / 6))
        for off, wt in weights:
            j = node + off
            flat = np.where((j >= 0) & (j < k), base + j, g * k)
            out += np.bincount(flat.ravel(), (m * wt).ravel(), minlength=g * k + 1)
        return out[:g * k].reshape(g, k)

    def _group(self, idx, k0, w, step, e_maj, major_y):
        """Per-group arrays, nodes ordered by increasing major-axis coordinate."""
        kidx = k0[:, None] + np.arange(w.shape[1])                  # (g, K) node numbers
        u = kidx * step[:, None]                                    # px along e
        flip = e_maj < 0
        w = np.where(flip[:, None], w[:, ::-1], w)
        u = np.where(flip[:, None], u[:, ::-1], u)
        e = self.e[idx]
        if self.polar:
            e_min = np.zeros(idx.size)
        else:
            e_min = np.where(major_y, e[:, 0], e[:, 1])
        return {
            "idx": idx, "w": np.ascontiguousarray(w), "major_y": major_y,
            "w32": np.ascontiguousarray(w, dtype=np.float32),
            "a0": u[:, 0] * e_maj,                                   # major coord of node 0
            "b": u * e_min[:, None],                                 # minor coords (g, K)
        }

    # -- per frame --------------------------------------------------------------------
    def images(self, shift_px, out=None) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free images for the given true displacements.

        Args:
            shift_px: ``(n, 2)`` displacement (x, y) of each spot, pixels, detector axes.
            out: optional ``(n, p, p)`` float64 array to write into.
        Returns:
            ``(images (n, p, p) float64, truncated (n,))``: polar blocks are in their local
            frame (rows local y, columns local x), cartesian in detector axes; each image
            sums to ``1 - truncated``.
        """
        s = self._checked_shift(shift_px)
        p = self.sensor.pixels
        if self.polar:
            s = detector_to_local(s, self.e)
        img = np.empty((self.n, p, p)) if out is None else out
        for g in self.groups:
            sg = s[g["idx"]]
            s_maj = np.where(g["major_y"], sg[:, 1], sg[:, 0])
            s_min = np.where(g["major_y"], sg[:, 0], sg[:, 1])
            img[g["idx"]] = self._render(g, s_maj, s_min)
        np.maximum(img, 0.0, out=img)        # rounding/sharpening can leave -1e-7 in dark pixels
        trunc = 1.0 - img.reshape(self.n, -1).sum(axis=1)
        return img, np.clip(trunc, 0.0, 1.0)

    def marginals(self, shift_px) -> np.ndarray:
        """``(n, 2, p)`` float64: each polar spot's column sums (``[:, 0]``, along local x)
        and row sums (``[:, 1]``, along local y), what :meth:`images`' ``img.sum(axis=1)``
        and ``img.sum(axis=2)`` give to rounding, without forming the images: a polar spot
        is the outer product of its line along e and its core across (the likelihood
        tables of :mod:`..centroiding.ml` need only these). ``shift_px (n, 2)`` as for
        :meth:`images`."""
        if not self.polar:
            raise ValueError("marginals: polar models only (a cartesian spot is not separable)")
        s = detector_to_local(self._checked_shift(shift_px), self.e)
        out = np.empty((self.n, 2, self.sensor.pixels))
        for g in self.groups:
            line, gmin = self._polar_lines(g, s[g["idx"], 0], s[g["idx"], 1])
            line = np.maximum(line, 0.0)          # as images() clamps (the core is >= 0)
            out[g["idx"], 0] = line * gmin.sum(axis=1)[:, None]
            out[g["idx"], 1] = gmin * line.sum(axis=1)[:, None]
        return out

    def _checked_shift(self, shift_px) -> np.ndarray:
        """``shift_px (n, 2)`` as float, refused beyond the ``max_shift_px`` the model was
        built for."""
        s = _check_shift(shift_px, self.n)
        if np.any(np.abs(s) > self.max_shift_px + 1e-9):
            raise ValueError(f"|shift| up to {np.abs(s).max():.3g} px exceeds max_shift_px="
                             f"{self.max_shift_px} this model was built for")
        return s

    def _polar_lines(self, g, s_maj, s_min):
        """``(line (g, p), core (g, p))``: a polar group's light per pixel along local x
        (the line along e) and along local y (the core across it)."""
        p, m, sig = self.sensor.pixels, g["m"], self.sigma_px
        nk = g["w"].shape[1]
        v = self._edge_cdf(g, s_maj)
        # cumulative light of the line at the p + 1 pixel edges: a correlation of V with w
        win = sliding_window_view(v, nk, axis=1)[:, ::m][:, :p + 1]       # (g, p + 1, K)
        cum = np.matmul(win, g["w"][:, ::-1, None])[:, :, 0]
        jm = np.arange(p + 1) - 0.5
        emin = ndtr((jm[None, :] - ((p - 1) / 2.0 + s_min)[:, None]) / sig)
        return cum[:, 1:] - cum[:, :-1], emin[:, 1:] - emin[:, :-1]

    def _render(self, g, s_maj, s_min):
        if self.polar:
            line, gmin = self._polar_lines(g, s_maj, s_min)
            return gmin[:, :, None] * line[:, None, :]                    # rows local y, cols local x
        v = self._edge_cdf(g, s_maj)
        gmaj = self._major_lines(g, v)
        gmin = self._minor_lines(g, s_min)
        im = np.matmul(gmin.transpose(0, 2, 1), gmaj)                # (g, minor, major), float32
        return np.where(g["major_y"][:, None, None], im.transpose(0, 2, 1), im)

    def _edge_cdf(self, g, s_maj):
        """``(g, m p + K)`` the core's CDF along the major axis: Phi at edge e - 1/2 of node
        k is ``V[m e - k + K - 1]``, for major-axis shifts ``s_maj (g,)`` px."""
        p, m, nk = self.sensor.pixels, g["m"], g["w"].shape[1]
        a0 = (p - 1) / 2.0 + g["a0"] + s_maj
        q = (np.arange(m * p + nk) - (nk - 1)) / m - 0.5
        return _core_cdf(q[None, :] - a0[:, None], self.sigma_px)

    def _major_lines(self, g, v):
        """``(g, K, p)`` float32: each node's light per pixel along the major axis (weighted),
        from the core's CDF ``v`` at the node edges (cartesian)."""
        p, nk = self.sensor.pixels, g["w"].shape[1]
        v = v.astype(np.float32)
        st = v.strides
        edges = as_strided(v[:, nk - 1:], shape=(v.shape[0], nk, p + 1),
                           strides=(st[0], -st[1], g["m"] * st[1]), writeable=False)
        gmaj = np.subtract(edges[:, :, 1:], edges[:, :, :-1])            # (g, K, p) float32
        gmaj *= g["w32"][:, :, None]
        return gmaj

    def _minor_lines(self, g, s_min):
        """``(g, K, p)`` float32: each node's core integrated over the pixels of the minor
        axis (cartesian). The table index of pixel j for node k is j / step + Y_k (integers)
        and the interpolation fraction phi_k is the same for all pixels of a node."""
        p, c = self.sensor.pixels, (self.sensor.pixels - 1) / 2.0
        tab, dtab, z0, inv_h = _pixel_core_table(self.sigma_px)
        t = -(c + g["b"] + s_min[:, None] + z0) * inv_h                  # (g, K)
        y0 = np.floor(t)
        phi = (t - y0).astype(np.float32)
        if _minor_compiled is not None:              # the same float32 numbers, no index array
            gmin = np.empty(t.shape + (p,), dtype=np.float32)
            _minor_compiled(y0.astype(np.intp), phi, int(inv_h), tab, dtab, gmin)
            return gmin
        i = y0.astype(np.intp)[:, :, None] + (np.arange(p) * int(inv_h))[None, None, :]
        gmin = tab.take(i, mode="clip")
        gmin += phi[:, :, None] * dtab.take(i, mode="clip")
        return gmin

    def cog_grid(self, t) -> np.ndarray:
        """``(n, T, T, 2)`` CoG (px from the block centre, detector axes) of every spot
        displaced by ``(t[a], t[b])`` px in (x, y), for a cartesian detector.

        A spot is a sum over nodes of a line along the major pixel axis times a core along
        the minor one, so its moments are sums of products of 1-D moments: ``2 T`` partial
        renders give the ``T^2`` positions (what :meth:`images` and a CoG give, to float32
        rounding).

        Args:
            t: ``(T,)`` shifts, px, each ``|t| <= max_shift_px``.

        Returns:
            NaN where the field keeps no more than :data:`NO_LIGHT` of a spot (the
            cartesian renders are float32: a CoG of less light is rounding noise).
        """
        if self.polar:
            raise ValueError("cog_grid is for a cartesian detector (polar spots: one render "
                             "per diagonal position gives both axes)")
        t = np.asarray(t, dtype=float)
        if np.any(np.abs(t) > self.max_shift_px + 1e-9):
            raise ValueError(f"|shift| up to {np.abs(t).max():.3g} px exceeds max_shift_px="
                             f"{self.max_shift_px} this model was built for")
        p = self.sensor.pixels
        w = np.stack([np.ones(p), np.arange(p) - (p - 1) / 2.0], axis=1).astype(np.float32)
        out = np.empty((self.n, t.size, t.size, 2))
        for g in self.groups:
            shift = [np.full(g["idx"].size, tk) for tk in t]
            # each line's sum and first moment in one product with (p, 2) (two float32
            # reductions over 16 pixels cost twice as much): (g, 2, T, K) float64
            a = np.stack([self._major_lines(g, self._edge_cdf(g, sk)) @ w for sk in shift])
            b = np.stack([self._minor_lines(g, sk) @ w for sk in shift])
            a = a.transpose(1, 3, 0, 2).astype(np.float64)
            b = b.transpose(1, 3, 2, 0).astype(np.float64)                  # (g, 2, K, T)
            m0 = a[:, 0] @ b[:, 0]                                  # (g, T, T) [major, minor]
            m_maj = a[:, 1] @ b[:, 0]
            m_min = a[:, 0] @ b[:, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                c_maj = np.where(m0 > NO_LIGHT, m_maj / m0, np.nan)
                c_min = np.where(m0 > NO_LIGHT, m_min / m0, np.nan)
            y = g["major_y"][:, None, None]                                  # (x node, y node)
            out[g["idx"], :, :, 0] = np.where(y, c_min.transpose(0, 2, 1), c_maj)
            out[g["idx"], :, :, 1] = np.where(y, c_maj.transpose(0, 2, 1), c_min)
        return out


def spot_images(sensor: Sensor, r_m, e, altitude_m, density, shift_px) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free spot images (one call; see :class:`SpotModel` to reuse a profile).

    Args:
        sensor: the sensor (pixels, scale, core, h_ref, zenith, detector).
        r_m: ``(n,)`` distance of each subaperture from the launch, m.
        e: ``(n, 2)`` unit elongation vectors, detector axes.
        altitude_m: ``(K,)`` ascending altitudes above the telescope, m.
        density: ``(K,)`` or ``(n, K)`` sodium density (any units, >= 0).
        shift_px: ``(n, 2)`` true displacement (x, y) of each spot, pixels, detector axes.
    Returns:
        ``(images (n, p, p) float64, truncated (n,))``, images normalised to
        ``1 - truncated``; polar blocks in their local frame.
    """
    r, _ = _check_subaps(r_m, e)
    s = _check_shift(shift_px, r.size)
    smax = float(np.abs(s).max()) if s.size else 0.0
    return SpotModel(sensor, r_m, e, altitude_m, density, max_shift_px=smax).images(s)


def _deposit_nodes(alpha, k0, k, g_c, dg_c, var_h, mass, out):
    # ProfileSpots._deposit's sums, compiled: out[o, r k + j] (o = 0..3 for node offsets
    # -1..2, last column the overflow) accumulates element by element in numpy's order (rows,
    # then elements; each offset's bincount in its own row), with the same float expressions
    # (no fastmath), so the caller's sum of the four rows equals numpy's bit for bit. The
    # element arrays are (g, E) (broadcast views where a profile is shared)
    g = alpha.shape[0]
    ne = g_c.shape[1]
    over = g * k
    for r in range(g):
        a = alpha[r]
        for e in range(ne):
            x = a * g_c[r, e]
            d = a * dg_c[r, e]
            v = d * d * var_h[r, e]
            m = mass[r, e]
            left = np.floor(x)
            t = x - left
            t2 = t * t + v
            t3 = t * (t * t + 3 * v)
            j = np.int64(left) - k0[r] - 1                  # the node of offset -1
            base = r * k
            out[0, base + j if 0 <= j < k else over] += m * (-(t3 - 3 * t2 + 2 * t) / 6)
            j += 1
            out[1, base + j if 0 <= j < k else over] += m * ((t3 - 2 * t2 - t + 2) / 2)
            j += 1
            out[2, base + j if 0 <= j < k else over] += m * (-(t3 - t2 - 2 * t) / 2)
            j += 1
            out[3, base + j if 0 <= j < k else over] += m * ((t3 - t) / 6)


def _minor_table(y0, phi, step, tab, dtab, out):
    # SpotModel._minor_lines' lookups, compiled: out[g, k, j] = tab[i] + phi[g, k] dtab[i]
    # with i = y0[g, k] + j step clipped to the table (numpy's take, mode "clip"), in float32
    # as numpy computes it (the product rounded, then the sum), without the (g, K, p) index
    # array
    last = tab.shape[0] - 1
    for a in range(out.shape[0]):
        for k in range(out.shape[1]):
            f = phi[a, k]
            i0 = y0[a, k]
            for j in range(out.shape[2]):
                i = min(max(i0 + j * step, 0), last)
                out[a, k, j] = tab[i] + np.float32(f * dtab[i])


if detector.numba is not None:         # the 'fast' extra (detector.numba is None without it)
    _deposit_compiled = detector.numba.njit(cache=True, nogil=True)(_deposit_nodes)
    _minor_compiled = detector.numba.njit(cache=True, nogil=True)(_minor_table)
else:                                  # pragma: no cover - exercised where it is absent
    _deposit_compiled = _minor_compiled = None


__all__ = ["SpotModel", "spot_images", "elongation_px", "linear_elongation_arcsec", "NO_LIGHT",
           "exact_elongation_arcsec", "light_centroid_px", "NODES_PER_PX", "SIGMA_PER_FWHM"]
