"""The correlation centroider's pass (:mod:`..correlation`): the map at the 3 x 3 whole
lags around its peak (found from the CoG, then climbed), and the peak fit, instead of the
FFT map.
"""

from __future__ import annotations

import numpy as np

from . import _jit
from .blocks import quantize


def _lag_product_impl(xw, refw, p, m, tx, ty, k0, k1):
    # c(tx, ty) = sum_u x(u + t) ref(u). xw holds the block at rows p..2p-1, columns
    # m..m+p-1 of rows W = p + 2m wide, zero elsewhere (3p rows); refw the reference in the
    # same row layout (p rows), zero outside its entries k0..k1-1. For |tx| <= m one
    # contiguous dot over those entries (the zero columns absorb the shift: vectorised);
    # beyond, the overlap summed directly.
    w = p + 2 * m
    if -m <= tx <= m:
        base = (p + ty) * w + tx
        xs = xw[base + k0:base + k1]
        rs = refw[k0:k1]
        acc = np.float32(0.0)
        for k in range(k1 - k0):
            acc += xs[k] * np.float32(rs[k])
        return acc
    acc = np.float32(0.0)
    for i in range(max(0, -ty), min(p, p - ty)):
        for j in range(max(0, -tx), min(p, p - tx)):
            acc += xw[(p + i + ty) * w + m + j + tx] * np.float32(refw[i * w + m + j])
    return acc


def _lag_block9_impl(xw, refw, p, m, lx, ly, k0, k1, v):
    # the nine c(lx + dx, ly + dy), dx, dy in -1..1, into v (row-major: k = 3 (dy + 1) +
    # dx + 1), for |lx| < m: one pass over the reference's p W values, each read once for
    # nine products (nine dots of _lag_product read it nine times: the loads bound the pass).
    # Slices, not computed indices: numba's negative-index wrap would stop vectorisation.
    # Only the reference's entries k0..k1-1 (its first to last non-zero one) are swept
    w = p + 2 * m
    n = k1 - k0
    b0 = (p + ly - 1) * w + lx - 1 + k0
    rs = refw[k0:k1]
    x0 = xw[b0:b0 + n]
    x1 = xw[b0 + 1:b0 + 1 + n]
    x2 = xw[b0 + 2:b0 + 2 + n]
    x3 = xw[b0 + w:b0 + w + n]
    x4 = xw[b0 + w + 1:b0 + w + 1 + n]
    x5 = xw[b0 + w + 2:b0 + w + 2 + n]
    x6 = xw[b0 + 2 * w:b0 + 2 * w + n]
    x7 = xw[b0 + 2 * w + 1:b0 + 2 * w + 1 + n]
    x8 = xw[b0 + 2 * w + 2:b0 + 2 * w + 2 + n]
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = np.float32(0.0)
    for k in range(n):
        r = np.float32(rs[k])
        a0 += r * x0[k]
        a1 += r * x1[k]
        a2 += r * x2[k]
        a3 += r * x3[k]
        a4 += r * x4[k]
        a5 += r * x5[k]
        a6 += r * x6[k]
        a7 += r * x7[k]
        a8 += r * x8[k]
    v[0] = a0
    v[1] = a1
    v[2] = a2
    v[3] = a3
    v[4] = a4
    v[5] = a5
    v[6] = a6
    v[7] = a7
    v[8] = a8


def _start_lag_impl(px, py, q):
    # the corner of the unit cell holding the predicted lag (px, py) nearest to it in the
    # metric q = (a, b, c), a dx^2 + b dx dy + c dy^2: the whole lag whose map value the
    # reference's own correlation, shifted there, makes the largest (on a ridge along a
    # pixel diagonal that is often not the nearest whole lag, which made 29 % of the
    # cartesian blocks climb a step)
    if q[1] == 0.0:                 # axes of the metric along the pixels': the nearest lag
        return int(np.floor(px + 0.5)), int(np.floor(py + 0.5))
    fx = np.floor(px)
    fy = np.floor(py)
    best = np.inf
    lx = ly = 0
    for ky in range(2):
        for kx in range(2):
            ux = fx + kx - px
            uy = fy + ky - py
            d = q[0] * ux * ux + q[1] * ux * uy + q[2] * uy * uy
            if d < best:
                best = d
                lx = int(fx) + kx
                ly = int(fy) + ky
    return lx, ly


#: zero columns each side of a block in :func:`corr_peak`'s buffers: lags within +-3 px
#: across the columns are one contiguous dot product each
CORR_PAD = 3


def _corr_lags_impl(frame, origins, p, refw, spans, metric, m, ref_cog, background, log,
                    climbs, v, lag, lr):
    # per block: the block less the background into the padded buffer, its CoG; the whole
    # lag nearest to CoG - the reference's CoG in the metric of the reference's own
    # correlation (_start_lag, start_metric: the plain nearest where the field cuts the
    # reference; 808 -> 127 climbs a cartesian frame, 0.05-0.07 ms, 2026-11-29);
    # the 3 x 3 correlation values around it,
    # moved to their maximum until it is the centre (at most ``climbs`` moves, each keeping
    # the values the new 3 x 3 shares with the old: the same numbers, 12-19 % faster a full
    # frame than computing all nine again; one sweep for a climb's new row or column
    # instead of three dots measured no faster, 2026-11-29). Into v[b] (the nine values,
    # row-major, NaN for a block without light), lag[b] (their centre) and, with ``log``,
    # lr[b] the five ratios whose logs the quadratic of the log takes (_corr_vertex; 1 where
    # a value is not positive). Measured on the benchmark's cartesian frame (2026-11-27):
    # the nine values in one sweep (_lag_block9) 1.41 -> 1.00 ms, integer block sums, int16
    # references and five logs of ratios instead of nine logs -> 0.88 ms; reading the
    # blocks alone costs 0.22 ms, the sweep 0.28 ms
    n = origins.shape[0]
    c = (p - 1) / 2.0
    w = p + 2 * m
    xw = np.zeros(3 * p * w, dtype=np.float32)
    w9 = np.empty(9)
    bg = np.float32(background)
    for b in range(n):
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        # integer sums (exact, vectorised); the background's share taken out after
        ts = 0
        tx = 0
        ty = 0
        for i in range(p):
            row = frame[r0 + i, c0:c0 + p]
            dst = xw[(p + i) * w + m:(p + i) * w + m + p]
            rs = np.int32(0)
            rx = np.int32(0)
            for j in range(p):
                q = np.int32(row[j])
                dst[j] = np.float32(q) - bg
                rs += q
                rx += q * j
            ts += rs
            tx += rx
            ty += i * rs
        s = ts - background * p * p
        sx = tx - c * ts                                 # sum of (j - c)(q - background)
        sy = ty - c * ts
        ref = refw[b]
        k0 = spans[b, 0]
        k1 = spans[b, 1]
        vb = v[b]
        if not s > 0 or k1 <= k0:
            vb[:] = np.nan
            lag[b, 0] = lag[b, 1] = 0
            if log:
                lr[b, :] = 1.0
            continue
        lim = p - 2
        lx, ly = _start_lag(sx / s - ref_cog[b, 0], sy / s - ref_cog[b, 1], metric[b])
        lx = min(max(lx, -lim), lim)
        ly = min(max(ly, -lim), lim)
        if -m < lx < m:
            _lag_block9(xw, ref, p, m, lx, ly, k0, k1, vb)
        else:
            for k in range(9):
                vb[k] = _lag_product(xw, ref, p, m, lx + k % 3 - 1, ly + k // 3 - 1, k0, k1)
        for step in range(climbs + 1):
            best = 0
            for k in range(1, 9):
                if vb[k] > vb[best]:
                    best = k
            if best == 4 or step == climbs:
                break
            nx = min(max(lx + best % 3 - 1, -lim), lim)
            ny = min(max(ly + best // 3 - 1, -lim), lim)
            if nx == lx and ny == ly:
                break
            # the 3 x 3 values around the new lag: those the old ones cover are kept
            # (4 or 6 of 9), the rest computed
            mx = nx - lx
            my = ny - ly
            for k in range(9):
                ox = k % 3 - 1 + mx
                oy = k // 3 - 1 + my
                if -1 <= ox <= 1 and -1 <= oy <= 1:
                    w9[k] = vb[(oy + 1) * 3 + ox + 1]
                else:
                    w9[k] = _lag_product(xw, ref, p, m, nx + k % 3 - 1, ny + k // 3 - 1, k0, k1)
            for k in range(9):
                vb[k] = w9[k]
            lx = nx
            ly = ny
        lag[b, 0] = lx
        lag[b, 1] = ly
        if log:
            positive = True
            for k in range(9):
                if not vb[k] > 0:
                    positive = False
            if positive:
                lr[b, 0] = vb[5] / vb[3]
                lr[b, 1] = vb[5] * vb[3] / (vb[4] * vb[4])
                lr[b, 2] = vb[7] / vb[1]
                lr[b, 3] = vb[7] * vb[1] / (vb[4] * vb[4])
                lr[b, 4] = vb[8] * vb[0] / (vb[6] * vb[2])
            else:
                lr[b, :] = 1.0


def _corr_vertex_impl(v, lag, lr, log, out):
    # per block: the lag plus the vertex of the quadratic through the nine values v[b]
    # around it (with ``log``, of their log, from lr[b] the logs of _corr_lags's five
    # ratios: taken by numpy's vectorised log between the passes, 0.01 ms a full frame
    # against 0.09 for five calls a block, 2026-11-29), as correlation._parabola_peak; NaN
    # for a block without light
    for b in range(v.shape[0]):
        vb = v[b]
        if not vb[4] == vb[4]:
            out[b, 0] = np.nan
            out[b, 1] = np.nan
            continue
        positive = log
        if log:
            for k in range(9):
                if not vb[k] > 0:
                    positive = False
        if positive:            # the quadratic of the log: five logs of ratios, not nine
            bb = 0.5 * lr[b, 0]
            d = 0.5 * lr[b, 1]
            cc = 0.5 * lr[b, 2]
            f = 0.5 * lr[b, 3]
            e = 0.25 * lr[b, 4]
        else:
            bb = (vb[5] - vb[3]) / 2
            d = (vb[5] + vb[3]) / 2 - vb[4]
            cc = (vb[7] - vb[1]) / 2
            f = (vb[7] + vb[1]) / 2 - vb[4]
            e = (vb[8] - vb[6] - vb[2] + vb[0]) / 4
        det = 4 * d * f - e * e
        if d < 0 and det > 0:
            ox = (e * cc - 2 * f * bb) / det
            oy = (e * bb - 2 * d * cc) / det
        else:
            ox = -bb / (2 * d) if d < 0 else 0.0
            oy = -cc / (2 * f) if f < 0 else 0.0
        out[b, 0] = lag[b, 0] + min(max(ox, -1.0), 1.0)
        out[b, 1] = lag[b, 1] + min(max(oy, -1.0), 1.0)


if _jit.COMPILED:
    from .blocks import FRAME_AHEAD, _prefetch_block
    _lag_product = _jit.numba.njit(cache=True, nogil=True, fastmath=True, inline="always")(
        _lag_product_impl)
    _lag_block9 = _jit.numba.njit(cache=True, nogil=True, fastmath=True, inline="always")(
        _lag_block9_impl)
    _start_lag = _jit.numba.njit(cache=True, nogil=True, inline="always")(_start_lag_impl)
    _corr_lags = _jit.numba.njit(cache=True, nogil=True, error_model="numpy",
                                 fastmath={"contract", "reassoc", "nsz", "arcp"})(_corr_lags_impl)
    _corr_vertex = _jit.numba.njit(cache=True, nogil=True, error_model="numpy")(
        _corr_vertex_impl)


def corr_rows(refs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, spans, metric)``: references ``(n, p, p)`` laid out for :func:`corr_peak`:
    ``rows (n, p * (p + 2 CORR_PAD))`` int16, each row between ``CORR_PAD`` zeros each side,
    each reference scaled to its largest magnitude at 32767 (:func:`quantize`; the peak fit
    does not see a reference's scale; half the bytes of float32: the pass reads every
    reference each frame), ``spans (n, 2)`` int64, the first and one past the last non-zero
    entry of each row (the pass sweeps only those: on polar pixels the rows across e beyond
    the spot's core are zero at this precision), and ``metric (n, 3)`` (:func:`start_metric`,
    where the pass starts)."""
    n, p, _ = refs.shape
    out = np.zeros((n, p, p + 2 * CORR_PAD))
    out[:, :, CORR_PAD:CORR_PAD + p] = refs
    rows = quantize(out.reshape(n, -1))[0]
    nz = rows != 0
    first = nz.argmax(axis=1)
    last = rows.shape[1] - nz[:, ::-1].argmax(axis=1)
    lit = nz.any(axis=1)
    spans = np.stack([np.where(lit, first, 0), np.where(lit, last, 0)], axis=1).astype(np.int64)
    return rows, spans, start_metric(refs)


def lags_around_zero(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``(n, 9)``: the linear correlation ``sum_u x(u + t) ref(u)`` of ``x`` and ``ref``
    (``(n, p, p)`` each, zero outside the block) at the 3 x 3 whole lags ``t`` around zero,
    row-major (``t_y``, then ``t_x``, each -1, 0, 1), summed directly (numpy)."""
    p = ref.shape[-1]
    xp = np.pad(np.asarray(x, dtype=np.float64), ((0, 0), (1, 1), (1, 1)))
    return np.stack([np.einsum("nij,nij->n", xp[:, 1 + dy:1 + dy + p, 1 + dx:1 + dx + p], ref)
                     for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=1)


#: :func:`start_metric`: a reference with more of its light than this in its outer ring of
#: pixels starts at the nearest lag: the field cuts such a spot, and a shift moves the cut,
#: so the map of the shifted spot is not its reference's own correlation (started from the
#: metric on such blocks, `corr` was 2-3 % further from the bound with a side launch and on
#: broad profiles, cartesian, 2026-11-29; the centre launch's measured profiles keep 0.4 %
#: at most there)
START_EDGE_LIGHT = 0.005


def start_metric(refs: np.ndarray) -> np.ndarray:
    """``(n, 3)`` ``(a, b, c)``: less the quadratic ``a x^2 + b x y + c y^2`` of the log of
    each reference's own correlation through its 3 x 3 whole lags around zero (the fit
    :func:`corr_peak` makes): a spot like its reference at ``s`` px makes the map at a
    whole lag ``t`` largest where ``(t - s)`` is shortest in this metric; ``(1, 0, 1)``
    (the nearest lag) where it is not positive definite; ``b`` is 0 (the nearest lag, the
    pass's cheaper start) where it is below 1e-9 of ``a + c`` (a separable spot's, as on
    polar pixels) and where more than :data:`START_EDGE_LIGHT` of the reference's light is
    in its outer ring of pixels."""
    auto = lags_around_zero(refs, refs)                                    # (n, 9)
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.log(auto)
        q = np.stack([lg[:, 4] - (lg[:, 5] + lg[:, 3]) / 2,
                      (lg[:, 6] + lg[:, 2] - lg[:, 8] - lg[:, 0]) / 4,
                      lg[:, 4] - (lg[:, 7] + lg[:, 1]) / 2], axis=1)
    ok = (np.isfinite(q).all(axis=1) & (q[:, 0] > 0) & (q[:, 2] > 0)
          & (4 * q[:, 0] * q[:, 2] > q[:, 1] ** 2))
    q = np.where(ok[:, None], q, [1.0, 0.0, 1.0])
    q[np.abs(q[:, 1]) <= 1e-9 * (q[:, 0] + q[:, 2]), 1] = 0.0     # separable (polar) spots
    with np.errstate(divide="ignore", invalid="ignore"):
        edge = 1.0 - refs[:, 1:-1, 1:-1].sum(axis=(1, 2)) / refs.sum(axis=(1, 2))
    q[~(edge <= START_EDGE_LIGHT), 1] = 0.0                        # the field cuts the spot
    return q


def corr_peak(frame: np.ndarray, origins: np.ndarray, p: int, refw: tuple,
              ref_cog: np.ndarray, background: float = 0.0, log: bool = True,
              climbs: int = 4) -> np.ndarray:
    """Correlation centroids (:class:`.correlation.Correlation`, linear correlation, peak
    ``gauss`` or ``parabola``), one compiled pass per valid block of an integer frame (see
    :func:`fits`): the correlation ``c(t) = sum_u x(u + t) ref(u)`` of the block less
    ``background`` with its reference (``refw``: :func:`corr_rows` of the references
    ``(n, p, p)``, background removed, any flux scale) is evaluated only on the 3 x 3 whole
    lags around a start, moved up to ``climbs`` times towards the largest value, then
    refined by the quadratic through those 9 values (of their log with ``log``). The start
    is the whole lag next to the block's CoG minus ``ref_cog (n, 2)`` (the references' CoGs,
    px from the block centre) where the reference's own correlation moved there would be
    largest (:func:`start_metric`). Returns ``(n, 2)`` px, block axes, NaN for a block
    without light. Where the map has one maximum this is the whole map's peak fit."""
    n = origins.shape[0]
    refw, spans, metric = refw
    if (refw.shape != (n, p * (p + 2 * CORR_PAD)) or refw.dtype != np.int16
            or spans.shape != (n, 2) or spans.dtype != np.int64 or metric.shape != (n, 3)):
        raise ValueError("corr_peak: refw must be corr_rows(references)")
    v = np.empty((n, 9))
    lag = np.empty((n, 2), dtype=np.int64)
    lr = np.empty((n, 5))
    _corr_lags(frame, origins, int(p), np.ascontiguousarray(refw), np.ascontiguousarray(spans),
               np.ascontiguousarray(metric, dtype=np.float64), CORR_PAD,
               np.ascontiguousarray(ref_cog, dtype=np.float64), float(background),
               bool(log), int(climbs), v, lag, lr)
    if log:
        np.log(lr, out=lr)
    out = np.empty((n, 2))
    _corr_vertex(v, lag, lr, bool(log), out)
    return out
