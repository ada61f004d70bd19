"""What a live node's refit latency costs: ``ml`` with refits installed late.

A live node cannot install a profile refit on the frame its period ends (an ``ml`` refit
takes ~0.25 s wall here, a period is 0.2 s at 700 Hz): it runs ``pupil_async: true`` and
installs each refit ``pupil_async_lag`` frames later (reproducible frame for frame). This
runs :func:`bench_accuracy.run_case` at the issue's protocol (700 warm-up + 700 scored
frames, full polar pupil, centre launch, AR(1) tilts, seed 0) for ``ml`` inline and with
lags, shorter time constants, a longer period, and the altitude tracker
(``pupil_altitude_s``), and prints the ratios to the CRB (raw / tip, tilt and focus
removed) per family and photon level (docs/accuracy.md, "A live node's refit latency").

Run: ``python benchmarks/latency_accuracy.py [FAMILY ...] [--jobs 2] [--out FILE.json]``
(default: the five unseen families; ~4 min a family on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_accuracy as ba  # noqa: E402

VARIANTS = {
    "ml_lag140": {"pupil_async": True, "pupil_async_lag": 140},
    "ml_lag280": {"pupil_async": True, "pupil_async_lag": 280},
    "ml_p280_lag280": {"pupil_async": True, "pupil_async_lag": 280, "pupil_period": 280},
    "ml_lag140_t15": {"pupil_async": True, "pupil_async_lag": 140, "pupil_time_constant_s": 0.15},
    "ml_lag280_t15": {"pupil_async": True, "pupil_async_lag": 280, "pupil_time_constant_s": 0.15},
    "ml_alt_lag140": {"pupil_async": True, "pupil_async_lag": 140,
                      "pupil_altitude_s": ba.ALTITUDE_S},
}
for _label, _opts in VARIANTS.items():
    ba.ESTIMATORS[_label] = ("ml", _opts)
LABELS = ("cog", "ml", "ml_alt", *VARIANTS)
FAMILIES = ("measured", "high", "sporadic", "broad", "narrow")


def case(family: str) -> dict:
    """One family: :func:`bench_accuracy.run_case` with every label."""
    return ba.run_case(family, "polar", 0.0, "ar1", 700, 700, LABELS, seed=0, log=lambda *a, **k: None)


def lines(cases: list[dict]) -> list[str]:
    """``family photons: label raw/ttf ...`` per case and photon level."""
    out = []
    for c in cases:
        for ph, table in c["photons"].items():
            out.append(f"{c['family']:<9} {ph:>4} ph: " + "  ".join(
                f"{lb} {v['ratio_crb']:.3f}/{v['ttf_ratio_crb']:.3f}" for lb, v in table.items()))
    return out


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("families", nargs="*", default=list(FAMILIES))
    ap.add_argument("--jobs", type=int, default=1, help="families run at a time (processes)")
    ap.add_argument("--out", default="", help="write the cases as JSON here")
    a = ap.parse_args(argv)
    if a.jobs > 1:
        import multiprocessing
        with multiprocessing.get_context("spawn").Pool(a.jobs) as pool:
            cases = pool.map(case, a.families)
    else:
        cases = [case(f) for f in a.families]
    print("\n".join(lines(cases)))
    if a.out:
        Path(a.out).write_text(json.dumps(cases, indent=1))
    return cases


if __name__ == "__main__":
    main()
