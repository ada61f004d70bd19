"""Every centroider option in one table: type, default, range, choices, description.

This is the one set of defaults shared by the Python API, ``lgs-wfs replay``, the demo and the
centroider node. The node declares one typed ROS parameter per row, named
``<algorithm>.<option>`` (e.g. ``cmf.reference``), with the row's description, range and
choices in its ParameterDescriptor; replay and the API pass plain option dicts. Both end in
:func:`build`.

A row whose ``unset`` value is not None has a sentinel: a parameter holding it means "not
given" (the class default or the sensor's value applies), because a ROS parameter cannot be
None. The classes still validate every value they receive; this table is what a user sees.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from . import make_centroider


@dataclass(frozen=True)
class Option:
    """One algorithm option.

    Attributes:
        algorithm: registry name ("cmf").
        name: the option key the class takes ("reference").
        default: the value used when not given (its Python type is the parameter's type:
            bool, int, float or str); equals ``unset`` for sentinel rows.
        description: one sentence, with the unit.
        low, high: inclusive range for numbers (None: unbounded).
        choices: the allowed values for strings (empty: any).
        unset: the sentinel meaning "not given", or None when every value is real.
        read_only: True when the value can only be set at start-up.
    """

    algorithm: str
    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple = field(default_factory=tuple)
    unset: Any = None
    read_only: bool = False

    @property
    def parameter(self) -> str:
        """The ROS parameter name, ``<algorithm>.<option>``."""
        return f"{self.algorithm}.{self.name}"

    @property
    def kind(self) -> type:
        """bool, int, float or str: the parameter's type."""
        return type(self.default)


def _rows(algorithm: str, *rows: tuple) -> tuple[Option, ...]:
    return tuple(Option(algorithm, *row[:3], **(row[3] if len(row) > 3 else {})) for row in rows)


_SENSOR = {"unset": -1.0, "low": -1.0}
_PUPIL = (
    ("pupil_period", 140, "Frames between refits of the sodium profile estimated from the whole "
     "pupil (and of what it implies: references, bias), e.g. 140 = 0.2 s at 700 Hz.",
     {"low": 1, "high": 1000000}),
    ("pupil_time_constant_s", 0.3, "Memory of the pupil profile estimate, seconds (exponential "
     "average of the mean images; 0: each period alone), e.g. 0.3.", {"low": 0.0, "high": 3600.0}),
    ("pupil_stride", 1, "Frames between frames added to the pupil calibration's mean images "
     "(1: every frame), e.g. 2 halves its per-frame cost.", {"low": 1, "high": 10000}),
    ("pupil_async", False, "Refit in a background thread and swap the new references in at a "
     "frame boundary (a live node then never stalls for the ~1-4 s refit); false: inline at "
     "the end of each period, reproducible frame for frame (replay, benchmarks)."),
    ("pupil_async_lag", 0, "With pupil_async: install each refit exactly this many frames after "
     "the period end that started it, waiting then if it is late (reproducible: a replay gives "
     "the live numbers); keep it as short as the refits allow, e.g. 140 (one default period): "
     "each refit then serves later frames, which costs accuracy where the profile moves "
     "(docs/accuracy.md, a live node's refit latency); 0: whenever it is ready.",
     {"low": 0, "high": 1000000}),
    ("pupil_altitude_s", 0.0, "Time constant (s) of a tracker of the sodium layer's altitude "
     "between profile refits, from the slopes' pupil-wide pattern along the elongation (focus "
     "with a centre launch): the slopes then lose the atmosphere's focus slower than this, as "
     "an LGS cannot tell it from the layer's altitude; e.g. 0.05; 0: off.",
     {"low": 0.0, "high": 3600.0}),
    ("pupil_trend", True, "Extrapolate the profile estimate to the frames it will serve, from "
     "its drift (two averages, time constants T and 2T): no lag behind a profile evolving "
     "steadily; false: the exponential average itself (lags it by ~T, steadier on a steady "
     "profile)."),
)
_HISTORY = (
    ("reference", "pupil", "Where the reference image comes from: the spot of the sodium profile "
     "estimated from the whole pupil (pupil), the mean of recent frames (history, the paper's), "
     "a static image given in Python (static) or a model spot at the subaperture centre (model).",
     {"choices": ("pupil", "history", "static", "model")}),
    ("history", 5, "Frames averaged into a history reference.", {"low": 1, "high": 10000}),
    ("include_current", True, "Include the current frame in the history reference."),
    ("update_period", 1, "Frames between reference updates.", {"low": 1, "high": 100000}),
    ("sodium_fwhm_m", 10e3, "Sodium layer FWHM of the model reference, metres.",
     {"low": 0.0, "high": 100e3}),
)

#: the grid of matched filters (gmf, and cmf with filters=grid)
_GRID = (
    ("grid", 5, "Grid of filters: reference positions per axis, odd (5: +-1 px at 0.5 px).",
     {"low": 1, "high": 15}),
    ("spacing_px", 0.5, "Grid of filters: distance between the filters' reference positions, "
     "pixels.", {"low": 0.05, "high": 4.0}),
    ("picks", 2, "Grid of filters: filter choices per block: 1 takes the position nearest the "
     "calibrated CoG; 2 picks again by that filter's measurement (3: once more).",
     {"low": 1, "high": 3}),
)

OPTIONS: dict[str, tuple[Option, ...]] = {
    "cog": _rows("cog", ("background", -1.0, "Background subtracted per pixel, counts "
                         "(-1: the sensor's background_e).", {**_SENSOR, "high": 1e6}),
                 ("bias", "none", "Bias removed from the plain CoG: none (the paper's CoG) or "
                  "pupil (the CoG of each subaperture's spot of the sodium profile estimated "
                  "from the whole pupil).", {"choices": ("none", "pupil")}),
                 ("linearize", True, "With bias pupil: invert the CoG's calibrated response to "
                  "a shift (its bias and the gain lost where the field's edge truncates the "
                  "spot); false: subtract the bias alone."),
                 *_PUPIL),
    "tcog": _rows(
        "tcog",
        ("background", -1.0, "Background subtracted per pixel, counts (-1: the sensor's).",
         {**_SENSOR, "high": 1e6}),
        ("threshold", -1.0, "Threshold in counts (-1: not used). Give one of threshold, "
         "threshold_rn, threshold_frac.", {**_SENSOR, "high": 1e6}),
        ("threshold_rn", -1.0, "Threshold in units of the read noise (-1: not used; 3 when "
         "no threshold is given).", {**_SENSOR, "high": 1e3}),
        ("threshold_frac", -1.0, "Threshold as a fraction of the subaperture's peak (-1: not "
         "used).", {**_SENSOR, "high": 1.0}),
        ("mode", "subtract", "Above the threshold, subtract it from each pixel (subtract) or "
         "only zero the pixels below it (zero).", {"choices": ("subtract", "zero")}),
    ),
    "wcog": _rows(
        "wcog",
        ("background", -1.0, "Background subtracted per pixel, counts (-1: the sensor's).",
         {**_SENSOR, "high": 1e6}),
        ("sodium_fwhm_m", 10e3, "Sodium layer FWHM the weight is shaped for, metres.",
         {"low": 0.0, "high": 100e3}),
        ("gain", "model", "How the weighting's gain loss is corrected.",
         {"choices": ("model", "analytic", "none")}),
    ),
    "cmf": _rows(
        "cmf",
        ("filters", "auto", "Matched filters per subaperture: a grid of them at reference "
         "positions spacing_px apart, the one nearest each spot applied (grid), one at the "
         "reference, its response linearised (single, the paper's kind), or auto (grid with "
         "the pupil reference, single with any other).", {"choices": ("auto", "grid", "single")}),
        *_GRID,
        *_HISTORY,
        ("dither", 0.02, "Shift used to build the filter's derivative images, pixels.",
         {"low": 1e-4, "high": 1.0}),
        ("constrained", True, "Constrain the filter to unit gain and zero cross-talk."),
        ("constraint_px", 1, "Half-width of the constraint's shift grid, pixels.",
         {"low": 1, "high": 4}),
        ("weighting", "auto", "Noise weighting of the filter: the image's own variance "
         "(image), the reference's (model, a filter fixed between reference updates) or auto "
         "(image with a history reference, else model).", {"choices": ("auto", "image", "model")}),
        ("read_noise_e", -1.0, "Read noise in the weighting, e- (-1: the sensor's).",
         {**_SENSOR, "high": 1e3}),
        ("background", -1.0, "Background in the weighting, counts (-1: the sensor's).",
         {**_SENSOR, "high": 1e6}),
        ("var_floor", 1.0, "Smallest pixel variance in the weighting, counts^2.",
         {"low": 1e-6, "high": 1e6}),
        ("derivative", "fourier", "How derivative images are made.",
         {"choices": ("fourier", "dither")}),
        ("linearize", True, "Calibrate the filter's non-linear response on the reference and "
         "invert it every frame (exact to 1e-3 px within +-1 px); applies to fixed references "
         "(pupil, model, static), not to history."),
        ("linearize_extent", 1.1, "Half-width of the calibrated response, pixels.",
         {"low": 0.1, "high": 4.0}),
        *_PUPIL,
    ),
    "corr": _rows(
        "corr", *_HISTORY,
        ("peak", "gauss", "Sub-pixel peak finder.", {"choices": ("parabola", "gauss", "cog")}),
        ("threshold", 0.0, "Correlation threshold as a fraction of the peak, [0, 1).",
         {"low": 0.0, "high": 0.999}),
        ("padding", 2, "Zero-padding factor of the correlation.", {"low": 1, "high": 2}),
        ("subtract_min", False, "Subtract the correlation's minimum before the peak finder."),
        ("background", -1.0, "Background subtracted per pixel, counts (-1: the sensor's).",
         {**_SENSOR, "high": 1e6}),
        *_PUPIL,
    ),
    "ann": _rows("ann", ("model", "", "ONNX model: a name in models/ or a path (empty: the "
                                       "default model).", {"unset": ""}),
                 ("out_of_domain", "refuse", "A sensor with subapertures outside the model's "
                  "training domain (radius, detector, input): refuse to start, with the reason "
                  "(refuse), or run and count them in the description (warn).",
                  {"choices": ("refuse", "warn")}),
                 ("bias", "auto", "Subtract the model's own reading of each subaperture's "
                  "noise-free reference, estimated from the whole pupil at every refit "
                  "(pupil), or not (none); auto: pupil for the models that read column sums "
                  "along e (ann_conv, ann_hyper, ann_marg), none for the others.",
                  {"choices": ("auto", "pupil", "none")}),
                 ("bins", "auto", "How a cartesian block's light reaches a column-sum "
                  "model's bins: each pixel split by its footprint along e (overlap), or "
                  "whole pixels summed along the pixel-grid direction nearest to e, the "
                  "network reading the shift along that direction (grid), or those sums in "
                  "bins sqrt 2 px wide along diagonals, holding the whole block (span); auto: "
                  "what the model was trained on. Polar detectors: unused.",
                  {"choices": ("auto", "overlap", "grid", "span")}),
                 ("recentre", False, "A filters model (ann_conv, ann_grid): read each block "
                  "against its reference moved along the bins by the nearest of -0.5..0.5 px "
                  "(quarter-pixel steps) to its calibrated CoG, filters for each made at every "
                  "refit (false: against the reference alone)."),
                 ("linearize", True, "A model on bins along e with bias pupil (ann_conv, "
                  "ann_grid, ann_hyper, ann_marg): remove the curvature of the network's "
                  "response along the bins, measured at every refit on the noise-free "
                  "calibrated reference moved by -1..1 px, keeping its gain (its slope over "
                  "+-0.5 px); false: the reading less the reading of the reference. Other "
                  "models: unused."),
                 *_PUPIL),
    "ml": _rows("ml", ("step_px", 0.25, "Grid step of the likelihood tables, pixels (a "
                       "parabola through the best grid point refines it).",
                       {"low": 0.01, "high": 1.0}),
                ("extent_px", 2.0, "Largest shift tabulated, pixels (beyond it the "
                 "pupil-calibrated CoG is returned).", {"low": 0.25, "high": 8.0}),
                *_PUPIL),
    "gmf": _rows("gmf", *_GRID,
                 ("background", -1.0, "Background subtracted per pixel and in the weighting, "
                  "counts (-1: the sensor's).", {**_SENSOR, "high": 1e6}),
                 ("read_noise_e", -1.0, "Read noise in the weighting, e- (-1: the sensor's).",
                  {**_SENSOR, "high": 1e3}),
                 ("var_floor", 1.0, "Smallest pixel variance in the weighting, counts^2.",
                  {"low": 1e-6, "high": 1e6}),
                 *_PUPIL),
}


def option(algorithm: str, name: str) -> Option:
    """The row for ``algorithm``'s option ``name``; ValueError naming the allowed ones."""
    rows = {o.name: o for o in OPTIONS.get(algorithm, ())}
    if name not in rows:
        raise ValueError(f"{algorithm}: unknown option {name!r}; allowed: {sorted(rows)}")
    return rows[name]


def coerce(opt: Option, value):
    """``value`` as the option's type, range and choices checked; ValueError with the reason.

    An integer is taken where a float is due (``photons:=1000`` style); nothing else is
    converted.
    """
    kind = opt.kind
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"{opt.parameter} must be {kind.__name__}, got {value!r}")
    if opt.unset is not None and value == opt.unset:
        return value
    if opt.choices and value not in opt.choices:
        raise ValueError(f"{opt.parameter} must be one of {', '.join(map(str, opt.choices))}, "
                         f"got {value!r}")
    if opt.low is not None and value < opt.low or opt.high is not None and value > opt.high:
        raise ValueError(f"{opt.parameter} must be in [{opt.low}, {opt.high}], got {value!r}")
    return value


def from_parameters(algorithm: str, values: Mapping[str, Any]) -> dict:
    """Options for ``algorithm`` from ``{"<algorithm>.<option>": value}`` (other keys are
    ignored); values equal to their sentinel are left out."""
    out = {}
    for opt in OPTIONS[algorithm]:
        if opt.parameter in values:
            value = coerce(opt, values[opt.parameter])
            if opt.unset is None or value != opt.unset:
                out[opt.name] = value
    return out


def defaults(algorithm: str) -> dict:
    """``{option: default}`` for ``algorithm``, sentinel rows left out."""
    return {o.name: o.default for o in OPTIONS[algorithm] if o.unset is None}


def build(algorithm: str, sensor, options: Mapping[str, Any] | None = None):
    """The centroider ``algorithm`` with ``options`` over this table's defaults.

    Raises:
        ValueError: unknown algorithm, unknown option or bad value, with the reason.
    """
    if algorithm not in OPTIONS:
        raise ValueError(f"unknown centroiding algorithm {algorithm!r}; "
                         f"choose one of {', '.join(OPTIONS)}")
    given = dict(options or {})
    for name in given:
        option(algorithm, name)
    return make_centroider(algorithm, sensor, **{**defaults(algorithm), **given})
