"""A picture of one slopes grid, for rviz and Foxglove: x and y maps side by side (rgb8).

Pure numpy (no rclpy): the centroider publishes it as a ``sensor_msgs/Image`` (``rgb8``) on
``slopes_picture`` at a few Hz. Each subaperture is a ``cell`` x ``cell`` square coloured on a
diverging scale (blue -range_px .. white 0 .. red +range_px, clipped); subapertures that are
not valid (NaN) are dark grey; a black band of one cell separates the x map (left) from the
y map (right).
"""

from __future__ import annotations

import numpy as np

NEGATIVE = np.array([33, 102, 172], dtype=np.float32)    # blue
ZERO = np.array([247, 247, 247], dtype=np.float32)       # white
POSITIVE = np.array([178, 24, 43], dtype=np.float32)     # red
INVALID = np.array([60, 60, 60], dtype=np.uint8)
PICTURE_PIXELS = 256      # about this many pixels per map side


def diverging(values: np.ndarray, range_px: float) -> np.ndarray:
    """``values`` (any shape, pixels) as rgb8 colours, shape + (3,); NaN -> INVALID."""
    t = np.clip(np.nan_to_num(values, nan=0.0) / float(range_px), -1.0, 1.0)[..., None]
    rgb = np.where(t < 0, ZERO + (NEGATIVE - ZERO) * (-t), ZERO + (POSITIVE - ZERO) * t)
    out = np.rint(rgb).astype(np.uint8)
    out[np.isnan(values)] = INVALID
    return out


def slopes_picture(grid: np.ndarray, range_px: float = 1.0, cell: int | None = None) -> np.ndarray:
    """The picture of a ``(G, G, 2)`` slopes grid (pixels, NaN where not valid).

    Returns:
        ``(G*cell, (2*G + 1)*cell, 3)`` uint8: x map, a black band, y map. ``cell`` defaults
        to about ``PICTURE_PIXELS / G`` (at least 1).
    """
    grid = np.asarray(grid, dtype=np.float32)
    g = grid.shape[0]
    cell = cell or max(1, PICTURE_PIXELS // g)
    band = np.zeros((g, 1, 3), dtype=np.uint8)
    small = np.concatenate([diverging(grid[..., 0], range_px), band,
                            diverging(grid[..., 1], range_px)], axis=1)
    return np.repeat(np.repeat(small, cell, axis=0), cell, axis=1)
