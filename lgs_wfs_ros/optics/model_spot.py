"""Model spots of a sodium profile given on altitude nodes, and their projection along e.

The pupil calibration (:mod:`lgs_wfs_ros.centroiding.pupil`) describes the sodium profile
by the light ``x_k`` in thin layers: triangles ("hats") on altitude nodes ``h_k``, so the
density is piecewise linear and every spot is linear in ``x``. This module renders those
spots through each subaperture's exact geometry with :class:`.spots.SpotModel` (launch
position, zenith angle, detector type and truncation at the field edge included) and
projects images onto bins along the elongation direction, where the profile lives.

Shapes: ``n`` subapertures, ``p x p`` pixels, ``K`` nodes, ``nb`` projection bins. Images
are in block pixel axes (the local frame on a polar detector), as the centroiders see them.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse

from ..sensor import Sensor
from . import fast_frames
from .geometry import local_to_detector
from .spots import SpotModel


def altitude_nodes(sensor: Sensor, count: int = 120, low_m: float = 70e3,
                   high_m: float = 130e3) -> np.ndarray:
    """``(count,)`` node altitudes (m), evenly spaced in ``1/h`` (so evenly spaced in image
    offset ``r cos z (1/h_ref - 1/h)`` at every radius), ascending."""
    if not (count >= 3 and 0 < low_m < high_m):
        raise ValueError("need count >= 3 and 0 < low_m < high_m")
    w = np.linspace(1.0 / high_m, 1.0 / low_m, int(count))
    return np.sort(1.0 / w)


def node_density(nodes_m: np.ndarray, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-linear density whose hat on node k holds ``light[..., k]``.

    Returns ``(altitude_m (K+2,), density (..., K+2))``: the nodes padded by one zero node
    below and above (one node spacing away), so the end hats are whole.
    """
    h = np.asarray(nodes_m, dtype=float)
    ext = np.concatenate([[2 * h[0] - h[1]], h, [2 * h[-1] - h[-2]]])
    width = 0.5 * (ext[2:] - ext[:-2])
    dens = np.asarray(light, dtype=float) / width
    pad = np.zeros(dens.shape[:-1] + (1,))
    return ext, np.concatenate([pad, dens, pad], axis=-1)


def shift_to_detector(sensor: Sensor, e: np.ndarray, shift_block: np.ndarray) -> np.ndarray:
    """Block-pixel-axes shifts ``(n, 2)`` -> detector axes (a rotation on a polar detector)."""
    s = np.asarray(shift_block, dtype=float)
    return local_to_detector(s, e) if sensor.detector == "polar" else s


class Projection:
    """Sum of each block's pixels into bins of width ``bin_px`` along its elongation.

    Args:
        sensor: pixels per side, detector type.
        e_pixel: ``(n, 2)`` elongation unit vectors in block pixel axes ((1, 0) on polar).
        bin_px: bin width along e, pixels (1: the pixel columns on a polar detector).

    :meth:`__call__` maps ``(..., n, p*p)`` to ``(..., n, nb)``; it is linear, so model and
    data projected alike stay comparable however coarse the bins.
    """

    def __init__(self, sensor: Sensor, e_pixel: np.ndarray, bin_px: float = 1.0):
        p = sensor.pixels
        e = np.asarray(e_pixel, dtype=float)
        n = e.shape[0]
        y, x = np.indices((p, p), dtype=float)
        c = (p - 1) / 2
        u = (x.ravel() - c)[None, :] * e[:, :1] + (y.ravel() - c)[None, :] * e[:, 1:]   # (n, pp)
        half = c * math.sqrt(2.0) + 1e-9
        self.nb = int(math.ceil(2 * half / bin_px)) + 1
        b = np.clip(np.floor((u + half) / bin_px).astype(np.int64), 0, self.nb - 1)
        self.n, self.pp = n, p * p
        rows = (b + self.nb * np.arange(n)[:, None]).ravel()
        cols = np.arange(n * p * p)
        self.matrix = sparse.csr_matrix((np.ones(n * p * p), (rows, cols)),
                                        shape=(n * self.nb, n * p * p))

    def __call__(self, flat: np.ndarray) -> np.ndarray:
        a = np.asarray(flat, dtype=float)
        lead = a.shape[:-2]
        v = a.reshape(-1, self.n * self.pp).T                       # (n*pp, m)
        out = (self.matrix @ v).T                                   # (m, n*nb)
        return out.reshape(lead + (self.n, self.nb))


def projected_hats(sensor: Sensor, r_m, e, nodes_m, projection: Projection,
                   shift_block=None, layout=None) -> np.ndarray:
    """``(n, nb, K)`` projected noise-free spots of unit light in each node's hat (light
    truncated by the field is lost, as in the frames), at zero shift or displaced by
    ``shift_block (n, 2)`` px, block axes (``e (n, 2)`` is in detector axes). With
    ``layout`` (whose valid blocks are the ``n`` subapertures) on a cartesian detector the
    spots come from the simulator's compiled renderer
    (:meth:`.fast_frames.FastRenderer.canvas`: within 1e-7 of the light of the exact
    renders, in a fifth of their time) where numba is installed."""
    ext = np.concatenate([[2 * nodes_m[0] - nodes_m[1]], nodes_m, [2 * nodes_m[-1] - nodes_m[-2]]])
    n = np.asarray(r_m).size
    out = np.empty((n, projection.nb, len(nodes_m)))
    shift = np.zeros((n, 2)) if shift_block is None else shift_to_detector(sensor, e, shift_block)
    reach = float(np.abs(shift).max()) if shift_block is not None else 0.0
    fast = None
    if layout is not None and sensor.detector == "cartesian" and fast_frames.AVAILABLE:
        fast = fast_frames.FastRenderer(layout)
    for k in range(len(nodes_m)):
        grid = ext[k:k + 3]
        model = SpotModel(sensor, r_m, e, grid, np.array([0.0, 1.0, 0.0]), max_shift_px=reach)
        img = model.images(shift)[0] if fast is None else fast.canvas(model, shift, 0)
        out[:, :, k] = projection(img.reshape(n, -1))
    return out


class ProfileSpots:
    """Noise-free spots of one profile on nodes, for every subaperture (references).

    Args:
        sensor, r_m (n,), e (n, 2) detector axes: the geometry.
        nodes_m (K,), light (K,): the profile as light per node hat.
        max_shift_px: largest shift :meth:`image_at` must render.
    """

    def __init__(self, sensor: Sensor, r_m, e, nodes_m, light, max_shift_px: float = 1.5):
        self.sensor, self.e = sensor, np.asarray(e, dtype=float)
        h, dens = node_density(nodes_m, np.maximum(light, 0.0))
        self.model = SpotModel(sensor, r_m, self.e, h, dens, max_shift_px=max_shift_px)
        self.n = self.model.n

    def image_at(self, shift_block: np.ndarray) -> np.ndarray:
        """``(n, p, p)`` unit-light images displaced by ``shift_block (n, 2)`` px, block axes."""
        img, _ = self.model.images(shift_to_detector(self.sensor, self.e, shift_block))
        return img

    def marginals_at(self, shift_block: np.ndarray) -> np.ndarray:
        """``(n, 2, p)`` column and row sums of :meth:`image_at`'s images (polar detector:
        :meth:`.spots.SpotModel.marginals`, no image formed)."""
        return self.model.marginals(shift_to_detector(self.sensor, self.e, shift_block))

    def reference(self, h: float = 0.01, image: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(image, d/dx, d/dy)`` at zero shift, unit light, block axes (central differences
        of exact renders: the Fourier dither is wrong for the under-sampled core); ``image``:
        that image if already rendered (``image_at`` of zero shifts)."""
        zero = np.zeros((self.n, 2))
        img = self.image_at(zero) if image is None else image
        ex, ey = np.array([h, 0.0]), np.array([0.0, h])
        dx = (self.image_at(zero + ex) - self.image_at(zero - ex)) / (2 * h)
        dy = (self.image_at(zero + ey) - self.image_at(zero - ey)) / (2 * h)
        return img, dx, dy


__all__ = ["altitude_nodes", "node_density", "shift_to_detector", "Projection",
           "projected_hats", "ProfileSpots"]
