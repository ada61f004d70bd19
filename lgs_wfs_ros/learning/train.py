"""Train the shipped networks from scratch: data, optimiser, export, validation record.

``train_model(name)`` runs one :mod:`.recipes` recipe end to end:

1. streams ``samples`` training samples (:mod:`.dataset`, tqdm progress bar) and a
   held-out monitor set from another seed;
2. trains the tanh MLP (Adam with a cosine learning rate; the paper's Levenberg-Marquardt
   was measured slower and worse, docs/training.md), keeping the weights with the lowest
   monitor error;
3. exports ONNX with the ``lgs_wfs.*`` metadata (:mod:`.export`);
4. records the validation errors (:mod:`.validate`) in ``lgs_wfs.training``.

PyTorch is imported inside the functions only.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from ..optics.geometry import detector_to_local
from ..optics.turbulence import turbulence_sigma_px
from ..sensor import Sensor
from . import dataset, domains, export, recipes
from .model import layers_of, linears, mlp, n_parameters

CHECK_SEED = 90_001          # seed of the small fixed check set stored in the metadata
CHECK_N = 2000
MONITOR_SEED = 77_777


def recipe_sensor(rec: recipes.Recipe) -> Sensor:
    """The training sensor of a recipe."""
    if rec.pupil:
        return Sensor()
    if rec.radius_m is None:
        return Sensor.paper_single(rec.detector)
    r = float(rec.radius_m)
    xy = (r, 0.0) if rec.detector == "polar" else (r / math.sqrt(2), r / math.sqrt(2))
    return Sensor(detector=rec.detector, single_subaperture_xy_m=xy)


def recipe_spec(rec: recipes.Recipe) -> dataset.DataSpec:
    """The :class:`.dataset.DataSpec` of a recipe."""
    return dataset.DataSpec(recipe_sensor(rec), photons=rec.photons, sigma_px=rec.sigma_px,
                            pupil=rec.pupil, conditioning=rec.conditioning,
                            profile_model=rec.profile_model, mix_fraction=rec.mix_fraction,
                            r_power=rec.r_power, detectors=rec.detectors)


def input_gain(rec: recipes.Recipe) -> float:
    """Pixel input scale: sum-normalised images times p*p (mean pixel 1)."""
    return float(recipe_sensor(rec).pixels ** 2)


def _features(data: dict, rec: recipes.Recipe) -> np.ndarray:
    if rec.conditioning == "e_r":
        return np.concatenate([data["x"], data["cond"]], axis=1)
    return data["x"]


def _mean_error(net, xt, yt) -> float:
    import torch
    with torch.no_grad():
        out = torch.cat([net(xt[a:a + 65536]) for a in range(0, xt.shape[0], 65536)])
    return float(torch.linalg.vector_norm(out - yt, dim=1).mean())


def input_jacobian(net, x):
    """Outputs and input Jacobian of a tanh :func:`.model.mlp` (differentiable in the weights).

    Args: ``net`` (Linear / Tanh ``Sequential``), ``x (B, in)`` torch tensor.
    Returns: ``(y (B, out), J (B, out, in))`` with ``J[b, k, i] = d y_k / d x_i``.
    """
    import torch
    h, slopes = x, []
    for m in net:
        h = m(h)
        if isinstance(m, torch.nn.Tanh):
            slopes.append(1.0 - h * h)                     # tanh' at this layer, (B, width)
    lin = linears(net)
    jac = lin[-1].weight.unsqueeze(0)                      # (1, out, width)
    for layer, d in zip(reversed(lin[:-1]), reversed(slopes)):
        jac = (jac * d.unsqueeze(1)) @ layer.weight        # (B, out, previous width)
    return h, jac


def poisson_penalty(jac, x, photons: float, input_gain: float):
    """Expected extra squared error of each output under photon noise, first order (Bishop 1995).

    The input is ``x = G c / sum(c)`` with Poisson counts ``c`` of mean ``N p`` (``p`` the
    noise-free image, ``sum(p) = 1``, ``G = input_gain``, ``N = photons``). To first order
    ``Cov(x) = (G diag(x) - x x^T) / N`` (the ``- x x^T`` term is the sum normalisation),
    so output ``k`` gains the variance ``(G sum_i J_ki^2 x_i - (sum_i J_ki x_i)^2) / N``.

    Args: ``jac (B, out, in)`` from :func:`input_jacobian`; ``x (B, in)`` noise-free
    inputs (with the gain, pixels only: conditioning columns carry no noise).
    Returns: ``(B, out)`` variances (units of the output squared, px^2).
    """
    jp = jac[..., :x.shape[1]]
    xs = x.unsqueeze(1)
    return (input_gain * (jp * jp * xs).sum(-1) - (jp * xs).sum(-1) ** 2) / photons


EUCLID_EPS_PX2 = 1e-3      # softening of the "euclid" loss at zero error, px^2


def _loss(net, xb, yb, loss: str, noise_penalty_photons, pixels, input_gain):
    """Mini-batch loss: "mse" (mean squared error per output, the paper's) or "euclid"
    (mean over samples of ``sqrt(|y - t|^2 + EUCLID_EPS_PX2)``, the validation metric's
    Euclidean error, softened at 0); with ``noise_penalty_photons`` the squared error of
    each output gets its first-order photon-noise variance (:func:`poisson_penalty`)."""
    if noise_penalty_photons is None:
        out, pen = net(xb), 0.0
    else:
        out, jac = input_jacobian(net, xb)
        pen = poisson_penalty(jac, xb[:, :pixels or xb.shape[1]], noise_penalty_photons,
                              input_gain)
    se = (out - yb) ** 2 + pen                                 # (B, out) expected, px^2
    if loss == "mse":
        return se.mean()
    return (se.sum(1) + EUCLID_EPS_PX2).sqrt().mean()


def fit_adam(net, x, y, xv, yv, *, epochs: int, batch: int, lr: float, seed: int,
             time_budget_s: float | None = None, progress: bool = True,
             weight_decay: float = 0.0, noise_penalty_photons: float | None = None,
             pixels: int | None = None, input_gain: float = 1.0,
             loss: str = "mse") -> list[dict]:
    """Adam, MSE loss, cosine-decayed ``lr``; keeps the best monitor weights.

    With ``noise_penalty_photons = N`` the squared error gets the :func:`poisson_penalty`
    of the first ``pixels`` inputs at ``N`` photons (so the loss is the expected loss of
    noisy images at ``N`` photons, to first order), from noise-free ``x`` only.
    ``loss = "euclid"``: per-sample root of that (expected) squared error instead of the
    MSE (:func:`_loss`).

    Args: torch float32 tensors ``x (N, in)``, ``y (N, 2)``, monitor ``xv``, ``yv``.
    Returns: history rows ``{"epoch", "train_mse", "monitor_err_px", "seconds"}``
    (``train_mse`` is the training loss, penalty included).
    """
    if loss not in ("mse", "euclid"):
        raise ValueError(f"loss must be 'mse' or 'euclid', got {loss!r}")
    import torch
    from tqdm.auto import tqdm

    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay) if weight_decay \
        else torch.optim.Adam(net.parameters(), lr=lr)
    steps = epochs * math.ceil(x.shape[0] / batch)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda k: 0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(k, steps) / steps)))
    best, best_state, hist = math.inf, None, []
    t0 = time.perf_counter()
    bar = tqdm(range(epochs), desc="adam", disable=not progress, mininterval=2.0)
    for ep in bar:
        perm = torch.randperm(x.shape[0], generator=g)
        tot = 0.0
        for a in range(0, x.shape[0], batch):
            idx = perm[a:a + batch]
            value = _loss(net, x[idx], y[idx], loss, noise_penalty_photons, pixels, input_gain)
            opt.zero_grad(set_to_none=True)
            value.backward()
            opt.step()
            sched.step()
            tot += float(value.detach()) * idx.numel()
        err = _mean_error(net, xv, yv)
        if err < best:
            best = err
            best_state = {k: v.clone() for k, v in net.state_dict().items()}
        row = {"epoch": ep, "train_mse": tot / x.shape[0], "monitor_err_px": err,
               "seconds": time.perf_counter() - t0}
        hist.append(row)
        bar.set_postfix(mse=f"{row['train_mse']:.4f}", err=f"{err:.4f}")
        if time_budget_s is not None and row["seconds"] > time_budget_s:
            break
    if best_state is not None:
        net.load_state_dict(best_state)
    return hist


def training_data(rec: recipes.Recipe, samples: int, seed: int, progress: bool = True) -> dict:
    """Generate the training arrays of a recipe (``x`` already has the input gain)."""
    return dataset.generate(recipe_spec(rec), samples, batch=8192, seed=seed, progress=progress,
                            input_gain=input_gain(rec))


def check_set(rec: recipes.Recipe, n: int = CHECK_N, seed: int = CHECK_SEED,
              sigma_px: float | None = None):
    """The small fixed check set of a model: fresh random profiles at the recipe's sensor,
    1000 photons (noise-free models: also 1000 photons), turbulence-like positions of rms
    ``sigma_px`` per axis (default :func:`..optics.turbulence.turbulence_sigma_px` of the
    reference sensor).

    Returns :class:`.dataset.Samples` (``x`` without gain, as the ONNX model takes it).
    """
    sigma = turbulence_sigma_px(Sensor()) if sigma_px is None else float(sigma_px)
    spec = recipe_spec(rec).replace(photons=1000.0, sigma_px=sigma)
    return dataset.sample(spec, np.random.default_rng(seed), n)


def check_error(path, rec: recipes.Recipe, n: int = CHECK_N, seed: int = CHECK_SEED) -> float:
    """Mean Euclidean error (px) of a model on its fixed check set (the position rms the
    model's metadata recorded for it, if any)."""
    meta = export.read_metadata(path)
    sigma = meta.get("lgs_wfs.training", {}).get("check", {}).get("sigma_px")
    s = check_set(rec, n, seed, sigma)
    out = export.predict_samples(Path(path), s)
    truth = s.y.astype(np.float64)
    if meta.get("lgs_wfs.output_frame") == "local":
        truth = detector_to_local(truth, s.e_pix)
    return float(np.linalg.norm(out - truth, axis=1).mean())


def target_path(name: str, out_dir=None, force: bool = False) -> Path:
    """Where ``train_model`` writes model ``name``: ``out_dir/NAME.onnx``, never over an
    existing file unless ``force``; ``out_dir=None``: a new temporary directory."""
    recipes.get(name)
    if out_dir is None:
        import tempfile
        out_dir = tempfile.mkdtemp(prefix="lgs-wfs-train-")
    path = Path(out_dir) / f"{name}.onnx"
    if path.exists() and not force:
        raise FileExistsError(f"{path} exists; train into another --out directory, or pass --force "
                              "to replace it")
    return path


def train_model(name: str, out_dir=None, samples: int | None = None, seed: int | None = None,
                quick: bool = False, validate: bool = True,
                progress: bool = True, time_budget_s: float | None = None,
                force: bool = False) -> dict:
    """Retrain a model from scratch into ``out_dir/NAME.onnx`` and regenerate the card.

    Args:
        name: a recipe name (:data:`.recipes.RECIPES`: ann_1k, ann_noiseless, ann_diag,
            ann_pupil and the ``ref_*`` reference networks).
        out_dir: output directory (created; default a new temporary directory).
        samples: training samples (default the recipe's; ``quick``: 20,000).
        seed: data/initialisation seed (default the recipe's).
        quick: a small fast run (fewer samples and epochs) to check the pipeline.
        validate: run :func:`.validate.validate_model` and record its numbers (for
            ann_pupil also the ring criterion against the ``ref_*`` networks found in
            ``out_dir``).
        time_budget_s: stop the optimiser after this wall time.
        force: replace an existing ``out_dir/NAME.onnx`` (else ``FileExistsError``,
            before any training).

    Returns:
        ``{"path", "recipe", "history", "check_err_px", "validation", "seconds", "card"}``.
    """
    target = target_path(name, out_dir, force)
    out_dir = target.parent
    import torch

    rec = recipes.get(name)
    t0 = time.perf_counter()
    seed = rec.seed if seed is None else int(seed)
    samples = (rec.quick_samples if quick else rec.samples) if samples is None else int(samples)
    epochs = max(2, rec.epochs // 8) if quick else rec.epochs
    line = rec.line(samples).replace(f"seed {rec.seed}", f"seed {seed}")
    print("recipe:", line, flush=True)
    torch.set_num_threads(1)

    data = training_data(rec, samples, seed, progress)
    mon_spec = recipe_spec(rec) if rec.monitor_photons is None else \
        recipe_spec(rec).replace(photons=rec.monitor_photons)
    mon = dataset.generate(mon_spec, min(20_000, max(2000, samples // 10)), batch=8192,
                           seed=MONITOR_SEED + seed, progress=False, input_gain=input_gain(rec))
    x = torch.from_numpy(_features(data, rec)); y = torch.from_numpy(data["y"])
    xv = torch.from_numpy(_features(mon, rec)); yv = torch.from_numpy(mon["y"])
    net = mlp(rec.sizes, seed=seed)
    t_fit = time.perf_counter()
    hist = fit_adam(net, x, y, xv, yv, epochs=epochs, batch=rec.batch, lr=rec.lr, seed=seed,
                    time_budget_s=time_budget_s, progress=progress, weight_decay=rec.weight_decay,
                    noise_penalty_photons=rec.noise_penalty_photons,
                    pixels=recipe_sensor(rec).pixels ** 2, input_gain=input_gain(rec),
                    loss=rec.loss)
    fit_s = time.perf_counter() - t_fit

    rotate = rec.conditioning != "none"
    frame = "local" if (rotate or rec.detector == "polar") else "detector"
    training = {"recipe": rec.to_dict(), "recipe_line": line, "optimizer": "adam", "seed": seed,
                "samples": samples, "quick": quick, "parameters": n_parameters(rec.sizes),
                "sensor": recipe_sensor(rec).to_dict(), "photons": rec.photons,
                "position_sigma_px": rec.sigma_px, "normalisation":
                "image / sum(image) (times p*p folded into the first layer)",
                "profiles": "random 5-Gaussian model fitted to measured profiles 0-65 (66-87 held out for validation)",
                "fit_seconds": round(fit_s, 1),
                "final_monitor_err_px": min(h["monitor_err_px"] for h in hist),
                "check": {"seed": CHECK_SEED, "n": CHECK_N, "photons": 1000.0,
                          "sigma_px": turbulence_sigma_px(Sensor())}}
    if rec.noise_penalty_photons is not None:
        training["noise_model"] = (
            f"trained on noise-free images only (training and monitor sets); photon noise "
            f"enters as its known first-order Poisson variance at {rec.noise_penalty_photons:g} "
            f"photons, Cov(x) = (G diag(x) - x x^T) / N with G = {input_gain(rec):g}, through the "
            f"penalty sum_i,j (dy_k/dx_i) Cov_ij (dy_k/dx_j) added to the squared error "
            f"(Bishop 1995), not as noisy samples; loss {rec.loss}")
    meta = {"lgs_wfs.detector": rec.detector, "lgs_wfs.output_frame": frame,
            "lgs_wfs.conditioning_frame": "pixel", "lgs_wfs.training": training,
            "lgs_wfs.domain": domains.recipe_domain(rec, training)}
    model = export.build_model(layers_of(net), pixels=recipe_sensor(rec).pixels,
                               conditioning=rec.conditioning, input_gain=input_gain(rec),
                               metadata=meta, name=name, rotate_to_local=rotate)
    tmp = export.save(model, target.with_name(target.name + ".partial"))
    training["check"]["mean_err_px"] = check_error(tmp, rec)
    validation = None
    if validate:
        validation = record_validation(tmp, rec, training, out_dir, quick, progress)
    export.update_metadata(tmp, {"lgs_wfs.training": training})
    path = tmp.replace(target)
    from . import card
    card_path = card.write(out_dir)
    secs = time.perf_counter() - t0
    print(f"wrote {path}: check error {training['check']['mean_err_px']:.4f} px, "
          f"{secs:.0f} s", flush=True)
    return {"path": str(path), "recipe": line, "history": hist,
            "check_err_px": training["check"]["mean_err_px"], "validation": validation,
            "seconds": secs, "card": str(card_path)}


def record_validation(path, rec: recipes.Recipe, training: dict, out_dir, quick: bool,
                      progress: bool) -> dict:
    """Validate a freshly written model and put the numbers into ``training`` (in place):
    the cases of :func:`.validate.validate_model`; for pupil models also the whole-pupil
    error and, when the ``ref_*`` networks are in ``out_dir``, the ring criterion."""
    from . import validate as val
    training["validation"] = val.validate_model(path, rec, quick=quick, progress=progress)
    if rec.pupil:
        n = 2000 if quick else val.PUPIL_CRITERION_N
        training["pupil_all_subapertures_err_px"] = val.pupil_all_subapertures(path, n)
        refs = [Path(out_dir) / f"{ref}.onnx" for ref, _ in val.RINGS.values()]
        if all(r.is_file() for r in refs):
            training["pupil_criterion"] = val.pupil_criterion(path, out_dir, out_dir, n=n)
        else:
            training["pupil_criterion_note"] = (f"not evaluated: train the ref_* networks into {out_dir} "
                                                "first")
    return training["validation"]
