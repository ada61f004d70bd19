"""The sensor description: one frozen dataclass every part of the package takes.

It holds the instrument, atmosphere and detector quantities of section 1 of
``docs/conventions.md`` with their units in the field names. Derived geometry
(valid subapertures, elongation vectors) lives in :mod:`lgs_wfs_ros.optics.geometry`.

A sensor is either the full pupil (``single_subaperture_xy_m is None``: an
``n_subaps x n_subaps`` grid, frame ``(n_subaps*pixels, n_subaps*pixels)``) or one
subaperture centred at a chosen pupil point (frame ``(pixels, pixels)``), the mode the
paper's figures use.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, fields

DETECTORS = ("cartesian", "polar")
DTYPES = ("uint16", "float32")
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0


class SensorError(ValueError):
    """A sensor description that cannot be used, with the reason."""


@dataclass(frozen=True)
class Sensor:
    """A Shack-Hartmann wavefront sensor looking at a sodium laser guide star.

    Every length is in metres, every angle in the unit its name says, counts in
    photo-electrons. Defaults are the TMT-like reference instrument of the contract.
    """

    diameter_m: float = 30.0
    obstruction_m: float = 3.6
    n_subaps: int = 60
    subap_pitch_m: float = 0.5
    pixels: int = 16
    pixel_scale_arcsec: float = 0.5
    wavelength_m: float = 589e-9
    core_fwhm_px: float = 1.19
    launch_xy_m: tuple[float, float] = (0.0, 0.0)
    h_ref_m: float = 90_000.0
    zenith_deg: float = 0.0
    frame_rate_hz: float = 700.0
    r0_m: float = 0.15
    r0_wavelength_m: float = 500e-9
    outer_scale_m: float = math.inf
    wind_speed_mps: float = 10.0
    wind_direction_deg: float = 0.0
    photons: float = 1000.0
    read_noise_e: float = 0.0
    background_e: float = 0.0
    detector: str = "cartesian"
    dtype: str = "uint16"
    valid_fraction: float = 0.5
    single_subaperture_xy_m: tuple[float, float] | None = None

    def __post_init__(self):
        # Normalise sequences (from JSON or ROS parameters) to tuples so the
        # dataclass stays hashable and comparable.
        object.__setattr__(self, "launch_xy_m", tuple(float(v) for v in self.launch_xy_m))
        if self.single_subaperture_xy_m is not None:
            object.__setattr__(self, "single_subaperture_xy_m",
                               tuple(float(v) for v in self.single_subaperture_xy_m))
        problems = self.problems()
        if problems:
            raise SensorError("invalid sensor: " + "; ".join(problems))

    # -- validation ---------------------------------------------------------------
    def problems(self) -> list[str]:
        """Every reason this description is unusable (empty when it is fine)."""
        p = []

        def positive(name):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                p.append(f"{name} must be a finite number > 0, got {v!r}")

        def non_negative(name):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                p.append(f"{name} must be a finite number >= 0, got {v!r}")

        for name in ("diameter_m", "subap_pitch_m", "pixel_scale_arcsec", "wavelength_m",
                     "core_fwhm_px", "h_ref_m", "frame_rate_hz", "r0_m", "r0_wavelength_m",
                     "photons"):
            positive(name)
        for name in ("obstruction_m", "wind_speed_mps", "read_noise_e", "background_e"):
            non_negative(name)
        if not (isinstance(self.outer_scale_m, (int, float)) and self.outer_scale_m > 0):
            p.append(f"outer_scale_m must be > 0 (inf for Kolmogorov), got {self.outer_scale_m!r}")
        if not (isinstance(self.n_subaps, int) and 1 <= self.n_subaps <= 256):
            p.append(f"n_subaps must be an integer in 1..256, got {self.n_subaps!r}")
        if not (isinstance(self.pixels, int) and 2 <= self.pixels <= 64):
            p.append(f"pixels must be an integer in 2..64, got {self.pixels!r}")
        if isinstance(self.obstruction_m, (int, float)) and isinstance(self.diameter_m, (int, float)) \
                and self.obstruction_m >= self.diameter_m:
            p.append("obstruction_m must be smaller than diameter_m")
        if not (isinstance(self.zenith_deg, (int, float)) and 0 <= self.zenith_deg < 80):
            p.append(f"zenith_deg must be in [0, 80), got {self.zenith_deg!r}")
        if not (isinstance(self.valid_fraction, (int, float)) and 0 < self.valid_fraction <= 1):
            p.append(f"valid_fraction must be in (0, 1], got {self.valid_fraction!r}")
        if self.detector not in DETECTORS:
            p.append(f"detector must be one of {DETECTORS}, got {self.detector!r}")
        if self.dtype not in DTYPES:
            p.append(f"dtype must be one of {DTYPES}, got {self.dtype!r}")
        if len(self.launch_xy_m) != 2 or not all(math.isfinite(v) for v in self.launch_xy_m):
            p.append(f"launch_xy_m must be two finite numbers, got {self.launch_xy_m!r}")
        if self.single_subaperture_xy_m is not None and (
                len(self.single_subaperture_xy_m) != 2
                or not all(math.isfinite(v) for v in self.single_subaperture_xy_m)):
            p.append("single_subaperture_xy_m must be None or two finite numbers")
        return p

    # -- derived scalars ---------------------------------------------------------------
    @property
    def is_single(self) -> bool:
        """True for the one-subaperture sensor of the paper's figures."""
        return self.single_subaperture_xy_m is not None

    @property
    def grid(self) -> int:
        """Subapertures per side of the frame (1 in single-subaperture mode)."""
        return 1 if self.is_single else self.n_subaps

    @property
    def frame_shape(self) -> tuple[int, int]:
        """Detector frame shape ``(rows, cols)`` in pixels."""
        n = self.grid * self.pixels
        return (n, n)

    @property
    def pixel_scale_rad(self) -> float:
        """Pixel scale in radians per pixel."""
        return self.pixel_scale_arcsec / ARCSEC_PER_RAD

    @property
    def mas_per_px(self) -> float:
        """Milli-arcseconds per pixel (500 at the default scale)."""
        return self.pixel_scale_arcsec * 1000.0

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.frame_rate_hz

    # -- construction helpers -------------------------------------------------------------
    def replace(self, **changes) -> "Sensor":
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def paper_single(cls, detector: str = "polar", **changes) -> "Sensor":
        """The paper's one-subaperture sensor: the outermost subaperture.

        Polar detector: at (r, 0) with r the outermost subaperture centre radius
        (14.75 m for the default grid), elongation along the pixel rows. Cartesian:
        the same radius on the diagonal, elongation at 45 degrees to the pixel axes.
        """
        base = cls(detector=detector, **changes)
        r = (base.n_subaps - 1) / 2 * base.subap_pitch_m
        xy = (r, 0.0) if detector == "polar" else (r / math.sqrt(2), r / math.sqrt(2))
        xy = (xy[0] + base.launch_xy_m[0], xy[1] + base.launch_xy_m[1])
        return base.replace(single_subaperture_xy_m=xy)

    # -- JSON ------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["launch_xy_m"] = list(self.launch_xy_m)
        if self.single_subaperture_xy_m is not None:
            d["single_subaperture_xy_m"] = list(self.single_subaperture_xy_m)
        if math.isinf(self.outer_scale_m):
            d["outer_scale_m"] = "inf"
        return d

    def to_json(self, **extra) -> str:
        """JSON text of the sensor; ``extra`` keys (seed, profile source...) are added."""
        d = self.to_dict()
        d.update(extra)
        return json.dumps(d, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "Sensor":
        """Build from a dict, ignoring keys that are not sensor fields (seed, ...)."""
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if kw.get("outer_scale_m") in ("inf", "Infinity", None):
            kw["outer_scale_m"] = math.inf
        for k in ("n_subaps", "pixels"):
            if k in kw and isinstance(kw[k], float) and kw[k].is_integer():
                kw[k] = int(kw[k])
        return cls(**kw)

    @classmethod
    def from_json(cls, text: str) -> "Sensor":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SensorError(f"sensor description is not JSON: {exc}") from exc
        if not isinstance(d, dict):
            raise SensorError("sensor description must be a JSON object")
        return cls.from_dict(d)


__all__ = ["Sensor", "SensorError", "DETECTORS", "DTYPES", "ARCSEC_PER_RAD"]
