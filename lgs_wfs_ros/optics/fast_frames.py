"""Full-pupil frames at live rates: tabulated polar spots, fused render + noise (issue 18).

The same physics and the same node representation of the line as :class:`spots.SpotModel`
(it is built from one), evaluated differently:

* **Polar detector: a tabulated line.** In its local frame a polar spot is the outer
  product of the line profile along ``e`` and the pixel-integrated core across it. The
  line's cumulative light at a pixel edge, ``C(y) = sum_k w_k Phi((y - u_k) / sigma)``,
  depends on the frame only through ``y = edge - shift``: it is tabulated once per
  profile, with its derivative (the line density), every ``1/H`` px (``H = 16``), and read
  each frame at the ``p + 1`` edges by cubic Hermite interpolation (error < 1e-6 of the
  spot's light). The node positions are multiples of ``1/16`` px there, so the table is
  an exact sum of exact ``Phi`` samples. Across ``e`` the core's CDF is read the same way.
* **Fused kernel** (numba): per subaperture the two 1-D profiles, the truncation, the
  per-field photon scale, then per pixel the expected count into a batch of ~8192 pixels;
  each full batch gets its exact Poisson draws in one tight loop
  (:func:`detector._poisson_run`, the fast path's sampler) and is written into the frame
  (for example a transport's loaned buffer); the blocks outside the pupil are zeroed.
* **Cartesian detector** (not separable on axis-aligned pixels): the same nodes summed by a
  compiled banded loop, each node's pixel-integrated core over the ~8 x 8 pixels within
  6.5 sigma + 1/2 px (the exact path's core table); then the noise and the write are fused.

Used by ``Simulator(..., fast=True)`` when the sensor has no read noise and no background
(the integer-count path); docs/simulator.md has the accuracy and the speed.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np
from scipy.special import ndtr

from . import detector
from .detector import POISSON_FLOOR, UINT16_MAX
from .geometry import detector_to_local
from .spots import CORE_SIGMAS, SpotModel, _pixel_core_table

H = 16                    # table samples per pixel (a multiple of every nodes-per-px m)
AVAILABLE = detector.FAST_AVAILABLE


@lru_cache(maxsize=8)
def core_kernels(sigma_px: float):
    """``Phi(q / (H sigma))`` and its derivative per px for ``q = -Q..Q`` (exact, ndtr).

    Returns ``(KP (2Q+1,), KD (2Q+1,), Q)``; beyond ``+-Q`` the CDF is 0 / 1 within 1e-10.
    """
    q_max = int(math.ceil(CORE_SIGMAS * sigma_px * H)) + 1
    z = np.arange(-q_max, q_max + 1) / (H * sigma_px)
    kp = ndtr(z)
    kd = np.exp(-0.5 * z * z) / (sigma_px * math.sqrt(2.0 * math.pi))
    for a in (kp, kd):
        a.setflags(write=False)
    return kp, kd, q_max


def _line_tables(w, k0, r, d0, kp, kd, q, tab, der):
    """Compiled: ``tab[i, g] = sum_k w[i, k] Phi((g + d0 - (k0_i + k) r_i) / (H sigma))``
    and ``der`` its derivative per px. ``d0 = H y_lo``: grid point ``g`` is at
    ``y = y_lo + g / H``; node ``k`` at ``(k0_i + k) / m_i`` px, ``r_i = H / m_i``."""
    n, nk = w.shape
    ng = tab.shape[1]
    pre = np.empty(nk + 1)
    for i in range(n):
        pre[0] = 0.0
        for k in range(nk):
            pre[k + 1] = pre[k] + w[i, k]
        ri = r[i]
        for g in range(ng):
            base = g + d0 - k0[i] * ri                  # argument of node k: base - k r
            kfull = -((q - base) // ri)                 # nodes k < kfull are past +Q: Phi = 1
            kfull = min(max(kfull, 0), nk)
            khi = min((base + q) // ri, nk - 1)         # nodes k > khi are before -Q: Phi = 0
            c = pre[kfull]
            d = 0.0
            for k in range(kfull, khi + 1):
                j = base - k * ri + q
                c += w[i, k] * kp[j]
                d += w[i, k] * kd[j]
            tab[i, g] = c
            der[i, g] = d


def _hermite_weights(t0):
    """``(g, h00, h10, h01, h11)``: the sample below ``t0`` and the cubic Hermite weights
    of the values at ``g``, ``g + 1`` and their derivatives per px (samples ``1/H`` px apart)."""
    g = math.floor(t0)
    f = t0 - g
    f2 = f * f
    f3 = f2 * f
    return g, 2 * f3 - 3 * f2 + 1, (f3 - 2 * f2 + f) / H, -2 * f3 + 3 * f2, (f3 - f2) / H


def _hermite_edges(tab, der, t0, n_edges, step, out):
    """Cubic Hermite reads of ``tab`` (with ``der`` per px) at indices ``t0 + j step``."""
    g, h00, h10, h01, h11 = _hermite_weights(t0)
    last = tab.size - 2
    for j in range(n_edges):
        i = g + j * step
        if i < 0:
            out[j] = tab[0]
        elif i > last:
            out[j] = tab[last + 1]
        else:
            out[j] = h00 * tab[i] + h10 * der[i] + h01 * tab[i + 1] + h11 * der[i + 1]


def _hermite_lines(lines, t0, n_edges, out):
    """Cubic Hermite reads at flat indices ``t0 + j H`` of one subaperture's phase-major
    line table ``lines (H, M, 2)``: flat index ``g = k H + phase`` at ``lines[phase, k]``
    = (cumulative light, its derivative per px). The ``n_edges`` reads of a block share
    their phase, so they walk two contiguous runs (value and derivative side by side)
    instead of ``2 n_edges`` cache lines of a flat table."""
    g, h00, h10, h01, h11 = _hermite_weights(t0)
    m = lines.shape[1]
    last = H * m - 2
    for j in range(n_edges):
        i = g + j * H
        if i < 0:
            out[j] = lines[0, 0, 0]
        elif i > last:
            out[j] = lines[H - 1, m - 1, 0]
        else:
            p0 = i % H
            k0 = i // H
            p1 = p0 + 1
            k1 = k0
            if p1 == H:
                p1 = 0
                k1 = k0 + 1
            out[j] = (h00 * lines[p0, k0, 0] + h10 * lines[p0, k0, 1]
                      + h01 * lines[p1, k1, 0] + h11 * lines[p1, k1, 1])


def _write_pixel(lam, integer, frame, row, col):
    """Expected count ``lam`` (no noise) written to ``frame[row, col]``, rounded for a
    uint16 frame; returns 1 if clipped at 65535."""
    if integer:
        v = np.int64(np.rint(lam))
        if v > UINT16_MAX:
            frame[row, col] = UINT16_MAX
            return 1
        frame[row, col] = v
    else:
        frame[row, col] = lam
    return 0


DRAW_BATCH = 8192         # pixels whose draws are batched (64 kB of expected counts)


def _batch_buffers(p):
    """Expected counts, draws and the frame row / column of each ``p``-pixel row."""
    n = max(DRAW_BATCH // p, p) * p
    return (np.empty(n), np.empty(n, dtype=np.int64), np.empty(n // p, dtype=np.int64),
            np.empty(n // p, dtype=np.int64))


def _draw_batch(lam, cnt, rpos, cpos, nl, p, integer, frame, x, d):
    """Compiled: Poisson draws of the ``nl`` batched block rows ``lam`` written into
    ``frame[rpos[j], cpos[j]:cpos[j] + p]`` (clipped at 65535 for a uint16 frame); returns
    ``(state, process distance, clipped)``. The draws run in one tight loop over the batch
    (:func:`detector._poisson_run`) rather than inside the rendering loop, where they
    measured ~1 ms a full frame slower (the cause was not isolated)."""
    x, d = detector._poisson_run(lam, nl * p, POISSON_FLOOR, x, d, cnt)
    sat = 0
    for j in range(nl):
        row, c0 = rpos[j], cpos[j]
        for c in range(p):
            v = cnt[j * p + c]
            if integer and v > UINT16_MAX:
                v = UINT16_MAX
                sat += 1
            frame[row, c0 + c] = v
    return x, d, sat


def _zero_blocks(frame, rows, cols, p):
    for b in range(rows.size):
        c0 = cols[b] * p
        for a in range(p):
            frame[rows[b] * p + a, c0:c0 + p] = 0


def _queue_row(lam, rpos, cpos, nl, p, row, col, scale, values):
    """Queues one block row's expected counts ``scale * values (p,)``, at frame pixel
    ``(row, col..col+p)``, for the batch draw; returns the batch's row count."""
    rpos[nl] = row
    cpos[nl] = col
    for c in range(p):
        lam[nl * p + c] = scale * values[c]
    return nl + 1


def _draw_if_full(lam, cnt, rpos, cpos, nl, p, integer, frame, x, d, last):
    """Draws the batch when it could not take another block's rows, or after the last
    block: ``(x, d, rows left in the batch, saturated)``."""
    if (nl + p) * p > lam.size or last:
        x, d, s = _draw_batch(lam, cnt, rpos, cpos, nl, p, integer, frame, x, d)
        return x, d, 0, s
    return x, d, nl, 0


def _render_polar(lines, lines2, wb, d0, s_maj, s_min, kp, kd, q, p, rows, cols, b0, b1,
                  photons, per_field, noise, integer, seed, frame, trunc):
    """Compiled: the valid blocks ``b0 <= i < b1`` of ``frame`` (rows local y, columns
    local x) from the line tables (``(1 - wb) lines + wb lines2``: two profiles' unit-light
    lines blended) and the core, Poisson-drawn from ``seed``'s stream (or expected counts if
    not ``noise``). Returns saturated pixels. Disjoint block ranges may run in parallel."""
    x = detector._seed_state(seed)
    cum = np.empty(p + 1)
    cum2 = np.empty(p + 1)
    emin = np.empty(p + 1)
    line = np.empty(p)
    gmin = np.empty(p)
    lam, cnt, rpos, cpos = _batch_buffers(p)
    nl = 0
    d = -1.0                                    # the small-mean process: not started
    sat = 0
    half = p / 2.0
    for i in range(b0, b1):
        _hermite_lines(lines[i], -H * half - d0 - H * s_maj[i], p + 1, cum)
        if wb > 0.0:
            _hermite_lines(lines2[i], -H * half - d0 - H * s_maj[i], p + 1, cum2)
            for j in range(p + 1):
                cum[j] += wb * (cum2[j] - cum[j])
        _hermite_edges(kp, kd, q - H * half - H * s_min[i], p + 1, H, emin)
        sl = 0.0
        sm = 0.0
        for j in range(p):
            line[j] = max(cum[j + 1] - cum[j], 0.0)
            gmin[j] = max(emin[j + 1] - emin[j], 0.0)
            sl += line[j]
            sm += gmin[j]
        total = sl * sm
        trunc[i] = min(max(1.0 - total, 0.0), 1.0)
        scale = photons
        if per_field:
            scale = photons / total if total > 0 else 0.0
        r0, c0 = rows[i] * p, cols[i] * p
        lmax = 0.0
        for c in range(p):
            lmax = max(lmax, line[c])
        if noise:                               # lit rows' expected counts into the batch
            for a in range(p):
                ga = scale * gmin[a]
                if ga * lmax <= POISSON_FLOOR:  # a dark row is all 0: no draws
                    frame[r0 + a, c0:c0 + p] = 0
                    continue
                nl = _queue_row(lam, rpos, cpos, nl, p, r0 + a, c0, ga, line)
            x, d, nl, s = _draw_if_full(lam, cnt, rpos, cpos, nl, p, integer, frame, x, d,
                                        i == b1 - 1)
            sat += s
            continue
        for a in range(p):
            ga = scale * gmin[a]
            top = ga * lmax                     # a dark row is all 0: no rounding
            if top == 0.0 or (integer and top < 0.5):
                frame[r0 + a, c0:c0 + p] = 0
                continue
            for c in range(p):
                sat += _write_pixel(ga * line[c], integer, frame, r0 + a, c0 + c)
    return sat


def _polar_lines(lines, d0, s_maj, s_min, kp, kd, q, p, line, core):
    """Compiled: each valid block's line along local x (``line (n, p)``) and core along
    local y (``core (n, p)``) from the line tables, as :func:`_render_polar` forms them: a
    noise-free polar block at unit light is ``float32(core[a] * line[c])``."""
    cum = np.empty(p + 1)
    emin = np.empty(p + 1)
    half = p / 2.0
    for i in range(line.shape[0]):
        _hermite_lines(lines[i], -H * half - d0 - H * s_maj[i], p + 1, cum)
        _hermite_edges(kp, kd, q - H * half - H * s_min[i], p + 1, H, emin)
        for j in range(p):
            line[i, j] = max(cum[j + 1] - cum[j], 0.0)
            core[i, j] = max(emin[j + 1] - emin[j], 0.0)


def _expose_blocks(images, p, rows, cols, b0, b1, photons, per_field, noise, integer,
                   seed, frame):
    """Compiled: ``images[b0:b1] (n, p, p)`` -> counts written into their blocks of
    ``frame`` (``seed``'s stream)."""
    x = detector._seed_state(seed)
    lam, cnt, rpos, cpos = _batch_buffers(p)
    nl = 0
    d = -1.0                                    # the small-mean process: not started
    sat = 0
    for i in range(b0, b1):
        scale = photons
        if per_field:
            total = 0.0
            for a in range(p):
                for c in range(p):
                    total += images[i, a, c]
            scale = photons / total if total > 0 else 0.0
        r0, c0 = rows[i] * p, cols[i] * p
        if noise:                               # expected counts into the batch
            for a in range(p):
                nl = _queue_row(lam, rpos, cpos, nl, p, r0 + a, c0, scale, images[i, a])
            x, d, nl, s = _draw_if_full(lam, cnt, rpos, cpos, nl, p, integer, frame, x, d,
                                        i == b1 - 1)
            sat += s
            continue
        for a in range(p):
            for c in range(p):
                sat += _write_pixel(scale * images[i, a, c], integer, frame, r0 + a, c0 + c)
    return sat


def _block_nodes(w, a0, b, inv_m, nk, tab, dtab, z0, inv_h, reach, s_maj, s_min, p, i,
                 pmaj, dmaj, acc, amaj, amin, deriv):
    """Block ``i``'s nodes into ``acc (p, p)`` (minor, major): each node's core,
    pixel-integrated along both detector axes (the fine table of
    :func:`spots._pixel_core_table`), added over the pixels within ``reach`` of it; with
    ``deriv`` also into ``amaj`` and ``amin`` their derivatives with respect to a shift along
    the major and the minor axis (one of the two table reads taken as its slope). ``pmaj``,
    ``dmaj`` ``(p,)`` scratch."""
    c = (p - 1) / 2.0
    last = tab.size - 2
    acc[:, :] = 0.0
    if deriv:
        amaj[:, :] = 0.0
        amin[:, :] = 0.0
    for k in range(nk[i]):
        wk = w[i, k]
        if wk == 0.0:
            continue
        xm = c + a0[i] + k * inv_m[i] + s_maj[i]
        ym = c + b[i, k] + s_min[i]
        j0 = max(0, math.ceil(xm - reach))
        j1 = min(p - 1, math.floor(xm + reach))
        i0 = max(0, math.ceil(ym - reach))
        i1 = min(p - 1, math.floor(ym + reach))
        if j0 > j1 or i0 > i1:
            continue
        for j in range(j0, j1 + 1):
            y = (j - xm - z0) * inv_h
            g = min(max(int(math.floor(y)), 0), last)
            pmaj[j] = tab[g] + (y - g) * dtab[g]
            if deriv:
                dmaj[j] = -inv_h * dtab[g]
        for a in range(i0, i1 + 1):
            y = (a - ym - z0) * inv_h
            g = min(max(int(math.floor(y)), 0), last)
            ga = wk * (tab[g] + (y - g) * dtab[g])
            if deriv:
                gd = wk * (-inv_h * dtab[g])
                for j in range(j0, j1 + 1):
                    acc[a, j] += ga * pmaj[j]
                    amaj[a, j] += ga * dmaj[j]
                    amin[a, j] += gd * pmaj[j]
            else:
                for j in range(j0, j1 + 1):
                    acc[a, j] += ga * pmaj[j]


def _render_cartesian(w, a0, b, inv_m, major_y, nk, tab, dtab, z0, inv_h, reach, s_maj,
                      s_min, p, b0, b1, images, trunc):
    """Compiled: for the subapertures ``b0 <= i < b1``, each node's core, pixel-integrated
    along both detector axes (:func:`_block_nodes`): ``images[i, minor, major]``
    (transposed when the major axis is y), and the truncation ``trunc[i] = 1 - sum``."""
    pmaj = np.empty(p)
    acc = np.empty((p, p))                                  # (minor, major)
    for i in range(b0, b1):
        img = images[i]
        _block_nodes(w, a0, b, inv_m, nk, tab, dtab, z0, inv_h, reach, s_maj, s_min, p, i,
                     pmaj, pmaj, acc, acc, acc, False)
        tot = 0.0
        for a in range(p):
            for j in range(p):
                v = max(acc[a, j], 0.0)
                tot += v
                if major_y[i]:
                    img[j, a] = v
                else:
                    img[a, j] = v
        trunc[i] = min(max(1.0 - tot, 0.0), 1.0)


def _render_cartesian_d(w, a0, b, inv_m, major_y, nk, tab, dtab, z0, inv_h, reach, s_maj,
                        s_min, p, images, dx, dy):
    """Compiled: :func:`_render_cartesian`'s noise-free ``images (n, q, q)`` of every
    subaperture and their derivatives with respect to a shift along detector x and y,
    ``dx``, ``dy`` (:func:`_block_nodes` with ``deriv``); zero where the image is clipped
    at zero."""
    pmaj = np.empty(p)
    dmaj = np.empty(p)
    acc = np.empty((p, p))                                  # (minor, major)
    amaj = np.empty((p, p))                                 # d/d(major shift)
    amin = np.empty((p, p))                                 # d/d(minor shift)
    for i in range(images.shape[0]):
        _block_nodes(w, a0, b, inv_m, nk, tab, dtab, z0, inv_h, reach, s_maj, s_min, p, i,
                     pmaj, dmaj, acc, amaj, amin, True)
        for a in range(p):
            for j in range(p):
                lit = acc[a, j] > 0.0
                v = acc[a, j] if lit else 0.0
                vmaj = amaj[a, j] if lit else 0.0
                vmin = amin[a, j] if lit else 0.0
                if major_y[i]:
                    images[i, j, a] = v
                    dy[i, j, a] = vmaj
                    dx[i, j, a] = vmin
                else:
                    images[i, a, j] = v
                    dx[i, a, j] = vmaj
                    dy[i, a, j] = vmin


if AVAILABLE:
    numba = detector.numba              # the optional import lives in detector
    _jit = numba.njit(cache=True, nogil=True)
    _line_tables = _jit(_line_tables)
    _hermite_weights = numba.njit(cache=True, nogil=True, inline="always")(_hermite_weights)
    _hermite_edges = _jit(_hermite_edges)
    _hermite_lines = _jit(_hermite_lines)
    _write_pixel = numba.njit(cache=True, nogil=True, inline="always")(_write_pixel)
    _batch_buffers = _jit(_batch_buffers)
    _draw_batch = _jit(_draw_batch)
    _draw_if_full = numba.njit(cache=True, nogil=True, inline="always")(_draw_if_full)
    _queue_row = numba.njit(cache=True, nogil=True, inline="always")(_queue_row)
    _zero_blocks = _jit(_zero_blocks)
    _render_polar = _jit(_render_polar)
    _polar_lines = _jit(_polar_lines)
    _expose_blocks = _jit(_expose_blocks)
    _block_nodes = numba.njit(cache=True, nogil=True, inline="always")(_block_nodes)
    _render_cartesian = _jit(_render_cartesian)
    _render_cartesian_d = _jit(_render_cartesian_d)


class PolarTable:
    """The line of every subaperture of a polar :class:`SpotModel`, tabulated for reads at
    any shift up to ``model.max_shift_px`` per detector axis (``sqrt 2`` times that in the
    local frame, plus one pixel).

    Attributes: ``lines (n, H, M, 2)``: the cumulative light and its derivative per px on
    ``y = y_lo + g / H`` at ``lines[i, g % H, g // H]`` (phase-major: a block's edges, one
    pixel apart, share a phase); ``d0 = H y_lo``.
    """

    def __init__(self, model: SpotModel):
        if not model.polar:
            raise ValueError("PolarTable needs a polar-detector SpotModel")
        p = model.sensor.pixels
        n = model.n
        nk = max(grp["w"].shape[1] for grp in model.groups)
        w = np.zeros((n, nk))
        k0 = np.zeros(n, dtype=np.int64)
        r = np.zeros(n, dtype=np.int64)
        for grp in model.groups:
            m = grp["m"]
            if H % m:
                raise ValueError(f"nodes per px {m} does not divide H={H}")
            idx = grp["idx"]
            w[idx, :grp["w"].shape[1]] = grp["w"]
            k0[idx] = np.rint(grp["a0"] * m).astype(np.int64)    # polar: node 0 at k0 / m px
            r[idx] = H // m
        reach = math.ceil(p / 2 + math.sqrt(2.0) * model.max_shift_px + 1.0)
        self.d0 = -H * reach
        self.sigma_px = model.sigma_px
        kp, kd, q = core_kernels(self.sigma_px)
        size = 2 * H * reach + 1
        tab = np.empty((n, size))
        der = np.empty_like(tab)
        _line_tables(w, k0, r, self.d0, kp, kd, q, tab, der)
        # phase-major, value and derivative side by side: lines[i, g % H, g // H] (padded
        # past the end with the final light and a zero derivative)
        m = -(-size // H)
        flat = np.empty((n, m * H, 2))
        flat[:, :size, 0], flat[:, :size, 1] = tab, der
        flat[:, size:, 0], flat[:, size:, 1] = tab[:, -1:], 0.0
        self.lines = np.ascontiguousarray(flat.reshape(n, m, H, 2).transpose(0, 2, 1, 3))


class CartesianNodes:
    """The nodes of a cartesian :class:`SpotModel` as padded per-subaperture arrays:
    weights ``w (n, K)``, major coordinate of node 0 ``a0``, minor coordinates ``b (n, K)``,
    node spacing ``inv_m`` (px), ``major_y``, node counts ``nk``."""

    def __init__(self, model: SpotModel):
        n = model.n
        kmax = max(grp["w"].shape[1] for grp in model.groups)
        self.w = np.zeros((n, kmax))
        self.b = np.zeros((n, kmax))
        self.a0 = np.zeros(n)
        self.inv_m = np.zeros(n)
        self.major_y = np.zeros(n, dtype=np.bool_)
        self.nk = np.zeros(n, dtype=np.int64)
        for grp in model.groups:
            idx, kk = grp["idx"], grp["w"].shape[1]
            self.w[idx, :kk] = grp["w"]
            self.b[idx, :kk] = grp["b"]
            self.a0[idx] = grp["a0"]
            self.inv_m[idx] = 1.0 / grp["m"]
            self.major_y[idx] = grp["major_y"]
            self.nk[idx] = kk


def chunk_seeds(seed: int, chunks: int) -> list[int]:
    """Independent 63-bit seeds of a frame's ``chunks`` draw streams (splitmix64 of
    ``seed`` and the chunk index): the frame is a function of ``seed`` alone, whatever the
    number of threads that render its chunks."""
    out = []
    mask = (1 << 64) - 1
    for c in range(chunks):
        z = (int(seed) * 0x9E3779B97F4A7C15 + (c + 1) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        out.append((z ^ (z >> 31)) >> 1)
    return out


class FastRenderer:
    """Frames of one layout written straight into a ``(G p, G p)`` buffer.

    Each spot model's table (:class:`PolarTable` or :class:`CartesianNodes`) is built on
    first use and kept for the last :attr:`KEEP` models, so a profile that changes every
    N frames, or blends between two knots, pays its table once.

    The valid blocks are drawn in :attr:`CHUNKS` contiguous chunks, each from its own
    stream (:func:`chunk_seeds`), so ``threads`` compiled calls (the kernels release the
    GIL) can render one frame together and the frame does not depend on ``threads``.

    Args:
        lay: the sensor layout (valid blocks and their rows/columns).
        threads: threads that render a frame (>= 1; 1 renders on the caller's thread).
    """

    KEEP = 4
    CHUNKS = 4

    def __init__(self, lay, threads: int = 1):
        if not (isinstance(threads, (int, np.integer)) and not isinstance(threads, bool)
                and threads >= 1):
            raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
        self.sensor = lay.sensor
        self.e = lay.e
        rows, cols = np.nonzero(lay.valid)              # row-major: the stack's order
        zr, zc = np.nonzero(~lay.valid)
        self.rows, self.cols = rows.astype(np.int64), cols.astype(np.int64)
        self.zrows, self.zcols = zr.astype(np.int64), zc.astype(np.int64)
        edges = np.linspace(0, rows.size, self.CHUNKS + 1).round().astype(int)
        self._ranges = list(zip(edges[:-1].tolist(), edges[1:].tolist()))
        self.threads = int(min(threads, self.CHUNKS))
        self._pool = None                               # the helper threads, on first use
        self._tables = {}                               # id(model) -> (model, table)
        self._tables_lock = threading.Lock()
        self._images = None

    def close(self) -> None:
        """Stop the helper threads (rendering again restarts them)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _chunks(self, kernel, seed) -> int:
        """Runs ``kernel(b0, b1, seed_c) -> saturated`` on every chunk, the chunks split
        between the caller and ``threads - 1`` helpers; returns the summed saturation."""
        work = [(b0, b1, sd) for (b0, b1), sd in zip(self._ranges,
                                                     chunk_seeds(seed, self.CHUNKS))]
        if self.threads == 1:
            return sum(kernel(*w) for w in work)
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="render")
        groups = [work[t::self.threads] for t in range(self.threads)]
        futures = [self._pool.submit(lambda g=g: sum(kernel(*w) for w in g))
                   for g in groups[1:]]
        sat = sum(kernel(*w) for w in groups[0])
        return sat + sum(f.result() for f in futures)

    def _check(self, out):
        s = self.sensor
        if out.shape != s.frame_shape or out.dtype != np.dtype(s.dtype):
            raise ValueError(f"out must be {s.frame_shape} {s.dtype}, got {out.shape} {out.dtype}")

    def table(self, model: SpotModel):
        """The model's table, built on first use (safe to call from a prefetch thread)."""
        hit = self._tables.get(id(model))
        if hit is not None and hit[0] is model:
            return hit[1]
        table = PolarTable(model) if model.polar else CartesianNodes(model)
        with self._tables_lock:                  # a prefetch thread may insert at once
            self._tables[id(model)] = (model, table)
            while len(self._tables) > self.KEEP:
                self._tables.pop(next(iter(self._tables)))
        return table

    def render(self, model: SpotModel, truth, out, photons, seed, noise=True, per_field=True,
               blend=None):
        """Write one frame into ``out``; returns ``(truncated (n,), saturated)``.

        Args:
            model: the profile's spot model.
            truth: ``(n, 2)`` true displacements, px, detector axes (``|.| <=
                model.max_shift_px``).
            out: ``sensor.frame_shape`` array of the sensor's dtype.
            photons: expected photons per subaperture (in the field if ``per_field``).
            seed: int seed of this frame's draws.
            blend: optional ``(model_b, wb)``: the light is ``(1 - wb)`` of ``model``'s
                unit-light spots plus ``wb`` of ``model_b``'s (same ``max_shift_px``),
                ``0 <= wb <= 1``: a profile between two knots without a model of its own.
        """
        self._check(out)
        integer = out.dtype == np.uint16
        p = self.sensor.pixels
        model_b, wb = blend if blend is not None else (model, 0.0)
        if not 0.0 <= wb <= 1.0 or model_b.max_shift_px != model.max_shift_px \
                or model_b.polar != model.polar:
            raise ValueError("blend needs 0 <= wb <= 1 and a model_b of the same detector "
                             "and max_shift_px")
        t, t2 = self.table(model), self.table(model_b)
        if model.polar:
            loc = detector_to_local(np.asarray(truth, dtype=float), self.e)
            kp, kd, q = core_kernels(model.sigma_px)
            trunc = np.empty(self.rows.size)
            s_maj, s_min = np.ascontiguousarray(loc[:, 0]), np.ascontiguousarray(loc[:, 1])
            sat = self._chunks(lambda b0, b1, sd: _render_polar(
                t.lines, t2.lines, float(wb), t.d0, s_maj, s_min, kp, kd, q, p, self.rows,
                self.cols, b0, b1, float(photons), bool(per_field), bool(noise), bool(integer),
                sd, out, trunc), seed)
            _zero_blocks(out, self.zrows, self.zcols, p)
            return trunc, int(sat)
        if self._images is None:
            self._images = (np.empty((self.rows.size, p, p)), np.empty((self.rows.size, p, p)))
        images, images_b = self._images
        trunc, trunc_b = np.empty(self.rows.size), np.empty(self.rows.size)
        args = (float(photons), bool(per_field), bool(noise), bool(integer))

        def chunk(b0, b1, sd):
            self._cartesian(model, t, truth, images, trunc, b0, b1)
            if wb > 0.0:
                self._cartesian(model_b, t2, truth, images_b, trunc_b, b0, b1)
                images[b0:b1] += wb * (images_b[b0:b1] - images[b0:b1])
                trunc[b0:b1] += wb * (trunc_b[b0:b1] - trunc[b0:b1])
            return _expose_blocks(images, p, self.rows, self.cols, b0, b1, *args, sd, out)

        sat = self._chunks(chunk, seed)
        _zero_blocks(out, self.zrows, self.zcols, p)
        return trunc, int(sat)

    def polar_lines(self, model: SpotModel, truth) -> tuple[np.ndarray, np.ndarray]:
        """``(line (n, p), core (n, p))`` float64: each noise-free unit-light polar spot
        displaced by ``truth (n, 2)`` px (detector axes) as its line along local x and its
        core along local y; :meth:`render` (noise off, ``photons`` 1, not per field) writes
        ``float32(core[:, a] * line[:, c])`` at row ``a``, column ``c`` of each block, so
        the block's images at several shifts come from 1-D passes alone."""
        if not model.polar:
            raise ValueError("polar_lines: polar models only")
        t = self.table(model)
        loc = detector_to_local(np.asarray(truth, dtype=float), self.e)
        kp, kd, q = core_kernels(model.sigma_px)
        n, p = self.rows.size, self.sensor.pixels
        line, core = np.empty((n, p)), np.empty((n, p))
        _polar_lines(t.lines, t.d0, np.ascontiguousarray(loc[:, 0]),
                     np.ascontiguousarray(loc[:, 1]), kp, kd, q, p, line, core)
        return line, core

    def canvas(self, model: SpotModel, truth, margin: int) -> np.ndarray:
        """``(n, p + 2 margin, p + 2 margin)`` float64: the noise-free unit-light spots of a
        cartesian ``model`` displaced by ``truth (n, 2)`` px (detector axes), on a canvas
        ``margin`` px wider than the block on every side (block pixel ``(i, j)`` is canvas
        pixel ``(i + margin, j + margin)``). The renderer is the same at every pixel, so the
        block's image of a spot moved by whole pixels ``(dx, dy)`` (``|d| <= margin``) is the
        crop ``[margin - dy : margin - dy + p, margin - dx : margin - dx + p]``: a grid of
        positions 0.5 px apart needs 4 renders instead of one each."""
        n, q = self._canvas_side(model, margin, "canvas")
        images = np.empty((n, q, q))
        self._cartesian(model, self.table(model), truth, images, np.empty(n), 0, n)
        return images

    def canvas_derivatives(self, model: SpotModel, truth, margin: int
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(images, d/dx, d/dy)``, each ``(n, p + 2 margin, p + 2 margin)`` float64:
        :meth:`canvas`'s images (the same values) and their derivatives with respect to a
        shift along detector x and y, px^-1, in one pass (the derivative of the renderer's
        interpolated core, where central differences of two more renders each would
        approximate it: a grid of positions' filters from 4 renders instead of 20)."""
        n, q = self._canvas_side(model, margin, "canvas_derivatives")
        out = tuple(np.empty((n, q, q)) for _ in range(3))
        _render_cartesian_d(*self._cartesian_args(model, self.table(model), truth), q, *out)
        return out

    def _canvas_side(self, model: SpotModel, margin, what: str) -> tuple[int, int]:
        """``(n, q)``: the blocks and the side of a canvas ``margin`` px wider than the block
        on every side, once the model and the margin are checked."""
        if model.polar:
            raise ValueError(f"{what}: cartesian models only")
        if not (isinstance(margin, (int, np.integer)) and margin >= 0):
            raise ValueError(f"{what}: margin must be an integer >= 0, got {margin!r}")
        return self.rows.size, self.sensor.pixels + 2 * int(margin)

    @staticmethod
    def _cartesian_args(model, t, truth) -> tuple:
        """The compiled cartesian renderers' arguments before the image side: the table
        ``t``, the core table and its reach, and ``truth (n, 2)`` as major and minor shifts."""
        truth = np.asarray(truth, dtype=float)
        s_maj = np.where(t.major_y, truth[:, 1], truth[:, 0])
        s_min = np.where(t.major_y, truth[:, 0], truth[:, 1])
        tab, dtab, z0, inv_h = _pixel_core_table(model.sigma_px)
        return (t.w, t.a0, t.b, t.inv_m, t.major_y, t.nk, tab, dtab, float(z0), float(inv_h),
                0.5 + CORE_SIGMAS * model.sigma_px, s_maj, s_min)

    def _cartesian(self, model, t, truth, images, trunc, b0, b1):
        """Noise-free ``images[b0:b1] (q, q)`` and ``trunc[b0:b1]`` of a cartesian model, on
        images of any side ``q`` (the block's, or a :meth:`canvas`), centred alike."""
        _render_cartesian(*self._cartesian_args(model, t, truth), images.shape[-1], b0, b1,
                          images, trunc)


__all__ = ["FastRenderer", "PolarTable", "core_kernels", "H", "AVAILABLE"]
