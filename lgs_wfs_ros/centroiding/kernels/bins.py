"""The reference-reading networks' passes (:mod:`..ann`): each block's light in bins along
e, the hyper network's first layer on them, the inverse of its straightened response, and
the steps from its reading to a shift.
"""

from __future__ import annotations

import numpy as np

from . import _jit


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
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
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
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
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


if _jit.COMPILED:
    from .blocks import FRAME_AHEAD, _block_moments, _block_sums, _prefetch_block
    _block_bins = _jit.numba.njit(cache=True, nogil=True)(_block_bins_impl)
    _grid_bins = _jit.numba.njit(cache=True, nogil=True)(_grid_bins_impl)
    _hyper_contract = _jit.numba.njit(cache=True, nogil=True, fastmath={"contract", "reassoc"})(
        _hyper_contract_impl)
    _inverse_at = _jit.numba.njit(cache=True, nogil=True, inline="always")(_inverse_at_impl)
    _response_inverse = _jit.numba.njit(cache=True, nogil=True)(_response_inverse_impl)
    _bins_shifts = _jit.numba.njit(cache=True, nogil=True)(_bins_shifts_impl)


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
    if _jit.enabled():
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
    if _jit.enabled():
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
    array passes; compiled only (check :data:`.AVAILABLE`)."""
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
