"""Compiled single-pass kernels over a whole detector frame, read in place.

numpy needs several passes over a 960 x 960 uint16 frame to centroid it (the block gather or
a cast to float, then the products); these numba kernels read each valid block's pixels once,
straight from the frame (a shared-memory view works: no copy, no float frame), and accumulate
in registers. Outside the pupil nothing is read.

- :func:`cog_moments`: ``(n, 3)`` [total, sum v (x - c), sum v (y - c)] per valid block,
  exact integer sums for integer frames (what ``rows @ [1, x, y]`` gives in float).
- :func:`block_contract`: ``(n, k)`` per-block weights times pixels (a CMF filter
  ``[R; 1]`` of ``(n, k, p*p)``), float32 weights times pixels summed in float64.

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


def _cog_moments_impl(frame, origins, p, centre, out):
    # int32 per row: at most 65535 p (p - 1) / 2 (7.9 M for p = 16; fits up to p = 255)
    n = origins.shape[0]
    for b in range(n):
        r0 = origins[b, 0]
        c0 = origins[b, 1]
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


if AVAILABLE:
    _cog_moments = numba.njit(cache=True, nogil=True)(_cog_moments_impl)
    _block_contract = numba.njit(cache=True, nogil=True, fastmath=True)(_block_contract_impl)


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


_warm = False


def warm_up() -> None:
    """Compile (or load from numba's cache) both kernels now, once per process, so the first
    frame of a running graph does not pay for it (~0.5 s)."""
    global _warm
    if _warm or not AVAILABLE:
        return
    frame = np.zeros((4, 4), np.uint16)
    o = np.zeros((1, 2), np.int64)
    cog_moments(frame, o, 4, 1.5)
    block_contract(frame, o, np.zeros((1, 3, 16), np.float32))
    _warm = True
