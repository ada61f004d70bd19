"""ANN centroider: runs an ONNX model with onnxruntime (one intra-op thread) on the stack.

The model file's side (where models are found, the ``lgs_wfs.*`` metadata contract, the
graph cuts and folds made at load time) is :mod:`.ann_model`.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from ..optics import geometry
from . import ann_model, bins_along_e
from . import domain as model_domain
from . import kernels
from . import pupil as pupil_cal
from .base import Centroider, check_options, choice

#: the default model per detector (docs/ann_ref.md): filters its pupil-calibrated reference
#: sets through convolutions, applied to the light in 1 px bins: ann_conv on polar pixels
#: (the column sums, along e); ann_grid on cartesian ones since 2026-11-27 11:10 UTC (the
#: same network trained on whole-pixel sums along the pixel-grid direction nearest to e:
#: 0.87 ms a frame, where ann_conv's split of every pixel takes 1.4-2.4 ms); ann_ref (the
#: whole image beside its reference) was the cartesian default before both
DEFAULT_MODELS = {"polar": "ann_conv", "cartesian": "ann_grid"}

#: option recentre: filter sets a block, from the reference moved along the bins by
#: ``(k - RECENTRE_SETS // 2) RECENTRE_STEP_PX`` px
RECENTRE_SETS, RECENTRE_STEP_PX = 5, 0.25
#: option linearize: the response is read at moves ``(k - LINEAR_SETS // 2) LINEAR_STEP_PX``
#: px along the bins, its gain is the slope of the moves within ``LINEAR_GAIN_SPAN_PX``
LINEAR_SETS, LINEAR_STEP_PX, LINEAR_GAIN_SPAN_PX = 9, 0.25, 0.5
DEFAULT_MODEL = DEFAULT_MODELS["cartesian"]
#: how the notice and the warning of a sky outside the training profiles begin
SKY_OUTSIDE = "the calibrated sky is outside the network's training profiles (it runs, extrapolating): "


# A frame is cast block by block in one pass and the network run on every block of the
# grid (~30 % outside the pupil) when that is cheaper than gathering the valid blocks
# first: for small networks (the paper's 4,146 weights), not for ann_pupil's 26,000.
ALL_BLOCKS_MAX_WEIGHTS = 10_000


class ANN(Centroider):
    """Neural-network centroider.

    Options:
        model: path or name (default: :data:`DEFAULT_MODELS` of the sensor's detector,
            ``ann_conv`` on polar pixels, ``ann_grid`` on cartesian ones), see
            :func:`.ann_model.resolve_model`.
        pupil_period, pupil_time_constant_s, pupil_stride: the pupil calibration that gives
            a reference-reading model (``lgs_wfs.conditioning = "reference"``) its
            references, as cmf's pupil reference (:mod:`.pupil`); unused by other models.
        out_of_domain: "refuse" (default: a sensor with any subaperture outside the
            model's training domain, :mod:`.domain`, raises ValueError with the reason) |
            "warn" (run; ``describe()["domain"]`` counts the subapertures outside).
        bias: "pupil" (subtract the model's own reading of each subaperture's noise-free
            calibrated reference, taken at every refit: what the network reads where the
            true shift is zero) | "none" | "auto" (default: "pupil" for a marginals model,
            whose reading of the noise-free reference is its mean reading under photon noise,
            "none" otherwise). Needs a reference-reading model; the option as run (pupil or
            none) is in ``describe()["options"]``.
        bins: a column-sum model on a cartesian detector: "auto" (default: what the model
            was trained on, ``lgs_wfs.bins_projection``) | "overlap" (each pixel split over
            the 1 px bins along e by its footprint, :func:`.bins_along_e.overlap_weights`) |
            "grid" (whole pixels summed along the pixel-grid direction nearest to e, bins
            along that direction, :func:`.bins_along_e.grid_weights`; the network reads
            the shift along it, the CoG across e gives the rest) | "span" (as grid, the
            bins sqrt 2 px wide along diagonals so that they hold the whole block).
        recentre: a filters model (``ann_conv``, ``ann_grid``): at every refit also make
            the filters of the reference moved along the bins by ``-0.5 .. +0.5`` px in steps
            of :data:`RECENTRE_STEP_PX` (:data:`RECENTRE_SETS` sets); each block is read
            against the one nearest its CoG along the bins less the reference's, less the
            network's reading of that moved reference, plus the move (``False``: the
            reference alone, the default).
        linearize: a marginals model with ``bias`` pupil (``ann_conv``, ``ann_grid``,
            ``ann_hyper``, ``ann_marg``): ``True`` (default) removes the curvature of the
            network's response along the bins: at every refit each block's noise-free
            calibrated reference is read moved by ``-1 .. +1`` px in quarter-pixel steps
            along them, and each reading goes through the inverse of that response, times
            its slope over ``+-0.5`` px (the gain the network gives a shift stays: it
            shrinks faint and broad spots toward zero, which lowers their error). ``False``:
            the reading less the reading of the reference. Other models: unused (as run in
            ``describe()["options"]``).
    """

    name = "ann"
    _allowed = ("model", "out_of_domain", "bias", "bins", "recentre", "linearize",
                *pupil_cal.OPTION_DEFAULTS)

    def __init__(self, sensor, **options):
        check_options(self.name, options, self._allowed)
        options.setdefault("model", DEFAULT_MODELS.get(sensor.detector, DEFAULT_MODEL))
        options.setdefault("out_of_domain", "refuse")
        if options["out_of_domain"] not in ("refuse", "warn"):
            raise ValueError(f"ann: out_of_domain must be 'refuse' or 'warn', got {options['out_of_domain']!r}")
        choice("bias", options.setdefault("bias", "auto"), ("auto", "pupil", "none"))
        choice("bins", options.setdefault("bins", "auto"), ("auto", *bins_along_e.PROJECTIONS))
        if not isinstance(options.setdefault("recentre", False), (bool, np.bool_)):
            raise ValueError(f"ann: recentre must be true or false, got {options['recentre']!r}")
        if not isinstance(options.setdefault("linearize", True), (bool, np.bool_)):
            raise ValueError(f"ann: linearize must be true or false, got {options['linearize']!r}")
        super().__init__(sensor, **options)
        self.path = ann_model.resolve_model(options["model"])
        self.session = ann_model.open_session(self.path)
        self.meta = ann_model.read_metadata(self.session.get_modelmeta().custom_metadata_map)
        md = self.meta
        self.pupil, self._graph, self._refit, self._trunk = None, None, None, None
        if md["hyper"]:                                  # the reference sets filters once per refit
            import onnx
            refit, frame = ann_model.split_hyper(onnx.load(str(self.path)), md["conditioning_input"],
                                                 md["hyper_outputs"])
            self._refit = ann_model.open_session(refit.SerializeToString())
            self.session = ann_model.open_session(frame.SerializeToString())
            self._trunk = ann_model.hyper_trunk(frame, md["hyper_trunk"])
        elif md["conditioning"] == "reference":           # the reference enters once per refit
            import onnx
            self._graph, self._ref_w = ann_model.split_reference(onnx.load(str(self.path)), md["conditioning_input"])
            self.session = ann_model.open_session(self._graph.SerializeToString())
            md["conditioning_input"] += "_code"
        if md["pixels"] != self.p:
            raise ValueError(f"ann: model {self.path.name} takes {md['pixels']} x {md['pixels']} "
                             f"pixels, the sensor has {self.p} x {self.p}")
        projectable = md["input"] == "marginals" and sensor.detector == "cartesian"
        if md["detector"] not in ("any", sensor.detector) and not projectable:
            raise ValueError(f"ann: model {self.path.name} is for a {md['detector']} detector, "
                             f"the sensor is {sensor.detector}")
        inputs = {i.name: i for i in self.session.get_inputs()}
        first = self.session.get_inputs()[0].name
        self.input_name = md["input_name"] or first
        if self.input_name not in inputs:
            raise ValueError(f"ann: model has no input {self.input_name!r} (inputs: {list(inputs)})")
        self.marginals = md["input"] == "marginals"
        # a marginals model on a cartesian detector: bins along e (pixels split by overlap)
        # or along the grid direction nearest to e (option bins)
        self._bins = None
        self._window = None
        self._dir = None        # the bins' direction where it is not e (grid, span): u, bins a px
        bins = md["bins_projection"] if options["bins"] == "auto" else options["bins"]
        self._projection = bins if projectable else None
        if projectable and bins in bins_along_e.GRID_PROJECTIONS:
            if md["bins_window"] != "centred":
                raise ValueError(f"ann: bins {bins!r} reads centred windows; {self.path.name} "
                                 f"reads {md['bins_window']!r} ones")
            start, w, self._dir = bins_along_e.grid_weights(self.layout.e, self.p,
                                                            span=bins == "span")
            self._centred = (start, w)
            self._place_window(np.zeros(self.n, dtype=np.int32))
            del self._centred
            self._grid_q = bins_along_e.grid_tables(self._dir, *self._bins)   # the frame pass's
        elif projectable:       # centred until the first reference places the windows
            self._centred = bins_along_e.overlap_weights(self.layout.e, self.p)
            self._place_window(np.zeros(self.n, dtype=np.int32))
            if md["bins_window"] == "centred":    # placed for good: no need of the exact split
                del self._centred
        _check_width(inputs[self.input_name], self.p if self.marginals else self.p * self.p,
                     "pixel input", self.n)
        self.cond, self._offset = None, None
        if md["hyper"]:
            missing = [nm for nm in md["hyper_outputs"] if nm not in inputs]
            if missing:
                raise ValueError(f"ann: the hyper model's frame part lacks inputs {missing}")
            self.pupil = pupil_cal.from_options(sensor, options, sensor.background_e)
            self.cond = ("hyper", None)
        elif md["conditioning"] != "none":
            cname = md["conditioning_input"]
            if cname not in inputs:
                raise ValueError(f"ann: conditioning {md['conditioning']!r} needs an input named "
                                 f"{cname!r}; the model has {list(inputs)}")
            e = np.asarray(self.layout.e, dtype=np.float32)
            if md["conditioning"] == "reference":
                self.pupil = pupil_cal.from_options(sensor, options, sensor.background_e)
                e = np.zeros((self.n, 0), dtype=np.float32)      # set by _install_reference
            elif md.get("conditioning_frame", "detector") == "pixel" and self.sensor.detector == "polar":
                # e in the block's own pixel axes: along local x on a polar detector
                e = np.tile(np.array([1.0, 0.0], dtype=np.float32), (e.shape[0], 1))
            if md["conditioning"] == "e_r":
                e = np.concatenate([e, (np.asarray(self.layout.r_m) / 15.0)[:, None]], axis=1)
            if self.pupil is None:
                _check_width(inputs[cname], e.shape[1], "conditioning input", self.n)
            self.cond = (cname, np.ascontiguousarray(e, dtype=np.float32))
        elif len(inputs) > 1:
            raise ValueError(f"ann: model has inputs {list(inputs)} but lgs_wfs.conditioning is 'none'")
        self._domain_record = model_domain.parse(self.meta["domain"])     # None: not declared
        self.domain = self._check_domain(options["out_of_domain"])
        self._debias = self._bias_option(options["bias"])
        self.options["bias"] = "pupil" if self._debias else "none"
        self._recentre = bool(options["recentre"])
        self._moved = None
        self._drift = None
        self._response = None           # option linearize: (readings (n, S), moves (S,), gain (n,))
        self._linear = bool(options["linearize"]) and self.marginals and self._debias
        self.options["linearize"] = self._linear
        if self._recentre and not (self.marginals and self._trunk is not None):
            raise ValueError(f"ann: recentre needs a model whose filters the reference sets, on "
                             f"bins along e (ann_conv, ann_grid); {self.path.name} is not one")
        self._sha256 = hashlib.sha256(self.path.read_bytes()).hexdigest()
        self._ones = np.ones(self.p * self.p, dtype=np.float32)
        self.folded = None
        if md["input_norm"] == "sum" and not self.marginals:
            self.folded = self._fold()
        if self.marginals:
            kernels.warm_up()
        self._sky = None                 # the calibrated profile against the model's (domain.ProfileCheck)
        self._sky_refits = [0, 0]        # profiles checked (each install), and found outside
        if self.pupil is not None:
            if self.pupil.asynchronous:    # the network's part of a refit too
                self.pupil.delegate(self._prepare_reference, ("drift_counts",))
            if self._bins is not None:     # the solve's CoG response, off the frame path too
                self.pupil.reads += ("cog_response",)
            self._install_reference()
            if self._refit is None:                     # the reference's code, one row each
                _check_width(inputs[self.cond[0]], self.cond[1].shape[1], "conditioning input", self.n)

    def _bias_option(self, value: str) -> bool:
        """Whether the model's reading of its calibrated reference is subtracted (option
        ``bias``); ValueError for ``pupil`` on a model that reads no reference."""
        if value == "auto":
            return self.marginals and self.pupil is not None
        if value == "pupil" and self.pupil is None:
            raise ValueError(f"ann: bias 'pupil' needs a model that reads the pupil-calibrated "
                             f"reference; {self.path.name} reads none (use bias none or auto)")
        return value == "pupil"

    def _place_window(self, offset: np.ndarray) -> None:
        """Bins along e read through windows at ``offset (n,)`` px along e
        (:func:`.bins_along_e.window_offsets`): ``(start int8, shares uint8)`` for the
        frame pass, ``(start, w)`` for numpy, both of the same quantised split."""
        if self._window is not None and np.array_equal(offset, self._window):
            return
        start, w = self._centred
        q = bins_along_e.quantised(bins_along_e.moved(start, offset), w)
        self._bins, self._bins_q, self._window = (q[0], q[2]), q[:2], offset

    # what taking the calibration's references sets (see _prepare_reference)
    _INSTALL_STATE = ("_bins", "_bins_q", "_window", "cond", "_moved", "_offset", "_response", "_ab",
                      "_projector", "_drift", "_sky")

    def _install_reference(self) -> None:
        """Take the calibration's current references (:meth:`_take_reference`): what a
        background refit prepared (``pupil_async``), or made now."""
        payload, self.pupil.payload = self.pupil.payload, None
        if payload is None or payload["version"] != self.pupil.version:
            payload = self._prepare_reference(self.pupil)
        for stale in ("_cond_rows", "_ab"):      # remade from the new references when needed
            self.__dict__.pop(stale, None)
        self.__dict__.update({k: v for k, v in payload.items() if k != "version"})
        if self._sky is not None:
            self._sky_refits[0] += 1
            self._sky_refits[1] += not self._sky.ok

    def _prepare_reference(self, calibration) -> dict:
        """The attributes :meth:`_take_reference` sets for ``calibration``, made by a shallow
        copy of this centroider (nothing the frame path reads is written): run in the refit
        thread on its snapshot with ``pupil_async`` (the network's filters, its reading of
        each reference and the straightened response: 0.3-1.4 s a cartesian refit that held
        the frame path), else on the frame that completes a period."""
        sh = self._copy_on(calibration)
        sh._take_reference()
        out = {k: sh.__dict__[k] for k in self._INSTALL_STATE if k in sh.__dict__}
        out["version"] = calibration.version
        return out

    def _take_reference(self) -> None:
        """Take the calibration's current references: on a cartesian detector the windows of
        bins along e moved to where each reference's light is, then the model's code of the
        references and the offset every reading loses (:meth:`_reference_offset`)."""
        if self._bins is not None and self.meta["bins_window"] == "reference":
            ref = self.pupil.reference_image().reshape(self.n, -1)
            self._place_window(bins_along_e.window_offsets(ref, self.layout.e))
        self.__dict__.pop("_ab", None)          # the solve follows the references' response
        self.cond = (self.cond[0], self._reference_code())
        if self._recentre:
            self._moved = self._moved_sets()
        self._offset = self._reference_offset()
        if self._linear:
            self._response = self._along_response()
        if self._offset is not None:
            self._follow_drift(self._drift_reading)
        self._sky = model_domain.check_profile(self._domain_record, *self.pupil.profile,
                                               self.model_name)

    def _moved_sets(self) -> tuple:
        """``(filters (n, S, K, p), fbias (n, S, K), less (n, S), cbias (n,))`` of option
        ``recentre``: set ``k`` from the calibrated reference moved by ``shift_k`` px along
        the bins (``u``: e, or the grid direction), ``less`` what a reading through set
        ``k`` loses (the network's raw reading of that moved reference when ``bias`` is
        pupil, less ``shift_k``, in raw output units), ``cbias`` the CoG along the bins of
        the reference, px."""
        shifts = (np.arange(RECENTRE_SETS) - RECENTRE_SETS // 2) * RECENTRE_STEP_PX
        fs, bs, less = [], [], []
        for t in shifts:
            along = self._along_moved(t)
            f, b = self._refit_filters(along)
            fs.append(f)
            bs.append(b)
            if t == 0:
                cbias = np.nan_to_num(self._row_cog(along))
            raw = self._trunk_out(*kernels.hyper_contract(along, f, b))[:, 0] if self._debias \
                else np.zeros(self.n)
            less.append(np.nan_to_num(raw) - t / self.meta["output_scale"])
        return (np.ascontiguousarray(np.stack(fs, axis=1), dtype=np.float32),
                np.ascontiguousarray(np.stack(bs, axis=1), dtype=np.float32),
                np.stack(less, axis=1), cbias)

    def _along_response(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(readings (n, S), moves (S,), gain (n,))`` of option ``linearize``: each
        block's reading along the bins (px: raw output times the output scale) of its
        noise-free calibrated reference moved by each of ``moves`` px along the bins, and
        the slope of a straight line fitted to those within ``LINEAR_GAIN_SPAN_PX`` of zero
        (NaN where the readings do not increase with the move, or are not finite)."""
        moves = (np.arange(LINEAR_SETS) - LINEAR_SETS // 2) * LINEAR_STEP_PX
        r = np.stack([self._marginals_out(self._along_moved(t))[:, 0] for t in moves],
                     axis=1).astype(np.float64) * self.meta["output_scale"]
        near = np.abs(moves) <= LINEAR_GAIN_SPAN_PX + 1e-9
        tc = moves[near] - moves[near].mean()
        gain = (r[:, near] - r[:, near].mean(axis=1, keepdims=True)) @ tc / (tc @ tc)
        with np.errstate(invalid="ignore"):
            ok = np.all(np.diff(r, axis=1) > 0, axis=1) & np.isfinite(gain)
        return r, moves, np.where(ok, gain, np.nan)

    def _straight(self, along: np.ndarray) -> np.ndarray:
        """``(n,)`` readings along the bins ``along`` (px, the reference's reading not yet
        removed) with the curvature of the network's response removed (option
        ``linearize``): through the inverse of :meth:`_along_response`'s readings, times
        its gain, plus its reading at zero move, which :meth:`_debiased` then removes."""
        if self._response is None:
            return along
        return kernels.response_inverse(along, *self._response)

    def _along_moved(self, t: float) -> np.ndarray:
        """``(n, p)`` float32: the bins (:meth:`_along`) of each block's noise-free calibrated
        reference moved by ``t`` px along them (options ``recentre`` and ``linearize``; on a
        polar detector the column sums straight from the spot model, no image formed)."""
        shift = t * np.asarray(self._bins_direction(), dtype=np.float64)
        if self._bins is None:
            return np.ascontiguousarray(self.pupil.marginals_at(shift)[:, 0], dtype=np.float32)
        return self._along(self.pupil.image_at(shift))

    def _bins_direction(self) -> np.ndarray:
        """``(n, 2)`` block axes, px: the shift that moves the light one bin along the bins
        (polar: x; cartesian: e, or the grid direction with ``bins`` grid; with ``bins``
        span sqrt 2 px along a diagonal, :func:`.bins_along_e.bins_step`)."""
        if self._bins is None:
            return np.tile([1.0, 0.0], (self.n, 1))
        return self.layout.e if self._dir is None else bins_along_e.bins_step(self._dir)

    def _reference_offset(self) -> np.ndarray | None:
        """``(n, 2)`` block axes, px, subtracted from every reading, or None: with ``bias``
        pupil the model's reading of each noise-free reference (at the calibration's flux);
        else, on a marginals model, block y's alone (the row sums' CoG is the calibrated
        CoG whatever the option)."""
        if not (self._debias or self.marginals):
            return None
        ref = self.pupil.reference_counts()
        if self._debias:
            reading = self._reading(ref)
        else:
            reading = self._combine(np.zeros(self.n), self._across(ref))
        return np.nan_to_num(reading, nan=0.0, posinf=0.0, neginf=0.0)

    def _drift_reading(self, counts: np.ndarray) -> np.ndarray:
        """``(n, 2)`` what the frame path reads of noise-free ``counts (n, p, p)`` before
        its offset: :meth:`_reading` straightened (the offset's own reading, for
        :meth:`_follow_drift`)."""
        if self._debias:
            return self._reading(counts, straight=True)
        return self._combine(np.zeros(self.n), self._across(counts))

    def _along(self, stack: np.ndarray) -> np.ndarray:
        """``(n, p)`` float32: the light of ``stack (n, p, p)`` in 1 px bins along e: the
        column sums on a polar detector, :mod:`.bins_along_e` on a cartesian one."""
        if self._bins is None:
            return np.ascontiguousarray(stack.sum(axis=1), dtype=np.float32)
        flat = np.asarray(stack).reshape(self.n, -1)
        proj = self.__dict__.get("_projector")
        if proj is None or any(a is not b for a, b in zip(proj.split, self._bins)):   # windows moved
            proj = self._projector = bins_along_e.Projector(*self._bins)
        return np.ascontiguousarray(proj(flat), dtype=np.float32)

    def _across(self, stack: np.ndarray) -> np.ndarray:
        """``(n,)`` px from the block centre: the CoG across e of ``stack (n, p, p)`` (block y's
        row sums on a polar detector; NaN without light)."""
        if self._bins is None:
            return self._row_cog(stack.sum(axis=2))
        pos = np.arange(self.p) - self.centre
        with np.errstate(divide="ignore", invalid="ignore"):
            tot = stack.sum(axis=(1, 2), dtype=np.float64)
            c = np.stack([stack.sum(axis=1, dtype=np.float64) @ pos,
                          stack.sum(axis=2, dtype=np.float64) @ pos], axis=1) / tot[:, None]
        return self._across_e(c)

    def _across_e(self, cog: np.ndarray) -> np.ndarray:
        """``(n,)`` the component across e of block CoGs ``cog (n, 2)`` (px, block axes)."""
        e = self.layout.e
        return -e[:, 1] * cog[:, 0] + e[:, 0] * cog[:, 1]

    def _combine(self, along: np.ndarray, across: np.ndarray) -> np.ndarray:
        """``(n, 2)`` block axes, px, of shifts ``along`` e and ``across`` it (``(n,)``
        each)."""
        if self._bins is None:
            return np.stack([along, across], axis=1).astype(np.float64)
        a, b = self._solve_ab()
        return along[:, None] * a + across[:, None] * b

    def _solve_ab(self) -> tuple[np.ndarray, np.ndarray]:
        """``(a, b)`` ``(n, 2)`` each, made once a refit: the shift is ``along a + across b``.

        The network reads the shift along its bins' direction ``u`` (``e``, or the grid
        direction ``d``; with ``bins`` span ``d`` over the bins' pitch: in bins), the CoG
        across e reads ``v^T J s``, with ``J`` the calibrated CoG's response at zero shift
        (``pupil.cog_response``): where the field's edge cuts a spot on a cartesian block
        the cut moves with the shift along e and pulls the CoG across e (the identity
        elsewhere). ``(a, b)`` are the columns of ``[u; v^T J]^-1``; where
        that matrix is far from the ideal ``[u; v]`` (determinant below 0.3, ideal at least
        cos 22.5 deg) or not finite, ``J = I``."""
        if "_ab" not in self.__dict__:
            e = np.asarray(self.layout.e, dtype=np.float64)
            v = np.stack([-e[:, 1], e[:, 0]], axis=1)
            u = e if self._dir is None else self._dir
            ideal = np.stack([u, v], axis=1)                                     # (n, 2, 2)
            m = ideal.copy()
            if self.pupil is not None:
                jac = self.pupil.cog_response().forward(np.zeros((self.n, 2)))[1]
                m[:, 1] = np.einsum("ni,nij->nj", v, jac)
                det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
                bad = ~(np.isfinite(det) & (np.abs(det) > 0.3))
                m[bad] = ideal[bad]
            inv = np.linalg.inv(m)
            self._ab = (np.ascontiguousarray(inv[:, :, 0]), np.ascontiguousarray(inv[:, :, 1]))
        return self._ab

    def _row_cog(self, rows: np.ndarray) -> np.ndarray:
        """``(n,)`` CoG of the row sums ``rows (n, p)``, px from the block centre (block y of
        a marginals model; NaN where a row sum has no light)."""
        return self._row_moments(rows)[0]

    def _row_moments(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(cog (n,), total (n,))`` float64 of the row sums ``rows (n, p)``: their CoG, px
        from the block centre (NaN where a row sum has no light), and their totals; one
        ``(n, p) @ (p, 2)`` product in the rows' precision (float32 sums of counts are exact
        to 2^24)."""
        if self.__dict__.get("_moment_cols") is None or self._moment_cols.dtype != rows.dtype:
            self._moment_cols = np.stack([np.arange(self.p) - self.centre, np.ones(self.p)],
                                         axis=1).astype(rows.dtype)
        m = np.asarray(rows @ self._moment_cols, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return m[:, 0] / m[:, 1], m[:, 1]

    def _reading(self, stack: np.ndarray, straight: bool = False) -> np.ndarray:
        """``(n, 2)`` raw readings, block axes, px, of float counts ``stack (n, p, p)``,
        no offset removed and nothing fed to the calibration (``straight``: through
        :meth:`_straight`, as the frame path reads)."""
        stack = np.asarray(stack, dtype=np.float32)
        if self.marginals:
            x = self._marginals_out(self._along(stack))[:, 0] * self.meta["output_scale"]
            if straight:
                x = self._straight(x)
            return self._combine(x, self._across(stack))
        if self._refit is not None:
            out = self._hyper_pixels_out(stack.reshape(self.n, -1))
        else:
            out = self._run_stack(stack)[0]
        return self._block_axes(out * self.meta["output_scale"])

    def _debiased(self, out: np.ndarray) -> np.ndarray:
        """Block-axes readings ``(n, 2)`` less :meth:`_reference_offset`."""
        return out if self._offset is None else out - self._offset

    def _reference_code(self) -> np.ndarray:
        """``(n, h)`` float32: the calibration's current references (unit sum, block axes)
        through the model's reference matrix."""
        ref = self.pupil.reference_image()
        if self.marginals:                  # bins along e (polar: the column sums)
            ref = self._along(ref)
        ref = ref.reshape(self.n, -1)
        if self._refit is not None:                  # hyper: the per-subaperture filters
            return dict(zip(self.meta["hyper_outputs"], self._refit_filters(ref)))
        return np.ascontiguousarray(_unit_rows(ref) @ self._ref_w, dtype=np.float32)

    def _refit_filters(self, ref: np.ndarray) -> list[np.ndarray]:
        """A hyper model's per-subaperture outputs (``lgs_wfs.hyper_outputs``: filters,
        fbias), float32, from references ``ref (n, h)`` (any scale: unit sum here)."""
        outs = self._refit.run(self.meta["hyper_outputs"],
                               {self.meta["conditioning_input"]: _unit_rows(ref)})
        return [np.ascontiguousarray(v, dtype=np.float32) for v in outs]

    def _trunk_out(self, z: np.ndarray, safe: np.ndarray) -> np.ndarray:
        """``(n, 1)`` the declared trunk on the first layer ``z`` and totals ``safe``."""
        names = self.meta["hyper_trunk"]
        return self._trunk.run(None, {names["z"]: z, names["total"]: safe})[0]

    def _observe(self, rows=None, flat=None) -> None:
        """Feed a frame to the pupil calibration (reference models); a refit installs the
        new references."""
        if self.pupil is None:
            return
        refit = self.pupil.observe_rows(rows, self.valid_rows) if rows is not None \
            else self.pupil.observe(np.asarray(flat, dtype=np.float64))
        if refit:
            self._install_reference()

    def _check_domain(self, policy: str) -> "model_domain.DomainCheck":
        """The sensor against the model's training domain; ValueError under "refuse"."""
        kind = {"none": "image", "e": "image+e", "e_r": "image+e_r"}.get(self.meta["conditioning"],
                                                                          "image+" + self.meta["conditioning"])
        if self.meta["input"] == "marginals":
            kind = "marginals+reference"
        name = Path(self.path).stem
        result = model_domain.check(self._domain_record, self.sensor, name, kind)
        if result.reasons and policy == "refuse":
            raise ValueError("ann: sensor outside the model's training domain: " + "; ".join(result.reasons)
                             + " (set ann.out_of_domain = warn to run it anyway)")
        return result

    def _fold(self):
        """Session of the model with the normalisation folded in, or None (not foldable)."""
        import onnx
        try:
            src = self._graph if self._graph is not None else onnx.load(str(self.path))
            model = ann_model.fold_sum_normalisation(src, self.input_name, self.p * self.p)
        except Exception:   # an unusual graph: keep the plain path
            return None
        if model is None:
            return None
        weights = sum(int(np.prod(i.dims)) for i in model.graph.initializer)
        self._all_blocks = weights <= ALL_BLOCKS_MAX_WEIGHTS
        return ann_model.open_session(model.SerializeToString())

    def run(self, x: np.ndarray) -> np.ndarray:
        """Raw model output ``(n, 2)`` float64 for ``(n, p*p)`` float32 inputs."""
        feed = {self.input_name: x}
        if self.cond is not None:
            feed[self.cond[0]] = self.cond[1]
        out = self.session.run(None, feed)[0]
        out = np.asarray(out, dtype=np.float64)
        if out.shape != (x.shape[0], 2):
            raise ValueError(f"ann: model output has shape {out.shape}, expected {(x.shape[0], 2)}")
        return out

    def _run_folded(self, x: np.ndarray, all_blocks: bool = False, cond=None) -> tuple[np.ndarray, np.ndarray]:
        """(output ``(m, 2)`` float64, totals ``(m,)``) of the folded model on raw counts
        ``x (m, p*p)``: the valid subapertures, every block of the grid (``all_blocks``), or
        rows whose conditioning ``cond`` is given."""
        feed = {self.input_name: x}
        if self.cond is not None:
            if cond is not None:
                feed[self.cond[0]] = cond
            elif all_blocks:
                if "_cond_rows" not in self.__dict__:
                    self._cond_rows = self.pad_rows(self.cond[1])
                feed[self.cond[0]] = self._cond_rows
            else:
                feed[self.cond[0]] = self.cond[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            out, total = self.folded.run(None, feed)
        if out.shape != (x.shape[0], 2):
            raise ValueError(f"ann: model output has shape {out.shape}, expected {(x.shape[0], 2)}")
        return np.asarray(out, dtype=np.float64), total[:, 0]

    def _run_stack(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(raw output ``(n, 2)``, totals ``(n,)``) for a frame or stack, valid blocks only."""
        x = self.float_stack(raw).reshape(self.n, -1)
        owned = not np.may_share_memory(x, raw)
        if x.dtype != np.float32:
            x, owned = x.astype(np.float32), True
        if self.folded is not None:                     # totals come out of the first product
            return self._run_folded(np.ascontiguousarray(x))
        total = x @ self._ones                          # BLAS row sums (faster than .sum)
        if self.meta["input_norm"] == "sum":
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = (1.0 / total)[:, None]
                x = np.multiply(x, scale, out=x) if owned else x * scale
        return self.run(np.ascontiguousarray(x)), total

    def centroid(self, data) -> np.ndarray:
        """As :meth:`Centroider.centroid` (bad rows go through the model as NaN/0, then NaN)."""
        raw = np.asarray(data)
        if self.marginals:
            return self._centroid_marginals(raw)
        if self._refit is not None:
            return self._centroid_hyper_pixels(raw)
        integer = self.folded is not None and kernels.fits(raw, self.sensor.frame_shape)
        rows = None
        if not integer and self.folded is not None and self._all_blocks:
            rows = self.frame_rows(raw)
        if integer:                                     # valid blocks, one compiled pass
            out, total = self._run_integer_frame(raw)
        elif rows is not None:                          # a frame: every block in one pass
            x = rows if rows.dtype == np.float32 else rows.astype(np.float32)
            self._observe(rows=x)
            out, total = self._run_folded(x, all_blocks=True)
            out, total = out[self.valid_rows], total[self.valid_rows]
        else:
            if self.pupil is not None:
                self._observe(flat=self.as_stack(raw).reshape(self.n, -1))
            out, total = self._run_stack(raw)
        ok = np.isfinite(total) & (total > 0)
        return self.finish(self._debiased(self._block_axes(out * self.meta["output_scale"])), ok)

    def _run_integer_frame(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(raw output ``(n, 2)``, totals ``(n,)``) of the folded model on an integer frame:
        the valid blocks cut and cast in one compiled pass (0.1-0.2 ms; numpy's cast of
        the whole block grid ~0.3 ms, and the model then ran on ~30 % more blocks), the
        calibration's sums by the compiled add of the frame; a refit installs its
        references for this frame."""
        x = kernels.block_rows(raw, kernels.origins(self), self.p, out=self.__dict__.get("_valid_x"))
        self._valid_x = x
        if self.pupil is not None and self.pupil.observe_frame(raw):
            self._install_reference()
        return self._run_folded(x)

    def _centroid_marginals(self, raw: np.ndarray) -> np.ndarray:
        """A marginals model: each block's column and row sums (one compiled pass over an
        integer frame, added into the pupil calibration's sums as ``ml`` does; a refit
        installs its references for this frame, as for ``cog`` with ``bias = pupil``); the
        network on the column sums gives block x, the calibrated CoG of the row sums y."""
        if self._bins is not None:
            return self._centroid_bins(raw)
        if kernels.fits(raw, self.sensor.frame_shape):
            acc = self.pupil.marginal_buffer()
            marg = kernels.block_marginals(raw, kernels.origins(self), self.p, acc)
            refit = self.pupil.observed_marginals(acc is not None)
        else:
            flat = self.float_stack(raw).reshape(self.n, -1).astype(np.float64)
            tot = flat.sum(axis=1)
            good = np.isfinite(tot) & (tot > 0)
            stack = np.where(good[:, None], flat, 0.0).reshape(self.n, self.p, self.p)
            marg = np.stack([stack.sum(axis=1), stack.sum(axis=2)], axis=1).astype(np.float32)
            marg[~good] = np.nan
            refit = self.pupil.observe(flat, good)
        if refit:
            self._install_reference()
        out = self._marginals_out(np.ascontiguousarray(marg[:, 0]))
        across, total = self._row_moments(marg[:, 1])
        ok = np.isfinite(total) & (total > 0)
        out = np.stack([self._straight(out[:, 0] * self.meta["output_scale"]), across], axis=1)
        return self.finish(self._debiased(out), ok)

    def _centroid_bins(self, raw: np.ndarray) -> np.ndarray:
        """A marginals model on a cartesian detector: each block's light in bins along e
        (:mod:`.bins_along_e`) through the network, across e the CoG; the frame feeds the
        pupil calibration first (a refit installs its references and their windows for this
        frame, before the frame is binned)."""
        if kernels.fits(raw, self.sensor.frame_shape):     # one compiled pass
            if self.pupil.observe_frame(raw):
                self._install_reference()
            if self._dir is not None:                       # whole-pixel sums, no split
                along, mom = kernels.grid_bins(raw, kernels.origins(self), self.p, *self._grid_q)
            else:
                along, mom = kernels.block_bins(raw, kernels.origins(self), self.p, *self._bins_q)
            out = kernels.bins_shifts(self._marginals_out(along), self.meta["output_scale"],
                                      self._response, mom, self.centre, self.layout.e,
                                      *self._solve_ab(), self._offset)
            return self.finish(out, mom[:, 0] > 0)          # the steps below, one pass
        flat = self.float_stack(raw).reshape(self.n, -1)
        tot = flat.sum(axis=1, dtype=np.float64)
        ok = np.isfinite(tot) & (tot > 0)
        if self.pupil.observe(np.asarray(flat, dtype=np.float64), ok):
            self._install_reference()
        stack = np.where(ok[:, None], flat, 0.0).reshape(self.n, self.p, self.p)
        along, across = self._along(stack), self._across(stack)
        x = self._marginals_out(np.ascontiguousarray(along))[:, 0] * self.meta["output_scale"]
        x = self._straight(x)
        return self.finish(self._debiased(self._combine(x, across)), ok)

    def _marginals_out(self, x: np.ndarray) -> np.ndarray:
        """A marginals model's raw output ``(n, 1)`` on the column sums ``x (n, p)``
        float32 (filters in one compiled pass and the trunk in onnxruntime, when the model
        declares its trunk)."""
        if self._trunk is not None:
            if self._moved is not None:                 # option recentre
                f, b, less, cbias = self._moved
                z, safe, k = kernels.hyper_contract_moved(x, f, b, cbias, RECENTRE_STEP_PX)
                out = self._trunk_out(z, safe) - less[np.arange(self.n), k][:, None]
            else:
                f, b = (self.cond[1][nm] for nm in self.meta["hyper_outputs"])
                out = self._trunk_out(*kernels.hyper_contract(x, f, b))
        else:
            feed = {self.input_name: x}
            if self._refit is not None:
                feed.update(self.cond[1])
            else:
                feed[self.cond[0]] = self.cond[1]
            out = self.session.run(None, feed)[0]
        if out.shape != (self.n, 1):
            raise ValueError(f"ann: model output has shape {out.shape}, expected {(self.n, 1)}")
        return out

    def _centroid_hyper_pixels(self, raw: np.ndarray) -> np.ndarray:
        """A hyper model on whole blocks (cartesian): each block's counts through its own
        filters (one compiled pass, :func:`.kernels.hyper_contract` over the block's
        ``p * p`` pixels) and the trunk in onnxruntime; the frame feeds the pupil calibration
        first (a refit installs its filters for this frame)."""
        flat = self.float_stack(raw).reshape(self.n, -1)
        self._observe(flat=flat)
        out = self._hyper_pixels_out(flat)
        total = flat.sum(axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(total) & (total > 0)
        return self.finish(self._debiased(self._block_axes(out * self.meta["output_scale"])), ok)

    def _hyper_pixels_out(self, flat: np.ndarray) -> np.ndarray:
        """A pixel hyper model's raw output ``(n, 2)`` float64 on counts ``flat (n, p*p)``."""
        f, b = (self.cond[1][nm] for nm in self.meta["hyper_outputs"])
        if self._trunk is not None:
            out = self._trunk_out(*kernels.hyper_contract(flat, f, b))
        else:
            feed = {self.input_name: np.ascontiguousarray(flat, dtype=np.float32), **self.cond[1]}
            out = self.session.run(None, feed)[0]
        if out.shape != (self.n, 2):
            raise ValueError(f"ann: model output has shape {out.shape}, expected {(self.n, 2)}")
        return np.asarray(out, dtype=np.float64)

    def _block_axes(self, out: np.ndarray) -> np.ndarray:
        """Model output ``(..., n, 2)`` in its ``output_frame`` -> block pixel axes."""
        if self.meta["output_frame"] == "block":
            return out
        if self.meta["output_frame"] == "local":
            out = geometry.local_to_detector(out, self.layout.e)
        return self.to_pixel_axes(out)

    def centroid_many(self, frames) -> np.ndarray:
        """As :meth:`Centroider.centroid_many`: one network run for all frames."""
        stacks = self.many_stacks(frames) if self.pupil is None else None   # pupil: frame by frame
        if stacks is None or not len(stacks) or self.folded is None:
            return super().centroid_many(frames)
        k = stacks.shape[0]
        x = np.ascontiguousarray(stacks.reshape(k * self.n, -1), dtype=np.float32)
        cond = None if self.cond is None else np.tile(self.cond[1], (k, 1))
        out, total = self._run_folded(x, cond=cond)
        out = out.reshape(k, self.n, 2) * self.meta["output_scale"]
        total = total.reshape(k, self.n)
        ok = np.isfinite(total) & (total > 0)
        return self.finish(self._block_axes(out), ok)

    def reset(self) -> None:
        """Forget the pupil calibration's profile (reference models): back to its prior."""
        if self.pupil is not None:
            self.pupil.reset()
            self._install_reference()

    def describe(self):
        """As :meth:`Centroider.describe`, the model given by name and sha256 (never an
        absolute path: a bag must replay on another machine; ``options.model`` is the
        name too)."""
        d = super().describe()
        d["model"] = self.model_name
        d["options"]["model"] = self.model_name
        d["model_sha256"] = self._sha256
        d["model_metadata"] = {k: v for k, v in self.meta.items()}
        d["domain"] = self.domain.summary()
        if self.domain.reasons:
            d["warning"] = (f"{self.domain.count} of {self.n} subapertures outside {self.model_name}'s "
                            "training domain (run with out_of_domain = warn): " + "; ".join(self.domain.reasons))
        if self._sky is not None:
            d["domain"]["profile"] = {**self._sky.summary(), "checked": self._sky_refits[0],
                                      "outside": self._sky_refits[1]}
            if not self._sky.ok:
                d["warning"] = "; ".join(w for w in (d.get("warning"), SKY_OUTSIDE
                                                     + "; ".join(self._sky.reasons)) if w)
        if self._bins is not None:       # a marginals model on a cartesian detector
            d["bins_window"] = {"kind": self.meta["bins_window"],
                                "moved_subapertures": int(np.count_nonzero(self._window))}
            d["bins_projection"] = self._projection
        if self.pupil is not None:
            pupil_cal.describe_into(d, self.pupil)
        return d

    @property
    def notice(self) -> str:
        """The sky outside the model's training profiles, as the last refit calibrated it
        ('' inside, or for a model that declares none): which ranges it left
        (:func:`.domain.check_profile`'s limits, without the profile's values, which
        ``describe()`` carries: the notice changes when the sky leaves a range or comes
        back, not at every refit while it stays out). A node logs each change once."""
        if self._sky is None or self._sky.ok:
            return ""
        return SKY_OUTSIDE + "; ".join(self._sky.limits)

    @property
    def model_name(self) -> str:
        """The model's name: its path inside a models directory without ``.onnx``
        (``ann_pupil``, ``paper_prior/ann_1k_paper``), else its file stem."""
        path = Path(self.path).resolve()
        for d in ann_model.model_dirs():
            try:
                return path.relative_to(Path(d).resolve()).with_suffix("").as_posix()
            except (ValueError, OSError):
                continue
        return path.stem


def _unit_rows(ref: np.ndarray) -> np.ndarray:
    """``ref (n, h)`` scaled to unit row sums, float32 C-contiguous (rows without light: 0)."""
    tot = ref.sum(axis=1, keepdims=True)
    return np.ascontiguousarray(np.where(tot > 0, ref / np.where(tot > 0, tot, 1.0), 0.0),
                                dtype=np.float32)


def _check_width(arg, width: int, label: str, n: int) -> None:
    """An input must be ``(batch, width)`` with a free batch (or exactly ``n``)."""
    shape = list(arg.shape)
    if len(shape) != 2:
        raise ValueError(f"ann: model {label} {arg.name!r} must be 2-D (batch, {width}), has shape {shape}")
    if isinstance(shape[1], int) and shape[1] != width:
        what = " (pixel-count mismatch)" if label == "pixel input" else ""
        raise ValueError(f"ann: model {label} {arg.name!r} takes {shape[1]} values, expected {width}{what}")
    if isinstance(shape[0], int) and shape[0] != n:
        raise ValueError(f"ann: model {label} {arg.name!r} has a fixed batch of {shape[0]}, "
                         f"the sensor has {n} subapertures; export it with a dynamic batch axis")
