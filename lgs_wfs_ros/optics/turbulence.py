"""Atmospheric turbulence: phase screens, frozen flow and the per-subaperture G-tilt.

Units and conventions
---------------------
* Phase is in radians at the wavelength ``r0_wavelength_m`` at which r0 is given (500 nm
  by default). The optical path difference is ``OPD = phase * r0_wavelength_m / (2 pi)``
  metres; angles of arrival (OPD gradients) are achromatic, so the observing wavelength
  (589 nm) never enters.
* Spatial frequencies ``k`` are in cycles per metre. The phase power spectrum is von
  Karman, ``Phi(k) = 0.023 r0^(-5/3) (k^2 + 1/L0^2)^(-11/6)`` rad^2 m^2 (``L0 = inf`` is
  Kolmogorov), whose structure function is ``6.88 (r/r0)^(5/3)`` for ``L0 = inf``.
* **Sign**: the spot displacement is ``+grad(OPD)`` averaged over the subaperture, divided
  by the pixel scale: an OPD that increases along +x moves the spot along +x (detector
  axes, ``docs/conventions.md`` section 2: pupil x -> detector x, pupil y -> detector y).
* **G-tilt** of a square subaperture of side ``d`` = mean gradient over the square =
  ``(mean phase on the right edge - mean phase on the left edge) / d`` (and likewise in
  y). On a screen sampled at ``delta = d / m`` the edge means are trapezoid sums of the
  ``m + 1`` samples along each edge: this is exactly the G-tilt of the bilinear interpolant
  of the samples.

Why our own screens, not aotools'
---------------------------------
aotools 1.0.8 was tried first:

* ``ft_sh_phase_screen(r0, N, delta, L0=inf, l0)`` (2 cm pixels, N = 1024, 8 screens) gives
  a structure function 15 % low at 2 cm and 48 % low at 5 m: its FFT cells take the PSD at
  the cell centre, which badly undercounts the steep Kolmogorov spectrum next to k = 0;
  with an int seed it also re-uses the same normal draws for the sub-harmonics and the FFT
  part (pass a Generator). It is not periodic either, so it cannot wrap.
* ``PhaseScreenKolmogorov`` / ``PhaseScreenVonKarman`` (infinite screens) extrude along
  one axis only (the wind would have to follow a screen axis), ``add_row`` copies the whole
  screen (``numpy.append``) per row, and the covariance/SVD set-up for a 30 m pupil at a
  few cm per sample is a ~2000 x 4000 problem: too slow for 800 Hz.

So :class:`PhaseScreen` is a periodic FFT "torus" whose Fourier coefficients carry the
PSD *integrated over their frequency cell* (exact near the origin), plus low-frequency
plane waves evaluated analytically: the 24 torus cells with ``|index| <= 2`` round the
origin and ``levels`` rings of 8 sub-harmonic cells (3x3 subdivision of the centre cell,
Lane et al. 1992 / Johansson & Gavel 1994), each with its frequency drawn inside its cell
with probability proportional to the PSD, so that every second-order statistic
(structure function, tilt variance) is unbiased. ``levels`` is chosen so that the
uncovered centre cell holds < 0.2 % of the G-tilt variance (13 for the default sensor).
:meth:`PhaseScreen.expected_gtilt_variance` gives the model's exact ensemble tilt variance:
within 0.5 % of :func:`gtilt_variance_theory` (Kolmogorov and L0 = 25 m).

Frozen flow
-----------
:class:`FrozenFlow` slides one such screen across the pupil at the wind velocity:
the phase at pupil point ``p`` in frame ``k`` is ``screen(p - v k / f)``, so the tilts of
frame ``k + j`` at ``p`` are those of frame ``k`` at ``p - j v / f``. The screen is sampled
at ``d / 8`` (6.25 cm) by default. The torus part wraps with a documented period
(:attr:`FrozenFlow.period_m`: across the wind >= twice the pupil, 64 m for the default
sensor; along it ``period_m``, 256 m by default = 25.6 s at 10 m/s, 27 MiB with padding);
the analytic low-frequency part does not repeat. Sub-pixel shifts are bilinear (a fixed
linear combination of 4 whole-sample shifts, so the G-tilt stays exact for the
interpolated screen). Tilts for any frame are a pure function of (seed, frame index):
bit-for-bit reproducible, and :meth:`FrozenFlow.tilts_at` gives random access.
Cost: about 0.6 ms per frame for the 2,784 valid subapertures of the default pupil (one
core), independent of how long the run has been going.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import scipy.fft
import scipy.integrate
import scipy.special

from ..sensor import Sensor
from .geometry import layout

KOLMOGOROV_COEFF = 0.023       # PSD coefficient, k in cycles/m
STRUCTURE_COEFF = 6.88         # D(r) = 6.88 (r/r0)^(5/3)

__all__ = [
    "phase_psd", "structure_function_theory", "gtilt_variance_theory", "turbulence_sigma_px",
    "random_displacements", "PhaseScreen", "phase_screen", "FrozenFlow",
]


# --------------------------------------------------------------------------- spectra / theory
def _check_r0_L0(r0_m, L0_m):
    if not (np.isfinite(r0_m) and r0_m > 0):
        raise ValueError(f"r0_m must be a finite number > 0, got {r0_m!r}")
    if not (L0_m > 0):
        raise ValueError(f"L0_m must be > 0 (inf for Kolmogorov), got {L0_m!r}")


def phase_psd(k: np.ndarray, r0_m: float, L0_m: float = math.inf) -> np.ndarray:
    """Von Karman phase power spectrum ``Phi(k)`` in rad^2 m^2.

    Args:
        k: spatial frequency magnitude(s), cycles per metre (any shape).
        r0_m: Fried parameter at the phase's wavelength, metres.
        L0_m: outer scale in metres (``inf``: Kolmogorov, ``Phi(0) = inf``).
    """
    _check_r0_L0(r0_m, L0_m)
    k = np.asarray(k, dtype=float)
    inv_l0_sq = 0.0 if math.isinf(L0_m) else 1.0 / L0_m ** 2
    with np.errstate(divide="ignore"):
        return KOLMOGOROV_COEFF * r0_m ** (-5.0 / 3.0) * (k * k + inv_l0_sq) ** (-11.0 / 6.0)


def structure_function_theory(r_m, r0_m: float, L0_m: float = math.inf) -> np.ndarray:
    """Phase structure function ``D(r)`` in rad^2 for separations ``r_m`` (metres, any shape).

    Kolmogorov: ``6.88 (r/r0)^(5/3)``. Von Karman: ``4 pi int Phi(k) (1 - J0(2 pi k r)) k dk``
    integrated numerically.
    """
    _check_r0_L0(r0_m, L0_m)
    r = np.asarray(r_m, dtype=float)
    if math.isinf(L0_m):
        return STRUCTURE_COEFF * (r / r0_m) ** (5.0 / 3.0)
    out = np.empty(r.shape)
    for idx, rr in np.ndenumerate(r):
        def f(lk, rr=rr):
            k = math.exp(lk)
            return phase_psd(k, r0_m, L0_m) * (1 - scipy.special.j0(2 * math.pi * k * rr)) * k * k
        lo, hi = math.log(1e-6 / L0_m), math.log(200.0 / max(rr, 1e-9))
        val = scipy.integrate.quad(f, lo, hi, limit=400)[0]
        out[idx] = 4 * math.pi * val
    return out


def _square_angular(u: np.ndarray) -> np.ndarray:
    """``int_0^{2pi} cos^2(t) sinc^2(u cos t) sinc^2(u sin t) dt`` (numpy sinc), ``(U,)``.

    Midpoint rule over one quadrant with >= 16 nodes per oscillation of the sincs.
    """
    u = np.asarray(u, dtype=float)
    out = np.empty(u.shape)
    lower = -np.inf
    for n in (64, 256, 1024, 4096, 16384):
        upper = (n - 64) / 16 if n < 16384 else np.inf
        sel = (u > lower) & (u <= upper)
        lower = upper
        if not sel.any():
            continue
        t = (np.arange(n) + 0.5) * (math.pi / 2 / n)       # nodes on [0, pi/2]
        c, s = np.cos(t), np.sin(t)
        uu = u[sel][:, None]
        vals = c * c * np.sinc(uu * c) ** 2 * np.sinc(uu * s) ** 2
        out[sel] = 4 * (math.pi / 2 / n) * vals.sum(axis=1)   # 4 quadrants
    return out


def _circular_angular(u: np.ndarray) -> np.ndarray:
    """``int_0^{2pi} cos^2(t) [2 J1(pi u)/(pi u)]^2 dt``, ``(U,)``."""
    a = np.pi * np.maximum(np.asarray(u, dtype=float), 1e-12)
    airy = 2 * scipy.special.j1(a) / a
    return np.pi * airy * airy


def gtilt_variance_theory(d_m: float, r0_m: float, wavelength_m: float = 500e-9,
                          L0_m: float = math.inf, aperture: str = "square") -> float:
    """Theoretical one-axis G-tilt (mean wavefront gradient) variance, rad^2 of angle.

    ``sigma^2 = lambda0^2 int int Phi(k) kx^2 |F(k)|^2 d^2k`` with ``Phi`` the von Karman
    phase PSD (:func:`phase_psd`) and ``F`` the aperture average: ``sinc(kx d) sinc(ky d)``
    for a square of side ``d`` (the Shack-Hartmann subaperture), ``2 J1(pi k d)/(pi k d)``
    for a circle of diameter ``d``. Integrated numerically: polar coordinates,
    in angle (midpoint), ``scipy.integrate.simpson`` in ``log k`` (relative error ~1e-4).

    For Kolmogorov and a circle this is the classic ``0.170 (lambda/d)^2 (d/r0)^(5/3)`` per
    axis (Z-tilt: 0.182). A square of side ``d`` (27 % more area than the circle of diameter
    ``d``) has a G-tilt variance of ``0.162 (lambda/d)^2 (d/r0)^(5/3)``, 5 % lower.

    Args:
        d_m: subaperture side (square) or diameter (circle), metres.
        r0_m: Fried parameter at ``wavelength_m``, metres.
        wavelength_m: wavelength at which ``r0_m`` is given (the angle is achromatic).
        L0_m: outer scale, metres (``inf``: Kolmogorov).
        aperture: ``"square"`` or ``"circle"``.
    """
    _check_r0_L0(r0_m, L0_m)
    if not (np.isfinite(d_m) and d_m > 0):
        raise ValueError(f"d_m must be a finite number > 0, got {d_m!r}")
    if not (np.isfinite(wavelength_m) and wavelength_m > 0):
        raise ValueError(f"wavelength_m must be a finite number > 0, got {wavelength_m!r}")
    if aperture not in ("square", "circle"):
        raise ValueError(f"aperture must be 'square' or 'circle', got {aperture!r}")
    return _gtilt_dimensionless(aperture, 0.0 if math.isinf(L0_m) else (d_m / L0_m) ** 2) * (
        KOLMOGOROV_COEFF * wavelength_m ** 2 * r0_m ** (-5.0 / 3.0) * d_m ** (-1.0 / 3.0))


@lru_cache(maxsize=64)
def _gtilt_dimensionless(aperture: str, eps: float) -> float:
    """``int_0^inf u^3 (u^2 + eps)^(-11/6) A(u) du`` with ``u = k d`` (cached)."""
    angular = _square_angular if aperture == "square" else _circular_angular
    lu = np.linspace(math.log(1e-10), math.log(512.0), 6001)
    u = np.exp(lu)
    f = u ** 4 * (u * u + eps) ** (-11.0 / 6.0) * angular(u)     # d(log u) integrand
    total = scipy.integrate.simpson(f, x=lu)
    total += f[0] / (4.0 / 3.0 if eps == 0 else 4.0)             # u < 1e-10 (power law)
    # Tail u > 512: A(u) ~ c/u^2, integrand ~ c u^(-8/3) -> c (3/5) u^(-5/3).
    c_tail = float(angular(np.array([512.0]))[0]) * 512.0 ** 2
    total += c_tail * 0.6 * 512.0 ** (-5.0 / 3.0)
    return float(total)


def turbulence_sigma_px(sensor: Sensor) -> float:
    """Theoretical rms one-axis spot displacement (pixels) from the sensor's turbulence."""
    var = gtilt_variance_theory(sensor.subap_pitch_m, sensor.r0_m, sensor.r0_wavelength_m,
                                sensor.outer_scale_m, "square")
    return math.sqrt(var) / sensor.pixel_scale_rad


def random_displacements(rng, n: int, sigma_px: float) -> np.ndarray:
    """``(n, 2)`` normal random spot positions (x, y) in pixels, the paper's training draw.

    Args:
        rng: a ``numpy.random.Generator`` (advanced) or an int seed.
        n: number of positions (>= 0).
        sigma_px: standard deviation per axis, pixels (>= 0).
    """
    if not (isinstance(n, (int, np.integer)) and n >= 0):
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    if not (np.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma_px!r}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    return gen.normal(0.0, float(sigma_px), size=(int(n), 2))


# --------------------------------------------------------------------------- screens
def _seed_sequence(seed) -> np.random.SeedSequence:
    """A SeedSequence from an int, a SeedSequence or a Generator (which is advanced once)."""
    if isinstance(seed, np.random.SeedSequence):
        return seed
    if isinstance(seed, np.random.Generator):
        return np.random.SeedSequence(seed.integers(0, 2 ** 63, size=4).tolist())
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0:
        return np.random.SeedSequence(int(seed))
    raise ValueError(f"seed must be an int >= 0 or a numpy Generator, got {seed!r}")


def _cell_psd(kx_c, ky_c, dkx, dky, r0_m, L0_m, sub: int = 16):
    """PSD integrated over rectangular cells, and the sub-cell weights.

    Args:
        kx_c, ky_c: ``(C,)`` cell centres, cycles/m. dkx, dky: cell sizes.
    Returns:
        ``(var (C,), w (C, sub*sub), offsets (sub*sub, 2))``: the integral of Phi over each cell
        (rad^2), the normalised sub-cell weights, and the sub-cell centre offsets (cycles/m).
    """
    s = (np.arange(sub) + 0.5) / sub - 0.5
    ox, oy = np.meshgrid(s * dkx, s * dky)
    offsets = np.stack([ox.ravel(), oy.ravel()], axis=1)
    kx = np.asarray(kx_c)[:, None] + offsets[None, :, 0]
    ky = np.asarray(ky_c)[:, None] + offsets[None, :, 1]
    phi = phase_psd(np.hypot(kx, ky), r0_m, L0_m) * (dkx * dky / sub ** 2)
    var = phi.sum(axis=1)
    return var, phi / var[:, None], offsets


def _torus_variance(shape, pixel_m, r0_m, L0_m, analytic: int = 2, inner: int = 8):
    """``(ny, nx//2 + 1)`` float32 variance (rad^2) of each rfft-layout Fourier cell.

    Each cell carries the PSD integrated over it (exact integral for cells within ``inner``
    of the origin, centre value beyond, error < 1 % there); cells with
    ``|a|, |b| <= analytic`` (frequency indices) are zero: they are analytic modes.
    Also returns ``(ky, kx)`` cycles/m, broadcastable.
    """
    ny, nx = shape
    dky, dkx = 1.0 / (ny * pixel_m), 1.0 / (nx * pixel_m)
    ky = np.fft.fftfreq(ny, pixel_m).astype(np.float32)[:, None]
    kx = np.fft.rfftfreq(nx, pixel_m).astype(np.float32)[None, :]
    var = phase_psd(np.sqrt(ky * ky + kx * kx), r0_m, L0_m).astype(np.float32)
    var *= np.float32(dkx * dky)
    ia = np.arange(-inner, inner + 1)
    ib = np.arange(0, inner + 1)
    ia = ia[np.abs(ia) < ny // 2]
    ib = ib[ib < nx // 2]
    A, B = np.meshgrid(ia, ib, indexing="ij")
    cells, _, _ = _cell_psd(B.ravel() * dkx, A.ravel() * dky, dkx, dky, r0_m, L0_m)
    var[A.ravel() % ny, B.ravel()] = cells
    var[np.ix_(np.arange(-analytic, analytic + 1) % ny, np.arange(analytic + 1))] = 0.0
    return var, ky, kx


def _torus(shape, pixel_m, r0_m, L0_m, rng, analytic: int = 2) -> np.ndarray:
    """Periodic FFT phase screen ``(ny, nx)`` float32 rad, without the cells round k = 0."""
    ny, nx = shape
    var, _, _ = _torus_variance(shape, pixel_m, r0_m, L0_m, analytic)
    # Columns kx = 0 and Nyquist stand for +-ky pairs whose conjugates irfft drops: x2 variance.
    var[:, 0] *= 2
    if nx % 2 == 0:
        var[:, -1] *= 2
    amp = np.sqrt(var * np.float32(0.5))
    coef = np.empty(var.shape, dtype=np.complex64)
    coef.real = rng.standard_normal(var.shape, dtype=np.float32) * amp
    coef.imag = rng.standard_normal(var.shape, dtype=np.float32) * amp
    del var, amp
    field = scipy.fft.irfft2(coef, s=(ny, nx), workers=1, overwrite_x=True)
    field *= np.float32(ny * nx)
    return np.ascontiguousarray(field, dtype=np.float32)


def _default_levels(cell_m: float, r0_m: float, L0_m: float, scale_m: float,
                    tol: float = 2e-3) -> int:
    """Sub-harmonic levels so the uncovered centre cell holds < ``tol`` of the variance.

    The centre cell left after ``p`` levels is a square of side ``w = 1 / (cell_m 3^p)``;
    its gradient power is bounded by the Kolmogorov disk of the same area (radius
    ``rho = w / sqrt(pi)``): ``int Phi kx^2 d^2k = 3 pi 0.023 r0^(-5/3) rho^(1/3)``, compared
    with the G-tilt of a square of side ``scale_m`` (the largest scale the caller cares
    about: the subaperture for tilts, the screen for structure functions).
    """
    ref = gtilt_variance_theory(scale_m, r0_m, 1.0, L0_m)        # int Phi kx^2 S d^2k
    for p in range(0, 40):
        rho = 1.0 / (cell_m * 3 ** p) / math.sqrt(math.pi)
        lost = 3 * math.pi * KOLMOGOROV_COEFF * r0_m ** (-5 / 3) * rho ** (1 / 3)
        if not math.isinf(L0_m):
            lost *= min(1.0, (rho * L0_m) ** (5.0 / 3.0))     # von Karman flattens below 1/L0
        if lost < tol * ref:
            return p
    return 40


class PhaseScreen:
    """A Kolmogorov / von Karman phase screen: periodic FFT torus + analytic low frequencies.

    The phase (rad at the wavelength of r0) at a point ``(x, y)`` metres is
    ``torus(x mod Lx, y mod Ly)`` (bilinear between samples) plus
    ``Re sum_j c_j exp(2 pi i k_j . (x, y))`` over the low-frequency modes.

    Attributes:
        torus: ``(ny, nx)`` float32 samples (rad), read-only; sample ``[a, b]`` is at
            ``(x, y) = (b, a) * pixel_m``.
        mode_k: ``(K, 2)`` mode frequencies (kx, ky), cycles/m.
        mode_c: ``(K,)`` complex mode amplitudes, rad.
    """

    def __init__(self, shape, pixel_m: float, r0_m: float, L0_m: float = math.inf,
                 seed=0, levels: int | None = None, scale_m: float | None = None,
                 analytic: int = 2):
        """
        Args:
            shape: ``(ny, nx)`` torus samples (each >= 8; powers of 2 are fastest).
            pixel_m: sample spacing, metres.
            r0_m: Fried parameter at the phase's wavelength, metres.
            L0_m: outer scale, metres (``inf`` = Kolmogorov).
            seed: int >= 0 or ``numpy.random.Generator`` (advanced once).
            levels: sub-harmonic levels below the torus grid (default: enough that the
                uncovered centre cell holds < 0.2 % of the G-tilt variance at ``scale_m``).
            scale_m: largest scale of interest for the default ``levels`` (default: half
                the torus diagonal).
            analytic: torus frequency cells with ``|index| <= analytic`` on both axes are
                analytic modes with PSD-drawn frequencies (unbiased), not FFT cells whose
                centre placement over-weights the steep spectrum near k = 0.
        """
        _check_r0_L0(r0_m, L0_m)
        ny, nx = (int(v) for v in shape)
        if ny < 8 or nx < 8:
            raise ValueError(f"screen shape must be at least 8 x 8, got {shape!r}")
        if not (np.isfinite(pixel_m) and pixel_m > 0):
            raise ValueError(f"pixel_m must be a finite number > 0, got {pixel_m!r}")
        self.shape = (ny, nx)
        self.pixel_m = float(pixel_m)
        self.r0_m, self.L0_m = float(r0_m), float(L0_m)
        ss_torus, ss_modes = _seed_sequence(seed).spawn(2)
        if not (isinstance(analytic, (int, np.integer)) and 1 <= analytic < min(ny, nx) // 4):
            raise ValueError(f"analytic must be an integer in [1, min(shape)/4), got {analytic!r}")
        self.analytic = int(analytic)
        self.torus = _torus(self.shape, self.pixel_m, r0_m, L0_m, np.random.default_rng(ss_torus),
                            self.analytic)
        self.torus.setflags(write=False)
        if levels is None:
            if scale_m is None:
                scale_m = 0.5 * math.hypot(*self.period_m)
            levels = _default_levels(max(self.period_m), r0_m, L0_m, scale_m)
        self.levels = int(levels)
        self.mode_k, self.mode_c = self._modes(np.random.default_rng(ss_modes))

    @property
    def period_m(self) -> tuple[float, float]:
        """``(Ly, Lx)``: the torus period in metres."""
        return (self.shape[0] * self.pixel_m, self.shape[1] * self.pixel_m)

    @property
    def nbytes(self) -> int:
        return int(self.torus.nbytes + self.mode_k.nbytes + self.mode_c.nbytes)

    def _modes(self, rng):
        ly, lx = self.period_m
        ks, cs = [], []
        for p in range(self.levels + 1):
            r = self.analytic if p == 0 else 1
            a, b = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
            ring = (a != 0) | (b != 0)
            a, b = a[ring].astype(float), b[ring].astype(float)     # ky index, kx index
            nc = a.size
            dkx, dky = 1.0 / (lx * 3 ** p), 1.0 / (ly * 3 ** p)
            var, w, off = _cell_psd(b * dkx, a * dky, dkx, dky, self.r0_m, self.L0_m)
            # Frequency drawn inside the cell with probability ~ PSD (sub-cell, then uniform).
            pick = np.array([rng.choice(w.shape[1], p=wi) for wi in w])
            jitter = (rng.random((nc, 2)) - 0.5) * (np.array([dkx, dky]) / 16)
            k = np.stack([b * dkx, a * dky], axis=1) + off[pick] + jitter
            c = (rng.standard_normal(nc) + 1j * rng.standard_normal(nc)) * np.sqrt(var)
            ks.append(k)
            cs.append(c)
        k = np.concatenate(ks)
        c = np.concatenate(cs)
        k.setflags(write=False)
        c.setflags(write=False)
        return k, c

    def expected_gtilt_variance(self, d_m: float, samples_per_subap: int) -> np.ndarray:
        """Ensemble mean square ``(x, y)`` G-tilt phase gradient (rad^2/m^2) of this model.

        Exact expectation over seeds of what :class:`FrozenFlow` computes at whole-sample
        shifts: FFT cells through the discrete trapezoid-edge G-tilt filter
        ``(e^{2 pi i kx d} - 1)/d * trapezoid_mean(e^{2 pi i ky y})``, analytic modes through
        the continuous ``2 pi i kx sinc(kx d) sinc(ky d)`` averaged over their frequency draw.
        Compare with :func:`gtilt_variance_theory` times ``(2 pi / lambda0)^2``.
        """
        m = int(samples_per_subap)
        var, ky, kx = _torus_variance(self.shape, self.pixel_m, self.r0_m, self.L0_m, self.analytic)
        var = var.astype(float)
        var[:, 1:] *= 2                                     # rfft columns stand for +-k
        if self.shape[1] % 2 == 0:
            var[:, -1] /= 2
        ky, kx = ky.astype(float), kx.astype(float)
        w = np.full(m + 1, 1.0)
        w[[0, -1]] = 0.5
        l = np.arange(m + 1) * self.pixel_m

        def trap(k):                                        # |trapezoid mean of e^{2 pi i k y}|^2
            return np.abs(np.exp(2j * np.pi * k[..., None] * l) @ w / m) ** 2

        diff_x = 4 * np.sin(np.pi * kx * d_m) ** 2 / d_m ** 2
        diff_y = 4 * np.sin(np.pi * ky * d_m) ** 2 / d_m ** 2
        out = np.array([np.sum(var * diff_x * trap(ky)), np.sum(var * diff_y * trap(kx))])
        ly, lx = self.period_m
        for p in range(self.levels + 1):
            r = self.analytic if p == 0 else 1
            a, b = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
            ring = (a != 0) | (b != 0)
            a, b = a[ring].astype(float), b[ring].astype(float)
            dkx, dky = 1.0 / (lx * 3 ** p), 1.0 / (ly * 3 ** p)
            cvar, cw, off = _cell_psd(b * dkx, a * dky, dkx, dky, self.r0_m, self.L0_m)
            qx = b[:, None] * dkx + off[None, :, 0]
            qy = a[:, None] * dky + off[None, :, 1]
            filt = (np.sinc(qx * d_m) * np.sinc(qy * d_m)) ** 2 * (2 * np.pi) ** 2
            out += [np.sum(cvar[:, None] * cw * filt * qx ** 2), np.sum(cvar[:, None] * cw * filt * qy ** 2)]
        return out

    def phase(self, x_m, y_m) -> np.ndarray:
        """Phase (rad) at points ``(x_m, y_m)`` (metres, broadcastable arrays)."""
        x, y = np.broadcast_arrays(np.asarray(x_m, float), np.asarray(y_m, float))
        ny, nx = self.shape
        u, v = x / self.pixel_m, y / self.pixel_m
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = u - iu, v - iv
        c0, r0 = iu.astype(np.int64) % nx, iv.astype(np.int64) % ny
        c1, r1 = (c0 + 1) % nx, (r0 + 1) % ny
        t = self.torus
        top = t[r0, c0] * (1 - fu) + t[r0, c1] * fu
        bot = t[r1, c0] * (1 - fu) + t[r1, c1] * fu
        out = top * (1 - fv) + bot * fv
        arg = 2 * np.pi * (x[..., None] * self.mode_k[:, 0] + y[..., None] * self.mode_k[:, 1])
        out = out + (np.exp(1j * arg) @ self.mode_c).real
        return out

    def grid(self, ny: int, nx: int) -> np.ndarray:
        """``(ny, nx)`` phase (rad) on the sample grid starting at (0, 0), float64.

        Torus samples (wrapping if larger than the torus) plus the modes, evaluated separably.
        """
        rows = np.arange(ny) % self.shape[0]
        cols = np.arange(nx) % self.shape[1]
        out = self.torus[np.ix_(rows, cols)].astype(float)
        y = np.arange(ny) * self.pixel_m
        x = np.arange(nx) * self.pixel_m
        ey = np.exp(2j * np.pi * np.outer(self.mode_k[:, 1], y))      # (K, ny)
        ex = np.exp(2j * np.pi * np.outer(self.mode_k[:, 0], x))      # (K, nx)
        out += ((ey * self.mode_c[:, None]).T @ ex).real
        return out


def phase_screen(n: int, pixel_m: float, r0_m: float, L0_m: float = math.inf,
                 seed=0, levels: int | None = None) -> np.ndarray:
    """An ``(n, n)`` Kolmogorov / von Karman phase screen in radians (at r0's wavelength).

    The FFT part is periodic over ``2 n`` samples (the screen is the first quarter of a
    ``2n x 2n`` torus, so its opposite edges are unrelated) plus analytic sub-harmonics.

    Args:
        n: samples per side. pixel_m: sample spacing, metres. r0_m: Fried parameter, metres.
        L0_m: outer scale (inf = Kolmogorov). seed: int or Generator. levels: sub-harmonic levels.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 4):
        raise ValueError(f"n must be an integer >= 4, got {n!r}")
    scr = PhaseScreen((2 * n, 2 * n), pixel_m, r0_m, L0_m, seed, levels)
    return scr.grid(n, n)


# --------------------------------------------------------------------------- frozen flow
def _pow2_at_least(n: float) -> int:
    return 1 << max(3, int(math.ceil(math.log2(max(n, 1)))))


def _edge_means(v: np.ndarray, f: float, m: int, g: int) -> np.ndarray:
    """Trapezoid means along axis 0 of ``v`` shifted by ``f`` samples, per lattice segment.

    ``w[l] = v[l] + f (v[l+1] - v[l])`` for ``l = 0 .. g*m``; returns the ``(g, ...)``
    trapezoid means of ``w`` over ``[i*m, (i+1)*m]`` (float64), from one block sum of ``v``
    (``w`` is never formed: the sums are linear in ``v``).
    """
    lo = np.arange(g) * m
    hi = lo + m
    block = v[:g * m].reshape((g, m) + v.shape[1:]).sum(axis=1, dtype=float)  # sum v[lo:hi]
    v_lo, v_lo1, v_hi, v_hi1 = (v[i].astype(float) for i in (lo, lo + 1, hi, hi + 1))
    # sum_{l=lo}^{hi} w[l] = (1-f) sum_{lo}^{hi} v + f sum_{lo+1}^{hi+1} v
    total = block + v_hi + f * (v_hi1 - v_lo)
    w_lo = v_lo + f * (v_lo1 - v_lo)
    w_hi = v_hi + f * (v_hi1 - v_hi)
    return (total - 0.5 * (w_lo + w_hi)) / m


class FrozenFlow:
    """One frozen-flow turbulent layer at the pupil; true spot displacements per frame.

    The layer (r0 = ``sensor.r0_m`` at ``sensor.r0_wavelength_m``, L0 = ``sensor.outer_scale_m``)
    moves ``wind_speed_mps / frame_rate_hz`` metres per frame towards ``wind_direction_deg``
    (0 = +x, 90 = +y): the phase at pupil point p in frame k is ``screen(p - v k / f)``.

    Tilts are the exact G-tilt of each square subaperture (side ``sensor.subap_pitch_m``)
    on the screen sampled at ``subap_pitch_m / samples_per_subap`` (bilinearly shifted),
    plus the analytic G-tilt of the low-frequency modes; divided by the pixel scale.

    Memory: one float32 torus of ``across x along`` samples, periodically padded by one
    pupil: across the wind it spans at least twice the pupil (64 m for the default sensor),
    along it ``period_m`` (default 256 m: 1024 x 4096 samples of 6.25 cm, 27 MiB with the
    padding). The torus part repeats every ``period_m / v`` seconds for a wind along x or y
    (25.6 s at 10 m/s); the low-frequency modes do not.

    Sampling: ``samples_per_subap = 8`` (6.25 cm) puts the model's ensemble G-tilt variance
    within 0.1 % of the theory (:meth:`PhaseScreen.expected_gtilt_variance`); the bilinear
    sub-sample shift lowers it by at most 0.8 % at half-sample offsets (0.2 % at 16).
    """

    def __init__(self, sensor: Sensor, seed, *, samples_per_subap: int = 8,
                 period_m: float = 256.0, levels: int | None = None):
        """
        Args:
            sensor: the sensor (pupil grid or single subaperture, turbulence fields).
            seed: int >= 0 or ``numpy.random.Generator`` (advanced once).
            samples_per_subap: screen samples per subaperture side (>= 2).
            period_m: torus length along the (dominant axis of the) wind, metres.
            levels: sub-harmonic levels (default: automatic, see :class:`PhaseScreen`).
        """
        if not isinstance(sensor, Sensor):
            raise ValueError(f"sensor must be a Sensor, got {type(sensor).__name__}")
        if not (isinstance(samples_per_subap, (int, np.integer)) and samples_per_subap >= 2):
            raise ValueError(f"samples_per_subap must be an integer >= 2, got {samples_per_subap!r}")
        if not (np.isfinite(period_m) and period_m > 0):
            raise ValueError(f"period_m must be a finite number > 0, got {period_m!r}")
        self.sensor = sensor
        lay = layout(sensor)
        self._valid = lay.valid.copy()
        self.n_valid = lay.n_valid
        g, d, m = sensor.grid, sensor.subap_pitch_m, int(samples_per_subap)
        self.m, self.d, self.g = m, d, g
        self.pixel_m = d / m
        # Lattice corner (left/bottom edge of subaperture (0, 0)); torus sample (0, 0) there.
        centre00 = (np.array(sensor.single_subaperture_xy_m) if sensor.is_single
                    else np.full(2, -(g - 1) / 2 * d))
        self.origin_xy_m = centre00 - d / 2
        theta = math.radians(sensor.wind_direction_deg)
        self.velocity_mps = sensor.wind_speed_mps * np.array([math.cos(theta), math.sin(theta)])
        self.step_m = self.velocity_mps / sensor.frame_rate_hz           # (x, y) per frame
        self._step_px = self.step_m / self.pixel_m
        across = max(_pow2_at_least(2 * (g * m + 2)), _pow2_at_least(16.0 / self.pixel_m))
        along = max(across, _pow2_at_least(period_m / self.pixel_m))
        shape = (across, along) if abs(self.velocity_mps[0]) >= abs(self.velocity_mps[1]) \
            else (along, across)
        self.screen = PhaseScreen(shape, self.pixel_m, sensor.r0_m, sensor.outer_scale_m,
                                  seed, levels, scale_m=d)
        # Periodic padding so every pupil window is a plain slice; the screen's torus
        # becomes a view into it (no second copy).
        pad = g * m + 2
        self._padded = np.pad(self.screen.torus, ((0, pad), (0, pad)), mode="wrap")
        self._padded.setflags(write=False)
        self.screen.torus = self._padded[:shape[0], :shape[1]]
        # phase gradient (rad/m at r0's wavelength) -> OPD gradient (rad) -> pixels
        self._scale = sensor.r0_wavelength_m / (2 * math.pi) / sensor.pixel_scale_rad
        self._modes_setup()
        self.frame = 0

    # -- geometry ---------------------------------------------------------------------------
    @property
    def period_m(self) -> tuple[float, float]:
        """``(Ly, Lx)`` torus period, metres."""
        return self.screen.period_m

    @property
    def period_frames(self) -> float:
        """Frames after which the torus part repeats (wind along x or y; inf if no wind)."""
        ly, lx = self.period_m
        sx, sy = np.abs(self.step_m)
        if sx == 0 and sy == 0:
            return math.inf
        return lx / sx if sx >= sy else ly / sy

    @property
    def nbytes(self) -> int:
        """Memory held by the screen and precomputed tables, bytes."""
        return int(self._padded.nbytes + self.screen.mode_k.nbytes + self.screen.mode_c.nbytes
                   + self._mode_ex.nbytes + self._mode_ey.nbytes)

    def _modes_setup(self):
        """Separable tables for the analytic G-tilt of the modes on the lattice.

        ``tilt[i, j, a] = Re sum_K z_K(t) A[K, a] Ey[K, i] Ex[K, j]`` with
        ``z_K(t) = exp(-2 pi i k_K . step * frame)``: two small complex GEMMs per frame.
        """
        k, c = self.screen.mode_k, self.screen.mode_c               # (K, 2), (K,)
        d, g = self.d, self.g
        centre = (np.arange(g) + 0.5) * d                             # lattice coords of centres
        self._mode_ex = np.exp(2j * np.pi * np.outer(k[:, 0], centre))   # (K, G)
        self._mode_ex_re = np.ascontiguousarray(self._mode_ex.real)
        self._mode_ex_im = np.ascontiguousarray(self._mode_ex.imag)
        self._mode_ey = np.exp(2j * np.pi * np.outer(k[:, 1], centre)).T.copy()  # (G, K)
        avg = np.sinc(k[:, 0] * d) * np.sinc(k[:, 1] * d)
        self._mode_a = (2j * np.pi * k * (c * avg)[:, None]) * self._scale   # (K, 2) px
        self._mode_kstep = k @ self.step_m                            # cycles per frame

    def _mode_tilts(self, frame: int) -> np.ndarray:
        """``(G, G, 2)`` analytic-mode displacements (pixels) on the whole lattice."""
        turns = np.mod(self._mode_kstep * float(frame), 1.0)
        z = np.exp(-2j * np.pi * turns)                               # (K,)
        w = z[:, None] * self._mode_a                                 # (K, 2)
        left = (self._mode_ey[None, :, :] * w.T[:, None, :]).reshape(2 * self.g, -1)  # (2G, K)
        # Re(L @ Ex) as two real GEMMs (half the flops of a complex one), both axes at once.
        t = (left.real @ self._mode_ex_re - left.imag @ self._mode_ex_im).reshape(2, self.g, self.g)
        return np.moveaxis(t, 0, -1)

    # -- tilts ---------------------------------------------------------------------------------
    def _shift(self, frame: int):
        u = -float(frame) * self._step_px                             # torus px (x, y)
        i = np.floor(u)
        f = u - i
        up = f > 1.0 - 1e-9                                           # snap rounding noise
        i = np.where(up, i + 1, i)
        f = np.where(up | (f < 1e-9), 0.0, f)
        return int(i[0]), int(i[1]), float(f[0]), float(f[1])

    def _torus_tilts(self, frame: int) -> np.ndarray:
        """``(G, G, 2)`` phase gradients (rad/m) of the torus part on the whole lattice.

        The window of the (periodically padded) torus under the pupil is sliced without
        copies; the edge samples are bilinearly shifted by the sub-pixel part of the
        frozen-flow offset, then trapezoid-summed per subaperture edge.
        """
        ix, iy, fx, fy = self._shift(frame)
        ny, nx = self.screen.shape
        m, g, d = self.m, self.g, self.d
        n = g * m + 2
        win = self._padded[iy % ny: iy % ny + n, ix % nx: ix % nx + n]   # (n, n) view
        # Vertical edges (x on the lattice, every y sample): columns j*m and j*m + 1.
        a = win[:, 0:n - 1:m]
        v = a + fx * (win[:, 1:n:m] - a)                              # (n, g+1), x-shifted
        ev = _edge_means(v, fy, m, g)                                 # (g, g+1)
        tx = (ev[:, 1:] - ev[:, :-1]) / d                             # (g, g)
        # Horizontal edges (y on the lattice, every x sample): rows i*m and i*m + 1.
        a = win[0:n - 1:m]
        h = a + fy * (win[1:n:m] - a)                                 # (g+1, n), y-shifted
        eh = _edge_means(h.T, fx, m, g).T                             # (g+1, g)
        ty = (eh[1:] - eh[:-1]) / d                                   # (g, g)
        return np.stack([tx, ty], axis=-1)

    def tilts_at(self, frame: int) -> np.ndarray:
        """``(n_valid, 2)`` true spot displacements (x, y) in pixels for frame ``frame`` (>= 0)."""
        if not (isinstance(frame, (int, np.integer)) and frame >= 0):
            raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
        grid = self._torus_tilts(int(frame)) * self._scale + self._mode_tilts(int(frame))
        return grid[self._valid]

    def next_tilts(self) -> np.ndarray:
        """``(n_valid, 2)`` displacements (pixels, detector x, y) of the next frame."""
        out = self.tilts_at(self.frame)
        self.frame += 1
        return out

    def tilts(self, n_frames: int) -> np.ndarray:
        """``(n_frames, n_valid, 2)`` displacements of the next ``n_frames`` frames."""
        if not (isinstance(n_frames, (int, np.integer)) and n_frames >= 0):
            raise ValueError(f"n_frames must be an integer >= 0, got {n_frames!r}")
        out = np.empty((int(n_frames), self.n_valid, 2))
        for i in range(int(n_frames)):
            out[i] = self.next_tilts()
        return out
