"""The ML estimator's pass (:mod:`..ml`): marginals, calibrated-CoG start and hill climb on
its likelihood tables, one pass over each block.
"""

from __future__ import annotations

import numpy as np

from . import _jit


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
        _prefetch_block(frame, origins, b + FRAME_AHEAD, p)
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


_NO_ACC = np.zeros((0, 2, 1))


if _jit.COMPILED:
    from .blocks import FRAME_AHEAD, _block_sums, _prefetch_block
    # the marginals are exact integers in float32 (at most 16 x 65535 = 1.05e6 < 2^24)
    _ml_line = _jit.numba.njit(cache=True, nogil=True, fastmath=True, inline="always")(_ml_line_impl)
    _ml_search = _jit.numba.njit(cache=True, nogil=True)(_ml_search_impl)


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
