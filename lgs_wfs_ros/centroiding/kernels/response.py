"""The linearisation's per-subaperture inversion of a 2-D Chebyshev response
(:mod:`..linearize`): polynomial start and Newton steps, one pass per subaperture in
registers (numpy needs a dozen ``(n, 2, D, D)`` passes and ~50 calls).
"""

from __future__ import annotations

import numpy as np

from . import _jit


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


if _jit.COMPILED:
    # numpy error model: a zero determinant gives inf/NaN (rejected), not an exception;
    # fast-math without the no-NaN/no-inf flags (NaN rows must stay NaN)
    _invert_response = _jit.numba.njit(cache=True, nogil=True, error_model="numpy",
                                  fastmath={"contract", "reassoc", "nsz", "arcp"})(_invert_response_impl)


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
