"""Poisson maximum likelihood against the pupil-calibrated spots (polar detector).

On a polar detector every subaperture's block is aligned with its elongation ``e`` and the
spot is separable in the block axes: the light of the spot displaced by ``(dx, dy)`` is
``F a(u - dx) b(v - dy)`` (``u`` along ``e``, ``v`` across; the profile convolved with the
core along ``u``, the core across; exact to 5e-16 for the simulator's spots). With Poisson
counts ``n_uv`` and the flux ``F`` free, the log-likelihood then splits into one term per
axis on the block's marginal sums ``Nx_u = sum_v n_uv``, ``Ny_v = sum_u n_uv`` (``N`` the
total)::

    l(dx, dy) = [sum_u Nx_u log a(u - dx) - N log sum_u a(u - dx)]
              + [sum_v Ny_v log b(v - dy) - N log sum_v b(v - dy)]

(the field's truncation is in the sums of ``a`` and ``b``), so the 2-D estimate is two 1-D
maximisations of 16 terms each. ``a`` and ``b`` come from the sodium profile the whole pupil
calibrates (:mod:`.pupil`), rendered by the simulator's spot model and tabulated as logs per
subaperture on a grid of ``step_px`` (:class:`Tables`: only the sub-pixel phases are
rendered, a whole-pixel shift moves the marginals; 2 MB for the full pupil at the default
1/4 px), rebuilt at each refit (0.3 s).

Per frame (:func:`.kernels.ml_search`, one compiled pass per block): the marginals (added
into the calibration's sums too: on a polar detector they are all its fit needs), the
pupil-calibrated CoG as the start, a hill climb on the grid from there and a parabola through
the best grid point and its neighbours. A climb that reaches the table's edge (a shift beyond
``extent_px``) returns the calibrated CoG instead. Without numba (or on float frames and
stacks) numpy scans the whole grid (~6 ms a full frame instead of ~0.6 ms).

Measured on unseen profile families (``benchmarks/bench_accuracy.py``, polar): 1.00-1.08x the
Cramer-Rao bound where the calibrated CoG with its bias alone was at 0.83-2.6x (1.0-1.5x
with its response inverted, the default since 2026-11-26) and the single-filter CMF at
1.15-3.2x.
On a cartesian detector the spot is not separable in the pixel axes and this estimator is
refused (use ``gmf``, :mod:`.gmf`, which reads whole blocks).
"""

from __future__ import annotations

import numpy as np

from . import kernels
from . import pupil as pupil_cal
from .cog import TabledCoG
from .base import check_options, finite_rows, number
from ..optics.model_spot import ProfileSpots

#: smallest tabulated light, relative to the largest of the subaperture's axis (a count far
#: in a wing the profile estimate misses costs at most ``log`` of this, not infinity)
FLOOR = 1e-4


class Tables:
    """Likelihood tables of one profile for every subaperture, both block axes.

    A shift ``d = i + j step`` (``i`` whole pixels, ``j`` of ``S = 1 / step`` phases) moves
    the marginals by ``i`` pixels, so only the ``S`` phases are rendered, on a field
    ``margin`` pixels wider on each side: ``logs[:, a, j, w]`` is ``log a(w - margin - j step)``
    (axis 0; ``b`` for axis 1) for ``w`` in ``0 .. p + 2 margin - 1``, and the marginals of a
    spot displaced by ``d_k = (k - M) step`` are the ``p`` entries from ``margin - i``.
    ``norms[:, a, k]`` is the log of their sum (the light the field keeps); ``bias (n, 2)``
    the CoG in the field of the spot at the true centre (the calibrated CoG's offset). Shapes:
    ``logs (n, 2, S, p + 2 margin)`` float32 (2 MB for the full pupil at S = 4, 3x less than
    one row per shift: the frame's pixels and the calibration's accumulator share the cache
    with it), ``norms (n, 2, K)``, ``K = 2 M + 1``, ``M = extent / step``.
    """

    def __init__(self, spots_of, sensor, step: float, extent: float):
        phases = int(round(1.0 / step))
        self.phases, self.step = phases, 1.0 / phases
        self.m = int(round(extent * phases))
        self.margin = int(np.ceil(extent)) + 1
        p = sensor.pixels
        wide = p + 2 * self.margin
        spots = spots_of(sensor.replace(pixels=wide))
        marg = np.empty((spots.n, 2, phases, wide))
        for j in range(phases):                 # the spots' column and row sums, (n, 2, w)
            marg[:, :, j] = spots.marginals_at(np.full((spots.n, 2), j * self.step))
        # phase 0 is the spot at the true centre: its CoG in the field is the calibrated
        # CoG's bias (what pupil.cog_bias gives, without rendering the reference again)
        centred = marg[:, :, 0, self.margin:self.margin + p]
        with np.errstate(divide="ignore", invalid="ignore"):
            bias = centred @ (np.arange(p) - (p - 1) / 2.0) / centred.sum(axis=2)
        self.bias = np.where(np.isfinite(bias), bias, 0.0)                    # (n, 2)
        floor = FLOOR * marg.max(axis=(2, 3), keepdims=True)
        marg = np.maximum(marg, np.where(floor > 0, floor, 1e-300))
        self.logs = np.log(marg).astype(np.float32)
        k = np.arange(2 * self.m + 1) - self.m
        whole, phase = np.divmod(k, phases)
        cols = self.margin - whole[:, None] + np.arange(p)[None, :]           # (K, p)
        self.norms = np.log(marg[:, :, phase[:, None], cols].sum(axis=-1))     # (n, 2, K)

    def rows(self, axis: int) -> np.ndarray:
        """``(n, K, p)`` float64 log marginals of every tabulated shift along ``axis``
        (the numpy path's full table)."""
        k = np.arange(2 * self.m + 1) - self.m
        whole, phase = np.divmod(k, self.phases)
        p = self.logs.shape[-1] - 2 * self.margin
        cols = self.margin - whole[:, None] + np.arange(p)[None, :]
        return self.logs[:, axis][:, phase[:, None], cols].astype(np.float64)


class ML(TabledCoG):
    """Poisson maximum likelihood on the block marginals (see the module docstring).

    Options:
        step_px: grid step of the likelihood tables, px (0.25; the parabola refines it: 1/8
            and 1/16 gave the same errors on the accuracy cases).
        extent_px: largest shift tabulated, px (2.0); beyond it the calibrated CoG is
            returned.
        background: counts per pixel (default ``sensor.background_e``); must be 0: the
            marginals of a uniform background are not separable (refused otherwise).
        pupil_period, pupil_time_constant_s, pupil_stride, pupil_async, pupil_async_lag,
        pupil_trend:
            the pupil calibration, as for ``cog`` with ``bias=pupil``.
    """

    name = "ml"
    refit_reads = ("drift_marginal_pair",)      # _follow_drift_marginals reads no image
    _public = ("background", "step_px", "extent_px", *pupil_cal.OPTION_DEFAULTS)
    _allowed = (*_public, "bias")            # CoG's, which this sets to "pupil" itself

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._public)
        if sensor.detector != "polar":
            raise ValueError("ml needs the polar detector (the spot must be separable in the "
                             "block axes); on a cartesian detector use cmf (by default "
                             "matched filters at a grid of positions) or cog with bias=pupil")
        step = number("step_px", options.pop("step_px", 0.25), minimum=0, strict=True)
        if abs(1.0 / step - round(1.0 / step)) > 1e-9:
            raise ValueError(f"ml: step_px must be 1 / an integer (0.25, 0.125, ...), got {step}")
        extent = number("extent_px", options.pop("extent_px", 2.0), minimum=0, strict=True)
        if not step <= extent <= 0.5 * sensor.pixels:
            raise ValueError(f"ml: need step_px <= extent_px <= {0.5 * sensor.pixels} px, got "
                             f"step_px {step}, extent_px {extent}")
        super().__init__(sensor, **{**options, "bias": "pupil"})
        if self.background or sensor.read_noise_e:
            raise ValueError("ml models photon noise alone: background and read noise must be "
                             f"0 (got {self.background} counts, {sensor.read_noise_e} e-); "
                             "use cmf, whose weighting includes them")
        self.options.update(step_px=step, extent_px=extent)
        self.options.pop("bias", None)
        self.step, self.extent = step, extent
        self._version = None
        self._start_tables()
        kernels.warm_up()

    # -- tables --------------------------------------------------------------------------
    def _prepare(self, calibration) -> dict:
        """What a (background) refit builds: the likelihood tables of its profile."""
        def spots_of(sensor):
            return ProfileSpots(sensor, self.layout.r_m, self.layout.e, calibration.nodes_m,
                                calibration.light, 1.5)
        tables = Tables(spots_of, self.sensor, self.step, self.extent)
        return self._with_drift(calibration, {"version": calibration.version,
                                              "bias": tables.bias, "tables": tables})

    _drift_keeps = ("_rows",)                       # the numpy path's, made for the drift

    def _install(self, payload: dict) -> None:
        self._set_tables(payload)
        self._drift, self._rows = payload["drift"], payload["_rows"]

    def _set_tables(self, payload: dict) -> None:
        self._version = payload["version"]
        self._tables, self._bias = payload["tables"], payload["bias"]
        self._rows = None                           # the numpy path's, made when needed

    def _follow_tables(self) -> None:
        self._follow_drift_marginals()

    def _follow_drift_marginals(self) -> None:
        """:meth:`Centroider._follow_drift` from marginals, all this estimator reads: the
        drifted reference's (:meth:`.PupilCalibration.drift_marginals`) less the current
        one's (:meth:`.PupilCalibration.reference_marginals`, the same render path: its
        tables' wider field, cropped, moved the high layer's ratio to the bound by +0.0014),
        without rendering either image."""
        pair = self.pupil.drift_marginal_pair()
        if pair is None:
            self._drift = None
            return
        drifted, ref = pair
        with np.errstate(divide="ignore", invalid="ignore"):
            moved = self._marginals_reading(drifted) - self._marginals_reading(ref)
        self._drift = np.nan_to_num(moved, nan=0.0, posinf=0.0, neginf=0.0)

    # -- frames --------------------------------------------------------------------------
    def centroid(self, data) -> np.ndarray:
        """As :meth:`Centroider.centroid`: each block's likelihood is maximised against the
        tables of the calibration's current profile, then the calibration sees the frame
        (its block marginals, read in the same pass; a refit it makes applies from the next
        frame on)."""
        self._refresh()
        drift = self._drift_term(pending=1)     # the frame is read before it is observed
        if kernels.fits(data, self.sensor.frame_shape):
            acc = self.pupil.marginal_buffer()
            t = self._tables
            out = kernels.ml_search(data, kernels.origins(self), self.p, t.logs, t.norms,
                                    self._bias, t.margin, acc)
            if self.pupil.observed_marginals(acc is not None):
                self._refresh()                   # the new tables now, on the refit's frame
            return self.finish(out - drift, finite_rows(out), drift=False)
        flat = self.float_stack(data).reshape(self.n, -1)
        tot = flat.sum(axis=1, dtype=np.float64)
        ok = np.isfinite(tot) & (tot > 0)
        flat = np.where(ok[:, None], flat, 0)
        out = self._reading(flat.reshape(self.n, self.p, self.p), tot)
        if self.pupil.observe(flat, ok):
            self._refresh()
        return self.finish(out - drift, ok, drift=False)

    def _reading(self, stack: np.ndarray, tot: np.ndarray | None = None) -> np.ndarray:
        """``(n, 2)`` block axes, px: the numpy path's shifts of counts ``stack (n, p, p)``
        (totals ``tot``, or their sums), nothing fed to the calibration."""
        stack = np.asarray(stack, dtype=np.float64)
        if tot is None:
            tot = stack.reshape(self.n, -1).sum(axis=1)
        return self._marginals_reading(np.stack([stack.sum(axis=1), stack.sum(axis=2)], axis=1),
                                       tot)

    def _marginals_reading(self, marg: np.ndarray, tot: np.ndarray | None = None) -> np.ndarray:
        """:meth:`_reading` of counts given by their marginals ``(n, 2, p)`` (column sums,
        then row sums; totals ``tot``, or the column sums' sums)."""
        if tot is None:
            tot = marg[:, 0].sum(axis=1)
        return np.stack([self._scan(marg[:, 0], 0, tot), self._scan(marg[:, 1], 1, tot)], axis=1)

    def _scan(self, marg: np.ndarray, axis: int, tot: np.ndarray) -> np.ndarray:
        """numpy path: ``(n,)`` shift along ``axis`` from ``(n, p)`` marginals, the whole grid
        scanned (the compiled kernel climbs from the calibrated CoG instead)."""
        if self._rows is None:
            self._rows = (self._tables.rows(0), self._tables.rows(1))
        ll = (np.einsum("nu,nku->nk", marg, self._rows[axis])
              - tot[:, None] * self._tables.norms[:, axis])
        m = (ll.shape[1] - 1) // 2
        k = np.argmax(ll, axis=1)
        i = np.arange(len(k))
        inner = (k > 0) & (k < ll.shape[1] - 1)
        kc = np.clip(k, 1, ll.shape[1] - 2)
        y0, y1, y2 = ll[i, kc - 1], ll[i, kc], ll[i, kc + 1]
        den = y0 - 2 * y1 + y2
        with np.errstate(divide="ignore", invalid="ignore"):
            off = np.where(den < 0, 0.5 * (y0 - y2) / den, 0.0)
        est = (kc - m + np.clip(off, -0.5, 0.5)) * self.step
        with np.errstate(divide="ignore", invalid="ignore"):
            cog = marg @ (np.arange(self.p) - self.centre) / tot - self._bias[:, axis]
        return np.where(inner, est, cog)

    def describe(self) -> dict:
        d = super().describe()
        d["likelihood_grid"] = {"step_px": self.step, "extent_px": self.extent,
                                "shifts": int(self._tables.norms.shape[2])}
        return d


__all__ = ["ML", "Tables", "FLOOR"]
