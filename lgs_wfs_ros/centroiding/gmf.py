"""Grid matched filter: matched filters at a grid of reference positions (both detectors).

A matched filter is efficient for a spot near the position of its reference and loses
efficiency as the spot moves away from it (the CMF's 1.14-1.3x the Cramer-Rao bound under
0.46 px rms tilts, docs/accuracy.md). Here every subaperture has filters built at a grid of
positions ``((kx, ky) - half) spacing`` px (default 5 x 5, 0.5 px apart, +-1 px), each
against the reference spot the pupil calibration (:mod:`.pupil`) renders at that position,
with its exact derivatives (central differences of renders). Per frame, the calibrated CoG
(the plain CoG minus the bias of the calibrated profile) picks the nearest position, that
filter measures the shift, and (``picks`` 2, the default) the position nearest to that
measurement is picked again and its filter, where it is another, measures it instead, so
the spot is within about a quarter pixel per axis of its filter's reference even where the
calibrated CoG is off by more (spots truncated by the field; beyond the grid, the nearest
edge position). Each filter gives

    s = g + R_g (x - b) / (sum(x - b))

with ``R_g`` the filter of position ``g`` (unit gain and zero cross-talk at ``g``, blind to
the flux: ``R_g [gx, gy, T] = [[1, 0, 0], [0, 1, 0]]``), ``x`` the block's counts and ``b``
the background. Weighting: the reference's counts at ``g`` plus background and read noise
squared, floored at ``var_floor``. Spots are separable or not: the same code runs on polar
and cartesian pixels.

Cost: per frame one compiled pass per block (the CoG's moments, then the chosen filter's
two rows, and a second filter's where the second pick moves; :func:`.kernels.grid_filter`:
one or two positions' rows, 1 kB a block each, the first asked for three blocks ahead) and
the calibration's accumulation. At each refit every position's reference and its
derivatives through the simulator's compiled renderer: on cartesian pixels each sub-pixel
phase of the grid rendered once, with the renderer's own derivatives, on a wider canvas and
the whole-pixel moves cropped from it (4 renders instead of 125 and their central
differences), on polar pixels each spot's line and core alone (:meth:`GMF._position_lines`,
no image, central differences); then each position's filters in one compiled pass
(:func:`.kernels.position_filters`, :func:`.kernels.separable_filters`), 72 MB in int16
for the full pupil (:func:`.kernels.quantize`). A full-pupil refit takes ~0.43-0.6 s CPU
cartesian on this host (more when the profile evolves and the fit iterates;
benchmarks/results.json). Refits can run in a background thread (``pupil_async``), as for
every pupil-calibrated estimator.
"""

from __future__ import annotations

import threading

import numpy as np

from . import kernels
from ..optics import fast_frames, geometry
from ..optics.model_spot import shift_to_detector
from .base import check_options, finite_rows, number
from .cmf import CMF, FILTERS, GRID_DEFAULTS, solve_filter
from . import pupil as pupil_cal
from .cog import TabledCoG

#: shift of the central differences that give each reference's derivatives, px
DERIVATIVE_STEP = 0.01


def _numpy_filters(img, dx, dy, var_add, floor):
    """:func:`.kernels.position_filters` in numpy (without numba): one grid position's
    ``(filters (n, 2, p*p) int16, scale (n, 2), rsum (n, 2), ok (n,))`` from its render
    and derivatives ``(n, p, p)`` counts (a px), through :func:`.cmf.solve_filter` and
    :func:`.kernels.quantize`."""
    n = img.shape[0]
    img = img.reshape(n, -1)
    flux = img.sum(axis=1)
    unit = np.where(flux > 0, 1.0 / np.where(flux > 0, flux, 1.0), 0.0)[:, None]
    design = np.stack([dx.reshape(n, -1) * unit, dy.reshape(n, -1) * unit,
                       img * unit], axis=2)                               # (n, pp, 3)
    var = np.maximum(np.maximum(img, 0.0) + var_add, floor)
    r, good = solve_filter(design, np.array([[1.0, 0, 0], [0, 1.0, 0]]), var)
    filters, scale = kernels.quantize(r)
    return filters, scale, (filters * scale[..., None]).sum(axis=2), good & (flux > 0)


class GMF(TabledCoG):
    """Matched filters at a grid of reference positions (see the module docstring).

    Options:
        spacing_px: distance between grid positions, px (0.5).
        grid: positions per axis, odd (5: +-1 px at the default spacing).
        picks: filter choices per block (2): 1 uses the position nearest the calibrated CoG;
            2 (3) picks again by that filter's measurement (once more).
        background: counts per pixel (default ``sensor.background_e``), subtracted and in
            the weighting.
        read_noise_e: read noise in the weighting, e- (default the sensor's).
        var_floor: smallest pixel variance in the weighting, counts^2 (1.0).
        pupil_period, pupil_time_constant_s, pupil_stride, pupil_async, pupil_async_lag,
        pupil_trend:
            the pupil calibration, as for ``cog`` with ``bias=pupil``.
    """

    name = "gmf"
    _public = ("background", "spacing_px", "grid", "picks", "read_noise_e", "var_floor",
               *pupil_cal.OPTION_DEFAULTS)
    _allowed = (*_public, "bias")            # CoG's, which this sets to "pupil" itself

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._public)
        spacing = number("spacing_px", options.pop("spacing_px", GRID_DEFAULTS["spacing_px"]),
                         minimum=0, strict=True)
        grid = number("grid", options.pop("grid", GRID_DEFAULTS["grid"]), minimum=1, integer=True)
        if grid % 2 == 0:
            raise ValueError(f"{self.name}: grid must be odd (a position at the centre), got {grid}")
        if spacing * (grid // 2) > 0.5 * sensor.pixels:
            raise ValueError(f"{self.name}: the grid reaches {spacing * (grid // 2)} px, beyond half "
                             f"the field ({0.5 * sensor.pixels} px)")
        picks = number("picks", options.pop("picks", GRID_DEFAULTS["picks"]), minimum=1, integer=True)
        if picks > 3:
            raise ValueError(f"{self.name}: picks must be 1, 2 or 3, got {picks}")
        rn = number("read_noise_e", options.pop("read_noise_e", float(sensor.read_noise_e)),
                    minimum=0)
        floor = number("var_floor", options.pop("var_floor", 1.0), minimum=0, strict=True)
        super().__init__(sensor, **{**options, "bias": "pupil"})
        self.options.update(spacing_px=spacing, grid=grid, picks=picks, read_noise_e=rn,
                            var_floor=floor)
        self.options.pop("bias", None)
        self.spacing, self.half, self.picks = spacing, grid // 2, picks
        self.read_noise, self.var_floor = rn, floor
        self.positions = (np.arange(grid) - self.half) * spacing          # (grid,) px
        self._spare, self._spare_lock = None, threading.Lock()            # _take_tables
        self._start_tables()

    # -- filters -------------------------------------------------------------------------
    def _prepare(self, calibration) -> dict:
        """What a (background) refit builds: every position's filters, from ``calibration``
        (one compiled pass a position where numba is: :func:`.kernels.position_filters`, or
        :func:`.kernels.separable_filters` from 1-D lines on a polar detector)."""
        filters, scale, rsum, good = tables = self._take_tables()
        args = (self.background + self.read_noise ** 2, self.var_floor)
        if self._separable():
            for k, lines, cores, counts in self._position_lines(calibration):
                kernels.separable_filters(lines, cores, counts, DERIVATIVE_STEP, *args,
                                          out=tuple(t[k] for t in tables))
        elif kernels.AVAILABLE:
            for k, *images in self._position_images(calibration):
                kernels.position_filters(*images, *args, out=tuple(t[k] for t in tables))
        else:
            for k, *images in self._position_images(calibration):
                filters[k], scale[k], rsum[k], good[k] = _numpy_filters(*images, *args)
        return self._with_drift(calibration, {
            "version": calibration.version, "filters": filters, "scale": scale, "rsum": rsum,
            "good": good, "ok": good.all(axis=0), "bias": calibration.cog_bias()})

    def _take_tables(self) -> tuple:
        """``(filters (G, n, 2, p*p) int16, scale (G, n, 2), rsum (G, n, 2), good (G, n))``
        for a refit to fill (``G`` positions): those of the refit before the one in use,
        which no frame reads any more, else new ones. Reusing them spares the 72 MB table's
        page faults each refit (prepare and install 0.385 -> 0.365 s CPU, cartesian full pupil)."""
        with self._spare_lock:
            spare, self._spare = self._spare, None
        return spare if spare is not None else (
            np.empty((self.positions.size ** 2, self.n, 2, self.p * self.p), dtype=np.int16),
            np.empty((self.positions.size ** 2, self.n, 2)),
            np.empty((self.positions.size ** 2, self.n, 2)),
            np.empty((self.positions.size ** 2, self.n), dtype=bool))

    def _position_images(self, calibration, canvas: bool = True):
        """Yield ``(k, img, dx, dy)`` for every grid position ``k`` (``ky G + kx``, at
        ``(positions[kx], positions[ky])``): the calibration's spots there, counts ``(n, p,
        p)``, and their derivatives along block x and y, counts a px: the central
        differences (:func:`.kernels.central_differences`) of the same spots rendered
        :data:`DERIVATIVE_STEP` px before and after the position, or, on cartesian pixels
        with the compiled renderer, the renderer's own. There each distinct sub-pixel
        phase of the grid is rendered once with its derivatives, on a canvas wider than the
        block, and the positions whole pixels from it are crops of that canvas
        (:meth:`..optics.fast_frames.FastRenderer.canvas_derivatives`: the default 5 x 5 grid,
        0.5 px apart, in 4 renders instead of 125; the images bit for bit, the derivatives
        within 1e-3 of their largest value of the central differences', tested); otherwise,
        or with ``canvas`` false, each position and its four moves are rendered."""
        g, h, n, side = self.positions, DERIVATIVE_STEP, self.n, self.positions.size
        if not (canvas and fast_frames.AVAILABLE and self.sensor.detector == "cartesian"):
            image_at = self._renders(calibration)
            for ky, kx in np.ndindex(side, side):
                d = np.tile([g[kx], g[ky]], (n, 1))
                dx = kernels.central_differences(image_at(d - [h, 0.0]), image_at(d + [h, 0.0]), h)
                dy = kernels.central_differences(image_at(d - [0.0, h]), image_at(d + [0.0, h]), h)
                yield ky * side + kx, image_at(d), dx, dy
            return
        renderer, model, scale = self._fast(calibration)
        whole = np.floor(g + 1e-9).astype(int)              # a position = whole px + phase
        phase = np.round(g - whole, 9)
        m, p = int(np.abs(whole).max()), self.p
        for fy in np.unique(phase):
            for fx in np.unique(phase):
                # counts of the spots at (fx, fy) px on the canvas, through float32 as the
                # frame path writes them (float64: the float32 values, exactly), and their
                # derivatives
                c0, dx, dy = renderer.canvas_derivatives(model, np.tile([fx, fy], (n, 1)), m)
                c0 = c0.astype(np.float32) * scale
                dx, dy = dx * scale, dy * scale
                for ky in np.flatnonzero(phase == fy):
                    for kx in np.flatnonzero(phase == fx):
                        rows = slice(m - whole[ky], m - whole[ky] + p)     # moved by whole px
                        cols = slice(m - whole[kx], m - whole[kx] + p)
                        yield (ky * side + kx, c0[:, rows, cols], dx[:, rows, cols],
                               dy[:, rows, cols])

    def _separable(self) -> bool:
        """Whether a refit builds the filters from 1-D lines (:meth:`_position_lines`): a
        polar detector with the compiled renderer and kernels."""
        return (self.sensor.detector == "polar" and fast_frames.AVAILABLE
                and kernels.AVAILABLE)

    def _position_lines(self, calibration):
        """Yield ``(k, lines (5, n, p), cores (5, n, p), counts (n,))`` for every grid
        position ``k`` on a polar detector: the compiled renderer's lines along block x and
        cores along block y (:meth:`.fast_frames.FastRenderer.polar_lines`) of the spots
        at the position and :data:`DERIVATIVE_STEP` px before and after it along x and y,
        and what takes them to counts: the renders :meth:`_position_images` would make,
        as 1-D passes (a polar refit's 125 renders 0.47-0.6 -> 0.12 s CPU, the same filters
        bit for bit, tested)."""
        g, h, n, side = self.positions, DERIVATIVE_STEP, self.n, self.positions.size
        renderer, model, scale = self._fast(calibration)
        sensor, e = renderer.sensor, self.layout.e
        for ky, kx in np.ndindex(side, side):
            d = np.tile([g[kx], g[ky]], (n, 1))
            parts = [renderer.polar_lines(model, shift_to_detector(sensor, e, s))
                     for s in (d, d - [h, 0.0], d + [h, 0.0], d - [0.0, h], d + [0.0, h])]
            yield (ky * side + kx, np.stack([a for a, _ in parts]),
                   np.stack([b for _, b in parts]), scale[:, 0, 0])

    def _fast(self, calibration):
        """``(renderer, model, scale (n, 1, 1))``: the compiled renderer of this layout, the
        calibration's spot model, and what takes its unit-light renders to counts."""
        sensor = self.sensor.replace(dtype="float32")           # expected counts, unrounded
        renderer = fast_frames.FastRenderer(geometry.layout(sensor))
        model = calibration.spots().model
        img0 = calibration.reference_image()
        flux = np.full(self.n, float(self.sensor.photons)) if calibration.flux is None \
            else calibration.flux
        tot = img0.reshape(self.n, -1).sum(axis=1)
        return renderer, model, (flux / np.where(tot > 0, tot, 1.0))[:, None, None]

    def _renders(self, calibration):
        """``image_at(shift_block (n, 2)) -> (n, p, p)`` counts of the calibration's spots
        (:meth:`.pupil.PupilCalibration.image_at`), through the simulator's compiled
        renderer where numba is (:mod:`..optics.fast_frames`: the same spot model, 2e-6 of
        the light off; a full frame in ~1 ms polar, ~20 ms cartesian instead of ~10 / ~80
        ms), else the calibration's own renders."""
        if not fast_frames.AVAILABLE:
            return calibration.image_at
        renderer, model, scale = self._fast(calibration)
        sensor, lay = renderer.sensor, geometry.layout(renderer.sensor)
        frame = np.empty(sensor.frame_shape, dtype=np.float32)

        def image_at(shift_block):
            truth = shift_to_detector(sensor, self.layout.e, shift_block)
            renderer.render(model, truth, frame, 1.0, 0, noise=False, per_field=False)
            return geometry.frame_to_stack(frame, lay).astype(np.float64) * scale
        return image_at

    def _install(self, payload: dict) -> None:
        if getattr(self, "_filters", None) is not None and self._filters is not payload["filters"]:
            with self._spare_lock:      # the tables in use until now: the next refit's
                self._spare = (self._filters, self._scale, self._rsum, self._good)
        self._set_tables(payload)
        self._drift = payload["drift"]

    def _set_tables(self, payload: dict) -> None:
        self._version, self._good = payload["version"], payload["good"]
        self._filters, self._scale = payload["filters"], payload["scale"]
        self._rsum = payload["rsum"]
        self._ok, self._bias = payload["ok"], payload["bias"]

    def _follow_tables(self) -> None:
        self._follow_drift(lambda c: self._numpy_slopes(c.reshape(self.n, -1) + self.background)[0])

    # -- frames --------------------------------------------------------------------------
    def centroid(self, data) -> np.ndarray:
        """As :meth:`Centroider.centroid`: each block through the filter of the grid position
        nearest to its calibrated CoG, then the calibration sees the frame (a refit it makes
        applies from the next frame on)."""
        self._refresh()
        drift = self._drift_term(pending=1)     # the frame is read before it is observed
        if kernels.fits(data, self.sensor.frame_shape):
            out, index = kernels.grid_filter(data, kernels.origins(self), self.p, self._bias,
                                             self._filters, self._scale, self._rsum,
                                             self.positions, self.background, self.picks)
            seen = self.pupil.observe_frame(data)
        else:
            flat = self.float_stack(data).reshape(self.n, -1)
            out, index = self._numpy_slopes(flat)
            tot = flat.sum(axis=1)
            seen = self.pupil.observe(flat, np.isfinite(tot) & (tot > 0))
        ok = (index >= 0) & finite_rows(out) & self._ok
        if seen:
            self._refresh()
        return self.finish(out - drift, ok, drift=False)

    def _numpy_slopes(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What :func:`.kernels.grid_filter` gives, for a float ``(n, p*p)`` stack."""
        flat = flat.astype(np.float64)
        tot = flat.sum(axis=1)
        flux = tot - self.background * self.p * self.p
        pos = np.arange(self.p) - self.centre
        st = flat.reshape(self.n, self.p, self.p)
        with np.errstate(divide="ignore", invalid="ignore"):
            est = np.stack([st.sum(axis=1) @ pos, st.sum(axis=2) @ pos], 1) / flux[:, None]
        est = np.nan_to_num(est) - self._bias
        side = 2 * self.half + 1
        n = np.arange(self.n)
        for _ in range(self.picks):            # a block whose position stays gets the same
            k = np.floor(est / self.spacing + 0.5).astype(np.int64)
            k = np.clip(k + self.half, 0, side - 1)
            index = k[:, 1] * side + k[:, 0]
            r = self._filters[index, n] * self._scale[index, n][..., None]      # (n, 2, pp)
            with np.errstate(divide="ignore", invalid="ignore"):
                est = self.positions[k] + (np.einsum("nkp,np->nk", r, flat)
                                           - self.background * self._rsum[index, n]) / flux[:, None]
            est = np.nan_to_num(est)
        bad = ~(np.isfinite(tot) & (tot > 0) & (flux > 0))
        est[bad] = np.nan
        index[bad] = -1
        return est, index

    def describe(self) -> dict:
        d = super().describe()
        d["filter_grid"] = {"positions_per_axis": 2 * self.half + 1, "spacing_px": self.spacing}
        return d


class GridCMF(GMF):
    """``cmf`` with ``filters="grid"`` (its default with the pupil reference): the grid of
    constrained matched filters above, under cmf's name and options.

    Each filter is a CMF's (unit gain, zero cross-talk, blind to the flux) built at one grid
    position; the single filter's own options (:attr:`.cmf.CMF.SINGLE_DEFAULTS`: reference,
    weighting, linearize, ...) are accepted at their defaults only, so a setting that would
    be silently ignored is refused with the reason. ``describe()`` records ``filters:
    grid`` and the grid's options: a bag replays through the same estimator.
    """

    name = "cmf"

    def __init__(self, sensor, **options):
        check_options(self.name, options, (*GMF._public, "filters", *CMF.SINGLE_DEFAULTS))
        filters = options.pop("filters", "grid")
        if filters not in FILTERS or filters == "single":
            raise ValueError(f"cmf: GridCMF is filters=grid, got filters={filters!r}")
        reference = options.pop("reference", "pupil")
        if reference != "pupil":
            raise ValueError(f"cmf: filters=grid renders its filters from the pupil "
                             f"calibration (reference=pupil), got reference={reference!r}; "
                             f"use filters=single for a {reference} reference")
        for key, default in CMF.SINGLE_DEFAULTS.items():
            if key in options and options.pop(key) != default:
                raise ValueError(f"cmf: option {key} applies to filters=single (one filter "
                                 f"at the reference); with filters=grid leave it at "
                                 f"{default!r} or set filters=single")
        super().__init__(sensor, **options)
        self.options.update(filters="grid", reference="pupil")


__all__ = ["GMF", "GridCMF", "DERIVATIVE_STEP"]
