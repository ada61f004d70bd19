"""Compiled single-pass kernels over a whole detector frame, read in place.

numpy needs several passes over a 960 x 960 uint16 frame to centroid it (the block gather or
a cast to float, then the products); these numba kernels read each valid block's pixels once,
straight from the frame (a shared-memory view works: no copy, no float frame), and accumulate
in registers. Outside the pupil nothing is read. One module per estimator family:

- :mod:`.blocks`: where the valid blocks start (:func:`block_origins`, :func:`fits`), and the
  sums every estimator starts from: :func:`cog_moments` ``(n, 3)`` [total, sum v (x - c),
  sum v (y - c)] per valid block, exact integer sums for integer frames (what ``rows @ [1,
  x, y]`` gives in float); :func:`block_marginals`, each block's row and column sums (the
  reference-reading network's input on a polar detector); :func:`add_counts`, the pupil
  calibration's frame sum.
- :mod:`.filters`: :func:`block_contract`, ``(n, k)`` per-block weights times pixels (a CMF
  filter ``[R; 1]`` of ``(n, k, p*p)``); :func:`filter_flux`, the CMF's ``R`` ``(n, 2,
  p*p)`` plus each block's pixel sum (the flux), 2/3 of the weight traffic of ``[R; 1]``;
  :func:`grid_filter`, the grid of filters (``cmf``'s default); at a refit,
  :func:`position_filters`, one grid position's filters from its render and derivatives
  (:func:`central_differences` of renders, or a renderer's own; :func:`separable_filters`:
  from separable spots' lines and cores).
- :mod:`.ml`: :func:`ml_search`, the ML estimator's marginals, calibrated-CoG start and hill
  climb on its likelihood tables, one pass over each block.
- :mod:`.corr`: :func:`corr_peak`, the correlation centroider's map at the 3 x 3 whole lags
  around its peak (found from the CoG, then climbed), and the peak fit, instead of the FFT map.
- :mod:`.bins`: the reference-reading networks' bins along e (:func:`block_bins`,
  :func:`grid_bins`), first layer (:func:`hyper_contract`) and the steps after them.
- :mod:`.response`: :func:`invert_response`, the linearisation's per-subaperture inversion
  of a 2-D Chebyshev response (:mod:`..linearize`).

numba is optional (the ``fast`` extra): :data:`AVAILABLE` says whether these run; callers
keep their numpy path for when it is False. Shapes: frames ``(G*p, G*p)``; ``origins``
``(n, 2)`` int64 (row, column) of each valid block's first pixel, in the contract's order.
"""

from __future__ import annotations

import numpy as np

from . import _jit
#: whether the compiled passes run (numba is installed); every wrapper reads it at each call
AVAILABLE = _jit.COMPILED
from .bins import (GRID_SLOTS, bins_shifts, block_bins, grid_bins, hyper_contract,
                   hyper_contract_moved, response_inverse)
from .blocks import (add_counts, block_marginals, block_origins, block_rows, cog_moments, fits,
                     origins, quantize, stack_origins, stack_view)
from .corr import CORR_PAD, corr_peak, corr_rows, lags_around_zero
from .filters import (block_contract, central_differences, filter_flux, grid_filter,
                      position_filters, separable_filters)
from .ml import ml_search
from .response import invert_response

__all__ = ["AVAILABLE", "CORR_PAD", "GRID_SLOTS", "add_counts", "bins_shifts", "block_bins",
           "block_contract", "block_marginals", "block_origins", "block_rows",
           "central_differences", "cog_moments", "corr_peak", "corr_rows", "filter_flux", "fits",
           "grid_bins", "grid_filter", "hyper_contract", "hyper_contract_moved", "invert_response",
           "lags_around_zero", "ml_search", "origins", "position_filters", "quantize",
           "response_inverse", "separable_filters", "stack_origins", "stack_view", "warm_up"]

_warm = False


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels now, once per process, so the first
    frame of a running graph does not pay for it (~0.5 s). Each frame kernel is warmed on a
    writable and on a read-only frame: shared-memory frames are read-only views, another
    signature for numba (compiled on a live node's first frame, that held it ~0.2 s)."""
    global _warm
    if _warm or not _jit.enabled():
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
    img = np.ones((1, 4, 4))
    position_filters(img, img, img, 1.0, 1.0)
    position_filters(*(np.ones((1, 6, 6))[:, 1:5, 1:5],) * 3, 1.0, 1.0)   # canvas crops
    separable_filters(np.ones((5, 1, 4)), np.ones((5, 1, 4)), np.ones(1), 0.01, 1.0, 1.0)
    _warm = True
