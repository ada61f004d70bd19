"""Training domains of the models (``lgs_wfs.domain``, see :mod:`..centroiding.domain`).

:func:`recipe_domain` derives a model's domain from what its training recorded: the
training sensor (``lgs_wfs.training.sensor``, else the recipe's), the detectors drawn, the
photons and the profile draw. :func:`train.train_model` writes it into every new model;
:func:`stamp` writes it into an existing file without retraining (how the shipped models
got theirs: ``python -m lgs_wfs_ros.learning.domains models models/paper_prior``).
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np

from ..centroiding import domain
from ..optics import geometry
from ..sensor import Sensor
from . import export, recipes, refdata

PRIORS = {
    "mvn": "random 5-Gaussian profiles, joint normal fitted to measured profiles 0-65",
    "independent": "random 5-Gaussian profiles, independent normals per parameter (the paper's "
                   "draw) fitted to measured profiles 0-65",
    "mix": "random 5-Gaussian profiles fitted to measured profiles 0-65: a fraction {f:g} with "
           "independent normals (the paper's draw), the rest joint normal",
}


def _sensor(rec: recipes.Recipe, training: dict | None) -> Sensor:
    sensor = (training or {}).get("sensor")
    if not sensor:
        raise ValueError(f"{rec.name}: the training metadata records no sensor; its domain is unknown")
    return Sensor.from_dict(sensor)


def recipe_domain(rec: recipes.Recipe, training: dict | None = None) -> dict:
    """The ``lgs_wfs.domain`` record of a model trained by ``rec`` (its recorded training
    ``training`` metadata, when given, supplies the sensor)."""
    if rec.conditioning == "reference":          # ann_ref: its sampled ranges, not a sensor's
        return reference_domain(rec)
    if rec.conditioning == "marginals":          # ann_marg, ann_conv: the same ranges, their detectors
        trained = ((training or {}).get("recipe") or {}).get("detectors") or rec.detectors
        return marginal_domain(detectors=trained)
    sensor = _sensor(rec, training)
    lay = geometry.layout(sensor)
    r = np.asarray(lay.r_m, dtype=float)
    dom = {"radius_m": [round(float(r.min()), 4), round(float(r.max()), 4)],
           "detector": sorted(set(rec.detectors)) if rec.pupil else [rec.detector],
           "photons": None if rec.photons is None else [float(rec.photons)] * 2,
           "profile_prior": PRIORS[rec.profile_model].format(f=rec.mix_fraction),
           "input": {"none": "image", "e": "image+e", "e_r": "image+e_r"}[rec.conditioning],
           "launch_xy_m": list(sensor.launch_xy_m)}
    if not rec.pupil and rec.detector == "cartesian":
        e = np.asarray(lay.e, dtype=float)[0]
        a = round(float(np.degrees(np.arctan2(e[1], e[0]))), 3)
        dom["e_angle_deg"] = [a, a]
    if rec.photons is None and rec.noise_penalty_photons is not None:
        dom["noise_model"] = f"noise-free images, first-order Poisson penalty at {rec.noise_penalty_photons:g} photons"
    return dom


#: the share of the prior's draws each declared profile range leaves out at each end
PROFILE_TAIL = 0.01
PROFILE_DRAWS = 4000


@functools.lru_cache(maxsize=4)
def profile_ranges(prior: refdata.PriorSpec) -> dict:
    """``{"profile_centroid_km": [lo, hi], "profile_fwhm_km": [lo, hi]}``: the central 98 %
    of ``PROFILE_DRAWS`` profiles of ``prior`` (a fixed draw), rounded outward to 0.1 km.
    The draws' own spread, not the prior's nominal ranges: double peaks and sporadic layers
    move a profile's centroid and width beyond the ranges its main layer is drawn in.
    Cached (~2 s a draw); callers must not mutate the result's lists."""
    prof = refdata.broad_profiles(np.random.default_rng(0), PROFILE_DRAWS, prior)
    out = {}
    for key, values in zip(domain.PROFILE_KEYS, zip(*(domain.profile_moments(refdata.GRID, p)
                                                      for p in prof))):
        lo, hi = np.quantile(values, [PROFILE_TAIL, 1.0 - PROFILE_TAIL])
        out[key] = [float(np.floor(lo * 10) / 10), float(np.ceil(hi * 10) / 10)]
    return out


def reference_domain(rec: recipes.Recipe, prior: refdata.PriorSpec = refdata.PriorSpec()) -> dict:
    """The domain of a reference-reading recipe: the ranges its pairs were drawn from."""
    return {"radius_m": list(prior.radius_m), "detector": ["cartesian", "polar"],
            "photons": list(prior.photons), "profile_prior": prior.describe(),
            **{k: list(v) for k, v in profile_ranges(prior).items()},
            "input": "image+reference",
            "reference": "the spot of the sodium profile estimated by the pupil calibration "
                         "(centroiding/pupil.py), trained with stale, node-sampled, noisy references"}


def marginal_domain(prior: refdata.PriorSpec = refdata.MARGINAL_SPEC, detectors=("polar",)) -> dict:
    """The domain of a network on the light in bins along e (``ann_marg``, ``ann_conv``): its
    spots' ranges and the detectors it was trained on (on a cartesian one the bins split each
    pixel by its overlap, :mod:`..centroiding.bins_along_e`)."""
    return {**reference_domain(None, prior), "detector": sorted(set(detectors)),
            "input": "marginals+reference"}


def stamp(path) -> dict:
    """Write the domain of the model file ``path`` (named after its recipe) into its
    metadata, from its recorded training; returns the domain."""
    path = Path(path)
    rec = recipes.get(path.stem)
    training = export.read_metadata(path).get("lgs_wfs.training")
    dom = recipe_domain(rec, training)
    export.update_metadata(path, {"lgs_wfs.domain": dom})
    return dom


def main(argv=None) -> int:
    """Stamp every recipe-named ``*.onnx`` in the given directories."""
    for d in (argv if argv is not None else sys.argv[1:]):
        for f in sorted(Path(d).glob("*.onnx")):
            if f.stem in recipes.RECIPES:
                print(f, stamp(f))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
