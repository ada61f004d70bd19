"""Write a trained MLP as a small ONNX model with the ``lgs_wfs.*`` metadata contract.

The graph is built directly with :mod:`onnx.helper` from numpy weights (no torch
needed), opset 17, float32:

    pixels (batch, p*p) --[MatMul W0 (+ MatMul e W0c)] + b0 -> tanh -> ... -> MatMul + b -> slopes (batch, 2)

The input normalisation constant (``input_gain``: the network was trained on
``pixels / total * input_gain``) is folded into the first weight matrix, so the
runtime only divides each image by its total (``lgs_wfs.input_norm = "sum"``).

Metadata (``metadata_props``, every value JSON-encoded):
``lgs_wfs.pixels`` (int), ``lgs_wfs.detector`` ("polar" | "cartesian" | "any"),
``lgs_wfs.input_norm`` ("sum"), ``lgs_wfs.output_scale`` (float, slope px = output *
scale), ``lgs_wfs.output_frame`` ("local" = the block's pixel axes | "detector"),
``lgs_wfs.conditioning`` ("none" | "e" | "e_r"), ``lgs_wfs.input_name`` (str) and
``lgs_wfs.training`` (dict).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

OPSET = 17
CONDITIONING_WIDTH = {"none": 0, "e": 2, "e_r": 3}
INPUT_NAME = "pixels"
COND_NAME = "e"
OUTPUT_NAME = "slopes"


def _check_layers(layers) -> list[tuple[np.ndarray, np.ndarray]]:
    if not layers:
        raise ValueError("need at least one (W, b) layer")
    out = []
    prev = None
    for k, (w, b) in enumerate(layers):
        w = np.asarray(w, dtype=np.float32)
        b = np.asarray(b, dtype=np.float32)
        if w.ndim != 2 or b.shape != (w.shape[1],):
            raise ValueError(f"layer {k}: W must be (in, out) and b (out,), got {w.shape}, {b.shape}")
        if prev is not None and w.shape[0] != prev:
            raise ValueError(f"layer {k}: input width {w.shape[0]} != previous output {prev}")
        prev = w.shape[1]
        out.append((w, b))
    if prev != 2:
        raise ValueError(f"the last layer must have 2 outputs, got {prev}")
    return out


def tanh_layers(layers, first: str, output: str | None):
    """``(nodes, initializers, last)``: the ONNX nodes of a tanh MLP from its first layer's
    product on: ``first`` names that product (``x W0``, without ``b0``); then ``+ b0``,
    ``tanh``, ``x W1 + b1``, ... with no tanh after the last layer, whose sum is named
    ``output`` (``None``: ``z<k>``, for a graph that goes on). ``layers`` as trained,
    ``[(W (in, out), b (out,)), ...]``, stored float32 (``W0`` is not used)."""
    from onnx import helper, numpy_helper

    nodes, inits, last = [], [], first
    for k, (w, b) in enumerate(layers):
        if k > 0:
            inits.append(numpy_helper.from_array(np.asarray(w, np.float32), f"W{k}"))
            nodes.append(helper.make_node("MatMul", [last, f"W{k}"], [f"z{k}m"]))
            last = f"z{k}m"
        is_out = k == len(layers) - 1
        out = output if is_out and output is not None else f"z{k}"
        inits.append(numpy_helper.from_array(np.asarray(b, np.float32), f"b{k}"))
        nodes.append(helper.make_node("Add", [last, f"b{k}"], [out]))
        last = out
        if not is_out:
            nodes.append(helper.make_node("Tanh", [out], [f"h{k}"]))
            last = f"h{k}"
    return nodes, inits, last


def build_model(layers, *, pixels: int, conditioning: str = "none", input_gain: float = 1.0,
                metadata: dict | None = None, name: str = "lgs_wfs_ann",
                rotate_to_local: bool = False):
    """ONNX ``ModelProto`` of a tanh MLP with a linear output.

    Args:
        layers: ``[(W (in, out), b (out,)), ...]`` float arrays, as trained: the first
            layer's input is ``concat(pixels / total * input_gain, cond)``.
        pixels: subaperture side p (the pixel input has ``p*p`` columns).
        conditioning: "none", "e" (2 columns) or "e_r" (3 columns) of extra input.
        input_gain: folded into the pixel rows of the first weight matrix.
        metadata: extra ``lgs_wfs.*`` keys (values JSON-encoded here).
        rotate_to_local: the network predicts the displacement in the block's pixel axes
            and the conditioning input starts with ``(ex, ey)`` in those axes; the graph
            rotates the prediction into the local frame (along e, across e), so the model
            output is ``output_frame = "local"`` on both detector types.

    Returns:
        ``onnx.ModelProto``, checked.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    if conditioning not in CONDITIONING_WIDTH:
        raise ValueError(f"conditioning must be one of {list(CONDITIONING_WIDTH)}, got {conditioning!r}")
    layers = _check_layers(layers)
    npx, nc = pixels * pixels, CONDITIONING_WIDTH[conditioning]
    w0, b0 = layers[0]
    if w0.shape[0] != npx + nc:
        raise ValueError(f"first layer takes {w0.shape[0]} inputs, expected {npx} pixels + {nc}")
    inits, nodes = [], []

    def init(arr, nm):
        dt = np.int64 if np.asarray(arr).dtype.kind == "i" else np.float32
        inits.append(numpy_helper.from_array(np.ascontiguousarray(arr, dtype=dt), nm))
        return nm

    inputs = [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", npx])]
    nodes.append(helper.make_node("MatMul", [INPUT_NAME, init(w0[:npx] * input_gain, "W0")], ["z0p"]))
    last = "z0p"
    if nc:
        inputs.append(helper.make_tensor_value_info(COND_NAME, TensorProto.FLOAT, ["batch", nc]))
        nodes.append(helper.make_node("MatMul", [COND_NAME, init(w0[npx:], "W0c")], ["z0c"]))
        nodes.append(helper.make_node("Add", ["z0p", "z0c"], ["z0pc"]))
        last = "z0pc"
    more, more_inits, last = tanh_layers(layers, last, None if rotate_to_local else OUTPUT_NAME)
    nodes += more
    inits += more_inits
    if rotate_to_local:
        if not nc:
            raise ValueError("rotate_to_local needs a conditioning input holding e")
        # local = (ex ox + ey oy, ex oy - ey ox)
        nodes.append(helper.make_node("Split", [last, init(np.array([1, 1], np.int64), "s11")],
                                      ["ox", "oy"], axis=1))
        nodes.append(helper.make_node("Split", [COND_NAME, init(np.array([1, 1, nc - 2], np.int64)
                                                                if nc > 2 else np.array([1, 1], np.int64), "sc")],
                                      ["ex", "ey"] + (["erest"] if nc > 2 else []), axis=1))
        for a, b, o in (("ex", "ox", "exox"), ("ey", "oy", "eyoy"), ("ex", "oy", "exoy"),
                        ("ey", "ox", "eyox")):
            nodes.append(helper.make_node("Mul", [a, b], [o]))
        nodes.append(helper.make_node("Add", ["exox", "eyoy"], ["lx"]))
        nodes.append(helper.make_node("Sub", ["exoy", "eyox"], ["ly"]))
        nodes.append(helper.make_node("Concat", ["lx", "ly"], [OUTPUT_NAME], axis=1))
    graph = helper.make_graph(
        nodes, name, inputs,
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["batch", 2])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="lgs_wfs_ros.learning")
    model.ir_version = 8
    meta = {"lgs_wfs.pixels": pixels, "lgs_wfs.input_norm": "sum",
            "lgs_wfs.conditioning": conditioning, "lgs_wfs.input_name": INPUT_NAME,
            "lgs_wfs.output_scale": 1.0, "lgs_wfs.output_frame": "local",
            "lgs_wfs.detector": "any"}
    meta.update(metadata or {})
    helper.set_model_props(model, {k: json.dumps(v, sort_keys=True) for k, v in meta.items()})
    onnx.checker.check_model(model)
    return model


def save(model, path) -> Path:
    """Write an ONNX model; returns the path."""
    import onnx
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def read_metadata(path) -> dict:
    """``lgs_wfs.*`` metadata of an ONNX file, JSON-decoded (other keys dropped)."""
    import onnx
    model = onnx.load(str(path), load_external_data=False)
    out = {}
    for p in model.metadata_props:
        if p.key.startswith("lgs_wfs."):
            out[p.key] = json.loads(p.value)
    return out


def update_metadata(path, changes: dict) -> None:
    """Rewrite some ``lgs_wfs.*`` metadata keys of an ONNX file in place."""
    import onnx
    from onnx import helper
    model = onnx.load(str(path))
    props = {p.key: p.value for p in model.metadata_props}
    props.update({k: json.dumps(v, sort_keys=True) for k, v in changes.items()})
    del model.metadata_props[:]
    helper.set_model_props(model, props)
    onnx.save(model, str(path))


def session(path_or_bytes, threads: int = 1):
    """An onnxruntime ``InferenceSession`` on CPU with ``threads`` intra-op threads."""
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    src = path_or_bytes if isinstance(path_or_bytes, (bytes, bytearray)) else str(path_or_bytes)
    return ort.InferenceSession(src, so, providers=["CPUExecutionProvider"])


def predict_samples(path_or_model, s) -> np.ndarray:
    """``(n, 2)`` outputs of a model (path or ``ModelProto``) on :class:`.dataset.Samples`,
    in the model's output frame; the conditioning input is fed when the model has one."""
    src = path_or_model if isinstance(path_or_model, (str, Path)) else \
        path_or_model.SerializeToString()
    sess = session(src)
    meta = read_metadata(path_or_model) if isinstance(path_or_model, (str, Path)) else {}
    cond = s.cond if meta.get("lgs_wfs.conditioning", "none") != "none" or \
        len(sess.get_inputs()) > 1 else None
    return predict(sess, s.images, cond)


def predict(sess, images: np.ndarray, cond: np.ndarray | None = None) -> np.ndarray:
    """Run a model on ``(n, p, p)`` or ``(n, p*p)`` images (sum-normalised here).

    Returns ``(n, 2)`` float64 network outputs (times ``lgs_wfs.output_scale`` = px).
    """
    x = np.asarray(images, dtype=np.float64).reshape(len(images), -1)
    tot = x.sum(axis=1, keepdims=True)
    x = (x / np.where(tot > 0, tot, 1.0)).astype(np.float32)
    feeds = {INPUT_NAME: x}
    if cond is not None:
        feeds[COND_NAME] = np.asarray(cond, dtype=np.float32)
    return np.asarray(sess.run([OUTPUT_NAME], feeds)[0], dtype=np.float64)
