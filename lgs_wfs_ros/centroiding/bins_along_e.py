"""A block's light in 1 px bins along its elongation, each pixel split by its overlap.

On a polar detector the elongation ``e`` runs along the block's pixel columns, and the
column sums are the light in 1 px bins along ``e``: what the marginal networks
(``ann_conv``) and ``ml`` read. On a cartesian detector ``e`` points anywhere. Here each
pixel (a unit square) is projected onto ``e``: its footprint along ``e`` is the
convolution of two boxes of widths ``|e_x|`` and ``|e_y|`` (a trapezoid, at most sqrt(2)
px wide), and its count is split between the ``p`` bins ``[k - p/2, k - p/2 + 1)`` px
from the block centre (``k = 0..p-1``) by the share of that footprint in each. Light
beyond +-p/2 px along ``e`` (a diagonal spot's far corners) is dropped, as a polar field
drops it. On a polar block (``e = (1, 0)``) the bins are the column sums exactly.

A cartesian block reaches ``p/2 (|e_x| + |e_y|)`` px along ``e`` (11.3 px for a diagonal
one), further than ``p`` bins. The window of bins may then move along ``e`` by a whole
number of pixels, ``o``, to where the light is (:func:`window_offsets`, from a reference
image): bins ``[k - p/2 + o, k - p/2 + o + 1)``. Spots far off centre (a high layer: 3-5 px)
keep their far end; a spot and its reference read through the same window stay comparable.
No shipped model reads moved windows (docs/ann_ref.md "Windows moved to the light").

Such bins keep the block's information along ``e`` (1.00-1.006x its Cramer-Rao bound on
the unseen families, docs/ann_ref.md "What a projection keeps"); whole pixels moved to the
bin of their centre lose 2-6 %. They share pixels, so they are correlated, not Poisson.

Splitting every pixel costs a compiled frame pass three scattered additions a pixel
(~0.9 ms a full frame, ~1.9 ms with sky background). :func:`grid_weights` splits none:
whole pixels summed along the pixel-grid direction ``d`` nearest to ``e`` (columns, rows,
diagonals, anti-diagonals: at most 22.5 deg from ``e``), each sum then spread by its
pixels' footprint over the 1 px bins along ``d``; the network reads the shift along ``d``
and the CoG across ``e`` gives the rest (``ann``'s option ``bins``, a model's
``lgs_wfs.bins_projection``). With projection ``span`` the bins along a diagonal are
sqrt 2 px wide, so that they hold the whole block.
"""

from __future__ import annotations

import numpy as np

from . import kernels

#: pixels of a block whose footprint along e can touch a bin: at most 3 (width <= sqrt 2)
SPAN = 3

#: where a block's window of bins sits: "centred" on the block, or "reference", moved to its
#: reference's light (:func:`window_offsets`); a model declares which in
#: ``lgs_wfs.bins_window``, a training recipe in ``bins_window``
WINDOWS = ("centred", "reference")


def _ramp_integral(x: np.ndarray) -> np.ndarray:
    """``int_-inf^x clip(s, 0, 1) ds``."""
    return np.where(x <= 0, 0.0, np.where(x < 1, 0.5 * x * x, x - 0.5))


def _footprint_cdf(t: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``P(a s1 + b s2 <= t)`` for ``s1, s2`` uniform on (-1/2, 1/2), ``a >= b >= 0``
    (broadcast): the share of a unit pixel's projected footprint below ``t`` px from its
    centre."""
    box = np.clip(t / np.maximum(a, 1e-12) + 0.5, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        hi = (t + b / 2) / a + 0.5
        lo = (t - b / 2) / a + 0.5
        trap = (a / b) * (_ramp_integral(hi) - _ramp_integral(lo))
    return np.where(b > 1e-9, trap, box)


def window_offsets(ref_flat: np.ndarray, e_pixel: np.ndarray) -> np.ndarray:
    """``(n,)`` int32 px: where each block's window of bins along e should sit.

    The light centre along ``e`` of the references ``ref_flat (n, p*p)`` (counts, any
    scale), rounded to a whole pixel and held where the window stays inside the block's
    reach along ``e``, ``p/2 (|e_x| + |e_y|)`` px, to within half a bin: 0 for a block whose
    ``e`` is within 3.7 deg of a pixel axis, +-1 px to 12 deg, +-2 px to 23 deg, +-3 px
    beyond. A block without light gets 0.
    """
    ref = np.nan_to_num(np.asarray(ref_flat, dtype=np.float64), nan=0.0)
    e = np.asarray(e_pixel, dtype=np.float64)
    n, pp = ref.shape
    p = int(round(pp ** 0.5))
    u = _along(e, p)                                                                 # (n, pp)
    tot = ref.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        centre = np.where(tot > 0, (ref * u).sum(axis=1) / np.where(tot > 0, tot, 1.0), 0.0)
    reach = np.floor(0.5 * p * (np.abs(e[:, 0]) + np.abs(e[:, 1])) - 0.5 * p + 0.5)
    return np.clip(np.rint(centre), -reach, reach).astype(np.int32)


def _along(e: np.ndarray, p: int) -> np.ndarray:
    """``(n, p*p)`` px: each pixel centre's position along ``e (n, 2)`` from the block
    centre (row-major pixels)."""
    c = (p - 1) / 2.0
    y, x = np.indices((p, p), dtype=np.float64)
    return (x.ravel() - c)[None, :] * e[:, :1] + (y.ravel() - c)[None, :] * e[:, 1:]


def moved(start: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``start`` of :func:`overlap_weights` for windows moved by ``offset (n,)`` whole px
    along e (:func:`window_offsets`). Moving the bin edges by whole pixels leaves every
    pixel's split unchanged and only renumbers its bins, so the shares ``w`` stay as they
    are."""
    return (np.asarray(start, dtype=np.int32) - np.asarray(offset, dtype=np.int32)[:, None])


def overlap_weights(e_pixel: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's share in the bins along e (windows centred on the blocks; see
    :func:`moved`).

    Args:
        e_pixel: ``(n, 2)`` unit vectors of the elongation in the block's pixel axes (x
            along the columns, y along the rows).
        p: pixels per block side (and bins).

    Returns:
        ``(start, w)``: ``start (n, p*p)`` int32, the first bin a pixel touches (row-major
        pixels, may lie outside ``0..p-1``); ``w (n, p*p, SPAN)`` float32, its shares in
        bins ``start .. start + 2`` (summing to 1; :func:`project` drops the bins outside
        ``0..p-1``).
    """
    e = np.asarray(e_pixel, dtype=np.float64)
    u0 = _along(e, p)                                                                # (n, pp)
    ax, ay = np.abs(e[:, 0]), np.abs(e[:, 1])
    a = np.maximum(ax, ay)[:, None, None]
    b = np.minimum(ax, ay)[:, None, None]
    half = 0.5 * (a[:, :, 0] + b[:, :, 0])                                          # (n, 1)
    start = np.floor(u0 - half + p / 2 + 1e-9).astype(np.int64)                     # (n, pp)
    k = start[..., None] + np.arange(SPAN)                                          # (n, pp, 3)
    lo = k - p / 2 - u0[..., None]                                                  # bin edges, px from the pixel centre
    w = _footprint_cdf(lo + 1.0, a, b) - _footprint_cdf(lo, a, b)
    return start.astype(np.int32), w.astype(np.float32)


#: how a cartesian block's light reaches the bins: "overlap" (each pixel split along e by
#: its footprint), "grid" (whole pixels summed along the pixel-grid direction nearest to
#: e, then 1 px bins along that direction: :func:`grid_weights`) or "span" (the same sums,
#: the bins sqrt 2 px wide along diagonals so that they span the whole block)
PROJECTIONS = ("overlap", "grid", "span")

#: the projections that read whole-pixel sums along the grid (:func:`grid_weights`)
GRID_PROJECTIONS = ("grid", "span")

#: how many whole-pixel sums a bin along d can take a share of (:func:`grid_tables`): sums
#: 1 / sqrt 2 px apart whose footprints are sqrt 2 px wide reach a 1 px bin from 2.4 px (the
#: compiled pass, :func:`.kernels.grid_bins`, unrolls that many)
GRID_SLOTS = kernels.GRID_SLOTS

#: the four pixel-grid directions, block axes: columns, diagonals, rows, anti-diagonals
GRID_DIRECTIONS = np.array([(1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (1.0, -1.0)]) / np.array(
    [1.0, np.sqrt(2.0), 1.0, np.sqrt(2.0)])[:, None]


def grid_direction(e_pixel: np.ndarray) -> np.ndarray:
    """``(n, 2)``: the pixel-grid direction (columns, rows, diagonals or anti-diagonals)
    nearest to each ``e (n, 2)``, signed to point along ``e`` (at most 22.5 deg from it)."""
    e = np.asarray(e_pixel, dtype=np.float64)
    k = np.rint((np.degrees(np.arctan2(e[:, 1], e[:, 0])) % 180.0) / 45.0).astype(int) % 4
    d = GRID_DIRECTIONS[k]
    return np.where(((d * e).sum(axis=1) < 0)[:, None], -d, d)


def grid_weights(e_pixel: np.ndarray, p: int,
                 span: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bins along the pixel-grid direction ``d`` nearest to ``e``: the overlap split of
    :func:`overlap_weights` along ``d`` instead of ``e``. Every pixel of one whole-pixel sum
    along the grid (a column or row sum, box footprint 1 px wide; a diagonal ``i + j`` or
    ``i - j``, triangle footprint sqrt 2 px wide, sums 1 / sqrt 2 px apart) then has the
    same split, so a compiled pass makes these bins from whole-row additions and splits no
    pixel on its own (:func:`grid_tables`). They keep 98-99 % of the block's information
    along e (``benchmarks/projection_information.py``, the shift across e known).

    The bins are 1 px wide. A diagonal reaches ``p / sqrt 2`` px each side of the centre,
    so ``p`` such bins drop its far corners, where a spot far off centre along a diagonal
    (a high layer at the pupil's edge) has light. With ``span`` the bins along a diagonal
    are ``sqrt 2`` px wide (the pitch ``|d_x| + |d_y|``): bin ``k`` takes diagonal ``2k``
    whole and half of each of its neighbours, and the ``p`` bins hold the whole block
    (columns and rows are as without). The bins' positions are then in units of that
    pitch. A network trained on them (recipe ``ann_span``, 2026-11-28) was not better on
    the high layer and worse on the sporadic one: docs/ann_ref.md "Bins that span a
    diagonal block"; no shipped model reads them.

    Returns:
        ``(start, w, u)``: as :func:`overlap_weights` for the bins along ``d``, and ``u =
        d / pitch (n, 2)``: a shift ``s`` (px, block axes) moves the light ``s . u`` bins
        (``u = d``, :func:`grid_direction`, without ``span``).
    """
    d = grid_direction(e_pixel)
    if span:
        d = d / (np.abs(d[:, :1]) + np.abs(d[:, 1:]))
    return (*overlap_weights(d, p), d)


def bins_step(u: np.ndarray) -> np.ndarray:
    """``(n, 2)`` px, block axes: the shift that moves the light one bin along bins of
    direction ``u (n, 2)`` (:func:`grid_weights`' ``u``, or a unit ``e``): ``u / |u|^2``."""
    u = np.asarray(u, dtype=np.float64)
    return u / (u * u).sum(axis=1, keepdims=True)


def grid_code(d: np.ndarray) -> np.ndarray:
    """``(n,)`` int8: which whole-pixel sums give the bins along ``d`` (:func:`grid_direction`):
    0 columns, 1 diagonals ``i + j``, 2 rows, 3 anti-diagonals ``j - i`` (row ``i``, column
    ``j``)."""
    d = np.asarray(d, dtype=np.float64)
    diag = (np.abs(d[:, 0]) > 0.1) & (np.abs(d[:, 1]) > 0.1)
    return np.where(diag, np.where(d[:, 0] * d[:, 1] > 0, 1, 3),
                    np.where(np.abs(d[:, 0]) > 0.5, 0, 2)).astype(np.int8)


def grid_tables(d: np.ndarray, start8: np.ndarray, wq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tables of :func:`.kernels.grid_bins` from a split of :func:`grid_weights` (as
    :func:`quantised` gives it: ``start8 (n, p*p)``, ``wq (n, p*p, 3)``): ``(code (n,)
    int8, sums (n, p, 3) int8, shares (n, p, 3) float32)``: for each bin the (at most
    three) whole-pixel sums it takes a share of, and those shares (0 for an unused slot).
    Every pixel of a sum has the same split, so the bins are those of the pixels' split."""
    n, pp = start8.shape
    p = int(round(pp ** 0.5))
    code = grid_code(d)
    y, x = np.indices((p, p))
    index = np.stack([x, x + y, y, x - y + p - 1]).reshape(4, pp)[code]             # (n, pp)
    nr = 2 * p - 1
    first = np.full((n, nr), -2, dtype=np.int64)          # each sum's first bin and shares
    share = np.zeros((n, nr, SPAN))
    rows = np.arange(n)[:, None]
    first[rows, index] = start8
    share[rows, index] = wq
    sums = np.zeros((n, p, GRID_SLOTS), dtype=np.int8)
    shares = np.zeros((n, p, GRID_SLOTS), dtype=np.float32)
    used = np.zeros((n, p), dtype=np.int64)
    for m in range(nr):                                   # sums in order: slots fill in order
        for s in range(SPAN):
            q = first[:, m] + s
            ok = (q >= 0) & (q < p) & (share[:, m, s] > 0)
            b, qq = np.nonzero(ok)[0], q[ok]
            slot = used[b, qq]
            if (slot >= GRID_SLOTS).any():
                raise ValueError(f"grid_tables: a bin takes more than {GRID_SLOTS} sums")
            sums[b, qq, slot] = m
            shares[b, qq, slot] = share[b, m, s]
            used[b, qq] += 1
    assert 0 <= sums.min() and sums.max() < nr       # the compiled pass indexes with them
    return code, sums, shares


def quantised(start: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shares in 1/255ths, as the compiled frame pass reads them
    (:func:`.kernels.block_bins`).

    Returns:
        ``(start8, shares, wq)``: ``start8 (n, p*p)`` int8 in ``-2..p-1`` (a pixel whose
        three bins all lie outside ``0..p-1`` gets ``-2`` and all its light in bin ``-1``,
        dropped); ``shares (n, p*p, 2)`` uint8, the first and third bins' shares (the
        second gets the rest); ``wq (n, p*p, 3)`` float32, the same split for
        :func:`project` with ``start8``. Data and references projected with the same split
        stay comparable; the rounding moves each pixel's split by at most 1/510 of its
        count.
    """
    p = int(round(start.shape[1] ** 0.5))
    q0 = np.rint(w[..., 0] * 255).astype(np.int32)
    q2 = np.rint(w[..., 2] * 255).astype(np.int32)
    away = (start + SPAN - 1 < 0) | (start > p - 1)
    start8 = np.where(away, -2, start).astype(np.int8)
    q0 = np.where(away, 0, q0)
    q2 = np.where(away, 0, q2)
    wq = np.stack([q0, 255 - q0 - q2, q2], axis=-1).astype(np.float32) / 255
    return start8, np.stack([q0, q2], axis=-1).astype(np.uint8), wq.astype(np.float32)


def project(flat: np.ndarray, start: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(n, p)`` float64: the light of blocks ``flat (n, p*p)`` in their bins along e
    (:func:`overlap_weights`); a NaN pixel makes its block's bins NaN. Once: for many
    projections of one split, keep its :class:`Projector`."""
    return Projector(start, w)(flat)


class Projector:
    """The projection of one split onto the bins as a sparse matrix, for the many
    projections of a refit (the network's reading of each moved reference): built once
    (~20 ms for the full pupil), then each call ~1.5 ms (a bincount over the split: ~23).

    Args:
        start, w: a split (:func:`overlap_weights`, :func:`grid_weights`, :func:`quantised`),
            ``(n, p*p)`` and ``(n, p*p, SPAN)``.
    """

    def __init__(self, start: np.ndarray, w: np.ndarray):
        from scipy import sparse
        n, pp = start.shape
        p = int(round(pp ** 0.5))
        k = start[..., None].astype(np.int64) + np.arange(w.shape[2])                 # (n, pp, 3)
        ok = (k >= 0) & (k < p)
        rows = (k + p * np.arange(n)[:, None, None])[ok]
        cols = np.broadcast_to((np.arange(n * pp).reshape(n, pp))[..., None], k.shape)[ok]
        self.shape = (n, p)
        self.split = (start, w)
        self.matrix = sparse.csr_matrix((np.asarray(w, dtype=np.float64)[ok], (rows, cols)),
                                        shape=(n * p, n * pp))

    def __call__(self, flat: np.ndarray) -> np.ndarray:
        """``(n, p)`` float64: the light of blocks ``flat (n, p*p)`` in their bins; a NaN
        pixel makes its block's bins NaN."""
        flat = np.asarray(flat, dtype=np.float64)
        out = (self.matrix @ flat.ravel()).reshape(self.shape)
        out[~np.isfinite(flat).all(axis=1)] = np.nan
        return out


__all__ = ["GRID_DIRECTIONS", "GRID_PROJECTIONS", "GRID_SLOTS", "PROJECTIONS", "Projector", "SPAN",
           "WINDOWS", "bins_step", "grid_code", "grid_direction", "grid_tables", "grid_weights", "moved", "overlap_weights", "project",
           "quantised", "window_offsets"]
