"""Training pipeline and shipped models of the neural-network centroiders.

Importing this package needs only numpy: PyTorch (the optional ``train`` extra) is
imported inside the training functions. Modules:

- :mod:`.dataset`: vectorised, streamed training samples (random 5-Gaussian profiles,
  normal positions, photon noise) in the block's pixel axes.
- :mod:`.model`: tanh MLPs (torch) and their numpy weights.
- :mod:`.lm`: Levenberg-Marquardt for the paper's 256-16-2 networks.
- :mod:`.train`: :func:`train_model` (``lgs-wfs train NAME``).
- :mod:`.export`: ONNX graphs with the ``lgs_wfs.*`` metadata.
- :mod:`.recipes`: the recipe of every shipped model.
- :mod:`.validate`: validation against CoG and CMF, the paper's Table 1 beside ours.

See ``docs/training.md``.
"""

from __future__ import annotations

from .recipes import RECIPES, SHIPPED


def train_model(name, out_dir="models", samples=None, seed=None, quick=False, **kwargs):
    """Retrain model ``name`` from scratch into ``out_dir`` (needs PyTorch).

    See :func:`lgs_wfs_ros.learning.train.train_model`.
    """
    try:
        import torch  # noqa: F401
    except ImportError as exc:   # pragma: no cover - depends on the environment
        raise RuntimeError("training needs PyTorch: pip install '.[train]' "
                           "(torch CPU)") from exc
    from .train import train_model as _train
    return _train(name, out_dir=out_dir, samples=samples, seed=seed, quick=quick, **kwargs)


__all__ = ["train_model", "RECIPES", "SHIPPED"]
