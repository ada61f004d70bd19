"""Compiled single-pass kernels over a whole detector frame, read in place.

numpy needs several passes over a 960 x 960 uint16 frame to centroid it (the block gather or
a cast to float, then the products); these numba kernels read each valid block's pixels once,
straight from the frame (a shared-memory view works: no copy, no float frame), and accumulate
in registers. Outside the pupil nothing is read.

- :func:`cog_moments`: ``(n, 3)`` [total, sum v (x - c), sum v (y - c)] per valid block,
  exact integer sums for integer frames (what ``rows @ [1, x, y]`` gives in float).
- :func:`block_contract`: ``(n, k)`` per-block weights times pixels (a CMF filter
  ``[R; 1]`` of ``(n, k, p*p)``), float32 weights times pixels summed in float64.
- :func:`filter_flux`: as :func:`block_contract` for the CMF's ``R`` ``(n, 2, p*p)`` plus
  each block's pixel sum (the flux), 2/3 of the weight traffic of ``[R; 1]``.
- :func:`block_marginals`: each valid block's row and column sums (the reference-reading
  network's input on a polar detector, :mod:`.ann`).
- :func:`ml_search`: the ML estimator's marginals, calibrated-CoG start and hill climb on
  its likelihood tables (:mod:`.ml`), one pass over each block.
- :func:`corr_peak`: the correlation centroider's map at the 3 x 3 whole lags around its
  peak (found from the CoG, then climbed), and the peak fit, instead of the FFT map.
- :func:`invert_response`: the linearisation's per-subaperture inversion of a 2-D
  Chebyshev response (:mod:`.linearize`): polynomial start and Newton steps, one pass per
  subaperture in registers (numpy needs a dozen ``(n, 2, D, D)`` passes and ~50 calls).

numba is optional (the ``fast`` extra): :data:`AVAILABLE` says whether these run; callers
keep their numpy path for when it is False. Shapes: frames ``(G*p, G*p)``; ``origins``
``(n, 2)`` int64 (row, column) of each valid block's first pixel, in the contract's order.
"""

from __future__ import annotations

import numpy as np

try:                                     # optional: the 'fast' extra
    import numba
    AVAILABLE = True
except ImportError:                      # pragma: no cover - exercised where it is absent
    numba = None
    AVAILABLE = False


def block_origins(layout) -> np.ndarray:
    """``(n, 2)`` int64 (row, column) of the first pixel of each valid block."""
    p = layout.sensor.pixels
    rows, cols = np.nonzero(np.asarray(layout.valid))      # row-major, the contract's order
    return np.ascontiguousarray(np.stack([rows * p, cols * p], axis=1).astype(np.int64))


def origins(centroider) -> np.ndarray:
    """:func:`block_origins` of a centroider's layout, cached on the instance."""
    cached = centroider.__dict__.get("_kernel_origins")
    if cached is None or cached[0] is not centroider.layout:
        cached = (centroider.layout, block_origins(centroider.layout))
        centroider.__dict__["_kernel_origins"] = cached
    return cached[1]


def stack_view(stack, n: int, p: int):
    """An integer ``(n, p, p)`` stack as a ``(n*p, p)`` frame whose blocks are at
    :func:`stack_origins` (a view; None if the stack does not fit the kernels), so that
    frames and stacks of the same pixels give the same sums bit for bit."""
    if not (AVAILABLE and isinstance(stack, np.ndarray) and stack.shape == (n, p, p)
            and stack.dtype.kind in "ui" and stack.itemsize <= 2 and stack.flags.c_contiguous):
        return None
    return stack.reshape(n * p, p)


_stack_origins: dict = {}


def stack_origins(n: int, p: int) -> np.ndarray:
    """``(n, 2)`` origins of the blocks of :func:`stack_view`."""
    key = (int(n), int(p))
    if key not in _stack_origins:
        _stack_origins[key] = np.ascontiguousarray(
            np.stack([np.arange(n) * p, np.zeros(n, int)], axis=1).astype(np.int64))
    return _stack_origins[key]


def fits(frame, shape) -> bool:
    """True when ``frame`` is an integer frame of ``shape`` these kernels take."""
    return (AVAILABLE and isinstance(frame, np.ndarray) and frame.shape == tuple(shape)
            and frame.dtype.kind in "ui" and frame.itemsize <= 2
            and frame.strides[1] == frame.itemsize)


def _block_moments_impl(frame, r0, c0, p):
    # (total, sum of x, sum of y) of the block at (r0, c0), pixel indices from 0: exact,
    # int32 per row (at most 65535 p (p - 1) / 2: 7.9 M for p = 16; fits up to p = 255)
    s = 0
    sx = 0
    sy = 0
    for i in range(p):
        row = frame[r0 + i, c0:c0 + p]
        rs = np.int32(0)
        rx = np.int32(0)
        for j in range(p):
            v = np.int32(row[j])
            rs += v
            rx += v * np.int32(j)
        s += rs
        sx += rx
        sy += rs * i
    return s, sx, sy


def _cog_moments_impl(frame, origins, p, centre, out):
    n = origins.shape[0]
    for b in range(n):
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        s, sx, sy = _block_moments(frame, r0, c0, p)
        out[b, 0] = s
        out[b, 1] = sx - centre * s
        out[b, 2] = sy - centre * s


def _block_contract_impl(frame, origins, p, weights, out):
    # float32 weights times exact pixel values, summed in float64: a float32 sum of 256
    # products of mixed sign loses ~1e-4 of the result to cancellation
    n = origins.shape[0]
    k = weights.shape[1]
    for b in range(n):
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


def _invert_response_impl(coef, extent, guess, gdeg, m, iterations, min_det, s_out, jac_out,
                          inside_out):
    # coef (n, 2, D, D) [out, x degree, y degree]; guess (n, K, 2) monomials x^i y^(d-i)
    n = m.shape[0]
    nd = coef.shape[3]
    tx = np.empty(nd)
    dx = np.empty(nd)
    ty = np.empty(nd)
    dy = np.empty(nd)
    xp = np.empty(gdeg + 1)
    yp = np.empty(gdeg + 1)
    inv_e = 1.0 / extent
    for b in range(n):
        mx = m[b, 0]
        my = m[b, 1]
        if gdeg >= 0:
            xp[0] = 1.0
            yp[0] = 1.0
            for d in range(1, gdeg + 1):
                xp[d] = xp[d - 1] * mx
                yp[d] = yp[d - 1] * my
            sx = 0.0
            sy = 0.0
            k = 0
            for d in range(gdeg + 1):
                for i in range(d + 1):
                    mono = xp[i] * yp[d - i]
                    sx += mono * guess[b, k, 0]
                    sy += mono * guess[b, k, 1]
                    k += 1
        else:
            sx = mx
            sy = my
        if not np.isfinite(sx):
            sx = 0.0 if np.isnan(sx) else sx
        if not np.isfinite(sy):
            sy = 0.0 if np.isnan(sy) else sy
        sx = min(max(sx, -extent), extent)
        sy = min(max(sy, -extent), extent)
        j00 = j01 = j10 = j11 = 0.0
        for _ in range(iterations):
            ux = sx * inv_e
            uy = sy * inv_e
            tx[0] = 1.0
            dx[0] = 0.0
            ty[0] = 1.0
            dy[0] = 0.0
            if nd > 1:
                tx[1] = ux
                dx[1] = 1.0
                ty[1] = uy
                dy[1] = 1.0
            for q in range(2, nd):
                tx[q] = 2 * ux * tx[q - 1] - tx[q - 2]
                dx[q] = 2 * ux * dx[q - 1] + 2 * tx[q - 1] - dx[q - 2]
                ty[q] = 2 * uy * ty[q - 1] - ty[q - 2]
                dy[q] = 2 * uy * dy[q - 1] + 2 * ty[q - 1] - dy[q - 2]
            f0 = 0.0
            f1 = 0.0
            j00 = 0.0
            j01 = 0.0
            j10 = 0.0
            j11 = 0.0
            for i in range(nd):
                c0 = 0.0
                c0d = 0.0
                c1 = 0.0
                c1d = 0.0
                for j in range(nd):
                    c0 += coef[b, 0, i, j] * ty[j]
                    c0d += coef[b, 0, i, j] * dy[j]
                    c1 += coef[b, 1, i, j] * ty[j]
                    c1d += coef[b, 1, i, j] * dy[j]
                f0 += c0 * tx[i]
                f1 += c1 * tx[i]
                j00 += c0 * dx[i]
                j01 += c0d * tx[i]
                j10 += c1 * dx[i]
                j11 += c1d * tx[i]
            j00 *= inv_e
            j01 *= inv_e
            j10 *= inv_e
            j11 *= inv_e
            r0 = f0 - mx
            r1 = f1 - my
            det = j00 * j11 - j01 * j10
            sx = sx - (j11 * r0 - j01 * r1) / det
            sy = sy - (j00 * r1 - j10 * r0) / det
        det = j00 * j11 - j01 * j10
        inside = abs(sx) <= extent and abs(sy) <= extent and det > min_det
        inside_out[b] = inside
        if inside:
            s_out[b, 0] = sx
            s_out[b, 1] = sy
            jac_out[b, 0, 0] = j00
            jac_out[b, 0, 1] = j01
            jac_out[b, 1, 0] = j10
            jac_out[b, 1, 1] = j11
        else:
            s_out[b, 0] = mx
            s_out[b, 1] = my
            jac_out[b, 0, 0] = 1.0
            jac_out[b, 0, 1] = 0.0
            jac_out[b, 1, 0] = 0.0
            jac_out[b, 1, 1] = 1.0


def _block_sums_impl(frame, r0, c0, p, col, dst, acc, b):
    # dst (2, p): [0] the column sums of the block at (r0, c0) (a function of block x), [1]
    # its row sums; added into acc[b] when acc has a row per block (the calibration's sums);
    # returns the block's total. col: an int32 (p,) scratch (at most p x 65535: p <= 255)
    for j in range(p):
        col[j] = 0
    tot = 0
    for i in range(p):
        row = frame[r0 + i, c0:c0 + p]
        rs = np.int32(0)
        for j in range(p):
            v = np.int32(row[j])
            rs += v
            col[j] += v
        dst[1, i] = rs
        tot += rs
    for j in range(p):
        dst[0, j] = col[j]
    if b < acc.shape[0]:
        for j in range(p):
            acc[b, 0, j] += dst[0, j]
            acc[b, 1, j] += dst[1, j]
    return tot


def _hyper_contract_impl(x, filters, fbias, pos, cbias, step, z, safe, chosen):
    # x (n, p) float32 marginals; filters (n, S, K, p), fbias (n, S, K) float32; out z (n, K),
    # safe (n, 1), chosen (n,) int64: the set S // 2 + round((CoG(x) - cbias) / step), clipped
    # (S = 1: set 0; the CoG over positions pos (p,))
    n, ns, k, p = filters.shape
    half = ns // 2
    for b in range(n):
        tot = np.float32(0.0)
        mom = np.float32(0.0)
        for j in range(p):
            tot += x[b, j]
            mom += x[b, j] * pos[j]
        s = tot if tot > 1.0 else np.float32(1.0)
        if tot != tot:                       # NaN row: NaN out
            s = tot
        safe[b, 0] = s
        c = half
        if ns > 1 and tot > 0:
            t = (mom / tot - cbias[b]) / step
            if t == t:                       # not NaN
                t = min(max(t, -half - 1.0), half + 1.0)
                c = min(max(half + int(np.floor(t + 0.5)), 0), ns - 1)
        chosen[b] = c
        for q in range(k):
            acc = np.float32(0.0)
            for j in range(p):
                acc += filters[b, c, q, j] * x[b, j]
            z[b, q] = acc / s + fbias[b, c, q]


def _inverse_at_impl(xb, r, t, g, b):
    # gain g * the inverse of the piecewise-linear response r[b] (S readings at moves t,
    # extended past the ends by the end segments) at xb, + r[b, S // 2]; xb itself where g
    # is NaN (a response that does not increase) or xb is NaN
    ns = r.shape[1]
    if g != g or xb != xb:
        return xb
    k = 1
    while k < ns - 1 and xb > r[b, k]:
        k += 1
    y = t[k - 1] + (xb - r[b, k - 1]) * (t[k] - t[k - 1]) / (r[b, k] - r[b, k - 1])
    return g * y + r[b, ns // 2]


def _response_inverse_impl(x, r, t, gain, out):
    # out (n,): _inverse_at of each reading x (n,) through its row of r (n, S)
    for b in range(r.shape[0]):
        out[b] = _inverse_at(x[b], r, t, gain[b], b)


def _bins_shifts_impl(raw, scale, r, t, gain, mom, centre, e, a, c, offset, out):
    # out (n, 2) float64: along the bins raw[b, 0] * scale (float32, as numpy forms it),
    # through _inverse_at when r has columns; across e the CoG of the moments mom (n, 3)
    # (total, sum x, sum y) less centre, onto (-e_y, e_x); out = along a + across c less
    # offset; NaN without light
    straight = r.shape[1] > 0
    for b in range(raw.shape[0]):
        tot = mom[b, 0]
        if not tot > 0:
            out[b, 0] = np.nan
            out[b, 1] = np.nan
            continue
        x = np.float64(raw[b, 0] * scale)
        if straight:
            x = _inverse_at(x, r, t, gain[b], b)
        cx = (mom[b, 1] - centre * tot) / tot
        cy = (mom[b, 2] - centre * tot) / tot
        across = -e[b, 1] * cx + e[b, 0] * cy
        out[b, 0] = x * a[b, 0] + across * c[b, 0] - offset[b, 0]
        out[b, 1] = x * a[b, 1] + across * c[b, 1] - offset[b, 1]


def _add_counts_impl(acc, counts):
    # acc (N,) uint32 += counts (N,) uint8/uint16: a flat loop the compiler vectorises
    # (numpy's add with a cast runs its buffered casting loop: twice as long)
    for k in range(counts.shape[0]):
        acc[k] += counts[k]


def _block_rows_impl(frame, origins, p, out):
    # out (n, p*p) float32: each valid block's counts, row-major, cast as they are read
    for b in range(origins.shape[0]):
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        for i in range(p):
            row = frame[r0 + i, c0:c0 + p]
            dst = out[b, i * p:(i + 1) * p]
            for j in range(p):
                dst[j] = row[j]


def _block_marginals_impl(frame, origins, p, acc, out):
    # out (n, 2, p) float32; acc (n, 2, p) float64 or a 0-row dummy
    col = np.zeros(p, dtype=np.int32)
    for b in range(origins.shape[0]):
        _block_sums(frame, origins[b, 0], origins[b, 1], p, col, out[b], acc, b)


def _block_bins_impl(frame, origins, p, start, w, bins, moments):
    # bins (n, p) float32: each pixel's count split over bins start, start + 1, start + 2
    # by its shares w (n, p*p, 2) uint8 (of 255: the first and the third; the second the
    # rest), a bin outside 0..p-1 dropped; moments (n, 3) float64: the block's total, sum
    # of x and sum of y (_block_moments). Even and odd pixels of a row add into two
    # buffers: neighbours hit the same bins, and two buffers let their additions overlap
    # instead of waiting on each other
    n = origins.shape[0]
    scale = np.float32(1.0 / 255.0)
    even = np.zeros(p + 4, dtype=np.float32)          # bins -2 .. p + 1
    odd = np.zeros(p + 4, dtype=np.float32)
    for b in range(n):
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        moments[b, 0], moments[b, 1], moments[b, 2] = _block_moments(frame, r0, c0, p)
        for k in range(p + 4):
            even[k] = 0.0
            odd[k] = 0.0
        for i in range(p):
            row = frame[r0 + i, c0:c0 + p]
            for j in range(p):
                q = np.int32(row[j])
                if q == 0:                          # dark pixels cost nothing
                    continue
                pix = i * p + j
                k = start[b, pix] + 2
                w0 = np.int32(w[b, pix, 0])
                w2 = np.int32(w[b, pix, 1])
                acc = even if j % 2 == 0 else odd
                acc[k] += np.float32(q * w0)
                acc[k + 1] += np.float32(q * (255 - w0 - w2))
                acc[k + 2] += np.float32(q * w2)
        for k in range(p):
            bins[b, k] = (even[k + 2] + odd[k + 2]) * scale


#: the whole-pixel sums a grid bin takes a share of, unrolled in the pass below
#: (:data:`.bins_along_e.GRID_SLOTS`)
GRID_SLOTS = 4


def _grid_bins_impl(frame, origins, p, code, sums, shares, raw, bins, moments):
    # bins (n, p) float32 along the pixel-grid direction of each block (code: 0 columns,
    # 1 diagonals i + j, 2 rows, 3 anti-diagonals j - i + p - 1): whole pixels summed into
    # raw (2p,: 2p - 1 sums and a zero), then each bin the shares[b, q] of sums[b, q] (four
    # slots, unrolled: a loop over them costs 15 %; a gather, no scattered additions
    # waiting on one another); moments (n, 3) float64: total, sum of x, sum of y (pixel
    # indices from 0). One read of each block: row i is added into the diagonal sums at
    # offset i (p - 1 - i for anti-diagonals) of one of two int32 accumulators taken in turn,
    # so that consecutive rows' overlapping additions do not wait on one another (one
    # accumulator: +15 %; a skewed float copy summed by columns, the previous pass: +50 %);
    # a diagonal block's sum of x comes from its diagonal sums, no column sums. Integer sums
    # throughout (exact: at most 2p x 65535 < 2^31), so the bins do not depend on the order.
    n = origins.shape[0]
    wk = 2 * p
    col = np.zeros(p, dtype=np.int32)
    marg = np.empty((2, p), dtype=np.float32)
    no_acc = np.zeros((0, 2, 1))
    dacc = np.zeros((2, wk), dtype=np.int32)
    for b in range(n):
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        k = code[b]
        tot = 0
        ty = 0
        tx = 0
        if k == 0 or k == 2:                         # columns or rows: the marginals
            tot = _block_sums(frame, r0, c0, p, col, marg, no_acc, b)
            for j in range(p):                       # integer chains: no float latency
                tx += col[j] * j
                ty += np.int32(marg[1, j]) * j
                raw[j] = marg[k // 2, j]
        else:                                        # diagonals or anti-diagonals
            for m in range(wk):
                dacc[0, m] = 0
                dacc[1, m] = 0
            for i in range(p):
                row = frame[r0 + i, c0:c0 + p]
                at = i if k == 1 else p - 1 - i
                d = dacc[i & 1, at:at + p]
                rs = np.int32(0)
                for j in range(p):
                    v = np.int32(row[j])
                    rs += v
                    d[j] += v
                tot += rs
                ty += rs * i
            sm = 0                                   # sum of the diagonal index
            for m in range(wk):
                dm = dacc[0, m] + dacc[1, m]
                raw[m] = np.float32(dm)
                sm += dm * m
            tx = sm - ty if k == 1 else sm - (p - 1) * tot + ty
        moments[b, 0] = tot
        moments[b, 1] = tx
        moments[b, 2] = ty
        for q in range(p):
            s = sums[b, q]
            w = shares[b, q]
            bins[b, q] = raw[s[0]] * w[0] + raw[s[1]] * w[1] + raw[s[2]] * w[2] + raw[s[3]] * w[3]


def _ml_line_impl(mg, lg, j, base, tot_norm):
    # log-likelihood of one axis' marginals mg (p,) against the shift whose marginals are
    # columns base .. base + p - 1 of phase j of the phase table lg (S, W)
    acc = 0.0
    for u in range(mg.shape[0]):
        acc += np.float64(mg[u]) * np.float64(lg[j, base + u])
    return acc - tot_norm


def _ml_search_impl(frame, origins, p, logs, norms, bias, kphase, kbase, acc, out):
    # logs (n, 2, S, W) float32 phase tables, norms (n, 2, K), bias (n, 2): the calibrated
    # CoG's offset; shift k is phase kphase[k] from column kbase[k]; grid step 1 / S
    n = origins.shape[0]
    phases = logs.shape[2]
    step = 1.0 / phases
    kk = norms.shape[2]
    m = (kk - 1) // 2
    c = (p - 1) / 2.0
    col = np.zeros(p, dtype=np.int32)
    marg = np.empty((2, p), dtype=np.float32)
    for b in range(n):                              # marginals (and the calibration's sums)
        tot = np.float64(_block_sums(frame, origins[b, 0], origins[b, 1], p, col, marg, acc, b))
        if not tot > 0:
            out[b, 0] = np.nan
            out[b, 1] = np.nan
            continue
        for a in range(2):
            mg = marg[a]
            lg = logs[b, a]
            nm = norms[b, a]
            mom = 0.0
            for u in range(p):
                mom += (u - c) * mg[u]
            start = mom / tot - bias[b, a]
            k = int(np.floor(start / step + 0.5)) + m
            k = min(max(k, 1), kk - 2)
            lm = _ml_line(mg, lg, kphase[k - 1], kbase[k - 1], tot * nm[k - 1])
            lk = _ml_line(mg, lg, kphase[k], kbase[k], tot * nm[k])
            lp = _ml_line(mg, lg, kphase[k + 1], kbase[k + 1], tot * nm[k + 1])
            while lm > lk and k > 1:
                k -= 1
                lp = lk
                lk = lm
                lm = _ml_line(mg, lg, kphase[k - 1], kbase[k - 1], tot * nm[k - 1])
            while lp > lk and k < kk - 2:
                k += 1
                lm = lk
                lk = lp
                lp = _ml_line(mg, lg, kphase[k + 1], kbase[k + 1], tot * nm[k + 1])
            if lm > lk or lp > lk:                 # the climb hit the table's edge
                out[b, a] = start
                continue
            den = lm - 2.0 * lk + lp
            off = 0.5 * (lm - lp) / den if den < 0 else 0.0
            out[b, a] = (k - m + min(max(off, -0.5), 0.5)) * step


def _rows_int16_impl(frame, r0, c0, p, w0, w1):
    # (pixel sum, w0 . block, w1 . block) of the block at (r0, c0): int16 rows, exact
    # integer sums (at most 256 x 32767 x 65535 < 2^63). Summed a pixel row at a time (the
    # row's pixel sum in int32: p x 65535 < 2^31; the products in int64), then the rows
    # added up: the same integers, 15-20 % faster on a cold full frame than one running sum
    # (filter_flux 0.26-0.27 against 0.32 ms, 2026-11-25)
    tot = np.int64(0)
    a0 = np.int64(0)
    a1 = np.int64(0)
    for i in range(p):
        row = frame[r0 + i, c0:c0 + p]
        o = i * p
        t = np.int32(0)
        b0 = np.int64(0)
        b1 = np.int64(0)
        for j in range(p):
            x = np.int32(row[j])
            t += x
            b0 += np.int32(w0[o + j]) * x
            b1 += np.int32(w1[o + j]) * x
        tot += t
        a0 += b0
        a1 += b1
    return tot, a0, a1


def _filter_flux_q_impl(frame, origins, p, weights, scale, out):
    # _filter_flux_impl with int16 filter rows (one scale each): exact integer sums, half
    # the filter bytes read a frame (the filter, not the frame, is most of the CMF's traffic)
    for b in range(origins.shape[0]):
        tot, a0, a1 = _rows_int16(frame, origins[b, 0], origins[b, 1], p, weights[b, 0],
                                  weights[b, 1])
        out[b, 0] = a0 * scale[b, 0]
        out[b, 1] = a1 * scale[b, 1]
        out[b, 2] = tot


def _grid_filter_impl(frame, origins, p, bias, filters, scale, rsum, positions, background,
                      picks, out, index):
    # per block: the CoG moments (exact int32 row sums), the calibrated CoG (minus bias) as
    # the first estimate; then up to `picks` times: the grid position nearest to the
    # estimate, that position's two filter rows applied to the block (int16 rows, exact
    # integer sums, then their scales), out[b] = position + (R x - background R 1) / flux,
    # which is the next estimate (stop when the position does not change)
    n = origins.shape[0]
    c = (p - 1) / 2.0
    side = positions.shape[0]
    half = (side - 1) // 2
    spacing = positions[1] - positions[0] if side > 1 else 1.0
    for b in range(n):
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        s, sx, sy = _block_moments(frame, r0, c0, p)
        flux = s - background * p * p
        if s <= 0 or not flux > 0:
            out[b, 0] = np.nan
            out[b, 1] = np.nan
            index[b] = -1
            continue
        # moments about the centre do not see a uniform background; the flux does
        ex = (sx - c * s) / flux - bias[b, 0]
        ey = (sy - c * s) / flux - bias[b, 1]
        g = -1
        for _ in range(picks):
            kx = min(max(int(np.floor(ex / spacing + 0.5)) + half, 0), side - 1)
            ky = min(max(int(np.floor(ey / spacing + 0.5)) + half, 0), side - 1)
            if ky * side + kx == g:
                break
            g = ky * side + kx
            _, a0, a1 = _rows_int16(frame, r0, c0, p, filters[g, b, 0], filters[g, b, 1])
            ex = positions[kx] + (a0 * scale[g, b, 0] - background * rsum[g, b, 0]) / flux
            ey = positions[ky] + (a1 * scale[g, b, 1] - background * rsum[g, b, 1]) / flux
        index[b] = g
        out[b, 0] = ex
        out[b, 1] = ey


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


def _corr_peak_impl(frame, origins, p, refw, spans, m, ref_cog, background, log, climbs, out):
    # per block: the block less the background into the padded buffer, its CoG; the whole
    # lag nearest to CoG - the reference's CoG; the 3 x 3 correlation values around it,
    # moved to their maximum until it is the centre (at most ``climbs`` moves, each keeping
    # the values the new 3 x 3 shares with the old: the same numbers, 12-19 % faster a full
    # frame than computing all nine again); then the quadratic (of the log with ``log``)
    # through the 3 x 3 values, as correlation._parabola_peak. Measured on the benchmark's
    # cartesian frame (2026-11-27): the nine values in one sweep (_lag_block9) 1.41 -> 1.00
    # ms, integer block sums, int16 references and five logs of ratios instead of nine
    # logs -> 0.88 ms; reading the blocks alone costs 0.22 ms, the sweep 0.28 ms
    n = origins.shape[0]
    c = (p - 1) / 2.0
    w = p + 2 * m
    xw = np.zeros(3 * p * w, dtype=np.float32)
    v = np.empty(9)
    w9 = np.empty(9)
    bg = np.float32(background)
    for b in range(n):
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
        if not s > 0 or k1 <= k0:
            out[b, 0] = np.nan
            out[b, 1] = np.nan
            continue
        lim = p - 2
        lx = min(max(int(np.floor(sx / s - ref_cog[b, 0] + 0.5)), -lim), lim)
        ly = min(max(int(np.floor(sy / s - ref_cog[b, 1] + 0.5)), -lim), lim)
        if -m < lx < m:
            _lag_block9(xw, ref, p, m, lx, ly, k0, k1, v)
        else:
            for k in range(9):
                v[k] = _lag_product(xw, ref, p, m, lx + k % 3 - 1, ly + k // 3 - 1, k0, k1)
        for step in range(climbs + 1):
            best = 0
            for k in range(1, 9):
                if v[k] > v[best]:
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
                    w9[k] = v[(oy + 1) * 3 + ox + 1]
                else:
                    w9[k] = _lag_product(xw, ref, p, m, nx + k % 3 - 1, ny + k // 3 - 1, k0, k1)
            for k in range(9):
                v[k] = w9[k]
            lx = nx
            ly = ny
        positive = log
        if log:
            for k in range(9):
                if not v[k] > 0:
                    positive = False
        if positive:            # the quadratic of the log: five logs of ratios, not nine
            bb = 0.5 * np.log(v[5] / v[3])
            d = 0.5 * np.log(v[5] * v[3] / (v[4] * v[4]))
            cc = 0.5 * np.log(v[7] / v[1])
            f = 0.5 * np.log(v[7] * v[1] / (v[4] * v[4]))
            e = 0.25 * np.log(v[8] * v[0] / (v[6] * v[2]))
        else:
            bb = (v[5] - v[3]) / 2
            d = (v[5] + v[3]) / 2 - v[4]
            cc = (v[7] - v[1]) / 2
            f = (v[7] + v[1]) / 2 - v[4]
            e = (v[8] - v[6] - v[2] + v[0]) / 4
        det = 4 * d * f - e * e
        if d < 0 and det > 0:
            ox = (e * cc - 2 * f * bb) / det
            oy = (e * bb - 2 * d * cc) / det
        else:
            ox = -bb / (2 * d) if d < 0 else 0.0
            oy = -cc / (2 * f) if f < 0 else 0.0
        out[b, 0] = lx + min(max(ox, -1.0), 1.0)
        out[b, 1] = ly + min(max(oy, -1.0), 1.0)


if AVAILABLE:
    # the marginals are exact integers in float32 (at most 16 x 65535 = 1.05e6 < 2^24)
    _ml_line = numba.njit(cache=True, nogil=True, fastmath=True, inline="always")(_ml_line_impl)
    _block_sums = numba.njit(cache=True, nogil=True, inline="always")(_block_sums_impl)
    _ml_search = numba.njit(cache=True, nogil=True)(_ml_search_impl)
    _block_marginals = numba.njit(cache=True, nogil=True)(_block_marginals_impl)
    _add_counts = numba.njit(cache=True, nogil=True)(_add_counts_impl)
    _block_rows = numba.njit(cache=True, nogil=True)(_block_rows_impl)
    _block_bins = numba.njit(cache=True, nogil=True)(_block_bins_impl)
    _grid_bins = numba.njit(cache=True, nogil=True)(_grid_bins_impl)
    _hyper_contract = numba.njit(cache=True, nogil=True, fastmath={"contract", "reassoc"})(
        _hyper_contract_impl)
    _inverse_at = numba.njit(cache=True, nogil=True, inline="always")(_inverse_at_impl)
    _response_inverse = numba.njit(cache=True, nogil=True)(_response_inverse_impl)
    _bins_shifts = numba.njit(cache=True, nogil=True)(_bins_shifts_impl)
    # numpy error model: a zero determinant gives inf/NaN (rejected), not an exception;
    # fast-math without the no-NaN/no-inf flags (NaN rows must stay NaN)
    _invert_response = numba.njit(cache=True, nogil=True, error_model="numpy",
                                  fastmath={"contract", "reassoc", "nsz", "arcp"})(_invert_response_impl)
    _block_moments = numba.njit(cache=True, nogil=True, inline="always")(_block_moments_impl)
    _cog_moments = numba.njit(cache=True, nogil=True)(_cog_moments_impl)
    _rows_int16 = numba.njit(cache=True, nogil=True, inline="always")(_rows_int16_impl)
    _grid_filter = numba.njit(cache=True, nogil=True, fastmath=True)(_grid_filter_impl)
    _lag_product = numba.njit(cache=True, nogil=True, fastmath=True, inline="always")(
        _lag_product_impl)
    _lag_block9 = numba.njit(cache=True, nogil=True, fastmath=True, inline="always")(
        _lag_block9_impl)
    _corr_peak = numba.njit(cache=True, nogil=True, error_model="numpy",
                            fastmath={"contract", "reassoc", "nsz", "arcp"})(_corr_peak_impl)
    _filter_flux = numba.njit(cache=True, nogil=True, fastmath=True)(_filter_flux_impl)
    _filter_flux_q = numba.njit(cache=True, nogil=True)(_filter_flux_q_impl)
    _block_contract = numba.njit(cache=True, nogil=True, fastmath=True)(_block_contract_impl)


def quantize(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(q, scale)``: filter rows ``r (..., pp)`` as int16 ``q`` with ``r ~ scale q`` (one
    scale per row, its largest coefficient at 32767: 3e-5 of it at most off), half the bytes
    of float32 and integer sums in the compiled pass."""
    top = np.abs(r).max(axis=-1)
    scale = np.where(top > 0, top / 32767.0, 1.0)
    return np.rint(r / scale[..., None]).astype(np.int16), scale


def cog_moments(frame: np.ndarray, origins: np.ndarray, p: int, centre: float,
                out: np.ndarray | None = None) -> np.ndarray:
    """``(n, 3)`` float64 [total, x moment, y moment] of each valid block (pixel axes,
    offsets from ``centre``); ``frame`` an integer ``(G*p, G*p)`` array (see :func:`fits`)."""
    if not 0 < p <= 255:
        raise ValueError(f"cog_moments: p must be 1 to 255 (int32 row sums), got {p}")
    if out is None:
        out = np.empty((origins.shape[0], 3))
    _cog_moments(frame, origins, int(p), float(centre), out)
    return out


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


def invert_response(coef: np.ndarray, extent: float, guess: np.ndarray | None, m: np.ndarray,
                    iterations: int, min_det: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shifts ``s (n, 2)`` px with ``f(s) = m``, ``df/ds (n, 2, 2)`` there and ``inside (n,)``
    bool (False where ``m`` was returned), as :meth:`.linearize.ResponseMap.invert` (float64
    throughout).

    Args:
        coef: ``(n, 2, D, D)`` float64 Chebyshev coefficients (output, x degree, y degree)
            over ``[-extent, extent]^2`` px.
        guess: ``(n, K, 2)`` float64 start polynomial in the monomials ``x^i y^(d-i)``
            (d = 0..degree, i = 0..d), or None (start at ``m``).
        m: ``(n, 2)`` measurements, px.
        iterations: Newton steps (>= 1).
        min_det: smallest accepted Jacobian determinant; below it, or outside the box,
            ``m`` is returned with an identity Jacobian.
    """
    m = np.ascontiguousarray(m, dtype=np.float64)
    n = m.shape[0]
    if guess is None:
        guess, gdeg = np.zeros((n, 1, 2)), -1
    else:
        gdeg = int(round((np.sqrt(8 * guess.shape[1] + 1) - 3) / 2))
    s = np.empty((n, 2))
    jac = np.empty((n, 2, 2))
    inside = np.empty(n, dtype=np.bool_)
    _invert_response(coef, float(extent), guess, gdeg, m, max(int(iterations), 1),
                     float(min_det), s, jac, inside)
    return s, jac, inside


def add_counts(acc: np.ndarray, counts: np.ndarray) -> bool:
    """``acc += counts`` for a uint32 ``acc`` and uint8/uint16 ``counts`` of one shape, both
    C-contiguous (a detector frame into the pupil calibration's accumulator: 0.07 ms for
    960 x 960 against numpy's 0.16 ms). Returns False, adding nothing, where that does not
    hold (or numba is missing): then the caller adds with numpy."""
    if not (AVAILABLE and acc.dtype == np.uint32 and counts.dtype in (np.uint8, np.uint16)
            and acc.shape == counts.shape and acc.flags.c_contiguous
            and counts.flags.c_contiguous):
        return False
    _add_counts(acc.reshape(-1), counts.reshape(-1))
    return True


def block_rows(frame: np.ndarray, origins: np.ndarray, p: int,
               out: np.ndarray | None = None) -> np.ndarray:
    """``(n, p*p)`` float32: the valid blocks of an integer frame (see :func:`fits`) as
    rows, cut and cast in one pass (a network's input: only the valid blocks, where numpy
    casts the whole block grid, ~30 % of it outside the pupil, or gathers then casts).
    ``out``, if given, is filled and returned."""
    n = origins.shape[0]
    if out is None:
        out = np.empty((n, p * p), dtype=np.float32)
    elif out.shape != (n, p * p) or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError("block_rows: out must be C-contiguous float32 (n, p*p)")
    _block_rows(frame, origins, int(p), out)
    return out


def block_marginals(frame: np.ndarray, origins: np.ndarray, p: int,
                    acc: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """``(n, 2, p)`` float32 marginals of each valid block: ``[:, 0]`` the column sums (a
    function of block x), ``[:, 1]`` the row sums (of block y); exact integers (at most
    ``p`` x 65535 < 2^24). ``acc`` ``(n, 2, p)`` float64, if given, gets them added (the
    pupil calibration's sums, :meth:`.pupil.PupilCalibration.marginal_buffer`)."""
    if not 0 < p <= 255:
        raise ValueError(f"block_marginals: p must be 1 to 255, got {p}")
    n = origins.shape[0]
    if out is None:
        out = np.empty((n, 2, p), dtype=np.float32)
    _block_marginals(frame, origins, int(p), np.empty((0, 2, p)) if acc is None else acc, out)
    return out


def block_bins(frame: np.ndarray, origins: np.ndarray, p: int, start: np.ndarray,
               shares: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(bins (n, p) float32, moments (n, 3) float64)`` of each valid block of an integer
    frame: its light in 1 px bins along e, each pixel split by its shares
    (:func:`.bins_along_e.quantised`: ``start (n, p*p)`` int8, ``shares (n, p*p, 2)`` uint8),
    and its total, sum of x and sum of y (pixel indices from 0)."""
    n = origins.shape[0]
    if start.shape != (n, p * p) or shares.shape != (n, p * p, 2):
        raise ValueError("block_bins: start and shares must be bins_along_e.quantised of the n blocks")
    bins = np.empty((n, p), dtype=np.float32)
    moments = np.empty((n, 3))
    _block_bins(frame, origins, int(p), np.ascontiguousarray(start, dtype=np.int8),
                np.ascontiguousarray(shares, dtype=np.uint8), bins, moments)
    return bins, moments


def grid_bins(frame: np.ndarray, origins: np.ndarray, p: int, code: np.ndarray,
              sums: np.ndarray, shares: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(bins (n, p) float32, moments (n, 3) float64)`` of each valid block of an integer
    frame: its light in 1 px bins along the pixel-grid direction nearest to its e (whole
    pixels summed along columns, rows, diagonals or anti-diagonals, each bin then a
    weighted sum of at most four of those sums: the tables of
    :func:`.bins_along_e.grid_tables`, ``code (n,)`` int8, ``sums (n, p, 4)`` int8,
    ``shares (n, p, 4)`` float32, 4 = :data:`GRID_SLOTS`), and its total, sum of x and sum of y (pixel indices from
    0). No pixel is split on its own: its cost does not grow with sky background."""
    n = origins.shape[0]
    if code.shape != (n,) or sums.shape != (n, p, GRID_SLOTS) or shares.shape != (n, p, GRID_SLOTS):
        raise ValueError("grid_bins: code, sums and shares must be bins_along_e.grid_tables of the n blocks")
    bins = np.empty((n, p), dtype=np.float32)
    moments = np.empty((n, 3))
    _grid_bins(frame, origins, int(p), np.ascontiguousarray(code, dtype=np.int8),
               np.ascontiguousarray(sums, dtype=np.int8), np.ascontiguousarray(shares, dtype=np.float32),
               np.zeros(2 * p, dtype=np.float32), bins, moments)
    return bins, moments


def hyper_contract(x: np.ndarray, filters: np.ndarray, fbias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(z (n, K), safe (n, 1))`` float32: each block's marginal ``x (n, p)`` through its
    own filters, ``z = filters (x / safe) + fbias`` with ``safe = max(sum x, 1)`` (NaN rows
    stay NaN): the first layer of a hyper network (``learning/hypertrain.py``), one pass
    instead of onnxruntime's per-block products. ``filters (n, K, p)``, ``fbias (n, K)``."""
    filters = np.asarray(filters)
    fbias = np.asarray(fbias)
    z, safe, _ = hyper_contract_moved(x, filters[:, None], fbias[:, None], np.zeros(x.shape[0]), 1.0)
    return z, safe


def hyper_contract_moved(x: np.ndarray, filters: np.ndarray, fbias: np.ndarray,
                         cbias: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`hyper_contract` with ``S`` filter sets a block (``filters (n, S, K, p)``,
    ``fbias (n, S, K)``, set ``S // 2`` at the reference, set ``S // 2 + k`` at the
    reference moved by ``k step`` px): each block takes the set nearest its CoG along the
    bins less ``cbias (n,)`` px (the reference's CoG), clipped to the sets. Returns ``(z (n,
    K), safe (n, 1), chosen (n,) int64)``; a block without light or with a NaN takes set
    ``S // 2``."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    filters = np.ascontiguousarray(filters, dtype=np.float32)
    fbias = np.ascontiguousarray(fbias, dtype=np.float32)
    n, p = x.shape
    if filters.ndim != 4 or filters.shape[0] != n or filters.shape[3] != p or fbias.shape != filters.shape[:3]:
        raise ValueError(f"hyper_contract: marginals {x.shape}, filters {filters.shape} and "
                         f"fbias {fbias.shape} do not match")
    pos = (np.arange(p) - (p - 1) / 2).astype(np.float32)
    cbias = np.ascontiguousarray(np.broadcast_to(cbias, (n,)), dtype=np.float32)
    z = np.empty((n, filters.shape[2]), dtype=np.float32)
    safe = np.empty((n, 1), dtype=np.float32)
    chosen = np.empty(n, dtype=np.int64)
    if AVAILABLE:
        _hyper_contract(x, filters, fbias, pos, cbias, np.float32(step), z, safe, chosen)
        return z, safe, chosen
    half = filters.shape[1] // 2
    tot = x.sum(axis=1)
    safe = np.where(np.isnan(tot), tot, np.maximum(tot, 1.0)).astype(np.float32)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((x @ pos / tot - cbias) / step, -half - 1.0, half + 1.0)
    use = np.isfinite(t) & (tot > 0) & (filters.shape[1] > 1)
    chosen = np.where(use, np.clip(half + np.floor(np.where(use, t, 0.0) + 0.5), 0,
                                   filters.shape[1] - 1), half).astype(np.int64)
    i = np.arange(n)
    z = (np.einsum("nkp,np->nk", filters[i, chosen], x) / safe + fbias[i, chosen]).astype(np.float32)
    return z, safe, chosen


def response_inverse(x: np.ndarray, response: np.ndarray, moves: np.ndarray,
                     gain: np.ndarray) -> np.ndarray:
    """``(n,)`` float64: readings ``x (n,)`` mapped through the inverse of each row of a
    piecewise-linear ``response (n, S)`` (its readings at ``moves (S,)``, increasing; past
    the ends the end segments go on), times ``gain (n,)``, plus the response at the middle
    move. A row whose gain is NaN, or a NaN reading, keeps ``x``. Used by ``ann``'s
    option ``linearize`` (:meth:`.ann.ANN._along_response`)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    r = np.ascontiguousarray(response, dtype=np.float64)
    t = np.ascontiguousarray(moves, dtype=np.float64)
    g = np.ascontiguousarray(gain, dtype=np.float64)
    if r.ndim != 2 or r.shape[0] != x.shape[0] or t.shape != (r.shape[1],) or g.shape != x.shape \
            or r.shape[1] < 2:
        raise ValueError(f"response_inverse: readings {x.shape}, response {r.shape}, moves "
                         f"{t.shape} and gain {g.shape} do not match")
    if AVAILABLE:
        out = np.empty_like(x)
        _response_inverse(x, r, t, g, out)
        return out
    k = np.clip((x[:, None] > r).sum(axis=1), 1, r.shape[1] - 1)
    i = np.arange(x.shape[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        y = t[k - 1] + (x - r[i, k - 1]) * (t[k] - t[k - 1]) / (r[i, k] - r[i, k - 1])
    return np.where(np.isnan(g) | np.isnan(x), x, g * y + r[:, r.shape[1] // 2])


def bins_shifts(raw: np.ndarray, scale: float, response: tuple | None, moments: np.ndarray,
                centre: float, e: np.ndarray, a: np.ndarray, c: np.ndarray,
                offset: np.ndarray | None) -> np.ndarray:
    """``(n, 2)`` float64 shifts, block axes, px, of a bins-along-e network's frame in one
    pass: the reading along the bins ``raw (n, 1)`` float32 times ``scale`` (in float32),
    through :func:`response_inverse` of ``response = (readings (n, S), moves (S,), gain
    (n,))`` unless None; across e the CoG of ``moments (n, 3)`` (:func:`grid_bins`) less
    ``centre`` onto ``(-e_y, e_x)`` for ``e (n, 2)``; the shift ``along a + across c``
    (``(n, 2)`` each) less ``offset (n, 2)`` (or nothing); NaN for a block without light.
    The steps of :meth:`.ann.ANN._centroid_bins` after the network, without their nine
    array passes; compiled only (check :data:`AVAILABLE`)."""
    n = raw.shape[0]
    if response is None:
        r, t, g = np.zeros((n, 0)), np.zeros(0), np.zeros(n)
    else:
        r, t, g = (np.ascontiguousarray(v, dtype=np.float64) for v in response)
        if r.shape[0] != n or t.shape != (r.shape[1],) or g.shape != (n,) or r.shape[1] < 2:
            raise ValueError(f"bins_shifts: response {r.shape}, moves {t.shape} and gain {g.shape} "
                             f"do not match {n} blocks")
    f64 = (lambda v: np.ascontiguousarray(v, dtype=np.float64))
    off = np.zeros((n, 2)) if offset is None else f64(offset)
    args = [f64(moments), f64(e), f64(a), f64(c), off]
    if raw.shape != (n, 1) or any(v.shape != (n, k) for v, k in zip(args, (3, 2, 2, 2, 2))):
        raise ValueError(f"bins_shifts: readings {raw.shape}, moments {moments.shape}, e, a, c "
                         f"and offset must be ({n}, 1), ({n}, 3) and ({n}, 2)")
    out = np.empty((n, 2))
    _bins_shifts(np.ascontiguousarray(raw, dtype=np.float32), np.float32(scale), r, t, g,
                 args[0], float(centre), *args[1:], out)
    return out


def ml_search(frame: np.ndarray, origins: np.ndarray, p: int, logs: np.ndarray,
              norms: np.ndarray, bias: np.ndarray, margin: int,
              acc: np.ndarray | None = None) -> np.ndarray:
    """``(n, 2)`` maximum-likelihood shifts, px, block axes, of each valid block of an
    integer frame (see :func:`fits`) against the phase tables of :class:`.ml.Tables`
    (``logs (n, 2, S, p + 2 margin)`` float32, ``norms (n, 2, K)``; grid step ``1 / S``
    px); the climb starts at the block's CoG minus ``bias (n, 2)``, which is returned where
    it leaves the grid. NaN for a block without light. ``acc`` (optional, ``(n, 2, p)``
    float64): each block's marginals (column sums, row sums) are added into it, read in
    the same pass (the pupil calibration's :meth:`~.pupil.PupilCalibration.marginal_buffer`)."""
    out = np.empty((origins.shape[0], 2))
    if acc is None:
        acc = _NO_ACC
    elif acc.shape != (origins.shape[0], 2, p) or acc.dtype != np.float64:
        raise ValueError(f"acc must be ({origins.shape[0]}, 2, {p}) float64")
    kk = norms.shape[2]
    m = (kk - 1) // 2
    whole, phase = np.divmod(np.arange(kk) - m, logs.shape[2])
    _ml_search(frame, origins, int(p), np.ascontiguousarray(logs, dtype=np.float32),
               np.ascontiguousarray(norms, dtype=np.float64),
               np.ascontiguousarray(bias, dtype=np.float64), phase.astype(np.int64),
               (int(margin) - whole).astype(np.int64), acc, out)
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


#: zero columns each side of a block in :func:`corr_peak`'s buffers: lags within +-3 px
#: across the columns are one contiguous dot product each
CORR_PAD = 3


def corr_rows(refs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, spans)``: references ``(n, p, p)`` laid out for :func:`corr_peak`: ``rows
    (n, p * (p + 2 CORR_PAD))`` int16, each row between ``CORR_PAD`` zeros each side, each
    reference scaled to its largest magnitude at 32767 (:func:`quantize`; the peak fit does
    not see a reference's scale; half the bytes of float32: the pass reads every reference
    each frame), and ``spans (n, 2)`` int64, the first and one past the last non-zero entry
    of each row (the pass sweeps only those: on polar pixels the rows across e beyond the
    spot's core are zero at this precision)."""
    n, p, _ = refs.shape
    out = np.zeros((n, p, p + 2 * CORR_PAD))
    out[:, :, CORR_PAD:CORR_PAD + p] = refs
    rows = quantize(out.reshape(n, -1))[0]
    nz = rows != 0
    first = nz.argmax(axis=1)
    last = rows.shape[1] - nz[:, ::-1].argmax(axis=1)
    lit = nz.any(axis=1)
    spans = np.stack([np.where(lit, first, 0), np.where(lit, last, 0)], axis=1).astype(np.int64)
    return rows, spans


def corr_peak(frame: np.ndarray, origins: np.ndarray, p: int, refw: tuple,
              ref_cog: np.ndarray, background: float = 0.0, log: bool = True,
              climbs: int = 4) -> np.ndarray:
    """Correlation centroids (:class:`.correlation.Correlation`, linear correlation, peak
    ``gauss`` or ``parabola``), one compiled pass per valid block of an integer frame (see
    :func:`fits`): the correlation ``c(t) = sum_u x(u + t) ref(u)`` of the block less
    ``background`` with its reference (``refw``: :func:`corr_rows` of the references
    ``(n, p, p)``, background removed, any flux scale) is evaluated only on the 3 x 3 whole
    lags around the block's CoG minus ``ref_cog (n, 2)`` (the references' CoGs, px from the
    block centre), moved up to ``climbs`` times towards the largest value, then refined by
    the quadratic through those 9 values (of their log with ``log``). Returns ``(n, 2)`` px,
    block axes, NaN for a block without light. Where the map has one maximum this is the
    whole map's peak fit."""
    n = origins.shape[0]
    refw, spans = refw
    if (refw.shape != (n, p * (p + 2 * CORR_PAD)) or refw.dtype != np.int16
            or spans.shape != (n, 2) or spans.dtype != np.int64):
        raise ValueError("corr_peak: refw must be corr_rows(references)")
    out = np.empty((n, 2))
    _corr_peak(frame, origins, int(p), np.ascontiguousarray(refw), np.ascontiguousarray(spans),
               CORR_PAD,
               np.ascontiguousarray(ref_cog, dtype=np.float64), float(background), bool(log),
               int(climbs), out)
    return out


_NO_ACC = np.zeros((0, 2, 1))
_warm = False


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels now, once per process, so the first
    frame of a running graph does not pay for it (~0.5 s). Each frame kernel is warmed on a
    writable and on a read-only frame: shared-memory frames are read-only views, another
    signature for numba (compiled on a live node's first frame, that held it ~0.2 s)."""
    global _warm
    if _warm or not AVAILABLE:
        return
    frame = np.zeros((4, 4), np.uint16)
    o = np.zeros((1, 2), np.int64)
    ro = frame.copy()
    ro.flags.writeable = False
    for f in (frame, ro):
        cog_moments(f, o, 4, 1.5)
        block_contract(f, o, np.zeros((1, 3, 16), np.float32))
        filter_flux(f, o, np.zeros((1, 2, 16), np.float32))
        filter_flux(f, o, np.zeros((1, 2, 16), np.int16), scale=np.ones((1, 2)))
        ml_search(f, o, 4, np.zeros((1, 2, 2, 8), np.float32), np.zeros((1, 2, 5)),
                  np.zeros((1, 2)), 2)
        grid_filter(f, o, 4, np.zeros((1, 2)), np.zeros((9, 1, 2, 16), np.int16),
                    np.ones((9, 1, 2)), np.zeros((9, 1, 2)), np.array([-0.5, 0.0, 0.5]))
        block_marginals(f, o, 4, np.zeros((1, 2, 4)))
        block_marginals(f, o, 4)
        block_bins(f, o, 4, np.zeros((1, 16), np.int8), np.zeros((1, 16, 2), np.uint8))
        grid_bins(f, o, 4, np.zeros(1, np.int8), np.zeros((1, 4, 4), np.int8), np.zeros((1, 4, 4), np.float32))
        corr_peak(f, o, 4, corr_rows(np.zeros((1, 4, 4))), np.zeros((1, 2)))
        add_counts(np.zeros(f.shape, np.uint32), f)
        block_rows(f, o, 4)
    invert_response(np.zeros((1, 2, 2, 2)), 1.0, np.zeros((1, 3, 2)), np.zeros((1, 2)), 1, 0.0)
    hyper_contract(np.zeros((1, 4), np.float32), np.zeros((1, 2, 4), np.float32), np.zeros((1, 2), np.float32))
    hyper_contract_moved(np.ones((1, 4), np.float32), np.zeros((1, 3, 2, 4), np.float32),
                         np.zeros((1, 3, 2), np.float32), np.zeros(1), 0.25)
    response_inverse(np.zeros(1), np.array([[-1.0, 0.0, 1.0]]), np.array([-1.0, 0.0, 1.0]), np.ones(1))
    _warm = True
