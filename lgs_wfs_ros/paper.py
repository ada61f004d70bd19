"""The paper's published numbers (Mello et al. 2014), read from ``data/paper_results.json``.

One data file holds every number the reproduction compares with: Tables 1-3 (mas), Table 2
(percent of CoG), the averages in the captions of the validation-run figures (pixels) and a
few figures quoted in the text. This module only reads and reshapes it; it sits beside
:mod:`.sensor` at the bottom of the import layers, so the reproduction (analysis) and the
network validation (learning) read the paper from this one place.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

PATH = Path(__file__).resolve().parent / "data" / "paper_results.json"

#: The four cases of Tables 1-2: case -> (detector, photons).
TABLE_CASES = {1: ("polar", 316), 2: ("polar", 1000), 3: ("cartesian", 316), 4: ("cartesian", 1000)}
ALGORITHMS = ("cog", "cmf", "ann")


@lru_cache(maxsize=1)
def load(path=None) -> dict:
    """The whole data file as a dict (cached; do not mutate)."""
    p = Path(path) if path is not None else PATH
    with open(p, encoding="utf-8") as f:
        return json.load(f)


def table1(algorithm: str, case: int) -> float:
    """Table 1: average error in mas of ``algorithm`` ("cog", "cmf", "ann") in ``case`` 1-4."""
    return float(load()["table1"][_alg(algorithm)][_case(case)])


def table2(algorithm: str, case: int) -> float:
    """Table 2: error relative to CoG, as a fraction (0.2491 for 24.91 %)."""
    return float(load()["table2"][_alg(algorithm)][_case(case)]) / 100.0


def table3(algorithm: str, detector: str) -> float:
    """Table 3: average error in mas of the 700 Hz validation run, "polar" or "cartesian"."""
    if detector not in ("polar", "cartesian"):
        raise ValueError(f"detector must be 'polar' or 'cartesian', got {detector!r}")
    return float(load()["table3"][detector][_alg(algorithm)])


def figure_average_px(algorithm: str, detector: str) -> float:
    """Average error in pixels quoted in the validation-run figure captions."""
    return float(load()["figure_averages_px"][detector][_alg(algorithm)])


def mas_per_px() -> float:
    return float(load()["mas_per_px"])


def citation() -> str:
    return load()["source"]["citation"]


def _alg(name: str) -> str:
    if name not in ALGORITHMS:
        raise ValueError(f"the paper reports {ALGORITHMS}, not {name!r}")
    return name


def _case(case) -> str:
    if int(case) not in TABLE_CASES:
        raise ValueError(f"case must be 1-4, got {case!r}")
    return str(int(case))


__all__ = ["load", "table1", "table2", "table3", "figure_average_px", "mas_per_px", "citation",
           "TABLE_CASES", "ALGORITHMS", "PATH"]
