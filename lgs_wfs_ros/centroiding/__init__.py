"""Centroiding algorithms behind one interface, vectorised over subapertures.

``make_centroider(name, sensor, **options)`` returns a :class:`Centroider` whose
``centroid(frame_or_stack)`` gives ``(n_valid, 2)`` slopes in pixels, detector axes,
from the subaperture centre (docs/conventions.md section 2). ``ALGORITHMS`` lists the
names; ``crb`` gives the Cramer-Rao bound for an image model.
"""

from __future__ import annotations

from .ann import ANN
from .ann_model import resolve_model
from .base import Centroider, notice_of
from .cmf import CMF, uses_grid
from .cog import CoG, TCoG, WCoG
from .correlation import Correlation
from .gmf import GMF, GridCMF
from .ml import ML
from .crb import cog_covariance, crb, crb_covariance, crb_of, fisher, model_derivatives

_CLASSES = {"cog": CoG, "tcog": TCoG, "wcog": WCoG, "cmf": CMF, "corr": Correlation, "ann": ANN,
            "ml": ML, "gmf": GMF}
ALGORITHMS = tuple(_CLASSES)


def make_centroider(name: str, sensor, **options) -> Centroider:
    """Build a centroider by registry name.

    Args:
        name: one of :data:`ALGORITHMS`.
        sensor: the :class:`lgs_wfs_ros.sensor.Sensor`.
        **options: algorithm options (see each class); ``None`` values mean "default".
            ``cmf`` is :class:`GridCMF` when its options ask for the grid of filters
            (:func:`.cmf.uses_grid`: the default, with the pupil reference), else
            :class:`CMF`, the single filter.

    Raises:
        ValueError: unknown name or bad option, with the reason.
    """
    if name not in _CLASSES:
        raise ValueError(f"unknown centroiding algorithm {name!r}; choose one of {', '.join(ALGORITHMS)}")
    options = {k: v for k, v in options.items() if v is not None}
    cls = GridCMF if name == "cmf" and uses_grid(options) else _CLASSES[name]
    try:
        return cls(sensor, **options)
    except TypeError as exc:   # e.g. an option of the wrong kind reaching numpy
        raise ValueError(f"{name}: bad options {options}: {exc}") from exc


__all__ = ["ALGORITHMS", "make_centroider", "Centroider", "notice_of", "CoG", "TCoG", "WCoG", "CMF",
           "Correlation", "ANN", "ML", "GMF", "GridCMF", "resolve_model", "cog_covariance", "crb", "crb_covariance", "crb_of", "fisher",
           "model_derivatives"]
