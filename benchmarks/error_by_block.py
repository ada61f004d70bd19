"""Where an estimator's error sits on the pupil: along and across e, by radius and by block
orientation, split into each subaperture's static part, its gain on the true shift and the
rest.

One case of the accuracy benchmark (``bench_accuracy.setup``: the same frames, photon
draws and seeds), 1000 photons, the estimators by their ``bench_accuracy.ESTIMATORS``
labels. For each, per subaperture over the scored frames, the error along e ``a (F, n)``
(px) is split into its mean (the static part), the slope of ``a`` on the true shift along
e (``gain - 1``) and the residual. Blocks are grouped by radius from the launch and by
whether e is nearer a pixel diagonal or a pixel axis (on a diagonal block the 16 bins of
``ann``'s grid projection span 16 of the block's 22.6 px along e).

Run: ``python benchmarks/error_by_block.py --family high --detector cartesian --seed 1``
(``--save FILE.npz`` keeps every error). Used in docs/ann_ref.md, "Where the cartesian
high layer's excess sits".
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_accuracy as bench  # noqa: E402

from lgs_wfs_ros.optics import geometry  # noqa: E402

PHOTONS = 1000.0
RADII_M = (0.0, 8.0, 13.0, 16.5)
STATIC_RINGS_M = np.arange(0.0, 18.0, 2.0)


def errors(family: str, detector: str, seed: int, warm: int, scored: int, labels) -> dict:
    """``{"truth" (F, n, 2), "r" (n,), "e" (n, 2), label: (F, n, 2) errors}``, px, block
    axes, over the scored frames at :data:`PHOTONS` (the 316-photon draws are made and
    dropped, so the frames are the benchmark's)."""
    base, truth, rend, _ = bench.setup(family, detector, 0.0, "ar1", warm, scored, seed)
    lay = geometry.layout(base)
    rng = np.random.default_rng([seed, 7])
    cents = bench.build(labels, base.replace(photons=PHOTONS))
    out = {lb: [] for lb in cents}
    for k in range(warm + scored):
        img = rend.images(k, truth[k])
        img = img / img.reshape(img.shape[0], -1).sum(axis=1)[:, None, None]
        for ph in bench.PHOTONS:                          # the benchmark's stream of draws
            counts = rng.poisson(img * ph).astype(np.uint16)
            if ph != PHOTONS:
                continue
            frame = geometry.stack_to_frame(counts, lay)
            for lb, c in cents.items():
                est = c.centroid(frame)
                if k >= warm:
                    out[lb].append(est - truth[k])
    res = {lb: np.asarray(v) for lb, v in out.items()}
    res.update(truth=truth[warm:], r=np.asarray(lay.r_m), e=np.asarray(lay.e, dtype=float))
    return res


def near_diagonal(e: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: e within 22.5 deg of a pixel diagonal (``e (n, 2)`` block axes)."""
    ang = np.degrees(np.arctan2(np.abs(e[:, 1]), np.abs(e[:, 0])))
    return np.abs(ang - 45.0) < 22.5


def split(err_along: np.ndarray, true_along: np.ndarray) -> dict:
    """rms (px) over ``(F, m)`` errors along e of the total, the static part (each
    subaperture's mean) and the residual after the static part and a per-subaperture
    slope on the true shift ``true_along (F, m)``; ``gain`` is 1 plus the mean slope."""
    static = err_along.mean(axis=0)
    tc = true_along - true_along.mean(axis=0)
    ac = err_along - static
    slope = (tc * ac).sum(axis=0) / (tc * tc).sum(axis=0)
    resid = ac - slope * tc
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    return {"total": rms(err_along), "static": rms(static), "residual": rms(resid),
            "gain": float(1.0 + slope.mean())}


def table(res: dict) -> list[str]:
    """Markdown lines: per estimator the mean 2-D error (mas), the rms across e, and the
    split along e by ring and orientation, then the static part along e by radius."""
    r, e = res["r"], res["e"]
    v = np.stack([-e[:, 1], e[:, 0]], axis=1)
    diag = near_diagonal(e)
    t_along = (res["truth"] * e).sum(axis=-1)
    labels = [k for k in res if k not in ("truth", "r", "e")]
    lines = ["| estimator | blocks | r (m) | along e: total / static / residual (px), gain |",
             "|---|---|---|---|"]
    for lb in labels:
        a = (res[lb] * e).sum(axis=-1)
        for lo, hi in zip(RADII_M[:-1], RADII_M[1:]):
            for name, sel in (("near a diagonal", diag), ("near an axis", ~diag)):
                m = sel & (r >= lo) & (r < hi)
                s = split(a[:, m], t_along[:, m])
                lines.append(f"| `{lb}` | {name} | {lo:g}-{hi:g} | {s['total']:.4f} / "
                             f"{s['static']:.4f} / {s['residual']:.4f}, {s['gain']:.3f} |")
    rings = [(a, b) for a, b in zip(STATIC_RINGS_M[:-1], STATIC_RINGS_M[1:])
             if np.any((r >= a) & (r < b))]
    lines += ["", "| estimator | mean 2-D (mas) | rms across e (px) | static along e (mas) by "
              "radius: " + ", ".join(f"{a:g}-{b:g} m" for a, b in rings) + " |",
              "|---|---|---|---|"]
    for lb in labels:
        err = res[lb]
        static = (err * e).sum(axis=-1).mean(axis=0) * bench.MAS
        lines.append(f"| `{lb}` | {np.hypot(err[..., 0], err[..., 1]).mean() * bench.MAS:.2f} | "
                     f"{np.sqrt(np.mean(((err * v).sum(axis=-1)) ** 2)):.4f} | "
                     + ", ".join(f"{static[(r >= a) & (r < b)].mean():+.1f}" for a, b in rings)
                     + " |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", default="high")
    ap.add_argument("--detector", default="cartesian", choices=("polar", "cartesian"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--warm", type=int, default=700)
    ap.add_argument("--scored", type=int, default=350)
    ap.add_argument("--labels", default="cmf,ann_grid")
    ap.add_argument("--save", type=Path)
    a = ap.parse_args(argv)
    res = errors(a.family, a.detector, a.seed, a.warm, a.scored, a.labels.split(","))
    if a.save:
        np.savez(a.save, **res)
    print(f"{a.family}, {a.detector}, seed {a.seed}, {a.warm} + {a.scored} frames, "
          f"{PHOTONS:g} photons")
    print("\n".join(table(res)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
