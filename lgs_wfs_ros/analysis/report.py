"""``lgs-wfs report BAG``: per-algorithm errors, CRB, error by radius and over time, plots, JSON.

For every centroider segment of a bag (see :mod:`.bagload`) the slopes are joined to the
truths by header stamp and summarised with :func:`.metrics.summarize` (mean Euclidean
error, per-axis mean absolute error, RMS, bias; px and mas). The Cramer-Rao bound needs the
noise-free image model of the same frames: for a bag written by our simulator it is rebuilt
from the simulator settings stored in the sensor description, at the truths of a sample of
frames (:func:`simulator_model`); :mod:`..centroiding.crb` then bounds the position error
(Poisson + read noise, flux a nuisance parameter), and gives beside it the CoG floor, the
error of a CoG whose bias and response are known exactly (``crb.cog_covariance``: what
no calibration of a CoG gets under). A bag from another tool has no such
model and its report says so. (Rebuilding the model from the noisy frames themselves was
tried and rejected: the spot core is 1.19 px FWHM, so Fourier re-centring of undersampled
frames rings and the bound collapses.) Neither the errors nor the CRB read the recorded frames,
so a bag whose frames were recorded as chosen subapertures only (or not at all) gets the
same report; the header line counts those subaperture frames.

Ratios compare like with like: ``x CoG`` on the frames both the algorithm and the (first)
cog segment measured, ``x CRB`` on the frames the CRB was computed at (up to 256 for a single
subaperture, 16 for a full pupil: :func:`crb_frame_count`); each says its basis. Plots
(``--out``): error over time as a median and 16-84 % band per time bin (thousands of frames
are never drawn one by one) with the CRB at its frames, the error distribution (density),
the ratios to CoG and CRB, and for a full pupil the error by distance from the launch; each
with a title, units in px and mas, and a legend.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
from scipy.special import ellipe

from ..optics import geometry
from . import metrics
from .bagload import BagData, joined, load_bag, skip_frames
from .report_plots import TIME_BINS, binned, write_plots

CRB_SAMPLES = 16             # frames the CRB is computed at, at least ...
CRB_SUBAPERTURE_FRAMES = 16 * 2784   # ... and up to this many subaperture-frames (<= 256 frames)
CRB_MAX_FRAMES = 256


def crb_frame_count(frames: int, n_subaps: int) -> int:
    """How many of ``frames`` truth frames the CRB is computed at: enough subaperture-frames
    for a ratio to the CRB that is not noise (a single subaperture gets up to 256 frames, a
    full pupil 16), never more than there are."""
    want = max(CRB_SAMPLES, min(CRB_MAX_FRAMES, -(-CRB_SUBAPERTURE_FRAMES // max(n_subaps, 1))))
    return min(frames, want)


# -- CRB --------------------------------------------------------------------------------------
def mean_abs_norm(cov: np.ndarray) -> np.ndarray:
    """``E|v|`` for ``v ~ N(0, cov)``: ``(..., 2, 2)`` covariances -> ``(...)``.

    With eigenvalues ``s1^2 >= s2^2``: ``sqrt(2/pi) s1 E(1 - s2^2/s1^2)`` (E the complete
    elliptic integral of the second kind): ``s sqrt(pi/2)`` for a round error, ``s1 sqrt(2/pi)``
    for a one-dimensional one.
    """
    ev = np.linalg.eigvalsh(np.nan_to_num(cov, nan=0.0))
    s1 = np.sqrt(np.maximum(ev[..., 1], 0))
    s2 = np.sqrt(np.maximum(ev[..., 0], 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.where(s1 > 0, 1 - (s2 / np.where(s1 > 0, s1, 1)) ** 2, 0.0)
    out = math.sqrt(2 / math.pi) * s1 * ellipe(m)
    return np.where(np.isfinite(cov).all(axis=(-1, -2)), out, np.nan)


def crb_summary(cov: np.ndarray, mas_per_px: float = 500.0) -> dict:
    """Summary of ``(n, 2, 2)`` CRB covariances (detector axes, px^2) in the report's metrics.

    ``mean_euclid``: mean over subapertures of the expected ``|err|`` of an unbiased
    estimator at the bound; ``mae``: expected per-axis mean absolute error
    (``sqrt(2/pi) sigma``, averaged over x and y); ``sigma_x``, ``sigma_y``: mean bound std.
    """
    sig = np.sqrt(np.einsum("nii->ni", cov))
    out = {"mean_euclid": float(np.nanmean(mean_abs_norm(cov))),
           "mae": float(np.nanmean(math.sqrt(2 / math.pi) * sig)),
           "sigma_x": float(np.nanmean(sig[:, 0])), "sigma_y": float(np.nanmean(sig[:, 1])),
           "n_subaps": int(np.isfinite(sig).all(axis=1).sum())}
    out.update({k + "_mas": out[k] * mas_per_px for k in ("mean_euclid", "mae", "sigma_x", "sigma_y")})
    return out


def crb_covariances(sensor, image_at, truths: np.ndarray) -> np.ndarray:
    """``(K*n, 2, 2)`` CRB covariances (detector axes, px^2) at ``K`` truths ``(K, n, 2)``.

    image_at(k, shift): expected counts ``(n, p, p)`` (block pixel axes, background included
    as in the frames) of frame ``k`` with the spot displaced by ``shift (n, 2)`` px, detector
    axes. Derivatives by central differences (``crb.model_derivatives``).
    """
    return bound_covariances(sensor, image_at, truths)["crb"]


def bound_covariances(sensor, image_at, truths: np.ndarray) -> dict:
    """``{"crb", "cog"}``, each ``(K*n, 2, 2)`` (detector axes, px^2): the Cramer-Rao bound
    and the photon-noise floor of the response-inverted CoG (``crb.cog_covariance``) of the
    same images; arguments as :func:`crb_covariances`, one set of derivatives for both."""
    from ..centroiding.crb import cog_covariance, crb_covariance, model_derivatives

    out = {"crb": [], "cog": []}
    for k, t in enumerate(truths):
        ok = np.isfinite(t).all(axis=1)
        t = np.where(ok[:, None], t, 0.0)
        mu, dx, dy = model_derivatives(lambda s, k=k: image_at(k, s), t.shape[0], shift=t)
        signal = np.maximum(mu - sensor.background_e, 0)
        for key, fn in (("crb", crb_covariance), ("cog", cog_covariance)):
            cov = fn(signal, dx, dy, read_noise_e=sensor.read_noise_e,
                     background_e=sensor.background_e)
            cov[~ok] = np.nan
            out[key].append(cov)
    return {key: np.concatenate(v) for key, v in out.items()}


def simulator_model(data: BagData):
    """``(image_at, truths (K, n, 2), note, stamps (K,))`` rebuilt from the simulator settings
    in the sensor description (keys ``simulation`` and ``start_stamp_ns``, as written by
    :func:`.bagwrite.make_sample_bag`) at :func:`crb_frame_count` frames spread over the bag,
    or None when the bag does not carry them."""
    info = data.sensor_info or {}
    if data.sensor is None or data.truth is None or not len(data.truth) or "simulation" not in info:
        return None
    from ..optics.simulator import SimulationConfig, Simulator
    try:
        cfg = SimulationConfig.from_dict(info["simulation"])
        sim = Simulator(data.sensor, cfg.replace(turbulence=False))
    except (ValueError, TypeError, KeyError, FileNotFoundError):
        return None
    start = int(info.get("start_stamp_ns", data.truth.stamps[0]))
    lay = geometry.layout(data.sensor)
    k = crb_frame_count(len(data.truth), lay.n_valid)
    idx = np.unique(np.linspace(0, len(data.truth) - 1, k).astype(int))
    truths = data.truth.data[idx][:, lay.valid.ravel()].astype(float)
    frame_index = np.rint((data.truth.stamps[idx] - start) * data.sensor.frame_rate_hz / 1e9).astype(int)
    s = data.sensor
    frame_index = np.maximum(frame_index, 0)
    profiles = {}
    if cfg.profile == "random" and frame_index.max() < 10**6:
        wanted = set(frame_index.tolist())      # random draws are sequential: replay them in order
        for i in range(int(frame_index.max()) + 1):
            d = sim.profile_at(i)
            if i in wanted:
                profiles[i] = d

    def image_at(k, shift):
        i = int(frame_index[k])
        density, key = profiles[i] if i in profiles else sim.profile_at(i)
        img, _ = sim.spots(density, key, shift)
        if cfg.per_field:
            img = img / img.sum(axis=(1, 2), keepdims=True)
        return img * s.photons + s.background_e
    return (image_at, truths, f"simulator image model ({cfg.profile} profile) at the truths of {len(idx)} frames",
            data.truth.stamps[idx])


# -- analysis ---------------------------------------------------------------------------------
def _valid(data: BagData) -> tuple[np.ndarray, np.ndarray | None]:
    """(valid cell mask (G*G,), r_m of the valid cells or None)."""
    if data.sensor is not None:
        lay = geometry.layout(data.sensor)
        return lay.valid.ravel(), np.asarray(lay.r_m)
    finite = np.isfinite(data.truth.data).all(axis=2).any(axis=0)
    return finite, None


def radius_edges(r_m: np.ndarray, rings: int = 6) -> np.ndarray:
    lo, hi = float(r_m.min()), float(r_m.max())
    if hi - lo < 1e-9:
        return np.array([lo - 0.25, hi + 0.25])
    return np.linspace(lo, hi + 1e-6, rings + 1)


def analyse(data: BagData, crb: bool = True, image_model=None) -> dict:
    """The report's numbers for a loaded bag (JSON-able dict; see :func:`report_bag`).

    image_model: ``(image_at(k, shift), truths (K, n, 2), note)`` for the CRB (default: the
    simulator's model from the bag's sensor description, when it has one).
    """
    if data.truth is None or len(data.truth) == 0:
        raise ValueError(f"{data.path}: no truths recorded; nothing to compare against")
    if not data.segments:
        raise ValueError(f"{data.path}: no slopes topic (/<namespace>/slopes); run "
                         f"`lgs-wfs replay {data.path} --algorithms cog,cmf` to add some")
    mas = data.mas_per_px
    valid, r_m = _valid(data)
    edges = radius_edges(r_m) if r_m is not None else None
    out = {"bag": data.path, "sensor": data.sensor_info or None, "mas_per_px": mas,
           "frames": data.frame_count, "truths": len(data.truth), "algorithms": {}, "crb": None,
           "subaperture_frames": data.subapertures}
    series, errs = {}, {}
    for seg in data.segments:
        if not len(seg.slopes):       # a centroider that described itself, no slope recorded
            out.setdefault("without_slopes", []).append(seg.label)
            continue
        stamps, est, tru, j = joined(data.truth, seg.slopes)
        err = metrics.errors(est[:, valid], tru[:, valid])            # (K, n, 2)
        s = metrics.summarize(err, mas)
        s["algorithm"] = seg.description.get("algorithm", seg.namespace)
        s["namespace"] = seg.namespace
        s["description"] = seg.description
        s["join"] = {"slopes": len(seg.slopes), "joined": int(len(stamps)),
                     "truth_without_slopes": int(j.n_missing[1]), "slopes_without_truth": int(j.n_missing[0]),
                     "duplicate_slope_stamps": int(j.duplicates[1]),
                     "duplicate_truth_stamps": int(j.duplicates[0])}
        if edges is not None:
            s["by_radius"] = metrics.by_radius(err, r_m, edges)
        dist = np.hypot(err[..., 0], err[..., 1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)      # frames with no finite error
            per_frame = np.nanmean(dist, axis=1) if dist.size else np.zeros(0)
        series[seg.label] = (stamps, per_frame)
        errs[seg.label] = (stamps, err)
        out["algorithms"][seg.label] = s
    if not out["algorithms"]:
        raise ValueError(f"{data.path}: no slopes recorded ({', '.join(out['without_slopes'])} "
                         f"described, none measured a frame in the bag)")
    _ratios_to_cog(out["algorithms"], errs)
    crb_frames = None
    if crb:
        out["crb"], crb_frames = _crb_block(data, r_m, edges, mas, image_model)
        _ratios_to_crb(out["algorithms"], errs, out["crb"], crb_frames)
        out["_crb_frames"] = crb_frames
    if data.sensor is not None and r_m is not None and len(r_m) >= 4:
        _ttf_removed(out["algorithms"], errs, data.sensor, mas, out.get("crb"), crb_frames,
                     r_m, edges)
    out["_series"] = series
    out["_errors"] = errs
    return out


def _frame_stats(stamps, err, keep):
    """(mean |err|, per-axis MAE) over the frames of ``stamps`` that are in ``keep``."""
    e = err[np.isin(stamps, keep)].reshape(-1, 2)
    e = e[np.isfinite(e).all(axis=1)]
    if not len(e):
        return float("nan"), float("nan")
    return float(np.hypot(e[:, 0], e[:, 1]).mean()), float(np.abs(e).mean())


def _ratios_to_cog(algs: dict, errs: dict) -> None:
    """Each algorithm's mean |err| and MAE over CoG's on the frames both measured (the first
    cog segment is the reference); on each one's own frames when they share none."""
    ref = next((k for k, v in algs.items() if v["algorithm"] == "cog"), None)
    for label, v in algs.items():
        v["ratio_to_cog"] = v["mae_ratio_to_cog"] = v["ratio_to_cog_basis"] = None
        if ref is None:
            continue
        common = np.intersect1d(errs[label][0], errs[ref][0])
        if len(common):
            (a, am), (b, bm) = _frame_stats(*errs[label], common), _frame_stats(*errs[ref], common)
            v["ratio_to_cog_basis"] = f"{len(common)} frames measured by both"
        else:
            (a, am), (b, bm) = (v["mean_euclid"], v["mae"]), (algs[ref]["mean_euclid"], algs[ref]["mae"])
            v["ratio_to_cog_basis"] = "each on its own frames (none in common)"
        v["ratio_to_cog"] = a / b if b > 0 else None
        v["mae_ratio_to_cog"] = am / bm if bm > 0 else None


def _ratios_to_crb(algs: dict, errs: dict, crb: dict, crb_frames) -> None:
    """Each algorithm's mean |err| over the CRB's expected |err| on the same frames and
    subapertures (the frames the CRB was computed at that the algorithm measured); against the
    CRB's mean when the CRB's frames are not known or none was measured."""
    if not crb or not crb.get("mean_euclid"):
        return
    for label, v in algs.items():
        stamps, err = errs[label]
        if crb_frames is not None:
            cst, d = crb_frames                                   # (K,), (K, n) expected |err|
            common, ia, ib = np.intersect1d(stamps, cst, return_indices=True)
            if len(common):
                e = np.hypot(err[ia, :, 0], err[ia, :, 1])
                ok = np.isfinite(e) & np.isfinite(d[ib])
                if ok.any():
                    v["ratio_to_crb"] = float(e[ok].mean() / d[ib][ok].mean())
                    v["ratio_to_crb_basis"] = f"{len(common)} frames"
                    continue
        v["ratio_to_crb"] = v["mean_euclid"] / crb["mean_euclid"]
        v["ratio_to_crb_basis"] = "all frames vs the CRB's sample"


def _ttf_removed(algs: dict, errs: dict, sensor, mas, crb, crb_frames, r_m=None,
                 edges=None) -> None:
    """Each algorithm's numbers with the pupil-wide tip, tilt and focus removed from the
    error (``v["ttf"]``: mean |err|, MAE, and the ratios to CoG and to the CRB on the same
    frames, against the raw bound: 3 modes of thousands of slopes change it by < 0.1 %;
    with ``edges``, its mean |err| by ring of ``r_m (n,)``, metres, as ``by_radius``)."""
    q = metrics.ttf_modes(geometry.layout(sensor).centre_xy_m)   # the valid cells, in order
    clean = {lb: (st, metrics.remove_ttf(err, q)) for lb, (st, err) in errs.items()}
    tmp = {}
    for lb, v in algs.items():
        s = metrics.summarize(clean[lb][1], mas)
        tmp[lb] = {"algorithm": v["algorithm"], "mean_euclid": s["mean_euclid"],
                   "mae": s["mae"], "mean_euclid_mas": s["mean_euclid_mas"]}
    _ratios_to_cog(tmp, clean)
    if crb and crb.get("mean_euclid"):
        _ratios_to_crb(tmp, clean, crb, crb_frames)
    for lb, v in algs.items():
        v["ttf"] = {k: tmp[lb].get(k) for k in ("mean_euclid", "mae", "mean_euclid_mas",
                                                 "ratio_to_cog", "ratio_to_crb")}
        if edges is not None:
            v["ttf"]["by_radius"] = metrics.by_radius(clean[lb][1], r_m, edges)


def _crb_block(data, r_m, edges, mas, image_model=None):
    """(CRB summary dict, (stamps (K,), expected |err| (K, n)) of the frames it was computed
    at, or None when their stamps are unknown)."""
    got = image_model if image_model is not None else simulator_model(data)
    if got is None:
        return {"method": "not computed: the bag carries no image model (simulator settings in "
                          "its sensor description)"}, None
    image_at, truths, note = got[:3]
    bounds = bound_covariances(data.sensor, image_at, truths)
    cov = bounds["crb"]
    block = crb_summary(cov, mas)
    block["frames"] = int(truths.shape[0])
    block["cog_floor"] = {k: v for k, v in crb_summary(bounds["cog"], mas).items()
                          if k.startswith(("mean_euclid", "mae"))}
    per_frame = None
    if len(got) > 3:
        per_frame = (np.asarray(got[3], np.int64), mean_abs_norm(cov).reshape(truths.shape[0], -1))
    block["method"] = (note + f", read noise {data.sensor.read_noise_e:g} e-, background "
                       f"{data.sensor.background_e:g} e-; flux a nuisance parameter")
    n = truths.shape[1]
    if edges is not None and n > 1:
        d = np.nanmean(mean_abs_norm(cov).reshape(-1, n), axis=0)
        ring = np.digitize(r_m, edges) - 1
        block["by_radius"] = [{"r_min_m": float(edges[k]), "r_max_m": float(edges[k + 1]),
                               "mean_euclid": float(np.nanmean(d[ring == k])) if (ring == k).any()
                               else float("nan")} for k in range(len(edges) - 1)]
    return block, per_frame


# -- output -----------------------------------------------------------------------------------
def format_report(res: dict) -> str:
    mas = res["mas_per_px"]
    sub = res.get("subaperture_frames")
    cut = ""
    if sub:
        ks = sorted({len(s) for s in sub["selections"]})
        cut = (f" (+ {sub['count']} cut to {'/'.join(map(str, ks)) or '?'} chosen subapertures "
               f"on {sub['topic']})")
    skipped = (f", scored after the first {res['skipped_frames']} exposures"
               if res.get("skipped_frames") else "")
    lines = [f"bag {res['bag']}: {res['frames']} frames{cut}, {res['truths']} truths{skipped}", ""]
    lines.append(metrics.table(res["algorithms"], mas))
    if res.get("without_slopes"):
        lines.append(f"no slopes recorded: {', '.join(res['without_slopes'])}")
    crb = res.get("crb") or {}
    if "mean_euclid" in crb:
        lines.append(f"{'CRB':<12}{crb['mean_euclid']:>12.4f}{crb['mae']:>11.4f}{'':>27}"
                     f"{crb['mean_euclid_mas']:>13.1f}   (unbiased floor)")
        fl = crb.get("cog_floor")
        if fl:
            lines.append(f"{'CoG floor':<12}{fl['mean_euclid']:>12.4f}{fl['mae']:>11.4f}{'':>27}"
                         f"{fl['mean_euclid_mas']:>13.1f}   (a CoG with its bias and response "
                         f"known exactly)")
    lines.append("")
    lines.append(f"{'algorithm':<16}{'x CoG':>8}{'x CRB':>8}{'MAE x CoG':>11}{'joined':>9}"
                 f"{'no slope':>10}{'dup':>6}")
    for name, v in res["algorithms"].items():
        f = (lambda x: f"{x:>8.3f}" if x is not None else f"{'-':>8}")
        j = v["join"]
        lines.append(f"{name:<16}{f(v.get('ratio_to_cog'))}{f(v.get('ratio_to_crb'))}"
                     f"{(f(v.get('mae_ratio_to_cog'))):>11}{j['joined']:>9}{j['truth_without_slopes']:>10}"
                     f"{j['duplicate_slope_stamps']:>6}")
    if any(v.get("ttf") for v in res["algorithms"].values()):
        lines.append("")
        lines.append("with the pupil-wide tip, tilt and focus removed from the error (LGS AO takes "
                     "them from a natural guide star)")
        lines.append(f"{'algorithm':<16}{'mean |err| px':>14}{'mas':>8}{'x CoG':>8}{'x CRB':>8}")
        for name, v in res["algorithms"].items():
            t = v.get("ttf") or {}
            f = (lambda x: f"{x:>8.3f}" if x is not None else f"{'-':>8}")
            lines.append(f"{name:<16}{t.get('mean_euclid', float('nan')):>14.4f}"
                         f"{t.get('mean_euclid_mas', float('nan')):>8.1f}{f(t.get('ratio_to_cog'))}"
                         f"{f(t.get('ratio_to_crb'))}")
    bases = sorted({f"x CoG on {v['ratio_to_cog_basis']}" for v in res["algorithms"].values()
                    if v.get("ratio_to_cog_basis")} |
                   {f"x CRB on {v['ratio_to_crb_basis']}" for v in res["algorithms"].values()
                    if v.get("ratio_to_crb_basis")})
    if bases:
        lines.append("(ratios on the same frames: " + "; ".join(bases) + ")")
    if "method" in crb:
        lines.append("")
        lines.append("CRB: " + crb["method"])
    first = next(iter(res["algorithms"].values()))
    if first.get("by_radius") and len(first["by_radius"]) > 1:
        lines += _radius_table(res, "mean |err| (px) by subaperture radius",
                               lambda v: v["by_radius"])
    if (first.get("ttf") or {}).get("by_radius") and len(first["by_radius"]) > 1:
        lines += _radius_table(res, "the same with the pupil-wide tip, tilt and focus removed",
                               lambda v: v["ttf"]["by_radius"])
    return "\n".join(lines)


def _radius_table(res: dict, title: str, rings_of) -> list[str]:
    """Lines of a table of mean |err| (px) by ring of subaperture radius: ``rings_of(v)`` an
    algorithm's rings (as :func:`.metrics.by_radius`), the CRB's beside them."""
    crb = res.get("crb") or {}
    algs = res["algorithms"]
    lines = ["", title,
             f"{'r (m)':<14}" + "".join(f"{n[:11]:>12}" for n in algs) +
             (f"{'CRB':>12}" if crb.get("by_radius") else "")]
    for k, ring in enumerate(rings_of(next(iter(algs.values())))):
        row = f"{ring['r_min_m']:5.2f}-{ring['r_max_m']:5.2f}   "
        row += "".join(f"{rings_of(v)[k]['mean_euclid']:>12.4f}" for v in algs.values())
        if crb.get("by_radius"):
            row += f"{crb['by_radius'][k]['mean_euclid']:>12.4f}"
        lines.append(row)
    return lines


def public(res: dict) -> dict:
    """The JSON summary: ``res`` without its private arrays, NaN written as null."""
    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items() if not str(k).startswith("_")}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, (np.floating, np.integer)):
            return clean(x.item())
        return x
    return clean(res)


def report_bag(path, out_dir=None, as_json: bool = False, max_frames: int = 200,
               skip: int = 0) -> int:
    """Analyse a bag, print the table (or with ``as_json`` the JSON summary alone).

    out_dir: where ``summary.json`` and the PNGs go; default ``<bag stem>_report`` beside
    the bag, none at all with ``as_json`` and no ``out_dir``. skip: exposures left out at the
    start (by the truth's stamps), e.g. a pupil calibration's ``pupil_period`` of warm-up.
    Returns 0. Raises BagError / ValueError for a bag that cannot be analysed.
    """
    data = skip_frames(load_bag(path, max_frames=max_frames + skip), skip)
    res = analyse(data)
    if skip:
        res["skipped_frames"] = int(skip)
    if out_dir is None and not as_json:
        out_dir = Path(path).with_name(Path(path).stem + "_report")
    summary = public(res)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        summary["plots"] = write_plots(res, out)
        (out / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    if as_json:
        print(json.dumps(summary, indent=2, sort_keys=True))
    else:
        print(format_report(res))
        if out_dir is not None:
            print(f"\nwrote {Path(out_dir) / 'summary.json'} and {len(summary['plots'])} plot(s)")
    return 0


__all__ = ["report_bag", "analyse", "format_report", "write_plots", "public", "crb_summary",
           "mean_abs_norm", "crb_covariances", "simulator_model", "crb_frame_count", "binned",
           "TIME_BINS"]
