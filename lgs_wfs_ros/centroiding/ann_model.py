"""ANN model files: where they are found, their metadata, and the graph surgery the
centroider (:mod:`.ann`) does at load time (onnx, onnxruntime).

Model metadata contract (ONNX ``metadata_props``, every value JSON-encoded; a bare string
is accepted too):

==========================  =================================================================
``lgs_wfs.pixels``          int, pixels per side the model takes (required)
``lgs_wfs.detector``        "polar" | "cartesian" | "any" (default "any")
``lgs_wfs.input_norm``      "sum" (each subaperture divided by its total) | "none" (default "sum")
``lgs_wfs.output_scale``    float: slope px = output * scale (default 1)
``lgs_wfs.output_frame``    "local" (along e / across e) | "detector" | "block" (the block's pixel
                            axes, as the input) (default "detector")
``lgs_wfs.conditioning``    "none" | "e" (second input ``(batch, 2)`` = e in detector axes) |
                            "e_r" (``(batch, 3)`` = (ex, ey, r_m / 15)) | "reference" (second
                            input ``(batch, p*p)``: the subaperture's current reference from
                            the pupil calibration, unit sum, block axes; it must feed one
                            ``MatMul`` with a constant matrix, :func:`split_reference`)
                            (default "none")
``lgs_wfs.conditioning_input``  name of that second input (default "e")
``lgs_wfs.conditioning_frame``  "detector" (default: e in detector axes) | "pixel" (e in the
                                block's pixel axes: (1, 0) on a polar detector)
``lgs_wfs.input``           "pixels" (default) | "marginals": a model that reads each
                            subaperture's light in 1 px bins along e ``(batch, p)``: on a
                            polar detector its column sums (raw counts, a function of block
                            x), on a cartesian one each pixel split by its overlap
                            (:mod:`.bins_along_e`); its reference input the same bins of the
                            reference (unit sum), its output ``(batch, 1)`` the shift along
                            e; across e (the core alone) the pupil-calibrated CoG
                            (``learning/margtrain.py``, ``hypertrain.py``). Its
                            ``lgs_wfs.detector`` is "polar" or "any"; its domain lists the
                            detectors it was trained on (a polar-only one refuses a cartesian
                            sensor unless ``out_of_domain = warn``)
``lgs_wfs.bins_window``     a marginals model on a cartesian detector: "centred" (default:
                            each block's window of bins centred on the block) | "reference"
                            (moved by whole pixels to its calibrated reference's light at
                            every refit, :func:`.bins_along_e.window_offsets`); a model
                            reads the windows it was trained on (3.6x worse in the other)
``lgs_wfs.bins_projection`` a marginals model on a cartesian detector: "overlap" (default:
                            each pixel split along e by its footprint) | "grid" (whole-pixel
                            sums along the pixel-grid direction nearest to e, the shift read
                            along that direction, :func:`.bins_along_e.grid_weights`); option
                            ``bins`` overrides it
``lgs_wfs.hyper``           bool (default false): a marginals model whose reference sets
                            per-subaperture filters (``learning/hypertrain.py``): the graph's
                            tensors ``lgs_wfs.hyper_outputs`` (default ``["filters", "fbias"]``)
                            depend on the reference input alone; the centroider cuts the graph
                            there (:func:`split_hyper`), runs the reference part once per
                            calibration refit and feeds its outputs to the frame part
``lgs_wfs.input_name``      name of the pixel input (default: the first input)
``lgs_wfs.training``        free-form JSON, reported by ``describe()``
``lgs_wfs.domain``          the training domain (:mod:`.domain`): radius range, detectors,
                            photons, profile prior, input kind (default: none declared)
==========================  =================================================================

Pixel input: float32 ``(batch, p*p)``, row-major subaperture pixels (block pixel axes: the
local frame on a polar detector). Output: ``(batch, 2)``.

Speed: for ``input_norm = "sum"`` models whose pixel input feeds one ``MatMul`` with a
constant weight matrix (every model ``learning/export.py`` writes), the normalisation is
folded into the graph at load time (:func:`fold_sum_normalisation`): one extra weight column
of ones gives each subaperture's total in the same product, and the first layer is divided
by it, ``(x @ W) / sum(x) = (x / sum(x)) @ W``, which saves two passes over the stack.

Model lookup (:func:`resolve_model`): an existing path; else a name or relative path
(with or without ``.onnx``, e.g. ``ann_1k`` or ``paper_prior/ann_1k_paper``) in, in order:
the source tree's ``models/``, the package's share directory through the ament index
(``share/lgs_wfs_ros/models`` of a colcon install, if ``ament_index_python`` is importable),
the share directory beside the installed package (found from this file, for a colcon
install without the index), ``sys.prefix/share/lgs_wfs_ros/models`` (pip), the directories
in ``$LGS_WFS_MODELS`` (``os.pathsep``-separated) and the user directory
``${XDG_DATA_HOME:-~/.local/share}/lgs_wfs_ros/models``.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from . import bins_along_e

META = "lgs_wfs."


class ModelNotFoundError(FileNotFoundError, ValueError):
    """A model name or path that resolves to no file; the message lists the paths searched."""


def _ament_share() -> list[Path]:
    """share/lgs_wfs_ros/models of the package in the ament index ([] without one)."""
    try:
        from ament_index_python.packages import (PackageNotFoundError,
                                                 get_package_share_directory)
    except ImportError:
        return []
    try:
        return [Path(get_package_share_directory("lgs_wfs_ros")) / "models"]
    except (PackageNotFoundError, ValueError, LookupError, OSError):
        return []


def model_dirs() -> list[Path]:
    """Directories searched for model names, in order (duplicates removed)."""
    here = Path(__file__).resolve()
    source = here.parents[2] / "models"                            # a source checkout
    dirs = [source] if source.is_dir() else []
    dirs += _ament_share()                                         # colcon: the ament index
    for parent in here.parents:                                    # <prefix>/lib/pythonX/site-packages
        if parent.name == "lib":
            dirs.append(parent.parent / "share" / "lgs_wfs_ros" / "models")
            break
    dirs.append(Path(sys.prefix) / "share" / "lgs_wfs_ros" / "models")   # pip
    env = os.environ.get("LGS_WFS_MODELS", "")
    dirs += [Path(d).expanduser() for d in env.split(os.pathsep) if d]
    dirs.append(Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
                / "lgs_wfs_ros" / "models")                        # the user's own
    unique = []
    for d in dirs:
        if d not in unique:
            unique.append(d)
    return unique


def resolve_model(model: str | os.PathLike) -> Path:
    """Path of a model given as a path or a name.

    Raises:
        ModelNotFoundError (a ValueError and a FileNotFoundError): not found; the message
            lists every path searched.
        ValueError: not a path or a name.
    """
    if not isinstance(model, (str, os.PathLike)) or not str(model):
        raise ValueError(f"ann: model must be a file path or a model name, got {model!r}")
    p = Path(model).expanduser()
    if p.is_file():
        return p
    names = [p] if p.suffix == ".onnx" else [p, p.with_name(p.name + ".onnx")]
    if p.is_absolute():
        raise ModelNotFoundError(f"ann: model file {str(model)!r} not found (no such file)")
    tried = []
    for d in model_dirs():
        for name in names:
            tried.append(d / name)
            if tried[-1].is_file():
                return tried[-1]
    raise ModelNotFoundError(f"ann: model {str(model)!r} not found; searched "
                             + ", ".join(str(d) for d in model_dirs())
                             + " (add a directory with $LGS_WFS_MODELS)")


def read_metadata(meta_map: dict) -> dict:
    """Parse the ``lgs_wfs.*`` entries of an ONNX custom metadata map, with defaults."""
    raw = {}
    for k, v in meta_map.items():
        if k.startswith(META):
            try:
                raw[k[len(META):]] = json.loads(v)
            except (json.JSONDecodeError, TypeError):
                raw[k[len(META):]] = v
    md = {"detector": "any", "input": "pixels", "input_norm": "sum", "output_scale": 1.0,
          "output_frame": "detector", "conditioning": "none", "conditioning_input": "e",
          "conditioning_frame": "detector",
          "input_name": None, "training": None, "domain": None,
          "hyper": False, "hyper_outputs": ["filters", "fbias"], "hyper_trunk": None,
          "bins_window": "centred", "bins_projection": "overlap"}
    md.update(raw)
    if "pixels" not in raw:
        raise ValueError("ann: model metadata lacks lgs_wfs.pixels")
    checks = [("detector", ("polar", "cartesian", "any")), ("input", ("pixels", "marginals")),
              ("input_norm", ("sum", "none")),
              ("output_frame", ("local", "detector", "block")),
              ("conditioning", ("none", "e", "e_r", "reference")),
              ("conditioning_frame", ("detector", "pixel")),
              ("bins_window", bins_along_e.WINDOWS),
              ("bins_projection", bins_along_e.PROJECTIONS)]
    for key, allowed in checks:
        if md[key] not in allowed:
            raise ValueError(f"ann: metadata lgs_wfs.{key} must be one of {list(allowed)}, got {md[key]!r}")
    try:
        md["pixels"] = int(md["pixels"])
        md["output_scale"] = float(md["output_scale"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"ann: bad metadata lgs_wfs.pixels/output_scale: {exc}") from exc
    if not np.isfinite(md["output_scale"]):
        raise ValueError("ann: metadata lgs_wfs.output_scale must be finite")
    if md["input"] == "marginals" and (md["detector"] not in ("polar", "any")
                                       or md["conditioning"] != "reference"):
        raise ValueError("ann: a marginals model must declare lgs_wfs.detector polar (or any) "
                         "and lgs_wfs.conditioning reference")
    if not isinstance(md["hyper"], bool):
        raise ValueError(f"ann: metadata lgs_wfs.hyper must be true or false, got {md['hyper']!r}")
    if md["hyper"] and (md["conditioning"] != "reference" or md["input_norm"] != "none"):
        raise ValueError("ann: a hyper model must read the reference (lgs_wfs.conditioning "
                         "reference) and raw counts (lgs_wfs.input_norm none)")
    if not (isinstance(md["hyper_outputs"], list) and md["hyper_outputs"]
            and all(isinstance(v, str) for v in md["hyper_outputs"])):
        raise ValueError("ann: metadata lgs_wfs.hyper_outputs must be a list of tensor names")
    trunk = md["hyper_trunk"]
    if trunk is not None and not (isinstance(trunk, dict) and set(trunk) == {"z", "total"}
                                  and all(isinstance(v, str) for v in trunk.values())):
        raise ValueError("ann: metadata lgs_wfs.hyper_trunk must be {\"z\": name, \"total\": name}")
    return md


def open_session(path):
    """onnxruntime session with one intra-op and one inter-op thread (CPU).

    Args:
        path: model file, or the serialised model (``bytes``).
    """
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    try:
        src = path if isinstance(path, bytes) else str(path)
        return ort.InferenceSession(src, sess_options=so, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ValueError(f"ann: cannot load model {str(path)!r}: {exc}") from exc


TOTAL_OUTPUT = "_lgs_wfs_total"


def split_reference(model, ref_input: str):
    """Cut a reference model's reference branch out of the graph.

    Args:
        model: ``onnx.ModelProto`` whose input ``ref_input`` is used once, by a ``MatMul``
            with a constant ``(p*p, h)`` matrix ``Wr`` (what ``learning/reftrain.py`` writes).

    Returns:
        ``(model', Wr)``: ``model'`` takes that product ``(batch, h)`` as its input named
        ``ref_input + "_code"``; the centroider computes ``reference @ Wr`` once per
        calibration refit, so a frame costs only the pixel branch.

    Raises:
        ValueError: the reference is not used that way.
    """
    import onnx
    from onnx import helper, numpy_helper
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    users = [n for n in g.node if ref_input in n.input]
    inits = {i.name: i for i in g.initializer}
    if len(users) != 1 or users[0].op_type != "MatMul" or users[0].input[0] != ref_input \
            or users[0].input[1] not in inits:
        raise ValueError(f"ann: the model's {ref_input!r} input must feed one MatMul with a constant matrix")
    mm = users[0]
    w = numpy_helper.to_array(inits[mm.input[1]]).astype(np.float32)
    g.node.remove(mm)
    if sum(mm.input[1] in n.input for n in g.node) == 0:
        g.initializer.remove(inits[mm.input[1]])
    code = ref_input + "_code"
    for node in g.node:
        for k, name in enumerate(node.input):
            if name == mm.output[0]:
                node.input[k] = code
    old = [i for i in g.input if i.name == ref_input][0]
    g.input.remove(old)
    g.input.append(helper.make_tensor_value_info(code, onnx.TensorProto.FLOAT, ["batch", w.shape[1]]))
    return m, w


def split_hyper(model, ref_input: str, outputs) -> tuple:
    """Cut a hyper model (``lgs_wfs.hyper``) at its reference-only tensors.

    Args:
        model: ``onnx.ModelProto`` with inputs ``ref_input`` and the frame's input(s), and
            intermediate tensors ``outputs`` computed from ``ref_input`` alone.

    Returns:
        ``(refit, frame)`` ``ModelProto``: ``refit`` maps ``ref_input`` to ``outputs`` (run
        once per calibration refit); ``frame`` takes the other inputs and ``outputs`` and
        gives the model's outputs.

    Raises:
        ValueError: the graph cannot be cut there (a tensor missing, or the frame part
            still reading the reference).
    """
    import onnx
    from onnx.utils import Extractor
    outputs = list(outputs)
    try:
        inferred = onnx.shape_inference.infer_shapes(model)
        ex = Extractor(inferred)
        refit = ex.extract_model([ref_input], outputs)
        others = [i.name for i in model.graph.input if i.name != ref_input]
        frame = ex.extract_model(others + outputs, [o.name for o in model.graph.output])
    except Exception as exc:  # onnx raises assorted types for a graph it cannot cut
        raise ValueError(f"ann: cannot split the hyper model at {outputs}: {exc}") from exc
    if any(ref_input in n.input for n in frame.graph.node):
        raise ValueError(f"ann: the hyper model's frame part still reads {ref_input!r}")
    for m in (refit, frame):
        m.ClearField("metadata_props")
    return refit, frame


def hyper_trunk(frame, names):
    """The trunk of a hyper model's frame part, or None.

    Args:
        frame: the frame part (:func:`split_hyper`) of a model whose metadata
            ``lgs_wfs.hyper_trunk`` names ``{"z": tensor, "total": tensor}``: ``z = filters
            (marginals / total) + fbias`` and ``total = max(sum marginals, 1)``
            (:func:`.kernels.hyper_contract` computes both in one pass).
        names: that metadata, or None (the whole frame part runs in onnxruntime).

    Returns:
        An onnxruntime session from ``(z, total)`` to the model's outputs, or None.

    Raises:
        ValueError: the frame part cannot be cut there, or its trunk still reads the
            marginals or the filters.
    """
    if names is None:
        return None
    import onnx
    from onnx.utils import Extractor
    try:
        trunk = Extractor(onnx.shape_inference.infer_shapes(frame)).extract_model(
            [names["z"], names["total"]], [o.name for o in frame.graph.output])
    except Exception as exc:  # onnx raises assorted types for a graph it cannot cut
        raise ValueError(f"ann: cannot cut the hyper model's trunk at {names}: {exc}") from exc
    read = {i for n in trunk.graph.node for i in n.input}
    outside = [i.name for i in frame.graph.input if i.name in read]
    if outside:
        raise ValueError(f"ann: the hyper model's trunk still reads {outside}")
    trunk.ClearField("metadata_props")
    return open_session(trunk.SerializeToString())


def fold_sum_normalisation(model, input_name: str, width: int):
    """Fold the per-subaperture sum normalisation into the model's first product.

    Args:
        model: ``onnx.ModelProto`` whose input ``input_name`` (``(batch, width)``) takes
            sum-normalised pixels.
        input_name: the pixel input.
        width: pixels per subaperture, ``p*p``.

    Returns:
        A new ``ModelProto`` taking raw counts on the same input, with an extra output
        ``TOTAL_OUTPUT`` ``(batch, 1)`` (each subaperture's total), or None when the graph
        does not have the foldable pattern (the pixel input used once, by a ``MatMul``
        with a constant ``(width, h)`` matrix, or by a ``Gemm`` with constant weights and
        bias, ``alpha = 1`` and no ``transA``).
    """
    import onnx
    from onnx import helper, numpy_helper

    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    users = [n for n in g.node if input_name in n.input]
    inits = {i.name: i for i in g.initializer}
    if len(users) != 1 or users[0].op_type not in ("MatMul", "Gemm") \
            or list(users[0].input).index(input_name) != 0 or users[0].input[1] not in inits:
        return None
    mm = users[0]
    attrs = {a.name: helper.get_attribute_value(a) for a in mm.attribute}
    if attrs.get("transA", 0) or attrs.get("alpha", 1.0) != 1.0:
        return None
    w = numpy_helper.to_array(inits[mm.input[1]])
    if attrs.get("transB", 0):
        w = w.T
    bias = None
    if mm.op_type == "Gemm" and len(mm.input) > 2 and mm.input[2]:
        if mm.input[2] not in inits:
            return None
        bias = numpy_helper.to_array(inits[mm.input[2]]) * attrs.get("beta", 1.0)
    if w.ndim != 2 or w.shape[0] != width:
        return None
    h = w.shape[1]
    for name in mm.input[1:]:
        if name in inits and sum(name in n.input for n in g.node) == 1:
            g.initializer.remove(inits[name])
    pre = "_lgs_wfs_fold_"
    g.initializer.extend([
        numpy_helper.from_array(np.concatenate([w, np.ones((width, 1), w.dtype)], axis=1), pre + "w"),
        numpy_helper.from_array(np.array([0], np.int64), pre + "i0"),
        numpy_helper.from_array(np.array([h], np.int64), pre + "ih"),
        numpy_helper.from_array(np.array([h + 1], np.int64), pre + "ih1"),
        numpy_helper.from_array(np.array([1], np.int64), pre + "axis")])
    out = mm.output[0]
    k = list(g.node).index(mm)
    g.node.remove(mm)
    new = [helper.make_node("MatMul", [input_name, pre + "w"], [pre + "ext"]),
           helper.make_node("Slice", [pre + "ext", pre + "i0", pre + "ih", pre + "axis"], [pre + "num"]),
           helper.make_node("Slice", [pre + "ext", pre + "ih", pre + "ih1", pre + "axis"], [TOTAL_OUTPUT])]
    if bias is None:
        new.append(helper.make_node("Div", [pre + "num", TOTAL_OUTPUT], [out]))
    else:                              # a Gemm's bias is added after the normalised product
        g.initializer.append(numpy_helper.from_array(bias.astype(w.dtype), pre + "bias"))
        new += [helper.make_node("Div", [pre + "num", TOTAL_OUTPUT], [pre + "div"]),
                helper.make_node("Add", [pre + "div", pre + "bias"], [out])]
    for j, node in enumerate(new):
        g.node.insert(k + j, node)
    g.output.append(helper.make_tensor_value_info(TOTAL_OUTPUT, onnx.TensorProto.FLOAT, ["batch", 1]))
    return m
