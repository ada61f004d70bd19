"""Matched-filter passes (:mod:`..cmf`, :mod:`..gmf`): per-block weights times pixels, the
CMF's filter and flux in one read, and the grid of filters picked by each block's CoG; and,
at a refit, the grid's filters of one position built from its renders in one pass.
"""

from __future__ import annotations

import numpy as np

from . import _jit


def _block_contract_impl(frame, origins, p, weights, out):
    # float32 weights times exact pixel values, summed in float64: a float32 sum of 256
    # products of mixed sign loses ~1e-4 of the result to cancellation
    n = origins.shape[0]
    k = weights.shape[1]
    for b in range(n):
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        for q in range(k):
            w = weights[b, q]
            acc = 0.0
            for i in range(p):
                row = frame[r0 + i, c0:c0 + p]
                wi = w[i * p:(i + 1) * p]
                for j in range(p):
                    acc += np.float64(wi[j]) * np.float64(row[j])
            out[b, q] = acc


def _filter_flux_impl(frame, origins, p, weights, out):
    # the CMF's two filter rows and a plain pixel sum (the flux row of [R; 1] without reading
    # 4 bytes of ones per pixel), all in one pass over each block's pixels
    for b in range(origins.shape[0]):
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
        r0, c0 = origins[b, 0], origins[b, 1]
        w0, w1 = weights[b, 0], weights[b, 1]
        tot, a0, a1 = 0, 0.0, 0.0
        for i in range(p):
            row = frame[r0 + i, c0:c0 + p]
            o = i * p
            for j in range(p):
                v = row[j]
                tot += np.int64(v)
                x = np.float64(v)
                a0 += np.float64(w0[o + j]) * x
                a1 += np.float64(w1[o + j]) * x
        out[b, 0] = a0
        out[b, 1] = a1
        out[b, 2] = tot


def _filter_flux_q_impl(frame, origins, p, weights, scale, out):
    # _filter_flux_impl with int16 filter rows (one scale each): exact integer sums, half
    # the filter bytes read a frame (the filter, not the frame, is most of the CMF's traffic)
    for b in range(origins.shape[0]):
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
        tot, a0, a1 = _rows_int16(frame, origins[b, 0], origins[b, 1], p, weights[b, 0],
                                  weights[b, 1])
        out[b, 0] = a0 * scale[b, 0]
        out[b, 1] = a1 * scale[b, 1]
        out[b, 2] = tot


#: blocks ahead of the one being filtered whose moments are taken and whose first filter rows
#: are asked for (:func:`grid_filter`)
FILTER_AHEAD = 3


def _grid_nearest_impl(e, spacing, half, side):
    # index of the grid position nearest to e, clamped to the grid
    return min(max(int(np.floor(e / spacing + 0.5)) + half, 0), side - 1)


def _grid_filter_impl(frame, origins, p, bias, filters, scale, rsum, positions, background,
                      picks, out, index):
    # per block: the CoG moments (exact int32 row sums), the calibrated CoG (minus bias) as
    # the first estimate; then up to `picks` times: the grid position nearest to the
    # estimate, that position's two filter rows applied to the block (int16 rows, exact
    # integer sums, then their scales), out[b] = position + (R x - background R 1) / flux,
    # which is the next estimate (stop when the position does not change).
    # Software-pipelined: the filter rows a block picks sit anywhere in a 71 MB table, so
    # at step b block b + FILTER_AHEAD's moments are taken (its first estimate kept in out,
    # its total in `total`) and its first pick's rows asked for, and the pixels of the block
    # FRAME_AHEAD after that; then block b is filtered (1.0 against 1.7 ms a full frame,
    # frames in turn, 2026-11-28; the same numbers bit for bit)
    n = origins.shape[0]
    c = (p - 1) / 2.0
    side = positions.shape[0]
    half = (side - 1) // 2
    spacing = positions[1] - positions[0] if side > 1 else 1.0
    nb = filters.shape[1]
    rows = filters.reshape(filters.size)
    row_len = 2 * p * p
    total = np.empty(n, dtype=np.int64)
    for b in range(-FILTER_AHEAD, n):
        a = b + FILTER_AHEAD
        if a < n:
            _prefetch_block(frame, origins, a + FRAME_AHEAD, p)
            s, sx, sy = _block_moments(frame, origins[a, 0], origins[a, 1], p)
            total[a] = s
            flux = s - background * p * p
            if s > 0 and flux > 0:
                # moments about the centre do not see a uniform background; the flux does
                ex = (sx - c * s) / flux - bias[a, 0]
                ey = (sy - c * s) / flux - bias[a, 1]
                out[a, 0] = ex
                out[a, 1] = ey
                g = _grid_nearest(ey, spacing, half, side) * side \
                    + _grid_nearest(ex, spacing, half, side)
                start = (g * nb + a) * row_len
                for q in range(0, row_len, 32):          # 32 int16 = one 64-byte line
                    _jit.prefetch(rows, start + q)
        if b < 0:
            continue
        s = total[b]
        flux = s - background * p * p
        if s <= 0 or not flux > 0:
            out[b, 0] = np.nan
            out[b, 1] = np.nan
            index[b] = -1
            continue
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        ex = out[b, 0]
        ey = out[b, 1]
        g = -1
        for _ in range(picks):
            kx = _grid_nearest(ex, spacing, half, side)
            ky = _grid_nearest(ey, spacing, half, side)
            if ky * side + kx == g:
                break
            g = ky * side + kx
            if s <= 65535:
                a0, a1 = _rows_int16_narrow(frame, r0, c0, p, filters[g, b, 0], filters[g, b, 1])
            else:
                _, a0, a1 = _rows_int16(frame, r0, c0, p, filters[g, b, 0], filters[g, b, 1])
            ex = positions[kx] + (a0 * scale[g, b, 0] - background * rsum[g, b, 0]) / flux
            ey = positions[ky] + (a1 * scale[g, b, 1] - background * rsum[g, b, 1]) / flux
        index[b] = g
        out[b, 0] = ex
        out[b, 1] = ey


def _block_solve_impl(img, dx, dy, p, var_add, floor, a, w, r, filters, scale, rsum):
    # one block, from its render img and its derivatives dx, dy along x and y, each (p, p)
    # counts (a px for the derivatives): the design A = [dI/dx, dI/dy, I] / flux, the
    # weights W = 1 / max(max(I, 0) + var_add, floor), the minimum-variance
    # filter R = M (A^T W A)^-1 A^T W with M = [[1, 0, 0], [0, 1, 0]] (cmf.solve_filter,
    # the Gram matrix scaled to a unit diagonal before its inverse), then R as int16 rows
    # with one scale each (blocks.quantize) into filters (2, p*p), scale (2,), rsum (2,),
    # the rows' sums; a, w, r scratch (3, p*p), (p*p,), (2, p*p). Returns True where
    # R A = M to 1e-6; a block without light, or whose Gram matrix is singular, gets zero
    # rows and False
    pp = p * p
    flux = 0.0
    for i in range(p):
        for j in range(p):
            flux += img[i, j]
    unit = 1.0 / flux if flux > 0 else 0.0
    for i in range(p):
        for j in range(p):
            k = i * p + j
            v = img[i, j]
            a[0, k] = dx[i, j] * unit
            a[1, k] = dy[i, j] * unit
            a[2, k] = v * unit
            w[k] = 1.0 / max(max(v, 0.0) + var_add, floor)
    g00, g01, g02, g11, g12, g22 = _gram(a, w, pp)
    good = flux > 0 and g00 > 0 and g11 > 0 and g22 > 0
    d0 = d1 = det = c00 = c01 = c02 = c11 = c12 = 1.0
    if good:
        d0, d1, d2 = np.sqrt(g00), np.sqrt(g11), np.sqrt(g22)
        s01, s02, s12 = g01 / (d0 * d1), g02 / (d0 * d2), g12 / (d1 * d2)
        c00 = 1.0 - s12 * s12                           # cofactors of the unit-diagonal
        c01 = s02 * s12 - s01                           # matrix (symmetric)
        c02 = s01 * s12 - s02
        c11 = 1.0 - s02 * s02
        c12 = s01 * s02 - s12
        det = c00 + s01 * c01 + s02 * c02
        good = det > 1e-12 and det < np.inf
    if not good:
        for q in range(2):
            scale[q] = 1.0
            rsum[q] = 0.0
            for k in range(pp):
                filters[q, k] = 0
        return False
    d2 = np.sqrt(g22)
    # rows 0 and 1 of the inverse, unscaled
    i00, i01, i02 = c00 / det / (d0 * d0), c01 / det / (d0 * d1), c02 / det / (d0 * d2)
    i11, i12 = c11 / det / (d1 * d1), c12 / det / (d1 * d2)
    e00, e01, e02, e10, e11, e12, t0, t1 = _rows(a, w, pp, i00, i01, i02, i11, i12, r)
    resid = max(abs(e00 - 1.0), abs(e01), abs(e02), abs(e10), abs(e11 - 1.0), abs(e12))
    for q in range(2):
        top = t0 if q == 0 else t1
        sc = top / 32767.0 if top > 0 else 1.0
        scale[q] = sc
        rsum[q] = _quantize_row(r[q], pp, 1.0 / sc, filters[q]) * sc
    return resid <= 1e-6


# The sums over a block's pixels of _block_solve, on its contiguous scratch rows a (3, pp),
# w (pp,), r (2, pp), compiled with reassociation (vectorised): their order depends on pp
# alone, not on the strides of the renders _block_solve read a and w from, so crops of a
# canvas and whole renders still give the same filters bit for bit (0.186 -> 0.155 s CPU for
# the 25 positions of a cartesian full pupil)


def _gram_impl(a, w, pp):
    # the weighted Gram matrix A^T W A's six distinct entries
    g00 = g01 = g02 = g11 = g12 = g22 = 0.0
    for k in range(pp):
        u0 = a[0, k] * w[k]
        u1 = a[1, k] * w[k]
        g00 += u0 * a[0, k]
        g01 += u0 * a[1, k]
        g02 += u0 * a[2, k]
        g11 += u1 * a[1, k]
        g12 += u1 * a[2, k]
        g22 += a[2, k] * w[k] * a[2, k]
    return g00, g01, g02, g11, g12, g22


def _rows_impl(a, w, pp, i00, i01, i02, i11, i12, r):
    # the filter rows R = M G^-1 A^T W into r, R A's six entries, each row's largest |value|
    e00 = e01 = e02 = e10 = e11 = e12 = 0.0
    t0 = 0.0
    t1 = 0.0
    for k in range(pp):
        r0 = (i00 * a[0, k] + i01 * a[1, k] + i02 * a[2, k]) * w[k]
        r1 = (i01 * a[0, k] + i11 * a[1, k] + i12 * a[2, k]) * w[k]
        r[0, k] = r0
        r[1, k] = r1
        e00 += r0 * a[0, k]
        e01 += r0 * a[1, k]
        e02 += r0 * a[2, k]
        e10 += r1 * a[0, k]
        e11 += r1 * a[1, k]
        e12 += r1 * a[2, k]
        t0 = max(t0, abs(r0))
        t1 = max(t1, abs(r1))
    return e00, e01, e02, e10, e11, e12, t0, t1


def _quantize_row_impl(row, pp, inv, out):
    # out = rint(row * inv) as int16; returns the sum of the rounded values
    acc = 0.0
    for k in range(pp):
        v = np.rint(row[k] * inv)
        out[k] = np.int16(v)
        acc += v
    return acc


def _position_filters_impl(img, dx, dy, var_add, floor, filters, scale, rsum, ok):
    # every block through _block_solve, its render and derivatives read in place (n, p, p),
    # any strides (crops of a wider canvas)
    n, p = img.shape[0], img.shape[1]
    pp = p * p
    a = np.empty((3, pp))
    w = np.empty(pp)
    r = np.empty((2, pp))
    for b in range(n):
        ok[b] = _block_solve(img[b], dx[b], dy[b], p, var_add, floor, a, w, r,
                             filters[b], scale[b], rsum[b])


def _separable_filters_impl(lines, cores, counts, h, var_add, floor, filters, scale, rsum, ok):
    # every block through _block_solve, its five renders formed from separable spots: render
    # k's pixel (i, j) is float32(cores[k, b, i] lines[k, b, j]) times counts[b], as the
    # polar renderer writes a noise-free block (FastRenderer.polar_lines) and the frame path
    # scales it (renders in the order img, xm, xp, ym, yp); the derivatives are their
    # central differences as central_differences takes them
    n, p = lines.shape[1], lines.shape[2]
    pp = p * p
    half_step = 0.5 / h
    a = np.empty((3, pp))
    w = np.empty(pp)
    r = np.empty((2, pp))
    im = np.empty((5, p, p))
    d = np.empty((2, p, p))
    for b in range(n):
        c = counts[b]
        for k in range(5):
            for i in range(p):
                ck = cores[k, b, i]
                for j in range(p):
                    im[k, i, j] = np.float64(np.float32(ck * lines[k, b, j])) * c
        for i in range(p):
            for j in range(p):
                d[0, i, j] = (im[2, i, j] - im[1, i, j]) * half_step
                d[1, i, j] = (im[4, i, j] - im[3, i, j]) * half_step
        ok[b] = _block_solve(im[0], d[0], d[1], p, var_add, floor, a, w, r,
                             filters[b], scale[b], rsum[b])

if _jit.COMPILED:
    from .blocks import (FRAME_AHEAD, _block_moments, _prefetch_block, _rows_int16,
                         _rows_int16_narrow)
    _grid_nearest = _jit.numba.njit(cache=True, nogil=True, inline="always")(_grid_nearest_impl)
    _block_contract = _jit.numba.njit(cache=True, nogil=True, fastmath=True)(_block_contract_impl)
    _filter_flux = _jit.numba.njit(cache=True, nogil=True, fastmath=True)(_filter_flux_impl)
    _filter_flux_q = _jit.numba.njit(cache=True, nogil=True)(_filter_flux_q_impl)
    _grid_filter = _jit.numba.njit(cache=True, nogil=True, fastmath=True)(_grid_filter_impl)
    # no reassociation: the sums keep one order whatever the arrays' strides, so crops of a
    # canvas and whole renders of the same values give the same filters bit for bit
    _sums = dict(cache=True, nogil=True, error_model="numpy",
                 fastmath={"reassoc", "contract", "nsz"})
    _gram = _jit.numba.njit(**_sums)(_gram_impl)
    _rows = _jit.numba.njit(**_sums)(_rows_impl)
    _quantize_row = _jit.numba.njit(**_sums)(_quantize_row_impl)
    _block_solve = _jit.numba.njit(cache=True, nogil=True, error_model="numpy")(
        _block_solve_impl)
    _position_filters = _jit.numba.njit(cache=True, nogil=True, error_model="numpy")(
        _position_filters_impl)
    _separable_filters = _jit.numba.njit(cache=True, nogil=True, error_model="numpy")(
        _separable_filters_impl)


def block_contract(frame: np.ndarray, origins: np.ndarray, weights: np.ndarray,
                   out: np.ndarray | None = None) -> np.ndarray:
    """``(n, k)`` float64: ``weights[b] @ block_b.ravel()`` for each valid block ``b``;
    ``weights`` float32 ``(n, k, p*p)`` (C-contiguous)."""
    n, k, pp = weights.shape
    p = int(round(pp ** 0.5))
    if out is None:
        out = np.empty((n, k))
    _block_contract(frame, origins, p, np.ascontiguousarray(weights, dtype=np.float32), out)
    return out


def filter_flux(frame: np.ndarray, origins: np.ndarray, weights: np.ndarray,
                out: np.ndarray | None = None, scale: np.ndarray | None = None) -> np.ndarray:
    """``(n, 3)`` float64: :func:`block_contract` of the ``(n, 2, p*p)`` filter rows, then
    each block's plain pixel sum (what a row of ones gives, read for free).

    ``weights`` float32, or int16 with ``scale (n, 2)`` (row ``k`` of block ``b`` is
    ``scale[b, k] weights[b, k]``, e.g. from :func:`quantize`): then the sums are exact
    integers, scaled once."""
    n, k, pp = weights.shape
    if k != 2:
        raise ValueError(f"filter_flux takes 2 filter rows, got {k}")
    p = int(round(pp ** 0.5))
    if out is None:
        out = np.empty((n, k + 1))
    if weights.dtype == np.int16:
        if scale is None or np.shape(scale) != (n, k):
            raise ValueError(f"int16 filter rows need scale of shape {(n, k)}")
        _filter_flux_q(frame, origins, p, np.ascontiguousarray(weights),
                       np.ascontiguousarray(scale, dtype=np.float64), out)
        return out
    _filter_flux(frame, origins, p, np.ascontiguousarray(weights, dtype=np.float32), out)
    return out


def grid_filter(frame: np.ndarray, origins: np.ndarray, p: int, bias: np.ndarray,
                filters: np.ndarray, scale: np.ndarray, rsum: np.ndarray,
                positions: np.ndarray, background: float = 0.0,
                picks: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Slopes of the grid matched filter (:class:`.gmf.GMF`), one compiled pass per valid
    block of an integer frame (see :func:`fits`): the filter of the grid position nearest to
    the block's calibrated CoG (its CoG minus ``bias (n, 2)``, block axes) is applied to it;
    with ``picks`` 2 (3) the position nearest to that estimate is chosen again and, where it
    differs, its filter applied instead (once more).
    ``filters (G*G, n, 2, p*p)`` int16 C-contiguous, the rows ``scale (G*G, n, 2)`` times
    them (position ``ky G + kx`` at ``(positions[kx], positions[ky])``, ``positions (G,)``
    px evenly spaced), ``rsum (G*G, n, 2)`` the rows' sums, ``background`` counts per pixel.
    Returns ``(slopes (n, 2)`` px, block axes, NaN for a block without light, ``index
    (n,)``: the position last used, -1 for none)."""
    n = origins.shape[0]
    if filters.dtype != np.int16 or not filters.flags.c_contiguous:
        raise ValueError("grid_filter: filters must be C-contiguous int16")
    out = np.empty((n, 2))
    index = np.empty(n, dtype=np.int64)
    _grid_filter(frame, origins, int(p), np.ascontiguousarray(bias, dtype=np.float64), filters,
                 np.ascontiguousarray(scale, dtype=np.float64),
                 np.ascontiguousarray(rsum, dtype=np.float64),
                 np.ascontiguousarray(positions, dtype=np.float64), float(background),
                 int(picks), out, index)
    return out, index


def central_differences(minus: np.ndarray, plus: np.ndarray, h: float) -> np.ndarray:
    """``(plus - minus) / 2h``, as ``(plus - minus) * (0.5 / h)``: the derivative of renders
    ``h`` px either side of a position, the same values :func:`separable_filters` takes
    from its lines (so both builds give the same filters bit for bit)."""
    return (plus - minus) * (0.5 / h)


def position_filters(img: np.ndarray, dx: np.ndarray, dy: np.ndarray, var_add: float,
                     floor: float, out: tuple = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The grid's filters of one reference position (:class:`.gmf.GMF`), one compiled pass
    over the blocks (a refit's filters without numpy's ``(n, p*p, 3)`` temporaries).

    ``img (n, p, p)`` counts of each block's reference at the position, ``dx, dy`` its
    derivatives along block x and y, counts a px (a renderer's own, or
    :func:`central_differences` of renders either side), all float64, any strides (crops
    of a wider canvas are read in place). Per block: the CMF of :func:`..cmf.solve_filter`
    with the design ``[dx, dy, img] / sum(img)``, constraint
    ``[[1, 0, 0], [0, 1, 0]]`` and pixel variances ``max(max(img, 0) + var_add, floor)``,
    quantized as :func:`.blocks.quantize` does. Returns ``(filters (n, 2, p*p)`` int16,
    ``scale (n, 2)``, ``rsum (n, 2)`` the sums of ``scale * filters``, ``ok (n,)``: True
    where ``R A = M`` holds to 1e-6; a block without light or with a singular system gets
    zero rows and False). ``out``, if given, is that tuple of arrays (C-contiguous; e.g.
    one position's slices of a refit's table), filled and returned."""
    n, p = img.shape[0], img.shape[1]
    filters, scale, rsum, ok = _outputs(n, p, out)
    _position_filters(img, dx, dy, float(var_add), float(floor), filters, scale, rsum, ok)
    return filters, scale, rsum, ok


def separable_filters(lines: np.ndarray, cores: np.ndarray, counts: np.ndarray, h: float,
                      var_add: float, floor: float, out: tuple = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`position_filters` for separable spots (a polar detector), without the images:
    ``lines, cores (5, n, p)`` the renders' lines along block x and cores along block y
    (:meth:`..optics.fast_frames.FastRenderer.polar_lines`) in the order image, ``-h`` and
    ``+h`` along x, ``-h`` and ``+h`` along y; render ``k``'s pixel ``(i, j)`` is
    ``float32(cores[k, :, i] lines[k, :, j]) counts`` (``counts (n,)``: unit light to
    counts), the values the frame path's renders give. Returns what
    :func:`position_filters` returns for those renders, bit for bit (into ``out`` as there)."""
    k, n, p = lines.shape
    if k != 5 or cores.shape != lines.shape or np.shape(counts) != (n,):
        raise ValueError("separable_filters: lines and cores (5, n, p), counts (n,)")
    filters, scale, rsum, ok = _outputs(n, p, out)
    _separable_filters(np.ascontiguousarray(lines, dtype=np.float64),
                       np.ascontiguousarray(cores, dtype=np.float64),
                       np.ascontiguousarray(counts, dtype=np.float64), float(h), float(var_add),
                       float(floor), filters, scale, rsum, ok)
    return filters, scale, rsum, ok


def _outputs(n: int, p: int, out: tuple | None) -> tuple:
    """``(filters (n, 2, p*p) int16, scale (n, 2), rsum (n, 2), ok (n,) bool)``: ``out``
    checked, or new arrays."""
    want = (((n, 2, p * p), np.int16), ((n, 2), np.float64), ((n, 2), np.float64),
            ((n,), np.bool_))
    if out is None:
        return tuple(np.empty(shape, dtype=dtype) for shape, dtype in want)
    if len(out) != 4 or any(a.shape != shape or a.dtype != dtype or not a.flags.c_contiguous
                            for a, (shape, dtype) in zip(out, want)):
        raise ValueError(f"filters: out must be C-contiguous arrays of shapes and types "
                         f"{[(sh, np.dtype(t).name) for sh, t in want]}")
    return tuple(out)
