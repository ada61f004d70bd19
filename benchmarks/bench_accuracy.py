"""Accuracy on sodium profiles no estimator was built on: full pupil, evolving profiles.

For every case (profile family x detector x launch x tilt model) the frames are rendered
exactly (:class:`lgs_wfs_ros.optics.spots.SpotModel`) from the unseen families of
:func:`lgs_wfs_ros.optics.sodium.unseen_sequence` (the measured night's test block, 1 s
profiles interpolated to 700 Hz, moved / stretched / squeezed / given a sporadic layer),
with per-subaperture tilts from

- ``ar1``: closed-loop-like residuals, AR(1) with 0.95 per frame, 0.46 px rms per axis,
  independent between subapertures;
- ``frozen_inf`` / ``frozen_30``: the simulator's frozen flow (r0 0.15 m, 10 m/s), L0
  infinite / 30 m;

and Poisson noise at 316 and 1000 photons per subaperture (inside the field). Each
estimator (built by ``options.build``: the node's defaults) sees warm-up frames, then the
scored frames. Reported per estimator: mean 2-D error and mean absolute error per axis
(mas), raw and with the pupil-wide tip, tilt and focus removed from the error (the same as
removing them from estimate and truth), the ratio to cog and to the Cramer-Rao bound of the
same frames (exact model of each sampled frame, profile known; the bound's 3 removed modes
out of 5,568 slopes change it by < 0.1 %, so the raw bound is used for both), and the CPU
time per frame: the per-frame part (frames without a refit) and the mean refit.

Plus the paper's Table 3 case: one subaperture (r = 14.75 m), the measured profiles from
profile 66 on (the held-out block), frozen flow at 10 m/s, 1000 photons.

Run: ``python benchmarks/bench_accuracy.py [--quick]`` (writes ``benchmarks/accuracy.json``
and ``benchmarks/accuracy.md``); ``benchmarks/run.py`` runs it too. ``--long``: the quick
mode's cases at the full mode's 700 + 700 frames, for the estimators the "done when" criteria
name (``LONG_ESTIMATORS``), no Table 3; writes ``accuracy_long.json`` / ``accuracy_long.md``
and leaves the docs alone. ``--jobs N`` runs N cases at a time (one process each).
``--only cog,LABEL,...`` runs those estimators alone on the same (seeded) frames and merges
them into the mode's stored result, refusing unless the CRB and cog scores agree.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from lgs_wfs_ros.analysis import metrics  # noqa: E402
from lgs_wfs_ros.analysis.report import bound_covariances, mean_abs_norm  # noqa: E402
from lgs_wfs_ros.centroiding import options as table  # noqa: E402
from lgs_wfs_ros.centroiding import pupil as pupil_cal  # noqa: E402
from lgs_wfs_ros.optics import geometry, sodium  # noqa: E402
from lgs_wfs_ros.optics.spots import SpotModel  # noqa: E402
from lgs_wfs_ros.sensor import Sensor  # noqa: E402

HERE = Path(__file__).resolve().parent
MAS = 500.0
PHOTONS = (316.0, 1000.0)
ALTITUDE_S = 0.05                                  # the altitude tracker's time constant, s
#: label -> (algorithm, options over the table's defaults)
ESTIMATORS = {
    "cog": ("cog", {}),
    "cog_pupil": ("cog", {"bias": "pupil"}),         # its response inverted (linearize)
    "cog_offset": ("cog", {"bias": "pupil", "linearize": False}),   # the bias alone
    "cmf": ("cmf", {}),                              # the grid of filters (filters=auto)
    "cmf_single": ("cmf", {"filters": "single"}),    # one linearised filter at the reference
    "ml": ("ml", {}),                                # polar only (refused on cartesian)
    "gmf": ("gmf", {}),                              # the same estimator as cmf's default
    "corr": ("corr", {}),
    "cmf_history": ("cmf", {"reference": "history"}),
    "ann_pupil": ("ann", {"model": "ann_pupil", "out_of_domain": "warn"}),   # side launch: r beyond its training radii
    "ann_marg": ("ann", {"model": "ann_marg"}),   # polar only (refused on cartesian)
    "ann_hyper": ("ann", {"model": "ann_hyper"}), # polar only; the default polar ann until 2026-11-26
    # the default ann on both detectors since 2026-11-27 (trained on both; on cartesian
    # pixels it reads bins along e, each pixel split by its overlap: centroiding/bins_along_e.py)
    "ann_conv": ("ann", {"model": "ann_conv"}),
    # the same network on cartesian pixels through whole-pixel sums along the pixel-grid
    # direction nearest to e (no pixel split; bins_along_e.grid_weights); polar: = ann_conv
    "ann_conv_grid": ("ann", {"model": "ann_conv", "bins": "grid"}),
    # trained on those sums (its cartesian spots; polar ones as ann_conv's): the cartesian
    # default since 2026-11-27
    "ann_grid": ("ann", {"model": "ann_grid"}),
    # ann_grid's recipe on bins sqrt 2 px wide along diagonals, holding the whole block
    # (bins_along_e.grid_weights span; docs/ann_ref.md "Bins that span a diagonal block");
    # not shipped: `lgs-wfs train ann_span --out models` first
    "ann_span": ("ann", {"model": "ann_span"}),
    # each block read against the reference moved to the nearest quarter pixel of its
    # calibrated CoG along the bins (option recentre; docs/ann_ref.md "Moved references")
    "ann_conv_rc": ("ann", {"model": "ann_conv", "recentre": True}),
    "ann_grid_rc": ("ann", {"model": "ann_grid", "recentre": True}),
    # with the altitude tracker (off by default: it takes the atmosphere's focus too)
    "ml_alt": ("ml", {"pupil_altitude_s": ALTITUDE_S}),
    "cmf_alt": ("cmf", {"pupil_altitude_s": ALTITUDE_S}),
}
QUICK_ESTIMATORS = ("cog", "cog_pupil", "cog_offset", "cmf", "cmf_single", "ml", "corr", "ann_pupil", "ann_marg",
                    "ann_hyper", "ann_conv", "ann_grid", "ml_alt", "cmf_alt")
#: the estimators issue 14's and 15's "done when" name, for --long
LONG_ESTIMATORS = ("cog", "cog_pupil", "cog_offset", "cmf", "cmf_single", "ml", "ann_marg", "ann_hyper", "ann_conv",
                   "ann_grid",
                   "ml_alt", "cmf_alt")
AR1_RHO, AR1_RMS_PX = 0.95, 0.46
SIDE_LAUNCH_M = 16.0
FROZEN = ("frozen_inf", "frozen_30")


def full_cases():
    out = []
    for fam in sodium.FAMILIES:
        for det in ("polar", "cartesian"):
            for launch in (0.0, SIDE_LAUNCH_M):
                out.append((fam, det, launch, "ar1"))
    for fam in ("measured", "broad"):
        for tilt in FROZEN:
            out.append((fam, "polar", 0.0, tilt))
    return out + side_frozen_cases()


def side_frozen_cases():
    """A side launch under frozen flow, both detectors, both outer scales: the window's mean
    tip towards the launch moves the spots as the profile's altitude does (docs/accuracy.md
    "A side launch under frozen flow")."""
    return [("measured", det, SIDE_LAUNCH_M, tilt) for det in ("polar", "cartesian") for tilt in FROZEN]


def quick_cases():
    out = [(fam, det, 0.0, "ar1") for det in ("polar", "cartesian") for fam in sodium.FAMILIES]
    out += [("measured", "polar", SIDE_LAUNCH_M, "ar1"),
            ("measured", "cartesian", SIDE_LAUNCH_M, "ar1"),
            ("measured", "polar", 0.0, "frozen_inf"), ("measured", "polar", 0.0, "frozen_30")]
    return out + side_frozen_cases()


# -- truth ---------------------------------------------------------------------------------------
def tilts(kind: str, sensor: Sensor, frames: int, seed: int) -> np.ndarray:
    """``(frames, n, 2)`` true displacements, px, detector axes."""
    n = geometry.layout(sensor).n_valid
    if kind == "ar1":
        rng = np.random.default_rng([seed, 1])
        out = np.empty((frames, n, 2))
        t = rng.normal(0.0, AR1_RMS_PX, (n, 2))
        innov = AR1_RMS_PX * math.sqrt(1 - AR1_RHO ** 2)
        for k in range(frames):
            t = AR1_RHO * t + rng.normal(0.0, innov, (n, 2))
            out[k] = t
        return out
    from lgs_wfs_ros.optics.turbulence import FrozenFlow
    l0 = {"frozen_inf": math.inf, "frozen_30": 30.0}[kind]
    return FrozenFlow(sensor.replace(outer_scale_m=l0), seed).tilts(frames)


class Renderer:
    """Noise-free images of an evolving profile: a blend of its knots' spots (exact, since a
    spot is linear in the density)."""

    def __init__(self, sensor: Sensor, evo, t0: float, max_shift: float):
        self.sensor, self.evo, self.t0 = sensor, evo, t0
        lay = geometry.layout(sensor)
        self.r, self.e, self.max_shift = lay.r_m, lay.e, max_shift
        w = np.gradient(evo.altitude_m)
        self.mass = (evo.profiles * w).sum(axis=1)
        self.models = {}

    def model(self, i):
        if i not in self.models:
            self.models = {k: v for k, v in self.models.items() if k >= i - 1}
            self.models[i] = SpotModel(self.sensor, self.r, self.e, self.evo.altitude_m,
                                       self.evo.profiles[i], max_shift_px=self.max_shift)
        return self.models[i]

    def images(self, k: int, shift: np.ndarray) -> np.ndarray:
        """``(n, p, p)`` unit-light images of frame ``k`` at ``shift (n, 2)``."""
        f = (self.t0 + k / self.sensor.frame_rate_hz) / self.evo.seconds_per_profile
        i = min(int(f), self.evo.n_profiles - 2)
        w = min(max(f - i, 0.0), 1.0)
        a, b = (1 - w) * self.mass[i], w * self.mass[i + 1]
        out = self.model(i).images(shift)[0] * a
        if b > 0:
            out += self.model(i + 1).images(shift)[0] * b
        return out / (a + b)


# -- scoring -------------------------------------------------------------------------------------
def ttf_modes(sensor: Sensor) -> np.ndarray:
    """``(2n, 3)`` orthonormal slope patterns of tip, tilt and focus (x, y interleaved)."""
    return metrics.ttf_modes(geometry.layout(sensor).centre_xy_m)


remove_ttf = metrics.remove_ttf


def score(err: np.ndarray, q: np.ndarray | None) -> dict:
    raw = metrics.summarize(err, MAS)
    out = {"mean_2d_mas": raw["mean_euclid_mas"], "mae_x_mas": raw["mae_x_mas"],
           "mae_y_mas": raw["mae_y_mas"], "bias_x_mas": raw["bias_x_mas"],
           "bias_y_mas": raw["bias_y_mas"], "n_nan": raw["n_nan"]}
    if q is not None:
        t = metrics.summarize(remove_ttf(err, q), MAS)
        out.update({"ttf_mean_2d_mas": t["mean_euclid_mas"], "ttf_mae_x_mas": t["mae_x_mas"],
                    "ttf_mae_y_mas": t["mae_y_mas"]})
    return out


def build(labels, sensor):
    out = {}
    for lb in labels:
        alg, opts = ESTIMATORS[lb]
        try:
            out[lb] = table.build(alg, sensor, opts)
        except (ValueError, FileNotFoundError) as exc:        # e.g. no ann model installed
            print(f"  {lb}: not run ({exc})", file=sys.stderr)
    return out


def refits(c) -> int:
    pupil = getattr(c, "pupil", None)
    return -1 if pupil is None else pupil.fits


def setup(family, det, launch, tilt, warm, scored, seed=0, single=False):
    """A case's ``(sensor, truth (frames, n, 2) px, Renderer, TTF modes or None)``, seeded."""
    if single:
        base = Sensor.paper_single(det)
    else:
        base = Sensor(detector=det, launch_xy_m=(launch, 0.0))
    frames = warm + scored
    if single:                                   # the paper's Table 3: measured, from profile 66
        h_m, prof = sodium.load_measured()
        evo = sodium.EvolvingProfile(h_m, prof[sodium.measured_split("test")])
        t0 = 0.0
    else:
        evo, t0 = sodium.unseen_sequence(family, frames, base.frame_rate_hz, seed)
    truth = tilts(tilt, base, frames, seed)
    rend = Renderer(base, evo, t0, float(np.abs(truth).max()) + 1.0)
    return base, truth, rend, (None if single else ttf_modes(base))


def bounds(base, truth, rend, warm: int, crb_samples: int) -> tuple[dict, dict]:
    """``(crb, cog_floor)`` of the scored frames, each ``{photons: {"mean_2d_mas", ...}}``:
    the Cramer-Rao bound and the photon-noise floor of the response-inverted CoG
    (``crb.cog_covariance``) at ``crb_samples`` frames spread over them (unit photons; both
    scale as 1/N with photon noise only)."""
    idx = np.unique(np.linspace(warm, truth.shape[0] - 1, crb_samples).astype(int))

    def image_at(j, s):
        k = idx[j]
        norm = rend.images(k, truth[k]).reshape(truth.shape[1], -1).sum(axis=1)[:, None, None]
        return rend.images(k, s) / norm
    unit = bound_covariances(base.replace(photons=1.0), image_at, truth[idx])
    crb, floor = {}, {}
    for ph in PHOTONS:
        cov = unit["crb"] / ph
        crb[str(int(ph))] = {"mean_2d_mas": float(np.nanmean(mean_abs_norm(cov))) * MAS,
                             "mae_mas": float(np.nanmean(math.sqrt(2 / math.pi)
                                                         * np.sqrt(np.einsum("nii->ni", cov)))) * MAS}
        floor[str(int(ph))] = {"mean_2d_mas": float(np.nanmean(mean_abs_norm(unit["cog"] / ph))) * MAS}
    return crb, floor


def run_case(family, det, launch, tilt, warm, scored, labels, seed=0, crb_samples=8, log=print,
             single=False):
    """One case at both photon levels: ``{"photons": {ph: {label: score}}, "crb", "cog_floor",
    "cpu_ms"}``."""
    base, truth, rend, q = setup(family, det, launch, tilt, warm, scored, seed, single)
    frames = warm + scored
    lay = geometry.layout(base)
    rng = np.random.default_rng([seed, 7])
    res = {"photons": {}, "cpu_ms": {}}
    cents = {ph: build(labels, base.replace(photons=ph)) for ph in PHOTONS}
    errs = {ph: {lb: [] for lb in cents[ph]} for ph in PHOTONS}
    cpu = {lb: [0.0, 0, 0.0, 0] for lb in cents[PHOTONS[-1]]}      # frame s, frames, refit s, refits
    shared = pupil_cal.HATS_BUILD_CPU_S                  # the shared bases' builds, timed apart
    basis_s = 0.0
    for k in range(frames):
        img = rend.images(k, truth[k])
        img = img / img.reshape(img.shape[0], -1).sum(axis=1)[:, None, None]
        for ph in PHOTONS:
            counts = geometry.stack_to_frame(rng.poisson(img * ph).astype(np.uint16), lay)  # as live
            for lb, c in cents[ph].items():
                before, built = refits(c), shared[0]
                t = time.process_time()
                est = c.centroid(counts)
                dt = time.process_time() - t
                spent = shared[0] - built                 # a basis every estimator shares
                dt -= spent
                basis_s += spent
                if ph == PHOTONS[-1]:            # first frame and refits: set-up, not per frame
                    slot = 2 if (refits(c) != before or k == 0) else 0
                    cpu[lb][slot] += dt
                    cpu[lb][slot + 1] += 1
                if k >= warm:
                    errs[ph][lb].append(est - truth[k])
    crb, floor = bounds(base, truth, rend, warm, crb_samples)
    for ph in PHOTONS:
        table_ph = {}
        for lb, e in errs[ph].items():
            table_ph[lb] = score(np.array(e), q)
        cog = table_ph.get("cog")
        for lb, s in table_ph.items():
            s["ratio_crb"] = s["mean_2d_mas"] / crb[str(int(ph))]["mean_2d_mas"]
            if q is not None:
                s["ttf_ratio_crb"] = s["ttf_mean_2d_mas"] / crb[str(int(ph))]["mean_2d_mas"]
            if cog:
                s["ratio_cog"] = s["mean_2d_mas"] / cog["mean_2d_mas"]
                if q is not None:
                    s["ttf_ratio_cog"] = s["ttf_mean_2d_mas"] / cog["ttf_mean_2d_mas"]
        res["photons"][str(int(ph))] = table_ph
    res["crb"], res["cog_floor"] = crb, floor
    res["cpu_ms"] = {lb: {"per_frame": 1e3 * v[0] / max(v[1], 1),
                          "refit": (1e3 * v[2] / v[3]) if v[3] else None, "refits": v[3]}
                     for lb, v in cpu.items()}
    res["basis_build_ms"] = 1e3 * basis_s
    res.update({"family": family, "detector": det, "launch_m": launch, "tilts": tilt,
                "warm_frames": warm, "scored_frames": scored, "n_subaps": int(truth.shape[1]),
                "truth_rms_px": float(np.sqrt(np.mean(truth[warm:] ** 2)))})
    log(f"  {family:<9} {det:<9} launch {launch:4.1f} m {tilt:<10}: " + "; ".join(
        f"{ph}: " + ", ".join(f"{lb} {v['mean_2d_mas']:.1f}" for lb, v in res["photons"][ph].items())
        + f", CRB {crb[ph]['mean_2d_mas']:.1f}" for ph in res["photons"]), flush=True)
    return res


# -- output --------------------------------------------------------------------------------------
def summary(result: dict) -> list[str]:
    """Per estimator: mean and worst ratio to the CRB (and mean ratio to cog) over the AR(1)
    cases (raw) and the frozen-flow cases (tip, tilt and focus removed), per photon level."""
    cases = result["cases"]
    labels = [lb for lb in ESTIMATORS if any(lb in c["photons"]["1000"] for c in cases)]
    lines = ["| estimator | tilts | photons | mean x CRB | worst x CRB | mean x cog | cases |",
             "|---|---|---|---|---|---|---|"]
    for lb in labels:
        for tilt, key in (("ar1", ""), ("frozen", "ttf_")):
            for ph in ("316", "1000"):
                rows = [c["photons"][ph][lb] for c in cases
                        if c["tilts"].startswith(tilt) and lb in c["photons"][ph]]
                if not rows:
                    continue
                crb = [r[key + "ratio_crb"] for r in rows]
                cog = [r.get(key + "ratio_cog", float("nan")) for r in rows]
                what = "AR(1), raw" if tilt == "ar1" else "frozen flow, TTF removed"
                lines.append(f"| {lb} | {what} | {ph} | {np.mean(crb):.2f} | {np.max(crb):.2f} | "
                             f"{np.mean(cog):.2f} | {len(rows)} |")
    return lines


def _floor_cell(c: dict, ph: str) -> str:
    """The case's CoG floor in mas and as a ratio to its CRB, or '-' for a run without it."""
    f = c.get("cog_floor", {}).get(ph)
    return "-" if f is None else f"{f['mean_2d_mas']:.1f} ({f['mean_2d_mas'] / c['crb'][ph]['mean_2d_mas']:.2f})"


def markdown(result: dict, title: bool = True) -> str:
    cases = result["cases"]
    labels = [lb for lb in ESTIMATORS if any(lb in c["photons"]["1000"] for c in cases)]
    lines = ([f"# Accuracy on unseen sodium profiles ({result['mode']})", ""] if title else []) + [
             result["what"], "", "### Summary", ""] + summary(result) + [
             "", "Mean 2-D error in mas (ratio to the CRB of the same frames in brackets); raw, then "
             "with the pupil-wide tip, tilt and focus removed. CoG floor: the photon-noise error "
             "of a CoG whose bias and response are known exactly (`crb.cog_covariance`), the "
             "least any calibrated CoG can reach on these frames.", ""]
    for key, title in (("", "raw"), ("ttf_", "tip, tilt and focus removed")):
        lines += [f"### {title}", "",
                  "| family | detector | launch | tilts | photons | " + " | ".join(labels)
                  + " | CRB | CoG floor |",
                  "|" + "---|" * (7 + len(labels))]
        for c in cases:
            for ph, row in c["photons"].items():
                cells = []
                for lb in labels:
                    s = row.get(lb)
                    cells.append("-" if s is None else
                                 f"{s[key + 'mean_2d_mas']:.1f} ({s[key + 'ratio_crb']:.2f})")
                lines.append(f"| {c['family']} | {c['detector']} | {c['launch_m']:g} m | {c['tilts']} "
                             f"| {ph} | " + " | ".join(cells) + f" | {c['crb'][ph]['mean_2d_mas']:.1f} | "
                             + _floor_cell(c, ph) + " |")
        lines.append("")
    t3 = result.get("table3")
    if t3:
        lines += ["### The paper's Table 3 case (one subaperture, r = 14.75 m, evolving measured "
                  "profiles from profile 66, frozen flow 10 m/s, 1000 photons)", "",
                  "| detector | " + " | ".join(labels) + " | CRB | CoG floor | paper ANN / CoG |",
                  "|" + "---|" * (4 + len(labels))]
        for c in t3:
            row = c["photons"]["1000"]
            cells = ["-" if lb not in row else
                     f"{row[lb]['mean_2d_mas']:.1f} ({row[lb]['ratio_cog']:.0%} of cog)" for lb in labels]
            lines.append(f"| {c['detector']} | " + " | ".join(cells)
                         + f" | {c['crb']['1000']['mean_2d_mas']:.1f} | {_floor_cell(c, '1000')} "
                         f"| {c['paper_ann_over_cog']:.0%} |")
        lines.append("")
    lines += ["### CPU per full frame (ms, one core; per-frame part / mean refit)", "",
              "The thin-layer basis a process builds once and every calibration of the same "
              "optics shares is left out of the refits since 2026-11-29 (before, the first "
              "calibrated estimator of a process was charged with it: 1-2 s more in its "
              "column; rows merged before then still carry it).", "",
              "| estimator | per frame | set-up / refit | set-up + refits per case |", "|---|---|---|---|"]
    for lb, v in result["cpu_ms"].items():
        refit = "-" if v["refit"] is None else f"{v['refit']:.0f}"
        lines.append(f"| {lb} | {v['per_frame']:.2f} | {refit} | {v['refits']} |")
    return "\n".join(lines) + "\n"


PAPER_T3 = {"polar": 88.06 / 237.31, "cartesian": 122.78 / 236.82}


def _case(args):
    """``run_case`` of one ``(family, detector, launch, tilts, warm, scored, labels)`` (a pool task)."""
    return run_case(*args)


def main(quick: bool = False, out_dir: Path = HERE, log=print, long: bool = False,
         jobs: int = 1, only: tuple = (), seed: int = 0, add_cases: bool = False) -> dict:
    """Run the mode's cases; with ``only`` (labels, ``cog`` among them), run those
    estimators alone and merge them into the mode's stored result (:func:`merge`); with
    ``add_cases``, run only the mode's cases the stored result lacks (every estimator it
    holds) and add them to it (:func:`add`). ``seed`` draws other frames (another start in
    the test block, layer, tilts and noise): its results go to their own files
    (:func:`result_name`), the docs are left alone."""
    t_start = time.time()
    if long:
        warm, scored, cases, labels, t3_frames = 700, 700, quick_cases(), LONG_ESTIMATORS, 0
    elif quick:
        warm, scored, cases, labels, t3_frames = 210, 140, quick_cases(), QUICK_ESTIMATORS, 1400
    else:
        warm, scored, cases, labels, t3_frames = 700, 700, full_cases(), tuple(ESTIMATORS), 7000
    name = result_name(long, seed)
    stored = None
    if add_cases:
        if only:
            raise SystemExit("--add-cases runs every estimator of the stored result: no --only")
        stored = json.loads((out_dir / f"{name}.json").read_text())
        have = {_key(c) for c in stored["cases"]}
        cases = [c for c in cases if c not in have]
        labels = tuple(lb for lb in ESTIMATORS if any(lb in c["photons"]["1000"] for c in stored["cases"]))
        if not cases:
            raise SystemExit(f"--add-cases: {name}.json holds every case of this mode")
    elif only:
        unknown = [lb for lb in only if lb not in ESTIMATORS]
        if unknown or "cog" not in only:
            raise SystemExit(f"--only: labels of ESTIMATORS, cog among them (it checks that the "
                             f"frames are the stored run's); got {', '.join(only)}")
        labels = tuple(only)
        if (out_dir / f"{name}.json").is_file():      # else: those alone make the first run
            stored = json.loads((out_dir / f"{name}.json").read_text())
    what = (f"{warm} warm-up + {scored} scored frames at 700 Hz per case, full pupil "
            f"(2,784 subapertures), photons {', '.join(f'{p:g}' for p in PHOTONS)}, "
            f"side launch {SIDE_LAUNCH_M:g} m off axis, AR(1) tilts {AR1_RHO} per frame "
            f"{AR1_RMS_PX} px rms per axis; estimators built with options.build (the node's "
            f"defaults) plus: " + "; ".join(f"{lb} = {ESTIMATORS[lb][0]} {ESTIMATORS[lb][1] or ''}"
                                              for lb in labels))
    mode = "long" if long else "quick" if quick else "full"
    out = {"mode": mode, "what": what, "cases": [], "table3": []}
    if stored is not None:
        name += "_only"                                   # partial results beside the stored
    if add_cases:
        t3_frames = 0
    tasks = [(fam, det, launch, tilt, warm, scored, labels, seed) for fam, det, launch, tilt in cases]
    if jobs > 1:
        import multiprocessing
        with multiprocessing.get_context("spawn").Pool(jobs) as pool:
            for c in pool.imap(_case, tasks):
                out["cases"].append(c)
                _save(out, out_dir, t_start, name)                     # partial results
    else:
        for t in tasks:
            out["cases"].append(run_case(*t, log=log))
            _save(out, out_dir, t_start, name)
    if t3_frames:
        for det in ("polar", "cartesian"):
            c = run_case("measured", det, 0.0, "frozen_inf", 0, t3_frames, labels, seed=seed,
                         crb_samples=50, log=log, single=True)
            c["paper_ann_over_cog"] = PAPER_T3[det]
            out["table3"].append(c)
    if stored is not None:
        out["seconds"] = round(time.time() - t_start, 1)
        (out_dir / f"{name}.json").unlink(missing_ok=True)
        (out_dir / f"{name}.md").unlink(missing_ok=True)
        out = add(stored, out, quick_cases() if quick or long else full_cases()) if add_cases \
            else merge(stored, out, labels)
        name = name[:-len("_only")]
    out["seed"] = seed
    _save(out, out_dir, t_start, name)
    if not long and not seed:
        write_docs(out)
    return out


def result_name(long: bool, seed: int = 0) -> str:
    """The stem of a run's json / md in ``benchmarks/``: ``accuracy`` (quick) or
    ``accuracy_long``, with ``_seed<N>`` for another seed than the tables' 0."""
    return ("accuracy_long" if long else "accuracy") + (f"_seed{seed}" if seed else "")


def _key(c: dict) -> tuple:
    return c["family"], c["detector"], c["launch_m"], c["tilts"]


def merge(stored: dict, new: dict, labels: tuple) -> dict:
    """``stored`` with ``labels``' scores and CPU times replaced (or added) by ``new``'s, a
    run of the same mode on the same frames: every case's CRB and cog scores must agree to
    1e-9 (the frames are seeded), or this refuses. The run's time is kept in ``merged``."""
    _same_mode(stored, new, "merge")
    for part in ("cases", "table3"):
        fresh = {_key(c): c for c in new[part]}
        if set(fresh) != {_key(c) for c in stored[part]}:
            raise SystemExit(f"merge: the stored {part} are not this run's")
        for c in stored[part]:
            f = fresh[_key(c)]
            for ph, row in c["photons"].items():
                same = (math.isclose(c["crb"][ph]["mean_2d_mas"], f["crb"][ph]["mean_2d_mas"],
                                     rel_tol=1e-9)
                        and math.isclose(row["cog"]["mean_2d_mas"],
                                         f["photons"][ph]["cog"]["mean_2d_mas"], rel_tol=1e-9))
                if not same:
                    raise SystemExit(f"merge: {_key(c)} at {ph} ph: other frames than the stored "
                                     f"run's (CRB or cog differ); rerun the whole benchmark")
                row.update({lb: f["photons"][ph][lb] for lb in labels if lb in f["photons"][ph]})
                # the stored order of columns, new labels after
                c["photons"][ph] = {lb: row[lb] for lb in ESTIMATORS if lb in row}
            c["cpu_ms"].update({lb: f["cpu_ms"][lb] for lb in labels if lb in f["cpu_ms"]})
    defs = "; ".join(f"{lb} = {ESTIMATORS[lb][0]} {ESTIMATORS[lb][1] or ''}" for lb in labels)
    return _logged(stored, new, {"labels": list(labels)},
                   "rerun on the same frames {utc} UTC and merged: " + defs)


def add(stored: dict, new: dict, order: list) -> dict:
    """``stored`` with ``new``'s cases (a run of the same mode and estimators on cases it
    lacked) added, in the mode's case ``order``; the run's time is kept in ``merged``."""
    _same_mode(stored, new, "add")
    cases = {_key(c): c for c in stored["cases"] + new["cases"]}
    stored["cases"] = [cases[k] for k in order if k in cases]
    keys = [list(_key(c)) for c in new["cases"]]
    return _logged(stored, new, {"cases": keys}, "cases " + ", ".join(
        "/".join(str(v) for v in k) for k in keys) + " run {utc} UTC and added")


def _same_mode(stored: dict, new: dict, verb: str) -> None:
    """Refuse to combine runs of different modes (quick, full, long)."""
    if stored["mode"] != new["mode"]:
        raise SystemExit(f"{verb}: the stored result is {stored['mode']}, this run {new['mode']}")


def _logged(stored: dict, new: dict, entry: dict, text: str) -> dict:
    """``stored`` with ``entry`` (plus the time now and ``new``'s run time) appended to its
    ``merged`` log and ``text`` (``{utc}`` filled in) to its ``what``."""
    utc = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    stored.setdefault("merged", []).append({**entry, "utc": utc, "seconds": new["seconds"]})
    stored["what"] += " [" + text.replace("{utc}", utc) + "]"
    return stored


def add_floors(result: dict, log=print) -> dict:
    """``result`` (a stored run) with each case's ``cog_floor`` computed from its seeded
    frames' models (no estimator runs); refuses unless each recomputed CRB is the stored one."""
    for part, samples, single in (("cases", 8, False), ("table3", 50, True)):
        for c in result.get(part, []):
            base, truth, rend, _ = setup(c["family"], c["detector"], c["launch_m"], c["tilts"],
                                         c["warm_frames"], c["scored_frames"], single=single)
            crb, floor = bounds(base, truth, rend, c["warm_frames"], samples)
            for ph, v in crb.items():
                if not math.isclose(v["mean_2d_mas"], c["crb"][ph]["mean_2d_mas"], rel_tol=1e-9):
                    raise SystemExit(f"floors: {_key(c)} at {ph} ph: the CRB is not the stored "
                                     f"one (other frames); rerun the benchmark")
            c["cog_floor"] = floor
            log(f"  {_key(c)}: CoG floor / CRB " + ", ".join(
                f"{ph} ph {floor[ph]['mean_2d_mas'] / crb[ph]['mean_2d_mas']:.3f}" for ph in crb))
    return result


def _save(out: dict, out_dir: Path, t_start: float, name: str = "accuracy") -> None:
    if "merged" not in out:                              # a merge keeps the stored run's
        out["seconds"] = round(time.time() - t_start, 1)
    cpu = {}
    for c in out["cases"]:
        for lb, v in c["cpu_ms"].items():
            d = cpu.setdefault(lb, {"per_frame": [], "refit": [], "refits": 0})
            d["per_frame"].append(v["per_frame"])
            if v["refit"] is not None:
                d["refit"].append(v["refit"])
            d["refits"] = v["refits"]
    out["cpu_ms"] = {lb: {"per_frame": float(np.median(v["per_frame"])),
                          "refit": float(np.median(v["refit"])) if v["refit"] else None,
                          "refits": v["refits"]} for lb, v in cpu.items()}
    (out_dir / f"{name}.json").write_text(json.dumps(out, indent=1) + "\n")
    (out_dir / f"{name}.md").write_text(markdown(out))


DOC = HERE.parent / "docs" / "accuracy.md"


def write_docs(result: dict, path: Path = DOC) -> None:
    """Replace the generated block of docs/accuracy.md with this run's tables."""
    if not path.is_file():
        return
    text = path.read_text()
    begin, end = "<!-- accuracy:begin -->", "<!-- accuracy:end -->"
    if begin not in text or end not in text:
        return
    block = (f"{begin}\n(generated by `python benchmarks/bench_accuracy.py"
             f"{' --quick' if result['mode'] == 'quick' else ''}`, {result['seconds']:.0f} s; "
             f"also in benchmarks/accuracy.md and accuracy.json)\n\n"
             + markdown(result, title=False) + end)
    path.write_text(text[:text.index(begin)] + block + text[text.index(end) + len(end):])


def run(quick: bool = False) -> list[dict]:
    """Rows for benchmarks/run.py: the best ratio to the CRB per photon level (unseen families,
    AR(1), full pupil) and each estimator's per-frame CPU time."""
    return rows(main(quick))


def rows(res: dict) -> list[dict]:
    """benchmarks/run.py rows of a result."""
    rows = []
    for ph in ("316", "1000"):
        for lb in LONG_ESTIMATORS:
            vals = [c["photons"][ph][lb]["ratio_crb"] for c in res["cases"]
                    if c["tilts"] == "ar1" and lb in c["photons"][ph]]
            if vals:
                rows.append({"name": f"accuracy {lb} worst ratio to CRB, AR(1), {ph} ph",
                             "value": float(max(vals)), "unit": "x CRB",
                             "target": {"cmf": "<= 1.1", "cog_pupil": "<= 1.1 centre, 1.3 side",
                                        "ann_conv": "<= 1.1", "ann_grid": "<= 1.1"}.get(lb, ""),
                             "note": f"{len(vals)} cases ({res['mode']})"})
        floor = [c["photons"][ph]["cog_pupil"]["mean_2d_mas"] / c["cog_floor"][ph]["mean_2d_mas"]
                 for c in res["cases"] if c["tilts"] == "ar1" and "cog_floor" in c
                 and "cog_pupil" in c["photons"][ph]]
        if floor:
            rows.append({"name": f"accuracy cog_pupil worst ratio to the CoG floor, AR(1), {ph} ph",
                         "value": float(max(floor)), "unit": "x floor", "target": "",
                         "note": f"{len(floor)} cases ({res['mode']}); the floor: a CoG with "
                                 f"its bias and response known exactly (crb.cog_covariance)"})
        for lb in LONG_ESTIMATORS:                 # frozen flow: scored with tip, tilt and focus removed
            frozen = [c["photons"][ph][lb] for c in res["cases"]
                      if c["tilts"] in FROZEN and lb in c["photons"][ph]]
            if frozen and lb != "cog":
                rows.append({"name": f"accuracy {lb} worst ratio to cog, frozen flow, tip, tilt and "
                                     f"focus removed, {ph} ph",
                             "value": float(max(v["ttf_ratio_cog"] for v in frozen)),
                             "unit": "x cog", "target": "<= 1",
                             "note": f"{len(frozen)} cases ({res['mode']}); worst ratio to the CRB "
                                     f"{max(v['ttf_ratio_crb'] for v in frozen):.3f}, raw "
                                     f"{max(v['ratio_crb'] for v in frozen):.3f}"})
        for det in ("polar", "cartesian"):         # the best estimator of each case, worst case
            best = [min(v["ratio_crb"] for k, v in c["photons"][ph].items() if k != "cog")
                    for c in res["cases"] if c["tilts"] == "ar1" and c["detector"] == det]
            if best:
                rows.append({"name": f"accuracy best estimator's worst ratio to CRB, AR(1), "
                                     f"{det}, {ph} ph", "value": float(max(best)),
                             "unit": "x CRB", "target": "<= 1.05",
                             "note": f"{len(best)} cases ({res['mode']}); ml_alt and cmf_alt "
                                     f"(pupil_altitude_s, off by default) count"})
    for lb, v in res["cpu_ms"].items():
        rows.append({"name": f"accuracy {lb} CPU per full frame", "value": v["per_frame"],
                     "unit": "ms", "target": "<= 1", "note": "per-frame part, every frame new, cases run side by side "
                     "(--jobs; one quiet core: bench_centroiders); refit "
                     + ("-" if v["refit"] is None else f"{v['refit']:.0f} ms every period")})
    return rows


def family_summary(cases, label: str) -> dict:
    """Per family: mean ratio of ``label``'s error to the CRB and to cog over its cases."""
    out = {}
    for c in cases:
        for ph, row in c["photons"].items():
            if label not in row:
                continue
            d = out.setdefault(c["family"], {"ratio_crb": [], "ratio_cog": []})
            d["ratio_crb"].append(row[label]["ratio_crb"])
            d["ratio_cog"].append(row[label]["ratio_cog"])
    return {f: {k: round(float(np.mean(v)), 3) for k, v in d.items()}
            | {"cases": len(d["ratio_crb"])} for f, d in out.items()}


def record(label: str, model: str, res: dict) -> None:
    """Write ``label``'s per-family summary of ``res`` into model ``model``'s
    ``lgs_wfs.training["accuracy"]`` and rewrite its directory's card (learning/card.py)."""
    from lgs_wfs_ros.centroiding.ann_model import resolve_model
    from lgs_wfs_ros.learning import card, export
    path = resolve_model(model)
    tr = export.read_metadata(path).get("lgs_wfs.training", {})
    tr["accuracy"] = {"what": f"bench_accuracy.run_case ({res['mode']}), label {label}",
                      "per_family": family_summary(res["cases"], label),
                      "cpu_ms_per_frame": {f"{c['family']}/{c['detector']}/{c['launch_m']:g}":
                                           round(c["cpu_ms"][label]["per_frame"], 2)
                                           for c in res["cases"] if label in c["cpu_ms"]}}
    export.update_metadata(path, {"lgs_wfs.training": tr})
    card.write(path.parent)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and cases (minutes)")
    ap.add_argument("--long", action="store_true",
                    help="the quick cases at 700 + 700 frames for the 'done when' estimators "
                         "(accuracy_long.json / .md; the docs are left alone)")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at a time (processes)")
    ap.add_argument("--only", default="", metavar="LABELS",
                    help="comma-separated estimators (cog among them) run alone on the mode's "
                         "frames and merged into its stored json / md (and docs, quick), or "
                         "written as the first run where none is stored (another --seed)")
    ap.add_argument("--add-cases", action="store_true",
                    help="run the mode's cases the stored result lacks (all its estimators) "
                         "and add them to it")
    ap.add_argument("--tables-only", action="store_true",
                    help="rewrite accuracy.md and docs/accuracy.md from accuracy.json, no run")
    ap.add_argument("--floors", action="store_true",
                    help="add each stored case's CoG floor (no estimator runs) to the mode's "
                         "json / md (quick: and the docs)")
    ap.add_argument("--seed", type=int, default=0,
                    help="draw other frames (start in the test block, layer, tilts, noise): "
                         "results in accuracy[_long]_seed<N>.json / .md, docs left alone "
                         "(one seed's ratios move by several percent on the high layer)")
    ap.add_argument("--record", default="", metavar="LABEL",
                    help="with --tables-only: write LABEL's (an ann estimator's) per-family "
                         "summary into its model's metadata and the model card")
    args = ap.parse_args()
    if args.record:
        res = json.loads((HERE / "accuracy.json").read_text())
        record(args.record, ESTIMATORS[args.record][1]["model"], res)
    if args.floors:
        name = "accuracy_long" if args.long else "accuracy"
        res = add_floors(json.loads((HERE / f"{name}.json").read_text()))
        (HERE / f"{name}.json").write_text(json.dumps(res, indent=1) + "\n")
        (HERE / f"{name}.md").write_text(markdown(res))
        if not args.long:
            write_docs(res)
    elif args.tables_only:
        res = json.loads((HERE / "accuracy.json").read_text())
        (HERE / "accuracy.md").write_text(markdown(res))
        write_docs(res)
        results = HERE / "results.json"                 # as `run.py --only accuracy` would
        if results.is_file():
            allres = json.loads(results.read_text())
            allres.setdefault("areas", {})["accuracy"] = {"rows": rows(res), "seconds": res["seconds"]}
            results.write_text(json.dumps(allres, indent=2) + "\n")
    else:
        main(args.quick, long=args.long, jobs=args.jobs,
             only=tuple(x for x in args.only.split(",") if x), seed=args.seed,
             add_cases=args.add_cases)
    print((HERE / f"{result_name(args.long, args.seed)}.md").read_text())
