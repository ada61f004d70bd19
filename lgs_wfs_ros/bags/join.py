"""Join several topics' messages by header stamp (the contract's join key)."""

from dataclasses import dataclass
from functools import reduce

import numpy as np


@dataclass(frozen=True)
class Join:
    """Result of :func:`join_by_stamp` for N inputs.

    stamps: (K,) int64 stamps present in every input, ascending; indices: N arrays (K,) of
    positions into each input (first occurrence of a duplicated stamp); missing: N arrays of
    stamps seen in some input but absent from this one; duplicates: N counts of repeated
    stamps dropped (each repeat after the first counts once)."""

    stamps: np.ndarray
    indices: tuple
    missing: tuple
    duplicates: tuple

    @property
    def n_missing(self):
        """Per input, how many stamps of the union it lacks."""
        return tuple(len(m) for m in self.missing)


def join_by_stamp(*stamps):
    """Align stamp arrays (each (F_i,) integer ns) on the stamps they all contain.

    Example: ``j = join_by_stamp(frame_stamps, truth_stamps, slope_stamps)``; then
    ``frames[j.indices[0]]``, ``truths[j.indices[1]]``, ``slopes[j.indices[2]]`` line up.
    """
    if not stamps:
        raise ValueError("join_by_stamp needs at least one stamp array")
    arrays = []
    for i, s in enumerate(stamps):
        a = np.asarray(s)
        if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"input {i}: stamps must be a 1-D integer array (ns), got {a.dtype} {a.shape}")
        arrays.append(a.astype(np.int64, copy=False))
    uniques = [np.unique(a, return_index=True) for a in arrays]
    common = reduce(np.intersect1d, [u for u, _ in uniques])
    union = reduce(np.union1d, [u for u, _ in uniques])
    indices = tuple(first[np.searchsorted(u, common)].astype(np.intp) for u, first in uniques)
    missing = tuple(np.setdiff1d(union, u, assume_unique=True) for u, _ in uniques)
    duplicates = tuple(int(len(a) - len(u)) for a, (u, _) in zip(arrays, uniques))
    return Join(stamps=common.astype(np.int64), indices=indices, missing=missing, duplicates=duplicates)
