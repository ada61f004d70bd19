"""Train and export the reference-reading network (``ann_ref``).

Network: a tanh MLP on ``[G (image - reference), G reference]`` (``G = p*p``: mean pixel
1; both sum-normalised, block pixel axes) -> the shift of the image from the reference, px,
block pixel axes. Exported (opset 17) as

    pixels (batch, p*p) --MatMul Wp--+
                                     +-- Add b0 -> tanh -> ... -> slopes (batch, 2)
    reference (batch, p*p) --MatMul Wr

with ``Wp = G Wd`` and ``Wr = G (Wref - Wd)``: the reference enters the first layer only,
linearly, so the centroider computes ``reference @ Wr`` once per calibration refit and a
frame costs one ``(n, p*p) x (p*p, h)`` product, like the paper's networks
(:func:`..centroiding.ann_model.split_reference`). Metadata: ``lgs_wfs.conditioning =
"reference"``, ``lgs_wfs.output_frame = "block"``, ``lgs_wfs.domain`` (input
``image+reference``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from . import domains, export, recipes, refdata
from .model import layers_of, mlp, n_parameters

REF_INPUT = "reference"
MONITOR_SEED = 55_555
CHECK_SEED, CHECK_N = 90_002, 2000      # the fixed check set whose error the metadata records


def features(p: refdata.Pairs, gain: float) -> np.ndarray:
    """``(n, 2 p*p)`` float32 network input."""
    return np.concatenate([(p.images - p.refs) * gain, p.refs * gain], axis=1).astype(np.float32)


def generate(n: int, seed: int, batch: int = 4096, progress: bool = True) -> refdata.Pairs:
    """``n`` pairs, batch ``k`` from ``default_rng([seed, k])`` (reproducible)."""
    from tqdm.auto import tqdm
    parts = []
    with tqdm(total=n, desc="pairs", unit="spot", disable=not progress, mininterval=5.0) as bar:
        k = 0
        while sum(len(q.y) for q in parts) < n:
            m = min(batch, n - sum(len(q.y) for q in parts))
            parts.append(refdata.pairs(np.random.default_rng([seed, k]), m))
            k += 1
            bar.update(m)
    return refdata.Pairs(*[np.concatenate([getattr(q, f) for q in parts])
                           for f in ("images", "refs", "y", "r_m", "e_pix", "photons")])


def build_model(layers, pixels: int, gain: float, metadata: dict, name: str = "ann_ref"):
    """ONNX ``ModelProto`` (see the module doc) from trained ``[(W (in, out), b), ...]``."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    npx = pixels * pixels
    w0, b0 = layers[0]
    wd, wref = w0[:npx], w0[npx:]
    inits = [numpy_helper.from_array((wd * gain).astype(np.float32), "Wp"),
             numpy_helper.from_array(((wref - wd) * gain).astype(np.float32), "Wr")]
    nodes = [helper.make_node("MatMul", [export.INPUT_NAME, "Wp"], ["zp"]),
             helper.make_node("MatMul", [REF_INPUT, "Wr"], ["zr"]),
             helper.make_node("Add", ["zp", "zr"], ["z0s"])]
    more, more_inits, _ = export.tanh_layers(layers, "z0s", export.OUTPUT_NAME)
    nodes += more
    inits += more_inits
    graph = helper.make_graph(
        nodes, name,
        [helper.make_tensor_value_info(export.INPUT_NAME, TensorProto.FLOAT, ["batch", npx]),
         helper.make_tensor_value_info(REF_INPUT, TensorProto.FLOAT, ["batch", npx])],
        [helper.make_tensor_value_info(export.OUTPUT_NAME, TensorProto.FLOAT, ["batch", 2])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", export.OPSET)],
                              producer_name="lgs_wfs_ros.learning")
    model.ir_version = 8
    meta = {"lgs_wfs.pixels": pixels, "lgs_wfs.input_norm": "sum", "lgs_wfs.conditioning": "reference",
            "lgs_wfs.conditioning_input": REF_INPUT, "lgs_wfs.input_name": export.INPUT_NAME,
            "lgs_wfs.output_scale": 1.0, "lgs_wfs.output_frame": "block", "lgs_wfs.detector": "any",
            **metadata}
    helper.set_model_props(model, {k: json.dumps(v, sort_keys=True) for k, v in meta.items()})
    onnx.checker.check_model(model)
    return model


def predict(path_or_model, p: refdata.Pairs) -> np.ndarray:
    """``(n, 2)`` model outputs (px, block axes) on pairs."""
    src = path_or_model if isinstance(path_or_model, (str, Path)) else path_or_model.SerializeToString()
    sess = export.session(src)
    return np.asarray(sess.run([export.OUTPUT_NAME], {export.INPUT_NAME: p.images, REF_INPUT: p.refs})[0],
                      dtype=np.float64)


def check_error(path_or_model, n: int = CHECK_N, seed: int = CHECK_SEED) -> float:
    """Mean 2-D error (px) on the fixed check pairs (fresh draws of the training prior)."""
    pairs = generate(n, seed, progress=False)
    return float(np.linalg.norm(predict(path_or_model, pairs) - pairs.y, axis=1).mean())


def train(rec: recipes.Recipe, target: Path, samples: int, seed: int, epochs: int,
          progress: bool = True, time_budget_s: float | None = None) -> dict:
    """Train ``rec`` into ``target`` (an ONNX path); returns the training record."""
    import torch
    from .train import fit_adam
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    gain = float(rec.sizes[0] // 2)
    data = generate(samples, seed, progress=progress)
    mon = generate(min(20_000, max(2000, samples // 10)), MONITOR_SEED + seed, progress=False)
    gen_s = time.perf_counter() - t0
    x, y = torch.from_numpy(features(data, gain)), torch.from_numpy(data.y)
    xv, yv = torch.from_numpy(features(mon, gain)), torch.from_numpy(mon.y)
    del data
    net = mlp(rec.sizes, seed=seed)
    hist = fit_adam(net, x, y, xv, yv, epochs=epochs, batch=rec.batch, lr=rec.lr, seed=seed,
                    time_budget_s=time_budget_s, progress=progress, loss=rec.loss)
    pixels = int(round((rec.sizes[0] // 2) ** 0.5))
    err = np.linalg.norm(predict(build_model(layers_of(net), pixels, gain, {}), mon) - mon.y, axis=1)
    training = {"recipe": rec.to_dict(), "recipe_line": rec.line(samples), "optimizer": "adam",
                "seed": seed, "samples": samples, "quick": False,
                "parameters": n_parameters(rec.sizes), "photons": None,
                "photons_range": list(refdata.PriorSpec().photons),
                "profiles": refdata.PriorSpec().describe(),
                "generate_seconds": round(gen_s, 1),
                "fit_seconds": round(hist[-1]["seconds"], 1) if hist else 0.0,
                "epochs_run": len(hist),
                "final_monitor_err_px": float(err.mean()),
                "monitor_pairs": int(err.size),
                "check": {"mean_err_px": check_error(build_model(layers_of(net), pixels, gain, {})),
                          "n": CHECK_N, "seed": CHECK_SEED,
                          "what": "fresh pairs of the training prior (reftrain.check_error)"}}
    model = build_model(layers_of(net), pixels, gain,
                        {"lgs_wfs.training": training, "lgs_wfs.domain": domains.reference_domain(rec)}, rec.name)
    path = export.save(model, Path(target))
    return {"path": str(path), "training": training, "history": hist}


def train_recipe(name: str, out_dir=None, samples: int | None = None, seed: int | None = None,
                 quick: bool = False, force: bool = False, progress: bool = True,
                 time_budget_s: float | None = None, trainer=None, **_ignored) -> dict:
    """``lgs-wfs train`` for a reference recipe: as :func:`.train.train_model` (same
    return keys), then the card of ``out_dir``. ``trainer``: the recipe's :func:`train`
    (default this module's; :mod:`.margtrain` passes its own)."""
    from . import card
    from .train import target_path
    target = target_path(name, out_dir, force)
    rec = recipes.get(name)
    seed = rec.seed if seed is None else int(seed)
    samples = (rec.quick_samples if quick else rec.samples) if samples is None else int(samples)
    epochs = max(2, rec.epochs // 8) if quick else rec.epochs
    t0 = time.perf_counter()
    print("recipe:", rec.line(samples), flush=True)
    done = (trainer or train)(rec, target, samples, seed, epochs, progress, time_budget_s)
    done["training"]["quick"] = quick
    export.update_metadata(target, {"lgs_wfs.training": done["training"]})
    return {"path": done["path"], "recipe": rec.line(samples), "history": done["history"],
            "check_err_px": done["training"]["check"]["mean_err_px"], "validation": None,
            "seconds": time.perf_counter() - t0, "card": str(card.write(target.parent))}


__all__ = ["train_recipe", "train", "build_model", "features", "generate", "predict", "REF_INPUT"]
