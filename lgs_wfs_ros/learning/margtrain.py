"""Train and export the marginal reference-reading network (``ann_marg``, polar detector).

On a polar detector a spot is the outer product of its marginals, and the counts' row and
column sums are all a shift estimate needs (the maximum-likelihood estimator ``ml`` reads
nothing else). The network measures the shift along e (block x), the hard axis: input =
the image's column sums (``p`` counts), the same sums of the subaperture's current reference
(unit sum, from the pupil calibration) and the log of the image's total; output = the
image's shift from the reference along e, px. Across e the spot is the core alone and the
pupil-calibrated CoG is as good (0.0306 vs the network's 0.0304 px rms on the prior's check
spots), so the centroider takes that axis from the row sums (:mod:`..centroiding.ann`).

Features (``F = 2 p + 1``): ``[p (m / N - r), p r, log10(N) / 3 - 0.8]``, ``m`` the
marginal, ``N`` its total, ``r`` the reference's marginal. Exported (opset 17) as::

    marginals (batch, p) -- sum N, divide, MatMul Wm --+
    log N                -- MatMul wN  ----------------+-- Add b0 -> tanh -> ... -> shift (batch, 1)
    reference (batch, p) -- MatMul Wr -----------------+

with ``Wm = p Wd``, ``Wr = p (Wref - Wd)``: the reference enters the first layer once,
linearly, so the centroider computes ``reference @ Wr`` per calibration refit
(:func:`..centroiding.ann_model.split_reference`). Metadata: ``lgs_wfs.input = "marginals"``,
``lgs_wfs.conditioning = "reference"``, ``lgs_wfs.detector = "polar"``; one row per
subaperture.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from . import domains, export, recipes, refdata
from .model import layers_of, mlp, n_parameters

MARG_INPUT, REF_INPUT, SHIFT_OUTPUT = "marginals", "reference", "shift"
MONITOR_SEED = 66_666
CHECK_SEED, CHECK_N = 90_003, 2000      # the fixed check set whose error the metadata records
LOG_OFFSET = 0.8                        # feature = log10(N) / 3 - LOG_OFFSET (~0 at 250 photons)


def features(marg: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """``(m, 2 p + 1)`` float32 network input from raw marginals and unit-sum references."""
    p = marg.shape[1]
    tot = np.maximum(marg.sum(axis=1, keepdims=True, dtype=np.float64), 1.0)
    return np.concatenate([p * (marg / tot - refs), p * refs,
                           np.log10(tot) / 3.0 - LOG_OFFSET], axis=1).astype(np.float32)


def generate(n: int, seed: int, batch: int = 4096, progress: bool = True,
             detectors=("polar",), window: str = "centred",
             projection: str = "overlap") -> refdata.MarginalPairs:
    """``n`` spots of :data:`.refdata.MARGINAL_SPEC` shared among ``detectors``
    (:func:`.refdata.split`); a detector's batch ``k`` comes from
    ``default_rng([seed, k, *refdata.STREAMS[d]])``,
    polar spots first; cartesian bins through ``window`` (:data:`.refdata.WINDOWS`) and
    ``projection`` (overlap or grid, :func:`.refdata.marginal_pairs`)."""
    from tqdm.auto import tqdm
    parts = []
    with tqdm(total=n, desc="spots", unit="spot", disable=not progress, mininterval=5.0) as bar:
        for det, count in refdata.split(n, detectors).items():
            done, k = 0, 0
            while done < count:
                m = min(batch, count - done)
                rng = np.random.default_rng([seed, k, *refdata.STREAMS[det]])
                parts.append(refdata.marginal_pairs(rng, m, detector=det, window=window,
                                                    projection=projection))
                done, k = done + m, k + 1
                bar.update(m)
    return refdata.MarginalPairs(*[np.concatenate([getattr(q, f) for q in parts])
                                   for f in ("marg", "refs", "y", "r_m", "photons")])


def build_model(layers, pixels: int, metadata: dict, name: str = "ann_marg"):
    """ONNX ``ModelProto`` (see the module doc) from trained ``[(W (in, out), b), ...]``."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    p = int(pixels)
    w0, b0 = layers[0]
    wd, wref, wn = w0[:p], w0[p:2 * p], w0[2 * p:2 * p + 1]
    f32 = lambda a: np.asarray(a, np.float32)                         # noqa: E731
    inits = [numpy_helper.from_array(f32(wd * p), "Wm"),
             numpy_helper.from_array(f32((wref - wd) * p), "Wr"),
             numpy_helper.from_array(f32(wn / (3.0 * math.log(10.0))), "wN"),
             numpy_helper.from_array(np.array([1], np.int64), "axis1"),
             numpy_helper.from_array(np.array([1.0], np.float32), "one")]
    nodes = [helper.make_node("ReduceSum", [MARG_INPUT, "axis1"], ["total"], keepdims=1),
             helper.make_node("Max", ["total", "one"], ["safe"]),
             helper.make_node("Div", [MARG_INPUT, "safe"], ["unit"]),
             helper.make_node("Log", ["safe"], ["logn"]),
             helper.make_node("MatMul", ["unit", "Wm"], ["zm"]),
             helper.make_node("MatMul", ["logn", "wN"], ["zn"]),
             helper.make_node("MatMul", [REF_INPUT, "Wr"], ["zr"]),
             helper.make_node("Add", ["zm", "zn"], ["zmn"]),
             helper.make_node("Add", ["zmn", "zr"], ["z0s"])]
    # the feature's -LOG_OFFSET goes into b0 (the graph scales ln(total) by wN / (3 ln 10))
    layers = [(w0, np.asarray(b0) - LOG_OFFSET * np.asarray(wn)[0]), *layers[1:]]
    more, more_inits, _ = export.tanh_layers(layers, "z0s", SHIFT_OUTPUT)
    nodes += more
    inits += more_inits
    graph = helper.make_graph(
        nodes, name,
        [helper.make_tensor_value_info(MARG_INPUT, TensorProto.FLOAT, ["batch", p]),
         helper.make_tensor_value_info(REF_INPUT, TensorProto.FLOAT, ["batch", p])],
        [helper.make_tensor_value_info(SHIFT_OUTPUT, TensorProto.FLOAT, ["batch", 1])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", export.OPSET)],
                              producer_name="lgs_wfs_ros.learning")
    model.ir_version = 8
    meta = {"lgs_wfs.pixels": p, "lgs_wfs.input": "marginals", "lgs_wfs.input_norm": "none",
            "lgs_wfs.conditioning": "reference", "lgs_wfs.conditioning_input": REF_INPUT,
            "lgs_wfs.input_name": MARG_INPUT, "lgs_wfs.output_scale": 1.0,
            "lgs_wfs.output_frame": "block", "lgs_wfs.detector": "polar", **metadata}
    helper.set_model_props(model, {k: json.dumps(v, sort_keys=True) for k, v in meta.items()})
    onnx.checker.check_model(model)
    return model


def predict(path_or_model, pairs: refdata.MarginalPairs) -> np.ndarray:
    """``(n, 1)`` model outputs (px along e) on marginal pairs."""
    src = (path_or_model if isinstance(path_or_model, (str, Path))
           else path_or_model.SerializeToString())
    sess = export.session(src)
    return np.asarray(sess.run([SHIFT_OUTPUT], {MARG_INPUT: pairs.marg, REF_INPUT: pairs.refs})[0],
                      dtype=np.float64)


def check_error(path_or_model, n: int = CHECK_N, seed: int = CHECK_SEED,
                detectors=("polar",), window: str = "centred", projection: str = "overlap") -> float:
    """Mean absolute error along e (px) on the fixed check spots (fresh draws of the prior,
    shared among ``detectors`` and binned through ``window`` as the model's training
    was)."""
    pairs = generate(n, seed, progress=False, detectors=detectors, window=window,
                     projection=projection)
    return float(np.abs(predict(path_or_model, pairs) - pairs.y).mean())


domain = domains.marginal_domain      # the training domain: the spots' ranges and detectors


def record(rec: recipes.Recipe, samples: int, seed: int, generate_s: float, history: list,
           monitor_mae_px: float, check_mae_px: float, check_what: str, **extra) -> dict:
    """The training record a model on the marginal prior carries (``lgs_wfs.training``):
    recipe, data, prior, timings, monitor and check errors (px), plus ``extra`` fields."""
    prior = refdata.MARGINAL_SPEC
    return {"recipe": rec.to_dict(), "recipe_line": rec.line(samples), "optimizer": "adam",
            "seed": seed, "samples": samples, "quick": False, **extra, "photons": None,
            "photons_range": list(prior.photons), "profiles": prior.describe(),
            "generate_seconds": round(generate_s, 1),
            "fit_seconds": round(history[-1]["seconds"], 1) if history else 0.0,
            "epochs_run": len(history), "final_monitor_mae_px": monitor_mae_px,
            "check": {"mean_err_px": check_mae_px, "n": CHECK_N, "seed": CHECK_SEED,
                      "what": check_what}}


def train(rec: recipes.Recipe, target: Path, samples: int, seed: int, epochs: int,
          progress: bool = True, time_budget_s: float | None = None) -> dict:
    """Train ``rec`` into ``target`` (an ONNX path); returns the training record."""
    import torch
    from .train import fit_adam
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    p = (rec.sizes[0] - 1) // 2
    data = generate(samples, seed, progress=progress)
    mon = generate(min(20_000, max(2000, samples // 10)), MONITOR_SEED + seed, progress=False)
    gen_s = time.perf_counter() - t0
    x, y = torch.from_numpy(features(data.marg, data.refs)), torch.from_numpy(data.y)
    xv, yv = torch.from_numpy(features(mon.marg, mon.refs)), torch.from_numpy(mon.y)
    del data
    net = mlp(rec.sizes, seed=seed)
    hist = fit_adam(net, x, y, xv, yv, epochs=epochs, batch=rec.batch, lr=rec.lr, seed=seed,
                    time_budget_s=time_budget_s, progress=progress, loss=rec.loss)
    model = build_model(layers_of(net), p, {})
    err = np.abs(predict(model, mon) - mon.y)
    training = record(rec, samples, seed, gen_s, hist, float(err.mean()), check_error(model),
                      "fresh spots of the training prior (margtrain.check_error)",
                      parameters=n_parameters(rec.sizes), monitor_spots=int(err.size))
    prior = refdata.MARGINAL_SPEC
    model = build_model(layers_of(net), p, {"lgs_wfs.training": training,
                                            "lgs_wfs.domain": domain(prior)}, rec.name)
    path = export.save(model, Path(target))
    return {"path": str(path), "training": training, "history": hist}


def train_recipe(name: str, **kwargs) -> dict:
    """``lgs-wfs train`` for the marginal recipe: :func:`.reftrain.train_recipe` with this
    module's :func:`train`."""
    from .reftrain import train_recipe as _train_recipe
    return _train_recipe(name, trainer=train, **kwargs)


__all__ = ["train_recipe", "train", "record", "build_model", "features", "generate", "predict", "domain"]
