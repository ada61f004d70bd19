"""The common centroider interface: input checks, bad-subaperture masking, axes.

Every centroider takes one detector frame ``(G*p, G*p)`` or a subaperture stack
``(n_valid, p, p)`` (any real dtype) and returns ``(n_valid, 2)`` float64 slopes in
pixels, detector axes (x = column, y = row), measured from the subaperture centre
``((p-1)/2, (p-1)/2)`` = (7.5, 7.5) for 16 pixels (docs/conventions.md, section 2).

A subaperture whose pixels contain NaN/inf, or whose total is zero or negative, gets a
NaN slope; the other subapertures of the frame are unaffected. A wrong shape raises
``ValueError``.

Polar detector: each block is sampled in its local frame (local x along the elongation
vector ``e``), so algorithms compute in block pixel axes and :meth:`Centroider.to_detector`
rotates the result back with :func:`lgs_wfs_ros.optics.geometry.local_to_detector`.
"""

from __future__ import annotations

import copy

import numpy as np

from ..optics import geometry
from ..sensor import Sensor
from .altitude import AltitudeTracker


class Centroider:
    """Base class. Subclasses implement :meth:`_centroid_pixels`.

    Attributes:
        name: the registry name ("cog", "cmf", ...).
        sensor: the :class:`Sensor`.
        layout: its :class:`geometry.Layout`.
        options: the options dict, as validated (JSON-able).
        pupil: the :class:`.pupil.PupilCalibration` an estimator calibrates from, or None.
    """

    name = "base"
    pupil = None          # set by the estimators that use a pupil calibration
    _altitude = None      # their AltitudeTracker, made at the first frame that needs it
    _drift = None         # (n, 2) block axes, px: see _follow_drift

    def __init__(self, sensor: Sensor, **options):
        if not isinstance(sensor, Sensor):
            raise ValueError(f"sensor must be a Sensor, got {type(sensor).__name__}")
        self.sensor = sensor
        self.layout = geometry.layout(sensor)
        self.options = dict(options)

    # -- geometry helpers -------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of valid subapertures."""
        return self.layout.n_valid

    @property
    def p(self) -> int:
        """Pixels per subaperture side."""
        return self.sensor.pixels

    @property
    def centre(self) -> float:
        """Pixel coordinate of the subaperture centre, ``(p - 1) / 2``."""
        return (self.sensor.pixels - 1) / 2.0

    @property
    def polar(self) -> bool:
        return self.sensor.detector == "polar"

    @property
    def e_pixel(self) -> np.ndarray:
        """``(n, 2)`` elongation unit vector in the block's pixel axes.

        ``(1, 0)`` everywhere on a polar detector (local frame), ``layout.e`` on a
        cartesian one.
        """
        if self.polar:
            e = np.zeros((self.n, 2))
            e[:, 0] = 1.0
            return e
        return np.asarray(self.layout.e, dtype=float)

    def to_detector(self, v: np.ndarray) -> np.ndarray:
        """``(..., n, 2)`` vectors in block pixel axes -> detector axes."""
        if self.polar:
            return geometry.local_to_detector(v, self.layout.e)
        return v

    def to_pixel_axes(self, v: np.ndarray) -> np.ndarray:
        """``(..., n, 2)`` detector-axes vectors -> block pixel axes."""
        if self.polar:
            return geometry.detector_to_local(v, self.layout.e)
        return v

    # -- input ----------------------------------------------------------------------
    def as_stack(self, data) -> np.ndarray:
        """Frame or stack -> ``(n, p, p)`` array (a view or copy, never the input mutated).

        Raises:
            ValueError: not a frame of this sensor nor an ``(n_valid, p, p)`` stack.
        """
        data = np.asarray(data)
        if data.dtype.kind not in "uif":
            raise ValueError(f"data must be a real numeric array, got dtype {data.dtype}")
        n, p = self.n, self.p
        if data.shape == self.sensor.frame_shape:
            return geometry.frame_to_stack(data, self.layout)
        if data.shape == (n, p, p):
            return data
        raise ValueError(
            f"data has shape {data.shape}; expected a frame {self.sensor.frame_shape} "
            f"or a subaperture stack {(n, p, p)}")

    def frame_rows(self, data) -> np.ndarray | None:
        """Every block of a detector frame as float rows, in one cast-and-cut pass.

        Cutting out only the valid blocks (a gather) and then converting them costs two
        passes over the data; casting the whole block grid at once costs one, and the
        ~30 % of blocks outside the pupil are cheaper to compute and drop than to gather.

        Args:
            data: anything; only a ``(G*p, G*p)`` real frame of this sensor is handled.

        Returns:
            ``(G*G, p*p)`` rows (float64 for a float64 frame, else float32; select the
            valid ones with :attr:`valid_rows`) in a buffer this instance reuses at the
            next call (never give it out), or None when ``data`` is not such a frame.
        """
        data = np.asarray(data)
        if data.shape != self.sensor.frame_shape or data.dtype.kind not in "uif":
            return None
        g, p = self.layout.grid, self.p
        dt = np.float64 if data.dtype == np.float64 else np.float32
        bufs = self.__dict__.setdefault("_row_buffers", {})
        if dt not in bufs:
            bufs[dt] = np.empty((g * g, p * p), dtype=dt)
        np.copyto(bufs[dt].reshape(g, g, p, p), data.reshape(g, p, g, p).swapaxes(1, 2),
                  casting="unsafe")
        return bufs[dt]

    @property
    def valid_rows(self) -> np.ndarray:
        """``(n,)`` indices of the valid subapertures among :meth:`frame_rows`' rows."""
        if "_valid_rows" not in self.__dict__:
            self._valid_rows = np.flatnonzero(np.asarray(self.layout.valid).ravel())
        return self._valid_rows

    def pad_rows(self, a: np.ndarray, fill=0) -> np.ndarray:
        """``(n, ...)`` per-subaperture array -> ``(G*G, ...)`` (``fill`` outside the pupil)."""
        out = np.full((self.layout.grid ** 2,) + a.shape[1:], fill, dtype=a.dtype)
        out[self.valid_rows] = a
        return out

    def float_stack(self, data) -> np.ndarray:
        """Frame or stack -> ``(n, p, p)`` float32 (float64 if the input is float64).

        May be the caller's array itself (never written to) when it already is a float
        stack; bad subapertures are not cleaned.
        """
        stack = self.as_stack(data)
        dtype = np.float64 if stack.dtype == np.float64 else np.float32
        return stack.astype(dtype, copy=False)

    def _copy_on(self, calibration, **attrs) -> "Centroider":
        """A shallow copy of this estimator reading ``calibration`` (a background refit's
        snapshot), with ``attrs`` set on the copy: what a refit's thread builds the new
        tables on, so that nothing the frame path reads is written."""
        sh = copy.copy(self)
        sh.pupil = calibration
        sh.__dict__.update(attrs)
        return sh

    def _take_refit(self, install) -> None:
        """At a pupil refit: swap in what a background refit's thread built (its payload, a
        dict of attributes; a new ``ref`` keeps this one's frame count), else ``install()``
        now (inline refits, or no ``prepare`` delegated)."""
        payload, self.pupil.payload = self.pupil.payload, None
        if payload is None:
            install()
            return
        if "ref" in payload:
            payload["ref"].frames = self.ref.frames
        self.__dict__.update(payload)

    def _follow_drift(self, read) -> None:
        """At a refit: how this estimator's reading of a spot at the true centre moves from
        the middle of the period the refit serves to its end, as the calibration's trend
        drifts the profile (``read(counts (n, p, p)) -> (n, 2)`` block axes, px, of noise-free
        counts, nothing fed to the calibration: of :meth:`.PupilCalibration.drift_counts`
        less of the reference's counts). :meth:`finish` removes it in proportion to
        :meth:`.PupilCalibration.drift_phase`; None without a trend."""
        drifted = self.pupil.drift_counts() if self.pupil is not None else None
        if drifted is None:
            self._drift = None
            return
        with np.errstate(divide="ignore", invalid="ignore"):
            moved = np.asarray(read(drifted), dtype=np.float64) - read(self.pupil.reference_counts())
        self._drift = np.nan_to_num(moved, nan=0.0, posinf=0.0, neginf=0.0)

    def _drift_term(self, pending: int = 0):
        """``(n, 2)`` block axes, px: the part of :meth:`_follow_drift`'s move due now (0
        without one; ``pending`` as :meth:`.PupilCalibration.drift_phase`'s)."""
        if self._drift is None or self.pupil is None:
            return 0.0
        return self.pupil.drift_phase(pending) * self._drift

    def finish(self, out: np.ndarray, ok: np.ndarray, drift: bool = True) -> np.ndarray:
        """Block-pixel-axes ``(n, 2)`` -> detector axes float64, NaN where not ``ok``; with a
        pupil calibration, less the profile's drift since the middle of the refit's period
        (:meth:`_follow_drift`; ``drift=False``: the caller removed it) and, with
        ``altitude_s`` set, corrected for the sodium altitude's drift since its last refit
        (:class:`.altitude.AltitudeTracker`)."""
        if drift and self._drift is not None:
            out = out - self._drift_term()
        out = np.asarray(self.to_detector(out), dtype=np.float64)
        out[~ok] = np.nan
        pupil = self.pupil
        if pupil is not None and pupil.altitude_s > 0 and out.ndim == 2:
            if self._altitude is None:
                self._altitude = AltitudeTracker(
                    self.layout, pupil.altitude_s, self.sensor.frame_rate_hz, self.to_detector)
            out = self._altitude.apply(out, ok, pupil)
        return out

    def prepare(self, data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame or stack -> (clean float stack, total, ok).

        Returns:
            stack: ``(n, p, p)`` float32 (float64 if the input was float64), never the
                caller's array when bad subapertures had to be zeroed (so they cannot
                poison vectorised maths); treat it as read-only.
            total: ``(n,)`` float64 sum of each subaperture (counts).
            ok: ``(n,)`` bool, finite pixels and total > 0.
        """
        stack = self.float_stack(data)
        total = stack.reshape(self.n, -1).sum(axis=1).astype(np.float64)
        ok = np.isfinite(total) & (total > 0)
        if not ok.all():
            stack = stack.copy()
            stack[~ok] = 0
        return stack, total, ok

    # -- public API -------------------------------------------------------------------
    def centroid(self, data) -> np.ndarray:
        """Slopes of one frame.

        Args:
            data: ``(G*p, G*p)`` frame or ``(n_valid, p, p)`` stack, counts, any real dtype.

        Returns:
            ``(n_valid, 2)`` float64 slopes (sx, sy), pixels, detector axes; NaN rows for
            bad subapertures.
        """
        stack, total, ok = self.prepare(data)
        return self.finish(self._centroid_pixels(stack, total, ok), ok)

    def centroid_many(self, frames) -> np.ndarray:
        """Slopes of ``k`` frames in time order, as ``k`` calls of :meth:`centroid`.

        Args:
            frames: ``(k, G*p, G*p)`` frames or ``(k, n_valid, p, p)`` stacks (or a list).

        Returns:
            ``(k, n_valid, 2)`` slopes, pixels, detector axes. Stateless algorithms override
            this with one vectorised call (a node drains several small frames at once);
            stateful ones (a history reference) see the frames one by one.
        """
        out = [self.centroid(f) for f in frames]
        return np.stack(out) if out else np.empty((0, self.n, 2))

    def many_stacks(self, frames) -> np.ndarray | None:
        """``(k, n, p, p)`` stacks of ``k`` frames or stacks of this sensor (integer or float,
        as given), or None when ``frames`` is not that (the caller then falls back to
        :meth:`centroid` per frame, which raises the usual errors)."""
        frames = np.asarray(frames)
        if frames.dtype.kind not in "uif" or frames.ndim < 3:
            return None
        if frames.ndim == 3 and frames.shape[1:] == self.sensor.frame_shape:
            return geometry.frame_to_stack(frames, self.layout)
        if frames.shape[1:] == (self.n, self.p, self.p):
            return frames
        return None

    def _centroid_pixels(self, stack, total, ok) -> np.ndarray:
        """``(n, 2)`` slopes in block pixel axes. Bad rows may hold anything."""
        raise NotImplementedError

    def reset(self) -> None:
        """Forget any state kept between frames (no-op for stateless algorithms)."""

    @property
    def notice(self) -> str:
        """What the estimator learned while running that its user should hear ('' for
        nothing): e.g. a network's sky outside its training profiles. A node logs each
        change once and republishes :meth:`describe`."""
        return ""

    def describe(self) -> dict:
        """JSON-able description for the node's ``centroider`` topic."""
        return {"algorithm": self.name, "options": _jsonable(self.options),
                "detector": self.sensor.detector, "pixels": self.sensor.pixels,
                "n_valid": self.n}


def notice_of(centroider) -> str:
    """``centroider.notice`` ('' for an object without one: a stand-in, or a user's
    centroider written before notices existed)."""
    return str(getattr(centroider, "notice", "") or "")


def _jsonable(x):
    """Options -> JSON-able values (arrays become lists, paths strings)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)


def check_options(name: str, options: dict, allowed) -> None:
    """Raise ``ValueError`` naming any option the algorithm does not take."""
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown}; allowed: {sorted(allowed)}")


def number(name: str, value, *, minimum=None, strict=False, integer=False) -> float:
    """Validate a scalar option, returning it as float (or int)."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    ok = ok and np.isfinite(value)
    if ok and integer:
        ok = float(value).is_integer()
    if ok and minimum is not None:
        ok = value > minimum if strict else value >= minimum
    if not ok:
        kind = "an integer" if integer else "a finite number"
        bound = "" if minimum is None else f" {'>' if strict else '>='} {minimum}"
        raise ValueError(f"option {name} must be {kind}{bound}, got {value!r}")
    return int(value) if integer else float(value)


def flag(name: str, value) -> bool:
    """Validate a true/false option, returning it as bool."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"option {name} must be true or false, got {value!r}")
    return bool(value)


def choice(name: str, value, allowed) -> str:
    if value not in allowed:
        raise ValueError(f"option {name} must be one of {list(allowed)}, got {value!r}")
    return value


def pixel_coords(p: int, centre: float) -> tuple[np.ndarray, np.ndarray]:
    """``(p*p,)`` x (column) and y (row) offsets of each pixel from ``centre``, row-major."""
    y, x = np.indices((p, p), dtype=float)
    return (x - centre).ravel(), (y - centre).ravel()



def all_columns(mask: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: rows of ``mask (n, k)`` true in every column, by ``k`` 1-D ands
    (numpy's ``all(axis=1)`` over a short axis is ~10x slower: 0.04 ms for 2,784 x 2,
    a sixth of the plain CoG's whole frame)."""
    out = mask[:, 0].copy()
    for j in range(1, mask.shape[1]):
        out &= mask[:, j]
    return out


def finite_rows(x: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: rows of ``x (n, k)`` with every value finite."""
    return all_columns(np.isfinite(x))
