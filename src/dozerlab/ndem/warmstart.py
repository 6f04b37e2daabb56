"""Warm start: the previous step's multipliers of contacts that persist.

A contact is named by the lower sphere id ``lo`` and ``hi`` — the other sphere's id, or
``-(b + 1)`` for body b — so it is recognised after the spatial re-sort moved its slots. The
vector multipliers are stored as acting on sphere ``lo``; a pair whose slots swapped is matched
with the sign flipped. Storage is compressed by ``lo`` (counting sort, no comparison sort).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _name(ids, ci, cj, k):
    """(lo, hi, sign) of contact k."""
    a = ids[ci[k]]
    if cj[k] < 0:
        return a, cj[k], 1.0
    b = ids[cj[k]]
    if a < b:
        return a, b, 1.0
    return b, a, -1.0


@njit(parallel=True, cache=True)
def _lookup(ids, ci, cj, normals, start, hi_store, lam_store):
    nc = ci.shape[0]
    lam = np.zeros((nc, 7))
    n_ids = start.shape[0] - 1
    for k in prange(nc):
        lo, hi, sign = _name(ids, ci, cj, k)
        if lo >= n_ids:
            continue
        for s in range(start[lo], start[lo + 1]):
            if hi_store[s] != hi:
                continue
            lam[k, 0] = lam_store[s, 0]
            for off in (1, 4):  # friction, rolling: flip, then drop the normal component
                dot = 0.0
                for a in range(3):
                    lam[k, off + a] = sign * lam_store[s, off + a]
                    dot += lam[k, off + a] * normals[k, a]
                for a in range(3):
                    lam[k, off + a] -= dot * normals[k, a]
            break
    return lam


@njit(cache=True)
def _store(ids, ci, cj, lam, n_ids):
    nc = ci.shape[0]
    lo_of = np.empty(nc, dtype=np.int64)
    start = np.zeros(n_ids + 1, dtype=np.int64)
    for k in range(nc):
        lo, _, _ = _name(ids, ci, cj, k)
        lo_of[k] = lo
        start[lo + 1] += 1
    for i in range(n_ids):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    hi_store = np.empty(nc, dtype=np.int64)
    lam_store = np.empty((nc, 7))
    for k in range(nc):
        lo, hi, sign = _name(ids, ci, cj, k)
        s = fill[lo]
        fill[lo] += 1
        hi_store[s] = hi
        lam_store[s, 0] = lam[k, 0]
        for a in range(1, 7):
            lam_store[s, a] = sign * lam[k, a]
    return start, hi_store, lam_store


class WarmStart:
    """Multipliers of the last step, grouped by the contact's lower sphere id."""

    def __init__(self) -> None:
        self.start = np.zeros(1, dtype=np.int64)
        self.hi = np.zeros(0, dtype=np.int64)
        self.lam = np.zeros((0, 7))

    def lookup(
        self, ids: np.ndarray, ci: np.ndarray, cj: np.ndarray, normals: np.ndarray
    ) -> np.ndarray:
        """Initial multipliers (Nc, 7) for this step's contacts (zero for new contacts).

        The friction and rolling vectors are projected onto the new tangent planes.
        """
        # A strided view (the contact table's normal columns) is read in place, not copied.
        return _lookup(ids, ci, cj, normals, self.start, self.hi, self.lam)

    def store(self, ids: np.ndarray, ci: np.ndarray, cj: np.ndarray, lam: np.ndarray) -> None:
        """Remember this step's multipliers."""
        self.start, self.hi, self.lam = _store(ids, ci, cj, lam, ids.shape[0])
