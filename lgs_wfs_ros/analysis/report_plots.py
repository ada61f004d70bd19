"""The report's pictures: error over time (binned median and 16-84 % band), the error
distribution, ratios to CoG and to the Cramer-Rao bound, and error by radius, each with a
title, px and mas axes and a legend. They draw the ``res`` dict of
:func:`lgs_wfs_ros.analysis.report.analyse`."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

TIME_BINS = 120          # the time series is drawn as at most this many bins, not one point a frame
HIST_BINS = 80


def _mas_axis(ax, mas_per_px: float, which: str = "y") -> None:
    """A second axis in mas beside a px axis."""
    conv = (lambda v: v * mas_per_px, lambda v: v / mas_per_px)
    if which == "y":
        ax.secondary_yaxis("right", functions=conv).set_ylabel("mas")
    else:
        ax.secondary_xaxis("top", functions=conv).set_xlabel("mas")


def _save(fig, path: Path) -> str:
    """Layout, write the PNG, close the figure; the path as text."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def binned(t: np.ndarray, y: np.ndarray, bins: int = TIME_BINS):
    """Per time bin: (centre, median, 16th, 84th percentile) of ``y`` (NaN skipped), for bins
    that hold a finite value; ``(t, y, y, y)`` when there are fewer points than bins."""
    ok = np.isfinite(y)
    t, y = t[ok], y[ok]
    if len(t) <= bins:
        return t, y, y, y
    edges = np.linspace(t.min(), t.max(), bins + 1)
    which = np.clip(np.digitize(t, edges) - 1, 0, bins - 1)
    order = np.argsort(which, kind="stable")
    groups = np.split(y[order], np.flatnonzero(np.diff(which[order])) + 1)
    centres = (edges[:-1] + edges[1:])[np.unique(which)] / 2
    q = np.array([np.percentile(g, [50, 16, 84]) for g in groups])
    return centres, q[:, 0], q[:, 1], q[:, 2]


def _title(res: dict) -> str:
    return Path(res["bag"]).name


def plot_timeseries(res: dict, path: Path) -> str:
    """Per-frame mean |error| over time: each algorithm's median and 16-84 % band per time bin
    (thousands of frames are not drawn one by one); the CRB at the frames it was computed at."""
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 4.2))
    t0 = min((s[0] for s, _ in res["_series"].values() if len(s)), default=0)
    n_max = 0
    for k, (name, (stamps, per_frame)) in enumerate(res["_series"].items()):
        t = (stamps - t0) / 1e9
        c, med, lo, hi = binned(t, per_frame)
        n_max = max(n_max, len(per_frame))
        color = f"C{k}"
        ax.fill_between(c, lo, hi, color=color, alpha=0.2, lw=0)
        ax.plot(c, med, color=color, lw=1.4,
                label=f"{name}: mean {res['algorithms'][name]['mean_euclid']:.3f} px")
    crb = res.get("crb") or {}
    frames = res.get("_crb_frames")
    if frames is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            d = np.nanmean(frames[1], axis=1)
        ax.plot((frames[0] - t0) / 1e9, d, "k.-", ms=2.5, lw=0.8,
                label=f"CRB at {len(d)} frames: mean {crb['mean_euclid']:.3f} px")
    elif "mean_euclid" in crb:
        ax.axhline(crb["mean_euclid"], color="k", ls="--", lw=1, label=f"CRB: {crb['mean_euclid']:.3f} px")
    ax.set_ylim(bottom=0)
    ax.set_xlabel("time from the first stamp (s)")
    ax.set_ylabel("mean |error| over subapertures (px)")
    _mas_axis(ax, res["mas_per_px"])
    per_bin = max(1, round(n_max / TIME_BINS)) if n_max > TIME_BINS else 1
    ax.set_title(f"Centroid error over time: {_title(res)}\n"
                 + (f"median (line) and 16-84 % (band) of ~{per_bin} frames per bin" if per_bin > 1
                    else "one point per frame"), fontsize=10)
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_distribution(res: dict, path: Path) -> str:
    """Density of |error| per subaperture and frame, one step line per algorithm."""
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4.2))
    dists = {}
    for name, (_, err) in res["_errors"].items():
        d = np.hypot(err[..., 0], err[..., 1]).ravel()
        dists[name] = d[np.isfinite(d)]
    top = max((np.percentile(d, 99.5) for d in dists.values() if len(d)), default=1.0)
    edges = np.linspace(0, top, HIST_BINS + 1)
    for k, (name, d) in enumerate(dists.items()):
        ax.hist(d, bins=edges, density=True, histtype="step", lw=1.4, color=f"C{k}",
                label=f"{name}: mean {d.mean():.3f} px ({len(d):,} values)" if len(d) else name)
    crb = res.get("crb") or {}
    if "mean_euclid" in crb:
        ax.axvline(crb["mean_euclid"], color="k", ls="--", lw=1, label=f"CRB mean: {crb['mean_euclid']:.3f} px")
    ax.set_xlabel("|error| (px), per subaperture and frame")
    ax.set_ylabel("density (1/px)")
    _mas_axis(ax, res["mas_per_px"], "x")
    ax.set_title(f"Distribution of the centroid error: {_title(res)}\n(99.5 % of the values shown)", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_ratios(res: dict, path: Path) -> str | None:
    """Each algorithm's mean |error| relative to CoG and to the CRB on the same frames."""
    import matplotlib.pyplot as plt
    names = list(res["algorithms"])
    cols = [(key, lab) for key, lab in (("ratio_to_cog", "x CoG"), ("ratio_to_crb", "x CRB"))
            if any(res["algorithms"][n].get(key) is not None for n in names)]
    if not cols:
        return None
    fig, ax = plt.subplots(figsize=(7, 0.6 + 0.55 * len(names) * len(cols) + 0.8))
    h = 0.8 / len(cols)
    y = np.arange(len(names))
    for j, (key, lab) in enumerate(cols):
        vals = np.array([res["algorithms"][n].get(key) or np.nan for n in names], float)
        bars = ax.barh(y + (j - (len(cols) - 1) / 2) * h, vals, height=h, color=f"C{j}", label=lab)
        for b, v in zip(bars, vals):
            if np.isfinite(v):
                ax.text(max(v, 1.0), b.get_y() + b.get_height() / 2, f"  {v:.2f}", va="center", fontsize=8)
    ax.axvline(1.0, color="k", lw=1)
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xlabel("mean |error| ratio (1 = as good as the reference)")
    ax.set_xlim(0, np.nanmax([res["algorithms"][n].get(k) or np.nan for n in names for k, _ in cols]) * 1.18)
    ax.set_title(f"Error relative to CoG and to the Cramer-Rao bound: {_title(res)}\n"
                 "on the frames both measured / the frames the CRB was computed at", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    return _save(fig, path)


def plot_by_radius(res: dict, path: Path) -> str | None:
    """Mean |error| per ring of subaperture distance from the launch (full pupil): raw
    (solid) and, where the report has it, with the pupil-wide tip, tilt and focus removed
    (dotted, same colour)."""
    import matplotlib.pyplot as plt
    first = next(iter(res["algorithms"].values()))
    if not first.get("by_radius") or len(first["by_radius"]) < 2:
        return None
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for k, (name, v) in enumerate(res["algorithms"].items()):
        mid = [(r["r_min_m"] + r["r_max_m"]) / 2 for r in v["by_radius"]]
        ax.plot(mid, [r["mean_euclid"] for r in v["by_radius"]], "o-", color=f"C{k}", label=name)
        ttf = (v.get("ttf") or {}).get("by_radius")
        if ttf:
            ax.plot(mid, [r["mean_euclid"] for r in ttf], "o:", color=f"C{k}", mfc="none",
                    label=f"{name}, tip, tilt, focus removed")
    crb = res.get("crb") or {}
    if crb.get("by_radius"):
        mid = [(r["r_min_m"] + r["r_max_m"]) / 2 for r in crb["by_radius"]]
        ax.plot(mid, [r["mean_euclid"] for r in crb["by_radius"]], "k--", label="CRB")
    ax.set_ylim(bottom=0)
    ax.set_xlabel("subaperture distance from the launch (m)")
    ax.set_ylabel("mean |error| (px)")
    _mas_axis(ax, res["mas_per_px"])
    ax.set_title(f"Error against spot elongation (distance from the launch): {_title(res)}", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _save(fig, path)


def write_plots(res: dict, out_dir: Path) -> list[str]:
    """PNG plots: error over time (binned), error distribution, ratios to CoG and CRB, and
    (full pupil) error by radius. Returns the files written."""
    import matplotlib
    matplotlib.use("Agg")
    out_dir = Path(out_dir)
    files = [plot_timeseries(res, out_dir / "error_timeseries.png"),
             plot_distribution(res, out_dir / "error_distribution.png"),
             plot_ratios(res, out_dir / "error_ratios.png"),
             plot_by_radius(res, out_dir / "error_by_radius.png")]
    return [f for f in files if f]
