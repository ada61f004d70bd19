"""Centroiding error metrics (docs/conventions.md section 4).

``err = estimate - truth`` in pixels, per subaperture and frame. NaN estimates (a subaperture a
centroider refused) are left out of the statistics and counted.
"""

from __future__ import annotations

import numpy as np


def errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``(..., 2)`` error vectors in pixels; shapes must match."""
    estimate = np.asarray(estimate, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if estimate.shape != truth.shape or estimate.shape[-1:] != (2,):
        raise ValueError(f"estimate {estimate.shape} and truth {truth.shape} must both be (..., 2)")
    return estimate - truth


def summarize(err: np.ndarray, mas_per_px: float = 500.0) -> dict:
    """Statistics of ``(..., 2)`` errors in pixels, plus the same in mas.

    Returns a dict with ``mean_euclid`` (mean |err|), ``mae_x``, ``mae_y``, ``mae`` (mean absolute
    error averaged over the two axes), ``rms`` (sqrt of mean |err|^2), ``bias_x``, ``bias_y``,
    ``n`` (finite error vectors used) and ``n_nan``; every length also as ``<name>_mas``.
    """
    err = np.asarray(err, dtype=float).reshape(-1, 2)
    finite = np.isfinite(err).all(axis=1)
    e = err[finite]
    out = {"n": int(e.shape[0]), "n_nan": int((~finite).sum())}
    if e.shape[0] == 0:
        stats = dict.fromkeys(("mean_euclid", "mae_x", "mae_y", "mae", "rms", "bias_x", "bias_y"),
                              float("nan"))
    else:
        a = np.abs(e)
        stats = {
            "mean_euclid": float(np.hypot(e[:, 0], e[:, 1]).mean()),
            "mae_x": float(a[:, 0].mean()),
            "mae_y": float(a[:, 1].mean()),
            "mae": float(a.mean()),
            "rms": float(np.sqrt((e ** 2).sum(axis=1).mean())),
            "bias_x": float(e[:, 0].mean()),
            "bias_y": float(e[:, 1].mean()),
        }
    out.update(stats)
    out.update({k + "_mas": v * mas_per_px for k, v in stats.items()})
    return out


def by_radius(err: np.ndarray, r_m: np.ndarray, edges_m) -> list[dict]:
    """Mean Euclidean error per ring of subaperture radius.

    Args:
        err: ``(F, n, 2)`` or ``(n, 2)`` errors, pixels.
        r_m: ``(n,)`` subaperture distance from the launch, metres.
        edges_m: ring edges, metres (ascending).
    """
    err = np.asarray(err, dtype=float)
    err = err.reshape(-1, r_m.shape[0], 2)
    dist = np.hypot(err[..., 0], err[..., 1])
    ring = np.digitize(r_m, edges_m) - 1
    rows = []
    for k in range(len(edges_m) - 1):
        d = dist[:, ring == k]
        d = d[np.isfinite(d)]
        rows.append({"r_min_m": float(edges_m[k]), "r_max_m": float(edges_m[k + 1]),
                     "n": int(d.size), "mean_euclid": float(d.mean()) if d.size else float("nan")})
    return rows


def table(rows: dict[str, dict], mas_per_px: float = 500.0) -> str:
    """A plain-text table of ``{algorithm: summarize(...)}``."""
    head = f"{'algorithm':<12}{'mean |err|':>12}{'MAE/axis':>11}{'RMS':>9}{'bias x':>9}{'bias y':>9}" \
           f"{'mean |err|':>13}{'n':>10}"
    unit = f"{'':<12}{'px':>12}{'px':>11}{'px':>9}{'px':>9}{'px':>9}{'mas':>13}{'':>10}"
    lines = [head, unit]
    for name, s in rows.items():
        lines.append(f"{name:<12}{s['mean_euclid']:>12.4f}{s['mae']:>11.4f}{s['rms']:>9.4f}"
                     f"{s['bias_x']:>9.4f}{s['bias_y']:>9.4f}{s['mean_euclid_mas']:>13.1f}{s['n']:>10d}")
    return "\n".join(lines)


def ttf_modes(centre_xy_m: np.ndarray) -> np.ndarray:
    """``(2n, 3)`` orthonormal slope patterns of tip, tilt and focus over subapertures at
    ``centre_xy_m (n, 2)`` (slopes x, y interleaved; focus: slope proportional to position)."""
    xy = np.asarray(centre_xy_m, dtype=float)
    m = np.zeros((xy.shape[0], 2, 3))
    m[:, 0, 0] = 1.0
    m[:, 1, 1] = 1.0
    m[:, :, 2] = xy
    q, _ = np.linalg.qr(m.reshape(-1, 3))
    return q


def remove_ttf(err: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``(K, n, 2)`` errors minus their pupil-wide tip, tilt and focus, frame by frame (the
    same as removing them from estimate and truth; NaN subapertures left out of each fit).
    ``q``: :func:`ttf_modes` of the same subapertures. LGS AO takes these three modes from a
    natural guide star: the sodium profile's altitude is exactly focus (docs/accuracy.md)."""
    k, n, _ = err.shape
    e = err.reshape(k, 2 * n)
    ok = np.isfinite(e)
    out = np.full_like(e, np.nan, dtype=float)
    for f in range(k):
        good = ok[f]
        if good.sum() < 4:
            continue
        coef, *_ = np.linalg.lstsq(q[good], e[f, good], rcond=None)
        out[f, good] = e[f, good] - q[good] @ coef
    return out.reshape(k, n, 2)
