"""Training pipeline and shipped models of the neural-network centroiders.

Importing this package needs only numpy: PyTorch (the optional ``train`` extra) is
imported inside the training functions. Modules:

- :mod:`.dataset`: vectorised, streamed training samples (random 5-Gaussian profiles,
  normal positions, photon noise) in the block's pixel axes.
- :mod:`.model`: tanh MLPs (torch) and their numpy weights.
- :mod:`.train`: :func:`train_model` (``lgs-wfs train NAME``).
- :mod:`.export`: ONNX graphs with the ``lgs_wfs.*`` metadata.
- :mod:`.recipes`: the recipe of every shipped model.
- :mod:`.validate`: validation against CoG and CMF, the paper's Table 1 beside ours.
- :mod:`.card`: the model card (``README.md`` of a model directory) from the metadata.

See ``docs/training.md``.
"""

from __future__ import annotations

from .recipes import RECIPES, SHIPPED


def train_model(name, out_dir=None, samples=None, seed=None, quick=False, force=False, **kwargs):
    """Retrain model ``name`` from scratch into ``out_dir`` (needs the ``train`` extra).

    Raises :class:`lgs_wfs_ros.extras.MissingExtra` (one line naming the extra) without
    PyTorch. See :func:`lgs_wfs_ros.learning.train.train_model`.
    """
    from ..extras import require
    require("torch", "train", "lgs-wfs train")
    if name in RECIPES and RECIPES[name].conditioning == "marginals" and RECIPES[name].filters:
        from .hypertrain import train_recipe
        return train_recipe(name, out_dir=out_dir, samples=samples, seed=seed, quick=quick,
                            force=force, **kwargs)
    if name in RECIPES and RECIPES[name].conditioning == "marginals":
        from .margtrain import train_recipe
        return train_recipe(name, out_dir=out_dir, samples=samples, seed=seed, quick=quick,
                            force=force, **kwargs)
    if name in RECIPES and RECIPES[name].conditioning == "reference":
        from .reftrain import train_recipe
        return train_recipe(name, out_dir=out_dir, samples=samples, seed=seed, quick=quick,
                            force=force, **kwargs)
    from .train import train_model as _train
    return _train(name, out_dir=out_dir, samples=samples, seed=seed, quick=quick, force=force,
                  **kwargs)


__all__ = ["train_model", "RECIPES", "SHIPPED"]
