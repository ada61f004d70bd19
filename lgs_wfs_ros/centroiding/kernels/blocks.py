"""Blocks of a frame read in place: where each valid block starts, stack views, and the
pixel sums the estimators start from (CoG moments, row and column sums, the calibration's
frame sum, exact integer sums of int16 filter rows).

Shapes: frames ``(G*p, G*p)``; ``origins`` ``(n, 2)`` int64 (row, column) of each valid
block's first pixel, in the contract's order.
"""

from __future__ import annotations

import numpy as np

from . import _jit


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
    if not (_jit.enabled() and isinstance(stack, np.ndarray) and stack.shape == (n, p, p)
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
    return (_jit.enabled() and isinstance(frame, np.ndarray) and frame.shape == tuple(shape)
            and frame.dtype.kind in "ui" and frame.itemsize <= 2
            and frame.strides[1] == frame.itemsize)


#: blocks ahead of the one being read whose pixels a pass asks for (:func:`_prefetch_block`):
#: a block's 16 rows are 1,920 bytes apart in a 960-pixel frame, 16 streams the hardware
#: does not follow (asked 2 blocks ahead, the CoG moments of a full frame take 0.34 ms
#: instead of 0.41, 2026-11-28)
FRAME_AHEAD = 2


def _prefetch_block_impl(frame, origins, b, p):
    # ask for the pixel rows of block b, if there is one (each row's first and last pixel:
    # a row that straddles two cache lines gets both); no value changes
    if b < origins.shape[0]:
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        for i in range(p):
            row = frame[r0 + i]
            _jit.prefetch(row, c0)
            _jit.prefetch(row, c0 + p - 1)


def _block_moments_impl(frame, r0, c0, p):
    # (total, sum of x, sum of y) of the block at (r0, c0), pixel indices from 0: exact,
    # int32 per row (at most 65535 p (p - 1) / 2: 7.9 M for p = 16; fits up to p = 255).
    # numba widens int32 arithmetic to int64; the casts keep the row sums in 32-bit lanes
    # (8 to a vector instead of 4: a full frame's moments 0.23 -> 0.15 ms, 2026-11-28)
    s = 0
    sx = 0
    sy = 0
    for i in range(p):
        row = frame[r0 + i, c0:c0 + p]
        rs = np.int32(0)
        rx = np.int32(0)
        for j in range(p):
            v = np.int32(row[j])
            rs = np.int32(rs + v)
            rx = np.int32(rx + np.int32(v * np.int32(j)))
        s += rs
        sx += rx
        sy += rs * i
    return s, sx, sy


def _cog_moments_impl(frame, origins, p, centre, out):
    n = origins.shape[0]
    for b in range(n):
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
        r0 = origins[b, 0]
        c0 = origins[b, 1]
        s, sx, sy = _block_moments(frame, r0, c0, p)
        out[b, 0] = s
        out[b, 1] = sx - centre * s
        out[b, 2] = sy - centre * s


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
            rs = np.int32(rs + v)             # 32-bit lanes, as in _block_moments
            col[j] = np.int32(col[j] + v)
        dst[1, i] = rs
        tot += rs
    for j in range(p):
        dst[0, j] = col[j]
    if b < acc.shape[0]:
        for j in range(p):
            acc[b, 0, j] += dst[0, j]
            acc[b, 1, j] += dst[1, j]
    return tot


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


def _rows_int16_narrow_impl(frame, r0, c0, p, w0, w1):
    # (w0 . block, w1 . block) as _rows_int16 gives them, for a block whose pixel sum is at
    # most 65535: then every partial sum is within 32767 x 65535 < 2^31, so 32-bit lanes
    # hold it exactly (the same integers; a full frame's two rows 0.32 -> 0.27 ms)
    a0 = np.int32(0)
    a1 = np.int32(0)
    for i in range(p):
        row = frame[r0 + i, c0:c0 + p]
        o = i * p
        for j in range(p):
            x = np.int32(row[j])
            a0 = np.int32(a0 + np.int32(np.int32(w0[o + j]) * x))
            a1 = np.int32(a1 + np.int32(np.int32(w1[o + j]) * x))
    return a0, a1


def _add_counts_impl(acc, counts):
    # acc (N,) uint32 += counts (N,) uint8/uint16: a flat loop the compiler vectorises
    # (numpy's add with a cast runs its buffered casting loop: twice as long)
    for k in range(counts.shape[0]):
        acc[k] += counts[k]


def _block_rows_impl(frame, origins, p, out):
    # out (n, p*p) float32: each valid block's counts, row-major, cast as they are read
    for b in range(origins.shape[0]):
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
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
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
        _block_sums(frame, origins[b, 0], origins[b, 1], p, col, out[b], acc, b)


if _jit.COMPILED:
    _prefetch_block = _jit.numba.njit(cache=True, nogil=True, inline="always")(_prefetch_block_impl)
    _block_moments = _jit.numba.njit(cache=True, nogil=True, inline="always")(_block_moments_impl)
    _cog_moments = _jit.numba.njit(cache=True, nogil=True)(_cog_moments_impl)
    _block_sums = _jit.numba.njit(cache=True, nogil=True, inline="always")(_block_sums_impl)
    _rows_int16 = _jit.numba.njit(cache=True, nogil=True, inline="always")(_rows_int16_impl)
    _rows_int16_narrow = _jit.numba.njit(cache=True, nogil=True, inline="always")(
        _rows_int16_narrow_impl)
    _add_counts = _jit.numba.njit(cache=True, nogil=True)(_add_counts_impl)
    _block_rows = _jit.numba.njit(cache=True, nogil=True)(_block_rows_impl)
    _block_marginals = _jit.numba.njit(cache=True, nogil=True)(_block_marginals_impl)


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


def add_counts(acc: np.ndarray, counts: np.ndarray) -> bool:
    """``acc += counts`` for a uint32 ``acc`` and uint8/uint16 ``counts`` of one shape, both
    C-contiguous (a detector frame into the pupil calibration's accumulator: 0.07 ms for
    960 x 960 against numpy's 0.16 ms). Returns False, adding nothing, where that does not
    hold (or numba is missing): then the caller adds with numpy."""
    if not (_jit.enabled() and acc.dtype == np.uint32 and counts.dtype in (np.uint8, np.uint16)
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
