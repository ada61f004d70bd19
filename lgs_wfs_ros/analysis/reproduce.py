"""``lgs-wfs reproduce [--quick]``: the paper's figures and tables with our code.

Mello et al. 2014 (``data/paper_results.json``) simulate the outermost subaperture of a
30 m telescope's Shack-Hartmann sensor (16 x 16 px at 0.5"/px, spot core 1.19 px FWHM,
photon noise only) and compare CoG, the constrained matched filter (CMF) and small neural
networks (ANN). This module reruns:

- the error versus total photons (100..30000) of its four cases: ``ideal`` (centred
  profile, polar detector, no turbulence), ``uncentred`` (polar, no turbulence),
  ``turbulent`` (uncentred, polar, r0 = 0.15 m) and ``diagonal`` (uncentred, cartesian
  detector with diagonal elongation, turbulence), with the Cramer-Rao bound (CRB);
- Tables 1-2 (cases 1-4 = turbulent polar / diagonal cartesian at 316 and 1000 photons);
- Table 3: the 700 Hz validation run with the measured lidar profiles interpolated in time
  and 10 m/s frozen-flow turbulence, polar and cartesian, 1000 photons;

and writes ``<out_dir>/reproduction.md``, ``<out_dir>/reproduction.json`` and
``<out_dir>/figures/*.png``. Spots come from :mod:`..optics.spots` (exact elongation,
pixel-integrated core), profiles from :mod:`..optics.sodium`, algorithms from
:func:`..centroiding.make_centroider`. Every centroider sees the frames one at a time, in
time order, as it would live (the CMF keeps its 5-frame history).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..optics import geometry, sodium
from ..optics.spots import SpotModel
from ..sensor import Sensor
from . import metrics, paper
from .report import crb_covariances, mean_abs_norm

CASES = {
    "ideal": {"detector": "polar", "profile": "centred", "turbulence": False,
              "title": "ideal case: centred profile, polar detector, no turbulence"},
    "uncentred": {"detector": "polar", "profile": "uncentred", "turbulence": False,
                  "title": "uncentred profile, polar detector, no turbulence"},
    "turbulent": {"detector": "polar", "profile": "uncentred", "turbulence": True,
                  "title": "uncentred profile, polar detector, turbulence r0 = 0.15 m"},
    "diagonal": {"detector": "cartesian", "profile": "uncentred", "turbulence": True,
                 "title": "uncentred profile, cartesian detector, diagonal elongation, turbulence"},
}
#: The sensitivity runs: Tables 1-2 again with the other reading of the paper's uncentred
#: profile (the random model's mean layer, lower part brightened: ``uncentred_profile(shape=
#: "model")``), to show how much the ANN's gain depends on the test profile's place in the
#: networks' training prior.
SENSITIVITY_PROFILE = "uncentred_model"
#: Tables 1-2 case -> (figure case, photons)
TABLE_CASES = {1: ("turbulent", 316), 2: ("turbulent", 1000), 3: ("diagonal", 316), 4: ("diagonal", 1000)}

#: label, registry name, options, detectors it is run on
ALGORITHMS = [
    ("CoG", "cog", {}, ("polar", "cartesian")),
    ("CMF", "cmf", {"reference": "history"}, ("polar", "cartesian")),   # the paper's CMF
    ("ANN 1k", "ann", {"model": "ann_1k"}, ("polar",)),
    ("ANN noiseless", "ann", {"model": "ann_noiseless"}, ("polar",)),
    ("ANN diag", "ann", {"model": "ann_diag"}, ("cartesian",)),
    ("ANN pupil", "ann", {"model": "ann_pupil"}, ("polar", "cartesian")),
    ("ANN 1k paper prior", "ann", {"model": "paper_prior/ann_1k_paper"}, ("polar",)),
    ("ANN diag paper prior", "ann", {"model": "paper_prior/ann_diag_paper"}, ("cartesian",)),
]
#: the networks the paper's tables use, per detector: the shipped one (profile prior fitted
#: to the measured sky) and the same recipe with the paper's own prior (independent normal
#: statistics per Gaussian parameter, models/paper_prior/: reproduction only)
TABLE_ANN = {"polar": "ANN 1k", "cartesian": "ANN diag"}
TABLE_ANN_PAPER = {"polar": "ANN 1k paper prior", "cartesian": "ANN diag paper prior"}
#: Table 3 starts at measured profile 66: profiles 0-65 trained the shipped networks
#: (their metadata), 66-87 are held out, so the validation run never shows a network a
#: profile it was trained on.
VALIDATION_START_S = 66.0


@dataclass
class Config:
    """What to run. ``quick``: fewer iterations and a shorter validation run."""

    photons: tuple = (100, 316, 1000, 3162, 10000, 30000)
    iterations: int = 5000
    run_seconds: float = 10.0
    cases: tuple = tuple(CASES)
    detectors: tuple = ("polar", "cartesian")
    crb_samples: int = 40
    seed: int = 2014
    label: str = "quick"
    notes: list = field(default_factory=list)

    @classmethod
    def make(cls, quick: bool) -> "Config":
        if quick:
            return cls()
        return cls(photons=(100, 178, 316, 562, 1000, 1778, 3162, 5623, 10000, 17783, 30000),
                   iterations=10000, run_seconds=20.0, label="full")


# -- simulation ---------------------------------------------------------------------------------
def altitude_grid() -> np.ndarray:
    return sodium.default_altitude_grid()


def case_profile(name: str, h: np.ndarray) -> np.ndarray:
    if name == "centred":
        return sodium.centred_profile(h, centre="harmonic")     # unbiased CoG, as the paper's
    if name == "uncentred":
        return sodium.uncentred_profile(h)
    if name == "uncentred_model":
        return sodium.uncentred_profile(h, shape="model")
    raise ValueError(f"unknown profile {name!r}")


def gtilt_series(sensor: Sensor, frames: int, seed: int) -> np.ndarray:
    """``(frames, 2)`` true spot displacements (px) of the single subaperture: the library's
    frozen-flow Kolmogorov layer (:class:`..optics.turbulence.FrozenFlow`: r0, wind and frame
    rate from the sensor; exact G-tilt of the subaperture)."""
    from ..optics.turbulence import FrozenFlow

    return FrozenFlow(sensor, int(seed)).tilts(int(frames))[:, 0, :]


def expected_images(sensor: Sensor, h, density, truths) -> np.ndarray:
    """``(T, p, p)`` noise-free images of the single subaperture, unit sum inside the field,
    for truths ``(T, 2)`` px and a profile ``(K,)`` or ``(T, K)``."""
    lay = geometry.layout(sensor)
    t = truths.shape[0]
    smax = float(np.abs(truths).max()) + 0.1 if t else 1.0
    model = SpotModel(sensor, np.repeat(lay.r_m, t), np.repeat(lay.e, t, axis=0), h, density,
                      max_shift_px=smax)
    img, _ = model.images(truths)
    return img / img.sum(axis=(1, 2), keepdims=True)


RECIPES: list = []


def _recipe_line(training) -> str:
    if isinstance(training, str):
        try:
            training = json.loads(training)
        except json.JSONDecodeError:
            return training[:200]
    if isinstance(training, dict):
        return str(training.get("recipe_line") or training.get("profiles") or "")
    return ""


def independent_tilts(sensor: Sensor, iterations: int, seed: int) -> np.ndarray:
    """``(iterations, 2)`` independent Kolmogorov displacements (px) of the single subaperture.

    The paper's photon sweeps (its Figs 8-11, Tables 1-2) run "ten thousand iterations" per
    photon level, each a new turbulence draw, and show the positions as a histogram; only the
    700 Hz validation run (Table 3) moves a screen in time. The G-tilt of one subaperture
    under Kolmogorov turbulence is a zero-mean normal variable, so independent iterations
    are normal draws with the theoretical G-tilt sigma of this subaperture
    (:func:`..optics.turbulence.turbulence_sigma_px`). This matters for the CMF: its
    history reference (mean of the last 5 images) then sits at the mean of 5 independent
    positions rather than on top of the current, slowly moving spot.
    """
    from ..optics.turbulence import random_displacements, turbulence_sigma_px

    rng = np.random.default_rng([int(seed), 7])
    return random_displacements(rng, int(iterations), turbulence_sigma_px(sensor))


def build_centroiders(sensor: Sensor, notes: list) -> dict:
    """``{label: centroider}`` for the algorithms that run on this detector and load."""
    from ..centroiding import make_centroider

    out = {}
    for label, name, opts, dets in ALGORITHMS:
        if sensor.detector not in dets:
            continue
        try:
            out[label] = make_centroider(name, sensor, **opts)
            meta = getattr(out[label], "meta", None) or {}
            line = _recipe_line(meta.get("training"))
            if line and not any(n.startswith(f"{label}: ") for n in RECIPES):
                RECIPES.append(f"{label}: `{out[label].path.name}`, {line}")
        except (ValueError, OSError, RuntimeError) as err:
            msg = f"{label} skipped on the {sensor.detector} detector: {str(err).splitlines()[0].split(' (')[0]}"
            if msg not in notes:
                notes.append(msg)
    return out


def run_centroiders(cents: dict, frames: np.ndarray) -> dict:
    """``{label: (T, 2) estimates}``; each centroider reset, then fed frame by frame."""
    out = {}
    for label, c in cents.items():
        c.reset()
        est = np.empty((frames.shape[0], 2))
        for k in range(frames.shape[0]):
            est[k] = c.centroid(frames[k:k + 1])[0]
        out[label] = est
    return out


def crb_unit(sensor: Sensor, h, density_at, truths: np.ndarray, samples: int) -> np.ndarray:
    """``(S, 2, 2)`` CRB covariances for ONE photon (px^2) at ``samples`` of the truths.

    With photon noise only the Fisher information is proportional to the photons, so the
    bound at N photons is this divided by N. ``density_at(k)`` gives frame k's profile.
    """
    lay = geometry.layout(sensor)
    idx = np.unique(np.linspace(0, len(truths) - 1, min(samples, len(truths))).astype(int))
    models = {}

    def image_at(j, s):
        k = idx[j]
        if k not in models:
            smax = float(np.abs(truths[k]).max()) + 0.5
            models[k] = SpotModel(sensor, lay.r_m, lay.e, h, density_at(k), max_shift_px=smax)
        img, _ = models[k].images(s)
        return img
    return crb_covariances(sensor, image_at, truths[idx][:, None, :])


def stats(err: np.ndarray) -> dict:
    s = metrics.summarize(err, paper.mas_per_px())
    return {k: s[k] for k in ("mean_euclid", "mae", "rms", "bias_x", "bias_y", "n", "n_nan",
                              "mean_euclid_mas", "mae_mas")}


def run_sweep(case: str, cfg: Config, log=print, profile: str | None = None,
              photons: tuple | None = None) -> dict:
    """Error versus photons for one figure case (``profile``/``photons`` override the case's)."""
    spec = dict(CASES[case])
    if profile:
        spec["profile"] = profile
    sensor = Sensor.paper_single(spec["detector"])
    h = altitude_grid()
    rho = case_profile(spec["profile"], h)
    rng = np.random.default_rng([cfg.seed, list(CASES).index(case)])
    t = cfg.iterations
    truths = independent_tilts(sensor, t, cfg.seed + 1) if spec["turbulence"] else np.zeros((t, 2))
    images = expected_images(sensor, h, rho, truths)
    cents = build_centroiders(sensor, cfg.notes)
    cov1 = crb_unit(sensor, h, lambda k: rho, truths, cfg.crb_samples)
    levels = tuple(photons or cfg.photons)
    label = f"{case} ({profile})" if profile else case
    res = {"case": case, **spec, "photons": list(levels), "iterations": t,
           "truth_rms_px": [float(v) for v in truths.std(axis=0)],
           "truth_mean_abs_px": float(np.hypot(truths[:, 0], truths[:, 1]).mean()), "algorithms": {}, "crb": {}}
    for n in levels:
        t0 = time.perf_counter()
        frames = rng.poisson(images * n).astype(np.float32)
        est = run_centroiders(cents, frames)
        for label, e in est.items():
            res["algorithms"].setdefault(label, {})[str(n)] = stats(e - truths)
        res["crb"][str(n)] = {"mean_euclid": float(np.nanmean(mean_abs_norm(cov1 / n))),
                              "mae": float(np.nanmean(np.sqrt(2 / np.pi) *
                                                      np.sqrt(np.einsum("nii->ni", cov1 / n))))}
        log(f"  {label:<10} {n:>6} photons: " + ", ".join(
            f"{lb} {res['algorithms'][lb][str(n)]['mean_euclid']:.3f}" for lb in est) +
            f", CRB {res['crb'][str(n)]['mean_euclid']:.3f} px  ({time.perf_counter() - t0:.1f} s)")
    return res


def _range(v) -> list:
    v = np.atleast_1d(np.asarray(v, dtype=float))
    return [float(v.min()), float(v.max())]


def run_validation(detector: str, cfg: Config, log=print) -> dict:
    """Table 3: evolving measured profile, frozen flow, 700 Hz, 1000 photons."""
    sensor = Sensor.paper_single(detector)
    evo = sodium.EvolvingProfile.measured(1.0)
    t = int(round(cfg.run_seconds * sensor.frame_rate_hz))
    times = np.arange(t) / sensor.frame_rate_hz
    dens = evo.at_many(VALIDATION_START_S + times)
    truths = gtilt_series(sensor, t, cfg.seed + 7)
    images = np.concatenate([expected_images(sensor, evo.altitude_m, dens[i:i + 1000], truths[i:i + 1000])
                             for i in range(0, t, 1000)])
    rng = np.random.default_rng([cfg.seed, 99, 0 if detector == "polar" else 1])
    frames = rng.poisson(images * 1000.0).astype(np.float32)
    cents = build_centroiders(sensor, cfg.notes)
    est = run_centroiders(cents, frames)
    cov = crb_unit(sensor, evo.altitude_m, lambda k: dens[k], truths, cfg.crb_samples) / 1000.0
    res = {"detector": detector, "frames": t, "seconds": cfg.run_seconds, "photons": 1000,
           "truth_rms_px": [float(v) for v in truths.std(axis=0)],
           "profile_cog_bias_px": _range(sodium.cog_offset_px(evo.altitude_m, dens[::max(1, t // 50)],
                                                              r_m=float(geometry.layout(sensor).r_m[0]))),
           "algorithms": {lb: stats(e - truths) for lb, e in est.items()},
           "crb": {"mean_euclid": float(np.nanmean(mean_abs_norm(cov))),
                   "mae": float(np.nanmean(np.sqrt(2 / np.pi) * np.sqrt(np.einsum("nii->ni", cov))))},
           "_series": {lb: np.hypot(*(e - truths).T) for lb, e in est.items()}, "_times": times}
    log(f"  700 Hz run {detector:<9}: " + ", ".join(
        f"{lb} {v['mean_euclid']:.3f}" for lb, v in res["algorithms"].items()) +
        f", CRB {res['crb']['mean_euclid']:.3f} px")
    return res


# -- tables -----------------------------------------------------------------------------------------
def tables_12(sweeps: dict) -> list[dict]:
    """Rows of Tables 1-2: per case and algorithm, ours (both metrics) beside the paper's."""
    rows = []
    for case, (fig, n) in TABLE_CASES.items():
        if fig not in sweeps or str(n) not in sweeps[fig]["crb"]:
            continue
        algs = sweeps[fig]["algorithms"]
        det = CASES[fig]["detector"]
        cog = algs["CoG"][str(n)]
        for key, label in (("cog", "CoG"), ("cmf", "CMF"), ("ann", TABLE_ANN[det]),
                           ("ann", TABLE_ANN_PAPER[det])):
            if label not in algs:
                continue
            s = algs[label][str(n)]
            p_mas, p_ratio = paper.table1(key, case), paper.table2(key, case)
            rows.append({"case": case, "detector": det, "photons": n, "algorithm": label, "paper_key": key,
                         "euclid_mas": s["mean_euclid_mas"], "mae_mas": s["mae_mas"], "paper_mas": p_mas,
                         "euclid_over_paper": s["mean_euclid_mas"] / p_mas, "mae_over_paper": s["mae_mas"] / p_mas,
                         "ratio_cog_euclid": s["mean_euclid"] / cog["mean_euclid"],
                         "ratio_cog_mae": s["mae"] / cog["mae"], "paper_ratio_cog": p_ratio})
    return rows


def table_3(vals: dict) -> list[dict]:
    rows = []
    for det, v in vals.items():
        algs = v["algorithms"]
        cog = algs.get("CoG")
        for key, label in (("cog", "CoG"), ("cmf", "CMF"), ("ann", TABLE_ANN[det]),
                           ("ann", TABLE_ANN_PAPER[det]), (None, "ANN pupil")):
            if label not in algs:
                continue
            s = algs[label]
            p = paper.table3(key, det) if key else None
            rows.append({"detector": det, "algorithm": label, "euclid_mas": s["mean_euclid_mas"],
                         "mae_mas": s["mae_mas"], "paper_mas": p,
                         "euclid_over_paper": s["mean_euclid_mas"] / p if p else None,
                         "ratio_cog_euclid": s["mean_euclid"] / cog["mean_euclid"] if cog else None,
                         "ratio_cog_mae": s["mae"] / cog["mae"] if cog else None,
                         "paper_ratio_cog": p / paper.table3("cog", det) if p else None,
                         "crb_mas": v["crb"]["mean_euclid"] * paper.mas_per_px()})
    return rows


def checks(rows12: list, rows3: list, suffix: str = "") -> list[dict]:
    """The issue's "done when" criteria, evaluated on our numbers (``suffix`` tags the checks
    of a variant run)."""
    out = []
    for r in rows12:
        if r["paper_key"] == "ann":
            ok = r["ratio_cog_euclid"] <= r["paper_ratio_cog"] and r["ratio_cog_mae"] <= r["paper_ratio_cog"]
            out.append({"check": f"case {r['case']}: {r['algorithm']}/CoG <= paper's {r['paper_ratio_cog']:.1%}{suffix}",
                        "value": f"{r['ratio_cog_euclid']:.1%} (mean abs err), {r['ratio_cog_mae']:.1%} (MAE)", "pass": bool(ok)})
        if r["paper_key"] == "cmf":
            rel = r["ratio_cog_euclid"] / r["paper_ratio_cog"] - 1
            out.append({"check": f"case {r['case']}: CMF/CoG within 25 % of paper's {r['paper_ratio_cog']:.1%}{suffix}",
                        "value": f"{r['ratio_cog_euclid']:.1%} ({rel:+.0%})", "pass": bool(abs(rel) <= 0.25)})
    if rows12 and not any(r["paper_key"] == "ann" for r in rows12):
        out.append({"check": "cases 1-4: ANN / CoG at or below the paper's ratio",
                    "value": "not evaluated: no ANN model could be loaded (see the notes)", "pass": None})
    for det in ("polar", "cartesian"):
        cog = [r for r in rows3 if r["detector"] == det and r["algorithm"] == "CoG"]
        for label in (TABLE_ANN[det], TABLE_ANN_PAPER[det]):
            ann = [r for r in rows3 if r["detector"] == det and r["algorithm"] == label]
            if ann and cog:
                out.append({"check": f"Table 3 {det}: {label} no worse than CoG",
                            "value": f"{ann[0]['euclid_mas']:.1f} vs {cog[0]['euclid_mas']:.1f} mas",
                            "pass": bool(ann[0]["euclid_mas"] <= cog[0]["euclid_mas"])})
    return out


def format_tables(rows12: list, rows3: list) -> str:
    def f(x, fmt):
        return format(x, fmt) if x is not None else "-"
    lines = ["Tables 1-2 (turbulence; case 1-2 polar, 3-4 cartesian diagonal; 316 / 1000 photons)",
             f"{'case':>4} {'algorithm':<14}{'|err| mas':>10}{'MAE mas':>9}{'paper':>8}{'|err|/p':>8}"
             f"{'MAE/p':>7}{'xCoG |e|':>9}{'xCoG MAE':>9}{'paper':>8}"]
    for r in rows12:
        lines.append(f"{r['case']:>4} {r['algorithm']:<14}{r['euclid_mas']:>10.1f}{r['mae_mas']:>9.1f}"
                     f"{r['paper_mas']:>8.1f}{r['euclid_over_paper']:>8.2f}{r['mae_over_paper']:>7.2f}"
                     f"{r['ratio_cog_euclid']:>9.1%}{r['ratio_cog_mae']:>9.1%}{r['paper_ratio_cog']:>8.1%}")
    lines += ["", "Table 3 (700 Hz run, evolving measured profile, 10 m/s frozen flow, 1000 photons)",
              f"{'detector':<10}{'algorithm':<14}{'|err| mas':>10}{'MAE mas':>9}{'paper':>8}{'|err|/p':>8}"
              f"{'xCoG |e|':>9}{'paper':>8}{'CRB mas':>9}"]
    for r in rows3:
        lines.append(f"{r['detector']:<10}{r['algorithm']:<14}{r['euclid_mas']:>10.1f}{r['mae_mas']:>9.1f}"
                     f"{f(r['paper_mas'], '.1f'):>8}{f(r['euclid_over_paper'], '.2f'):>8}"
                     f"{f(r['ratio_cog_euclid'], '.1%'):>9}{f(r['paper_ratio_cog'], '.1%'):>8}{r['crb_mas']:>9.1f}")
    return "\n".join(lines)


# -- figures --------------------------------------------------------------------------------------
def plot_sweep(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.array(res["photons"], float)
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for label, by_n in res["algorithms"].items():
        ax.loglog(n, [by_n[str(int(k))]["mean_euclid"] for k in n], "o-", ms=4, label=label)
    ax.loglog(n, [res["crb"][str(int(k))]["mean_euclid"] for k in n], "k--", label="CRB")
    ax.set_xlabel("total detected photons")
    ax.set_ylabel("mean |error| (px)")
    ax.set_title(res["title"], fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_validation(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.0))
    t = res["_times"]
    for k, (label, d) in enumerate(res["_series"].items()):
        w = max(1, len(d) // 300)
        sm = np.convolve(np.nan_to_num(d), np.ones(w) / w, mode="same")
        line, = ax.plot(t, sm, lw=0.8, label=f"{label} (mean {np.nanmean(d):.3f} px)")
        ax.axhline(np.nanmean(d), color=line.get_color(), ls="--", lw=0.8)
    ax.axhline(res["crb"]["mean_euclid"], color="k", ls=":", lw=1, label=f"CRB ({res['crb']['mean_euclid']:.3f} px)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|error| (px, running mean)")
    ax.set_title(f"700 Hz run, evolving measured profile, {res['detector']} detector", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- report ---------------------------------------------------------------------------------------
def _md_table(rows, cols):
    head = "| " + " | ".join(c[0] for c in cols) + " |"
    sep = "|" + "|".join("---:" if i else "---" for i in range(len(cols))) + "|"
    body = []
    for r in rows:
        cells = []
        for _, key, fmt in cols:
            v = r.get(key)
            cells.append("-" if v is None else (format(v, fmt) if fmt else str(v)))
        body.append("| " + " | ".join(cells) + " |")
    return "\n".join([head, sep] + body)


def write_markdown(path: Path, cfg: Config, sweeps: dict, vals: dict, rows12, rows3, checks_, seconds,
                   rows_s=()) -> None:
    cols12 = [("case", "case", ""), ("algorithm", "algorithm", ""), ("ours mean abs err (mas)", "euclid_mas", ".1f"),
              ("ours per-axis MAE (mas)", "mae_mas", ".1f"), ("paper (mas)", "paper_mas", ".2f"),
              ("ours/paper (abs err)", "euclid_over_paper", ".2f"), ("ours/paper (MAE)", "mae_over_paper", ".2f"),
              ("ours / CoG (abs err)", "ratio_cog_euclid", ".1%"), ("ours / CoG (MAE)", "ratio_cog_mae", ".1%"),
              ("paper / CoG (Table 2)", "paper_ratio_cog", ".1%")]
    cols3 = [("detector", "detector", ""), ("algorithm", "algorithm", ""), ("ours mean abs err (mas)", "euclid_mas", ".1f"),
             ("ours per-axis MAE (mas)", "mae_mas", ".1f"), ("paper (mas)", "paper_mas", ".2f"),
             ("ours/paper", "euclid_over_paper", ".2f"), ("ours / CoG", "ratio_cog_euclid", ".1%"),
             ("paper / CoG", "paper_ratio_cog", ".1%"), ("CRB (mas)", "crb_mas", ".1f")]
    L = [f"# Reproducing Mello et al. 2014 ({cfg.label} run)", "",
         f"Generated by `lgs-wfs reproduce{' --quick' if cfg.label == 'quick' else ''}` "
         f"({seconds / 60:.1f} min on this machine); numbers and figures below are regenerated by that "
         "command, the discussion of departures is part of the generator. The paper's values come from "
         "`lgs_wfs_ros/data/paper_results.json` (its Tables 1-3 and figure captions).", "",
         "## Setup", "",
         "- One subaperture, the outermost (r = 14.75 m from a centred launch), 16 x 16 px at 0.5\"/px, "
         "Gaussian core of 1.19 px FWHM, h_ref = 90 km, exact elongation geometry "
         "(`docs/conventions.md` section 3); photon noise only; the photon count is the expected total inside "
         "the 16 x 16 field.",
         f"- Photon levels {', '.join(str(n) for n in cfg.photons)}; {cfg.iterations} frames per level and case "
         "(the paper: 10,000). Frames are fed to every algorithm one by one, in time order.",
         "- Turbulence, photon sweeps (Tables 1-2): Kolmogorov, r0 = 0.15 m at 500 nm; each iteration an "
         "independent draw of the subaperture's G-tilt, a normal variable with the theoretical sigma "
         f"({_sigma_theory():.2f} px per axis, `optics.turbulence.turbulence_sigma_px`), as the paper's "
         "10,000 independent iterations and its position histogram. Validation run (Table 3): one frozen-flow "
         "layer at 10 m/s, 700 Hz (`optics.turbulence.FrozenFlow`, exact G-tilt). Spot rms in the sweeps: "
         + ", ".join(f"{c} {sweeps[c]['truth_rms_px'][0]:.2f} / {sweeps[c]['truth_rms_px'][1]:.2f} px (x / y)" for c in sweeps if sweeps[c]["turbulence"]) + ".",
         "- CoG: plain centre of gravity. CMF: Gilles & Ellerbroek constrained matched filter as the paper ran it "
         "(reference = mean of the last 5 frames incl. the current one, 0.02 px dither derivatives, refreshed "
         "every frame, noise weights from the image). ANN: the shipped ONNX models (`models/`).",
         "- CRB: Cramer-Rao bound of an unbiased estimator for the same noise-free image model "
         "(photon noise, flux a nuisance parameter), shown as the expected mean |error| at the bound. "
         "Biased estimators (CoG on an uncentred profile) can sit above or below it.",
         "- Metrics: `mean |err|` is the mean Euclidean (2-D) error, `MAE` the per-axis mean absolute error "
         "averaged over x and y; the paper does not say which it used, so both are printed and the "
         "comparisons lean on ratios to CoG.", ""]
    if RECIPES:
        L += ["**Networks used** (from each model's metadata):", ""] + [f"- {r}" for r in RECIPES] + [""]
    if cfg.notes:
        L += ["**Notes from this run:**", ""] + [f"- {n}" for n in cfg.notes] + [""]
    L += ["## Error versus photons", ""]
    for c, r in sweeps.items():
        L += [f"### {r['title'][0].upper() + r['title'][1:]}", "", f"![{c}](figures/error_vs_photons_{c}.png)", ""]
        labels = list(r["algorithms"])
        rows = []
        for n in r["photons"]:
            row = {"photons": n}
            for lb in labels:
                row[lb] = r["algorithms"][lb][str(n)]["mean_euclid"]
            row["CRB"] = r["crb"][str(n)]["mean_euclid"]
            rows.append(row)
        L += [_md_table(rows, [("photons", "photons", "")] + [(f"{lb} (px)", lb, ".3f") for lb in labels]
                        + [("CRB (px)", "CRB", ".3f")]), ""]
    L += ["## Tables 1 and 2", "", _md_table(rows12, cols12), ""]
    if rows_s:
        cols_s = [c for c in cols12 if c[1] in ("case", "algorithm", "euclid_mas", "mae_mas", "ratio_cog_euclid",
                                                 "ratio_cog_mae", "paper_ratio_cog")]
        L += ["### The same cases with the other reading of the uncentred profile", "",
              "The paper describes its uncentred profile only as denser 'on its lower part, from 80 km to "
              "90 km'. Ours above is a measured profile's five-Gaussian fit with its lower part raised; its "
              "three lower layers also sit 0.7-1 km below the random model's mean positions. The other reading keeps the "
              "model's mean layer and brightens only its lower three Gaussians, by a common factor, until CoG "
              "has the same 0.45 px bias (`sodium.uncentred_profile(shape=\"model\")`). Same turbulence "
              "draws and networks; only the profile differs.", "", _md_table(list(rows_s), cols_s), ""]
    L += [
          "## Table 3: the 700 Hz validation run", "",
          f"{cfg.run_seconds:g} s at 700 Hz ({int(cfg.run_seconds * 700)} frames) of the measured LZT lidar "
          f"profiles from profile {VALIDATION_START_S:g} on (held out from the networks' training; 1 s apart, "
          "linearly interpolated), frozen-flow turbulence, 1000 photons.", "",
          _md_table(rows3, cols3), ""]
    for det in vals:
        L += [f"![{det}](figures/validation_{det}.png)", ""]
    shown = [dict(c, verdict={True: "yes", False: "**no**", None: "not evaluated"}[c["pass"]]) for c in checks_]
    L += ["## Criteria of issue 7", "", _md_table(shown, [("check", "check", ""), ("ours", "value", ""),
                                                        ("met", "verdict", "")]), ""]
    L += ["## Departures from the paper, and why", ""] + [f"- {d}" for d in departures(sweeps, vals, rows12, rows3, rows_s)] + [""]
    path.write_text("\n".join(L) + "\n")


def _sigma_theory() -> float:
    from ..optics.turbulence import turbulence_sigma_px
    return turbulence_sigma_px(Sensor.paper_single("polar"))


def departures(sweeps, vals, rows12, rows3=(), rows_s=()) -> list[str]:
    d = []
    ideal = sweeps.get("ideal")
    floor = (f" (our CoG error in the ideal case still levels off at "
             f"{ideal['algorithms']['CoG'][str(max(ideal['photons']))]['mean_euclid']:.2f} px: the light the "
             "16 px field cuts off the upper tail moves the CoG)") if ideal else ""
    d.append("**Sodium profiles.** The paper's centred and uncentred profiles are not published. Ours "
             "(`optics.sodium.centred_profile`, `uncentred_profile`) are multi-peak lidar-like shapes; the "
             "centred one has its harmonic-mean altitude at h_ref, which makes the CoG of the untruncated "
             "light unbiased with the exact geometry" + floor + "; the uncentred one is placed so that the "
             "untruncated noise-free CoG error is the 0.45 px the paper quotes. The absolute CoG errors are "
             "therefore close to the paper's by construction, and everything else is compared through "
             "ratios to CoG.")
    d.append("**CMF below the CRB.** Without turbulence the CMF's reference includes the frame being measured "
             "and the truth never moves, so its estimate is pulled towards the (correct) zero: a biased "
             "estimator that the unbiased bound does not constrain. It is the paper's idealised setting, "
             "not something a real system could run.")
    d.append("**Metric.** The paper's 'average centroiding error' is either the 2-D distance or a per-axis "
             "figure. For the uncentred cases CoG's error is mostly a bias along the elongation, so the "
             "paper's 224 mas (0.45 px) compares with our mean absolute (2-D) error, while a per-axis MAE "
             "is about half of it. We print both.")
    d.append("**Photon levels.** The tables say 316 photons, the text says 300 (SN 17.32); we use 316.")
    d.append("**Turbulence.** The paper's phase screens and their time behaviour in the photon sweeps are "
             "unspecified ('spot movement limited to one pixel', a position histogram, 'ten thousand "
             "iterations'); we draw each iteration independently from the G-tilt distribution. With "
             "temporally correlated frozen flow instead, the CMF's 5-frame history reference sits on the "
             "moving spot and its error approaches the spot's own motion (about 0.56 px), far above the "
             "paper's 144 mas; with independent draws the reference sits at the mean of 5 positions, "
             "sigma/sqrt(5) from the centre, which reproduces the paper's CMF figure. The cartesian figure "
             "caption says 'no turbulence' while the text and Tables 1-2 say turbulence; we use turbulence.")
    d.append("**CMF reference.** With the paper's history reference (mean of the last 5 frames, including the "
             "current one) a matched filter measures the displacement relative to the recent mean spot, so a "
             "stationary spot reads as centred: with no turbulence it measures the truth (0) almost perfectly "
             "whatever the profile, which is why the CMF wins the untroubled cases; under turbulence the "
             "reference is the mean of the recent spots and the CMF misses that mean's offset (next item), "
             "as the paper observed.")
    turb = sweeps.get("turbulent")
    if turb:
        sig = float(np.mean(turb["truth_rms_px"]))
        cmf = turb["algorithms"].get("CMF", {})
        levels = ", ".join(f"{cmf[str(n)]['mean_euclid']:.2f}" for n in turb["photons"] if str(n) in cmf)
        d.append("**CMF under turbulence.** With the history reference the filter measures the spot "
                 "relative to the mean of the last five images, so what it misses is that mean's own "
                 f"offset from the centre: for independent positions of rms {sig:.2f} px per axis, "
                 f"{sig:.2f} / sqrt(5) = {sig / np.sqrt(5):.2f} px per axis, a mean Euclidean error of "
                 f"about {sig / np.sqrt(5) * np.sqrt(np.pi / 2):.2f} px before noise and the filter's own "
                 f"nonlinearity. Our CMF's error in the turbulent sweep is {levels} px from the lowest to "
                 "the highest photon level, the paper's 0.27-0.29 px (Table 1, 135-144 mas). The CMF/CoG "
                 "ratio under turbulence therefore measures the turbulence amplitude and the reference's "
                 "history length more than the filter itself.")
    unc = sweeps.get("uncentred")
    if unc:
        top = str(max(unc["photons"]))
        d.append(f"**Uncentred CoG level.** Our CoG error in the uncentred case is "
                 f"{unc['algorithms']['CoG'][top]['mean_euclid']:.2f} px at {top} photons rather than 0.45 px: "
                 "the profile is placed for a 0.45 px bias of the untruncated spot, but its upper tail falls "
                 "outside the 16 px field and the truncation moves the CoG further.")
    c2 = [r for r in rows12 if r["case"] == 2 and r["paper_key"] == "cmf"]
    c4 = [r for r in rows12 if r["case"] == 4 and r["paper_key"] == "cmf"]
    if c2 and c4:
        d.append("**CMF on the cartesian detector.** The paper's CMF is no better than CoG on the diagonal "
                 "cartesian case (Table 2: 100.5 %, 99.0 %) but clearly better on the polar one (60-64 %). "
                 f"Ours gives {c4[0]['ratio_cog_euclid']:.0%} of CoG in case 4 and {c2[0]['ratio_cog_euclid']:.0%} "
                 "in case 2: under our turbulence its error is set by the spot motion on both detectors (item "
                 "above), so the cartesian agreement with the paper is not evidence that the two filters "
                 "treat a diagonal spot alike. Our CMF builds its filter from the image in detector axes, which "
                 "suits any elongation direction.")
    d.append("**ANN.** The networks are the project's (`models/*.onnx`; recipes listed above from their "
             "metadata), not the paper's Matlab networks trained with Levenberg-Marquardt on its own "
             "profile statistics, so the ANN columns test the method, not the same weights.")
    anns = [r for r in rows12 if r["paper_key"] == "ann" and r["algorithm"] in TABLE_ANN.values()]
    if anns:
        worst = max(anns, key=lambda r: r["ratio_cog_euclid"])
        d.append("**Why our ANN does not reach the paper's ratio on the uncentred profile.** Our "
                 f"{worst['algorithm']} stays at {worst['ratio_cog_euclid']:.0%} of CoG in case {worst['case']} "
                 f"(paper: {worst['paper_ratio_cog']:.1%}). One image shows the profile's shape, not its "
                 "altitude: a network can only undo the CoG bias of shapes that, in its training set, came "
                 "with that offset, i.e. it returns the training prior's expected truth for the image. Our "
                 "networks are trained on the random 5-Gaussian model fitted to the measured LZT profiles, "
                 "whose light is centred near h_ref; the fixed uncentred profile, placed to give a 0.45 px "
                 "bias, is far out in that prior, so the network reads it like CoG does. The paper's "
                 "uncentred profile was evidently typical of its own training profiles. On the held-out "
                 "measured profiles of Table 3, which the training prior does cover, the networks remove "
                 "most of CoG's bias (Table 3 and the next item).")
    pp12 = [r for r in rows12 if r["algorithm"] in TABLE_ANN_PAPER.values()]
    pp3 = [r for r in rows3 if r["algorithm"] in TABLE_ANN_PAPER.values() and r["ratio_cog_euclid"] is not None]
    if pp12:
        d.append("**The paper's own profile prior.** The paper drew its training profiles from independent "
                 "normal distributions of each Gaussian's parameters (its section on the sodium model); "
                 "that spreads the layer centroid over ~1.2 km while the layer's extent stays put, so a "
                 "network learns to read the layer's edges rather than its centroid. The same recipes "
                 "trained with that prior (`models/paper_prior/`, `lgs-wfs train ann_1k_paper`, "
                 "`ann_diag_paper`) give, in Tables 1-2: "
                 + "; ".join(f"case {r['case']} {r['ratio_cog_euclid']:.0%} of CoG (paper "
                             f"{r['paper_ratio_cog']:.1%})" for r in pp12)
                 + ". They reproduce the paper's gain on its uncentred profile, and they pay for it on "
                 "the sky: on the held-out measured profiles of Table 3 they reach "
                 + ("; ".join(f"{r['detector']} {r['ratio_cog_euclid']:.0%} of CoG" for r in pp3) or "-")
                 + ". No single network here meets both the Tables 1-2 ratios and the Table 3 "
                 "criterion: which one wins is decided by the altitude prior, not by the method. The "
                 "shipped networks keep the sky-fitted prior; the paper-prior ones are for this "
                 "reproduction only.")
    ps = [r for r in rows_s if r["algorithm"] in TABLE_ANN_PAPER.values()]
    sh = [r for r in rows_s if r["algorithm"] in TABLE_ANN.values()]
    if ps:
        d.append("**Which uncentred profile.** The paper-prior networks' ratio depends on where the test "
                 "profile sits in their training prior. With the other reading of the paper's description "
                 "(the model's mean layer, its lower three Gaussians brightened to the same 0.45 px CoG "
                 "bias; table above) they reach "
                 + "; ".join(f"case {r['case']} {r['ratio_cog_euclid']:.0%} of CoG (paper "
                             f"{r['paper_ratio_cog']:.1%})" for r in ps)
                 + (", while the shipped networks stay at " + ", ".join(f"{r['ratio_cog_euclid']:.0%}" for r in sh)
                    if sh else "")
                 + ". So the paper's Tables 1-2 ratios are within reach of the method when the uncentred "
                 "profile is a typical draw of the training prior, as the paper's presumably was (its test "
                 "profiles and its prior both came from the LZT measurements); with a profile whose layers sit off the prior's "
                 "positions, as our measured-fit one does, the network attributes part of the offset to "
                 "tilt. Neither reading is the paper's profile, which is not published; the criteria "
                 "table shows both.")
    d.append("**Table 3 profiles.** The paper used 'a portion of the measured profiles over a few seconds'; "
             "which portion is unknown. We start at profile 66 of the 88 LZT profiles shipped with the package: "
             "profiles 0-65 are the ones the project's networks were trained on, 66-87 are held out. "
             "Those measured profiles sit closer to h_ref than the uncentred case: the untruncated CoG bias they give this subaperture "
             "ranges over " + (", ".join(f"{det} {v['profile_cog_bias_px'][0]:+.2f}..{v['profile_cog_bias_px'][1]:+.2f} px"
                                      for det, v in vals.items()) if vals else "a small interval")
             + ", against the 0.45-0.47 px the paper's CoG column implies, so our CoG errors in Table 3 are far "
             "below the paper's 237 mas and only the ratios to CoG compare. "
             + ("; ".join(f"{r['detector']} {r['algorithm']}: {r['ratio_cog_euclid']:.0%} of CoG (paper "
                          f"{r['paper_ratio_cog']:.0%})" for r in rows3
                          if r["algorithm"] == TABLE_ANN[r["detector"]] and r["ratio_cog_euclid"] is not None)
                or "No network ran") + ".")
    d.append("**Iterations.** `--quick` uses fewer frames per level and a shorter validation run than the "
             "paper's 10,000; the statistical uncertainty of each mean is about its value / sqrt(frames) for "
             "noise-dominated errors.")
    return d


# -- driver ---------------------------------------------------------------------------------------
def run(cfg: Config, out_dir="docs", log=print) -> dict:
    """Run everything in ``cfg``; write the report under ``out_dir``; return the results."""
    t0 = time.perf_counter()
    RECIPES.clear()
    out = Path(out_dir)
    figs = out / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    log(f"reproduce ({cfg.label}): {len(cfg.cases)} cases x {len(cfg.photons)} photon levels x "
        f"{cfg.iterations} frames; 700 Hz run {cfg.run_seconds:g} s")
    sweeps = {c: run_sweep(c, cfg, log) for c in cfg.cases}
    sens = {c: run_sweep(c, cfg, log, profile=SENSITIVITY_PROFILE,
                         photons=tuple(sorted({n for f, n in TABLE_CASES.values() if f == c})))
            for c in ("turbulent", "diagonal") if c in cfg.cases}
    vals = {d: run_validation(d, cfg, log) for d in cfg.detectors}
    rows12, rows3, rows_s = tables_12(sweeps), table_3(vals), tables_12(sens)
    chk = checks(rows12, rows3) + checks(rows_s, [], suffix=" (model-shaped uncentred profile)")
    for c, r in sweeps.items():
        plot_sweep(r, figs / f"error_vs_photons_{c}.png")
    for d, r in vals.items():
        plot_validation(r, figs / f"validation_{d}.png")
    seconds = time.perf_counter() - t0
    write_markdown(out / "reproduction.md", cfg, sweeps, vals, rows12, rows3, chk, seconds, rows_s)
    result = {"config": asdict(cfg), "seconds": seconds, "sweeps": sweeps, "sensitivity": sens,
              "tables12_sensitivity": rows_s,
              "validation": {d: {k: v for k, v in r.items() if not k.startswith("_")} for d, r in vals.items()},
              "tables12": rows12, "table3": rows3, "checks": chk}
    (out / "reproduction.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    log("")
    log(format_tables(rows12, rows3))
    log("")
    for c in chk:
        log(f"{'SKIP' if c['pass'] is None else 'PASS' if c['pass'] else 'FAIL'}  {c['check']}: {c['value']}")
    for n in cfg.notes:
        log("note: " + n)
    log(f"\nwrote {out / 'reproduction.md'} and {len(cfg.cases) + len(cfg.detectors)} figures in "
        f"{seconds / 60:.1f} min")
    result["_vals"] = vals
    return result


def reproduce(quick: bool = False, out_dir="docs") -> int:
    """The ``lgs-wfs reproduce`` command; returns 0."""
    run(Config.make(quick), out_dir)
    return 0


__all__ = ["reproduce", "run", "Config", "CASES", "TABLE_CASES", "ALGORITHMS", "gtilt_series",
           "independent_tilts",
           "run_sweep", "run_validation", "tables_12", "table_3", "checks"]
