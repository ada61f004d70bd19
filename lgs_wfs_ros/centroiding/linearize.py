"""Response linearisation: undo a centroider's non-linear response per subaperture.

A linear filter such as the CMF reads a shift ``s`` of its reference as ``f(s)``, with
``f(0) = 0``, unit gain at 0 and (CMF) ``f = s`` at the +-1 px constraint points, but a
smooth non-linear response in between (about 0.02 px off at +-0.5 px and 0.2 px in the
+-1 px corners for the 1.19 px core). Real systems calibrate this response with a
tip/tilt scan; here the scan is done on noise-free images of the reference shifted on a
Chebyshev grid, ``f`` is fitted per subaperture as a 2-D Chebyshev series of degree
``degree`` in each axis over ``[-extent, extent]^2`` px, and a measurement ``m`` is
inverted by Newton's method, ``s <- s - J(s)^-1 (f(s) - m)``.

Everything is in the block's pixel axes (the local frame on a polar detector), per
subaperture. With numba (the ``fast`` extra) a frame's inversion is one compiled pass per
subaperture (:func:`.kernels.invert_response`, float64, ~0.1 us a subaperture); without it,
numpy evaluates the same steps vectorised (a few ``(n, 2, D, D)`` float32 contractions,
``D = degree + 1``, ~1 us a subaperture and ~1 ms of call overhead a frame). The two agree
to ~1e-6 px (float32 rounding of the numpy path).
"""

from __future__ import annotations

import numpy as np

from . import kernels


def chebyshev_nodes(points: int, extent: float) -> np.ndarray:
    """``(points,)`` Chebyshev nodes of the first kind on ``[-extent, extent]`` px."""
    return extent * np.cos(np.pi * (np.arange(points) + 0.5) / points)[::-1]


def chebyshev_basis(u: np.ndarray, degree: int, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """``T_k(u)`` and ``dT_k/du`` for ``k = 0..degree``.

    Args:
        u: ``(n,)`` arguments (nominally in [-1, 1]).

    Returns:
        two ``(degree + 1, n)`` arrays (row k: ``T_k``, ``T_k'``).
    """
    u = np.asarray(u, dtype=dtype)
    n = u.shape[0]
    t = np.empty((degree + 1, n), dtype=dtype)
    d = np.empty((degree + 1, n), dtype=dtype)
    t[0], d[0] = 1.0, 0.0
    if degree >= 1:
        t[1], d[1] = u, 1.0
    u2 = 2 * u
    for k in range(2, degree + 1):                       # recurrences, over k only
        np.multiply(u2, t[k - 1], out=t[k])
        t[k] -= t[k - 2]
        np.multiply(u2, d[k - 1], out=d[k])
        d[k] += 2 * t[k - 1]
        d[k] -= d[k - 2]
    return t, d


class ResponseMap:
    """Fitted forward response ``f(s)`` of ``n`` subapertures and its inverse.

    Args:
        coef: ``(n, 2, D, D)`` Chebyshev coefficients: output axis, x degree, y degree.
        extent: half-width of the calibrated box, px.
    """

    def __init__(self, coef: np.ndarray, extent: float):
        self.coef = np.asarray(coef, dtype=float)
        self.extent = float(extent)
        self.degree = self.coef.shape[-1] - 1
        self.fit_error = np.nan
        self.guess = None
        # float32 copy laid out (y degree, n, out, x degree) for the per-frame contractions
        self._coef_j = np.ascontiguousarray(self.coef.transpose(3, 0, 1, 2), dtype=np.float32)
        self._coef64 = np.ascontiguousarray(self.coef)       # the compiled kernel's layout
        self.use_kernel = kernels.AVAILABLE

    @classmethod
    def fit(cls, measure, n: int, extent: float = 1.1, points: int = 12,
            degree: int = 8) -> "ResponseMap":
        """Scan and fit.

        Args:
            measure: callable ``shift (n, 2) px -> (n, 2)`` raw estimates (block pixel
                axes) of the noise-free reference displaced by ``shift``.
            n: subapertures.
            extent: half-width of the scanned box, px (slightly beyond the range to
                linearise: the fit is used inside, extrapolated linearly outside).
            points: grid points per axis (``points^2`` calls of ``measure``).
            degree: Chebyshev degree per axis (< ``points``).
        """
        if not 1 <= degree < points:
            raise ValueError(f"need 1 <= degree < points, got degree {degree}, points {points}")
        g = chebyshev_nodes(points, extent)
        gx, gy = np.meshgrid(g, g, indexing="ij")
        grid = np.stack([gx.ravel(), gy.ravel()], axis=1)                       # (G, 2)
        resp = np.stack([measure(np.broadcast_to(s, (n, 2)).copy()) for s in grid], axis=1)
        tx, _ = chebyshev_basis(grid[:, 0] / extent, degree)
        ty, _ = chebyshev_basis(grid[:, 1] / extent, degree)
        v = (tx.T[:, :, None] * ty.T[:, None, :]).reshape(len(grid), -1)         # (G, D*D)
        rhs = resp.transpose(1, 0, 2).reshape(len(grid), -1)                     # (G, n*2)
        finite = np.isfinite(rhs).all(axis=0)
        sol = np.zeros((v.shape[1], rhs.shape[1]))
        sol[:, finite] = np.linalg.lstsq(v, rhs[:, finite], rcond=None)[0]
        d = degree + 1
        coef = sol.reshape(d, d, n, 2).transpose(2, 3, 0, 1)                    # (n, 2, D, D)
        bad = ~finite.reshape(n, 2).all(axis=1)
        coef[bad] = np.nan
        out = cls(coef, extent)
        fitted = np.einsum("gk,kj->gj", v, sol).reshape(len(grid), n, 2).transpose(1, 0, 2)
        out.fit_error = float(np.nanmax(np.abs(fitted - resp))) if finite.any() else np.nan
        out.guess = _fit_inverse(resp, grid, GUESS_DEGREE)
        return out

    def forward(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``f(s)`` ``(n, 2)`` and its Jacobian ``(n, 2, 2)`` (``[n, out, in]``) at ``s (n, 2)`` px
        (evaluated in float32: ~1e-6 px, far below the fit's own residual)."""
        tx, dx = chebyshev_basis(s[:, 0] / self.extent, self.degree, np.float32)    # (D, n)
        ty, dy = chebyshev_basis(s[:, 1] / self.extent, self.degree, np.float32)
        cy = np.einsum("jnki,jn->nki", self._coef_j, ty)                            # (n, 2, D)
        cdy = np.einsum("jnki,jn->nki", self._coef_j, dy)
        f = np.einsum("nki,in->nk", cy, tx)
        jac = np.stack([np.einsum("nki,in->nk", cy, dx),
                        np.einsum("nki,in->nk", cdy, tx)], axis=2) / self.extent
        return f.astype(np.float64), jac.astype(np.float64)

    def invert(self, m: np.ndarray, iterations: int = 2,
               outside: str = "raw") -> tuple[np.ndarray, np.ndarray]:
        """Shifts ``s (n, 2)`` px with ``f(s) = m`` and the Jacobian ``df/ds (n, 2, 2)`` there.

        Starts from a low-degree polynomial fit of the inverse (a few 0.01 px off in the
        corners) and takes ``iterations`` Newton steps on the fitted forward response
        (quadratic convergence: one step reaches ~1e-4 px); the start is kept in the
        calibrated box. Where the solution falls outside the box, or the response has
        folded (gain below ``MIN_GAIN``), ``outside`` decides: ``"raw"`` returns the
        measurement unchanged (a filter whose raw reading is already about the shift),
        ``"offset"`` the measurement less the response at 0, ``m - f(0)`` (an estimator with
        a large offset, such as a CoG's bias: its gain there is unknown, the offset is not);
        the Jacobian is the identity either way. NaN rows stay NaN.
        """
        if outside not in ("raw", "offset"):
            raise ValueError(f"outside must be 'raw' or 'offset', got {outside!r}")
        m = np.asarray(m, dtype=float)
        if self.use_kernel:
            guess = None if self.guess is None else np.ascontiguousarray(self.guess, dtype=float)
            s, jac, inside = kernels.invert_response(self._coef64, self.extent, guess, m,
                                                     iterations, MIN_GAIN ** 2)
        else:
            s, jac, inside = self._invert_numpy(m, iterations)
        if outside == "offset" and not inside.all():
            out = ~inside
            s[out] = m[out] - self.at_zero()[out]
        return s, jac

    def at_zero(self) -> np.ndarray:
        """``f(0) (n, 2)``, px (cached)."""
        if getattr(self, "_zero", None) is None:
            self._zero = self.forward(np.zeros((self.coef.shape[0], 2)))[0]
        return self._zero

    def _invert_numpy(self, m: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray,
                                                                      np.ndarray]:
        """:meth:`invert`'s steps vectorised in numpy (no numba): ``(s, jac, inside)``."""
        lim = self.extent
        s = m if self.guess is None else _eval_inverse(self.guess, m)
        s = np.clip(np.nan_to_num(s), -lim, lim)
        with np.errstate(invalid="ignore", over="ignore"):   # inf/NaN rows stay NaN
            for _ in range(max(int(iterations), 1)):
                f, jac = self.forward(s)
                s = s - _solve2(jac, f - m)
            det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
        inside = (np.abs(s) <= lim).all(axis=1) & (det > MIN_GAIN ** 2)
        s = np.where(inside[:, None], s, m)
        jac = np.where(inside[:, None, None], jac, np.eye(2))
        return s, jac, inside


GUESS_DEGREE = 5
MIN_GAIN = 0.1      # below this response gain (sqrt of the Jacobian determinant) keep m


def _monomials(m: np.ndarray, degree: int) -> np.ndarray:
    """``(..., K)`` monomials ``x^i y^j``, ``i + j <= degree``, of ``m (..., 2)`` (a view
    with the monomials on the last axis; the same products as one at a time, 2.4x faster)."""
    x, y = m[..., 0], m[..., 1]
    xp = np.empty((degree + 1,) + x.shape)
    yp = np.empty_like(xp)
    xp[0] = yp[0] = 1.0
    for d in range(1, degree + 1):                      # powers by products (np.power is slow)
        xp[d] = xp[d - 1] * x
        yp[d] = yp[d - 1] * y
    i, j = np.array([(i, d - i) for d in range(degree + 1) for i in range(d + 1)]).T
    return np.moveaxis(xp[i] * yp[j], 0, -1)


def _fit_inverse(resp: np.ndarray, grid: np.ndarray, degree: int) -> np.ndarray:
    """``(n, K, 2)`` least-squares polynomial ``s = P(m)`` from responses ``(n, G, 2)``
    to the scanned shifts ``grid (G, 2)``."""
    bad = ~np.isfinite(resp).all(axis=(1, 2))          # e.g. a spot that leaves the field
    v = _monomials(np.where(bad[:, None, None], 0.0, resp), degree)          # (n, G, K)
    vt = v.transpose(0, 2, 1)
    vtv = vt @ v                     # batched BLAS: 9x faster than the einsum, same sums
    vtv += (1e-12 * (1.0 + np.trace(vtv, axis1=1, axis2=2)))[:, None, None] * np.eye(v.shape[-1])
    out = np.linalg.solve(vtv, vt @ grid)
    out[bad] = np.nan
    return out


def _eval_inverse(coef: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Evaluate :func:`_fit_inverse`'s polynomial at ``m (n, 2)``."""
    return np.einsum("nk,nkj->nj", _monomials(m, GUESS_DEGREE), coef)


def _solve2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``a x = b`` for ``(n, 2, 2)`` ``a`` and ``(n, 2)`` ``b`` (closed form; NaN if singular)."""
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        x0 = (a[:, 1, 1] * b[:, 0] - a[:, 0, 1] * b[:, 1]) / det
        x1 = (a[:, 0, 0] * b[:, 1] - a[:, 1, 0] * b[:, 0]) / det
    return np.stack([x0, x1], axis=1)


def transform_covariance(cov: np.ndarray, jac: np.ndarray) -> np.ndarray:
    """Covariance of ``s`` from that of ``m = f(s)``: ``J^-1 C J^-T`` (``(n, 2, 2)``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ji = np.linalg.inv(np.where(np.isfinite(jac), jac, np.eye(2)))
    ji[~np.isfinite(jac).all(axis=(1, 2))] = np.nan
    return ji @ cov @ np.swapaxes(ji, 1, 2)
