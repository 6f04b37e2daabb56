"""Warm start: the previous step's multipliers of contacts that persist.

A contact is named by the lower sphere id ``lo`` and ``hi`` — the other sphere's id, or
``-(b + 1)`` for body b — so it is recognised after the spatial re-sort moved its slots. The
vector multipliers are stored as acting on sphere ``lo``; a pair whose slots swapped is matched
with the sign flipped. Contacts among sleeping spheres (the active zone) are not in a step's
list, so the store carries their multipliers over until one of the spheres wakes. Storage is compressed by ``lo`` (counting sort, no comparison sort).
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
def _lookup(ids, ci, cj, normals, start, hi_store, lam_store, spin):
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
                if off == 4 and spin:
                    # the spinning row's impulse along the normal: flipped with the normal
                    # when the pair swapped, so the rolling vector's normal part is kept
                    continue
                for a in range(3):
                    lam[k, off + a] -= dot * normals[k, a]
            break
    return lam


@njit(cache=True, inline="always")
def _carried(lo, hi, lam, asleep):
    """Whether a stored contact (``lo``, ``hi``) with multipliers ``lam`` (7,) is kept though it
    is not among this step's contacts: a loaded one between spheres (or a sphere and a body)
    that all sleep (``asleep`` by id), so its multipliers are there when one wakes."""
    if lam[0] == 0.0 or lo >= asleep.shape[0] or not asleep[lo]:
        return False
    return hi < 0 or (hi < asleep.shape[0] and asleep[hi])


@njit(cache=True)
def _store(ids, ci, cj, lam, n_ids, old_start, old_hi, old_lam, asleep):
    nc = ci.shape[0]
    lo_of = np.empty(nc, dtype=np.int64)
    start = np.zeros(n_ids + 1, dtype=np.int64)
    for k in range(nc):
        lo, _, _ = _name(ids, ci, cj, k)
        lo_of[k] = lo
        start[lo + 1] += 1
    n_old = min(old_start.shape[0] - 1, n_ids)
    for lo in range(n_old):
        for s in range(old_start[lo], old_start[lo + 1]):
            if _carried(lo, old_hi[s], old_lam[s], asleep):
                start[lo + 1] += 1
    for i in range(n_ids):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    hi_store = np.empty(start[n_ids], dtype=np.int64)
    lam_store = np.empty((start[n_ids], 7))
    for k in range(nc):
        lo, hi, sign = _name(ids, ci, cj, k)
        s = fill[lo]
        fill[lo] += 1
        hi_store[s] = hi
        lam_store[s, 0] = lam[k, 0]
        for a in range(1, 7):
            lam_store[s, a] = sign * lam[k, a]
    for lo in range(n_old):
        for s in range(old_start[lo], old_start[lo + 1]):
            if _carried(lo, old_hi[s], old_lam[s], asleep):
                t = fill[lo]
                fill[lo] += 1
                hi_store[t] = old_hi[s]
                for a in range(7):
                    lam_store[t, a] = old_lam[s, a]
    return start, hi_store, lam_store


@njit(cache=True)
def _held(start, hi, lam, asleep):
    held = np.zeros(asleep.shape[0])
    for lo in range(min(start.shape[0] - 1, asleep.shape[0])):
        for s in range(start[lo], start[lo + 1]):
            if _carried(lo, hi[s], lam[s], asleep):
                held[lo] += lam[s, 0]
                if hi[s] >= 0:
                    held[hi[s]] += lam[s, 0]
    return held


class WarmStart:
    """Multipliers of the last step, grouped by the contact's lower sphere id."""

    def __init__(self) -> None:
        self.start = np.zeros(1, dtype=np.int64)
        self.hi = np.zeros(0, dtype=np.int64)
        self.lam = np.zeros((0, 7))

    def lookup(
        self,
        ids: np.ndarray,
        ci: np.ndarray,
        cj: np.ndarray,
        normals: np.ndarray,
        spin: bool = False,
    ) -> np.ndarray:
        """Initial multipliers (Nc, 7) for this step's contacts (zero for new contacts).

        The friction and rolling vectors are projected onto the new tangent planes; with
        ``spin`` (spinning resistance on) the rolling vector keeps its part along the normal,
        the spinning row's impulse.
        """
        # A strided view (the contact table's normal columns) is read in place, not copied.
        return _lookup(ids, ci, cj, normals, self.start, self.hi, self.lam, spin)

    def held(self, asleep: np.ndarray) -> np.ndarray:
        """Per sphere id (N,), the normal impulses (N·s) summed over its stored contacts that a
        step with ``asleep`` (N,) bool by id leaves out (among sleepers and bodies): what holds
        a sleeping sphere still."""
        return _held(self.start, self.hi, self.lam, asleep)

    def store(
        self,
        ids: np.ndarray,
        ci: np.ndarray,
        cj: np.ndarray,
        lam: np.ndarray,
        asleep: np.ndarray | None = None,
    ) -> None:
        """Remember this step's multipliers, and keep the loaded contacts among sleeping spheres
        (``asleep`` (N,) bool by sphere id; None: none sleeps), which a step leaves out."""
        keep = np.zeros(0, dtype=np.bool_) if asleep is None else asleep
        self.start, self.hi, self.lam = _store(
            ids, ci, cj, lam, ids.shape[0], self.start, self.hi, self.lam, keep
        )
