"""Pupil and subaperture geometry: valid mask, centres, elongation vectors, frame layout.

Conventions (docs/conventions.md, sections 2-3): subaperture (i, j) is row i, column j
and owns ``frame[p*i:p*i+p, p*j:p*j+p]``; its centre in the pupil is
``x_j = (j - (N-1)/2) d``, ``y_i = (i - (N-1)/2) d`` metres; ``r = |centre - launch|`` and
``e = (centre - launch) / r`` (``(1, 0)`` where ``r = 0``).

Arrays over valid subapertures have a leading axis of length ``n`` in row-major (i, j)
order; that order is the one of :func:`frame_to_stack` and every centroider.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..sensor import Sensor


@dataclass(frozen=True, eq=False)
class Layout:
    """Where the valid subapertures are. Arrays are read-only.

    Attributes:
        sensor: the sensor this layout describes.
        illuminated: ``(G, G)`` fraction of each subaperture square inside the pupil.
        valid: ``(G, G)`` bool, illuminated fraction >= ``sensor.valid_fraction``.
        index: ``(n, 2)`` int, (row i, column j) of each valid subaperture.
        centre_xy_m: ``(n, 2)`` pupil coordinates (x, y) of the centres, metres.
        r_m: ``(n,)`` distance from the laser launch, metres.
        e: ``(n, 2)`` unit elongation vector (x, y), detector axes.
    """

    sensor: Sensor
    illuminated: np.ndarray
    valid: np.ndarray
    index: np.ndarray
    centre_xy_m: np.ndarray
    r_m: np.ndarray
    e: np.ndarray

    @property
    def n_valid(self) -> int:
        return int(self.index.shape[0])

    @property
    def grid(self) -> int:
        return self.sensor.grid


def _illuminated_fraction(sensor: Sensor, samples: int = 32) -> np.ndarray:
    """``(N, N)`` fraction of each subaperture square inside the annular pupil."""
    n, d = sensor.n_subaps, sensor.subap_pitch_m
    centres = (np.arange(n) - (n - 1) / 2) * d
    sub = ((np.arange(samples) + 0.5) / samples - 0.5) * d
    coord = (centres[:, None] + sub[None, :]).ravel()          # (n*samples,)
    rho2 = coord[None, :] ** 2 + coord[:, None] ** 2             # [y, x]
    inside = (rho2 <= (sensor.diameter_m / 2) ** 2) & (rho2 >= (sensor.obstruction_m / 2) ** 2)
    return inside.reshape(n, samples, n, samples).mean(axis=(1, 3))


def _elongation(centre_xy_m: np.ndarray, launch_xy_m) -> tuple[np.ndarray, np.ndarray]:
    rel = centre_xy_m - np.asarray(launch_xy_m, dtype=float)
    r = np.hypot(rel[:, 0], rel[:, 1])
    e = np.empty_like(rel)
    safe = r > 0
    e[safe] = rel[safe] / r[safe, None]
    e[~safe] = (1.0, 0.0)
    return r, e


@lru_cache(maxsize=32)
def layout(sensor: Sensor) -> Layout:
    """The (cached) layout of a sensor's valid subapertures."""
    if sensor.is_single:
        illuminated = np.ones((1, 1))
        valid = np.ones((1, 1), dtype=bool)
        index = np.zeros((1, 2), dtype=np.intp)
        centre = np.array([sensor.single_subaperture_xy_m], dtype=float)
    else:
        illuminated = _illuminated_fraction(sensor)
        valid = illuminated >= sensor.valid_fraction - 1e-12
        index = np.argwhere(valid)
        n, d = sensor.n_subaps, sensor.subap_pitch_m
        centre = np.stack([(index[:, 1] - (n - 1) / 2) * d, (index[:, 0] - (n - 1) / 2) * d], axis=1)
    r, e = _elongation(centre, sensor.launch_xy_m)
    for a in (illuminated, valid, index, centre, r, e):
        a.setflags(write=False)
    return Layout(sensor, illuminated, valid, index, centre, r, e)


def frame_to_stack(frame: np.ndarray, lay: Layout) -> np.ndarray:
    """Cut a frame into the valid subaperture images.

    Args:
        frame: ``(G*p, G*p)`` detector frame (any dtype), or ``(F, G*p, G*p)`` frames.
        lay: the sensor layout.

    Returns:
        ``(n, p, p)`` (or ``(F, n, p, p)``) array, a copy, in row-major subaperture order.
    """
    g, p = lay.grid, lay.sensor.pixels
    shape = (g * p, g * p)
    if frame.shape[-2:] != shape:
        raise ValueError(f"frame has shape {frame.shape[-2:]}, the sensor expects {shape}")
    lead = frame.shape[:-2]
    blocks = frame.reshape(*lead, g, p, g, p).swapaxes(-3, -2)   # (..., G, G, p, p)
    return blocks[..., lay.valid, :, :]


def stack_to_frame(stack: np.ndarray, lay: Layout, fill=0) -> np.ndarray:
    """Inverse of :func:`frame_to_stack`: ``(n, p, p)`` -> ``(G*p, G*p)`` frame."""
    g, p = lay.grid, lay.sensor.pixels
    blocks = np.full((g, g, p, p), fill, dtype=stack.dtype)
    blocks[lay.valid] = stack
    return blocks.swapaxes(1, 2).reshape(g * p, g * p)


def slopes_to_grid(slopes: np.ndarray, lay: Layout) -> np.ndarray:
    """``(n, 2)`` slopes -> ``(G, G, 2)`` float32 grid, NaN where not valid."""
    grid = np.full((lay.grid, lay.grid, 2), np.nan, dtype=np.float32)
    grid[lay.valid] = slopes
    return grid


def grid_to_slopes(grid: np.ndarray, lay: Layout) -> np.ndarray:
    """``(G, G, 2)`` grid -> ``(n, 2)`` slopes of the valid subapertures."""
    if grid.shape != (lay.grid, lay.grid, 2):
        raise ValueError(f"slope grid has shape {grid.shape}, expected {(lay.grid, lay.grid, 2)}")
    return grid[lay.valid]


def local_to_detector(v: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Rotate ``(..., n, 2)`` vectors from the local frame (x along e) to detector axes."""
    ex, ey = e[:, 0], e[:, 1]
    x, y = v[..., 0], v[..., 1]
    return np.stack([ex * x - ey * y, ey * x + ex * y], axis=-1)


def detector_to_local(v: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Rotate ``(..., n, 2)`` vectors from detector axes to the local frame (x along e)."""
    ex, ey = e[:, 0], e[:, 1]
    x, y = v[..., 0], v[..., 1]
    return np.stack([ex * x + ey * y, -ey * x + ex * y], axis=-1)
