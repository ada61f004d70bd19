"""Detector model: photon (Poisson) noise, background, read noise, counts.

Units: counts are photo-electrons (gain 1 e-/ADU). ``images`` are photon-normalised
spots: pixel values are the fraction of a subaperture's photons expected in the pixel,
as :mod:`lgs_wfs_ros.optics.spots` makes them (each image sums to ``1 - truncated``).
With ``photons = N`` the expected count in a pixel is ``N * image``, so ``N`` is the
number of photons a subaperture would detect with an unbounded field: with truncation
the field receives ``N (1 - truncated)`` on average. Pass ``per_field=True`` to make ``N``
the expected count inside the field instead (each image is divided by its sum first).

Speed (docs/simulator.md): ``numpy``'s Poisson sampler costs ~35 ns a pixel whatever
its mean, so with no background only the pixels whose expected count exceeds
``POISSON_FLOOR`` (1e-9 photons) are drawn; the others are 0. The photons ignored that
way are below ``POISSON_FLOOR`` times the number of such pixels (< 1e-3 photon per
full frame), far below anything measurable; every drawn pixel is an exact Poisson draw.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

try:                                   # optional: the 'fast' extra (compiled Poisson noise)
    import numba
except ImportError:                    # pragma: no cover - exercised where it is absent
    numba = None

POISSON_FLOOR = 1e-9      # expected photons below which a pixel is not drawn (background 0)
UINT16_MAX = 65535
DTYPES = ("uint16", "float32", "float64")


def _photon_map(images, photons, per_field: bool) -> np.ndarray:
    img = np.asarray(images, dtype=float)
    if img.ndim < 2:
        raise ValueError(f"images must be (..., p, p), got shape {img.shape}")
    if img.size and not (img.min() >= 0 and np.isfinite(img.max())):   # NaN fails both
        raise ValueError("images must be finite and >= 0")
    ph = np.asarray(photons, dtype=float)
    if not np.all(np.isfinite(ph)) or np.any(ph < 0):
        raise ValueError("photons must be finite and >= 0")
    if ph.ndim > img.ndim - 2 or ph.shape != img.shape[:ph.ndim]:
        raise ValueError(f"photons must be a scalar or have the leading shape of images "
                         f"{img.shape[:-2]}, got {ph.shape}")
    ph = ph.reshape(ph.shape + (1,) * (img.ndim - ph.ndim))
    if per_field:
        total = img.sum(axis=(-2, -1), keepdims=True)
        if np.any(total <= 0):
            raise ValueError("per_field=True needs every image to hold some light")
        return img * (ph / total)
    return img * ph


DELTA = 0.125             # table grid: Poisson(m) = Poisson(c) + Poisson(m - c), c = DELTA floor(m / DELTA)
LAM_MAX = 128.0           # tabulated inversion below this mean, Hormann's PTRS above
GUIDE_BITS = 7            # 128 guide entries per grid value (uint8): the search starts 0 short 95 %
_NGRID = int(LAM_MAX / DELTA)
_INV_DELTA = 1.0 / DELTA
_ONE = 1 << 53            # uniforms are integers w in [0, 2^53): u = w / 2^53


def _seed_state(seed):
    """A xorshift64* state from an int seed (compiled code only)."""
    return np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) | np.uint64(1)


_INV_K = 1.0 / np.arange(1.0, 1001.0)   # 1/k for the search (a multiply instead of a divide)
_LOG_FACT = np.array([math.lgamma(k + 1.0) for k in range(4096)])   # log k! for PTRS


@lru_cache(maxsize=1)
def poisson_tables():
    """The inversion tables of ``Poisson(c)`` for every grid mean ``c = g DELTA``,
    ``g = 0 .. LAM_MAX / DELTA - 1``, built once (~50 ms) in exact integer arithmetic:

    * ``thr`` (uint64, flat): ``thr[start[g] + k] = ceil(2^53 F_c(k))``, ``F_c`` the CDF
      (``exp(-c)`` correctly rounded to 100 digits by :mod:`decimal`, the terms
      ``c^k / k! exp(-c)`` in 240-bit fixed point, each rounded down: every threshold is
      exact unless ``2^53 F_c(k)`` lies within ~1e-50 of an integer). A uniform integer
      ``w`` in ``[0, 2^53)`` draws the smallest ``k`` with ``w < thr[start[g] + k]``: exact
      inversion of the 53-bit uniform. Each row ends at the first ``k`` whose threshold
      is ``2^53`` (``1 - F_c(k) <= 2^-53``: no uniform goes past it).
    * ``hi``, ``lo`` (uint32): ``thr``'s top 32 bits (``2^32 - 1`` for ``2^53``) and its low
      21 bits, what the search reads: ``w >= thr`` iff ``w >> 21 > hi``, or ``w >> 21 ==
      hi`` and ``w & (2^21 - 1) >= lo`` (``lo`` is read only on a tie of the top bits,
      ~2^-32 of the comparisons): half the cache footprint of ``thr``, and each array under
      numba's 1 MB limit for constants that can be cached.
    * ``guide`` (uint8, ``(NGRID << GUIDE_BITS,)``): for the top ``GUIDE_BITS`` bits ``j``
      of ``w``, the smallest ``k`` with ``thr > j 2^(53 - GUIDE_BITS)``: where the search
      starts (no smaller ``k`` can be the answer).
    * ``start`` (int64, ``(NGRID,)``): the flat index of ``k = 0`` of each row.
    """
    from decimal import Decimal, localcontext

    frac = 240
    shift = frac - 53
    thr, start = [], []
    step = int(round(1.0 / DELTA))
    with localcontext() as ctx:
        ctx.prec = 100
        one = Decimal(2) ** frac                                      # exact (73 digits)
        for g in range(_NGRID):
            start.append(len(thr))
            term = int((-Decimal(g) / step).exp() * one)              # exp(-c) 2^frac, floor
            s = term
            k = 0
            while True:
                t = -((-s) >> shift)                                  # ceil(s / 2^shift)
                if t >= _ONE:
                    thr.append(_ONE)
                    break
                thr.append(t)
                k += 1
                term = term * g // (step * k)                         # c^k / k! exp(-c)
                s += term
    thr = np.array(thr, dtype=np.uint64)
    start = np.array(start, dtype=np.int64)
    hi = np.minimum(thr >> np.uint64(21), np.uint64(2**32 - 1)).astype(np.uint32)
    lo = np.where(thr == _ONE, np.uint64(1 << 21), thr & np.uint64((1 << 21) - 1)).astype(np.uint32)
    nb = 1 << GUIDE_BITS
    bucket = np.arange(nb, dtype=np.uint64) << np.uint64(53 - GUIDE_BITS)
    guide = np.empty(_NGRID * nb, dtype=np.uint8)
    ends = np.append(start[1:], thr.size)
    assert np.all(ends - start <= 256)
    for g in range(_NGRID):
        guide[g * nb:(g + 1) * nb] = np.searchsorted(thr[start[g]:ends[g]], bucket, side="right")
    for a in (thr, hi, lo, guide, start):
        a.setflags(write=False)
    return thr, hi, lo, guide, start


def _bits(x):
    """xorshift64*: ``(w, new state)``, ``w`` a uniform integer in ``[0, 2^53)``."""
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    return (x * np.uint64(0x2545F4914F6CDD1D)) >> np.uint64(11), x


def _uniform(x):
    """xorshift64*: ``(u in [0, 1) with 53 bits, new state)``."""
    w, x = _bits(x)
    return np.float64(w) * (1.0 / 9007199254740992.0), x


def _ptrs(m, x):
    """Hormann's transformed rejection (PTRS, numpy's algorithm for large means)."""
    slam = math.sqrt(m)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    vr = 0.9277 - 3.6224 / (b - 2.0)
    while True:
        u, x = _uniform(x)
        v, x = _uniform(x)
        u -= 0.5
        us = 0.5 - abs(u)
        k = math.floor((2.0 * a / us + b) * u + m + 0.43)
        if us >= 0.07 and v <= vr:
            return np.int64(k), x
        if k < 0 or (us < 0.013 and v > us):
            continue
        inv_alpha = 1.1239 + 1.1328 / (b - 3.4)
        lf = _LOG_FACT[k] if k < _LOG_FACT.size else math.lgamma(k + 1.0)
        if math.log(v * inv_alpha / (a / (us * us) + b)) <= -m + k * math.log(m) - lf:
            return np.int64(k), x


def _small(r, x):
    """Exact ``Poisson(r)`` for a small ``r >= 0`` by sequential inversion: ``u <= 1 - r``
    implies ``u <= exp(-r)``, so most draws are 0 without an exp."""
    u, x = _uniform(x)
    if u <= 1.0 - r:
        return np.int64(0), x
    p = math.exp(-r)
    f = p
    k = 0
    while u > f and k < 1000:
        p *= r * _INV_K[k]
        k += 1
        f += p
    return np.int64(k), x


def _draw(m, x):
    """One exact ``Poisson(m)`` draw (``m > 0``) and the new xorshift64* state ``x``
    (the tables: :func:`poisson_tables`, compiled in as constants). Below ``LAM_MAX``, ``m = c + r`` with
    ``c = DELTA floor(m / DELTA)``: ``Poisson(c)`` by inversion of one 53-bit uniform
    against the exact table of ``c`` (a guide-table start, a short search), plus
    ``Poisson(r)``, ``r < DELTA``, by :func:`_small` (the sum of independent Poisson draws
    is Poisson of the summed means: exact). Above ``LAM_MAX``: PTRS."""
    if m >= LAM_MAX:
        return _ptrs(m, x)
    k = np.int64(0)
    g = np.int64(m * _INV_DELTA)                     # floor (m > 0)
    if g > 0:
        w, x = _bits(x)
        s = _START[g]
        i = s + np.int64(_GUIDE[(g << GUIDE_BITS) + np.int64(w >> np.uint64(53 - GUIDE_BITS))])
        wh = w >> np.uint64(21)
        while wh > np.uint64(_HI[i]) or (wh == np.uint64(_HI[i]) and
                                         (w & np.uint64(0x1FFFFF)) >= np.uint64(_LO[i])):
            i += 1
        k = i - s
        m -= g * DELTA                               # exact: DELTA a power of 2, m < 2 g DELTA
    j, x = _small(m, x)
    return k + j, x


def _poisson_run(lam, n, floor, x, d, out):
    """Compiled: ``out[i] ~ Poisson(lam[i])`` for ``i < n`` (0 where ``lam <= floor``) from
    the xorshift64* state ``x`` and the small-mean process's distance ``d`` to its next
    event (``d < 0``: not started); returns the new ``(x, d)``: consecutive calls draw
    exactly what one call over the concatenated means would. One tight loop (the fused frame
    kernels batch their expected counts and call it: the draws inside the rendering loop
    cost ~1 ms more a full frame).

    Means below ``DELTA`` (most of a frame's drawn pixels) are the consecutive intervals of
    one unit-rate Poisson process: ``d`` is the distance to its next event (exponential,
    ``-log(1 - u)``), each such pixel takes ``d -= lam`` and counts the events that fall
    in its interval. The counts of a Poisson process in disjoint intervals are independent
    Poisson draws of the intervals' lengths: exact, with no uniform for a pixel that gets
    no photon (one uniform and one log a photon instead). Larger means: :func:`_draw`."""
    if d < 0.0:
        u, x = _uniform(x)
        d = -math.log(1.0 - u)
    for i in range(n):
        m = lam[i]
        v = np.int64(0)
        if m <= floor:
            pass
        elif m >= DELTA:
            v, x = _draw(m, x)
        else:
            d -= m
            while d < 0.0:
                v += 1
                u, x = _uniform(x)
                d -= math.log(1.0 - u)
        out[i] = v
    return x, d


def _poisson_fill(lam, floor, seed, out):
    """Compiled: ``out[i] ~ Poisson(lam[i])`` (0 where ``lam <= floor``), see :func:`_draw`."""
    _poisson_run(lam, lam.size, floor, _seed_state(seed), -1.0, out)


if numba is not None:
    # Global arrays are frozen into the compiled code as constants: no reference counting
    # in the per-pixel loops (passing the tables as arguments to the inlined draw costs
    # ~12 ns a pixel in increfs/decrefs). Built at import (~40 ms) for the compiler.
    _, _HI, _LO, _GUIDE, _START = poisson_tables()
    _jit_inline = numba.njit(cache=True, nogil=True, inline="always")
    _seed_state = numba.njit(cache=True, nogil=True)(_seed_state)
    _bits = _jit_inline(_bits)
    _uniform = _jit_inline(_uniform)
    _ptrs = _jit_inline(_ptrs)
    _small = _jit_inline(_small)
    _draw = _jit_inline(_draw)
    _poisson_run = numba.njit(cache=True, nogil=True)(_poisson_run)
_poisson_fast = (numba.njit(cache=True, nogil=True)(_poisson_fill) if numba is not None
                 else None)
FAST_AVAILABLE = _poisson_fast is not None


def poisson(lam: np.ndarray, rng: np.random.Generator, floor: float = 0.0,
            fast: bool = False) -> np.ndarray:
    """Exact Poisson draws of mean ``lam`` (any shape) as int64; pixels with
    ``lam <= floor`` are set to 0 without a draw (``floor = 0``: only exact zeros).

    ``fast``: the compiled sampler (numba, seeded from ``rng``: the same seed gives the same
    draws; the same distribution as numpy's, other draws), ~3x cheaper on a full pupil;
    numpy's where numba is absent."""
    if fast and FAST_AVAILABLE:
        flat = np.ascontiguousarray(lam, dtype=np.float64).reshape(-1)
        out = np.empty(flat.size, dtype=np.int64)
        _poisson_fast(flat, float(floor), int(rng.integers(2**31 - 1)), out)
        return out.reshape(np.shape(lam))
    flat = lam.reshape(-1)
    idx = np.flatnonzero(flat > floor)
    out = np.zeros(flat.size, dtype=np.int64)
    if idx.size == flat.size:
        return rng.poisson(lam).astype(np.int64, copy=False)
    out[idx] = rng.poisson(flat[idx])
    return out.reshape(lam.shape)


def expose(images, photons, rng: np.random.Generator | None = None, read_noise_e: float = 0.0,
           background_e: float = 0.0, subtract_background: bool = True, dtype: str = "uint16",
           noise_free: bool = False, per_field: bool = False, return_clipped: bool = False,
           fast: bool = False):
    """Turn photon-normalised images into detector counts.

    Args:
        images: ``(..., p, p)`` expected fraction of a subaperture's photons per pixel.
        photons: expected photons per subaperture (scalar or the leading shape of images).
        rng: ``numpy.random.Generator`` (required unless ``noise_free``).
        read_noise_e: Gaussian read noise rms per pixel, e-.
        background_e: expected background per pixel, e- (Poisson, like the signal).
        subtract_background: subtract the expected background (before rounding).
        dtype: ``"uint16"`` (rounded, clipped to 0..65535), ``"float32"`` or ``"float64"``.
        noise_free: return the expected counts (no random draw).
        per_field: ``photons`` is the expected count inside the field (see module doc).
        return_clipped: also return the number of pixels clipped at 65535 (saturated) and
            at 0 (uint16 only; both 0 for float output) as a dict.
        fast: compiled Poisson draws (:func:`poisson`), same distribution, other draws.
    Returns:
        ``counts`` of shape ``images.shape`` and the requested dtype (a new array; inputs
        are never modified), or ``(counts, {"saturated": int, "negative": int})``.
    """
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    for name, v in (("read_noise_e", read_noise_e), ("background_e", background_e)):
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    lam = _photon_map(images, photons, per_field)
    if background_e > 0:
        lam = lam + background_e
    if noise_free:
        counts = lam
    else:
        if not isinstance(rng, np.random.Generator):
            raise ValueError("rng must be a numpy.random.Generator unless noise_free=True")
        floor = POISSON_FLOOR if background_e == 0 else 0.0
        counts = poisson(lam, rng, floor, fast)
        integer = read_noise_e == 0 and not (subtract_background and background_e > 0)
        if integer and dtype == "uint16":                 # fast path: no float round trip
            sat = 0
            if counts.size and counts.max() > UINT16_MAX:
                sat = int(np.count_nonzero(counts > UINT16_MAX))
                counts = np.minimum(counts, UINT16_MAX)
            out = counts.astype(np.uint16)
            return (out, {"saturated": sat, "negative": 0}) if return_clipped else out
        counts = counts.astype(float)
        if read_noise_e > 0:
            counts += rng.normal(0.0, read_noise_e, size=counts.shape)
    if subtract_background and background_e > 0:
        counts = counts - background_e
    clipped = {"saturated": 0, "negative": 0}
    if dtype == "uint16":
        counts = np.rint(counts)
        clipped["saturated"] = int(np.count_nonzero(counts > UINT16_MAX))
        clipped["negative"] = int(np.count_nonzero(counts < 0))
        counts = np.clip(counts, 0, UINT16_MAX).astype(np.uint16)
    else:
        counts = np.asarray(counts, dtype=dtype)
    return (counts, clipped) if return_clipped else counts


__all__ = ["expose", "poisson", "POISSON_FLOOR", "UINT16_MAX"]
