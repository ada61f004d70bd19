"""The training domain of a neural-network model, and the check of a sensor against it.

A network is only trustworthy where it was trained. Each model records its domain in the
ONNX metadata key ``lgs_wfs.domain`` (a JSON object):

=================  ================================================================================
``radius_m``       ``[lo, hi]``: distance of the subaperture centre from the launch, metres
``detector``       list of detector types trained on (``["polar"]``, ``["polar", "cartesian"]``)
``photons``        ``[lo, hi]``: photons per subaperture of the training images (equal ends: one
                   level; ``null``: noise-free training)
``profile_prior``  one sentence: the sodium profiles trained on
``input``          ``"image"`` (pixels only) | ``"image+e"`` / ``"image+e_r"`` (pixels, e (and r)) |
                   ``"image+reference"`` (pixels and the subaperture's current reference)
``e_angle_deg``    optional ``[lo, hi]``: angle of the elongation in detector axes, degrees, for
                   cartesian single-subaperture models (a cartesian network sees e's direction)
``profile_centroid_km``  optional ``[lo, hi]``: the training profiles' centroid altitudes, km
                   (models that read the pupil calibration's reference: the sky is checked
                   against it at each refit, :func:`check_profile`)
``profile_fwhm_km``      optional ``[lo, hi]``: their widths, km, as FWHM = 2.355 x the rms
                   width (the training prior's own measure of a width, ``learning/refdata.py``)
=================  ================================================================================

:func:`check` returns a :class:`DomainCheck`: which subapertures are outside, and why. The
centroider (:class:`.ann.ANN`) refuses a sensor with any out-of-domain subaperture unless
its option ``out_of_domain`` is ``"warn"``, and then reports the count in ``describe()``.

The sky is checked too, where a model declares the profiles it was trained on and reads the
pupil calibration's reference: after each refit the calibrated profile's centroid and width
are compared with those ranges (:func:`check_profile`). A sky cannot be refused (it changes
under a running node), so a profile outside them is a warning in ``describe()`` and the
count of refits that found it so; the node logs it once each time the sky leaves the
domain, and again when it is back.

Photons are reported but never refuse: the pixel input is normalised by its total, so a
network trained at one level runs at another with that level's noise (the paper applies its
1000-photon networks at 316 photons in its Table 1); the check says so in its warnings.

A model without ``lgs_wfs.domain`` (a user's model, or one written before domains were
recorded) is run unchecked: :func:`check` returns ``known = False`` and a warning saying the
model declares no domain, and ``describe()`` carries that warning. Refusing it would break
every older model; silently trusting it is what this module exists to stop, so the warning
is always there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..optics import geometry, sodium
from ..optics.gaussian_spot import FWHM_PER_SIGMA

INPUT_KINDS = ("image", "image+e", "image+e_r", "image+reference", "marginals+reference")
PROFILE_KEYS = ("profile_centroid_km", "profile_fwhm_km")
RADIUS_TOL_M = 1e-3           # float slack on the radius range (layout radii are rounded sums)
ANGLE_TOL_DEG = 0.5


@dataclass
class DomainCheck:
    """Result of checking a sensor against a model's domain.

    Attributes:
        known: the model declares a domain.
        outside: ``(n,)`` bool, valid subapertures outside the domain.
        reasons: one sentence per failed criterion (empty: inside).
        warnings: sentences that do not refuse (photons, no domain declared).
    """

    known: bool
    outside: np.ndarray
    reasons: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    @property
    def count(self) -> int:
        """Number of valid subapertures outside the domain."""
        return int(np.count_nonzero(self.outside))

    @property
    def ok(self) -> bool:
        return not self.reasons

    def summary(self) -> dict:
        """JSON-able record for ``describe()``."""
        return {"known": self.known, "out_of_domain_subapertures": self.count,
                "subapertures": int(self.outside.size), "reasons": list(self.reasons),
                "warnings": list(self.warnings)}


def parse(raw) -> dict | None:
    """The domain record from the decoded ``lgs_wfs.domain`` value (None: not declared).

    Raises:
        ValueError: a malformed record (wrong keys, ranges, input kind), with the reason.
    """
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ValueError(f"ann: metadata lgs_wfs.domain must be a JSON object, got {raw!r}")
    d = dict(raw)
    for key in ("radius_m", "detector", "input"):
        if key not in d:
            raise ValueError(f"ann: metadata lgs_wfs.domain lacks {key!r}")
    for key in ("radius_m", "photons", "e_angle_deg", *PROFILE_KEYS):
        v = d.get(key)
        if v is None:
            continue
        if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(a, (int, float)) for a in v)
                and v[0] <= v[1]):
            raise ValueError(f"ann: metadata lgs_wfs.domain.{key} must be [lo, hi] with lo <= hi, got {v!r}")
        d[key] = [float(v[0]), float(v[1])]
    det = d["detector"]
    det = [det] if isinstance(det, str) else list(det)
    if not det or any(x not in ("polar", "cartesian") for x in det):
        raise ValueError(f"ann: metadata lgs_wfs.domain.detector must list polar/cartesian, got {d['detector']!r}")
    d["detector"] = det
    if d["input"] not in INPUT_KINDS:
        raise ValueError(f"ann: metadata lgs_wfs.domain.input must be one of {list(INPUT_KINDS)}, "
                         f"got {d['input']!r}")
    return d


def describe_range(lo: float, hi: float, unit: str) -> str:
    return f"{lo:g} {unit}" if lo == hi else f"{lo:g}-{hi:g} {unit}"


def check(domain: dict | None, sensor, model: str = "model", input_kind: str | None = None) -> DomainCheck:
    """Check every valid subaperture of ``sensor`` against ``domain`` (:func:`parse`'s).

    Args:
        domain: the parsed record, or None (not declared).
        sensor: the :class:`lgs_wfs_ros.sensor.Sensor`.
        model: the model's name, for the messages.
        input_kind: what the centroider will feed (checked against ``domain["input"]``).

    Returns:
        :class:`DomainCheck`; ``reasons`` name the model, the trained range and the
        sensor's range, e.g. "ann_1k was trained at r = 14.75 m; 2776 of 2784 subapertures
        of this sensor lie at 0.35-14.9 m from the launch".
    """
    lay = geometry.layout(sensor)
    r = np.asarray(lay.r_m, dtype=float)
    n = r.size
    if domain is None:
        return DomainCheck(False, np.zeros(n, dtype=bool), [],
                           [f"{model} declares no training domain (no lgs_wfs.domain metadata): "
                            f"run unchecked"])
    out = np.zeros(n, dtype=bool)
    reasons, warnings = [], []
    if sensor.detector not in domain["detector"]:
        out[:] = True
        reasons.append(f"{model} was trained on a {'/'.join(domain['detector'])} detector; "
                       f"the sensor is {sensor.detector}")
    lo, hi = domain["radius_m"]
    bad = (r < lo - RADIUS_TOL_M) | (r > hi + RADIUS_TOL_M)
    if bad.any():
        out |= bad
        reasons.append(f"{model} was trained at r = {describe_range(lo, hi, 'm')} from the launch; "
                       f"{int(bad.sum())} of {n} subapertures of this sensor lie outside it "
                       f"(its radii run {r.min():.2f}-{r.max():.2f} m)")
    ang = domain.get("e_angle_deg")
    if ang is not None and sensor.detector == "cartesian":
        a = np.degrees(np.arctan2(lay.e[:, 1], lay.e[:, 0]))
        mid, half = 0.5 * (ang[0] + ang[1]), 0.5 * (ang[1] - ang[0]) + ANGLE_TOL_DEG
        bad = np.abs((a - mid + 180.0) % 360.0 - 180.0) > half
        if bad.any():
            out |= bad
            reasons.append(f"{model} was trained with the elongation at "
                           f"{describe_range(ang[0], ang[1], 'deg')} on a cartesian detector; "
                           f"{int(bad.sum())} of {n} subapertures have it elsewhere")
    if input_kind is not None and input_kind != domain["input"]:
        out[:] = True
        reasons.append(f"{model} takes input {domain['input']!r}; the centroider feeds {input_kind!r}")
    ph = domain.get("photons")
    if ph is None:
        warnings.append(f"{model} was trained on noise-free images")
    elif not (ph[0] * 0.999 <= sensor.photons <= ph[1] * 1.001):
        warnings.append(f"{model} was trained at {describe_range(ph[0], ph[1], 'photons')}; the "
                        f"sensor has {sensor.photons:g} (sum-normalised input: runs, with that "
                        f"level's noise; not refused)")
    return DomainCheck(True, out, reasons, warnings)


def profile_moments(altitude_m, density) -> tuple[float, float]:
    """``(centroid_km, fwhm_km)`` of a sodium profile: ``density (K,)`` (any scale) on
    ``altitude_m (K,)`` ascending, m; the width as FWHM = 2.355 x the rms width (a Gaussian
    layer's FWHM; the measure the training prior draws widths in)."""
    c = sodium.centroid_altitude(altitude_m, density)
    w = sodium.rms_width(altitude_m, density)
    return float(c) / 1e3, float(w) * FWHM_PER_SIGMA / 1e3


@dataclass
class ProfileCheck:
    """A calibrated profile against a model's profile ranges.

    Attributes:
        centroid_km, fwhm_km: the profile's centroid altitude and width (km).
        limits: one sentence per range it falls outside, the range alone (empty: inside):
            the same while the profile stays outside, however it moves there.
        reasons: each limit with the profile's value.
    """

    centroid_km: float
    fwhm_km: float
    limits: list = field(default_factory=list)
    reasons: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.reasons

    def summary(self) -> dict:
        """JSON-able record for ``describe()``."""
        return {"centroid_km": round(self.centroid_km, 2), "fwhm_km": round(self.fwhm_km, 2),
                "inside": self.ok, "reasons": list(self.reasons)}


def check_profile(domain: dict | None, altitude_m, density, model: str = "model") -> ProfileCheck | None:
    """The profile ``density (K,)`` on ``altitude_m (K,)`` m (the pupil calibration's) against
    ``domain``'s ``profile_centroid_km`` and ``profile_fwhm_km`` (:func:`parse`'s record);
    None when the domain declares neither. A range is ``[lo, hi]`` km, ends included."""
    if domain is None or not any(domain.get(k) is not None for k in PROFILE_KEYS):
        return None
    centroid, fwhm = profile_moments(altitude_m, density)
    limits, reasons = [], []
    for key, value, what in (("profile_centroid_km", centroid, "centroid"),
                             ("profile_fwhm_km", fwhm, "FWHM")):
        rng = domain.get(key)
        if rng is not None and not (rng[0] <= value <= rng[1]):
            limits.append(f"{model} was trained on sodium profiles of {what} "
                          f"{describe_range(rng[0], rng[1], 'km')}")
            reasons.append(f"{limits[-1]}; the calibrated profile's is {value:.1f} km")
    return ProfileCheck(centroid, fwhm, limits, reasons)


__all__ = ["INPUT_KINDS", "PROFILE_KEYS", "DomainCheck", "ProfileCheck", "parse", "check",
           "check_profile", "profile_moments"]
